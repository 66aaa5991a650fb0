"""How well a sequence's depth agrees with its own ground truth: the floor under any tracker.

Each depth frame ``a`` is back-projected (every ``--pixel-stride``-th valid pixel), moved into
frame ``a + gap`` with the ground-truth relative pose, projected, and compared with that
frame's depth at the nearest pixel. Pairs are split into slow and fast ones by GT's rotation
per frame. The relative rotation is also scaled by each ``--scales`` factor: if the depth
fits best at a factor below 1, the images themselves say the camera turned less than GT
says, and a tracker that follows the images under-rotates by that much.

    python benchmarks/depth_gt_consistency.py [PATH] [--frames 150] [--gap 3] [--first A --last B]

PATH defaults to TUM fr1/rpy in ../shared/data. Frames are read as the pipeline reads them
(``slam.data.open_sequence``: undistorted, full resolution; each frame takes the nearest
ground-truth pose). It needs no map: numpy, and slam.geometry for rotations.

For a TUM folder, ``--lag-ms`` and ``--regular-stamps`` test the sensor's timing instead:
ground truth is then interpolated (from ``groundtruth.txt``) at each frame's timestamp plus
the lag, or at timestamps refitted to a constant frame period (the Kinect captures at a
fixed rate; the driver's stamps jitter by a few milliseconds).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import frames_with_gt  # noqa: E402

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "rgbd_dataset_freiburg1_rpy"


def rotvec(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (3,) rotation vector in radians (``slam.geometry.so3_log``)."""
    import torch

    from slam.geometry import so3_log

    return so3_log(torch.as_tensor(R, dtype=torch.float64)).numpy()


def rotation(v: np.ndarray) -> np.ndarray:
    """(3,) rotation vector -> (3, 3) rotation (``slam.geometry.so3_exp``)."""
    import torch

    from slam.geometry import so3_exp

    return so3_exp(torch.as_tensor(v, dtype=torch.float64)).numpy()


def interpolated_poses(groundtruth: Path, stamps: np.ndarray) -> np.ndarray:
    """(N,) times -> (N, 4, 4) poses interpolated in ``groundtruth.txt`` (TUM rows): position
    linearly, rotation along the geodesic between the two neighbouring poses."""
    from slam.data.tum import read_tum_list
    from slam.geometry import pose_from_tum

    rows = read_tum_list(groundtruth, columns=7)
    times = np.array([t for t, _ in rows])
    poses = pose_from_tum(np.array([[float(v) for v in fields] for _, fields in rows]))
    if not (times[0] <= stamps.min() and stamps.max() <= times[-1]):
        raise SystemExit(f"{groundtruth}: the frames' times lie outside the ground truth's")
    after = np.clip(np.searchsorted(times, stamps), 1, len(times) - 1)
    out = np.empty((len(stamps), 4, 4))
    for n, (j, t) in enumerate(zip(after, stamps)):
        T0, T1 = poses[j - 1], poses[j]
        alpha = (t - times[j - 1]) / (times[j] - times[j - 1])
        out[n] = np.eye(4)
        out[n, :3, :3] = T0[:3, :3] @ rotation(alpha * rotvec(T0[:3, :3].T @ T1[:3, :3]))
        out[n, :3, 3] = (1 - alpha) * T0[:3, 3] + alpha * T1[:3, 3]
    return out


