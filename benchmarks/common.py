"""Shared pieces of the benchmarks: data paths, figures with targets, markdown tables, machine
state (load average), peak memory of a process tree, mapping with given poses, cached frames.

Benchmarks are scripts, not tests: they print a markdown table and can write JSON
(``--json FILE``) that ``run_all.py`` gathers into one report.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"
REPLICA = SHARED_DATA / "Replica"
TUM_RPY = SHARED_DATA / "rgbd_dataset_freiburg1_rpy"


class MissingData(RuntimeError):
    """A benchmark's input is not on this machine; the message says which path."""


def require(path: Path) -> Path:
    """``path`` if it exists, else MissingData naming it (callers skip that figure)."""
    if not path.exists():
        raise MissingData(f"benchmark data not found: {path} (expected ../shared/data next to the repo)")
    return path


# ------------------------------------------------------------------ figures
@dataclass(frozen=True)
class Figure:
    """One measured number against its target.

    ``target`` is ``"<= 2.0"`` / ``">= 24"`` (checked) or free text (reported, not checked);
    ``value`` None means it could not be measured (``note`` says why).
    """

    name: str
    value: float | None
    unit: str
    target: str = ""
    note: str = ""

    @property
    def passed(self) -> bool | None:
        if self.value is None or not self.target[:2] in ("<=", ">="):
            return None
        bound = float(self.target[2:].split()[0])
        return self.value <= bound if self.target.startswith("<=") else self.value >= bound

    def row(self) -> list[str]:
        verdict = {True: "yes", False: "**no**", None: ""}[self.passed]
        target = f"{self.target} {self.unit}".strip() if self.target else ""
        return [self.name, format_number(self.value, self.unit), target, verdict, self.note]


def format_number(value: float | None, unit: str = "") -> str:
    if value is None:
        return "n/a"
    digits = 3 if abs(value) < 10 else (2 if abs(value) < 100 else 1)
    return f"{value:.{digits}f} {unit}".strip()


def markdown_table(headers: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join(" --- " for _ in headers) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def figures_table(figures: Sequence[Figure]) -> str:
    return markdown_table(["figure", "measured", "target", "met", "note"], [f.row() for f in figures])


# ------------------------------------------------------------ machine state
def machine_state() -> dict:
    """What a timing depends on: CPU count, load average now, torch threads, commit, time."""
    import torch

    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    return {
        "time": time.strftime("%Y-%m-%d %H:%M:%S %z"),
        "cpus": os.cpu_count(),
        "load_average_1_5_15": [round(x, 2) for x in load],
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "commit": _git_commit(),
    }


def _git_commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO_ROOT, capture_output=True,
                             text=True, timeout=10, check=False)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "slam"], cwd=REPO_ROOT,
                               capture_output=True, text=True, timeout=10, check=False)
        return out.stdout.strip() + ("+dirty slam/" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def load_line() -> str:
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f} / {five:.2f} / {fifteen:.2f} on {os.cpu_count()} CPUs"


def write_json(path: Path | None, payload: dict) -> None:
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2, default=_jsonable))


def _jsonable(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def figures_payload(title: str, figures: Sequence[Figure], extra: dict | None = None) -> dict:
    return {"title": title, "machine": machine_state(), "figures": [asdict(f) for f in figures],
            **(extra or {})}


# ------------------------------------------------------------- peak memory
def _tree_rss_psutil(pid: int) -> int:
    import psutil

    try:
        root = psutil.Process(pid)
        procs = [root] + root.children(recursive=True)
    except psutil.NoSuchProcess:
        return 0
    total = 0
    for proc in procs:
        try:
            total += proc.memory_info().rss
        except psutil.NoSuchProcess:
            pass
    return total


def _tree_rss_proc(pid: int) -> int:
    """Sum of VmRSS over ``pid`` and its descendants, read from /proc (no psutil)."""
    children: dict[int, list[int]] = {}
    rss: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            status = Path(f"/proc/{entry}/status").read_text()
        except OSError:
            continue
        fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
        ppid = int(fields.get("PPid", "0").strip())
        children.setdefault(ppid, []).append(int(entry))
        rss[int(entry)] = int(fields.get("VmRSS", "0 kB").split()[0]) * 1024
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        total += rss.get(p, 0)
        todo += children.get(p, [])
    return total


def tree_rss(pid: int) -> int:
    """Resident bytes of process ``pid`` and all its descendants (shared pages count per process)."""
    try:
        return _tree_rss_psutil(pid)
    except ImportError:
        return _tree_rss_proc(pid)


class PeakMemory:
    """Samples the RSS of a process tree in a thread; ``peak`` holds the largest sum seen."""

    def __init__(self, pid: int, interval: float = 0.05):
        self.pid, self.interval, self.peak = pid, interval, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, tree_rss(self.pid))
            self._stop.wait(self.interval)

    def __enter__(self) -> PeakMemory:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


