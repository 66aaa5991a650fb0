"""``GET /api/sessions/{id}/series``: what the page plots (``server.series``), also while running."""

from __future__ import annotations

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query, status

from server.deps import get_manager, require_token
from server.routes_sessions import trajectory_file
from server.schemas import ErrorOut, SeriesOut
from server.series import NOTHING, compare, rounded, source_facts
from server.sessions import ENDED, SessionManager, check_session_id
from server.upload import MAX_AGENTS
from slam import DataError, Trajectory, read_tum

router = APIRouter(prefix="/api/sessions", tags=["sessions"], dependencies=[Depends(require_token)],
                   responses={401: {"model": ErrorOut}, 404: {"model": ErrorOut}})

_EMPTY = Trajectory(np.zeros(0), np.zeros((0, 4, 4)))


def estimated_trajectory(manager: SessionManager, session_id: str, agent: int) -> Trajectory:
    """The agent's trajectory as ``GET .../trajectory`` serves it: the written file once the
    session ended, else the poses tracked so far (the file when this server did not run it)."""
    path = trajectory_file(manager.session_dir(session_id), agent)
    if not (path.is_file() and manager.get(session_id).status in ENDED):
        _, stamps, poses = manager.tracked_poses(session_id, agent)
        if len(stamps) or not path.is_file():
            return Trajectory(stamps, poses)
    try:
        return read_tum(path)
    except DataError:
        return _EMPTY


@router.get("/{session_id}/series", response_model=SeriesOut,
            summary="Trajectory against the ground truth, error per frame, frames/s over time (for plots)")
def get_series(session_id: str,
               agent: int = Query(0, ge=0, le=MAX_AGENTS - 1, description="agent (camera); 0 is the first"),
               manager: SessionManager = Depends(get_manager)) -> SeriesOut:
    """The estimate is aligned onto the ground truth as the ATE aligns it (timestamp pairs
    within 20 ms, rigid Umeyama), so ``estimated`` and ``ground_truth`` share one frame and
    ``error_m`` is each frame's distance after alignment; without ground truth the estimate
    is in the session's world frame and the error fields are null; ``ground_truth_note`` says
    why an input's ground truth is not shown (too large to read). ``fps_*`` sample the
    tracking phase (the status's frames/s is ``fps_frames[-1] / fps_time_s[-1]``)."""
    state = manager.get(check_session_id(session_id))
    agents = manager.agent_count(session_id)
    if agent >= agents:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"session {session_id} has no agent {agent}: it has "
                                                       f"{agents} agent{'s' if agents != 1 else ''}")
    sources = state.sources
    facts = source_facts(sources[agent]) if agent < len(sources) else NOTHING
    truth = facts.truth
    estimate = estimated_trajectory(manager, session_id, agent)
    comparison = compare(estimate, truth)
    samples = manager.fps_samples(session_id)
    return SeriesOut(
        agent=agent, timestamps=rounded(estimate.timestamps), estimated=rounded(comparison.estimated),
        aligned=comparison.aligned, ground_truth=None if truth is None else rounded(truth.positions),
        ground_truth_note=facts.note,
        error_m=rounded(comparison.errors) if comparison.aligned else None, ate_rmse_m=comparison.rmse,
        fps_time_s=[t for t, _ in samples], fps_frames=[n for _, n in samples])
