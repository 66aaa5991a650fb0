"""Timestamped trajectories, TUM text I/O and timestamp association.

A TUM trajectory file has one pose per line, ``timestamp tx ty tz qx qy qz qw`` (camera-to-world,
quaternion ``xyzw`` as in the TUM benchmark), and ``#`` comment lines. Parsing and formatting
are pure functions on strings (``parse_tum`` / ``format_tum``) so the server can use them on
uploaded or served text; ``read_tum`` / ``write_tum`` add the file around them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam.data.frame import DataError
from slam.geometry import pose_from_tum, pose_to_tum

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"


@dataclass(frozen=True)
class Trajectory:
    """Camera poses with timestamps.

    Attributes:
        timestamps: (N,) float64 seconds.
        poses: (N, 4, 4) float64 camera-to-world ``T_world_cam``.
    """

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        timestamps = np.asarray(self.timestamps, dtype=np.float64)
        poses = np.asarray(self.poses, dtype=np.float64)
        if timestamps.ndim != 1:
            raise ValueError(f"Trajectory timestamps must be (N,), got shape {timestamps.shape}")
        if poses.shape != (len(timestamps), 4, 4):
            raise ValueError(
                f"Trajectory poses must be (N, 4, 4) with N = {len(timestamps)} timestamps, "
                f"got shape {poses.shape}"
            )
        # frozen: normalise dtypes once, through object.__setattr__.
        object.__setattr__(self, "timestamps", timestamps)
        object.__setattr__(self, "poses", poses)

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) camera centres in the world frame."""
        return self.poses[:, :3, 3]

    def subset(self, indices: np.ndarray) -> Trajectory:
        """The poses at (M,) integer ``indices``, in that order."""
        return Trajectory(self.timestamps[indices], self.poses[indices])


def parse_tum(text: str, source: str = "<string>") -> Trajectory:
    """TUM text -> Trajectory. Raises DataError naming ``source`` and the bad line.

    Blank lines and lines starting with ``#`` are skipped; commas count as separators.
    """
    timestamps, rows = [], []
    for line_number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = stripped.replace(",", " ").split()
        if len(fields) != 8:
            raise DataError(
                f"{source}:{line_number}: expected 8 columns 'timestamp tx ty tz qx qy qz qw', "
                f"got {len(fields)}: {stripped!r}"
            )
        values = _parse_floats(fields, source, line_number, stripped)
        if np.linalg.norm(values[4:]) < 1e-8:
            raise DataError(f"{source}:{line_number}: quaternion has zero norm: {stripped!r}")
        timestamps.append(values[0])
        rows.append(values[1:])
    if not rows:
        raise DataError(f"{source}: holds no poses (expected lines 'timestamp tx ty tz qx qy qz qw')")
    return Trajectory(np.array(timestamps), pose_from_tum(np.array(rows)))


def parse_pose_rows(text: str, source: str = "<string>") -> Trajectory:
    """Replica/NICE-SLAM ``traj.txt`` text (16 numbers per line: a row-major 4x4
    camera-to-world matrix) -> Trajectory with the line index as timestamp."""
    poses = []
    for line_number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = stripped.split()
        if len(fields) != 16:
            raise DataError(
                f"{source}:{line_number}: expected 16 numbers (row-major 4x4 pose), "
                f"got {len(fields)}: {stripped!r}"
            )
        poses.append(_parse_floats(fields, source, line_number, stripped).reshape(4, 4))
    if not poses:
        raise DataError(f"{source}: holds no poses")
    return Trajectory(np.arange(len(poses), dtype=np.float64), np.stack(poses))


