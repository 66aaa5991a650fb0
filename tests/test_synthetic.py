"""Synthetic RGB-D source: scenes, ray caster, GT mesh, trajectories, noise and spec parsing."""

from __future__ import annotations

import numpy as np
import pytest

from slam.data.frame import DataError, Frame, RGBDSequence
from slam.data.synthetic import (
    HALL_LAYOUTS,
    HALL_SIZES,
    LAPS_NOMINAL_FRAMES,
    NOMINAL_FRAMES,
    TRAJECTORY_KINDS,
    TRAJECTORY_SCENES,
    DepthNoiseModel,
    SyntheticSpec,
    cast_rays,
    default_intrinsics,
    gt_mesh,
    look_at,
    make_agent_trajectories,
    make_scene,
    make_trajectory,
    nominal_frames,
    open_synthetic,
    parse_synthetic_spec,
    rasterise_view,
    render_rgbd,
)
from slam.data.synthetic.scene import (
    Box,
    Cylinder,
    Sphere,
    Texture,
    surface_colour,
)

SMALL = {"width": 160}  # 160x120 keeps renders ~25 ms
ROOM_KINDS = tuple(k for k in TRAJECTORY_KINDS if TRAJECTORY_SCENES[k] == "room")
MOTION_BOUNDS = {"laps": (0.025, 1.5)}
"""Largest step (m, deg) per frame at NOMINAL_FRAMES; the room kinds' is (0.016, 1.1)."""


# ---------------------------------------------------------------------------------------------
# helpers


def step_sizes(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4, 4) poses -> per-step translation (m) and rotation (deg), each (N - 1,)."""
    translation = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    R_rel = np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, :3])
    cos = np.clip((np.trace(R_rel, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return translation, np.degrees(np.arccos(cos))


def backproject(depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """(H, W) depth -> (M, 3) world points of the valid pixels (pixel centres at integers)."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], 1)
    return cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]


