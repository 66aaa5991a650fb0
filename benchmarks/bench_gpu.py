"""The GPU figures of issue 40 in one command (about 8 minutes on a GPU; a few on a CPU).

Per preset (default ``gpu``, ``paper``, ``cpu``):

* **tracking ms a frame** and **mapping ms a window**: TUM fr1/rpy at the preset's width,
  frames 0-3 mapped with GT poses, then each next frame tracked from the previous GT pose
  (``Tracker.track``) and handed to ``Mapper.process`` (its window's optimisation), in this
  process, the device synchronised around each call; medians;
* **peak memory**: ``torch.cuda.max_memory_allocated`` over those calls (GPU only);
* **view ms**: a 640 x 480 colour + depth view of that map (``slam.views.render_view``), warm,
  median of three;
* **frames/s, ATE, SM busy**: ``run_slam`` on the fr1/rpy frames in process mode, loops on,
  the GPU sampled every 0.2 s meanwhile (NVML through ``pynvml`` when it imports, else
  ``nvidia-smi``, else n/a): mean utilisation (the share of time a kernel ran: what
  ``nvidia-smi dmon`` shows as ``sm``) and the peak memory the device reported;
* **ATE walk**: the same on the first 100 frames of the 200-frame synthetic walk (320 x 240);
* **4 sessions**: four ``voxfusion run`` processes (process mode, no loops) on 30 frames of
  that walk at once against one alone: total frames/s of the four over one's.

Data travels with the working tree: ``--prepare`` copies fr1/rpy from ``../shared/data`` into
``benchmarks/data/`` (git-ignored; colour as JPEG at quality 95 and depth as the original
16-bit PNGs, 150 frames in about 35 MB: the device machine takes 64 MiB), and the synthetic
scenes are generated. Without the copy, ``../shared/data`` is read where it exists.

A time budget (``--budget``, seconds) bounds the whole: a stage that would start after it is
reported as skipped. ``--device cpu`` is the quick mode (the ``test`` and ``cpu`` presets,
four frames at 160 px, 160 x 120 views, two-frame sessions): it checks the script, its
figures mean nothing.

    python benchmarks/bench_gpu.py --prepare [--prepare-frames 150]
    python benchmarks/bench_gpu.py [--device cuda|cpu] [--presets gpu,paper,cpu] [--frames 150]
        [--budget 450] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO_ROOT, SHARED_DATA, markdown_table, write_json  # noqa: E402

DATA = Path(__file__).resolve().parent / "data"
TUM_NAME = "rgbd_dataset_freiburg1_rpy"
WALK = "synthetic:walk?frames=200&width={width}&height={height}"
"""The 200-frame synthetic walk (its motion per frame is that of 200 frames); runs take the first N."""


# ------------------------------------------------------------------ data
def prepare(frames: int) -> Path:
    """Copy the first ``frames`` frames of fr1/rpy into benchmarks/data (colour as JPEG)."""
    import cv2

    src = SHARED_DATA / TUM_NAME
    if not src.is_dir():
        raise SystemExit(f"bench_gpu.py --prepare: {src} not found")
    dst = DATA / TUM_NAME
    if dst.exists():
        shutil.rmtree(dst)
    (dst / "rgb").mkdir(parents=True)
    (dst / "depth").mkdir()

    def entries(name: str) -> list[tuple[str, str]]:
        rows = []
        for line in (src / name).read_text().splitlines():
            if line.strip() and not line.startswith("#"):
                stamp, path = line.split()[:2]
                rows.append((stamp, path))
        return rows

    rgb = entries("rgb.txt")[:frames]
    last = float(rgb[-1][0]) + 0.05
    depth = [(s, p) for s, p in entries("depth.txt") if float(s) <= last]
    rgb_lines = []
    for stamp, path in rgb:
        image = cv2.imread(str(src / path), cv2.IMREAD_COLOR)
        out = Path(path).with_suffix(".jpg")
        cv2.imwrite(str(dst / out), image, [cv2.IMWRITE_JPEG_QUALITY, 95])
        rgb_lines.append(f"{stamp} {out}")
    for _, path in depth:
        shutil.copy2(src / path, dst / path)
    (dst / "rgb.txt").write_text("# color images (JPEG q95 of the originals)\n# timestamp filename\n"
                                 + "\n".join(rgb_lines) + "\n")
    (dst / "depth.txt").write_text("# depth maps\n# timestamp filename\n"
                                   + "\n".join(f"{s} {p}" for s, p in depth) + "\n")
    shutil.copy2(src / "groundtruth.txt", dst / "groundtruth.txt")
    size = sum(f.stat().st_size for f in dst.rglob("*") if f.is_file())
    print(f"{dst}: {len(rgb)} colour (JPEG) and {len(depth)} depth frames, {size / 2**20:.1f} MiB")
    return dst


def tum_path() -> Path | None:
    for base in (DATA, SHARED_DATA):
        if (base / TUM_NAME / "rgb.txt").exists():
            return base / TUM_NAME
    return None


# ------------------------------------------------------------------ GPU monitor
class GpuSampler:
    """Samples the GPU's utilisation (%) and memory used (MiB) every ``period`` s in a
    thread: NVML via pynvml, else nvidia-smi, else nothing (``source`` says which)."""

    def __init__(self, period: float = 0.2, index: int = 0):
        self.period, self.index = period, index
        self.util: list[float] = []
        self.memory: list[float] = []
        self.source = "n/a"
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._read = self._reader()

    def _reader(self):
        try:
            import pynvml

            pynvml.nvmlInit()
            handle = pynvml.nvmlDeviceGetHandleByIndex(self.index)
            self.source = "nvml"

            def read():
                u = pynvml.nvmlDeviceGetUtilizationRates(handle)
                m = pynvml.nvmlDeviceGetMemoryInfo(handle)
                return float(u.gpu), m.used / 2**20

            return read
        except Exception:  # noqa: BLE001 - no pynvml, or no driver: try the next source
            pass
        if shutil.which("nvidia-smi"):
            self.source = "nvidia-smi"

            def read():
                out = subprocess.run(["nvidia-smi", f"--id={self.index}", "--query-gpu=utilization.gpu,memory.used",
                                      "--format=csv,noheader,nounits"], capture_output=True, text=True, timeout=5)
                u, m = out.stdout.strip().split(",")[:2]
                return float(u), float(m)

            return read
        return None

    def __enter__(self) -> "GpuSampler":
        if self._read is not None:
            self._thread = threading.Thread(target=self._run, daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                u, m = self._read()
                self.util.append(u)
                self.memory.append(m)
            except Exception:  # noqa: BLE001 - a failed sample is skipped
                pass
            self._stop.wait(self.period)

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)

    def summary(self) -> dict:
        if not self.util:
            return {"sm_busy_pct": None, "peak_memory_mib": None, "source": self.source}
        return {"sm_busy_pct": statistics.fmean(self.util), "peak_memory_mib": max(self.memory),
                "source": self.source, "samples": len(self.util)}


# ------------------------------------------------------------------ stages
def _sync(device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def inner_timings(name: str, frames: list, device, width: int | None, steps: int,
                  view_size: tuple[int, int] = (640, 480)) -> dict:
    """Tracking ms a frame, mapping ms a window, peak memory and a view's ms (640 x 480)."""
    import torch

    from common import map_with_gt_poses, pipeline_frame

    from slam.config import preset
    from slam.frames import prepare_frame
    from slam.mapping import TrackedFrame
    from slam.tracking import FrozenMap, Tracker
    from slam.views import render_view

    config = preset(name)
    config = replace(config, runtime=replace(config.runtime, device=str(device)),
                     mapping=replace(config.mapping, final_iterations=0))
    width = config.runtime.input_width if width is None else width
    frames = [pipeline_frame(f, width) for f in frames[:4 + steps]]
    torch.manual_seed(0)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    mapper = map_with_gt_poses(frames[:4], config, device=device)
    tracker = Tracker(config, device)
    track_ms, map_ms = [], []
    for i in range(4, len(frames)):
        fmap = FrozenMap(mapper.snapshot(), config, device)
        tf = prepare_frame(frames[i], None, device, config.voxel.max_depth)
        T_prev = torch.as_tensor(frames[i - 1].T_world_cam, dtype=torch.float32, device=device)
        _sync(device)
        t0 = time.perf_counter()
        result = tracker.track(tf, fmap, T_prev)
        _sync(device)
        t1 = time.perf_counter()
        mapper.process(TrackedFrame(tf, result.T_world_cam))
        _sync(device)
        t2 = time.perf_counter()
        track_ms.append((t1 - t0) * 1e3)
        map_ms.append((t2 - t1) * 1e3)
    # The first of each pays compilation and allocator warm-up.
    out = {"tracking_ms": statistics.median(track_ms[1:] or track_ms),
           "mapping_ms": statistics.median(map_ms[1:] or map_ms), "steps": len(track_ms)}
    if device.type == "cuda":
        out["peak_allocated_mib"] = torch.cuda.max_memory_allocated(device) / 2**20
    vw, vh = view_size
    K = np.asarray(frames[0].K, np.float64) * np.array([[vw / frames[0].width], [vh / frames[0].height], [1.0]])
    T = frames[len(frames) // 2].T_world_cam
    times = []
    for _ in range(4):
        _sync(device)
        t0 = time.perf_counter()
        render_view(mapper.maps, T, K, vw, vh, device=device)
        _sync(device)
        times.append((time.perf_counter() - t0) * 1e3)
    out["view_640x480_ms"] = statistics.median(times[1:])
    return out


def whole_run(name: str, source: str, device, frames: int, width: int | None, timeout: float) -> dict:
    """run_slam in process mode, loops on, in a child process, the GPU sampled meanwhile."""
    with tempfile.TemporaryDirectory() as out, GpuSampler() as gpu:
        cmd = [sys.executable, "-m", "slam.cli", "run", source, "--out", out, "--preset", name,
               "--device", str(device.type), "--max-frames", str(frames), "--quiet"]
        if width is not None:
            cfg = Path(out) / "width.json"
            cfg.write_text(json.dumps({"runtime": {"input_width": width}}))
            cmd += ["--config", str(cfg)]
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=REPO_ROOT)
        except subprocess.TimeoutExpired:
            return {"error": f"over {timeout:.0f} s"}
        wall = time.perf_counter() - t0
        run = Path(out) / "run.json"
        if proc.returncode != 0 or not run.exists():
            return {"error": (proc.stderr or proc.stdout)[-400:]}
        data = json.loads(run.read_text())
    ate = data.get("ate_rmse_m")
    return {"frames": data.get("frames"), "fps": data.get("fps"), "wall_s": wall,
            "ate_cm": None if ate is None else ate * 100, **gpu.summary()}


