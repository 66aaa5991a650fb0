"""The scene depth that hides virtual objects: a frame's sensor depth where it measured,
the map's rendered depth only where it did not, and for rendered views (no sensor) the map's
depth with its edges moved onto the colour edges near the objects.

An input frame's sensor depth (registered to its colour) has the edges of the objects in it
at pixel scale; the map's depth at 0.2 m voxels is a smooth lump at anything under a few
centimetres, so it draws an object behind a mug over the mug's rim. The sensor has holes
(dark, shiny and grazing surfaces, the shadow beside an edge, beyond its range): there, and
only there, the map's depth stands in (``fill_holes``). The map is rendered only for the
holes the objects cover, in a window around them (``holes_under_objects``, ``window_intrinsics``).

A rendered view has no sensor depth. Its colour keeps edges that its depth blurs (the colour
head is sharper than the SDF's zero crossing): ``refine_depth`` replaces each pixel's depth
near the objects by the weighted median of its neighbours' depths, weighted by how alike
their colours are (a joint bilateral median, which never invents a depth between the two
sides of an edge). It moves a blurred ramp onto the colour edge, but on real frames the map's
depth at small occluders is a lump in the wrong place rather than a blurred step, and the
refinement fixed no occlusion there (``benchmarks/bench_ar_occlusion.py`` (d)): it is measured
by the benchmark, not applied by the server or ``voxfusion ar``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ar.objects import VirtualObject
from ar.raster import rasterize_objects

RenderDepth = Callable[[np.ndarray, int, int], np.ndarray]
"""Depth of the map for the same pose: (K (3, 3), width, height) -> (height, width) metres, 0 = none."""


@dataclass(frozen=True)
class RefineOptions:
    """The joint bilateral median of ``refine_depth``.

    Attributes:
        radius: half side (pixels) of the square window of neighbours.
        step: pixels between the neighbours taken in the window (a wide window at a fixed cost).
        sigma_color: colour distance (RGB in [0, 1], Euclidean) at which a neighbour's weight
            falls to exp(-1/2).
        sigma_space: pixels at which a neighbour's weight falls to exp(-1/2) by distance.
        margin: pixels around the objects' footprint that are refined (the rest is untouched).
    """

    radius: int = 6
    step: int = 1
    sigma_color: float = 0.06
    sigma_space: float = 4.0
    margin: int = 2


@dataclass(frozen=True)
class SceneDepth:
    """The depth the composite tests against and where it came from.

    Attributes:
        depth: (H, W) float32 metres, 0 = unknown (far).
        filled: (H, W) bool, pixels whose depth is the map's (a sensor hole under an object).
    """

    depth: np.ndarray
    filled: np.ndarray


def valid_depth(depth: np.ndarray) -> np.ndarray:
    """(H, W) bool: finite and positive (0, NaN and negative mean "no measurement")."""
    depth = np.asarray(depth)
    return np.isfinite(depth) & (depth > 0)


def fill_holes(sensor: np.ndarray, rendered: np.ndarray) -> np.ndarray:
    """(H, W) float32: ``sensor`` where it is valid, ``rendered`` elsewhere (0 where neither is)."""
    sensor = np.asarray(sensor, dtype=np.float32)
    rendered = np.asarray(rendered, dtype=np.float32)
    if sensor.shape != rendered.shape:
        raise ValueError(f"rendered: shape {rendered.shape} differs from sensor {sensor.shape}")
    return np.where(valid_depth(sensor), sensor, np.where(valid_depth(rendered), rendered, 0.0)).astype(np.float32)


def object_footprint(objects: Sequence[VirtualObject], K: np.ndarray, T_world_cam: np.ndarray,
                     width: int, height: int, margin: int = 0) -> np.ndarray:
    """(H, W) bool: pixels any object covers (one sample per pixel), grown by ``margin`` pixels."""
    mask = np.zeros(height * width, dtype=bool)
    if objects:
        layer = rasterize_objects(objects, K, T_world_cam, width, height, supersample=1)
        mask[layer.pixel_index.cpu().numpy()] = True
    mask = mask.reshape(height, width)
    return grow(mask, margin) if margin > 0 else mask


def grow(mask: np.ndarray, pixels: int) -> np.ndarray:
    """(H, W) bool ``mask`` dilated by a square of half side ``pixels``."""
    if pixels <= 0 or not mask.any():
        return mask
    as_float = torch.from_numpy(mask.astype(np.float32))[None, None]
    return (torch.nn.functional.max_pool2d(as_float, 2 * pixels + 1, stride=1, padding=pixels)[0, 0] > 0).numpy()


def bounding_window(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1), end exclusive, of the True pixels of an (H, W) mask; None when empty."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return None
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def window_intrinsics(K: np.ndarray, window: tuple[int, int, int, int]) -> np.ndarray:
    """(3, 3) intrinsics of the sub-image ``window`` (x0, y0, x1, y1) of a ``K`` camera."""
    x0, y0 = window[0], window[1]
    K_window = np.array(K, dtype=np.float64, copy=True)
    K_window[0, 2] -= x0
    K_window[1, 2] -= y0
    return K_window


def holes_under_objects(sensor: np.ndarray, objects: Sequence[VirtualObject], K: np.ndarray,
                        T_world_cam: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels some object covers where the sensor measured nothing."""
    height, width = np.shape(sensor)
    return object_footprint(objects, K, T_world_cam, width, height) & ~valid_depth(sensor)


