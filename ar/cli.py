"""``voxfusion ar``: composite virtual objects into a view of a saved map, with occlusion.

    voxfusion ar DIR/map.pt --objects FILE.json --pose POSE --intrinsics fx,fy,cx,cy,W,H
                 --out composite.png [--background render|RGB.png] [--background-depth DEPTH.png]
                 [--depth-scale 1000] [--mask-out mask.png] [--depth-tolerance 0.01]

The scene's colour and depth come from the neural map rendered at the camera
(``--background render``, the default). With ``--background RGB.png``
(a real frame) the objects are drawn over that image instead; the depth test then uses
``--background-depth`` (a 16-bit PNG registered to the colour, ``--depth-scale`` units per
metre; 1000 = millimetres, as ``voxfusion render --depth`` writes) wherever it measured, and
the map's rendered depth only in its holes under the objects
(``ar.scene_depth.sensor_depth_with_map``); without it, the map's rendered depth. A depth
given without a background image replaces the map's depth under the rendered colour.

``--mask-out`` writes an 8-bit PNG: 255 where virtual content is visible, 128 where it is
hidden by the scene, 0 elsewhere (``CompositeResult.object_mask`` / ``occlusion_mask``).

Bad input (a missing or corrupt file, a malformed pose, intrinsics or object spec, image sizes
that differ from the intrinsics) prints one line naming it and returns 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ar.composite import CompositeResult, composite
from ar.objects import ObjectSpecError, _check_rigid, load_objects_json
from ar.scene_depth import sensor_depth_with_map
from slam import parse_pose as parse_pose_text

PROG = "voxfusion ar"
RENDER_BACKGROUND = "render"
MASK_VISIBLE, MASK_HIDDEN = 255, 128


class ARInputError(ValueError):
    """A command-line input is malformed; the message names the argument or the file."""


@dataclass(frozen=True)
class PinholeCamera:
    """K (3, 3) float64 intrinsics of a ``width`` x ``height`` image, T_world_cam (4, 4) float64."""

    K: np.ndarray
    T_world_cam: np.ndarray
    width: int
    height: int


# --------------------------------------------------------------------------- parsing
def parse_pose(text: str) -> np.ndarray:
    """(4, 4) float64 rigid ``T_world_cam`` from 16 numbers (row-major, separated by commas
    or spaces), a JSON 4x4 list, or the path of a file holding either."""
    try:
        pose = parse_pose_text(text, "--pose")
        _check_rigid(pose, "--pose")
    except ValueError as error:
        raise ARInputError(str(error)) from None
    return pose


def parse_intrinsics(text: str) -> tuple[np.ndarray, int, int]:
    """``fx,fy,cx,cy,W,H`` -> (K (3, 3) float64, width, height)."""
    try:
        values = [float(v) for v in text.replace(" ", "").split(",")]
    except ValueError:
        raise ARInputError(f"--intrinsics: expected fx,fy,cx,cy,width,height as numbers, got {text!r}") from None
    if len(values) != 6:
        raise ARInputError(f"--intrinsics: expected 6 numbers fx,fy,cx,cy,width,height, got {len(values)}")
    fx, fy, cx, cy, width, height = values
    if not all(np.isfinite(values)) or fx <= 0 or fy <= 0:
        raise ARInputError(f"--intrinsics: fx and fy must be positive and all values finite, got {text!r}")
    if width != int(width) or height != int(height) or width < 1 or height < 1:
        raise ARInputError(f"--intrinsics: width and height must be positive integers, got {width:g}x{height:g}")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return K, int(width), int(height)


def read_background_rgb(path: Path, width: int, height: int) -> np.ndarray:
    """(H, W, 3) float32 RGB in [0, 1] from an 8- or 16-bit colour image of the camera's size."""
    image = _read_image(path, "--background")
    if image.dtype not in (np.uint8, np.uint16):
        raise ARInputError(f"--background: {path} must be an 8- or 16-bit image, got {image.dtype}")
    _check_size(image, path, "--background", width, height)
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    elif image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    scale = float(np.iinfo(image.dtype).max)
    return (cv2.cvtColor(image, cv2.COLOR_BGR2RGB).astype(np.float32) / scale).astype(np.float32)


