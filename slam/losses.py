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
        """The five terms as floats, in one read of the device."""
        names = ("total", "rgb", "depth", "fs", "sdf")
        values = torch.stack([getattr(self, k).detach().float() for k in names]).tolist()
        return dict(zip(names, values))


def _per_ray_mean(values: torch.Tensor, mask: torch.Tensor, ray_index: torch.Tensor,
                  num_rays: int, stands_for: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over rays (that have any masked sample) of the mean of ``values[mask]`` per ray,
    each sample counted ``stands_for`` (S,) times (None: once); 0 when no ray has one.
    Masks instead of boolean indexing: no value is read back from the device."""
    m = mask.to(values.dtype) if stands_for is None else mask.to(values.dtype) * stands_for
    sums = values.new_zeros(num_rays).index_add(0, ray_index, values * m)
    counts = values.new_zeros(num_rays).index_add(0, ray_index, m)
    has = counts > 0
    per_ray = sums / torch.where(has, counts, torch.ones_like(counts))
    return per_ray.sum() / has.sum().clamp(min=1).to(values.dtype)


def _slot_means(fs_values: torch.Tensor, front: torch.Tensor, sdf_values: torch.Tensor, band: torch.Tensor,
                ray_index: torch.Tensor, use: torch.Tensor, stands_for: torch.Tensor | None = None,
                grid_counts: torch.Tensor | None = None,
                valid: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The release's free-space and SDF terms (``criterion.py``, ``get_sdf_loss``) on flat samples.

    The release holds samples in a (rays, most samples of any ray) tensor padded behind each
    ray, and takes the mean of the masked squares over every slot of it, padding included;
    then it scales the free-space mean by the share of SDF-band samples among the front and
    band samples, and the SDF mean by the share of front samples. Rays: those in ``use``.
    Thinned samples (``slam.render.thin_training_samples``) count ``stands_for`` (S,) times
    and the width is that of the rays' ``grid_counts`` (R,) before thinning, so the terms
    keep their expectation. ``valid`` (S,): the samples among padded slots (None: all).
    Every count stays a tensor (nothing is read back from the device).
    """
    dtype = fs_values.dtype
    zero = fs_values.sum() * 0.0
    if grid_counts is None:
        ones = torch.ones_like(ray_index) if valid is None else valid.to(ray_index.dtype)
        counts = torch.zeros(use.shape[0], dtype=ray_index.dtype, device=ray_index.device).index_add(0, ray_index, ones)
    else:
        counts = grid_counts
    rays = use.sum()
    width = (counts * use).max() if use.numel() else counts.new_zeros(())
    front_count = front.to(dtype) if stands_for is None else front * stands_for
    n_front, n_band = front_count.sum(), band.to(dtype).sum()
    both = n_front + n_band
    ok = (width > 0) & (both > 0)
    slots = (rays * width).to(dtype).clamp(min=1)
    safe_both = torch.where(ok, both, torch.ones_like(both))
    fs = (fs_values * front_count).sum() / slots * (n_band / safe_both)
    sdf = (sdf_values * band).sum() / slots * (n_front / safe_both)
    return torch.where(ok, fs, zero), torch.where(ok, sdf, zero)


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
    # Means over the rays kept, as masked sums: no count is read back from the device.
    use_f, depth_f = use.to(out.depth.dtype), valid_depth.to(out.depth.dtype)
    rgb = ((out.color - rgb_gt).abs() * use_f[:, None]).sum() / (3.0 * use_f.sum()).clamp(min=1.0)
    depth = ((out.depth - depth_gt).abs() * depth_f).sum() / depth_f.sum().clamp(min=1.0)

    r = out.samples.ray_index
    t = out.samples.t
    d = depth_gt[r]
    ok = valid_depth[r]
    if out.samples.valid is not None:
        ok = ok & out.samples.valid
    front = ok & (t < d - truncation)
    band = ok & ((t - d).abs() <= truncation)
    fs_values, sdf_values = (out.sdf - 1.0) ** 2, (t + out.sdf * truncation - d) ** 2
    if normalisation == "ray":
        fs = _per_ray_mean(fs_values, front, r, num_rays, out.samples.stands_for)
        sdf = _per_ray_mean(sdf_values, band, r, num_rays)
    elif normalisation == "slots":
        fs, sdf = _slot_means(fs_values, front, sdf_values, band, r, use, out.samples.stands_for,
                              out.samples.grid_counts, out.samples.valid)
    else:
        raise ValueError(f"unknown loss normalisation {normalisation!r}: 'ray' or 'slots'")
    total = weights.rgb * rgb + weights.depth * depth + weights.fs * fs + weights.sdf * sdf
    return Losses(total, rgb, depth, fs, sdf)
