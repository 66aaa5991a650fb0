"""One entry point for every input: ``open_sequence(path, format="auto", ...)``."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Callable, Sequence

from slam.data.frame import DataError, RGBDSequence
from slam.data.io import FileSequence, Intrinsics, SequenceLayout
from slam.data.registration import ColorCamera
from slam.data.replica import COLOR_PATTERN as REPLICA_COLOR_PATTERN
from slam.data.replica import replica_layout
from slam.data.scannet import scannet_color_camera, scannet_layout
from slam.data.sevenscenes import sevenscenes_layout
from slam.data.tum import tum_layout

FORMATS = ("auto", "tum", "replica", "scannet", "7scenes", "synthetic")
SYNTHETIC_PREFIX = "synthetic:"

_LAYOUTS: dict[str, Callable[..., SequenceLayout]] = {
    "tum": tum_layout,
    "replica": replica_layout,
    "scannet": scannet_layout,
    "7scenes": sevenscenes_layout,
}

FORMAT_NAMES = {"tum": "TUM RGB-D", "replica": "Replica", "scannet": "ScanNet", "7scenes": "7-Scenes"}

_WHAT_WE_LOOK_FOR = (
    "rgb.txt + depth.txt (TUM RGB-D); results/frame*.jpg or traj.txt + results/ (Replica); "
    "color/ + depth/ + pose/ (ScanNet); seq-* folders or frame-*.color.png (7-Scenes)"
)


def _is_replica(root: Path) -> bool:
    results = root / "results"
    if not results.is_dir():
        return False
    if (root / "traj.txt").is_file():
        return True
    return any(re.fullmatch(REPLICA_COLOR_PATTERN, p.name) for p in results.glob("frame*"))


def detect_format(path: str | Path) -> str:
    """The format of a dataset folder from its layout: tum | replica | scannet | 7scenes.

    A string starting with ``synthetic:`` is ``synthetic``. Raises DataError listing what was
    looked for when nothing matches.
    """
    if str(path).startswith(SYNTHETIC_PREFIX):
        return "synthetic"
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"not a folder: {root}")
    if (root / "rgb.txt").is_file() and (root / "depth.txt").is_file():
        return "tum"
    if _is_replica(root):
        return "replica"
    if all((root / name).is_dir() for name in ("color", "depth", "pose")):
        return "scannet"
    if any(p.is_dir() for p in root.glob("seq-*")) or any(root.glob("frame-*.color.png")):
        return "7scenes"
    raise DataError(f"cannot tell the dataset format of {root}: looked for {_WHAT_WE_LOOK_FOR}")


def _open_synthetic(spec: str, width: int | None, stride: int, max_frames: int | None,
                    intrinsics: object, depth_scale: object) -> RGBDSequence:
    if intrinsics is not None or depth_scale is not None:
        raise DataError("intrinsics and depth_scale do not apply to synthetic sequences (their camera is generated)")
    # Imported here: the generator pulls in mesh code that readers of real data never need.
    from slam.data.synthetic import open_synthetic

    return open_synthetic(spec, width=width, stride=stride, max_frames=max_frames)


def open_sequence(
    path: str | Path,
    format: str = "auto",
    *,
    width: int | None = None,
    stride: int = 1,
    max_frames: int | None = None,
    intrinsics: Sequence[float] | Intrinsics | None = None,
    depth_scale: float | None = None,
    color_camera: ColorCamera | None = None,
) -> RGBDSequence:
    """Open a dataset folder (or a ``synthetic:SPEC`` string) as a lazily loaded sequence.

    Args:
        path: dataset folder, or ``synthetic:SPEC`` (SPEC goes to ``open_synthetic``).
        format: auto | tum | replica | scannet | 7scenes | synthetic. With ``synthetic`` the
            whole ``path`` (minus a ``synthetic:`` prefix) is the generator's spec.
        width: resize colour and depth to this width (aspect kept; depth by nearest
            neighbour), intrinsics scaled to match. None keeps the native size.
        stride: take every ``stride``-th frame; then ``max_frames`` keeps the first ones.
        intrinsics: (fx, fy, cx, cy) or (fx, fy, cx, cy, k1, k2, p1, p2, k3), replacing the
            format's own camera; with distortion, frames are undistorted to the same K.
        depth_scale: raw depth units per metre, replacing the format's default.
        color_camera: the colour camera when colour and depth come from two cameras; each
            frame's colour is then registered onto the depth camera (``slam.data.registration``).

    Frame.index is the position in the selected frames; Frame.timestamp is the format's time
    (TUM seconds) or the frame number.
    """
    if format not in FORMATS:
        raise DataError(f"format must be one of {', '.join(FORMATS)}; got {format!r}")
    text = str(path)
    if format == "synthetic" or (format == "auto" and text.startswith(SYNTHETIC_PREFIX)):
        spec = text[len(SYNTHETIC_PREFIX):] if text.startswith(SYNTHETIC_PREFIX) else text
        if color_camera is not None:
            raise DataError("a synthetic scene's colour and depth come from one camera: it takes no colour camera")
        return _open_synthetic(spec, width, stride, max_frames, intrinsics, depth_scale)
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"not a folder: {root}")
    if format == "auto":
        format = detect_format(root)
    if intrinsics is not None and not isinstance(intrinsics, Intrinsics):
        intrinsics = Intrinsics.from_values(intrinsics, source="intrinsics argument")
    try:
        layout = _LAYOUTS[format](root, intrinsics=intrinsics, depth_scale=depth_scale)
    except DataError as error:
        raise DataError(f"{error}{_detected_instead(root, format)}") from error
    if format == "scannet" and color_camera is None and intrinsics is None and layout.frames:
        # ScanNet exports its colour camera: register colour to depth rather than resize it.
        color_camera = scannet_color_camera(root, layout.frames[0].rgb)
    return FileSequence(layout, width=width, stride=stride, max_frames=max_frames, color_camera=color_camera)


def _detected_instead(root: Path, asked: str) -> str:
    """'; it looks like ... (--format X)' when the folder's layout is another format than the
    one asked for, else ''."""
    try:
        found = detect_format(root)
    except DataError:
        return ""
    if found == asked:
        return ""
    return f"; the folder looks like {FORMAT_NAMES[found]} instead: format {found!r} (or 'auto')"
