"""Volume rendering over the sparse voxel map (paper: Volume Renderer).

One small function per idea, nerfacc-style: rays -> voxel hits -> flat samples with a ray
index (no padding) -> trilinear embeddings -> decoder -> SDF weights -> per-ray sums.

Ray parametrisation: a ray is ``x(t) = origin + t * direction`` with the camera-frame
direction ``K^-1 [u, v, 1]`` rotated into the map frame, so ``t`` *is* the z-depth and the
rendered depth compares directly with the depth image.

SDF units: the decoder predicts ``s`` in units of the truncation ``tr`` (free space has
``s = 1``), as in the paper's implementation; the paper's weight
``w = sigmoid(s / tr) * sigmoid(-s / tr)`` is applied to it, which makes the weights peak
within a few centimetres of the surface. Samples more than ``tr`` past the first sign change
of a ray are masked (the paper masks points behind the truncation region), and by default
also those more than ``tr`` in front of it (``RenderConfig.mask_in_front``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from . import kernels
from .voxels import MORTON_OFFSET, lookup_sorted, morton_decode, morton_encode


@dataclass(frozen=True)
class MapView:
    """The tensors of one map that rendering reads (all in the map frame).

    voxel_codes: (Nv,) sorted int64 Morton codes. voxel_corners: (Nv, 8) int64 embedding rows.
    embeddings: (Nc, D) float32 (may require grad). voxel_size: metres.
    """

    voxel_codes: torch.Tensor
    voxel_corners: torch.Tensor
    embeddings: torch.Tensor
    voxel_size: float
    voxel_coords: torch.Tensor | None = None
    """(Nv, 3) float coordinates of the voxels (decoded once instead of per sample)."""

    def __post_init__(self) -> None:
        if self.voxel_coords is None:
            object.__setattr__(self, "voxel_coords", morton_decode(self.voxel_codes).to(torch.float32))

    @classmethod
    def of(cls, vmap) -> "MapView":
        return cls(vmap.voxel_codes, vmap.voxel_corners, vmap.embeddings, vmap.voxel_size)

    def find(self, ijk: torch.Tensor) -> torch.Tensor:
        """Row in ``voxel_codes`` of each voxel (M, 3) int64, -1 where absent: the same as
        ``lookup_sorted(voxel_codes, morton_encode(ijk))`` for coordinates in the Morton
        range, in a tenth of the operators. The voxels' linear keys ``(i << 42) | (j << 21)
        | k`` (offset by 2^20 per axis) are sorted once per view (the static-shape
        renderers look up every grid point of every iteration)."""
        keys, rows = self._linear_table()
        if keys.numel() == 0:
            return torch.full_like(ijk[:, 0], -1)
        query = _linear_key(ijk)
        pos = torch.searchsorted(keys, query).clamp(max=keys.numel() - 1)
        return torch.where(keys[pos] == query, rows[pos], torch.full_like(query, -1))

    def _linear_table(self) -> tuple[torch.Tensor, torch.Tensor]:
        table = self.__dict__.get("_linear")
        if table is None:
            keys = _linear_key(self.voxel_coords.to(torch.int64))
            keys, rows = torch.sort(keys)
            table = (keys, rows)
            object.__setattr__(self, "_linear", table)
        return table


def _linear_key(ijk: torch.Tensor) -> torch.Tensor:
    """(M, 3) int64 voxel coordinates in [-2^20, 2^20) -> (M,) int64 keys, one per voxel."""
    u = ijk + MORTON_OFFSET
    return (u[:, 0] << 42) | (u[:, 1] << 21) | u[:, 2]


@dataclass(frozen=True)
class VoxelHits:
    """Segments of rays inside allocated voxels, sorted by ray then by ``t``.

    ray_index (H,) int64, voxel_index (H,) int64 into ``voxel_codes``, t_in/t_out (H,) float.
    """

    ray_index: torch.Tensor
    voxel_index: torch.Tensor
    t_in: torch.Tensor
    t_out: torch.Tensor


@dataclass(frozen=True)
class RaySamples:
    """Flat samples: ray_index (S,) int64, t (S,) z-depth, voxel_index (S,) int64.

    ``segments``: when the samples come from ``VoxelHits``, which hit each sample lies in,
    (S,) int64, and the voxel of each hit, (H,) int64 (read by ``interpolate_with_gradient``
    and ``interpolate_embeddings_reference``; the fused ``interpolate_embeddings`` needs none).
    """

    ray_index: torch.Tensor
    t: torch.Tensor
    voxel_index: torch.Tensor
    segments: Segments | None = None
    stands_for: torch.Tensor | None = None
    """After ``thin_training_samples``: (S,) float, how many samples of the full grid each one
    stands for in the losses' sums (1 or the free-space stride); None: 1 each."""
    grid_counts: torch.Tensor | None = None
    """After ``thin_training_samples``: (R,) int64, each ray's sample count before thinning
    (the ``slots`` normalisation's padded width)."""
    valid: torch.Tensor | None = None
    """Padded samples (``slam.padded``): (S,) bool, which slots hold a sample (None: all)."""


