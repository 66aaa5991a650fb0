"""``voxfusion stream SOURCE --url URL``: send a camera (or a replayed folder) to a running server.

Flow: open the source (its camera is known before anything is sent), create a stream session
over HTTP (``POST /api/sessions``, intrinsics and depth scale given there), open the session's
WebSocket (``/api/sessions/ID/stream``, protocol in ``server/routes_stream.py``), wait until
the session's worker tracks (its start takes seconds; a replay's clock starts then), send binary
frames waiting for each answer (the server's flow control), then ``{"type": "finish"}``.

Back-pressure: a reader thread takes frames from the source as they arrive and puts them in a
``FrameSlot`` of one frame. By default a new frame replaces the one not yet sent (counted as
dropped), so the camera never stalls and nothing queues; with ``all_frames`` the reader waits
for the slot instead (a replay then runs at the server's pace and every frame is processed).
The server answers every frame at once, accepted or dropped (its buffer is full); a dropped
frame is sent again after the server's ``retry_after_s`` with ``all_frames`` (nothing is lost;
``BUSY_WAIT_S`` without room ends the stream), and counted and left behind otherwise (a live
camera's next frame is newer). The end prints frames sent, accepted and dropped.

Faults end with a message on stderr and a non-zero exit code: 1 the stream failed (server
gone, source failed mid-stream), 2 bad source or arguments, 3 the server could not be reached
or refused the session (401: token), 130 Ctrl-C. The session is finished with the frames it
has whenever the server is still there.

A stream socket that breaks mid-stream is reopened on the same session (``reconnect``, up to
``RECONNECT_S`` for a server that cannot be reached meanwhile): after a network blip the
stream goes on. A server that restarted has no stream for the session any more (it lists it
as failed, "interrupted: ..."), so the client says how the server lists it and exits 1.
"""

from __future__ import annotations

import json
import os
import struct
import sys
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from collections import deque
from dataclasses import dataclass, field
from typing import Callable, TextIO

from client.camera_sources import CameraInfo, EncodedFrame, FrameSource, PendingFrame, SourceError

BINARY_PREFIX = struct.Struct("<dI")

HTTP_TIMEOUT_S = 10.0
ACK_TIMEOUT_S = 90.0
"""Longest wait for the answer to one frame (the server answers at once; older ones held a
frame up to 30 s before answering 503)."""
RECONNECT_S = 15.0
"""How long a broken stream tries to get back to its session: a network blip, or a server that
restarts (it comes back without the session's stream; then the session's state is reported)."""
BUSY_WAIT_S = 300.0
"""``all_frames``: how long one frame is sent again while the server drops it (its buffer full)
before the stream ends as failed: the session has stopped taking frames."""
RETRY_AFTER_S = (0.05, 0.5, 5.0)
"""Wait before sending a dropped frame again: (least, without the server's word, most) seconds."""
START_TIMEOUT_S = 600.0
"""Longest wait for a new session to start tracking (it may be queued behind others)."""
STATUS_EVERY_S = 0.25
LIVE_STATUS_EVERY_S = 0.1
"""Keep-the-newest mode: the sender waits on the tracked count (``MAX_AHEAD``), so it is read
more often: a count a quarter second old left the tracker without frames."""
MAX_AHEAD = 2
"""Keep-the-newest mode: frames acknowledged but not yet tracked by the server, at most. The
server itself buffers up to 16 frames (``stream_queue_frames``) before it holds an ack back, so
without this a slow session would track frames many seconds old."""
PROGRESS_EVERY_S = 0.5
LATENCY_SAMPLES = 10000
"""Latencies kept for the summary (the newest ones)."""

EXIT_OK, EXIT_FAILED, EXIT_SOURCE, EXIT_SERVER = 0, 1, 2, 3
EXIT_INTERRUPTED = 130
"""Ctrl-C (as shells report SIGINT); the session was still finished with the frames sent."""


class StreamError(RuntimeError):
    """A fault that ends the stream; ``code`` is the exit code, the message one line."""

    def __init__(self, message: str, code: int = EXIT_FAILED) -> None:
        super().__init__(message)
        self.code = code


class Unreachable(StreamError):
    """Nothing answers at the server's address (not running, or restarting)."""


class ConnectionLost(StreamError):
    """The stream socket broke mid-stream: the session may still be there, worth reconnecting.
    ``unsent``: the frame whose sending failed (it never left, so it is sent again after a
    reconnect); None when the break came while waiting for an ack (the server may have it)."""

    def __init__(self, message: str, unsent: PendingFrame | None = None) -> None:
        super().__init__(message)
        self.unsent = unsent


# --------------------------------------------------------------------------------------------
# The newest-frame buffer