def sensor_depth_with_map(sensor: np.ndarray, objects: Sequence[VirtualObject], K: np.ndarray,
                          T_world_cam: np.ndarray, render_depth: RenderDepth | None) -> SceneDepth:
    """The sensor's depth with the map's in the holes the objects cover.

    Args:
        sensor: (H, W) metres, registered to the frame's colour; 0 / NaN = none.
        objects, K (3, 3), T_world_cam (4, 4): as ``ar.composite``.
        render_depth: the map's depth of a window at this pose (called once, for the bounding
            window of the covered holes); None: no map, holes stay unknown (far).
    """
    sensor = np.asarray(sensor, dtype=np.float32)
    holes = holes_under_objects(sensor, objects, K, T_world_cam)
    window = bounding_window(holes)
    if render_depth is None or window is None:
        return SceneDepth(np.where(valid_depth(sensor), sensor, 0.0).astype(np.float32), np.zeros_like(holes))
    x0, y0, x1, y1 = window
    rendered = np.zeros_like(sensor)
    part = np.asarray(render_depth(window_intrinsics(K, window), x1 - x0, y1 - y0), dtype=np.float32)
    if part.shape != (y1 - y0, x1 - x0):
        raise ValueError(f"render_depth: expected shape {(y1 - y0, x1 - x0)}, got {part.shape}")
    rendered[y0:y1, x0:x1] = part
    # Only the covered holes take the map's depth: elsewhere the frame keeps what it measured.
    depth = np.where(holes, fill_holes(sensor, rendered), np.where(valid_depth(sensor), sensor, 0.0))
    return SceneDepth(depth.astype(np.float32), holes & valid_depth(rendered))


def refine_depth(depth: np.ndarray, guide_rgb: np.ndarray, where: np.ndarray,
                 options: RefineOptions = RefineOptions()) -> np.ndarray:
    """(H, W) float32 ``depth`` with the pixels of ``where`` replaced by the joint bilateral
    median of their neighbourhood: the depth below which half the neighbours' weight lies, a
    neighbour's weight falling with its colour distance in ``guide_rgb`` and its distance in
    pixels. Neighbours without depth have no weight; a pixel with none keeps its depth.

    Args:
        depth: (H, W) metres, 0 / NaN = none.
        guide_rgb: (H, W, 3) colour in [0, 1] of the same view.
        where: (H, W) bool, the pixels to refine (the objects' footprint).
    """
    depth = np.asarray(depth, dtype=np.float32)
    guide = np.asarray(guide_rgb, dtype=np.float32)
    if guide.shape != (*depth.shape, 3):
        raise ValueError(f"guide_rgb: expected shape {(*depth.shape, 3)}, got {guide.shape}")
    out = np.where(valid_depth(depth), depth, 0.0).astype(np.float32)
    ys, xs = np.nonzero(where)
    if len(ys) == 0:
        return out
    r = int(options.radius)
    height, width = depth.shape
    dy, dx = np.mgrid[-r:r + 1:options.step, -r:r + 1:options.step]
    dy, dx = dy.reshape(-1), dx.reshape(-1)
    space = np.exp(-0.5 * (dx**2 + dy**2) / options.sigma_space**2).astype(np.float32)
    chunk = max(1, (1 << 22) // len(dx))  # about 16 MB of float32 per temporary
    for start in range(0, len(ys), chunk):
        y, x = ys[start:start + chunk], xs[start:start + chunk]
        ny, nx = y[:, None] + dy[None], x[:, None] + dx[None]
        inside = (ny >= 0) & (ny < height) & (nx >= 0) & (nx < width)
        ny, nx = np.clip(ny, 0, height - 1), np.clip(nx, 0, width - 1)
        values = out[ny, nx]  # (P, N)
        colour = np.sum((guide[ny, nx] - guide[y, x][:, None]) ** 2, axis=-1)
        weight = np.exp(-0.5 * colour / options.sigma_color**2) * space[None] * (inside & (values > 0))
        order = np.argsort(values, axis=1)
        sorted_values = np.take_along_axis(values, order, axis=1)
        cumulative = np.cumsum(np.take_along_axis(weight, order, axis=1), axis=1)
        total = cumulative[:, -1]
        median = np.argmax(cumulative >= 0.5 * total[:, None], axis=1)
        chosen = sorted_values[np.arange(len(y)), median]
        out[y, x] = np.where(total > 0, chosen, out[y, x])
    return out


def refined_render_depth(depth: np.ndarray, rgb: np.ndarray, objects: Sequence[VirtualObject], K: np.ndarray,
                         T_world_cam: np.ndarray, options: RefineOptions = RefineOptions()) -> np.ndarray:
    """(H, W) float32: a rendered view's ``depth`` refined with its colour ``rgb`` (H, W, 3)
    where the objects (grown by ``options.margin``) cover it (``refine_depth``)."""
    height, width = np.shape(depth)
    where = object_footprint(objects, K, T_world_cam, width, height, options.margin)
    return refine_depth(depth, rgb, where, options)