def format_tum(trajectory: Trajectory) -> str:
    """Trajectory -> TUM text: a header comment, timestamps with 6 decimals, quaternion xyzw."""
    rows = pose_to_tum(trajectory.poses) if len(trajectory) else np.zeros((0, 7))
    lines = [TUM_HEADER]
    for stamp, row in zip(trajectory.timestamps, rows):
        lines.append(f"{stamp:.6f} " + " ".join(f"{value:.9f}" for value in row))
    return "\n".join(lines) + "\n"


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file. Raises DataError (missing file, bad line)."""
    return parse_tum(_read_text(path), str(path))


def read_trajectory(path: str | Path) -> Trajectory:
    """Read a TUM file (8 columns) or a Replica ``traj.txt`` (16 columns), chosen by the
    column count of the first pose line."""
    text = _read_text(path)
    first = next((s for s in (ln.strip() for ln in text.splitlines()) if s and not s.startswith("#")), "")
    if len(first.split()) == 16:
        return parse_pose_rows(text, str(path))
    return parse_tum(text, str(path))


def write_tum(path: str | Path, trajectory: Trajectory) -> None:
    """Write ``trajectory`` as a TUM file (the parent folder must exist)."""
    Path(path).write_text(format_tum(trajectory))


def associate(
    stamps_a: np.ndarray, stamps_b: np.ndarray, max_dt: float = 0.02
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matching of two timestamp lists, closest pairs first (as TUM's associate.py).

    Every pair with ``|a - b| <= max_dt`` is a candidate; candidates are taken in order of
    increasing time difference, skipping those whose a or b is already used.

    Args:
        stamps_a: (N,) seconds, any order.
        stamps_b: (M,) seconds, any order.
        max_dt: largest accepted difference in seconds.
    Returns:
        idx_a, idx_b: (K,) int64 indices into a and b, sorted by idx_a.
    """
    if max_dt < 0:
        raise ValueError(f"max_dt must be >= 0, got {max_dt}")
    a = np.asarray(stamps_a, dtype=np.float64)
    b = np.asarray(stamps_b, dtype=np.float64)
    cand_a, cand_b = _candidate_pairs(a, b, max_dt)
    dt = np.abs(a[cand_a] - b[cand_b])
    order = np.lexsort((cand_b, cand_a, dt))  # by dt, ties broken by index for determinism
    used_a = np.zeros(len(a), dtype=bool)
    used_b = np.zeros(len(b), dtype=bool)
    keep = []
    for k in order:
        i, j = cand_a[k], cand_b[k]
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            keep.append(k)
    keep = np.array(keep, dtype=np.int64)
    idx_a, idx_b = cand_a[keep], cand_b[keep]
    by_a = np.argsort(idx_a, kind="stable")
    return idx_a[by_a], idx_b[by_a]


def _candidate_pairs(a: np.ndarray, b: np.ndarray, max_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """All (i, j) with |a[i] - b[j]| <= max_dt, via a sorted b (no N x M matrix)."""
    b_order = np.argsort(b, kind="stable")
    b_sorted = b[b_order]
    lo = np.searchsorted(b_sorted, a - max_dt, side="left")
    hi = np.searchsorted(b_sorted, a + max_dt, side="right")
    counts = hi - lo
    cand_a = np.repeat(np.arange(len(a)), counts)
    # Position within each a's window: a running index minus the window's start offset.
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    cand_b = b_order[np.repeat(lo, counts) + offsets]
    within = np.abs(a[cand_a] - b[cand_b]) <= max_dt  # guards float rounding in a +- max_dt
    return cand_a[within].astype(np.int64), cand_b[within].astype(np.int64)


def _parse_floats(fields: list[str], source: str, line_number: int, line: str) -> np.ndarray:
    try:
        values = np.array([float(f) for f in fields], dtype=np.float64)
    except ValueError:
        raise DataError(f"{source}:{line_number}: not a number in {line!r}") from None
    if not np.isfinite(values).all():
        raise DataError(f"{source}:{line_number}: non-finite value in {line!r}")
    return values


def _read_text(path: str | Path) -> str:
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such trajectory file")
    try:
        return path.read_text()
    except UnicodeDecodeError:
        raise DataError(f"{path}: not a text file") from None
