"""Tests for slam/eval: TUM I/O, association, Umeyama/ATE (cross-checked with evo), mesh metrics, CLI."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from slam.data.frame import DataError
from slam.eval import (
    CullCamera,
    Trajectory,
    associate,
    ate,
    cull_to_cameras,
    format_tum,
    mesh_metrics,
    parse_tum,
    read_trajectory,
    read_tum,
    umeyama_alignment,
    write_tum,
)
from slam.eval.commands import add_eval_ate_arguments, add_eval_mesh_arguments, cmd_eval_ate, cmd_eval_mesh
from slam.geometry import make_pose, so3_exp

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
RPY_GT = DATA / "rgbd_dataset_freiburg1_rpy" / "groundtruth.txt"
REPLICA = DATA / "Replica"


def needs(path: Path) -> None:
    if not path.exists():
        pytest.skip(f"shared data not found: {path}")


def rotation(omega) -> np.ndarray:
    """(3,) axis-angle -> (3, 3) float64 rotation."""
    return so3_exp(torch.as_tensor(omega, dtype=torch.float64)).numpy()


def pose(omega, t) -> np.ndarray:
    return make_pose(torch.as_tensor(rotation(omega)), torch.as_tensor(t, dtype=torch.float64)).numpy()


def random_walk(rng: np.random.Generator, n: int, hz: float = 30.0, t0: float = 1000.0) -> Trajectory:
    """A smooth-ish handheld-like trajectory: random-walk positions and rotations."""
    positions = np.cumsum(rng.normal(0, 0.02, (n, 3)), axis=0)
    angles = np.cumsum(rng.normal(0, 0.02, (n, 3)), axis=0)
    poses = make_pose(so3_exp(torch.from_numpy(angles)), torch.from_numpy(positions)).numpy()
    return Trajectory(t0 + np.arange(n) / hz, poses)


def perturbed(
    traj: Trajectory, rng: np.random.Generator, T_new_old: np.ndarray, noise: float, drift: float, dt: float
) -> Trajectory:
    """Copy of ``traj`` in another world frame, with growing drift, noise and shifted stamps."""
    n = len(traj)
    poses = T_new_old @ traj.poses
    drift_xyz = np.linspace(0, 1, n)[:, None] * np.array([drift, -0.5 * drift, 0.3 * drift])
    poses[:, :3, 3] += drift_xyz + rng.normal(0, noise, (n, 3))
    return Trajectory(traj.timestamps + dt, poses)


def brute_force_associate(a: np.ndarray, b: np.ndarray, max_dt: float) -> set[tuple[int, int]]:
    """TUM associate.py, quadratic: all close pairs sorted by difference, taken greedily."""
    pairs = sorted((abs(x - y), i, j) for i, x in enumerate(a) for j, y in enumerate(b) if abs(x - y) <= max_dt)
    used_a, used_b, out = set(), set(), set()
    for _, i, j in pairs:
        if i not in used_a and j not in used_b:
            used_a.add(i), used_b.add(j), out.add((i, j))
    return out


# ---------------------------------------------------------------- TUM files


def test_trajectory_validates_shapes():
    with pytest.raises(ValueError, match="poses"):
        Trajectory(np.zeros(3), np.zeros((2, 4, 4)))
    with pytest.raises(ValueError, match="timestamps"):
        Trajectory(np.zeros((3, 1)), np.zeros((3, 4, 4)))


def test_parse_tum_skips_comments_and_converts_xyzw():
    text = "# header\n\n1.5 1 2 3 0 0 0.7071067811865476 0.7071067811865476\n  # indented comment\n2.0,0,0,0,0,0,0,1\n"
    traj = parse_tum(text)
    np.testing.assert_allclose(traj.timestamps, [1.5, 2.0])
    np.testing.assert_allclose(traj.poses[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(traj.positions, [[1, 2, 3], [0, 0, 0]])
    np.testing.assert_allclose(traj.poses[1], np.eye(4))


@pytest.mark.parametrize(
    "bad_line, message",
    [
        ("3.0 1 2 3 0 0 0", r"traj\.txt:3: expected 8 columns.*got 7"),
        ("3.0 1 2 3 0 0 0 1 9", r"traj\.txt:3: expected 8 columns.*got 9"),
        ("3.0 1 2 x 0 0 0 1", r"traj\.txt:3: not a number"),
        ("3.0 1 2 nan 0 0 0 1", r"traj\.txt:3: non-finite"),
        ("3.0 1 2 3 0 0 0 0", r"traj\.txt:3: quaternion has zero norm"),
    ],
)
def test_read_tum_names_the_bad_line(tmp_path, bad_line, message):
    path = tmp_path / "traj.txt"
    path.write_text(f"# c\n1.0 0 0 0 0 0 0 1\n{bad_line}\n")
    with pytest.raises(DataError, match=message):
        read_tum(path)


def test_read_tum_missing_and_empty(tmp_path):
    with pytest.raises(DataError, match="nope.txt: no such trajectory file"):
        read_tum(tmp_path / "nope.txt")
    (tmp_path / "empty.txt").write_text("# only a comment\n")
    with pytest.raises(DataError, match="empty.txt: holds no poses"):
        read_tum(tmp_path / "empty.txt")


def test_write_read_round_trip(tmp_path):
    traj = random_walk(np.random.default_rng(0), 40)
    traj = Trajectory(traj.timestamps + 0.1234567, traj.poses)
    path = tmp_path / "out.txt"
    write_tum(path, traj)
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    assert len(lines) == 40
    assert lines[0].split()[0] == f"{traj.timestamps[0]:.6f}"  # 6 decimals
    back = read_tum(path)
    np.testing.assert_allclose(back.timestamps, traj.timestamps, atol=6e-7, rtol=0)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-8, rtol=0)
    assert format_tum(back).splitlines()[0].startswith("#")


def test_read_trajectory_accepts_replica_rows(tmp_path):
    T = pose([0.1, 0.2, -0.3], [1, 2, 3])
    (tmp_path / "traj.txt").write_text(" ".join(f"{v:.17g}" for v in T.ravel()) + "\n" + " ".join(["0"] * 15) + "\n")
    with pytest.raises(DataError, match=r"traj\.txt:2: expected 16 numbers"):
        read_trajectory(tmp_path / "traj.txt")
    (tmp_path / "traj.txt").write_text((" ".join(f"{v:.17g}" for v in T.ravel()) + "\n") * 3)
    traj = read_trajectory(tmp_path / "traj.txt")
    np.testing.assert_allclose(traj.timestamps, [0, 1, 2])
    np.testing.assert_allclose(traj.poses[2], T)


@pytest.mark.shared_data
def test_read_real_groundtruth():
    needs(RPY_GT)
    traj = read_tum(RPY_GT)
    assert len(traj) == 2742  # 2745 lines minus 3 comments
    assert traj.timestamps[0] == pytest.approx(1305031225.9334)
    np.testing.assert_allclose(traj.positions[0], [1.3357, 0.6698, 1.6180])
    R = traj.poses[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)


# ---------------------------------------------------------------- association


def test_associate_is_one_to_one_closest_first():
    # b's only stamp is closer to a[1] (4 ms) than to a[0] (6 ms): nearest-per-a would use it twice.
    idx_a, idx_b = associate(np.array([1.000, 1.010]), np.array([1.006]), max_dt=0.02)
    assert idx_a.tolist() == [1] and idx_b.tolist() == [0]


def test_associate_respects_max_dt_and_unsorted_input():
    a = np.array([3.0, 1.0, 2.0])
    b = np.array([2.005, 0.5, 3.03, 1.001])
    idx_a, idx_b = associate(a, b, max_dt=0.02)
    assert list(zip(idx_a.tolist(), idx_b.tolist())) == [(1, 3), (2, 0)]  # 3.0 vs 3.03 too far
    assert associate(a, np.array([]), 0.02)[0].size == 0
    with pytest.raises(ValueError, match="max_dt"):
        associate(a, b, max_dt=-1)


def test_associate_matches_brute_force_tum_rule():
    rng = np.random.default_rng(1)
    for _ in range(5):
        a = np.sort(rng.uniform(0, 3, 120))
        b = rng.uniform(0, 3, 90)  # unsorted on purpose
        idx_a, idx_b = associate(a, b, max_dt=0.02)
        assert set(zip(idx_a.tolist(), idx_b.tolist())) == brute_force_associate(a, b, 0.02)
        assert len(set(idx_a.tolist())) == len(idx_a) and len(set(idx_b.tolist())) == len(idx_b)
        assert np.all(np.diff(idx_a) > 0)


# ---------------------------------------------------------------- Umeyama and ATE


def test_umeyama_recovers_known_transform():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(50, 3))
    R_true, t_true = rotation([0.4, -1.2, 2.5]), np.array([1.0, -2.0, 0.5])
    R, t, s = umeyama_alignment(src, src @ R_true.T + t_true)
    np.testing.assert_allclose(R, R_true, atol=1e-12)
    np.testing.assert_allclose(t, t_true, atol=1e-12)
    assert s == 1.0
    R, t, s = umeyama_alignment(src, 2.5 * src @ R_true.T + t_true, with_scale=True)
    np.testing.assert_allclose(R, R_true, atol=1e-12)
    np.testing.assert_allclose(t, t_true, atol=1e-12)
    assert s == pytest.approx(2.5, abs=1e-12)


def test_umeyama_never_returns_a_reflection():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(30, 3))
    R, _, _ = umeyama_alignment(src, src * np.array([1.0, 1.0, -1.0]))
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_umeyama_rejects_collinear_and_bad_shapes():
    line = np.linspace(0, 1, 10)[:, None] * np.array([[1.0, 2.0, 3.0]])
    with pytest.raises(DataError, match="collinear"):
        umeyama_alignment(line, line + 1)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        umeyama_alignment(np.zeros((5, 2)), np.zeros((5, 2)))


def test_ate_of_rigidly_moved_copy_is_zero():
    gt = random_walk(np.random.default_rng(4), 100)
    T_new_old = pose([0.3, -0.2, 1.0], [5.0, -1.0, 2.0])
    est = Trajectory(gt.timestamps + 0.005, T_new_old @ gt.poses)
    result = ate(gt, est)
    assert result.num_pairs == 100
    assert result.rmse < 1e-10 and result.max < 1e-10
    np.testing.assert_allclose(result.T_gt_est, np.linalg.inv(T_new_old), atol=1e-10)
    unaligned = ate(gt, est, align=False)
    assert unaligned.rmse > 1.0
    np.testing.assert_allclose(unaligned.T_gt_est, np.eye(4))


def test_ate_noisy_copy_statistics():
    rng = np.random.default_rng(5)
    gt = random_walk(rng, 2000)
    sigma = 0.01
    est = perturbed(gt, rng, pose([0.1, 0.2, 0.3], [1, 2, 3]), noise=sigma, drift=0.0, dt=0.0)
    result = ate(gt, est)
    # |N(0, sigma^2 I_3)| has RMS sigma * sqrt(3); alignment removes only 6 of 6000 dof.
    assert result.rmse == pytest.approx(sigma * math.sqrt(3), rel=0.05)
    assert result.min <= result.median <= result.max
    assert result.errors.shape == (2000,)
    assert result.rmse == pytest.approx(math.sqrt(result.mean**2 + result.std**2))


def test_ate_without_alignment_measures_offset():
    gt = random_walk(np.random.default_rng(6), 20)
    est = Trajectory(gt.timestamps, gt.poses.copy())
    est.poses[:, :3, 3] += [0.03, 0.04, 0.0]
    result = ate(gt, est, align=False)
    assert result.rmse == pytest.approx(0.05) and result.std == pytest.approx(0.0, abs=1e-12)


def test_ate_without_pairs_is_a_clear_error():
    gt = random_walk(np.random.default_rng(7), 10)
    est = Trajectory(gt.timestamps + 5.0, gt.poses)
    with pytest.raises(DataError, match="no associated poses"):
        ate(gt, est)


# ---------------------------------------------------------------- cross-check with evo


def evo_ape(gt_path: Path, est_path: Path, align: bool, max_dt: float) -> dict:
    """``evo_ape tum GT EST [-a] --t_max_diff max_dt`` through evo's Python API."""
    pytest.importorskip("evo")
    from evo.core import metrics, sync
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(gt_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    ref, est = sync.associate_trajectories(ref, est, max_diff=max_dt)
    if align:
        est.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    stats = ape.get_all_statistics()
    stats["num_pairs"] = ref.num_poses
    return stats


def assert_matches_evo(gt_path: Path, est_path: Path, align: bool = True, max_dt: float = 0.02) -> float:
    ours = ate(read_tum(gt_path), read_tum(est_path), align=align, max_dt=max_dt)
    theirs = evo_ape(gt_path, est_path, align, max_dt)
    assert ours.num_pairs == theirs["num_pairs"]
    differences = [abs(getattr(ours, key) - theirs[key]) for key in ("rmse", "mean", "median", "max", "min", "std")]
    assert max(differences) < 1e-4, differences
    return max(differences)


@pytest.mark.shared_data
def test_ate_matches_evo_on_real_groundtruth(tmp_path):
    needs(RPY_GT)
    pytest.importorskip("evo")
    gt = read_tum(RPY_GT)
    rng = np.random.default_rng(8)
    # A 30 Hz estimate in its first camera's frame, drifting 10 cm, 5 mm noise, stamps 3 ms late.
    sub = gt.subset(np.arange(0, len(gt), 3))
    est = perturbed(sub, rng, np.linalg.inv(gt.poses[0]), noise=0.005, drift=0.1, dt=0.003)
    write_tum(tmp_path / "est.txt", est)
    assert_matches_evo(RPY_GT, tmp_path / "est.txt", align=True)
    assert_matches_evo(RPY_GT, tmp_path / "est.txt", align=False)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ate_matches_evo_on_synthetic(tmp_path, seed):
    pytest.importorskip("evo")
    rng = np.random.default_rng(100 + seed)
    gt = random_walk(rng, 300, hz=100.0)
    keep = np.sort(rng.choice(len(gt), 200, replace=False))  # dropped frames
    est = perturbed(gt.subset(keep), rng, pose(rng.normal(size=3), rng.normal(size=3)), 0.01, 0.2, 0.002)
    est = Trajectory(est.timestamps + rng.uniform(-0.002, 0.002, len(est)), est.poses)
    write_tum(tmp_path / "gt.txt", gt)
    write_tum(tmp_path / "est.txt", est)
    assert_matches_evo(tmp_path / "gt.txt", tmp_path / "est.txt", align=True)


# ---------------------------------------------------------------- mesh metrics


def plane(size_x: float = 1.0, size_y: float = 1.0, z: float = 0.0, x0: float = 0.0) -> trimesh.Trimesh:
    """A rectangle [x0, x0 + size_x] x [0, size_y] at height z, two triangles."""
    vertices = np.array([[x0, 0, z], [x0 + size_x, 0, z], [x0 + size_x, size_y, z], [x0, size_y, z]], dtype=float)
    return trimesh.Trimesh(vertices, np.array([[0, 1, 2], [0, 2, 3]]), process=False)


def grid_plane(n: int, size: float, z: float) -> trimesh.Trimesh:
    """An n x n grid of quads over [-size/2, size/2]^2 at height z (vertices to cull)."""
    xs = np.linspace(-size / 2, size / 2, n + 1)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    vertices = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], 1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return trimesh.Trimesh(vertices, faces, process=False)


