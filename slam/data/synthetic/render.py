"""Vectorised numpy ray caster for synthetic scenes, and a Kinect-like depth noise model.

Rays are ``origin + t * direction`` with *unnormalised* directions. For camera rays the
direction is ``R_world_cam @ K^-1 [u, v, 1]``, whose camera-frame z component is 1, so the hit
parameter ``t`` is exactly the z-depth along the optical axis (not the ray length): depth comes
out of the intersection with no extra conversion. Pixel centres are at integer ``(u, v)``
(OpenCV convention), matching ``x = (u - cx) / fx * z`` back-projection.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from slam.data.synthetic.scene import Box, Cylinder, Primitive, Room, Scene, Sphere, group_indices, surface_colour

_T_EPS = 1e-9
"""Hits closer than this ray parameter are ignored (self-intersection guard)."""


@dataclass(frozen=True)
class RayHits:
    """Nearest surface along each ray.

    Attributes:
        t: (N,) float64 ray parameter of the hit (z-depth for camera rays), inf where missed.
        surface: (N,) int64 surface id (:meth:`Scene.surface_textures` order), -1 where missed.
        points: (N, 3) float64 world hit points (nan where missed).
        normals: (N, 3) float64 unit normals facing the visible side (0 where missed).
    """

    t: np.ndarray
    surface: np.ndarray
    points: np.ndarray
    normals: np.ndarray


# ----------------------------------------------------------------------------------------------
# Ray-primitive intersections. Internally rays are component-major: origins ``o`` (3, 1) or
# (3, N) and directions ``d`` (3, N), because numpy reductions across a length-3 last axis are
# ~100x slower than elementwise maths on contiguous rows. Each returns (N,) t, inf = miss.


def room_exit(room: Room, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where rays starting inside ``room`` leave it.

    Returns:
        t: (N,) exit parameter (inf for zero directions, negative if the origin is outside).
        face: (N,) int64 face index ``2 * axis + (direction > 0)`` (see ``ROOM_FACES``).
    """
    t = np.full(d.shape[1], np.inf)
    face = np.full(d.shape[1], -1, dtype=np.int64)
    for axis in range(3):
        positive = d[axis] > 0
        bound = np.where(positive, room.hi[axis], room.lo[axis])
        with np.errstate(divide="ignore", invalid="ignore"):
            t_axis = (bound - o[axis]) / d[axis]
        closer = (d[axis] != 0) & (t_axis < t)
        t = np.where(closer, t_axis, t)
        face = np.where(closer, 2 * axis + positive, face)
    return t, face


