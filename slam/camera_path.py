"""Camera paths for fly-through videos: a smooth path through keyframe poses, and its frames.

A path is a few keyframe poses ``T_world_cam`` (camera-to-world, OpenCV axes). Between them the
camera position follows a cubic spline (periodic for a loop) and its orientation a rotation
spline (``scipy.spatial.transform.RotationSpline``, continuous angular velocity). Keyframes are
placed in time by the distance between them, translation plus ``ANGLE_METRES`` per radian of
turn, so that the camera moves at an even pace and a pure turn still takes time.

    path = CameraPath(keyframes, duration_s=6.0, fps=24, loop=False)
    poses = path_poses(path)            # (N, 4, 4), N = duration * fps
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ANGLE_METRES = 0.5
"""Metres of path a radian of turn counts as, when keyframes are spaced in time."""
MAX_FRAMES = 3600
"""Most frames a path may have (two and a half minutes at 24 frames/s)."""


@dataclass(frozen=True)
class CameraPath:
    """Keyframe poses (K, 4, 4) and how to play them: seconds, frames per second, and whether
    the path returns to its first keyframe."""

    keyframes: np.ndarray
    duration_s: float = 6.0
    fps: float = 24.0
    loop: bool = False

    def __post_init__(self) -> None:
        keyframes = np.asarray(self.keyframes, np.float64)
        if keyframes.ndim != 3 or keyframes.shape[1:] != (4, 4) or len(keyframes) < 2:
            raise ValueError(f"a camera path needs at least 2 keyframe poses (4x4), got shape {keyframes.shape}")
        if not np.isfinite(keyframes).all():
            raise ValueError("camera path keyframes must be finite")
        rotations = keyframes[:, :3, :3]
        if not np.allclose(rotations @ rotations.transpose(0, 2, 1), np.eye(3), atol=1e-3):
            raise ValueError("camera path keyframes must be rigid transforms (orthonormal rotations)")
        if not (self.duration_s > 0 and self.fps > 0):
            raise ValueError(f"duration and fps must be positive, got {self.duration_s} s at {self.fps} frames/s")
        if self.frame_count > MAX_FRAMES:
            raise ValueError(f"{self.frame_count} frames ({self.duration_s:g} s at {self.fps:g} frames/s): at most "
                             f"{MAX_FRAMES}")
        object.__setattr__(self, "keyframes", keyframes)

    @property
    def frame_count(self) -> int:
        return max(2, int(round(self.duration_s * self.fps)))


def keyframe_times(keyframes: np.ndarray) -> np.ndarray:
    """(K, 4, 4) poses -> (K,) times in [0, 1], spaced by translation plus ``ANGLE_METRES`` per
    radian between consecutive keyframes (evenly when they all coincide)."""
    from scipy.spatial.transform import Rotation

    moves = np.linalg.norm(np.diff(keyframes[:, :3, 3], axis=0), axis=1)
    turns = (Rotation.from_matrix(keyframes[:-1, :3, :3]).inv() * Rotation.from_matrix(keyframes[1:, :3, :3])).magnitude()
    steps = moves + ANGLE_METRES * turns
    if steps.sum() <= 1e-9:
        steps = np.ones_like(steps)
    steps = np.maximum(steps, 1e-3 * steps.sum())  # a repeated keyframe still takes a moment
    times = np.concatenate([[0.0], np.cumsum(steps)])
    return times / times[-1]


def path_poses(path: CameraPath) -> np.ndarray:
    """The path's frames: (N, 4, 4) float64 T_world_cam at N = ``path.frame_count`` evenly
    spaced times; the first is the first keyframe, the last the last keyframe (or, for a loop,
    the frame before the first again)."""
    from scipy.interpolate import CubicSpline
    from scipy.spatial.transform import Rotation, RotationSpline

    keys = path.keyframes
    if path.loop:
        keys = np.concatenate([keys, keys[:1]])
    times = keyframe_times(keys)
    n = path.frame_count
    samples = np.linspace(0.0, 1.0, n, endpoint=not path.loop)
    positions = CubicSpline(times, keys[:, :3, 3], bc_type="periodic" if path.loop else "natural")(samples)
    if len(keys) == 2:
        rotations = Rotation.from_matrix(keys[:, :3, :3])
        turn = (rotations[0].inv() * rotations[1]).as_rotvec()
        orientation = rotations[0] * Rotation.from_rotvec(samples[:, None] * turn[None, :])
    else:
        orientation = RotationSpline(times, Rotation.from_matrix(keys[:, :3, :3]))(samples)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = orientation.as_matrix()
    poses[:, :3, 3] = positions
    return poses


def normals_from_depth(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W) z-depth in metres (0: nothing) and (3, 3) intrinsics -> (H, W, 3) unit normals in
    the camera frame (OpenCV axes, facing the camera), zero where a neighbour has no depth.
    Central differences of the back-projected points."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    z = depth.astype(np.float64)
    points = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1)
    du = np.zeros_like(points)
    dv = np.zeros_like(points)
    du[:, 1:-1] = points[:, 2:] - points[:, :-2]
    dv[1:-1] = points[2:] - points[:-2]
    normals = np.cross(dv, du)
    valid = z > 0
    seen = valid.copy()
    seen[:, 1:-1] &= valid[:, 2:] & valid[:, :-2]
    seen[1:-1] &= valid[2:] & valid[:-2]
    seen[[0, -1], :] = False
    seen[:, [0, -1]] = False
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    normals = np.where(seen[..., None] & (length > 0), normals / np.maximum(length, 1e-12), 0.0)
    facing = np.sum(normals * points, axis=-1, keepdims=True) > 0
    return np.where(facing, -normals, normals)


def normals_image(normals: np.ndarray) -> np.ndarray:
    """(H, W, 3) camera-frame normals -> (H, W, 3) colours in [0, 1] (the usual 0.5 + n / 2 with
    y and z flipped, so that a surface facing the camera is blue and up is green); black where
    there is no normal."""
    shown = normals * np.array([1.0, -1.0, -1.0])
    colors = 0.5 + 0.5 * shown
    return np.where(np.any(normals != 0, axis=-1, keepdims=True), colors, 0.0)
