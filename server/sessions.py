"""The session manager: SLAM sessions as worker processes, a FIFO queue, status on disk.

Each session runs ``server.worker.run_worker`` in its own spawn-context process (not daemonic:
the runtime starts a mapping process of its own), on this machine or on a Ray cluster node: the
manager drives it through an executor (``server.executors``, ``VOXFUSION_EXECUTOR``) and does
not care which. One supervisor thread in the API process

* drains every worker's event queue and applies the events to the session's status and to the
  event sinks (the live viewer),
* notices workers that end, normally or not (a crash fails only that session, with its error),
* kills the process group of a cancelled worker that outlives the grace period,
* starts queued sessions while fewer than ``max_sessions`` run.

The queue holds at most ``max_queued`` sessions (``VOXFUSION_MAX_QUEUED``): ``create`` raises
:class:`QueueFull` beyond (429 with ``Retry-After``, ``register_error_handlers``). A queued
session holds no descriptor: its execution (the worker's queues and pipes) is made when it
starts; a queued stream's frames wait in its ``StreamInput``'s buffer until then.

Outputs live in ``DATA_DIR/sessions/<id>/`` (``server.session_store``: the folder's files, and
how an ended session's status is settled against them), so finished sessions are listed again
after a restart. A session that was queued or running when the server went away (stopped, or
killed) comes back as ``failed`` with an error that starts with ``interrupted:``, so a user can
tell it from a session they cancelled; a worker of it that outlived its server is ended then
(a worker also ends itself when its server is gone: ``server.worker``).

``request_shutdown`` (called from the server's SIGTERM/SIGINT handler, ``server.cli``) asks
every running session to stop at once, before uvicorn has drained its connections; ``stop``
then waits for them until ``grace_s`` after that request and kills the rest.

The event-to-status fold (phase, frames/s, counters) is ``server.session_status``; the events'
own fold (tracks, live meshes), shared with the viewer, is ``server.session_state``. This module
is the scheduler: queue, workers, supervision, persistence.
"""

from __future__ import annotations

import json
import re
import secrets
import threading
import time
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from server.errors import strip_paths
from server.execution import Execution, Executor, ExecutorError, WorkerPlaced
from server.executors import make_executor
from server.session_status import (ENDED, SessionStatus, StatusFold, now_iso, run_end, with_stream_counts,
                                   with_worker_totals)
from server.session_store import (
    WORKER_PID_FILE,
    disk_is_full,
    end_orphaned_worker,
    log_line,
    read_progress,
    settle_outputs,
    write_pid,
    write_progress,
    write_status,
)
from server.settings import Settings, render_threads_now, usable_cores
from server.stream import StreamInput
from server.tracks import FrameCamera, TrackedPose
from server.worker import DISK_FULL, SourceSpec, WorkerDone, WorkerJob, WorkerStarted, describe_sources
from slam import FinishedEvent
INTERRUPTED_RUNNING = "interrupted: the server stopped while the session was running"
INTERRUPTED_QUEUED = "interrupted: the server stopped before the session started"
SESSION_ID = re.compile(r"^[0-9a-f]{12}$")
EventSink = Callable[[str, object], None]
"""Called with (session id, event) in the supervisor thread for every worker event."""

_SUPERVISOR_TICK_S = 0.05
_MAX_EVENTS_PER_TICK = 200
_PERSIST_EVERY_S = 1.0


class SessionNotFound(KeyError):
    pass


class SessionConflict(RuntimeError):
    """The session is in a state where the request makes no sense (409)."""


QUEUE_RETRY_AFTER_S = 30
"""The ``Retry-After`` of a 429 for a full queue (a queued session waits minutes, not seconds)."""


class QueueFull(RuntimeError):
    """``max_queued`` sessions wait already: 429 with ``Retry-After`` (``register_error_handlers``)."""

    def __init__(self, message: str, retry_after_s: int = QUEUE_RETRY_AFTER_S) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


def register_error_handlers(app) -> None:
    """Add the manager's own HTTP answers to a FastAPI ``app``: :class:`QueueFull` -> 429
    ``{"detail": ...}`` with ``Retry-After`` (``server.main`` calls this with its handlers)."""
    from fastapi.responses import JSONResponse

    async def queue_full(request, error: QueueFull) -> JSONResponse:
        return JSONResponse({"detail": str(error)}, status_code=429,
                            headers={"Retry-After": str(error.retry_after_s)})

    app.add_exception_handler(QueueFull, queue_full)


