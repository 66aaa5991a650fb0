"""TUM RGB-D benchmark folders: ``rgb.txt``, ``depth.txt``, optional ``groundtruth.txt``.

- rgb frames are paired with depth frames by nearest timestamp, at most 20 ms apart, greedily
  by smallest difference and one-to-one, as TUM's ``associate.py`` does. An rgb frame with no
  depth within 20 ms is dropped.
- Ground truth is **not interpolated**: each kept rgb frame takes the nearest ground-truth pose
  within 20 ms (same greedy one-to-one association) or None. At 100 Hz motion capture the
  nearest pose is at most ~5 ms away, which is below the Kinect's own timing jitter.
- Intrinsics, by priority: the ``intrinsics`` argument, ``intrinsics.txt`` in the folder
  (``fx fy cx cy [k1 k2 p1 p2 k3]``), TUM's published calibration of the camera named by the
  folder (``freiburg1``, ``freiburg2``, ``freiburg3``). fr1 and fr2 images are distorted and
  get undistorted to the same pinhole K; fr3 images are already undistorted.
- Depth: 16-bit PNG, 5000 units per metre unless overridden.
- Frame.timestamp is the rgb timestamp (what TUM's evaluation tools match against).
"""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np

from slam.data.frame import DataError
from slam.data.io import (
    FrameFiles,
    Intrinsics,
    SequenceLayout,
    confined,
    dataset_entry,
    read_intrinsics_txt,
    read_text,
    resolve_depth_scale,
)
from slam.geometry import pose_from_tum

MAX_TIME_DIFFERENCE = 0.02
"""Seconds: the largest rgb-depth or rgb-groundtruth gap that still counts as a match."""

DEPTH_SCALE = 5000.0

