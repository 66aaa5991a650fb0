"""AR occlusion at object scale: an input frame's sensor depth hides objects wherever it
measured, the map's depth only fills its holes (``ar.scene_depth``, ``server.ar_compose``,
``server.render_calls.ar_composite``); the colour-guided refinement of a rendered depth;
a placed object stands on the picked surface's normal (``static/app.js`` ``surfacePose``)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from ar import VirtualObject, composite, make_shape
from ar.scene_depth import (
    RefineOptions,
    fill_holes,
    refine_depth,
    sensor_depth_with_map,
    window_intrinsics,
)
from server.ar_compose import Background, composite_png, scene_depth
from server.rendering import Camera

WIDTH, HEIGHT = 96, 72
K = np.array([[80.0, 0.0, 47.5], [0.0, 80.0, 35.5], [0.0, 0.0, 1.0]])
T_CAM = np.eye(4)
WALL_M, OCCLUDER_M = 2.0, 1.0
STRIPE = slice(46, 50)
"""A thin vertical occluder (a chair slat, a mug's rim): 4 columns, 5 cm at 1 m."""


def cube_behind_occluder() -> VirtualObject:
    """A 10 cm cube 15 cm behind the occluder (1.15-1.25 m), centred on it."""
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, OCCLUDER_M + 0.2]
    return VirtualObject(make_shape("cube"), T, scale=0.1)


def sensor_depth() -> np.ndarray:
    depth = np.full((HEIGHT, WIDTH), WALL_M, np.float32)
    depth[:, STRIPE] = OCCLUDER_M
    return depth


def smooth_map_depth() -> np.ndarray:
    """The map's lump at the occluder: never nearer than 1.6 m, so it hides nothing at 1.2 m."""
    columns = np.arange(WIDTH)
    lump = WALL_M - 0.4 * np.exp(-0.5 * ((columns - 47.5) / 8.0) ** 2)
    return np.broadcast_to(lump.astype(np.float32), (HEIGHT, WIDTH)).copy()


def hidden_columns(result) -> np.ndarray:
    return np.flatnonzero(result.occlusion_mask.any(axis=0))


def frame_background(depth: np.ndarray) -> Background:
    rgb = np.full((HEIGHT, WIDTH, 3), 0.5, np.float32)
    return Background(rgb, depth, Camera(T_CAM, K, WIDTH, HEIGHT), sensed=True)


def test_sensor_depth_hides_the_object_behind_a_thin_occluder_where_the_map_does_not():
    cube = cube_behind_occluder()
    rgb = np.full((HEIGHT, WIDTH, 3), 0.5, np.float32)
    over_map = composite(rgb, smooth_map_depth(), [cube], K, T_CAM)
    assert not over_map.occlusion_mask.any(), "the map's smooth depth draws the cube over the occluder"
    background = scene_depth(frame_background(sensor_depth()), [cube], lambda *_: smooth_map_depth())
    result = composite(rgb, background.depth, [cube], K, T_CAM)
    # Hidden exactly behind the stripe (its anti-aliased edge columns may go either way).
    assert set(range(STRIPE.start, STRIPE.stop)) <= set(hidden_columns(result))
    assert set(hidden_columns(result)) <= set(range(STRIPE.start - 1, STRIPE.stop + 1))
    np.testing.assert_array_equal(background.depth, sensor_depth(), "no hole: the sensor's depth is kept whole")


def test_the_map_fills_only_the_sensor_holes_under_the_objects():
    cube = cube_behind_occluder()
    sensor = sensor_depth()
    sensor[:, STRIPE] = 0.0  # the slat is too dark for the sensor
    sensor[:5, :5] = 0.0  # a hole no object covers
    calls = []

    def map_depth(K_window: np.ndarray, width: int, height: int) -> np.ndarray:
        calls.append((K_window, width, height))
        # The map sees the slat where the sensor did not: map depth of the window's columns.
        columns = np.arange(width) - K_window[0, 2] + K[0, 2]
        return np.broadcast_to(np.where((columns >= 46) & (columns < 50), OCCLUDER_M, 0.5).astype(np.float32),
                               (height, width)).copy()

    fused = sensor_depth_with_map(sensor, [cube], K, T_CAM, map_depth)
    assert len(calls) == 1, "one render, of the window around the covered holes"
    K_window, width, height = calls[0]
    assert width < WIDTH and height < HEIGHT and K_window[0, 2] < K[0, 2]
    assert fused.filled[:, STRIPE].any() and not fused.filled[:5, :5].any()
    assert (fused.depth[:5, :5] == 0).all(), "a hole under no object stays unknown"
    measured = sensor > 0
    np.testing.assert_array_equal(fused.depth[measured], sensor[measured], "the map never overrides the sensor")
    rgb = np.full((HEIGHT, WIDTH, 3), 0.5, np.float32)
    assert set(range(STRIPE.start, STRIPE.stop)) <= set(hidden_columns(composite(rgb, fused.depth, [cube], K, T_CAM)))
    without_map = sensor_depth_with_map(sensor, [cube], K, T_CAM, None)
    assert not composite(rgb, without_map.depth, [cube], K, T_CAM).occlusion_mask.any(), "holes are far without a map"


def test_fill_holes_and_window_intrinsics():
    sensor = np.array([[1.0, 0.0], [np.nan, 2.0]], np.float32)
    rendered = np.array([[5.0, 3.0], [0.0, 5.0]], np.float32)
    np.testing.assert_array_equal(fill_holes(sensor, rendered), [[1.0, 3.0], [0.0, 2.0]])
    np.testing.assert_allclose(window_intrinsics(K, (10, 4, 30, 20))[:2, 2], [37.5, 31.5])


