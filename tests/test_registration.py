"""Colour from another camera registered onto the depth camera (``slam.data.registration``):
a synthetic scene rendered from a depth camera and from a colour camera beside it with other
intrinsics, whose answer (the scene's colour seen by the depth camera) is known."""

import numpy as np
import pytest

from slam.data.frame import DataError
from slam.data.registration import ColorCamera, register_color, register_color_reference
from slam.data.synthetic import open_synthetic
from slam.data.synthetic.render import render_rgbd


def _two_cameras(width=64, height=48):
    """The depth camera's depth and true colour, the colour camera's image, and its camera:
    2.5 cm to the side, 11 % longer focal length, principal point off by a few pixels (as a
    Kinect's)."""
    seq = open_synthetic(f"synthetic:walk?frames=5&width={width}&height={height}")
    T_world_depth = seq.trajectory[2]
    K_depth = seq.K
    T_color_depth = np.eye(4)
    T_color_depth[0, 3] = -0.025
    K_color = K_depth.copy()
    K_color[0, 0] *= 1.11
    K_color[1, 1] *= 1.11
    K_color[0, 2] += 3.0
    K_color[1, 2] -= 2.0
    camera = ColorCamera(K_color, width, height, T_color_depth)
    T_world_color = T_world_depth @ np.linalg.inv(T_color_depth)
    rgb_true, depth = render_rgbd(seq.scene, K_depth, T_world_depth, width, height)
    rgb_color, _ = render_rgbd(seq.scene, K_color, T_world_color, width, height)
    return rgb_true, depth, K_depth, rgb_color, camera


def test_registered_colour_matches_what_the_depth_camera_would_see():
    rgb_true, depth, K_depth, rgb_color, camera = _two_cameras()
    registered, valid = register_color(rgb_color, depth, K_depth, camera)
    assert registered.shape == rgb_true.shape and valid.dtype == bool
    assert valid.mean() > 0.7  # the colour camera sees a narrower field: a border falls outside
    error = np.abs(registered - rgb_true).mean(-1)
    naive = np.abs(rgb_color - rgb_true).mean(-1)  # taken as if registered
    assert np.median(error[valid]) < 0.03
    assert error[valid].mean() < 0.5 * naive[valid].mean(), (error[valid].mean(), naive[valid].mean())


def test_the_vectorised_path_matches_the_plain_loop():
    rgb_true, depth, K_depth, rgb_color, camera = _two_cameras(32, 24)
    depth = depth.copy()
    depth[5:8, 10:14] = 0  # missing depth: mapped at the median depth
    fast, fast_valid = register_color(rgb_color, depth, K_depth, camera)
    plain, plain_valid = register_color_reference(rgb_color, depth, K_depth, camera)
    assert (fast_valid == plain_valid).mean() > 0.99  # rounding at the z-buffer's pixel edges
    both = fast_valid & plain_valid
    np.testing.assert_allclose(fast[both], plain[both], atol=1e-4)


def test_a_point_hidden_from_the_colour_camera_gets_no_colour():
    # A near square in front of a far wall, the colour camera 10 cm to the side: the wall just
    # beside the square is seen by the depth camera but hidden from the colour camera.
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    depth = np.full((48, 64), 3.0, np.float32)
    depth[16:32, 24:40] = 1.0
    T = np.eye(4)
    T[0, 3] = -0.10  # colour camera to the right of depth: x_color = x_depth - 0.10
    camera = ColorCamera(K, 64, 48, T)
    rgb = np.zeros((48, 64, 3), np.float32)
    _, valid = register_color(rgb, depth, K, camera)
    assert valid[16:32, 24:40].all()  # the square itself is seen
    # The wall just left of the square in the depth image (columns 21-23: x -0.68 to -0.48 m
    # at 3 m) lies in the square's shadow from the colour camera; farther left it does not.
    assert not valid[20:28, 21:24].any()
    assert valid[20:28, 5:19].all() and valid[20:28, 45:60].all()


def test_an_identity_colour_camera_changes_nothing():
    rgb_true, depth, K_depth, _, _ = _two_cameras()
    camera = ColorCamera(K_depth, 64, 48, np.eye(4))
    registered, valid = register_color(rgb_true, depth, K_depth, camera)
    assert valid.all()
    np.testing.assert_allclose(registered, rgb_true, atol=1e-5)


