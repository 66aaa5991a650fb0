"""End to end through the HTTP API: synthetic and TUM-zip sessions, results, rendering, AR,
restart, deletion, token, OpenAPI. The helpers here are shared by the other server tests."""

from __future__ import annotations

import importlib
import io
import time
import zipfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient

from server.main import create_app
from server.settings import Settings

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
ENDED = ("finished", "failed", "cancelled")
SYNTHETIC_SPEC = "orbit?frames=12&width=160&height=120"


def runtime_available() -> bool:
    try:
        importlib.import_module("slam.runtime")
    except ImportError:
        return False
    return True


needs_runtime = pytest.mark.skipif(not runtime_available(), reason="slam.runtime (the SLAM runtime) is not in the tree yet")


@contextmanager
def running_app(data_dir: Path, **overrides) -> Iterator[TestClient]:
    """The app on ``data_dir`` with its lifespan running, as a TestClient."""
    settings = Settings(data_dir=data_dir, viewer_port=overrides.pop("viewer_port", -1), **overrides)
    with TestClient(create_app(settings)) as client:
        yield client


def wait_for(client: TestClient, session_id: str, statuses=ENDED, timeout: float = 150.0,
             condition=None) -> dict:
    """Poll the session until its status is one of ``statuses`` (and ``condition(state)`` holds)."""
    deadline = time.monotonic() + timeout
    while True:
        state = client.get(f"/api/sessions/{session_id}").json()
        if state["status"] in statuses and (condition is None or condition(state)):
            return state
        if time.monotonic() > deadline:
            raise AssertionError(f"session {session_id} still {state} after {timeout} s")
        time.sleep(0.2)


def start_synthetic(client: TestClient, spec: str = SYNTHETIC_SPEC, preset: str = "test") -> str:
    response = client.post("/api/sessions", json={"source": "synthetic", "spec": spec, "preset": preset})
    assert response.status_code == 201, response.text
    assert response.json()["status"] == "queued"
    return response.json()["id"]


def zip_folder(folder: Path, top: str | None = None) -> bytes:
    """A zip of ``folder`` (inside a ``top`` folder if given), in memory."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_STORED) as archive:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                name = path.relative_to(folder).as_posix()
                archive.write(path, f"{top}/{name}" if top else name)
    return buffer.getvalue()


def decode_png(data: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None, "response is not a decodable PNG"
    return image


def camera_looking_at(target, eye, width=160, height=120, f=120.0) -> dict:
    """Render request for a camera at ``eye`` looking at ``target`` (world z up)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, forward], axis=1)
    T[:3, 3] = eye
    return {"T_world_cam": T.tolist(),
            "intrinsics": {"fx": f, "fy": f, "cx": width / 2, "cy": height / 2, "width": width, "height": height}}


def first_pose_camera(client: TestClient, session_id: str, width=80, height=60, f=60.0) -> dict:
    """Render request at the session's first estimated pose (it saw the map from there)."""
    from slam.eval.trajectory import parse_tum

    trajectory = parse_tum(client.get(f"/api/sessions/{session_id}/trajectory").text)
    return {"T_world_cam": trajectory.poses[0].tolist(),
            "intrinsics": {"fx": f, "fy": f, "cx": width / 2, "cy": height / 2, "width": width, "height": height}}


# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("voxfusion-data")


@pytest.fixture(scope="module")
def client(data_dir) -> Iterator[TestClient]:
    with running_app(data_dir, max_sessions=2) as client:
        yield client


@pytest.fixture(scope="module")
def synthetic_session(client) -> str:
    if not runtime_available():
        pytest.skip("slam.runtime (the SLAM runtime) is not in the tree yet")
    session_id = start_synthetic(client)
    state = wait_for(client, session_id)
    assert state["status"] == "finished", state
    return session_id


@needs_runtime
def test_synthetic_session_status_and_results(client, synthetic_session):
    state = client.get(f"/api/sessions/{synthetic_session}").json()
    assert state["frames_done"] == state["frames_total"] == 12
    assert state["fps"] > 0 and state["keyframes"] >= 1 and state["maps"] >= 1
    assert state["error"] is None and state["preset"] == "test"
    assert state["phase"] == "done"
    assert 0 <= state["ate_rmse_m"] < 0.5, "the synthetic scene has ground truth: its ATE is reported"
    assert state["outputs"] == {"trajectory": True, "mesh": True, "map": True}
    assert synthetic_session in [s["id"] for s in client.get("/api/sessions").json()]

    from slam.eval.trajectory import parse_tum

    trajectory = parse_tum(client.get(f"/api/sessions/{synthetic_session}/trajectory").text)
    assert len(trajectory) == 12
    for file_format in ("ply", "glb", "obj"):
        response = client.get(f"/api/sessions/{synthetic_session}/mesh", params={"format": file_format})
        assert response.status_code == 200, response.text
        mesh = trimesh.load(io.BytesIO(response.content), file_type=file_format, force="mesh")
        assert len(mesh.faces) > 100, file_format
    assert client.get(f"/api/sessions/{synthetic_session}/mesh", params={"format": "stl"}).status_code == 422


