"""Executors: where a session's worker runs (``VOXFUSION_EXECUTOR``).

The session manager (``server.sessions``) drives a session through the small seam in
``server.execution`` (an :class:`~server.execution.Execution`: start it, its events, stop, kill,
why it ended, clean up). Two executors implement it:

* ``local`` (the default, :class:`LocalExecutor`, here): one spawn-context process per session
  on this machine running ``server.worker.run_worker``, exactly as before the seam existed;
* ``ray`` (``server.ray_executor.RayExecutor``): one Ray actor per session on a cluster node,
  which runs the same ``run_worker`` in a process of its own there and ships events and files
  back (imported only when chosen, so the default install needs no Ray).

``make_executor`` picks one.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import signal
import socket
from pathlib import Path

from server.execution import Executor, ExecutorError, WorkerInfo, describe_exit
from server.settings import Settings
from server.worker import WorkerJob, run_worker


def make_executor(settings: Settings) -> Executor:
    """The executor ``settings.executor`` names."""
    if settings.executor == "ray":
        from server.ray_executor import RayExecutor  # only when chosen: the default install needs no Ray

        return RayExecutor(settings)
    return LocalExecutor(settings)


class LocalExecutor:
    """Sessions as spawn-context processes on this machine (module doc)."""

    name = "local"

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._ctx = mp.get_context("spawn")

    def prepare(self, job: WorkerJob, directory: Path, stream: bool) -> "LocalExecution":
        frames = self._ctx.Queue(maxsize=self.settings.stream_queue_frames) if stream else None
        return LocalExecution(self._ctx, job, self._ctx.Event(), self._ctx.Queue(), frames)

    def close(self) -> None:
        pass


class LocalExecution:
    """A worker process whose process group holds its mapping process too (``server.worker``)."""

    def __init__(self, ctx, job: WorkerJob, stop_event, event_queue, frame_queue) -> None:
        self._ctx = ctx
        self.job = job
        self.stop_event = stop_event
        self.event_queue = event_queue
        self.frame_queue = frame_queue
        self.process: mp.process.BaseProcess | None = None

    def start(self) -> WorkerInfo:
        process = self._ctx.Process(
            target=run_worker, name=f"voxfusion-session-{self.job.session_id}",
            args=(self.job, self.stop_event, self.event_queue, self.frame_queue), daemon=False)
        try:
            process.start()
        except (OSError, RuntimeError) as error:
            raise ExecutorError(f"could not start the worker process: {error}") from None
        # The API process only reads events. Closing its copy of the pipe's write end means
        # a worker that dies mid-message gives EOF instead of a read that waits forever.
        self.event_queue._writer.close()
        self.process = process
        return WorkerInfo(executor="local", node=socket.gethostname())

    @property
    def pid(self) -> int | None:
        return None if self.process is None else self.process.pid

    def poll(self, limit: int) -> list[object]:
        events: list[object] = []
        while len(events) < limit:
            try:
                events.append(self.event_queue.get_nowait())
            except queue.Empty:
                break
            except (EOFError, OSError, ValueError):
                break  # the worker is gone and the pipe is closed: nothing more will come
            except Exception as error:  # noqa: BLE001 - half a message from a killed worker
                print(f"voxfusion: dropping an unreadable event of session {self.job.session_id}: {error}")
                break
        return events

    def is_alive(self) -> bool:
        return self.process is not None and self.process.is_alive()

    def request_stop(self) -> None:
        self.stop_event.set()

    def kill(self) -> None:
        """SIGKILL the worker's process group (the worker and the mapping process it started)."""
        process = self.process
        if process is None or process.pid is None:
            return
        try:
            os.killpg(process.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            # Not yet in its own group (killed before it called setpgrp): kill just the worker.
            process.kill()
        process.join(timeout=5.0)

    def exit_error(self) -> str:
        self.process.join(timeout=1.0)
        return describe_exit(self.process.exitcode)

    def finish(self, worker_pid: int | None) -> None:
        process = self.process
        process.join(timeout=1.0)
        if process.is_alive():
            self.kill()
        elif worker_pid is not None:
            # A worker that crashed leaves its mapping process behind: end the whole group.
            kill_group(worker_pid)
        try:
            process.close()
        except ValueError:
            pass

    def release(self) -> None:
        """Close and drop the queues and the stop event, so their semaphores and pipes are freed."""
        for q in (self.event_queue, self.frame_queue):
            if q is not None:
                q.cancel_join_thread()
                q.close()
        self.event_queue = self.frame_queue = self.stop_event = None


def kill_group(group: int) -> None:
    try:
        os.killpg(group, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
