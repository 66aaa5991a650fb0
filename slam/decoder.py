"""The small MLP F_theta: interpolated embedding -> SDF and colour (paper: Implementation Details).

Shared FC layers (16-D input, ``num_layers`` of ``hidden_dim``, ReLU) end in a head that outputs
the SDF ``s`` (in units of the truncation, see ``slam.render``) and a feature vector; the colour
head (``color_layers`` FC layers of ``color_hidden_dim``) maps the feature to RGB through a
sigmoid. Split in two calls so the renderer can run the colour head on a subset of samples.
"""

from __future__ import annotations

import torch
from torch import nn

from . import kernels
from .config import DecoderConfig


def _mlp(sizes: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


class _TwoLinears(torch.autograd.Function):
    """z = (h Wf^T + bf) Wc^T + bc as one product with Wc Wf (C, H), gradients included.

    h (S, H), Wf (F, H), bf (F,), Wc (C, F), bc (C,) -> z (S, C). With f = h Wf^T + bf and
    M = g_z^T h (C, H), s = sum of g_z over samples: g_h = g_z (Wc Wf), g_Wc = M Wf^T + s bf^T,
    g_Wf = Wc^T M, g_bf = Wc^T s, g_bc = s: two (S, H)-sized products, the rest is H x H.
    """

    @staticmethod
    def forward(ctx, h, wf, bf, wc, bc):
        ctx.save_for_backward(h, wf, bf, wc)
        return torch.addmm(wc @ bf + bc, h, (wc @ wf).t())

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_z):
        h, wf, bf, wc = ctx.saved_tensors
        need = ctx.needs_input_grad
        g_h = g_z @ (wc @ wf) if need[0] else None
        m = g_z.t() @ h
        s = g_z.sum(0)
        g_wf = wc.t() @ m if need[1] else None
        g_bf = wc.t() @ s if need[2] else None
        g_wc = torch.addr(m @ wf.t(), s, bf) if need[3] else None
        return g_h, g_wf, g_bf, g_wc, s if need[4] else None


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

    def color_from_hidden(self, hidden: torch.Tensor) -> torch.Tensor:
        """(S, H) trunk output -> (S, 3) RGB: ``color(feature_from_hidden(hidden))`` with the
        feature rows of the SDF head and the colour head's first layer multiplied into one
        matrix (no activation lies between them). Three (S, H)-sized products forward and
        backward instead of six; the feature is never formed. ``VOXFUSION_KERNELS=torch``
        runs the plain two layers."""
        if kernels.requested() == "torch":
            return self.color(self.feature_from_hidden(hidden))
        first, rest = self.color_head[0], self.color_head[1:]
        w, b = self.sdf_head.weight, self.sdf_head.bias
        z = _TwoLinears.apply(hidden, w[1:], b[1:], first.weight, first.bias)
        return torch.sigmoid(rest(z))

    def sdf(self, emb: torch.Tensor) -> torch.Tensor:
        """(S, D) -> (S,) SDF only."""
        return self.sdf_and_hidden(emb)[0]

    def color(self, feature: torch.Tensor) -> torch.Tensor:
        """(S, F) features -> (S, 3) RGB in [0, 1]."""
        return torch.sigmoid(self.color_head(feature))

    def num_bytes(self) -> int:
        return sum(p.numel() * p.element_size() for p in self.parameters())
