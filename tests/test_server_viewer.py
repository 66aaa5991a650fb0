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
    chunk_changed,
    frustum_segments,
    map_color,
    mesh_chunks,
)
from slam.events import KeyframeEvent, LoopEvent, MapUpdateEvent, PoseEvent, StatsEvent


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


def mesh_event(mesh: trimesh.Trimesh, T_world_map: np.ndarray, version: int) -> MapUpdateEvent:
    vertices = np.asarray(mesh.vertices) @ T_world_map[:3, :3].T + T_world_map[:3, 3]
    return MapUpdateEvent(0, version, T_world_map, 100, np.zeros((0, 4, 4)), vertices.astype(np.float32),
                          np.asarray(mesh.faces, np.int32), np.full((len(mesh.vertices), 3), 150, np.uint8))


def test_scene_nodes_and_only_changed_chunks_resent(adapter):
    sid = "0123456789ab"
    mesh = box_mesh()
    for i in range(5):
        adapter.handle_event(sid, pose_event(i))
    adapter.handle_event(sid, KeyframeEvent(0, 0, 0, pose_event(0).T_world_cam))
    adapter.handle_event(sid, mesh_event(mesh, np.eye(4), 1))
    adapter.handle_event(sid, StatsEvent(5, 10, 4.0, 1, 1, 0, 100))
    adapter.flush(force=True)
    names = set(adapter._handles)
    assert f"/sessions/{sid}/camera/frustum" in names
    assert f"/sessions/{sid}/meshes/map_0" in names
    first = adapter.stats.chunks_sent
    assert first == len(mesh_chunks(mesh.vertices, mesh.faces, None))

    # A loop correction moves the whole map: the node moves, no chunk is resent.
    T_corrected = np.eye(4)
    T_corrected[:3, 3] = [0.3, -0.2, 0.0]
    adapter.handle_event(sid, mesh_event(mesh, T_corrected, 2))
    adapter.handle_event(sid, LoopEvent(0, 0, 4, 0, 0.95, T_corrected, np.eye(4)))
    adapter.flush(force=True)
    assert adapter.stats.chunks_sent == first
    assert adapter.stats.chunks_skipped >= first
    assert np.allclose(adapter._handles[f"/sessions/{sid}/meshes/map_0"].position, [0.3, -0.2, 0.0])
    assert f"/sessions/{sid}/loops" in adapter._handles

    # The mesh grows on one side: only the chunks there are sent again.
    grown = trimesh.util.concatenate([mesh, trimesh.creation.box((0.5, 0.5, 0.5)).apply_translation([3.2, 0, 0])])
    adapter.handle_event(sid, mesh_event(grown, T_corrected, 3))
    adapter.flush(force=True)
    new_chunks = adapter.stats.chunks_sent - first
    assert 0 < new_chunks < first

    adapter.remove_session(sid)
    assert not any(name.startswith(f"/sessions/{sid}") for name in adapter._handles)


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
