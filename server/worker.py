"""The SLAM worker process of one session (started by ``server.sessions`` with spawn).

The worker opens its sources (one per agent: several for a collaborative session; a stream
session is one :class:`AgentFrames` source whose frames name their agent), runs
``slam.runtime.run_slam`` (which starts the mapping process itself, so this process is not
daemonic) and forwards every runtime event to the API process
through ``event_queue``, followed by one :class:`WorkerDone`. It puts itself in a new process
group first, so that a cancel that runs out of patience can kill it together with the mapping
process it started, and it watches its server: when the API process is gone (killed, crashed)
the whole group ends at once, since nobody is left to read its events (a worker that went on
finished its run and then blocked on its event pipe forever). Its stdout and stderr (and the
mapping process's) go to ``worker.log`` in the session folder; a log the disk has no room
for loses its lines, never the run. A run that ends because the disk is full (an ENOSPC
anywhere in its error) fails with :data:`DISK_FULL`.

Everything crossing the process boundary is a small frozen dataclass of plain values.
"""

from __future__ import annotations

import errno
import io
import os
import queue
import signal
import sys
import threading
import time
import traceback
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Iterator

import numpy as np

from slam import DataError, Frame
from slam.data.io import SkippedFrame


@dataclass(frozen=True)
class SourceSpec:
    """What a session reads.

    kind: ``dataset`` (a folder, ``path``), ``synthetic`` (``path`` is the generator spec) or
    ``stream`` (frames arrive on the worker's frame queue).
    """

    kind: str
    path: str | None = None
    format: str = "auto"
    intrinsics: tuple[float, ...] | None = None
    depth_scale: float | None = None
    stride: int = 1
    max_frames: int | None = None
    name: str | None = None
    """An upload's file name as the client gave it (a label for the session list, never a path)."""
    color_intrinsics: tuple[float, ...] | None = None
    """The colour camera when colour and depth come from two cameras: fx, fy, cx, cy, width,
    height[, distortion] (``slam.data.registration.color_camera_from_values``)."""
    depth_to_color: tuple[float, ...] | None = None
    """With ``color_intrinsics``: the depth camera's frame in the colour camera's, 12 or 16 numbers."""
    live: bool = False
    """A stream from a camera at its own rate: the run does not hold its frames back
    (``runtime.live``)."""

    def color_camera(self):
        """The ``ColorCamera`` these options give, or None: colour registered to depth already."""
        if self.color_intrinsics is None:
            return None
        from slam.data.registration import color_camera_from_values

        return color_camera_from_values(self.color_intrinsics, self.depth_to_color, source="color_intrinsics")

    def describe(self) -> str:
        """A short human-readable label for the session list."""
        if self.kind == "dataset":
            return f"upload ({self.format})" if self.format != "auto" else "upload"
        if self.kind == "synthetic":
            return f"synthetic:{self.path}"
        return "stream"


def describe_sources(specs: "tuple[SourceSpec, ...] | list[SourceSpec]") -> str:
    """The session list's label for one source, or for the agents of a collaborative session."""
    if len(specs) == 1:
        return specs[0].describe()
    labels = [s.describe() for s in specs]
    if len(set(labels)) == 1:
        return f"{labels[0]} x {len(specs)} agents"
    return f"{len(specs)} agents: " + " | ".join(labels)


@dataclass(frozen=True)
class WorkerJob:
    """One session's work: ``sources`` holds one spec per agent (agent k = k-th), in order.
    A stream session has one ``stream`` spec; its frames say which agent they belong to."""

    session_id: str
    sources: tuple[SourceSpec, ...]
    preset: str
    out_dir: str
    use_gt_poses: bool = False

    def __post_init__(self) -> None:
        if not self.sources:
            raise ValueError("a worker job needs at least one source")
        if any(s.kind == "stream" for s in self.sources) and len(self.sources) != 1:
            raise ValueError("a stream is the only source of its session (its frames name their agents)")

    @property
    def source(self) -> SourceSpec:
        """The first agent's source."""
        return self.sources[0]


@dataclass(frozen=True)
class WorkerStarted:
    """First message of a worker: it is alive and its process group is ``pid``."""

    pid: int


@dataclass(frozen=True)
class WorkerDone:
    """Last message of a worker."""

    status: str
    """finished | failed | cancelled"""
    error: str | None
    frames: int = 0
    keyframes: int = 0
    maps: int = 0
    loops: int = 0
    fps: float = 0.0
    agents: int = 0
    """Agents in ``run.json`` (0: not known)."""
    ate_rmse: float | None = None
    """Agent 0's final ATE RMSE (m), None without ground truth."""


END_OF_STREAM = None
"""Put on a stream session's frame queue to end its input."""