def read_background_depth(path: Path, depth_scale: float, width: int, height: int) -> np.ndarray:
    """(H, W) float32 metres (0 = invalid) from a single-channel 16-bit PNG of the camera's size."""
    if not np.isfinite(depth_scale) or depth_scale <= 0:
        raise ARInputError(f"--depth-scale: must be a positive number, got {depth_scale}")
    image = _read_image(path, "--background-depth")
    if image.ndim != 2 or image.dtype != np.uint16:
        raise ARInputError(f"--background-depth: {path} must be a single-channel 16-bit image, "
                           f"got {image.dtype} with shape {image.shape}")
    _check_size(image, path, "--background-depth", width, height)
    return (image.astype(np.float32) / np.float32(depth_scale)).astype(np.float32)


def _read_image(path: Path, what: str) -> np.ndarray:
    if not path.is_file():
        raise ARInputError(f"{what}: {path} does not exist")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ARInputError(f"{what}: {path} is not a readable image")
    return image


def _check_size(image: np.ndarray, path: Path, what: str, width: int, height: int) -> None:
    if image.shape[:2] != (height, width):
        raise ARInputError(f"{what}: {path} is {image.shape[1]}x{image.shape[0]}, "
                           f"but --intrinsics say {width}x{height}")


# --------------------------------------------------------------------------- outputs
def mask_image(result: CompositeResult) -> np.ndarray:
    """(H, W) uint8: MASK_VISIBLE where objects show, MASK_HIDDEN where the scene hides them."""
    mask = np.zeros(result.object_mask.shape, dtype=np.uint8)
    mask[result.occlusion_mask] = MASK_HIDDEN
    mask[result.object_mask] = MASK_VISIBLE
    return mask