def sampling_floor(area: float, num_points: int) -> float:
    """Mean nearest-neighbour distance of uniform random points on a surface: 1 / (2 sqrt(density)).

    The protocol compares two independent point samples, so even identical meshes score this.
    """
    return 0.5 * math.sqrt(area / num_points)


def test_identical_meshes_score_perfectly():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    metrics = mesh_metrics(mesh, mesh, num_points=20_000)
    floor = sampling_floor(mesh.area, 20_000)  # ~6 mm here
    assert metrics.accuracy == pytest.approx(floor, rel=0.05)
    assert metrics.completion == pytest.approx(floor, rel=0.05)
    assert metrics.completion_ratio == 1.0 and metrics.precision == 1.0 and metrics.fscore == 1.0
    assert metrics.num_points == 20_000 and metrics.threshold == 0.05


def test_metrics_are_deterministic_per_seed():
    mesh = trimesh.creation.icosphere(subdivisions=2)
    shifted = mesh.copy().apply_translation([0.01, 0, 0])
    first = mesh_metrics(mesh, shifted, num_points=2000, seed=3)
    assert first == mesh_metrics(mesh, shifted, num_points=2000, seed=3)
    assert first != mesh_metrics(mesh, shifted, num_points=2000, seed=4)


def test_shift_of_two_centimetres():
    # 0.2 m squares sampled densely: the lateral sample spacing (< 1 mm) barely adds to 2 cm.
    rec, gt = plane(0.2, 0.2, z=0.02), plane(0.2, 0.2, z=0.0)
    metrics = mesh_metrics(rec, gt, num_points=20_000, threshold=0.05)
    assert metrics.accuracy == pytest.approx(0.02, abs=2e-4)
    assert metrics.completion == pytest.approx(0.02, abs=2e-4)
    assert metrics.accuracy >= 0.02 and metrics.completion >= 0.02  # never below the true gap
    assert metrics.completion_ratio == 1.0 and metrics.precision == 1.0
    strict = mesh_metrics(rec, gt, num_points=20_000, threshold=0.01)
    assert strict.completion_ratio == 0.0 and strict.precision == 0.0 and strict.fscore == 0.0