class FrameSlot:
    """A buffer of one frame between the source's thread and the sender.

    ``put`` with ``replace=True`` overwrites a frame that has not been taken (``dropped`` + 1);
    with ``replace=False`` it waits until the slot is free. ``close`` marks the end of the
    source (``error``: why it ended early); ``get`` then returns None once the slot is empty.
    """

    def __init__(self, replace: bool = True) -> None:
        self.replace = replace
        self.dropped = 0
        self.error: str | None = None
        self._item: PendingFrame | None = None
        self._closed = False
        self._cond = threading.Condition()

    def put(self, item: PendingFrame, stop: Callable[[], bool] = lambda: False) -> None:
        """Offer a frame; without ``replace``, wait for the slot (giving up when ``stop()``)."""
        with self._cond:
            if self.replace:
                self.dropped += self._item is not None
            else:
                while self._item is not None:
                    if stop():
                        return
                    self._cond.wait(0.1)
            self._item = item
            self._cond.notify_all()

    def get(self, timeout: float | None = None) -> PendingFrame | None:
        """The newest frame (waits for one); None when the source has ended and nothing is left."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while self._item is None and not self._closed:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    raise TimeoutError("no frame from the source")
                self._cond.wait(left if left is not None else 0.5)
            item, self._item = self._item, None
            self._cond.notify_all()
            return item

    def ended(self) -> bool:
        """The source has ended and its last frame was taken: nothing more will come."""
        with self._cond:
            return self._closed and self._item is None

    def close(self, error: str | None = None) -> None:
        with self._cond:
            self._closed = True
            self.error = self.error or error
            self._cond.notify_all()


def read_source(source: FrameSource, slot: FrameSlot, stop: threading.Event) -> None:
    """Thread body: move frames from the source into the slot until it ends (or ``stop``)."""
    error = None
    try:
        for item in source.frames(stop.is_set):
            slot.put(item, stop.is_set)
    except SourceError as exc:
        error = str(exc)
    except Exception as exc:  # a device library's own error types
        error = f"the source failed: {type(exc).__name__}: {exc}"
    finally:
        slot.close(error)


# --------------------------------------------------------------------------------------------
# HTTP


@dataclass(frozen=True)
class Server:
    """Where the server is: ``url`` like ``http://127.0.0.1:8000`` and an optional token."""

    url: str
    token: str | None = None

    def api(self, method: str, path: str, body: dict | None = None, timeout: float = HTTP_TIMEOUT_S) -> dict:
        """One JSON request; StreamError (code 3) with the server's ``detail`` on failure."""
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(self.url.rstrip("/") + path, data=data, method=method)
        request.add_header("accept", "application/json")
        if data is not None:
            request.add_header("content-type", "application/json")
        if self.token:
            request.add_header("authorization", f"Bearer {self.token}")
        try:
            with urllib.request.urlopen(request, timeout=timeout) as response:
                return json.loads(response.read() or b"null")
        except urllib.error.HTTPError as error:
            raise StreamError(self._http_message(error), EXIT_SERVER) from None
        except (urllib.error.URLError, OSError) as error:
            reason = getattr(error, "reason", error)
            raise Unreachable(f"cannot reach the server at {self.url}: {reason}", EXIT_SERVER) from None

    def _http_message(self, error: urllib.error.HTTPError) -> str:
        try:
            detail = json.loads(error.read()).get("detail")
        except (ValueError, AttributeError, OSError):
            detail = None
        if error.code == 401:
            given = "the token given was refused" if self.token else "the server needs a token"
            return f"{given} (401): pass --token or set VOXFUSION_TOKEN to the server's token"
        return f"the server answered {error.code}: {detail or error.reason}"

    def websocket_url(self, session_id: str) -> str:
        parts = urllib.parse.urlsplit(self.url)
        scheme = "wss" if parts.scheme == "https" else "ws"
        query = urllib.parse.urlencode({"token": self.token}) if self.token else ""
        return urllib.parse.urlunsplit((scheme, parts.netloc, f"{parts.path.rstrip('/')}/api/sessions/"
                                        f"{session_id}/stream", query, ""))

    def page_url(self, session_id: str | None = None) -> str:
        """The page, opened on ``session_id`` when given (``/?session=ID``)."""
        fields = {**({"session": session_id} if session_id else {}), **({"token": self.token} if self.token else {})}
        query = "?" + urllib.parse.urlencode(fields) if fields else ""
        return self.url.rstrip("/") + "/" + query


