"""How well a scene depth (e.g. the neural map's rendered depth) reproduces the occlusion of
virtual objects that a reference depth (exact synthetic depth, or the sensor's input depth)
gives: the measure of the paper's AR application and of the AR benchmark's figures.

The objects are rasterised once and composited over both depths with the same per-sample
test, so the only difference between the two composites is the scene depth.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ar.composite import CompositeResult, _check_images, composite_layer, mask_iou
from ar.objects import VirtualObject
from ar.raster import DEFAULT_Z_NEAR, Light, rasterize_objects


@dataclass(frozen=True)
class OcclusionComparison:
    """Composites over a reference and a candidate depth, and how far their masks agree.

    Attributes:
        reference, candidate: the two composites.
        hidden_fraction: share of the objects' pixels (visible or hidden) that the reference
            scene hides; 0.3-0.7 makes an occlusion test meaningful.
        occlusion_iou: IoU of the ``occlusion_mask`` (object pixels hidden by the scene).
        object_iou: IoU of the ``object_mask`` (object pixels shown).
    """

    reference: CompositeResult
    candidate: CompositeResult
    hidden_fraction: float
    occlusion_iou: float
    object_iou: float


def hidden_fraction(result: CompositeResult) -> float:
    """Share of the pixels covered by objects that the scene hides; 0.0 when nothing is covered."""
    hidden = int(result.occlusion_mask.sum())
    shown = int(result.object_mask.sum())
    return 0.0 if hidden + shown == 0 else hidden / (hidden + shown)


def compare_occlusion(
    background_rgb: np.ndarray,
    reference_depth: np.ndarray,
    candidate_depth: np.ndarray,
    objects: Sequence[VirtualObject],
    K: np.ndarray,
    T_world_cam: np.ndarray,
    *,
    depth_tolerance: float = 0.01,
    supersample: int = 2,
    light: Light = Light(),
    z_near: float = DEFAULT_Z_NEAR,
    device: str | torch.device = "cpu",
) -> OcclusionComparison:
    """Composite the objects over both depths and compare the masks.

    Args:
        background_rgb: (H, W, 3) float in [0, 1].
        reference_depth, candidate_depth: (H, W) metres, z in the camera frame, 0 = unknown.
        objects, K (3, 3), T_world_cam (4, 4) and the keywords: as ``ar.composite``.
    """
    background, reference = _check_images(background_rgb, reference_depth)
    candidate = np.asarray(candidate_depth, dtype=np.float32)
    if candidate.shape != reference.shape:
        raise ValueError(f"candidate_depth: shape {candidate.shape} differs from reference_depth {reference.shape}")
    if not np.isfinite(depth_tolerance) or depth_tolerance < 0:
        raise ValueError(f"depth_tolerance: must be a finite number >= 0, got {depth_tolerance}")
    height, width = reference.shape
    layer = rasterize_objects(
        objects, K, T_world_cam, width, height, light=light, supersample=supersample, z_near=z_near, device=device
    )
    reference_result = composite_layer(background, reference, layer, depth_tolerance=depth_tolerance)
    candidate_result = composite_layer(background, candidate, layer, depth_tolerance=depth_tolerance)
    return OcclusionComparison(
        reference=reference_result,
        candidate=candidate_result,
        hidden_fraction=hidden_fraction(reference_result),
        occlusion_iou=mask_iou(candidate_result.occlusion_mask, reference_result.occlusion_mask),
        object_iou=mask_iou(candidate_result.object_mask, reference_result.object_mask),
    )