@dataclass(frozen=True)
class ChildRun:
    returncode: int
    seconds: float
    peak_rss_bytes: int
    output: str


def run_child(args: list[str], timeout: float | None = None) -> ChildRun:
    """Run ``python args...`` from the repo root, sampling its process tree's peak RSS."""
    started = time.perf_counter()
    proc = subprocess.Popen([sys.executable, *args], cwd=REPO_ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    with PeakMemory(proc.pid) as memory:
        try:
            output, _ = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            output, _ = proc.communicate()
            output += f"\n[killed after {timeout} s]"
    return ChildRun(proc.returncode, time.perf_counter() - started, memory.peak, output)


# --------------------------------------------------------- cached sequences
class CachedSequence:
    """Frames saved as .npz in a folder, served like any ``RGBDSequence``.

    The synthetic generator ray-casts each frame in numpy (~0.1 s for 320x240), which would
    be timed as part of either SLAM system; rendering once and loading from disk makes the
    synthetic runs time the systems, as reading PNGs does for real data.
    """

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.files = sorted(self.folder.glob("frame_*.npz"))
        if not self.files:
            raise MissingData(f"no cached frames in {self.folder}")

    @property
    def has_gt(self) -> bool:
        return True

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, i: int):
        from slam.data.frame import Frame

        with np.load(self.files[i]) as data:
            T = data["T_world_cam"]
            return Frame(int(data["index"]), float(data["timestamp"]), data["rgb"], data["depth"], data["K"],
                         T if np.isfinite(T).all() else None)

    def __iter__(self) -> Iterator:
        for i in range(len(self)):
            yield self[i]


def cache_sequence(sequence, folder: Path) -> CachedSequence:
    """Write every frame of ``sequence`` to ``folder`` once (kept if already complete)."""
    folder.mkdir(parents=True, exist_ok=True)
    done = folder / "complete"
    if not done.exists():
        for frame in sequence:
            T = frame.T_world_cam if frame.T_world_cam is not None else np.full((4, 4), np.nan)
            np.savez(folder / f"frame_{frame.index:05d}.npz", index=frame.index, timestamp=frame.timestamp,
                     rgb=frame.rgb, depth=frame.depth, K=frame.K, T_world_cam=T)
        done.write_text(str(len(sequence)))
    return CachedSequence(folder)


# ------------------------------------------------------- mapping, GT poses
def frames_with_gt(path: str, max_frames: int | None, script: str) -> list:
    """Every frame of the sequence at ``path`` (at most ``max_frames``), each with its GT pose;
    a missing folder, unreadable data or a frame without GT ends ``script`` with a clear message."""
    from slam.data import open_sequence
    from slam.data.frame import DataError

    try:
        sequence = open_sequence(str(require(Path(path))), max_frames=max_frames)
        frames = [sequence[i] for i in range(len(sequence))]
    except (DataError, MissingData) as err:
        raise SystemExit(f"{script}: {err}") from None
    if any(f.T_world_cam is None for f in frames):
        raise SystemExit(f"{path}: every frame needs a ground-truth pose")
    return frames


def pipeline_frame(frame, width: int | None):
    """A reader frame at the pipeline width, as ``slam.runtime`` resizes it."""
    from slam.data.io import resize_frame

    return resize_frame(frame, width)


