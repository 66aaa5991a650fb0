"""Multi-maps: map groups, the final refinement's shares, untracked-frame interpolation,
duplicate-geometry removal, and runs that split into maps (region, tracking loss, agents).

Runs use the ``test`` preset in one process (``processes=False``) on tiny synthetic data.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

import slam.runtime as runtime
from slam.checkpoint import load_checkpoint
from slam.config import preset
from slam.data import open_sequence
from slam.data.frame import Frame
from slam.eval.trajectory import read_tum
from slam.events import SubmapEvent
from slam.geometry import se3_exp
from slam.mapping_process import final_iterations_per_map
from slam.maps import MapSet, SubMap
from slam.mesh import extract_mesh
from slam.outputs import interpolate_untracked

_BASE = preset("test")
NO_LOOPS = replace(_BASE, loop=replace(_BASE.loop, enabled=False),
                   runtime=replace(_BASE.runtime, processes=False, checkpoint_every_keyframes=0),
                   mesh=replace(_BASE.mesh, resolution=2, update_every_keyframes=100))
pytestmark = pytest.mark.timeout(300)


@pytest.fixture(autouse=True)
def one_thread(monkeypatch):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    monkeypatch.setattr(runtime, "process_threads", lambda device, processes: None)
    yield
    torch.set_num_threads(threads)


def _submap(map_id: int, parent: int | None = None) -> SubMap:
    m = SubMap.create(map_id, 0, NO_LOOPS, torch.device("cpu"))
    m.parent = parent
    return m


def test_groups_follow_parents_and_loop_links():
    maps = MapSet(NO_LOOPS, [_submap(0), _submap(1, 0), _submap(2), _submap(3, 2), _submap(4)])
    g = maps.groups()
    assert g == {0: 0, 1: 0, 2: 2, 3: 2, 4: 4}
    maps.links.append((3, 1))  # a loop joins the two chains; map 4 still floats
    g = maps.groups()
    assert g[2] == g[3] == g[0] == 0 and g[4] == 4


def test_final_iterations_are_shared_by_keyframes():
    assert final_iterations_per_map([10], 500) == [500]
    shares = final_iterations_per_map([30, 10, 0], 500)
    assert shares[2] == 0 and shares[0] > shares[1] >= 100
    assert final_iterations_per_map([3, 3], 0) == [0, 0]


def test_interpolate_untracked_between_neighbours():
    T = np.tile(np.eye(4), (5, 1, 1))
    T[:, 0, 3] = [0.0, 9.0, 9.0, 9.0, 4.0]  # frames 1-3 failed
    T[4, :3, :3] = se3_exp(torch.tensor([0, 0, 0, 0, 0, 0.4], dtype=torch.float64))[:3, :3].numpy()
    ts = np.arange(5, dtype=float)
    out = interpolate_untracked(T, ts, np.array([True, False, False, False, True]))
    np.testing.assert_allclose(out[:, 0, 3], [0, 1, 2, 3, 4])
    angle = np.arctan2(out[2, 1, 0], out[2, 0, 0])
    assert angle == pytest.approx(0.2, abs=1e-9)
    np.testing.assert_array_equal(out[[0, 4]], T[[0, 4]])


def _trained_map(frames, map_id: int, T_world_map: np.ndarray):
    from slam.frames import prepare_frame
    from slam.mapping import Mapper, NewMap, TrackedFrame

    mapper = Mapper(NO_LOOPS, torch.device("cpu"), seed=map_id)
    for i, f in enumerate(frames):
        tf = prepare_frame(f, None, torch.device("cpu"), NO_LOOPS.voxel.max_depth)
        nm = NewMap("start", 0, torch.from_numpy(T_world_map).float()) if i == 0 else None
        mapper.process(TrackedFrame(tf, torch.from_numpy(f.T_world_cam).float(), new_map=nm), optimize=True)
    mapper.global_bundle_adjustment(mapper.current, 30, 256)
    submap = mapper.current
    submap.map_id = map_id
    return submap


def test_duplicate_geometry_is_kept_from_the_oldest_map_of_a_group():
    frames = list(open_sequence("synthetic:orbit?frames=100&width=80&height=60", max_frames=2))
    T0 = np.eye(4)
    T1 = np.eye(4)
    T1[:3, 3] = [0.3, -0.2, 0.1]  # the same place, mapped in a map with another origin
    a, b = _trained_map(frames, 0, T0), _trained_map(frames, 1, T1)
    one = extract_mesh(MapSet(NO_LOOPS, [a]), resolution=2)
    assert len(one.faces) > 100
    floating = MapSet(NO_LOOPS, [a, b])  # no relation: both kept
    assert len(extract_mesh(floating, resolution=2).faces) >= 1.9 * len(one.faces)
    joined = MapSet(NO_LOOPS, [a, b], links=[(0, 1)])
    both = extract_mesh(joined, resolution=2)
    assert len(both.faces) < 1.3 * len(one.faces), "the second map's copy of the walls is dropped"
    assert len(extract_mesh(joined, resolution=2, dedupe=False).faces) >= 1.9 * len(one.faces)


def _run(sources, tmp_path, config=NO_LOOPS):
    events: list = []
    result = runtime.run_slam(sources, config, tmp_path, on_event=events.append)
    assert result.status == "finished", result.error
    return result, events, json.loads((tmp_path / "run.json").read_text())


def test_leaving_the_region_starts_a_map_that_continues_the_last(tmp_path):
    cfg = replace(NO_LOOPS, multimap=replace(NO_LOOPS.multimap, region_size=0.6))
    src = open_sequence("synthetic:walk?frames=100&width=80&height=60", max_frames=30)
    result, events, info = _run([src], tmp_path, cfg)
    starts = [e for e in events if isinstance(e, SubmapEvent)]
    assert result.maps == len(starts) >= 2 and [e.reason for e in starts[1:]] == ["region"] * (len(starts) - 1)
    assert info["map_groups"] == 1, "region maps are related by the tracking chain"
    mapset = load_checkpoint(tmp_path / "map.pt")
    assert [m.parent for m in mapset.maps] == [None] + list(range(len(mapset.maps) - 1))
    assert set(mapset.groups().values()) == {0}
    for m in mapset.maps[1:]:  # a region map's origin is its first camera, inside the region
        parent = mapset.maps[m.parent]
        offset = torch.linalg.inv(parent.T_world_map) @ m.T_world_map
        assert float(offset[:3, 3].abs().max()) > 0.3 - 1e-3
    assert len(read_tum(tmp_path / "trajectory.txt").timestamps) == 30
    assert result.ate_rmse is not None and result.ate_rmse < 0.1


class _Blanked:
    """A sequence with frames [a, b] blanked (no colour, no depth): a forced tracking loss."""

    def __init__(self, frames: list[Frame], a: int, b: int):
        self.frames, self.a, self.b = frames, a, b

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self):
        for i, f in enumerate(self.frames):
            if self.a <= i <= self.b:
                f = Frame(f.index, f.timestamp, np.zeros_like(f.rgb), np.zeros_like(f.depth), f.K, f.T_world_cam)
            yield f


def test_a_lost_camera_starts_a_floating_map(tmp_path):
    frames = list(open_sequence("synthetic:orbit?frames=100&width=80&height=60", max_frames=16))
    result, events, info = _run([_Blanked(frames, 6, 9)], tmp_path)
    reasons = [e.reason for e in events if isinstance(e, SubmapEvent)]
    assert reasons == ["start", "tracking_failure"]
    assert info["map_groups"] == 2, "without a loop the new map floats in its own group"
    assert info["agents"][0]["frames_interpolated"] >= 4
    assert len(read_tum(tmp_path / "trajectory.txt").timestamps) == 16


def test_two_agents_write_one_trajectory_each(tmp_path):
    a = open_sequence("synthetic:agents?agent=0&agents=2&frames=100&width=80&height=60", max_frames=6)
    b = open_sequence("synthetic:agents?agent=1&agents=2&frames=100&width=80&height=60", max_frames=5)
    result, events, info = _run([a, b], tmp_path)
    assert result.agents == 2 and result.maps == 2
    assert len(read_tum(tmp_path / "trajectory_0.txt").timestamps) == 6
    assert len(read_tum(tmp_path / "trajectory_1.txt").timestamps) == 5
    assert (tmp_path / "trajectory.txt").read_text() == (tmp_path / "trajectory_0.txt").read_text()
    agents = {a["agent"]: a for a in info["agents"]}
    assert agents[0]["joined"] and not agents[1]["joined"], "loops are off: agent 1 never joins"
    starts = [e for e in events if isinstance(e, SubmapEvent)]
    assert sorted((e.agent, e.reason) for e in starts) == [(0, "start"), (1, "start")]
    first_1 = read_tum(tmp_path / "trajectory_1.txt").poses[0]
    np.testing.assert_allclose(first_1, np.eye(4), atol=1e-5)  # an unjoined agent floats at the origin


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def test_two_agents_are_joined_by_a_verified_loop(tmp_path):
    """Agents with unknown relative start poses (agent 1 starts at the origin of its own
    frame) meet halfway around the table: a verified loop joins agent 1's map to agent 0's
    world, and both trajectories then fit the ground truth with one alignment."""
    from slam.eval import ate
    from slam.eval.loops import loop_pose_errors
    from slam.eval.trajectory import Trajectory

    cfg = replace(_BASE, runtime=replace(_BASE.runtime, processes=False, checkpoint_every_keyframes=0),
                  mesh=replace(_BASE.mesh, resolution=2, update_every_keyframes=100))
    specs = [f"synthetic:agents?agent={k}&agents=2&frames=60&width=160&height=120" for k in range(2)]
    seqs = [list(open_sequence(s)) for s in specs]
    result, events, info = _run(seqs, tmp_path, cfg)
    assert result.loops >= 1 and all(a["joined"] for a in info["agents"])
    reloaded = load_checkpoint(tmp_path / "map.pt")
    assert len(reloaded.maps) == 2 and set(reloaded.groups().values()) == {0}, "loop links are saved"
    np.testing.assert_allclose(reloaded.maps[0].T_world_map.numpy(), np.eye(4), atol=1e-5,
                               err_msg="the world is the first agent's first map, whichever side found the loop")
    np.testing.assert_allclose(reloaded.maps[1].T_world_map.numpy(), np.asarray(info["map_poses"]["1"]).reshape(4, 4),
                               atol=1e-5)
    gt = {k: {f.index: f.T_world_cam for f in seq} for k, seq in enumerate(seqs)}
    for c in info["loop_closures"]:
        Ta, Tb = gt[c["agent"]][c["frame_index"]], gt[c["match_agent"]][c["match_frame_index"]]
        assert np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]) < 1.0 and _angle_deg(Ta[:3, :3].T @ Tb[:3, :3]) < 30
        assert c["scores"]["pnp_inliers"] >= cfg.loop.min_inliers
    assert {c["agent"] for c in info["loop_closures"]} <= {0, 1}
    assert any(c["agent"] != c["match_agent"] for c in info["loop_closures"])
    # Each loop records the relative pose it measured, which ground truth can check (issue 41).
    errors = loop_pose_errors(info["loop_closures"], lambda agent, index: gt[agent].get(index))
    assert len(errors) == len(info["loop_closures"])
    for error in errors:
        assert error.translation_m < 0.05 and error.rotation_deg < 3.0, error
    est = [read_tum(tmp_path / f"trajectory_{k}.txt") for k in range(2)]
    both = Trajectory(np.concatenate([e.timestamps + 100 * k for k, e in enumerate(est)]),
                      np.concatenate([e.poses for e in est]))
    truth = Trajectory(both.timestamps, np.concatenate([np.stack([f.T_world_cam for f in s]) for s in seqs]))
    joint = ate(truth, both).rmse
    assert joint < 0.08, f"one alignment for both agents: {joint * 100:.1f} cm"
    assert joint < 3 * max(a["ate_rmse_m"] for a in info["agents"])
    loop_events = [e for e in events if type(e).__name__ == "LoopEvent"]
    assert len(loop_events) == result.loops
    # The end-of-run keyframe graph used every verified loop (the accepted ones among them).
    verified = [c for c in info["loop_candidates"] if c["verified"]]
    assert len(verified) >= result.loops
    graph = info["keyframe_graph"]
    assert graph["loops_used"] + graph["loops_rejected"] == len(verified) and graph["loops_used"] >= 1


@pytest.mark.shared_data
def test_agents_with_different_cameras_and_formats_run_together(shared_data, tmp_path):
    """A real TUM sequence (640 x 480 Kinect, PNG folder) and a synthetic one (another camera,
    another size) as two agents: both are tracked into their own maps and written."""
    desk = open_sequence(str(shared_data / "rgbd_dataset_freiburg1_desk"), max_frames=4)
    synth = open_sequence("synthetic:orbit?frames=100&width=120&height=90", max_frames=4)
    result, events, info = _run([desk, synth], tmp_path)
    assert result.agents == 2 and result.frames == 8 and result.maps == 2
    for k in range(2):
        assert len(read_tum(tmp_path / f"trajectory_{k}.txt").timestamps) == 4


def test_a_mapper_that_fails_mid_run_is_reported_not_waited_for(tmp_path):
    """The tracker keeps submitting while the mapping process has failed and is flushing its
    traceback at exit: submit raises with that traceback instead of both processes waiting
    for each other (a deadlock seen on the laps hall)."""
    from slam.mapping_process import MapperFailed, ProcessMapper
    from slam.messages import FrameMessage

    frame = next(iter(open_sequence("synthetic:orbit?frames=100&width=80&height=60", max_frames=1)))
    mapper = ProcessMapper(NO_LOOPS, torch.device("cpu"), tmp_path, False, 0)
    try:
        bad = FrameMessage(0, frame, 7, np.eye(4, dtype=np.float32), True)  # map 7 was never started
        with pytest.raises(MapperFailed, match="no map 7"):
            for _ in range(50):  # as fast as it takes them: the mapper must not drain forever
                mapper.submit(bad)
    finally:
        mapper.close()
    assert not mapper.process.is_alive()


def test_the_region_is_centred_on_the_first_camera_not_the_world_origin(tmp_path):
    """A dataset whose ground truth puts the first camera 5 m from the world origin (as
    TUM's motion capture does) is not split at its first tracked frame."""
    shift = np.eye(4)
    shift[:3, 3] = [5.0, -4.0, 1.0]
    frames = [Frame(f.index, f.timestamp, f.rgb, f.depth, f.K, shift @ f.T_world_cam)
              for f in open_sequence("synthetic:orbit?frames=100&width=80&height=60", max_frames=6)]
    cfg = replace(NO_LOOPS, multimap=replace(NO_LOOPS.multimap, region_size=3.0))
    result, events, info = _run([frames], tmp_path, cfg)
    assert result.maps == 1, info["map_reasons"]
