"""The one fold of a session's events (``server.session_state``) and the status fold on it
(``server.session_status``): plain data, no viser, no server, no worker."""

from __future__ import annotations

import numpy as np

from server.session_state import Change, SessionState
from server.session_status import SessionStatus, StatusFold
from server.tracks import MapPlacements
from server.worker import SourceSpec
from slam.events import (
    FinishedEvent,
    KeyframeEvent,
    LoopEvent,
    MapUpdateEvent,
    PhaseEvent,
    PoseEvent,
    PosesUpdatedEvent,
    StatsEvent,
    SubmapEvent,
)


def T(x: float = 0.0, y: float = 0.0, z: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    out = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    out[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    out[:3, 3] = [x, y, z]
    return out


def pose(agent: int, index: int, map_id: int, T_map_cam: np.ndarray) -> PoseEvent:
    return PoseEvent(agent, index, index / 30, T_map_cam, map_id, True, None, np.eye(3), (80, 60))


def test_placement_rule():
    maps = MapPlacements()
    assert np.allclose(maps.T_world_map(3), np.eye(4)), "identity until placed"
    assert maps.set(3, np.eye(4)) is False, "placed where it was assumed: nothing moves"
    assert maps.set(3, T(1.0, yaw=0.4)) is True
    assert maps.set(3, T(1.0, yaw=0.4)) is False
    assert np.allclose(maps.to_world(3, T(0.5)), T(1.0, yaw=0.4) @ T(0.5))
    assert np.allclose(maps.point_to_world(3, [1.0, 0.0, 0.0]), (T(1.0, yaw=0.4) @ T(1.0))[:3, 3])


def test_everything_in_a_map_follows_its_placement():
    state = SessionState()
    T1 = T(2.0, 1.0, yaw=0.5)
    change = state.apply(SubmapEvent(1, 0, T1, "start"))
    assert change.moved == {1} and change.submap == 1
    state.apply(pose(0, 0, 1, T(0.1)))
    state.apply(KeyframeEvent(0, 0, 1, T(0.1)))
    assert np.allclose(state.tracks.world_pose(0, 0), T1 @ T(0.1)), "placed by its map"
    assert np.allclose(state.keyframe_poses(1)[0], T(0.1)), "the keyframe is kept in the map frame"

    T1_new = T(2.0, 1.5, yaw=0.5)
    change = state.apply(PosesUpdatedEvent({1: T1_new}, {}, {1: 0}, "loop"))
    assert change.moved == {1}
    assert np.allclose(state.tracks.world_pose(0, 0), T1_new @ T(0.1)), "moved with its map"
    state.apply(pose(0, 1, 1, T(0.2)))
    assert np.allclose(state.tracks.world_positions(0)[1], (T1_new @ T(0.2))[:3, 3])
    assert state.tracks.agents_in({1}) == {0} and state.tracks.agents_in({0}) == set()


def test_a_pose_before_its_map_is_placed_moves_with_the_placement():
    state = SessionState()
    state.apply(pose(0, 0, 2, T(0.1)))
    assert np.allclose(state.tracks.world_pose(0, 0), T(0.1)), "an unplaced map sits at the identity"
    change = state.apply(SubmapEvent(2, 0, T(3.0), "region"))
    assert change.moved == {2}
    assert np.allclose(state.tracks.world_pose(0, 0), T(3.1))


def test_retracked_frame_keeps_its_place_in_arrival_order():
    state = SessionState()
    for i in (0, 1, 2):
        assert state.apply(pose(0, i, 0, T(0.1 * i))).retracked_slot is None
    change = state.apply(pose(0, 1, 0, T(5.0)))
    assert change.frame == (0, 1) and change.retracked_slot == 1
    assert len(state.tracks) == 3
    assert np.allclose(state.tracks.world_positions(0)[:, 0], [0.0, 5.0, 0.2])
    assert np.allclose(state.camera_pose(0), T(5.0)), "the newest pose is the camera"


def test_meshes_are_kept_in_the_map_frame_and_follow_it():
    state = SessionState(keep_meshes=True)
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    change = state.apply(MapUpdateEvent(0, 1, T(3.0), 10, np.zeros((0, 4, 4)), tri,
                                        np.array([[0, 1, 2]], np.int32), None))
    assert change.mesh is not None and change.mesh[0] == 0
    assert np.allclose(change.mesh[1].vertices, tri), "map frame"
    assert np.allclose(state.world_mesh(0)[0], tri + [3, 0, 0])
    state.apply(PosesUpdatedEvent({0: T(2.0, 1.0)}, {}, {0: 0}, "refinement"))
    vertices, faces, _ = state.world_mesh(0)
    assert vertices.dtype == np.float32 and np.allclose(vertices, tri + [2, 1, 0])
    change = state.apply(MapUpdateEvent(0, 2, T(2.0, 1.0), 10, np.zeros((0, 4, 4)), np.zeros((0, 3), np.float32),
                                        np.zeros((0, 3), np.int32), None))
    assert change.mesh is not None and len(change.mesh[1].faces) == 0, "an empty mesh is a change"
    assert len(state.meshes[0].faces) == 1, "but the kept mesh is the last non-empty one"
    assert state.meshes[0].vertices.dtype == np.float32
    assert SessionState(keep_meshes=False).meshes == {}


def test_loop_ends_follow_their_frames_or_their_maps():
    state = SessionState()
    state.apply(SubmapEvent(0, 0, np.eye(4), "start"))
    state.apply(SubmapEvent(1, 0, T(1.0), "tracking_failure"))
    state.apply(pose(0, 3, 0, T(0.2)))
    change = state.apply(LoopEvent(0, 1, 40, 1.3, 0, 0, 3, 0.1, T(0.5, 0.5), T(9.0), {}))
    assert change.loop and change.maps == {0, 1} and state.loop_events == 1
    assert np.allclose(state.loop_points()[0], [[1.5, 0.5, 0], [0.2, 0, 0]]), "a seen frame wins over the event"
    state.apply(PosesUpdatedEvent({0: np.eye(4), 1: T(1.0, 2.0)}, {}, {0: 0, 1: 0}, "refinement"))
    assert np.allclose(state.loop_points()[0, 0], [1.5, 2.5, 0]), "moved with its map"
    assert state.reasons == {0: "start", 1: "tracking_failure"}


def test_keyframes_replaced_by_map_updates_and_pose_updates():
    state = SessionState()
    state.apply(SubmapEvent(0, 0, T(1.0), "start"))
    change = state.apply(KeyframeEvent(0, 0, 0, T(0.5)))
    assert change.keyframe and change.keyframes == {0} and state.keyframe_events == 1
    assert np.allclose(state.keyframe_poses(0)[0], T(0.5))
    change = state.apply(MapUpdateEvent(0, 1, T(1.0), 5, np.stack([T(0.2), T(0.4)])))
    assert change.keyframes == {0} and not change.keyframe and change.mesh is None
    assert np.allclose(state.keyframe_poses(0)[:, 0, 3], [0.2, 0.4])
    state.apply(PosesUpdatedEvent({0: T(2.0)}, {0: np.stack([T(0.3)])}, {0: 0}, "loop"))
    assert np.allclose(state.keyframe_poses(0)[:, 0, 3], [0.3])


def test_stats_phase_and_end_are_recorded_and_other_objects_ignored():
    state = SessionState()
    assert state.apply(object()) == Change(), "not a runtime event: nothing changes"
    stats = StatsEvent(5, 10, 2.0, 1, 1, 0, 100)
    assert state.apply(stats).stats is stats and state.stats is stats
    assert state.apply(PhaseEvent("refining")).phase == "refining"
    end = FinishedEvent("finished")
    assert state.apply(end).finished is end and state.finished is end


def status() -> SessionStatus:
    return SessionStatus(id="cccccccccccc", status="running", created="2026-01-01T00:00:00+00:00", source="x",
                         preset="test", spec=SourceSpec(kind="synthetic"))


def test_status_fold_counts_and_frames_per_second():
    fold = StatusFold()
    state = status()
    step = fold.apply(state, PhaseEvent("tracking"), now=100.0)
    assert step.persist and step.status.phase == "tracking" and fold.tracking_started == 100.0
    state = step.status
    for i in range(4):
        step = fold.apply(state, pose(1, i, 1, T(0.1 * i)), now=101.0 + i * 0.1)
        assert step.dirty and not step.persist
        state = step.status
    assert (state.frames_done, state.agents) == (4, 2)
    assert state.fps == round(4 / 1.3, 3)
    assert fold.fps_samples[0] == (1.0, 1) and fold.fps_samples[-1] == (1.3, 4)
    state = fold.apply(state, SubmapEvent(1, 1, np.eye(4), "start"), now=102.0).status
    state = fold.apply(state, KeyframeEvent(1, 0, 1, np.eye(4)), now=102.0).status
    state = fold.apply(state, LoopEvent(1, 1, 2, 0.2, 1, 1, 0, 0.0, np.eye(4), np.eye(4)), now=102.0).status
    assert (state.maps, state.keyframes, state.loops) == (1, 1, 1)
    step = fold.apply(state, StatsEvent(4, 8, 99.0, 0, 0, 0, 10, ate_rmse=0.01234567), now=102.0)
    assert step.event.fps == state.fps, "the sinks get the status's frames/s, not the worker's"
    assert (step.status.keyframes, step.status.maps, step.status.loops) == (1, 1, 1), "counted events stay"
    assert step.status.ate_rmse_m == 0.012346 and step.status.frames_total == 8


def test_status_fold_phase_budget_and_end():
    fold = StatusFold()
    step = fold.apply(status(), PhaseEvent("refining"), started_at=0.0, now=100.0)
    assert step.status.phase == "refining" and step.persist
    assert step.status.phase_budget_s is None or step.status.phase_budget_s > 0
    assert fold.apply(status(), PhaseEvent("nonsense")).status.phase == "queued", "unknown phases are ignored"
    step = fold.apply(status(), FinishedEvent("failed", "boom"))
    assert step.finished == FinishedEvent("failed", "boom") and not step.dirty
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    fold.apply(status(), MapUpdateEvent(2, 1, T(1.0), 1, np.zeros((0, 4, 4)), tri,
                                        np.array([[0, 1, 2]], np.int32), None))
    assert np.allclose(fold.live_meshes()[2][0], tri + [1, 0, 0])


def test_the_folds_do_not_import_viser_or_the_web_stack():
    import subprocess
    import sys
    from pathlib import Path

    code = ("import sys, server.session_status, server.viewer_state; "
            "print(sorted(m for m in ('viser', 'fastapi', 'uvicorn') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[1])
    assert out.stdout.strip() == "[]"


def test_how_a_run_ends():
    from server.session_status import run_end
    from server.worker import WorkerDone

    def crash() -> str:
        return "exit code -9"

    failed = WorkerDone("failed", "out of memory")
    finished = WorkerDone("finished", None)
    stopping = ("failed", "interrupted: the server stopped")
    assert run_end(None, stopping, False, None, crash) == stopping
    assert run_end(finished, stopping, False, None, crash) == stopping, "its answer to the stop"
    assert run_end(failed, stopping, True, None, crash) == ("failed", "out of memory"), "a failure wins"
    assert run_end(finished, None, True, None, crash) == ("cancelled", None)
    assert run_end(finished, None, False, None, crash) == ("finished", None)
    assert run_end(None, None, False, "killed", crash) == ("cancelled", "killed")
    assert run_end(None, None, False, None, crash) == ("failed", "exit code -9")


def test_worker_totals_keep_the_status_fps():
    from server.session_status import with_worker_totals
    from server.worker import WorkerDone

    state = status()
    assert with_worker_totals(state, None) is state
    assert with_worker_totals(state, WorkerDone("finished", None)) is state, "no frames: nothing to take"
    done = WorkerDone("finished", None, frames=9, keyframes=3, maps=2, loops=1, fps=7.123456, agents=2,
                      ate_rmse=0.05)
    total = with_worker_totals(state, done)
    assert (total.frames_done, total.keyframes, total.maps, total.loops, total.agents) == (9, 3, 2, 1, 2)
    assert total.fps == 7.123 and total.ate_rmse_m == 0.05
    from dataclasses import replace

    assert with_worker_totals(replace(state, fps=2.5), done).fps == 2.5


def test_settling_a_folder_without_outputs(tmp_path):
    import json

    from server.session_store import read_progress, settle_outputs, write_progress, write_status

    ended = SessionStatus(id="cccccccccccc", status="failed", created="x", source="x", preset="test",
                          keyframes=4, error="boom")
    settled = settle_outputs(tmp_path, ended, frames_refused=2)
    assert (settled.frames_done, settled.keyframes, settled.frames_skipped) == (0, 0, 2)
    run = json.loads((tmp_path / "run.json").read_text())
    assert (run["status"], run["error"], run["frames"]) == ("failed", "boom", 0)
    assert settle_outputs(tmp_path / "gone", ended) is ended
    write_status(tmp_path, settled)
    assert SessionStatus.from_json(json.loads((tmp_path / "session.json").read_text())) == settled
    assert read_progress(tmp_path) == []
    write_progress(tmp_path, [(0.5, 3), (1.0, 7)])
    assert read_progress(tmp_path) == [(0.5, 3), (1.0, 7)]
