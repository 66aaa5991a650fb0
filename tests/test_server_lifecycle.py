"""What becomes of sessions when the server stops, is killed or restarts, and of streams that
stop sending: never "running" forever, never a worker left behind, always a message."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from server.sessions import INTERRUPTED_QUEUED, INTERRUPTED_RUNNING, SessionStatus
from tests.live_server import free_port
from tests.test_server_api import needs_runtime, running_app, wait_for
from tests.test_server_stream import DEPTH_SCALE, encoded_frames, k_text, post_frame

REPO = Path(__file__).resolve().parents[1]


def write_session(data_dir: Path, session_id: str, status: str) -> Path:
    """A session folder as a server that died mid-run leaves it."""
    folder = data_dir / "sessions" / session_id
    folder.mkdir(parents=True)
    state = SessionStatus(id=session_id, status=status, created="2025-01-01T00:00:00+00:00", source="stream",
                          preset="test", phase="tracking" if status == "running" else "queued")
    (folder / "session.json").write_text(json.dumps(state.to_json()))
    return folder


def alive(pid: int) -> bool:
    """True while ``pid`` exists and is not a zombie (a reparented child nobody reaped yet)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return False
    return fields[0] != "Z"


def wait_until_gone(pids, timeout: float) -> list[int]:
    """The pids still alive after ``timeout`` seconds (empty: all ended)."""
    deadline = time.monotonic() + timeout
    while True:
        left = [pid for pid in pids if alive(pid)]
        if not left or time.monotonic() > deadline:
            return left
        time.sleep(0.2)


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (from /proc's parent links)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs Linux /proc")
def test_interrupted_sessions_come_back_failed_and_their_leftover_worker_ends(tmp_path):
    running = write_session(tmp_path, "aaaaaaaaaaaa", "running")
    queued = write_session(tmp_path, "bbbbbbbbbbbb", "queued")
    # A worker that outlived its server: its own process group, stdout in the session's log.
    with open(running / "worker.log", "ab") as log:
        leftover = subprocess.Popen(["sleep", "60"], stdout=log, stderr=log, start_new_session=True)
    # Not ours although in a group whose number is written down: its stdout is elsewhere.
    stranger = subprocess.Popen(["sleep", "60"], stdout=subprocess.DEVNULL, start_new_session=True)
    (running / "worker.pid").write_text(f"{leftover.pid}\n")
    (queued / "worker.pid").write_text(f"{stranger.pid}\n")
    try:
        with running_app(tmp_path) as client:
            listed = {s["id"]: s for s in client.get("/api/sessions").json()}
            assert leftover.wait(timeout=10) == -signal.SIGKILL, "the leftover worker was ended"
            assert stranger.poll() is None, "a process that is not the session's worker is left alone"
        for session_id, error in (("aaaaaaaaaaaa", INTERRUPTED_RUNNING), ("bbbbbbbbbbbb", INTERRUPTED_QUEUED)):
            state = listed[session_id]
            assert (state["status"], state["phase"], state["error"]) == ("failed", "done", error), state
            assert state["error"].startswith("interrupted:")
        assert not (running / "worker.pid").exists()
    finally:
        for process in (leftover, stranger):
            process.kill()
            process.wait(timeout=10)


def test_status_follows_the_runs_phase_ate_and_keyframes(tmp_path):
    """What a worker's events do to the status (no worker here: the events are applied as
    the supervisor applies them)."""
    import numpy as np

    from server.sessions import SessionManager
    from server.settings import Settings
    from server.worker import SourceSpec
    from slam.events import KeyframeEvent, PhaseEvent, StatsEvent

    manager = SessionManager(Settings(data_dir=tmp_path))
    manager.settings.sessions_dir.mkdir(parents=True)
    state = manager.create("cccccccccccc", SourceSpec(kind="synthetic", path="orbit"), "test")
    assert (state.phase, state.ate_rmse_m) == ("queued", None)
    session = manager._get("cccccccccccc")
    manager._apply(session, KeyframeEvent(0, 0, 0, np.eye(4)))
    manager._apply(session, StatsEvent(10, 20, 2.0, keyframes=0, maps=1, loops=0, voxels=5, ate_rmse=0.0123))
    assert manager.get("cccccccccccc").keyframes == 1, "keyframes count as they are taken"
    manager._set_status(session, "running", None)
    assert manager.get("cccccccccccc").phase == "starting", "running, not yet tracking: the worker starts"
    for phase in ("tracking", "refining", "writing"):
        manager._apply(session, PhaseEvent(phase))
        assert manager.get("cccccccccccc").phase == phase
    assert manager.get("cccccccccccc").ate_rmse_m == 0.0123
    saved = json.loads((tmp_path / "sessions" / "cccccccccccc" / "session.json").read_text())
    assert saved["phase"] == "writing", "a phase change is on disk at once"
    manager._set_status(session, "finished", None)
    assert manager.get("cccccccccccc").phase == "done"
    manager._release_ipc(session)


def start_stream(client, frames: list, count: int) -> str:
    """A stream session that has been sent ``count`` frames."""
    session_id = client.post("/api/sessions", json={"source": "stream", "preset": "test", "depth_scale": DEPTH_SCALE,
                                                    "intrinsics": k_text(frames[0][3])}).json()["id"]
    for stamp, color, depth, _ in frames[:count]:
        assert post_frame(client, session_id, stamp, color, depth).status_code == 200
    return session_id


@needs_runtime
def test_a_graceful_stop_reports_sessions_as_interrupted_not_cancelled(tmp_path):
    frames = encoded_frames(2)
    with running_app(tmp_path, max_sessions=1, cancel_grace_s=5.0) as client:
        running = start_stream(client, frames, 1)
        queued = start_stream(client, frames, 0)
        state = wait_for(client, running, statuses=("running",), condition=lambda s: s["frames_done"] >= 1,
                         timeout=120)
        assert state["phase"] == "tracking" and state["ate_rmse_m"] is None, "a stream has no ground truth"
        assert client.get(f"/api/sessions/{queued}").json()["phase"] == "queued"
    with running_app(tmp_path) as client:
        listed = {s["id"]: s for s in client.get("/api/sessions").json()}
    assert (listed[running]["status"], listed[running]["error"]) == ("failed", INTERRUPTED_RUNNING)
    assert (listed[queued]["status"], listed[queued]["error"]) == ("failed", INTERRUPTED_QUEUED)
    assert listed[running]["phase"] == listed[queued]["phase"] == "done"
    assert listed[running]["outputs"]["trajectory"], "what it did before the stop is kept"


@needs_runtime
def test_an_idle_stream_finishes_with_its_frames_or_fails_without_any(tmp_path):
    frames = encoded_frames(2)
    with running_app(tmp_path, max_sessions=2, stream_idle_timeout_s=3.0) as client:
        empty = start_stream(client, frames, 0)
        fed = start_stream(client, frames, 2)
        failed = wait_for(client, empty, timeout=120)
        assert failed["status"] == "failed" and "no frame within 3 s" in failed["error"], failed
        assert "VOXFUSION_STREAM_IDLE_S" in failed["error"]
        done = wait_for(client, fed, timeout=120)
        assert done["status"] == "finished" and done["frames_done"] == 2 and done["phase"] == "done", done
        late = post_frame(client, fed, 9.0, frames[0][1], frames[0][2])
        assert late.status_code == 409 and "no frame for 3 s" in late.json()["detail"]


@needs_runtime
def test_a_stream_socket_is_closed_once_its_session_fails_on_the_idle_timeout(tmp_path):
    """The socket used to stay open and answer every frame with an error after its session had
    failed on VOXFUSION_STREAM_IDLE_S; now it gets one error that says why and is closed
    (code 4409, the reason in the close frame), and HTTP frames get 409 saying it ended."""
    import websockets.sync.client as ws_client
    from websockets.exceptions import ConnectionClosed

    from server.main import create_app
    from server.settings import Settings
    from tests.live_server import start_uvicorn

    frames = encoded_frames(1)
    live = start_uvicorn(create_app(Settings(data_dir=tmp_path, viewer_port=-1, stream_idle_timeout_s=2.0)))
    try:
        with httpx.Client(base_url=live.url, timeout=30) as client:
            session_id = start_stream(client, frames, 0)
            ws_url = live.url.replace("http://", "ws://") + f"/api/sessions/{session_id}/stream"
            with ws_client.connect(ws_url, open_timeout=10, close_timeout=5) as socket:
                socket.send(json.dumps({}))
                assert json.loads(socket.recv(timeout=10))["type"] == "ready"
                error = json.loads(socket.recv(timeout=120))  # the worker starts, then idles 2 s
                assert error["type"] == "error" and error["status"] == 409, error
                assert "no frame within 2 s" in error["detail"], error
                with pytest.raises(ConnectionClosed) as closed:
                    socket.recv(timeout=10)
                assert closed.value.rcvd is not None and closed.value.rcvd.code == 4409
                assert "no frame within 2 s" in closed.value.rcvd.reason
            deadline = time.monotonic() + 60
            while client.get(f"/api/sessions/{session_id}").json()["status"] != "failed":
                assert time.monotonic() < deadline, "the session did not end"
                time.sleep(0.2)
            late = post_frame(client, session_id, 1.0, frames[0][1], frames[0][2])
            assert late.status_code == 409 and "has ended (failed: " in late.json()["detail"], late.text
            with ws_client.connect(ws_url, open_timeout=10, close_timeout=5) as socket:
                socket.send(json.dumps({}))  # the header is read, then answered with the error
                again = json.loads(socket.recv(timeout=10))
                assert again["status"] == 409 and "has ended" in again["detail"], again
                with pytest.raises(ConnectionClosed) as closed:
                    socket.recv(timeout=10)
                assert closed.value.rcvd.code == 4409
    finally:
        live.stop()


def serve(data_dir: Path, port: int, log: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    with open(log, "ab") as out:
        return subprocess.Popen([sys.executable, "-m", "server.cli", "serve", "--host", "127.0.0.1",
                                 "--port", str(port), "--data-dir", str(data_dir), "--viewer-port", "-1"],
                                cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)


def wait_until_up(process: subprocess.Popen, url: str, timeout: float = 90.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            httpx.get(f"{url}/api/sessions", timeout=5)
            return
        except httpx.TransportError:
            assert process.poll() is None, "the server exited"
            assert time.monotonic() < deadline, "the server did not come up"
            time.sleep(0.3)


@needs_runtime
@pytest.mark.skipif(not Path("/proc/self/stat").is_file(), reason="needs Linux /proc")
def test_a_killed_server_leaves_no_worker_behind(tmp_path):
    """SIGKILL the server while a session runs: its worker and mapping process notice and end
    (their parent's pipe closes), what it had written at its last keyframe is there (the
    trajectory and a run.json), and the next start lists the session as interrupted with a
    status that agrees with those files."""
    frames = encoded_frames(3)
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    server = serve(tmp_path, port, tmp_path / "server.log")
    try:
        wait_until_up(server, url)
        with httpx.Client(base_url=url, timeout=30) as client:
            session_id = start_stream(client, frames, 3)
            deadline = time.monotonic() + 120
            while True:
                reported = client.get(f"/api/sessions/{session_id}").json()
                if reported["frames_done"] >= 3 and reported["keyframes"] >= 1:
                    break
                assert time.monotonic() < deadline, "the session did not start"
                time.sleep(0.3)
        workers = descendants(server.pid)
        assert len(workers) >= 2, "a worker and its mapping process run"
        server.kill()
        server.wait(timeout=10)
        left = wait_until_gone(workers, timeout=15)
        assert not left, f"processes outlived the killed server: {left}"
    finally:
        if server.poll() is None:
            server.kill()
    folder = tmp_path / "sessions" / session_id
    rows = [line for line in (folder / "trajectory.txt").read_text().splitlines() if line and line[0] != "#"]
    assert 1 <= len(rows) <= 3, "the poses up to the last keyframe were on disk before the kill"
    port = free_port()
    again = serve(tmp_path, port, tmp_path / "server.log")
    try:
        wait_until_up(again, f"http://127.0.0.1:{port}")
        state = httpx.get(f"http://127.0.0.1:{port}/api/sessions/{session_id}", timeout=10).json()
        assert (state["status"], state["error"], state["phase"]) == ("failed", INTERRUPTED_RUNNING, "done"), state
    finally:
        again.terminate()
        again.wait(timeout=60)
    run = json.loads((folder / "run.json").read_text())
    assert state["frames_done"] == run["frames"] == len(rows), (state, run)
    assert (run["status"], run["error"]) == (state["status"], state["error"])
    assert state["outputs"]["trajectory"] and state["outputs"]["map"] == (folder / "map.pt").is_file()
