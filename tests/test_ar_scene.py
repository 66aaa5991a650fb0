"""AR in a reconstructed scene (issue 6): virtual objects hidden by the neural map's rendered
depth as they are by the exact depth, and the ``voxfusion ar`` command (``ar.cli``).

Figure 1 of the issue: in the synthetic room (exact depth), a cube stands under the table so
that the table top hides part of it (it floats clear of every surface). A neural map is built from a few frames with their GT
poses; the cube is composited at a frame once with the map's rendered depth and once with
the exact depth, and the occlusion masks are compared. The issue's bar (IoU >= 0.95) is held
by ``benchmarks/bench_ar_occlusion.py`` with a fully trained map; the few seconds of training
affordable here give a weaker map, so this test holds a lower bar (see MIN_TEST_IOU).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from ar import VirtualObject, composite, make_shape, render_objects
from ar.cli import (
    MASK_HIDDEN,
    MASK_VISIBLE,
    ARInputError,
    cmd_ar,
    main,
    parse_intrinsics,
    parse_pose,
)
from ar.occlusion import compare_occlusion, hidden_fraction
from slam.checkpoint import save_checkpoint
from slam.config import apply_overrides, preset
from slam.data import open_sequence
from slam.frames import backproject, prepare_frame
from slam.mapping import Mapper, TrackedFrame
from slam.maps import MapSet, SubMap
from slam.views import render_view

SEQUENCE = "synthetic:orbit?frames=20&width=160&height=120"
MAP_FRAMES = (0, 5, 10, 14, 19)
AR_FRAME = 10
"""The AR view is an input frame (the map was trained on it), as when objects are shown in the
live camera image; the benchmark also reports a held-out view."""
MAP_CONFIG = apply_overrides(preset("cpu"), {
    # The cpu preset's decoder (the test preset's is too narrow to place the table's edges
    # within a pixel), with 4 cm steps and a quarter of its rays: ~15 s of CPU here.
    "render": {"step_ratio": 0.2},
    "mapping": {"num_rays": 128, "iterations": 10, "first_frame_iterations": 60},
    "runtime": {"device": "cpu"},
})
FINAL_ITERATIONS = 150
"""Window optimisation after the last frame, as the mapper runs while the camera rests."""
MIN_TEST_IOU = 0.88
"""Measured 0.92 (occlusion) and 0.95 (visible part) with this map on this machine; the
issue's 0.95 is the benchmark's bar, reached there with the full cpu preset."""


@pytest.fixture(scope="module", autouse=True)
def single_thread():
    """One torch thread: on the shared 2-core machine spinning workers only cost time."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def sequence():
    return open_sequence(SEQUENCE)


def cube_under_table(scene) -> VirtualObject:
    """A 0.5 m cube under the synthetic table (15 cm above the floor, 7 cm below the table top,
    4 cm from the legs), whose upper part the table top hides from the orbit's cameras."""
    table = scene.objects[0]
    T_world_obj = np.eye(4)
    T_world_obj[:3, 3] = (table.centre[0], table.centre[1], table.height - 0.36)
    return VirtualObject(make_shape("cube"), T_world_obj, scale=0.5, color=(0.9, 0.2, 0.2))


