"""What an attacker tried (issue 39): uploads that name the server's files, image bombs,
small requests that name huge sizes, bodies past their route's budget, values far out of
range, and the operator's findings (empty mesh exports, lists racing deletions, tokens in the
access log, unbounded assets). Each test failed before its fix."""

from __future__ import annotations

import io
import logging
import struct
import zipfile
import zlib
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.test_server_api import running_app

TUM_TIMES = (1.0, 1.033, 1.066)


def png(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", image)[1].tobytes()


COLOR = png(np.full((48, 64, 3), 120, np.uint8))
DEPTH = png(np.full((48, 64), 5000, np.uint16))


def png_bomb(width: int, height: int) -> bytes:
    """A valid 8-bit grey PNG of ``width`` x ``height`` zeros: tiny compressed, huge decoded."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    compressor = zlib.compressobj(9)
    row = b"\x00" * (width + 1)  # filter byte + pixels
    body = b"".join(compressor.compress(row) for _ in range(height)) + compressor.flush()
    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", body) + chunk(b"IEND", b"")


def tum_zip(rgb_names: list[str] | None = None, files: dict[str, bytes] | None = None) -> bytes:
    """A TUM folder (``freiburg1`` in its name) of three frames, with ``rgb.txt`` naming
    ``rgb_names`` instead of its own files when given."""
    top = "rgbd_dataset_freiburg1_tiny/"
    names = rgb_names or [f"rgb/{t:.6f}.png" for t in TUM_TIMES]
    entries = {
        top + "rgb.txt": "".join(f"{t:.6f} {n}\n" for t, n in zip(TUM_TIMES, names)).encode(),
        top + "depth.txt": "".join(f"{t:.6f} depth/{t:.6f}.png\n" for t in TUM_TIMES).encode(),
        top + "intrinsics.txt": b"52 52 31.5 23.5\n",
    }
    for t in TUM_TIMES:
        entries[top + f"rgb/{t:.6f}.png"] = COLOR
        entries[top + f"depth/{t:.6f}.png"] = DEPTH
    for name, data in (files or {}).items():
        entries[top + name] = data
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, data in entries.items():
            archive.writestr(name, data)
    return buffer.getvalue()


def upload(client: TestClient, data: bytes, **form) -> tuple[int, str]:
    response = client.post("/api/sessions", files={"file": ("data.zip", data, "application/zip")},
                           data={"preset": "test", **form})
    return response.status_code, response.json().get("detail", "")


def rss_mb() -> float:
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmRSS:")) / 1024


@pytest.fixture(scope="module")
def client(tmp_path_factory) -> Iterator[TestClient]:
    # No session of this app runs: every request is refused before one starts, or only queued.
    with running_app(tmp_path_factory.mktemp("abuse-data"), max_upload_mb=64) as client:
        client.app.state.manager._start_queued = lambda: None
        yield client


# --- 1. uploads that name files outside themselves ---------------------------------------------


@pytest.mark.parametrize("name", ["/etc/hostname", "/no/such/file.png", "../../../../../etc/hostname",
                                  "rgb/../../../x.png", "C:/Windows/win.ini"])
def test_a_dataset_list_cannot_name_files_outside_the_dataset(client, name):
    status, detail = upload(client, tum_zip([name] + [f"rgb/{t:.6f}.png" for t in TUM_TIMES[1:]]))
    assert status == 422, detail
    assert "rgb.txt" in detail and "not a path inside the dataset folder" in detail
    # The same answer whether the file exists or not: no oracle of the server's files.
    assert "missing" not in detail and "decode" not in detail


def test_an_upload_cannot_read_another_sessions_input(client):
    status, _ = upload(client, tum_zip())
    assert status == 201
    victim = next(s for s in client.get("/api/sessions").json() if s["source"] == "upload (tum)")["id"]
    stolen = f"../../../{victim}/input/rgbd_dataset_freiburg1_tiny/rgb/{TUM_TIMES[0]:.6f}.png"
    status, detail = upload(client, tum_zip([stolen] + [f"rgb/{t:.6f}.png" for t in TUM_TIMES[1:]]))
    assert status == 422 and "not a path inside the dataset folder" in detail


def test_links_out_of_a_local_dataset_folder_are_refused(tmp_path):
    """``voxfusion run`` on an untrusted folder: a symlink that leads out is refused too."""
    from slam.data import DataError, open_sequence

    folder = tmp_path / "rgbd_dataset_freiburg1_tiny"
    with zipfile.ZipFile(io.BytesIO(tum_zip())) as archive:
        archive.extractall(tmp_path)
    secret = tmp_path / "secret.png"
    secret.write_bytes(COLOR)
    target = folder / "rgb" / f"{TUM_TIMES[0]:.6f}.png"
    target.unlink()
    target.symlink_to(secret)
    with pytest.raises(DataError, match="leads outside the dataset folder"):
        open_sequence(folder)
    target.unlink()
    target.symlink_to(folder / "rgb" / f"{TUM_TIMES[1]:.6f}.png")  # a link that stays inside is fine
    assert len(open_sequence(folder)) == 3
    (folder / "groundtruth.txt").symlink_to(tmp_path / "elsewhere.txt")
    with pytest.raises(DataError, match="groundtruth.txt: leads outside"):
        open_sequence(folder)


# --- 2. image bombs -------------------------------------------------------------------------------


def test_an_image_bomb_in_a_zip_is_refused_from_its_header(client):
    bomb = png_bomb(10_000, 10_000)  # 100 Mpx, ~100 KB compressed
    before = rss_mb()
    status, detail = upload(client, tum_zip(files={f"rgb/{TUM_TIMES[2]:.6f}.png": bomb}))
    assert status == 413, detail
    assert "10000x10000 pixels is over the limit" in detail and f"rgb/{TUM_TIMES[2]:.6f}.png" in detail
    assert rss_mb() - before < 100, "the API process decoded the bomb"


def test_decoding_runs_in_a_helper_that_survives_a_blowup():
    from server.decoding import DecodeFailed, DecodeHelper

    helper = DecodeHelper(memory_limit_bytes=256 * 1024 * 1024, timeout_s=60)
    try:
        with pytest.raises(DecodeFailed, match="more than the 256 MiB"):
            helper.call(np.ones, (1024, 1024, 1024), np.uint8)  # 1 GiB, over the cap
        assert helper.call(np.ones, (4, 4)).sum() == 16  # a fresh or the same helper goes on
        with pytest.raises(ValueError, match="negative dimensions"):
            helper.call(np.ones, (-1,))
    finally:
        helper.close()


def test_a_corrupt_frame_in_the_middle_is_skipped_and_counted(tmp_path):
    from slam.data import open_sequence

    with zipfile.ZipFile(io.BytesIO(tum_zip())) as archive:
        archive.extractall(tmp_path)
    folder = tmp_path / "rgbd_dataset_freiburg1_tiny"
    (folder / "rgb" / f"{TUM_TIMES[1]:.6f}.png").write_bytes(COLOR[:40])
    sequence = open_sequence(folder)
    frames = list(sequence)
    assert [f.index for f in frames] == [0, 2]
    assert len(sequence.skipped) == 1 and sequence.skipped[0].index == 1


# --- 3. sizes named by small requests ------------------------------------------------------------


@pytest.mark.parametrize("spec", ["orbit?frames=100000000000", "orbit?frames=1000000", "orbit?width=5000",
                                  "orbit?width=320&height=100000"])
def test_synthetic_sizes_are_bounded_at_the_request(client, spec):
    response = client.post("/api/sessions", json={"source": "synthetic", "spec": spec, "preset": "test"})
    assert response.status_code == 422, response.text
    assert "must be in" in response.json()["detail"]


@pytest.mark.parametrize("field,value", [("stride", "100000"), ("max_frames", "10000000000"),
                                         ("stride", "9" * 5000)])
def test_upload_options_are_bounded(client, field, value):
    status, detail = upload(client, tum_zip(), **{field: value})
    assert status == 422 and field in detail


def test_trajectory_agent_is_bounded(client):
    response = client.get("/api/sessions/000000000000/trajectory", params={"agent": 10**30})
    assert response.status_code == 422


# --- 5. bodies past their route's budget -----------------------------------------------------------


def test_json_bodies_have_a_small_limit_checked_before_reading(client):
    body = b'{"source": "synthetic", "spec": "' + b"x" * (2 * 1024 * 1024) + b'"}'
    before = rss_mb()
    response = client.post("/api/sessions", content=body, headers={"content-type": "application/json"})
    assert response.status_code == 413 and "256 KiB, the limit for a JSON body" in response.json()["detail"]
    assert rss_mb() - before < 50


def test_deeply_nested_json_is_a_400_not_a_500(client):
    for route in ("/api/sessions", "/api/sessions/000000000000/render", "/api/sessions/000000000000/ar"):
        response = client.post(route, content=b"[" * 100_000 + b"]" * 100_000,
                               headers={"content-type": "application/json"})
        assert response.status_code == 400 and "nests 100000 levels deep" in response.json()["detail"]
    response = client.post("/api/sessions", content=b'{"max_frames": ' + b"9" * 10_000 + b"}",
                           headers={"content-type": "application/json"})
    assert response.status_code == 400 and "not valid JSON" in response.json()["detail"]


def test_json_depth_counts_outside_strings():
    from server.budget import json_depth

    assert json_depth(b'{"a": [1, {"b": "[[[[{"}]}') == 3
    assert json_depth(b'"\\"[[["') == 0
    assert json_depth(b"") == 0


def test_form_routes_keep_their_own_larger_limits():
    from server.budget import FRAME_BODY_BYTES, JSON_BODY_BYTES, RequestBudget

    budget = RequestBudget(app=None, max_upload_bytes=2 * 1024**3)
    assert budget.limit_for("POST", "/api/sessions", "multipart/form-data; boundary=x")[0] == 2 * 1024**3
    assert budget.limit_for("POST", "/api/sessions", "application/json")[0] == JSON_BODY_BYTES
    assert budget.limit_for("POST", "/api/sessions/0123456789ab/frames", "multipart/form-data")[0] == FRAME_BODY_BYTES
    assert budget.limit_for("POST", "/api/sessions/0123456789ab/frames/../../x", "multipart/form-data")[0] < 2**20


# --- 7. values far out of range, the same rules everywhere ------------------------------------


@pytest.mark.parametrize("value", ["1e-300", "1e300"])
def test_depth_scale_range_is_checked_for_form_json_and_stream(client, value):
    status, detail = upload(client, tum_zip(), depth_scale=value)
    assert status == 422 and "depth_scale: must lie in 0.01..1e+06" in detail
    response = client.post("/api/sessions", json={"source": "stream", "depth_scale": float(value)})
    assert response.status_code == 422 and "depth_scale" in response.json()["detail"]
    session = client.post("/api/sessions", json={"source": "stream", "preset": "test"}).json()["id"]
    response = client.post(f"/api/sessions/{session}/frames", files={"color": ("c.png", COLOR), "depth": ("d.png", DEPTH)},
                           data={"depth_scale": value, "intrinsics": "52,52,31.5,23.5"})
    assert response.status_code == 422 and "depth_scale: must lie in" in response.json()["detail"]


@pytest.mark.parametrize("text", ["1e-300,1e-300,0,0", "1e300,1e300,0,0", "500,500,1e300,0"])
def test_intrinsics_range_is_checked_for_form_json_and_stream(client, text):
    status, detail = upload(client, tum_zip(), intrinsics=text)
    assert status == 422 and "intrinsics:" in detail
    response = client.post("/api/sessions", json={"source": "stream", "intrinsics": text})
    assert response.status_code == 422 and "intrinsics:" in response.json()["detail"]
    session = client.post("/api/sessions", json={"source": "stream", "preset": "test"}).json()["id"]
    response = client.post(f"/api/sessions/{session}/frames", files={"color": ("c.png", COLOR), "depth": ("d.png", DEPTH)},
                           data={"intrinsics": text})
    assert response.status_code == 422 and "intrinsics" in response.json()["detail"]


# --- 7. the operator's findings -------------------------------------------------------------------


def test_an_empty_mesh_exports_as_409_not_500(tmp_path):
    import trimesh

    from server.rendering import MeshFiles, NoMapYet, mesh_bytes_from_arrays

    ply = tmp_path / "mesh.ply"
    trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64)).export(ply)
    for fmt in ("glb", "obj"):
        with pytest.raises(NoMapYet, match="the mesh is empty"):
            MeshFiles().convert(ply, fmt)
        with pytest.raises(NoMapYet, match="the mesh is empty"):
            mesh_bytes_from_arrays([(np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.uint8))], fmt)


def test_an_empty_mesh_of_a_finished_session_answers_409(client):
    import trimesh

    manager = client.app.state.manager
    session_id = client.post("/api/sessions", json={"source": "synthetic", "spec": "orbit?frames=2",
                                                    "preset": "test"}).json()["id"]
    trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64)).export(manager.session_dir(session_id) / "mesh.ply")
    with manager._lock:
        session = manager._sessions[session_id]
        manager._queue.remove(session_id)
        manager._set_status(session, "finished", None)
    response = client.get(f"/api/sessions/{session_id}/mesh", params={"format": "glb"})
    assert response.status_code == 409 and "empty" in response.json()["detail"]


def test_a_list_racing_a_deletion_lists_the_rest(client, monkeypatch):
    from server.sessions import SessionManager, SessionNotFound

    sessions = client.get("/api/sessions").json()
    assert len(sessions) >= 2
    gone = sessions[0]["id"]
    original = SessionManager.agent_count

    def deleted_meanwhile(self, session_id):
        if session_id == gone:
            raise SessionNotFound(session_id)
        return original(self, session_id)

    monkeypatch.setattr(SessionManager, "agent_count", deleted_meanwhile)
    response = client.get("/api/sessions")
    assert response.status_code == 200
    assert [s["id"] for s in response.json()] == [s["id"] for s in sessions[1:]]


def test_the_token_never_reaches_the_access_log():
    from server.main import RedactTokens

    record = logging.LogRecord("uvicorn.access", logging.INFO, __file__, 1, '%s - "%s %s HTTP/%s" %d',
                               ("127.0.0.1:5", "GET", "/viewer?token=s3cret&x=1", "1.1", 200), None)
    RedactTokens().filter(record)
    assert "s3cret" not in record.getMessage() and "token=***&x=1" in record.getMessage()


def test_assets_are_bounded_and_can_be_deleted(tmp_path):
    from server.assets import AssetsFull, AssetStore

    cube = Path(__file__).with_name("data_cube.obj")
    data = cube.read_bytes() if cube.is_file() else _cube_obj()
    store = AssetStore(tmp_path, max_assets=3, cache_entries=2)
    ids = [store.add(data, f"cube{k}.obj")[0] for k in range(3)]
    assert store.cached() == 2, "only the most recent meshes stay parsed"
    with pytest.raises(AssetsFull, match="the limit is 3 assets"):
        store.add(data, "one-more.obj")
    assert store.resolve(ids[0]) is not None  # parsed again from disk
    store.delete(ids[0])
    with pytest.raises(KeyError):
        store.resolve(ids[0])
    store.add(data, "fits-again.obj")


def test_asset_routes_refuse_a_full_store_and_delete(client, monkeypatch):
    monkeypatch.setattr(client.app.state.assets, "max_assets", 1)
    response = client.post("/api/assets", files={"file": ("cube.obj", _cube_obj(), "text/plain")})
    assert response.status_code == 201, response.text
    asset = response.json()["id"]
    full = client.post("/api/assets", files={"file": ("cube.obj", _cube_obj(), "text/plain")})
    assert full.status_code == 409 and "DELETE /api/assets/{id}" in full.json()["detail"]
    assert client.delete(f"/api/assets/{asset}").status_code == 204
    assert client.delete(f"/api/assets/{asset}").status_code == 404
    assert client.post("/api/assets", files={"file": ("cube.obj", _cube_obj(), "text/plain")}).status_code == 201


def _cube_obj() -> bytes:
    corners = [(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 1)]
    faces = [(1, 2, 4), (1, 4, 3), (5, 7, 8), (5, 8, 6), (1, 5, 6), (1, 6, 2), (3, 4, 8), (3, 8, 7),
             (1, 3, 7), (1, 7, 5), (2, 6, 8), (2, 8, 4)]
    return ("".join(f"v {x} {y} {z}\n" for x, y, z in corners)
            + "".join(f"f {a} {b} {c}\n" for a, b, c in faces)).encode()


# --- 7. a bad frame in the middle is skipped and counted, not the end of the run ---------------


@pytest.fixture(scope="module")
def running(tmp_path_factory) -> Iterator[TestClient]:
    """An app whose sessions run (test preset, tiny frames)."""
    with running_app(tmp_path_factory.mktemp("abuse-running"), max_sessions=2) as client:
        yield client


def synthetic_tum_zip(frames: int, corrupt: int | None = None) -> bytes:
    """A TUM folder of ``frames`` synthetic 160x120 frames; frame ``corrupt``'s colour truncated."""
    from tests.test_server_stream import encoded_frames, k_text

    top = "room/"
    encoded = encoded_frames(frames)
    entries = {top + "intrinsics.txt": k_text(encoded[0][3]).replace(",", " ").encode(),
               top + "rgb.txt": "".join(f"{t:.6f} rgb/{k}.png\n" for k, (t, *_) in enumerate(encoded)).encode(),
               top + "depth.txt": "".join(f"{t:.6f} depth/{k}.png\n" for k, (t, *_) in enumerate(encoded)).encode()}
    for k, (_, color, depth, _) in enumerate(encoded):
        entries[top + f"rgb/{k}.png"] = color[:60] if k == corrupt else color
        entries[top + f"depth/{k}.png"] = depth
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, data in entries.items():
            archive.writestr(name, data)
    return buffer.getvalue()


def test_a_corrupt_frame_mid_upload_is_skipped_and_counted(running):
    from tests.test_server_api import wait_for

    response = running.post("/api/sessions", files={"file": ("room.zip", synthetic_tum_zip(5, corrupt=2))},
                            data={"preset": "test", "depth_scale": "5000"})
    assert response.status_code == 201, response.text
    state = wait_for(running, response.json()["id"])
    assert state["status"] == "finished", state
    assert state["frames_done"] == 4 and state["frames_skipped"] == 1
    run = (running.app.state.manager.session_dir(state["id"]) / "run.json").read_text()
    skipped = __import__("json").loads(run)["skipped_frames"]
    assert [s["index"] for s in skipped] == [2] and "cannot decode" in skipped[0]["reason"]


def test_a_stream_counts_the_frames_it_refused_and_caps_the_rest(running, monkeypatch):
    from server import stream
    from tests.test_server_api import wait_for
    from tests.test_server_stream import DEPTH_SCALE, encoded_frames, k_text

    frames = encoded_frames(3)
    session = running.post("/api/sessions", json={"source": "stream", "preset": "test", "depth_scale": DEPTH_SCALE,
                                                  "intrinsics": k_text(frames[0][3])}).json()["id"]

    def send(color, depth):
        return running.post(f"/api/sessions/{session}/frames", files={"color": ("c.png", color), "depth": ("d.png", depth)})

    assert send(frames[0][1], frames[0][2]).status_code == 200
    assert send(frames[1][1][:60], frames[1][2]).status_code == 422
    monkeypatch.setattr(stream, "MAX_STREAM_FRAMES", 2)
    assert send(frames[1][1], frames[1][2]).status_code == 200
    capped = send(frames[2][1], frames[2][2])
    assert capped.status_code == 413 and "the most one stream session takes" in capped.json()["detail"]
    assert running.post(f"/api/sessions/{session}/finish").status_code == 200
    state = wait_for(running, session)
    assert state["frames_done"] == 2 and state["frames_skipped"] == 1, "the bad frame; the capped one was not sent"
