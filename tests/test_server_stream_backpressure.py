"""A stream that outruns its session: every frame's fate is told (ack or dropped, with the count),
the socket stays open through the keepalive, HTTP frames get 503 with ``Retry-After``, the
client resends in all-frames mode and counts in live mode, and a socket on a session that is
not a stream closes with 4409.

The session here is deliberately slow: no session ever starts (``_start_queued`` does nothing),
so a stream's frames wait in its buffer of ``stream_queue_frames`` (2); a test that needs a
worker takes frames from that buffer itself, at its own pace.
"""

from __future__ import annotations

import json
import struct
import threading
import time
from typing import Iterator

import cv2
import httpx
import numpy as np
import pytest

from client.camera_sources import FolderSource
from client.stream import FrameSlot, Progress, Server, _Printer, _send_all, create_session, open_socket, read_source
from tests.live_server import LiveServer, start_uvicorn

QUEUE_FRAMES = 2
PUT_TIMEOUT_S = 0.5
PING_INTERVAL_S, PING_TIMEOUT_S = 0.5, 1.0
"""uvicorn's keepalive, short: a socket whose pongs go unread closes within 1.5 s."""
INTRINSICS = "50,50,31.5,23.5"
COLOR = cv2.imencode(".png", np.full((48, 64, 3), 120, np.uint8))[1].tobytes()
DEPTH = cv2.imencode(".png", np.full((48, 64), 1000, np.uint16))[1].tobytes()


@pytest.fixture(scope="module")
def live(tmp_path_factory) -> Iterator[LiveServer]:
    from server.main import create_app
    from server.sessions import SessionManager
    from server.settings import Settings

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(SessionManager, "_start_queued", lambda self: None)  # every session stays queued
        settings = Settings(data_dir=tmp_path_factory.mktemp("backpressure"), viewer_port=-1,
                            stream_queue_frames=QUEUE_FRAMES, stream_put_timeout_s=PUT_TIMEOUT_S)
        server = start_uvicorn(create_app(settings), ws_ping_interval=PING_INTERVAL_S,
                               ws_ping_timeout=PING_TIMEOUT_S)
        yield server
        server.stop()


def new_stream(live: LiveServer) -> str:
    body = {"source": "stream", "preset": "test", "intrinsics": INTRINSICS, "depth_scale": 1000}
    response = httpx.post(f"{live.url}/api/sessions", json=body, timeout=10)
    assert response.status_code == 201, response.text
    return response.json()["id"]


def socket_url(live: LiveServer, session_id: str) -> str:
    return live.url.replace("http://", "ws://") + f"/api/sessions/{session_id}/stream"


def frame_message(i: int) -> bytes:
    return struct.pack("<dI", i / 30, len(COLOR)) + COLOR + DEPTH


def buffer_of(live: LiveServer, session_id: str):
    """The queued session's frame buffer (what its worker would read)."""
    return live.server.config.app.state.manager.stream(session_id).frame_queue


def take_frames(live: LiveServer, session_id: str, every_s: float, stop: threading.Event) -> list[float]:
    """A slow worker: takes one frame from the buffer every ``every_s`` until ``stop``; their timestamps."""
    taken: list[float] = []

    def run() -> None:
        buffer = buffer_of(live, session_id)
        while not stop.wait(every_s):
            if not buffer.empty():
                taken.append(buffer.get_nowait().timestamp)

    threading.Thread(target=run, daemon=True, name="slow-worker").start()
    return taken


def test_a_socket_that_outruns_its_session_hears_every_frames_fate_and_stays_open(live):
    """Frames sent faster than the session takes them used to wait for room with the socket's
    reader stalled: the client's pongs went unread and the keepalive closed the socket (1011)
    with frames unanswered. Now each gets an ack or a drop with the count, at once."""
    import websockets.sync.client as ws_client

    session_id = new_stream(live)
    sent = 12
    with ws_client.connect(socket_url(live, session_id), open_timeout=10, close_timeout=2) as socket:
        socket.send(json.dumps({}))
        assert json.loads(socket.recv(timeout=10))["type"] == "ready"
        for i in range(sent):
            socket.send(frame_message(i))
        answers = [json.loads(socket.recv(timeout=10)) for _ in range(sent)]
        acks = [a for a in answers if a["type"] == "ack"]
        drops = [a for a in answers if a["type"] == "dropped"]
        assert len(acks) + len(drops) == sent, answers
        assert [a["index"] for a in acks] == list(range(QUEUE_FRAMES))
        assert [d["dropped"] for d in drops] == list(range(1, sent - QUEUE_FRAMES + 1))
        assert all(d["status"] == 503 and d["retry_after_s"] > 0 and "buffer" in d["detail"] for d in drops)

        time.sleep(PING_INTERVAL_S + PING_TIMEOUT_S + 0.5)  # a keepalive round with the session still full
        socket.send(frame_message(sent))
        assert json.loads(socket.recv(timeout=10))["dropped"] == sent - QUEUE_FRAMES + 1, "the socket is open"
        buffer_of(live, session_id).get_nowait()  # the worker takes one: room for one
        socket.send(frame_message(sent + 1))
        assert json.loads(socket.recv(timeout=10)) == {"type": "ack", "index": QUEUE_FRAMES,
                                                       "dropped": sent - QUEUE_FRAMES + 1}
    httpx.delete(f"{live.url}/api/sessions/{session_id}", timeout=10)