def project(points: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(M, 3) world points -> pixel u, v and camera z, each (M,)."""
    cam = (points - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    z = cam[:, 2]
    return K[0, 0] * cam[:, 0] / z + K[0, 2], K[1, 1] * cam[:, 1] / z + K[1, 2], z


def bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample (H, W[, C]) ``image`` at float pixels; also return whether the 4 taps are usable
    (inside, valid depth when 2D, and not straddling a depth edge)."""
    h, w = image.shape[:2]
    inside = (u >= 0) & (v >= 0) & (u < w - 1) & (v < h - 1)
    u0 = np.clip(np.floor(u).astype(int), 0, w - 2)
    v0 = np.clip(np.floor(v).astype(int), 0, h - 2)
    fu, fv = u - u0, v - v0
    taps = [image[v0, u0], image[v0, u0 + 1], image[v0 + 1, u0], image[v0 + 1, u0 + 1]]
    weights = [(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv]
    if image.ndim == 3:
        weights = [wt[:, None] for wt in weights]
    value = sum(wt * tap for wt, tap in zip(weights, taps))
    ok = inside
    if image.ndim == 2:
        stack = np.stack(taps)
        ok = ok & (stack.min(0) > 0) & (stack.max(0) - stack.min(0) < 0.02 * stack.max(0))
    return value, ok


def ray_mesh_depth(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest Moller-Trumbore hit of each ray from ``origin`` with a triangle mesh (a check
    independent of the caster). Each ray only tests the triangles whose bounding-sphere cone
    (seen from the origin) contains it.

    Returns (R,) ray parameter (inf = miss) and (R,) index of the triangle hit (-1 = miss).
    """
    tri = vertices[faces]  # (F, 3 corners, 3)
    centre = tri.mean(1)
    radius = np.linalg.norm(tri - centre[:, None], axis=2).max(1)
    to_centre = centre - origin
    dist = np.linalg.norm(to_centre, axis=1)
    cos_cone = np.where(dist > radius, np.sqrt(np.clip(1 - (radius / dist) ** 2, 0, 1)), -1.0)
    axis = to_centre / dist[:, None]
    t_best = np.full(len(directions), np.inf)
    face_best = np.full(len(directions), -1)
    for r, d in enumerate(directions):
        cand = np.flatnonzero(axis @ (d / np.linalg.norm(d)) >= cos_cone - 1e-9)
        v0, v1, v2 = tri[cand, 0], tri[cand, 1], tri[cand, 2]
        e1, e2 = v1 - v0, v2 - v0
        p = np.cross(d, e2)
        det = (e1 * p).sum(1)
        s = origin - v0
        q = np.cross(s, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            a = (s * p).sum(1) / det
            b = (q @ d) / det
            t = (e2 * q).sum(1) / det
        hit = (np.abs(det) > 1e-12) & (a >= 0) & (b >= 0) & (a + b <= 1) & (t > 1e-9)
        if hit.any():
            k = np.flatnonzero(hit)[t[hit].argmin()]
            t_best[r], face_best[r] = t[k], cand[k]
    return t_best, face_best


# ---------------------------------------------------------------------------------------------
# determinism and basic contract


def test_scene_is_deterministic_from_seed():
    assert make_scene("room", 3) == make_scene("room", 3)
    assert make_scene("room", 3) != make_scene("room", 4)
    assert make_scene("empty", 0).objects == ()
    assert len(make_scene("room", 0).primitives) >= 15


def test_frames_are_deterministic_and_depend_on_seed():
    a = open_synthetic("walk?seed=5", **SMALL)[7]
    b = open_synthetic("synthetic:walk?seed=5", **SMALL)[7]
    c = open_synthetic("walk?seed=6", **SMALL)[7]
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
    assert not np.array_equal(a.rgb, c.rgb)
    assert not np.array_equal(a.T_world_cam, c.T_world_cam)
    for kind in TRAJECTORY_KINDS:
        np.testing.assert_array_equal(make_trajectory(kind, 30, 2), make_trajectory(kind, 30, 2))
        assert not np.allclose(make_trajectory(kind, 30, 2), make_trajectory(kind, 30, 3))


def test_sequence_satisfies_protocol_and_frame_contract():
    seq = open_synthetic("orbit?frames=12", **SMALL)
    assert isinstance(seq, RGBDSequence)
    assert seq.has_gt and len(seq) == 12 and seq.name.startswith("synthetic:orbit")
    frame = seq[-1]
    assert isinstance(frame, Frame) and frame.index == 11
    assert frame.rgb.shape == (120, 160, 3) and frame.rgb.dtype == np.float32
    assert frame.depth.shape == (120, 160) and frame.depth.dtype == np.float32
    assert 0.0 <= frame.rgb.min() and frame.rgb.max() <= 1.0
    assert frame.K.dtype == np.float64 and frame.T_world_cam.dtype == np.float64
    np.testing.assert_allclose(frame.T_world_cam, seq.trajectory[11])
    assert frame.timestamp == pytest.approx(11 / 30)
    assert [f.index for f in seq][:3] == [0, 1, 2]
    frame.depth[:] = 0  # callers may scribble on frames without corrupting the cache
    assert (seq[-1].depth > 0).all()
    with pytest.raises(IndexError):
        seq[12]


def test_stride_max_frames_and_width_override():
    full = open_synthetic("orbit?frames=40")
    seq = open_synthetic("orbit?frames=40", width=160, stride=3, max_frames=5)
    assert len(seq) == 5 and (seq.width, seq.height) == (160, 120)
    np.testing.assert_allclose(seq.trajectory, full.trajectory[::3][:5])
    assert seq[4].timestamp == pytest.approx(12 / 30) and seq[4].index == 4
    np.testing.assert_allclose(seq.K[:2, :2], full.K[:2, :2] / 2)
    assert open_synthetic("orbit?width=200").height == 150
    assert (open_synthetic("orbit?width=64&height=64").width, open_synthetic("orbit?width=64&height=64").height) == (64, 64)
    # 60 degrees horizontal field of view.
    K = default_intrinsics(320, 240)
    assert np.degrees(2 * np.arctan(160 / K[0, 0])) == pytest.approx(60.0)


@pytest.mark.parametrize(
    "spec, words",
    [
        ("spiral", ["spiral", "orbit", "walk", "loop", "agents"]),
        ("synthetic:orbit?fps=30", ["fps", "frames", "seed", "noise"]),
        ("orbit?frames=ten", ["frames", "integer"]),
        ("orbit?frames=0", ["frames"]),
        ("orbit?noise=2", ["noise"]),
        ("orbit?agent=1", ["agent", "agents"]),
        ("agents?agent=2&agents=2", ["agent=2"]),
        ("orbit?seed=1&seed=2", ["seed", "twice"]),
        ("orbit?seed", ["seed"]),
        ("orbit?width=8", ["width"]),
        ("laps?size=huge", ["size", "'huge'", "compact", "large"]),
        ("laps?size=", ["size", "compact", "large"]),
        ("orbit?size=large", ["size", "laps"]),
        ("laps?size=large&size=compact", ["size", "twice"]),
    ],
)
def test_bad_specs_raise_data_error_naming_the_problem(spec, words):
    with pytest.raises(DataError) as info:
        open_synthetic(spec)
    for word in words:
        assert word in str(info.value)


def test_bad_arguments_raise():
    with pytest.raises(DataError, match="stride"):
        open_synthetic("orbit", stride=0)
    with pytest.raises(DataError, match="max_frames"):
        open_synthetic("orbit", max_frames=0)
    with pytest.raises(DataError, match="width"):
        open_synthetic("orbit", width=4)
    with pytest.raises(DataError, match="room, empty"):
        make_scene("castle")
    with pytest.raises(DataError, match="compact, large"):
        make_scene("hall", 0, size="medium")
    with pytest.raises(DataError, match="only to kind 'hall'"):
        make_scene("room", 0, size="large")
    with pytest.raises(DataError, match="compact, large"):
        make_trajectory("laps", 10, size="medium")
    with pytest.raises(DataError, match="only to kind 'laps'"):
        make_trajectory("orbit", 10, size="compact")
    with pytest.raises(DataError, match="only to kind 'laps'"):
        nominal_frames("loop", "large")
    with pytest.raises(DataError, match="n_agents"):
        make_agent_trajectories(0, 10)
    with pytest.raises(ValueError, match="scale"):
        Texture("checker", (1, 0, 0), (0, 0, 1), scale=0.01)
    with pytest.raises(ValueError, match="outside the room"):
        render_rgbd(make_scene("empty"), default_intrinsics(32, 24), np.eye(4), 32, 24)


# ---------------------------------------------------------------------------------------------
# geometry of the ray caster and the mesh


def test_depth_is_z_depth_not_ray_length():
    """Facing a wall head-on, every pixel's z-depth is the wall distance, corners included."""
    scene = make_scene("empty", 0)  # room x in [-3, 3]
    T = look_at(np.array([[0.0, 0.0, 1.5]]), np.array([[1.0, 0.0, 1.5]]))[0]
    rgb, depth = render_rgbd(scene, default_intrinsics(160, 120), T, 160, 120)
    np.testing.assert_allclose(depth, 3.0, atol=1e-5)
    assert rgb.std() > 0.03  # the wall is textured


def test_ray_caster_agrees_with_gt_mesh():
    scene = make_scene("room", 1)
    mesh = gt_mesh(scene)
    rng = np.random.default_rng(0)
    T = make_trajectory("orbit", 10, seed=1)[4]
    K = default_intrinsics(320, 240)
    # 300 random pixels plus 100 aimed at the table objects (spheres, cylinders, boxes).
    uv = rng.uniform([0, 0], [319, 239], size=(300, 2))
    aim = rng.normal(0.0, 0.12, size=(100, 3)) + [0.0, 0.0, 0.9]
    cam = (aim - T[:3, 3]) @ T[:3, :3]
    uv = np.concatenate([uv, np.stack([K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2], K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]], 1)])
    d_cam = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))], 1)
    directions = d_cam @ T[:3, :3].T
    hits = cast_rays(scene, T[:3, 3], directions)
    t_mesh, face = ray_mesh_depth(np.asarray(mesh.vertices), np.asarray(mesh.faces), T[:3, 3], directions)
    assert np.isfinite(hits.t).all() and (face >= 0).all()
    error = np.abs(hits.t - t_mesh)
    # Rays grazing a curved silhouette may pass the polygon but hit the true surface.
    assert np.mean(error < 1e-3) >= 0.98
    assert np.median(error) < 1e-4
    assert len(np.unique(hits.surface)) >= 6  # several walls and objects were probed
    # Mesh triangles face the camera (counter-clockwise from the visible side).
    facing = (mesh.face_normals[face] * directions).sum(1)
    assert np.mean(facing < 0) >= 0.98
    # Caster normals face the camera too, and are unit length.
    assert np.all((hits.normals * directions).sum(1) < 0)
    np.testing.assert_allclose(np.linalg.norm(hits.normals, axis=1), 1.0, atol=1e-9)


