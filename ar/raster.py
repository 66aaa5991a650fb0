"""A vectorised z-buffer rasteriser for virtual objects (colour and depth, anti-aliased).

Pipeline, all on tensors (torch, CPU by default, CUDA if asked):

1. ``camera_triangles``: object vertices to the camera frame, Lambert shading per triangle
   corner (flat by face normal, or smooth by vertex normal), two-sided; back faces of closed
   meshes that cannot be seen are skipped (half the work, same image).
2. ``clip_triangles_near``: triangles crossing the plane ``z = z_near`` are cut (one triangle
   becomes one or two); those wholly behind it are dropped.
3. ``rasterize_triangles``: each triangle's clamped screen bounding box is cut into sample
   rows; on each row the three barycentric half-planes bound an exact run of covered samples
   (float64, one small computation per row instead of an inside test per sample). Runs of all
   triangles are expanded at once and stored flat with a run index (like samples with a ray
   index in a volume renderer). ``1/z`` and ``colour/z`` are affine in screen space, so depth
   (z in the camera frame) and colour are perspective-correct. The z-test is one
   ``scatter_reduce(amin)`` over 64-bit keys ``(float bits of z) << 32 | triangle``: positive
   floats order like their bit patterns, so the minimum key holds the nearest depth and the
   triangle that made it. Colour is then computed once per covered sample, for the winning
   triangle only (deferred shading).
4. ``downsample``: the supersampled layer (``s x s`` samples per pixel) is averaged into
   coverage and colour; compositing (ar.composite) uses the samples directly so that the
   depth test is per sample.

Pixel convention: OpenCV, pixel ``(u, v)`` has its centre at ``(u, v)``; with supersampling
``s`` the sample ``(j, i)`` of the fine grid sits at ``u = (j + 0.5) / s - 0.5``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from ar.objects import VirtualObject

DEFAULT_Z_NEAR = 0.01
"""Metres; geometry nearer than this to the camera centre is clipped away."""

_CANDIDATES_PER_CHUNK = 1 << 21
"""Covered (sample, triangle) pairs expanded at once, about 60 MB of temporaries."""

_INSIDE_EPS = 1e-6
"""Barycentric slack so samples exactly on a shared edge are not lost to rounding."""

_EMPTY_KEY = torch.iinfo(torch.int64).max


@dataclass(frozen=True)
class Light:
    """A directional light plus ambient term, Lambert model.

    Attributes:
        direction: (3,) direction the light travels (from the light into the scene); need
            not be unit length. The default comes from above-left, slightly behind the camera.
        ambient: intensity on surfaces facing away from the light.
        diffuse: extra intensity at normal incidence.
        in_camera_frame: True: ``direction`` is in the camera frame (OpenCV axes, the light
            moves with the viewer); False: in the world frame.
    """

    direction: tuple[float, float, float] = (0.4, 0.6, 1.0)
    ambient: float = 0.35
    diffuse: float = 0.65
    in_camera_frame: bool = True

    def direction_in_camera(self, T_world_cam: np.ndarray) -> np.ndarray:
        """(3,) float64 unit direction of travel in the camera frame."""
        direction = np.asarray(self.direction, dtype=np.float64)
        norm = np.linalg.norm(direction)
        if direction.shape != (3,) or not np.isfinite(norm) or norm == 0:
            raise ValueError(f"Light.direction: expected a non-zero 3-vector, got {self.direction!r}")
        direction = direction / norm
        return direction if self.in_camera_frame else T_world_cam[:3, :3].T @ direction


@dataclass(frozen=True)
class SampleLayer:
    """The object layer on the sample grid ``(height * s, width * s)``, covered samples only.

    Stored flat like samples with a ray index: most of a view is empty, and compositing then
    touches only the samples that hold an object.

    Attributes:
        width, height: image size in pixels; supersample: s samples per pixel along each axis.
        sample_index: (N,) int64 ascending row-major index into the sample grid.
        pixel_index: (N,) int64 row-major index of each sample's pixel in the (height, width)
            image.
        depth: (N,) float32 z in the camera frame of the nearest surface.
        rgb: (N, 3) float32 shaded colour in [0, 1].
    """

    width: int
    height: int
    supersample: int
    sample_index: torch.Tensor
    pixel_index: torch.Tensor
    depth: torch.Tensor
    rgb: torch.Tensor

    def dense(self) -> tuple[np.ndarray, np.ndarray]:
        """depth (H*s, W*s) float32 with inf where empty and rgb (H*s, W*s, 3) float32."""
        s = self.supersample
        num_samples = self.height * s * self.width * s
        depth = np.full(num_samples, np.inf, dtype=np.float32)
        rgb = np.zeros((num_samples, 3), dtype=np.float32)
        index = self.sample_index.cpu().numpy()
        depth[index] = self.depth.cpu().numpy()
        rgb[index] = self.rgb.cpu().numpy()
        return depth.reshape(self.height * s, self.width * s), rgb.reshape(self.height * s, self.width * s, 3)


@dataclass(frozen=True)
class ObjectRender:
    """The objects alone, at pixel resolution.

    Attributes:
        rgb: (H, W, 3) float32 mean colour of the covered samples (not premultiplied), 0 where
            empty.
        depth: (H, W) float32 nearest object z in the camera frame, inf where empty.
        coverage: (H, W) float32 in [0, 1], fraction of the pixel's samples an object covers.
    """

    rgb: np.ndarray
    depth: np.ndarray
    coverage: np.ndarray


def check_camera(K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Validated float64 copies of K (3, 3) and T_world_cam (4, 4); raises ValueError."""
    K = _check_intrinsics(K)
    T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
    if T_world_cam.shape != (4, 4) or not np.isfinite(T_world_cam).all():
        raise ValueError(f"T_world_cam: expected a finite 4x4 matrix, got shape {T_world_cam.shape}")
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"image size: width and height must be positive, got {width}x{height}")
    return K, T_world_cam


