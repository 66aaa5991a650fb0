"""The input side of a streamed session: validate each frame, hand it to the worker through a
bounded queue (back-pressure instead of unbounded memory), and keep a copy of the raw bytes in
the session folder so that the frames can be shown again later (AR ``frame:N`` backgrounds).

A frame that finds the queue full is dropped and counted (``frames_dropped``), with a
:class:`StreamBusy` (503) that says so: at once for a WebSocket frame (``wait=False``: the
socket's reader must never stall, or the server stops reading the client's pongs and its
keepalive closes the socket), after waiting up to ``put_timeout_s`` for room for an HTTP frame
(one request holds one frame). The wait for room holds no lock, so one waiting frame never
holds up another transport's frames.

A queued session has no worker queue yet (the executor makes its pipes only when the session
starts, so a queue of waiting sessions holds no descriptors): until then frames wait in an
in-process buffer of the same size, with the same back-pressure, and ``attach`` moves them, in
order, to the worker's queue when the session starts.

A stream may carry several agents (cameras of one collaborative session): each frame names
its ``agent`` (default 0). Frame indices, intrinsics and depth scale are per agent: each
agent's frames count from 0, and each agent gives its camera on its first frame unless the
session was created with one (which then applies to every agent).

Layout of ``sessions/<id>/input/`` for a stream::

    frames.jsonl          one JSON object per frame: agent, index, timestamp, color, depth, depth_scale, K
    color/000000.png      agent 0's colour bytes as sent (PNG or JPEG)
    depth/000000.png      agent 0's 16-bit depth PNG as sent
    color/agent1_000000.png, depth/agent1_000000.png     the other agents' frames
"""

from __future__ import annotations

import json
import queue
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from server.budget import MAX_STREAM_FRAMES
from server.upload import (
    PNG_SIGNATURE,
    StreamFrame,
    UploadError,
    decode_color,
    decode_depth,
    decode_stream_frame,
    encode_png_rgb,
    intrinsics_matrix,
    parse_agent,
    parse_depth_scale,
    parse_intrinsics,
)

DEFAULT_DEPTH_SCALE = 1000.0
"""Raw depth units per metre when neither the session nor the first frame says (millimetres)."""
DEFAULT_FPS = 30.0
"""A frame without a timestamp is stamped index / 30 s."""
MAX_GROUND_TRUTH_POSES = 200_000
"""Rows of ground truth a stream takes (as many as the series reads from an upload's file)."""
GROUND_TRUTH_DT_S = 0.02
"""Largest time between a frame and the ground-truth row it takes (as the ATE's association)."""


BUSY_RETRY_AFTER_S = 1
"""Seconds a client is told to wait before it sends a dropped frame again (``Retry-After``)."""


class StreamClosed(UploadError):
    """Frames after ``finish`` (or after the session ended): 409."""

    def __init__(self, message: str) -> None:
        super().__init__(message, status=409)


class StreamBusy(UploadError):
    """The session's frame buffer is full: the frame was dropped (503, module doc).

    ``dropped``: frames dropped so far in this stream, this one included;
    ``retry_after_s``: when to send it again (a client that must not lose it)."""

    def __init__(self, message: str, dropped: int, retry_after_s: int = BUSY_RETRY_AFTER_S) -> None:
        super().__init__(message, status=503)
        self.dropped = dropped
        self.retry_after_s = retry_after_s


@dataclass(frozen=True)
class RecordedFrame:
    """A stream frame read back from the session folder."""

    rgb: np.ndarray
    """(H, W, 3) float32 in [0, 1]."""
    depth: np.ndarray
    """(H, W) float32 metres, 0 = invalid."""
    K: np.ndarray
    """(3, 3) float64."""
    timestamp: float


PUT_POLL_S = 0.02
"""How often a frame that finds the queue full looks again."""


