"""The calls that run in the render and video helpers (``server.render_pools``), never in the
API process: renders, picks, AR composites, mesh exports and camera-path videos.

Each takes a small frozen description (a map's path, a camera, the torch threads to use) and
returns encoded bytes or a small result. A helper loads ``map.pt`` itself and keeps the last
few in :data:`HELPER_MAPS` (keyed by path, modification time and size), so the API process
never loads a map for these routes. Errors a client caused come back as
:class:`RequestProblem` (its HTTP status and message).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from server.helper_pool import report_progress
from server.rendering import (
    Camera,
    MapCache,
    MeshFiles,
    NoMapYet,
    PickResult,
    mesh_bytes_from_arrays,
    mesh_from_arrays,
    pick_surface,
    png_from_depth,
    png_from_depth_preview,
    png_from_normals,
    png_from_rgb,
    render,
    with_threads,
)

HELPER_CACHED_MAPS = 2
"""Maps one helper keeps loaded (the sessions being looked at now)."""
HELPER_MAPS = MapCache(HELPER_CACHED_MAPS)
HELPER_MESH_FILES = MeshFiles()

PRELOAD = ("slam", "ar", "server.render_calls", "trimesh", "imageio_ffmpeg")
"""What a render or video helper imports before its memory cap is set."""


class RequestProblem(Exception):
    """The request cannot be served as asked: ``status`` and a message for the client."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(status, detail)
        self.status, self.detail = status, detail

    def __str__(self) -> str:
        return self.detail


@dataclass(frozen=True)
class ViewCall:
    """One view of a session's map."""

    map_path: str
    camera: Camera
    threads: int
    """Torch threads the helper renders with (``SessionManager.render_threads``)."""
    crop: tuple | None = None
    """(min (3,), max (3,)) world box: only what lies inside is rendered."""


def helper_map(map_path: str):
    """The MapSet at ``map_path``, loaded once per file version in this helper."""
    return HELPER_MAPS.get(map_path, Path(map_path))


def render_view_of(call: ViewCall):
    """``slam.views.RenderedView`` of the call's camera."""
    return with_threads(call.threads, render, helper_map(call.map_path), call.camera, crop=call.crop)


def depth_range(depth: np.ndarray, low: float | None, high: float | None) -> tuple[float, float] | None:
    """The preview's colour range: the given ends, the view's own percentiles for the rest (an
    automatic end moved inside a given one, which a schema-valid request may put anywhere);
    RequestProblem 422 when two given ends cross."""
    if low is None and high is None:
        return None
    from slam.path_video import auto_depth_range

    auto = auto_depth_range(depth)
    near = auto[0] if low is None else low
    far = auto[1] if high is None else high
    if low is None and not near < far:
        near = far / 2
    elif high is None and not near < far:
        far = near * 2
    if not near < far:
        raise RequestProblem(422, f"depth_min ({near:g} m) must be below depth_max ({far:g} m)")
    return near, far


def render_png(call: ViewCall, output: str, depth_min: float | None = None, depth_max: float | None = None) -> bytes:
    """The view as PNG: ``color``, ``depth`` (16-bit mm), ``depth_preview`` or ``normals``."""
    view = render_view_of(call)
    if output == "color":
        return png_from_rgb(view.rgb)
    if output == "depth":
        return png_from_depth(view.depth)
    if output == "normals":
        return png_from_normals(view.depth, call.camera.K)
    return png_from_depth_preview(view.depth, depth_range(view.depth, depth_min, depth_max))


def pick(call: ViewCall, u: float, v: float) -> PickResult | None:
    """The surface under pixel (u, v) of the call's camera (``rendering.pick_surface``)."""
    return with_threads(call.threads, pick_surface, helper_map(call.map_path), call.camera, u, v)