def create_session(server: Server, info: CameraInfo, preset: str | None, live: bool = False) -> str:
    """POST a stream session with the source's camera; its id. ``live``: frames come at a
    camera's pace, which does not wait (the session's ``live``)."""
    body: dict = {"source": "stream", "intrinsics": info.intrinsics_text(), "depth_scale": info.depth_scale}
    if preset:
        body["preset"] = preset
    if live:
        body["live"] = True
    return str(server.api("POST", "/api/sessions", body)["id"])


# --------------------------------------------------------------------------------------------
# Progress


@dataclass
class Progress:
    """What the stream did so far (counts of frames; seconds)."""

    arrived: int = 0
    sent: int = 0
    """Frame messages sent (a frame sent again counts again)."""
    resent: int = 0
    """Of those, the ones that sent again a frame the server had dropped (``all_frames``)."""
    acked: int = 0
    rejected: int = 0
    dropped: int = 0
    """Frames replaced in the slot by newer ones before they could be sent."""
    server_dropped: int = 0
    """Frames the server dropped (its buffer full) and not sent again (live mode)."""
    lost: int = 0
    """Frames in flight when the connection broke (reconnected after; the server may or may
    not have taken them, so they are not sent twice)."""
    server_fps: float | None = None
    server_frames_done: int | None = None
    server_handled: int | None = None
    """Frames the server is done with, in the order sent: the ones tracked, and in a live
    session also those it passed over for a newer one (its newest tracked frame + 1); None
    while the status cannot be read. The sender waits on it (``MAX_AHEAD``)."""
    ack_latency_s: deque = field(default_factory=lambda: deque(maxlen=LATENCY_SAMPLES))
    """Seconds from a frame's arrival from the source to its ack."""
    track_latency_s: deque = field(default_factory=lambda: deque(maxlen=LATENCY_SAMPLES))
    """Seconds from a frame leaving the client to the server counting it tracked (to within a
    status poll, ``STATUS_EVERY_S``)."""
    sent_at: dict = field(default_factory=dict)
    """Ack index -> ``time.monotonic()`` when it was sent, until the server has tracked it."""
    first_track_latency_s: float | None = None
    """Seconds from the first frame timed (the first frame sent, unless a live session passed
    it over) leaving the client to the server counting it tracked: the session's first pose
    (to within a status poll)."""

    def note_tracked(self, handled: int, now: float, newest_only: bool = False) -> None:
        """The server is done with the first ``handled`` frames sent: time the ones that were
        waiting; ``newest_only`` (a live session, which passes over frames): only the newest
        of them is known to be tracked."""
        for index in sorted(i for i in self.sent_at if i < handled):
            latency = now - self.sent_at.pop(index)
            if newest_only and index != handled - 1:
                continue
            self.track_latency_s.append(latency)
            if self.first_track_latency_s is None:
                self.first_track_latency_s = latency

    def line(self) -> str:
        fps = "-" if self.server_fps is None else f"{self.server_fps:.1f}"
        done = "-" if self.server_frames_done is None else str(self.server_frames_done)
        lost = f"lost {self.lost}  " if self.lost else ""
        return (f"sent {self.frames_sent}  acked {self.acked}  dropped {self.all_dropped}  {lost}"
                f"rejected {self.rejected}  "
                f"server: {done} tracked, {fps} frames/s")

    @property
    def frames_sent(self) -> int:
        """Frames sent, each counted once however often it was sent again."""
        return self.sent - self.resent

    @property
    def all_dropped(self) -> int:
        """Frames that never reached the server's queue: replaced before sending, or dropped by it."""
        return self.dropped + self.server_dropped

    def summary(self) -> str:
        """The end's counts in one line: sent, accepted, dropped (and why), rejected."""
        resent = f", {self.resent} sent again after the server dropped them" if self.resent else ""
        return (f"frames sent {self.frames_sent}, accepted {self.acked}, dropped {self.all_dropped} "
                f"({self.server_dropped} by the server, its buffer full; {self.dropped} replaced by newer ones "
                f"before sending), rejected {self.rejected}{resent}")

    def latency_summary(self) -> str:
        parts = []
        for what, samples in (("arrival to ack", self.ack_latency_s), ("sent to tracked", self.track_latency_s)):
            if samples:
                values = sorted(samples)
                parts.append(f"{what}: median {values[len(values) // 2] * 1000:.0f} ms, "
                             f"max {values[-1] * 1000:.0f} ms")
        if self.first_track_latency_s is not None:
            parts.append(f"first frame tracked {self.first_track_latency_s * 1000:.0f} ms after it was sent")
        return "; ".join(parts) or "no acks"


