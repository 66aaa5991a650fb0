"""The depth-against-ground-truth check of benchmarks/depth_gt_consistency.py: its warp and its
ground-truth interpolation on cases with known answers."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from depth_gt_consistency import depth_misfit, interpolated_poses, rotation, rotvec  # noqa: E402

K = np.array([[100.0, 0.0, 32.0], [0.0, 100.0, 24.0], [0.0, 0.0, 1.0]])


def test_a_plane_warped_with_its_true_motion_fits_and_a_wrong_motion_does_not():
    plane = np.full((48, 64), 2.0)
    moved = np.full((48, 64), 1.9)  # the camera stepped 10 cm towards the wall
    forward = np.eye(4)
    forward[2, 3] = -0.1  # camera b = camera a 10 cm forward: z_b = z_a - 0.1
    assert np.median(depth_misfit(plane, moved, K, forward, 1, 5.0)) == pytest.approx(0.0, abs=1e-9)
    assert np.median(depth_misfit(plane, moved, K, np.eye(4), 1, 5.0)) == pytest.approx(0.1)


def test_pixels_without_depth_or_beyond_the_cut_are_left_out():
    depth = np.full((48, 64), 2.0)
    depth[:, :32] = 0.0
    assert depth_misfit(depth, depth, K, np.eye(4), 1, 5.0).size == 48 * 32
    assert depth_misfit(depth, depth, K, np.eye(4), 1, 1.5).size == 0


def test_rotation_vector_round_trip():
    v = np.array([0.1, -0.4, 0.25])
    assert np.allclose(rotvec(rotation(v)), v)
    assert np.allclose(rotation(np.zeros(3)), np.eye(3))


def test_ground_truth_interpolates_halfway_between_its_rows(tmp_path):
    # Two poses 0.1 s apart: at rest, and 1 m along x turned 0.2 rad about z.
    rows = ["# timestamp tx ty tz qx qy qz qw", "10.0 0 0 0 0 0 0 1",
            f"10.1 1 0 0 0 0 {np.sin(0.1):.12f} {np.cos(0.1):.12f}"]
    (tmp_path / "groundtruth.txt").write_text("\n".join(rows) + "\n")
    T = interpolated_poses(tmp_path / "groundtruth.txt", np.array([10.05]))[0]
    assert np.allclose(T[:3, 3], [0.5, 0.0, 0.0])
    assert np.allclose(rotvec(T[:3, :3]), [0.0, 0.0, 0.1])
    with pytest.raises(SystemExit, match="outside"):
        interpolated_poses(tmp_path / "groundtruth.txt", np.array([11.0]))
