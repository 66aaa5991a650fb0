"""Honest progress at the end of a run, and a stream's frames on the page.

Every end-of-run step (final bundle adjustment, re-tracking, fine colour fit, map and mesh,
outputs) is announced by its own PhaseEvent with its own estimate; the status names the step
and times it from the step's start; the page's text (``static/status-text.js``, run under node)
never shows an elapsed time past a bound. A stream's sent / dropped / tracked frames are in
the status while it runs and after it ended."""

from __future__ import annotations

import json
import shutil
import subprocess
from dataclasses import replace
from pathlib import Path

import pytest

from server.session_status import SessionStatus, StatusFold, stream_fields, with_stream_counts
from server.worker import SourceSpec
from slam.events import END_STEPS, PhaseEvent
from tests.test_server_api import needs_runtime

ROOT = Path(__file__).resolve().parent.parent
NODE = shutil.which("node")


def status(**fields) -> SessionStatus:
    base = SessionStatus(id="s", status="running", created="2025-01-01T00:00:00+00:00", source="x", preset="test")
    return replace(base, **fields)


# ------------------------------------------------------------ the status fold
def test_each_end_of_run_step_restarts_the_clock_with_its_own_estimate():
    fold, state = StatusFold(), status(phase="tracking")
    state = fold.apply(state, PhaseEvent("refining"), now=10.0).status
    assert (state.phase, state.phase_step, state.phase_estimate_s) == ("refining", None, None)
    step = fold.apply(state, PhaseEvent("refining", "bundle_adjustment", 41.54), now=11.0)
    assert step.persist, "a step change is written at once (the page reads it after a restart too)"
    state = step.status
    assert (state.phase_step, state.phase_estimate_s, state.phase_budget_s) == ("bundle_adjustment", 41.5, None)
    state = fold.apply(state, PhaseEvent("refining", "colour_fit"), now=50.0).status
    assert (state.phase_step, state.phase_estimate_s) == ("colour_fit", None), \
        "the colour fit is not bound by the bundle adjustment's cap"
    state = fold.apply(state, PhaseEvent("writing", "outputs"), now=60.0).status
    assert (state.phase, state.phase_step) == ("writing", "outputs")


def test_an_old_session_json_still_loads():
    data = status().to_json()
    for key in ("phase_step", "phase_estimate_s", "frames_received", "frames_dropped"):
        data.pop(key)
    data["phase_budget_s"] = 12.0
    loaded = SessionStatus.from_json(data)
    assert loaded.phase_step is None and loaded.frames_received is None


# ------------------------------------------------------------ the runtime's events
def test_the_runtime_announces_every_end_of_run_step_in_order(tmp_path):
    """A tiny run with the re-tracking on: the bundle adjustment (with its time cap as the
    estimate), the re-tracking (a forecast), the mesh and the outputs, in that order."""
    import torch

    from slam.config import preset
    from slam.data import open_sequence
    from slam.runtime import run_slam

    base = preset("test")
    cfg = replace(base, mapping=replace(base.mapping, iterations=1, first_frame_iterations=30, final_iterations=3,
                                        final_time_share=0.1, final_min_seconds=2.0),
                  tracking=replace(base.tracking, iterations=2, retrack_iterations=1),
                  mesh=replace(base.mesh, resolution=2, update_every_keyframes=100),
                  runtime=replace(base.runtime, processes=False))
    events: list = []
    threads = torch.get_num_threads()
    try:
        run_slam([list(open_sequence("synthetic:orbit?frames=100&width=80&height=60", max_frames=3))], cfg,
                 tmp_path, on_event=events.append)
    finally:
        torch.set_num_threads(threads)
    steps = [(e.phase, e.step, e.estimate_s) for e in events if isinstance(e, PhaseEvent) and e.step]
    names = [s for _, s, _ in steps]
    assert names == [s for s in END_STEPS if s in names], f"steps out of order: {names}"
    assert {"bundle_adjustment", "retracking", "mesh", "outputs"} <= set(names), names
    estimates = {s: e for _, s, e in steps}
    assert estimates["bundle_adjustment"] >= 2.0, "the bundle adjustment's estimate is its time cap"
    assert estimates["retracking"] is not None and estimates["retracking"] >= 0
    assert steps[-1][:2] == ("writing", "outputs")


# ------------------------------------------------------------ the page's text
def page_text(statuses: list[dict]) -> list[dict]:
    """static/status-text.js's phase text, progress and description of each status, under node."""
    script = (f"const T = require({json.dumps(str(ROOT / 'static' / 'status-text.js'))});"
              f"const all = {json.dumps(statuses)};"
              "console.log(JSON.stringify(all.map((s) => ({phase: T.phase(s), progress: T.progress(s), "
              "describe: T.describe(s)}))));")
    out = subprocess.run([NODE, "-e", script], capture_output=True, text=True, timeout=30, check=True)
    return json.loads(out.stdout)