def test_shifted_sphere_is_about_two_centimetres():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.2)
    grown = trimesh.creation.icosphere(subdivisions=4, radius=0.22)
    metrics = mesh_metrics(grown, sphere, num_points=20_000)
    assert metrics.accuracy == pytest.approx(0.02, abs=1e-3)
    assert metrics.completion == pytest.approx(0.02, abs=1e-3)


def test_half_mesh_completes_half():
    length, threshold = 2.0, 0.05
    gt = plane(size_x=length, size_y=0.2)
    half = plane(size_x=length / 2, size_y=0.2)
    metrics = mesh_metrics(half, gt, num_points=20_000, threshold=threshold)
    # GT points beyond the cut at x in [L/2, L] are (x - L/2) away; the half is inside the GT.
    assert metrics.completion_ratio == pytest.approx(0.5 + threshold / length, abs=0.01)
    assert metrics.completion == pytest.approx(length / 8, rel=0.03)
    assert metrics.accuracy == pytest.approx(sampling_floor(gt.area, 20_000), rel=0.1)
    assert metrics.precision == 1.0
    assert metrics.recall == metrics.completion_ratio
    expected_f = 2 * metrics.precision * metrics.recall / (metrics.precision + metrics.recall)
    assert metrics.fscore == pytest.approx(expected_f)