def test_mesh_vertex_colours_match_render_colours():
    scene = make_scene("room", 2)
    mesh = gt_mesh(scene)
    T = make_trajectory("orbit", 5, seed=2)[0]
    idx = np.random.default_rng(1).choice(len(mesh.vertices), 3000, replace=False)
    vertices = np.asarray(mesh.vertices)[idx]
    hits = cast_rays(scene, T[:3, 3], vertices - T[:3, 3])
    # Visible: the first hit is the vertex itself, on the vertex's own face (a vertex on a box
    # edge is shared in space by two faces, each with its own copy, normal and colour).
    visible = (np.abs(hits.t - 1.0) < 1e-6) & ((hits.normals * mesh.vertex_normals[idx]).sum(1) > 0.999)
    assert visible.sum() > 300
    colour = surface_colour(scene, hits.surface[visible], hits.points[visible].T, hits.normals[visible].T).T
    mesh_colour = np.asarray(mesh.visual.vertex_colors)[idx[visible], :3] / 255.0
    assert np.all(np.abs(colour - mesh_colour) <= 0.5 / 255 + 1e-6)


# ---------------------------------------------------------------------------------------------
# what every frame sees


@pytest.mark.parametrize("kind", ROOM_KINDS)
def test_every_frame_has_valid_depth_and_texture(kind):
    seq = open_synthetic(f"{kind}?frames=9&seed=1", **SMALL)
    for frame in seq:
        valid = frame.depth > 0
        assert valid.mean() > 0.8
        assert 0.4 < np.percentile(frame.depth[valid], 1) and 0.5 < np.median(frame.depth[valid]) < 5.0
        assert frame.rgb.std() > 0.08
        gray = frame.rgb.mean(2)
        gradient = np.abs(np.diff(gray, axis=1)).mean() + np.abs(np.diff(gray, axis=0)).mean()
        assert gradient > 0.01  # enough texture for photometric tracking


def test_reprojection_between_frames_agrees_with_gt_poses():
    seq = open_synthetic("orbit?frames=60&seed=2")
    a, b = seq[20], seq[25]
    points = backproject(a.depth, a.K, a.T_world_cam)
    colours = a.rgb[a.depth > 0]
    u, v, z = project(points, b.K, b.T_world_cam)
    depth_b, ok = bilinear(b.depth, u, v)
    visible = ok & (np.abs(depth_b - z) < 0.05)
    assert visible.mean() > 0.7
    assert np.median(np.abs(depth_b - z)[ok]) < 1e-3
    colour_b, _ = bilinear(b.rgb, u, v)
    assert np.median(np.abs(colour_b - colours)[visible]) < 0.01  # view-independent colour


# ---------------------------------------------------------------------------------------------
# trajectories


@pytest.mark.parametrize("kind", TRAJECTORY_KINDS)
def test_motion_per_frame_is_bounded_and_set_by_frame_count(kind):
    n = NOMINAL_FRAMES[kind]
    T = make_trajectory(kind, n, seed=4)
    translation, rotation = step_sizes(T)
    max_step, max_turn = MOTION_BOUNDS.get(kind, (0.016, 1.1))
    assert translation.max() < max_step and rotation.max() < max_turn
    assert translation.min() > 0.002  # it does move
    # Same path, more frames: same ends, half the steps.
    T2 = make_trajectory(kind, 2 * n - 1, seed=4)
    np.testing.assert_allclose(T2[[0, -1]], T[[0, -1]], atol=1e-12)
    np.testing.assert_allclose(T2[::2], T, atol=1e-12)
    assert step_sizes(T2)[0].max() < 0.6 * translation.max()


