"""The numbers behind the page's plots: a session's estimated trajectory against the input's
ground truth (aligned as the ATE aligns them), the error of every frame, and frames/s over
the tracking phase.

The ground truth is read from the session's input (a synthetic scene's generated path, a
dataset's ``groundtruth.txt`` / pose files) with the options the worker opened it with, so
its timestamps are the ones the runtime reports; estimate and ground truth are associated by
timestamp and rigidly aligned (Umeyama, no scale) by ``slam.eval.ate.ate_from_pairs``, as the
ATE is.

The input is untrusted (an upload), so it is read in the decode helper (``server.decoding``),
never in the API process: :func:`read_source_facts` opens the source there once and sends back
only what the routes use, the first frame's camera and the ground truth's timestamps and
camera centres (:class:`SourceFacts`). Before the reader parses a ground-truth file
(``traj.txt``, ``groundtruth.txt``) its size and line count are checked against
``MAX_GROUND_TRUTH_BYTES`` / ``MAX_GROUND_TRUTH_LINES``; past them the series comes without
ground truth and says why (``note``). The API process keeps the answers for reuse (a page polls
the series while a session runs, and inputs do not change) in :class:`SourceFactsCache`,
bounded in entries and bytes, refusals included so that a slow input is read once. Reads queue
one at a time (``server.helper_queue``); a request that would wait longer than
``SOURCE_WAIT_S`` beyond the read's own limit gets a note instead of the ground truth.

Reading in the helper at the first request (rather than the worker writing the arrays into
the session folder) also serves sessions that ran before, and streams and the camera route
need no second path.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Hashable

import numpy as np

from server.decoding import DecodeFailed, shared_helper
from server.helper_pool import HelperTimedOut, PoolBusy
from server.helper_queue import HelperQueue
from server.tracks import FrameCamera
from server.worker import SourceSpec, open_source
from slam import DataError, Trajectory, associate, ate_from_pairs

MAX_DT_S = 0.02
"""Largest timestamp difference of an estimate-ground truth pair (as ``voxfusion eval-ate``)."""
DECIMALS = 4
"""Rounding of positions and errors in the JSON (0.1 mm)."""
GROUND_TRUTH_FILES = ("traj.txt", "groundtruth.txt")
"""The ground-truth files a reader parses whole (Replica, TUM); the other layouts have one
small pose file per frame."""
MAX_GROUND_TRUTH_LINES = 200_000
"""Lines of a ground-truth file the series reads (TUM's longest has tens of thousands)."""
MAX_GROUND_TRUTH_BYTES = 64 * 1024 * 1024
"""Size of a ground-truth file the series reads."""
SOURCE_READ_TIMEOUT_S = 60.0
"""Longest the helper may take to open a source for the series (a normal one: a second)."""
SOURCE_WAIT_S = 5.0
"""Longest a series request waits for its turn at the helper."""
SOURCE_CACHE_ENTRIES = 16
SOURCE_CACHE_BYTES = 64 * 1024 * 1024
"""What the API process keeps of the sources' facts (a frame's centre and time: 32 bytes)."""


@dataclass(frozen=True)
class GroundTruth:
    """The ground truth as the series uses it.

    Attributes:
        timestamps: (N,) float64 seconds, the input's frame times.
        positions: (N, 3) float64 camera centres (metres, the ground truth's frame).
    """

    timestamps: np.ndarray
    positions: np.ndarray

    def __len__(self) -> int:
        return len(self.timestamps)


@dataclass(frozen=True)
class SourceFacts:
    """What the API process keeps of one source (read in the decode helper).

    Attributes:
        camera: the first frame's camera, or None (a stream, an unreadable input).
        truth: the ground truth, or None (none in the input, or not read: ``note`` says why).
        note: why the ground truth was not read, for the series answer; None otherwise.
    """

    camera: FrameCamera | None
    truth: GroundTruth | None
    note: str | None = None

    @property
    def nbytes(self) -> int:
        arrays = [] if self.truth is None else [self.truth.timestamps, self.truth.positions]
        arrays += [] if self.camera is None else [self.camera.K]
        return sum(int(a.nbytes) for a in arrays)


NOTHING = SourceFacts(None, None)


def ground_truth_problem(root: Path) -> str | None:
    """Why a dataset's ground-truth file is too large to read (size, then lines counted up to
    the cap), or None."""
    for name in GROUND_TRUTH_FILES:
        path = root / name
        if not path.is_file() or root.resolve() not in path.resolve().parents:
            continue  # absent, or a link out of the folder (the reader refuses it)
        if path.stat().st_size > MAX_GROUND_TRUTH_BYTES:
            return f"the ground truth is not shown: {name} is larger than {MAX_GROUND_TRUTH_BYTES // 2**20} MiB"
        lines = 0
        with path.open("rb") as file:
            while lines <= MAX_GROUND_TRUTH_LINES and (chunk := file.read(1 << 20)):
                lines += chunk.count(b"\n")
        if lines > MAX_GROUND_TRUTH_LINES:
            return f"the ground truth is not shown: {name} has more than {MAX_GROUND_TRUTH_LINES} lines"
    return None


def read_source_facts(spec: SourceSpec) -> SourceFacts:
    """The first frame's camera and the ground truth of a synthetic or dataset source (runs in
    the decode helper; module doc). NOTHING for a stream or an input that cannot be read."""
    if spec.kind not in ("synthetic", "dataset") or not spec.path:
        return NOTHING
    if spec.kind == "dataset" and (problem := ground_truth_problem(Path(spec.path))):
        return SourceFacts(None, None, problem)
    try:
        sequence = open_source(spec)
    except (DataError, OSError):
        return NOTHING
    return SourceFacts(_first_camera(sequence), _ground_truth(spec, sequence))


def _first_camera(sequence) -> FrameCamera | None:
    """The intrinsics and size of the sequence's first frame (decoded), or None."""
    try:
        frame = sequence[0]
    except (DataError, OSError, IndexError):
        return None
    return FrameCamera(np.asarray(frame.K, np.float64), frame.width, frame.height)


def _ground_truth(spec: SourceSpec, sequence) -> GroundTruth | None:
    """The frames' times and ground-truth camera centres (those frames that have a pose)."""
    if spec.kind == "synthetic":
        from slam.data.synthetic import FPS

        return GroundTruth(sequence.frame_numbers / FPS, sequence.trajectory[:, :3, 3].copy())
    pairs = [(t, T[:3, 3]) for t, T in zip(sequence.timestamps, sequence.gt_poses) if T is not None]
    if not pairs:
        return None
    return GroundTruth(np.array([t for t, _ in pairs], np.float64), np.array([c for _, c in pairs], np.float64))


class SourceFactsCache:
    """SourceFacts by source, the most recently used kept within ``max_entries`` and
    ``max_bytes`` (facts larger than the whole budget are not kept). Thread-safe."""

    def __init__(self, max_entries: int = SOURCE_CACHE_ENTRIES, max_bytes: int = SOURCE_CACHE_BYTES) -> None:
        self.max_entries, self.max_bytes = max_entries, max_bytes
        self._facts: OrderedDict[Hashable, SourceFacts] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Hashable) -> SourceFacts | None:
        with self._lock:
            if key in self._facts:
                self._facts.move_to_end(key)
            return self._facts.get(key)

    def put(self, key: Hashable, facts: SourceFacts) -> None:
        if facts.nbytes > self.max_bytes:
            return
        with self._lock:
            self._facts[key] = facts
            self._facts.move_to_end(key)
            while len(self._facts) > self.max_entries or self._nbytes() > self.max_bytes:
                self._facts.popitem(last=False)

    def nbytes(self) -> int:
        with self._lock:
            return self._nbytes()

    def _nbytes(self) -> int:
        return sum(f.nbytes for f in self._facts.values())

    def __len__(self) -> int:
        with self._lock:
            return len(self._facts)