def looking_down(height: float) -> np.ndarray:
    """(4, 4) camera at (0, 0, height) looking along -z (OpenCV z axis pointing down)."""
    return pose([math.pi, 0, 0], [0, 0, height])


K_SMALL = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])  # 64 x 48, ~65 x 51 deg fov


def test_culling_removes_faces_outside_frusta():
    mesh = grid_plane(40, 20.0, 0.0)  # 20 m wide floor, camera 2 m above sees ~2.5 m x 1.8 m
    camera = CullCamera(K_SMALL, looking_down(2.0), 64, 48)
    culled = cull_to_cameras(mesh, [camera])
    assert 0 < len(culled.faces) < len(mesh.faces) // 20
    assert np.abs(culled.vertices[:, 0]).max() < 1.3 + 0.5 and np.abs(culled.vertices[:, 1]).max() < 1.0 + 0.5
    # A camera looking away (up) sees nothing; a plain tuple works as a camera.
    assert len(cull_to_cameras(mesh, [(K_SMALL, pose([0, 0, 0], [0, 0, 2.0]), 64, 48)]).faces) == 0
    # Two cameras keep the union.
    second = CullCamera(K_SMALL, looking_down(2.0) @ pose([0, 0, 0], [4.0, 0, 0]), 64, 48)
    assert len(cull_to_cameras(mesh, [camera, second]).faces) == pytest.approx(2 * len(culled.faces), rel=0.1)


