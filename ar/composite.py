"""Depth-tested compositing of virtual objects over a real (or rendered) view.

Each object sample is kept where it is in front of the scene:
``object_depth < scene_depth + depth_tolerance``, with scene depth 0 (unknown) counting as
far, so objects show over holes in the map. The visible samples of a pixel give its alpha
(the anti-aliased coverage) and premultiplied colour, blended over the background:
``rgb = background * (1 - alpha) + sum(visible colour) / s^2``.

Both depths are z in the camera frame (what an RGB-D sensor and the map renderer give).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from ar.objects import VirtualObject
from ar.raster import DEFAULT_Z_NEAR, Light, SampleLayer, rasterize_objects


@dataclass(frozen=True)
class CompositeResult:
    """A composited view.

    Attributes:
        rgb: (H, W, 3) float32 in [0, 1].
        object_mask: (H, W) bool, pixels where at least half the samples are visible virtual
            content.
        occlusion_mask: (H, W) bool, pixels where more than half the samples are virtual
            content hidden by the real scene (disjoint from object_mask).
        alpha: (H, W) float32 in [0, 1], fraction of samples with visible virtual content.
    """

    rgb: np.ndarray
    object_mask: np.ndarray
    occlusion_mask: np.ndarray
    alpha: np.ndarray


def composite(
    background_rgb: np.ndarray,
    scene_depth: np.ndarray,
    objects: Sequence[VirtualObject],
    K: np.ndarray,
    T_world_cam: np.ndarray,
    *,
    depth_tolerance: float = 0.01,
    supersample: int = 2,
    light: Light = Light(),
    z_near: float = DEFAULT_Z_NEAR,
    device: str | torch.device = "cpu",
) -> CompositeResult:
    """Render the objects for the camera and blend them over the background with occlusion.

    Args:
        background_rgb: (H, W, 3) float in [0, 1] (uint8 is accepted and scaled).
        scene_depth: (H, W) metres, z in the camera frame; 0 or non-finite = unknown (far).
        objects: the virtual objects (may be empty).
        K: (3, 3) intrinsics of the (W, H) image; T_world_cam: (4, 4) camera-to-world.
        depth_tolerance: metres by which an object may lie behind the scene and still show
            (objects resting on a surface do not flicker).
        supersample: s x s samples per pixel; the depth test is done per sample.
        light, z_near, device: see ``ar.raster.render_objects``.
    """
    background, depth = _check_images(background_rgb, scene_depth)
    if not np.isfinite(depth_tolerance) or depth_tolerance < 0:
        raise ValueError(f"depth_tolerance: must be a finite number >= 0, got {depth_tolerance}")
    height, width = depth.shape
    layer = rasterize_objects(
        objects, K, T_world_cam, width, height, light=light, supersample=supersample, z_near=z_near, device=device
    )
    return composite_layer(background, depth, layer, depth_tolerance=depth_tolerance)


def composite_layer(
    background_rgb: np.ndarray, scene_depth: np.ndarray, layer: SampleLayer, *, depth_tolerance: float
) -> CompositeResult:
    """Blend a rasterised object layer over a background with a per-sample depth test.

    Args:
        background_rgb: (H, W, 3) float32 in [0, 1].
        scene_depth: (H, W) float32 metres, 0 / non-finite = unknown.
        layer: the covered object samples of the (H * s, W * s) grid.
        depth_tolerance: metres.
    """
    height, width = scene_depth.shape
    if (layer.height, layer.width) != (height, width):
        raise ValueError(f"layer: rendered for {layer.width}x{layer.height}, image is {width}x{height}")
    device = layer.depth.device
    num_pixels = height * width
    samples_per_pixel = float(layer.supersample**2)
    scene = torch.as_tensor(scene_depth, dtype=torch.float32, device=device).reshape(-1)
    # NaN > 0 is false, so NaN, zero and negative depths all become "far".
    scene = torch.where(scene > 0, scene, torch.full_like(scene, float("inf")))
    pixel = layer.pixel_index
    visible = (layer.depth < torch.index_select(scene, 0, pixel) + depth_tolerance).to(torch.float32)
    alpha = torch.zeros(num_pixels, device=device).index_add_(0, pixel, visible) / samples_per_pixel
    covered = torch.bincount(pixel, minlength=num_pixels).to(torch.float32) / samples_per_pixel
    premultiplied = torch.zeros((num_pixels, 3), device=device).index_add_(0, pixel, layer.rgb * visible[:, None])
    background = torch.as_tensor(background_rgb, dtype=torch.float32, device=device).reshape(-1, 3)
    rgb = torch.addcmul(premultiplied / samples_per_pixel, background, (1.0 - alpha)[:, None])
    shape = (height, width)
    return CompositeResult(
        rgb=torch.clamp(rgb, 0.0, 1.0).view(*shape, 3).cpu().numpy(),
        object_mask=(alpha >= 0.5).view(shape).cpu().numpy(),
        occlusion_mask=(covered - alpha > 0.5).view(shape).cpu().numpy(),
        alpha=alpha.view(shape).cpu().numpy(),
    )


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two (H, W) bool masks; 1.0 when both are empty."""
    a, b = np.asarray(a, dtype=bool), np.asarray(b, dtype=bool)
    if a.shape != b.shape:
        raise ValueError(f"mask_iou: shapes differ, {a.shape} and {b.shape}")
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)


def _check_images(background_rgb: np.ndarray, scene_depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float32 copies; raises ValueError naming the argument for bad shapes or values."""
    background = np.asarray(background_rgb)
    depth = np.asarray(scene_depth)
    if background.ndim != 3 or background.shape[2] != 3:
        raise ValueError(f"background_rgb: expected shape (H, W, 3), got {background.shape}")
    if depth.shape != background.shape[:2]:
        raise ValueError(f"scene_depth: shape {depth.shape} differs from background_rgb {background.shape[:2]}")
    if background.dtype == np.uint8:
        background = background.astype(np.float32) / 255.0
    background = background.astype(np.float32, copy=False)
    if not np.isfinite(background).all():
        raise ValueError("background_rgb: contains NaN or inf")
    return np.clip(background, 0.0, 1.0), depth.astype(np.float32, copy=False)