@pytest.mark.parametrize("kind", TRAJECTORY_KINDS)
def test_cameras_stay_in_free_space_with_opencv_axes(kind):
    for seed in (0, 1, 2):
        T = make_trajectory(kind, 60, seed)
        R = T[:, :3, :3]
        np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
        assert np.all(R[:, 2, 0] == pytest.approx(0.0, abs=1e-12))  # x axis level: no roll
        assert np.all(R[:, 2, 1] < 0)  # image y points down
        scene = make_scene(TRAJECTORY_SCENES[kind], seed)
        lo, hi = np.array(scene.room.lo), np.array(scene.room.hi)
        positions = T[:, :3, 3]
        assert np.all(positions - lo >= 0.4) and np.all(hi - positions >= 0.4)
        # No surface (walls, furniture, table) within 0.4 m in any direction.
        dirs = np.random.default_rng(0).normal(size=(300, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        for p in positions[::10]:
            assert cast_rays(scene, p, dirs).t.min() > 0.4


def test_loop_returns_to_its_start():
    T = make_trajectory("loop", NOMINAL_FRAMES["loop"], seed=0)
    start, end = T[0], T[-1]
    assert np.linalg.norm(end[:3, 3] - start[:3, 3]) < 0.3
    assert np.degrees(np.arccos(np.clip(end[:3, 2] @ start[:3, 2], -1, 1))) < 15
    # ... after going somewhere else: half way it is far away and looks elsewhere.
    middle = T[len(T) // 2]
    assert np.linalg.norm(middle[:3, 3] - start[:3, 3]) > 1.5
    assert middle[:3, 2] @ start[:3, 2] < 0


def test_agents_start_apart_and_overlap():
    agents = make_agent_trajectories(3, 40, seed=1)
    assert agents.shape == (3, 40, 4, 4)
    starts = agents[:, 0, :3, 3]
    for i in range(3):
        for j in range(i + 1, 3):
            assert np.linalg.norm(starts[i] - starts[j]) > 0.5
    for k in range(2):  # consecutive agents' paths pass within 0.3 m of each other
        gaps = np.linalg.norm(agents[k][:, None, :3, 3] - agents[k + 1][None, :, :3, 3], axis=2)
        assert gaps.min() < 0.3
    # Shared content: much of what agent 0 sees at the end, agent 1 sees at its end.
    seqs = [open_synthetic(f"agents?frames=40&seed=1&agents=3&agent={k}", **SMALL) for k in (0, 1)]
    assert seqs[0].scene == seqs[1].scene
    np.testing.assert_allclose(seqs[1].trajectory, agents[1])
    a, b = seqs[0][-1], seqs[1][-1]
    u, v, z = project(backproject(a.depth, a.K, a.T_world_cam), b.K, b.T_world_cam)
    depth_b, ok = bilinear(b.depth, u, v)
    assert np.mean(ok & (z > 0) & (np.abs(depth_b - z) < 0.02)) > 0.3


# ---------------------------------------------------------------------------------------------
# depth noise


def test_noise_and_holes_are_plausible_and_deterministic():
    clean = open_synthetic("orbit?frames=20&seed=3")[10].depth
    noisy = open_synthetic("orbit?frames=20&seed=3&noise=1")[10].depth
    again = open_synthetic("orbit?frames=20&seed=3&noise=1")[10].depth
    other = open_synthetic("orbit?frames=20&seed=4&noise=1")[10].depth
    np.testing.assert_array_equal(noisy, again)
    assert not np.array_equal(noisy[noisy > 0][:1000], other[other > 0][:1000])
    valid = noisy > 0
    assert 0.8 < valid.mean() < 0.995  # holes, but most depth survives
    model = DepthNoiseModel()
    z = clean[valid].astype(np.float64)
    sigma = model.sigma_base + model.sigma_quadratic * (z - model.sigma_z0) ** 2
    residual = (noisy[valid] - z) / sigma
    assert np.mean(noisy[valid] != clean[valid]) > 0.9
    assert 0.8 < residual.std() < 1.25 and abs(residual.mean()) < 0.1
    assert np.abs(noisy[valid] - z).max() < 6 * sigma.max() + model.quantum
    # Holes gather at depth edges.
    edge = np.zeros_like(valid)
    edge[:, 1:] |= np.abs(np.diff(clean, axis=1)) > 0.1
    edge[:, :-1] |= np.abs(np.diff(clean, axis=1)) > 0.1
    assert (~valid[edge]).mean() > 3 * (~valid[~edge]).mean()


def test_rasterise_view_reports_grazing_incidence():
    scene = make_scene("empty", 0)
    # Looking along the floor: the floor near the horizon is seen at grazing angles.
    T = look_at(np.array([[-2.0, 0.0, 0.5]]), np.array([[2.0, 0.0, 0.4]]))[0]
    view = rasterise_view(scene, default_intrinsics(80, 60), T, 80, 60)
    floor = view.surface == 4
    assert floor.any() and view.incidence_cos[floor].min() < 0.2
    wall = view.surface == 1  # x = hi, seen head-on
    assert view.incidence_cos[wall].min() > 0.8


# ---------------------------------------------------------------------------------------------
# the hall and its laps (loop-closure benchmark)


def surface_distance(scene, points: np.ndarray) -> np.ndarray:
    """(M, 3) points -> (M,) exact distance to the nearest surface (room faces or primitive);
    0 inside a primitive."""
    lo, hi = np.array(scene.room.lo), np.array(scene.room.hi)
    best = np.minimum(points - lo, hi - points).min(1)
    for prim in scene.primitives:
        if isinstance(prim, Box):
            local = (points - np.array(prim.centre)) @ prim.rotation
            d = np.linalg.norm(np.maximum(np.abs(local) - np.array(prim.half_size), 0.0), axis=1)
        elif isinstance(prim, Sphere):
            d = np.maximum(np.linalg.norm(points - np.array(prim.centre), axis=1) - prim.radius, 0.0)
        else:
            rel = points - np.array(prim.base)
            radial = np.maximum(np.hypot(rel[:, 0], rel[:, 1]) - prim.radius, 0.0)
            dz = np.maximum(np.maximum(-rel[:, 2], rel[:, 2] - prim.height), 0.0)
            d = np.hypot(radial, dz)
        best = np.minimum(best, d)
    return best


def footprint(prim) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal (2,) lo, hi of a primitive's bounding box (yaw-free in the hall)."""
    if isinstance(prim, Box):
        c, h = np.array(prim.centre[:2]), np.array(prim.half_size[:2])
    elif isinstance(prim, Sphere):
        c, h = np.array(prim.centre[:2]), np.full(2, prim.radius)
    else:
        c, h = np.array(prim.base[:2]), np.full(2, prim.radius)
    return c - h, c + h


def block_distance(xy: np.ndarray, size: str) -> np.ndarray:
    """(M, 2) -> (M,) horizontal distance to the central block of the ``size`` hall (0 inside)."""
    return np.linalg.norm(np.maximum(np.abs(xy) - np.array(HALL_LAYOUTS[size].block_half_size), 0.0), axis=1)


HALL_DIMS = {"compact": ((4.4, 3.6, 3.0), (1.6, 0.8, 3.0), 1.4, 14), "large": ((10.0, 8.0, 3.0), (5.6, 3.6, 3.0), 2.2, 20)}
"""Per size: hall extents, block extents, corridor width, least number of furniture pieces."""
LAPS_BOUNDS = {"compact": ((16.0, 20.0), (0.05, 0.2)), "large": ((45.0, 56.0), (0.08, 0.3))}
"""Per size: path length (m) and how far the second lap passes from the first (m)."""


def test_hall_sizes_and_nominal_frames():
    assert HALL_SIZES == ("compact", "large") and set(HALL_LAYOUTS) == set(HALL_SIZES)
    assert make_scene("hall", 4) == make_scene("hall", 4, size="compact") != make_scene("hall", 4, size="large")
    assert NOMINAL_FRAMES["laps"] == nominal_frames("laps") == LAPS_NOMINAL_FRAMES["compact"]
    assert 700 <= LAPS_NOMINAL_FRAMES["compact"] <= 800 and LAPS_NOMINAL_FRAMES["large"] == 2200
    assert nominal_frames("laps", "large") == 2200 and nominal_frames("loop") == 500
    np.testing.assert_array_equal(make_trajectory("laps", 50, 3), make_trajectory("laps", 50, 3, size="compact"))
    assert not np.allclose(make_trajectory("laps", 50, 3), make_trajectory("laps", 50, 3, size="large"))


@pytest.mark.parametrize("size", HALL_SIZES)
def test_hall_geometry_is_a_ring_corridor_with_furniture_near_the_walls(size):
    layout = HALL_LAYOUTS[size]
    hall_dims, block_dims, width, min_pieces = HALL_DIMS[size]
    scene = make_scene("hall", 0, size=size)
    assert scene.name == ("hall-0" if size == "large" else "hall-compact-0") and make_scene("hall", 0, size=size) == scene
    lo, hi = np.array(scene.room.lo), np.array(scene.room.hi)
    np.testing.assert_allclose(hi - lo, hall_dims)
    block = scene.primitives[scene.group("block")[0] - 6]
    assert isinstance(block, Box) and block.yaw == 0.0
    np.testing.assert_allclose(2 * np.array(block.half_size), block_dims)  # full height
    np.testing.assert_allclose(block.centre, [0.0, 0.0, 1.5])
    np.testing.assert_allclose(layout.corridor_width, [width, width])
    # Every piece of furniture lies within the band along an outer wall or a block face, on the floor.
    structure = set(scene.group("block")) | {scene.group("plain_east")[-1]}  # block, facades, mat
    pieces = [(6 + i, p) for i, p in enumerate(scene.primitives) if 6 + i not in structure]
    assert len(pieces) >= min_pieces
    for sid, prim in pieces:
        a, b = footprint(prim)
        xs, ys = np.meshgrid(np.linspace(a[0], b[0], 9), np.linspace(a[1], b[1], 9))
        xy = np.stack([xs.ravel(), ys.ravel()], 1)
        to_outer = np.minimum(hi[0] - np.abs(xy[:, 0]), hi[1] - np.abs(xy[:, 1]))
        assert np.all((to_outer <= layout.wall_band + 1e-9) | (block_distance(xy, size) <= layout.wall_band + 1e-9)), sid
        inside = (np.abs(xy) < np.array(layout.block_half_size) - 1e-9).all(1)
        assert np.all(block_distance(xy[inside], size) > 0), sid
        assert np.all(to_outer >= -1e-9)  # inside the hall, outside the block
    # The seed changes textures only, never the layout.
    other = make_scene("hall", 1, size=size)
    assert other != scene and len(other.primitives) == len(scene.primitives)
    for p, q in zip(scene.primitives, other.primitives):
        assert type(p) is type(q) and {k: v for k, v in vars(p).items() if k != "texture"} == \
            {k: v for k, v in vars(q).items() if k != "texture"}
    assert other.groups == scene.groups


PLAIN_VIEWS = {
    # (plain: eye, target), (busy: eye, target), west wall stretch with nothing in front
    "compact": (((1.45, -0.2, 1.45), (2.2, 0.25, 1.15)), ((-0.6, -1.1, 1.45), (0.6, -1.1, 1.2)), (-1.4, 0.9)),
    "large": (((3.9, -1.0, 1.45), (5.0, 0.0, 1.2)), ((-1.0, -2.9, 1.45), (1.0, -2.9, 1.2)), (-3.5, 3.5)),
}


@pytest.mark.parametrize("size", HALL_SIZES)
def test_hall_plain_stretches_are_single_colour_with_nothing_in_front(size):
    scene = make_scene("hall", 3, size=size)
    (hx, hy), (bx, by) = HALL_LAYOUTS[size].half_size, HALL_LAYOUTS[size].block_half_size
    (plain_eye, plain_target), (busy_eye, busy_target), (west_lo, west_hi) = PLAIN_VIEWS[size]
    textures = scene.surface_textures()
    for name in ("plain_east", "plain_west"):
        for sid in scene.group(name):
            assert textures[sid].pattern == "solid" and textures[sid].grain == 0.0
    east = set(scene.group("plain_east")) | set(scene.group("block"))
    for i, prim in enumerate(scene.primitives):
        a, b = footprint(prim)
        if 6 + i not in east:  # nothing stands in the east corridor
            assert b[0] <= bx + 1e-9 or a[1] >= by - 1e-9 or b[1] <= -by + 1e-9, i
        # ... nor in front of the west wall's plain stretch.
        assert a[0] >= -hx + 0.5 or a[1] >= west_hi or b[1] <= west_lo, i
    # Rendered, a view of the east corridor is nearly uniform; the south corridor is not.
    K = default_intrinsics(80, 60)
    plain = rasterise_view(scene, K, look_at(np.array([plain_eye]), np.array([plain_target]))[0], 80, 60)
    busy = rasterise_view(scene, K, look_at(np.array([busy_eye]), np.array([busy_target]))[0], 80, 60)
    assert np.isin(plain.surface, scene.group("plain_east")).mean() > 0.95
    assert plain.rgb.std(axis=(0, 1)).max() < 0.03 and busy.rgb.std() > 0.1


COPY_VIEWS = {"compact": ((-0.4, -0.9), 0.15, 0.6), "large": ((-0.6, -1.2), 0.2, 0.8)}
"""Per size: eye offset (x, y) from a copy of the repeated set, and the point looked at: this far
in front of its wall, at this height."""


def view_of_copy(size: str, k: int) -> np.ndarray:
    """A camera pose in the corridor in front of repeated set ``k``, looking at its cabinet."""
    x, y = HALL_LAYOUTS[size].repeat_spots[k]
    (dx, dy), front, height = COPY_VIEWS[size]
    return look_at(np.array([[x + dx, y + dy, 1.45]]), np.array([[x, y - front, height]]))[0]


REPEAT_PAIRS = [("large", 0, 1), ("large", 2, 3), ("large", 0, 2), ("large", 1, 3),
                ("compact", 0, 1), ("compact", 1, 2), ("compact", 0, 2)]
SAME_SURROUNDINGS = {("large", 2, 3)}
"""Pairs whose whole views match too (same wall and floor pattern behind, nothing else near; in
the compact hall other pieces are always in view)."""


@pytest.mark.parametrize("size, a, b", REPEAT_PAIRS)
def test_hall_repeated_furniture_renders_identically(size, a, b):
    scene = make_scene("hall", 2, size=size)
    assert len(HALL_LAYOUTS[size].repeat_spots) >= 3
    ids_a, ids_b = scene.group(f"repeat_{a}"), scene.group(f"repeat_{b}")
    # Same shapes and textures, only moved.
    pa, pb = [scene.primitives[i - 6] for i in ids_a], [scene.primitives[i - 6] for i in ids_b]
    assert [type(p) for p in pa] == [type(p) for p in pb] and [p.texture for p in pa] == [p.texture for p in pb]
    K = default_intrinsics(96, 72)
    va, vb = (rasterise_view(scene, K, view_of_copy(size, k), 96, 72) for k in (a, b))
    mask_a, mask_b = np.isin(va.surface, ids_a), np.isin(vb.surface, ids_b)
    assert mask_a.mean() > 0.15
    assert (mask_a & mask_b).sum() >= 0.99 * max(mask_a.sum(), mask_b.sum())
    both = mask_a & mask_b
    np.testing.assert_allclose(va.depth[both], vb.depth[both], atol=1e-5)
    assert np.percentile(np.abs(va.rgb[both] - vb.rgb[both]), 99) < 2e-3
    if (size, a, b) in SAME_SURROUNDINGS:
        assert np.mean(np.abs(va.rgb - vb.rgb).max(2) < 2e-3) > 0.97


@pytest.mark.parametrize("size", HALL_SIZES)
def test_laps_is_two_laps_around_the_block_in_free_space(size):
    n = nominal_frames("laps", size)
    (shortest, longest), (near, far) = LAPS_BOUNDS[size]
    for seed in (0, 1, 5):
        T = make_trajectory("laps", n, seed, size=size)
        p = T[:, :3, 3]
        translation, rotation = step_sizes(T)
        assert translation.sum() >= 15.0 and shortest < translation.sum() < longest
        assert translation.max() < 0.025 and rotation.max() < 1.5 and translation.min() > 0.015
        winding = np.unwrap(np.arctan2(p[:, 1], p[:, 0]))
        assert winding[-1] - winding[0] > 2 * 2 * np.pi - 0.35  # two full turns, anticlockwise
        assert np.all(np.diff(winding) > 0)
        assert 1.3 <= p[:, 2].min() and p[:, 2].max() <= 1.6
        scene = make_scene("hall", seed, size=size)
        assert surface_distance(scene, p).min() > 0.5
        # Looking mostly ahead: the optical axis is within 35 deg of the direction of motion.
        motion = np.gradient(p[:, :2], axis=0)
        forward = T[:, :2, 2]
        cos = (motion * forward).sum(1) / np.linalg.norm(motion, axis=1) / np.linalg.norm(forward, axis=1)
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 35
        # The second lap passes every place of the first a few cm away, never on the same pose.
        lap = (winding - winding[0]) / (2 * np.pi)
        first, second = p[lap < 0.7], p[(lap > 1.05) & (lap < 1.7)]
        gap = np.linalg.norm(second[:, None] - first[None, ::2], axis=2).min(1)
        assert near < gap.min() and gap.max() < far


@pytest.mark.parametrize("size", HALL_SIZES)
def test_laps_sees_valid_depth_within_5_m_everywhere(size):
    T = make_trajectory("laps", nominal_frames("laps", size), 0, size=size)[::3]
    scene = make_scene("hall", 0, size=size)
    K = default_intrinsics(16, 12)
    u, v = np.meshgrid(np.arange(16.0), np.arange(12.0))
    rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])  # z = 1
    directions = np.einsum("nij,jr->nri", T[:, :3, :3], rays).reshape(-1, 3)
    origins = np.repeat(T[:, :3, 3], rays.shape[1], axis=0)
    depth = cast_rays(scene, origins, directions).t.reshape(len(T), -1)
    assert np.isfinite(depth).all() and depth.min() > 0.3
    assert np.mean(depth < 5.0, axis=1).min() > 0.6
    assert np.median(depth, axis=1).max() < 4.5


@pytest.mark.parametrize("size, every", [("compact", 20), ("large", 55)])
def test_laps_frames_mostly_textured_with_plain_stretches(size, every):
    seq = open_synthetic(f"laps?size={size}", width=64)
    assert seq.scene == make_scene("hall", 0, size=size) and len(seq) == nominal_frames("laps", size)
    assert (seq.width, seq.height) == (64, 48)
    gradients = []
    for i in range(0, len(seq), every):
        frame = seq[i]
        assert (frame.depth > 0).mean() > 0.99
        gray = frame.rgb.mean(2)
        gradients.append(np.abs(np.diff(gray, axis=1)).mean() + np.abs(np.diff(gray, axis=0)).mean())
    gradients = np.array(gradients)
    assert np.mean(gradients > 0.03) > 0.7  # tracking has texture on most of the path
    assert gradients.min() < 0.01  # ... but not at the plain corners


@pytest.mark.parametrize("size", HALL_SIZES)
def test_laps_sees_every_copy_of_the_repeated_furniture_on_both_laps(size):
    n = nominal_frames("laps", size)
    T = make_trajectory("laps", n, 0, size=size)
    scene = make_scene("hall", 0, size=size)
    frames = np.arange(0, n, 6 if size == "compact" else 12)
    K = default_intrinsics(24, 18)
    u, v = np.meshgrid(np.arange(24.0), np.arange(18.0))
    rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    directions = np.einsum("nij,jr->nri", T[frames, :3, :3], rays).reshape(-1, 3)
    surface = cast_rays(scene, np.repeat(T[frames, :3, 3], rays.shape[1], axis=0), directions).surface
    surface = surface.reshape(len(frames), -1)
    shares = np.stack([np.isin(surface, scene.group(f"repeat_{k}")).mean(1)
                       for k in range(len(HALL_LAYOUTS[size].repeat_spots))], 1)
    for lap in (frames < n // 2, frames >= n // 2):
        assert np.all((shares[lap] >= 0.03).sum(0) >= 3)  # each copy in several frames of each lap


@pytest.mark.parametrize("size", HALL_SIZES)
def test_laps_spec_uses_the_hall_and_its_name_round_trips(size):
    option = "" if size == "compact" else f"&size={size}"
    seq = open_synthetic(f"synthetic:laps?frames=300&seed=2&width=32&height=24&noise=1{option}", max_frames=3)
    assert seq.scene == make_scene("hall", 2, size=size)
    assert seq.name == f"synthetic:laps?frames=300&seed=2&width=32&height=24&noise=1&size={size}"
    assert parse_synthetic_spec(seq.name) == parse_synthetic_spec(seq.name.replace(f"&size={size}", option))
    np.testing.assert_allclose(seq.trajectory, make_trajectory("laps", 300, 2, size=size)[:3])
    parsed = parse_synthetic_spec(f"laps?size={size}")
    assert parsed.frames == LAPS_NOMINAL_FRAMES[size] and parsed.size == size
    assert parse_synthetic_spec("orbit").size is None
    assert SyntheticSpec("laps", frames=nominal_frames("laps")) == parse_synthetic_spec("laps")  # size given or not
    frame = seq[2]
    assert frame.depth.shape == (24, 32) and (frame.depth > 0).mean() > 0.3  # noisy at this size
    with pytest.raises(ValueError, match="outside the room"):  # the hall path does not fit the room
        rasterise_view(make_scene("room", 0), default_intrinsics(16, 12), make_trajectory("laps", 300, 2, size="large")[0], 16, 12)


@pytest.mark.parametrize("size", HALL_SIZES)
def test_hall_gt_mesh_has_no_hidden_block_surfaces_and_agrees_with_the_caster(size):
    scene = make_scene("hall", 0, size=size)
    bx, by = HALL_LAYOUTS[size].block_half_size
    spacing, margin = (0.25, 0.05) if size == "large" else (0.1, 0.08)  # margin: floor cells across the edge
    mesh = gt_mesh(scene, spacing=spacing)
    centroids = np.asarray(mesh.triangles_center)
    inside = np.all(np.abs(centroids[:, :2]) < np.array([bx, by]) - margin, axis=1)
    assert not inside.any()  # no floor or ceiling under the block, no block top
    behind_facade = (np.abs(np.abs(centroids[:, 0]) - bx) < 1e-6) & (np.abs(centroids[:, 1]) < by - 0.3)
    assert not behind_facade.any()  # the block's own east and west faces are covered
    assert len(np.unique(mesh.faces)) > 0.999 * len(mesh.vertices)  # culled vertices went too
    T = make_trajectory("laps", 40, 0, size=size)[7]
    K = default_intrinsics(64, 48)
    uv = np.random.default_rng(3).uniform([0, 0], [63, 47], size=(120, 2))
    directions = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))], 1) @ T[:3, :3].T
    hits = cast_rays(scene, T[:3, 3], directions)
    t_mesh, face = ray_mesh_depth(np.asarray(mesh.vertices), np.asarray(mesh.faces), T[:3, 3], directions)
    assert (face >= 0).all() and np.mean(np.abs(hits.t - t_mesh) < 1e-3) >= 0.98