def sessions(name: str, device, count: int, frames: int, size: tuple[int, int], timeout: float) -> dict:
    """``count`` runs at once against one alone: total frames/s of all over one's."""
    spec = WALK.format(width=size[0], height=size[1])

    def launch(out: str) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "slam.cli", "run", spec, "--out", out, "--preset", name,
                                 "--device", device.type, "--no-loops", "--quiet", "--max-frames", str(frames)],
                                cwd=REPO_ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)

    def wait_all(procs, deadline) -> bool:
        for p in procs:
            try:
                p.wait(timeout=max(1.0, deadline - time.perf_counter()))
            except subprocess.TimeoutExpired:
                for q in procs:
                    q.kill()
                return False
        return all(p.returncode == 0 for p in procs)

    with tempfile.TemporaryDirectory() as root:
        t0 = time.perf_counter()
        ok = wait_all([launch(f"{root}/one")], t0 + timeout / 3)
        one = time.perf_counter() - t0
        if not ok:
            return {"error": "the single session failed or ran out of time"}
        t0 = time.perf_counter()
        with GpuSampler() as gpu:
            ok = wait_all([launch(f"{root}/s{k}") for k in range(count)], t0 + 2 * timeout / 3)
        many = time.perf_counter() - t0
        if not ok:
            return {"error": f"{count} sessions failed or ran out of time"}
    one_fps, many_fps = frames / one, count * frames / many
    return {"sessions": count, "one_fps": one_fps, "total_fps": many_fps, "ratio": many_fps / one_fps,
            **{f"concurrent_{k}": v for k, v in gpu.summary().items()}}


