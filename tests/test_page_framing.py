"""The viewer follows the page (issue 20, item 1) and frames what it shows; its panel's
frames/s and phase are the status's (item 2). Real viser, no browser."""

from __future__ import annotations

import numpy as np
import pytest

from server.viewer import FRAME_DIRECTION, MIN_FRAME_RADIUS_M, ViewerAdapter, framing
from slam.events import PhaseEvent, PoseEvent, StatsEvent


@pytest.fixture()
def adapter():
    viewer = ViewerAdapter("127.0.0.1", 0)
    viewer.start()
    yield viewer
    viewer.stop()


def pose(i: int) -> PoseEvent:
    T = np.eye(4)
    T[0, 3] = 0.01 * i
    return PoseEvent(agent=0, frame_index=i, timestamp=i / 30, T_map_cam=T, map_id=0, tracking_ok=True)


@pytest.mark.parametrize("size", [0.2, 1.0, 8.0])
def test_framing_fits_the_bounds_whatever_their_size(size):
    lo, hi = np.array([1.0, 2.0, 0.0]), np.array([1.0, 2.0, 0.0]) + size
    fov = np.radians(60)
    position, look_at = framing(lo, hi, fov)
    np.testing.assert_allclose(look_at, (lo + hi) / 2)
    radius = max(0.5 * np.linalg.norm(hi - lo), MIN_FRAME_RADIUS_M)
    distance = np.linalg.norm(position - look_at)
    # The bounding sphere spans the view's height: a small mesh is not a speck.
    assert distance == pytest.approx(radius / np.tan(fov / 2))
    np.testing.assert_allclose((position - look_at) / distance, FRAME_DIRECTION)


def test_select_shows_a_session_before_its_first_event(adapter):
    adapter.handle_event("aaaaaaaaaaaa", pose(0))
    adapter.flush(force=True)
    assert adapter.selected == "aaaaaaaaaaaa"
    adapter.select("bbbbbbbbbbbb")  # created a moment ago: queued, no event yet
    assert adapter.selected == "bbbbbbbbbbbb"
    assert "bbbbbbbbbbbb" in adapter.session_ids()
    for i in range(3):
        adapter.handle_event("bbbbbbbbbbbb", pose(i))
        adapter.handle_event("aaaaaaaaaaaa", pose(i + 1))
    adapter.flush(force=True)
    assert adapter.selected == "bbbbbbbbbbbb", "events of another session do not take the viewer away"
    assert adapter._sessions["bbbbbbbbbbbb"].framed_size is not None, "framed once it had something to show"


def test_panel_shows_the_phase_and_the_forwarded_frames_per_second(adapter):
    session = "cccccccccccc"
    adapter.handle_event(session, PhaseEvent("tracking"))
    adapter.handle_event(session, pose(0))
    adapter.handle_event(session, StatsEvent(frames_done=1, frames_total=5, fps=2.345, keyframes=1, maps=1,
                                             loops=0, voxels=10))
    adapter.flush(force=True)
    assert "(tracking)" in adapter.status_line() and "2.3 frames/s" in adapter.status_line()
    adapter.handle_event(session, PhaseEvent("refining"))
    adapter.flush(force=True)
    assert "(refining)" in adapter.status_line(), "a phase change alone refreshes the panel"