def test_composite_png_of_a_frame_takes_its_sensor_depth_and_the_map_in_its_holes():
    cube = cube_behind_occluder()
    sensor = sensor_depth()
    sensor[:, STRIPE] = 0.0
    background = frame_background(sensor)
    _, report = composite_png(background, [cube], [True])
    hidden_pixels = report[0]["visible_pixels"]
    _, report = composite_png(background, [cube], [True], lambda Kw, w, h: np.full((h, w), OCCLUDER_M, np.float32))
    assert report[0]["visible_pixels"] < hidden_pixels, "the map's depth hides the cube in the sensor's hole"


def test_ar_composite_helper_renders_the_map_for_the_holes(monkeypatch):
    from server import render_calls
    from server.render_calls import ViewCall, ar_composite

    asked = []

    class View:
        def __init__(self, camera):
            self.depth = np.full((camera.height, camera.width), OCCLUDER_M, np.float32)

    def fake_render(call):
        asked.append(call.camera)
        return View(call.camera)

    monkeypatch.setattr(render_calls, "render_view_of", fake_render)
    cube = cube_behind_occluder()
    sensor = sensor_depth()
    sensor[:, STRIPE] = 0.0
    camera = Camera(T_CAM, K, WIDTH, HEIGHT)
    background = Background(np.full((HEIGHT, WIDTH, 3), 0.5, np.float32), sensor, camera, sensed=True,
                            map_view=ViewCall("map.pt", camera, 1))
    _, report = ar_composite(background, [cube], [True])
    assert len(asked) == 1 and asked[0].width < WIDTH, "only the window of the covered holes is rendered"
    assert report[0]["state"] == "visible"
    full = Background(background.rgb, sensor_depth(), camera, sensed=True, map_view=ViewCall("map.pt", camera, 1))
    ar_composite(full, [cube], [True])
    assert len(asked) == 1, "no hole under the cube: no render"


def test_refine_depth_moves_a_blurred_edge_onto_the_colour_edge():
    """A map's ramp from 1 m to 2 m over 8 columns; the colour steps at column 20."""
    width = 40
    ramp = np.clip((np.arange(width) - 16) / 8.0, 0.0, 1.0) + 1.0
    depth = np.broadcast_to(ramp.astype(np.float32), (10, width)).copy()
    rgb = np.zeros((10, width, 3), np.float32)
    rgb[:, 20:] = 1.0
    where = np.zeros((10, width), bool)
    where[:, 10:30] = True
    refined = refine_depth(depth, rgb, where, RefineOptions(radius=6, sigma_space=6.0))
    assert (refined[:, 12:20] < 1.3).all() and (refined[:, 20:28] > 1.7).all()
    np.testing.assert_array_equal(refined[:, :10], depth[:, :10], "outside the objects' footprint: untouched")


# ------------------------------------------------------------------ normal-up placement
APP_JS = Path(__file__).resolve().parents[1] / "static" / "app.js"


def js_function(source: str, name: str) -> str:
    match = re.search(rf"^function {name}\(.*?^}}", source, re.S | re.M)
    assert match, f"{name} not in app.js"
    return match.group(0)


def poses_from_page(calls: list[tuple[str, list]]) -> list[np.ndarray]:
    """Run the page's own yawPose / surfacePose in node for each (function, arguments)."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    source = APP_JS.read_text()
    script = "\n".join([
        "const deg = (d) => (d * Math.PI) / 180;",
        js_function(source, "yawPose"),
        js_function(source, "surfacePose"),
        f"const calls = {json.dumps(calls)};",
        "console.log(JSON.stringify(calls.map(([f, args]) => (f === 'yaw' ? yawPose : surfacePose)(...args))));",
    ])
    out = subprocess.run([node, "-e", script], capture_output=True, text=True, timeout=30, check=True)
    return [np.array(T) for T in json.loads(out.stdout)]


@pytest.mark.parametrize("normal", [[0.0, -1.0, 0.0], [0.3, -0.8, -0.5], [1.0, 0.0, 0.0], [0.0, 0.0, -2.0]])
def test_a_placed_object_takes_the_surface_normal_as_its_up_axis(normal):
    position = [0.1, 0.2, 1.5]
    (T,) = poses_from_page([("surface", [position, normal, 30.0])])
    R = T[:3, :3]
    np.testing.assert_allclose(R[:, 2], np.array(normal) / np.linalg.norm(normal), atol=1e-9)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(T[:3, 3], position)
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])


def test_on_a_level_floor_the_normal_pose_is_the_upright_one():
    """The world's up is -y: a floor's normal gives yawPose's pose, yaw included."""
    calls = [(f, [[0.0, 0.5, 2.0], *([[0.0, -1.0, 0.0]] if f == "surface" else []), yaw])
             for yaw in (0.0, 45.0) for f in ("yaw", "surface")]
    poses = poses_from_page(calls)
    for upright, on_normal in zip(poses[::2], poses[1::2]):
        np.testing.assert_allclose(on_normal, upright, atol=1e-9)


def test_the_page_offers_normal_up_on_by_default():
    html = (APP_JS.parent / "index.html").read_text()
    assert re.search(r'id="ar-normal-up" type="checkbox" checked', html)
    assert "surfacePose(" in js_function(APP_JS.read_text(), "arObject")
