"""Novel views of a session's map: colour or depth images for any camera, and surface picking.

The views are rendered in the render helpers (``server.render_pools``), which load the map
themselves: the API process only checks that ``map.pt`` exists and waits for the PNG."""

from __future__ import annotations

from typing import Literal

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query, Response, status
from pydantic import ValidationError

from server.deps import get_manager, get_render_pools, get_viewer, require_token
from server.errors import validation_message
from server import render_calls
from server.render_calls import ViewCall, depth_range  # noqa: F401 - depth_range: tests use it from here
from server.render_pools import HELPER_RESPONSES, RenderPools, http_answers
from server.rendering import Camera, NoMapYet, check_pose, intrinsics_matrix
from server.routes_series import estimated_trajectory
from server.schemas import (
    CameraRequest,
    CropBox,
    ErrorOut,
    Intrinsics,
    PickOut,
    PickRequest,
    SessionCameraOut,
    ViewerCameraOut,
    ViewerInfo,
)
from server.series import source_camera
from server.upload import MAX_AGENTS
from server.sessions import ENDED, SessionManager, check_session_id
from server.viewer import ViewerAdapter

router = APIRouter(tags=["render"], dependencies=[Depends(require_token)],
                   responses={401: {"model": ErrorOut}, 404: {"model": ErrorOut}})

PNG = {"content": {"image/png": {}}, "description": "PNG image"}


def camera_from(request: CameraRequest) -> Camera:
    """Validated pinhole camera; 422 with the reason for a matrix that is not a rigid pose."""
    try:
        T = check_pose(np.array(request.T_world_cam, dtype=np.float64))
    except ValueError as error:
        raise HTTPException(422, str(error)) from None
    i = request.intrinsics
    return Camera(T, intrinsics_matrix(i.fx, i.fy, i.cx, i.cy), i.width, i.height)


def map_file(manager: SessionManager, session_id: str) -> str:
    """The path of a session's newest ``map.pt`` (409 while it has none). Only its existence
    is checked here: the helpers load it (``server.render_calls``)."""
    directory = manager.session_dir(check_session_id(session_id))
    manager.get(session_id)
    path = directory / "map.pt"
    if not path.is_file():
        raise no_map_yet(session_id, NoMapYet("the session has no map yet: map.pt is written after the first keyframes"))
    return str(path)


def no_map_yet(session_id: str, error: NoMapYet) -> HTTPException:
    return HTTPException(status.HTTP_409_CONFLICT, f"session {session_id}: {error}")


@router.post("/api/sessions/{session_id}/render", response_class=Response,
             responses={200: PNG, 409: {"model": ErrorOut}, 422: {"model": ErrorOut}, **HELPER_RESPONSES},
             summary="Render the map from a camera: colour PNG, or depth as a 16-bit PNG in millimetres")
async def render_image(session_id: str, request: CameraRequest,
                      output: Literal["color", "depth", "depth_preview", "normals"] = Query(
                          "color", description="color: RGB PNG; depth: 16-bit PNG in millimetres (0 = no surface); "
                                               "depth_preview: colour-mapped 8-bit PNG for display; normals: the "
                                               "surface normals (from the rendered depth) as colours"),
                      depth_min: float | None = Query(None, ge=0, description="depth_preview: metres shown red"),
                      depth_max: float | None = Query(None, gt=0, description="depth_preview: metres shown blue"),
                      manager: SessionManager = Depends(get_manager),
                      pools: RenderPools = Depends(get_render_pools)) -> Response:
    """Works while the session runs (the newest ``map.pt``) and after it ended. Rendered and
    encoded in a render helper (``server.render_pools``: 503 with Retry-After when they are
    all busy, 504 past the time limit)."""
    if depth_min is not None and depth_max is not None and not depth_min < depth_max:
        raise HTTPException(422, f"depth_min ({depth_min:g} m) must be below depth_max ({depth_max:g} m)")
    call = view_call(manager, session_id, camera_from(request), request.crop)
    try:
        with http_answers(f"render of session {session_id}"):
            data = await pools.render.run(render_calls.render_png, call, output, depth_min, depth_max)
    except NoMapYet as error:
        raise no_map_yet(session_id, error) from None
    return Response(data, media_type="image/png")


def view_call(manager: SessionManager, session_id: str, camera: Camera, crop=None) -> ViewCall:
    """What a helper needs to render ``camera``'s view of the session's newest map."""
    box = None if crop is None else (crop.min, crop.max)
    return ViewCall(map_file(manager, session_id), camera, manager.render_threads(), box)


@router.post("/api/sessions/{session_id}/pick", response_model=PickOut,
             responses={409: {"model": ErrorOut}, 422: {"model": ErrorOut}, **HELPER_RESPONSES},
             summary="Back-project a pixel of a rendered view onto the map's surface")
async def pick(session_id: str, request: PickRequest, manager: SessionManager = Depends(get_manager),
                     pools: RenderPools = Depends(get_render_pools)) -> PickOut:
    """The world point (and surface normal) seen at pixel (u, v); used to place AR objects."""
    camera = camera_from(request)
    if request.u > camera.width or request.v > camera.height:
        raise HTTPException(422,
                            f"pixel ({request.u}, {request.v}) is outside the {camera.width}x{camera.height} image")
    call = view_call(manager, session_id, camera)
    try:
        with http_answers(f"pick in session {session_id}"):
            result = await pools.render.run(render_calls.pick, call, request.u, request.v)
    except NoMapYet as error:
        raise no_map_yet(session_id, error) from None
    if result is None:
        return PickOut(hit=False)
    return PickOut(hit=True, point=result.point.tolist(), normal=result.normal.tolist(), depth=result.depth)