def _check_intrinsics(K: np.ndarray) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K: expected 3x3 pinhole intrinsics with fx, fy > 0, got {K.tolist()}")
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise ValueError(f"K: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
    return K


# ---------------------------------------------------------------------------------------
# 1. Objects to shaded camera-frame triangles.


def camera_triangles(
    objects: Sequence[VirtualObject],
    T_world_cam: np.ndarray,
    light: Light,
    *,
    cull_distance: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """All objects' triangles in the camera frame with Lambert-shaded corner colours.

    Args:
        objects: the virtual objects.
        T_world_cam: (4, 4) camera-to-world pose.
        light: the light.
        cull_distance: when given, back faces of closed meshes (``outward_winding != 0``) are
            dropped for objects whose bounding box is farther than this from the camera
            centre. They are hidden behind the mesh's own front faces then, so the image is
            unchanged and the rasteriser does half the work. Nearer objects keep them: the
            camera may be inside, or the near plane may cut the mesh open.

    Returns:
        tri_cam (T, 3, 3) float64 corner positions and tri_rgb (T, 3, 3) float32 corner
        colours in [0, 1].
    """
    T_cam_world = np.linalg.inv(T_world_cam)
    R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
    light_dir = light.direction_in_camera(T_world_cam)
    positions, colors = [], []
    for obj in objects:
        faces = obj.mesh.faces
        tri = (obj.world_vertices() @ R.T + t)[faces]
        normals_world = obj.world_vertex_normals()
        normals = None if normals_world is None else (normals_world @ R.T)[faces]
        albedo = obj.vertex_albedo()[faces]
        if cull_distance is not None and obj.mesh.outward_winding != 0:
            if _distance_to_bounds(obj, T_world_cam[:3, 3]) > cull_distance:
                front = _front_facing(tri, obj.mesh.outward_winding)
                tri, albedo = tri[front], albedo[front]
                normals = None if normals is None else normals[front]
        positions.append(tri)
        colors.append(shade_lambert(tri, normals, albedo, light_dir, light.ambient, light.diffuse))
    if not positions:
        return np.zeros((0, 3, 3)), np.zeros((0, 3, 3), dtype=np.float32)
    return np.concatenate(positions), np.concatenate(colors)


def _distance_to_bounds(obj: VirtualObject, point_world: np.ndarray) -> float:
    """Distance in metres from a world point to the object's scaled object-frame box."""
    R, t = obj.T_world_obj[:3, :3], obj.T_world_obj[:3, 3]
    point = R.T @ (point_world - t)
    low = obj.mesh.vertices.min(axis=0) * obj.scale
    high = obj.mesh.vertices.max(axis=0) * obj.scale
    return float(np.linalg.norm(np.maximum(0.0, np.maximum(low - point, point - high))))


def _front_facing(tri_cam: np.ndarray, outward_winding: int) -> np.ndarray:
    """(T,) bool, the outward normal points back towards the camera centre (the origin)."""
    normal = np.cross(tri_cam[:, 1] - tri_cam[:, 0], tri_cam[:, 2] - tri_cam[:, 0]) * outward_winding
    return np.einsum("ti,ti->t", normal, tri_cam[:, 0]) < 0


def cull_distance_for(K: np.ndarray, width: int, height: int, z_near: float) -> float:
    """Distance beyond which no point of an object can be cut by the near plane.

    A point in the view frustum with z < z_near has |x| <= z (|cx| + W) / fx and likewise
    for y, so it lies within z_near * (1 + (|cx| + W) / fx + (|cy| + H) / fy) of the centre.
    """
    return z_near * (1.0 + (abs(K[0, 2]) + width) / K[0, 0] + (abs(K[1, 2]) + height) / K[1, 1])


def shade_lambert(
    tri_cam: np.ndarray,
    corner_normals: np.ndarray | None,
    albedo: np.ndarray,
    light_dir: np.ndarray,
    ambient: float,
    diffuse: float,
) -> np.ndarray:
    """Two-sided Lambert shading at the triangle corners (interpolated later: Gouraud).

    ``colour = albedo * (ambient + diffuse * max(0, n . -light_dir))`` clipped to [0, 1],
    where n is turned to face the camera (at the origin), so a surface seen from inside is lit
    like its outside.

    Args:
        tri_cam: (T, 3, 3) corner positions in the camera frame.
        corner_normals: (T, 3, 3) normals at the corners, or None for flat face normals.
        albedo: (T, 3, 3) base colours.
        light_dir: (3,) unit direction of travel of the light, camera frame.

    Returns:
        (T, 3, 3) float32 shaded colours.
    """
    face_normal = np.cross(tri_cam[:, 1] - tri_cam[:, 0], tri_cam[:, 2] - tri_cam[:, 0])
    face_normal /= np.maximum(np.linalg.norm(face_normal, axis=1, keepdims=True), 1e-30)
    # The camera sees the side whose normal points back towards the origin.
    facing_sign = np.where(np.einsum("ti,ti->t", face_normal, tri_cam[:, 0]) > 0, -1.0, 1.0)
    front_normal = face_normal * facing_sign[:, None]
    if corner_normals is None:
        normals = np.broadcast_to(front_normal[:, None, :], tri_cam.shape)
    else:
        normals = corner_normals / np.maximum(np.linalg.norm(corner_normals, axis=2, keepdims=True), 1e-30)
        flip = np.einsum("tci,ti->tc", normals, front_normal) < 0
        normals = np.where(flip[..., None], -normals, normals)
    lambert = np.maximum(normals @ -light_dir, 0.0)
    intensity = ambient + diffuse * lambert
    return np.clip(albedo * intensity[..., None], 0.0, 1.0).astype(np.float32)


# ---------------------------------------------------------------------------------------
# 2. Near-plane clipping.


def clip_triangles_near(
    tri_cam: np.ndarray, attributes: np.ndarray, z_near: float
) -> tuple[np.ndarray, np.ndarray]:
    """Cut triangles at the plane ``z = z_near`` (Sutherland-Hodgman on one plane).

    A triangle with one corner in front becomes one smaller triangle, with two corners in
    front a quad split into two; attributes are interpolated linearly along the cut edges,
    which is exact in the camera frame. Winding is preserved.

    Args:
        tri_cam: (T, 3, 3) corner positions in the camera frame.
        attributes: (T, 3, C) per-corner attributes.
        z_near: the plane, metres > 0.

    Returns:
        (T', 3, 3) positions with every z >= z_near (up to rounding) and (T', 3, C) attributes.
    """
    signed = tri_cam[..., 2] - z_near
    inside = signed >= 0
    count = inside.sum(axis=1)
    kept = [(tri_cam[count == 3], attributes[count == 3])]
    for num_inside in (1, 2):
        select = count == num_inside
        if not select.any():
            continue
        # Rotate corners so that the odd one out (the lone inside or lone outside corner) is first.
        odd = np.argmax(inside[select] if num_inside == 1 else ~inside[select], axis=1)
        order = (odd[:, None] + np.arange(3)) % 3
        p = np.take_along_axis(tri_cam[select], order[..., None], axis=1)
        a = np.take_along_axis(attributes[select], order[..., None], axis=1)
        d = np.take_along_axis(signed[select], order, axis=1)[..., None]
        t_ab = d[:, 0] / (d[:, 0] - d[:, 1])
        t_ac = d[:, 0] / (d[:, 0] - d[:, 2])
        p_ab, a_ab = p[:, 0] + t_ab * (p[:, 1] - p[:, 0]), a[:, 0] + t_ab * (a[:, 1] - a[:, 0])
        p_ac, a_ac = p[:, 0] + t_ac * (p[:, 2] - p[:, 0]), a[:, 0] + t_ac * (a[:, 2] - a[:, 0])
        if num_inside == 1:
            kept.append((np.stack([p[:, 0], p_ab, p_ac], 1), np.stack([a[:, 0], a_ab, a_ac], 1)))
        else:
            # Polygon p_ab, B, C, p_ac (walking A->B->C->A with A cut off), fanned from p_ab.
            kept.append((np.stack([p_ab, p[:, 1], p[:, 2]], 1), np.stack([a_ab, a[:, 1], a[:, 2]], 1)))
            kept.append((np.stack([p_ab, p[:, 2], p_ac], 1), np.stack([a_ab, a[:, 2], a_ac], 1)))
    positions = np.concatenate([k[0] for k in kept])
    attrs = np.concatenate([k[1] for k in kept]).astype(attributes.dtype, copy=False)
    return positions, attrs


# ---------------------------------------------------------------------------------------
# 3. Rasterisation.


@dataclass(frozen=True)
class _ScreenTriangles:
    """Per-triangle set-up in sample-grid units (sample j has its centre at x = j + 0.5).

    Attributes:
        x0, x1, y0, y1: (T,) int64 clamped bounding box in samples (inclusive), non-empty.
        edge_planes: (T, 3, 3) float64 barycentric b_i(x, y) = [i, 0] x + [i, 1] y + [i, 2].
        inv_z_plane: (T, 3) float64 plane of 1/z, same form.
        shading: (11, T) float32 (attribute-major, so gathered rows are contiguous): planes of
            r/z, g/z, b/z as ``(d/dx, d/dy, value at the first sample of the box)``, then that
            sample's column and row. Planes re-based at the box keep float32 precise for small
            triangles far from the image origin.
    """

    x0: torch.Tensor
    x1: torch.Tensor
    y0: torch.Tensor
    y1: torch.Tensor
    edge_planes: torch.Tensor
    inv_z_plane: torch.Tensor
    shading: torch.Tensor


def _setup_triangles(
    tri_cam: np.ndarray,
    tri_rgb: np.ndarray,
    K: np.ndarray,
    grid_width: int,
    grid_height: int,
    supersample: int,
    device: torch.device,
) -> _ScreenTriangles:
    """Project clipped triangles, drop degenerate/off-screen ones, build attribute planes."""
    z = tri_cam[..., 2]
    x = (K[0, 0] * tri_cam[..., 0] / z + K[0, 1] * tri_cam[..., 1] / z + K[0, 2] + 0.5) * supersample
    y = (K[1, 1] * tri_cam[..., 1] / z + K[1, 2] + 0.5) * supersample
    x0 = np.clip(np.ceil(x.min(1) - 0.5), 0, grid_width).astype(np.int64)
    x1 = np.clip(np.floor(x.max(1) - 0.5), -1, grid_width - 1).astype(np.int64)
    y0 = np.clip(np.ceil(y.min(1) - 0.5), 0, grid_height).astype(np.int64)
    y1 = np.clip(np.floor(y.max(1) - 0.5), -1, grid_height - 1).astype(np.int64)
    area2 = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    keep = (x1 >= x0) & (y1 >= y0) & (np.abs(area2) > 1e-12)
    x, y, z, area2, tri_rgb = x[keep], y[keep], z[keep], area2[keep], tri_rgb[keep]
    x0, x1, y0, y1 = x0[keep], x1[keep], y0[keep], y1[keep]
    edges = _barycentric_planes(x, y, area2)
    inv_z = 1.0 / z
    inv_z_plane = np.einsum("ti,tip->tp", inv_z, edges)
    # The same planes re-based at the first sample of the box for float32 colour evaluation.
    local = _barycentric_planes(x - (x0 + 0.5)[:, None], y - (y0 + 0.5)[:, None], area2)
    color_planes = np.einsum("tic,tip->tcp", tri_rgb * inv_z[..., None], local)
    shading = np.concatenate([color_planes.reshape(-1, 9), x0[:, None], y0[:, None]], axis=1).T

    def tensor(a: np.ndarray, dtype: torch.dtype) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=device)

    return _ScreenTriangles(
        x0=tensor(x0, torch.int64),
        x1=tensor(x1, torch.int64),
        y0=tensor(y0, torch.int64),
        y1=tensor(y1, torch.int64),
        edge_planes=tensor(edges, torch.float64),
        inv_z_plane=tensor(inv_z_plane, torch.float64),
        shading=tensor(shading, torch.float32),
    )


def _barycentric_planes(x: np.ndarray, y: np.ndarray, area2: np.ndarray) -> np.ndarray:
    """(T, 3 corners, 3) planes ``b_i(x, y) = a x + b y + c`` of the screen barycentrics.

    Args:
        x, y: (T, 3) corner coordinates; area2: (T,) twice the signed area.
    """
    planes = np.empty((len(x), 3, 3))
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        planes[:, i, 0] = (y[:, j] - y[:, k]) / area2
        planes[:, i, 1] = (x[:, k] - x[:, j]) / area2
        planes[:, i, 2] = (x[:, j] * y[:, k] - x[:, k] * y[:, j]) / area2
    return planes


@dataclass(frozen=True)
class _Spans:
    """One run of covered samples per (triangle, sample row), at least one sample long.

    Attributes:
        triangle: (R,) int64 triangle index.
        first_sample: (R,) int64 flat grid index of the run's first sample.
        length: (R,) int64 samples in the run.
        inv_z_start: (R,) float32 1/z at the first sample; inv_z_step: (R,) float32 per sample.
    """

    triangle: torch.Tensor
    first_sample: torch.Tensor
    length: torch.Tensor
    inv_z_start: torch.Tensor
    inv_z_step: torch.Tensor


def _triangle_spans(screen: _ScreenTriangles, grid_width: int) -> _Spans:
    """Intersect every sample row of every bounding box with its triangle.

    On a row at height y each barycentric ``b_i = a_i x + e_i`` must be >= -eps, which bounds
    x from below (a_i > 0) or above (a_i < 0); the samples between the bounds are inside.
    This is done per row in float64, so no per-sample inside test is needed.
    """
    device = screen.x0.device
    heights = screen.y1 - screen.y0 + 1
    triangle = torch.repeat_interleave(torch.arange(len(heights), device=device), heights)
    first_row = torch.cumsum(heights, 0) - heights
    row = _take(screen.y0 - first_row, triangle) + torch.arange(len(triangle), device=device)
    y = row.to(torch.float64) + 0.5
    planes = _take(screen.edge_planes, triangle)  # (R, 3, 3)
    slope = planes[..., 0]
    offset = planes[..., 1] * y[:, None] + planes[..., 2]
    bound = (-_INSIDE_EPS - offset) / torch.where(slope == 0, torch.ones_like(slope), slope)
    inf = torch.full_like(bound, float("inf"))
    lower = torch.where(slope > 0, bound, -inf).amax(1)
    upper = torch.where(slope < 0, bound, inf).amin(1)
    blocked = ((slope == 0) & (offset < -_INSIDE_EPS)).any(1)
    first_col = torch.maximum(torch.ceil(lower - 0.5), _take(screen.x0, triangle).to(torch.float64))
    last_col = torch.minimum(torch.floor(upper - 0.5), _take(screen.x1, triangle).to(torch.float64))
    length = (last_col - first_col + 1).clamp(min=0).to(torch.int64)
    keep = ((length > 0) & ~blocked).nonzero().squeeze(1)
    triangle, row, y, first_col, length = (_take(a, keep) for a in (triangle, row, y, first_col, length))
    inv_z = _take(screen.inv_z_plane, triangle)
    inv_z_start = inv_z[:, 0] * (first_col + 0.5) + inv_z[:, 1] * y + inv_z[:, 2]
    return _Spans(
        triangle=triangle,
        first_sample=row * grid_width + first_col.to(torch.int64),
        length=length,
        inv_z_start=inv_z_start.to(torch.float32),
        inv_z_step=inv_z[:, 0].to(torch.float32).contiguous(),
    )


def _floor_div(values: torch.Tensor, divisor: int) -> torch.Tensor:
    """Floor division of non-negative int64 values; a shift when the divisor is a power of 2."""
    if divisor & (divisor - 1) == 0:
        return values >> (divisor.bit_length() - 1)
    return torch.div(values, divisor, rounding_mode="floor")


def _take(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``values[index]`` along the first axis; index_select is several times faster on CPU."""
    return torch.index_select(values, 0, index)


def _chunk_bounds(counts: torch.Tensor, budget: int) -> list[tuple[int, int]]:
    """Split items [0, N) into consecutive runs whose counts sum to <= budget (a run holds
    at least one item however large)."""
    ends = torch.cumsum(counts, 0).cpu().numpy()
    bounds, start, base = [], 0, 0
    while start < len(ends):
        stop = max(int(np.searchsorted(ends, base + budget, side="right")), start + 1)
        bounds.append((start, stop))
        base = int(ends[stop - 1])
        start = stop
    return bounds


def _depth_test(spans: _Spans, num_samples: int) -> torch.Tensor:
    """(num_samples,) int64 z-buffer of keys ``bits(z) << 32 | triangle``, empty = int64 max."""
    device = spans.length.device
    zbuffer = torch.full((num_samples,), _EMPTY_KEY, dtype=torch.int64, device=device)
    for start, stop in _chunk_bounds(spans.length, _CANDIDATES_PER_CHUNK):
        lengths = spans.length[start:stop]
        span = torch.repeat_interleave(torch.arange(start, stop, device=device), lengths)
        first = torch.cumsum(lengths, 0) - lengths
        step = torch.arange(len(span), device=device) - _take(first, span - start)
        inv_z = torch.addcmul(_take(spans.inv_z_start, span), _take(spans.inv_z_step, span), step.to(torch.float32))
        # 1/z is positive inside clipped triangles; the clamp keeps a sample taken within the
        # edge slack of an extreme sliver from wrapping to a negative, always-winning key.
        depth = torch.reciprocal(inv_z.clamp_(min=1e-12))
        key = (depth.view(torch.int32).to(torch.int64) << 32) | _take(spans.triangle, span)
        zbuffer.scatter_reduce_(0, _take(spans.first_sample, span) + step, key, reduce="amin")
    return zbuffer


def _shade_samples(
    zbuffer: torch.Tensor, screen: _ScreenTriangles, width: int, supersample: int
) -> tuple[torch.Tensor, ...]:
    """Covered sample indices (N,), their pixel indices (N,), depth (N,) and
    perspective-correct colour (N, 3)."""
    grid_width = width * supersample
    sample = (zbuffer != _EMPTY_KEY).nonzero().squeeze(1)
    key = _take(zbuffer, sample)
    depth = (key >> 32).to(torch.int32).view(torch.float32)
    shading = torch.index_select(screen.shading, 1, key & 0xFFFFFFFF)  # (11, N)
    row = _floor_div(sample, grid_width)
    col = sample - row * grid_width
    pixel = _floor_div(row, supersample) * width + _floor_div(col, supersample)
    fx = col.to(torch.float32) - shading[9]
    fy = row.to(torch.float32) - shading[10]
    planes = shading[:9].view(3, 3, -1)  # [channel, (d/dx, d/dy, value)]
    color_over_z = torch.addcmul(torch.addcmul(planes[:, 2], planes[:, 0], fx), planes[:, 1], fy)
    rgb = torch.clamp(color_over_z * depth, 0.0, 1.0).t().contiguous()
    return sample, pixel, depth, rgb


def rasterize_triangles(
    tri_cam: np.ndarray,
    tri_rgb: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    *,
    supersample: int = 1,
    z_near: float = DEFAULT_Z_NEAR,
    device: str | torch.device = "cpu",
) -> SampleLayer:
    """Z-buffer camera-frame triangles onto the (height*s, width*s) sample grid.

    Args:
        tri_cam: (T, 3, 3) corner positions in the camera frame (OpenCV axes, metres);
            triangles with a non-finite corner are skipped.
        tri_rgb: (T, 3, 3) corner colours, interpolated perspective-correctly.
        K: (3, 3) intrinsics of the (width, height) image.
        supersample: s >= 1 samples per pixel along each axis.
        z_near: near clipping plane, metres > 0.
        device: torch device for the per-sample work.

    Returns:
        SampleLayer with, at each covered sample centre, z of the nearest triangle.
    """
    tri_cam = np.asarray(tri_cam, dtype=np.float64)
    tri_rgb = np.asarray(tri_rgb, dtype=np.float32)
    if tri_cam.ndim != 3 or tri_cam.shape[1:] != (3, 3) or tri_rgb.shape != tri_cam.shape:
        raise ValueError(f"tri_cam, tri_rgb: expected two (T, 3, 3) arrays, got {tri_cam.shape} and {tri_rgb.shape}")
    if int(supersample) != supersample or supersample < 1:
        raise ValueError(f"supersample: must be an integer >= 1, got {supersample}")
    if not z_near > 0:
        raise ValueError(f"z_near: must be > 0, got {z_near}")
    K = _check_intrinsics(K)
    device = torch.device(device)
    width, height, supersample = int(width), int(height), int(supersample)
    grid_width, grid_height = width * supersample, height * supersample
    finite = np.isfinite(tri_cam).all(axis=(1, 2))
    tri_cam, tri_rgb = clip_triangles_near(tri_cam[finite], tri_rgb[finite], z_near)
    screen = _setup_triangles(tri_cam, tri_rgb, K, grid_width, grid_height, supersample, device)
    zbuffer = _depth_test(_triangle_spans(screen, grid_width), grid_width * grid_height)
    sample, pixel, depth, rgb = _shade_samples(zbuffer, screen, width, supersample)
    return SampleLayer(
        width=width,
        height=height,
        supersample=supersample,
        sample_index=sample,
        pixel_index=pixel,
        depth=depth,
        rgb=rgb,
    )


def rasterize_objects(
    objects: Sequence[VirtualObject],
    K: np.ndarray,
    T_world_cam: np.ndarray,
    width: int,
    height: int,
    *,
    light: Light = Light(),
    supersample: int = 2,
    z_near: float = DEFAULT_Z_NEAR,
    device: str | torch.device = "cpu",
    cull_back_faces: bool = True,
) -> SampleLayer:
    """Shade and rasterise virtual objects at sample resolution (see ``render_objects``).

    ``cull_back_faces`` skips hidden back faces of closed meshes (see ``camera_triangles``);
    it changes nothing in the image, only the time.
    """
    K, T_world_cam = check_camera(K, T_world_cam, width, height)
    cull_distance = cull_distance_for(K, width, height, z_near) if cull_back_faces else None
    tri_cam, tri_rgb = camera_triangles(objects, T_world_cam, light, cull_distance=cull_distance)
    return rasterize_triangles(
        tri_cam, tri_rgb, K, width, height, supersample=supersample, z_near=z_near, device=device
    )


# ---------------------------------------------------------------------------------------
# 4. Down to pixels.


def downsample(layer: SampleLayer) -> ObjectRender:
    """Average the s x s samples of each pixel: coverage, mean covered colour, min depth."""
    num_pixels = layer.height * layer.width
    pixel = layer.pixel_index
    count = torch.bincount(pixel, minlength=num_pixels).to(torch.float32)
    rgb_sum = torch.zeros((num_pixels, 3), dtype=torch.float32, device=pixel.device).index_add_(0, pixel, layer.rgb)
    depth = torch.full((num_pixels,), float("inf"), dtype=torch.float32, device=pixel.device)
    depth.scatter_reduce_(0, pixel, layer.depth, reduce="amin")
    shape = (layer.height, layer.width)
    return ObjectRender(
        rgb=(rgb_sum / count.clamp(min=1.0)[:, None]).view(*shape, 3).cpu().numpy(),
        depth=depth.view(shape).cpu().numpy(),
        coverage=(count / layer.supersample**2).view(shape).cpu().numpy(),
    )


def render_objects(
    objects: Sequence[VirtualObject],
    K: np.ndarray,
    T_world_cam: np.ndarray,
    width: int,
    height: int,
    *,
    light: Light = Light(),
    supersample: int = 2,
    z_near: float = DEFAULT_Z_NEAR,
    device: str | torch.device = "cpu",
) -> ObjectRender:
    """Colour, depth and coverage of the virtual objects alone for a pinhole camera.

    Args:
        objects: the virtual objects.
        K: (3, 3) intrinsics; T_world_cam: (4, 4) camera-to-world pose, OpenCV axes.
        width, height: image size in pixels.
        light: Lambert light (camera frame by default).
        supersample: s x s samples per pixel for anti-aliased edges (1 = aliased).
        z_near: near clipping plane in metres.
        device: torch device.
    """
    layer = rasterize_objects(
        objects, K, T_world_cam, width, height, light=light, supersample=supersample, z_near=z_near, device=device
    )
    return downsample(layer)