class StreamInput:
    """Frames of one streamed session, in order; thread-safe (one frame is handled at a time).

    ``frame_queue``: the worker's queue, or None while the session is queued (frames then wait
    in a buffer of ``buffer_frames`` until ``attach``; module doc)."""

    def __init__(self, frame_queue, input_dir: Path, *, intrinsics: tuple[float, ...] | None,
                 depth_scale: float | None, put_timeout_s: float, buffer_frames: int = 16,
                 color_camera=None) -> None:
        self._queue = frame_queue if frame_queue is not None else queue.Queue(maxsize=max(1, buffer_frames))
        self._buffer_frames = max(1, buffer_frames)
        self._queue_lock = threading.Lock()
        """Held to swap ``_queue`` (``attach``) and around each put, so no frame lands in the
        buffer after it was moved."""
        self._input_dir = input_dir
        self._session_K = None if intrinsics is None else intrinsics_matrix(*intrinsics[:4])
        self._session_depth_scale = depth_scale
        self._color_camera = color_camera
        """The session's colour camera (``slam.data.registration.ColorCamera``), or None: every
        frame's colour is registered to its depth already."""
        self._K: dict[int, np.ndarray] = {}
        """agent -> the camera its first frame (or the session) gave."""
        self._depth_scale: dict[int, float] = {}
        self._put_timeout_s = put_timeout_s
        self._lock = threading.Lock()
        self._count = 0
        self._refused = 0
        self._dropped = 0
        self._agent_counts: dict[int, int] = {}
        self._ground_truth: dict[int, np.ndarray] = {}
        """agent -> (N, 13) ground-truth rows sorted by time (``set_ground_truth``)."""
        self._closed_reason: str | None = None
        self._finish_reason: str | None = None
        """Why the input ended normally (``finish``, or finished after idling)."""
        self._ended: str | None = None
        """Set once the session has ended (``end``): "the session has ended (failed: ...)"."""
        self._last_frame_at: float | None = None
        (input_dir / "color").mkdir(parents=True, exist_ok=True)
        (input_dir / "depth").mkdir(parents=True, exist_ok=True)

    @property
    def frames_received(self) -> int:
        """Frames of all agents together."""
        return self._count

    @property
    def frames_refused(self) -> int:
        """Frames refused as bad (422/413: corrupt, too large, inconsistent): skipped, counted."""
        return self._refused

    @property
    def frames_dropped(self) -> int:
        """Frames dropped because the session's buffer was full (503, ``StreamBusy``)."""
        return self._dropped

    @property
    def agent_count(self) -> int:
        """1 + the highest agent id seen (1 before any frame: agent 0 is expected)."""
        return max(self._agent_counts, default=0) + 1

    def frames_of(self, agent: int) -> int:
        return self._agent_counts.get(agent, 0)

    @property
    def finished(self) -> bool:
        """No more frames are accepted (the input was finished, or the session stops or ended)."""
        return self._closed_reason is not None

    @property
    def closed_reason(self) -> str | None:
        """Why no more frames are accepted (None while they are): once the session has ended,
        "the session has ended (<status>[: <error>])", followed by how the input was finished
        when it was."""
        if self._ended is not None:
            return self._ended if self._finish_reason is None else f"{self._ended}; {self._finish_reason}"
        return self._closed_reason

    @property
    def frame_queue(self):
        """Where frames go now: the worker's queue once attached, the buffer before, None after release."""
        return self._queue

    @property
    def last_frame_at(self) -> float | None:
        """time.monotonic() of the latest accepted frame (None before the first)."""
        return self._last_frame_at

    def add_frame(self, color: bytes, depth: bytes, *, timestamp: float | str | None = None,
                  depth_scale: float | str | None = None, intrinsics: str | list | None = None,
                  agent: int | str | None = None, wait: bool = True) -> int:
        """Validate one frame of ``agent`` (default 0) and queue it for the worker; returns its
        index among that agent's frames. When the buffer is full the frame waits up to
        ``put_timeout_s`` for room, or not at all without ``wait`` (module doc).

        Raises UploadError: 422 bad frame, bad agent or missing intrinsics, 409 after finish;
        StreamBusy (503) when it found no room: the frame was dropped (send it again later).
        """
        agent = 0 if agent in (None, "") else parse_agent(agent)
        deadline = time.monotonic() + (self._put_timeout_s if wait else 0.0)
        while True:
            index = self._try_add_frame(color, depth, timestamp, depth_scale, intrinsics, agent)
            if index is not None:
                return index
            if not wait or not self._wait_for_room(deadline):
                raise self._drop(waited=wait)

    def _try_add_frame(self, color: bytes, depth: bytes, timestamp, depth_scale, intrinsics,
                       agent: int) -> int | None:
        """``add_frame`` once: the frame's index, or None when the buffer is full."""
        with self._lock:
            self._check_open()
            if self._count >= MAX_STREAM_FRAMES:
                raise UploadError(f"the session has received {self._count} frames, the most one stream session "
                                  f"takes; finish it and start another", status=413)
            if self._queue_full():
                return None  # before decoding: a stream that outruns the worker costs no decoding
            try:
                K = self._resolve_intrinsics(intrinsics, agent)
                scale = self._resolve_depth_scale(depth_scale, agent)
                index = self._agent_counts.get(agent, 0)
                stamp = index / DEFAULT_FPS if timestamp in (None, "") else _parse_timestamp(timestamp)
                frame = decode_stream_frame(color, depth, stamp, scale, K, agent=agent,
                                            color_camera=self._color_camera)
            except UploadError:
                self._refused += 1  # the frame is skipped; the stream goes on
                raise
            frame = self._with_ground_truth(frame)
            if not self._put_nowait(frame):
                return None
            self._record(agent, index, frame, color, depth)
            self._K[agent], self._depth_scale[agent] = K, scale
            self._agent_counts[agent] = index + 1
            self._count += 1
            self._last_frame_at = time.monotonic()
            return index

    def set_ground_truth(self, poses, agent: int = 0) -> int:
        """The client's ground truth for ``agent``'s frames: rows ``[t, r00, r01, r02, tx, r10,
        ..., tz]`` (seconds, then the top three rows of T_world_cam); each later frame within
        GROUND_TRUTH_DT_S of a row carries its pose, so the run reports an ATE as an upload's
        does. Returns the rows kept; UploadError (422) for anything else."""
        if not isinstance(poses, list) or not 0 < len(poses) <= MAX_GROUND_TRUTH_POSES:
            raise UploadError(f"ground_truth: expected 1 to {MAX_GROUND_TRUTH_POSES} rows of 13 numbers")
        try:
            rows = np.array(poses, dtype=np.float64)
        except (TypeError, ValueError):
            rows = np.zeros((0, 0))
        if rows.ndim != 2 or rows.shape[1] != 13 or not np.isfinite(rows).all():
            raise UploadError("ground_truth: each row must be 13 finite numbers (t and a 3x4 pose, row-major)")
        rows = rows[np.argsort(rows[:, 0], kind="stable")]
        with self._lock:
            self._ground_truth[agent] = rows
        return len(rows)

    def _with_ground_truth(self, frame: StreamFrame) -> StreamFrame:
        """The frame with its agent's ground-truth pose at its time, if the client sent one."""
        rows = self._ground_truth.get(frame.agent)
        if rows is None:
            return frame
        j = int(np.searchsorted(rows[:, 0], frame.timestamp))
        near = min((k for k in (j - 1, j) if 0 <= k < len(rows)), key=lambda k: abs(rows[k, 0] - frame.timestamp))
        if abs(rows[near, 0] - frame.timestamp) > GROUND_TRUTH_DT_S:
            return frame
        T = np.eye(4)
        T[:3, :] = rows[near, 1:].reshape(3, 4)
        return replace(frame, T_world_cam=T)

    def finish(self) -> int:
        """End the input: the worker finishes after the frames already queued (waiting up to
        ``put_timeout_s`` for room to say so). Returns the count."""
        from server.worker import END_OF_STREAM

        deadline = time.monotonic() + self._put_timeout_s
        while True:
            with self._lock:
                if self._closed_reason is not None:
                    return self._count
                if self._put_nowait(END_OF_STREAM):
                    self._closed_reason = self._finish_reason = "the stream was finished"
                    return self._count
            if not self._wait_for_room(deadline):
                raise UploadError("the session's frame buffer stayed full; finish again later", status=503)

    def finish_if_idle(self, reason: str) -> bool:
        """End the input as ``finish`` does, but only if no frame is being added and the worker
        has taken every frame queued (never waits); True when it ended the input."""
        from server.worker import END_OF_STREAM

        if not self._lock.acquire(blocking=False):
            return False
        try:
            with self._queue_lock:
                frame_queue = self._queue
                if self._closed_reason is not None or frame_queue is None or not frame_queue.empty():
                    return False
                try:
                    frame_queue.put_nowait(END_OF_STREAM)
                except queue.Full:
                    return False
            self._closed_reason = self._finish_reason = reason
            return True
        finally:
            self._lock.release()

    def attach(self, frame_queue) -> None:
        """The session starts: move the buffered frames (in order) to the worker's
        ``frame_queue`` and send the later ones there. It must hold at least the buffer's
        size (the executors make it ``stream_queue_frames`` long, as the buffer). Nothing
        happens after ``release``."""
        with self._queue_lock:
            buffered = self._queue
            if buffered is None or buffered is frame_queue:
                return
            while True:
                try:
                    item = buffered.get_nowait()
                except queue.Empty:
                    break
                frame_queue.put_nowait(item)
            self._queue = frame_queue

    def close(self, reason: str) -> None:
        """Refuse further frames (the session stops or was cancelled). Does not wait for a
        frame that is waiting for room in the queue: that one gives up within a poll."""
        if self._closed_reason is None:
            self._closed_reason = reason

    def end(self, status: str, error: str | None = None) -> None:
        """The session has ended (``status``, ``error``): refuse frames, saying so."""
        self.close(f"the session {status}")
        self._ended = f"the session has ended ({status}{': ' + error if error else ''})"

    def release(self, reason: str) -> None:
        """Close, and let go of the queue (its worker is gone) so its OS resources are freed."""
        self.close(reason)
        with self._queue_lock:
            self._queue = None

    def _check_open(self) -> None:
        reason = self.closed_reason
        if reason is not None:
            raise StreamClosed(f"the stream does not accept frames: {reason}")

    def _drop(self, waited: bool) -> StreamBusy:
        """Count a frame that found no room; the error that says so."""
        with self._lock:
            self._dropped += 1
            dropped = self._dropped
        why = (f"the session has not taken a frame for {self._put_timeout_s:g} s" if waited else
               "the session is behind")
        return StreamBusy(f"{why} (its buffer of {self._buffer_frames} frames is full): frame dropped, "
                          f"{dropped} so far; send it again after {BUSY_RETRY_AFTER_S} s", dropped)

    def _queue_full(self) -> bool:
        """Whether the worker's queue (or the buffer) has no room now; StreamClosed after ``release``."""
        with self._queue_lock:
            if self._queue is None:
                raise StreamClosed("the stream does not accept frames: the session has ended")
            return self._queue.full()

    def _put_nowait(self, item) -> bool:
        """Queue ``item`` if there is room; StreamClosed after ``release``."""
        with self._queue_lock:
            if self._queue is None:
                raise StreamClosed("the stream does not accept frames: the session has ended")
            try:
                self._queue.put_nowait(item)
                return True
            except queue.Full:
                return False

    def _wait_for_room(self, deadline: float, poll_s: float = PUT_POLL_S) -> bool:
        """Wait (holding no lock) until the queue has room: True, or False at ``deadline``.
        Raises StreamClosed if the stream is closed meanwhile."""
        while True:
            self._check_open()
            if not self._queue_full():
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(poll_s)

    def _resolve_intrinsics(self, intrinsics: str | list | None, agent: int) -> np.ndarray:
        # The session's camera applies to every agent; without one, each agent's first frame names its own.
        known = self._K.get(agent, self._session_K)
        whose = "" if agent == 0 else f" of agent {agent}"
        if intrinsics not in (None, ""):
            K = intrinsics_matrix(*parse_intrinsics(intrinsics))
            if known is not None and not np.allclose(K, known):
                raise UploadError(f"intrinsics{whose}: changed mid-stream (was {_k_text(known)}, got {_k_text(K)}); "
                                  f"start a new session (or use another agent) for another camera")
            return K
        if known is None:
            raise UploadError(f"intrinsics: required on the first frame{whose} (or when creating the session) "
                              "as 'fx,fy,cx,cy'")
        return known

    def _resolve_depth_scale(self, depth_scale: float | str | None, agent: int) -> float:
        if depth_scale not in (None, ""):
            return parse_depth_scale(depth_scale)
        if agent in self._depth_scale:
            return self._depth_scale[agent]
        return self._session_depth_scale if self._session_depth_scale is not None else DEFAULT_DEPTH_SCALE

    def _record(self, agent: int, index: int, frame: StreamFrame, color: bytes, depth: bytes) -> None:
        if frame.color_valid is not None:
            color = encode_png_rgb(frame.rgb)  # the colour registered onto depth, as replays read it
        extension = "png" if color.startswith(PNG_SIGNATURE) else "jpg"
        stem = f"{index:06d}" if agent == 0 else f"agent{agent}_{index:06d}"
        color_name = f"color/{stem}.{extension}"
        depth_name = f"depth/{stem}.png"
        (self._input_dir / color_name).write_bytes(color)
        (self._input_dir / depth_name).write_bytes(depth)
        K = frame.K
        row = {"agent": agent, "index": index, "timestamp": frame.timestamp, "color": color_name,
               "depth": depth_name, "depth_scale": frame.depth_scale, "K": [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]}
        with open(self._input_dir / "frames.jsonl", "a") as log:
            log.write(json.dumps(row) + "\n")


