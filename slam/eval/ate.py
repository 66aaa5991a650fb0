"""Absolute trajectory error (ATE): associate by timestamp, align rigidly, measure translations.

Pure: arrays and ``Trajectory`` objects in, numbers out (files are read in ``trajectory.py``).
The numbers match ``evo_ape tum GT EST -a`` (translation part, SE(3) Umeyama alignment).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.data.frame import DataError
from slam.eval.trajectory import Trajectory, associate


@dataclass(frozen=True)
class ATEResult:
    """Statistics of the per-pose translation error, in metres.

    Attributes:
        rmse, mean, median, std, max, min: of the (num_pairs,) error norms; std is the
            population standard deviation.
        num_pairs: poses associated between the two trajectories.
        T_gt_est: (4, 4) float64 alignment applied to the estimate (identity without alignment).
        errors: (num_pairs,) float64 per-pair error norms, in ground-truth timestamp order.
    """

    rmse: float
    mean: float
    median: float
    std: float
    max: float
    min: float
    num_pairs: int
    T_gt_est: np.ndarray
    errors: np.ndarray


def umeyama_alignment(
    src: np.ndarray, dst: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity ``dst ~ s * R @ src + t`` (Umeyama, PAMI 1991).

    Args:
        src: (N, 3) points.
        dst: (N, 3) corresponding points.
        with_scale: estimate the scale ``s``; otherwise ``s = 1`` (rigid).
    Returns:
        R (3, 3) rotation with det +1, t (3,), s.
    Raises:
        DataError: the points are too few or collinear, so the rotation is not determined.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise ValueError(f"umeyama_alignment needs two (N, 3) arrays, got {src.shape} and {dst.shape}")
    mean_src, mean_dst = src.mean(0), dst.mean(0)
    src_c, dst_c = src - mean_src, dst - mean_dst
    covariance = dst_c.T @ src_c / len(src)
    U, singular, Vt = np.linalg.svd(covariance)
    # Rank 2 is enough (the third axis follows from the right-hand rule); below that the
    # rotation about the points' line is arbitrary.
    if len(src) < 3 or singular[1] <= 1e-12 * max(singular[0], 1e-300):
        raise DataError(
            f"cannot align trajectories: {len(src)} associated positions are too few or collinear"
        )
    # Flip the weakest axis if needed so R is a rotation, not a reflection.
    signs = np.array([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt)) or 1.0])
    R = U @ np.diag(signs) @ Vt
    scale = float(singular @ signs / (src_c**2).sum(1).mean()) if with_scale else 1.0
    t = mean_dst - scale * R @ mean_src
    return R, t, scale


def ate(gt: Trajectory, est: Trajectory, align: bool = True, max_dt: float = 0.02) -> ATEResult:
    """ATE of ``est`` against ``gt``.

    Poses are associated one-to-one by nearest timestamps within ``max_dt`` seconds; with
    ``align`` the estimate is moved by the rigid transform (rotation + translation, no scale)
    that best fits its positions onto the ground truth's, as for a SLAM run whose world frame
    is its first camera.

    Raises:
        DataError: no pairs within ``max_dt``, or too few/collinear positions to align.
    """
    idx_gt, idx_est = associate(gt.timestamps, est.timestamps, max_dt)
    if len(idx_gt) == 0:
        raise DataError(
            f"no associated poses: none of the {len(est)} estimated timestamps is within "
            f"{max_dt} s of the {len(gt)} ground-truth timestamps"
        )
    return ate_from_pairs(gt.positions[idx_gt], est.positions[idx_est], align)


def ate_from_pairs(gt_xyz: np.ndarray, est_xyz: np.ndarray, align: bool = True) -> ATEResult:
    """ATE of positions already paired: ``est_xyz[i]`` is the estimate of ``gt_xyz[i]``.

    The one place the aligned error is computed: ``ate`` (after association), a run's ATE
    (``slam.outputs.aligned_rmse``) and the page's error plot (``server.series.compare``) all
    come here. With ``align`` the estimate is moved by the rigid Umeyama fit (no scale)
    ``T_gt_est`` onto the ground truth first; ``errors[i] = |gt_xyz[i] - T_gt_est est_xyz[i]|``.

    Args:
        gt_xyz: (N, 3) ground-truth positions.
        est_xyz: (N, 3) estimated positions, in the same order.
    Raises:
        DataError: no pairs, or (with ``align``) fewer than 3 or collinear positions.
        ValueError: the arrays are not both (N, 3).
    """
    gt_xyz = np.asarray(gt_xyz, dtype=np.float64)
    est_xyz = np.asarray(est_xyz, dtype=np.float64)
    if gt_xyz.ndim != 2 or gt_xyz.shape[1] != 3 or gt_xyz.shape != est_xyz.shape:
        raise ValueError(f"ate_from_pairs needs two (N, 3) arrays, got {gt_xyz.shape} and {est_xyz.shape}")
    if len(gt_xyz) == 0:
        raise DataError("no position pairs to measure")
    T_gt_est = np.eye(4)
    if align:
        R, t, _ = umeyama_alignment(est_xyz, gt_xyz, with_scale=False)
        T_gt_est[:3, :3], T_gt_est[:3, 3] = R, t
    aligned = est_xyz @ T_gt_est[:3, :3].T + T_gt_est[:3, 3]
    errors = np.linalg.norm(gt_xyz - aligned, axis=1)
    return ATEResult(
        rmse=float(np.sqrt(np.mean(errors**2))),
        mean=float(errors.mean()),
        median=float(np.median(errors)),
        std=float(errors.std()),
        max=float(errors.max()),
        min=float(errors.min()),
        num_pairs=len(errors),
        T_gt_est=T_gt_est,
        errors=errors,
    )