@needs_runtime
def test_render_colour_and_depth(client, synthetic_session):
    camera = first_pose_camera(client, synthetic_session)
    url = f"/api/sessions/{synthetic_session}/render"
    color = client.post(url, json=camera)
    assert color.status_code == 200 and color.headers["content-type"] == "image/png"
    rgb = decode_png(color.content)
    assert rgb.shape == (60, 80, 3)
    assert rgb.std() > 5, "the render shows structure"
    depth = decode_png(client.post(url, json=camera, params={"output": "depth"}).content)
    assert depth.dtype == np.uint16 and depth.shape == (60, 80)
    seen = depth[depth > 0]
    assert seen.size > 0.5 * depth.size
    assert 300 < np.median(seen) < 8000, "millimetres, a room-sized scene"


def test_render_threads_follow_the_running_sessions():
    from server.settings import render_threads_now, settings_from_env

    assert render_threads_now(0, running_sessions=0, cores=8) == 8, "idle: a view gets every core"
    assert render_threads_now(0, running_sessions=1, cores=8) == 1, "a running session takes every core"
    assert render_threads_now(3, running_sessions=0, cores=8) == 3 == render_threads_now(3, 2, 8)
    assert settings_from_env({}).render_threads == 0
    assert settings_from_env({"VOXFUSION_RENDER_THREADS": "2"}).render_threads == 2


@needs_runtime
def test_a_render_uses_every_core_while_no_session_runs(client, synthetic_session, monkeypatch):
    from server.settings import usable_cores

    pool = client.app.state.render_pools.render
    seen = []

    async def counting_run(function, call, *args, **kwargs):
        seen.append(call.threads)  # the torch threads the render helper is told to use
        return await run(function, call, *args, **kwargs)

    run = pool.run
    monkeypatch.setattr(pool, "run", counting_run)
    response = client.post(f"/api/sessions/{synthetic_session}/render", json=first_pose_camera(client, synthetic_session))
    assert response.status_code == 200, response.text
    assert seen == [usable_cores()]


@needs_runtime
def test_render_rejects_bad_cameras(client, synthetic_session):
    url = f"/api/sessions/{synthetic_session}/render"
    camera = first_pose_camera(client, synthetic_session)
    skewed = {**camera, "T_world_cam": (np.array(camera["T_world_cam"]) * 2).tolist()}
    response = client.post(url, json=skewed)
    assert response.status_code == 422 and "last row" in response.json()["detail"]
    huge = {**camera, "intrinsics": {**camera["intrinsics"], "width": 5000}}
    response = client.post(url, json=huge)
    assert response.status_code == 422 and response.json()["detail"].startswith("body.intrinsics.width: ")
    assert client.post("/api/sessions/000000000000/render", json=camera).status_code == 404
    far = np.array(camera["T_world_cam"])
    far[0, 3] = 1e300
    response = client.post(url, json={**camera, "T_world_cam": far.tolist()})
    assert response.status_code == 422 and "from the world origin" in response.json()["detail"]


@needs_runtime
@pytest.mark.parametrize("focal", [5e-324, 1e-300, 1e300])
def test_render_pick_and_ar_refuse_degenerate_focal_lengths(client, synthetic_session, focal):
    """A focal length that passed "> 0" (5e-324, 1e-300) broke the ray traversal (a 500)."""
    camera = first_pose_camera(client, synthetic_session)
    camera["intrinsics"]["fy"] = focal
    url = f"/api/sessions/{synthetic_session}"
    requests = [("render", camera), ("pick", {**camera, "u": 40, "v": 30}),
                ("ar", {"background": "render", **camera, "objects": [{"shape": "cube"}]}),
                ("ar", {"background": "frame:0", "intrinsics": camera["intrinsics"], "objects": [{"shape": "cube"}]})]
    for call, body in requests:
        response = client.post(f"{url}/{call}", json=body)
        assert response.status_code == 422, (call, response.text)
        message = response.json()["detail"]
        assert message.startswith("body.intrinsics: fy=") and "focal length is too" in message, message