class StatusPoller:
    """Reads the session's status now and then in a thread (frames/s, frames tracked)."""

    def __init__(self, server: Server, session_id: str, progress: Progress, live: bool = False) -> None:
        self.server, self.session_id, self.progress, self.live = server, session_id, progress, live
        self.every_s = LIVE_STATUS_EVERY_S if live else STATUS_EVERY_S
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="stream-status")

    def __enter__(self) -> "StatusPoller":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=HTTP_TIMEOUT_S)

    def _run(self) -> None:
        while True:
            try:
                state = self.server.api("GET", f"/api/sessions/{self.session_id}", timeout=5)
            except StreamError:
                self.progress.server_handled = None  # unknown: the sender stops waiting on it
                if self._stop.wait(self.every_s):
                    return
                continue
            self.progress.server_fps = state.get("fps")
            self.progress.server_frames_done = state.get("frames_done")
            self.progress.server_handled = self._handled(state)
            if self.progress.server_handled is not None:
                self.progress.note_tracked(self.progress.server_handled, time.monotonic(), newest_only=self.live)
            if self._stop.wait(self.every_s):
                return

    def _handled(self, state: dict) -> int | None:
        """``Progress.server_handled`` from a status (``latest_frame`` is agent 0's)."""
        if not self.live:
            return state.get("frames_done")
        latest = state.get("latest_frame")
        return 0 if latest is None else int(latest) + 1


# --------------------------------------------------------------------------------------------
# The WebSocket loop


def binary_message(frame: EncodedFrame) -> bytes:
    """The protocol's binary frame: <float64 timestamp><uint32 colour length><colour><depth>."""
    return BINARY_PREFIX.pack(frame.timestamp, len(frame.color)) + frame.color + frame.depth


def _receive(socket, timeout: float) -> dict:
    from websockets.exceptions import ConnectionClosed

    try:
        message = json.loads(socket.recv(timeout=timeout))
    except TimeoutError:
        raise StreamError(f"the server sent no answer within {timeout:g} s") from None
    except ConnectionClosed as error:
        raise ConnectionLost(f"the server closed the stream ({_close_reason(error)})") from None
    except OSError as error:
        raise ConnectionLost(f"the connection to the server broke: {error}") from None
    return message if isinstance(message, dict) else {}


def _close_reason(error) -> str:
    frame = getattr(error, "rcvd", None)
    if frame is None:
        return "connection lost"
    if frame.code in (1001, 1012):
        return f"code {frame.code}: the server is shutting down"
    return f"code {frame.code}: {frame.reason}" if frame.reason else f"code {frame.code}"


def send_frame(socket, item: PendingFrame, progress: Progress) -> float | None:
    """Send one frame and wait for its answer; counts go to ``progress``. None when the server
    took it (or refused it as bad); when it dropped it (its buffer full), the seconds to wait
    before sending it again (``deliver`` decides whether to)."""
    sent_at = _send_message(socket, binary_message(item.encode()), item)
    progress.sent += 1
    answer = _receive(socket, ACK_TIMEOUT_S)
    if answer.get("type") == "ack":
        progress.acked += 1
        progress.ack_latency_s.append(time.monotonic() - item.arrived)
        if isinstance(answer.get("index"), int) and len(progress.sent_at) < LATENCY_SAMPLES:
            progress.sent_at[answer["index"]] = sent_at
        return None
    if answer.get("status") == 503:  # "dropped"; an older server's "error" after its wait
        return retry_after_s(answer)
    if answer.get("type") == "error" and answer.get("status") == 409:
        raise StreamError(f"the session does not take frames any more: {answer.get('detail')}")
    progress.rejected += 1
    print(f"voxfusion stream: frame {item.index} rejected: {answer.get('detail', answer)}", file=sys.stderr)
    return None


def deliver(socket, item: PendingFrame, progress: Progress, resend_dropped: bool) -> None:
    """Send one frame. One the server drops is sent again after the wait it asks for with
    ``resend_dropped`` (StreamError after BUSY_WAIT_S of that), else counted as dropped."""
    busy_since = time.monotonic()
    while (retry_s := send_frame(socket, item, progress)) is not None:
        if not resend_dropped:
            progress.server_dropped += 1
            return
        if time.monotonic() - busy_since > BUSY_WAIT_S:
            raise StreamError(f"the session took no frame for {BUSY_WAIT_S:g} s (its buffer stayed full)")
        time.sleep(retry_s)
        progress.resent += 1


def _send_message(socket, message: bytes | str, item: PendingFrame | None) -> float:
    """Send ``item``'s message (or the header); ``time.monotonic()`` when it went (ConnectionLost: it did not)."""
    from websockets.exceptions import ConnectionClosed

    sent_at = time.monotonic()
    try:
        socket.send(message)
    except ConnectionClosed as error:
        raise ConnectionLost(f"the server closed the stream ({_close_reason(error)})", item) from None
    except OSError as error:
        raise ConnectionLost(f"the connection to the server broke while sending: {error}", item) from None
    return sent_at


