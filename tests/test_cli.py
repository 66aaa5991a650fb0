"""The core command line (slam.cli.main): run, render, eval-ate, and bad input.

One tiny single-process run per module; render and eval-ate use its outputs.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import slam.runtime as runtime
from slam.cli import main
from slam.data import open_sequence
from slam.eval.trajectory import Trajectory, read_tum, write_tum

SPEC = "synthetic:orbit?frames=100&width=80&height=60"
FRAMES = 6
# Overrides of the test preset: enough first-frame iterations for a surface, little else.
OVERRIDES = {"mapping": {"iterations": 1, "first_frame_iterations": 30},
             "tracking": {"iterations": 2},
             "mesh": {"resolution": 2, "update_every_keyframes": 100}}


@pytest.fixture(scope="module", autouse=True)
def single_thread():
    """One torch thread; run_slam would otherwise take every core of this loaded machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    patch = pytest.MonkeyPatch()
    patch.setattr(runtime, "process_threads", lambda device, processes: None)
    yield
    patch.undo()
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cli")
    cfg = root / "overrides.json"
    cfg.write_text(json.dumps(OVERRIDES))
    out = root / "out"
    code = main(["run", SPEC, "--out", str(out), "--preset", "test", "--max-frames", str(FRAMES),
                 "--config", str(cfg), "--single-process", "--quiet"])
    assert code == 0
    return out


def test_run_writes_outputs_with_the_overrides(run_dir, capsys):
    for name in ("trajectory.txt", "mesh.ply", "map.pt", "run.json"):
        assert (run_dir / name).is_file(), name
    info = json.loads((run_dir / "run.json").read_text())
    assert info["status"] == "finished" and info["frames"] == FRAMES
    assert info["config"]["preset"] == "test"
    assert info["config"]["mapping"]["first_frame_iterations"] == 30
    assert info["config"]["runtime"]["processes"] is False
    assert len(read_tum(run_dir / "trajectory.txt").timestamps) == FRAMES


def test_render_from_the_runs_map(run_dir, tmp_path):
    seq = open_sequence(SPEC, max_frames=1)
    first = read_tum(run_dir / "trajectory.txt").poses[0]  # the run's world is its first camera's frame
    pose = tmp_path / "pose.json"
    pose.write_text(json.dumps(first.tolist()))
    K = seq[0].K
    intr = f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]},80,60"
    image, depth = tmp_path / "view.png", tmp_path / "depth.png"
    assert main(["render", str(run_dir / "map.pt"), "--pose", str(pose), "--intrinsics", intr,
                 "--out", str(image), "--depth", str(depth)]) == 0
    rgb = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    d = cv2.imread(str(depth), cv2.IMREAD_UNCHANGED)
    assert rgb.shape == (60, 80, 3) and rgb.dtype == np.uint8
    assert d.shape == (60, 80) and d.dtype == np.uint16
    seen = d > 0
    assert seen.mean() > 0.5, "the first frame's view is mapped"
    # Rendered depth (mm) against the input depth of that frame: the map is coarse (3 frames,
    # few iterations) but must be in the right place.
    gt = seq[0].depth * 1000
    both = seen & (gt > 0)
    assert np.median(np.abs(d[both] - gt[both])) < 100
    # A pose as 16 whitespace-separated numbers works too.
    pose_txt = tmp_path / "pose.txt"
    pose_txt.write_text(" ".join(map(str, first.ravel())))
    assert main(["render", str(run_dir / "map.pt"), "--pose", str(pose_txt), "--intrinsics", intr,
                 "--out", str(tmp_path / "view2.png")]) == 0


def test_eval_ate_against_a_gt_file(run_dir, tmp_path, capsys):
    seq = open_sequence(SPEC, max_frames=FRAMES)
    gt = tmp_path / "gt.txt"
    write_tum(gt, Trajectory(np.array([f.timestamp for f in seq]), np.stack([f.T_world_cam for f in seq])))
    summary = tmp_path / "ate.json"
    capsys.readouterr()
    assert main(["eval-ate", str(gt), str(run_dir / "trajectory.txt"), "--json", str(summary)]) == 0
    assert "ATE" in capsys.readouterr().out
    result = json.loads(summary.read_text())
    assert result["num_pairs"] == FRAMES
    assert 0 <= result["rmse"] < 0.05, "6 frames about 1.3 cm apart: any sane tracker is within 5 cm"
    assert main(["eval-ate", str(gt), str(gt)]) == 0


@pytest.mark.parametrize("argv, where", [
    (["run", "/nonexistent/dataset", "--out", "{tmp}/o", "--preset", "test"], "/nonexistent/dataset"),
    (["run", "synthetic:nope", "--out", "{tmp}/o", "--preset", "test"], "nope"),
    (["run", SPEC, "--out", "{tmp}/o", "--preset", "test", "--config", "{tmp}/missing.json"], "missing.json"),
    (["render", "{tmp}/missing.pt", "--pose", "{tmp}/pose.txt", "--intrinsics", "1,1,1,1,8,8",
      "--out", "{tmp}/x.png"], "missing.pt"),
    (["eval-ate", "{tmp}/missing_gt.txt", "{tmp}/missing_est.txt"], "missing_gt.txt"),
])
def test_bad_input_exits_2_with_a_message(argv, where, tmp_path, capsys):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert where in err, err
    assert "Traceback" not in err


def test_bad_config_field_exits_2_naming_it(tmp_path, capsys):
    cfg = tmp_path / "bad.json"
    cfg.write_text(json.dumps({"mapping": {"iterationz": 3}}))
    assert main(["run", SPEC, "--out", str(tmp_path / "o"), "--preset", "test", "--config", str(cfg)]) == 2
    assert "mapping.iterationz" in capsys.readouterr().err


def test_bad_pose_file_exits_2(run_dir, tmp_path, capsys):
    pose = tmp_path / "pose.txt"
    pose.write_text("1 0 0 0 1")
    assert main(["render", str(run_dir / "map.pt"), "--pose", str(pose), "--intrinsics", "1,1,1,1,8,8",
                 "--out", str(tmp_path / "x.png")]) == 2
    assert "16 numbers" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [
    ["run", SPEC, "--out", "o", "--intrinsics", "1,2,3"],
    ["run", SPEC],  # --out is required
    ["render", "map.pt", "--pose", "p", "--intrinsics", "1,2,3,4", "--out", "x.png"],
    ["frobnicate"],
])
def test_argument_errors_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    assert capsys.readouterr().err


def test_render_takes_the_pose_inline_too(run_dir, tmp_path, capsys):
    """``--pose`` takes the 16 numbers themselves (commas or spaces) as well as a file; a run's
    summary counts in the singular where there is one."""
    seq = open_sequence(SPEC, max_frames=1)
    inline = ",".join(map(str, seq[0].T_world_cam.ravel()))
    K = seq[0].K
    intr = f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]},80,60"
    assert main(["render", str(run_dir / "map.pt"), "--pose", inline, "--intrinsics", intr,
                 "--out", str(tmp_path / "inline.png")]) == 0
    assert cv2.imread(str(tmp_path / "inline.png")).shape == (60, 80, 3)
    assert main(["render", str(run_dir / "map.pt"), "--pose", "1 0 0", "--intrinsics", intr,
                 "--out", str(tmp_path / "x.png")]) == 2
    assert "--pose: a pose needs 16 numbers" in capsys.readouterr().err


def test_counts_read_in_the_singular_for_one():
    from slam.cli import _count

    assert (_count(1, "map"), _count(2, "map"), _count(0, "loop")) == ("1 map", "2 maps", "0 loops")