def test_depth_aware_culling_drops_occluded_surfaces():
    near, far = grid_plane(20, 6.0, 1.0), grid_plane(20, 6.0, 0.0)
    both = trimesh.util.concatenate([near, far])
    camera = CullCamera(K_SMALL, looking_down(2.0), 64, 48)
    near_faces = len(cull_to_cameras(near, [camera]).faces)
    assert 0 < near_faces < len(cull_to_cameras(far, [camera]).faces)
    assert len(cull_to_cameras(both, [camera]).faces) == near_faces + len(cull_to_cameras(far, [camera]).faces)
    depth = np.full((48, 64), 1.0)  # the camera sees the near plane 1 m away everywhere
    occlusion_aware = cull_to_cameras(both, [camera], depths=[depth])
    assert len(occlusion_aware.faces) == near_faces
    assert np.all(occlusion_aware.vertices[:, 2] == 1.0)
    with pytest.raises(ValueError, match="depth map shape"):
        cull_to_cameras(both, [camera], depths=[np.ones((10, 10))])


def test_culled_metrics_ignore_unseen_parts():
    # Same 10 cm grid, so both cull to the same faces; only the part under the camera
    # (and a margin) was reconstructed.
    gt = grid_plane(200, 20.0, 0.0)
    rec = grid_plane(40, 4.0, 0.0)
    camera = CullCamera(K_SMALL, looking_down(2.0), 64, 48)
    plain = mesh_metrics(rec, gt, num_points=20_000)
    culled = mesh_metrics(rec, gt, num_points=20_000, cull_cameras=[camera])
    assert plain.completion_ratio < 0.1
    assert culled.completion_ratio == 1.0 and culled.precision == 1.0
    assert culled.accuracy < 1.1 * sampling_floor(cull_to_cameras(rec, [camera]).area, 20_000)


