"""Static-shape rendering: a fixed number of sample slots per ray, for the GPU.

The flat renderer (``slam.render``) keeps only the samples that exist, so its tensors' sizes
depend on the data: every ``nonzero``, boolean index and ``int(count)`` reads the device
before the next kernel can be launched, and on a GPU the loops wait on the host. Here every
tensor's shape depends only on the ray count R, the grid size G and the slot count N, so a
tracking or mapping iteration reads nothing back from the device (and could be captured as
a CUDA graph). ``slam.render.render_rays`` is the plain reference these functions are tested
against (``tests/test_padded.py``).

Sampling (``grid_samples``, ``pack_samples``): the fixed grid ``t_j = (k0 + j + u) * step``,
``j < G``, from each ray's ``near`` (the flat renderer's grid: ``sample_points_from_hits``
and ``sample_points_in_band`` sample the same ``t``). A grid point is a sample where
``t < far``, its voxel is allocated (a lookup of its Morton code) and, with an M_h cap, that
voxel is among the first ``max_hits`` allocated voxels along the ray. The samples of a ray
are packed right-aligned into N slots in order; a ray with more than N keeps its last N
(the ones nearest ``far``, around the observed surface; ``pack_samples`` counts the dropped).

Differences from the flat renderer, all measured in the tests:

* a voxel that the ray crosses without a grid point inside it (a corner clipped by less
  than a step) does not count toward M_h here; the traversal counts it;
* the colour head runs on a window of ``color_slots`` slots centred on each ray's largest
  weight (on those whose weight exceeds ``color_weight_eps``). With ``mask_in_front`` a ray
  that crosses a surface has all its weighted samples within ``tr`` of the crossing, so a
  window of ``2 tr / step + 4`` slots holds every one of them and its colour is the
  reference's; a ray without a crossing keeps every sample's weight, and its coloured
  samples outside the window are left out (such a ray grazes a surface, or meets a young
  map's free space that is not yet at s = 1).

The per-ray sums are sums over the slot axis, and every invalid slot holds the grid's
``t`` (finite), voxel 0 and weight 0, so it adds nothing to a value or a gradient.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .render import (
    MapView,
    RaySamples,
    RenderOutput,
    TrainingThinning,
    color_of_hidden,
    decode_samples,
)

SLOT_MULTIPLE = 16
"""Slot and grid counts are rounded up to a multiple of this (fewer distinct shapes)."""


def round_up(n: int, multiple: int = SLOT_MULTIPLE) -> int:
    """The smallest multiple of ``multiple`` >= max(n, 1)."""
    return max(multiple, -(-int(n) // multiple) * multiple)


def grid_size(near_min: float, far_max: float, step: float) -> int:
    """G: grid points that cover every ray's [near, far) when near >= ``near_min`` and
    far <= ``far_max`` (metres of z-depth), rounded up to ``SLOT_MULTIPLE``.
    Example: near 0.05, far 1.0, step 0.1 -> 16 (10 points needed)."""
    return round_up(math.ceil(max(far_max - near_min, 0.0) / step) + 2)


def band_grid_size(band: float, truncation: float, step: float) -> int:
    """G for tracking's band ``depth -+ band * tr`` (``slam.tracking.tracking_bounds``)."""
    return round_up(math.ceil(2.0 * band * truncation / step) + 2)


def color_slots(truncation: float, step: float, slots: int, mask_in_front: bool = True) -> int:
    """C: slots of a ray's colour window, centred on its largest weight; with
    ``mask_in_front`` every weighted sample of a ray that crosses a surface (they lie within
    tr of the crossing, and so does the largest), else all N."""
    if not mask_in_front:
        return slots
    return min(slots, 2 * math.ceil(truncation / step) + 4)


@dataclass(frozen=True)
class GridSamples:
    """Every grid point of R rays, G each (``grid_samples``).

    t (R, G) z-depth; voxel_index (R, G) int64 (-1: unallocated); keep (R, G) bool: a sample
    (in range, allocated, within the M_h cap, kept by the thinning); stands_for (R, G) float
    or None (thinning); grid_counts (R,) int64: samples per ray before thinning.
    """

    t: torch.Tensor
    voxel_index: torch.Tensor
    keep: torch.Tensor
    stands_for: torch.Tensor | None
    grid_counts: torch.Tensor

    def counts(self) -> torch.Tensor:
        """(R,) int64 samples per ray (after thinning): the slots each ray needs."""
        return self.keep.sum(1)