def build_map(sequence, frames, config, final_iterations: int) -> MapSet:
    """The neural map of ``frames`` mapped at their GT poses (no tracking)."""
    mapper = Mapper(config, torch.device("cpu"))
    for index in frames:
        frame = sequence[index]
        tensors = prepare_frame(frame, None, torch.device("cpu"), config.voxel.max_depth)
        mapper.process(TrackedFrame(tensors, torch.from_numpy(frame.T_world_cam).float()))
    # In rounds, each over a fresh random keyframe window, so every frame keeps training.
    for _ in range(final_iterations // config.mapping.iterations):
        mapper.optimize(mapper.current, config.mapping.iterations)
    return mapper.maps


@pytest.fixture(scope="module")
def neural_map(sequence) -> MapSet:
    return build_map(sequence, MAP_FRAMES, MAP_CONFIG, FINAL_ITERATIONS)


# ---------------------------------------------------------------------------- figure 1
def test_cube_is_partly_hidden_by_the_table(sequence):
    """The figure is only meaningful when a good share of the object is hidden, not all."""
    frame = sequence[AR_FRAME]
    result = composite(frame.rgb, frame.depth, [cube_under_table(sequence.scene)], frame.K, frame.T_world_cam)
    assert 0.3 <= hidden_fraction(result) <= 0.7
    # The hidden part lies above the visible one: the table top hides the cube's top.
    hidden_rows = np.nonzero(result.occlusion_mask.any(axis=1))[0]
    visible_rows = np.nonzero(result.object_mask.any(axis=1))[0]
    assert np.median(hidden_rows) < np.median(visible_rows)


def test_neural_map_depth_hides_the_cube_as_the_exact_depth_does(sequence, neural_map):
    frame = sequence[AR_FRAME]
    view = render_view(neural_map, frame.T_world_cam, frame.K, frame.width, frame.height)
    objects = [cube_under_table(sequence.scene)]
    comparison = compare_occlusion(frame.rgb, frame.depth, view.depth, objects, frame.K, frame.T_world_cam)
    assert 0.3 <= comparison.hidden_fraction <= 0.7
    assert comparison.occlusion_iou >= MIN_TEST_IOU, comparison.occlusion_iou
    assert comparison.object_iou >= MIN_TEST_IOU, comparison.object_iou
    # Without a scene depth nothing is hidden: the agreement above comes from the map.
    blind = compare_occlusion(frame.rgb, frame.depth, np.zeros_like(view.depth), objects, frame.K, frame.T_world_cam)
    assert blind.occlusion_iou == 0.0


def test_compare_occlusion_of_identical_depths_is_perfect(sequence):
    frame = sequence[AR_FRAME]
    objects = [cube_under_table(sequence.scene)]
    same = compare_occlusion(frame.rgb, frame.depth, frame.depth, objects, frame.K, frame.T_world_cam)
    assert same.occlusion_iou == 1.0 and same.object_iou == 1.0
    np.testing.assert_array_equal(same.candidate.rgb, same.reference.rgb)
    with pytest.raises(ValueError, match="candidate_depth"):
        compare_occlusion(frame.rgb, frame.depth, frame.depth[:-1], objects, frame.K, frame.T_world_cam)


# ---------------------------------------------------------------------------- the CLI
CLI_WIDTH, CLI_HEIGHT = 64, 48
CLI_K = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])
CLI_INTRINSICS = "50,50,31.5,23.5,64,48"
OBJECT_DEPTH = 0.6
"""The CLI's cube floats this far in front of the camera, nearer than any mapped surface."""


@pytest.fixture(scope="module")
def tiny_map(sequence, tmp_path_factory) -> Path:
    """An untrained map (allocated voxels, initial embeddings) of one synthetic frame: enough
    for the command's plumbing; its renders are not meaningful."""
    config = preset("test")
    frame = sequence[0]
    submap = SubMap.create(0, 0, config, torch.device("cpu"))
    tensors = prepare_frame(frame, None, torch.device("cpu"), config.voxel.max_depth)
    submap.voxels.allocate(backproject(tensors, torch.from_numpy(frame.T_world_cam).float(), 4, (0.0,)))
    return save_checkpoint(MapSet(config, [submap]), tmp_path_factory.mktemp("map") / "map.pt")


def camera_pose(sequence) -> np.ndarray:
    return sequence[0].T_world_cam


def cube_spec(T_world_cam: np.ndarray) -> list[dict]:
    """A 0.2 m cube OBJECT_DEPTH in front of the camera, in the object spec format."""
    T_world_obj = np.eye(4)
    T_world_obj[:3, 3] = T_world_cam[:3, :3] @ [0.0, 0.0, OBJECT_DEPTH] + T_world_cam[:3, 3]
    return [{"shape": "cube", "T_world_obj": T_world_obj.tolist(), "scale": 0.2, "color": [1.0, 0.0, 0.0]}]


def write_json(path: Path, value) -> Path:
    path.write_text(json.dumps(value))
    return path


