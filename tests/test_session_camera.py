"""``GET /api/sessions/{id}/camera``: the render panel starts at the newest tracked frame with
the input camera's own intrinsics (issue 44 item 2), live and after a server restart."""

from __future__ import annotations

import numpy as np
import pytest

from server.session_state import SessionState
from slam.eval.trajectory import parse_tum
from slam.events import PoseEvent, SubmapEvent
from tests.test_server_api import (
    client,  # noqa: F401 - fixtures
    data_dir,  # noqa: F401
    needs_runtime,
    running_app,
    synthetic_session,  # noqa: F401
)


def pose_event(index: int, T: np.ndarray, K: np.ndarray | None = None, map_id: int = 0) -> PoseEvent:
    return PoseEvent(0, index, 0.1 * index, T, map_id, True, K=K, image_size=None if K is None else (160, 120))


def test_the_fold_keeps_the_newest_frame_and_its_camera_where_its_map_is_now():
    state = SessionState()
    K = np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]])
    assert state.camera_pose(0) is None
    T1 = np.eye(4)
    T1[:3, 3] = [1, 0, 0]
    state.apply(SubmapEvent(0, 0, np.eye(4), "start"))
    state.apply(pose_event(0, np.eye(4), K))
    state.apply(pose_event(1, T1))  # no K: the camera stays the last one reported
    assert state.latest[0][0] == 1 and np.allclose(state.camera_pose(0), T1)
    assert (state.cameras[0].width, state.cameras[0].height) == (160, 120) and np.allclose(state.cameras[0].K, K)
    moved = np.eye(4)
    moved[:3, 3] = [0, 2, 0]
    state.apply(SubmapEvent(0, 0, moved, "start"))  # a loop closure moves the map: the frame follows
    assert np.allclose(state.camera_pose(0)[:3, 3], [1, 2, 0])


@needs_runtime
def test_camera_of_a_finished_session_is_its_last_pose_with_the_input_camera(client, synthetic_session,  # noqa: F811
                                                                             data_dir):  # noqa: F811
    url = f"/api/sessions/{synthetic_session}"
    last = parse_tum(client.get(f"{url}/trajectory").text).poses[-1]
    for app in (client, None):
        if app is None:  # a restarted server has no events: the written trajectory and the input
            with running_app(data_dir, viewer_port=0) as second:
                camera = second.get(f"{url}/camera").json()
            assert camera["index"] is None
        else:
            camera = client.get(f"{url}/camera").json()
            assert camera["index"] == 11
        intrinsics = camera["intrinsics"]
        assert (intrinsics["width"], intrinsics["height"]) == (160, 120)
        assert 50 < intrinsics["fy"] < 400 and abs(intrinsics["cx"] - 80) < 2
        assert np.allclose(np.array(camera["T_world_cam"]), last, atol=1e-4)
        # ready for the render call as it is
        response = client.post(f"{url}/render", json={"T_world_cam": camera["T_world_cam"],
                                                      "intrinsics": intrinsics})
        assert response.status_code == 200
    missing = client.get(f"{url}/camera", params={"agent": 1})
    assert missing.status_code == 404 and "has no agent 1" in missing.json()["detail"]


def test_camera_before_the_first_frame_is_409(client):  # noqa: F811
    created = client.post("/api/sessions", json={"source": "stream", "preset": "test",
                                                  "intrinsics": "100,100,80,60"}).json()
    url = f"/api/sessions/{created['id']}"
    response = client.get(f"{url}/camera")
    assert response.status_code == 409 and "no tracked frame" in response.json()["detail"]
    assert client.delete(url).status_code == 204
