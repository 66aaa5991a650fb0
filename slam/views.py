"""Whole images of the neural map: colour and depth for any camera pose and intrinsics.

Every pixel centre ``(u, v)`` (integer coordinates, the OpenCV convention of the readers) becomes a ray; each submap renders the rays in its
own frame (``T_map_cam = T_world_map^-1 T_world_cam``) with ``slam.render.render_rays``, in
chunks of ``config.render.chunk_rays`` rays under ``torch.no_grad`` so that memory does not
grow with the image size. Depth is z-depth in metres, as the input depth images.

A ray *sees a surface* in a submap when the SDF changes sign between two of its neighbouring
samples, or when one of its samples lies within one sampling step of the zero level set
(``|s| * tr <= step``: a crossing just in front of its first sample, a surface near the front
face of the allocated region). The sign change is needed as well: a learned SDF is often
steeper than a distance (slope 2 on fr1/rpy and Replica), and then both samples around a
crossing can lie more than a step from zero (Replica room0: 130 such pixels a 640-wide view,
black before, 0.2 dB of PSNR). A ray through free space (``s`` near 1) or past voxels with no
surface has neither, and stays empty: depth 0 and black. A per-ray weight threshold would not
do: poorly trained free space (``s = 0.5``) adds weight on every sample, so long rays would
pass it. Where several submaps see a surface, the nearest one wins.

Two methods give nearly the same image:

``full`` (the reference) samples every ray from ``near`` to D_max through all the voxels it
meets, up to M_h of them, and decodes every sample.

``banded`` (the default) renders first a coarse grid of every ``coarse_stride``-th pixel in
each direction with the SDF head only (at ``COARSE_STEP_FACTOR`` times the step), then every
pixel only within a band around the depths its coarse neighbours saw: from the nearest to the
farthest, widened on both sides by ``BAND_WEIGHT_WIDTHS`` widths of the SDF weight (3 tr^2,
3 cm at tr = 0.1 m). The samples lie on the same grid in ``t`` whatever the ray's range, and
they are found by lookup rather than by traversal (``slam.render.sample_points_in_band``), so
a pixel gets the full render's samples near its surface, and drops only those whose weight is
too small to colour it: its depth moves by a few millimetres at most and its colour by a few
levels, for about a third of the time (decisions.md#views.BAND_WEIGHT_WIDTHS). A pixel none of whose coarse neighbours (the 4 x 4 coarse cells
around it) saw a surface stays empty: only a surface narrower than about ``coarse_stride``
pixels, or one hidden behind the first surface at every neighbour, can differ more. Where
the coarse samples around a pixel lie on one plane (``planar_depths``: within
``PLANAR_TOLERANCE``), its band centres on the depth interpolated between them instead of
spanning their range: a floor seen at a grazing angle then costs fewer samples
(decisions.md#views.PLANAR_TOLERANCE). The banded pixels render
in runs of similar sample counts (``band_chunks``), not of similar pixel counts.

Views need no gradients, so on a CPU that multiplies bfloat16 natively (AVX512-BF16 or AMX)
the decoder runs in bfloat16 (``precision="auto"``, ``Bfloat16Decoder``): 20 % off a banded
view, 0.01 dB. Elsewhere it runs in float32, where the numba kernels of ``slam.kernels``
sample the bands and interpolate the embeddings in one pass each.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from .fine_color import with_fine
from .render import band_grid, camera_rays, rays_in_map, render_rays

# The tuned constants below are measured in benchmarks/decisions.md (views.*), one entry each.
# Rays start this far in front of the camera (z-depth, metres): a camera placed inside an
# allocated voxel must not render the SDF at its own centre. Real depth starts beyond it.
DEFAULT_NEAR = 0.05
# The colour head only runs on samples above this weight, a fifth of the peak (0.25); a pixel's
# colour is their weighted mean (decisions.md#views.VIEW_COLOR_WEIGHT_EPS).
VIEW_COLOR_WEIGHT_EPS = 5e-2
VIEW_METHODS = ("banded", "full")
VIEW_PRECISIONS = ("auto", "float32", "bfloat16")
# Every 4th pixel in each direction: 1/16 of the rays for the coarse pass, fine enough that a
# 640x480 view's surfaces narrower than 4 pixels are all that can be missed.
DEFAULT_COARSE_STRIDE = 4
# The band reaches this many weight widths (tr^2) past the coarse neighbours' depths: beyond 3
# the weight is under VIEW_COLOR_WEIGHT_EPS (decisions.md#views.BAND_WEIGHT_WIDTHS).
BAND_WEIGHT_WIDTHS = 3.0
# ... and at least this many sampling steps, so that a coarse preset's band still holds the
# two samples that bracket the surface and one more.
BAND_MIN_STEPS = 1.5
# Where the coarse samples around a pixel lie on one plane to within this (metres of depth),
# its band centres on their interpolated depth (``planar_depths``); 0: off
# (decisions.md#views.PLANAR_TOLERANCE).
PLANAR_TOLERANCE = 0.01
# The coarse pass samples at this many times the step: it only places the bands
# (decisions.md#views.COARSE_STEP_FACTOR).
COARSE_STEP_FACTOR = 2.0
# The band pass renders its pixels in runs of at most this many samples for each ray of a
# ``chunk_rays`` chunk, not in chunks of ``chunk_rays`` pixels (decisions.md#views.BAND_CHUNK_SAMPLES_PER_RAY).
BAND_CHUNK_SAMPLES_PER_RAY = 16


def _cpu_flags() -> set[str] | None:
    """The CPU's feature flags from /proc/cpuinfo (Linux), or None where it cannot be read."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as info:
            for line in info:
                if line.startswith("flags"):
                    return set(line.partition(":")[2].split())
    except OSError:
        pass
    return None