@pytest.mark.parametrize("bad, message", [
    (dict(K=np.eye(3) * [0, 1, 1]), "positive focal"),
    (dict(T_color_depth=np.diag([2.0, 1, 1, 1])), "rigid"),
    (dict(width=0), "size"),
    (dict(dist=[0.1, 0.2, 0.3]), "distortion"),
])
def test_a_wrong_colour_camera_is_refused_with_a_reason(bad, message):
    args = dict(K=np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]), width=64, height=48, T_color_depth=np.eye(4))
    args.update(bad)
    with pytest.raises(DataError, match=message):
        ColorCamera(**args)


def _write_two_camera_tum(root, frames=2):
    """A TUM folder whose colour comes from the colour camera of ``_two_cameras`` (at 80x60,
    its own size) and whose depth from the depth camera (64x48), with calibration.json."""
    import cv2
    import json

    seq = open_synthetic("synthetic:walk?frames=5&width=64&height=48")
    T_color_depth = np.eye(4)
    T_color_depth[0, 3] = -0.025
    K_color = np.array([[1.11 * seq.K[0, 0] * 1.25, 0, 43.0], [0, 1.11 * seq.K[1, 1] * 1.25, 28.0], [0, 0, 1]])
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    truths, lines_rgb, lines_depth = [], [], []
    for k in range(frames):
        T_wd = seq.trajectory[k]
        rgb_true, depth = render_rgbd(seq.scene, seq.K, T_wd, 64, 48)
        rgb_color, _ = render_rgbd(seq.scene, K_color, T_wd @ np.linalg.inv(T_color_depth), 80, 60)
        t = 1.0 + k / 30
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), cv2.cvtColor((rgb_color * 255).round().astype(np.uint8),
                                                                    cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(root / "depth" / f"{t:.6f}.png"), (depth * 5000).round().astype(np.uint16))
        lines_rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        lines_depth.append(f"{t:.6f} depth/{t:.6f}.png")
        truths.append(rgb_true)
    (root / "rgb.txt").write_text("\n".join(lines_rgb) + "\n")
    (root / "depth.txt").write_text("\n".join(lines_depth) + "\n")
    K = seq.K
    (root / "intrinsics.txt").write_text(f"{K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")
    calibration = {"color_intrinsics": [K_color[0, 0], K_color[1, 1], K_color[0, 2], K_color[1, 2], 80, 60],
                   "T_color_depth": T_color_depth.tolist()}
    (root / "calibration.json").write_text(json.dumps(calibration))
    return truths


def test_a_dataset_with_its_colour_camera_is_read_registered(tmp_path):
    from slam.data import open_sequence
    from slam.data.registration import read_color_calibration

    root = tmp_path / "two_cameras"
    truths = _write_two_camera_tum(root)
    camera = read_color_calibration(root / "calibration.json")
    registered = open_sequence(root, color_camera=camera)
    frame = registered[1]
    assert frame.rgb.shape == (48, 64, 3) and frame.color_valid is not None
    error = np.abs(frame.rgb - truths[1]).mean(-1)[frame.color_valid]
    assert np.median(error) < 0.03
    with pytest.raises(DataError, match="rgb and depth sizes differ"):
        open_sequence(root)[0]  # without its colour camera the sizes disagree, and it says so


def test_the_cli_refuses_half_a_colour_camera(tmp_path, capsys):
    from slam.cli import main

    root = tmp_path / "two_cameras"
    _write_two_camera_tum(root, frames=1)
    code = main(["run", str(root), "--out", str(tmp_path / "out"), "--preset", "test",
                 "--depth-to-color", ",".join(["1", "0", "0", "0"] * 4)])
    assert code == 2 and "--depth-to-color needs --color-intrinsics" in capsys.readouterr().err
    code = main(["run", str(root), "--out", str(tmp_path / "out"), "--preset", "test",
                 "--color-intrinsics", "60,60,40,30,81,60"])
    assert code == 2 and "colour camera's intrinsics are for 81x60" in capsys.readouterr().err


