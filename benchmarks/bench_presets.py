"""Presets against each other on short windows (issue 21): the ``paper`` preset is the
paper's system as stated (and the Vox-Fusion release where the paper is silent), ``cpu``
is ours; this measures what the difference costs and buys on a CPU.

Each run is ``bench_slam.py``'s voxfusion worker in its own child process (tracking and
mapping in separate processes, the final mesh included in the wall time); ATE RMSE is the
run's own (rigid alignment on the frames it tracked).

Sequences: TUM fr1/rpy, first 30 frames (640x480); ``synthetic:walk?frames=200``, first 60
frames (320x240, rendered once into a frame cache).

    python benchmarks/bench_presets.py [--presets cpu,paper] [--rpy-frames 30] [--walk-frames 60]
                                       [--timeout S] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import TUM_RPY, cache_sequence, load_line, markdown_table, run_child, write_json  # noqa: E402

WALK_SPEC = "synthetic:walk?frames=200"


def sources(work: Path, rpy_frames: int, walk_frames: int) -> list[tuple[str, Path, int]]:
    """(name, source folder, frames) of the two windows; fr1/rpy only where the data is."""
    from slam.data import open_sequence

    cache = cache_sequence(open_sequence(WALK_SPEC, max_frames=walk_frames), work / f"walk200_{walk_frames}")
    out = [(f"synthetic walk {walk_frames}", cache.folder, walk_frames)]
    if TUM_RPY.is_dir():
        out.insert(0, (f"fr1/rpy {rpy_frames}", TUM_RPY, rpy_frames))
    return out


def run_one(source: Path, frames: int, preset: str, out: Path, timeout: float) -> dict:
    child = run_child(["benchmarks/bench_slam.py", "--worker", "voxfusion", "--source", str(source),
                       "--max-frames", str(frames), "--out", str(out), "--preset", preset], timeout=timeout)
    result = out / "result.json"
    if child.returncode != 0 or not result.exists():
        return {"error": child.output[-2000:]}
    info = json.loads(result.read_text())
    return {"ate_cm": 100 * info["run_ate_m"], "fps": info["fps"], "seconds": info["seconds"],
            "keyframes": info["keyframes"], "tracking_failures": info["tracking_failures"]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--presets", default="cpu,paper")
    p.add_argument("--rpy-frames", type=int, default=30)
    p.add_argument("--walk-frames", type=int, default=60)
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds per run")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args()
    presets = args.presets.split(",")
    results: dict[str, dict[str, dict]] = {}
    print(load_line())
    with tempfile.TemporaryDirectory(prefix="bench-presets-") as tmp:
        work = Path(tmp)
        for window, (name, source, frames) in enumerate(sources(work, args.rpy_frames, args.walk_frames)):
            for preset in presets:
                r = run_one(source, frames, preset, work / f"{preset}_{window}", args.timeout)
                results.setdefault(name, {})[preset] = r
                print(name, preset, json.dumps(r)[:300], flush=True)
    rows = []
    for name, by_preset in results.items():
        for preset, r in by_preset.items():
            if "error" in r:
                rows.append([name, preset, "error", "", "", ""])
                continue
            rows.append([name, preset, f"{r['ate_cm']:.2f}", f"{r['fps']:.3f}", str(r["keyframes"]),
                         str(r["tracking_failures"])])
    print(markdown_table(["window", "preset", "ATE cm", "frames/s", "keyframes", "tracking failures"], rows))
    print(load_line())
    write_json(args.json, {"title": "presets", "results": results})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
