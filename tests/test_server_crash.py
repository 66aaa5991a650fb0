"""Hardening (issue 39): a capped queue that holds no descriptors, a bounded SIGTERM that keeps
the sessions' outputs, and what a running session has written surviving a SIGKILL."""

from __future__ import annotations

import json
import os
import queue
import signal
import socket
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from server.sessions import INTERRUPTED_RUNNING, QueueFull, SessionManager
from server.settings import Settings
from server.stream import StreamInput
from server.upload import UploadError
from server.worker import SourceSpec
from tests.live_server import free_port
from tests.test_server_api import needs_runtime, running_app
from tests.test_server_lifecycle import serve, start_stream, wait_until_up
from tests.test_server_stream import DEPTH_SCALE, encoded_frames

needs_proc = pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs Linux /proc")


def open_descriptors() -> int:
    return len(os.listdir("/proc/self/fd"))


def tum_rows(path: Path) -> int:
    return sum(1 for line in path.read_text().splitlines() if line.strip() and not line.startswith("#"))


# -- the queue ---------------------------------------------------------------------------------


@needs_proc
def test_queued_sessions_hold_no_descriptors_and_the_queue_has_a_cap(tmp_path):
    """150 queued sessions used to hold 2-4 descriptors each (their worker's queues, made at
    creation) until the server ran out; now the IPC is made when a session starts, and a
    full queue refuses the next one (and removes the folder made for it)."""
    manager = SessionManager(Settings(data_dir=tmp_path, max_queued=6))
    manager.settings.sessions_dir.mkdir(parents=True)
    before = open_descriptors()
    for k in range(6):
        spec = (SourceSpec(kind="stream", intrinsics=(50.0, 50.0, 32.0, 24.0)) if k % 2 else
                SourceSpec(kind="synthetic", path="orbit?frames=6&width=64&height=48"))
        assert manager.create(f"{k:012x}", spec, "test").status == "queued"
    assert open_descriptors() <= before, "queued sessions hold no pipes"
    refused = manager.session_dir("00000000000f")
    (refused / "input").mkdir(parents=True)  # as an upload leaves it before create
    with pytest.raises(QueueFull) as error:
        manager.create("00000000000f", SourceSpec(kind="synthetic", path="orbit"), "test")
    assert "queue is full" in str(error.value) and "VOXFUSION_MAX_QUEUED" in str(error.value)
    assert error.value.retry_after_s > 0
    assert not refused.exists(), "the refused session's folder is removed"
    assert len(manager.list()) == 6
    manager.cancel("000000000000")
    manager.create("00000000000f", SourceSpec(kind="synthetic", path="orbit"), "test")  # room again


def test_a_full_queue_answers_429_with_retry_after(tmp_path, monkeypatch):
    monkeypatch.setattr(SessionManager, "_start_queued", lambda self: None)  # nothing starts: all queue
    with running_app(tmp_path, max_queued=2) as client:
        body = {"source": "synthetic", "spec": "orbit?frames=6&width=64&height=48", "preset": "test"}
        assert [client.post("/api/sessions", json=body).status_code for _ in range(2)] == [201, 201]
        full = client.post("/api/sessions", json=body)
        assert full.status_code == 429, full.text
        assert int(full.headers["Retry-After"]) > 0
        detail = full.json()["detail"]
        assert isinstance(detail, str) and "\n" not in detail and "queue is full" in detail
        assert len(client.get("/api/sessions").json()) == 2
        responses = client.get("/openapi.json").json()["paths"]["/api/sessions"]["post"]["responses"]
        assert "429" in responses, "the 429 is documented"


def test_a_queued_stream_buffers_its_frames_until_it_starts(tmp_path):
    """While queued a stream session has no worker queue: its frames wait in a buffer of the
    same size (the 503 back-pressure as documented), moved to the worker's queue at start."""
    import multiprocessing as mp

    from tests.test_server_stream import encoded_frames as frames_of

    frames = frames_of(5)
    K = frames[0][3]
    stream = StreamInput(None, tmp_path / "input", intrinsics=(K[0, 0], K[1, 1], K[0, 2], K[1, 2]),
                         depth_scale=DEPTH_SCALE, put_timeout_s=0.3, buffer_frames=3)
    for stamp, color, depth, _ in frames[:3]:
        stream.add_frame(color, depth, timestamp=stamp)
    with pytest.raises(UploadError) as behind:
        stream.add_frame(frames[3][1], frames[3][2], timestamp=frames[3][0])
    assert behind.value.status == 503
    worker_queue = mp.get_context("spawn").Queue(maxsize=3)
    try:
        stream.attach(worker_queue)
        got = [worker_queue.get(timeout=5) for _ in range(3)]
        assert [round(item.timestamp, 6) for item in got] == [round(f[0], 6) for f in frames[:3]]
        stream.add_frame(frames[3][1], frames[3][2], timestamp=frames[3][0])
        assert round(worker_queue.get(timeout=5).timestamp, 6) == round(frames[3][0], 6)
        stream.finish()
        assert worker_queue.get(timeout=5) is None, "END_OF_STREAM follows"
    finally:
        worker_queue.cancel_join_thread()
        worker_queue.close()


# -- SIGTERM -----------------------------------------------------------------------------------


