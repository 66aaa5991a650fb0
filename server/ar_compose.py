"""The AR composite as plain functions of arrays: objects placed, composited with a depth
test against the scene, and each object's visibility. It runs in a render helper
(``server.render_calls.ar_composite``), never in the API process (``server.routes_ar``).

The scene depth is an input frame's sensor depth, with the map's rendered depth only in the
holes the objects cover (``ar.scene_depth.sensor_depth_with_map``); a rendered view's is the
map's as rendered (its colour-guided refinement, ``ar.scene_depth.refined_render_depth``, moved
no occlusion the right way on real frames: see ``benchmarks/bench_ar_occlusion.py`` (d))."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from ar import UPRIGHT, VirtualObject, composite, rasterize_objects
from ar.scene_depth import sensor_depth_with_map
from server.rendering import Camera, png_from_rgb

DEPTH_TOLERANCE_M = 0.01
"""How far an object may lie behind the scene and still show (as ``ar.composite``'s default)."""
PLACE_DISTANCE_M = 1.0
"""How far ahead an object without a pose goes when the image centre has no depth."""
CENTRE_WINDOW = 0.2
"""Share of the image's width and height, around its centre, whose median depth places an object."""


@dataclass(frozen=True)
class Background:
    """What the objects are composited into."""

    rgb: np.ndarray
    """(H, W, 3) float32 in [0, 1]."""
    depth: np.ndarray
    """(H, W) float32 metres, 0 = unknown."""
    camera: Camera
    sensed: bool = False
    """True: ``depth`` is a sensor's (an input frame's), kept wherever it measured; False: the
    map's rendered depth."""
    map_view: object | None = None
    """For a sensed background, the ``render_calls.ViewCall`` of the session's map at this
    camera, whose depth fills the sensor's holes under the objects; None: holes stay far."""


def central_depth(depth: np.ndarray) -> float | None:
    """Median valid depth (metres) in the CENTRE_WINDOW around the image centre, or None."""
    height, width = depth.shape
    dy, dx = max(1, int(height * CENTRE_WINDOW / 2)), max(1, int(width * CENTRE_WINDOW / 2))
    window = depth[height // 2 - dy: height // 2 + dy, width // 2 - dx: width // 2 + dx]
    valid = window[np.isfinite(window) & (window > 0)]
    return float(np.median(valid)) if len(valid) else None


def object_box(obj: VirtualObject) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) corners of the object's scaled mesh in its own frame."""
    vertices = np.asarray(obj.mesh.vertices, dtype=np.float64) * obj.scale
    return vertices.min(axis=0), vertices.max(axis=0)


def in_front_of_camera(obj: VirtualObject, background: Background) -> VirtualObject:
    """``obj`` with its box centre on the camera's optical axis, just before the surface seen
    at the image centre (PLACE_DISTANCE_M ahead without depth there), standing upright in the
    world (``ar.UPRIGHT``)."""
    lo, hi = object_box(obj)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    surface = central_depth(background.depth)
    distance = PLACE_DISTANCE_M if surface is None else max(surface - radius, 2.0 * radius)
    T_cam = background.camera.T_world_cam
    T = np.eye(4)
    T[:3, :3] = UPRIGHT
    T[:3, 3] = T_cam[:3, 3] + distance * T_cam[:3, 2] - UPRIGHT @ ((lo + hi) / 2)
    return replace(obj, T_world_obj=T)


def visibility(objects: list[VirtualObject], background: Background) -> list[dict]:
    """Per object, whether it shows in the composite (``routes_ar.OBJECTS_HEADER``), each
    rasterised alone at one sample per pixel against the scene depth, with the composite's
    depth test."""
    camera = background.camera
    scene = np.asarray(background.depth, dtype=np.float32).reshape(-1)
    scene = np.where(np.isfinite(scene) & (scene > 0), scene, np.inf)
    report = []
    for obj in objects:
        layer = rasterize_objects([obj], camera.K, camera.T_world_cam, camera.width, camera.height, supersample=1)
        pixels = layer.pixel_index.cpu().numpy()
        visible = int((layer.depth.cpu().numpy() < scene[pixels] + DEPTH_TOLERANCE_M).sum())
        centre = obj.T_world_obj[:3, :3] @ (sum(object_box(obj)) / 2) + obj.T_world_obj[:3, 3]
        state = "outside" if len(pixels) == 0 else "visible" if visible else "hidden"
        report.append({"state": state, "visible_pixels": visible, "position": [round(float(v), 4) for v in centre]})
    return report


WindowDepth = Callable[[np.ndarray, int, int], np.ndarray]
"""The map's depth at the background's pose: (K (3, 3), width, height) -> (height, width) metres."""


def scene_depth(background: Background, objects: list[VirtualObject], map_depth: WindowDepth | None) -> Background:
    """``background`` with the depth the objects are tested against: a sensed one with
    ``map_depth`` in its holes under the objects; a rendered one as it is."""
    if not background.sensed:
        return background
    camera = background.camera
    fused = sensor_depth_with_map(background.depth, objects, camera.K, camera.T_world_cam, map_depth)
    return replace(background, depth=fused.depth)


def composite_png(background: Background, objects: list[VirtualObject], posed: list[bool],
                  map_depth: WindowDepth | None = None) -> tuple[bytes, list[dict]]:
    """The composite as PNG bytes and the visibility report; an object whose ``posed`` is
    False is placed in front of the camera first (on the background's own depth), then the
    scene depth is made for the objects (``scene_depth``)."""
    objects = [obj if has_pose else in_front_of_camera(obj, background) for obj, has_pose in zip(objects, posed)]
    background = scene_depth(background, objects, map_depth)
    camera = background.camera
    result = composite(background.rgb, background.depth, objects, camera.K, camera.T_world_cam,
                       depth_tolerance=DEPTH_TOLERANCE_M)
    return png_from_rgb(result.rgb), visibility(objects, background)