@dataclass
class _Session:
    """Mutable bookkeeping of one session; only the manager touches it, under its lock."""

    status: SessionStatus
    directory: Path
    job: WorkerJob
    execution: Execution | None = None
    """Made when the session starts (none while queued: no pipes), dropped once it ended
    (``_release_ipc``)."""
    active: bool = False
    """Its execution was started and has not been reaped yet."""
    stream: StreamInput | None = None
    worker_pid: int | None = None
    done: WorkerDone | None = None
    cancel_requested_at: float | None = None
    end_reason: tuple[str, str] | None = None
    """(status, error) the session ends with once its worker stopped, instead of ``cancelled``:
    set when the server stops or a stream idles out (not a user's cancel)."""
    started_at: float | None = None
    """time.monotonic() when its worker started."""
    delete_when_stopped: bool = False
    dirty_since: float | None = None
    fold: StatusFold = field(default_factory=StatusFold)
    """The status as its events make it, with the events' fold (tracks, live meshes, frames/s history)."""

    @property
    def process(self):
        """The local worker process while it runs (None with another executor)."""
        return getattr(self.execution, "process", None) if self.active else None

    @property
    def frame_queue(self):
        """Where a stream's frames go now: the worker's queue, or the buffer while queued."""
        return None if self.stream is None else self.stream.frame_queue


def new_session_id() -> str:
    return secrets.token_hex(6)


def check_session_id(session_id: str) -> str:
    """The id if it has our shape (12 hex digits); it is used in paths, so nothing else passes."""
    if not SESSION_ID.match(session_id):
        raise SessionNotFound(session_id)
    return session_id


