"""Camera-path videos: ``POST /api/sessions/{id}/render/path`` starts one,
``GET .../render/path/{job}`` tells its progress, ``GET .../render/path/{job}/video`` serves the
MP4 (colour | depth | normals side by side) once it is written.

Videos render in the video helper (``server.path_jobs``); a video of more than
``budget.MAX_VIDEO_PIXELS`` rendered pixels gets 422, one more than ``budget.MAX_VIDEO_JOBS``
queued or rendering gets 429."""

from __future__ import annotations

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, status
from fastapi.responses import FileResponse

from server.budget import MAX_VIDEO_PIXELS
from server.deps import get_manager, get_path_jobs, get_viewer, require_token
from server.path_jobs import PathJob, PathJobs, TooManyJobs
from server.render_calls import VideoCall
from server.rendering import check_pose, intrinsics_matrix
from server.routes_render import map_file
from server.schemas import ErrorOut, PathJobOut, PathPreview, PathRequest
from server.sessions import SessionManager, check_session_id
from server.viewer import ViewerAdapter
from slam.camera_path import CameraPath, path_poses

PREVIEW_FRAMES = 120
"""Points of a path's preview line in the viewer."""

router = APIRouter(prefix="/api/sessions", tags=["render"], dependencies=[Depends(require_token)],
                   responses={401: {"model": ErrorOut}, 404: {"model": ErrorOut}})


def job_out(job: PathJob) -> PathJobOut:
    return PathJobOut(id=job.id, state=job.state, frames_done=job.frames_done, frames_total=job.frames_total,
                      error=job.error, video=f"/api/sessions/{job.session_id}/render/path/{job.id}/video")


def camera_path(request: PathRequest | PathPreview) -> CameraPath:
    """The request's path; 422 naming the keyframe that is not a rigid pose."""
    keyframes = []
    for k, matrix in enumerate(request.keyframes):
        try:
            keyframes.append(check_pose(np.array(matrix, dtype=np.float64)))
        except ValueError as error:
            raise HTTPException(422, f"keyframes[{k}]: {error}") from None
    duration, fps = (request.duration_s, request.fps) if isinstance(request, PathRequest) else (PREVIEW_FRAMES, 1.0)
    try:
        return CameraPath(np.stack(keyframes), duration, fps, request.loop)
    except ValueError as error:
        raise HTTPException(422, str(error)) from None


@router.post("/{session_id}/render/path", response_model=PathJobOut, status_code=status.HTTP_202_ACCEPTED,
             responses={409: {"model": ErrorOut}, 422: {"model": ErrorOut},
                        429: {"model": ErrorOut, "description": "as many videos as the server takes are queued or "
                                                                "rendering; retry after Retry-After seconds",
                              "headers": {"Retry-After": {"schema": {"type": "integer"},
                                                          "description": "seconds to wait"}}}},
             summary="Render a video along a smooth camera path through keyframe poses (MP4, in the background)")
def start_path_video(session_id: str, request: PathRequest, manager: SessionManager = Depends(get_manager),
                     jobs: PathJobs = Depends(get_path_jobs)) -> PathJobOut:
    """The map as it is now (a running session's newest ``map.pt``), rendered in the video
    helper; poll the job for progress. A video may render at most MAX_VIDEO_PIXELS pixels."""
    path = camera_path(request)
    i = request.intrinsics
    check_video_size(path.frame_count, i.width, i.height)
    call = VideoCall(map_file(manager, session_id), path, intrinsics_matrix(i.fx, i.fy, i.cx, i.cy), i.width,
                     i.height, tuple(request.outputs), out_file="", threads=manager.render_threads(),
                     depth_range=request.depth_range,
                     crop=None if request.crop is None else (request.crop.min, request.crop.max))
    try:
        return job_out(jobs.start(session_id, manager.session_dir(session_id), call))
    except TooManyJobs as error:
        raise HTTPException(status.HTTP_429_TOO_MANY_REQUESTS, str(error),
                            headers={"Retry-After": str(error.retry_after_s)}) from None


def check_video_size(frames: int, width: int, height: int) -> None:
    """422 saying the numbers when frames x width x height passes MAX_VIDEO_PIXELS."""
    pixels = frames * width * height
    if pixels > MAX_VIDEO_PIXELS:
        raise HTTPException(422,
                            f"the video would render {frames} frames of {width}x{height} = {pixels / 1e6:,.1f} "
                            f"million pixels; at most {MAX_VIDEO_PIXELS / 1e6:,.0f} million are rendered per video "
                            f"(a shorter duration_s, a lower fps or a smaller image)")


def _job(session_id: str, job_id: str, jobs: PathJobs) -> PathJob:
    job = jobs.get(check_session_id(session_id), job_id)
    if job is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"session {session_id} has no video job {job_id!r}")
    return job


@router.get("/{session_id}/render/path/{job_id}", response_model=PathJobOut, summary="Progress of a path video")
def path_video_status(session_id: str, job_id: str, jobs: PathJobs = Depends(get_path_jobs)) -> PathJobOut:
    return job_out(_job(session_id, job_id, jobs))


@router.get("/{session_id}/render/path/{job_id}/video", response_class=FileResponse,
            responses={200: {"content": {"video/mp4": {}}}, 409: {"model": ErrorOut}},
            summary="The MP4 of a finished path video")
def path_video(session_id: str, job_id: str, jobs: PathJobs = Depends(get_path_jobs)) -> FileResponse:
    job = _job(session_id, job_id, jobs)
    if job.state != "finished" or not job.file.is_file():
        detail = f"video {job_id} is {job.state}" + (f": {job.error}" if job.error else
                                                     f" ({job.frames_done} of {job.frames_total} frames)")
        raise HTTPException(status.HTTP_409_CONFLICT, detail)
    return FileResponse(job.file, media_type="video/mp4", filename=f"{session_id}_path_{job_id}.mp4")


@router.put("/{session_id}/render/path/preview", status_code=status.HTTP_204_NO_CONTENT, tags=["viewer"],
            responses={422: {"model": ErrorOut}}, summary="Draw a camera path in the 3D viewer")
def preview_path(session_id: str, request: PathPreview, manager: SessionManager = Depends(get_manager),
                 viewer: ViewerAdapter | None = Depends(get_viewer)) -> None:
    """The smooth path through the keyframes, as the video will fly it, in the session's scene."""
    manager.get(check_session_id(session_id))
    path = camera_path(request)
    if viewer is not None:
        viewer.show_path(session_id, path_poses(path))


@router.delete("/{session_id}/render/path/preview", status_code=status.HTTP_204_NO_CONTENT, tags=["viewer"],
               summary="Remove the camera path drawn in the 3D viewer")
def clear_path(session_id: str, manager: SessionManager = Depends(get_manager),
               viewer: ViewerAdapter | None = Depends(get_viewer)) -> None:
    manager.get(check_session_id(session_id))
    if viewer is not None:
        viewer.show_path(session_id, None)