# ---------------------------------------------------------------------------------------------
# forced tracking loss: blank and drop


def test_blank_frames_are_black_with_no_depth_but_keep_time_and_pose():
    spec = "orbit?frames=20&seed=1&width=32&height=24&noise=1"
    plain, seq = open_synthetic(spec), open_synthetic(spec + "&blank=5-7")
    assert seq.name == parse_synthetic_spec(spec).name + "&blank=5-7" and len(seq) == 20
    for i in range(20):
        frame, reference = seq[i], plain[i]
        assert frame.timestamp == reference.timestamp and frame.index == i
        np.testing.assert_array_equal(frame.T_world_cam, reference.T_world_cam)
        if 5 <= i <= 7:
            assert not frame.rgb.any() and not frame.depth.any() and seq.is_blank(i)
            assert frame.rgb.shape == (24, 32, 3) and frame.rgb.dtype == np.float32 and frame.depth.dtype == np.float32
        else:
            np.testing.assert_array_equal(frame.rgb, reference.rgb)
            np.testing.assert_array_equal(frame.depth, reference.depth)
    # Blank ranges follow frame numbers, whatever the stride.
    strided = open_synthetic(spec + "&blank=5-7", stride=3)
    assert [strided.is_blank(i) for i in range(len(strided))][:4] == [False, False, True, False]


