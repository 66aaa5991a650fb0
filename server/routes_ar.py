"""Augmented reality: virtual objects composited into a rendered view or an input frame,
hidden where the reconstructed scene is in front of them.

An object without a pose is placed in front of the camera (``in_front_of_camera``), and the
response says of every object whether it shows (``X-AR-Objects``): a composite with nothing in
it looked like success ("Done.") when the object lay outside the view or behind a wall."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Response, status
from starlette.concurrency import run_in_threadpool

from ar import UPRIGHT, ObjectSpecError, VirtualObject, composite, load_objects_json, rasterize_objects
from server.assets import AssetStore
from server.decoding import DecodeFailed, shared_helper
from server.deps import get_assets, get_manager, get_map_cache, require_token
from server.errors import error_text, strip_paths
from server.inputs import input_frame
from server.rendering import Camera, MapCache, check_pose, intrinsics_matrix, png_from_rgb, render, with_threads
from server.routes_render import load_map
from server.schemas import ARRequest, ErrorOut
from server.sessions import SessionManager, check_session_id
from slam import DataError

router = APIRouter(tags=["ar"], dependencies=[Depends(require_token)],
                   responses={401: {"model": ErrorOut}, 404: {"model": ErrorOut}})

TIMESTAMP_TOLERANCE_S = 1e-3
DEPTH_TOLERANCE_M = 0.01
"""How far an object may lie behind the scene and still show (as ``ar.composite``'s default)."""
PLACE_DISTANCE_M = 1.0
"""How far ahead an object without a pose goes when the image centre has no depth."""
CENTRE_WINDOW = 0.2
"""Share of the image's width and height, around its centre, whose median depth places an object."""
OBJECTS_HEADER = "X-AR-Objects"
"""Response header: a JSON list, per requested object, of ``{"state": "visible" | "hidden" |
"outside", "visible_pixels", "position"}`` (hidden: behind the scene everywhere; outside: not
in the camera's view at all, or behind it; position: the object's centre in the world)."""


@dataclass(frozen=True)
class Background:
    """What the objects are composited into."""

    rgb: np.ndarray
    """(H, W, 3) float32 in [0, 1]."""
    depth: np.ndarray
    """(H, W) float32 metres, 0 = unknown."""
    camera: Camera


def estimated_pose(manager: SessionManager, session_id: str, index: int, timestamp: float,
                   agent: int = 0) -> np.ndarray | None:
    """The session's estimate of ``agent``'s frame ``index``: from this run's pose events,
    else the agent's trajectory file (``trajectory.txt``, or ``trajectory_<agent>.txt`` when
    the run wrote one per agent)."""
    indices, _, poses = manager.tracked_poses(session_id, agent)
    hit = np.flatnonzero(indices == index)
    if len(hit):
        return poses[hit[0]]
    directory = manager.session_dir(session_id)
    path = directory / f"trajectory_{agent}.txt"
    if not path.is_file() and agent == 0:
        path = directory / "trajectory.txt"
    if not path.is_file():
        return None
    from slam import read_tum

    trajectory = read_tum(path)
    if len(trajectory) == 0:
        return None
    nearest = int(np.argmin(np.abs(trajectory.timestamps - timestamp)))
    if abs(trajectory.timestamps[nearest] - timestamp) > TIMESTAMP_TOLERANCE_S:
        return None
    return trajectory.poses[nearest]


def _camera_override(request: ARRequest) -> tuple[np.ndarray | None, np.ndarray | None, tuple[int, int] | None]:
    T = None
    if request.T_world_cam is not None:
        try:
            T = check_pose(np.array(request.T_world_cam, dtype=np.float64))
        except ValueError as error:
            raise HTTPException(422, str(error)) from None
    K = size = None
    if request.intrinsics is not None:
        i = request.intrinsics
        K, size = intrinsics_matrix(i.fx, i.fy, i.cx, i.cy), (i.width, i.height)
    return T, K, size


async def background_for(request: ARRequest, session_id: str, manager: SessionManager, maps: MapCache) -> Background:
    T, K, size = _camera_override(request)
    if request.background == "render":
        if T is None or K is None:
            raise HTTPException(422,
                                "background 'render' needs T_world_cam and intrinsics")
        camera = Camera(T, K, *size)
        mapset = await load_map(manager, maps, session_id)
        view = await run_in_threadpool(with_threads, manager.render_threads(), render, mapset, camera)
        return Background(np.asarray(view.rgb), np.asarray(view.depth), camera)
    index, agent = int(request.background.split(":", 1)[1]), request.agent
    state = manager.get(session_id)
    whose = "" if agent == 0 else f" of agent {agent}"
    try:
        # In the decode helper: the frame is an untrusted image (server.inputs).
        rgb, depth, frame_K, stamp = await run_in_threadpool(shared_helper().call, input_frame, state.sources,
                                                             manager.session_dir(session_id), index, agent)
    except DecodeFailed as error:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_ENTITY, f"background frame:{index}{whose}: {error}") from None
    except (KeyError, DataError) as error:
        message = strip_paths(error_text(error), manager.session_dir(session_id) / "input", "the input")
        # No such frame: 404; a frame that exists but cannot be used (corrupt, too large): 422.
        code = status.HTTP_404_NOT_FOUND if isinstance(error, KeyError) else status.HTTP_422_UNPROCESSABLE_ENTITY
        raise HTTPException(code, f"background frame:{index}{whose}: {message}") from None
    height, width = depth.shape
    if size is not None and size != (width, height):
        raise HTTPException(422,
                            f"intrinsics are for {size[0]}x{size[1]} but frame {index} is {width}x{height}")
    if T is None:
        T = estimated_pose(manager, session_id, index, stamp, agent)
        if T is None:
            raise HTTPException(status.HTTP_409_CONFLICT,
                                f"frame {index}{whose} has no estimated pose yet; give T_world_cam")
    return Background(rgb, depth, Camera(T, frame_K if K is None else K, width, height))


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
    """Per object, whether it shows in the composite (OBJECTS_HEADER), each rasterised alone
    at one sample per pixel against the scene depth, with the composite's depth test."""
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