def bf16_matmul_is_native() -> bool:
    """Whether this CPU multiplies bfloat16 natively (oneDNN with AVX512-BF16 or AMX); elsewhere
    torch emulates it, slower than float32. oneDNN's own check also says yes on AVX-512 CPUs
    without BF16 instructions (an Ice Lake Xeon: a 100k x 64 x 64 product took 16.9 ms in
    bfloat16 against 9.2 ms in float32), so where Linux lists the CPU's flags they decide."""
    try:
        supported = bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False
    flags = _cpu_flags()
    return supported and (flags is None or bool(flags & {"avx512_bf16", "amx_bf16"}))


class Bfloat16Decoder:
    """A view-only copy of a decoder whose matrix products run in bfloat16 (accumulated in
    float32 by oneDNN), returning float32 SDF and colour: 2.4x faster on this machine's CPU
    (1M samples: 0.25 against 0.60 s), SDF within 0.5 mm, colour within 1/500. The renderer
    keeps the weights, depth and sums in float32. For ``torch.no_grad`` views only.

    With ``fused`` (where oneDNN's fused linear + activation is at hand and the CPU multiplies
    bfloat16 natively) each layer and its ReLU or sigmoid are one oneDNN call, and the colour
    runs the feature rows of the SDF head and the colour head's first layer as one product
    (as ``Decoder.color_from_hidden``): 0.8x a 640x480 view's time, no ReLU or conversion
    passes left (decisions.md#views.Bfloat16Decoder). ``fused=False`` is the plain
    layer-by-layer twin."""

    def __init__(self, decoder, fused: bool | None = None) -> None:
        self._decoder = copy.deepcopy(decoder).to(torch.bfloat16)
        on_cpu = decoder.sdf_head.weight.device.type == "cpu"  # oneDNN's op takes CPU tensors
        use = fused_linear_available() if fused is None else fused
        self._fused = _fused_layers(decoder) if use and on_cpu else None

    def sdf_and_hidden(self, emb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self._fused is None:
            sdf, hidden = self._decoder.sdf_and_hidden(emb.to(torch.bfloat16))
            return sdf.float(), hidden
        hidden = emb.to(torch.bfloat16)
        for layer in self._fused.trunk:
            hidden = layer(hidden)
        return self._fused.sdf(hidden)[:, 0].float(), hidden

    def feature_from_hidden(self, hidden: torch.Tensor) -> torch.Tensor:
        return self._decoder.feature_from_hidden(hidden)

    def color_from_hidden(self, hidden: torch.Tensor) -> torch.Tensor:
        """(S, H) trunk output -> (S, 3) RGB, float32."""
        if self._fused is None:
            return self.color(self.feature_from_hidden(hidden))
        out = hidden
        for layer in self._fused.color:
            out = layer(out)
        return out.float()

    def color(self, feature: torch.Tensor) -> torch.Tensor:
        return self._decoder.color(feature).float()


@dataclass(frozen=True)
class _FusedLinear:
    """One bfloat16 layer ``activation(x W^T + b)`` as a single oneDNN call; activation is
    ``relu``, ``sigmoid`` or ``none``."""

    weight: torch.Tensor
    bias: torch.Tensor
    activation: str

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return torch.ops.mkldnn._linear_pointwise(x, self.weight, self.bias, self.activation, [], "")


@dataclass(frozen=True)
class _FusedDecoder:
    """A decoder's layers for ``Bfloat16Decoder``'s fused path: the trunk (each with its
    ReLU), the SDF row, and the colour from the trunk output."""

    trunk: tuple[_FusedLinear, ...]
    sdf: _FusedLinear
    color: tuple[_FusedLinear, ...]


def _fused_layers(decoder) -> _FusedDecoder:
    """``decoder``'s (float32) layers in bfloat16 for ``_FusedLinear``; the SDF head's feature
    rows and the colour head's first layer are multiplied in float32 first (no activation lies
    between them)."""
    def fused(weight: torch.Tensor, bias: torch.Tensor, activation: str) -> _FusedLinear:
        return _FusedLinear(weight.detach().to(torch.bfloat16).contiguous(),
                            bias.detach().to(torch.bfloat16).contiguous(), activation)

    trunk = tuple(fused(m.weight, m.bias, "relu") for m in decoder.trunk_linears())
    head_w, head_b = decoder.sdf_head.weight.detach(), decoder.sdf_head.bias.detach()
    linears = [m for m in decoder.color_head if isinstance(m, torch.nn.Linear)]
    first, rest = linears[0], linears[1:]
    color = [fused(first.weight @ head_w[1:], first.weight @ head_b[1:] + first.bias,
                   "relu" if rest else "sigmoid")]
    color += [fused(m.weight, m.bias, "relu" if i < len(rest) - 1 else "sigmoid") for i, m in enumerate(rest)]
    return _FusedDecoder(trunk, fused(head_w[:1], head_b[:1], "none"), tuple(color))


def fused_linear_available() -> bool:
    """Whether ``Bfloat16Decoder`` can run its fused path: oneDNN's fused linear + activation
    (``torch.ops.mkldnn._linear_pointwise``, what torch.compile's CPU backend calls) on a CPU
    that multiplies bfloat16 natively."""
    return hasattr(torch.ops.mkldnn, "_linear_pointwise") and bf16_matmul_is_native()


def view_decoder(decoder, device: torch.device, precision: str):
    """The decoder views run: ``decoder`` itself for ``float32``; for ``auto``, a bfloat16 copy
    on a CPU that multiplies bfloat16 natively; ``bfloat16`` forces the copy."""
    if precision == "float32" or (precision == "auto" and not (device.type == "cpu" and bf16_matmul_is_native())):
        return decoder
    return Bfloat16Decoder(decoder)


@dataclass(frozen=True)
class RenderedView:
    """A rendered image.

    rgb (H, W, 3) float32 in [0, 1], black where no surface; depth (H, W) float32 z-depth in
    metres, 0 where no surface; map_index (H, W) int32 index into ``MapSet.maps`` of the
    submap that gave each pixel, -1 where none.
    """

    rgb: np.ndarray
    depth: np.ndarray
    map_index: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool: pixels that see a surface."""
        return self.map_index >= 0


def _as_tensor(value, name: str, shape: tuple[int, ...]) -> torch.Tensor:
    """A float64 CPU tensor of the given shape from an array or tensor, or a ValueError."""
    tensor = value.detach().cpu() if torch.is_tensor(value) else torch.as_tensor(np.asarray(value))
    tensor = tensor.to(torch.float64)
    if tuple(tensor.shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(tensor.shape)}")
    if not bool(torch.isfinite(tensor).all()):
        raise ValueError(f"{name} holds non-finite values")
    return tensor


def pixel_centres(width: int, height: int) -> torch.Tensor:
    """(H * W, 2) float32 pixel centres ``(u, v)`` at integer coordinates, row-major."""
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float32),
                          torch.arange(width, dtype=torch.float32), indexing="ij")
    return torch.stack([u.reshape(-1), v.reshape(-1)], -1)


def rays_near_surface(sdf: torch.Tensor, t: torch.Tensor, ray_index: torch.Tensor, num_rays: int,
                      band: float, max_gap: float) -> torch.Tensor:
    """(R,) bool: rays with a sample whose ``|sdf| <= band``, or two consecutive samples at
    most ``max_gap`` apart in ``t`` whose SDF changes sign.

    sdf (S,) and band in the same units (here: the truncation), t (S,) and max_gap in metres,
    ray_index (S,), sorted by ray, then t -> (R,). The sign change catches a surface whose
    learned SDF is steeper than a distance (slope 2 is common on real data): its two
    samples around the crossing can both lie more than a step from zero. The gap keeps a
    change across unallocated space, between two unrelated surfaces, from counting.
    Example: sdf [1, 0.3, -0.1 | 1, 0.5 | 0.4, -0.4], t [0, 1, 2 | 0, 1 | 0, 1],
    rays [0, 0, 0 | 1, 1 | 2, 2], band 0.2, max_gap 1.5 -> [True, False, True, False].
    """
    found = torch.zeros(num_rays, dtype=torch.bool, device=sdf.device)
    found[ray_index[sdf.abs() <= band]] = True
    crossing = ((sdf[1:] * sdf[:-1] < 0) & (ray_index[1:] == ray_index[:-1])
                & (t[1:] - t[:-1] <= max_gap))
    found[ray_index[1:][crossing]] = True
    return found


def rendered_voxels(submap):
    """The MapView views render: the voxels the mapper has optimised. A voxel it never
    optimised holds random embeddings, which render nothing."""
    return submap.optimised_view(1)


@torch.no_grad()
def _render_submap_chunk(submap, T_map_cam: torch.Tensor, dirs_cam: torch.Tensor, config,
                         near: torch.Tensor, far: torch.Tensor, *, with_color: bool = True,
                         traverse: bool = True, decoder=None, view=None,
                         fine: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Render (R, 3) camera-frame directions in one submap between ``near`` and ``far`` (R,).

    -> colour (R, 3) (zero without ``with_color``: the coarse pass needs depth only; without
    the fine colour level when ``fine`` is False), depth (R,), surface (R,) bool, all on the
    submap's device. ``traverse=False`` for short
    ranges: samples by lookup instead of the voxel traversal (``render_rays``). ``decoder``
    defaults to the submap's (``view_decoder`` gives a faster one for views); ``view`` to its
    optimised voxels (``rendered_voxels``: pass it to build it once per image, not per chunk).
    """
    render = config.render
    step = render.step_ratio * submap.voxels.voxel_size
    origins, dirs = rays_in_map(T_map_cam, dirs_cam)
    num_rays = dirs.shape[0]
    out = render_rays(origins, dirs, rendered_voxels(submap) if view is None else view, decoder or submap.decoder, near=near, far=far,
                      step=step, truncation=render.truncation, max_hits=render.max_hits,
                      color_weight_eps=VIEW_COLOR_WEIGHT_EPS if with_color else float("inf"),
                      traverse=traverse, mask_in_front=render.mask_in_front, renormalise_color=True)
    # s is in units of tr: one step of depth is step / tr of s. Consecutive samples of a
    # voxel lie a step apart; 1.5 steps allows for float error.
    surface = rays_near_surface(out.sdf, out.samples.t, out.samples.ray_index, num_rays,
                                step / render.truncation, 1.5 * step)
    color = with_fine(submap.fine, origins, dirs, out.color, out.depth, surface) if with_color and fine else out.color
    return color, out.depth, surface


CROP_SLACK = 1e-3
"""Metres a cropped view's depth may lie outside the crop's range along its ray (float error)."""


def crop_range(T_world_cam: torch.Tensor, dirs_cam: torch.Tensor, box_min: torch.Tensor, box_max: torch.Tensor,
               near: float, far: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each ray is inside a world box: (R, 3) camera-frame directions (z = 1, so ``t``
    is z-depth in every frame), the box's (3,) corners -> near (R,), far (R,) within [near,
    far]; a ray that misses the box gets far = near (nothing to render)."""
    dirs = dirs_cam @ T_world_cam[:3, :3].transpose(0, 1)
    origin = T_world_cam[:3, 3]
    safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t0 = (box_min - origin) / safe
    t1 = (box_max - origin) / safe
    ray_near = torch.minimum(t0, t1).amax(1).clamp(min=near)
    ray_far = torch.maximum(t0, t1).amin(1).clamp(max=far)
    return ray_near, torch.maximum(ray_far, ray_near)


def _ray_range(dirs_cam: torch.Tensor, config, near: float, ray_range) -> tuple[torch.Tensor, torch.Tensor]:
    """Each ray's [near, far]: ``ray_range`` (a crop's), else ``near`` to D_max."""
    if ray_range is not None:
        return ray_range
    return torch.full_like(dirs_cam[:, 0], near), torch.full_like(dirs_cam[:, 0], config.render.max_distance)


def _render_submap_full(submap, T_map_cam: torch.Tensor, dirs_cam: torch.Tensor, config,
                        near: float, chunk: int, *, with_color: bool = True, decoder=None, view=None,
                        ray_range: tuple[torch.Tensor, torch.Tensor] | None = None
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every ray of (N, 3) ``dirs_cam`` from ``near`` to D_max (or over ``ray_range``, (N,)
    near and far each), in chunks -> colour, depth, surface."""
    ray_near, ray_far = _ray_range(dirs_cam, config, near, ray_range)
    parts = []
    for start in range(0, dirs_cam.shape[0], chunk):
        d = dirs_cam[start:start + chunk]
        parts.append(_render_submap_chunk(submap, T_map_cam, d, config, ray_near[start:start + chunk],
                                          ray_far[start:start + chunk], with_color=with_color,
                                          decoder=decoder, view=view))
    if not parts:
        empty = dirs_cam.new_zeros(0)
        return dirs_cam.new_zeros(0, 3), empty, empty.bool()
    return tuple(torch.cat(p) for p in zip(*parts))


