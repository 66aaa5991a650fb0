"""ScanNet scans exported by its SensReader: ``color/N.jpg``, ``depth/N.png``, ``pose/N.txt``,
``intrinsic/intrinsic_depth.txt``.

- The colour camera (1296x968) has intrinsics of its own: with ``intrinsic/intrinsic_color.txt``
  (and, when both are there, ``extrinsic_color.txt`` and ``extrinsic_depth.txt``, each camera's
  pose in the sensor's frame) ``scannet_color_camera`` gives the colour camera, and colour is
  registered onto the depth camera as it is read. Without them the colour image is resized to
  the depth camera's size (640x480) and the depth intrinsics are used for both, as NICE-SLAM
  and Vox-Fusion do.
- Depth is 16-bit millimetres; 0 is invalid.
- ``pose/N.txt`` is a 4x4 camera-to-world matrix; lost poses are written as ``-inf`` and
  become ``T_world_cam = None``, as does a missing pose file.
- Frame.timestamp is the frame number N.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slam.data.frame import DataError
from slam.data.registration import ColorCamera
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
INTRINSICS_FILE = Path("intrinsic") / "intrinsic_depth.txt"


COLOR_INTRINSICS_FILE = Path("intrinsic") / "intrinsic_color.txt"
COLOR_EXTRINSICS_FILE = Path("intrinsic") / "extrinsic_color.txt"
DEPTH_EXTRINSICS_FILE = Path("intrinsic") / "extrinsic_depth.txt"


def scannet_color_camera(root: Path, first_color: Path) -> ColorCamera | None:
    """The scan's colour camera from ``intrinsic_color.txt`` (its size from ``first_color``'s
    header), placed by the two extrinsics when both are exported (else at the depth
    camera); None without ``intrinsic_color.txt``."""
    from slam.data.images import header_of

    root = Path(root)
    path = confined(root / COLOR_INTRINSICS_FILE, root, str(COLOR_INTRINSICS_FILE))
    if not path.is_file():
        return None
    K = read_matrix_file(path)[:3, :3]
    width, height = header_of(first_color, first_color.name)
    T_color_depth = np.eye(4)
    extrinsics = [confined(root / f, root, str(f)) for f in (COLOR_EXTRINSICS_FILE, DEPTH_EXTRINSICS_FILE)]
    if all(f.is_file() for f in extrinsics):
        E_color, E_depth = (read_matrix_file(f) for f in extrinsics)
        T_color_depth = np.linalg.inv(E_color) @ E_depth
    try:
        return ColorCamera(K, width, height, T_color_depth)
    except DataError as error:
        raise DataError(f"{path}: {error}") from error


def read_scannet_intrinsics(path: Path) -> Intrinsics:
    """``intrinsic_depth.txt`` (a 4x4 matrix whose top-left 3x3 is K) -> Intrinsics."""
    K = read_matrix_file(path)
    return Intrinsics.from_values([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], source=str(path))


def _pose(path: Path, root: Path) -> np.ndarray | None:
    confined(path, root, f"pose/{path.name}")
    return valid_pose_or_none(read_matrix_file(path)) if path.is_file() else None


def scannet_layout(root: Path, intrinsics: Intrinsics | None = None, depth_scale: float | None = None) -> SequenceLayout:
    """Describe a ScanNet scan folder (see the module docstring)."""
    root = Path(root)
    for folder in ("color", "depth"):
        if not (root / folder).is_dir():
            raise DataError(f"missing folder: {root / folder} (a ScanNet scan has color/, depth/, pose/)")
    frames = tuple(
        FrameFiles(
            rgb=path,
            depth=root / "depth" / f"{number}.png",
            timestamp=float(number),
            T_world_cam=_pose(root / "pose" / f"{number}.txt", root),
        )
        for number, path in numbered_files(root / "color", r"(\d+)\.(?:jpg|jpeg|png)")
    )
    if intrinsics is None:
        confined(root / INTRINSICS_FILE, root, str(INTRINSICS_FILE))
        if not (root / INTRINSICS_FILE).is_file():
            raise DataError(f"missing file: {root / INTRINSICS_FILE}; give intrinsics (--intrinsics fx,fy,cx,cy)")
        intrinsics = read_scannet_intrinsics(root / INTRINSICS_FILE)
    return SequenceLayout(
        name=root.name,
        root=root,
        frames=frames,
        intrinsics=intrinsics,
        depth_scale=resolve_depth_scale(depth_scale, DEPTH_SCALE),
        color_to_depth_size=True,
    )
