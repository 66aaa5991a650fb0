"""Replica renders in NICE-SLAM's layout.

```
SCENE/results/frame000000.jpg, depth000000.png, ...
SCENE/traj.txt          one row-major 4x4 camera-to-world matrix per line, OpenCV axes
cam_params.json         in SCENE or its parent: {"camera": {w, h, fx, fy, cx, cy, scale}}
```

Row n of ``traj.txt`` is the pose of frame number n (the number in the file name), so a folder
holding only some frames of a full trajectory still gets the right poses. Depth is 16-bit with
``scale`` (6553.5) units per metre. Frame.timestamp is the frame number.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from slam.data.frame import DataError
from slam.data.io import (
    FrameFiles,
    Intrinsics,
    SequenceLayout,
    confined,
    numbered_files,
    read_text,
    resolve_depth_scale,
    valid_pose_or_none,
)

DEPTH_SCALE = 6553.5
COLOR_PATTERN = r"frame(\d+)\.(?:jpg|jpeg|png)"


def read_cam_params(path: Path) -> tuple[Intrinsics, float]:
    """Parse NICE-SLAM's ``cam_params.json`` -> (intrinsics with image size, depth scale)."""
    try:
        camera = json.loads(read_text(path))["camera"]
        intrinsics = Intrinsics.from_values([camera[k] for k in ("fx", "fy", "cx", "cy")], source=str(path))
        size = (int(camera["w"]), int(camera["h"]))
        scale = float(camera.get("scale", DEPTH_SCALE))
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        raise DataError(
            f"{path}: expected JSON {{\"camera\": {{\"w\", \"h\", \"fx\", \"fy\", \"cx\", \"cy\", \"scale\"}}}} ({err!r})"
        ) from err
    return replace(intrinsics, image_size=size), scale


def find_cam_params(root: Path) -> Path | None:
    """``cam_params.json`` in the scene folder, else in its parent, else None."""
    for folder in (root, root.parent):
        if (folder / "cam_params.json").is_file():
            return confined(folder / "cam_params.json", folder, "cam_params.json")
    return None


def read_trajectory(path: Path) -> list[np.ndarray | None]:
    """``traj.txt`` -> one (4, 4) camera-to-world pose per line (None where not finite)."""
    poses: list[np.ndarray | None] = []
    for lineno, line in enumerate(read_text(path).splitlines(), start=1):
        if not line.strip():
            continue
        try:
            numbers = [float(v) for v in line.split()]
        except ValueError as err:
            raise DataError(f"{path}:{lineno}: not a row of numbers ({err})") from err
        if len(numbers) != 16:
            raise DataError(f"{path}:{lineno}: expected 16 numbers (a row-major 4x4 pose), got {len(numbers)}")
        poses.append(valid_pose_or_none(np.array(numbers).reshape(4, 4)))
    return poses


def replica_layout(root: Path, intrinsics: Intrinsics | None = None, depth_scale: float | None = None) -> SequenceLayout:
    """Describe a Replica scene folder (see the module docstring)."""
    root = Path(root)
    results = root / "results"
    if not results.is_dir():
        raise DataError(f"missing folder: {results} (a Replica scene has results/frameNNNNNN.jpg)")
    colors = numbered_files(results, COLOR_PATTERN)
    traj_path = confined(root / "traj.txt", root, "traj.txt")
    poses = read_trajectory(traj_path) if traj_path.is_file() else None
    if poses is not None and colors and colors[-1][0] >= len(poses):
        raise DataError(f"{traj_path} has {len(poses)} poses but there is a frame number {colors[-1][0]}")
    frames = tuple(
        FrameFiles(
            rgb=path,
            depth=results / f"depth{path.name[len('frame'):].split('.')[0]}.png",
            timestamp=float(number),
            T_world_cam=None if poses is None else poses[number],
        )
        for number, path in colors
    )
    default_scale = DEPTH_SCALE
    if intrinsics is None:
        params = find_cam_params(root)
        if params is None:
            raise DataError(
                f"{root}: no cam_params.json here or in {root.parent}; give intrinsics "
                "(--intrinsics fx,fy,cx,cy)"
            )
        intrinsics, default_scale = read_cam_params(params)
    return SequenceLayout(
        name=root.name,
        root=root,
        frames=frames,
        intrinsics=intrinsics,
        depth_scale=resolve_depth_scale(depth_scale, default_scale),
    )
