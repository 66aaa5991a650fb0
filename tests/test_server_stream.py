"""Streamed sessions: frames over HTTP and over the WebSocket protocol, run to the end."""

from __future__ import annotations

import base64
import struct
from typing import Iterator

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from tests.test_server_api import needs_runtime, running_app, wait_for

FRAMES = 10
DEPTH_SCALE = 5000.0


def encoded_frames(count: int = FRAMES, seed: int = 0) -> list[tuple[float, bytes, bytes, np.ndarray]]:
    """(timestamp, colour PNG, 16-bit depth PNG, K) of a small synthetic sequence."""
    from slam.data import open_sequence

    sequence = open_sequence(f"synthetic:orbit?frames={count}&width=160&height=120&seed={seed}")
    frames = []
    for frame in sequence:
        bgr = cv2.cvtColor(np.round(frame.rgb * 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
        depth = np.round(frame.depth * DEPTH_SCALE).astype(np.uint16)
        frames.append((frame.timestamp, cv2.imencode(".png", bgr)[1].tobytes(),
                       cv2.imencode(".png", depth)[1].tobytes(), frame.K))
    return frames


def k_text(K: np.ndarray) -> str:
    return f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}"


@pytest.fixture(scope="module")
def client(tmp_path_factory) -> Iterator[TestClient]:
    with running_app(tmp_path_factory.mktemp("stream-data"), max_sessions=2) as client:
        yield client


def post_frame(client, session_id, timestamp, color, depth, **fields):
    return client.post(f"/api/sessions/{session_id}/frames",
                       files={"color": ("c.png", color, "image/png"), "depth": ("d.png", depth, "image/png")},
                       data={"timestamp": str(timestamp), **fields})


def binary_message(timestamp: float, color: bytes, depth: bytes) -> bytes:
    return struct.pack("<dI", timestamp, len(color)) + color + depth


@needs_runtime
def test_http_then_websocket_stream_runs_to_the_end(client):
    """One stream session fed over both transports (they share the session's input)."""
    frames = encoded_frames()
    session_id = client.post("/api/sessions", json={"source": "stream", "preset": "test"}).json()["id"]
    by_http = FRAMES // 3

    # HTTP: intrinsics and depth scale on the first frame only.
    for i, (stamp, color, depth, K) in enumerate(frames[:by_http]):
        extra = {"intrinsics": k_text(K), "depth_scale": str(DEPTH_SCALE)} if i == 0 else {}
        response = post_frame(client, session_id, stamp, color, depth, **extra)
        assert response.status_code == 200, response.text
        assert response.json()["index"] == i

    # WebSocket: an empty header (the session knows its camera now), then binary and
    # base64-JSON frames, one bad frame in the middle.
    with client.websocket_connect(f"/api/sessions/{session_id}/stream") as socket:
        socket.send_json({})
        assert socket.receive_json() == {"type": "ready", "frames_received": by_http}
        for i, (stamp, color, depth, _) in enumerate(frames[by_http:], start=by_http):
            if i % 2 == 0:
                socket.send_bytes(binary_message(stamp, color, depth))
            else:
                socket.send_json({"timestamp": stamp, "color": base64.b64encode(color).decode(),
                                  "depth": base64.b64encode(depth).decode()})
            assert socket.receive_json() == {"type": "ack", "index": i}
            if i == by_http + 1:
                socket.send_bytes(binary_message(stamp, color, color))  # colour PNG where depth belongs
                error = socket.receive_json()
                assert error["type"] == "error" and error["status"] == 422
                assert "single-channel" in error["detail"] or "16-bit" in error["detail"]

        # The mesh is served while the session still runs (its input is open).
        state = wait_for(client, session_id, statuses=("running",), timeout=120,
                         condition=lambda s: s["outputs"]["mesh"])
        assert state["frames_total"] is None
        mesh = client.get(f"/api/sessions/{session_id}/mesh")
        assert mesh.status_code == 200 and len(mesh.content) > 1000
        assert client.get(f"/api/sessions/{session_id}").json()["status"] == "running"

        socket.send_json({"type": "finish"})
        assert socket.receive_json() == {"type": "finished", "frames": FRAMES}

    assert client.post(f"/api/sessions/{session_id}/finish").json() == {"frames": FRAMES}, "finish is idempotent"
    late = post_frame(client, session_id, 99.0, frames[0][1], frames[0][2])
    assert late.status_code == 409 and "finished" in late.json()["detail"]

    from slam.eval.trajectory import parse_tum

    state = wait_for(client, session_id)
    assert state["status"] == "finished", state
    assert state["frames_done"] == FRAMES
    trajectory = parse_tum(client.get(f"/api/sessions/{session_id}/trajectory").text)
    assert np.allclose(trajectory.timestamps, [f[0] for f in frames], atol=1e-6)

    # The recorded input serves AR frame backgrounds.
    response = client.post(f"/api/sessions/{session_id}/ar", json={"background": "frame:3", "objects": [{"shape": "cube"}]})
    assert response.status_code == 200, response.text


def test_websocket_refuses_bad_header_and_unknown_session(client):
    from starlette.websockets import WebSocketDisconnect

    with pytest.raises(WebSocketDisconnect):
        with client.websocket_connect("/api/sessions/000000000000/stream") as socket:
            socket.receive_json()
    session_id = client.post("/api/sessions", json={"source": "stream", "preset": "test"}).json()["id"]
    with client.websocket_connect(f"/api/sessions/{session_id}/stream") as socket:
        socket.send_text("not json")
        error = socket.receive_json()
        assert error["type"] == "error" and "JSON object" in error["detail"]
    client.delete(f"/api/sessions/{session_id}")