def coarse_grid(size: int, stride: int) -> torch.Tensor:
    """Coarse sample positions along one image axis: every ``stride``-th pixel and the last.

    Example: size 10, stride 4 -> [0, 4, 8, 9].
    """
    ticks = list(range(0, size, stride))
    if ticks[-1] != size - 1:
        ticks.append(size - 1)
    return torch.tensor(ticks, dtype=torch.long)


def _bracketing_cells(cu: torch.Tensor, cv: torch.Tensor, width: int, height: int
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Indices (u0, u1) (W,) into ``cu`` and (v0, v1) (H,) into ``cv`` of the coarse columns
    and rows that bracket each pixel column and row (equal at the last one)."""
    u = torch.arange(width, device=cu.device)
    v = torch.arange(height, device=cv.device)
    u0 = (torch.searchsorted(cu, u, right=True) - 1).clamp(0, len(cu) - 1)
    v0 = (torch.searchsorted(cv, v, right=True) - 1).clamp(0, len(cv) - 1)
    return u0, (u0 + 1).clamp(max=len(cu) - 1), v0, (v0 + 1).clamp(max=len(cv) - 1)


def depth_bands(coarse_depth: torch.Tensor, coarse_surface: torch.Tensor, cu: torch.Tensor,
                cv: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel depth range of the surfaces seen by its coarse neighbours.

    coarse_depth, coarse_surface (hc, wc) at pixel columns ``cu`` (wc,) and rows ``cv`` (hc,)
    -> lo, hi (H * W,) row-major: the least and greatest depth over the 2 x 2 coarse cells
    that bracket each pixel where one of them saw a surface (a smooth surface between them
    lies within their range), else over the 4 x 4 around them (the edge of a surface that
    the bracket just missed); lo = inf where none of those saw one.
    """
    inf = torch.tensor(float("inf"), dtype=coarse_depth.dtype, device=coarse_depth.device)
    lo_c = torch.where(coarse_surface, coarse_depth, inf)
    hi_c = torch.where(coarse_surface, coarse_depth, -inf)
    u0, u1, v0, v1 = _bracketing_cells(cu, cv, width, height)

    def bracket(lo_grid: torch.Tensor, hi_grid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        lo = torch.minimum(torch.minimum(lo_grid[v0][:, u0], lo_grid[v0][:, u1]),
                           torch.minimum(lo_grid[v1][:, u0], lo_grid[v1][:, u1]))
        hi = torch.maximum(torch.maximum(hi_grid[v0][:, u0], hi_grid[v0][:, u1]),
                           torch.maximum(hi_grid[v1][:, u0], hi_grid[v1][:, u1]))
        return lo, hi

    lo, hi = bracket(lo_c, hi_c)
    # Grown by one coarse cell (3 x 3 pooling) for the pixels whose bracket saw nothing.
    lo_grown, hi_grown = bracket(-torch.nn.functional.max_pool2d(-lo_c[None, None], 3, 1, 1)[0, 0],
                                 torch.nn.functional.max_pool2d(hi_c[None, None], 3, 1, 1)[0, 0])
    missed = torch.isinf(lo)
    lo, hi = torch.where(missed, lo_grown, lo), torch.where(missed, hi_grown, hi)
    return lo.reshape(-1), hi.reshape(-1)


def _second_differences(q: torch.Tensor, seen: torch.Tensor, dim: int) -> torch.Tensor:
    """|q[i-1] - 2 q[i] + q[i+1]| along ``dim`` of a (hc, wc) grid; inf on the grid's edge and
    where one of the three saw no surface (nothing to say there that a plane holds)."""
    q, seen = q.movedim(dim, 0), seen.movedim(dim, 0)
    out = torch.full_like(q, float("inf"))
    if q.shape[0] >= 3:
        inner = (q[:-2] - 2 * q[1:-1] + q[2:]).abs()
        both = seen[:-2] & seen[1:-1] & seen[2:]
        out[1:-1] = torch.where(both, inner, out[1:-1])
    return out.movedim(0, dim)


def planar_depths(coarse_depth: torch.Tensor, coarse_surface: torch.Tensor, cu: torch.Tensor,
                  cv: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel depth interpolated between the 2 x 2 coarse samples that bracket it, and how
    far the coarse samples around it are from one plane.

    coarse_depth, coarse_surface (hc, wc) at pixel columns ``cu`` (wc,) and rows ``cv`` (hc,),
    evenly spaced but for the last -> depth, off_plane (H * W,) row-major, metres. On a plane,
    inverse depth q = 1/z is affine in the pixel coordinates, so bilinear interpolation of q
    is exact there. ``off_plane`` bounds how far the four bracketing samples and their
    neighbours along each axis are from affine: the cell's twist ``q00 - q01 - q10 + q11``
    (a quarter of it: bilinear against the best plane) and the second differences along
    each axis at the four corners (a crease that runs inside the cell, such as a wall
    meeting the floor, leaves the twist at zero but not these), turned into depth with
    ``|dz| = z^2 |dq|``. It is inf where one of those samples saw no surface, and on the
    grid's edge.
    Example: samples of the plane z = 1 / (0.5 + 0.01 u) -> that plane's depth at every
    pixel, off_plane 0 inside the grid.
    """
    q = torch.where(coarse_surface, 1.0 / coarse_depth.clamp(min=1e-6), torch.zeros_like(coarse_depth))
    bend = torch.maximum(_second_differences(q, coarse_surface, 0), _second_differences(q, coarse_surface, 1))
    u0, u1, v0, v1 = _bracketing_cells(cu, cv, width, height)
    u = torch.arange(width, device=cu.device)
    v = torch.arange(height, device=cv.device)
    a = ((u - cu[u0]).to(q.dtype) / (cu[u1] - cu[u0]).clamp(min=1).to(q.dtype)).clamp(0, 1)[None, :]
    b = ((v - cv[v0]).to(q.dtype) / (cv[v1] - cv[v0]).clamp(min=1).to(q.dtype)).clamp(0, 1)[:, None]
    q00, q01, q10, q11 = q[v0][:, u0], q[v0][:, u1], q[v1][:, u0], q[v1][:, u1]
    q_pixel = (1 - b) * ((1 - a) * q00 + a * q01) + b * ((1 - a) * q10 + a * q11)
    depth = 1.0 / q_pixel.clamp(min=1e-6)
    corners_bend = torch.maximum(torch.maximum(bend[v0][:, u0], bend[v0][:, u1]),
                                 torch.maximum(bend[v1][:, u0], bend[v1][:, u1]))
    off_q = torch.maximum(0.25 * (q00 - q01 - q10 + q11).abs(), corners_bend)
    s = coarse_surface
    all_four = s[v0][:, u0] & s[v0][:, u1] & s[v1][:, u0] & s[v1][:, u1]
    off_plane = torch.where(all_four, off_q * depth * depth, torch.full_like(depth, float("inf")))
    return depth.reshape(-1), off_plane.reshape(-1)


def band_sample_counts(near: torch.Tensor, far: torch.Tensor, step: float) -> torch.Tensor:
    """(R,) int64: how many grid samples each ray's band [near, far) holds, those in
    unallocated voxels included (``slam.render.band_grid``): an upper bound on what
    ``sample_points_in_band`` returns."""
    return band_grid(near, far, step)[1]


def band_chunks(counts: torch.Tensor, max_samples: int) -> list[tuple[int, int]]:
    """Consecutive runs ``[start, end)`` of rays with at most ``max_samples`` samples in all
    (a ray with more makes a run alone), covering every ray. counts (R,) int64.
    Example: counts [3, 3, 3, 9, 1], max_samples 6 -> [(0, 2), (2, 3), (3, 4), (4, 5)].
    """
    total = torch.cumsum(counts, 0)
    runs, start = [], 0
    while start < counts.numel():
        before = int(total[start] - counts[start])
        end = int(torch.searchsorted(total, before + max_samples, right=True))
        end = max(end, start + 1)
        runs.append((start, end))
        start = end
    return runs


def _coarse_config(config):
    """The coarse pass's config: the same but for a step ``COARSE_STEP_FACTOR`` times longer."""
    if COARSE_STEP_FACTOR == 1.0:
        return config
    render = dataclasses.replace(config.render, step_ratio=config.render.step_ratio * COARSE_STEP_FACTOR)
    return dataclasses.replace(config, render=render)


def _pixel_bands(submap, T_map_cam: torch.Tensor, dirs_cam: torch.Tensor, config, near: float, chunk: int,
                 width: int, height: int, stride: int, decoder=None, view=None,
                 planar_tolerance: float = PLANAR_TOLERANCE, ray_range=None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The coarse pass and the bands it gives: (H * W, 3) directions -> the pixels with a band
    (P,) int64 and its [near, far) (P,) in metres of ``t``, within ``ray_range`` if given."""
    device = dirs_cam.device
    ray_near, ray_far = _ray_range(dirs_cam, config, near, ray_range)
    cu, cv = coarse_grid(width, stride).to(device), coarse_grid(height, stride).to(device)
    coarse_index = (cv[:, None] * width + cu[None, :]).reshape(-1)
    _, coarse_depth, coarse_surface = _render_submap_full(
        submap, T_map_cam, dirs_cam[coarse_index], _coarse_config(config), near, chunk, with_color=False,
        decoder=decoder, view=view, ray_range=(ray_near[coarse_index], ray_far[coarse_index]))
    coarse_depth = coarse_depth.reshape(len(cv), len(cu))
    coarse_surface = coarse_surface.reshape(len(cv), len(cu))
    lo, hi = depth_bands(coarse_depth, coarse_surface, cu, cv, width, height)
    if planar_tolerance > 0:
        planar, off_plane = planar_depths(coarse_depth, coarse_surface, cu, cv, width, height)
        on_plane = off_plane <= planar_tolerance
        lo = torch.where(on_plane, planar - off_plane, lo)
        hi = torch.where(on_plane, planar + off_plane, hi)
    # At least BAND_MIN_STEPS steps, so that a coarse preset's band still holds the two
    # samples that bracket the surface and one more.
    margin = max(BAND_WEIGHT_WIDTHS * config.render.truncation ** 2,
                 BAND_MIN_STEPS * config.render.step_ratio * submap.voxels.voxel_size)
    banded = torch.nonzero(torch.isfinite(lo), as_tuple=True)[0]
    band_near = torch.maximum(lo[banded] - margin, ray_near[banded])
    band_far = torch.maximum(torch.minimum(hi[banded] + margin, ray_far[banded]), band_near)
    return banded, band_near, band_far


def _render_submap_banded(submap, T_map_cam: torch.Tensor, dirs_cam: torch.Tensor, config,
                          near: float, chunk: int, width: int, height: int, stride: int, decoder=None,
                          view=None, planar_tolerance: float = PLANAR_TOLERANCE, ray_range=None,
                          fine: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The ``banded`` method for one submap: (H * W, 3) directions -> colour, depth, surface
    (colour without the fine level when ``fine`` is False)."""
    banded, band_near, band_far = _pixel_bands(submap, T_map_cam, dirs_cam, config, near, chunk, width, height,
                                               stride, decoder=decoder, view=view, planar_tolerance=planar_tolerance,
                                               ray_range=ray_range)
    step = config.render.step_ratio * submap.voxels.voxel_size
    num_pixels = width * height
    device = dirs_cam.device
    rgb = torch.zeros(num_pixels, 3, device=device)
    depth = torch.zeros(num_pixels, device=device)
    surface = torch.zeros(num_pixels, dtype=torch.bool, device=device)
    runs = band_chunks(band_sample_counts(band_near, band_far, step), chunk * BAND_CHUNK_SAMPLES_PER_RAY)
    for start, end in runs:
        idx = banded[start:end]
        c, d, s = _render_submap_chunk(submap, T_map_cam, dirs_cam[idx], config, band_near[start:end],
                                       band_far[start:end], traverse=False, decoder=decoder, view=view,
                                       fine=fine)
        rgb[idx], depth[idx], surface[idx] = c, d, s
    return rgb, depth, surface


def _check_view_options(width: int, height: int, method: str, precision: str, coarse_stride: int,
                        planar_tolerance: float) -> None:
    """ValueError naming the first of ``render_view``'s options that is out of range."""
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if method not in VIEW_METHODS:
        raise ValueError(f"method must be one of {VIEW_METHODS}, got {method!r}")
    if precision not in VIEW_PRECISIONS:
        raise ValueError(f"precision must be one of {VIEW_PRECISIONS}, got {precision!r}")
    if int(coarse_stride) < 1:
        raise ValueError(f"coarse_stride must be at least 1, got {coarse_stride}")
    if not float(planar_tolerance) >= 0:
        raise ValueError(f"planar_tolerance must be at least 0 (metres; 0 turns it off), got {planar_tolerance}")


@torch.no_grad()
def coarse_surface(submap, T_map_cam: torch.Tensor, K: torch.Tensor, width: int, height: int, config,
                   near: float = DEFAULT_NEAR, decoder=None, view=None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One submap seen by a ``width`` x ``height`` pinhole camera (K (3, 3)) at T_map_cam (4, 4),
    in the map's own frame and without its fine colour level, as ``render_view`` renders it
    (``banded``, decoder precision ``auto``) -> coarse colour (H * W, 3), the map-frame surface
    point of each pixel (H * W, 3) (its ray at the rendered depth) and surface (H * W,) bool.
    The fine level's rendered-surface fit learns its residual against these
    (``Mapper.fit_fine_rendered``), so that views add it at the very points it was fitted.
    ``decoder`` and ``view``: ``view_decoder(submap.decoder, device, "auto")`` and
    ``rendered_voxels(submap)``, built here unless given (give them to render many cameras)."""
    device = submap.voxels.device
    T_map_cam = T_map_cam.to(device, torch.float32)
    dirs_cam = camera_rays(K.to(device, torch.float32), pixel_centres(width, height).to(device))
    color, depth, surface = _render_submap_banded(
        submap, T_map_cam, dirs_cam, config, near, config.render.chunk_rays, width, height, DEFAULT_COARSE_STRIDE,
        decoder=decoder or view_decoder(submap.decoder, device, "auto"), view=view or rendered_voxels(submap),
        fine=False)
    origins, dirs = rays_in_map(T_map_cam, dirs_cam)
    return color, origins + depth[:, None] * dirs, surface


def render_view(mapset, T_world_cam, K, width: int, height: int, *, chunk_rays: int | None = None,
                device: str | torch.device | None = None, near: float = DEFAULT_NEAR,
                method: str = "banded", coarse_stride: int = DEFAULT_COARSE_STRIDE,
                precision: str = "auto", planar_tolerance: float = PLANAR_TOLERANCE,
                crop: tuple | None = None) -> RenderedView:
    """Render colour and depth of the whole map set seen by one pinhole camera.

    T_world_cam (4, 4) camera-to-world, OpenCV axes; K (3, 3) intrinsics of a
    ``width`` x ``height`` image (arrays or tensors). ``chunk_rays`` defaults to
    ``config.render.chunk_rays``; ``device`` to the first submap's. Rays run from ``near``
    to ``config.render.max_distance`` (D_max) in z-depth. ``method`` is ``banded`` (coarse
    pass, then a depth band per pixel) or ``full`` (the reference); see the module docstring.
    ``precision`` is the decoder's: ``auto`` (bfloat16 on a CPU that multiplies it natively,
    ``Bfloat16Decoder``; else float32), ``float32`` or ``bfloat16``. ``planar_tolerance``
    (metres, ``banded`` only; 0: off): see ``PLANAR_TOLERANCE``. ``crop`` (min (3,), max (3,))
    world-frame corners of a box: only what lies inside it is rendered.
    """
    width, height = int(width), int(height)
    _check_view_options(width, height, method, precision, coarse_stride, planar_tolerance)
    T_world_cam = _as_tensor(T_world_cam, "T_world_cam", (4, 4))
    K = _as_tensor(K, "K", (3, 3))
    config = mapset.config
    chunk = int(chunk_rays or config.render.chunk_rays)
    if chunk <= 0:
        raise ValueError(f"chunk_rays must be positive, got {chunk_rays}")
    if device is None:
        device = mapset.maps[0].voxels.device if mapset.maps else torch.device("cpu")
    device = torch.device(device)

    num_pixels = width * height
    dirs_cam = camera_rays(K.to(torch.float32), pixel_centres(width, height)).to(device)
    ray_range = None
    if crop is not None:
        box_min, box_max = (_as_tensor(c, "crop", (3,)).to(device, torch.float32) for c in crop)
        if not bool((box_min < box_max).all()):
            raise ValueError(f"crop: every min must be below its max, got {box_min.tolist()} and {box_max.tolist()}")
        ray_range = crop_range(T_world_cam.to(device, torch.float32), dirs_cam, box_min, box_max, near,
                               config.render.max_distance)
    best_depth = torch.full((num_pixels,), float("inf"), device=device)
    rgb = torch.zeros(num_pixels, 3, device=device)
    source = torch.full((num_pixels,), -1, dtype=torch.int32, device=device)
    for map_index, submap in enumerate(mapset.maps):
        if submap.voxels.num_voxels == 0:
            continue
        T_world_map = _as_tensor(submap.T_world_map, "T_world_map", (4, 4))
        T_map_cam = (torch.linalg.inv(T_world_map) @ T_world_cam).to(device, torch.float32)
        decoder = view_decoder(submap.decoder, device, precision)
        voxels = rendered_voxels(submap)
        if method == "full" or coarse_stride == 1:
            color, depth, surface = _render_submap_full(submap, T_map_cam, dirs_cam, config, near, chunk,
                                                        decoder=decoder, view=voxels, ray_range=ray_range)
        else:
            color, depth, surface = _render_submap_banded(submap, T_map_cam, dirs_cam, config, near, chunk,
                                                          width, height, int(coarse_stride), decoder=decoder,
                                                          view=voxels, planar_tolerance=float(planar_tolerance),
                                                          ray_range=ray_range)
        if ray_range is not None:  # samples snap to the voxels' step grid: keep only depths inside the crop
            surface = surface & (depth >= ray_range[0] - CROP_SLACK) & (depth <= ray_range[1] + CROP_SLACK)
        nearer = surface & (depth < best_depth)
        best_depth = torch.where(nearer, depth, best_depth)
        rgb = torch.where(nearer[:, None], color.clamp(0.0, 1.0), rgb)
        source = torch.where(nearer, torch.full_like(source, map_index), source)

    depth_out = torch.where(source >= 0, best_depth, torch.zeros_like(best_depth))
    return RenderedView(
        rgb=rgb.reshape(height, width, 3).cpu().numpy().astype(np.float32),
        depth=depth_out.reshape(height, width).cpu().numpy().astype(np.float32),
        map_index=source.reshape(height, width).cpu().numpy(),
    )
