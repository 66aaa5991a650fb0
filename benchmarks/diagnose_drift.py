"""Where a trajectory drifts: the SLAM loop in one process, frame by frame, against GT.

Tracks each frame from the previous estimate against a snapshot of the map (as the tracking
process does), then maps it (as the mapping process does), deterministically and without
the final bundle adjustment, so that two configs compare frame for frame. Printed per
frame: the estimate's position error in the GT camera frame (x right, y down, z forward,
cm) and its rotation error; then the raw ATE, the median ratio of estimated to GT rotation
between consecutive frames (1 = no under-rotation), and the rotation from the first frame to
``--at`` against GT's.

    python benchmarks/diagnose_drift.py [PATH] [--frames 50] [--config F] [--every 5]

PATH defaults to TUM fr1/rpy in ../shared/data. The process-mode runtime (``voxfusion run``)
overlaps tracking and mapping, so its figures differ from these by the map's lag; use this
to find where and how error accrues, and ``bench_slam.py`` for the figures of record.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import pipeline_frame, require  # noqa: E402

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "rgbd_dataset_freiburg1_rpy"


def rotation_deg(R: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) in degrees of a (3, 3) rotation."""
    import torch

    from slam.geometry import so3_log

    return np.degrees(so3_log(torch.as_tensor(R, dtype=torch.float64)).numpy())


def rotation_ratio(estimate: np.ndarray, gt: np.ndarray, min_deg: float = 1.0) -> float:
    """Median over consecutive frames moving > min_deg of the estimated rotation projected on
    GT's, over GT's: (N, 4, 4) each."""
    ratios = []
    for k in range(1, len(gt)):
        g = rotation_deg((np.linalg.inv(gt[k - 1]) @ gt[k])[:3, :3])
        e = rotation_deg((np.linalg.inv(estimate[k - 1]) @ estimate[k])[:3, :3])
        if np.linalg.norm(g) > min_deg:
            ratios.append(float(e @ g / (g @ g)))
    return float(np.median(ratios)) if ratios else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("path", nargs="?", default=str(DEFAULT))
    parser.add_argument("--frames", type=int, default=50)
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--config", type=Path, default=None, help="JSON overrides of the preset")
    parser.add_argument("--every", type=int, default=5, help="print every k-th frame")
    parser.add_argument("--at", type=int, default=45, help="frame for the accumulated rotation")
    parser.add_argument("--optimize-every", type=int, default=1,
                        help="optimise after every k-th frame only (all are integrated), as the process-mode "
                             "mapper does when k - 1 frames queued up while it optimised")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--quick", action="store_true", help="smoke run: 8 frames")
    args = parser.parse_args()
    if args.optimize_every < 1:
        parser.error("--optimize-every must be at least 1")

    import torch

    from slam.config import apply_overrides, load_config
    from slam.data import open_sequence
    from slam.eval import Trajectory, ate
    from slam.features import FeatureOdometry
    from slam.frames import prepare_frame
    from slam.mapping import Mapper, TrackedFrame
    from slam.tracking import FrozenMap, Tracker

    torch.set_num_threads(args.threads)
    frames = 8 if args.quick else args.frames
    config = apply_overrides(load_config(args.preset, args.config), {"mapping": {"final_iterations": 0}})
    path = args.path if args.path.startswith("synthetic:") else str(require(Path(args.path)))
    sequence = open_sequence(path, max_frames=frames)
    device = torch.device("cpu")
    torch.manual_seed(config.runtime.seed)
    mapper = Mapper(config, device, seed=config.runtime.seed)
    tracker = Tracker(config, device, seed=config.runtime.seed)
    poses: list[torch.Tensor] = []
    gt = []
    started = time.perf_counter()
    print("| frame | position error x, y, z (cm, GT camera frame) | rotation error (deg) | keyframe |")
    print("| --- | --- | --- | --- |")
    features = FeatureOdometry.from_config(config)
    for i in range(len(sequence)):
        raw = sequence[i]
        frame = pipeline_frame(raw, config.runtime.input_width)
        if frame.T_world_cam is None:
            raise SystemExit(f"{path}: frame {i} has no ground-truth pose")
        tf = prepare_frame(frame, None, device, config.voxel.max_depth)
        matches = features.correspondences(raw) if features is not None else None
        if i == 0:
            T = torch.as_tensor(frame.T_world_cam, dtype=torch.float32)
            ok = True
        else:
            result = tracker.track(tf, FrozenMap(mapper.snapshot(), config, device), poses[-1], matches)
            T, ok = result.T_world_cam, result.ok
        if features is not None:
            features.remember(T.double().numpy() if ok else None)
        step = mapper.process(TrackedFrame(tf, T), optimize=(i == 0 or (i + 1) % args.optimize_every == 0))
        poses.append(T)
        gt.append(np.asarray(frame.T_world_cam, np.float64))
        error = np.linalg.inv(gt[-1]) @ T.double().numpy()
        if i % args.every == 0 or i == len(sequence) - 1:
            xyz = ", ".join(f"{v:+.1f}" for v in error[:3, 3] * 100)
            print(f"| {i} | {xyz} | {np.linalg.norm(rotation_deg(error[:3, :3])):.2f} | {'yes' if step.is_keyframe else ''} |")
    estimate = torch.stack(poses).double().numpy()
    gt_poses = np.stack(gt)
    stamps = np.arange(len(gt_poses), dtype=np.float64)
    raw_ate = ate(Trajectory(stamps, gt_poses), Trajectory(stamps, estimate)).rmse
    at = min(args.at, len(gt_poses) - 1)
    print()
    print(f"raw ATE (no final bundle adjustment): {raw_ate * 100:.2f} cm over {len(gt_poses)} frames")
    print(f"rotation ratio (median, frames moving > 1 deg): {rotation_ratio(estimate, gt_poses):.3f}")
    turned = rotation_deg((np.linalg.inv(estimate[0]) @ estimate[at])[:3, :3])
    truth = rotation_deg((np.linalg.inv(gt_poses[0]) @ gt_poses[at])[:3, :3])
    print(f"rotation 0 -> {at} (deg): estimate {np.round(turned, 1).tolist()}, GT {np.round(truth, 1).tolist()}")
    print(f"config overrides: {json.dumps(json.loads(args.config.read_text())) if args.config else '{}'}; "
          f"{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