def test_empty_mesh_after_culling_is_a_clear_error():
    mesh = grid_plane(4, 1.0, 0.0)
    away = CullCamera(K_SMALL, pose([0, 0, 0], [0, 0, 2.0]), 64, 48)
    with pytest.raises(DataError, match="no faces"):
        mesh_metrics(mesh, mesh, num_points=100, cull_cameras=[away])
    with pytest.raises(ValueError, match="threshold"):
        mesh_metrics(mesh, mesh, threshold=0.0)


def replica_office0_cameras() -> list[CullCamera]:
    params = json.loads((REPLICA / "cam_params.json").read_text())["camera"]
    K = np.array([[params["fx"], 0, params["cx"]], [0, params["fy"], params["cy"]], [0, 0, 1]])
    poses = read_trajectory(REPLICA / "office0" / "traj.txt").poses[:4]
    return [CullCamera(K, T, int(params["w"]), int(params["h"])) for T in poses]


@pytest.mark.shared_data
def test_replica_office0_mesh_against_itself_culled():
    needs(REPLICA / "office0_mesh.ply")
    mesh = trimesh.load(REPLICA / "office0_mesh.ply", force="mesh")
    cameras = replica_office0_cameras()
    culled = cull_to_cameras(mesh, cameras)
    assert 0.05 * len(mesh.faces) < len(culled.faces) < 0.8 * len(mesh.faces)
    metrics = mesh_metrics(mesh, mesh, num_points=50_000, cull_cameras=cameras)
    # Identical meshes: only the sampling floor (~1 cm at 50k points on the ~20 m^2 seen).
    floor = sampling_floor(culled.area, 50_000)
    assert metrics.accuracy < 1.2 * floor and metrics.completion < 1.2 * floor
    assert metrics.completion_ratio > 0.99 and metrics.fscore > 0.99
    # Occlusion-aware culling with the rendered depth keeps fewer faces (hidden ones go).
    cv2 = pytest.importorskip("cv2")
    depth_files = [REPLICA / "office0" / "results" / f"depth{i:06d}.png" for i in range(4)]
    depths = [cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64) / 6553.5 for path in depth_files]
    visible = cull_to_cameras(mesh, cameras, depths=depths)
    assert 0 < len(visible.faces) < len(culled.faces)


# ---------------------------------------------------------------- command line


