"""Plain, slow twins of the fast paths, for the tests only.

They loop over samples and triangles in Python and share no code with ``ar.raster`` or
``ar.composite``: depth comes from a ray-triangle intersection (Moller-Trumbore) instead of
screen-space planes, colour from 3D barycentrics at the hit point.
"""

from __future__ import annotations

import numpy as np


def raycast_triangles_reference(
    tri_cam: np.ndarray,
    tri_rgb: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    *,
    supersample: int = 1,
    z_near: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """Cast one ray per sample centre and keep the nearest hit with z >= z_near.

    Args:
        tri_cam: (T, 3, 3) corners in the camera frame; tri_rgb: (T, 3, 3) corner colours.
        K: (3, 3) intrinsics of the (width, height) image.

    Returns:
        depth (H*s, W*s) float64 z of the hit (inf if none) and rgb (H*s, W*s, 3).
    """
    s = supersample
    K_inv = np.linalg.inv(np.asarray(K, dtype=np.float64))
    depth = np.full((height * s, width * s), np.inf)
    rgb = np.zeros((height * s, width * s, 3))
    for row in range(height * s):
        for col in range(width * s):
            u, v = (col + 0.5) / s - 0.5, (row + 0.5) / s - 0.5
            direction = K_inv @ np.array([u, v, 1.0])  # z component is 1, so t = z
            for corners, colors in zip(tri_cam, tri_rgb):
                hit = _ray_triangle(direction, corners)
                if hit is None:
                    continue
                t, b1, b2 = hit
                if z_near <= t < depth[row, col]:
                    depth[row, col] = t
                    rgb[row, col] = (1 - b1 - b2) * colors[0] + b1 * colors[1] + b2 * colors[2]
    return depth, rgb


def _ray_triangle(direction: np.ndarray, corners: np.ndarray) -> tuple[float, float, float] | None:
    """Moller-Trumbore for a ray from the origin: (t, b1, b2) or None."""
    edge1, edge2 = corners[1] - corners[0], corners[2] - corners[0]
    p = np.cross(direction, edge2)
    det = float(edge1 @ p)
    if abs(det) < 1e-14:
        return None
    to_origin = -corners[0]
    b1 = float(to_origin @ p) / det
    if b1 < 0 or b1 > 1:
        return None
    q = np.cross(to_origin, edge1)
    b2 = float(direction @ q) / det
    if b2 < 0 or b1 + b2 > 1:
        return None
    return float(edge2 @ q) / det, b1, b2


def composite_reference(
    background_rgb: np.ndarray,
    scene_depth: np.ndarray,
    sample_depth: np.ndarray,
    sample_rgb: np.ndarray,
    supersample: int,
    depth_tolerance: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel loop over the samples: (rgb (H, W, 3), object_mask, occlusion_mask)."""
    height, width = scene_depth.shape
    s = supersample
    rgb = np.zeros((height, width, 3))
    object_mask = np.zeros((height, width), bool)
    occlusion_mask = np.zeros((height, width), bool)
    for row in range(height):
        for col in range(width):
            scene = scene_depth[row, col]
            if not (np.isfinite(scene) and scene > 0):
                scene = np.inf
            visible, hidden, color_sum = 0, 0, np.zeros(3)
            for i in range(s):
                for j in range(s):
                    z = sample_depth[row * s + i, col * s + j]
                    if not np.isfinite(z):
                        continue
                    if z < scene + depth_tolerance:
                        visible += 1
                        color_sum += sample_rgb[row * s + i, col * s + j]
                    else:
                        hidden += 1
            alpha = visible / (s * s)
            rgb[row, col] = background_rgb[row, col] * (1 - alpha) + color_sum / (s * s)
            object_mask[row, col] = 2 * visible >= s * s
            occlusion_mask[row, col] = 2 * hidden > s * s
    return rgb, object_mask, occlusion_mask