def open_source(source: SourceSpec, frame_queue=None, stop_event=None):
    """The iterable ``run_slam`` reads for this source: frames, or (agent, frame) for a stream."""
    from slam import open_sequence

    if source.kind == "dataset":
        return open_sequence(source.path, source.format, stride=source.stride, max_frames=source.max_frames,
                             intrinsics=source.intrinsics, depth_scale=source.depth_scale,
                             color_camera=source.color_camera())
    if source.kind == "synthetic":
        return open_sequence(f"synthetic:{source.path}", "synthetic", stride=source.stride,
                             max_frames=source.max_frames)
    if source.kind == "stream":
        return stream_source(frame_queue, stop_event, live=source.live)
    raise ValueError(f"unknown source kind {source.kind!r}")


def slam_sources(job: WorkerJob, frame_queue, stop_event) -> list:
    """What the worker hands to ``run_slam`` as ``sources``: one frame iterable per agent (read
    round-robin), or for a stream one ``AgentStream`` (its only element) yielding (agent, frame)."""
    return [open_source(spec, frame_queue, stop_event) for spec in job.sources]


def frame_from_stream(index: int, item) -> Frame:
    """A validated ``server.upload.StreamFrame`` -> the pipeline's float :class:`Frame`."""
    return Frame(
        index=index,
        timestamp=item.timestamp,
        rgb=item.rgb.astype(np.float32) / 255.0,
        depth=item.depth_raw.astype(np.float32) / np.float32(item.depth_scale),
        K=np.asarray(item.K, dtype=np.float64),
        T_world_cam=getattr(item, "T_world_cam", None),  # the client's ground truth: the run's ATE
        color_valid=getattr(item, "color_valid", None),
    )


LIVE_SKIP_REASON = "live: a newer frame of the camera had arrived before it was tracked"


def stream_frames(frame_queue, stop_event, poll_s: float = 0.25,
                  skipped: list | None = None) -> Iterator[tuple[int, Frame]]:
    """(agent, frame) as the API process hands them over, until END_OF_STREAM or a stop
    request. Frame indices count from 0 for each agent, every frame received counted.

    ``skipped`` (a live camera's stream): of the frames waiting, only each agent's newest is
    tracked; the others are appended there (``SkippedFrame``) and left out."""
    counts: dict[int, int] = {}
    while not stop_event.is_set():
        try:
            items = [frame_queue.get(timeout=poll_s)]
        except queue.Empty:
            continue
        if skipped is not None:
            items += _waiting(frame_queue)
        ended = END_OF_STREAM in items
        received = [(int(getattr(item, "agent", 0)), item) for item in items if item is not END_OF_STREAM]
        newest = {agent: position for position, (agent, _) in enumerate(received)}
        for position, (agent, item) in enumerate(received):
            index = counts.get(agent, 0)
            counts[agent] = index + 1
            if skipped is not None and newest[agent] != position:
                skipped.append(SkippedFrame(index, LIVE_SKIP_REASON, agent))
                continue
            yield agent, frame_from_stream(index, item)
        if ended:
            return


def _waiting(frame_queue) -> list:
    """What the queue holds now, taken without waiting."""
    out = []
    while True:
        try:
            out.append(frame_queue.get_nowait())
        except queue.Empty:
            return out


def stream_source(frame_queue, stop_event, poll_s: float = 0.25, live: bool = False):
    """The stream as ``run_slam`` wants it: an ``AgentStream`` yielding (agent, Frame);
    ``live``: only the newest frames (``stream_frames``), the others in its ``skipped``."""
    from slam import AgentStream

    class AgentFrames(AgentStream):
        """A live stream whose frames name their agent (``slam.runtime.AgentStream``)."""

        def __init__(self) -> None:
            self.skipped: list = []
            """Frames left out (``run.json``'s ``skipped_frames``)."""

        def __iter__(self) -> Iterator[tuple[int, Frame]]:
            return stream_frames(frame_queue, stop_event, poll_s, self.skipped if live else None)

    return AgentFrames()


def _run_agents(out_dir: Path) -> int:
    """How many agents ``run.json`` lists (0 when it does not say)."""
    import json

    try:
        agents = json.loads((out_dir / "run.json").read_text()).get("agents")
    except (OSError, ValueError, AttributeError):
        return 0
    return len(agents) if isinstance(agents, list) else 0


def short_error(text: str | None) -> str | None:
    """The last line of a traceback ("DataError: rgb/5.png: cannot decode"), for the status."""
    if not text:
        return text
    lines = [line.strip() for line in text.strip().splitlines() if line.strip()]
    if not lines or not lines[0].startswith("Traceback"):
        return text.strip()
    kind, sep, message = lines[-1].partition(":")
    return f"{kind.rsplit('.', 1)[-1]}{sep}{message}" + " (traceback in worker.log)"


