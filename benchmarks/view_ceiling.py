"""How far could a 3-D colour field take a run's training views? The ceiling of issue 43's figure.

    python benchmarks/view_ceiling.py RUN_DIR SEQUENCE [--iterations N] [--gt]

RUN_DIR is a ``voxfusion run --out`` folder (``map.pt``, ``trajectory.txt``) of the
``bench_real.py`` sequence named SEQUENCE. Its 12 training views (``view_quality.py``: every
k-th frame at its tracked pose, 320 wide) are scored, PSNR dB, on the pixels each view observed
*with measured depth* that the run's render reaches and whose measured point lies in an
allocated voxel (one mask per view for every row at the tracked poses), four ways:

* ``render``: the run's view, as ``view_quality.py`` scores it (on these pixels);
* ``keyframes @ depth``: a fresh fine colour level of the run's config fitted, at the
  *measured* depth, to the run's keyframes (``Mapper.fit_fine``), read at each view's measured
  depth: what perfect geometry would give the map the run kept;
* ``views @ depth``: the same fitted to the 12 views themselves: the best one colour field can
  do for these frames at these poses (the test frames are the training data);
* ``each view``: one fit per view, on that view alone: what the field can hold of one image.

``views @ depth`` far above ``render`` means the map loses it; ``each view`` far above
``views @ depth`` means the frames disagree with each other where they overlap (pose error,
motion blur, colour taken at another instant than depth), which no single 3-D field undoes.
``--gt`` repeats ``views @ depth`` at the ground-truth poses (rigidly aligned to the run's).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_real import sequences  # noqa: E402
from view_quality import observed_mask, psnr, tracked_views  # noqa: E402


@dataclass(frozen=True)
class FitFrame:
    """What ``Mapper.fit_fine`` reads of a keyframe: its pipeline frame and T_map_cam (4, 4)."""

    frame: object
    T_map_cam: torch.Tensor


def aligned_ground_truth(views, sequence, stamps: np.ndarray, run_poses: np.ndarray) -> list[np.ndarray]:
    """The views' ground-truth T_world_cam moved into the run's world by the rigid transform
    A = argmin sum ||A T_gt_i - T_run_i|| over every tracked frame (chordal mean of the
    rotations, then the mean translation): pure rotations (fr1/rpy) leave positions too close
    together for a point alignment."""
    gts, runs = [], []
    for T_run, t in run_poses:
        gt = sequence[int(np.argmin(np.abs(stamps - t)))].T_world_cam
        if gt is not None:
            gts.append(gt)
            runs.append(T_run)
    M = sum(r[:3, :3] @ g[:3, :3].T for r, g in zip(runs, gts))
    u, _, vt = np.linalg.svd(M)
    R = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    t = np.mean([r[:3, 3] - R @ g[:3, 3] for r, g in zip(runs, gts)], axis=0)
    A = np.eye(4)
    A[:3, :3], A[:3, 3] = R, t
    return [A @ sequence[int(np.argmin(np.abs(stamps - f.timestamp)))].T_world_cam for f, _ in views]


def measured_points(frame, T_map_cam: np.ndarray) -> torch.Tensor:
    """(H*W, 3) map-frame points of a frame's pixels at their measured depth (0 where none)."""
    h, w = frame.depth.shape
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    K = frame.K
    dirs = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    cam = (dirs * frame.depth[..., None]).reshape(-1, 3)
    return torch.from_numpy(cam @ T_map_cam[:3, :3].T + T_map_cam[:3, 3]).to(torch.float32)


