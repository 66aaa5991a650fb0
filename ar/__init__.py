"""Augmented reality: virtual objects composited into real or rendered views with correct
occlusion (the paper's Applications section). Arrays in, arrays out; imports ``slam`` at most,
never the server.

``AssetError`` and ``load_asset`` are imported on first use (module ``__getattr__``): asset
files need trimesh, whose import costs a command line that never reads one seconds.
"""

from typing import Any

from ar.composite import CompositeResult, composite, composite_layer, mask_iou
from ar.objects import UPRIGHT, ObjectMesh, ObjectSpecError, VirtualObject, load_objects_json, make_shape
from ar.occlusion import OcclusionComparison, compare_occlusion, hidden_fraction
from ar.raster import Light, ObjectRender, SampleLayer, rasterize_objects, rasterize_triangles, render_objects

__all__ = [
    "UPRIGHT",
    "AssetError",
    "CompositeResult",
    "Light",
    "ObjectMesh",
    "ObjectRender",
    "ObjectSpecError",
    "OcclusionComparison",
    "SampleLayer",
    "VirtualObject",
    "compare_occlusion",
    "composite",
    "composite_layer",
    "hidden_fraction",
    "load_asset",
    "load_objects_json",
    "make_shape",
    "mask_iou",
    "rasterize_objects",
    "rasterize_triangles",
    "render_objects",
]

_LAZY = {"AssetError": "ar.assets", "load_asset": "ar.assets"}


def __getattr__(name: str) -> Any:
    """``AssetError`` and ``load_asset``, imported from ``ar.assets`` on first use."""
    if name not in _LAZY:
        raise AttributeError(f"module 'ar' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(_LAZY[name]), name)
    globals()[name] = value
    return value
