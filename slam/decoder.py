"""The small MLP F_theta: interpolated embedding -> SDF and colour (paper: Implementation Details).

Shared FC layers (16-D input, ``num_layers`` of ``hidden_dim``, ReLU) end in a head that outputs
the SDF ``s`` (in units of the truncation, see ``slam.render``) and a feature vector; the colour
head (``color_layers`` FC layers of ``color_hidden_dim``) maps the feature to RGB through a
sigmoid. Split in two calls so the renderer can run the colour head on a subset of samples.
"""

from __future__ import annotations

import torch
from torch import nn

from .config import DecoderConfig


def _mlp(sizes: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


class Decoder(nn.Module):
    def __init__(self, config: DecoderConfig, embed_dim: int):
        super().__init__()
        self.config = config
        shared = [embed_dim] + [config.hidden_dim] * config.num_layers
        self.trunk = nn.Sequential(_mlp(shared), nn.ReLU(inplace=True))
        self.sdf_head = nn.Linear(config.hidden_dim, 1 + config.feature_dim)
        self.color_head = _mlp([config.feature_dim] + [config.color_hidden_dim] * config.color_layers + [3])

    def trunk_linears(self) -> list[nn.Linear]:
        """The trunk's layers in order; each is followed by a ReLU (``slam.kernels.fused``
        runs the trunk from these)."""
        return [m for m in self.trunk.modules() if isinstance(m, nn.Linear)]

    def sdf_and_feature(self, emb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(S, D) embeddings -> SDF (S,) in units of tr and feature (S, F)."""
        out = self.sdf_head(self.trunk(emb))
        return out[:, 0], out[:, 1:]

    def sdf_and_hidden(self, emb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(S, D) -> SDF (S,) and the trunk output (S, H), without the feature rows.

        The renderer needs the feature only for the few samples near a surface; computing
        the SDF row alone for all samples saves most of the head's cost.
        """
        hidden = self.trunk(emb)
        w, b = self.sdf_head.weight, self.sdf_head.bias
        return hidden @ w[0] + b[0], hidden

    def feature_from_hidden(self, hidden: torch.Tensor) -> torch.Tensor:
        """(S, H) trunk output -> (S, F) feature, the same numbers as ``sdf_and_feature``."""
        w, b = self.sdf_head.weight, self.sdf_head.bias
        return torch.nn.functional.linear(hidden, w[1:], b[1:])

    def sdf(self, emb: torch.Tensor) -> torch.Tensor:
        """(S, D) -> (S,) SDF only."""
        return self.sdf_and_hidden(emb)[0]

    def color(self, feature: torch.Tensor) -> torch.Tensor:
        """(S, F) features -> (S, 3) RGB in [0, 1]."""
        return torch.sigmoid(self.color_head(feature))

    def num_bytes(self) -> int:
        return sum(p.numel() * p.element_size() for p in self.parameters())