def retry_after_s(answer: dict) -> float:
    """Seconds to wait before sending a dropped frame again: the server's word, within bounds."""
    least, default, most = RETRY_AFTER_S
    value = answer.get("retry_after_s")
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return default
    return min(max(float(value), least), most)


def open_socket(server: Server, session_id: str):
    """Connect the session's WebSocket and exchange the header (the session has the camera)."""
    from websockets.exceptions import InvalidStatus, WebSocketException
    from websockets.sync.client import connect

    try:
        socket = connect(server.websocket_url(session_id), open_timeout=HTTP_TIMEOUT_S, max_size=None,
                         close_timeout=5)
    except InvalidStatus as error:
        raise StreamError(f"the server refused the stream socket ({error.response.status_code})", EXIT_SERVER) from None
    except (WebSocketException, OSError, TimeoutError) as error:
        raise Unreachable(f"cannot open the stream socket: {error}", EXIT_SERVER) from None
    _send_message(socket, json.dumps({}), None)
    answer = _receive(socket, HTTP_TIMEOUT_S)
    if answer.get("type") != "ready":
        socket.close()
        raise StreamError(f"the server did not accept the stream: {answer.get('detail', answer)}", EXIT_SERVER)
    return socket


def ground_truth_rows(source: FrameSource) -> list[list[float]]:
    """A folder's ground truth as the protocol's rows (``[t, 3x4 pose row-major]``, one per
    frame that has one); [] for a camera or a folder without ground truth."""
    import numpy as np

    sequence = getattr(source, "sequence", None)
    stamps, poses = getattr(sequence, "timestamps", None), getattr(sequence, "gt_poses", None)
    if stamps is None or poses is None:
        return []
    return [[float(t), *np.asarray(T, np.float64)[:3, :].reshape(-1).tolist()]
            for t, T in zip(stamps, poses) if T is not None]


def send_ground_truth(socket, source: FrameSource, out: TextIO) -> None:
    """Send the folder's ground truth once, before the frames, so that the session reports an
    ATE as an upload does (a server that does not know the message says so; the stream goes on)."""
    rows = ground_truth_rows(source)
    if not rows:
        return
    _send_message(socket, json.dumps({"type": "ground_truth", "poses": rows}), None)
    answer = _receive(socket, HTTP_TIMEOUT_S)
    if answer.get("type") == "ground_truth":
        print(f"voxfusion stream: sent the ground truth ({answer.get('poses')} poses): the session reports an ATE",
              file=out, flush=True)
    else:
        print(f"voxfusion stream: the server did not take the ground truth: {answer.get('detail', answer)}",
              file=out, flush=True)


def finish(server: Server, session_id: str, socket) -> int | None:
    """End the input: over the socket when it is open, else ``POST .../finish``; frames the
    server has, or None when it cannot be told (server gone)."""
    if socket is not None:
        try:
            socket.send(json.dumps({"type": "finish"}))
            for _ in range(3):  # an answer still under way (Ctrl-C while waiting for it) comes first
                answer = _receive(socket, ACK_TIMEOUT_S)
                if answer.get("type") == "finished":
                    return int(answer["frames"])
                if answer.get("type") not in ("ack", "dropped"):
                    break
        except Exception:
            pass
    try:
        return int(server.api("POST", f"/api/sessions/{session_id}/finish", timeout=HTTP_TIMEOUT_S)["frames"])
    except StreamError:
        return None


def session_state(server: Server, session_id: str) -> str:
    """How the server lists the session now, in words (for the message after a fault)."""
    try:
        state = server.api("GET", f"/api/sessions/{session_id}", timeout=5)
    except StreamError:
        return "the server cannot be reached"
    error = f" ({state['error']})" if state.get("error") else ""
    return f"the server lists it as {state.get('status')}{error}, frames tracked: {state.get('frames_done') or 0}"


def reconnect(server: Server, session_id: str, lost: ConnectionLost, timeout_s: float | None = None):
    """Reopen the session's stream socket after ``lost``, waiting up to ``timeout_s`` (default
    RECONNECT_S) for a server that cannot be reached (restarting); StreamError when it refuses
    the socket (a restarted server has no stream for the session any more) or does not come back."""
    timeout_s = RECONNECT_S if timeout_s is None else timeout_s
    print(f"voxfusion stream: {lost}; reconnecting (up to {timeout_s:g} s)", file=sys.stderr, flush=True)
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            socket = open_socket(server, session_id)
        except Unreachable:
            if time.monotonic() > deadline:
                raise StreamError(f"{lost}; the server did not come back within {timeout_s:g} s") from None
            time.sleep(0.5)
            continue
        except StreamError:
            raise StreamError(f"{lost}; the session cannot take frames any more: "
                              f"{session_state(server, session_id)}") from None
        print("voxfusion stream: reconnected; streaming on", file=sys.stderr, flush=True)
        return socket