class SessionManager:
    """Owns all sessions. Thread-safe; ``start()``/``stop()`` are called by the app's lifespan."""

    def __init__(self, settings: Settings, event_sinks: list[EventSink] | None = None,
                 removal_hooks: list[Callable[[str], None]] | None = None) -> None:
        self.settings = settings
        self._event_sinks = list(event_sinks or [])
        self._removal_hooks = list(removal_hooks or [])
        self._executor: Executor = make_executor(settings)
        self._lock = threading.RLock()
        self._sessions: dict[str, _Session] = {}
        self._queue: deque[str] = deque()
        self._stopping_sessions: list[_Session] = []
        """Deleted sessions whose workers are still stopping (no longer listed)."""
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._shutdown = threading.Event()
        """Set by ``request_shutdown`` (a signal handler): the supervisor stops every session."""
        self._shutdown_at: float | None = None
        self._shutdown_done = False

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self) -> None:
        self.settings.sessions_dir.mkdir(parents=True, exist_ok=True)
        self._recover()
        self._stopping.clear()
        self._thread = threading.Thread(target=self._supervise, name="session-supervisor", daemon=True)
        self._thread.start()

    def request_shutdown(self) -> None:
        """The server is going to stop (SIGTERM): stop every session now, so that workers write
        their outputs while uvicorn still drains connections. Safe in a signal handler (it only
        sets an event; the supervisor does the rest within a tick)."""
        if self._shutdown_at is None:
            self._shutdown_at = time.monotonic()
        self._shutdown.set()

    def _interrupt_all(self) -> list[_Session]:
        """Ask every running session to stop as interrupted and fail the queued ones (under
        the lock); returns the sessions whose workers are stopping."""
        self._shutdown_done = True
        running = [s for s in self._sessions.values() if s.active] + self._stopping_sessions
        for session in running:
            # A worker that already reported its end keeps it; a user's cancel stays one.
            if session.end_reason is None and session.cancel_requested_at is None and session.done is None:
                waiting = session.status.status == "queued"  # handed to Ray, no node yet
                session.end_reason = ("failed", INTERRUPTED_QUEUED if waiting else INTERRUPTED_RUNNING)
            self._request_stop(session, "the server is stopping")
        for session_id in list(self._queue):
            session = self._sessions[session_id]
            self._set_status(session, "failed", INTERRUPTED_QUEUED)
            if session.stream is not None:
                session.stream.end("failed", INTERRUPTED_QUEUED)
            self._release_ipc(session)
        self._queue.clear()
        return running

    def stop(self, grace_s: float = 5.0) -> None:
        """Stop running sessions (they end as ``failed``, "interrupted: ...", with what they
        wrote so far: not ``cancelled``, which is a user's doing), wait for them until
        ``grace_s`` after ``request_shutdown`` (or after now), kill the rest; queued ones are
        failed the same way."""
        with self._lock:
            running = self._interrupt_all()
        deadline = (self._shutdown_at if self._shutdown_at is not None else time.monotonic()) + grace_s
        while time.monotonic() < deadline and any(s.active for s in running):
            time.sleep(_SUPERVISOR_TICK_S)
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        with self._lock:
            for session in running:
                if session.active:
                    session.execution.kill()
                    self._reap(session, forced_reason="the server stopped while it was running")
            for session in self._sessions.values():
                self._persist(session)
        self._executor.close()

    def _recover(self) -> None:
        """List the sessions already on disk; those that were queued or running are marked
        failed ("interrupted: ..."), and a worker of theirs that outlived its server is ended."""
        for meta in sorted(self.settings.sessions_dir.glob("*/session.json")):
            try:
                status = SessionStatus.from_json(json.loads(meta.read_text()))
            except (OSError, ValueError, TypeError, KeyError) as error:
                log_line(f"voxfusion: skipping unreadable {meta}: {error}")
                continue
            interrupted = status.status not in ENDED
            if interrupted:
                end_orphaned_worker(meta.parent)
                status = replace(status, status="failed", phase="done",
                                 error=INTERRUPTED_QUEUED if status.status == "queued" else INTERRUPTED_RUNNING)
            job = WorkerJob(session_id=status.id, sources=status.sources, preset=status.preset,
                            out_dir=str(meta.parent))
            session = _Session(status=status, directory=meta.parent, job=job)
            if interrupted:
                self._settle_outputs(session)
            self._sessions[status.id] = session
            self._persist(session)

    # -- creating ----------------------------------------------------------------------------

    def session_dir(self, session_id: str) -> Path:
        return self.settings.sessions_dir / check_session_id(session_id)

    def check_queue_room(self) -> None:
        """Raise QueueFull when ``max_queued`` sessions wait already (``create`` checks it too;
        a route may call it before it reads a large upload)."""
        with self._lock:
            waiting = len(self._queue)
        if waiting >= self.settings.max_queued:
            raise QueueFull(f"the queue is full: {waiting} sessions are waiting to start "
                            f"(VOXFUSION_MAX_QUEUED={self.settings.max_queued}); retry later")

    def _refuse_when_full(self, session_id: str, directory: Path) -> None:
        """QueueFull when the queue is full, after removing the folder made for this new session."""
        with self._lock:
            try:
                self.check_queue_room()
            except QueueFull:
                if session_id not in self._sessions:
                    import shutil

                    shutil.rmtree(directory, ignore_errors=True)
                raise

    def create(self, session_id: str, spec: SourceSpec | Sequence[SourceSpec], preset: str) -> SessionStatus:
        """Register and queue a session whose folder (with ``input/`` for uploads) exists.

        ``spec``: one source, or one per agent (agent k = k-th) for a collaborative session.
        Raises QueueFull when ``max_queued`` sessions wait already; the folder made for this
        one is removed then. Nothing that holds a descriptor is made here (``_start_queued``)."""
        specs = (spec,) if isinstance(spec, SourceSpec) else tuple(spec)
        directory = self.session_dir(session_id)
        self._refuse_when_full(session_id, directory)  # before anything is made for it
        job = WorkerJob(session_id=session_id, sources=specs, preset=preset, out_dir=str(directory))
        spec = specs[0]
        directory.mkdir(parents=True, exist_ok=True)
        created = now_iso()
        status = SessionStatus(id=session_id, status="queued", created=created, source=describe_sources(specs),
                               preset=preset, spec=spec, specs=specs if len(specs) > 1 else (), agents=len(specs),
                               phase_started=created)
        session = _Session(status=status, directory=directory, job=job)
        if spec.kind == "stream":
            # No worker queue yet: frames wait in the input's buffer until the session starts.
            session.stream = StreamInput(None, directory / "input", intrinsics=spec.intrinsics,
                                         depth_scale=spec.depth_scale, color_camera=spec.color_camera(),
                                         put_timeout_s=self.settings.stream_put_timeout_s,
                                         buffer_frames=self.settings.stream_queue_frames)
        with self._lock:
            # Again, under the same lock as the append: another create may have taken the last place.
            self._refuse_when_full(session_id, directory)
            self._sessions[session_id] = session
            self._queue.append(session_id)
            self._persist(session)
        return status

    # -- reading -----------------------------------------------------------------------------

    def list(self) -> list[SessionStatus]:
        with self._lock:
            return sorted((s.status for s in self._sessions.values()), key=lambda s: s.created, reverse=True)

    def get(self, session_id: str) -> SessionStatus:
        return self._get(session_id).status

    def _get(self, session_id: str) -> _Session:
        with self._lock:
            session = self._sessions.get(session_id)
        if session is None:
            raise SessionNotFound(session_id)
        return session

    def stream(self, session_id: str) -> StreamInput:
        """The frame input of a stream session (SessionConflict for other kinds)."""
        session = self._get(session_id)
        if session.stream is None:
            raise SessionConflict(f"session {session_id} reads {session.status.source}, not a stream")
        return session.stream

    def live_meshes(self, session_id: str) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The latest mesh per map seen in this session's events (empty before the first), in
        the world frame as the maps are placed now: (V, 3) float32, (F, 3) int32, (V, 3) uint8."""
        session = self._get(session_id)
        with self._lock:
            return session.fold.live_meshes()

    def tracked_poses(self, session_id: str, agent: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Poses of one agent reported so far while this server ran the session: (N,) frame
        indices, (N,) timestamps, (N, 4, 4) T_world_cam (moved with their maps by loop
        closures), sorted by frame index (empty after a restart)."""
        session = self._get(session_id)
        with self._lock:
            return session.fold.scene.tracks.world_poses(agent)

    def newest_camera(self, session_id: str, agent: int = 0) -> tuple[TrackedPose, np.ndarray, FrameCamera] | None:
        """The agent's newest tracked frame, its current T_world_cam and its camera, or None
        before its first frame (and after a server restart: the events are gone)."""
        session = self._get(session_id)
        with self._lock:
            state = session.fold.scene
            latest, camera = state.latest.get(agent), state.cameras.get(agent)
            if latest is None or camera is None:
                return None
            return state.tracks.by_agent[agent][latest[0]], state.camera_pose(agent), camera

    def tracked_agents(self, session_id: str) -> list[int]:
        """Agents with at least one pose reported while this server ran the session."""
        session = self._get(session_id)
        with self._lock:
            return session.fold.scene.tracks.agents()

    def fps_samples(self, session_id: str) -> list[tuple[float, int]]:
        """(seconds since tracking began, frames tracked) over the session's tracking phase:
        from this run's events, else from ``progress.json`` (empty when neither has any)."""
        session = self._get(session_id)
        with self._lock:
            samples = list(session.fold.fps_samples)
        return samples or read_progress(session.directory)

    def agent_count(self, session_id: str) -> int:
        """Agents of the session: its sources, or for a stream the agents seen so far."""
        session = self._get(session_id)
        with self._lock:
            count = session.status.agents
            if session.stream is not None:
                count = max(count, session.stream.agent_count)
            return count

    def running_count(self) -> int:
        with self._lock:
            return self._workers_alive()

    def _workers_alive(self) -> int:
        """Sessions whose worker has not exited yet, deleted ones still stopping included: a
        stopping worker holds its slot (memory, cores) until its process is gone (under the lock)."""
        return sum(1 for s in self._sessions.values() if s.active) + sum(1 for s in self._stopping_sessions if s.active)

    def render_threads(self) -> int:
        """torch threads for the API process's next render, mesh or pick
        (``Settings.render_threads``, ``render_threads_now``)."""
        return render_threads_now(self.settings.render_threads, self.running_count(), usable_cores())

    # -- cancelling and deleting -------------------------------------------------------------

    def cancel(self, session_id: str) -> SessionStatus:
        """Stop a queued or running session; its outputs so far are kept."""
        session = self._get(session_id)
        with self._lock:
            if session.status.status == "queued" and not session.active:
                self._queue.remove(session_id)
                self._set_status(session, "cancelled", None)
                if session.stream is not None:
                    session.stream.end("cancelled")
                self._release_ipc(session)
            elif session.active:  # running, or handed to an executor that has not placed it yet
                self._request_stop(session, "the session was cancelled")
            return session.status

    def delete(self, session_id: str) -> None:
        """Cancel if needed, forget the session and remove its folder (once its worker is gone)."""
        session = self._get(session_id)
        with self._lock:
            del self._sessions[session_id]
            if session_id in self._queue:
                self._queue.remove(session_id)
            self._close_inputs(session, "the session was deleted")
            if session.active:
                session.delete_when_stopped = True
                self._request_stop(session, "the session was deleted")
                self._stopping_sessions.append(session)
            else:
                self._release_ipc(session)
                self._remove_files(session)
        for hook in self._removal_hooks:
            hook(session_id)

    def _request_stop(self, session: _Session, reason: str) -> None:
        """Ask the worker to stop; a stream refuses frames from now on, saying ``reason``."""
        if session.cancel_requested_at is None:
            session.cancel_requested_at = time.monotonic()
            if session.execution is not None:
                session.execution.request_stop()
            self._close_inputs(session, reason)

    def _close_inputs(self, session: _Session, reason: str) -> None:
        if session.stream is not None:
            session.stream.close(reason)

    def _release_ipc(self, session: _Session) -> None:
        """Free the execution's queues and events (pipes, semaphores, Ray handles). The stream
        lets go of its queue first, so no frame is put into a queue that is closed."""
        if session.stream is not None:
            session.stream.release("the session ended")
        if session.execution is not None:
            session.execution.release()
        session.execution = None

    def _remove_files(self, session: _Session) -> None:
        import shutil

        shutil.rmtree(session.directory, ignore_errors=True)

    # -- the supervisor ----------------------------------------------------------------------

    def _supervise(self) -> None:
        while not self._stopping.is_set():
            try:
                self._tick()
            except Exception as error:  # noqa: BLE001 - the supervisor must outlive one bad event
                import traceback

                log_line(f"voxfusion: supervisor error: {traceback.format_exc()}")
            time.sleep(_SUPERVISOR_TICK_S)

    def _tick(self) -> None:
        if self._shutdown.is_set() and not self._shutdown_done:
            with self._lock:
                self._interrupt_all()
        with self._lock:
            active = [s for s in self._sessions.values() if s.active]
            active += self._stopping_sessions
        for session in active:
            self._drain(session)
        with self._lock:
            for session in active:
                self._check_worker(session)
            self._stopping_sessions = [s for s in self._stopping_sessions if s.active]
            self._start_queued()
            now = time.monotonic()
            for session in active:
                self._check_idle_stream(session, now)
            for session in self._sessions.values():
                if session.dirty_since is not None and now - session.dirty_since >= _PERSIST_EVERY_S:
                    self._persist(session)

    def _check_idle_stream(self, session: _Session, now: float) -> None:
        """A running stream that got no frame for ``stream_idle_timeout_s`` would hold its slot
        forever: finish it with what it has, or fail it when it has nothing."""
        timeout = self.settings.stream_idle_timeout_s
        stream = session.stream
        if (not timeout or stream is None or not session.active or session.started_at is None
                or stream.finished or session.cancel_requested_at is not None or session.done is not None):
            return
        last = max(session.started_at, stream.last_frame_at or 0.0)
        if now - last < timeout:
            return
        setting = f"{timeout:g} s (VOXFUSION_STREAM_IDLE_S)"
        if stream.frames_received == 0:
            error = f"the stream received no frame within {setting}"
            session.end_reason = ("failed", error)
            self._request_stop(session, f"the session failed: {error}")
        elif stream.finish_if_idle(f"the stream was finished after no frame for {setting}"):
            log_line(f"voxfusion: session {session.status.id}: no frame for {setting}; finishing with "
                     f"{stream.frames_received} frames")

    def _drain(self, session: _Session) -> None:
        if session.execution is None:
            return
        for event in session.execution.poll(_MAX_EVENTS_PER_TICK):
            self._apply(session, event)

    def _apply(self, session: _Session, event: object) -> None:
        """One message from the worker: its own (started, placed, done) or a runtime event,
        which the session's status fold takes and the event sinks get."""
        with self._lock:
            if self._apply_worker_message(session, event):
                return
            step = session.fold.apply(session.status, event, session.started_at)
            session.status = step.status
            if step.persist:
                self._persist(session)
            elif step.dirty:
                self._mark_dirty(session)
            if step.finished is not None and session.done is None:
                session.done = WorkerDone(status=step.finished.status, error=step.finished.error)
            event = step.event
        if session.delete_when_stopped:
            return
        for sink in self._event_sinks:
            sink(session.status.id, event)

    def _apply_worker_message(self, session: _Session, message: object) -> bool:
        """Take a message of the worker's own; False for a runtime event."""
        if isinstance(message, WorkerStarted):
            if session.status.worker is None or session.status.worker.executor == "local":
                session.worker_pid = message.pid  # a process group on this machine
        elif isinstance(message, WorkerPlaced):
            session.status = replace(session.status, worker=message.worker)
            if session.status.status == "queued" and session.cancel_requested_at is None:
                self._set_status(session, "running", None)
        elif isinstance(message, WorkerDone):
            session.done = message
        else:
            return False
        return True

    def _check_worker(self, session: _Session) -> None:
        if not session.active:
            return
        if session.execution.is_alive():
            grace = self.settings.cancel_grace_s
            if session.cancel_requested_at is not None and time.monotonic() - session.cancel_requested_at > grace:
                session.execution.kill()
            return
        self._drain(session)
        self._reap(session)

    def _reap(self, session: _Session, forced_reason: str | None = None) -> None:
        """The worker has exited (or was killed): settle the final status and free resources."""
        execution = session.execution
        status, error = run_end(session.done, session.end_reason, session.cancel_requested_at is not None,
                                forced_reason, lambda: self._exit_error(session))
        session.status = with_worker_totals(session.status, session.done)
        if error is not None:
            error = strip_paths(error, session.directory / "input", "the input")
        if session.stream is not None and session.stream.agent_count > session.status.agents:
            session.status = replace(session.status, agents=session.stream.agent_count)
        session.status = with_stream_counts(session.status, session.stream)
        execution.finish(session.worker_pid)
        session.active = False
        (session.directory / WORKER_PID_FILE).unlink(missing_ok=True)
        if session.stream is not None:
            session.stream.end(status, error)
        self._release_ipc(session)
        session.fold.scene.meshes.clear()
        if session.delete_when_stopped:
            self._remove_files(session)
            return
        write_progress(session.directory, session.fold.fps_samples)
        self._set_status(session, status, error)
        for sink in self._event_sinks:
            sink(session.status.id, FinishedEvent(status=status, error=error))

    def _exit_error(self, session: _Session) -> str:
        """Why a worker ended without a result; a worker that could no longer write to its
        folder's full disk (its log included) says so."""
        error = session.execution.exit_error()
        return f"{DISK_FULL} ({error})" if disk_is_full(session.directory) else error

    def _start_queued(self) -> None:
        running = self._workers_alive()
        while (self._queue and running < self.settings.max_sessions and not self._stopping.is_set()
               and not self._shutdown.is_set()):
            session = self._sessions[self._queue.popleft()]
            try:
                # The IPC is made now, not while queued (module doc).
                session.execution = self._executor.prepare(session.job, session.directory,
                                                           stream=session.stream is not None)
                if session.stream is not None:
                    session.stream.attach(session.execution.frame_queue)
                worker = session.execution.start()
            except (ExecutorError, OSError) as error:
                message = str(error) if isinstance(error, ExecutorError) else f"could not start the worker: {error}"
                if session.stream is not None:
                    session.stream.end("failed", message)
                self._release_ipc(session)
                self._set_status(session, "failed", message)
                continue
            session.active = True
            session.started_at = time.monotonic()
            pid = getattr(session.execution, "pid", None)
            if pid is not None:
                write_pid(session.directory / WORKER_PID_FILE, pid)
            if worker is not None:  # else it stays queued until the executor says where it runs
                session.status = replace(session.status, worker=worker)
                self._set_status(session, "running", None)
            running += 1

    # -- status on disk ----------------------------------------------------------------------

    def _set_status(self, session: _Session, status: str, error: str | None) -> None:
        """Set and persist the status; a session that ends now is settled against its folder."""
        phase = "done" if status in ENDED else session.status.phase
        if status == "running" and phase == "queued":
            # Until the worker's runtime says it tracks (its processes spawned, the mapper
            # ready: seconds), frames sent would only wait in its queue.
            phase = "starting"
        same = phase == session.status.phase
        ends = status in ENDED and session.status.status not in ENDED
        session.status = replace(session.status, status=status, error=error, phase=phase,
                                 phase_started=session.status.phase_started if same else now_iso(),
                                 phase_budget_s=session.status.phase_budget_s if same else None)
        if ends:
            self._settle_outputs(session)
        self._persist(session)

    def _settle_outputs(self, session: _Session) -> None:
        """An ended session's status against its folder (``server.session_store``)."""
        refused = session.stream.frames_refused if session.stream is not None else None
        session.status = settle_outputs(session.directory, session.status, refused)

    def _mark_dirty(self, session: _Session) -> None:
        if session.dirty_since is None:
            session.dirty_since = time.monotonic()

    def _persist(self, session: _Session) -> None:
        session.dirty_since = None
        write_status(session.directory, session.status)