def map_with_gt_poses(frames: Sequence, config, *, extra_iterations: int = 0,
                      on_frame: Callable[[int, object], None] | None = None, device=None):
    """Map ``frames`` (already at pipeline size) with their GT poses as ``--gt-poses`` runs do:
    ``Mapper.process`` on every frame with keyframe poses fixed, then the end-of-sequence global
    bundle adjustment (``mapping.final_iterations``). ``extra_iterations`` adds more iterations
    of the windowed optimisation, in rounds of ``mapping.iterations`` over a fresh random
    keyframe window each. ``on_frame(i, mapper)`` runs after frame i is mapped. ``device``:
    where to map (default the CPU). Returns the ``Mapper``."""
    import torch

    from slam.frames import prepare_frame
    from slam.mapping import Mapper, TrackedFrame
    from slam.runtime import with_given_poses

    device = torch.device("cpu" if device is None else device)
    config = with_given_poses(config)
    torch.manual_seed(config.runtime.seed)
    mapper = Mapper(config, device, seed=config.runtime.seed)
    for i, frame in enumerate(frames):
        if frame.T_world_cam is None:
            raise ValueError(f"frame {frame.index} has no ground-truth pose to map with")
        tf = prepare_frame(frame, None, device, config.voxel.max_depth)
        mapper.process(TrackedFrame(tf, torch.as_tensor(frame.T_world_cam, dtype=torch.float32, device=device)))
        if on_frame is not None:
            on_frame(i, mapper)
    m = config.mapping
    mapper.global_bundle_adjustment(mapper.current, m.final_iterations, m.final_rays)
    # Extra rounds re-draw the keyframe window each time, as mapping more frames would.
    rounds, rest = divmod(extra_iterations, max(config.mapping.iterations, 1))
    for n in [config.mapping.iterations] * rounds + ([rest] if rest else []):
        mapper.optimize(mapper.current, n)
    return mapper


def T_gt_run(estimated, ground_truth) -> np.ndarray:
    """(4, 4) from a run's world to the ground truth's: runs start in their first camera's frame
    (issue 44 item 6), so ``T_gt(t0) T_est(t0)^-1`` at the first estimated timestamp t0
    (``Trajectory`` each; the GT pose nearest in time)."""
    t0 = estimated.timestamps[0]
    nearest = int(np.argmin(np.abs(ground_truth.timestamps - t0)))
    return ground_truth.poses[nearest] @ np.linalg.inv(estimated.poses[0])


def mesh_in_gt_frame(mesh, estimated, ground_truth):
    """A copy of a run's mesh moved into the ground truth's frame (``T_gt_run``)."""
    return mesh.copy().apply_transform(T_gt_run(estimated, ground_truth))


def map_memory_mb(mapper) -> dict[str, float]:
    """Embeddings and decoder MB as ``run.json`` counts them, plus the voxel index and the fine
    colour level's tables (``slam.fine_color``; 0 without one)."""
    embed = sum(m.voxels.embeddings.numel() * m.voxels.embeddings.element_size() for m in mapper.maps.maps)
    decoder = sum(m.decoder.num_bytes() for m in mapper.maps.maps)
    index = sum(m.voxels.nbytes() for m in mapper.maps.maps) - embed
    fine = sum(m.fine.num_bytes() for m in mapper.maps.maps if m.fine is not None)
    return {"embeddings": embed / 2**20, "decoder": decoder / 2**20, "voxel_index": index / 2**20,
            "fine": fine / 2**20, "voxels": mapper.maps.num_voxels()}


@dataclass
class Stopwatch:
    """Named wall-clock totals (seconds)."""

    totals: dict[str, float] = field(default_factory=dict)

    def time(self, name: str):
        watch = self

        class _Span:
            def __enter__(self):
                self.t0 = time.perf_counter()

            def __exit__(self, *exc):
                watch.totals[name] = watch.totals.get(name, 0.0) + time.perf_counter() - self.t0

        return _Span()