def ar_composite(background, objects: list, posed: list[bool]) -> tuple[bytes, list[dict]]:
    """The AR composite PNG and its visibility report (``server.ar_compose``); ``background``
    is a ``ViewCall`` (render it here) or an ``ar_compose.Background`` (an input frame: its
    sensor depth, the map rendered here only for the holes under the objects)."""
    from functools import partial

    from server.ar_compose import Background, composite_png

    if isinstance(background, ViewCall):
        view = render_view_of(background)
        background = Background(np.asarray(view.rgb), np.asarray(view.depth), background.camera)
    map_depth = None if background.map_view is None else partial(window_depth, background.map_view)
    return composite_png(background, objects, posed, map_depth)


def window_depth(call: ViewCall, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(height, width) depth of the call's map at its pose through intrinsics ``K``; zeros when
    the map cannot be loaded (the frame's own depth then stands alone)."""
    from dataclasses import replace

    try:
        view = render_view_of(replace(call, camera=Camera(call.camera.T_world_cam, K, width, height)))
    except NoMapYet:
        return np.zeros((height, width), dtype=np.float32)
    return np.asarray(view.depth)


@dataclass(frozen=True)
class PlyMesh:
    """A session's written ``mesh.ply``."""

    path: str


@dataclass(frozen=True)
class LiveMesh:
    """A running session's live per-map meshes: (V,3 / F,3 / V,3 uint8) world-frame parts."""

    parts: list


@dataclass(frozen=True)
class MapMesh:
    """The mesh extracted from a session's ``map.pt``."""

    map_path: str
    threads: int


def export_mesh(source: PlyMesh | LiveMesh | MapMesh, file_format: str, box: tuple | None = None) -> bytes:
    """The source's mesh encoded as ``file_format``, only its faces inside ``box`` ((min,
    max) world corners) when given; NoMapYet for an empty mesh, RequestProblem 409 for a box
    with no face inside."""
    if box is None:
        return _whole_mesh_bytes(source, file_format)
    from slam import crop_mesh, mesh_to_bytes

    mesh = crop_mesh(_whole_mesh(source), *box)
    if len(mesh.faces) == 0:
        raise RequestProblem(409, "crop: no face of the mesh lies inside the box")
    return mesh_to_bytes(mesh, file_format)


def _whole_mesh_bytes(source, file_format: str) -> bytes:
    if isinstance(source, PlyMesh):
        return HELPER_MESH_FILES.convert(Path(source.path), file_format)
    if isinstance(source, LiveMesh):
        return mesh_bytes_from_arrays(source.parts, file_format)
    return with_threads(source.threads, HELPER_MESH_FILES.extract_from_map, helper_map(source.map_path), file_format)


def _whole_mesh(source):
    if isinstance(source, PlyMesh):
        import trimesh

        return trimesh.load(source.path, file_type="ply", process=False)
    if isinstance(source, LiveMesh):
        return mesh_from_arrays(source.parts)
    from slam import extract_mesh

    mesh = with_threads(source.threads, extract_mesh, helper_map(source.map_path))
    if len(mesh.faces) == 0:
        raise NoMapYet("the map has no surface yet")
    return mesh


@dataclass(frozen=True)
class VideoCall:
    """A camera-path video of a session's map, written to ``out_file``."""

    map_path: str
    path: object
    """``slam.camera_path.CameraPath``."""
    K: np.ndarray
    """(3, 3) intrinsics of every frame."""
    width: int
    height: int
    outputs: tuple[str, ...]
    out_file: str
    threads: int
    depth_range: tuple[float, float] | None = None
    crop: tuple | None = None


def render_video(call: VideoCall) -> None:
    """Render every frame and encode the MP4 (written beside ``out_file``, then moved onto
    it); reports (frames done, frames total) as it goes."""
    from slam.path_video import path_frames, write_mp4

    out = Path(call.out_file)
    partial = out.with_suffix(".part.mp4")
    try:
        frames = path_frames(helper_map(call.map_path), call.path, call.K, call.width, call.height, call.outputs,
                             depth_range=call.depth_range, crop=call.crop, on_frame=report_progress)
        with_threads(call.threads, write_mp4, frames, partial, call.path.fps)
        partial.replace(out)
    finally:
        partial.unlink(missing_ok=True)