@needs_runtime
def test_ar_composites_with_render_and_frame_backgrounds(client, synthetic_session):
    camera = first_pose_camera(client, synthetic_session)
    url = f"/api/sessions/{synthetic_session}"
    pick = client.post(f"{url}/pick", json={**camera, "u": 40, "v": 30}).json()
    assert pick["hit"], pick
    point = np.array(pick["point"])
    T_obj = np.eye(4)
    # The cube (half-size 0.1 m) sits on the picked pixel's ray, its centre 0.15 m in front of
    # the picked surface: the ray enters it at least 0.25 m in front, so the rendered depth of
    # a map from a short run cannot hide it there or at the pixels around. (A cube around the
    # picked point itself was hidden at some of them now and then.)
    camera_centre = np.asarray(camera["T_world_cam"])[:3, 3]
    towards_camera = (camera_centre - point) / np.linalg.norm(camera_centre - point)
    assert np.linalg.norm(camera_centre - point) > 0.5, "the cube must lie in front of the camera"
    T_obj[:3, 3] = point + 0.15 * towards_camera
    objects = [{"shape": "cube", "T_world_obj": T_obj.tolist(), "scale": 0.2, "color": [1.0, 0.0, 0.0]}]
    background = decode_png(client.post(f"{url}/render", json=camera).content)
    composite = client.post(f"{url}/ar", json={"background": "render", **camera, "objects": objects})
    assert composite.status_code == 200, composite.text
    image = decode_png(composite.content)
    changed = np.abs(image.astype(int) - background.astype(int)).sum(axis=2) > 30
    covered = changed[28:32, 38:42].mean()
    assert covered > 0.5, f"the cube covers the picked pixel and those around it: {covered:.2f}"
    framed = client.post(f"{url}/ar", json={"background": "frame:0", "objects": objects})
    assert framed.status_code == 200, framed.text
    assert decode_png(framed.content).shape == (120, 160, 3)
    bad = client.post(f"{url}/ar", json={"background": "frame:0", "objects": [{"shape": "teapot"}]})
    assert bad.status_code == 422
    missing = client.post(f"{url}/ar", json={"background": "frame:999", "objects": objects})
    assert missing.status_code == 404
    assert missing.json()["detail"] == "background frame:999: frame 999 does not exist (the input has 12 frames)"


@needs_runtime
@pytest.mark.shared_data
def test_tum_zip_upload_runs_to_the_end(client):
    desk = SHARED_DATA / "rgbd_dataset_freiburg1_desk"
    if not desk.is_dir():
        pytest.skip(f"real RGB-D data not found at {desk}")
    response = client.post("/api/sessions", files={"file": ("desk.zip", zip_folder(desk, top=desk.name), "application/zip")},
                           data={"preset": "test", "format": "auto"})
    assert response.status_code == 201, response.text
    state = wait_for(client, response.json()["id"])
    assert state["status"] == "finished", state
    assert state["frames_done"] == state["frames_total"] > 0
    assert state["source"] == "upload (tum)"
    trajectory = client.get(f"/api/sessions/{state['id']}/trajectory").text
    assert trajectory.count("\n1305031453.") == state["frames_done"], "TUM timestamps of the input"
    assert client.get(f"/api/sessions/{state['id']}/mesh").status_code == 200


@needs_runtime
def test_finished_sessions_are_listed_after_a_restart(data_dir, client, synthetic_session):
    with running_app(data_dir, viewer_port=0) as second:
        listed = {s["id"]: s for s in second.get("/api/sessions").json()}
        assert listed[synthetic_session]["status"] == "finished"
        assert listed[synthetic_session]["outputs"]["map"]
        camera = first_pose_camera(second, synthetic_session)
        response = second.post(f"/api/sessions/{synthetic_session}/render", json=camera)
        assert response.status_code == 200
        assert second.get(f"/api/sessions/{synthetic_session}/mesh", params={"format": "glb"}).status_code == 200
        assert second.post(f"/api/viewer/select/{synthetic_session}").status_code == 204
        viewer = second.app.state.viewer
        assert viewer.has_session(synthetic_session), "the viewer shows it again, read from disk"
        viewer.flush(force=True)
        assert viewer.stats.chunks_sent > 0


def test_stream_session_without_a_map_answers_409(client):
    created = client.post("/api/sessions", json={"source": "stream", "preset": "test",
                                                  "intrinsics": "100,100,80,60"}).json()
    url = f"/api/sessions/{created['id']}"
    camera = camera_looking_at([0, 0, 0], [1, 1, 1])
    response = client.post(f"{url}/render", json=camera)
    assert response.status_code == 409 and "no map yet" in response.json()["detail"]
    assert client.get(f"{url}/mesh").status_code == 409
    assert client.delete(url).status_code == 204
    assert client.get(url).status_code == 404