def _parse_timestamp(value: float | str) -> float:
    try:
        stamp = float(value)
    except (TypeError, ValueError):
        raise UploadError(f"timestamp: expected seconds as a number, got {value!r}") from None
    if not np.isfinite(stamp):
        raise UploadError(f"timestamp: must be finite, got {value!r}")
    return stamp


def _k_text(K: np.ndarray) -> str:
    return f"{K[0, 0]:g},{K[1, 1]:g},{K[0, 2]:g},{K[1, 2]:g}"


def read_recorded_frame(input_dir: Path, index: int, agent: int = 0) -> RecordedFrame:
    """Frame ``index`` of ``agent`` in a recorded stream. KeyError when there is no such frame."""
    log = input_dir / "frames.jsonl"
    if not log.is_file():
        raise KeyError("no frames were streamed to this session")
    with open(log) as rows:
        for line in rows:
            row = json.loads(line)
            if row["index"] == index and row.get("agent", 0) == agent:
                break
        else:
            whose = "" if agent == 0 else f" of agent {agent}"
            raise KeyError(f"frame {index}{whose} was not streamed to this session")
    # Names come from our own log, but are still checked to stay inside the input folder.
    color_path = (input_dir / row["color"]).resolve()
    depth_path = (input_dir / row["depth"]).resolve()
    for path in (color_path, depth_path):
        if input_dir.resolve() not in path.parents:
            raise KeyError(f"frame {index}: recorded path outside the session folder")
    rgb = decode_color(color_path.read_bytes()).astype(np.float32) / 255.0
    depth = decode_depth(depth_path.read_bytes()).astype(np.float32) / np.float32(row["depth_scale"])
    return RecordedFrame(rgb=rgb, depth=depth, K=intrinsics_matrix(*row["K"]), timestamp=float(row["timestamp"]))
