"""The SLAM runtime (slam.runtime.run_slam) end to end on a tiny synthetic sequence.

The `test` preset is shrunk further (1 mapping iteration per frame, 2 tracking iterations,
coarse meshes) so that a run is about a second in one process; the process-mode run pays
~10 s for spawning the mapper (importing torch there). Outputs and events are checked for
both modes from one run each.
"""

from __future__ import annotations

import json
import multiprocessing
import threading
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

import slam.outputs as outputs
import slam.runtime as runtime
from slam.checkpoint import load_checkpoint
from slam.config import ConfigError, SLAMConfig, apply_overrides, preset
from slam.data import DataError, open_sequence
from slam.data.frame import Frame
from slam.eval.trajectory import read_tum
from slam.events import FinishedEvent, KeyframeEvent, MapUpdateEvent, PhaseEvent, PoseEvent, StatsEvent, SubmapEvent
from slam.runtime import run_slam

NUM_FRAMES = 4
SPEC = "synthetic:orbit?frames=100&width=80&height=60"
_BASE = preset("test")
FAST = replace(
    _BASE,
    # 30 first-frame iterations are the fewest that reliably give a non-empty mesh here.
    mapping=replace(_BASE.mapping, iterations=1, first_frame_iterations=30),
    tracking=replace(_BASE.tracking, iterations=2),
    mesh=replace(_BASE.mesh, resolution=2, update_every_keyframes=100),
)
# Runs that only test failure handling need no usable map.
FAILING = replace(FAST, mapping=replace(FAST.mapping, first_frame_iterations=2))
# No run may hang: the process-mode ones take ~15 s on a quiet 2-core machine.
pytestmark = pytest.mark.timeout(180)


def config(processes: bool, base=FAST):
    return replace(base, runtime=replace(base.runtime, processes=processes))