def test_an_http_frame_that_finds_no_room_gets_503_with_retry_after(live):
    session_id = new_stream(live)
    files = {"color": ("c.png", COLOR, "image/png"), "depth": ("d.png", DEPTH, "image/png")}
    with httpx.Client(base_url=live.url, timeout=10) as client:
        for _ in range(QUEUE_FRAMES):
            assert client.post(f"/api/sessions/{session_id}/frames", files=files).status_code == 200
        started = time.monotonic()
        busy = client.post(f"/api/sessions/{session_id}/frames", files=files)
        assert busy.status_code == 503, busy.text
        assert busy.headers.get("retry-after") == "1"
        assert "frame dropped, 1 so far" in busy.json()["detail"]
        assert time.monotonic() - started >= PUT_TIMEOUT_S * 0.9, "an HTTP frame waits for room first"
        client.delete(f"/api/sessions/{session_id}")


def test_a_stream_socket_on_a_session_that_is_not_a_stream_closes_with_4409(live):
    """It used to be refused before the handshake (HTTP 403), not with the documented 4409."""
    import websockets.sync.client as ws_client
    from websockets.exceptions import ConnectionClosed

    created = httpx.post(f"{live.url}/api/sessions", timeout=10,
                         json={"source": "synthetic", "spec": "orbit?frames=3&width=32&height=24", "preset": "test"})
    assert created.status_code == 201, created.text
    session_id = created.json()["id"]
    with ws_client.connect(socket_url(live, session_id), open_timeout=10, close_timeout=2) as socket:
        socket.send(json.dumps({}))
        error = json.loads(socket.recv(timeout=10))
        assert error["type"] == "error" and error["status"] == 409 and "not a stream" in error["detail"], error
        with pytest.raises(ConnectionClosed) as closed:
            socket.recv(timeout=10)
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 4409
    assert "not a stream" in closed.value.rcvd.reason
    httpx.delete(f"{live.url}/api/sessions/{session_id}", timeout=10)


def stream_source(live: LiveServer, frames: int, all_frames: bool, every_s: float | None
                  ) -> tuple[Progress, int, list[float], list[float]]:
    """``frames`` of a synthetic scene through the client's sender into a new session whose
    worker takes a frame every ``every_s`` (None: never); (progress, exit code, frames the
    worker took, the source's timestamps)."""
    source = FolderSource(f"synthetic:orbit?frames={frames}&width=40&height=30", fps=1000)
    server = Server(live.url)
    session_id = create_session(server, source.info, "test")
    stop = threading.Event()
    taken = take_frames(live, session_id, every_s, stop) if every_s is not None else []
    slot, progress = FrameSlot(replace=not all_frames), Progress()
    reader = threading.Thread(target=read_source, args=(source, slot, threading.Event()), daemon=True)
    socket = open_socket(server, session_id)
    try:
        reader.start()
        code, _ = _send_all(socket, slot, progress, _Printer(None, quiet=True))
        progress.dropped = slot.dropped
        deadline = time.monotonic() + 5
        while every_s is not None and len(taken) < progress.acked and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        stop.set()
        socket.close()
        reader.join(timeout=5)
        httpx.delete(f"{live.url}/api/sessions/{session_id}", timeout=10)
    return progress, code, taken, [source.sequence[i].timestamp for i in range(frames)]


def test_the_client_in_all_frames_mode_resends_dropped_frames_and_delivers_every_one(live):
    frames = 8
    progress, code, taken, stamps = stream_source(live, frames, all_frames=True, every_s=0.1)
    assert code == 0
    assert progress.acked == frames and progress.resent > 0, "the session was full: frames were resent"
    assert np.allclose(taken, stamps), "every frame reached the worker, in order"
    assert progress.summary().startswith(f"frames sent {frames}, accepted {frames}, dropped 0 ")


def test_the_client_in_live_mode_drops_and_counts(live):
    frames = 6
    progress, code, _, _ = stream_source(live, frames, all_frames=False, every_s=None)
    assert code == 0
    assert progress.acked == QUEUE_FRAMES and progress.resent == 0
    assert progress.frames_sent == progress.acked + progress.server_dropped, "every frame sent has its fate"
    assert progress.frames_sent + progress.dropped == frames
    assert f"accepted {QUEUE_FRAMES}, dropped {frames - QUEUE_FRAMES} " in progress.summary()