def hold_slow_request(port: int, seconds: float) -> threading.Thread:
    """A client that sends a request body at 2 bytes a second for ``seconds`` (bounded)."""

    def trickle() -> None:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=5) as conn:
                conn.sendall(b"POST /api/sessions HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                             b"Content-Type: application/json\r\nContent-Length: 4096\r\n\r\n{")
                deadline = time.monotonic() + seconds
                while time.monotonic() < deadline:
                    conn.sendall(b" ")
                    time.sleep(0.5)
        except OSError:
            pass  # the server went away: what the test wants

    thread = threading.Thread(target=trickle, name="slow-client", daemon=True)
    thread.start()
    return thread


def read_run(folder: Path) -> dict:
    return json.loads((folder / "run.json").read_text())


@needs_runtime
@needs_proc
@pytest.mark.slow
def test_sigterm_with_a_slow_request_writes_the_outputs_and_exits_in_time(tmp_path):
    """``docker stop`` gives 10 s between SIGTERM and SIGKILL: a client trickling a body must
    not hold the server past it, and running sessions write their trajectory and run.json at
    once; after a restart the status agrees with them."""
    frames = encoded_frames(3)
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    server = serve(tmp_path, port, tmp_path / "server.log")
    try:
        wait_until_up(server, url)
        with httpx.Client(base_url=url, timeout=30) as client:
            session_id = start_stream(client, frames, 3)
            deadline = time.monotonic() + 120
            while client.get(f"/api/sessions/{session_id}").json()["frames_done"] < 3:
                assert time.monotonic() < deadline, "the session did not track its frames"
                time.sleep(0.3)
        hold_slow_request(port, seconds=40)
        time.sleep(1.0)
        sent = time.monotonic()
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(timeout=20)
        except Exception:
            pass
        took = time.monotonic() - sent
        assert server.poll() is not None and took < 10, f"still running {took:.1f} s after SIGTERM"
    finally:
        if server.poll() is None:
            server.kill()
            server.wait(timeout=10)
    folder = tmp_path / "sessions" / session_id
    assert tum_rows(folder / "trajectory.txt") == 3
    run = read_run(folder)
    assert (run["status"], run["error"], run["frames"]) == ("failed", INTERRUPTED_RUNNING, 3), run
    port = free_port()
    again = serve(tmp_path, port, tmp_path / "server.log")
    try:
        wait_until_up(again, f"http://127.0.0.1:{port}")
        state = httpx.get(f"http://127.0.0.1:{port}/api/sessions/{session_id}", timeout=10).json()
    finally:
        again.terminate()
        again.wait(timeout=60)
    assert (state["status"], state["error"], state["frames_done"]) == ("failed", INTERRUPTED_RUNNING, 3), state
    assert state["outputs"]["trajectory"] and state["outputs"]["map"] == (folder / "map.pt").is_file()


# -- what a session has written ----------------------------------------------------------------


@needs_runtime
def test_the_trajectory_is_written_at_every_keyframe(tmp_path):
    """The runtime rewrites trajectory.txt and a run.json that says ``running`` atomically at
    each keyframe (a kill loses at most the frames after the last one)."""
    from slam.config import load_config
    from slam.data import open_sequence
    from slam.events import KeyframeEvent
    from slam.runtime import run_slam

    seen: list[tuple[int, int, dict]] = []

    def on_event(event) -> None:
        if isinstance(event, KeyframeEvent):
            # Written before the event goes out: what a server that counted it can find on disk.
            seen.append((event.frame_index, tum_rows(tmp_path / "trajectory.txt"), read_run(tmp_path)))

    config = load_config("test")
    run_slam([open_sequence("synthetic:orbit?frames=6&width=64&height=48")], config, tmp_path, on_event=on_event)
    assert seen, "keyframes were taken"
    for frame_index, rows, run in seen:
        assert rows >= frame_index + 1 and run["frames"] == rows, (frame_index, rows, run)
        assert run["status"] == "running"
    assert read_run(tmp_path)["status"] == "finished"
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")], "no temporary file is left"


def test_status_and_run_json_agree_after_a_kill(tmp_path):
    """A session killed with the server: the restart derives frames_done from the poses on
    disk and writes run.json's status as the API's (a run.json is written when none was)."""
    from server.sessions import SessionStatus

    for session_id, partial in (("aaaaaaaaaaaa", True), ("bbbbbbbbbbbb", False)):
        folder = tmp_path / "sessions" / session_id
        folder.mkdir(parents=True)
        state = SessionStatus(id=session_id, status="running", created="2025-01-01T00:00:00+00:00",
                              source="synthetic:orbit", preset="test", phase="tracking", frames_done=9,
                              keyframes=4)
        (folder / "session.json").write_text(json.dumps(state.to_json()))
        if partial:
            (folder / "trajectory.txt").write_text("# t tx ty tz qx qy qz qw\n" +
                                                  "".join(f"{k} 0 0 0 0 0 0 1\n" for k in range(5)))
            (folder / "run.json").write_text(json.dumps({"status": "running", "error": None, "frames": 5,
                                                         "keyframes": 2, "maps": 1, "loops": 0}))
    with running_app(tmp_path) as client:
        listed = {s["id"]: s for s in client.get("/api/sessions").json()}
    with_poses, without = listed["aaaaaaaaaaaa"], listed["bbbbbbbbbbbb"]
    assert (with_poses["frames_done"], with_poses["keyframes"], with_poses["outputs"]["trajectory"]) == (5, 2, True)
    assert (without["frames_done"], without["outputs"]["trajectory"]) == (0, False)
    for session_id, state in listed.items():
        run = read_run(tmp_path / "sessions" / session_id)
        assert (run["status"], run["error"]) == (state["status"], state["error"]) == ("failed", INTERRUPTED_RUNNING)
        assert run["frames"] == state["frames_done"]
