"""Assets and ground truth are parsed in the decode helper, within limits checked before the
parsers see the data: a GLB whose nodes nest thousands deep, an OBJ or PLY that announces
millions of faces and a dataset whose ground-truth file has too many lines are refused with a
message, quickly, and the API process keeps answering other clients."""

from __future__ import annotations

import io
import json
import resource
import struct
import threading
import time
import zipfile
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.test_server_api import running_app

CUBE_OBJ = ("".join(f"v {x} {y} {z}\n" for x in (-1, 1) for y in (-1, 1) for z in (-1, 1))
            + "f 1 2 4\nf 1 4 3\nf 5 7 8\nf 5 8 6\nf 1 5 6\nf 1 6 2\n"
              "f 3 4 8\nf 3 8 7\nf 1 3 7\nf 1 7 5\nf 2 6 8\nf 2 8 4\n").encode()
FRAME_W, FRAME_H = 64, 48


def png(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", image)[1].tobytes()


def jpg(image: np.ndarray) -> bytes:
    return cv2.imencode(".jpg", image)[1].tobytes()


def glb(nodes: list[dict]) -> bytes:
    """A GLB of one triangle, instanced by every node that names ``"mesh": 0``."""
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32).tobytes()
    indices = np.array([0, 1, 2], np.uint16).tobytes() + b"\0\0"
    document = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": nodes,
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "buffers": [{"byteLength": len(positions) + len(indices)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(positions)},
                        {"buffer": 0, "byteOffset": len(positions), "byteLength": 6}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                       "min": [0, 0, 0], "max": [1, 1, 0]},
                      {"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"}],
    }
    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 4)
    binary = positions + indices
    body = struct.pack("<I4s", len(text), b"JSON") + text + struct.pack("<I4s", len(binary), b"BIN\0") + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def node_chain(depth: int) -> bytes:
    """``depth`` nodes, each the only child of the one before, each holding the triangle."""
    return glb([{"mesh": 0, "children": [i + 1]} for i in range(depth - 1)] + [{"mesh": 0}])


def replica_zip(traj_lines: int | None = None, frames: int = 3) -> bytes:
    """A Replica scene of ``frames`` frames whose ``traj.txt`` has one pose per frame, or
    ``traj_lines`` copies of one pose (a few kilobytes compressed)."""
    top = "room0/"  # NICE-SLAM's layout: cam_params.json beside the scene folder
    entries = {"cam_params.json": json.dumps({"camera": {"w": FRAME_W, "h": FRAME_H, "fx": 50.0, "fy": 50.0,
                                                               "cx": 31.5, "cy": 23.5, "scale": 6553.5}}).encode()}
    rows = []
    for n in range(frames):
        entries[top + f"results/frame{n:06d}.jpg"] = jpg(np.full((FRAME_H, FRAME_W, 3), 100 + 10 * n, np.uint8))
        entries[top + f"results/depth{n:06d}.png"] = png(np.full((FRAME_H, FRAME_W), 6553 + n, np.uint16))
        pose = np.eye(4)
        pose[:3, 3] = [0.1 * n, 0.02 * n * n, 1.0 - 0.05 * n]
        rows.append(" ".join(f"{v:.6f}" for v in pose.ravel()))
    if traj_lines is not None:
        rows = [rows[0]] * traj_lines
    entries[top + "traj.txt"] = ("\n".join(rows) + "\n").encode()
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, data in entries.items():
            archive.writestr(name, data)
    return buffer.getvalue()


def post_asset(client: TestClient, name: str, data: bytes):
    return client.post("/api/assets", files={"file": (name, data, "application/octet-stream")})


def upload(client: TestClient, data: bytes) -> str:
    response = client.post("/api/sessions", files={"file": ("scene.zip", data, "application/zip")},
                           data={"preset": "test"})
    assert response.status_code == 201, response.text
    return response.json()["id"]


def rss_mb() -> float:
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmRSS:")) / 1024


@pytest.fixture(scope="module")
def client(tmp_path_factory) -> Iterator[TestClient]:
    # Sessions only queue (no worker runs): the routes read their inputs, never their results.
    with running_app(tmp_path_factory.mktemp("parsing-budget")) as client:
        client.app.state.manager._start_queued = lambda: None
        assert post_asset(client, "warm.obj", CUBE_OBJ).status_code == 201  # the helper is started
        yield client


# --- assets ---------------------------------------------------------------------------------


