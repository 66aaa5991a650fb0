"""The viser adapter: mesh chunking, change detection, frustums, rate limits (real viser, no browser)."""

from __future__ import annotations

import time

import numpy as np
import pytest
import trimesh

from server.viewer import (
    UPDATE_HZ,
    MeshChunk,
    ViewerAdapter,
    agent_color,
    chunk_changed,
    frustum_segments,
    map_color,
    mesh_chunks,
)
from slam.events import KeyframeEvent, LoopEvent, MapUpdateEvent, PoseEvent, PosesUpdatedEvent, StatsEvent, SubmapEvent


def box_mesh(size: float = 2.5) -> trimesh.Trimesh:
    return trimesh.creation.box((size, size, 1.0)).subdivide().subdivide()


def test_mesh_chunks_partition_the_faces():
    mesh = box_mesh()
    colors = np.random.default_rng(0).integers(0, 255, (len(mesh.vertices), 3), dtype=np.uint8)
    chunks = mesh_chunks(mesh.vertices, mesh.faces, colors, chunk_size=1.0)
    assert len(chunks) > 4
    assert sum(len(c.faces) for c in chunks.values()) == len(mesh.faces)
    original = {tuple(sorted(map(tuple, np.round(tri, 6)))) for tri in mesh.vertices[mesh.faces]}
    rebuilt = set()
    for key, chunk in chunks.items():
        triangles = chunk.vertices[chunk.faces]
        centroids = triangles.mean(axis=1)
        assert np.all(np.floor(centroids / 1.0) == np.array(key)), "every face lies in its own cube"
        rebuilt |= {tuple(sorted(map(tuple, np.round(tri.astype(np.float64), 6)))) for tri in triangles}
        assert chunk.colors.shape == (len(chunk.vertices), 3)
    assert rebuilt == original