def test_drop_removes_frames_and_later_ones_keep_their_timestamps():
    spec = "walk?frames=30&seed=2&width=32&height=24&noise=1"
    full, seq = open_synthetic(spec), open_synthetic(spec + "&drop=10-19")
    assert len(seq) == 20 and seq.name.endswith("&noise=1&drop=10-19")
    np.testing.assert_array_equal(seq.frame_numbers, np.r_[0:10, 20:30])
    np.testing.assert_allclose(seq.trajectory, full.trajectory[seq.frame_numbers])
    after = seq[10]
    assert after.index == 10 and after.timestamp == pytest.approx(20 / 30)
    np.testing.assert_array_equal(after.depth, full[20].depth)  # the same noise as undropped
    np.testing.assert_array_equal(after.rgb, full[20].rgb)
    # With blank, stride and max_frames together.
    both = open_synthetic(spec + "&blank=22-23&drop=10-19", stride=2, max_frames=8)
    assert both.name.endswith("&blank=22-23&drop=10-19")
    np.testing.assert_array_equal(both.frame_numbers, [0, 2, 4, 6, 8, 20, 22, 24])
    assert [both.is_blank(i) for i in range(8)] == [False] * 6 + [True, False]


def test_names_round_trip_and_stay_unchanged_without_loss_options():
    assert parse_synthetic_spec("orbit").name == "synthetic:orbit?frames=100&seed=0&width=320&height=240&noise=0"
    assert parse_synthetic_spec("agents?agent=1").name == \
        "synthetic:agents?frames=100&seed=0&width=320&height=240&noise=0&agent=1&agents=2"
    assert parse_synthetic_spec("laps").name == "synthetic:laps?frames=780&seed=0&width=320&height=240&noise=0&size=compact"
    for spec in ("laps?frames=800&width=160&height=120&noise=1&blank=100-130", "laps?size=large&drop=5-9",
                 "synthetic:loop?drop=3-4&blank=7-7&seed=9", "agents?agent=1&agents=3&drop=0-10"):
        parsed = parse_synthetic_spec(spec)
        assert parse_synthetic_spec(parsed.name) == parsed
        assert parse_synthetic_spec(parsed.name).name == parsed.name
    assert parse_synthetic_spec("loop?blank=0010-20").blank == (10, 20)


