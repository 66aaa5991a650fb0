"""Where a frame's time goes: every stage of a run, in ms a frame and as a share of wall time.

    python benchmarks/bench_stages.py [--sequences rpy150,sun3d,...] [--preset cpu] [--runs 1]
                                      [--peer] [--reuse DIR ...] [--json FILE] [--markdown FILE]

Each run is ``voxfusion run`` in a child process, the way users run it (tracking and mapping in
two processes), on the real sequences of ``bench_real.py`` (the whole fr1/rpy where the cache
has it). From its ``run.json`` (``timings_s``, filled by ``slam.profiling.StageClock`` on both
sides) it prints, per sequence:

* the run: frames, wall, frames/s, with ``--peer`` Open3D's frames/s at 1 cm in the same sitting
  and the ratio, ATE; the cost of the last 100 frames over the first 100 (``progress`` samples;
  the first 100 include the start: process spawn and the first frame's mapping); the end-of-run
  phases' share of wall;
* the tracking process's stages (read and decode, prepare, map update, ORB features, tracking,
  pixels kept for the re-tracking, publish, hand-over, the mapper's replies) and the mapping
  process's (keyframe decision, voxel allocation, the window's render -- sampling, rendering,
  decoder and losses -- and backward pass with the optimiser steps, loop detection, publish,
  checkpoint), each in ms a frame and as a share of the wall; the two processes run at once, so
  each side's shares add up to its own busy share;
* each end-of-run phase: the final bundle adjustment, the fine colour fit, the map and mesh
  written, the re-tracking (in the tracking process, beside the fit and the outputs), and their
  wall time together after the last frame.

``--reuse DIR`` reads finished runs (folders with ``run.json``) instead of running.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_real import Variant, run_peer, run_voxfusion, sequences  # noqa: E402
from common import markdown_table  # noqa: E402

TRACKING_STAGES = ("read", "prepare", "map_update", "features", "track", "keep_rays", "publish", "hand_over",
                   "replies")
"""The tracking process's stages for each frame, in the order a frame meets them."""
MAPPING_STAGES = ("keyframe_decision", "voxel_allocation", "render", "backward", "loop_detection", "publish",
                  "checkpoint")
"""The mapping process's stages during the run (render and backward include the idle optimisation)."""
END_PHASES = (("mapping_final_bundle_adjustment", "final bundle adjustment"),
              ("mapping_fine_fit", "fine colour fit"),
              ("mapping_final_outputs", "map and mesh written"),
              ("tracking_retracking", "re-tracking (beside the fit and outputs)"),
              ("tracking_end_of_run", "all of them, wall after the last frame"))
SPAN = 100
"""Frames of the first and last stretch compared for flat cost."""


@dataclass(frozen=True)
class RunFigures:
    """One run's figures from its run.json."""

    sequence: str
    frames: int
    wall_s: float
    fps: float
    ate_cm: float | None
    timings: dict[str, float]
    last_over_first: float | None
    """Seconds of the last SPAN frames over the first SPAN's (None: fewer than 2 x SPAN frames)."""

    @property
    def end_share(self) -> float:
        return self.timings.get("tracking_end_of_run", 0.0) / max(self.wall_s, 1e-9)


def last_over_first(progress: list[dict], span: int = SPAN) -> float | None:
    """Wall seconds of the run's last ``span`` tracked frames over its first ``span``'s, from
    ``run.json``'s progress samples (frames, wall_s), None when the run is shorter than 2 x span."""
    samples = {int(p["frames"]): float(p["wall_s"]) for p in progress}
    if not samples:
        return None
    last = max(samples)
    if last < 2 * span or span not in samples or last - span not in samples:
        return None
    return (samples[last] - samples[last - span]) / max(samples[span], 1e-9)


def figures(sequence: str, info: dict) -> RunFigures:
    ate = info.get("ate_rmse_m")
    return RunFigures(sequence, int(info["frames"]), float(info["timings_s"]["wall"]), float(info["fps"]),
                      None if ate is None else ate * 100, dict(info["timings_s"]),
                      last_over_first(info.get("progress", [])))


