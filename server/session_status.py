"""A session's status and its fold of the worker's events: what ``GET /api/sessions/<id>`` says.

``SessionStatus`` is what the API reports (and ``session.json`` holds); :class:`StatusFold`
derives it from the session's events, read through the one fold of them
(``server.session_state.SessionState``, which also keeps the trajectories and live meshes the
trajectory and AR endpoints serve). The scheduler (``server.sessions.SessionManager``) owns one
``StatusFold`` per session, applies every event under its lock and persists what the fold says
to persist; what the fold does not know (the queue, the worker's start and end, the session
folder) stays with the scheduler.

``phase`` refines ``running``: ``tracking`` (frames are read), ``refining`` (the final bundle
adjustment and mesh), ``writing`` (trajectories, ``run.json``); ``queued`` before and ``done``
after, whatever the session's end (``status`` says which). The end of a run is several steps
(``slam.events.END_STEPS``), each announced by its own PhaseEvent: ``phase_step`` names the one
that runs, ``phase_started`` says since when (the step's start), ``phase_estimate_s`` about how
long it should take where something predicts it (a time cap, a forecast from the run so far).
A step may run past its estimate: the page then says so instead of showing a bound.

A stream's frames (``frames_received``, ``frames_dropped``, ``frames_refused``: see
``server.stream``) come from its input while it runs (:func:`stream_fields`) and are kept in
the status once it ends (:func:`with_stream_counts`).

``fps`` has one definition, shared by the status, the page and the viewer's panel (the
viewer gets StatsEvents with this value): frames tracked (all agents) per second of the
tracking phase, from its PhaseEvent to the latest pose, both as the API process receives them.
It is fixed once tracking ends, so the final refinement does not drag it down (``run.json``'s
``fps`` divides by the whole run's wall time instead). Its history, one sample per
FPS_SAMPLE_S, is kept for the page's plot (``fps_samples``; ``progress.json`` once ended).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from datetime import datetime, timezone
from typing import Callable

import numpy as np

from server.execution import WorkerInfo
from server.session_state import Change, SessionState
from server.worker import SourceSpec, WorkerDone
from slam import FinishedEvent

STATUSES = ("queued", "running", "finished", "failed", "cancelled")
ENDED = ("finished", "failed", "cancelled")
PHASES = ("queued", "starting", "tracking", "refining", "writing", "done")
FPS_SAMPLE_S = 0.5
"""Shortest time between two samples of the frames/s history."""
MIN_FPS_SPAN_S = 0.25
"""Shortest tracking time frames/s is computed over."""


def now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


@dataclass(frozen=True)
class SessionStatus:
    """What the API reports for a session (also the content of ``session.json``)."""

    id: str
    status: str
    created: str
    """ISO 8601, UTC."""
    source: str
    preset: str
    frames_done: int = 0
    latest_frame: int | None = None
    """Agent 0's newest tracked frame (its index in the input); None before the first. A live
    stream tracks only the newest frames, so its client waits on this, not ``frames_done``."""
    frames_total: int | None = None
    fps: float = 0.0
    keyframes: int = 0
    maps: int = 0
    loops: int = 0
    agents: int = 1
    """Agents (cameras) of the session: the upload's parts, or those a stream has seen so far."""
    phase: str = "queued"
    """One of PHASES (see the module doc)."""
    phase_started: str | None = None
    """ISO 8601, UTC: when the current phase began (None for sessions from before it was kept)."""
    phase_budget_s: float | None = None
    """No longer set (``phase_estimate_s`` replaced it); kept so older ``session.json`` files load."""
    phase_step: str | None = None
    """The end-of-run step that runs (``slam.events.END_STEPS``); None outside them."""
    phase_estimate_s: float | None = None
    """About how many seconds ``phase_step`` should take; None when nothing predicts it."""
    frames_received: int | None = None
    """A stream's frames accepted by the server (all agents); None for other sources."""
    frames_dropped: int | None = None
    """A stream's frames dropped because its buffer was full (503); None for other sources."""
    ate_rmse_m: float | None = None
    """Agent 0's ATE RMSE in metres (so far while running, final after); None without ground truth."""
    frames_skipped: int = 0
    """Input frames left out because they could not be read (an upload's corrupt frames, a
    stream's refused ones); known once the session has ended."""
    color_camera: str | None = None
    """How the (first) source's colour came onto the depth camera, in words (``run.json``'s
    ``color_cameras``: given, or estimated and applied or not); known once the session has ended."""
    error: str | None = None
    spec: SourceSpec = field(default_factory=lambda: SourceSpec(kind="synthetic"))
    """The (first agent's) source."""
    specs: tuple[SourceSpec, ...] = ()
    """Every agent's source, in agent order, for a collaborative session; () for one source."""
    worker: WorkerInfo | None = None
    """Where the session runs or ran (None while queued, and for sessions from before it was kept)."""

    @property
    def sources(self) -> tuple[SourceSpec, ...]:
        return self.specs or (self.spec,)

    def to_json(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_json(data: dict) -> "SessionStatus":
        data = dict(data)
        data.setdefault("phase", "done" if data.get("status") in ENDED else "queued")
        spec = _spec_from_json(data.pop("spec"))
        specs = tuple(_spec_from_json(s) for s in data.pop("specs", None) or ())
        worker = data.pop("worker", None)
        worker = WorkerInfo(**worker) if isinstance(worker, dict) else None
        return SessionStatus(spec=spec, specs=specs, worker=worker, **data)


def _spec_from_json(spec: dict) -> SourceSpec:
    spec = dict(spec)
    for key in ("intrinsics", "color_intrinsics", "depth_to_color"):
        if spec.get(key) is not None:
            spec[key] = tuple(spec[key])
    return SourceSpec(**spec)


@dataclass(frozen=True)
class StatusStep:
    """What one event did to a session's status, and what the scheduler is to do about it."""

    status: SessionStatus
    persist: bool = False
    """Write ``session.json`` now (a phase change)."""
    dirty: bool = False
    """Write it within the scheduler's persist interval."""
    event: object = None
    """The event as the event sinks (the viewer) get it: a StatsEvent carries the status's fps."""
    finished: FinishedEvent | None = None
    """The runtime said how the run ended."""


class StatusFold:
    """One session's status as its events make it (module doc). Not thread-safe: the
    scheduler applies events under its lock."""

    def __init__(self) -> None:
        self.scene = SessionState(keep_meshes=True)
        """The events' fold: tracks (poses following their maps), live meshes, counters."""
        self.tracking_started: float | None = None
        """time.monotonic() when the tracking phase began (see the module doc on fps)."""
        self.fps_samples: list[tuple[float, int]] = []
        """(seconds since tracking began, frames tracked) at most every FPS_SAMPLE_S."""

    def apply(self, status: SessionStatus, event: object, started_at: float | None = None,
              now: float | None = None) -> StatusStep:
        """Fold in one event. ``started_at``: time.monotonic() when the worker started (no
        longer used: each end-of-run step carries its own estimate); ``now``: time.monotonic()
        (default: now)."""
        now = time.monotonic() if now is None else now
        change = self.scene.apply(event)
        step = StatusStep(status, event=event, finished=change.finished)
        if change.stats is not None:
            step = self._on_stats(status, change, event)
        elif change.phase is not None and change.phase in PHASES:
            step = self._on_phase(status, change, now, event)
        elif change.keyframe:
            # The mapper's statistics come at the end; keyframes as they are taken.
            step = StatusStep(replace(status, keyframes=max(self.scene.keyframe_events, status.keyframes)),
                              dirty=True, event=event)
        elif change.frame is not None:
            # Stats come every few frames; poses give the progress in between.
            frames = len(self.scene.tracks)
            agent, index = change.frame
            latest = status.latest_frame if agent != 0 else max(index, status.latest_frame or 0)
            status = replace(status, frames_done=max(frames, status.frames_done), latest_frame=latest,
                             agents=max(status.agents, change.frame[0] + 1), fps=self._tracking_fps(frames, now))
            step = StatusStep(status, dirty=True, event=event)
        elif change.submap is not None:
            agent = self.scene.maps.agents[change.submap]
            status = replace(status, maps=max(len(self.scene.maps.poses), status.maps),
                             agents=max(status.agents, agent + 1))
            step = StatusStep(status, dirty=True, event=event)
        elif change.loop:
            step = StatusStep(replace(status, loops=max(self.scene.loop_events, status.loops)), dirty=True,
                              event=event)
        return step

    def _on_stats(self, status: SessionStatus, change: Change, event) -> StatusStep:
        stats = change.stats
        ate = stats.ate_rmse
        status = replace(
            status, frames_done=max(stats.frames_done, status.frames_done), frames_total=stats.frames_total,
            keyframes=max(stats.keyframes, self.scene.keyframe_events),
            maps=max(stats.maps, len(self.scene.maps.poses)), loops=max(stats.loops, self.scene.loop_events),
            ate_rmse_m=status.ate_rmse_m if ate is None else round(float(ate), 6))
        # The viewer shows the status's frames/s (see the module doc), not the worker's.
        return StatusStep(status, dirty=True, event=replace(event, fps=status.fps))

    def _on_phase(self, status: SessionStatus, change: Change, now: float, event) -> StatusStep:
        """A phase or one of its steps starts: its clock restarts, with the step's own estimate."""
        if change.phase == "tracking":
            self.tracking_started = now
        estimate = change.estimate_s
        status = replace(status, phase=change.phase, phase_started=now_iso(), phase_budget_s=None,
                         phase_step=change.step,
                         phase_estimate_s=None if estimate is None else round(float(estimate), 1))
        return StatusStep(status, persist=True, event=event)

    def _tracking_fps(self, frames: int, now: float) -> float:
        """Frames per second of tracking so far, now that ``frames`` are tracked (module doc);
        samples its history."""
        if self.tracking_started is None:  # no PhaseEvent (an older worker): from the first pose
            self.tracking_started = now
        elapsed = now - self.tracking_started
        samples = self.fps_samples
        if len(samples) >= 2 and elapsed - samples[-2][0] < FPS_SAMPLE_S:
            samples[-1] = (round(elapsed, 3), frames)  # the last sample is always the latest pose
        else:
            samples.append((round(elapsed, 3), frames))
        # At least MIN_FPS_SPAN_S: the phase's start and the first poses can arrive in one batch.
        return round(frames / max(elapsed, MIN_FPS_SPAN_S), 3)

    def live_meshes(self) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The newest mesh per map, in the world as the maps are placed now."""
        return {m: self.scene.world_mesh(m) for m in list(self.scene.meshes)}


def run_end(done: WorkerDone | None, end_reason: tuple[str, str] | None, cancel_requested: bool,
            forced_reason: str | None, exit_error: Callable[[], str]) -> tuple[str, str | None]:
    """(status, error) a session ends with once its worker has exited: the server's reason
    to stop it (``end_reason``: stopping, an idle stream), a user's cancel, what the worker
    reported (``done``), a forced kill (``forced_reason``), else a crash (``exit_error()``).
    A failure the worker reported wins over a stop or a cancel."""
    failed = done is not None and done.status == "failed"
    if end_reason is not None and not failed:
        # Set only while the worker had not reported its end (see SessionManager.stop,
        # _check_idle_stream): what it says now is its answer to the stop.
        return end_reason
    if cancel_requested:
        return ("failed", done.error) if failed else ("cancelled", None)
    if done is not None:
        return done.status, done.error
    if forced_reason is not None:
        return "cancelled", forced_reason
    return "failed", exit_error()


def with_worker_totals(status: SessionStatus, done: WorkerDone | None) -> SessionStatus:
    """The status with the totals the worker's last message reports (when it tracked frames);
    the fps stays the status's (module doc) unless it has none."""
    if done is None or not done.frames:
        return status
    ate = done.ate_rmse
    return replace(status, frames_done=done.frames, keyframes=done.keyframes, maps=done.maps, loops=done.loops,
                   fps=status.fps or round(done.fps, 3), agents=done.agents or status.agents,
                   ate_rmse_m=status.ate_rmse_m if ate is None else round(float(ate), 6))


def stream_fields(status: SessionStatus, stream) -> dict:
    """A stream session's frame counts for the API (``frames_sent`` among them): live from its input (``server.stream.
    StreamInput``) while it has one, else as the status kept them; {} for other sources."""
    if stream is None:
        if status.frames_received is None:
            return {}
        received, dropped, refused = status.frames_received, status.frames_dropped or 0, status.frames_skipped
    else:
        received, dropped, refused = stream.frames_received, stream.frames_dropped, stream.frames_refused
    # Every frame a client sent was accepted, dropped or refused (server.stream).
    return {"frames_received": received, "frames_dropped": dropped, "frames_sent": received + dropped + refused}


def manager_stream_fields(manager, status: SessionStatus) -> dict:
    """:func:`stream_fields` of a session of ``server.sessions.SessionManager``."""
    if status.spec.kind != "stream":
        return {}
    try:
        stream = manager.stream(status.id)
    except (KeyError, RuntimeError):  # gone, or not a stream (SessionNotFound, SessionConflict)
        stream = None
    return stream_fields(status, stream)


def with_stream_counts(status: SessionStatus, stream) -> SessionStatus:
    """The status with its stream's frame counts kept (so an ended stream still reports them)."""
    if stream is None:
        return status
    return replace(status, frames_received=stream.frames_received, frames_dropped=stream.frames_dropped)