def depth_misfit(depth_a: np.ndarray, depth_b: np.ndarray, K: np.ndarray, T_b_a: np.ndarray,
                 stride: int, max_depth: float) -> np.ndarray:
    """|depth_b at the projection - the warped point's z| (M,) for pixels of a seen in b.

    depth_a, depth_b (H, W) metres (0 = none); K (3, 3); T_b_a (4, 4) maps camera a to b.
    """
    v, u = np.nonzero((depth_a > 0) & (depth_a < max_depth))
    v, u = v[::stride], u[::stride]
    z = depth_a[v, u]
    points = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], 1)
    q = points @ T_b_a[:3, :3].T + T_b_a[:3, 3]
    front = q[:, 2] > 0.1
    q = q[front]
    col = np.rint(K[0, 0] * q[:, 0] / q[:, 2] + K[0, 2]).astype(int)
    row = np.rint(K[1, 1] * q[:, 1] / q[:, 2] + K[1, 2]).astype(int)
    h, w = depth_b.shape
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    observed = depth_b[row[inside], col[inside]]
    valid = observed > 0
    return np.abs(observed[valid] - q[inside][valid, 2])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("path", nargs="?", default=str(DEFAULT))
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--gap", type=int, default=3, help="frames between the two depth maps of a pair")
    parser.add_argument("--fast-deg", type=float, default=2.0,
                        help="a pair is fast when GT turns more than this per frame (degrees)")
    parser.add_argument("--scales", default="0.85,0.9,0.95,1.0,1.05",
                        help="factors on GT's relative rotation")
    parser.add_argument("--first", type=int, default=0, help="first frame of a pair's start frames")
    parser.add_argument("--last", type=int, default=None, help="last frame of a pair's start frames")
    parser.add_argument("--lag-ms", type=float, default=None,
                        help="TUM: interpolate ground truth at each frame's time plus this (ms)")
    parser.add_argument("--regular-stamps", action="store_true",
                        help="TUM: interpolate ground truth at times refitted to a constant frame period")
    parser.add_argument("--pixel-stride", type=int, default=5)
    parser.add_argument("--max-depth", type=float, default=3.0)
    parser.add_argument("--quick", action="store_true", help="smoke run: 12 frames, two scales")
    args = parser.parse_args()
    if args.gap < 1:
        parser.error("--gap must be at least 1")

    started = time.perf_counter()
    frames = 12 if args.quick else args.frames
    scales = [1.0, 0.95] if args.quick else [float(s) for s in args.scales.split(",")]
    loaded = frames_with_gt(args.path, frames, "depth_gt_consistency.py")
    gt_poses = np.stack([f.T_world_cam for f in loaded])
    timing = "nearest ground-truth pose to each frame's stamp"
    if args.lag_ms is not None or args.regular_stamps:
        groundtruth = Path(args.path) / "groundtruth.txt"
        if not groundtruth.is_file():
            raise SystemExit(f"--lag-ms / --regular-stamps need a TUM folder with groundtruth.txt: {groundtruth}")
        stamps = np.array([f.timestamp for f in loaded])
        where = "the stamps"
        if args.regular_stamps:
            index = np.arange(len(stamps))
            fit = np.polyfit(index, stamps, 1)
            jitter_ms = np.std(stamps - np.polyval(fit, index)) * 1000
            stamps = np.polyval(fit, index)
            where = f"refitted stamps (period {fit[0] * 1000:.2f} ms, stamp jitter {jitter_ms:.1f} ms rms)"
        lag_ms = args.lag_ms or 0.0
        gt_poses = interpolated_poses(groundtruth, stamps + lag_ms / 1000)
        timing = f"ground truth interpolated at {where} {lag_ms:+.0f} ms"
    misfits: dict[tuple[str, float], list[np.ndarray]] = {}
    pairs = {"slow": 0, "fast": 0}
    last = len(loaded) - args.gap - 1 if args.last is None else min(args.last, len(loaded) - args.gap - 1)
    for a in range(args.first, last + 1):
        fa, fb = loaded[a], loaded[a + args.gap]
        T_b_a = np.linalg.inv(gt_poses[a + args.gap]) @ gt_poses[a]
        turned = rotvec(T_b_a[:3, :3])
        kind = "fast" if np.degrees(np.linalg.norm(turned)) / args.gap > args.fast_deg else "slow"
        pairs[kind] += 1
        for k in scales:
            T = T_b_a.copy()
            T[:3, :3] = rotation(turned * k)
            misfits.setdefault((kind, k), []).append(
                depth_misfit(fa.depth, fb.depth, fa.K, T, args.pixel_stride, args.max_depth))
    print(f"# Depth against ground truth: {Path(args.path).name}, pairs ({args.first}..{last}, +{args.gap})\n")
    print(f"timing: {timing}\n")
    print(f"slow pairs: {pairs['slow']}, fast pairs (GT > {args.fast_deg:g} deg per frame): {pairs['fast']}\n")
    print("| GT rotation x | slow: median misfit (mm) | slow: within 1 cm | fast: median misfit (mm) | fast: within 1 cm |")
    print("| --- | --- | --- | --- | --- |")
    for k in scales:
        cells = []
        for kind in ("slow", "fast"):
            residual = np.concatenate(misfits.get((kind, k), [np.zeros(0)]))
            cells += (["-", "-"] if residual.size == 0 else
                      [f"{np.median(residual) * 1000:.1f}", f"{(residual < 0.01).mean():.0%}"])
        print(f"| {k:g} | " + " | ".join(cells) + " |")
    print(f"\n{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
