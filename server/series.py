"""The numbers behind the page's plots: a session's estimated trajectory against the input's
ground truth (aligned as the ATE aligns them), the error of every frame, and frames/s over
the tracking phase.

The ground truth is read from the session's input (a synthetic scene's generated path, a
dataset's ``groundtruth.txt`` / pose files) with the options the worker opened it with, so
its timestamps are the ones the runtime reports; estimate and ground truth are associated by
timestamp and rigidly aligned (Umeyama, no scale) by ``slam.eval.ate.ate_from_pairs``, as the
ATE is.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from server.tracks import FrameCamera
from server.worker import SourceSpec, open_source
from slam import DataError, Trajectory, associate, ate_from_pairs

MAX_DT_S = 0.02
"""Largest timestamp difference of an estimate-ground truth pair (as ``voxfusion eval-ate``)."""
DECIMALS = 4
"""Rounding of positions and errors in the JSON (0.1 mm)."""


@lru_cache(maxsize=16)
def source_camera(spec: SourceSpec) -> FrameCamera | None:
    """The input camera of a synthetic or dataset source (its first frame's intrinsics and
    size), or None (a stream, an unreadable input). Cached as ``ground_truth``."""
    if spec.kind not in ("synthetic", "dataset") or not spec.path:
        return None
    try:
        frame = open_source(spec)[0]
    except (DataError, OSError, IndexError):
        return None
    return FrameCamera(np.asarray(frame.K, np.float64), frame.width, frame.height)


@lru_cache(maxsize=16)
def ground_truth(spec: SourceSpec) -> Trajectory | None:
    """The ground-truth trajectory of one source, or None (a stream, an input without poses).
    Cached: a page polls it while the session runs, and inputs do not change."""
    if spec.kind not in ("synthetic", "dataset") or not spec.path:
        return None
    try:
        sequence = open_source(spec)
        if spec.kind == "synthetic":
            from slam.data.synthetic import FPS

            return Trajectory(sequence.frame_numbers / FPS, sequence.trajectory)
    except (DataError, OSError):
        return None
    pairs = [(t, T) for t, T in zip(sequence.timestamps, sequence.gt_poses) if T is not None]
    if not pairs:
        return None
    return Trajectory(np.array([t for t, _ in pairs]), np.stack([T for _, T in pairs]))


@dataclass(frozen=True)
class TrajectoryComparison:
    """An estimate placed onto the ground truth.

    Attributes:
        estimated: (N, 3) camera centres, in the ground truth's frame when ``aligned``.
        errors: (N,) metres per estimated frame; NaN for a frame without a ground-truth pair.
        aligned: whether at least 3 non-collinear pairs fixed the alignment.
    """

    estimated: np.ndarray
    errors: np.ndarray
    aligned: bool

    @property
    def rmse(self) -> float | None:
        valid = self.errors[np.isfinite(self.errors)]
        return float(np.sqrt(np.mean(valid ** 2))) if self.aligned and len(valid) else None


def compare(estimate: Trajectory, truth: Trajectory | None) -> TrajectoryComparison:
    """Align ``estimate`` onto ``truth`` by its timestamp pairs; unaligned without enough pairs."""
    positions = estimate.positions
    unaligned = TrajectoryComparison(positions, np.full(len(positions), np.nan), False)
    if truth is None or len(estimate) < 3:
        return unaligned
    idx_gt, idx_est = associate(truth.timestamps, estimate.timestamps, MAX_DT_S)
    if len(idx_est) < 3:
        return unaligned
    try:
        paired = ate_from_pairs(truth.positions[idx_gt], positions[idx_est])
    except DataError:  # collinear: the rotation about the line is not determined
        return unaligned
    T_gt_est = paired.T_gt_est
    errors = np.full(len(positions), np.nan)
    errors[idx_est] = paired.errors
    return TrajectoryComparison(positions @ T_gt_est[:3, :3].T + T_gt_est[:3, 3], errors, True)


def rounded(values: np.ndarray) -> list:
    """Nested lists of rounded floats, NaN as None (JSON has no NaN)."""
    array = np.round(np.asarray(values, dtype=np.float64), DECIMALS)
    if array.ndim > 1:
        return [rounded(row) for row in array]
    return [float(v) if np.isfinite(v) else None for v in array]