def wait_until_tracking(server: Server, session_id: str, out: TextIO, timeout_s: float = START_TIMEOUT_S) -> None:
    """Wait (bounded) until the session's worker tracks: frames sent before would only wait in
    the server's queue, and a replay's clock would run while the worker starts (seconds)."""
    deadline, said = time.monotonic() + timeout_s, False
    while True:
        state = server.api("GET", f"/api/sessions/{session_id}")
        if state.get("status") == "running" and state.get("phase") == "tracking":
            return
        if state.get("status") in ("finished", "failed", "cancelled"):
            raise StreamError(f"the session ended before it started: {state.get('error') or state.get('status')}")
        if state.get("status") == "queued" and not said and time.monotonic() > deadline - timeout_s + 3:
            print("voxfusion stream: the session is queued behind others; waiting for it to start", file=out,
                  flush=True)
            said = True
        if time.monotonic() > deadline:
            raise StreamError(f"the session did not start within {timeout_s:g} s ({state.get('status')})")
        time.sleep(0.25)


def wait_until_done(server: Server, session_id: str, timeout_s: float) -> dict:
    """Poll the status until the session ended (``timeout_s`` bounds it)."""
    deadline = time.monotonic() + timeout_s
    while True:
        state = server.api("GET", f"/api/sessions/{session_id}")
        if state.get("status") in ("finished", "failed", "cancelled"):
            return state
        if time.monotonic() > deadline:
            raise StreamError(f"the session was still {state.get('status')} after {timeout_s:g} s")
        time.sleep(0.5)


# --------------------------------------------------------------------------------------------
# The whole run


@dataclass(frozen=True)
class StreamOptions:
    """What ``voxfusion stream`` was asked (see ``add_stream_arguments``)."""

    preset: str | None = None
    all_frames: bool = False
    wait_s: float | None = None
    """After finishing, wait up to this long for the session's result (None: do not wait)."""
    quiet: bool = False


@dataclass(frozen=True)
class StreamResult:
    """How it ended: exit code, session id (None if none was made), counts, final status."""

    code: int
    session_id: str | None
    progress: Progress
    frames_on_server: int | None = None
    state: dict | None = None


class _Printer:
    """The progress line, redrawn in place on a terminal, every few seconds otherwise."""

    def __init__(self, out: TextIO | None, quiet: bool) -> None:
        self.out, self.quiet = out or sys.stdout, quiet
        self.tty = self.out.isatty()
        self.last = 0.0

    def update(self, progress: Progress, force: bool = False) -> None:
        now = time.monotonic()
        every = PROGRESS_EVERY_S if self.tty else 5.0
        if self.quiet or (not force and now - self.last < every):
            return
        self.last = now
        print(("\r" + progress.line() + "   ") if self.tty else progress.line(), end="" if self.tty else "\n",
              file=self.out, flush=True)

    def done(self) -> None:
        if self.tty and not self.quiet:
            print(file=self.out)


def stream(source: FrameSource, server: Server, options: StreamOptions, out: TextIO | None = None) -> StreamResult:
    """Create the session, send the source's frames, finish; never raises StreamError."""
    out = out or sys.stdout
    progress = Progress()
    try:
        session_id = create_session(server, source.info, options.preset, live=not options.all_frames)
    except StreamError as error:
        print(f"voxfusion stream: {error}", file=sys.stderr)
        return StreamResult(error.code, None, progress)
    print(f"voxfusion stream: session {session_id} from {source.info.name}", file=out)
    print(f"voxfusion stream: open {server.page_url(session_id)} to watch it", file=out, flush=True)
    # To the end: frames are tracked after finishing too.
    with StatusPoller(server, session_id, progress, live=not options.all_frames):
        result = _stream_session(source, server, session_id, options, progress, out)
    if progress.track_latency_s or progress.ack_latency_s:
        print(f"voxfusion stream: latency ({len(progress.track_latency_s)} of {progress.acked} frames tracked "
              f"while the client watched): {progress.latency_summary()}", file=out, flush=True)
    return result


