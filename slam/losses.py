"""The four objectives of the paper (Optimization Objectives): colour, depth, free space, SDF.

Units follow the paper's implementation: the SDF ``s`` is in units of the truncation ``tr``,
so the free-space target is ``s = 1`` and the SDF target inside the band is
``(D_gt - t) / tr``; the SDF loss is reported in metres squared, ``((t + s tr) - D_gt)^2``.
Free-space and SDF terms average first over a ray's samples, then over rays, as the paper's
``1/|P| sum_p 1/S_p sum_s`` does (``normalisation="ray"``); ``"slots"`` is the Vox-Fusion
release's normalisation instead (``LossConfig.normalisation``, ``_slot_means``).
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
                  num_rays: int, stands_for: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over rays (that have any masked sample) of the mean of ``values[mask]`` per ray,
    each sample counted ``stands_for`` (S,) times (None: once)."""
    m = mask.to(values.dtype) if stands_for is None else mask.to(values.dtype) * stands_for
    sums = values.new_zeros(num_rays).index_add(0, ray_index, values * m)
    counts = values.new_zeros(num_rays).index_add(0, ray_index, m)
    has = counts > 0
    if not bool(has.any()):
        return values.sum() * 0.0
    return (sums[has] / counts[has]).mean()


def _slot_means(fs_values: torch.Tensor, front: torch.Tensor, sdf_values: torch.Tensor, band: torch.Tensor,
                ray_index: torch.Tensor, use: torch.Tensor, stands_for: torch.Tensor | None = None,
                grid_counts: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The release's free-space and SDF terms (``criterion.py``, ``get_sdf_loss``) on flat samples.

    The release holds samples in a (rays, most samples of any ray) tensor padded behind each
    ray, and takes the mean of the masked squares over every slot of it, padding included;
    then it scales the free-space mean by the share of SDF-band samples among the front and
    band samples, and the SDF mean by the share of front samples. Rays: those in ``use``.
    Thinned samples (``slam.render.thin_training_samples``) count ``stands_for`` (S,) times
    and the width is that of the rays' ``grid_counts`` (R,) before thinning, so the terms
    keep their expectation.
    """
    zero = fs_values.sum() * 0.0
    counts = torch.bincount(ray_index, minlength=use.shape[0]) if grid_counts is None else grid_counts
    rays = int(use.sum())
    width = int(counts[use].max()) if rays else 0
    front_count = front.to(fs_values.dtype) if stands_for is None else front * stands_for
    n_front, n_band = float(front_count.sum()), float(band.sum())
    if width == 0 or n_front + n_band == 0:
        return zero, zero
    slots = float(rays * width)
    fs = (fs_values * front_count).sum() / slots * (n_band / (n_front + n_band))
    sdf = (sdf_values * band).sum() / slots * (n_front / (n_front + n_band))
    return fs, sdf


def compute_losses(out: RenderOutput, rgb_gt: torch.Tensor, depth_gt: torch.Tensor, truncation: float,
                   weights: LossWeights, ray_weight: torch.Tensor | None = None,
                   max_depth: float = 10.0, normalisation: str = "ray") -> Losses:
    """Losses of R rendered rays against rgb_gt (R, 3) and depth_gt (R,) (0 = invalid).

    ``ray_weight`` (R,) in {0, 1} drops rays (tracking's outliers) from every term.
    ``normalisation``: ``ray`` (per-ray means, the paper) or ``slots`` (the release's padded
    slot means, ``_slot_means``) for the free-space and SDF terms.
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
    fs_values, sdf_values = (out.sdf - 1.0) ** 2, (t + out.sdf * truncation - d) ** 2
    if normalisation == "ray":
        fs = _per_ray_mean(fs_values, front, r, num_rays, out.samples.stands_for)
        sdf = _per_ray_mean(sdf_values, band, r, num_rays)
    elif normalisation == "slots":
        fs, sdf = _slot_means(fs_values, front, sdf_values, band, r, use, out.samples.stands_for,
                              out.samples.grid_counts)
    else:
        raise ValueError(f"unknown loss normalisation {normalisation!r}: 'ray' or 'slots'")
    total = weights.rgb * rgb + weights.depth * depth + weights.fs * fs + weights.sdf * sdf
    return Losses(total, rgb, depth, fs, sdf)