@pytest.fixture(scope="module", autouse=True)
def single_thread():
    """One torch thread in this process. run_slam sets torch's thread count to every core in
    single-process mode; on this loaded 2-core machine that made runs several times slower,
    so the setter is disabled here (the mapping process still sets its own)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    patch = pytest.MonkeyPatch()
    patch.setattr(runtime, "process_threads", lambda device, processes: None)
    yield
    patch.undo()
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(open_sequence(SPEC, max_frames=NUM_FRAMES))


def mapping_children() -> list:
    return [p for p in multiprocessing.active_children() if p.name == "voxfusion-mapping"]


@dataclass
class Run:
    result: runtime.RunResult
    events: list
    out: Path
    info: dict
    config: SLAMConfig


def do_run(sources, cfg, out: Path, **kwargs) -> Run:
    events: list = []
    result = run_slam(sources, cfg, out, on_event=events.append, **kwargs)
    return Run(result, events, out, json.loads((out / "run.json").read_text()), cfg)


@pytest.fixture(scope="module", params=[True, False], ids=["processes", "single-process"])
def run(request, frames, tmp_path_factory) -> Run:
    out = tmp_path_factory.mktemp("run")
    done = do_run([frames], config(request.param), out)
    assert not mapping_children(), "the mapping process must be gone when run_slam returns"
    return done


# ------------------------------------------------------------ normal runs
def test_run_finishes_and_writes_every_output(run, frames):
    assert run.result.status == "finished" and run.result.error is None, run.result.error
    assert run.result.frames == NUM_FRAMES
    for name in ("trajectory.txt", "mesh.ply", "map.pt", "run.json"):
        assert (run.out / name).is_file(), name


def test_trajectory_has_the_input_timestamps(run, frames):
    traj = read_tum(run.out / "trajectory.txt")
    np.testing.assert_allclose(traj.timestamps, [f.timestamp for f in frames], atol=1e-6)
    assert traj.poses.shape == (NUM_FRAMES, 4, 4)
    # The world is the first camera's frame, ground truth or not (issue 44 item 6).
    np.testing.assert_allclose(traj.poses[0], np.eye(4), atol=1e-6)


def test_mesh_has_vertex_colours_in_the_world_frame(run, frames):
    mesh = trimesh.load(run.out / "mesh.ply", force="mesh")
    assert len(mesh.vertices) > 100 and len(mesh.faces) > 100
    colors = np.asarray(mesh.visual.vertex_colors)
    assert colors.shape == (len(mesh.vertices), 4) and colors.dtype == np.uint8
    # Colours come from the colour head, not a default: after this short a run (30 iterations
    # on the first frame) the head has learnt the scene's mean colour but little detail, so
    # a count of distinct colours (1-4 here) would test the training's luck, not the mesh.
    observed = np.concatenate([f.rgb.reshape(-1, 3) for f in frames]).astype(np.float64)
    observed *= 255.0 if observed.max() <= 1.0 else 1.0
    assert np.abs(colors[:, :3].mean(axis=0) - observed.mean(axis=0)).max() < 40, "the scene's mean colour"
    assert not (colors[:, :3] == [102, 102, 102]).all(), "not trimesh's default grey"
    # Every vertex lies in the world-frame box of the frames' back-projected depth, grown by
    # two voxels (allocation covers depth +- tr rounded out to whole voxels). The run's world is
    # its first camera's frame: the GT poses are moved into it.
    T_run_gt = read_tum(run.out / "trajectory.txt").poses[0] @ np.linalg.inv(frames[0].T_world_cam)
    pts = []
    for f in frames:
        v, u = np.nonzero(f.depth > 0)
        cam = np.linalg.inv(f.K) @ np.stack([u, v, np.ones_like(u)]) * f.depth[v, u]
        T = T_run_gt @ f.T_world_cam
        pts.append((T[:3, :3] @ cam).T + T[:3, 3])
    pts = np.concatenate(pts)
    margin = 2 * FAST.voxel.voxel_size
    assert bool((mesh.vertices > pts.min(0) - margin).all()) and bool((mesh.vertices < pts.max(0) + margin).all())


def test_map_checkpoint_loads_and_matches_run_json(run):
    mapset = load_checkpoint(run.out / "map.pt")
    assert len(mapset.maps) == 1 == run.info["maps"]
    assert mapset.num_voxels() == run.info["voxels"] > 0
    assert mapset.num_keyframes() == run.info["keyframes"] == run.result.keyframes >= 1
    assert mapset.config == run.config


def test_phases_and_final_ate_are_reported(run):
    """A client can tell tracking from the final refinement and the writing of outputs (they
    take minutes on a long run with nothing else to say), and reads the ATE in the last stats."""
    phases = [e.phase for e in run.events if isinstance(e, PhaseEvent)]
    # Each end-of-run step repeats its phase (tests/test_progress_and_streams.py).
    assert [p for i, p in enumerate(phases) if i == 0 or phases[i - 1] != p] == ["tracking", "refining", "writing"]
    order = [type(e) for e in run.events]
    assert order.index(PhaseEvent) < order.index(PoseEvent), "tracking is announced before the first pose"
    last_stats = [e for e in run.events if isinstance(e, StatsEvent)][-1]
    assert last_stats.ate_rmse == pytest.approx(run.result.ate_rmse) and run.result.ate_rmse is not None


def test_run_json_fields(run):
    info = run.info
    assert info["status"] == "finished" and info["error"] is None
    assert info["config"] == run.config.to_dict()
    assert (info["frames"], info["frames_total"], info["loops"]) == (NUM_FRAMES, NUM_FRAMES, 0)
    assert info["maps"] == 1 and info["keyframes"] >= 1 and info["voxels"] > 0
    assert info["map_memory_mb"]["embeddings"] > 0 and info["map_memory_mb"]["decoder"] > 0
    assert info["map_memory_mb"]["fine_color"] == 0, "the test preset has no fine colour level"
    assert info["timings_s"]["wall"] > 0 and info["fps"] > 0
    assert set(info["busy_share"]) == {"tracking", "mapping"}
    assert len(info["keyframe_poses"]) == info["keyframes"]
    assert "ate_rmse_m" in info and info["ate_rmse_m"] is not None, "synthetic frames carry GT"


def test_run_json_times_every_stage(run):
    """Where a frame's time goes: each stage of both sides, and the phases after the last frame,
    as ``benchmarks/bench_stages.py`` tabulates them."""
    timings = run.info["timings_s"]
    for stage in ("read", "prepare", "map_update", "track", "publish", "hand_over", "replies", "end_of_run"):
        assert timings[f"tracking_{stage}"] >= 0, stage
    for stage in ("keyframe_decision", "voxel_allocation", "render", "backward", "final_bundle_adjustment",
                  "final_outputs"):
        assert timings[f"mapping_{stage}"] >= 0, stage
    assert timings["tracking_track"] > 0 and timings["mapping_render"] > 0
    tracked = sum(timings[f"tracking_{s}"] for s in ("read", "prepare", "map_update", "track", "publish"))
    assert tracked + timings["tracking_end_of_run"] <= timings["wall"] * 1.01, "stages are parts of the wall"


def test_run_json_traces_the_runs_course(frames, tmp_path, monkeypatch):
    monkeypatch.setattr(runtime, "PROGRESS_EVERY", 2)
    info = do_run([frames], config(False), tmp_path).info
    samples = info["progress"]
    assert [s["frames"] for s in samples] == [2, 4]
    assert 0 < samples[0]["wall_s"] < samples[1]["wall_s"] <= info["timings_s"]["wall"]
    assert samples[1]["voxels"] > 0 and samples[1]["keyframes"] >= 1 and samples[1]["map_mb"] > 0
    assert all(s["maps"] == 1 for s in samples)


def test_trajectory_carries_the_bundle_adjusted_keyframe_poses(run, frames):
    traj = read_tum(run.out / "trajectory.txt")
    for index, pose in run.info["keyframe_poses"].items():
        np.testing.assert_allclose(traj.poses[int(index)], np.reshape(pose, (4, 4)), atol=1e-5)


def test_refine_with_keyframes_moves_each_frame_with_its_keyframe():
    pose = _pose
    tracked = np.stack([pose(0.0), pose(0.1), pose(0.2, 0.1), pose(0.3, 0.1), pose(0.4, 0.2)])
    ba_kf2 = pose(0.25, 0.12)
    refined = runtime.refine_with_keyframes(tracked, [5, 6, 7, 8, 9], {5: pose(0.0).ravel().tolist(),
                                                                      7: ba_kf2.ravel().tolist()})
    np.testing.assert_allclose(refined[:2], tracked[:2], atol=1e-12)  # keyframe 5 did not move
    np.testing.assert_allclose(refined[2], ba_kf2, atol=1e-12)
    # Frames after keyframe 7 keep their motion relative to it.
    for i in (3, 4):
        np.testing.assert_allclose(np.linalg.inv(refined[2]) @ refined[i],
                                   np.linalg.inv(tracked[2]) @ tracked[i], atol=1e-12)
    assert np.array_equal(runtime.refine_with_keyframes(tracked, [0, 1, 2, 3, 4], {}), tracked)


def _pose(x: float, yaw: float = 0.0) -> np.ndarray:
    """(4, 4): x metres along x, ``yaw`` radians about z."""
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T[0, 3] = x
    return T


def test_interpolated_corrections_blend_the_keyframes_either_side():
    pose = _pose
    tracked = np.stack([pose(0.1 * i) for i in range(7)])
    # Keyframes 0 and 4: bundle adjustment leaves the first and moves the second 0.4 m in x
    # and 0.2 rad in yaw; frames 5, 6 after the last keyframe keep its correction.
    ba = {0: tracked[0].ravel().tolist(), 4: (pose(0.8, 0.2)).ravel().tolist()}
    refined = runtime.refine_with_keyframes(tracked, list(range(7)), ba, interpolate=True)
    latest = runtime.refine_with_keyframes(tracked, list(range(7)), ba)
    np.testing.assert_allclose(refined[[0, 4, 5, 6]], latest[[0, 4, 5, 6]], atol=1e-12)
    np.testing.assert_allclose(latest[1:4], tracked[1:4], atol=1e-12)  # latest: keyframe 0 did not move
    correction = pose(0.8, 0.2) @ np.linalg.inv(tracked[4])
    for i in (1, 2, 3):  # a quarter, half, three quarters of the way: yaw and shift in proportion
        blended = refined[i] @ np.linalg.inv(tracked[i])
        s = i / 4
        np.testing.assert_allclose(np.arctan2(blended[1, 0], blended[0, 0]), 0.2 * s, atol=1e-12)
        np.testing.assert_allclose(blended[:3, 3], s * correction[:3, 3], atol=1e-12)
    with pytest.raises(ConfigError):
        apply_overrides(preset("cpu"), {"mapping": {"frame_correction": "nearest"}})


def test_events_arrive_in_order(run, frames):
    ev = run.events
    poses = [e for e in ev if isinstance(e, PoseEvent)]
    assert [e.frame_index for e in poses] == list(range(NUM_FRAMES))
    assert [e.timestamp for e in poses] == pytest.approx([f.timestamp for f in frames])
    assert all(e.T_map_cam.shape == (4, 4) and e.thumbnail is not None and e.thumbnail.dtype == np.uint8
               for e in poses)
    assert poses[0].image_size == (80, 60)
    keyframes = [e for e in ev if isinstance(e, KeyframeEvent)]
    assert [e.frame_index for e in keyframes][:1] == [0], "the first frame is a keyframe"
    assert len(keyframes) == run.info["keyframes"], "one KeyframeEvent per keyframe"
    submaps = [e for e in ev if isinstance(e, SubmapEvent)]
    assert [(s.map_id, s.reason) for s in submaps] == [(0, "start")]
    meshes = [e for e in ev if isinstance(e, MapUpdateEvent) and e.mesh_vertices is not None]
    assert meshes, "at least the final map update carries a mesh"
    last = meshes[-1]
    assert last.mesh_vertices.dtype == np.float32 and last.mesh_vertices.shape[1] == 3
    assert last.mesh_faces.dtype == np.int32 and last.mesh_faces.shape[1] == 3
    assert last.mesh_colors.dtype == np.uint8 and last.mesh_colors.shape == last.mesh_vertices.shape
    assert int(last.mesh_faces.max()) < len(last.mesh_vertices)
    assert last.num_voxels == run.info["voxels"]
    stats = [e for e in ev if isinstance(e, StatsEvent)]
    assert stats and stats[-1].frames_done == NUM_FRAMES and stats[-1].frames_total == NUM_FRAMES
    finished = [e for e in ev if isinstance(e, FinishedEvent)]
    assert finished == [ev[-1]] and ev[-1].status == "finished" and ev[-1].error is None


def test_gt_poses_mode_writes_the_gt_trajectory(frames, tmp_path):
    """Given poses stay put through the windowed and the final bundle adjustment."""
    cfg = replace(FAST, mapping=replace(FAST.mapping, final_iterations=3, lr_pose=1e-2))
    done = do_run([frames], config(False, cfg), tmp_path, use_gt_poses=True)
    assert done.result.status == "finished"
    traj = read_tum(tmp_path / "trajectory.txt")
    np.testing.assert_allclose(traj.poses, np.stack([f.T_world_cam for f in frames]), atol=1e-6)
    assert done.result.ate_rmse == pytest.approx(0.0, abs=1e-6)
    assert done.info["timings_s"]["mapping_final_bundle_adjustment"] > 0
    assert done.info["final_bundle_adjustment"] == {**done.info["final_bundle_adjustment"], "iterations_budget": 3,
                                                    "iterations_run": 3, "stopped_by_time": False}
    assert done.info["config"]["mapping"]["optimize_poses"] is False
    for index, pose in done.info["keyframe_poses"].items():
        np.testing.assert_allclose(np.reshape(pose, (4, 4)), frames[int(index)].T_world_cam, atol=1e-5)


# ------------------------------------------------------------ failing runs
def test_stop_after_two_frames_cancels_and_still_writes(frames, tmp_path):
    stop = threading.Event()

    def on_event(event):
        events.append(event)
        if isinstance(event, PoseEvent) and event.frame_index == 1:
            stop.set()

    events: list = []
    result = run_slam([frames], config(False), tmp_path, on_event=on_event, stop=stop)
    assert result.status == "cancelled" and result.frames == 2
    info = json.loads((tmp_path / "run.json").read_text())
    assert info["status"] == "cancelled" and info["frames"] == 2
    assert len(read_tum(tmp_path / "trajectory.txt").timestamps) == 2
    assert load_checkpoint(tmp_path / "map.pt").num_voxels() > 0
    assert (tmp_path / "mesh.ply").is_file()
    assert isinstance(events[-1], FinishedEvent) and events[-1].status == "cancelled"
    assert info["timings_s"]["mapping_final_bundle_adjustment"] < 0.05, "a stopped run skips the refinement"


def test_a_finished_run_refines_globally_in_the_mapping_process(frames, tmp_path):
    cfg = replace(FAST, mapping=replace(FAST.mapping, final_iterations=3))
    done = do_run([frames], config(True, cfg), tmp_path)
    assert done.result.status == "finished"
    assert done.info["timings_s"]["mapping_final_bundle_adjustment"] > 0


@pytest.mark.parametrize("processes", [True, False], ids=["processes", "single-process"])
def test_the_final_retracking_moves_every_tracked_frame_against_the_refined_map(frames, tmp_path, monkeypatch,
                                                                               processes):
    # tracking.retrack_iterations: after the final bundle adjustment every tracked frame (the
    # first, which starts the map, too: the refined map no longer holds it exactly at the pose
    # it started with) is tracked again against the refined map, from its corrected pose; that
    # pose is what the trajectory holds. The mapping side sends the maps
    # before its colour fit and outputs, so the re-tracking happens before Done arrives.
    cfg = replace(FAST, mapping=replace(FAST.mapping, final_iterations=3),
                  tracking=replace(FAST.tracking, retrack_iterations=2))
    order: list[str] = []
    handle = runtime._handle_replies

    def spy(replies, side, emit):
        def seen():
            for reply in replies:
                order.append(type(reply).__name__)
                yield reply
        handle(seen(), side, emit)

    monkeypatch.setattr(runtime, "_handle_replies", spy)
    calls: list[np.ndarray] = []
    retrack = runtime.Tracker.retrack

    def counting(self, rays, fmap, T_init):
        calls.append(T_init.numpy().astype(np.float64))
        return retrack(self, rays, fmap, T_init)

    monkeypatch.setattr(runtime.Tracker, "retrack", counting)
    done = do_run([frames], config(processes, cfg), tmp_path / "on")
    assert done.result.status == "finished", done.result.error
    assert len(calls) == NUM_FRAMES and done.info["frames_retracked"] == NUM_FRAMES
    assert order.index("FinalMaps") < order.index("Done")
    assert done.info["timings_s"]["tracking_retracking"] > 0
    poses = read_tum(tmp_path / "on" / "trajectory.txt").poses
    # Each re-tracked pose starts from the frame's corrected pose and moves (a little) from it.
    moved = [np.linalg.norm(p[:3, 3] - c[:3, 3]) for p, c in zip(poses, calls)]
    assert np.allclose(calls[0], np.eye(4)), "the first frame starts from the map's origin"
    assert all(m < 0.05 for m in moved) and any(m > 0 for m in moved), moved
    ate_on = done.info["ate_rmse_m"]
    off = do_run([frames], config(processes, replace(cfg, tracking=FAST.tracking)), tmp_path / "off")
    assert off.info["frames_retracked"] == 0 and "FinalMaps" not in order[order.index("Done") + 1:]
    assert ate_on < 0.05 and off.info["ate_rmse_m"] < 0.05


def test_the_retracking_frame_budget_spreads_its_frames_over_each_map():
    assert outputs.retrack_anchors([0] * 5, 0) == [0, 1, 2, 3, 4]  # 0: every frame
    assert outputs.retrack_anchors([0] * 5, 8) == [0, 1, 2, 3, 4]
    assert outputs.retrack_anchors([0] * 9, 3) == [0, 4, 8]  # first, middle, last
    # Two maps: each gets the budget over its own frames, its first and last included.
    assert outputs.retrack_anchors([0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1, 1], 2) == [0, 4, 5, 11]


def test_frames_left_out_of_the_retracking_take_their_neighbours_corrections():
    pose = _pose
    start = np.stack([pose(0.1 * i) for i in range(7)])
    map_ids = [0, 0, 0, 0, 0, 1, 1]
    # Frames 0 and 4 re-tracked: 0 did not move, 4 moved 0.4 m and 0.2 rad; frame 6 (map 1) moved.
    moved = {0: start[0], 4: pose(0.8, 0.2), 6: pose(0.7, 0.1)}
    spread = outputs.spread_corrections(start, map_ids, moved, [1, 2, 3, 5])
    correction = pose(0.8, 0.2) @ np.linalg.inv(start[4])
    for i in (1, 2, 3):  # blended by place, as bundle adjustment's keyframe corrections are
        expected = outputs.blend_poses(np.eye(4), correction, i / 4) @ start[i]
        np.testing.assert_allclose(spread[i], expected, atol=1e-12)
    # Frame 5 has a re-tracked frame of its own map on one side only (frame 4 is map 0's).
    np.testing.assert_allclose(spread[5], moved[6] @ np.linalg.inv(start[6]) @ start[5], atol=1e-12)
    assert outputs.spread_corrections(start, map_ids, {}, [1, 2]) == {}  # nothing to spread: left out


def test_the_retracking_frame_budget_tracks_that_many_frames_and_moves_all(frames, tmp_path, monkeypatch):
    cfg = replace(FAST, mapping=replace(FAST.mapping, final_iterations=3),
                  tracking=replace(FAST.tracking, retrack_iterations=2, retrack_frame_budget=3))
    calls: list[int] = []
    retrack = runtime.Tracker.retrack

    def counting(self, rays, fmap, T_init):
        calls.append(1)
        return retrack(self, rays, fmap, T_init)

    monkeypatch.setattr(runtime.Tracker, "retrack", counting)
    done = do_run([frames], config(False, cfg), tmp_path / "budget")
    assert done.result.status == "finished", done.result.error
    assert len(calls) == 3 and done.info["frames_retracked"] == 3
    assert done.info["ate_rmse_m"] < 0.05


def test_a_short_run_keeps_more_pixels_a_frame_for_the_retracking():
    tracking = replace(FAST.tracking, retrack_rays=512, retrack_ray_budget=76_800)
    assert runtime.retrack_rays_per_frame(tracking, None) == 512  # a stream: its length is unknown
    assert runtime.retrack_rays_per_frame(tracking, 150) == 512
    assert runtime.retrack_rays_per_frame(tracking, 300) == 512  # never fewer than retrack_rays
    assert runtime.retrack_rays_per_frame(tracking, 75) == 1024
    assert runtime.retrack_rays_per_frame(tracking, 9) == 2048  # at most 4x
    assert runtime.retrack_rays_per_frame(replace(tracking, retrack_ray_budget=0), 9) == 512
    with pytest.raises(ValueError):
        replace(tracking, retrack_ray_budget=-1)


@pytest.mark.parametrize("lag", [0, 1])
def test_deterministic_mode_gives_one_trajectory_whatever_the_timing(tmp_path, monkeypatch, lag):
    """runtime.deterministic_lag (issue 41 item 3): a tracker slowed at random (as a loaded
    machine would) changes nothing: every frame is tracked against exactly the map of the
    frames before it but the newest ``lag``, and the mapper neither batches nor idles."""
    frames = list(open_sequence(SPEC, max_frames=8))
    cfg = replace(FAST, runtime=replace(FAST.runtime, processes=True, deterministic_lag=lag),
                  mapping=replace(FAST.mapping, final_iterations=2))
    seen: list[tuple[int, int, int]] = []
    frozen_map, track = runtime._TrackingSide.frozen_map, runtime.Tracker.track

    def spy(self, map_id):
        seen.append((self.frames_sent + len(self.held), self.frames_integrated, map_id))
        return frozen_map(self, map_id)

    monkeypatch.setattr(runtime._TrackingSide, "frozen_map", spy)
    trajectories = []
    for delays in ([0.0] * 8, [0.3, 0.0, 0.05, 0.4, 0.0, 0.2, 0.0, 0.1]):
        pending = list(delays)

        def slow_track(self, *args, **kwargs):
            import time

            time.sleep(pending.pop(0) if pending else 0.0)
            return track(self, *args, **kwargs)

        monkeypatch.setattr(runtime.Tracker, "track", slow_track)
        seen.clear()
        done = do_run([frames], cfg, tmp_path / f"run{len(trajectories)}")
        assert done.result.status == "finished", done.result.error
        # Frame k (k >= 1) is tracked with the k frames before it handed over, all but `lag` mapped.
        assert [(tracked, integrated) for tracked, integrated, _ in seen] == \
            [(k, max(k - lag, 1)) for k in range(1, len(frames))], seen
        trajectories.append((tmp_path / f"run{len(trajectories)}" / "trajectory.txt").read_bytes())
    assert trajectories[0] == trajectories[1]


@pytest.mark.parametrize("processes", [True, False], ids=["processes", "single-process"])
def test_the_window_refined_pose_replaces_the_tracked_one(frames, tmp_path, monkeypatch, processes):
    # mapping.optimize_current_pose (issue 21 item 2): the mapper optimises each mapped
    # non-keyframe frame's pose in its window and sends it back; the trajectory carries it,
    # and (single-process, where it comes back before the next frame) the next frame starts
    # from it. One keyframe (frame 0, fixed), no final BA, no loops: the trajectory is the
    # frames' records composed with map 0's pose, the identity.
    from slam.messages import FrameMessage, FramePose

    sent: dict[int, np.ndarray] = {}
    replies: list = []
    starts: list[np.ndarray] = []
    channel = runtime.ProcessMapper if processes else runtime.InlineMapper
    submit, poll, finish, track = channel.submit, channel.poll, channel.finish, runtime.Tracker.track

    def spy_submit(self, msg):
        if isinstance(msg, FrameMessage):
            sent[msg.frame.index] = np.asarray(msg.T_map_cam, np.float64)
        return submit(self, msg)

    def spy_poll(self, block=False):
        out = poll(self, block)
        replies.extend(out)
        return out

    def spy_finish(self, refine=True):
        out = list(finish(self, refine))
        replies.extend(out)
        return out

    def spy_track(self, frame, fmap, T_init, matches=None):
        starts.append(T_init.detach().cpu().numpy().astype(np.float64))
        return track(self, frame, fmap, T_init, matches)

    monkeypatch.setattr(channel, "submit", spy_submit)
    monkeypatch.setattr(channel, "poll", spy_poll)
    monkeypatch.setattr(channel, "finish", spy_finish)
    monkeypatch.setattr(runtime.Tracker, "track", spy_track)
    cfg = replace(FAST, mapping=replace(FAST.mapping, optimize_current_pose=True, keyframe_ratio=2.0,
                                        lr_pose=1e-2, iterations=3, final_iterations=0),
                  loop=replace(FAST.loop, enabled=False))
    done = do_run([frames], config(processes, cfg), tmp_path)
    assert done.result.status == "finished", done.result.error
    assert done.info["keyframes"] == 1
    refined = {p.frame_index: p for p in replies if isinstance(p, FramePose)}
    assert refined and set(refined) <= set(range(1, NUM_FRAMES))
    if not processes:
        assert set(refined) == set(range(1, NUM_FRAMES)), "every frame is mapped on its own"
    traj = read_tum(tmp_path / "trajectory.txt")
    for index, pose in refined.items():
        assert pose.agent == 0 and pose.map_id == 0
        assert float(np.abs(pose.T_map_cam - sent[index]).max()) > 1e-5, "the window moved it"
        np.testing.assert_allclose(traj.poses[index], pose.T_map_cam, atol=1e-6)
        if not processes and index + 1 < NUM_FRAMES:
            np.testing.assert_allclose(starts[index], pose.T_map_cam, atol=1e-6)  # starts[0] is frame 1's


def test_a_refined_pose_moves_the_record_history_and_features_of_its_frame():
    # The reply is in the frame of the map the frame was integrated into, which may not be the
    # one it was tracked against (a new region map not yet published to the tracker).
    from slam.messages import FramePose
    from slam.outputs import FrameRecord

    class Features:
        delta = None

        def transform(self, delta):
            self.delta = delta

    def pose(x):
        T = np.eye(4)
        T[:3, 3] = [x, 0.0, 0.0]
        return T

    side = runtime._TrackingSide(FAST, torch.device("cpu"), tracker=None)
    side.map_poses = {0: np.eye(4), 1: pose(1.0)}
    track = side.agents.setdefault(0, runtime.AgentTrack(0))
    track.records = [FrameRecord(i, 0.1 * i, 0, pose(0.1 * i), True, None) for i in range(3)]
    track.good_poses, track.good_frames = [pose(0.1), pose(0.2)], [1, 2]
    track.features = Features()
    runtime._handle_replies([FramePose(0, 2, 1, pose(-0.75))], side, lambda event: None)
    assert track.records[2].map_id == 1 and np.allclose(track.records[2].T_map_cam, pose(-0.75))
    assert np.allclose(track.good_poses[1], pose(0.25)) and np.allclose(track.good_poses[0], pose(0.1))
    assert np.allclose(track.features.delta @ pose(0.2), pose(0.25)), "the remembered frame moves too"
    track.features.delta = None
    runtime._handle_replies([FramePose(0, 1, 0, pose(0.12))], side, lambda event: None)
    assert np.allclose(track.good_poses[0], pose(0.12)) and track.features.delta is None, "not the last frame"
    assert [r.index for r in track.records] == [0, 1, 2]


def raising_source(frames, good: int):
    for f in frames[:good]:
        yield f
    raise DataError(f"frame {good}: corrupt depth image (test)")


@pytest.mark.timeout(120)
def test_source_error_fails_the_run_and_ends_the_mapping_process(frames, tmp_path):
    done = do_run([raising_source(frames, 2)], config(True, FAILING), tmp_path)
    assert done.result.status == "failed"
    assert "Traceback" in done.info["error"] and "frame 2: corrupt depth image" in done.info["error"]
    assert done.info["status"] == "failed" and done.info["frames"] == 2
    assert not mapping_children(), "the mapping process must be gone"
    assert isinstance(done.events[-1], FinishedEvent) and done.events[-1].status == "failed"
    assert "corrupt depth image" in done.events[-1].error
    assert len(read_tum(tmp_path / "trajectory.txt").timestamps) == 2, "what was tracked is kept"


def test_mapper_error_fails_the_run_with_its_traceback(frames, tmp_path):
    blank = replace(frames[0], depth=np.zeros_like(frames[0].depth))
    done = do_run([[blank] + frames[1:2]], config(False, FAILING), tmp_path)
    assert done.result.status == "failed"
    assert "Traceback" in done.info["error"] and "no valid depth" in done.info["error"]


def test_stream_source_without_len(frames, tmp_path):
    stream = (f for f in frames[:3])
    assert not hasattr(stream, "__len__")
    done = do_run([stream], config(False), tmp_path)
    assert done.result.status == "finished" and done.result.frames == 3
    assert done.info["frames_total"] is None and done.info["frames"] == 3
    stats = [e for e in done.events if isinstance(e, StatsEvent)]
    assert stats[-1].frames_total is None and stats[-1].frames_done == 3


def test_gt_poses_on_frames_without_gt_fail_clearly(frames, tmp_path):
    no_gt = [replace(f, T_world_cam=None) for f in frames[:2]]
    done = do_run([no_gt], config(False, FAILING), tmp_path, use_gt_poses=True)
    assert done.result.status == "failed"
    assert "frame 0 has no ground-truth pose" in done.info["error"]



@pytest.mark.shared_data
def test_real_frames_are_tracked_with_feature_matches(shared_data, tmp_path, monkeypatch):
    """TUM fr1/desk (9 frames at 640x480, tracked at the test preset's 160 px): features are
    detected on the frames as read and every frame after the first reaches the tracker with
    its matches, whose PnP pose then starts the optimisation."""
    seen: list[bool] = []
    track = runtime.Tracker.track

    def recording(self, frame, fmap, T_init, matches=None):
        seen.append(matches is not None and len(matches.pixels) > 100)
        return track(self, frame, fmap, T_init, matches)

    monkeypatch.setattr(runtime.Tracker, "track", recording)
    base = replace(FAST, tracking=replace(FAST.tracking, feature_count=1000, feature_weight=0.003))
    frames = list(open_sequence(str(shared_data / "rgbd_dataset_freiburg1_desk")))
    done = do_run([frames], config(False, base), tmp_path)
    assert done.result.status == "finished", done.result.error
    assert seen == [True] * (len(frames) - 1)
    assert done.info["ate_rmse_m"] < 0.015, done.info["ate_rmse_m"]  # measured 0.53 cm


@pytest.mark.shared_data
@pytest.mark.slow
@pytest.mark.timeout(900)
def test_the_first_frame_is_refined_like_every_other(shared_data, tmp_path):
    """fr1/desk, ``cpu`` preset (deterministic, no colour fit): the final re-tracking moves
    frame 0 with the refined map like every other frame, so once the trajectory is aligned on
    frames 1-8 its error is within 3x their median (it stayed at the map's origin, 3.8x)."""
    from slam.eval import umeyama_alignment

    cpu = preset("cpu")
    cfg = replace(cpu, fine_color=replace(cpu.fine_color, final_fit_iterations=0),
                  runtime=replace(cpu.runtime, deterministic_lag=1, device="cpu"))
    frames = list(open_sequence(str(shared_data / "rgbd_dataset_freiburg1_desk")))
    done = do_run([frames], config(True, cfg), tmp_path)
    assert done.result.status == "finished", done.result.error
    assert done.info["frames_retracked"] == len(frames)
    est = read_tum(tmp_path / "trajectory.txt").poses[:, :3, 3]
    gt = np.stack([f.T_world_cam for f in frames])[:, :3, 3]
    R, t, _ = umeyama_alignment(est[1:], gt[1:])
    errors = np.linalg.norm(est @ R.T + t - gt, axis=1)
    assert errors[0] <= 3 * np.median(errors[1:]), (errors[0], np.median(errors[1:]))


# ------------------------------------------------ messages and shared work (issue 42)
def test_every_message_between_the_two_sides_pickles_by_value(frames):
    # They cross the mapping process's queues: each must come back equal in type and content.
    import pickle

    from slam import messages as m
    from slam.events import KeyframeEvent

    frame = frames[0]
    stats = m.MapperStats(1, 1, 10, 40, 8, 0.5, {"x": 1.0}, [m.KeyframeRecord(0, 0, 0, [0.0] * 16)],
                          {0: np.eye(4)}, {0: 0}, {0: 0}, {0: "start"}, [], [], 0, {},
                          m.FinalRefinement(5, 5, 0.1, None, False))
    sent = [m.FrameMessage(0, frame, 0, np.eye(4, dtype=np.float32), True, m.MapStart("start", 0, np.eye(4))),
            m.EndOfInput(refine=False), m.Ready(), m.MapPosesReply({0: np.eye(4)}), m.FramePose(0, 1, 0, np.eye(4)),
            m.EventReply(KeyframeEvent(0, 1, 0, np.eye(4))), m.Done(stats), m.Failed("Traceback ..."),
            m.FinalMaps([], {0: np.eye(4)}, [m.KeyframeRecord(0, 0, 0, [0.0] * 16)])]
    for message in sent:
        back = pickle.loads(pickle.dumps(message))
        assert type(back) is type(message)
    back = pickle.loads(pickle.dumps(sent[0]))
    assert back.new_map.reason == "start" and np.array_equal(back.frame.rgb, frame.rgb)
    assert pickle.loads(pickle.dumps(sent[6])).stats.refinement.iterations_run == 5


def test_the_tracker_detects_the_features_the_loop_closer_would():
    # tracking.feature_count = 1000 (cpu): the tracker's ORB detector is the appearance
    # check's, so the features it found travel with the frame instead of being found again.
    from slam.features import FeatureOdometry, tracking_features_serve_loops
    from slam.loop.closing import LoopCloser

    cfg = preset("cpu")
    assert tracking_features_serve_loops(cfg)
    assert not tracking_features_serve_loops(replace(cfg, tracking=replace(cfg.tracking, feature_count=500)))
    assert not tracking_features_serve_loops(FAST), "no tracker features, nothing to share"
    frame = next(iter(open_sequence("synthetic:laps?frames=100&width=320&height=240", max_frames=1)))
    odometry = FeatureOdometry.from_config(cfg)
    odometry.correspondences(frame)
    detected = odometry.detected
    assert detected is not None and len(detected.pixels) > 50
    closer = LoopCloser(cfg, torch.device("cpu"))
    own, own_verify = closer._describe(frame, None)
    shared, shared_verify = closer._describe(frame, detected)
    assert np.any(own)
    assert np.array_equal(own, shared) and np.array_equal(own_verify.pixels, shared_verify.pixels)
    odometry.remember(np.eye(4))
    assert odometry.detected is None


def test_a_frame_is_prepared_once_in_one_process(frames, tmp_path, monkeypatch):
    # Single-process: the mapper integrates the tensors the tracker prepared, a map's first
    # frame's too (the tracker keeps its pixels for the re-tracking). Across processes the
    # mapper prepares its own (cheaper than pickling tensors), so the message leaves them out.
    import slam.mapping_process as mapping_process

    calls: list[str] = []
    prepare = runtime.prepare_frame

    def counting(side):
        def spy(*args, **kwargs):
            calls.append(side)
            return prepare(*args, **kwargs)
        return spy

    monkeypatch.setattr(runtime, "prepare_frame", counting("tracker"))
    monkeypatch.setattr(mapping_process, "prepare_frame", counting("mapper"))
    done = do_run([frames], config(False), tmp_path)
    assert done.result.status == "finished", done.result.error
    assert calls.count("mapper") == 0 and calls.count("tracker") == NUM_FRAMES, calls
    put: list = []

    class Queue:
        def put(self, msg, timeout=None):
            put.append(msg)

    channel = object.__new__(runtime.ProcessMapper)
    channel.frames = Queue()
    from slam.messages import FrameMessage

    tf = prepare(frames[0], None, torch.device("cpu"), 4.0)
    channel.submit(FrameMessage(0, frames[0], 0, np.eye(4, dtype=np.float32), True, prepared=tf))
    assert put[0].prepared is None and put[0].frame is frames[0]


# ------------------------------------------------------------ live mode
class _FullQueue:
    """A mapper channel whose queue takes ``room`` frames, then is full until ``drain``."""

    def __init__(self, room: int) -> None:
        self.room, self.got = room, []

    def offer(self, msg) -> bool:
        if self.room <= 0:
            return False
        self.room -= 1
        self.got.append(msg.frame.index)
        return True

    def submit(self, msg) -> None:  # waits for room in the real channel
        self.got.append(msg.frame.index)


def test_live_hand_over_never_waits_and_gives_the_mapper_the_newest_frames(frames):
    """runtime.live: a frame that finds the queue full waits in one slot, where the next frame
    replaces it; a frame that starts a map always goes; the end of the input sends the last."""
    from slam.messages import FrameMessage, MapStart

    cfg = replace(FAST, runtime=replace(FAST.runtime, live=True))
    side = runtime._TrackingSide(cfg, torch.device("cpu"), None)
    channel = _FullQueue(room=1)

    def message(i: int, starts_map: bool = False) -> FrameMessage:
        start = MapStart("start", i, np.eye(4)) if starts_map else None
        return FrameMessage(0, replace(frames[0], index=i), 0, np.eye(4, dtype=np.float32), True, start)

    runtime._hand_over(side, message(0, starts_map=True), channel)  # a map's first frame: sent
    runtime._hand_over(side, message(1), channel)  # room for one
    runtime._hand_over(side, message(2), channel)  # full: waits
    runtime._hand_over(side, message(3), channel)  # still full: 2 is left out, 3 waits
    assert channel.got == [0, 1] and side.waiting.frame.index == 3 and side.frames_unmapped == 1
    channel.room = 1
    runtime._hand_over(side, message(4), channel)  # room again: 3 goes first, 4 waits
    runtime._hand_over(side, message(5, starts_map=True), channel)  # 4 left out; 5 must go
    assert channel.got == [0, 1, 3, 5] and side.waiting is None and side.frames_unmapped == 2
    runtime._hand_over(side, message(6), channel)
    runtime._send_waiting(side, channel)
    assert channel.got == [0, 1, 3, 5, 6] and side.frames_sent == 5


def test_live_and_deterministic_modes_exclude_each_other():
    with pytest.raises(ConfigError, match="runtime.live and runtime.deterministic_lag exclude each other"):
        replace(FAST.runtime, live=True, deterministic_lag=0)


def test_a_live_run_maps_its_first_frame_in_published_steps(tmp_path, monkeypatch):
    """runtime.live, in processes: the run finishes with every frame tracked, says how many the
    mapper never got, and the mapping process publishes its first frame's map after a window's
    iterations, then again after each further step until the first frame's iterations are done."""
    import slam.mapping_process as mapping_process

    cfg = replace(FAST, runtime=replace(FAST.runtime, processes=False, live=True),
                  mapping=replace(FAST.mapping, iterations=2, first_frame_iterations=7))
    steps: list[int] = []
    optimize = mapping_process.Mapper.optimize

    def spy(self, submap, iterations, *args, **kwargs):
        steps.append(iterations)
        return optimize(self, submap, iterations, *args, **kwargs)

    monkeypatch.setattr(mapping_process.Mapper, "optimize", spy)
    side = mapping_process._make_side(cfg, torch.device("cpu"), tmp_path, False, 0)
    first = list(open_sequence(SPEC, max_frames=1))[0]
    from slam.messages import FrameMessage, MapStart

    msg = FrameMessage(0, first, 0, np.eye(4, dtype=np.float32), True, MapStart("start", 0, np.eye(4)))
    replies = mapping_process._integrate_batch(side, [msg])
    assert side.first_frame_debt == {0: 5}, "a window's iterations now, the other 5 owed"
    paid = []
    while side.first_frame_debt:
        paid += mapping_process._pay_first_frames(side)
    assert steps == [2, 2, 1] and len(paid) == 3 and all(isinstance(r, type(replies[-1])) for r in paid)
    steps.clear()
    inline = mapping_process.InlineMapper(cfg, torch.device("cpu"), tmp_path / "inline", False, 0)
    inline.submit(msg)
    assert steps == [2, 2, 1] and not inline.side.first_frame_debt, "in one process the first frame is paid at once"

    frames8 = list(open_sequence(SPEC, max_frames=8))
    done = do_run([frames8], replace(cfg, runtime=replace(cfg.runtime, processes=True)), tmp_path / "run")
    assert done.result.status == "finished", done.result.error
    assert done.info["frames"] == 8 and 0 <= done.info["frames_unmapped"] <= 6