@pytest.mark.timeout(60)
def test_a_glb_whose_nodes_nest_5000_deep_is_refused_quickly(client):
    data = node_chain(5000)
    started = time.monotonic()
    response = post_asset(client, "tower.glb", data)
    elapsed = time.monotonic() - started
    assert response.status_code == 422, response.text
    detail = response.json()["detail"]
    assert "tower.glb" in detail and "5000" in detail and "64" in detail, detail
    assert elapsed < 5.0, f"refused after {elapsed:.1f} s"
    assert client.get("/api/sessions").status_code == 200


def test_glb_node_graphs_that_are_not_trees_are_refused():
    from ar import AssetError, load_asset

    with pytest.raises(AssetError, match="cycle"):
        load_asset(glb([{"mesh": 0, "children": [1]}, {"mesh": 0, "children": [0]}]), "loop.glb")
    with pytest.raises(AssetError, match="more than one parent"):
        load_asset(glb([{"children": [2]}, {"children": [2]}, {"mesh": 0}]), "shared.glb")
    with pytest.raises(AssetError, match="nodes"):
        load_asset(glb([{"mesh": 0} for _ in range(5000)]), "crowd.glb")
    with pytest.raises(AssetError, match="faces"):
        load_asset(glb([{"mesh": 0}]), "small.glb", max_faces=0)
    assert load_asset(node_chain(64), "deep.glb").num_faces == 64


def test_huge_face_counts_are_refused_before_trimesh_parses(monkeypatch):
    import trimesh

    from ar import AssetError, load_asset

    def no_parse(*args, **kwargs):
        raise AssertionError("trimesh parsed a file the pre-scan should have refused")

    monkeypatch.setattr(trimesh, "load", no_parse)
    obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * 600_001
    with pytest.raises(AssetError, match=r"big\.obj: 600001 faces; the limit is 500000"):
        load_asset(obj, "big.obj")
    obj_vertices = b"v 0 0 0\n" * 1_500_001 + b"f 1 2 3\n"
    with pytest.raises(AssetError, match="1500001 vertices; the limit is 1500000"):
        load_asset(obj_vertices, "points.obj")
    ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n" \
          b"property float z\nelement face 7000000\nproperty list uchar int vertex_indices\nend_header\n"
    with pytest.raises(AssetError, match="7000000 faces; the limit is 500000"):
        load_asset(ply, "bomb.ply")
    odd = ply.replace(b"element face 7000000", b"element edge 9000000000")
    with pytest.raises(AssetError, match="9000000000 edge"):
        load_asset(odd, "edges.ply")


def test_a_huge_ply_header_gets_422_from_the_api(client):
    ply = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n" \
          b"element face 7000000\nproperty list uchar int vertex_indices\nend_header\n"
    response = post_asset(client, "bomb.ply", ply)
    assert response.status_code == 422
    assert "bomb.ply: 7000000 faces; the limit is 500000" in response.json()["detail"]


def test_assets_are_parsed_in_the_helper_and_work_in_ar(client, monkeypatch):
    import trimesh

    asset = post_asset(client, "cube.obj", CUBE_OBJ)
    assert asset.status_code == 201 and asset.json()["faces"] == 12, asset.text
    session = upload(client, replica_zip())
    # Parsed again on the next use (the cache forgotten); trimesh in this process is broken, so
    # only a parse in the helper process can succeed.
    client.app.state.assets._cache.clear()
    monkeypatch.setattr(trimesh, "load", lambda *a, **k: (_ for _ in ()).throw(AssertionError("parsed in the API")))
    T_world_obj = np.eye(4)
    T_world_obj[2, 3] = 0.5
    response = client.post(f"/api/sessions/{session}/ar", json={
        "background": "frame:0", "T_world_cam": np.eye(4).tolist(),
        "intrinsics": {"fx": 50, "fy": 50, "cx": 31.5, "cy": 23.5, "width": FRAME_W, "height": FRAME_H},
        "objects": [{"asset": asset.json()["id"], "T_world_obj": T_world_obj.tolist(), "scale": 0.1}]})
    assert response.status_code == 200, response.text
    assert json.loads(response.headers["X-AR-Objects"])[0]["state"] == "visible"
    assert client.app.state.assets.cached() == 1


