"""Sessions under abuse: slots held until a worker's process is gone, zips the disk cannot
unpack, a full disk, and SIGTERM in a session's first frames."""

from __future__ import annotations

import errno
import io
import json
import multiprocessing as mp
import queue
import signal
import time
import zipfile
from dataclasses import replace
from pathlib import Path

import httpx
import pytest

from server.execution import WorkerInfo
from server.sessions import SessionManager
from server.settings import Settings
from server.upload import (MAX_ENTRY_DEPTH, UploadError, ZipLimits, check_zip, extract_zip,
                           save_upload)
from server.worker import DISK_FULL, SourceSpec, WorkerDone, WorkerJob, disk_full_error
from tests.live_server import free_port
from tests.test_server_api import needs_runtime, running_app
from tests.test_server_lifecycle import serve, start_stream, wait_until_up
from tests.test_server_stream import encoded_frames

SYNTHETIC = SourceSpec(kind="synthetic", path="orbit?frames=4&width=32&height=24", format="synthetic")
LIMITS = ZipLimits(max_entries=1000, max_unzipped_bytes=1 << 20)


def disk_full() -> OSError:
    return OSError(errno.ENOSPC, "No space left on device")


# -- slots: a worker counts until its process has exited ----------------------------------------


class FakeExecution:
    """An execution whose 'process' lives until the test ends it (``exit``)."""

    frame_queue = None
    pid = None

    def __init__(self, log: list) -> None:
        self.alive = False
        self.stop_requested = False
        self.log = log

    def start(self) -> WorkerInfo:
        self.alive = True
        self.log.append(self)
        return WorkerInfo(executor="local", node="test")

    def exit(self) -> None:
        self.alive = False

    def poll(self, limit: int) -> list:
        return []

    def is_alive(self) -> bool:
        return self.alive

    def request_stop(self) -> None:
        self.stop_requested = True

    def kill(self) -> None:
        self.alive = False

    def exit_error(self) -> str:
        return "the worker process exited with code 120 without a result; see worker.log"

    def finish(self, worker_pid) -> None:
        pass

    def release(self) -> None:
        pass


class FakeExecutor:
    name = "local"

    def __init__(self) -> None:
        self.started: list[FakeExecution] = []

    def prepare(self, job, directory, stream):
        return FakeExecution(self.started)

    def close(self) -> None:
        pass


def fake_manager(tmp_path: Path, **settings) -> tuple[SessionManager, FakeExecutor]:
    manager = SessionManager(Settings(data_dir=tmp_path, viewer_port=-1, **settings))
    executor = manager._executor = FakeExecutor()
    manager.settings.sessions_dir.mkdir(parents=True)
    return manager, executor


def alive_count(executor: FakeExecutor) -> int:
    return sum(e.alive for e in executor.started)


def test_a_stopping_worker_holds_its_slot_until_its_process_has_exited(tmp_path):
    """MAX_SESSIONS=1: a deleted or cancelled session's worker keeps the slot through its grace
    period; the next session starts only once that process is gone."""
    manager, executor = fake_manager(tmp_path, max_sessions=1, cancel_grace_s=60.0)
    ids = ["a00000000000", "b00000000000", "c00000000000"]
    for session_id in ids:
        manager.create(session_id, SYNTHETIC, "test")
    manager._tick()
    assert alive_count(executor) == 1
    manager.delete(ids[0])  # deleted while running: no longer listed, still stopping
    for _ in range(3):
        manager._tick()
    assert executor.started[0].stop_requested
    assert len(executor.started) == 1, "the next session started while the deleted one's worker ran"
    executor.started[0].exit()
    manager._tick()
    assert len(executor.started) == 2 and manager.get(ids[1]).status == "running"
    manager.cancel(ids[1])
    manager._tick()
    assert len(executor.started) == 2, "the next session started while the cancelled one's worker ran"
    assert manager.running_count() == 1
    executor.started[1].exit()
    manager._tick()
    assert manager.get(ids[1]).status == "cancelled" and manager.get(ids[2]).status == "running"
    assert alive_count(executor) == 1


