"""A finished run's frames tracked again against its final map, offline: ATE before and after
(how the final re-tracking, ``tracking.retrack_iterations``, was found and sized; decisions.md#tracking.retrack_iterations).

    python benchmarks/retrack_offline.py RUN_DIR DATASET [--max-frames N] [--iterations 2] [--rays 512]
        [--skip-keyframes]

RUN_DIR is a ``voxfusion run`` output folder (``map.pt``, ``trajectory.txt``, ``run.json``),
DATASET the sequence it ran on (with ``groundtruth.txt``). Every frame of the trajectory is
tracked by Levenberg-Marquardt (``iterations`` steps on ``rays`` pixels, no convergence stop)
against the map of ``map.pt``, from its pose in the trajectory; ``--skip-keyframes`` leaves
the keyframes at their bundle-adjusted poses. One process, one thread.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from slam import load_checkpoint, read_tum
from slam.data import open_sequence
from slam.eval import ate
from slam.eval.trajectory import Trajectory, associate
from slam.frames import prepare_frame
from slam.mapping import MapSnapshot
from slam.tracking import FrozenMap, Tracker

CPU = torch.device("cpu")


def frozen_maps(mapset) -> list[FrozenMap]:
    """The tracker's view of every submap of a loaded checkpoint."""
    out = []
    for sub in mapset.maps:
        v = sub.voxels
        snapshot = MapSnapshot(
            version=0, map_id=sub.map_id, T_world_map=sub.T_world_map.detach().numpy(), voxel_size=v.voxel_size,
            voxel_codes=v.voxel_codes.numpy(), voxel_corners=v.voxel_corners.numpy(),
            embeddings=v.embeddings.detach().numpy(),
            decoder_state={k: t.detach().numpy() for k, t in sub.decoder.state_dict().items()},
            corner_updates=sub.updates().numpy())
        out.append(FrozenMap(snapshot, mapset.config, CPU))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--iterations", type=int, default=2)
    parser.add_argument("--rays", type=int, default=512)
    parser.add_argument("--skip-keyframes", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(1)

    mapset = load_checkpoint(args.run / "map.pt")
    config = mapset.config
    fmaps = frozen_maps(mapset)
    tracking = replace(config.tracking, optimizer="gauss_newton", iterations=args.iterations,
                       num_rays=args.rays, convergence_tol=0.0)
    tracker = Tracker(replace(config, tracking=tracking), CPU)
    keyframes = {int(k) for k in json.loads((args.run / "run.json").read_text())["keyframe_poses"]}
    sequence = open_sequence(args.dataset, max_frames=args.max_frames)
    trajectory = read_tum(args.run / "trajectory.txt")
    estimate_idx, frame_idx = associate(trajectory.timestamps, np.asarray(sequence.timestamps, np.float64),
                                        max_dt=1e-3)
    poses = trajectory.poses.copy()
    t0 = time.perf_counter()
    for e, f in zip(estimate_idx, frame_idx):
        frame = sequence[int(f)]
        if args.skip_keyframes and frame.index in keyframes:
            continue
        prepared = prepare_frame(frame, config.runtime.input_width, CPU, config.voxel.max_depth)
        start = torch.as_tensor(trajectory.poses[e], dtype=torch.float32)
        results = [r for r in (tracker.track(prepared, fmap, start) for fmap in fmaps) if r.ok]
        if results:
            poses[e] = min(results, key=lambda r: r.loss).T_world_cam.double().numpy()
    seconds = time.perf_counter() - t0
    gt = read_tum(args.dataset / "groundtruth.txt")
    before = ate(gt, trajectory).rmse * 100
    after = ate(gt, Trajectory(trajectory.timestamps, poses)).rmse * 100
    print(f"{len(estimate_idx)} frames re-tracked in {seconds:.1f} s "
          f"({args.iterations} x {args.rays} pixels): ATE {before:.3f} -> {after:.3f} cm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
