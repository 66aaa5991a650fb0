"""Synthetic RGB-D source: scenes, ray caster, GT mesh, trajectories, noise and spec parsing."""

from __future__ import annotations

import numpy as np
import pytest

from slam.data.frame import DataError, Frame, RGBDSequence
from slam.data.synthetic import (
    NOMINAL_FRAMES,
    TRAJECTORY_KINDS,
    DepthNoiseModel,
    cast_rays,
    default_intrinsics,
    gt_mesh,
    look_at,
    make_agent_trajectories,
    make_scene,
    make_trajectory,
    open_synthetic,
    render_rgbd,
    render_view,
)
from slam.data.synthetic_scene import Texture, surface_colour

SMALL = {"width": 160}  # 160x120 keeps renders ~25 ms


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


@pytest.mark.parametrize("kind", TRAJECTORY_KINDS)
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
    assert translation.max() < 0.016 and rotation.max() < 1.1
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
        scene = make_scene("room", seed)
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


def test_render_view_reports_grazing_incidence():
    scene = make_scene("empty", 0)
    # Looking along the floor: the floor near the horizon is seen at grazing angles.
    T = look_at(np.array([[-2.0, 0.0, 0.5]]), np.array([[2.0, 0.0, 0.4]]))[0]
    view = render_view(scene, default_intrinsics(80, 60), T, 80, 60)
    floor = view.surface == 4
    assert floor.any() and view.incidence_cos[floor].min() < 0.2
    wall = view.surface == 1  # x = hi, seen head-on
    assert view.incidence_cos[wall].min() > 0.8
