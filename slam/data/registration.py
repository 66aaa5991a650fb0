"""Colour seen by another camera than depth, resampled onto the depth camera.

Most RGB-D sensors see colour and depth through two cameras: the colour camera has its own
intrinsics (and distortion) and sits a few centimetres from the depth camera
(``ColorCamera.T_color_depth``). The pipeline works in the depth camera (its pixels carry the
measured geometry), so each frame's colour is registered to it once, at input: every depth
pixel is lifted to 3-D with its measured depth, moved into the colour camera, projected, and
takes the colour there (bilinear). A depth pixel that another, nearer depth point hides from
the colour camera gets no colour (``color_valid`` False), nor does one that projects outside
the colour image. Where depth is missing the pixel is mapped as if it lay at the frame's
median depth, so that it still gets a plausible colour (the pipeline uses no depth there).

``register_color`` is the vectorised path (OpenCV remap and a z-buffer by ``np.minimum.at``),
``register_color_reference`` the plain per-pixel loop it is tested against.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from slam.data.frame import DataError

OCCLUSION_TOLERANCE_M = 0.02
"""A depth point farther than the colour camera's nearest point at its pixel by more than
this (plus 2 % of its depth) is hidden from the colour camera."""


@dataclass(frozen=True)
class ColorCamera:
    """The colour camera of a two-camera RGB-D sensor.

    K: (3, 3) intrinsics at the colour image's resolution; width, height: that resolution;
    T_color_depth: (4, 4) rigid transform from the depth camera's frame to the colour
    camera's (OpenCV axes, metres); dist: OpenCV distortion coefficients (k1, k2, p1, p2[, k3])
    of the colour camera, or None (undistorted).
    """

    K: np.ndarray
    width: int
    height: int
    T_color_depth: np.ndarray
    dist: np.ndarray | None = None

    def __post_init__(self) -> None:
        K = np.asarray(self.K, np.float64)
        T = np.asarray(self.T_color_depth, np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise DataError(f"colour intrinsics must be a finite 3x3 matrix with positive focal lengths, got {K.tolist()}")
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise DataError(f"depth-to-colour transform must be a finite 4x4 matrix, got shape {T.shape}")
        R = T[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or not np.allclose(T[3], [0, 0, 0, 1]):
            raise DataError("depth-to-colour transform must be rigid: an orthonormal rotation and a last row 0 0 0 1")
        if self.width < 1 or self.height < 1:
            raise DataError(f"colour image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "T_color_depth", T)
        if self.dist is not None:
            d = np.asarray(self.dist, np.float64).ravel()
            if d.size not in (4, 5, 8) or not np.all(np.isfinite(d)):
                raise DataError(f"colour distortion must be 4, 5 or 8 finite OpenCV coefficients, got {d.tolist()}")
            object.__setattr__(self, "dist", None if not np.any(d) else d)

    def scaled(self, width: int, height: int) -> "ColorCamera":
        """The same camera for its image resized to width x height."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        return ColorCamera(K, width, height, self.T_color_depth, self.dist)


def color_camera_from_values(intrinsics: Sequence[float], depth_to_color: Sequence[float] | None,
                             source: str = "arguments") -> ColorCamera:
    """A ColorCamera from ``fx, fy, cx, cy, width, height[, k1, k2, p1, p2[, k3]]`` and the
    depth-to-colour transform as 16 (4 x 4) or 12 (3 x 4) row-major numbers (None: the
    cameras share their centre and axes, only the intrinsics differ)."""
    values = [float(v) for v in intrinsics]
    if len(values) not in (6, 10, 11):
        raise DataError(f"{source}: colour intrinsics need fx,fy,cx,cy,width,height and optionally "
                        f"k1,k2,p1,p2[,k3] (6, 10 or 11 numbers), got {len(values)}")
    fx, fy, cx, cy, width, height = values[:6]
    if width != int(width) or height != int(height):
        raise DataError(f"{source}: colour image size must be whole pixels, got {width}x{height}")
    T = np.eye(4)
    if depth_to_color is not None:
        numbers = np.asarray([float(v) for v in depth_to_color], np.float64)
        if numbers.size not in (12, 16):
            raise DataError(f"{source}: the depth-to-colour transform needs 16 (4x4) or 12 (3x4) row-major "
                            f"numbers, got {numbers.size}")
        T[:3] = numbers[:12].reshape(3, 4)
        if numbers.size == 16:
            T[3] = numbers[12:]
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return ColorCamera(K, int(width), int(height), T, np.asarray(values[6:]) if len(values) > 6 else None)