@dataclass(frozen=True)
class PaddedSamples:
    """Samples packed into N slots per ray (``pack_samples``), right-aligned, in order.

    t, voxel_index (R, N) (invalid slots: finite t, voxel 0), valid (R, N) bool,
    stands_for (R, N) float or None, grid_counts (R,) int64, dropped (R,) int64: samples
    beyond N that the ray lost (its nearest)."""

    t: torch.Tensor
    voxel_index: torch.Tensor
    valid: torch.Tensor
    stands_for: torch.Tensor | None
    grid_counts: torch.Tensor
    dropped: torch.Tensor

    @property
    def num_rays(self) -> int:
        return self.t.shape[0]

    @property
    def slots(self) -> int:
        return self.t.shape[1]

    def flat(self) -> RaySamples:
        """The same samples as ``slam.render.RaySamples`` of R * N slots (ray-major), with
        ``valid`` marking the samples (what ``slam.losses.compute_losses`` reads)."""
        R, N = self.t.shape
        ray = torch.arange(R, device=self.t.device)[:, None].expand(R, N).reshape(-1)
        stands_for = None if self.stands_for is None else self.stands_for.reshape(-1)
        return RaySamples(ray, self.t.reshape(-1), self.voxel_index.reshape(-1), None, stands_for,
                          self.grid_counts, self.valid.reshape(-1))


def grid_samples(origins: torch.Tensor, dirs: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                 step: float, view: MapView, grid: int, *, max_hits: int = 0,
                 offsets: torch.Tensor | None = None, thinning: TrainingThinning | None = None) -> GridSamples:
    """The grid points ``t = (k0 + j + u) * step``, j < ``grid``, of R rays and which are samples.

    origins, dirs (R, 3) map frame; near, far (R,); offsets (R,) in [0, 1) (None: 0.5);
    ``max_hits`` > 0 keeps the samples of the first M_h allocated voxels of each ray;
    ``thinning``: mapping's cheaper set (``slam.render.thin_training_samples``, the same
    choice on the grid). Reads nothing back from the device.
    """
    R = origins.shape[0]
    device = origins.device
    u = torch.full((R,), 0.5, device=device, dtype=origins.dtype) if offsets is None else offsets
    k0 = torch.ceil(near / step - u)
    j = torch.arange(grid, device=device, dtype=origins.dtype)
    t = (k0[:, None] + j[None, :] + u[:, None]) * step                          # (R, G)
    points = origins[:, None, :] + t[..., None] * dirs[:, None, :]                # (R, G, 3)
    ijk = torch.floor(points / view.voxel_size).long().clamp(-(1 << 20), (1 << 20) - 1)
    voxel = view.find(ijk.reshape(-1, 3)).reshape(R, grid)
    keep = (t < far[:, None]) & (voxel >= 0)
    if max_hits > 0:
        # A new voxel run starts where the previous grid point is no sample or lies in
        # another voxel (a ray meets a convex voxel in one stretch).
        prev_keep = torch.nn.functional.pad(keep[:, :-1], (1, 0), value=False)
        prev_voxel = torch.nn.functional.pad(voxel[:, :-1], (1, 0), value=-1)
        starts = keep & ~(prev_keep & (prev_voxel == voxel))
        keep = keep & (torch.cumsum(starts, 1) <= max_hits)
    grid_counts = keep.sum(1)
    stands_for = None
    if thinning is not None:
        d = thinning.depth[:, None]
        valid = (d > 0.01) & (d < thinning.max_depth)
        front = valid & (t < d - thinning.truncation)
        behind = valid & (t > d + thinning.truncation)
        stride = thinning.free_space_stride
        # Free-space samples are a prefix of their ray, so their rank among the ray's
        # samples is their rank in the free space (as the flat twin).
        rank = torch.cumsum(keep, 1) - 1
        picked = (rank + thinning.phase[:, None]) % stride == 0
        keep = keep & ~behind & (~front | picked)
        stands_for = torch.where(front, float(stride), 1.0).to(t.dtype)
    return GridSamples(t, voxel, keep, stands_for, grid_counts)


def pack_samples(grid: GridSamples, slots: int) -> PaddedSamples:
    """The samples of ``grid`` packed right-aligned into ``slots`` slots per ray, in order;
    a ray with more keeps its last ``slots`` (nearest ``far``)."""
    keep = grid.keep
    R, G = keep.shape
    N = int(slots)
    total = keep.sum(1, keepdim=True)
    from_end = total - torch.cumsum(keep, 1)                   # 0 for a ray's last sample
    fits = keep & (from_end < N)
    slot = torch.where(fits, N - 1 - from_end, torch.full_like(from_end, N))    # N: discarded

    def packed(values: torch.Tensor, fill) -> torch.Tensor:
        out = torch.full((R, N + 1), fill, dtype=values.dtype, device=values.device)
        return out.scatter(1, slot, values)[:, :N]

    # Invalid slots take the ray's last grid t (finite): they add nothing, but stay usable.
    t = packed(grid.t, 0.0)
    valid = packed(fits, False)
    t = torch.where(valid, t, grid.t[:, -1:].expand(R, N))
    voxel = packed(grid.voxel_index.clamp(min=0), 0)
    stands_for = None if grid.stands_for is None else packed(grid.stands_for, 0.0)
    dropped = (keep & ~fits).sum(1)
    return PaddedSamples(t, voxel, valid, stands_for, grid.grid_counts, dropped)