def write_png(path: Path, image: np.ndarray, what: str) -> None:
    """Write an (H, W) gray or (H, W, 3) RGB uint8 image as PNG, whatever the file's suffix."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise ARInputError(f"{what}: could not encode the PNG for {path}")
    try:
        path.write_bytes(encoded.tobytes())
    except OSError as error:
        raise ARInputError(f"{what}: cannot write {path} ({error})") from None


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float in [0, 1] -> uint8."""
    return np.clip(np.rint(np.asarray(rgb) * 255.0), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- command
def add_ar_arguments(parser: argparse.ArgumentParser) -> None:
    """The arguments of ``voxfusion ar`` (values are parsed and checked by ``cmd_ar``)."""
    parser.add_argument("checkpoint", type=Path, help="map.pt of a run")
    parser.add_argument("--objects", required=True, type=Path,
                        help='JSON list of objects: [{"shape": "cube", "T_world_obj": 4x4, "scale": 0.2, '
                             '"color": [r, g, b]}, ...] (or {"objects": [...]})')
    parser.add_argument("--pose", required=True,
                        help="camera T_world_cam: 16 numbers (row-major), a JSON 4x4 list, or a file with either")
    parser.add_argument("--intrinsics", required=True, metavar="fx,fy,cx,cy,W,H",
                        help="pinhole intrinsics and image size in pixels")
    parser.add_argument("--out", required=True, type=Path, help="composite colour PNG")
    parser.add_argument("--background", default=RENDER_BACKGROUND, metavar="render|RGB.png",
                        help="'render' (the map's colour, default) or a colour image of the camera's size")
    parser.add_argument("--background-depth", type=Path, default=None, metavar="DEPTH.png",
                        help="16-bit depth image for the depth test (default: the map's rendered depth)")
    parser.add_argument("--depth-scale", type=float, default=1000.0,
                        help="units per metre of --background-depth (default 1000: millimetres)")
    parser.add_argument("--mask-out", type=Path, default=None,
                        help="8-bit mask PNG: 255 visible object, 128 object hidden by the scene, 0 none")
    parser.add_argument("--depth-tolerance", type=float, default=0.01,
                        help="metres an object may lie behind the scene and still show (default 0.01)")
    parser.add_argument("--supersample", type=int, default=2, help="samples per pixel along each axis (default 2)")
    parser.add_argument("--device", default="cpu", choices=["auto", "cpu", "cuda"],
                        help="torch device for rendering and compositing (default cpu)")
    from slam.cli import FIRST_CALL_NOTE, add_threads_argument

    add_threads_argument(parser)
    # ``voxfusion ar``'s subparser comes without a description: say what a fresh process costs.
    parser.description = parser.description or (
        f"Composite virtual objects into a view of a saved map, with occlusion. {FIRST_CALL_NOTE}")


def cmd_ar(args: argparse.Namespace) -> int:
    """Run ``voxfusion ar``; 0 on success, 2 on bad input (one line on stderr says what)."""
    from slam.cli import threads_for_views

    try:
        with threads_for_views(args.threads):
            written = _run(args)
    except (ARInputError, ObjectSpecError) as error:
        print(f"{PROG}: {error}", file=sys.stderr)
        return 2
    print(f"wrote {', '.join(str(p) for p in written)}")
    return 0


def _run(args: argparse.Namespace) -> list[Path]:
    """Read the inputs, render what is needed, composite and write; returns the paths written."""
    K, width, height = parse_intrinsics(args.intrinsics)
    camera = PinholeCamera(K, parse_pose(args.pose), width, height)
    objects = load_objects_json(args.objects)
    if args.supersample < 1:
        raise ARInputError(f"--supersample: must be >= 1, got {args.supersample}")
    if not np.isfinite(args.depth_tolerance) or args.depth_tolerance < 0:
        raise ARInputError(f"--depth-tolerance: must be a number >= 0, got {args.depth_tolerance}")
    device = _resolve_device(args.device)
    given_rgb = None if args.background == RENDER_BACKGROUND else read_background_rgb(
        Path(args.background), width, height)
    given_depth = None if args.background_depth is None else read_background_depth(
        args.background_depth, args.depth_scale, width, height)
    mapset = _load_map(args.checkpoint, device)
    from slam import render_view

    if given_depth is not None:
        def map_depth(K: np.ndarray, w: int, h: int) -> np.ndarray:
            return np.asarray(render_view(mapset, camera.T_world_cam, K, w, h, device=device).depth)

        # The sensor's depth where it measured; the map's only in its holes under the objects.
        given_depth = sensor_depth_with_map(given_depth, objects, camera.K, camera.T_world_cam, map_depth).depth
    if given_rgb is None or given_depth is None:
        view = render_view(mapset, camera.T_world_cam, camera.K, width, height, device=device)
        given_rgb = view.rgb if given_rgb is None else given_rgb
        given_depth = view.depth if given_depth is None else given_depth
    result = composite(given_rgb, given_depth, objects, camera.K, camera.T_world_cam,
                       depth_tolerance=args.depth_tolerance, supersample=args.supersample, device=device)
    write_png(args.out, to_uint8(result.rgb), "--out")
    written = [args.out]
    if args.mask_out is not None:
        write_png(args.mask_out, mask_image(result), "--mask-out")
        written.append(args.mask_out)
    return written


def _resolve_device(name: str) -> str:
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise ARInputError("--device: cuda was asked for but no CUDA device is available")
    return name


def _load_map(path: Path, device: str):
    """The checkpoint's MapSet; loaded even when both images are given, so that a wrong map
    path is reported rather than silently ignored."""
    from slam import CheckpointError, load_checkpoint

    try:
        return load_checkpoint(path, device=device)
    except CheckpointError as error:
        raise ARInputError(str(error)) from None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    add_ar_arguments(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m ar.cli ...``: the same as ``voxfusion ar ...``."""
    return cmd_ar(build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
