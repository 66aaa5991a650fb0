"""The four objectives of the paper (Optimization Objectives): colour, depth, free space, SDF.

Units follow the paper's implementation: the SDF ``s`` is in units of the truncation ``tr``,
so the free-space target is ``s = 1`` and the SDF target inside the band is
``(D_gt - t) / tr``; the SDF loss is reported in metres squared, ``((t + s tr) - D_gt)^2``.
Free-space and SDF terms average first over a ray's samples, then over rays, as the paper's
``1/|P| sum_p 1/S_p sum_s`` does.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .render import RenderOutput


@dataclass(frozen=True)
class LossWeights:
    rgb: float
    depth: float
    sdf: float
    fs: float


@dataclass(frozen=True)
class Losses:
    total: torch.Tensor
    rgb: torch.Tensor
    depth: torch.Tensor
    fs: torch.Tensor
    sdf: torch.Tensor

    def as_floats(self) -> dict[str, float]:
        return {k: float(getattr(self, k).detach()) for k in ("total", "rgb", "depth", "fs", "sdf")}


def _per_ray_mean(values: torch.Tensor, mask: torch.Tensor, ray_index: torch.Tensor,
                  num_rays: int) -> torch.Tensor:
    """Mean over rays (that have any masked sample) of the mean of ``values[mask]`` per ray."""
    m = mask.to(values.dtype)
    sums = values.new_zeros(num_rays).index_add(0, ray_index, values * m)
    counts = values.new_zeros(num_rays).index_add(0, ray_index, m)
    has = counts > 0
    if not bool(has.any()):
        return values.sum() * 0.0
    return (sums[has] / counts[has]).mean()


def compute_losses(out: RenderOutput, rgb_gt: torch.Tensor, depth_gt: torch.Tensor, truncation: float,
                   weights: LossWeights, ray_weight: torch.Tensor | None = None,
                   max_depth: float = 10.0) -> Losses:
    """Losses of R rendered rays against rgb_gt (R, 3) and depth_gt (R,) (0 = invalid).

    ``ray_weight`` (R,) in {0, 1} drops rays (tracking's outliers) from every term.
    """
    num_rays = rgb_gt.shape[0]
    use = out.hit if ray_weight is None else out.hit & (ray_weight > 0)
    valid_depth = use & (depth_gt > 0.01) & (depth_gt < max_depth)
    zero = out.depth.sum() * 0.0
    rgb = (out.color[use] - rgb_gt[use]).abs().mean() if bool(use.any()) else zero
    depth = (out.depth[valid_depth] - depth_gt[valid_depth]).abs().mean() if bool(valid_depth.any()) else zero

    r = out.samples.ray_index
    t = out.samples.t
    d = depth_gt[r]
    ok = valid_depth[r]
    front = ok & (t < d - truncation)
    band = ok & ((t - d).abs() <= truncation)
    fs = _per_ray_mean((out.sdf - 1.0) ** 2, front, r, num_rays)
    sdf = _per_ray_mean((t + out.sdf * truncation - d) ** 2, band, r, num_rays)
    total = weights.rgb * rgb + weights.depth * depth + weights.fs * fs + weights.sdf * sdf
    return Losses(total, rgb, depth, fs, sdf)