def _stream_session(source: FrameSource, server: Server, session_id: str, options: StreamOptions,
                    progress: Progress, out: TextIO) -> StreamResult:
    """Send, finish and (``--wait``) wait for the result of the session just created."""
    printer = _Printer(out, options.quiet)
    socket, code, message = _send_source(source, server, session_id, options, progress, printer)
    printer.update(progress, force=True)
    printer.done()
    print(f"voxfusion stream: {progress.summary()}", file=out, flush=True)
    frames = finish(server, session_id, socket)
    if socket is not None:
        socket.close()
    if message:
        print(f"voxfusion stream: {message}", file=sys.stderr)
    if frames is None:
        print(f"voxfusion stream: could not finish session {session_id} ({session_state(server, session_id)}); "
              f"{progress.acked} frames were acknowledged", file=sys.stderr)
        return StreamResult(code or EXIT_FAILED, session_id, progress)
    print(f"voxfusion stream: finished session {session_id}: {frames} frames on the server, "
          f"{progress.all_dropped} dropped{_lost(progress)}", file=out, flush=True)
    if options.wait_s is None or code not in (EXIT_OK, EXIT_INTERRUPTED):
        return StreamResult(code, session_id, progress, frames)
    return _wait_for_result(server, session_id, options.wait_s, code, progress, frames, out)


def _lost(progress: Progress) -> str:
    return f", {progress.lost} lost when the connection broke" if progress.lost else ""


def _send_source(source: FrameSource, server: Server, session_id: str, options: StreamOptions,
                 progress: Progress, printer: _Printer) -> tuple[object, int, str | None]:
    """Open the socket, run the source's reader and send; (socket or None, exit code, message)."""
    slot = FrameSlot(replace=not options.all_frames)
    stop = threading.Event()
    reader = threading.Thread(target=read_source, args=(source, slot, stop), daemon=True, name="stream-source")
    socket, code, message = None, EXIT_OK, None
    try:
        socket = open_socket(server, session_id)
        send_ground_truth(socket, source, printer.out)
        wait_until_tracking(server, session_id, printer.out)
        reader.start()
        unsent = None
        while True:
            try:
                code, message = _send_all(socket, slot, progress, printer,
                                          None if options.all_frames else MAX_AHEAD, unsent)
                break
            except ConnectionLost as lost:
                progress.lost += lost.unsent is None
                unsent = lost.unsent
                socket.close()
                socket = reconnect(server, session_id, lost)
    except StreamError as error:
        code, message = error.code, str(error)
    except KeyboardInterrupt:
        code = EXIT_INTERRUPTED
        print("\nvoxfusion stream: interrupted: finishing the session with the frames sent", file=sys.stderr)
    finally:
        stop.set()
        progress.dropped = slot.dropped
        source.close()
    return socket, code, message


def _wait_for_result(server: Server, session_id: str, wait_s: float, code: int, progress: Progress,
                     frames: int, out: TextIO) -> StreamResult:
    """``--wait``: poll until the session ended and say how; exit 1 unless it finished."""
    try:
        state = wait_until_done(server, session_id, wait_s)
    except StreamError as error:
        print(f"voxfusion stream: {error}", file=sys.stderr)
        return StreamResult(EXIT_FAILED, session_id, progress, frames)
    error = f"; error: {state['error']}" if state.get("error") else ""
    print(f"voxfusion stream: session {state['status']}: {state.get('frames_done')} frames tracked, "
          f"{state.get('fps') or 0:.2f} frames/s{error}", file=out, flush=True)
    if state["status"] != "finished" and code == EXIT_OK:
        code = EXIT_FAILED
    return StreamResult(code, session_id, progress, frames, state)