def test_delete_removes_the_session_folder(client, data_dir):
    created = client.post("/api/sessions", json={"source": "stream", "preset": "test"}).json()
    folder = data_dir / "sessions" / created["id"]
    assert (folder / "session.json").is_file()
    assert client.delete(f"/api/sessions/{created['id']}").status_code == 204
    deadline = time.monotonic() + 30
    while folder.exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not folder.exists()
    assert client.delete(f"/api/sessions/{created['id']}").status_code == 404
    assert client.get("/api/sessions/..%2f..%2fetc").status_code == 404


def test_token_is_required_when_set(tmp_path):
    with running_app(tmp_path, token="s3cret") as client:
        assert client.get("/api/sessions").status_code == 401
        assert client.get("/api/sessions", headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert client.get("/api/sessions", headers={"Authorization": "Bearer s3cret"}).status_code == 200
        assert client.get("/api/sessions", params={"token": "s3cret"}).status_code == 200
        assert client.get("/").status_code == 401
        page = client.get("/", params={"token": "s3cret"})
        assert page.status_code == 200 and "voxfusion" in page.text
        assert client.cookies.get("voxfusion_token") == "s3cret", "the page's token rides along to the viewer"
        client.cookies.clear()
        assert client.get("/viewer").status_code == 401
        assert client.post("/api/sessions", json={"source": "stream"}).status_code == 401


def test_openapi_documents_every_call_with_examples(client):
    schema = client.get("/openapi.json").json()
    paths = schema["paths"]
    expected = {
        ("post", "/api/sessions"), ("get", "/api/sessions"), ("get", "/api/sessions/{session_id}"),
        ("post", "/api/sessions/{session_id}/frames"), ("post", "/api/sessions/{session_id}/finish"),
        ("get", "/api/sessions/{session_id}/trajectory"), ("get", "/api/sessions/{session_id}/mesh"),
        ("post", "/api/sessions/{session_id}/render"), ("post", "/api/sessions/{session_id}/ar"),
        ("post", "/api/assets"), ("delete", "/api/sessions/{session_id}"),
    }
    for method, path in expected:
        assert method in paths.get(path, {}), f"{method.upper()} {path} missing from the OpenAPI schema"
    create = paths["/api/sessions"]["post"]["requestBody"]["content"]
    assert {"multipart/form-data", "application/json"} <= set(create)
    assert create["application/json"]["examples"]
    render = schema["components"]["schemas"]["CameraRequest"]
    assert render.get("examples"), "render request has an example"
    assert "WebSocket" in schema["info"]["description"]


def test_pages_are_served(client):
    page = client.get("/")
    assert page.status_code == 200 and "/static/app.js" in page.text
    assert client.get("/static/app.js").status_code == 200
    assert client.get("/static/style.css").status_code == 200


def test_demo_command_serves_and_starts_a_synthetic_session(tmp_path):
    """``voxfusion demo`` as a user runs it: the server comes up, prints the URL, lists a session."""
    import os
    import socket
    import subprocess
    import sys

    import httpx

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    repo = Path(__file__).resolve().parents[1]
    env = {**os.environ, "VOXFUSION_CANCEL_GRACE_S": "1",
           "PYTHONPATH": os.pathsep.join(filter(None, [str(repo), os.environ.get("PYTHONPATH")]))}
    process = subprocess.Popen(
        [sys.executable, "-m", "server.cli", "demo", "--port", str(port), "--data-dir", str(tmp_path),
         "--viewer-port", "-1", "--preset", "test", "--spec", "orbit?frames=3&width=80&height=60"],
        cwd=repo, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 90
        while True:
            try:
                sessions = httpx.get(f"http://127.0.0.1:{port}/api/sessions", timeout=5).json()
                break
            except httpx.TransportError:
                assert process.poll() is None and time.monotonic() < deadline, "the demo server did not start"
                time.sleep(0.5)
        assert len(sessions) == 1 and sessions[0]["source"].startswith("synthetic:orbit")
        assert httpx.get(f"http://127.0.0.1:{port}/", timeout=5).status_code == 200
    finally:
        process.terminate()
        output, _ = process.communicate(timeout=60)
    assert f"open http://127.0.0.1:{port}/" in output
    # uvicorn shuts down cleanly on SIGTERM (and then re-raises it, hence no exit code 0).
    assert "Application shutdown complete" in output
    import json

    from server.sessions import INTERRUPTED_QUEUED, INTERRUPTED_RUNNING

    saved = [json.loads(p.read_text()) for p in tmp_path.glob("sessions/*/session.json")]
    assert len(saved) == 1
    assert (saved[0]["status"], saved[0]["error"]) in (("failed", INTERRUPTED_RUNNING), ("failed", INTERRUPTED_QUEUED),
                                                        ("finished", None)), \
        "a session that the server's stop interrupted says so (not 'cancelled', a user's doing)"