PAGE_BASE = {"status": "running", "frames_done": 290, "frames_total": None, "fps": 3.0, "keyframes": 4,
             "maps": 1, "loops": 0, "agents": 1, "ate_rmse_m": None}


@pytest.mark.skipif(NODE is None, reason="node is not installed")
def test_the_page_never_shows_an_elapsed_time_past_its_bound():
    cases = [
        {**PAGE_BASE, "phase": "refining", "phase_step": "bundle_adjustment", "phase_elapsed_s": 5,
         "phase_estimate_s": 10},
        {**PAGE_BASE, "phase": "refining", "phase_step": "bundle_adjustment", "phase_elapsed_s": 34,
         "phase_estimate_s": 10},
        {**PAGE_BASE, "phase": "refining", "phase_step": "colour_fit", "phase_elapsed_s": 110,
         "phase_estimate_s": None},
        {**PAGE_BASE, "phase": "writing", "phase_step": "outputs", "phase_elapsed_s": 2, "phase_estimate_s": None},
    ]
    within, over, unbounded, writing = page_text(cases)
    assert within["phase"] == "refining: final bundle adjustment · 0:05 of about 0:10"
    assert within["progress"] == {"max": 10, "value": 5}
    assert "0:34" in over["phase"] and "of about" not in over["phase"] and "at most" not in over["phase"]
    assert "longer than its estimate" in over["phase"]
    assert over["progress"] == {}, "past its estimate the bar runs (indeterminate)"
    assert unbounded["phase"] == "refining: fitting the fine colour · 1:50"
    assert writing["phase"].startswith("writing trajectories and run.json")


@pytest.mark.skipif(NODE is None, reason="node is not installed")
def test_the_page_shows_a_streams_sent_dropped_and_tracked_frames():
    stream, upload = page_text([{**PAGE_BASE, "phase": "tracking", "frames_sent": 300, "frames_received": 290,
                                 "frames_dropped": 10},
                                {**PAGE_BASE, "phase": "tracking", "frames_total": 400}])
    assert stream["describe"].startswith("300 sent · 10 dropped · 290 tracked")
    assert upload["describe"].startswith("290 / 400 frames")


@pytest.mark.skipif(NODE is None, reason="node is not installed")
def test_the_page_says_when_colour_was_registered():
    from server.session_store import describe_color_camera

    estimated = {"source": "estimated", "scale": 0.9, "shift_x": 4.2, "shift_y": -0.8, "confidence": 0.67,
                 "applied": True, "reason": "edges 44% closer than identity"}
    texts = [describe_color_camera({"color_cameras": [c]}) for c in
             (estimated, {**estimated, "applied": False}, {"source": "given", "width": 640, "height": 480})]
    assert texts[0].startswith("estimated from the data (scale 0.900, shift +4.2, -0.8 px") and ": applied" in texts[0]
    assert ": not applied" in texts[1] and texts[2].startswith("given: 640x480")
    assert describe_color_camera({}) is None and describe_color_camera({"color_cameras": [None]}) is None
    applied, left, given, none = page_text([{**PAGE_BASE, "phase": "done", "color_camera": t}
                                            for t in (*texts, None)])
    assert applied["describe"].endswith("colour registered (camera estimated from the data)")
    assert "colour" not in left["describe"] and "colour" not in none["describe"]
    assert given["describe"].endswith("colour registered (given camera)")


# ------------------------------------------------------------ a stream's counts
class FakeStream:
    frames_received, frames_dropped, frames_refused = 290, 10, 1


def test_a_streams_counts_come_live_then_from_the_kept_status():
    spec = SourceSpec(kind="stream")
    live = stream_fields(status(spec=spec), FakeStream())
    assert live == {"frames_received": 290, "frames_dropped": 10, "frames_sent": 301}
    ended = with_stream_counts(status(spec=spec, status="finished", frames_skipped=1), FakeStream())
    reloaded = SessionStatus.from_json(json.loads(json.dumps(ended.to_json())))
    assert stream_fields(reloaded, None) == live, "an ended stream keeps its counts (session.json)"
    assert stream_fields(status(), None) == {}, "an upload has none"