# ------------------------------------------------------------------ main
def fmt(value, digits: int = 1, unit: str = "") -> str:
    if value is None:
        return "n/a"
    if isinstance(value, str):
        return value
    return f"{value:.{digits}f}{unit}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--prepare", action="store_true", help="copy fr1/rpy into benchmarks/data and stop")
    parser.add_argument("--prepare-frames", type=int, default=150)
    parser.add_argument("--device", default="cuda", choices=("cuda", "cpu"))
    parser.add_argument("--presets", default=None, help="default: gpu,paper,cpu (cpu device: test,cpu)")
    parser.add_argument("--frames", type=int, default=None, help="fr1/rpy frames of the whole runs (150; cpu: 6)")
    parser.add_argument("--budget", type=float, default=450.0, help="seconds for everything")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.prepare:
        prepare(args.prepare_frames)
        return 0

    import torch

    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("bench_gpu.py: no CUDA device (use --device cpu for the quick mode)")
    device = torch.device(args.device)
    quick = device.type == "cpu"
    names = (args.presets or ("test,cpu" if quick else "gpu,paper,cpu")).split(",")
    frames = args.frames or (4 if quick else 150)
    width = 160 if quick else None
    steps = 2 if quick else 8
    session_frames, session_size = (2, (160, 120)) if quick else (30, (320, 240))
    walk_frames, walk_size = (4, (160, 120)) if quick else (100, (320, 240))
    started = time.perf_counter()
    tum = tum_path()
    gpu_name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU (quick mode)"
    print(f"device: {gpu_name}; fr1/rpy from {tum or 'nowhere (skipped)'}", flush=True)
    real = []
    if tum is not None:
        from slam.data import open_sequence

        seq = open_sequence(str(tum), max_frames=4 + steps)
        real = [seq[i] for i in range(len(seq))]
    results: dict = {"device": gpu_name, "presets": {}}

    def left() -> float:
        return args.budget - (time.perf_counter() - started)

    for name in names:
        r: dict = {}
        results["presets"][name] = r
        share = left() / max(1, len(names) - list(names).index(name))
        if real and left() > 20:
            try:
                r["inner"] = inner_timings(name, real, device, width, steps, (160, 120) if quick else (640, 480))
            except Exception as err:  # noqa: BLE001 - one stage's failure is reported, the rest still runs
                r["inner"] = {"error": f"{type(err).__name__}: {err}"}
        if tum is not None and left() > 20:
            r["run"] = whole_run(name, str(tum), device, frames, width, timeout=max(20.0, 0.5 * share))
        if left() > 20:
            r["walk"] = whole_run(name, WALK.format(width=walk_size[0], height=walk_size[1]),
                                  device, walk_frames, None, timeout=max(20.0, 0.2 * share))
        if left() > 20:
            r["sessions"] = sessions(name, device, 4, session_frames, session_size, timeout=max(30.0, 0.3 * share))
        print(f"done {name} ({time.perf_counter() - started:.0f} s)", file=sys.stderr, flush=True)

    rows = []
    for name, r in results["presets"].items():
        inner, run, walk, many = r.get("inner", {}), r.get("run", {}), r.get("walk", {}), r.get("sessions", {})
        rows.append([
            name, fmt(inner.get("tracking_ms"), 0), fmt(inner.get("mapping_ms"), 0),
            fmt(run.get("fps"), 2) if "error" not in run else "failed", fmt(run.get("ate_cm"), 2),
            fmt(walk.get("ate_cm"), 2), fmt(run.get("sm_busy_pct"), 0, " %"),
            fmt(inner.get("peak_allocated_mib"), 0) + " / " + fmt(run.get("peak_memory_mib"), 0),
            fmt(inner.get("view_640x480_ms"), 0),
            ("failed" if "error" in many else f"{fmt(many.get('total_fps'), 2)} ({fmt(many.get('ratio'), 2)}x)")
            if many else "skipped"])
    print(markdown_table(["preset", "tracking ms/frame", "mapping ms/window", f"run frames/s ({frames} fr1/rpy)",
                          "ATE fr1/rpy cm", f"ATE walk ({walk_frames}) cm", "SM busy", "peak MiB (in-process / device)",
                          "view ms (640x480; quick: 160x120)", "4 sessions frames/s (x one)"], rows))
    for name, r in results["presets"].items():
        for stage, value in r.items():
            if isinstance(value, dict) and "error" in value:
                print(f"{name} {stage}: {value['error']}", file=sys.stderr)
    results["seconds"] = time.perf_counter() - started
    write_json(args.json, results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