DISK_FULL = "the disk is full: no space left to write the session's outputs (what was written before is kept)"
"""A session's error when its worker could not write for want of space."""
_DISK_FULL_MARKS = tuple(f"[Errno {code}]" for code in (errno.ENOSPC, errno.EDQUOT)) + (os.strerror(errno.ENOSPC),)


def disk_full_error(error: BaseException | str | None) -> str | None:
    """:data:`DISK_FULL` when ``error`` (an exception, or a run's error with its traceback) came
    from a full disk, else None."""
    if isinstance(error, OSError):
        return DISK_FULL if error.errno in (errno.ENOSPC, errno.EDQUOT) else None
    text = error if isinstance(error, str) else ""
    return DISK_FULL if any(mark in text for mark in _DISK_FULL_MARKS) else None


class _LossyLog(io.TextIOWrapper):
    """A text stream whose writes a full disk drops instead of raising: a print may not end
    the run, nor the interpreter's last flush turn the exit code into 120."""

    def write(self, text: str) -> int:
        try:
            return super().write(text)
        except OSError:
            return len(text)

    def flush(self) -> None:
        try:
            super().flush()
        except OSError:
            pass


def _redirect_output(log_path: Path) -> None:
    """Send this process's (and its children's) stdout/stderr to the session's log file."""
    log = open(log_path, "ab", buffering=0)
    os.dup2(log.fileno(), 1)
    os.dup2(log.fileno(), 2)
    sys.stdout = _LossyLog(open(1, "wb", buffering=0, closefd=False), write_through=True)
    sys.stderr = _LossyLog(open(2, "wb", buffering=0, closefd=False), write_through=True)


PARENT_POLL_S = 0.5
"""How often a worker without a parent sentinel (not started by multiprocessing) checks its parent."""


def _wait_for_parent_death(poll_s: float = PARENT_POLL_S) -> None:
    """Return once the process that started this one has exited: EOF on the sentinel pipe
    multiprocessing gives a spawned child, else a change of ``getppid()``."""
    import multiprocessing

    parent = multiprocessing.parent_process()
    if parent is not None and getattr(parent, "sentinel", None) is not None:
        from multiprocessing.connection import wait

        wait([parent.sentinel])
        return
    parent_pid = os.getppid()
    while os.getppid() == parent_pid:
        time.sleep(poll_s)


def end_group_when_parent_dies(wait_for_death=_wait_for_parent_death) -> threading.Thread:
    """A daemon thread that SIGKILLs this process's group (itself and the mapping process)
    once the server is gone. Only a group leader (``os.setpgrp()`` first) ends its group; any
    other process ends just itself."""

    def watch() -> None:
        wait_for_death()
        print("worker: the server process is gone; ending this session's processes", flush=True)
        if os.getpgrp() == os.getpid():
            os.killpg(os.getpgrp(), signal.SIGKILL)
        os._exit(1)

    thread = threading.Thread(target=watch, name="parent-watch", daemon=True)
    thread.start()
    return thread


def run_worker(job: WorkerJob, stop_event, event_queue, frame_queue) -> None:
    """Process entry point: run the session, report events, always end with WorkerDone."""
    os.setpgrp()
    out_dir = Path(job.out_dir)
    _redirect_output(out_dir / "worker.log")
    end_group_when_parent_dies()
    event_queue.put(WorkerStarted(pid=os.getpid()))
    try:
        from slam import load_config, run_slam

        config = load_config(job.preset)
        if any(source.live for source in job.sources):
            config = replace(config, runtime=replace(config.runtime, live=True))
        if stop_event.is_set():  # cancelled while this process was starting
            done = WorkerDone(status="cancelled", error=None)
        else:
            sources = slam_sources(job, frame_queue, stop_event)
            result = run_slam(sources, config, out_dir, use_gt_poses=job.use_gt_poses,
                              on_event=event_queue.put, stop=stop_event)
            if result.error:
                print(result.error, flush=True)  # the whole traceback, for worker.log
            error = disk_full_error(result.error) or short_error(result.error)
            done = WorkerDone(status=result.status, error=error, frames=result.frames,
                              keyframes=result.keyframes, maps=result.maps, loops=result.loops,
                              fps=float(result.fps),
                              agents=int(getattr(result, "agents", 0) or 0) or _run_agents(out_dir),
                              ate_rmse=result.ate_rmse)
    except DataError as error:
        done = WorkerDone(status="failed", error=f"bad input data: {error}")
    except Exception as error:  # noqa: BLE001 - any crash fails only this session; traceback goes to the log
        traceback.print_exc()
        reason = disk_full_error(error) or disk_full_error(traceback.format_exc())
        done = WorkerDone(status="failed", error=reason or f"{type(error).__name__}: {error}")
    print(f"worker done: {done.status} {done.error or ''}", flush=True)
    event_queue.put(done)
    # Flush the queue's feeder thread before exiting, so the last messages are not lost.
    event_queue.close()
    event_queue.join_thread()