@dataclass(frozen=True)
class Segments:
    """Samples grouped by the stretch of a ray inside one voxel (about ten samples each).

    sample_segment (S,) int64 into segment_voxel (H,) int64; segment_voxel[sample_segment]
    is the samples' voxel_index.
    """

    sample_segment: torch.Tensor
    segment_voxel: torch.Tensor


@dataclass(frozen=True)
class RenderOutput:
    """Per-ray results for R rays and the per-sample values the losses need.

    color (R, 3), depth (R,), weight_sum (R,), hit (R,) bool: the ray has samples;
    depth_var (R,): weighted variance of sample depths (an uncertainty for tracking).
    samples: the flat samples; sdf (S,) in units of tr.
    """

    color: torch.Tensor
    depth: torch.Tensor
    weight_sum: torch.Tensor
    hit: torch.Tensor
    depth_var: torch.Tensor
    samples: RaySamples
    sdf: torch.Tensor


# --------------------------------------------------------------------- rays
def camera_rays(K: torch.Tensor, pixels_uv: torch.Tensor) -> torch.Tensor:
    """Camera-frame directions with z = 1. K (3, 3) or one per pixel (R, 3, 3), pixels_uv
    (R, 2) float -> (R, 3).

    OpenCV convention: the centre of pixel (u, v) is at the integer coordinates (u, v), so
    callers pass integer pixel indices as floats for pixel centres (the readers scale K with
    the same convention).
    """
    x = (pixels_uv[:, 0] - K[..., 0, 2]) / K[..., 0, 0]
    y = (pixels_uv[:, 1] - K[..., 1, 2]) / K[..., 1, 1]
    return torch.stack([x, y, torch.ones_like(x)], -1)