def read_rgb(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None, path
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def cube_coverage(T_world_cam: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels the CLI's cube fully covers."""
    spec = cube_spec(T_world_cam)[0]
    cube = VirtualObject(make_shape("cube"), np.array(spec["T_world_obj"]), scale=spec["scale"])
    return render_objects([cube], CLI_K, T_world_cam, CLI_WIDTH, CLI_HEIGHT).coverage == 1.0


def ar_args(tiny_map: Path, objects: Path, pose: str, out: Path, *extra: str) -> list[str]:
    return [str(tiny_map), "--objects", str(objects), "--pose", pose, "--intrinsics", CLI_INTRINSICS,
            "--out", str(out), *extra]


def test_cli_composites_over_the_rendered_map(sequence, tiny_map, tmp_path):
    T = camera_pose(sequence)
    pose = ",".join(f"{v:.17g}" for v in T.reshape(-1))
    objects = write_json(tmp_path / "objects.json", cube_spec(T))
    empty = write_json(tmp_path / "none.json", [])
    assert main(ar_args(tiny_map, objects, pose, tmp_path / "ar.png", "--mask-out", str(tmp_path / "mask.png"))) == 0
    assert main(ar_args(tiny_map, empty, pose, tmp_path / "plain.png")) == 0
    composited, plain = read_rgb(tmp_path / "ar.png"), read_rgb(tmp_path / "plain.png")
    assert composited.shape == plain.shape == (CLI_HEIGHT, CLI_WIDTH, 3)
    covered = cube_coverage(T)
    assert covered.sum() > 50
    # The cube's pixels are red (Lambert-shaded), the rest is the map's render unchanged.
    assert (np.abs(composited.astype(int) - plain.astype(int)).sum(-1)[covered] > 30).all()
    assert (composited[covered][:, 0] > 2 * composited[covered][:, 1:].max(-1)).all()
    outside = ~cube_coverage_dilated(covered)
    np.testing.assert_array_equal(composited[outside], plain[outside])
    mask = cv2.imread(str(tmp_path / "mask.png"), cv2.IMREAD_UNCHANGED)
    assert mask.shape == (CLI_HEIGHT, CLI_WIDTH) and mask.dtype == np.uint8
    assert (mask[covered] == MASK_VISIBLE).all()


def cube_coverage_dilated(covered: np.ndarray) -> np.ndarray:
    """The covered pixels and their neighbours (the anti-aliased edge)."""
    return cv2.dilate(covered.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)


@pytest.mark.parametrize("wall_depth, hidden", [(0.4, True), (3.0, False)])
def test_cli_real_frame_depth_decides_the_occlusion(sequence, tiny_map, tmp_path, wall_depth, hidden):
    """Over an input frame with its depth: a wall in front of the cube hides it wholly."""
    T = camera_pose(sequence)
    rng = np.random.default_rng(0)
    background = rng.integers(0, 256, (CLI_HEIGHT, CLI_WIDTH, 3), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "rgb.png"), cv2.cvtColor(background, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(tmp_path / "depth.png"), np.full((CLI_HEIGHT, CLI_WIDTH), wall_depth * 5000, np.uint16))
    objects = write_json(tmp_path / "objects.json", cube_spec(T))
    pose_file = write_json(tmp_path / "pose.json", T.tolist())
    code = main(ar_args(tiny_map, objects, str(pose_file), tmp_path / "ar.png", "--background", str(tmp_path / "rgb.png"),
                        "--background-depth", str(tmp_path / "depth.png"), "--depth-scale", "5000",
                        "--mask-out", str(tmp_path / "mask.png")))
    assert code == 0
    composited = read_rgb(tmp_path / "ar.png")
    mask = cv2.imread(str(tmp_path / "mask.png"), cv2.IMREAD_UNCHANGED)
    covered = cube_coverage(T)
    if hidden:
        np.testing.assert_array_equal(composited, background)
        assert (mask[covered] == MASK_HIDDEN).all() and not (mask == MASK_VISIBLE).any()
    else:
        assert (mask[covered] == MASK_VISIBLE).all()
        assert (np.abs(composited.astype(int) - background.astype(int)).sum(-1)[covered] > 0).all()
        outside = ~cube_coverage_dilated(covered)
        np.testing.assert_array_equal(composited[outside], background[outside])


def test_pose_forms_agree(tmp_path):
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.array([0.1, -0.2, 0.3]))[0]
    T[:3, 3] = (1.0, -2.0, 0.5)
    inline = " ".join(f"{v:.17g}" for v in T.reshape(-1))
    as_json = json.dumps(T.tolist())
    in_file = tmp_path / "pose.txt"
    in_file.write_text("\n".join(" ".join(f"{v:.17g}" for v in row) for row in T))
    for text in (inline, inline.replace(" ", ","), as_json, str(in_file)):
        np.testing.assert_array_equal(parse_pose(text), T)
    K, width, height = parse_intrinsics("500,510,319.5,239.5,640,480")
    np.testing.assert_array_equal(K, [[500, 0, 319.5], [0, 510, 239.5], [0, 0, 1]])
    assert (width, height) == (640, 480)


@pytest.mark.parametrize("text, message", [
    ("1 2 3", "16 numbers"),
    ("[[1, 0], [0, 1]]", "16 numbers"),
    ("2 0 0 0  0 1 0 0  0 0 1 0  0 0 0 1", "rotation"),
    ("1 0 0 0  0 1 0 0  0 0 1 0  0 0 1 1", "last row"),
    ("not-a-pose", "not a file"),
])
def test_bad_pose_is_named(text, message):
    with pytest.raises(ARInputError, match=message):
        parse_pose(text)


@pytest.mark.parametrize("text, message", [
    ("500,500,320,240", "6 numbers"), ("500,500,320,240,64.5,48", "integers"), ("0,500,320,240,64,48", "positive"),
    ("a,b,c,d,e,f", "numbers"),
])
def test_bad_intrinsics_are_named(text, message):
    with pytest.raises(ARInputError, match=message):
        parse_intrinsics(text)


def bad_case(name: str, tmp_path: Path, tiny_map: Path, T: np.ndarray) -> tuple[list[str], str]:
    """Arguments of one bad invocation and a word the error must contain."""
    pose = json.dumps(T.tolist())
    objects = write_json(tmp_path / "objects.json", cube_spec(T))
    out = tmp_path / "ar.png"
    if name == "objects-not-json":
        (tmp_path / "bad.json").write_text("[{\"shape\": ")
        return ar_args(tiny_map, tmp_path / "bad.json", pose, out), "not valid JSON"
    if name == "objects-unknown-shape":
        return ar_args(tiny_map, write_json(tmp_path / "bad.json", [{"shape": "teapot"}]), pose, out), "teapot"
    if name == "objects-missing":
        return ar_args(tiny_map, tmp_path / "missing.json", pose, out), "cannot read"
    if name == "map-missing":
        return ar_args(tmp_path / "none.pt", objects, pose, out), "does not exist"
    if name == "map-corrupt":
        (tmp_path / "bad.pt").write_bytes(b"not a map")
        return ar_args(tmp_path / "bad.pt", objects, pose, out), "corrupt"
    if name == "pose":
        return ar_args(tiny_map, objects, "1 2 3", out), "--pose"
    if name == "background-size":
        cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((10, 10, 3), np.uint8))
        return ar_args(tiny_map, objects, pose, out, "--background", str(tmp_path / "rgb.png")), "64x48"
    if name == "background-missing":
        return ar_args(tiny_map, objects, pose, out, "--background", str(tmp_path / "no.png")), "does not exist"
    if name == "depth-8-bit":
        cv2.imwrite(str(tmp_path / "d.png"), np.zeros((CLI_HEIGHT, CLI_WIDTH), np.uint8))
        return ar_args(tiny_map, objects, pose, out, "--background-depth", str(tmp_path / "d.png")), "16-bit"
    if name == "out-folder-missing":
        return ar_args(tiny_map, objects, pose, tmp_path / "no" / "ar.png"), "cannot write"
    raise AssertionError(name)


@pytest.mark.parametrize("name", ["objects-not-json", "objects-unknown-shape", "objects-missing", "map-missing",
                                  "map-corrupt", "pose", "background-size", "background-missing", "depth-8-bit",
                                  "out-folder-missing"])
def test_cli_bad_input_exits_2_naming_it(name, sequence, tiny_map, tmp_path, capsys):
    argv, message = bad_case(name, tmp_path, tiny_map, camera_pose(sequence))
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "ar.png").exists()


def test_cmd_ar_takes_a_parsed_namespace(sequence, tiny_map, tmp_path):
    """The ``voxfusion`` parser adds these arguments to its subcommand and calls cmd_ar."""
    import argparse

    from ar.cli import add_ar_arguments

    parser = argparse.ArgumentParser()
    add_ar_arguments(parser)
    T = camera_pose(sequence)
    objects = write_json(tmp_path / "objects.json", cube_spec(T))
    args = parser.parse_args(ar_args(tiny_map, objects, json.dumps(T.tolist()), tmp_path / "ar.png"))
    assert cmd_ar(args) == 0
    assert read_rgb(tmp_path / "ar.png").shape == (CLI_HEIGHT, CLI_WIDTH, 3)