@router.post("/api/sessions/{session_id}/ar", response_class=Response,
             responses={200: {"content": {"image/png": {}}, "description": "composited PNG",
                              "headers": {OBJECTS_HEADER: {
                                  "description": "JSON list, one entry per object: state (visible, hidden: behind "
                                                 "the scene everywhere, outside: not in the view), visible_pixels, "
                                                 "position (its centre in the world)",
                                  "schema": {"type": "string"}}}},
                        409: {"model": ErrorOut}, 422: {"model": ErrorOut}},
             summary="Composite virtual objects into a view of the session, with occlusion")
async def ar_view(session_id: str, request: ARRequest, manager: SessionManager = Depends(get_manager),
                  maps: MapCache = Depends(get_map_cache), assets: AssetStore = Depends(get_assets)) -> Response:
    check_session_id(session_id)
    try:
        objects = await run_in_threadpool(
            load_objects_json, [o.model_dump(exclude_none=True) for o in request.objects], assets.resolve)
    except (ObjectSpecError, ValueError, KeyError) as error:
        raise HTTPException(422, error_text(error)) from None
    background = await background_for(request, session_id, manager, maps)
    objects = [obj if given.T_world_obj is not None else in_front_of_camera(obj, background)
               for obj, given in zip(objects, request.objects)]
    camera = background.camera
    result = await run_in_threadpool(composite, background.rgb, background.depth, objects, camera.K,
                                     camera.T_world_cam, depth_tolerance=DEPTH_TOLERANCE_M)
    report = await run_in_threadpool(visibility, objects, background)
    return Response(await run_in_threadpool(png_from_rgb, result.rgb), media_type="image/png",
                    headers={OBJECTS_HEADER: json.dumps(report)})
