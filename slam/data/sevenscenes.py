"""Microsoft 7-Scenes: ``SCENE/seq-XX/frame-NNNNNN.{color.png,depth.png,pose.txt}``.

- The path may be one ``seq-XX`` folder or a scene folder; a scene's sequences are read one
  after the other in name order (their poses share the scene's world frame, and the jump
  between them is a relocalisation / new-map case for the SLAM).
- Depth is 16-bit millimetres; 0 and 65535 are invalid. Depth is not registered to colour
  in this dataset (its documentation says so) and its colour camera is not published: the
  reader takes one pinhole K for both, fx = fy = 585, cx = 320, cy = 240 by default. Give the
  colour camera if you know it (``voxfusion run --color-intrinsics/--depth-to-color`` or
  ``--calibration``); otherwise the run estimates how colour lies on depth from the frames
  (``slam.data.selfcalibration``) and registers it when it is confident.
- ``pose.txt`` is a 4x4 camera-to-world matrix; a missing or non-finite one gives None.
- Frame.timestamp is the frame number; in a multi-sequence scene each sequence continues
  after the previous one's last number so that timestamps stay unique.
"""

from __future__ import annotations

from pathlib import Path

from slam.data.frame import DataError
from slam.data.io import (
    FrameFiles,
    Intrinsics,
    SequenceLayout,
    confined,
    numbered_files,
    read_matrix_file,
    resolve_depth_scale,
    valid_pose_or_none,
)

DEPTH_SCALE = 1000.0
INVALID_DEPTH_RAW = (65535,)
DEFAULT_INTRINSICS = Intrinsics(585.0, 585.0, 320.0, 240.0, image_size=(640, 480), source="7-Scenes default camera")
COLOR_PATTERN = r"frame-(\d+)\.color\.png"


def sequence_folders(root: Path) -> list[Path]:
    """The ``seq-XX`` folders to read: ``root`` itself when it holds frames, else its seq-*."""
    if any(root.glob("frame-*.color.png")):
        return [root]
    return sorted(p for p in root.glob("seq-*") if p.is_dir())


def _frames_of(folder: Path, first_timestamp: float) -> list[FrameFiles]:
    frames = []
    for number, path in numbered_files(folder, COLOR_PATTERN):
        stem = path.name[: -len(".color.png")]
        pose_path = confined(folder / f"{stem}.pose.txt", folder, f"{stem}.pose.txt")
        pose = valid_pose_or_none(read_matrix_file(pose_path)) if pose_path.is_file() else None
        frames.append(FrameFiles(path, folder / f"{stem}.depth.png", first_timestamp + number, pose))
    return frames


def sevenscenes_layout(root: Path, intrinsics: Intrinsics | None = None, depth_scale: float | None = None) -> SequenceLayout:
    """Describe a 7-Scenes scene or sequence folder (see the module docstring)."""
    root = Path(root)
    folders = sequence_folders(root)
    if not folders:
        raise DataError(f"{root}: no frame-NNNNNN.color.png and no seq-XX folders")
    frames: list[FrameFiles] = []
    for folder in folders:
        start = frames[-1].timestamp + 1 if frames else 0.0
        frames += _frames_of(folder, start)
    name = root.name if len(folders) > 1 or folders[0] != root else f"{root.parent.name}/{root.name}"
    return SequenceLayout(
        name=name,
        root=root,
        frames=tuple(frames),
        intrinsics=DEFAULT_INTRINSICS if intrinsics is None else intrinsics,
        depth_scale=resolve_depth_scale(depth_scale, DEPTH_SCALE),
        invalid_depth_raw=INVALID_DEPTH_RAW,
    )
