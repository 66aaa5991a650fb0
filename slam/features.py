"""Sparse visual correspondences for tracking: ORB features matched frame to frame.

Why the tracker needs them. The paper tracks with its rendering losses alone, and on scenes
dominated by large smooth surfaces those are led by depth: a wall or a desk constrains the
pose only along its normal, and the map's colour (embeddings at 0.2 m voxel corners) is too
smooth to pin the rest. On TUM fr1/rpy's fast yaw sweep the depth frames themselves
disagree with the motion-capture poses (they fit best with about 0.9 of GT's rotation
between frames, and Open3D's point-to-plane ICP between two depth frames, started at GT's
motion, settles 13 % short), so a depth-led tracker under-rotates and trades the missing
rotation for sideways translation. Sharp image corners do not: chaining frame-to-frame PnP
on ORB matches (no map at all) turns 61.7 deg where GT turns 62.1 deg over the sweep.
(``benchmarks/README.md``, "Where fr1/rpy drifts", has the measurements.)

So each frame's ORB features are matched to the previous tracked frame's, whose depth and
estimated pose place them in the world; their reprojection error in the new image is added
to the tracking loss (``reprojection_terms``, a robust Huber cost in milliradians), and a RANSAC
PnP on the same matches gives the initial pose. The dense loss still decides wherever the
features are few or wrong, and the map keeps the estimate from drifting as a chain of
frame-to-frame motions would.

Pure functions on arrays and tensors; ``FeatureOdometry`` keeps the previous frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from .config import SLAMConfig
from .data.frame import Frame


@dataclass(frozen=True)
class FrameFeatures:
    """ORB features of one frame with usable depth.

    pixels (N, 2) float64 (u, v), descriptors (N, 32) uint8, points_cam (N, 3) float64:
    each feature back-projected with its depth in the camera frame; sigmas (N,) float64: the
    scale of the pyramid level it was found on (1 at full resolution), which its position
    error grows with.
    """

    pixels: np.ndarray
    descriptors: np.ndarray
    points_cam: np.ndarray
    sigmas: np.ndarray


@dataclass(frozen=True)
class Correspondences:
    """Matches of a new frame against 3-D points of the previous one.

    points_world (M, 3) float64, pixels (M, 2) float64 in the new frame's image with
    intrinsics K (3, 3) float64; sigmas (M,) float64: each match's expected pixel error (the
    RMS of its two features' pyramid scales); T_world_cam_pnp (4, 4) float64: the RANSAC PnP
    pose of the new frame from the M inliers (the tracker's initial guess).
    """

    points_world: np.ndarray
    pixels: np.ndarray
    K: np.ndarray
    sigmas: np.ndarray
    T_world_cam_pnp: np.ndarray


def gray_u8(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 in [0, 1] (or uint8) -> (H, W) uint8 gray."""
    img = rgb if rgb.dtype == np.uint8 else (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)


def stable_depth(depth: np.ndarray, pixels: np.ndarray, max_relative_range: float) -> np.ndarray:
    """Depth (N,) at pixels (N, 2) of depth (H, W), 0 where unusable.

    A keypoint on a depth edge (ORB likes the corners of objects) would take the depth of the
    foreground or of the background by a pixel's chance, so a pixel whose 3x3 neighbourhood
    spans more than ``max_relative_range`` of its depth, or holds a hole, gets none.
    """
    h, w = depth.shape
    u = np.clip(np.round(pixels[:, 0]).astype(np.int64), 1, w - 2)
    v = np.clip(np.round(pixels[:, 1]).astype(np.int64), 1, h - 2)
    patches = np.stack([depth[v + dv, u + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], axis=1)
    z = depth[v, u].astype(np.float64)
    lo, hi = patches.min(1), patches.max(1)
    ok = (lo > 0) & (hi - lo <= max_relative_range * z)
    return np.where(ok, z, 0.0)


def detect_features(frame: Frame, count: int, max_depth: float, detector: cv2.ORB | None = None) -> FrameFeatures:
    """ORB keypoints of ``frame`` that have stable depth below ``max_depth``."""
    orb = detector if detector is not None else cv2.ORB_create(count)
    keypoints, descriptors = orb.detectAndCompute(gray_u8(frame.rgb), None)
    if descriptors is None or not keypoints:
        return FrameFeatures(np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros((0, 3)), np.zeros(0))
    pixels = np.array([kp.pt for kp in keypoints], np.float64)
    sigmas = orb.getScaleFactor() ** np.array([kp.octave for kp in keypoints], np.float64)
    z = stable_depth(frame.depth, pixels, max_relative_range=0.03)
    keep = (z > 0) & (z < max_depth)
    K = np.asarray(frame.K, np.float64)
    p, z = pixels[keep], z[keep]
    points = np.stack([(p[:, 0] - K[0, 2]) / K[0, 0] * z, (p[:, 1] - K[1, 2]) / K[1, 1] * z, z], axis=1)
    return FrameFeatures(p, descriptors[keep], points, sigmas[keep])


def match_features(a: FrameFeatures, b: FrameFeatures) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours by Hamming distance: indices (M,) into a and (M,) into b."""
    if len(a.descriptors) == 0 or len(b.descriptors) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(a.descriptors, b.descriptors)
    ia = np.array([m.queryIdx for m in matches], np.int64)
    ib = np.array([m.trainIdx for m in matches], np.int64)
    return ia, ib


def pnp_ransac(points_world: np.ndarray, pixels: np.ndarray, K: np.ndarray, reprojection_px: float,
               min_inliers: int) -> tuple[np.ndarray, np.ndarray] | None:
    """T_world_cam (4, 4) and inlier mask (M,) from 3-D points (M, 3) seen at pixels (M, 2),
    or None when fewer than ``min_inliers`` agree (RANSAC over EPnP, then Levenberg-Marquardt
    on the inliers)."""
    if len(points_world) < max(min_inliers, 6):
        return None
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        points_world, pixels, K, None, iterationsCount=200, reprojectionError=reprojection_px,
        confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    if not ok or inliers is None or len(inliers) < min_inliers:
        return None
    idx = inliers[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(points_world[idx], pixels[idx], K, None, rvec, tvec)
    T_cam_world = np.eye(4)
    T_cam_world[:3, :3] = cv2.Rodrigues(rvec)[0]
    T_cam_world[:3, 3] = tvec[:, 0]
    mask = np.zeros(len(points_world), bool)
    mask[idx] = True
    return np.linalg.inv(T_cam_world), mask


def project(T_map_cam: torch.Tensor, points_map: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels (M, 2) and camera-frame points (M, 3) of map points (M, 3) seen from T_map_cam."""
    R, t = T_map_cam[:3, :3], T_map_cam[:3, 3]
    x = (points_map - t) @ R  # R^T (X - t)
    z = x[:, 2].clamp(min=1e-6)
    uv = torch.stack([K[0, 0] * x[:, 0] / z + K[0, 2], K[1, 1] * x[:, 1] / z + K[1, 2]], -1)
    return uv, x


def huber(e: torch.Tensor, delta: float) -> torch.Tensor:
    """Huber cost (M,) of error norms (M,): e^2 inside delta, 2 delta e - delta^2 outside."""
    return torch.where(e <= delta, e * e, 2.0 * delta * e - delta * delta)


def _angular_scale(K: torch.Tensor) -> torch.Tensor:
    """(2,) factors from pixels to milliradians (1000 / focal length) of each image axis."""
    return 1000.0 / torch.stack([K[0, 0], K[1, 1]])


def huber_threshold(K: np.ndarray, huber_px: float) -> float:
    """The Huber threshold in milliradians of ``huber_px`` pixels for intrinsics K (3, 3) held
    on the host (``reprojection_cost``'s ``delta``, without reading K from the device)."""
    K = np.asarray(K, np.float64)
    return float(huber_px * np.mean([1000.0 / K[0, 0], 1000.0 / K[1, 1]]))


def reprojection_cost(T_map_cam: torch.Tensor, points_map: torch.Tensor, pixels: torch.Tensor,
                      sigmas: torch.Tensor, K: torch.Tensor, weight: float, huber_px: float,
                      delta: float | None = None) -> torch.Tensor:
    """``weight`` times the summed Huber cost of the reprojection errors of map points (M, 3)
    observed at pixels (M, 2), each divided by its expected error sigmas (M,); differentiable in T_map_cam (the Adam tracker's term and the
    reference of ``reprojection_terms``). A sum, not a mean: each match is an observation, and
    forty matches on a poorly textured image should say less than four hundred.

    Errors are measured in milliradians (pixels * 1000 / focal length), so that one weight
    means the same for a 320- and a 1280-pixel-wide camera; the Huber threshold is given in
    pixels, where detection noise lives.
    """
    scale = _angular_scale(K)
    uv, _ = project(T_map_cam, points_map, K)
    e = ((uv - pixels) * scale / sigmas[:, None]).norm(dim=-1)
    if delta is None:
        delta = huber_px * float(scale.mean())
    return weight * huber(e, delta).sum()


def reprojection_terms(T_map_cam: torch.Tensor, points_map: torch.Tensor, pixels: torch.Tensor,
                       sigmas: torch.Tensor, K: torch.Tensor, weight: float, huber_px: float,
                       delta: float | None = None,
                       tensor_cost: bool = False) -> tuple[float | torch.Tensor, torch.Tensor, torch.Tensor]:
    """``reprojection_cost`` and its Gauss-Newton model (H (6, 6), g (6,)) for the twist
    ``xi = (rho, phi)`` of ``T_map_cam exp(xi)``, in ``slam.gauss_newton``'s convention
    (the cost is ``sum omega r^2`` near the current pose, H = sum omega J^T J, g = sum omega J^T r).

    A camera-frame point moves as ``x' = exp(-xi) x ~ x - rho + [x]_x phi``; the Huber cost is
    handled by iteratively reweighted least squares (omega falls as delta / e outside delta).
    ``delta``: the Huber threshold in milliradians (``huber_threshold``; None: from K, read
    from the device); ``tensor_cost``: the cost as a 0-dim float64 tensor instead of a float
    (nothing read back from the device).
    """
    scale = _angular_scale(K)
    if delta is None:
        delta = huber_px * float(scale.mean())
    uv, x = project(T_map_cam, points_map, K)
    r = (uv - pixels) * scale / sigmas[:, None]  # (M, 2) milliradians per unit of sigma
    e = r.norm(dim=-1)
    omega = weight * torch.clamp(delta / e.clamp(min=1e-12), max=1.0)
    X, Y, Z = x[:, 0], x[:, 1], x[:, 2].clamp(min=1e-6)
    zeros = torch.zeros_like(X)
    # d(r_u, r_v)/dx (M, 2, 3): 1000 * d(x/z, y/z)/dx
    d_r = 1000.0 * torch.stack([torch.stack([1.0 / Z, zeros, -X / Z ** 2], -1),
                                torch.stack([zeros, 1.0 / Z, -Y / Z ** 2], -1)], 1)
    eye = torch.eye(3, dtype=x.dtype, device=x.device).expand(x.shape[0], 3, 3)
    skew_x = torch.zeros_like(eye)
    skew_x[:, 0, 1], skew_x[:, 0, 2] = -x[:, 2], x[:, 1]
    skew_x[:, 1, 0], skew_x[:, 1, 2] = x[:, 2], -x[:, 0]
    skew_x[:, 2, 0], skew_x[:, 2, 1] = -x[:, 1], x[:, 0]
    d_x = torch.cat([-eye, skew_x], -1)  # (M, 3, 6)
    J = d_r @ d_x / sigmas[:, None, None]  # (M, 2, 6)
    Jw = J * omega[:, None, None]
    H = torch.einsum("mki,mkj->ij", Jw, J)
    g = torch.einsum("mki,mk->i", Jw, r)
    cost = (weight * huber(e, delta).sum()).to(torch.float64)
    return (cost if tensor_cost else float(cost)), H, g


LOOP_FEATURE_COUNT = 1000
"""The fewest ORB features the loop closer's appearance check detects per keyframe."""


def loop_feature_count(config: SLAMConfig) -> int:
    """ORB features per keyframe for the loop closer's appearance check (and its verification
    detector's maximum): the tracker's count, at least ``LOOP_FEATURE_COUNT``."""
    return max(config.tracking.feature_count, LOOP_FEATURE_COUNT)


def tracking_features_serve_loops(config: SLAMConfig) -> bool:
    """Whether the tracker's ORB detector (``FeatureOdometry``) is the loop closer's
    appearance-check detector (default ORB parameters, the same count and depth limit): then,
    on the same image, the features the tracker detected are the ones the loop closer would
    detect, and they are sent along with the frame (``slam.messages.FrameMessage.features``)."""
    count = config.tracking.feature_count
    return count > 0 and count == loop_feature_count(config)


class FeatureOdometry:
    """The previous tracked frame's features, and the correspondences of each new frame.

    ``correspondences(frame)`` detects the new frame's features and matches them to the
    previous frame's; ``remember(T_world_cam)`` then keeps them with the frame's final pose
    (only a frame tracked well should be remembered: points placed with a failed pose would
    pull the next one off too).
    """

    def __init__(self, count: int, max_depth: float, reprojection_px: float, min_inliers: int):
        self.count = count
        self.max_depth = max_depth
        self.reprojection_px = reprojection_px
        self.min_inliers = min_inliers
        self._orb = cv2.ORB_create(count)
        self._previous: tuple[FrameFeatures, np.ndarray] | None = None
        self._current: FrameFeatures | None = None

    @staticmethod
    def from_config(config: SLAMConfig) -> "FeatureOdometry | None":
        """The tracker's feature odometry as ``config.tracking`` sets it (None when off)."""
        c = config.tracking
        if c.feature_count <= 0:
            return None
        return FeatureOdometry(c.feature_count, config.voxel.max_depth, c.feature_ransac_px, c.feature_min_inliers)

    def correspondences(self, frame: Frame) -> Correspondences | None:
        """Inlier matches of ``frame`` against the remembered frame, or None (first frame,
        too few matches)."""
        self._current = detect_features(frame, self.count, self.max_depth, self._orb)
        if self._previous is None:
            return None
        previous, T_world_prev = self._previous
        ia, ib = match_features(previous, self._current)
        if len(ia) < self.min_inliers:
            return None
        points = previous.points_cam[ia] @ T_world_prev[:3, :3].T + T_world_prev[:3, 3]
        pixels = self._current.pixels[ib]
        sigmas = np.sqrt((previous.sigmas[ia] ** 2 + self._current.sigmas[ib] ** 2) / 2)
        K = np.asarray(frame.K, np.float64)
        solved = pnp_ransac(points, pixels, K, self.reprojection_px, self.min_inliers)
        if solved is None:
            return None
        T_pnp, inliers = solved
        return Correspondences(points[inliers], pixels[inliers], K, sigmas[inliers], T_pnp)

    def transform(self, delta: np.ndarray) -> None:
        """The world moved under the remembered frame (a loop moved its map): its pose
        becomes ``delta @ T_world_cam``, delta (4, 4)."""
        if self._previous is not None:
            features, T = self._previous
            self._previous = (features, np.asarray(delta, np.float64) @ T)

    def remember(self, T_world_cam: np.ndarray | None) -> None:
        """Keep the last detected frame's features at pose T_world_cam (None: forget them, so
        the next frame is tracked without correspondences)."""
        if T_world_cam is None or self._current is None:
            self._previous = None
        else:
            self._previous = (self._current, np.asarray(T_world_cam, np.float64))
        self._current = None

    @property
    def detected(self) -> FrameFeatures | None:
        """The features ``correspondences`` detected on its frame, until ``remember``."""
        return self._current