def read_color_calibration(path: Path) -> ColorCamera:
    """A colour camera from a JSON file: ``{"color_intrinsics": [fx, fy, cx, cy, width, height,
    (k1, k2, p1, p2, k3)], "T_color_depth": 4 x 4 rows (or 16 numbers)}``, the second optional."""
    import json

    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as error:
        raise DataError(f"{path}: not a readable JSON calibration ({error})") from error
    if not isinstance(data, dict) or "color_intrinsics" not in data:
        raise DataError(f'{path}: a calibration needs "color_intrinsics" (and optionally "T_color_depth")')
    transform = data.get("T_color_depth")
    try:
        numbers = None if transform is None else np.asarray(transform, np.float64).ravel().tolist()
        return color_camera_from_values(data["color_intrinsics"], numbers, source=str(path))
    except (TypeError, ValueError) as error:
        raise DataError(f"{path}: {error}") from error


def _fill_missing_depth(depth: np.ndarray) -> np.ndarray:
    """Depth (H, W) with its missing pixels (0) at the median of the valid ones (1 m if none)."""
    valid = depth > 0
    median = float(np.median(depth[valid])) if valid.any() else 1.0
    return np.where(valid, depth, median)


def _distort(x: np.ndarray, y: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's distortion of normalised coordinates (radial k1 k2 k3 (k4 k5 k6), tangential p1 p2)."""
    k = np.zeros(8)
    k[: dist.size] = dist
    k1, k2, p1, p2, k3, k4, k5, k6 = k
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def project_depth_pixels(depth: np.ndarray, K_depth: np.ndarray, camera: ColorCamera
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each depth pixel lands in the colour image: (u, v) (H, W) float colour-pixel
    coordinates and z (H, W) its depth in the colour camera. Missing depth (0) is placed at
    the frame's median depth."""
    H, W = depth.shape
    d = _fill_missing_depth(depth.astype(np.float64))
    fx, fy, cx, cy = K_depth[0, 0], K_depth[1, 1], K_depth[0, 2], K_depth[1, 2]
    uu, vv = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    X = np.stack([(uu - cx) / fx * d, (vv - cy) / fy * d, d], -1)
    T = camera.T_color_depth
    Xc = X @ T[:3, :3].T + T[:3, 3]
    z = Xc[..., 2]
    safe = np.where(z > 1e-6, z, np.nan)
    x, y = Xc[..., 0] / safe, Xc[..., 1] / safe
    if camera.dist is not None:
        x, y = _distort(x, y, camera.dist)
    Kc = camera.K
    u = Kc[0, 0] * x + Kc[0, 1] * y + Kc[0, 2]
    v = Kc[1, 1] * y + Kc[1, 2]
    return u, v, z


def _inside(u, v, camera: ColorCamera):
    """Whether colour-pixel coordinates fall on the colour image (its pixels' area, so that
    an identity camera's border pixels are inside)."""
    return (np.isfinite(u) & np.isfinite(v) & (u >= -0.5) & (v >= -0.5)
            & (u <= camera.width - 0.5) & (v <= camera.height - 0.5))


def _pixel(coordinate, size: int):
    """The pixel (int) a coordinate falls on, within 0..size-1."""
    return np.clip(np.rint(coordinate), 0, size - 1).astype(np.int64)


def _visible(u: np.ndarray, v: np.ndarray, z: np.ndarray, measured: np.ndarray, camera: ColorCamera) -> np.ndarray:
    """(H, W) bool: the depth pixel projects inside the colour image and no nearer measured
    depth point covers its colour pixel (a z-buffer at the colour image's resolution)."""
    inside = _inside(u, v, camera)
    ui, vi = _pixel(np.where(inside, u, 0), camera.width), _pixel(np.where(inside, v, 0), camera.height)
    splat = inside & measured
    zbuf = np.full((camera.height, camera.width), np.inf)
    np.minimum.at(zbuf, (vi[splat], ui[splat]), z[splat])
    nearest = zbuf[vi, ui]
    return inside & (z <= nearest + OCCLUSION_TOLERANCE_M + 0.02 * z)


def register_color(rgb: np.ndarray, depth: np.ndarray, K_depth: np.ndarray, camera: ColorCamera
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Colour ``rgb`` (Hc, Wc, 3) of ``camera`` resampled onto the depth camera's pixels
    through ``depth`` (H, W) metres (0: missing) with intrinsics ``K_depth`` (3, 3).

    Returns rgb (H, W, 3) float32 and color_valid (H, W) bool: the pixels the colour camera
    saw (inside its image, not hidden behind nearer depth)."""
    import cv2

    if rgb.shape[:2] != (camera.height, camera.width):
        raise DataError(f"colour image is {rgb.shape[1]}x{rgb.shape[0]}, the colour camera's intrinsics are for "
                         f"{camera.width}x{camera.height}")
    u, v, z = project_depth_pixels(depth, K_depth, camera)
    valid = _visible(u, v, z, depth > 0, camera)
    map_x = np.where(np.isfinite(u), u, -1).astype(np.float32)
    map_y = np.where(np.isfinite(v), v, -1).astype(np.float32)
    out = cv2.remap(np.ascontiguousarray(rgb, np.float32), map_x, map_y, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.astype(np.float32), valid


def register_color_reference(rgb: np.ndarray, depth: np.ndarray, K_depth: np.ndarray, camera: ColorCamera
                             ) -> tuple[np.ndarray, np.ndarray]:
    """``register_color`` pixel by pixel: the plain twin its tests compare against."""
    H, W = depth.shape
    d = _fill_missing_depth(depth.astype(np.float64))
    R, t = camera.T_color_depth[:3, :3], camera.T_color_depth[:3, 3]
    Kinv = np.linalg.inv(K_depth)
    proj = np.full((H, W, 3), np.nan)
    for y in range(H):
        for x in range(W):
            Xc = R @ (Kinv @ np.array([x, y, 1.0]) * d[y, x]) + t
            if Xc[2] <= 1e-6:
                continue
            nx, ny = Xc[0] / Xc[2], Xc[1] / Xc[2]
            if camera.dist is not None:
                nx, ny = _distort(np.array(nx), np.array(ny), camera.dist)
            uc = camera.K[0, 0] * nx + camera.K[0, 1] * ny + camera.K[0, 2]
            vc = camera.K[1, 1] * ny + camera.K[1, 2]
            proj[y, x] = uc, vc, Xc[2]
    zbuf = np.full((camera.height, camera.width), np.inf)
    inside = np.zeros((H, W), bool)
    for y in range(H):
        for x in range(W):
            uc, vc, zc = proj[y, x]
            if np.isfinite(uc) and -0.5 <= uc <= camera.width - 0.5 and -0.5 <= vc <= camera.height - 0.5:
                inside[y, x] = True
                if depth[y, x] > 0:
                    ui, vi = int(_pixel(uc, camera.width)), int(_pixel(vc, camera.height))
                    zbuf[vi, ui] = min(zbuf[vi, ui], zc)
    out = np.zeros((H, W, 3), np.float32)
    valid = np.zeros((H, W), bool)
    for y in range(H):
        for x in range(W):
            if not inside[y, x]:
                continue
            uc, vc, zc = proj[y, x]
            ui, vi = int(_pixel(uc, camera.width)), int(_pixel(vc, camera.height))
            valid[y, x] = zc <= zbuf[vi, ui] + OCCLUSION_TOLERANCE_M + 0.02 * zc
            uc, vc = min(max(uc, 0.0), camera.width - 1.0), min(max(vc, 0.0), camera.height - 1.0)  # edge pixels repeat
            x0, y0 = int(np.floor(uc)), int(np.floor(vc))
            x1, y1 = min(x0 + 1, camera.width - 1), min(y0 + 1, camera.height - 1)
            ax, ay = uc - x0, vc - y0
            out[y, x] = ((1 - ax) * (1 - ay) * rgb[y0, x0] + ax * (1 - ay) * rgb[y0, x1]
                         + (1 - ax) * ay * rgb[y1, x0] + ax * ay * rgb[y1, x1])
    return out, valid
