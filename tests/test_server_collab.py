"""Collaborative sessions through the API: several upload parts (one agent each), synthetic
spec lists, stream frames that name their agent, per-agent trajectories, agents/maps/loops in
the status, and the live trajectory following loop corrections.

Most tests keep the workers from starting (``_start_queued`` is switched off), so they check
the API and the session manager in a second; one slow test runs a real 2-agent session."""

from __future__ import annotations

import io
import json
import queue
import threading
import zipfile
from typing import Iterator

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from server.sessions import SessionManager, SessionStatus
from server.worker import END_OF_STREAM, SourceSpec, WorkerJob, slam_sources, stream_frames
from slam.events import MapUpdateEvent, PoseEvent, PosesUpdatedEvent, StatsEvent, SubmapEvent
from tests.test_server_api import needs_runtime, running_app, wait_for

TINY = "width=80&height=60"


def png(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", image)[1].tobytes()


def tum_zip(spec: str = f"synthetic:agents?agent=0&agents=2&frames=3&{TINY}", top: str = "room") -> bytes:
    """A small TUM RGB-D folder (rgb.txt, depth.txt, intrinsics.txt, 16-bit depth at 5000/m) zipped."""
    from slam.data import open_sequence

    sequence = open_sequence(spec)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        rgb_list, depth_list = ["# color images"], ["# depth images"]
        for frame in sequence:
            stamp = f"{100.0 + frame.timestamp:.6f}"
            bgr = cv2.cvtColor(np.round(frame.rgb * 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
            archive.writestr(f"{top}/rgb/{stamp}.png", png(bgr))
            archive.writestr(f"{top}/depth/{stamp}.png", png(np.round(frame.depth * 5000).astype(np.uint16)))
            rgb_list.append(f"{stamp} rgb/{stamp}.png")
            depth_list.append(f"{stamp} depth/{stamp}.png")
        K = sequence[0].K
        archive.writestr(f"{top}/rgb.txt", "\n".join(rgb_list) + "\n")
        archive.writestr(f"{top}/depth.txt", "\n".join(depth_list) + "\n")
        archive.writestr(f"{top}/intrinsics.txt", f"{K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")
    return buffer.getvalue()


@pytest.fixture(scope="module")
def zips() -> tuple[bytes, bytes]:
    return (tum_zip(f"synthetic:agents?agent=0&agents=2&frames=3&{TINY}"),
            tum_zip(f"synthetic:agents?agent=1&agents=2&frames=3&{TINY}"))


@pytest.fixture()
def idle(tmp_path, monkeypatch) -> Iterator[TestClient]:
    """The app with queued sessions never started: API and manager only, no worker processes."""
    monkeypatch.setattr(SessionManager, "_start_queued", lambda self: None)
    with running_app(tmp_path, max_sessions=2) as client:
        yield client


def detail(response) -> str:
    return response.json()["detail"]


def upload(client, *parts: tuple[str, bytes], **fields):
    return client.post("/api/sessions", files=[("file", (name, data, "application/zip")) for name, data in parts],
                       data=fields)


# -- uploads -------------------------------------------------------------------------------------

def test_two_file_parts_make_one_session_with_two_sources(idle, zips, tmp_path):
    response = upload(idle, ("first.zip", zips[0]), ("second.zip", zips[1]), preset="test", format="tum")
    assert response.status_code == 201, response.text
    session_id = response.json()["id"]
    job = idle.app.state.manager._get(session_id).job
    assert len(job.sources) == 2
    assert [s.kind for s in job.sources] == ["dataset", "dataset"]
    assert [s.format for s in job.sources] == ["tum", "tum"]
    folder = tmp_path / "sessions" / session_id / "input"
    assert [s.path for s in job.sources] == [str(folder / "0" / "room"), str(folder / "1" / "room")]
    state = idle.get(f"/api/sessions/{session_id}").json()
    assert state["agents"] == 2 and state["maps"] == 0 and state["loops"] == 0
    assert state["source"] == "upload (tum) x 2 agents"
    # The agents' sources survive a restart (session.json).
    saved = SessionStatus.from_json(json.loads((folder.parent / "session.json").read_text()))
    assert saved.sources == job.sources and saved.agents == 2


def test_one_file_part_is_still_a_single_agent_session(idle, zips, tmp_path):
    response = upload(idle, ("only.zip", zips[0]), preset="test")
    assert response.status_code == 201, response.text
    session_id = response.json()["id"]
    job = idle.app.state.manager._get(session_id).job
    assert len(job.sources) == 1 and job.source.path == str(tmp_path / "sessions" / session_id / "input" / "room")
    assert idle.get(f"/api/sessions/{session_id}").json()["agents"] == 1


@pytest.mark.parametrize("second, status, reason", [
    (b"PK this is no zip", 400, "not a valid zip"),
    (None, 422, "cannot tell the dataset format"),
])
def test_a_bad_second_part_is_named_and_nothing_starts(idle, zips, tmp_path, second, status, reason):
    if second is None:
        buffer = io.BytesIO()
        with zipfile.ZipFile(buffer, "w") as archive:
            archive.writestr("notes/readme.txt", "hello")
        second = buffer.getvalue()
    response = upload(idle, ("good.zip", zips[0]), ("bad.zip", second), preset="test")
    assert response.status_code == status, response.text
    assert "file 2 of 2 ('bad.zip')" in detail(response) and reason in detail(response)
    assert "/sessions/" not in detail(response), "no server paths"
    assert idle.get("/api/sessions").json() == [], "no session was created"
    assert not any((tmp_path / "sessions").iterdir()), "the first part's files are gone again"


def test_a_bad_option_refuses_every_part_and_other_sessions_stay(idle, zips):
    kept = upload(idle, ("a.zip", zips[0]), preset="test").json()["id"]
    response = upload(idle, ("a.zip", zips[0]), ("b.zip", zips[1]), preset="fastest")
    assert response.status_code == 422 and "preset" in detail(response)
    too_many = upload(idle, *[(f"{k}.zip", zips[0]) for k in range(17)], preset="test")
    assert too_many.status_code == 400 and "16" in detail(too_many)
    text_part = idle.post("/api/sessions", files=[("file", ("a.zip", zips[0], "application/zip"))],
                          data={"file": "not a file", "preset": "test"})
    assert text_part.status_code == 422 and "must be a file" in detail(text_part)
    assert [s["id"] for s in idle.get("/api/sessions").json()] == [kept]
    assert idle.get(f"/api/sessions/{kept}").json()["status"] == "queued"


def test_synthetic_spec_list_is_one_agent_per_spec(idle):
    specs = [f"agents?agent=0&agents=2&frames=12&{TINY}", f"synthetic:agents?agent=1&agents=2&frames=12&{TINY}"]
    response = idle.post("/api/sessions", json={"source": "synthetic", "spec": specs, "preset": "test"})
    assert response.status_code == 201, response.text
    job = idle.app.state.manager._get(response.json()["id"]).job
    assert [s.path for s in job.sources] == [specs[0], specs[1].removeprefix("synthetic:")]
    assert idle.get(f"/api/sessions/{response.json()['id']}").json()["agents"] == 2
    bad = idle.post("/api/sessions", json={"source": "synthetic", "spec": [specs[0], "agents?agent=5&agents=2"]})
    assert bad.status_code == 422 and "spec[1] (agent 1)" in detail(bad) and "agent=5" in detail(bad)
    empty = idle.post("/api/sessions", json={"source": "synthetic", "spec": []})
    assert empty.status_code == 422 and "one per agent" in detail(empty)
    stream = idle.post("/api/sessions", json={"source": "stream", "spec": specs})
    assert stream.status_code == 422 and "name their agent" in detail(stream)


# -- streams -------------------------------------------------------------------------------------

COLOR = png(np.full((60, 80, 3), 120, np.uint8))
DEPTH = png(np.full((60, 80), 5000, np.uint16))


def post_frame(client, session_id, **fields):
    return client.post(f"/api/sessions/{session_id}/frames",
                       files={"color": ("c.png", COLOR, "image/png"), "depth": ("d.png", DEPTH, "image/png")},
                       data=fields)


def test_stream_frames_name_their_agent(idle):
    session_id = idle.post("/api/sessions", json={"source": "stream", "preset": "test"}).json()["id"]
    first = post_frame(idle, session_id, intrinsics="80,80,40,30")
    assert first.status_code == 200 and first.json() == {"index": 0, "frames_received": 1, "agent": 0}
    missing = post_frame(idle, session_id, agent="1")
    assert missing.status_code == 422 and "required on the first frame of agent 1" in detail(missing)
    other = post_frame(idle, session_id, agent="1", intrinsics="70,70,40,30")
    assert other.status_code == 200 and other.json() == {"index": 0, "frames_received": 2, "agent": 1}
    assert post_frame(idle, session_id, agent="1").json()["index"] == 1, "agent 1 keeps its camera"
    assert post_frame(idle, session_id).json()["index"] == 1, "indices count per agent"
    changed = post_frame(idle, session_id, agent="1", intrinsics="80,80,40,30")
    assert changed.status_code == 422 and "intrinsics of agent 1: changed mid-stream" in detail(changed)
    for bad, reason in (("-1", "whole number >= 0"), ("one", "whole number >= 0"), ("1.5", "whole number >= 0"),
                        ("99", "between 0 and 15")):
        response = post_frame(idle, session_id, agent=bad)
        assert response.status_code == 422 and detail(response).startswith("agent: ") and reason in detail(response)
    state = idle.get(f"/api/sessions/{session_id}").json()
    assert state["agents"] == 2

    # The WebSocket: a header agent for binary/base64 frames, a frame's own agent wins.
    import base64
    import struct

    with idle.websocket_connect(f"/api/sessions/{session_id}/stream") as socket:
        socket.send_json({"agent": 1})
        assert socket.receive_json() == {"type": "ready", "frames_received": 4}
        socket.send_bytes(struct.pack("<dI", 1.0, len(COLOR)) + COLOR + DEPTH)
        assert socket.receive_json() == {"type": "ack", "index": 2, "agent": 1}
        frame = {"timestamp": 2.0, "color": base64.b64encode(COLOR).decode(), "depth": base64.b64encode(DEPTH).decode()}
        socket.send_json({**frame, "agent": 0})
        assert socket.receive_json() == {"type": "ack", "index": 2}
        socket.send_json({**frame, "agent": "x"})
        error = socket.receive_json()
        assert error["type"] == "error" and error["status"] == 422 and "frame: agent" in error["detail"]
        socket.send_json({**frame, "agent": True})
        assert socket.receive_json()["type"] == "error"
    with idle.websocket_connect(f"/api/sessions/{session_id}/stream") as socket:
        socket.send_json({"agent": -2})
        error = socket.receive_json()
        assert error["type"] == "error" and "header: agent" in error["detail"]
    # What the worker will read: (agent, frame) in arrival order, indices per agent.
    frames = idle.app.state.manager._get(session_id).frame_queue
    items = [frames.get(timeout=5) for _ in range(6)]
    assert [item.agent for item in items] == [0, 1, 1, 0, 1, 0]
    rows = [json.loads(line) for line in
            (idle.app.state.manager.session_dir(session_id) / "input" / "frames.jsonl").read_text().splitlines()]
    assert [(r["agent"], r["index"]) for r in rows] == [(0, 0), (1, 0), (1, 1), (0, 1), (1, 2), (0, 2)]
    assert rows[1]["color"] == "color/agent1_000000.png"


def test_worker_feeds_a_stream_as_one_agent_stream():
    from slam.runtime import AgentStream
    from server.upload import StreamFrame

    frame_queue, stop = queue.Queue(), threading.Event()
    rgb, depth = np.zeros((4, 5, 3), np.uint8), np.full((4, 5), 1000, np.uint16)
    for agent, stamp in ((0, 0.0), (1, 0.1), (1, 0.2), (0, 0.3)):
        frame_queue.put(StreamFrame(stamp, rgb, depth, 1000.0, np.eye(3), agent=agent))
    frame_queue.put(END_OF_STREAM)
    job = WorkerJob("000000000000", (SourceSpec(kind="stream"),), "test", "/tmp")
    sources = slam_sources(job, frame_queue, stop)
    assert len(sources) == 1 and isinstance(sources[0], AgentStream)
    got = list(sources[0])
    assert [(agent, frame.index, frame.timestamp) for agent, frame in got] == [
        (0, 0, 0.0), (1, 0, 0.1), (1, 1, 0.2), (0, 1, 0.3)]
    assert np.allclose(got[0][1].depth, 1.0), "raw depth / depth_scale = metres"
    stop.set()
    assert list(stream_frames(frame_queue, stop)) == [], "a stop request ends the stream"
    spec = SourceSpec(kind="synthetic", path=f"agents?agent=0&agents=2&frames=2&{TINY}")
    two = slam_sources(WorkerJob("000000000000", (spec, spec), "test", "/tmp"), None, stop)
    assert len(two) == 2 and len(two[1]) == 2


def test_a_live_stream_tracks_each_agents_newest_waiting_frame():
    """A camera's stream (``live``): of the frames waiting when the tracker reads, each agent's
    newest is tracked and the others are listed as passed over; indices still count every frame."""
    from server.upload import StreamFrame
    from server.worker import LIVE_SKIP_REASON

    frame_queue, stop = queue.Queue(), threading.Event()
    rgb, depth = np.zeros((4, 5, 3), np.uint8), np.full((4, 5), 1000, np.uint16)
    for agent, stamp in ((0, 0.0), (0, 0.1), (1, 0.2), (0, 0.3), (1, 0.4)):
        frame_queue.put(StreamFrame(stamp, rgb, depth, 1000.0, np.eye(3), agent=agent))
    frame_queue.put(END_OF_STREAM)
    source = slam_sources(WorkerJob("000000000000", (SourceSpec(kind="stream", live=True),), "test", "/tmp"),
                          frame_queue, stop)[0]
    got = [(agent, frame.index, frame.timestamp) for agent, frame in source]
    assert got == [(0, 2, 0.3), (1, 1, 0.4)]
    assert [(s.agent, s.index, s.reason) for s in source.skipped] == [
        (0, 0, LIVE_SKIP_REASON), (0, 1, LIVE_SKIP_REASON), (1, 0, LIVE_SKIP_REASON)]


# -- per-agent trajectories and status -----------------------------------------------------------

TUM_0 = "# timestamp tx ty tz qx qy qz qw\n0.000000 0 0 1 0 0 0 1\n0.033333 0.05 0 1 0 0 0 1\n"
TUM_1 = "# timestamp tx ty tz qx qy qz qw\n0.000000 2 1 1 0 0 0 1\n"


def fabricate_finished(data_dir, session_id: str, agents: int) -> None:
    """A finished session folder as a collaborative run leaves it (no run needed)."""
    folder = data_dir / "sessions" / session_id
    folder.mkdir(parents=True)
    spec = SourceSpec(kind="synthetic", path=f"agents?agent=0&agents={agents}&frames=2", format="synthetic")
    specs = tuple(SourceSpec(kind="synthetic", path=f"agents?agent={k}&agents={agents}&frames=2", format="synthetic")
                  for k in range(agents))
    status = SessionStatus(id=session_id, status="finished", created="2025-01-01T00:00:00+00:00",
                           source="synthetic", preset="test", frames_done=3, frames_total=3, maps=agents, loops=1,
                           agents=agents, spec=spec, specs=specs if agents > 1 else ())
    (folder / "session.json").write_text(json.dumps(status.to_json()))
    (folder / "trajectory.txt").write_text(TUM_0)
    if agents > 1:
        (folder / "trajectory_0.txt").write_text(TUM_0)
        (folder / "trajectory_1.txt").write_text(TUM_1)
    (folder / "run.json").write_text(json.dumps({
        "frames": 3, "maps": agents, "loops": 1, "loop_candidates_rejected": 0,
        "agents": [{"agent": k, "frames": 2 - k, "ate_rmse_m": None, "trajectory": f"trajectory_{k}.txt",
                    "joined": True} for k in range(agents)]}))


def test_trajectory_of_each_agent_from_a_finished_session(tmp_path, monkeypatch):
    monkeypatch.setattr(SessionManager, "_start_queued", lambda self: None)
    fabricate_finished(tmp_path, "aaaaaaaaaaa2", agents=2)
    fabricate_finished(tmp_path, "aaaaaaaaaaa1", agents=1)
    with running_app(tmp_path) as client:
        url = "/api/sessions/aaaaaaaaaaa2"
        assert client.get(f"{url}/trajectory").text == TUM_0
        assert client.get(f"{url}/trajectory", params={"agent": 0}).text == TUM_0
        assert client.get(f"{url}/trajectory", params={"agent": 1}).text == TUM_1
        missing = client.get(f"{url}/trajectory", params={"agent": 2})
        assert missing.status_code == 404 and "no agent 2" in detail(missing) and "2 agents" in detail(missing)
        assert client.get(f"{url}/trajectory", params={"agent": -1}).status_code == 422
        assert client.get(f"{url}/trajectory", params={"agent": "x"}).status_code == 422
        state = client.get(url).json()
        assert (state["agents"], state["maps"], state["loops"]) == (2, 2, 1)
        single = client.get("/api/sessions/aaaaaaaaaaa1/trajectory", params={"agent": 1})
        assert single.status_code == 404 and "one agent" in detail(single)
        assert client.get("/api/sessions/aaaaaaaaaaa1/trajectory", params={"agent": 0}).text == TUM_0


def T(x: float, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = [x, y, z]
    return out


def test_live_status_and_trajectories_follow_loop_corrections(idle):
    """Events as a running collaborative session sends them: per-agent trajectories while
    running, moved with their maps when a PosesUpdatedEvent comes; agents/maps/loops counted."""
    from slam.events import LoopEvent

    specs = [f"agents?agent={k}&agents=2&frames=4&{TINY}" for k in range(2)]
    session_id = idle.post("/api/sessions", json={"source": "synthetic", "spec": specs, "preset": "test"}).json()["id"]
    manager = idle.app.state.manager
    session = manager._get(session_id)
    K = np.eye(3)
    events = []
    for i in range(3):
        events.append(PoseEvent(0, i, 0.1 * i, T(0.1 * i), 0, True, None, K, (80, 60)))
        events.append(PoseEvent(1, i, 0.1 * i, T(0.0, 0.1 * i), 1, True, None, K, (80, 60)))
        if i == 0:  # a map placed after its first frame's pose: that frame moves with it
            events += [SubmapEvent(0, 0, np.eye(4), "start"), SubmapEvent(1, 1, T(3.0), "start")]
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    events.append(MapUpdateEvent(1, 1, T(3.0), 10, np.zeros((0, 4, 4)), tri,
                                 np.array([[0, 1, 2]], np.int32), np.full((3, 3), 200, np.uint8)))
    events.append(LoopEvent(1, 1, 2, 0.2, 0, 0, 0, 0.0, T(0.0, 0.2), np.eye(4), {"similarity": 0.9}))
    events.append(PosesUpdatedEvent({0: np.eye(4), 1: T(2.0, 1.0)}, {0: np.zeros((0, 4, 4)), 1: np.zeros((0, 4, 4))},
                                    {0: 0, 1: 1}, "loop"))
    for event in events:
        manager._apply(session, event)
    state = idle.get(f"/api/sessions/{session_id}").json()
    assert (state["agents"], state["maps"], state["loops"], state["frames_done"]) == (2, 2, 1, 6)

    from slam.eval.trajectory import parse_tum

    zero = parse_tum(idle.get(f"/api/sessions/{session_id}/trajectory").text)
    one = parse_tum(idle.get(f"/api/sessions/{session_id}/trajectory", params={"agent": 1}).text)
    assert np.allclose(zero.positions[:, 0], [0.0, 0.1, 0.2]), "map 0 did not move"
    assert np.allclose(one.positions, [[2.0, 1.0, 0], [2.0, 1.1, 0], [2.0, 1.2, 0]]), "moved with map 1"
    mesh = manager.live_meshes(session_id)[1]
    assert np.allclose(mesh[0], tri + [2, 1, 0]), "the live mesh moved with its map"
    absent = idle.get(f"/api/sessions/{session_id}/trajectory", params={"agent": 3})
    assert absent.status_code == 404 and "so far" in detail(absent)
    manager._apply(session, StatsEvent(6, 8, 2.0, 2, 2, 1, 10))
    assert idle.get(f"/api/sessions/{session_id}").json()["maps"] == 2


# -- end to end ----------------------------------------------------------------------------------

@needs_runtime
@pytest.mark.slow
def test_two_agent_synthetic_session_runs_to_the_end(tmp_path):
    """A real collaborative run: two agents of the synthetic 'agents' scene, the test preset."""
    from slam.eval.trajectory import parse_tum

    frames = 12
    specs = [f"agents?agent={k}&agents=2&frames={frames}&{TINY}" for k in range(2)]
    with running_app(tmp_path, max_sessions=1) as client:
        response = client.post("/api/sessions", json={"source": "synthetic", "spec": specs, "preset": "test"})
        assert response.status_code == 201, response.text
        session_id = response.json()["id"]
        state = wait_for(client, session_id, timeout=600)
        assert state["status"] == "finished", state
        assert state["agents"] == 2 and state["maps"] >= 2 and state["loops"] >= 0
        assert state["frames_done"] == 2 * frames
        url = f"/api/sessions/{session_id}"
        for agent in (0, 1):
            trajectory = parse_tum(client.get(f"{url}/trajectory", params={"agent": agent}).text)
            assert len(trajectory) == frames, agent
        assert client.get(f"{url}/trajectory", params={"agent": 2}).status_code == 404
        run = json.loads((tmp_path / "sessions" / session_id / "run.json").read_text())
        assert [a["agent"] for a in run["agents"]] == [0, 1]
        assert isinstance(run["loop_closures"], list)
        assert client.get(f"{url}/mesh").status_code == 200
        # Every map renders from the one map.pt: a view from agent 1's first pose.
        first = parse_tum(client.get(f"{url}/trajectory", params={"agent": 1}).text).poses[0]
        camera = {"T_world_cam": first.tolist(),
                  "intrinsics": {"fx": 60.0, "fy": 60.0, "cx": 40.0, "cy": 30.0, "width": 80, "height": 60}}
        render = client.post(f"{url}/render", json=camera, params={"output": "depth"})
        assert render.status_code == 200, render.text
        depth = cv2.imdecode(np.frombuffer(render.content, np.uint8), cv2.IMREAD_UNCHANGED)
        assert (depth > 0).mean() > 0.3, "agent 1's part of the map is rendered where it saw it"
        # AR over agent 1's own input frame (not agent 0's frame of the same number), at its
        # estimated pose: the default object sits on that camera's optical axis.
        objects = [{"shape": "cube", "scale": 0.05}]
        ar = client.post(f"{url}/ar", json={"background": "frame:3", "agent": 1, "objects": objects})
        assert ar.status_code == 200, ar.text
        placed = np.array(json.loads(ar.headers["X-AR-Objects"])[0]["position"])
        T = parse_tum(client.get(f"{url}/trajectory", params={"agent": 1}).text).poses[3]  # with the final corrections
        assert float(np.linalg.norm(np.cross(placed - T[:3, 3], T[:3, 2]))) < 0.03
        composite = cv2.cvtColor(cv2.imdecode(np.frombuffer(ar.content, np.uint8), cv2.IMREAD_COLOR),
                                 cv2.COLOR_BGR2RGB).astype(np.float64) / 255

        def background_error(agent: int) -> float:  # the cube covers a few pixels only
            from slam.data import open_sequence

            frame = open_sequence(f"synthetic:{specs[agent]}")[3]
            return float(np.median(np.abs(composite - frame.rgb)))

        assert background_error(1) < 0.02 < background_error(0), (background_error(1), background_error(0))
        missing = client.post(f"{url}/ar", json={"background": "frame:3", "agent": 2, "objects": objects})
        assert missing.status_code == 404 and "agent 2 does not exist" in missing.json()["detail"], missing.text


@needs_runtime
@pytest.mark.slow
def test_two_agent_stream_runs_to_the_end(tmp_path):
    """A live stream whose frames name their agent (the worker's AgentStream), interleaved."""
    from slam.data import open_sequence
    from slam.eval.trajectory import parse_tum

    frames = 6
    sequences = [open_sequence(f"synthetic:agents?agent={k}&agents=2&frames={frames}&{TINY}") for k in range(2)]
    with running_app(tmp_path, max_sessions=1) as client:
        session_id = client.post("/api/sessions", json={"source": "stream", "preset": "test",
                                                        "depth_scale": 5000}).json()["id"]
        for i in range(frames):
            for agent, sequence in enumerate(sequences):
                frame = sequence[i]
                bgr = cv2.cvtColor(np.round(frame.rgb * 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
                K = frame.K
                response = client.post(
                    f"/api/sessions/{session_id}/frames",
                    files={"color": ("c.png", png(bgr), "image/png"),
                           "depth": ("d.png", png(np.round(frame.depth * 5000).astype(np.uint16)), "image/png")},
                    data={"timestamp": str(100 * agent + frame.timestamp), "agent": str(agent),
                          **({"intrinsics": f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}"} if i == 0 else {})})
                assert response.status_code == 200, response.text
                assert response.json()["index"] == i
        assert client.post(f"/api/sessions/{session_id}/finish").json() == {"frames": 2 * frames}
        state = wait_for(client, session_id, timeout=600)
        assert state["status"] == "finished", state
        assert state["agents"] == 2 and state["frames_done"] == 2 * frames
        for agent, sequence in enumerate(sequences):
            trajectory = parse_tum(client.get(f"/api/sessions/{session_id}/trajectory", params={"agent": agent}).text)
            assert np.allclose(trajectory.timestamps, [100 * agent + f.timestamp for f in sequence], atol=1e-6)
        assert client.get(f"/api/sessions/{session_id}/trajectory", params={"agent": 2}).status_code == 404


def test_only_a_stream_can_be_live_and_its_job_says_so(idle):
    refused = idle.post("/api/sessions", json={"source": "synthetic", "live": True, "preset": "test"})
    assert refused.status_code == 422 and "only a stream" in detail(refused)
    session_id = idle.post("/api/sessions", json={"source": "stream", "live": True, "preset": "test"}).json()["id"]
    state = idle.app.state.manager._get(session_id).status
    assert state.spec.kind == "stream" and state.spec.live
    plain = idle.post("/api/sessions", json={"source": "stream", "preset": "test"}).json()["id"]
    assert not idle.app.state.manager._get(plain).status.spec.live