_cache = SourceFactsCache()
_reads = HelperQueue("reading a session's input", SOURCE_WAIT_S, SOURCE_READ_TIMEOUT_S)


def _read_and_keep(spec: SourceSpec) -> SourceFacts:
    """On the queue's thread: the cache again (requests that queued for one source read it
    once), else the helper's answer, kept even when the request stopped waiting."""
    facts = _cache.get(spec)
    if facts is not None:
        return facts
    try:
        facts = shared_helper().call(read_source_facts, spec, timeout_s=_reads.timeout_s)
    except DecodeFailed as error:
        facts = SourceFacts(None, None, f"the ground truth is not shown: reading the input failed ({error})")
        if not isinstance(error, HelperTimedOut):  # the helper may have failed for reasons of its own
            return facts
    _cache.put(spec, facts)  # a read that timed out too: it would take as long again
    return facts


def source_facts(spec: SourceSpec) -> SourceFacts:
    """The camera and ground truth of ``spec``, read once in the decode helper (module doc)."""
    if spec.kind not in ("synthetic", "dataset") or not spec.path:
        return NOTHING
    facts = _cache.get(spec)
    if facts is not None:
        return facts
    try:
        return _reads.run(_read_and_keep, spec)
    except PoolBusy:
        return SourceFacts(None, None, "the ground truth is not shown yet: the server is busy reading inputs; "
                                       "ask again in a few seconds")


