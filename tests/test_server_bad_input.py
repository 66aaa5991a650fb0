"""Bad input gets a 4xx that says what is wrong, a crash or cancel ends only its own session,
and a session running meanwhile is not disturbed."""

from __future__ import annotations

import io
import os
import re
import signal
import time
import zipfile
from typing import Iterator

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.test_server_api import needs_runtime, running_app, runtime_available, wait_for

UPLOAD_LIMIT_MB = 1
VICTIM_FRAMES = 4


def png(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", image)[1].tobytes()


COLOR = png(np.full((60, 80, 3), 120, np.uint8))
DEPTH = png(np.full((60, 80), 5000, np.uint16))


def zip_bytes(entries: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, data in entries.items():
            archive.writestr(name, data)
    return buffer.getvalue()


@pytest.fixture(scope="module")
def client(tmp_path_factory) -> Iterator[TestClient]:
    with running_app(tmp_path_factory.mktemp("bad-input-data"), max_sessions=3, max_upload_mb=UPLOAD_LIMIT_MB,
                     cancel_grace_s=3.0) as client:
        yield client


@pytest.fixture(scope="module")
def victim(client) -> tuple[str, list]:
    """A stream session that runs (two frames mapped, waiting for more) while everything else
    here goes wrong; returns its id and the frames to send it."""
    if not runtime_available():
        pytest.skip("slam.runtime (the SLAM runtime) is not in the tree yet")
    from tests.test_server_stream import DEPTH_SCALE, encoded_frames, k_text

    frames = encoded_frames(VICTIM_FRAMES)
    session_id = client.post("/api/sessions", json={"source": "stream", "preset": "test", "depth_scale": DEPTH_SCALE,
                                                    "intrinsics": k_text(frames[0][3])}).json()["id"]
    for stamp, color, depth, _ in frames[:2]:
        assert post_frame(client, session_id, color, depth, timestamp=str(stamp)).status_code == 200
    return session_id, frames


def post_frame(client, session_id, color=COLOR, depth=DEPTH, **fields):
    return client.post(f"/api/sessions/{session_id}/frames",
                       files={"color": ("c.png", color, "image/png"), "depth": ("d.png", depth, "image/png")},
                       data=fields)


def detail(response) -> str:
    return response.json()["detail"]


@needs_runtime
def test_bad_frames_are_refused_with_the_reason(client, victim):
    session_id, frames = victim
    stamp, color, depth, _ = frames[2]
    corrupt = post_frame(client, session_id, color[:200], depth)
    assert corrupt.status_code == 422 and "color: cannot decode" in detail(corrupt)
    eight_bit = post_frame(client, session_id, color, png(np.full((120, 160), 5, np.uint8)))
    assert eight_bit.status_code == 422 and "16-bit PNG, got 8-bit" in detail(eight_bit)
    sizes = post_frame(client, session_id, color, png(np.zeros((60, 80), np.uint16)))
    assert sizes.status_code == 422 and "color is 160x120 but depth is 80x60" in detail(sizes)
    other_camera = post_frame(client, session_id, color, depth, intrinsics="80,80,40,30")
    assert other_camera.status_code == 422 and "changed mid-stream" in detail(other_camera)
    bad_k = post_frame(client, session_id, color, depth, intrinsics="80,80,40")
    assert bad_k.status_code == 422 and "fx,fy,cx,cy" in detail(bad_k)
    bad_stamp = post_frame(client, session_id, color, depth, timestamp="yesterday")
    assert bad_stamp.status_code == 422 and "timestamp" in detail(bad_stamp)
    good = post_frame(client, session_id, color, depth, timestamp=str(stamp))
    assert good.status_code == 200 and good.json()["index"] == 2, "the stream goes on after bad frames"


def test_bad_zips_are_refused_with_the_reason(client):
    def upload(data: bytes, **fields):
        return client.post("/api/sessions", files={"file": ("data.zip", data, "application/zip")}, data=fields)

    escaping = upload(zip_bytes({"seq/rgb.txt": b"", "../../etc/cron.d/x": b"boom"}))
    assert escaping.status_code == 422 and "'..' would escape the archive root" in detail(escaping)
    absolute = upload(zip_bytes({"/etc/passwd": b"x"}))
    assert absolute.status_code == 422 and "absolute paths" in detail(absolute)
    not_zip = upload(b"PK but not really a zip")
    assert not_zip.status_code == 400 and "not a valid zip" in detail(not_zip)
    unknown = upload(zip_bytes({"notes/readme.txt": b"hello"}))
    assert unknown.status_code == 422 and "cannot tell the dataset format" in detail(unknown)
    assert "/sessions/" not in detail(unknown), "server paths are not shown"
    broken_tum = upload(zip_bytes({"fr1_x/rgb.txt": b"1.0 rgb/1.png\n", "fr1_x/depth.txt": b"1.0 depth/1.png\n",
                                   "fr1_x/rgb/1.png": b"not a png", "fr1_x/depth/1.png": DEPTH}), intrinsics="80,80,40,30")
    assert broken_tum.status_code == 422 and "rgb/1.png" in detail(broken_tum)
    bad_option = upload(zip_bytes({"a.txt": b"x"}), preset="fastest")
    assert bad_option.status_code == 422 and "preset" in detail(bad_option)
    oversized = upload(os.urandom(UPLOAD_LIMIT_MB * 1024 * 1024 + 10_000))
    assert oversized.status_code == 413 and "larger than 1 MiB" in detail(oversized)
    listed = client.get("/api/sessions").json()
    assert all(s["source"] != "upload" for s in listed), "refused uploads leave no session behind"


def test_bad_json_requests(client):
    response = client.post("/api/sessions", content=b"{not json", headers={"content-type": "application/json"})
    assert response.status_code == 400 and "not valid JSON" in detail(response)
    response = client.post("/api/sessions", json={"source": "synthetic", "spec": "orbit?frames=abc"})
    assert response.status_code == 422 and "frames='abc' is not an integer" in detail(response)
    response = client.post("/api/sessions", json={"source": "webcam"})
    assert response.status_code == 422 and "source" in detail(response)
    response = client.post("/api/sessions", json={"source": "stream", "intrinsics": "1,2"})
    assert response.status_code == 422 and "intrinsics" in detail(response)


def test_invalid_utf8_json_is_a_400_not_a_500(client):
    response = client.post("/api/sessions", content=bytes.fromhex("c3287b7d"),
                           headers={"content-type": "application/json"})
    assert response.status_code == 400 and "not UTF-8" in detail(response)


def test_validation_errors_are_one_message_with_the_field_location(client):
    response = client.get("/api/sessions/000000000000/mesh", params={"format": "stl"})
    assert response.status_code == 422 and detail(response) == "query.format: Input should be 'ply', 'glb' or 'obj'"
    response = client.post("/api/sessions/000000000000/render", json={"T_world_cam": 1})
    assert response.status_code == 422
    assert detail(response) == "body.T_world_cam: Input should be a valid list; body.intrinsics: Field required"
    camera = {"T_world_cam": np.eye(4).tolist(),
              "intrinsics": {"fx": 100, "fy": -1, "cx": 40, "cy": 30, "width": 80, "height": 60}}
    response = client.post("/api/sessions/000000000000/pick", json={**camera, "u": 1, "v": 1})
    assert response.status_code == 422 and detail(response) == "body.intrinsics.fy: Input should be greater than 0"
    response = client.post("/api/sessions/000000000000/render", content=b"{not json",
                           headers={"content-type": "application/json"})
    # Every route answers a body that does not parse alike, before it runs (server.budget).
    assert response.status_code == 400 and detail(response).startswith("the body is not valid JSON (")
    response = client.post("/api/sessions", json={"source": "stream", "depth_scale": "much"})
    assert response.status_code == 422 and detail(response).startswith("body.depth_scale: ")
    schema = client.get("/openapi.json").json()
    assert "HTTPValidationError" not in schema["components"]["schemas"], "422s are documented as they are sent"
    render_422 = schema["paths"]["/api/sessions/{session_id}/render"]["post"]["responses"]["422"]
    assert render_422["content"]["application/json"]["schema"] == {"$ref": "#/components/schemas/ErrorOut"}


def test_upload_errors_name_the_upload_not_the_server_disk(client):
    data_dir = str(client.app.state.settings.data_dir)
    for entries in ({"readme.txt": b"hello"}, {"notes/readme.txt": b"hello"}):
        response = client.post("/api/sessions", files={"file": ("data.zip", zip_bytes(entries), "application/zip")})
        message = detail(response)
        assert response.status_code == 422 and "cannot tell the dataset format of " in message, message
        assert data_dir not in message and "/sessions/" not in message and "/tmp" not in message, message
        assert not re.search(r"\b[0-9a-f]{12}\b", message), f"the id of a session never created: {message}"
    assert "of the top level of the zip: " in detail(
        client.post("/api/sessions", files={"file": ("d.zip", zip_bytes({"readme.txt": b"x"}), "application/zip")}))


def test_a_bad_asset_names_the_users_file_in_a_plain_sentence(client):
    response = client.post("/api/assets", files={"file": ("chair.glb", b"glTF\x02\x00\x00\x00" + bytes(16),
                                                          "model/gltf-binary")})
    assert response.status_code == 422
    assert detail(response) == "chair.glb could not be read as a GLB file: it is damaged or not a GLB file"


def start_streams_with_a_frame(client, count: int) -> list[str]:
    """Stream sessions that have each mapped one frame and now wait (idle) for more."""
    ids = []
    for _ in range(count):
        session_id = client.post("/api/sessions", json={"source": "stream", "preset": "test"}).json()["id"]
        missing = post_frame(client, session_id)
        assert missing.status_code == 422 and "intrinsics: required on the first frame" in detail(missing)
        response = post_frame(client, session_id, timestamp="0", intrinsics="80,80,40,30", depth_scale="1000")
        assert response.status_code == 200, response.text
        ids.append(session_id)
    for session_id in ids:
        wait_for(client, session_id, statuses=("running",), condition=lambda s: s["frames_done"] >= 1, timeout=120)
    return ids


def process_group_gone(group: int, timeout: float = 10.0) -> bool:
    """True once no process of the group (a worker and the mapping process it started) is left."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            os.killpg(group, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.2)
    return False


@needs_runtime
def test_crash_and_cancel_end_only_their_own_session(client, victim):
    manager = client.app.state.manager
    doomed, stopped = start_streams_with_a_frame(client, 2)
    queued = client.post("/api/sessions", json={"source": "stream", "preset": "test"}).json()["id"]
    assert client.get(f"/api/sessions/{queued}").json()["status"] == "queued", "three sessions already run"
    assert client.post(f"/api/sessions/{queued}/cancel").json()["status"] == "cancelled"

    worker = manager._get(doomed).process.pid
    os.kill(worker, signal.SIGKILL)
    crashed = wait_for(client, doomed, timeout=30)
    assert crashed["status"] == "failed" and "SIGKILL" in crashed["error"], crashed
    assert process_group_gone(worker), "the crashed worker's mapping process is cleaned up too"

    group = manager._get(stopped).process.pid
    client.post(f"/api/sessions/{stopped}/cancel")
    assert wait_for(client, stopped, timeout=30)["status"] == "cancelled"
    assert process_group_gone(group), "the cancelled session's processes are still alive"
    late = post_frame(client, stopped, intrinsics="80,80,40,30")
    assert late.status_code == 409 and "cancelled" in detail(late)

    # The victim took bad frames, a neighbour's crash and a cancel, and ends normally.
    session_id, frames = victim
    for stamp, color, depth, _ in frames[3:]:
        assert post_frame(client, session_id, color, depth, timestamp=str(stamp)).status_code == 200
    assert client.post(f"/api/sessions/{session_id}/finish").json()["frames"] == VICTIM_FRAMES
    state = wait_for(client, session_id, timeout=120)
    assert state["status"] == "finished" and state["error"] is None, state
    assert state["frames_done"] == VICTIM_FRAMES
