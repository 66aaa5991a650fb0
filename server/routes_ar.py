"""Augmented reality: virtual objects composited into a rendered view or an input frame,
hidden where the reconstructed scene is in front of them.

An object without a pose is placed in front of the camera (``ar_compose.in_front_of_camera``), and the
response says of every object whether it shows (``X-AR-Objects``): a composite with nothing in
it looked like success ("Done.") when the object lay outside the view or behind a wall.

The render of the background and the composite run in a render helper (``server.ar_compose``
through ``server.render_pools``); an input frame behind it is decoded in the decode helper and
travels with its sensor depth, which hides the objects wherever it measured (the map's depth
only fills its holes, in the render helper)."""

from __future__ import annotations

import json

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Response, status
from starlette.concurrency import run_in_threadpool

from ar import ObjectSpecError, load_objects_json
from server.ar_compose import Background
from server.assets import AssetStore
from server.decoding import DecodeFailed, shared_helper
from server.deps import get_assets, get_manager, get_render_pools, require_token
from server.errors import error_text, strip_paths
from server.inputs import input_frame
from server.render_calls import ViewCall, ar_composite
from server.render_pools import HELPER_RESPONSES, RenderPools, http_answers
from server.rendering import Camera, NoMapYet, check_pose, intrinsics_matrix
from server.routes_render import map_file, no_map_yet
from server.schemas import ARRequest, ErrorOut
from server.sessions import SessionManager, check_session_id
from slam import DataError

router = APIRouter(tags=["ar"], dependencies=[Depends(require_token)],
                   responses={401: {"model": ErrorOut}, 404: {"model": ErrorOut}})

TIMESTAMP_TOLERANCE_S = 1e-3
OBJECTS_HEADER = "X-AR-Objects"
"""Response header: a JSON list, per requested object, of ``{"state": "visible" | "hidden" |
"outside", "visible_pixels", "position"}`` (hidden: behind the scene everywhere; outside: not
in the camera's view at all, or behind it; position: the object's centre in the world)."""


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


def background_for(request: ARRequest, session_id: str, manager: SessionManager) -> ViewCall | Background:
    """What to composite into: a view to render (a ``ViewCall``, rendered in the render
    helper) or an input frame (decoded in the decode helper) with its camera."""
    T, K, size = _camera_override(request)
    if request.background == "render":
        if T is None or K is None:
            raise HTTPException(422,
                                "background 'render' needs T_world_cam and intrinsics")
        return ViewCall(map_file(manager, session_id), Camera(T, K, *size), manager.render_threads())
    index, agent = int(request.background.split(":", 1)[1]), request.agent
    state = manager.get(session_id)
    whose = "" if agent == 0 else f" of agent {agent}"
    try:
        # In the decode helper: the frame is an untrusted image (server.inputs).
        rgb, depth, frame_K, stamp = shared_helper().call(input_frame, state.sources, manager.session_dir(session_id),
                                                          index, agent)
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
    camera = Camera(T, frame_K if K is None else K, width, height)
    try:  # the map fills the sensor's holes under the objects; a session without one yet has none
        map_view = ViewCall(map_file(manager, session_id), camera, manager.render_threads())
    except HTTPException:
        map_view = None
    return Background(rgb, depth, camera, sensed=True, map_view=map_view)


def composite_in_helpers(pools: RenderPools, request: ARRequest, session_id: str, manager: SessionManager,
                         objects: list) -> tuple[bytes, list[dict]]:
    """The composite PNG and visibility report, made in a render helper. The helper is taken
    first, so that at most one input frame per render helper waits in this process."""
    with http_answers(f"AR composite of session {session_id}"), pools.render.lease() as helper:
        background = background_for(request, session_id, manager)
        return helper.call(ar_composite, background, objects, [o.T_world_obj is not None for o in request.objects])


@router.post("/api/sessions/{session_id}/ar", response_class=Response,
             responses={200: {"content": {"image/png": {}}, "description": "composited PNG",
                              "headers": {OBJECTS_HEADER: {
                                  "description": "JSON list, one entry per object: state (visible, hidden: behind "
                                                 "the scene everywhere, outside: not in the view), visible_pixels, "
                                                 "position (its centre in the world)",
                                  "schema": {"type": "string"}}}},
                        409: {"model": ErrorOut}, 422: {"model": ErrorOut}, **HELPER_RESPONSES},
             summary="Composite virtual objects into a view of the session, with occlusion")
async def ar_view(session_id: str, request: ARRequest, manager: SessionManager = Depends(get_manager),
                  pools: RenderPools = Depends(get_render_pools), assets: AssetStore = Depends(get_assets)) -> Response:
    check_session_id(session_id)
    try:
        with http_answers("AR objects"):  # assets are parsed in the decode helper: 503 when it stays busy
            objects = await run_in_threadpool(
                load_objects_json, [o.model_dump(exclude_none=True) for o in request.objects], assets.resolve)
    except (ObjectSpecError, ValueError, KeyError) as error:
        raise HTTPException(422, error_text(error)) from None
    try:
        data, report = await run_in_threadpool(composite_in_helpers, pools, request, session_id, manager, objects)
    except NoMapYet as error:
        raise no_map_yet(session_id, error) from None
    return Response(data, media_type="image/png", headers={OBJECTS_HEADER: json.dumps(report)})
