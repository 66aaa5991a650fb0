"""Camera-path videos rendered in the background: ``POST .../render/path`` starts a job, its
status counts the frames, and the MP4 is served once it is written.

One video renders at a time (a thread of the API process, with the other renders' torch
threads); jobs wait in order. Each session keeps its newest ``KEPT_PER_SESSION`` videos in its
folder (``paths/``); a job's record lives as long as the server.
"""

from __future__ import annotations

import secrets
import threading
import traceback
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

KEPT_PER_SESSION = 4
"""Videos kept per session: an older one is deleted when a new job starts."""


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


@dataclass(frozen=True)
class PathRender:
    """What to render: the map, the path, the camera and the panels."""

    mapset: object
    path: object
    K: np.ndarray
    width: int
    height: int
    outputs: tuple[str, ...]
    depth_range: tuple[float, float] | None = None
    crop: tuple | None = None


@dataclass
class PathJobs:
    """The server's video jobs, by id."""

    jobs: dict[str, PathJob] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _pool: ThreadPoolExecutor = field(default_factory=lambda: ThreadPoolExecutor(1, thread_name_prefix="path-video"))

    def start(self, session_id: str, directory: Path, render: PathRender) -> PathJob:
        """Queue a video of ``render`` into ``directory / 'paths'``; returns the job."""
        folder = directory / "paths"
        folder.mkdir(parents=True, exist_ok=True)
        job_id = secrets.token_hex(6)
        job = PathJob(job_id, session_id, folder / f"{job_id}.mp4", render.path.frame_count)
        with self._lock:
            self.jobs[job_id] = job
            self._forget_old(session_id)
        self._pool.submit(self._run, job_id, render)
        return job

    def get(self, session_id: str, job_id: str) -> PathJob | None:
        with self._lock:
            job = self.jobs.get(job_id)
        return job if job is not None and job.session_id == session_id else None

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)

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

    def _run(self, job_id: str, render: PathRender) -> None:
        from slam.path_video import path_frames, write_mp4

        job = self.jobs[job_id]
        self._update(job_id, state="rendering")
        partial = job.file.with_suffix(".part.mp4")
        try:
            frames = path_frames(render.mapset, render.path, render.K, render.width, render.height, render.outputs,
                                 depth_range=render.depth_range, crop=render.crop,
                                 on_frame=lambda done, total: self._update(job_id, frames_done=done))
            write_mp4(frames, partial, render.path.fps)
            partial.replace(job.file)
            self._update(job_id, state="finished")
        except Exception as error:  # noqa: BLE001 - a failed video fails its job only
            partial.unlink(missing_ok=True)
            last = traceback.format_exception_only(type(error), error)[-1].strip()
            self._update(job_id, state="failed", error=last)