def wait_for_server(progress: Progress, max_ahead: int, timeout_s: float = ACK_TIMEOUT_S,
                    tick: Callable[[], None] = lambda: None) -> None:
    """Wait (bounded) until the server has tracked all but ``max_ahead`` of the acknowledged
    frames (``progress.server_handled`` comes from the ``StatusPoller``); ``tick`` runs
    while waiting (the progress line)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        tick()
        done = progress.server_handled
        if done is None or progress.acked - done <= max_ahead:
            return  # caught up, or the server's status cannot be read (the send will tell)
        time.sleep(0.02)


def _show(printer: _Printer, progress: Progress, slot: FrameSlot) -> None:
    progress.dropped = slot.dropped
    printer.update(progress)


def _send_all(socket, slot: FrameSlot, progress: Progress, printer: _Printer,
              max_ahead: int | None = None, first: PendingFrame | None = None) -> tuple[int, str | None]:
    """Send ``first`` (a frame a broken connection did not send), then until the source ends;
    (exit code, message) where the source failed. With ``max_ahead``, a frame is taken from
    the slot only once the server has caught up (the newest one then)."""
    while True:
        if first is None and slot.ended():
            break  # nothing more will come: no waiting for the server
        if first is None and max_ahead is not None and progress.acked > max_ahead:
            wait_for_server(progress, max_ahead, tick=lambda: _show(printer, progress, slot))
        item, first = first or slot.get(), None
        if item is None:
            break
        deliver(socket, item, progress, resend_dropped=not slot.replace)  # all frames: none may be lost
        progress.arrived = item.index + 1
        _show(printer, progress, slot)
    if slot.error:
        return EXIT_FAILED, f"the source stopped: {slot.error}"
    if progress.acked == 0:
        return EXIT_FAILED, "no frame was accepted by the server"
    return EXIT_OK, None


# --------------------------------------------------------------------------------------------
# Command line


def add_stream_arguments(parser) -> None:
    """The options of ``voxfusion stream`` on an argparse parser."""
    parser.add_argument("source", metavar="SOURCE",
                        help="a dataset folder (TUM, Replica, ScanNet, 7-Scenes) or synthetic:SPEC, replayed in "
                             "time; 'realsense' (a live camera); a RealSense .bag recording; 'record3d' (an "
                             "iPhone/iPad streaming from the Record3D app over USB); a Record3D .r3d export")
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="the server (default http://127.0.0.1:8000)")
    parser.add_argument("--token", default=None, help="the server's token (default VOXFUSION_TOKEN)")
    parser.add_argument("--preset", choices=("test", "cpu", "paper", "gpu"), default=None,
                        help="the session's config preset (default: the server's)")
    parser.add_argument("--max-frames", type=int, default=None, help="stop after this many frames of the source")
    parser.add_argument("--fps", type=float, default=None,
                        help="folder replay rate (default: recorded timestamps for TUM, else 30)")
    pace = parser.add_mutually_exclusive_group()
    pace.add_argument("--all-frames", action="store_true",
                      help="send every frame, waiting for the server (the default for recordings: folders, "
                           "files, .bag, .r3d)")
    pace.add_argument("--live", action="store_true",
                      help="keep the newest frame and drop older unsent ones when the server is slower than the "
                           "source (the default for live cameras; for a recording, a replay as a camera would send it)")
    parser.add_argument("--width", type=int, default=None,
                        help="folder, record3d, .r3d: resize frames to this width first")
    parser.add_argument("--serial", default=None,
                        help="realsense: the serial number of the camera to use; record3d: the device's UDID")
    parser.add_argument("--min-confidence", type=int, choices=(0, 1, 2), default=1,
                        help="record3d, .r3d: the lowest ARKit depth confidence kept (0 low, 1 medium, 2 high; "
                             "default 1)")
    parser.add_argument("--wait", type=float, default=None, metavar="SECONDS",
                        help="after finishing, wait up to this long for the session's result")
    parser.add_argument("--quiet", action="store_true", help="no progress line")
    from slam.cli import add_color_camera_arguments

    add_color_camera_arguments(parser)  # a folder's colour camera: its colour is registered before it is sent


def stream_command(args) -> int:
    """``voxfusion stream``: the exit code (0 ok, 1 stream failed, 2 bad source, 3 server, 130 Ctrl-C)."""
    if args.fps is not None and args.fps <= 0:
        print("voxfusion stream: --fps must be positive", file=sys.stderr)
        return EXIT_SOURCE
    if args.max_frames is not None and args.max_frames < 1:
        print("voxfusion stream: --max-frames must be at least 1", file=sys.stderr)
        return EXIT_SOURCE
    from client.open import open_source
    from slam.cli import color_camera_of
    from slam.data.frame import DataError

    try:
        color_camera = color_camera_of(args)
    except DataError as error:
        print(f"voxfusion stream: {error}", file=sys.stderr)
        return EXIT_SOURCE
    try:
        # A recording is not a camera: it waits for the server unless --live asks for a camera's pace.
        source = open_source(args.source, fps=args.fps, max_frames=args.max_frames, width=args.width,
                             serial=args.serial, all_frames=not args.live,
                             min_confidence=args.min_confidence, color_camera=color_camera)
    except SourceError as error:
        print(f"voxfusion stream: {error}", file=sys.stderr)
        return EXIT_SOURCE
    if args.all_frames and source.info.live:
        print("voxfusion stream: --all-frames with a live camera: frames the server cannot take in time are "
              "lost in the camera's own queue instead of being counted here", file=sys.stderr)
    server = Server(args.url, args.token if args.token is not None else os.environ.get("VOXFUSION_TOKEN"))
    all_frames = args.all_frames or not (args.live or source.info.live)
    options = StreamOptions(preset=args.preset, all_frames=all_frames, wait_s=args.wait, quiet=args.quiet)
    try:
        return stream(source, server, options).code
    except KeyboardInterrupt:  # during --wait, or a second Ctrl-C while finishing
        print("\nvoxfusion stream: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        source.close()