def rays_in_map(T_map_cam: torch.Tensor, dirs_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotate camera-frame directions (R, 3) by T_map_cam (4, 4) -> origins (R, 3), dirs (R, 3)."""
    dirs = dirs_cam @ T_map_cam[:3, :3].transpose(0, 1)
    origins = T_map_cam[:3, 3].expand_as(dirs)
    return origins, dirs


# ---------------------------------------------------------- ray-voxel tests
def _plane_range(o: torch.Tensor, d: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                 voxel_size: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The voxel-face planes of one axis that rays cross inside (near, far): the first plane's
    index k_lo (R,) float, their count (R,) int64, and whether the ray moves on the axis."""
    p0 = o + near * d
    p1 = o + far * d
    k_lo = torch.floor(torch.minimum(p0, p1) / voxel_size) + 1
    k_hi = torch.floor(torch.maximum(p0, p1) / voxel_size)
    moving = d.abs() > 1e-9
    count = torch.where(moving, (k_hi - k_lo + 1).clamp(min=0), torch.zeros_like(k_lo)).long()
    return k_lo, count, moving


def _axis_crossings(o: torch.Tensor, d: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                    voxel_size: float) -> torch.Tensor:
    """t of every voxel-face plane of one axis crossed inside (near, far); inf-padded.

    o, d, near, far: (R,) -> (R, n) with n the largest count over the rays.
    """
    k_lo, count, moving = _plane_range(o, d, near, far, voxel_size)
    n = int(count.max()) if count.numel() else 0
    if n == 0:
        return o.new_full((o.shape[0], 0), float("inf"))
    j = torch.arange(n, device=o.device, dtype=o.dtype)
    planes = (k_lo[:, None] + j[None]) * voxel_size
    safe_d = torch.where(moving, d, torch.ones_like(d))
    t = (planes - o[:, None]) / safe_d[:, None]
    return torch.where(j[None] < count[:, None], t, torch.full_like(t, float("inf")))


def clip_to_box(origins: torch.Tensor, dirs: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                voxel_codes: torch.Tensor, voxel_size: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Narrow [near, far] (R,) to where each ray is inside the bounding box of the voxels.

    Keeps the traversal's cost bounded by the map's extent, whatever the ray's range or a
    wild pose; rays that miss the box get an empty interval (far = near).
    """
    if voxel_codes.numel() == 0:
        return near, near.clone()
    ijk = morton_decode(voxel_codes)
    lo = ijk.min(0).values.to(origins.dtype) * voxel_size
    hi = (ijk.max(0).values + 1).to(origins.dtype) * voxel_size
    safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t0 = (lo - origins) / safe
    t1 = (hi - origins) / safe
    t_enter = torch.minimum(t0, t1).amax(1)
    t_exit = torch.maximum(t0, t1).amin(1)
    new_near = torch.maximum(near, t_enter)
    new_far = torch.minimum(far, t_exit)
    return new_near, torch.maximum(new_far, new_near)


def ray_voxel_intersections(origins: torch.Tensor, dirs: torch.Tensor, near: torch.Tensor,
                            far: torch.Tensor, voxel_codes: torch.Tensor, voxel_size: float,
                            max_hits: int) -> VoxelHits:
    """Allocated voxels each ray passes through within [near, far], at most ``max_hits`` each.

    Exact traversal without a per-step loop: the t of every face plane crossed is gathered on
    each axis, sorted, and each interval between consecutive crossings lies in one voxel,
    found from its midpoint. Hits come out near to far, so keeping the first ``max_hits``
    is the paper's "gather, sort near to far, mask the far ones" with ``far <= D_max``.

    origins, dirs (R, 3); near, far (R,) in units of t -> VoxelHits.
    Example: a ray from (0.1, 0.1, -1) along +z with voxels [0,0,0] and [0,0,2] allocated
    (size 1) and near=0, far=5 hits voxel 0 on t in [1, 2] and voxel 1 on [3, 4].
    Float32 CPU rays take one numba pass per ray where ``slam.kernels`` selects it (the same
    hits to the bit); ``ray_voxel_intersections_reference`` is the plain twin.
    """
    if kernels.use_numba(origins, dirs, near, far):
        from .kernels.fused import traverse

        with torch.no_grad():
            o, d = origins.detach(), dirs.detach()
            near, far = clip_to_box(o, d, near, far, voxel_codes, voxel_size)
            planes = [_plane_range(o[:, a], d[:, a], near, far, voxel_size) for a in range(3)]
            k_lo = torch.stack([k for k, _, _ in planes], 1)
            counts = torch.stack([n for _, n, _ in planes], 1)
            return VoxelHits(*traverse(o, d, near.contiguous(), far.contiguous(), k_lo, counts, voxel_codes,
                                       voxel_size, max_hits))
    return ray_voxel_intersections_reference(origins, dirs, near, far, voxel_codes, voxel_size, max_hits)


def ray_voxel_intersections_reference(origins: torch.Tensor, dirs: torch.Tensor, near: torch.Tensor,
                                      far: torch.Tensor, voxel_codes: torch.Tensor, voxel_size: float,
                                      max_hits: int) -> VoxelHits:
    """``ray_voxel_intersections`` in plain torch operators, whatever ``VOXFUSION_KERNELS`` says."""
    with torch.no_grad():
        o, d = origins.detach(), dirs.detach()
        near, far = clip_to_box(o, d, near, far, voxel_codes, voxel_size)
        crossings = [_axis_crossings(o[:, a], d[:, a], near, far, voxel_size) for a in range(3)]
        bounds = torch.cat([near[:, None]] + crossings + [far[:, None]], 1)
        bounds, _ = torch.sort(bounds, dim=1)
        bounds = torch.minimum(bounds, far[:, None])
        t0, t1 = bounds[:, :-1], bounds[:, 1:]
        valid = t1 > t0 + 1e-7
        mid = 0.5 * (t0 + t1)
        pts = o[:, None, :] + mid[..., None] * d[:, None, :]
        ijk = torch.floor(pts / voxel_size).long()
        ray_idx, seg_idx = torch.nonzero(valid, as_tuple=True)
        # Points outside the Morton range cannot be in the map; clamp so they just miss.
        codes = morton_encode(ijk[ray_idx, seg_idx].clamp(-(1 << 20), (1 << 20) - 1))
        vox = lookup_sorted(voxel_codes, codes)
        hit = vox >= 0
        ray_idx, seg_idx, vox = ray_idx[hit], seg_idx[hit], vox[hit]
        if max_hits > 0 and ray_idx.numel():
            rank = _rank_within_groups(ray_idx)
            keep = rank < max_hits
            ray_idx, seg_idx, vox = ray_idx[keep], seg_idx[keep], vox[keep]
        return VoxelHits(ray_idx, vox, t0[ray_idx, seg_idx], t1[ray_idx, seg_idx])


def _rank_within_groups(sorted_group: torch.Tensor) -> torch.Tensor:
    """0, 1, 2, ... within each run of equal values of a sorted (N,) tensor."""
    n = sorted_group.numel()
    starts = torch.ones(n, dtype=torch.bool, device=sorted_group.device)
    starts[1:] = sorted_group[1:] != sorted_group[:-1]
    idx = torch.arange(n, device=sorted_group.device)
    group_start = torch.cummax(torch.where(starts, idx, torch.zeros_like(idx)), 0).values
    return idx - group_start


# ------------------------------------------------------------------ sampling
def sample_points_from_hits(hits: VoxelHits, step: float, offsets: torch.Tensor) -> RaySamples:
    """Samples at ``t = (k + offset[ray]) * step`` (k integer) inside every hit segment.

    A fixed grid along each ray (the paper's fixed step length), shifted per ray by
    ``offsets`` (R,) in [0, 1): 0.5 for rendering, uniform random for stratified training.
    Output is flat and stays sorted by ray, then t.
    """
    u = offsets[hits.ray_index]
    k0 = torch.ceil(hits.t_in / step - u)
    k1 = torch.ceil(hits.t_out / step - u)
    counts = (k1 - k0).clamp(min=0).long()
    total = int(counts.sum())
    seg = torch.repeat_interleave(torch.arange(counts.numel(), device=counts.device), counts)
    first = torch.cumsum(counts, 0) - counts
    j = torch.arange(total, device=counts.device) - first[seg]
    t = (k0[seg] + j + u[seg]) * step
    return RaySamples(hits.ray_index[seg], t, hits.voxel_index[seg], Segments(seg, hits.voxel_index))


def band_grid(near: torch.Tensor, far: torch.Tensor, step: float, offset: float = 0.5
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """The grid samples ``t = (k + offset) * step`` in each ray's [near, far): the first k (R,)
    float and how many (R,) int64, those in unallocated voxels included.
    Example: near [0.0], far [0.5], step 0.1 -> k0 [0.], counts [5] (t = 0.05 .. 0.45)."""
    k0 = torch.ceil(near / step - offset)
    return k0, (torch.ceil(far / step - offset) - k0).clamp(min=0).long()


def sample_points_in_band(origins: torch.Tensor, dirs: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                          step: float, view: MapView, offset: float = 0.5) -> RaySamples:
    """Samples at ``t = (k + offset) * step`` in [near, far) that lie in allocated voxels,
    without the traversal: each grid point finds its voxel by lookup (in one numba pass where
    ``slam.kernels`` selects it; ``sample_points_in_band_reference`` is the plain twin).

    The same samples as ``ray_voxel_intersections`` then ``sample_points_from_hits`` with a
    constant offset (but no M_h cap), at a cost that grows with the range instead of with
    the voxels a ray crosses: for short ranges, such as a band around a known depth.
    origins, dirs (R, 3); near, far (R,) -> RaySamples (no segments), sorted by ray, then t.
    """
    k0, counts = band_grid(near, far, step, offset)
    if kernels.use_numba(origins, dirs, k0):
        from .kernels.fused import band_samples

        with torch.no_grad():
            return RaySamples(*band_samples(origins.detach(), dirs.detach(), k0.detach(), counts, step, offset,
                                            view.voxel_size, view.voxel_codes))
    return _band_samples_torch(origins, dirs, k0, counts, step, view, offset)


def sample_points_in_band_reference(origins: torch.Tensor, dirs: torch.Tensor, near: torch.Tensor,
                                    far: torch.Tensor, step: float, view: MapView,
                                    offset: float = 0.5) -> RaySamples:
    """``sample_points_in_band`` in plain torch operators, whatever ``VOXFUSION_KERNELS`` says."""
    k0, counts = band_grid(near, far, step, offset)
    return _band_samples_torch(origins, dirs, k0, counts, step, view, offset)


def _band_samples_torch(origins: torch.Tensor, dirs: torch.Tensor, k0: torch.Tensor, counts: torch.Tensor,
                        step: float, view: MapView, offset: float) -> RaySamples:
    total = int(counts.sum())
    ray = torch.repeat_interleave(torch.arange(counts.numel(), device=counts.device), counts)
    first = torch.cumsum(counts, 0) - counts
    j = torch.arange(total, device=counts.device) - first[ray]
    t = (k0[ray] + j + offset) * step
    points = origins[ray] + t[:, None] * dirs[ray]
    ijk = torch.floor(points / view.voxel_size).long().clamp(-(1 << 20), (1 << 20) - 1)
    voxel = lookup_sorted(view.voxel_codes, morton_encode(ijk))
    keep = voxel >= 0
    return RaySamples(ray[keep], t[keep], voxel[keep])


@dataclass(frozen=True)
class TrainingThinning:
    """What ``thin_training_samples`` needs: the rays' observed depth (R,) (invalid outside
    (0.01, max_depth)), the truncation, the free-space stride and a phase per ray (R,) int64
    in [0, stride), drawn anew every iteration."""

    depth: torch.Tensor
    truncation: float
    max_depth: float
    free_space_stride: int
    phase: torch.Tensor


def thin_training_samples(samples: RaySamples, thinning: TrainingThinning) -> RaySamples:
    """A cheaper unbiased sample set for the mapping losses (``MappingConfig.free_space_stride``).

    Of a ray with valid depth ``d``, the losses read the free-space samples (``t < d - tr``)
    through a sum and the SDF-band ones (``|t - d| <= tr``) one by one; samples behind the
    band feed neither and, once the map has its surface near ``d``, fall outside the first
    surface's window, so they are dropped. Of the free-space samples every ``stride``-th
    (from the ray's random phase) is kept and stands for ``stride`` (``stands_for``): the
    free-space sum keeps its expectation at a fraction of the decoder's work. Rays without
    valid depth keep every sample. Sorted by ray, then t, as the input. Float32 CPU samples
    choose in one numba pass (``slam.kernels``), the same choice as the torch lines here.
    """
    r, t = samples.ray_index, samples.t
    num_rays = thinning.depth.shape[0]
    stride = thinning.free_space_stride
    if kernels.use_numba(t, thinning.depth):
        from .kernels.fused import thin_mask

        keep, stands_for = thin_mask(r, t, thinning.depth, thinning.phase, thinning.truncation,
                                     thinning.max_depth, stride)
        stands_for = stands_for[keep]
    else:
        d = thinning.depth[r]
        valid = (d > 0.01) & (d < thinning.max_depth)
        front = valid & (t < d - thinning.truncation)
        behind = valid & (t > d + thinning.truncation)
        # Free-space samples are a prefix of their ray, so their rank in the ray is their
        # rank in the free space.
        picked = (_rank_within_groups(r) + thinning.phase[r]) % stride == 0
        keep = ~behind & (~front | picked)
        stands_for = torch.where(front, float(stride), 1.0)[keep]
    segments = samples.segments
    if segments is not None:
        segments = Segments(segments.sample_segment[keep], segments.segment_voxel)
    return RaySamples(r[keep], t[keep], samples.voxel_index[keep], segments, stands_for,
                      torch.bincount(r, minlength=num_rays))


# ------------------------------------------------------------- interpolation
def _corner_products(ax: torch.Tensor, ay: torch.Tensor, az: torch.Tensor) -> torch.Tensor:
    """(S, 2) factors per axis -> (S, 8) products, corner c at (c & 1, (c >> 1) & 1, (c >> 2) & 1)."""
    return (az[:, :, None, None] * ay[:, None, :, None] * ax[:, None, None, :]).reshape(-1, 8)


def trilinear_weights(local: torch.Tensor) -> torch.Tensor:
    """(S, 3) position inside the voxel in [0, 1]^3 -> (S, 8) corner weights.

    Corner c sits at offset (c & 1, (c >> 1) & 1, (c >> 2) & 1); weights sum to one.
    """
    wx, wy, wz = (torch.stack([1 - a, a], -1) for a in local.unbind(-1))
    return _corner_products(wx, wy, wz)


def _local_and_corner_embeddings(points: torch.Tensor, voxel_index: torch.Tensor, view: MapView,
                                 segments: Segments | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Position inside each sample's voxel (S, 3) in [0, 1] and its 8 corner rows (S, 8, D).

    With ``segments`` the corner rows are gathered once per segment and then copied to its
    samples as one 8 D-wide row each: the same numbers, but the backward scatters H x 8
    rows into the embeddings instead of S x 8 (S ~ 10 H), which roughly halves the cost of
    interpolation's backward on CPU.
    """
    D = view.embeddings.shape[1]
    ijk = view.voxel_coords[voxel_index].to(points.dtype)
    local = (points / view.voxel_size - ijk).clamp(0.0, 1.0)
    if segments is None:
        rows = _corner_rows(voxel_index, view)
    else:
        per_segment = _corner_rows(segments.segment_voxel, view).reshape(-1, 8 * D)
        rows = per_segment.index_select(0, segments.sample_segment)
    return local, rows.reshape(-1, 8, D)


def _corner_rows(voxel_index: torch.Tensor, view: MapView) -> torch.Tensor:
    """The 8 corner embeddings of voxels (N,) -> (N, 8, D)."""
    corners = view.voxel_corners[voxel_index]  # (N, 8)
    # index_select, not F.embedding: the same values, and its backward (index_add) takes
    # two thirds of embedding's dense backward on CPU (240k rows: 24 ms against 36 ms).
    rows = view.embeddings.index_select(0, corners.reshape(-1))
    return rows.reshape(*corners.shape, view.embeddings.shape[1])


class _WeightedCornerSum(torch.autograd.Function):
    """sum_c weights[s, c] * embeddings[corners[s, c]]: (Nc, D), (S, 8) int64, (S, 8) -> (S, D).

    The forward is ``embedding_bag`` (one fused gather-and-sum, no (S, 8, D) intermediate).
    Its built-in backward for the table sorts all S x 8 indices, which costs more than the
    rest of the interpolation on CPU; eight ``index_add_`` calls, one per corner, do the
    same sum without sorting. Reference: ``interpolate_embeddings_reference``.
    """

    @staticmethod
    def forward(ctx, embeddings: torch.Tensor, corners: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(embeddings, corners, weights)
        return torch.nn.functional.embedding_bag(corners, embeddings, mode="sum", per_sample_weights=weights)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        embeddings, corners, weights = ctx.saved_tensors
        grad_embeddings = grad_weights = None
        if ctx.needs_input_grad[0]:
            grad_embeddings = torch.zeros_like(embeddings)
            for c in range(corners.shape[1]):
                grad_embeddings.index_add_(0, corners[:, c], grad * weights[:, c:c + 1])
        if ctx.needs_input_grad[2]:
            rows = embeddings.index_select(0, corners.reshape(-1)).reshape(*corners.shape, -1)
            grad_weights = torch.bmm(rows, grad[:, :, None])[..., 0]
        return grad_embeddings, None, grad_weights


def interpolate_embeddings(points: torch.Tensor, voxel_index: torch.Tensor, view: MapView) -> torch.Tensor:
    """TriLerp of corner embeddings. points (S, 3) map frame, voxel_index (S,) -> (S, D).

    Differentiable with respect to both the embeddings and the points (tracking needs the
    latter). The fused path of ``_WeightedCornerSum``, which gathers rows inside
    ``embedding_bag`` and so needs no per-segment gather; ``interpolate_embeddings_reference``
    is the plain one it is tested against. Where nothing needs its gradient (views) and
    ``slam.kernels`` selects numba, one numba pass computes it.
    """
    differentiable = torch.is_grad_enabled() and (points.requires_grad or view.embeddings.requires_grad)
    if not differentiable and kernels.use_numba(points, view.embeddings):
        from .kernels.fused import interpolate

        return interpolate(points, voxel_index, view.voxel_coords, view.voxel_corners, view.voxel_size,
                           view.embeddings.detach())
    ijk = view.voxel_coords[voxel_index].to(points.dtype)
    local = (points / view.voxel_size - ijk).clamp(0.0, 1.0)
    return _WeightedCornerSum.apply(view.embeddings, view.voxel_corners[voxel_index], trilinear_weights(local))


def interpolate_embeddings_reference(points: torch.Tensor, voxel_index: torch.Tensor, view: MapView,
                                     segments: Segments | None = None) -> torch.Tensor:
    """``interpolate_embeddings`` in plain autograd: every sample's 8 corner rows gathered,
    weighted and summed."""
    local, feats = _local_and_corner_embeddings(points, voxel_index, view, segments)
    return (trilinear_weights(local)[..., None] * feats).sum(1)


def trilinear_weights_and_gradients(local: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``trilinear_weights`` (S, 8) and their derivatives (S, 3, 8) along x, y, z of ``local``."""
    wx, wy, wz = (torch.stack([1 - a, a], -1) for a in local.unbind(-1))
    one = torch.ones_like(local[:, 0])
    dw = torch.stack([-one, one], -1)
    grads = torch.stack([_corner_products(dw, wy, wz), _corner_products(wx, dw, wz),
                         _corner_products(wx, wy, dw)], 1)
    return _corner_products(wx, wy, wz), grads


def interpolate_with_gradient(points: torch.Tensor, voxel_index: torch.Tensor, view: MapView,
                              segments: Segments | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """TriLerp of corner embeddings and its exact spatial derivative, without autograd.

    points (S, 3) map frame, voxel_index (S,) -> features (S, D), d features / d point
    (S, 3, D) per metre. ``interpolate_embeddings`` under autograd is the reference. On float32
    CPU tensors one numba pass (``slam.kernels``; ``segments`` is then not needed).
    """
    if kernels.use_numba(points, view.embeddings):
        from .kernels.fused import interpolate_with_slopes

        return interpolate_with_slopes(points, voxel_index, view.voxel_coords, view.voxel_corners,
                                       view.voxel_size, view.embeddings)
    local, feats = _local_and_corner_embeddings(points, voxel_index, view, segments)
    w, dw = trilinear_weights_and_gradients(local)
    both = torch.bmm(torch.cat([w[:, None, :], dw / view.voxel_size], 1), feats)  # (S, 4, D)
    return both[:, 0], both[:, 1:]


def decode_samples(points: torch.Tensor, voxel_index: torch.Tensor, view: MapView,
                   decoder) -> tuple[torch.Tensor, torch.Tensor]:
    """SDF (S,) and trunk output (S, H) of the samples: points (S, 3), voxel_index (S,).

    ``decoder.sdf_and_hidden(interpolate_embeddings(...))``; for a ``Decoder`` on float32 CPU
    tensors, the fused numba kernels of ``slam.kernels.fused`` compute the same numbers
    (and gradients) without the per-sample intermediates (``VOXFUSION_KERNELS`` chooses).
    """
    if hasattr(decoder, "trunk_linears") and kernels.use_numba(points, view.embeddings, decoder.sdf_head.weight):
        from .kernels.fused import field_sdf_and_hidden

        return field_sdf_and_hidden(points, voxel_index, view.voxel_coords, view.voxel_corners,
                                    view.voxel_size, view.embeddings, decoder)
    return decoder.sdf_and_hidden(interpolate_embeddings(points, voxel_index, view))


def color_of_hidden(decoder, hidden: torch.Tensor) -> torch.Tensor:
    """(S, H) trunk output -> (S, 3) RGB; ``Decoder.color_from_hidden`` where the decoder has it."""
    if hasattr(decoder, "color_from_hidden"):
        return decoder.color_from_hidden(hidden)
    return decoder.color(decoder.feature_from_hidden(hidden))


# ------------------------------------------------------------------ weights
def first_zero_crossing(sdf: torch.Tensor, t: torch.Tensor, ray_index: torch.Tensor, num_rays: int) -> torch.Tensor:
    """(R,) ``t`` of each ray's first sign change of the SDF, inf where it has none.

    sdf, t, ray_index (S,) sorted by ray, then t. The crossing is interpolated linearly
    between the two samples around it, so it does not depend on where the samples fall.
    Example: sdf [0.5, -0.5 | 1], t [1.0, 1.2 | 1.0], rays [0, 0 | 1] -> [1.1, inf].
    """
    same_ray = ray_index[1:] == ray_index[:-1]
    change = (sdf[1:] * sdf[:-1] < 0) & same_ray
    first = torch.full((num_rays,), float("inf"), dtype=t.dtype, device=t.device)
    if bool(change.any()):
        s0, s1 = sdf[:-1][change], sdf[1:][change]
        t0, t1 = t[:-1][change], t[1:][change]
        t_zero = t0 + (t1 - t0) * s0 / (s0 - s1)
        first = first.scatter_reduce(0, ray_index[:-1][change], t_zero, "amin")
    return first


def first_surface_mask(sdf: torch.Tensor, t: torch.Tensor, ray_index: torch.Tensor, num_rays: int,
                       truncation: float, mask_in_front: bool = True) -> torch.Tensor:
    """(S,) bool: the sample lies within tr of its ray's first zero crossing.

    The paper masks samples more than tr behind the first zero crossing. With
    ``mask_in_front`` (the default, ``RenderConfig.mask_in_front``) we also mask those more
    than tr in front of it: while a map is young its free space is not yet at s = 1, and
    those samples drag the rendered depth toward the camera; the tracker then "fixes" that
    by backing the camera away, a drift that compounds (observed on every sequence we tried).
    Without it, only the samples behind are masked, as in the paper. Rays without a crossing
    keep all their samples.
    """
    with torch.no_grad():
        crossing = first_zero_crossing(sdf, t, ray_index, num_rays)[ray_index]
        behind_ok = t < crossing + truncation
        if not mask_in_front:
            return behind_ok
        return behind_ok & ((t > crossing - truncation) | torch.isinf(crossing))


def sdf_weights(sdf: torch.Tensor, t: torch.Tensor, ray_index: torch.Tensor, num_rays: int,
                truncation: float, mask_in_front: bool = True) -> torch.Tensor:
    """w = sigmoid(s/tr) * sigmoid(-s/tr), kept only within tr of the first surface
    (``first_surface_mask``). sdf (S,) in units of tr, t (S,), ray_index (S,) sorted -> (S,)."""
    w = torch.sigmoid(sdf / truncation) * torch.sigmoid(-sdf / truncation)
    return w * first_surface_mask(sdf, t, ray_index, num_rays, truncation, mask_in_front)


def sdf_weights_and_slope(sdf: torch.Tensor, t: torch.Tensor, ray_index: torch.Tensor, num_rays: int,
                          truncation: float, mask_in_front: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """``sdf_weights`` and its derivative dw/ds (S,), the mask held fixed.

    With a = s/tr: dw/da = w (1 - 2 sigmoid(a)), so dw/ds = w (1 - 2 sigmoid(a)) / tr.
    """
    sig = torch.sigmoid(sdf / truncation)
    w = sig * (1.0 - sig) * first_surface_mask(sdf, t, ray_index, num_rays, truncation, mask_in_front)
    return w, w * (1.0 - 2.0 * sig) / truncation


def accumulate_along_rays(weights: torch.Tensor, values: torch.Tensor, ray_index: torch.Tensor,
                          num_rays: int) -> torch.Tensor:
    """Sum of weights * values per ray. weights (S,), values (S, C) -> (R, C)."""
    out = values.new_zeros(num_rays, values.shape[1])
    return out.index_add(0, ray_index, weights[:, None] * values)


# ------------------------------------------------------------------ renderer
def render_rays(origins: torch.Tensor, dirs: torch.Tensor, view: MapView, decoder,
                *, near: torch.Tensor, far: torch.Tensor, step: float, truncation: float,
                max_hits: int, offsets: torch.Tensor | None = None,
                color_weight_eps: float = 1e-5, traverse: bool = True,
                mask_in_front: bool = True, renormalise_color: bool = False,
                thinning: TrainingThinning | None = None) -> RenderOutput:
    """Render R rays of one map. origins, dirs (R, 3) map frame; near, far (R,) -> RenderOutput.

    The colour head only runs on samples whose weight exceeds ``color_weight_eps`` (the
    others add nothing to the normalised colour), which saves most of its cost. With
    ``renormalise_color`` a ray's colour is normalised by the weights of those samples
    instead of all of them, so a large ``color_weight_eps`` does not darken it (views).
    ``traverse=False`` finds the samples by ``sample_points_in_band`` (short [near, far]
    ranges; no M_h cap, no ``offsets``). ``mask_in_front``: see ``first_surface_mask``
    (``RenderConfig.mask_in_front``; the fused decoder kernels end before the weights, so
    both kernel backends follow it). ``thinning``: mapping's cheaper sample set
    (``thin_training_samples``).
    """
    num_rays = origins.shape[0]
    if not traverse:
        samples = sample_points_in_band(origins, dirs, near, far, step, view)
    else:
        if offsets is None:
            offsets = torch.full((num_rays,), 0.5, device=origins.device)
        hits = ray_voxel_intersections(origins, dirs, near, far, view.voxel_codes, view.voxel_size, max_hits)
        samples = sample_points_from_hits(hits, step, offsets)
    if thinning is not None:
        samples = thin_training_samples(samples, thinning)
    r = samples.ray_index
    points = origins[r] + samples.t[:, None] * dirs[r]
    sdf, hidden = decode_samples(points, samples.voxel_index, view, decoder)
    w = sdf_weights(sdf, samples.t, r, num_rays, truncation, mask_in_front)
    wsum = torch.zeros(num_rays, device=w.device, dtype=w.dtype).index_add(0, r, w)
    norm = 1.0 / (wsum + 1e-8)
    depth = torch.zeros_like(wsum).index_add(0, r, w * samples.t) * norm
    depth_var = torch.zeros_like(wsum).index_add(0, r, w * (samples.t - depth.detach()[r]) ** 2) * norm
    active = torch.nonzero(w.detach() > color_weight_eps, as_tuple=True)[0]
    rgb_active = color_of_hidden(decoder, hidden[active])
    if renormalise_color:
        w_active = torch.zeros_like(wsum).index_add(0, r[active], w[active])
        color = accumulate_along_rays(w[active], rgb_active, r[active], num_rays) / (w_active + 1e-8)[:, None]
    else:
        color = accumulate_along_rays(w[active], rgb_active, r[active], num_rays) * norm[:, None]
    hit = torch.zeros(num_rays, dtype=torch.bool, device=origins.device)
    hit[r] = True
    return RenderOutput(color, depth, wsum, hit, depth_var, samples, sdf)