def field_colour(submap, points: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Coarse point colour plus the fine level at (N, 3) map points -> (N, 3) colour in [0, 1]
    and (N,) bool: the point lies in an allocated voxel."""
    from slam.fine_color import coarse_point_color

    with torch.no_grad():
        coarse, inside = coarse_point_color(points, submap.view(), submap.decoder)
        return (coarse + submap.fine(points)).clamp(0, 1).numpy(), inside.numpy()


def fit(mapset, frames: list[FitFrame], iterations: int, seed: int) -> None:
    """A fresh fine level on the (single) submap, fitted at the measured depth of ``frames``."""
    import slam.mapping as mapping
    from slam.fine_color import FineColor

    submap = mapset.maps[0]
    submap.fine = FineColor(mapset.config.fine_color, seed=seed)
    keyframes = submap.keyframes
    submap.keyframes = frames
    try:
        mapper = mapping.Mapper(mapset.config, torch.device("cpu"), seed=seed)
        mapper.fit_fine(submap, iterations, len(frames))
    finally:
        submap.keyframes = keyframes


def main(argv: list[str] | None = None) -> int:
    from slam import load_checkpoint, read_tum
    from slam.data import open_sequence
    from slam.frames import prepare_frame
    from slam.views import render_view

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("sequence")
    parser.add_argument("--iterations", type=int, default=600)
    parser.add_argument("--gt", action="store_true", help="also fit the views at aligned ground-truth poses")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    seq = next(s for s in sequences(None) if s.name == args.sequence)
    sequence = open_sequence(seq.path, max_frames=seq.max_frames)
    stamps = np.asarray(sequence.timestamps, np.float64)
    views = tracked_views(args.run_dir, sequence)
    seen = observed_mask(sequence, views[0][0])
    mapset = load_checkpoint(args.run_dir / "map.pt")
    if len(mapset.maps) != 1 or mapset.maps[0].fine is None:
        parser.error("view_ceiling.py reads runs of one submap with a fine colour level")
    submap, config = mapset.maps[0], mapset.config
    T_map_world = np.linalg.inv(submap.T_world_map.to(torch.float64).numpy())

    def pipeline(index: int):
        return prepare_frame(sequence[index], config.runtime.input_width, torch.device("cpu"), config.voxel.max_depth)

    renders = [render_view(mapset, T, f.K, f.width, f.height) for f, T in views]
    targets = [f.rgb.astype(np.float32) for f, _ in views]
    tracked = [T for _, T in views]

    def scored(colours: list[np.ndarray], insides: list[np.ndarray]) -> list[float]:
        return [psnr(c.reshape(t.shape), t, m & i.reshape(m.shape)) for c, i, t, m in zip(colours, insides, targets, masks)]

    def read_at(poses: list[np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
        out = [field_colour(submap, measured_points(f, T_map_world @ T)) for (f, _), T in zip(views, poses)]
        return [c for c, _ in out], [i for _, i in out]

    _, insides = read_at(tracked)
    masks = [seen & (f.depth > 0) & r.valid & i.reshape(f.depth.shape) for (f, _), r, i in zip(views, renders, insides)]
    rows: dict[str, list[float]] = {}
    rows["render"] = [psnr(np.clip(r.rgb, 0, 1).astype(np.float32), t, m) for r, t, m in zip(renders, targets, masks)]
    view_frames = [pipeline(int(np.argmin(np.abs(stamps - f.timestamp)))) for f, _ in views]

    def as_fit(poses: list[np.ndarray]) -> list[FitFrame]:
        return [FitFrame(fr, torch.from_numpy(T_map_world @ T).to(torch.float32)) for fr, T in zip(view_frames, poses)]

    keyframes = [FitFrame(pipeline(int(np.argmin(np.abs(stamps - kf.timestamp)))), kf.T_map_cam.detach())
                 for kf in submap.keyframes]
    fit(mapset, keyframes, args.iterations, seed=1)
    rows["keyframes @ depth"] = scored(*read_at(tracked))
    fit(mapset, as_fit(tracked), args.iterations, seed=1)
    rows["views @ depth"] = scored(*read_at(tracked))
    if args.gt:
        run = read_tum(args.run_dir / "trajectory.txt")
        gt_poses = aligned_ground_truth(views, sequence, stamps, list(zip(run.poses, run.timestamps)))
        fit(mapset, as_fit(gt_poses), args.iterations, seed=1)
        rows["views @ depth, GT poses"] = scored(*read_at(gt_poses))
    each = []
    for k in range(len(views)):
        fit(mapset, as_fit(tracked)[k:k + 1], args.iterations, seed=1)
        colour, inside = field_colour(submap, measured_points(views[k][0], T_map_world @ tracked[k]))
        each.append(psnr(colour.reshape(targets[k].shape), targets[k], masks[k] & inside.reshape(masks[k].shape)))
    rows["each view"] = each
    for name, values in rows.items():
        print(f"{args.sequence} {args.run_dir.name} {name}: PSNR {np.mean(values):.2f} dB "
              f"(views {' '.join(f'{v:.1f}' for v in values)})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