# TUM's published colour-camera calibration per Kinect (fx fy cx cy k1 k2 p1 p2 k3), 640x480.
FREIBURG_CALIBRATION: dict[int, tuple[float, ...]] = {
    1: (517.3, 516.5, 318.6, 255.3, 0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    2: (520.9, 521.0, 325.1, 249.7, 0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
    3: (535.4, 539.2, 320.1, 247.6),
}


def read_tum_list(path: Path, columns: int) -> list[tuple[float, list[str]]]:
    """Parse a TUM list file -> [(timestamp, the other fields)] in file order.

    Lines starting with ``#`` and blank lines are skipped; fields may be separated by spaces,
    tabs or commas. ``columns`` is the number of fields after the timestamp.
    """
    rows = []
    for lineno, line in enumerate(read_text(path).splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) < 1 + columns:
            raise DataError(f"{path}:{lineno}: expected a timestamp and {columns} field(s), got {line!r}")
        try:
            stamp = float(fields[0])
        except ValueError as err:
            raise DataError(f"{path}:{lineno}: bad timestamp {fields[0]!r}") from err
        rows.append((stamp, fields[1 : 1 + columns]))
    return rows


def associate(first: np.ndarray, second: np.ndarray, max_difference: float) -> list[tuple[int, int]]:
    """Match (N,) timestamps to (M,) timestamps one-to-one, closest pairs first.

    Returns index pairs (i, j) with ``|first[i] - second[j]| <= max_difference``, sorted by i.
    Example: first = [0, 0.03], second = [0.012, 0.02, 0.1], 0.02 -> [(0, 0), (1, 1)]:
    0.03-0.02 = 0.01 is the closest pair and is taken first, then 0-0.012.
    """
    first = np.asarray(first, dtype=np.float64)
    second = np.asarray(second, dtype=np.float64)
    order = np.argsort(second, kind="stable")
    sorted_second = second[order]
    tolerance = max_difference + 1e-9  # timestamps are printed with 6 decimals
    lo = np.searchsorted(sorted_second, first - tolerance, side="left")
    hi = np.searchsorted(sorted_second, first + tolerance, side="right")
    candidates = [
        (abs(first[i] - sorted_second[k]), i, int(order[k]))
        for i in range(len(first))
        for k in range(lo[i], hi[i])
    ]
    candidates.sort()
    used_first: set[int] = set()
    used_second: set[int] = set()
    pairs = []
    for _, i, j in candidates:
        if i not in used_first and j not in used_second:
            used_first.add(i)
            used_second.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def freiburg_intrinsics(root: Path) -> Intrinsics:
    """TUM's calibration for the Kinect named in the folder name (``..._freiburg2_...``)."""
    match = re.search(r"freiburg(\d+)", root.name)
    if match is None:
        raise DataError(
            f"{root}: cannot tell the camera: the folder name has no 'freiburg1/2/3'; "
            "give intrinsics (an intrinsics.txt with 'fx fy cx cy [k1 k2 p1 p2 k3]' in the "
            "folder, or --intrinsics fx,fy,cx,cy)"
        )
    number = int(match.group(1))
    if number not in FREIBURG_CALIBRATION:
        raise DataError(
            f"{root}: unknown camera 'freiburg{number}' (known: freiburg1/2/3); give intrinsics "
            "(intrinsics.txt in the folder or --intrinsics fx,fy,cx,cy)"
        )
    calibration = Intrinsics.from_values(FREIBURG_CALIBRATION[number], source=f"TUM freiburg{number} calibration")
    return replace(calibration, image_size=(640, 480))


def _groundtruth_poses(root: Path, rgb_times: np.ndarray) -> list[np.ndarray | None]:
    """(N,) rgb timestamps -> the matched ground-truth (4, 4) pose or None for each."""
    path = root / "groundtruth.txt"
    if not path.is_file():
        return [None] * len(rgb_times)
    rows = read_tum_list(path, columns=7)
    if not rows:
        return [None] * len(rgb_times)
    try:
        values = np.array([[float(v) for v in fields] for _, fields in rows], dtype=np.float64)
    except ValueError as err:
        raise DataError(f"{path}: ground truth rows must be 'timestamp tx ty tz qx qy qz qw' ({err})") from err
    poses = pose_from_tum(values)
    gt_times = np.array([stamp for stamp, _ in rows])
    matched: list[np.ndarray | None] = [None] * len(rgb_times)
    for i, j in associate(rgb_times, gt_times, MAX_TIME_DIFFERENCE):
        if np.all(np.isfinite(values[j])):
            matched[i] = poses[j]
    return matched


def tum_layout(root: Path, intrinsics: Intrinsics | None = None, depth_scale: float | None = None) -> SequenceLayout:
    """Describe a TUM RGB-D folder (see the module docstring for the rules)."""
    root = Path(root)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "intrinsics.txt"):
        confined(root / name, root, name)
    for required in ("rgb.txt", "depth.txt"):
        if not (root / required).is_file():
            raise DataError(f"missing file: {root / required} (a TUM folder has rgb.txt and depth.txt)")
    rgb_rows = read_tum_list(root / "rgb.txt", columns=1)
    depth_rows = read_tum_list(root / "depth.txt", columns=1)
    rgb_times = np.array([stamp for stamp, _ in rgb_rows])
    pairs = associate(rgb_times, np.array([stamp for stamp, _ in depth_rows]), MAX_TIME_DIFFERENCE)
    kept_times = rgb_times[[i for i, _ in pairs]] if pairs else np.zeros(0)
    poses = _groundtruth_poses(root, kept_times)
    frames = tuple(
        FrameFiles(
            rgb=dataset_entry(root, rgb_rows[i][1][0], "rgb.txt"),
            depth=dataset_entry(root, depth_rows[j][1][0], "depth.txt"),
            timestamp=rgb_rows[i][0],
            T_world_cam=pose,
        )
        for (i, j), pose in zip(pairs, poses)
    )
    if intrinsics is None:
        own_file = root / "intrinsics.txt"
        intrinsics = read_intrinsics_txt(own_file) if own_file.is_file() else freiburg_intrinsics(root)
    return SequenceLayout(
        name=root.name,
        root=root,
        frames=frames,
        intrinsics=intrinsics,
        depth_scale=resolve_depth_scale(depth_scale, DEPTH_SCALE),
    )
