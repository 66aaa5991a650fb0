"""Camera paths and their videos (issue 44 item 9): the spline passes through its keyframes at
an even pace, normals from depth, and the API renders an MP4 in the background."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from slam.camera_path import CameraPath, keyframe_times, normals_from_depth, path_poses
from tests.test_server_api import (
    camera_looking_at,
    client,  # noqa: F401 - fixtures
    data_dir,  # noqa: F401
    needs_runtime,
    synthetic_session,  # noqa: F401
)


def look_at(eye, target) -> np.ndarray:
    """T_world_cam at ``eye`` looking at ``target``, world z up, OpenCV axes."""
    return np.array(camera_looking_at(target, eye)["T_world_cam"])


def circle_keys(n: int = 4, radius: float = 1.0) -> np.ndarray:
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([look_at([radius * np.cos(a), radius * np.sin(a), 1.0], [0, 0, 1.0]) for a in angles])


def test_path_passes_through_its_keyframes_and_stays_rigid():
    keys = circle_keys(4)[:3]
    poses = path_poses(CameraPath(keys, duration_s=2.0, fps=25))
    assert poses.shape == (50, 4, 4)
    assert np.allclose(poses[0], keys[0], atol=1e-9) and np.allclose(poses[-1], keys[-1], atol=1e-9)
    R = poses[:, :3, :3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(R), 1.0)
    # the middle keyframe is on the path, at its time
    t = keyframe_times(keys)
    middle = int(round(t[1] * 49))
    assert np.linalg.norm(poses[middle, :3, 3] - keys[1, :3, 3]) < 0.05


def test_a_loop_closes_smoothly_at_an_even_pace():
    keys = circle_keys(4)
    poses = path_poses(CameraPath(keys, duration_s=4.0, fps=25, loop=True))
    positions = poses[:, :3, 3]
    steps = np.linalg.norm(np.diff(np.concatenate([positions, positions[:1]]), axis=0), axis=1)
    assert steps.max() / steps.min() < 1.5, "even pace, the seam included"
    radius = np.linalg.norm(positions[:, :2], axis=1)
    assert np.allclose(radius, 1.0, atol=0.1), "a cubic through four points of a circle stays near it"
    # every camera still looks roughly at the centre
    to_centre = np.array([0, 0, 1.0]) - positions
    to_centre /= np.linalg.norm(to_centre, axis=1, keepdims=True)
    assert (np.einsum("ni,ni->n", poses[:, :3, 2], to_centre) > 0.95).all()


def test_a_pure_turn_still_takes_time_and_bad_paths_are_refused():
    T = np.eye(4)
    turned = look_at([0, 0, 0], [1, 0, 0.0])
    poses = path_poses(CameraPath(np.stack([T, turned]), duration_s=1.0, fps=10))
    angles = [np.degrees(np.arccos(np.clip((np.trace(p[:3, :3].T @ poses[0, :3, :3]) - 1) / 2, -1, 1)))
              for p in poses]
    assert np.all(np.diff(angles) > 0), "the turn is spread over the frames"
    with pytest.raises(ValueError, match="at least 2"):
        CameraPath(T[None])
    with pytest.raises(ValueError, match="rigid"):
        CameraPath(np.stack([T, 2 * T]))
    with pytest.raises(ValueError, match="at most"):
        CameraPath(np.stack([T, T]), duration_s=150, fps=60)


def test_normals_of_a_tilted_plane():
    K = np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])
    v, u = np.mgrid[0:60, 0:80].astype(float)
    # the plane z = 2 + 0.5 x seen by the camera: depth along each ray
    x_over_z = (u - 40) / 100
    depth = 2.0 / (1 - 0.5 * x_over_z)
    normals = normals_from_depth(depth, K)
    expected = np.array([0.5, 0.0, -1.0]) / np.linalg.norm([0.5, 0.0, -1.0])
    inner = normals[5:-5, 5:-5].reshape(-1, 3)
    assert np.allclose(inner, expected, atol=1e-6)
    assert (normals[0] == 0).all() and (normals[:, -1] == 0).all(), "no normal without both neighbours"




@needs_runtime
def test_the_api_renders_a_path_video_in_the_background(client, synthetic_session):  # noqa: F811
    from slam.eval.trajectory import parse_tum

    url = f"/api/sessions/{synthetic_session}/render/path"
    poses = parse_tum(client.get(f"/api/sessions/{synthetic_session}/trajectory").text).poses
    intrinsics = {"fx": 60.0, "fy": 60.0, "cx": 40.0, "cy": 30.0, "width": 80, "height": 60}
    body = {"keyframes": [poses[0].tolist(), poses[6].tolist(), poses[-1].tolist()], "intrinsics": intrinsics,
            "duration_s": 1.0, "fps": 8, "outputs": ["color", "depth", "normals"]}
    started = client.post(url, json=body)
    assert started.status_code == 202, started.text
    job = started.json()
    assert job["frames_total"] == 8 and job["state"] in ("queued", "rendering")
    deadline = time.monotonic() + 120
    while job["state"] not in ("finished", "failed"):
        assert time.monotonic() < deadline, job
        time.sleep(0.3)
        job = client.get(f"{url}/{job['id']}").json()
    assert job["state"] == "finished" and job["frames_done"] == 8, job
    video = client.get(job["video"])
    assert video.status_code == 200 and video.headers["content-type"] == "video/mp4"
    assert video.content[4:8] == b"ftyp", "an MP4 container"
    path = data_dir_file(video.content)
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    assert len(frames) == 8 and frames[0].shape == (60, 240, 3), (len(frames), frames[0].shape if frames else None)
    colour, depth = frames[0][:, :80], frames[0][:, 80:160]
    assert colour.std() > 5 and depth.std() > 5, "the panels show the map"
    assert capture.get(cv2.CAP_PROP_FOURCC) and int(capture.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little") in \
        (b"avc1", b"h264", b"H264")


def data_dir_file(content: bytes):
    import tempfile
    from pathlib import Path

    path = Path(tempfile.mkdtemp()) / "video.mp4"
    path.write_bytes(content)
    return path


def test_bad_path_requests_say_what_is_wrong(client):  # noqa: F811
    created = client.post("/api/sessions", json={"source": "stream", "preset": "test",
                                                  "intrinsics": "100,100,80,60"}).json()
    url = f"/api/sessions/{created['id']}/render/path"
    intrinsics = {"fx": 60.0, "fy": 60.0, "cx": 40.0, "cy": 30.0, "width": 80, "height": 60}
    eye = np.eye(4).tolist()
    one = client.post(url, json={"keyframes": [eye], "intrinsics": intrinsics})
    assert one.status_code == 422 and "keyframes" in one.json()["detail"]
    skew = (2 * np.eye(4)).tolist()
    skew[3][3] = 1.0
    bad = client.post(url, json={"keyframes": [eye, skew], "intrinsics": intrinsics})
    assert bad.status_code == 422 and "keyframes[1]" in bad.json()["detail"]
    big = client.post(url, json={"keyframes": [eye, eye], "intrinsics": {**intrinsics, "width": 1280,
                                                                         "height": 720, "cx": 640, "cy": 360}})
    assert big.status_code == 422 and "640x480" in big.json()["detail"]
    no_map = client.post(url, json={"keyframes": [eye, eye], "intrinsics": intrinsics})
    assert no_map.status_code == 409 and "no map yet" in no_map.json()["detail"]
    assert client.get(f"{url}/nope").status_code == 404
    assert client.delete(f"/api/sessions/{created['id']}").status_code == 204


@needs_runtime
def test_render_path_command_flies_through_a_run(client, synthetic_session, tmp_path, capsys):  # noqa: F811
    from slam.cli import main

    run_dir = client.app.state.manager.session_dir(synthetic_session)
    out = tmp_path / "fly.mp4"
    code = main(["render-path", str(run_dir), "--out", str(out), "--every", "4", "--fps", "4",
                 "--intrinsics", "60,60,40,30,80,60", "--outputs", "color,normals"])
    assert code == 0
    assert "12 frames through 4 keyframes, color | normals" in capsys.readouterr().out
    capture = cv2.VideoCapture(str(out))
    ok, frame = capture.read()
    assert ok and frame.shape == (60, 160, 3)
    assert main(["render-path", str(tmp_path), "--out", str(out)]) == 2
    assert "map.pt" in capsys.readouterr().err


def test_a_path_preview_is_drawn_in_the_viewer_and_cleared(tmp_path):
    """Issue 44 item 9: the page's keyframes drawn as the smooth path in the 3D viewer."""
    from tests.test_server_api import running_app

    with running_app(tmp_path, viewer_port=0) as app:
        created = app.post("/api/sessions", json={"source": "stream", "preset": "test",
                                                  "intrinsics": "100,100,80,60"}).json()
        url = f"/api/sessions/{created['id']}/render/path/preview"
        keys = [np.array(camera_looking_at([0, 0, 0], eye)["T_world_cam"]).tolist()
                for eye in ([1, 0, 1], [0, 1, 1], [-1, 0, 1])]
        assert app.put(url, json={"keyframes": keys, "loop": True}).status_code == 204
        handles = app.app.state.viewer.nodes
        line = np.asarray(handles[f"/sessions/{created['id']}/path/line"].points)
        assert line.shape == (119, 2, 3), "120 frames of a closed path: 119 segments"
        assert np.allclose(line[0, 0], [1, 0, 1], atol=1e-6), "it starts at the first keyframe"
        assert f"/sessions/{created['id']}/path/cameras" in handles
        bad = app.put(url, json={"keyframes": keys[:1]})
        assert bad.status_code == 422
        assert app.delete(url).status_code == 204
        assert f"/sessions/{created['id']}/path/line" not in handles
        assert app.put("/api/sessions/0123456789ab/render/path/preview", json={"keyframes": keys}).status_code == 404