def stage_rows(runs: list[RunFigures]) -> list[list[str]]:
    """Per stage: ms a frame and share of wall, mean over the runs of one sequence."""
    rows = []

    def add(side: str, label: str, key: str, per_frame: bool = True) -> None:
        values = [r.timings.get(key) for r in runs]
        if all(v is None for v in values):
            return
        seconds = statistics.fmean(v or 0.0 for v in values)
        frames = statistics.fmean(r.frames for r in runs)
        share = statistics.fmean((r.timings.get(key) or 0.0) / max(r.wall_s, 1e-9) for r in runs)
        rows.append([side, label, f"{seconds:.1f}", f"{1000 * seconds / max(frames, 1):.1f}" if per_frame else "-",
                     f"{100 * share:.1f} %"])

    for stage in TRACKING_STAGES:
        add("tracking", stage, f"tracking_{stage}")
    add("tracking", "busy (all its stages but read, prepare, publish, hand-over, replies)", "tracking_busy")
    for stage in MAPPING_STAGES:
        add("mapping", stage, f"mapping_{stage}")
    add("mapping", "of which idle optimisation", "mapping_idle_optimisation")
    add("mapping", "busy", "mapping_busy")
    for key, label in END_PHASES:
        add("end of run", label, key, per_frame=False)
    return rows


def run_rows(runs: list[RunFigures], peer_fps: dict[str, list[float]]) -> list[list[str]]:
    rows = []
    for sequence in dict.fromkeys(r.sequence for r in runs):
        mine = [r for r in runs if r.sequence == sequence]
        fps = statistics.fmean(r.fps for r in mine)
        peer = statistics.fmean(peer_fps[sequence]) if peer_fps.get(sequence) else None
        ates = [r.ate_cm for r in mine if r.ate_cm is not None]
        ratios = [r.last_over_first for r in mine if r.last_over_first is not None]
        rows.append([sequence, str(len(mine)), str(mine[0].frames), f"{statistics.fmean(r.wall_s for r in mine):.0f}",
                     f"{fps:.2f}", "-" if peer is None else f"{peer:.2f}", "-" if peer is None else f"{fps / peer:.2f}x",
                     "-" if not ates else f"{statistics.fmean(ates):.2f}",
                     "-" if not ratios else f"{statistics.fmean(ratios):.2f}",
                     f"{100 * statistics.fmean(r.end_share for r in mine):.0f} %"])
    return rows


def report(runs: list[RunFigures], peer_fps: dict[str, list[float]]) -> str:
    parts = [markdown_table(["sequence", "runs", "frames", "wall s", "frames/s", "Open3D 1 cm frames/s", "ratio",
                             "ATE cm", f"last/first {SPAN} frames", "end of run"], run_rows(runs, peer_fps))]
    for sequence in dict.fromkeys(r.sequence for r in runs):
        parts.append(f"\n**{sequence}**\n")
        parts.append(markdown_table(["side", "stage", "s", "ms a frame", "share of wall"],
                                    stage_rows([r for r in runs if r.sequence == sequence])))
    return "\n".join(parts)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", default=None, help="comma-separated names (default: every one found)")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--peer", action="store_true", help="Open3D at 1 cm on each sequence in the same sitting")
    parser.add_argument("--reuse", type=Path, nargs="*", default=None, help="finished run folders (run.json) to read")
    parser.add_argument("--timeout", type=float, default=3600.0)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--markdown", type=Path, default=None)
    args = parser.parse_args()
    runs: list[RunFigures] = []
    peer_fps: dict[str, list[float]] = {}
    if args.reuse:
        runs = [figures(path.name, json.loads((path / "run.json").read_text())) for path in args.reuse]
    else:
        seqs = sequences(None)
        if args.sequences:
            seqs = [s for s in seqs if s.name in args.sequences.split(",")]
        work = Path(tempfile.mkdtemp(prefix="bench-stages-"))
        print(f"sequences: {', '.join(s.name for s in seqs)}; work in {work}", flush=True)
        for round_ in range(args.runs):
            for seq in seqs:
                started = time.perf_counter()
                info = run_voxfusion(seq, Variant(args.preset, args.preset), work / f"{seq.name}_{round_}", [],
                                     args.timeout)
                runs.append(figures(seq.name, info))
                print(f"round {round_} {seq.name}: {info['fps']:.2f} frames/s "
                      f"({time.perf_counter() - started:.0f} s)", flush=True)
                if args.peer:
                    peer = run_peer(seq, work / f"{seq.name}_open3d_{round_}", args.timeout)
                    peer_fps.setdefault(seq.name, []).append(float(peer["fps"]))
                    print(f"round {round_} {seq.name} open3d: {peer['fps']:.2f} frames/s", flush=True)
    text = report(runs, peer_fps)
    print("\n" + text)
    if args.markdown:
        args.markdown.write_text(text + "\n")
    if args.json:
        args.json.write_text(json.dumps({"runs": [r.__dict__ for r in runs], "peer_fps": peer_fps}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
