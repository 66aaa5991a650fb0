"""The seam between the session manager and the place a session runs (an executor).

The session manager (``server.sessions``) keeps the queue, the status and the viewer; what it
needs from the place a session runs is small, and it is :class:`Execution`: start it, the
events it has sent so far, ask it to stop, kill it, whether it still runs, why it ended when it
said nothing, and clean up. The executors that implement it are ``server.executors`` (local
processes, and ``make_executor``) and ``server.ray_executor`` (Ray actors); this module is
what both share, so neither imports the other.

Events are what ``run_worker`` sends (``slam.events``, :class:`~server.worker.WorkerStarted`,
:class:`~server.worker.WorkerDone`) plus :class:`WorkerPlaced` from an executor that learns
only later where a session runs (Ray queues actors until a node has room).
"""

from __future__ import annotations

import signal
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from server.worker import WorkerJob


@dataclass(frozen=True)
class WorkerInfo:
    """Where a session runs (``worker`` in ``GET /api/sessions/{id}``)."""

    executor: str
    """``local`` or ``ray``."""
    node: str | None = None
    """The machine: this host's name (local), the Ray node id (ray)."""
    address: str | None = None
    """The node's IP address as Ray knows it; None for local."""


@dataclass(frozen=True)
class WorkerPlaced:
    """An executor's event: the session's work has a node now and runs (Ray placed its actor)."""

    worker: WorkerInfo


class ExecutorError(RuntimeError):
    """The executor cannot run a session; the message is the session's error as it stands."""


class Execution(Protocol):
    """One session's work, as the session manager drives it (see the module doc)."""

    frame_queue: object | None
    """Where a stream session's frames go (``put``, ``put_nowait``, ``empty``), else None;
    ``StreamInput.attach`` moves the frames buffered while the session was queued there."""

    def start(self) -> WorkerInfo | None:
        """Hand the work over. Returns where it runs, or None when that is known only once a
        :class:`WorkerPlaced` event arrives (the session stays queued till then). Raises
        ExecutorError."""

    def poll(self, limit: int) -> list[object]:
        """Up to ``limit`` events that have arrived; never waits."""

    def is_alive(self) -> bool:
        """False once the work has ended (normally or not) and no event is left in transit."""

    def request_stop(self) -> None:
        """Ask the worker to stop (it writes what it has and ends ``cancelled``)."""

    def kill(self) -> None:
        """End the work now, with everything it started."""

    def exit_error(self) -> str:
        """Why the work ended, for a worker that ended without a WorkerDone."""

    def finish(self, worker_pid: int | None) -> None:
        """After the end: make sure nothing of the work is left running and free it."""

    def release(self) -> None:
        """Free the queues and events (also for work that never started)."""


class Executor(Protocol):
    name: str

    def prepare(self, job: WorkerJob, directory: Path, stream: bool) -> Execution:
        """The execution of one session (queues made, nothing started yet). The manager calls
        it when the session is about to start, not while it is queued, since the queues hold
        pipes (descriptors); a stream's ``frame_queue`` must hold ``stream_queue_frames``."""

    def close(self) -> None:
        """The server stops: let go of what the executor holds."""


def describe_exit(exitcode: int | None) -> str:
    """A worker process's end in words, for a worker that did not report one."""
    if exitcode is None:
        return "the worker process vanished"
    if exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        hint = " (out of memory?)" if -exitcode == signal.SIGKILL else ""
        return f"the worker process was killed by {name}{hint}; see worker.log"
    return f"the worker process exited with code {exitcode} without a result; see worker.log"
