"""The viewer's state without viser (``server.viewer_state``): what a session shows and what
is stale after each event, what is resent, when the browsers are framed."""

from __future__ import annotations

import numpy as np

from server.viewer_state import (
    REFRAME_GROWTH,
    TRAJECTORY_BLOCK,
    ViewerSession,
    agent_color,
    map_color,
    mesh_chunks,
    scene_bounds,
)
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

K = np.array([[80.0, 0, 40], [0, 80.0, 30], [0, 0, 1]])


def T(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = [x, y, z]
    return out


def pose(agent: int, index: int, map_id: int, T_map_cam: np.ndarray, thumbnail=None) -> PoseEvent:
    return PoseEvent(agent, index, index / 30, T_map_cam, map_id, True, thumbnail, K, (80, 60))


def square(offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    vertices = np.array([[0, 0, 0], [1.5, 0, 0], [1.5, 1.5, 0], [0, 1.5, 0]], np.float32) + [offset, 0, 0]
    return vertices.astype(np.float32), np.array([[0, 1, 2], [0, 2, 3]], np.int32)


def settle(state: ViewerSession) -> None:
    """What a flush does to the flags (the facade clears them as it sends)."""
    for view in state.maps.values():
        view.pose_dirty = view.keyframes_dirty = view.bounds_dirty = False
    for view in state.agents.values():
        view.dirty = view.camera_dirty = False
    state.loops_dirty = state.status_dirty = False


def test_events_mark_what_is_stale():
    state = ViewerSession("s")
    thumb = np.zeros((3, 4, 3), np.uint8)
    state.apply(pose(0, 0, 0, T(0.1), thumb))
    assert set(state.maps) == {0} and state.maps[0].pose_dirty
    assert state.agents[0].dirty and state.agents[0].camera_dirty
    T_cam, thumbnail = state.camera(0)
    assert np.allclose(T_cam, T(0.1)) and thumbnail is thumb
    settle(state)
    state.apply(SubmapEvent(0, 0, T(0.0), "start"))
    assert state.maps[0].pose_dirty and not state.agents[0].dirty, "placed where it was assumed: nothing moved"
    settle(state)
    state.apply(KeyframeEvent(0, 0, 0, T(0.1)))
    assert state.maps[0].keyframes_dirty
    frusta = state.keyframe_frusta(0)
    assert frusta.shape == (8, 2, 3) and np.allclose(frusta[0, 0], [0.1, 0, 0])
    settle(state)
    state.apply(LoopEvent(0, 0, 0, 0.0, 0, 3, 7, 0.0, T(0.1), T(2.0)))
    assert state.loops_dirty and set(state.maps) == {0, 3}, "a loop names its maps"
    settle(state)
    state.apply(PosesUpdatedEvent({0: T(0.0, 1.0)}, {}, {0: 0}, "loop"))
    assert state.maps[0].pose_dirty and state.agents[0].dirty and state.agents[0].camera_dirty
    assert state.loops_dirty and state.agents[0].sent_blocks == 0
    assert np.allclose(state.world_positions(0), [[0.1, 1.0, 0.0]])
    settle(state)
    state.apply(StatsEvent(1, 2, 3.25, 1, 1, 1, 10))
    assert state.status_dirty
    state.apply(PhaseEvent("refining"))
    assert "(refining)" in state.status_text() and "3.2 frames/s" in state.status_text()
    state.framed_size = 1.0
    state.apply(FinishedEvent("finished"))
    assert state.phase == "finished" and state.framed_size is None, "framed again on what it ended with"
    assert state.status_text().startswith("**s** (finished): 1 pose, 2 maps, 1 loop")


def test_trajectory_blocks_are_sent_once_complete_and_resent_when_retracked():
    state = ViewerSession("s")
    count = TRAJECTORY_BLOCK + 10
    for i in range(count):
        state.apply(pose(0, i, 0, T(0.01 * i)))
    blocks = state.trajectory_blocks(0, by_map=False)
    assert [b.part for b in blocks] == [0, 1]
    assert len(blocks[0].segments) == TRAJECTORY_BLOCK and len(blocks[1].segments) == 9
    assert (blocks[0].colors == agent_color(0)).all()
    assert state.agents[0].sent_blocks == 1, "the complete block is not sent again"
    assert [b.part for b in state.trajectory_blocks(0, by_map=False)] == [1]
    state.apply(pose(0, 3, 0, T(5.0)))  # re-tracked: its (complete) block is sent again
    assert state.agents[0].sent_blocks == 0
    assert [b.part for b in state.trajectory_blocks(0, by_map=True)][0] == 0


def test_no_trajectory_segment_into_a_map_started_after_tracking_failure():
    state = ViewerSession("s")
    state.apply(SubmapEvent(0, 0, T(), "start"))
    for i in range(3):
        state.apply(pose(0, i, 0, T(0.05 * i)))
    state.apply(SubmapEvent(1, 0, T(5.0), "tracking_failure"))
    for i in range(3, 6):
        state.apply(pose(0, i, 1, T(0.05 * i)))
    (block,) = state.trajectory_blocks(0, by_map=True)
    assert len(block.segments) == 4
    assert [tuple(c) for c in block.colors] == [map_color(0)] * 2 + [map_color(1)] * 2


def test_mesh_chunks_resent_only_when_changed_and_after_a_recolouring():
    state = ViewerSession("s")
    vertices, faces = square()
    state.apply(MapUpdateEvent(0, 1, T(), 4, np.zeros((0, 4, 4)), vertices, faces, None))
    assert state.maps[0].bounds_dirty and np.allclose(state.maps[0].bounds[1], [1.5, 1.5, 0])
    first = state.take_chunk_update(0)
    assert len(first.changed) == len(mesh_chunks(vertices, faces, None)) and not first.removed
    assert state.take_chunk_update(0) is None, "nothing pending"
    # The map moves, the mesh with it: the vertices in the map frame did not change.
    state.apply(MapUpdateEvent(0, 2, T(0.3), 4, np.zeros((0, 4, 4)), vertices, faces, None))
    update = state.take_chunk_update(0)
    assert not update.changed and update.skipped == len(first.changed)
    # The mesh moves elsewhere: the old chunks go, new ones come.
    moved, _ = square(5.0)
    state.apply(MapUpdateEvent(0, 3, T(0.3), 4, np.zeros((0, 4, 4)), moved, faces, None))
    update = state.take_chunk_update(0)
    assert set(update.removed) == set(first.changed) and update.changed
    state.resend_meshes()
    assert len(state.take_chunk_update(0).changed) == len(update.changed)


def test_framing_when_shown_and_when_grown():
    state = ViewerSession("s")
    assert state.bounds_to_frame() is None and scene_bounds(state) is None
    state.apply(pose(0, 0, 0, T(0.0)))
    state.apply(pose(0, 1, 0, T(1.0)))
    lo, hi = state.bounds_to_frame()
    assert np.allclose(lo, 0) and np.allclose(hi, [1, 0, 0]) and state.framed_size == 1.0
    state.apply(pose(0, 2, 0, T(1.2)))
    assert state.bounds_to_frame() is None, "not grown enough"
    state.apply(pose(0, 3, 0, T(REFRAME_GROWTH + 0.1)))
    assert state.bounds_to_frame() is not None
    state.shown()
    assert state.framed_size is None and state.status_dirty and state.last_update == 0.0


def test_finished_session_from_disk():
    state = ViewerSession("s")
    vertices, faces = square()
    state.load_finished(mesh_chunks(vertices, faces, None), {0: np.zeros((3, 3)), 1: np.ones((4, 3)), 2: None})
    assert set(state.agents) == {0, 1} and state.agents[1].dirty and state.pose_count == 7
    assert np.allclose(state.world_positions(1), 1.0)
    assert state.maps[0].pending_chunks and state.camera(1) is None, "no camera for a finished session"