def test_chunk_change_tolerates_small_drift_only():
    mesh = box_mesh()
    chunk = next(iter(mesh_chunks(mesh.vertices, mesh.faces, None).values()))
    nudged = MeshChunk(chunk.vertices + 0.001, chunk.faces, chunk.colors)
    moved = MeshChunk(chunk.vertices + 0.05, chunk.faces, chunk.colors)
    recoloured = MeshChunk(chunk.vertices, chunk.faces, chunk.colors // 2)
    assert not chunk_changed(chunk, nudged)
    assert chunk_changed(chunk, moved)
    assert chunk_changed(chunk, recoloured)
    assert chunk_changed(None, chunk)


def test_frustum_segments_geometry():
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    segments = frustum_segments(T[None], K, 100, 80, depth=0.5)
    assert segments.shape == (8, 2, 3)
    assert np.allclose(segments[:4, 0], [1, 2, 3]), "spokes start at the camera centre"
    corners = segments[:4, 1]
    assert np.allclose(corners[:, 2], 3.5), "image plane at depth 0.5 along +z (OpenCV forward)"
    assert np.allclose(corners[0, :2], [1 - 0.25, 2 - 0.2])


def test_map_colors_are_distinct():
    colors = {map_color(i) for i in range(8)}
    assert len(colors) == 8


@pytest.fixture()
def adapter():
    viewer = ViewerAdapter("127.0.0.1", 0)
    viewer.start()
    yield viewer
    viewer.stop()


def pose_event(i: int, map_id: int = 0) -> PoseEvent:
    T = np.eye(4)
    T[:3, 3] = [0.05 * i, 0.0, 1.0]
    K = np.array([[80.0, 0, 40], [0, 80.0, 30], [0, 0, 1]])
    thumb = np.full((30, 40, 3), 100, np.uint8)
    return PoseEvent(0, i, i / 30, T, map_id, True, thumb, K, (80, 60))


def mesh_event(mesh: trimesh.Trimesh, T_world_map: np.ndarray, version: int, map_id: int = 0) -> MapUpdateEvent:
    """Map ``map_id``'s mesh (in its frame, as the runtime sends it), the map placed at T_world_map."""
    vertices = np.asarray(mesh.vertices, dtype=np.float32)
    return MapUpdateEvent(map_id, version, T_world_map, 100, np.zeros((0, 4, 4)), vertices,
                          np.asarray(mesh.faces, np.int32), np.full((len(mesh.vertices), 3), 150, np.uint8))


def test_scene_nodes_and_only_changed_chunks_resent(adapter):
    sid = "0123456789ab"
    mesh = box_mesh()
    for i in range(5):
        adapter.handle_event(sid, pose_event(i))
    adapter.handle_event(sid, KeyframeEvent(0, 0, 0, pose_event(0).T_map_cam))
    adapter.handle_event(sid, mesh_event(mesh, np.eye(4), 1))
    adapter.handle_event(sid, StatsEvent(5, 10, 4.0, 1, 1, 0, 100))
    adapter.flush(force=True)
    names = set(adapter.nodes)
    assert f"/sessions/{sid}/camera/frustum" in names
    assert f"/sessions/{sid}/meshes/map_0" in names
    first = adapter.stats.chunks_sent
    assert first == len(mesh_chunks(mesh.vertices, mesh.faces, None))

    # A loop correction moves the whole map: the node moves, no chunk is resent.
    T_corrected = np.eye(4)
    T_corrected[:3, 3] = [0.3, -0.2, 0.0]
    adapter.handle_event(sid, mesh_event(mesh, T_corrected, 2))
    adapter.handle_event(sid, LoopEvent(0, 0, 4, 4 / 30, 0, 0, 0, 0.0, T_corrected, np.eye(4), {"similarity": 0.95}))
    adapter.flush(force=True)
    assert adapter.stats.chunks_sent == first
    assert adapter.stats.chunks_skipped >= first
    assert np.allclose(adapter.nodes[f"/sessions/{sid}/meshes/map_0"].position, [0.3, -0.2, 0.0])
    assert f"/sessions/{sid}/loops" in adapter.nodes

    # The mesh grows on one side: only the chunks there are sent again.
    grown = trimesh.util.concatenate([mesh, trimesh.creation.box((0.5, 0.5, 0.5)).apply_translation([3.2, 0, 0])])
    adapter.handle_event(sid, mesh_event(grown, T_corrected, 3))
    adapter.flush(force=True)
    new_chunks = adapter.stats.chunks_sent - first
    assert 0 < new_chunks < first

    adapter.remove_session(sid)
    assert not any(name.startswith(f"/sessions/{sid}") for name in adapter.nodes)


def test_updates_are_rate_limited(adapter):
    sid = "ba9876543210"
    adapter.handle_event(sid, pose_event(0))
    adapter.flush(force=True)
    before = adapter.stats.updates
    start = time.monotonic()
    i = 1
    while time.monotonic() - start < 1.0:  # a run reporting poses as fast as it can
        adapter.handle_event(sid, pose_event(i))
        i += 1
        time.sleep(0.002)
    time.sleep(0.1)
    sent = adapter.stats.updates - before
    assert i > 100
    assert 1 <= sent <= UPDATE_HZ * 1.1 + 2, f"{sent} browser updates for {i} poses in 1 s"


def test_no_camera_without_browser(adapter):
    assert adapter.current_camera() is None
    assert adapter.client_count() == 0


# -- several maps and agents, loop closure and pose updates -------------------------------------

def translation(x: float, y: float = 0.0, z: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [x, y, z]
    return T


def agent_pose(agent: int, i: int, map_id: int) -> PoseEvent:
    """Frame i of an agent, 5 cm apart along x in its map's frame (as the runtime reports it)."""
    T_map_cam = translation(0.05 * i, 0.5 * agent, 1.0)
    K = np.array([[80.0, 0, 40], [0, 80.0, 30], [0, 0, 1]])
    return PoseEvent(agent, i, i / 30, T_map_cam, map_id, True, np.full((30, 40, 3), 90, np.uint8), K, (80, 60))


def segment_points(adapter, name: str) -> np.ndarray:
    return np.asarray(adapter.nodes[name].points, dtype=np.float64)


def test_agent_colors_are_distinct_and_differ_from_maps():
    colors = [agent_color(a) for a in range(12)]
    assert len(set(colors)) == 12
    assert agent_color(0) not in {map_color(m) for m in range(8)}


def test_two_agents_maps_loop_and_pose_update(adapter):
    """Two agents, a map each; a loop joins them and moves agent 1's map: its mesh node, its
    keyframes, its trajectory and the loop edge move by T_new @ inv(T_old); agent 0 stays."""
    sid = "c0ffee000001"
    mesh = box_mesh()
    T0, T1 = np.eye(4), translation(3.0, 1.0, 0.0)
    adapter.handle_event(sid, SubmapEvent(0, 0, T0, "start"))
    adapter.handle_event(sid, SubmapEvent(1, 1, T1, "start"))
    for i in range(6):
        adapter.handle_event(sid, agent_pose(0, i, 0))
        adapter.handle_event(sid, agent_pose(1, i, 1))
    adapter.handle_event(sid, KeyframeEvent(1, 2, 1, agent_pose(1, 2, 1).T_map_cam))
    adapter.handle_event(sid, mesh_event(mesh, T0, 1))
    adapter.handle_event(sid, mesh_event(mesh, T1, 1, map_id=1))
    adapter.flush(force=True)
    root = f"/sessions/{sid}"
    names = set(adapter.nodes)
    for path in ("meshes/map_0", "meshes/map_1", "regions/map_1/bounds", "trajectory/agent_0/part_0",
                 "trajectory/agent_1/part_0", "camera/frustum",
                 "camera/frustum_1", "keyframes/map_1/frusta"):
        assert f"{root}/{path}" in names, path
    # Each agent's path in its own colour; every map in its own.
    colors_0 = np.asarray(adapter.nodes[f"{root}/trajectory/agent_0/part_0"].colors).reshape(-1, 3)
    colors_1 = np.asarray(adapter.nodes[f"{root}/trajectory/agent_1/part_0"].colors).reshape(-1, 3)
    assert (colors_0 == agent_color(0)).all() and (colors_1 == agent_color(1)).all()
    assert np.allclose(np.asarray(adapter.nodes[f"{root}/keyframes/map_1/frusta"].colors).reshape(-1, 3)[0],
                       map_color(1))
    assert np.allclose(adapter.nodes[f"{root}/meshes/map_1"].position, [3.0, 1.0, 0.0])
    assert not adapter.nodes[f"{root}/regions"].visible, "region boxes are off until ticked"
    assert adapter.nodes[f"{root}/meshes"].visible
    chunks_before = adapter.stats.chunks_sent
    before_0 = adapter.trajectory_positions(sid, 0)
    before_1 = adapter.trajectory_positions(sid, 1)
    assert np.allclose(before_1[4], (T1 @ translation(0.2, 0.5, 1.0))[:3, 3])

    # A loop between agent 1's frame 5 and agent 0's frame 1, then the optimisation moves map 1.
    adapter.handle_event(sid, LoopEvent(1, 1, 5, 5 / 30, 0, 0, 1, 1 / 30, agent_pose(1, 5, 1).T_map_cam,
                                        agent_pose(0, 1, 0).T_map_cam, {"similarity": 0.9}))
    adapter.flush(force=True)
    edge = segment_points(adapter, f"{root}/loops/edges")
    assert edge.shape == (1, 2, 3)
    assert np.allclose(edge[0, 0], before_1[5], atol=1e-5) and np.allclose(edge[0, 1], before_0[1], atol=1e-5)

    T1_new = translation(2.5, 0.8, 0.1, yaw=0.3)
    keyframes_new = translation(0.1, 0.5, 1.0)[None]
    adapter.handle_event(sid, PosesUpdatedEvent({0: T0, 1: T1_new}, {0: np.zeros((0, 4, 4)), 1: keyframes_new},
                                                {0: 0, 1: 1}, "loop"))
    adapter.flush(force=True)
    delta = T1_new @ np.linalg.inv(T1)
    after_1 = adapter.trajectory_positions(sid, 1)
    assert np.allclose(after_1, before_1 @ delta[:3, :3].T + delta[:3, 3], atol=1e-9)
    assert np.allclose(adapter.trajectory_positions(sid, 0), before_0), "agent 0's map did not move"
    drawn = segment_points(adapter, f"{root}/trajectory/agent_1/part_0")
    assert np.allclose(drawn[:, 0], after_1[:-1], atol=1e-5) and np.allclose(drawn[:, 1], after_1[1:], atol=1e-5)
    assert np.allclose(adapter.nodes[f"{root}/meshes/map_1"].position, T1_new[:3, 3])
    assert np.allclose(adapter.nodes[f"{root}/keyframes/map_1"].position, T1_new[:3, 3])
    assert adapter.stats.chunks_sent == chunks_before, "moving a map resends no mesh chunk"
    edge = segment_points(adapter, f"{root}/loops/edges")
    assert np.allclose(edge[0, 0], after_1[5], atol=1e-5) and np.allclose(edge[0, 1], before_0[1], atol=1e-5)
    frustum = adapter.nodes[f"{root}/camera/frustum_1"]
    assert np.allclose(frustum.position, after_1[-1], atol=1e-6), "agent 1's camera moved with its map"
    # The keyframes now sit where the event says (drawn in the map frame under the moved node).
    frusta = segment_points(adapter, f"{root}/keyframes/map_1/frusta")
    assert np.allclose(frusta[0, 0], (translation(0.1, 0.5, 1.0))[:3, 3], atol=1e-5)

    # A new pose tracked in the moved map lands where the map is now.
    adapter.handle_event(sid, agent_pose(1, 6, 1))
    assert np.allclose(adapter.trajectory_positions(sid, 1)[-1], (T1_new @ translation(0.3, 0.5, 1.0))[:3, 3])
    assert "2 agents" in adapter.status_line() and "1 loop, 2 agents" in adapter.status_line()
    adapter.remove_session(sid)
    assert not any(name.startswith(root) for name in adapter.nodes)


def test_loop_edge_without_tracked_frames_follows_its_maps(adapter):
    """A loop whose frames the viewer never saw (e.g. it joined late) is drawn at the event's
    keyframe poses, which are in their maps' frames: the edge moves with its maps."""
    sid = "c0ffee000002"
    adapter.handle_event(sid, SubmapEvent(0, 0, np.eye(4), "start"))
    adapter.handle_event(sid, SubmapEvent(1, 0, translation(1.0), "tracking_failure"))
    adapter.handle_event(sid, LoopEvent(0, 1, 40, 1.3, 0, 0, 3, 0.1, translation(0.5, 0.5), translation(0.2), {}))
    adapter.flush(force=True)
    assert np.allclose(adapter.loop_segments(sid)[0], [[1.5, 0.5, 0], [0.2, 0, 0]])
    adapter.handle_event(sid, PosesUpdatedEvent({0: np.eye(4), 1: translation(1.0, 0.5)}, {}, {0: 0, 1: 0}, "loop"))
    adapter.flush(force=True)
    assert np.allclose(adapter.loop_segments(sid)[0], [[1.5, 1.0, 0], [0.2, 0, 0]])
    adapter.handle_event(sid, PosesUpdatedEvent({0: np.eye(4), 1: translation(1.0, 2.0)}, {}, {0: 0, 1: 0},
                                                "refinement"))
    adapter.flush(force=True)
    assert np.allclose(adapter.loop_segments(sid)[0], [[1.5, 2.5, 0], [0.2, 0, 0]])
    assert np.allclose(segment_points(adapter, f"/sessions/{sid}/loops/edges")[0], [[1.5, 2.5, 0], [0.2, 0, 0]])
    # drawn to stand out: thicker than a trajectory, with a dot at each end
    edges = adapter.nodes[f"/sessions/{sid}/loops/edges"]
    assert edges.thickness >= 6.0
    assert np.allclose(np.asarray(adapter.nodes[f"/sessions/{sid}/loops/ends"].points),
                       [[1.5, 2.5, 0], [0.2, 0, 0]])


def test_a_map_placed_after_its_first_pose_takes_it_along(adapter):
    """Poses come in their map's frame: a frame that arrives before its map's placement is
    drawn where the map is placed once its SubmapEvent comes."""
    sid = "c0ffee000005"
    T1 = translation(2.0, 1.0, yaw=0.5)
    adapter.handle_event(sid, agent_pose(1, 0, 1))
    adapter.handle_event(sid, KeyframeEvent(1, 0, 1, agent_pose(1, 0, 1).T_map_cam))
    adapter.handle_event(sid, SubmapEvent(1, 1, T1, "start"))
    adapter.handle_event(sid, agent_pose(1, 1, 1))
    expected = np.stack([(T1 @ translation(0.05 * i, 0.5, 1.0))[:3, 3] for i in range(2)])
    assert np.allclose(adapter.trajectory_positions(sid, 1), expected)
    adapter.flush(force=True)
    assert np.allclose(adapter.nodes[f"/sessions/{sid}/camera/frustum_1"].position, expected[1])
    frusta = segment_points(adapter, f"/sessions/{sid}/keyframes/map_1/frusta")
    assert np.allclose(frusta[0, 0], translation(0.0, 0.5, 1.0)[:3, 3], atol=1e-6), "keyframe in the map frame"
    T1_new = translation(2.0, 1.2, yaw=0.5)
    adapter.handle_event(sid, PosesUpdatedEvent({1: T1_new}, {}, {1: 1}, "loop"))
    assert np.allclose(adapter.trajectory_positions(sid, 1), expected + [0, 0.2, 0])


def test_no_trajectory_segment_into_a_map_after_tracking_failure(adapter):
    sid = "c0ffee000003"
    adapter.handle_event(sid, SubmapEvent(0, 0, np.eye(4), "start"))
    for i in range(3):
        adapter.handle_event(sid, agent_pose(0, i, 0))
    adapter.handle_event(sid, SubmapEvent(1, 0, translation(5.0), "tracking_failure"))
    for i in range(3, 6):
        adapter.handle_event(sid, agent_pose(0, i, 1))
    adapter.flush(force=True)
    drawn = segment_points(adapter, f"/sessions/{sid}/trajectory/agent_0/part_0")
    assert len(drawn) == 4, "5 steps, but none across the lost-tracking jump"
    assert np.linalg.norm(drawn[:, 1] - drawn[:, 0], axis=1).max() < 0.1


def test_finished_session_from_disk_shows_every_agent(adapter, tmp_path):
    sid = "c0ffee000004"
    adapter.load_finished(sid, tmp_path / "missing.ply", {0: np.zeros((3, 3)), 1: np.ones((4, 3))})
    adapter.flush(force=True)
    assert f"/sessions/{sid}/trajectory/agent_1/part_0" in adapter.nodes
    assert len(adapter.trajectory_positions(sid, 1)) == 4
