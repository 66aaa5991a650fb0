"""Frame-to-frame odometry without any map: which image cue a sequence's motion agrees with.

Chains the relative pose of each consecutive frame pair from the first frame's GT pose and
reports ATE RMSE (cm) over the whole run and over a segment (default: fr1/rpy's fast yaw
sweep, frames 36-60), for three estimators:

* ``orb-pnp``: ``slam.features.FeatureOdometry``, the tracker's own sparse term (ORB matches,
  RANSAC PnP with the previous frame's depth), alone;
* ``open3d-color``: Open3D's photometric RGB-D odometry (``RGBDOdometryJacobianFromColorTerm``);
* ``open3d-hybrid``: Open3D's photometric + geometric odometry (``...FromHybridTerm``).

Run it to see whether depth or the image leads a tracker astray on a sequence: on fr1/rpy the
depth-led estimator is far off while the two image-led ones stay near 4-5 cm with no map at
all. Open3D is a benchmark-only extra (``bash scripts/bench-deps.sh``); without it only
``orb-pnp`` runs.

    python benchmarks/odometry_baselines.py [PATH] [--frames 150] [--segment 36,60] [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import TUM_RPY, frames_with_gt  # noqa: E402


def chain_orb_pnp(frames: list, count: int = 1000) -> np.ndarray:
    """(N, 4, 4) poses chained from PnP on ORB matches (the previous frame's depth)."""
    from slam.features import FeatureOdometry

    odometry = FeatureOdometry(count, max_depth=10.0, reprojection_px=2.0, min_inliers=20)
    poses = [np.asarray(frames[0].T_world_cam, np.float64)]
    odometry.correspondences(frames[0])
    odometry.remember(poses[0])
    for frame in frames[1:]:
        matches = odometry.correspondences(frame)
        # No matches: keep the last pose (zero motion), as a tracker without a map would.
        poses.append(matches.T_world_cam_pnp if matches is not None else poses[-1])
        odometry.remember(poses[-1])
    return np.stack(poses)


def chain_open3d(frames: list, term: str) -> np.ndarray:
    """(N, 4, 4) poses chained from Open3D's RGB-D odometry with the ``color`` or ``hybrid`` term."""
    from peer_open3d import import_open3d

    o3d = import_open3d()
    K = frames[0].K
    intrinsic = o3d.camera.PinholeCameraIntrinsic(frames[0].width, frames[0].height, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    jacobian = {"color": o3d.pipelines.odometry.RGBDOdometryJacobianFromColorTerm,
                "hybrid": o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm}[term]()

    def rgbd(frame):
        color = o3d.geometry.Image((np.clip(frame.rgb, 0, 1) * 255).astype(np.uint8))
        depth = o3d.geometry.Image((frame.depth * 1000).astype(np.uint16))
        return o3d.geometry.RGBDImage.create_from_color_and_depth(color, depth, depth_scale=1000.0, depth_trunc=4.0)

    images = [rgbd(f) for f in frames]
    poses = [np.asarray(frames[0].T_world_cam, np.float64)]
    option = o3d.pipelines.odometry.OdometryOption()
    for a in range(len(frames) - 1):
        # source = the new frame, target = the previous one: the result is T_prev_new.
        ok, T_prev_new, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
            images[a + 1], images[a], intrinsic, np.eye(4), jacobian, option)
        poses.append(poses[-1] @ (T_prev_new if ok else np.eye(4)))
    return np.stack(poses)


def errors_cm(estimate: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-frame position errors (N,) in cm after a rigid (Umeyama, no scale) alignment."""
    from slam.eval.ate import umeyama_alignment

    R, t, _ = umeyama_alignment(estimate[:, :3, 3], gt[:, :3, 3])
    return np.linalg.norm(estimate[:, :3, 3] @ R.T + t - gt[:, :3, 3], axis=1) * 100


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("path", nargs="?", default=str(TUM_RPY))
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--segment", default="36,60", help="first,last frame of the segment reported apart")
    parser.add_argument("--quick", action="store_true", help="smoke run: 12 frames, orb-pnp only")
    args = parser.parse_args()
    first, last = (int(v) for v in args.segment.split(","))

    started = time.perf_counter()
    frames = frames_with_gt(args.path, 12 if args.quick else args.frames, "odometry_baselines.py")
    gt = np.stack([f.T_world_cam for f in frames])
    estimators = {"orb-pnp": chain_orb_pnp}
    if not args.quick:
        estimators |= {"open3d-color": lambda f: chain_open3d(f, "color"),
                       "open3d-hybrid": lambda f: chain_open3d(f, "hybrid")}
    print(f"# Frame-to-frame odometry, no map: {Path(args.path).name}, {len(frames)} frames\n")
    print(f"| estimator | ATE RMSE (cm) | mean error, frames {first}-{last} (cm) | mean error, other frames (cm) | s |")
    print("| --- | --- | --- | --- | --- |")
    inside = (np.arange(len(frames)) >= first) & (np.arange(len(frames)) <= last)
    for name, chain in estimators.items():
        t0 = time.perf_counter()
        try:
            estimate = chain(frames)
        except Exception as err:  # noqa: BLE001 - Open3D missing: report, keep the other rows
            print(f"| {name} | - | - | - | {err} |")
            continue
        e = errors_cm(estimate, gt)
        seg = f"{e[inside].mean():.1f}" if inside.any() else "-"
        rest = f"{e[~inside].mean():.1f}" if (~inside).any() else "-"
        print(f"| {name} | {np.sqrt((e ** 2).mean()):.2f} | {seg} | {rest} | {time.perf_counter() - t0:.0f} |")
    print(f"\n{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