def source_camera(spec: SourceSpec) -> FrameCamera | None:
    """The input camera of a synthetic or dataset source (its first frame's intrinsics and
    size), or None (a stream, an unreadable input)."""
    return source_facts(spec).camera


@dataclass(frozen=True)
class TrajectoryComparison:
    """An estimate placed onto the ground truth.

    Attributes:
        estimated: (N, 3) camera centres, in the ground truth's frame when ``aligned``.
        errors: (N,) metres per estimated frame; NaN for a frame without a ground-truth pair.
        aligned: whether at least 3 non-collinear pairs fixed the alignment.
    """

    estimated: np.ndarray
    errors: np.ndarray
    aligned: bool

    @property
    def rmse(self) -> float | None:
        valid = self.errors[np.isfinite(self.errors)]
        return float(np.sqrt(np.mean(valid ** 2))) if self.aligned and len(valid) else None


def compare(estimate: Trajectory, truth: GroundTruth | Trajectory | None) -> TrajectoryComparison:
    """Align ``estimate`` onto ``truth`` (timestamps and positions) by its timestamp pairs;
    unaligned without enough pairs."""
    positions = estimate.positions
    unaligned = TrajectoryComparison(positions, np.full(len(positions), np.nan), False)
    if truth is None or len(estimate) < 3:
        return unaligned
    idx_gt, idx_est = associate(truth.timestamps, estimate.timestamps, MAX_DT_S)
    if len(idx_est) < 3:
        return unaligned
    try:
        paired = ate_from_pairs(truth.positions[idx_gt], positions[idx_est])
    except DataError:  # collinear: the rotation about the line is not determined
        return unaligned
    T_gt_est = paired.T_gt_est
    errors = np.full(len(positions), np.nan)
    errors[idx_est] = paired.errors
    return TrajectoryComparison(positions @ T_gt_est[:3, :3].T + T_gt_est[:3, 3], errors, True)


def rounded(values: np.ndarray) -> list:
    """Nested lists of rounded floats, NaN as None (JSON has no NaN)."""
    array = np.round(np.asarray(values, dtype=np.float64), DECIMALS)
    if array.ndim > 1:
        return [rounded(row) for row in array]
    return [float(v) if np.isfinite(v) else None for v in array]