# ------------------------------------------------------------ a stream's ground truth
def test_a_streams_ground_truth_rides_on_the_frames_at_its_times(tmp_path):
    import queue

    import numpy as np

    from server.stream import StreamInput
    from server.upload import UploadError
    from tests.test_server_stream import encoded_frames, k_text

    frames = encoded_frames(3)
    stream = StreamInput(queue.Queue(maxsize=8), tmp_path, intrinsics=None, depth_scale=5000.0, put_timeout_s=1.0)
    T = np.eye(4)
    T[:3, 3] = (1.0, 2.0, 3.0)
    rows = [[frames[1][0] + 0.005, *T[:3].reshape(-1)], [frames[0][0], *np.eye(4)[:3].reshape(-1)]]
    assert stream.set_ground_truth(rows) == 2
    for stamp, color, depth, K in frames:
        stream.add_frame(color, depth, timestamp=stamp, intrinsics=k_text(K))
    queued = [stream.frame_queue.get_nowait() for _ in frames]
    assert np.allclose(queued[0].T_world_cam, np.eye(4))
    assert np.allclose(queued[1].T_world_cam, T), "the nearest row within 20 ms"
    assert queued[2].T_world_cam is None, "no row near its time"
    for bad in ([], [[1.0, 2.0]], [[float("nan")] * 13], "rows", [["a"] * 13]):
        with pytest.raises(UploadError):
            stream.set_ground_truth(bad)


def test_the_client_sends_a_folders_ground_truth_as_rows():
    import numpy as np

    from client.stream import ground_truth_rows

    T = np.eye(4)
    T[:3, 3] = (0.5, 0.0, 1.0)

    class Folder:
        class sequence:
            timestamps = [10.0, 10.033]
            gt_poses = [T, None]

    rows = ground_truth_rows(Folder())
    assert rows == [[10.0, 1.0, 0.0, 0.0, 0.5, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0]]
    assert ground_truth_rows(object()) == [], "a camera has none"


@needs_runtime
def test_a_stream_with_ground_truth_reports_its_ate_and_its_frames(tmp_path):
    """Over the WebSocket: the ground truth once, then the frames; the session's status has
    the ATE (as an upload's) and the frames sent, dropped and tracked."""
    from slam.data import open_sequence
    from tests.test_server_api import running_app, wait_for
    from tests.test_server_stream import binary_message, encoded_frames, k_text

    count = 8
    truth = [[f.timestamp, *f.T_world_cam[:3].reshape(-1).tolist()]
             for f in open_sequence(f"synthetic:orbit?frames={count}&width=160&height=120&seed=0")]
    frames = encoded_frames(count)
    with running_app(tmp_path, max_sessions=1) as client:
        session_id = client.post("/api/sessions", json={"source": "stream", "preset": "test",
                                                         "intrinsics": k_text(frames[0][3]),
                                                         "depth_scale": 5000}).json()["id"]
        with client.websocket_connect(f"/api/sessions/{session_id}/stream") as socket:
            socket.send_json({})
            assert socket.receive_json()["type"] == "ready"
            socket.send_json({"type": "ground_truth", "poses": truth})
            assert socket.receive_json() == {"type": "ground_truth", "poses": count}
            for stamp, color, depth, _ in frames:
                socket.send_bytes(binary_message(stamp, color, depth))
                assert socket.receive_json()["type"] == "ack"
            socket.send_json({"type": "finish"})
            assert socket.receive_json()["type"] == "finished"
        state = wait_for(client, session_id)
        assert state["status"] == "finished", state["error"]
        assert (state["frames_sent"], state["frames_received"], state["frames_dropped"]) == (count, count, 0)
        assert state["frames_done"] == count
        assert state["ate_rmse_m"] is not None and state["ate_rmse_m"] < 0.5


# ------------------------------------------------------------ the viewer
def test_the_live_frustum_is_scaled_to_the_scene():
    import numpy as np

    from server.viewer_state import FRUSTUM_MAX_M, frustum_scale

    still = frustum_scale((np.zeros(3), np.full(3, 0.01)))  # a live camera that barely moved
    assert still <= 0.05, "framed at MIN_FRAME_RADIUS_M, it must not fill the view"
    assert frustum_scale((np.zeros(3), np.full(3, 4.0))) == FRUSTUM_MAX_M, "a room keeps the usual size"
    assert frustum_scale(None) == still


def test_the_camera_path_is_not_drawn_in_a_trajectorys_colours():
    import numpy as np

    from server.viewer_scene import PATH_COLOR
    from server.viewer_state import LOOP_COLOR, agent_color, map_color

    taken = [agent_color(a) for a in range(8)] + [map_color(m) for m in range(4)] + [LOOP_COLOR]
    distance = min(float(np.linalg.norm(np.subtract(PATH_COLOR, c))) for c in taken)
    assert distance > 60, f"the path's colour {PATH_COLOR} is too close to a trajectory's, map's or loop's"