def test_a_busy_helper_gets_503_with_retry_after(client, monkeypatch):
    from server.decoding import shared_helper

    asset = post_asset(client, "cube.obj", CUBE_OBJ).json()["id"]
    session = upload(client, replica_zip())
    client.app.state.assets._cache.clear()
    queue = client.app.state.assets.parse_queue
    monkeypatch.setattr(queue, "wait_s", 0.2)
    monkeypatch.setattr(queue, "timeout_s", 0.3)
    holder = threading.Thread(target=shared_helper().call, args=(time.sleep, 4.0))
    holder.start()
    try:
        time.sleep(0.3)
        uploaded = post_asset(client, "cube.obj", CUBE_OBJ)
        composited = client.post(f"/api/sessions/{session}/ar", json={
            "background": "frame:0", "T_world_cam": np.eye(4).tolist(), "objects": [{"asset": asset}]})
    finally:
        holder.join()
    for response in (uploaded, composited):
        assert response.status_code == 503, response.text
        assert int(response.headers["Retry-After"]) > 0 and "busy" in response.json()["detail"]
    time.sleep(0.5)
    assert post_asset(client, "cube.obj", CUBE_OBJ).status_code == 201


# --- ground truth ---------------------------------------------------------------------------


def test_the_series_of_a_normal_replica_upload_is_as_before(client):
    from slam import open_sequence

    data = replica_zip()
    session = upload(client, data)
    series = client.get(f"/api/sessions/{session}/series")
    assert series.status_code == 200, series.text
    body = series.json()
    root = Path(client.app.state.manager.get(session).sources[0].path)
    sequence = open_sequence(root)
    expected = np.stack([T[:3, 3] for T in sequence.gt_poses])
    np.testing.assert_allclose(body["ground_truth"], expected, atol=1e-4)
    assert body["ground_truth_note"] is None and body["estimated"] == [] and body["error_m"] is None
    camera = client.get(f"/api/sessions/{session}/camera")
    assert camera.status_code == 409  # nothing tracked yet: as before


@pytest.mark.timeout(120)
def test_a_ground_truth_over_the_line_cap_is_skipped_with_a_note(client):
    from server.series import MAX_GROUND_TRUTH_LINES

    data = replica_zip(traj_lines=MAX_GROUND_TRUTH_LINES + 1)
    assert len(data) < 200_000
    session = upload(client, data)
    before = rss_mb()
    started = time.monotonic()
    response = client.get(f"/api/sessions/{session}/series")
    elapsed = time.monotonic() - started
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["ground_truth"] is None and body["error_m"] is None
    note = body["ground_truth_note"]
    assert "traj.txt" in note and f"{MAX_GROUND_TRUTH_LINES}" in note, note
    assert elapsed < 5.0, f"answered after {elapsed:.1f} s"
    assert rss_mb() - before < 50
    again = client.get(f"/api/sessions/{session}/series").json()  # remembered, not read again
    assert again["ground_truth_note"] == note


def test_the_api_keeps_compact_ground_truth_within_a_budget():
    from server.series import GroundTruth, SourceFacts, SourceFactsCache

    def facts(frames: int) -> SourceFacts:
        return SourceFacts(None, GroundTruth(np.arange(frames, dtype=np.float64), np.zeros((frames, 3))), None)

    cache = SourceFactsCache(max_entries=3, max_bytes=10_000)
    for key in range(5):
        cache.put(key, facts(100))  # 3,200 bytes each
    assert len(cache) == 3 and cache.nbytes() <= 10_000 and cache.get(0) is None and cache.get(4) is not None
    cache.put("big", facts(1000))  # over the whole budget: not kept
    assert cache.get("big") is None and len(cache) == 3


def test_an_input_that_times_out_is_read_once_and_a_failed_helper_is_asked_again(monkeypatch):
    import server.series as series
    from server.helper_pool import HelperFailed, HelperTimedOut
    from server.worker import SourceSpec

    class FailingHelper:
        def __init__(self, error: Exception) -> None:
            self.error, self.calls = error, 0

        def call(self, *args, **kwargs):
            self.calls += 1
            raise self.error

    monkeypatch.setattr(series, "_cache", series.SourceFactsCache())
    for error, calls in ((HelperTimedOut("decoding took longer than 60 s"), 1), (HelperFailed("did not start"), 2)):
        helper = FailingHelper(error)
        monkeypatch.setattr(series, "shared_helper", lambda: helper)
        spec = SourceSpec("dataset", f"/nowhere/{calls}")
        notes = [series.source_facts(spec).note for _ in range(2)]
        assert helper.calls == calls and all(str(error) in note for note in notes), notes