@pytest.mark.parametrize(
    "spec, words",
    [
        ("orbit?blank=5", ["blank", "A-B"]),
        ("orbit?blank=a-b", ["blank", "A-B"]),
        ("orbit?drop=-1-3", ["drop", "A-B"]),
        ("orbit?blank=7-5", ["blank", "reversed"]),
        ("orbit?frames=20&drop=5-20", ["drop", "20", "last frame 19"]),
        ("orbit?frames=20&drop=0-19", ["drop", "no frames"]),
        ("orbit?blank=1-2&blank=3-4", ["blank", "twice"]),
        ("orbit?blank=", ["blank", "A-B"]),
    ],
)
def test_bad_loss_options_raise_data_error(spec, words):
    with pytest.raises(DataError) as info:
        open_synthetic(spec)
    for word in words:
        assert word in str(info.value)


def test_drop_with_stride_leaving_nothing_raises():
    with pytest.raises(DataError, match="no frames"):
        open_synthetic("orbit?frames=10&drop=0-8", stride=2)


# The synthetic camera's colour: exposure changes and a colour-depth offset.
def test_synthetic_exposure_and_colour_shift_change_the_colour_as_specified():
    from slam.data.synthetic import camera_colour, open_synthetic, parse_synthetic_spec

    plain = open_synthetic("synthetic:walk?frames=20&width=64&height=48")
    exposed = open_synthetic("synthetic:walk?frames=20&width=64&height=48&exposure=0.3")
    shifted = open_synthetic("synthetic:walk?frames=20&width=64&height=48&color_shift=3")
    for i in (0, 7):
        gain, bias = exposed.exposure_of(i)
        assert np.all((gain > 0.7 * 0.94) & (gain < 1.3 * 1.06)) and abs(bias[0]) <= 0.06 and np.all(bias == bias[0])
        assert np.allclose(exposed[i].rgb, np.clip(plain[i].rgb * gain + bias, 0, 1), atol=1e-6)
        assert np.array_equal(exposed[i].depth, plain[i].depth) and np.array_equal(shifted[i].depth, plain[i].depth)
        assert np.array_equal(shifted[i].rgb[:, 3:], plain[i].rgb[:, :-3])
        assert np.array_equal(shifted[i].rgb[:, :3], np.repeat(plain[i].rgb[:, :1], 3, axis=1))
    assert not np.allclose(exposed.exposure_of(0)[0], exposed.exposure_of(1)[0])
    assert np.array_equal(camera_colour(plain[0].rgb, np.ones(3), np.zeros(3), 0), plain[0].rgb)
    spec = parse_synthetic_spec("laps?width=160&height=120&exposure=0.25&color_shift=2")
    assert spec.name.endswith("&exposure=0.25&color_shift=2") and parse_synthetic_spec(spec.name) == spec
    assert "exposure" not in parse_synthetic_spec("laps?width=160").name


@pytest.mark.parametrize("spec,words", [
    ("walk?exposure=1.5", "exposure=1.5 must be in [0, 0.9]"),
    ("walk?exposure=-0.1", "must be in"),
    ("walk?exposure=nan", "must be in"),
    ("walk?exposure=bright", "is not a number"),
    ("walk?color_shift=-1", "color_shift=-1 must be in 0..64"),
    ("walk?color_shift=65&width=1024", "must be in 0..64"),
    ("walk?color_shift=40&width=160", "below a quarter of the width"),
    ("walk?color_shift=1.5", "not an integer"),
])
def test_bad_camera_colour_options_raise(spec, words):
    from slam.data.synthetic import parse_synthetic_spec

    with pytest.raises(DataError, match=words.replace("[", r"\[").replace("]", r"\]").replace(".", r"\.")):
        parse_synthetic_spec(spec)