def _slab(lo: float, hi: float, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit parameters of rays through the slab lo <= x <= hi (1D components)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
    return np.minimum(t1, t2), np.maximum(t1, t2)


def box_hit(box: Box, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Slab test in the box frame; rays starting inside the box miss it."""
    R = box.rotation
    o_local = R.T @ (o - np.asarray(box.centre)[:, None])
    d_local = R.T @ d
    t_near = np.full(d.shape[1], -np.inf)
    t_far = np.full(d.shape[1], np.inf)
    for axis, h in enumerate(box.half_size):
        near, far = _slab(-h, h, o_local[axis], d_local[axis])
        # fmax/fmin skip the nan of a ray lying exactly in a face plane.
        t_near = np.fmax(t_near, near)
        t_far = np.fmin(t_far, far)
    hit = (t_near <= t_far) & (t_near > _T_EPS)
    return np.where(hit, t_near, np.inf)


def sphere_hit(sphere: Sphere, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Near root of ``|o + t d - c|^2 = r^2``; rays starting inside miss."""
    oc = o - np.asarray(sphere.centre)[:, None]
    a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    b = oc[0] * d[0] + oc[1] * d[1] + oc[2] * d[2]
    c = oc[0] * oc[0] + oc[1] * oc[1] + oc[2] * oc[2] - sphere.radius**2
    disc = b * b - a * c
    with np.errstate(invalid="ignore"):
        t = (-b - np.sqrt(disc)) / a
    return np.where((disc >= 0) & (t > _T_EPS), t, np.inf)


def cylinder_hit(cyl: Cylinder, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Nearest of the side (within the height) and the two caps (within the radius)."""
    ox, oy, oz = o - np.asarray(cyl.base)[:, None]
    dx, dy, dz = d
    a = dx * dx + dy * dy
    b = ox * dx + oy * dy
    c = ox * ox + oy * oy - cyl.radius**2
    disc = b * b - a * c
    with np.errstate(divide="ignore", invalid="ignore"):
        t_side = (-b - np.sqrt(disc)) / a
        z_side = oz + t_side * dz
        side_ok = (disc >= 0) & (a > 0) & (t_side > _T_EPS) & (z_side >= 0) & (z_side <= cyl.height)
        best = np.where(side_ok, t_side, np.inf)
        for z_cap in (0.0, cyl.height):
            t_cap = (z_cap - oz) / dz
            x = ox + t_cap * dx
            y = oy + t_cap * dy
            cap_ok = (t_cap > _T_EPS) & (x * x + y * y <= cyl.radius**2)
            best = np.where(cap_ok & (t_cap < best), t_cap, best)
    return best


def primitive_hit(prim: Primitive, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(3, 1) or (3, N) origins, (3, N) directions -> (N,) nearest t on ``prim``, inf = miss."""
    if isinstance(prim, Box):
        return box_hit(prim, o, d)
    if isinstance(prim, Sphere):
        return sphere_hit(prim, o, d)
    return cylinder_hit(prim, o, d)


def bounding_sphere(prim: Primitive) -> tuple[np.ndarray, float]:
    """(3,) centre and radius of a sphere enclosing ``prim``."""
    if isinstance(prim, Sphere):
        return np.asarray(prim.centre, dtype=np.float64), prim.radius
    if isinstance(prim, Box):
        return np.asarray(prim.centre, dtype=np.float64), float(np.linalg.norm(prim.half_size))
    centre = np.asarray(prim.base, dtype=np.float64) + [0.0, 0.0, prim.height / 2]
    return centre, float(np.hypot(prim.radius, prim.height / 2))


def primitive_normals(prim: Primitive, points: np.ndarray) -> np.ndarray:
    """(3, N) points on ``prim``'s surface -> (3, N) outward unit normals."""
    if isinstance(prim, Sphere):
        return (points - np.asarray(prim.centre)[:, None]) / prim.radius
    if isinstance(prim, Box):
        R = prim.rotation
        local = R.T @ (points - np.asarray(prim.centre)[:, None])
        # The face hit is the axis where the point is (relatively) furthest out.
        axis = (np.abs(local) / np.asarray(prim.half_size)[:, None]).argmax(axis=0)
        columns = np.arange(local.shape[1])
        n_local = np.zeros_like(local)
        n_local[axis, columns] = np.sign(local[axis, columns])
        return R @ n_local
    local = points - np.asarray(prim.base)[:, None]
    radial = np.hypot(local[0], local[1])
    # Which feature is the point on: side, bottom cap or top cap (nearest wins).
    feature = np.stack([np.abs(radial - prim.radius), np.abs(local[2]), np.abs(local[2] - prim.height)]).argmin(0)
    n = np.zeros_like(local)
    side = feature == 0
    n[:2, side] = local[:2, side] / np.maximum(radial[side], 1e-12)
    n[2, feature == 1] = -1.0
    n[2, feature == 2] = 1.0
    return n


def _candidate_rays(primitives: tuple[Primitive, ...], origin: np.ndarray, d: np.ndarray) -> list[np.ndarray | None]:
    """Per primitive, the indices of rays from one (3,) ``origin`` along (3, N) ``d`` that point
    into the cone around its bounding sphere (None: the origin is inside that sphere, test all).

    The cone test compares ``cos(angle(d, c - o)) >= sqrt(1 - (r / |c - o|)^2)``.
    """
    spheres = [bounding_sphere(p) for p in primitives]
    if not spheres:
        return []
    to_centre = np.stack([c for c, _ in spheres]) - origin
    dist = np.linalg.norm(to_centre, axis=1)
    radius = np.array([r for _, r in spheres])
    inside = dist <= radius * 1.001
    cos_cone = np.sqrt(np.clip(1.0 - (radius / dist) ** 2, 0.0, 1.0))
    unit_d = d / np.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
    axis = to_centre / dist[:, None]
    # Row by row: a (3,) x (3, N) product is several times faster than one tiny-K matmul.
    return [None if inside[k] else np.flatnonzero(axis[k] @ unit_d >= cos_cone[k] - 1e-9)
            for k in range(len(primitives))]


def cast_rays_cm(scene: Scene, o: np.ndarray, d: np.ndarray) -> RayHits:
    """:func:`cast_rays` on component-major arrays: ``o`` (3,) or (3, N), ``d`` (3, N).

    The returned ``points`` and ``normals`` are (N, 3) like :func:`cast_rays`'s.
    """
    single_origin = o.ndim == 1
    o = o[:, None] if single_origin else o
    n_rays = d.shape[1]
    t, surface = room_exit(scene.room, o, d)
    surface = np.where(t > _T_EPS, surface, -1)
    t = np.where(surface >= 0, t, np.inf)
    primitives = scene.primitives
    candidates = _candidate_rays(primitives, o[:, 0], d) if single_origin else [None] * len(primitives)
    for i, (prim, idx) in enumerate(zip(primitives, candidates)):
        if idx is None:
            t_prim = primitive_hit(prim, o, d)
            closer = t_prim < t
            t = np.where(closer, t_prim, t)
            surface = np.where(closer, 6 + i, surface)
        elif idx.size:
            t_prim = primitive_hit(prim, o, d[:, idx])
            closer = t_prim < t[idx]
            t[idx[closer]] = t_prim[closer]
            surface[idx[closer]] = 6 + i
    points = o + t * d
    normals = np.zeros((3, n_rays))
    for sid, sel in group_indices(surface):
        if sid < 0:
            points[:, sel] = np.nan
        elif sid < 6:
            axis, side = divmod(int(sid), 2)
            normals[axis, sel] = -1.0 if side else 1.0  # into the room
        else:
            normals[:, sel] = primitive_normals(primitives[sid - 6], points[:, sel])
    return RayHits(t, surface, points.T, normals.T)


def cast_rays(scene: Scene, origins: np.ndarray, directions: np.ndarray) -> RayHits:
    """Nearest hit of each ray with the scene (room faces and every primitive).

    Args:
        origins: (3,) or (N, 3) ray origins inside the room.
        directions: (N, 3) ray directions, any non-zero length (t is in units of it).
    """
    origins = np.asarray(origins, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    if directions.ndim != 2 or directions.shape[1] != 3:
        raise ValueError(f"directions must be (N, 3), got {directions.shape}")
    if origins.shape not in ((3,), directions.shape):
        raise ValueError(f"origins must be (3,) or {directions.shape}, got {origins.shape}")
    o = origins if origins.ndim == 1 else np.ascontiguousarray(origins.T)
    return cast_rays_cm(scene, o, np.ascontiguousarray(directions.T))


# ----------------------------------------------------------------------------------------------
# Camera rendering.


@dataclass(frozen=True)
class RasterView:
    """A ray-cast view.

    Attributes:
        rgb: (H, W, 3) float32 in [0, 1].
        depth: (H, W) float32 z-depth in metres, 0 where nothing was hit.
        incidence_cos: (H, W) float32 |cos| of the angle between the viewing ray and the normal
            (1 = head-on, 0 = grazing), used by the depth noise model.
        surface: (H, W) int32 surface id, -1 where nothing was hit.
    """

    rgb: np.ndarray
    depth: np.ndarray
    incidence_cos: np.ndarray
    surface: np.ndarray


def default_intrinsics(width: int, height: int, hfov_deg: float = 60.0) -> np.ndarray:
    """(3, 3) float64 pinhole K with square pixels, ``hfov_deg`` horizontal field of view and
    the principal point at the image centre ((W - 1) / 2, (H - 1) / 2) in pixel-centre coordinates."""
    if width < 1 or height < 1:
        raise ValueError(f"image size {width}x{height} must be positive")
    f = (width / 2) / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


@lru_cache(maxsize=8)
def _pixel_rays_cached(K_bytes: bytes, width: int, height: int) -> np.ndarray:
    K = np.frombuffer(K_bytes, dtype=np.float64).reshape(3, 3)
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    rays = rays / rays[2]  # exactly z = 1
    rays.setflags(write=False)
    return rays


def pixel_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(3, H*W) camera-frame ray directions with z = 1 through every pixel centre, row-major
    pixel order (component-major layout; transpose for (H*W, 3))."""
    return _pixel_rays_cached(np.ascontiguousarray(K, dtype=np.float64).tobytes(), int(width), int(height))


def rasterise_view(scene: Scene, K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int) -> RasterView:
    """Ray-cast colour, z-depth, incidence and surface ids of ``scene`` from one camera.

    Args:
        K: (3, 3) pinhole intrinsics.
        T_world_cam: (4, 4) camera-to-world pose, OpenCV camera axes.
    """
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(T_world_cam, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    if T.shape != (4, 4):
        raise ValueError(f"T_world_cam must be (4, 4), got {T.shape}")
    if width < 1 or height < 1:
        raise ValueError(f"image size {width}x{height} must be positive")
    origin = T[:3, 3]
    if np.any(origin <= scene.room.lo) or np.any(origin >= scene.room.hi):
        raise ValueError(f"camera position {origin.tolist()} is outside the room {scene.room.lo}..{scene.room.hi}")
    d = T[:3, :3] @ pixel_rays(K, width, height)
    hits = cast_rays_cm(scene, origin, d)
    # Every ray from inside the closed room hits something; no invalid pixels to mask.
    rgb = surface_colour(scene, hits.surface, hits.points.T, hits.normals.T)
    depth = np.where(hits.surface >= 0, hits.t, 0.0)
    n = hits.normals.T
    incidence = np.abs(n[0] * d[0] + n[1] * d[1] + n[2] * d[2]) / np.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
    return RasterView(
        rgb=np.ascontiguousarray(rgb.T).reshape(height, width, 3),
        depth=depth.reshape(height, width).astype(np.float32),
        incidence_cos=incidence.reshape(height, width).astype(np.float32),
        surface=hits.surface.reshape(height, width).astype(np.int32),
    )


def render_rgbd(scene: Scene, K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast ``(rgb (H, W, 3) float32 in [0, 1], depth (H, W) float32 z-depth metres)``.

    Exact: depth is the analytic intersection (0 only where a ray leaves the scene, which
    cannot happen from inside the closed room).
    """
    view = rasterise_view(scene, K, T_world_cam, width, height)
    return view.rgb, view.depth


# ----------------------------------------------------------------------------------------------
# Depth noise.


@dataclass(frozen=True)
class DepthNoiseModel:
    """Kinect-like depth errors (Nguyen et al. 2012 axial noise; holes as seen on TUM/ScanNet)."""

    sigma_base: float = 0.0012
    """Axial noise sigma at ``sigma_z0`` metres."""
    sigma_quadratic: float = 0.0019
    """sigma(z) = sigma_base + sigma_quadratic * (z - sigma_z0)^2."""
    sigma_z0: float = 0.4
    quantum: float = 1.0 / 5000
    """Round depth to multiples of this (a 16-bit PNG at scale 5000); 0 disables."""
    dropout_rate: float = 0.01
    """Probability that any pixel is missing at random."""
    grazing_cos: float = 0.2
    """Pixels seen at |cos(incidence)| below this (beyond ~78 deg) have no depth."""
    edge_jump: float = 0.05
    """A neighbour farther than this fraction of the depth marks a depth edge."""
    edge_drop_probability: float = 0.7
    """Probability that a pixel on a depth edge is missing."""


def depth_edges(depth: np.ndarray, relative_jump: float) -> np.ndarray:
    """(H, W) depth -> (H, W) bool, True where a 4-neighbour differs by > relative_jump * depth."""
    edges = np.zeros(depth.shape, dtype=bool)
    for axis in (0, 1):
        jump = np.abs(np.diff(depth, axis=axis)) > relative_jump * np.minimum(
            np.delete(depth, -1, axis=axis), np.delete(depth, 0, axis=axis)
        )
        pad_before = [(0, 0), (0, 0)]
        pad_after = [(0, 0), (0, 0)]
        pad_before[axis] = (1, 0)
        pad_after[axis] = (0, 1)
        edges |= np.pad(jump, pad_before) | np.pad(jump, pad_after)
    return edges


def add_depth_noise(depth: np.ndarray, incidence_cos: np.ndarray, rng: np.random.Generator,
                    model: DepthNoiseModel = DepthNoiseModel()) -> np.ndarray:
    """Noisy, holed copy of an exact depth map.

    Args:
        depth: (H, W) float32 exact z-depth, 0 = invalid.
        incidence_cos: (H, W) |cos| of the viewing angle on the surface.
        rng: the only source of randomness (seed it per frame for reproducible sequences).
    Returns:
        (H, W) float32 depth, 0 where missing.
    """
    z = depth.astype(np.float64)
    valid = z > 0
    sigma = model.sigma_base + model.sigma_quadratic * (z - model.sigma_z0) ** 2
    noisy = z + sigma * rng.standard_normal(z.shape)
    if model.quantum > 0:
        noisy = np.round(noisy / model.quantum) * model.quantum
    drop = rng.random(z.shape) < model.dropout_rate
    drop |= incidence_cos < model.grazing_cos
    drop |= depth_edges(z, model.edge_jump) & (rng.random(z.shape) < model.edge_drop_probability)
    keep = valid & ~drop & (noisy > 0)
    return np.where(keep, noisy, 0.0).astype(np.float32)