def run_cli(add_arguments, command, argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return command(parser.parse_args(argv))


def test_cli_eval_ate_table_and_json(tmp_path, capsys):
    rng = np.random.default_rng(9)
    gt = random_walk(rng, 60)
    est = perturbed(gt, rng, pose([0, 0, 0.5], [1, 0, 0]), noise=0.01, drift=0.0, dt=0.001)
    write_tum(tmp_path / "gt.txt", gt)
    write_tum(tmp_path / "est.txt", est)
    out = tmp_path / "ate.json"
    assert run_cli(add_eval_ate_arguments, cmd_eval_ate, [str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    expected = ate(gt, read_tum(tmp_path / "est.txt"))
    assert "60 pose pairs" in printed and f"{expected.rmse * 100:10.4f} cm" in printed
    saved = json.loads(out.read_text())
    assert saved["rmse"] == pytest.approx(expected.rmse) and saved["num_pairs"] == 60 and saved["aligned"] is True
    assert np.array(saved["T_gt_est"]).shape == (4, 4)
    assert run_cli(add_eval_ate_arguments, cmd_eval_ate, [str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--no-align"]) == 0
    assert "no alignment" in capsys.readouterr().out


def test_cli_eval_ate_errors_exit_2(tmp_path, capsys):
    gt = random_walk(np.random.default_rng(10), 10)
    write_tum(tmp_path / "gt.txt", gt)
    assert run_cli(add_eval_ate_arguments, cmd_eval_ate, [str(tmp_path / "gt.txt"), str(tmp_path / "missing.txt")]) == 2
    assert "missing.txt: no such trajectory file" in capsys.readouterr().err
    (tmp_path / "bad.txt").write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0\n")
    assert run_cli(add_eval_ate_arguments, cmd_eval_ate, [str(tmp_path / "gt.txt"), str(tmp_path / "bad.txt")]) == 2
    assert "bad.txt:2: expected 8 columns" in capsys.readouterr().err
    write_tum(tmp_path / "late.txt", Trajectory(gt.timestamps + 100, gt.poses))
    assert run_cli(add_eval_ate_arguments, cmd_eval_ate, [str(tmp_path / "gt.txt"), str(tmp_path / "late.txt")]) == 2
    assert "no associated poses" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        run_cli(add_eval_ate_arguments, cmd_eval_ate, [str(tmp_path / "gt.txt"), str(tmp_path / "gt.txt"), "--max-dt", "-1"])
    assert exit_info.value.code == 2


def test_cli_eval_mesh_with_culling(tmp_path, capsys):
    grid_plane(200, 20.0, 0.0).export(tmp_path / "gt.ply")
    grid_plane(40, 4.0, 0.0).export(tmp_path / "rec.ply")
    write_tum(tmp_path / "cams.txt", Trajectory(np.array([0.0]), looking_down(2.0)[None]))
    out = tmp_path / "mesh.json"
    base = [str(tmp_path / "rec.ply"), str(tmp_path / "gt.ply"), "--num-points", "5000", "--json", str(out)]
    cull = ["--cull-traj", str(tmp_path / "cams.txt"), "--intrinsics", "50,50,31.5,23.5", "--size", "64,48"]
    assert run_cli(add_eval_mesh_arguments, cmd_eval_mesh, base + cull) == 0
    printed = capsys.readouterr().out
    saved = json.loads(out.read_text())
    assert saved["culled"] is True and saved["completion_ratio"] > 0.99 and saved["num_points"] == 5000
    assert "completion ratio" in printed and f"{saved['accuracy'] * 100:10.4f} cm" in printed
    assert run_cli(add_eval_mesh_arguments, cmd_eval_mesh, base) == 0
    assert json.loads(out.read_text())["completion_ratio"] < 0.1


def test_cli_eval_mesh_errors_exit_2(tmp_path, capsys):
    plane().export(tmp_path / "a.ply")
    assert run_cli(add_eval_mesh_arguments, cmd_eval_mesh, [str(tmp_path / "a.ply"), str(tmp_path / "none.ply")]) == 2
    assert "none.ply: no such mesh file" in capsys.readouterr().err
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(10, 3))).export(tmp_path / "cloud.ply")
    assert run_cli(add_eval_mesh_arguments, cmd_eval_mesh, [str(tmp_path / "a.ply"), str(tmp_path / "cloud.ply")]) == 2
    assert "cloud.ply" in capsys.readouterr().err
    (tmp_path / "junk.ply").write_bytes(b"ply\nformat nonsense\n")
    assert run_cli(add_eval_mesh_arguments, cmd_eval_mesh, [str(tmp_path / "a.ply"), str(tmp_path / "junk.ply")]) == 2
    assert "junk.ply" in capsys.readouterr().err
    write_tum(tmp_path / "cams.txt", Trajectory(np.array([0.0]), np.eye(4)[None]))
    argv = [str(tmp_path / "a.ply"), str(tmp_path / "a.ply"), "--cull-traj", str(tmp_path / "cams.txt")]
    assert run_cli(add_eval_mesh_arguments, cmd_eval_mesh, argv) == 2
    assert "--intrinsics" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        run_cli(add_eval_mesh_arguments, cmd_eval_mesh, argv + ["--intrinsics", "1,2,3", "--size", "64,48"])
    assert exit_info.value.code == 2


def test_loop_pose_error_against_ground_truth():
    """A loop's measured relative pose (query camera in the match camera's frame) against GT."""
    from slam.eval.loops import loop_pose_errors, relative_pose_error

    T_match, T_query = np.eye(4), np.eye(4)
    T_query[0, 3] = 0.1
    assert relative_pose_error(np.eye(4), T_match, T_query) == pytest.approx((0.1, 0.0))
    turn = np.eye(4)
    turn[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # 90 degrees about z
    measured = T_query.copy()
    # The world frame of the ground truth does not matter, only the two poses' relation.
    assert relative_pose_error(measured, turn @ T_match, turn @ T_query) == pytest.approx((0.0, 0.0), abs=1e-9)
    assert relative_pose_error(measured, T_match, T_query @ turn)[1] == pytest.approx(90.0)
    gt = {(0, 3): T_query, (0, 1): T_match}
    loops = [{"agent": 0, "frame_index": 3, "match_agent": 0, "match_frame_index": 1, "T_match_query": measured.tolist()},
             {"agent": 0, "frame_index": 3, "match_agent": 0, "match_frame_index": 2, "T_match_query": measured.tolist()},
             {"agent": 0, "frame_index": 3, "match_agent": 0, "match_frame_index": 1}]
    errors = loop_pose_errors(loops, lambda agent, index: gt.get((agent, index)))
    assert len(errors) == 1 and errors[0].translation_m == pytest.approx(0.0) and errors[0].gt_distance_m == 0.1


def test_run_ate_uses_the_frames_that_have_ground_truth():
    """A real sequence lacks GT for a few frames (fr1/rpy: 3 of 723): the run's ATE pairs the
    others, as TUM's evaluation does, instead of giving none (issue 41's 300-frame windows)."""
    from slam.outputs import AgentTrajectory, _ate

    rng = np.random.default_rng(0)
    gt = [np.eye(4) for _ in range(10)]
    for k, T in enumerate(gt):
        T[:3, 3] = rng.normal(size=3)
    est = np.stack(gt).copy()
    est[:, :3, 3] += 0.01 * rng.normal(size=(10, 3))
    full = _ate([AgentTrajectory(0, np.arange(10.0), est, list(gt), 0)])
    holes = list(gt)
    holes[3] = holes[7] = None
    partial = _ate([AgentTrajectory(0, np.arange(10.0), est, holes, 0)])
    keep = [k for k in range(10) if k not in (3, 7)]
    assert partial is not None and full is not None
    assert partial == pytest.approx(_ate([AgentTrajectory(0, np.arange(8.0), est[keep], [gt[k] for k in keep], 0)]))
    assert _ate([AgentTrajectory(0, np.arange(10.0), est, [None] * 8 + gt[:2], 0)]) is None


def test_one_aligned_ate_for_eval_runs_and_the_page():
    """Issue 42: the aligned ATE is computed once (``slam.eval.ate.ate_from_pairs``). ``ate``,
    a run's ATE (``slam.outputs.aligned_rmse``) and the page's error plot
    (``server.series.compare``) give the same numbers on one trajectory, and the same as the
    formula each used before (Umeyama, then the RMSE of the aligned positions)."""
    from server.series import MAX_DT_S, compare
    from slam.eval import ate_from_pairs
    from slam.outputs import aligned_rmse

    rng = np.random.default_rng(42)
    full = random_walk(rng, 120)
    est = perturbed(full, rng, pose([0.2, -0.1, 0.4], [1.0, -2.0, 0.5]), noise=0.01, drift=0.05, dt=0.004)
    kept = np.setdiff1d(np.arange(120), [5, 50, 51])  # three estimated frames without ground truth
    gt = Trajectory(full.timestamps[kept], full.poses[kept])
    reference = ate(gt, est, max_dt=MAX_DT_S)
    idx_gt, idx_est = associate(gt.timestamps, est.timestamps, MAX_DT_S)
    assert reference.num_pairs == len(idx_est) == 117

    R, t, _ = umeyama_alignment(est.positions[idx_est], gt.positions[idx_gt])
    before = np.linalg.norm(est.positions[idx_est] @ R.T + t - gt.positions[idx_gt], axis=1)
    assert reference.rmse == pytest.approx(float(np.sqrt((before ** 2).mean())), rel=1e-12)

    assert aligned_rmse(est.positions[idx_est], gt.positions[idx_gt]) == reference.rmse
    paired = ate_from_pairs(gt.positions[idx_gt], est.positions[idx_est])
    np.testing.assert_array_equal(paired.errors, reference.errors)
    np.testing.assert_array_equal(paired.T_gt_est, reference.T_gt_est)

    plot = compare(est, gt)
    assert plot.aligned and plot.rmse == pytest.approx(reference.rmse, rel=1e-12)
    np.testing.assert_array_equal(plot.errors[idx_est], reference.errors)
    assert np.isnan(plot.errors[[5, 50, 51]]).all()
    np.testing.assert_allclose(plot.estimated, est.positions @ R.T + t, atol=1e-12)

    # Too few or collinear pairs: no ATE, the same way everywhere.
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(DataError):
        ate_from_pairs(line, line + 1)
    assert aligned_rmse(line + 1, line) is None and aligned_rmse(line[:2], line[:2]) is None
    with pytest.raises(ValueError):
        ate_from_pairs(np.zeros((4, 3)), np.zeros((5, 3)))
