"""Camera-path videos rendered in the background: ``POST .../render/path`` starts a job, its
status counts the frames, and the MP4 is served once it is written.

A video renders in the video helper (``server.render_pools``, a process with a memory cap
and a time limit), which loads the map itself and reports each frame done back to the API
process; the API process only waits on its pipe, in one thread. One video renders at a time;
jobs wait in order, at most ``budget.MAX_VIDEO_JOBS`` queued and rendering together (more:
:class:`TooManyJobs`, 429). Each session keeps its newest ``KEPT_PER_SESSION`` videos in its
folder (``paths/``); a job's record lives as long as the server.
"""

from __future__ import annotations

import secrets
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

from server.budget import MAX_VIDEO_JOBS, VIDEO_RETRY_AFTER_S
from server.helper_pool import HelperPool
from server.render_calls import VideoCall, render_video

KEPT_PER_SESSION = 4
"""Videos kept per session: an older one is deleted when a new job starts."""


class TooManyJobs(RuntimeError):
    """MAX_VIDEO_JOBS videos are queued or rendering: 429 with Retry-After."""

    retry_after_s = VIDEO_RETRY_AFTER_S


@dataclass(frozen=True)
class PathJob:
    """A video job. ``state``: queued, rendering, finished, failed."""

    id: str
    session_id: str
    file: Path
    frames_total: int
    frames_done: int = 0
    state: str = "queued"
    error: str | None = None


class PathJobs:
    """The server's video jobs, by id, rendered one at a time in ``pool``."""

    def __init__(self, pool: HelperPool, max_jobs: int = MAX_VIDEO_JOBS) -> None:
        self.pool, self.max_jobs = pool, max_jobs
        self.jobs: dict[str, PathJob] = {}
        self._lock = threading.Lock()
        self._runner = ThreadPoolExecutor(1, thread_name_prefix="path-video")

    def start(self, session_id: str, directory: Path, call: VideoCall) -> PathJob:
        """Queue a video of ``call`` (its ``out_file`` is set here, in ``directory / 'paths'``);
        TooManyJobs when MAX_VIDEO_JOBS are queued or rendering."""
        folder = directory / "paths"
        job_id = secrets.token_hex(6)
        job = PathJob(job_id, session_id, folder / f"{job_id}.mp4", call.path.frame_count)
        with self._lock:
            waiting = sum(j.state in ("queued", "rendering") for j in self.jobs.values())
            if waiting >= self.max_jobs:
                raise TooManyJobs(f"{waiting} videos are queued or rendering, the most the server takes at once "
                                  f"({self.max_jobs}); retry after {VIDEO_RETRY_AFTER_S} s")
            folder.mkdir(parents=True, exist_ok=True)
            self.jobs[job_id] = job
            self._forget_old(session_id)
        self._runner.submit(self._run, job_id, replace(call, out_file=str(job.file)))
        return job

    def get(self, session_id: str, job_id: str) -> PathJob | None:
        with self._lock:
            job = self.jobs.get(job_id)
        return job if job is not None and job.session_id == session_id else None

    def close(self) -> None:
        self._runner.shutdown(wait=False, cancel_futures=True)

    def _update(self, job_id: str, **changes) -> None:
        with self._lock:
            if job_id in self.jobs:
                self.jobs[job_id] = replace(self.jobs[job_id], **changes)

    def _forget_old(self, session_id: str) -> None:
        """Keep the session's newest KEPT_PER_SESSION jobs (called under the lock)."""
        mine = [j for j in self.jobs.values() if j.session_id == session_id]
        for job in mine[:-KEPT_PER_SESSION]:
            if job.state in ("finished", "failed"):
                job.file.unlink(missing_ok=True)
                del self.jobs[job.id]

    def _run(self, job_id: str, call: VideoCall) -> None:
        self._update(job_id, state="rendering")
        try:
            self.pool.call(render_video, call, on_progress=lambda done, total: self._update(job_id, frames_done=done))
            self._update(job_id, state="finished")
        except Exception as error:  # noqa: BLE001 - a failed video fails its job only
            self._update(job_id, state="failed", error=f"{type(error).__name__}: {error}")