def test_an_upload_names_what_is_wrong_with_its_colour_camera():
    from server.upload import UploadError, parse_color_camera

    assert parse_color_camera(None, None) == (None, None)
    intrinsics, transform = parse_color_camera("60,60,40,30,80,60", ",".join(str(v) for v in np.eye(4).ravel()))
    assert intrinsics == (60.0, 60.0, 40.0, 30.0, 80.0, 60.0) and len(transform) == 16
    for color, depth_to_color, message in [(None, "1,0,0,0", "needs color_intrinsics"),
                                           ("60,60,40,30", None, "6, 10 or 11 numbers"),
                                           ("60,60,40,30,80,x", None, "comma-separated numbers"),
                                           ("60,60,40,30,80,60", "1,2,3", "16 \\(4x4\\) or 12"),
                                           ("60,60,40,30,80,60", ",".join(["2"] * 16), "rigid")]:
        with pytest.raises(UploadError, match=message):
            parse_color_camera(color, depth_to_color)


def test_a_run_writes_how_each_source_got_its_colour(tmp_path):
    # Given: the calibration's camera in run.json. Estimated: a registered folder's colour is
    # estimated, found registered already, and left as it is (``slam.data.selfcalibration``).
    import json

    from slam.cli import main
    from slam.data import open_sequence

    root = tmp_path / "two_cameras"
    _write_two_camera_tum(root, frames=2)
    assert main(["run", str(root), "--out", str(tmp_path / "given"), "--preset", "test", "--quiet",
                 "--calibration", str(root / "calibration.json")]) == 0
    cameras = json.loads((tmp_path / "given" / "run.json").read_text())["color_cameras"]
    assert cameras[0]["source"] == "given" and cameras[0]["width"] == 80
    np.testing.assert_allclose(np.asarray(cameras[0]["T_color_depth"])[0, 3], -0.025)

    seq = open_synthetic("synthetic:walk?frames=30&width=160&height=120")
    registered = tmp_path / "registered"
    (registered / "rgb").mkdir(parents=True)
    (registered / "depth").mkdir()
    lines = {"rgb": [], "depth": []}
    for k in range(0, 30, 3):
        import cv2

        frame, t = seq[k], 1.0 + k / 30
        cv2.imwrite(str(registered / "rgb" / f"{t:.6f}.png"),
                    cv2.cvtColor((frame.rgb * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(registered / "depth" / f"{t:.6f}.png"), (frame.depth * 5000).round().astype(np.uint16))
        lines["rgb"].append(f"{t:.6f} rgb/{t:.6f}.png")
        lines["depth"].append(f"{t:.6f} depth/{t:.6f}.png")
    for kind, rows in lines.items():
        (registered / f"{kind}.txt").write_text("\n".join(rows) + "\n")
    K = seq.K
    (registered / "intrinsics.txt").write_text(f"{K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")
    sequence = open_sequence(registered)
    warp = sequence.calibrate_colour()
    assert warp is not None and not warp.applied and sequence.color_warp is warp
    before = sequence[4].rgb
    np.testing.assert_array_equal(before, open_sequence(registered)[4].rgb)  # nothing changed


def test_a_stream_with_its_colour_camera_gets_registered_frames(tmp_path):
    import cv2

    from server.stream import StreamInput
    from server.upload import UploadError

    rgb_true, depth, K_depth, rgb_color, camera = _two_cameras()
    stream = StreamInput(None, tmp_path / "input", intrinsics=(K_depth[0, 0], K_depth[1, 1], K_depth[0, 2], K_depth[1, 2]),
                         depth_scale=5000.0, put_timeout_s=1.0, color_camera=camera)
    color_png = cv2.imencode(".png", cv2.cvtColor((rgb_color * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))[1]
    depth_png = cv2.imencode(".png", (depth * 5000).round().astype(np.uint16))[1]
    assert stream.add_frame(color_png.tobytes(), depth_png.tobytes(), timestamp=1.0) == 0
    frame = stream.frame_queue.get_nowait()
    assert frame.rgb.shape == (48, 64, 3) and frame.color_valid is not None
    error = np.abs(frame.rgb / 255.0 - rgb_true).mean(-1)[frame.color_valid]
    assert np.median(error) < 0.03
    recorded = cv2.imread(str(next((tmp_path / "input" / "color").iterdir())))
    assert recorded.shape[:2] == (48, 64)  # what replays read: the registered colour
    wrong = cv2.imencode(".png", np.zeros((60, 81, 3), np.uint8))[1]
    with pytest.raises(UploadError, match="colour camera is 64x48"):
        stream.add_frame(wrong.tobytes(), depth_png.tobytes(), timestamp=2.0)
    assert stream.frames_refused == 1