@router.get("/api/sessions/{session_id}/camera", response_model=SessionCameraOut,
            responses={404: {"model": ErrorOut}, 409: {"model": ErrorOut}},
            summary="The newest tracked frame's pose and camera (a view that shows what the camera saw)")
def newest_camera(session_id: str, agent: int = Query(0, ge=0, le=MAX_AGENTS - 1, description="agent (camera)"),
                  manager: SessionManager = Depends(get_manager)) -> SessionCameraOut:
    """The pose is the last of ``GET .../trajectory`` (the written, refined one once the session
    ended; the tracked one, moved with its map by loop closures, while it runs); the camera is
    the one its frames were tracked with, or after a server restart the input's."""
    check_session_id(session_id)
    agents = manager.agent_count(session_id)
    if agent >= agents:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"session {session_id} has no agent {agent}: it has "
                                                       f"{agents} agent{'s' if agents != 1 else ''}")
    trajectory = estimated_trajectory(manager, session_id, agent)
    newest = manager.newest_camera(session_id, agent)
    sources = manager.get(session_id).sources
    if newest is not None:
        camera = newest[2]
    else:
        camera = source_camera(sources[agent]) if agent < len(sources) else None
    if camera is None or not len(trajectory.timestamps):
        raise HTTPException(status.HTTP_409_CONFLICT, f"session {session_id}: no tracked frame of agent {agent} yet")
    timestamp = float(trajectory.timestamps[-1])
    index = newest[0].index if newest is not None and abs(newest[0].timestamp - timestamp) < 1e-6 else None
    K = camera.K
    intrinsics = Intrinsics(fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                            width=camera.width, height=camera.height)
    return SessionCameraOut(agent=agent, index=index, timestamp=timestamp,
                            T_world_cam=np.asarray(trajectory.poses[-1], np.float64).tolist(), intrinsics=intrinsics)


@router.get("/api/viewer", response_model=ViewerInfo, tags=["viewer"], summary="Is the 3D viewer running")
def viewer_info(viewer: ViewerAdapter | None = Depends(get_viewer)) -> ViewerInfo:
    if viewer is None or not viewer.running:
        return ViewerInfo(enabled=False, port=None, clients=0)
    return ViewerInfo(enabled=True, port=viewer.port, clients=viewer.client_count(), selected=viewer.selected)


@router.post("/api/viewer/select/{session_id}", status_code=204, tags=["viewer"],
             summary="Show this session in the 3D viewer")
def viewer_select(session_id: str, manager: SessionManager = Depends(get_manager),
                  viewer: ViewerAdapter | None = Depends(get_viewer)) -> Response:
    state = manager.get(check_session_id(session_id))
    if viewer is None:
        return Response(status_code=204)
    if not viewer.has_session(session_id) and state.status in ENDED:
        # A session from before a restart: show its results from disk.
        directory = manager.session_dir(session_id)
        viewer.load_finished(session_id, directory / "mesh.ply", _agent_positions(directory, state.agents))
    viewer.select(session_id)
    return Response(status_code=204)


def _agent_positions(directory, agents: int) -> dict[int, np.ndarray]:
    """Camera centres per agent from a finished session's trajectory files (missing ones left out)."""
    paths = {0: directory / "trajectory.txt"}
    paths.update({k: directory / f"trajectory_{k}.txt" for k in range(1, max(agents, 1))})
    positions = {k: _positions(path) for k, path in paths.items()}
    return {k: v for k, v in positions.items() if v is not None}


def _positions(path) -> np.ndarray | None:
    from slam import DataError, read_tum

    try:
        return read_tum(path).positions if path.is_file() else None
    except DataError:
        return None


@router.get("/api/viewer/camera", response_model=ViewerCameraOut, tags=["viewer"],
            responses={409: {"model": ErrorOut}},
            summary="The current camera of the 3D viewer (the browser that moved last)")
def viewer_camera(width: int = Query(320, ge=16, le=2048, description="image width wanted; aspect kept"),
                  viewer: ViewerAdapter | None = Depends(get_viewer)) -> ViewerCameraOut:
    camera = None if viewer is None else viewer.current_camera()
    if camera is None:
        raise HTTPException(status.HTTP_409_CONFLICT, "no browser is connected to the 3D viewer")
    fx, fy, cx, cy, w, h = camera.intrinsics(width)
    try:
        intrinsics = Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=min(h, 2048))
    except ValidationError as error:  # a browser window so wide that the view is no pinhole camera
        raise HTTPException(status.HTTP_409_CONFLICT,
                            f"the viewer's camera cannot be rendered: {validation_message(error.errors())}") from None
    return ViewerCameraOut(T_world_cam=camera.T_world_cam.tolist(), intrinsics=intrinsics)


@router.get("/api/viewer/crop", response_model=CropBox, tags=["viewer"], responses={409: {"model": ErrorOut}},
            summary="The crop box of the 3D viewer (the browser that changed its crop last, of those that crop)")
def viewer_crop(viewer: ViewerAdapter | None = Depends(get_viewer)) -> CropBox:
    box = None if viewer is None else viewer.current_crop()
    if box is None:
        raise HTTPException(status.HTTP_409_CONFLICT, "no browser crops the 3D viewer (tick Crop in its Crop box)")
    return CropBox(min=box.lo, max=box.hi)