def test_a_worker_that_ended_on_a_full_disk_says_so(tmp_path, monkeypatch):
    manager, executor = fake_manager(tmp_path)
    manager.create("d00000000000", SYNTHETIC, "test")
    manager._tick()
    monkeypatch.setattr("server.sessions.disk_is_full", lambda directory: True)
    executor.started[0].exit()  # gone without a WorkerDone, as a worker whose log could not be written
    manager._tick()
    state = manager.get("d00000000000")
    assert state.status == "failed" and state.error.startswith("the disk is full"), state.error


# -- zips the disk cannot unpack ----------------------------------------------------------------


def zip_of(names: list[str]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name in names:
            archive.writestr(name, b"x")
    return buffer.getvalue()


LONG_NAME = "n" * 300
DEEP = "/".join(["d"] * 2000) + "/x.png"
BAD_ZIPS = {
    "file, then a file inside it": (["d/x", "d/x/y"], "d/x' is a file in the zip"),
    "a file inside, then the file": (["d/x/y", "d/x"], "d/x' is a file in the zip"),
    "a 300-character name": ([f"rgb/{LONG_NAME}.png", "rgb.txt"], "304 bytes long; at most 255"),
    "2000 folders deep": ([DEEP, "rgb.txt"], f"at most {MAX_ENTRY_DEPTH} are allowed"),
}


@pytest.mark.parametrize("case", list(BAD_ZIPS))
@pytest.mark.parametrize("layout", ["root", "folder", "a part of several"])
def test_zips_the_disk_cannot_unpack_get_422_naming_the_entry_and_leave_nothing(tmp_path, case, layout):
    names, expected = BAD_ZIPS[case]
    if layout != "root":
        names = [f"rgbd_dataset_freiburg1_x/{name}" for name in names]
    files = [("file", ("a.zip", zip_of(names), "application/zip"))]
    if layout == "a part of several":  # unpacked into input/0/
        files.append(("file", ("b.zip", zip_of(["rgb.txt"]), "application/zip")))
    with running_app(tmp_path) as client:
        response = client.post("/api/sessions", files=files, data={"preset": "test"})
    detail = response.json()["detail"]
    assert response.status_code == 422, (response.status_code, detail[:300])
    assert expected in detail and "zip entry " in detail and len(detail) < 400, detail
    assert list((tmp_path / "sessions").iterdir()) == [], "nothing of the upload is left"
    assert not any((tmp_path / "uploads").iterdir())


def test_an_entry_the_disk_refuses_while_unpacking_is_422_naming_it(tmp_path, monkeypatch):
    """What the checks before extraction cannot foresee is caught during it."""
    zip_path = tmp_path / "a.zip"
    zip_path.write_bytes(zip_of(["rgb.txt", "rgb/1.png"]))
    real_open = open

    def refusing_open(path, mode="r", *args, **kwargs):
        if str(path).endswith("1.png"):
            raise OSError(errno.ENAMETOOLONG, "File name too long", str(path))
        return real_open(path, mode, *args, **kwargs)

    monkeypatch.setattr("server.upload.open", refusing_open, raising=False)
    with pytest.raises(UploadError) as refused:
        extract_zip(zip_path, tmp_path / "out", LIMITS)
    assert refused.value.status == 422 and "'rgb/1.png'" in str(refused.value)
    assert "File name too long" in str(refused.value) and str(tmp_path) not in str(refused.value)


def test_entry_checks_pass_a_dataset_with_plain_names(tmp_path):
    names = [f"rgbd_dataset_freiburg1_desk/rgb/{k:06d}.png" for k in range(3)] + ["rgbd_dataset_freiburg1_desk/rgb.txt"]
    zip_path = tmp_path / "a.zip"
    zip_path.write_bytes(zip_of(names + ["rgbd_dataset_freiburg1_desk/rgb/"]))
    assert len(check_zip(zip_path, LIMITS)) == 4


# -- a full disk --------------------------------------------------------------------------------


def test_a_full_disk_while_saving_or_unpacking_an_upload_is_507_and_leaves_nothing(tmp_path, monkeypatch):
    import server.upload as upload

    real_copy = upload._copy_limited
    for failing_call in (1, 2):  # 1: saving the upload, 2: unpacking its first entry
        calls = []

        def copy(source, sink, budget, name, *args, failing_call=failing_call, calls=calls):
            calls.append(name)
            if len(calls) == failing_call:
                sink.write(b"partial")
                raise disk_full()
            return real_copy(source, sink, budget, name, *args)

        monkeypatch.setattr(upload, "_copy_limited", copy)
        with running_app(tmp_path) as client:
            response = client.post("/api/sessions", data={"preset": "test"},
                                   files={"file": ("a.zip", zip_of(["rgb.txt", "rgb/1.png"]), "application/zip")})
        assert response.status_code == 507, (failing_call, response.text)
        assert "disk is full" in response.json()["detail"]
        assert list((tmp_path / "sessions").iterdir()) == [] and not any((tmp_path / "uploads").iterdir())


def test_a_full_disk_while_receiving_the_body_is_507(tmp_path, monkeypatch):
    from tempfile import SpooledTemporaryFile

    class FullDisk(SpooledTemporaryFile):
        def write(self, data):
            raise disk_full()

    monkeypatch.setattr("starlette.formparsers.SpooledTemporaryFile", FullDisk)
    with running_app(tmp_path) as client:
        response = client.post("/api/sessions", data={"preset": "test"},
                               files={"file": ("a.zip", zip_of(["rgb.txt"]), "application/zip")})
    assert response.status_code == 507 and "disk is full" in response.json()["detail"], response.text


def test_save_upload_removes_what_it_wrote_on_a_full_disk(tmp_path, monkeypatch):
    import server.upload as upload

    def copy(source, sink, budget, name, *args):
        sink.write(b"partial")
        raise disk_full()

    monkeypatch.setattr(upload, "_copy_limited", copy)
    with pytest.raises(UploadError) as refused:
        save_upload(io.BytesIO(b"zip"), tmp_path / "up" / "a.zip", 1 << 20)
    assert refused.value.status == 507 and list((tmp_path / "up").iterdir()) == []


def test_an_atomic_status_write_that_fails_leaves_no_temporary_file(tmp_path, monkeypatch):
    from server.session_status import SessionStatus
    from server.session_store import write_status

    state = SessionStatus(id="e00000000000", status="running", created="2025-01-01T00:00:00+00:00",
                          source="stream", preset="test")
    write_status(tmp_path, state)
    before = (tmp_path / "session.json").read_text()
    real_write_text = Path.write_text

    def half_then_full(self, text, *args, **kwargs):
        real_write_text(self, text[: len(text) // 2], *args, **kwargs)
        raise disk_full()

    monkeypatch.setattr(Path, "write_text", half_then_full)
    write_status(tmp_path, replace(state, status="failed"))  # logged, not raised
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["session.json"], "no temporary file is left"
    assert (tmp_path / "session.json").read_text() == before


def _worker_on_a_full_disk(job, stop_event, event_queue, frame_queue) -> None:
    """``run_worker`` in a process whose file writes all meet a full disk (the mapping side
    inline, so that it meets it too)."""
    import slam
    from server.worker import run_worker

    def write_text(self, text, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(self))

    real_load = slam.load_config
    slam.load_config = lambda name: (lambda c: replace(c, runtime=replace(c.runtime, processes=False)))(real_load(name))
    Path.write_text = write_text
    run_worker(job, stop_event, event_queue, frame_queue)


@needs_runtime
def test_a_worker_that_cannot_write_fails_at_once_saying_the_disk_is_full(tmp_path):
    """Not 'exited with code 120', not running on without its outputs: the run ends at its first
    keyframe's write, as failed because the disk is full."""
    ctx = mp.get_context("spawn")
    events, stop = ctx.Queue(), ctx.Event()
    job = WorkerJob(session_id="f00000000000", preset="test", out_dir=str(tmp_path),
                    sources=(SourceSpec(kind="synthetic", path="orbit?frames=40&width=32&height=24",
                                        format="synthetic"),))
    process = ctx.Process(target=_worker_on_a_full_disk, args=(job, stop, events, None))
    process.start()
    received, deadline = [], time.monotonic() + 120
    try:
        while not received or not isinstance(received[-1], WorkerDone):
            assert time.monotonic() < deadline, received[-3:]
            try:
                received.append(events.get(timeout=1.0))
            except queue.Empty:
                assert process.is_alive() or not events.empty(), f"the worker died: {process.exitcode}"
        process.join(timeout=30)
    finally:
        if process.is_alive():
            process.kill()
    done = received[-1]
    assert (done.status, done.error) == ("failed", DISK_FULL), done
    assert process.exitcode == 0
    poses = sum(type(e).__name__ == "PoseEvent" for e in received)
    assert poses < 40, "the run went on without being able to write"
    assert not list(tmp_path.glob("*.tmp")) and not list(tmp_path.glob(".*.tmp"))


def test_disk_full_errors_are_told_apart():
    assert disk_full_error(OSError(errno.ENOSPC, "No space left on device")) == DISK_FULL
    assert disk_full_error(OSError(errno.EACCES, "Permission denied")) is None
    assert disk_full_error("Traceback ...\nOSError: [Errno 28] No space left on device: 'x'") == DISK_FULL
    assert disk_full_error("Traceback ...\nValueError: bad") is None


def test_progress_writes_on_a_full_disk_end_the_run(tmp_path, monkeypatch):
    """Other write errors are logged and the run goes on; a full disk fails it."""
    import slam.runtime as runtime

    side = runtime._TrackingSide(config=None, device=None, tracker=None)
    for code, raises in ((errno.EACCES, False), (errno.ENOSPC, True)):
        def refuse(*args, code=code, **kwargs):
            raise OSError(code, "refused")

        monkeypatch.setattr(runtime, "write_progress", refuse)
        if raises:
            with pytest.raises(OSError):
                runtime._write_progress(tmp_path, side, None, time.perf_counter())
        else:
            runtime._write_progress(tmp_path, side, None, time.perf_counter())


# -- SIGTERM in a session's first frames --------------------------------------------------------


class SilentMapper:
    """A mapping side that never answers (busy with a first frame's mapping)."""

    def __init__(self) -> None:
        self.polls = 0

    def poll(self, block: bool = False) -> list:
        self.polls += 1
        if self.polls > 50:
            raise AssertionError("the tracker went on waiting for the mapper after the stop")
        return []


def test_a_stop_ends_the_trackers_wait_for_the_first_map(tmp_path):
    import slam.runtime as runtime
    from slam import load_config

    side = runtime._TrackingSide(config=load_config("test"), device=None, tracker=None)
    track = runtime.AgentTrack(0)
    track.active_map = 0  # started by the first frame, not yet mapped
    side.stopped = lambda: True
    with pytest.raises(runtime.RunStopped):
        runtime._track_map(side, track, SilentMapper(), lambda event: None)


def tum_rows(path: Path) -> int:
    return sum(1 for line in path.read_text().splitlines() if line.strip() and not line.startswith("#"))


@needs_runtime
@pytest.mark.slow
def test_sigterm_in_the_first_frames_writes_the_trajectory_of_a_run_and_a_stream(tmp_path, monkeypatch):
    """SIGTERM as soon as a synthetic run and a stream have each reported their first frame
    (the mapper still on its first frame): both write their trajectory and a run.json with
    those frames before the server is gone, well within docker's 10 s."""
    monkeypatch.setenv("VOXFUSION_MAX_SESSIONS", "2")
    frames = encoded_frames(4)
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    server = serve(tmp_path, port, tmp_path / "server.log")
    try:
        wait_until_up(server, url)
        with httpx.Client(base_url=url, timeout=30) as client:
            run = client.post("/api/sessions", json={"source": "synthetic", "preset": "test",
                                                     "spec": "orbit?frames=60&width=64&height=48"}).json()["id"]
            stream = start_stream(client, frames, 4)
            deadline = time.monotonic() + 90
            while min(client.get(f"/api/sessions/{s}").json()["frames_done"] for s in (run, stream)) < 1:
                assert time.monotonic() < deadline, "the sessions did not start"
                time.sleep(0.05)
        sent = time.monotonic()
        server.send_signal(signal.SIGTERM)
        server.wait(timeout=20)
        took = time.monotonic() - sent
    finally:
        if server.poll() is None:
            server.kill()
            server.wait(timeout=10)
    assert took < 10, f"the server took {took:.1f} s to go"
    for session_id in (run, stream):
        folder = tmp_path / "sessions" / session_id
        assert (folder / "trajectory.txt").is_file(), f"{session_id}: no trajectory after SIGTERM"
        written = json.loads((folder / "run.json").read_text())
        assert written["frames"] == tum_rows(folder / "trajectory.txt") >= 1, written