def first_zero_crossing_padded(sdf: torch.Tensor, t: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(R,) ``t`` of each ray's first sign change of the SDF between two consecutive valid
    slots, inf where none: sdf, t, valid (R, N), right-aligned (``slam.render.first_zero_crossing``
    on padded samples). Example: sdf [[x, 0.5, -0.5]], t [[x, 1.0, 1.2]], valid
    [[False, True, True]] -> [1.1]."""
    s0, s1 = sdf[:, :-1], sdf[:, 1:]
    change = valid[:, :-1] & valid[:, 1:] & (s0 * s1 < 0)
    t0, t1 = t[:, :-1], t[:, 1:]
    denom = torch.where(change, s0 - s1, torch.ones_like(s0))
    t_zero = t0 + (t1 - t0) * s0 / denom
    inf = torch.full_like(t_zero, float("inf"))
    if t_zero.shape[1] == 0:
        return torch.full_like(t[:, 0], float("inf"))
    return torch.where(change, t_zero, inf).amin(1)


def sdf_weights_padded(sdf: torch.Tensor, t: torch.Tensor, valid: torch.Tensor, truncation: float,
                       mask_in_front: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """``slam.render.sdf_weights_and_slope`` on padded samples: w and dw/ds (R, N), zero at
    invalid slots and outside the first surface's window."""
    with torch.no_grad():
        crossing = first_zero_crossing_padded(sdf.detach(), t, valid)[:, None]
        mask = valid & (t < crossing + truncation)
        if mask_in_front:
            mask = mask & ((t > crossing - truncation) | torch.isinf(crossing))
    sig = torch.sigmoid(sdf / truncation)
    w = sig * (1.0 - sig) * mask
    return w, w * (1.0 - 2.0 * sig) / truncation


def color_window(w: torch.Tensor, eps: float, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Slots (R, C) of each ray's colour window and which of them are coloured (weight above
    ``eps``): C = ``size`` slots centred on the ray's largest weight, inside its N slots.
    w (R, N) -> index (R, C) int64, active (R, C) bool.
    Example: w [[0, .2, .1, 0]], eps 0.05, size 3 -> index [[0, 1, 2]], active
    [[False, True, True]]."""
    R, N = w.shape
    size = min(size, N)
    wd = w.detach()
    start = (torch.argmax(wd, 1) - size // 2).clamp(0, N - size)
    index = start[:, None] + torch.arange(size, device=w.device)[None, :]
    return index, wd.gather(1, index) > eps


def render_padded(origins: torch.Tensor, dirs: torch.Tensor, view: MapView, decoder, samples: PaddedSamples, *,
                  truncation: float, color_weight_eps: float = 1e-5, color_slots: int | None = None,
                  mask_in_front: bool = True, renormalise_color: bool = False) -> RenderOutput:
    """``slam.render.render_rays`` on padded samples: origins, dirs (R, 3) map frame ->
    RenderOutput whose ``samples`` are ``samples.flat()`` (R * N slots with ``valid``) and
    ``sdf`` (R * N,). ``color_slots``: C, the colour window (None: every slot)."""
    R, N = samples.t.shape
    t = samples.t
    if view.voxel_codes.shape[0] == 0 or N == 0:
        zero = t.new_zeros(R)
        flat = samples.flat()
        return RenderOutput(t.new_zeros(R, 3), zero, zero, torch.zeros(R, dtype=torch.bool, device=t.device),
                            zero, flat, t.new_zeros(R * N))
    points = (origins[:, None, :] + t[..., None] * dirs[:, None, :]).reshape(-1, 3)
    sdf, hidden = decode_samples(points, samples.voxel_index.reshape(-1), view, decoder)
    s = sdf.view(R, N)
    w, _ = sdf_weights_padded(s, t, samples.valid, truncation, mask_in_front)
    wsum = w.sum(1)
    norm = 1.0 / (wsum + 1e-8)
    depth = (w * t).sum(1) * norm
    depth_var = (w * (t - depth.detach()[:, None]) ** 2).sum(1) * norm
    C = N if color_slots is None else min(int(color_slots), N)
    if math.isinf(color_weight_eps) or C == 0:
        color = t.new_zeros(R, 3)
    else:
        index, active = color_window(w, color_weight_eps, C)
        H = hidden.shape[1]
        h = hidden.view(R, N, H).gather(1, index[..., None].expand(R, C, H)).reshape(-1, H)
        rgb = color_of_hidden(decoder, h).view(R, C, 3)
        wc = w.gather(1, index) * active
        numerator = (wc[..., None] * rgb).sum(1)
        color = numerator / ((wc.sum(1) if renormalise_color else wsum) + 1e-8)[:, None]
    hit = samples.valid.any(1)
    return RenderOutput(color, depth, wsum, hit, depth_var, samples.flat(), sdf)
