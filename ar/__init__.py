"""Augmented reality: virtual objects composited into real or rendered views with correct
occlusion (the paper's Applications section). Arrays in, arrays out; imports ``slam`` at most,
never the server.
"""

from ar.assets import AssetError, load_asset
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
