"""The whole SLAM loop (issue 4 figures): voxfusion against the classical Open3D peer.

For each sequence, each system runs in its own child process (so that its peak memory, the
RSS summed over its process tree, is its own): voxfusion through ``slam.runtime.run_slam``
with the ``cpu`` preset (every frame tracked, tracking and mapping in separate processes),
the peer through ``peer_open3d.run_open3d_slam`` at its default voxels (``open3d``) and at
1 cm (``open3d-1cm``). The parent then computes ATE RMSE
(``slam.eval.ate``, rigid alignment) against the ground truth and, where a GT mesh exists,
mesh metrics with the GT culled to what the cameras saw (occlusion-aware).

Sequences: ``synthetic:walk?frames=200`` at 320x240 (rendered once into a frame cache so the
ray caster is not timed as part of either system) and TUM fr1/rpy, first 150 frames at
640x480. frames/s = frames / wall time of the whole SLAM call, final mesh included; the
ratio of voxfusion's to each peer's is a figure (issue 18: >= 0.6x the default peer's).

    python benchmarks/bench_slam.py [--quick] [--systems voxfusion,open3d,open3d-1cm] [--json FILE]
    python benchmarks/bench_slam.py --worker voxfusion|open3d|open3d-1cm --source S --out DIR   (internal)
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (
    TUM_RPY,
    CachedSequence,
    Figure,
    MissingData,
    cache_sequence,
    figures_payload,
    load_line,
    markdown_table,
    mesh_in_gt_frame,
    require,
    run_child,
    write_json,
)

SYSTEMS = ("voxfusion", "open3d", "open3d-1cm")
"""``open3d`` is the peer at its default voxels (3 m / 512, 5.86 mm); ``open3d-1cm`` the same
at 1 cm voxels, a map closer to ours in detail and cheaper to integrate and ray-cast."""
PEER_VOXEL_SIZE = {"open3d": 3.0 / 512, "open3d-1cm": 0.01}


@dataclass(frozen=True)
class BenchSequence:
    """name; source: a dataset folder or a frame-cache folder; peer_depth_max in metres."""

    name: str
    source: Path
    max_frames: int
    peer_depth_max: float
    synthetic_spec: str | None = None
    ate_target_cm: float | None = None
    accuracy_target_cm: float | None = None


def open_source(source: Path, max_frames: int):
    """A frame cache (``frame_*.npz``) or a dataset folder, limited to ``max_frames``."""
    if any(source.glob("frame_*.npz")):
        cached = CachedSequence(source)
        cached.files = cached.files[:max_frames]
        return cached
    from slam.data import open_sequence

    return open_sequence(source, max_frames=max_frames)


# ----------------------------------------------------------------- workers
def worker_voxfusion(source: Path, max_frames: int, out: Path, preset_name: str, quick: bool) -> dict:
    from dataclasses import replace

    from slam.config import preset
    from slam.runtime import run_slam

    config = preset(preset_name)
    if quick:  # a smoke run: shorter map initialisation, same code paths
        config = replace(config, mapping=replace(config.mapping, first_frame_iterations=20))
    sequence = open_source(source, max_frames)
    result = run_slam([sequence], config, out)
    info = json.loads((out / "run.json").read_text())
    if result.status != "finished":
        raise RuntimeError(f"voxfusion run {result.status}: {result.error}")
    return {"frames": result.frames, "seconds": info["timings_s"]["wall"], "fps": result.fps,
            "map_mb": sum(info["map_memory_mb"].values()),
            "keyframes": result.keyframes, "busy_share": info["busy_share"],
            "tracking_failures": info["tracking_failures"], "run_ate_m": info["ate_rmse_m"],
            "timings_s": info["timings_s"]}


def worker_open3d(source: Path, max_frames: int, out: Path, depth_max: float, voxel_size: float) -> dict:
    import trimesh
    from peer_open3d import Open3DParams, run_open3d_slam

    from slam.eval import Trajectory, write_tum

    sequence = open_source(source, max_frames)
    t0 = time.perf_counter()
    result = run_open3d_slam(sequence, Open3DParams(voxel_size=voxel_size, depth_max=depth_max))
    write_tum(out / "trajectory.txt", Trajectory(result.timestamps, result.poses))
    mesh = trimesh.Trimesh(result.vertices, result.faces, vertex_colors=result.colors, process=False)
    mesh.export(out / "mesh.ply")
    seconds = time.perf_counter() - t0
    frames = len(result.timestamps)
    return {"frames": frames, "seconds": seconds, "fps": frames / seconds,
            "loop_fps": frames / result.loop_seconds, "map_mb": result.map_mb,
            "capacity_mb": result.capacity_blocks * result.bytes_per_block / 2**20,
            "active_blocks": result.active_blocks, "tracking_failures": result.tracking_failures}


def worker_main(args) -> int:
    args.out.mkdir(parents=True, exist_ok=True)
    if args.worker == "voxfusion":
        info = worker_voxfusion(args.source, args.max_frames, args.out, args.preset, args.quick)
    else:
        info = worker_open3d(args.source, args.max_frames, args.out, args.depth_max, PEER_VOXEL_SIZE[args.worker])
    (args.out / "result.json").write_text(json.dumps(info, indent=2))
    return 0


# ------------------------------------------------------------------ parent
def sequences(quick: bool, work: Path) -> list[BenchSequence]:
    """The two benchmark sequences; the synthetic one rendered into ``work`` once."""
    from slam.data import open_sequence

    # --quick takes the first frames of the same 200-frame path (a shorter spec would move
    # faster: the path is spread over the frames it is given).
    frames = 10 if quick else 200
    spec = "synthetic:walk?frames=200"
    cache = cache_sequence(open_sequence(spec, max_frames=frames), work / f"cache_walk200_{frames}")
    out = [BenchSequence(f"synthetic walk {frames} @320x240", cache.folder, frames, 6.0, spec, 1.0, 2.0)]
    if TUM_RPY.is_dir():
        out.append(BenchSequence(f"TUM fr1/rpy {10 if quick else 150} @640x480", TUM_RPY, 10 if quick else 150,
                                 3.0, None, 5.0, None))
    return out


def gt_trajectory(seq: BenchSequence):
    from slam.eval import Trajectory, read_trajectory

    if seq.synthetic_spec is None:
        return read_trajectory(require(seq.source / "groundtruth.txt"))
    cached = open_source(seq.source, seq.max_frames)
    frames = [cached[i] for i in range(len(cached))]
    return Trajectory(np.array([f.timestamp for f in frames]), np.stack([f.T_world_cam for f in frames]))


def evaluate(seq: BenchSequence, out: Path, info: dict, points: int) -> dict:
    """ATE (cm) and, for the synthetic scene, mesh metrics (cm, %) of one run's outputs."""
    import trimesh

    from slam.data import open_sequence
    from slam.eval import CullCamera, ate, mesh_metrics, read_trajectory

    truth, estimate = gt_trajectory(seq), read_trajectory(out / "trajectory.txt")
    result = {"ate_cm": ate(truth, estimate).rmse * 100}
    if seq.synthetic_spec is not None and (out / "mesh.ply").is_file():
        rec = mesh_in_gt_frame(trimesh.load(out / "mesh.ply", force="mesh", process=False), estimate, truth)
        cached = open_source(seq.source, seq.max_frames)
        frames = [cached[i] for i in range(len(cached))]
        cameras = [CullCamera(f.K, f.T_world_cam, f.width, f.height) for f in frames]
        metrics = mesh_metrics(rec, open_sequence(seq.synthetic_spec).gt_mesh(), num_points=points,
                               cull_cameras=cameras, gt_depths=[f.depth for f in frames])
        result.update(accuracy_cm=metrics.accuracy * 100, completion_cm=metrics.completion * 100,
                      completion_ratio=metrics.completion_ratio * 100)
    return result


def run_system(system: str, seq: BenchSequence, work: Path, preset_name: str, points: int,
               timeout: float, quick: bool) -> dict:
    out = work / f"{system}_{seq.name.split()[0]}_{seq.max_frames}"
    args = ["benchmarks/bench_slam.py", "--worker", system, "--source", str(seq.source), "--max-frames",
            str(seq.max_frames), "--out", str(out), "--depth-max", str(seq.peer_depth_max), "--preset", preset_name]
    args += ["--quick"] if quick else []
    load_before = load_line()
    if system.startswith("open3d") and importlib.util.find_spec("open3d") is None:
        from peer_open3d import INSTALL_HINT

        return {"system": system, "sequence": seq.name, "child_seconds": 0.0, "load_after": load_before,
                "error": f"skipped: {INSTALL_HINT}"}
    child = run_child(args, timeout=timeout)
    row = {"system": system, "sequence": seq.name, "peak_rss_mb": child.peak_rss_bytes / 2**20,
           "child_seconds": child.seconds, "load_before": load_before, "load_after": load_line()}
    if child.returncode != 0 or not (out / "result.json").is_file():
        tail = "\n".join(child.output.strip().splitlines()[-5:])
        return {**row, "error": f"exit code {child.returncode}: {tail}"}
    info = json.loads((out / "result.json").read_text())
    return {**row, **info, **evaluate(seq, out, info, points)}


def cell(row: dict, key: str, digits: int = 2) -> str:
    value = row.get(key)
    return "n/a" if value is None else f"{value:.{digits}f}"


def results_table(rows: list[dict]) -> str:
    lines = []
    for r in rows:
        if "error" in r:
            lines.append([r["system"], r["sequence"]] + ["n/a"] * 7 + [r["error"].replace("\n", " ")[:200]])
            continue
        notes = []
        if "busy_share" in r:
            notes.append(f"busy: tracking {r['busy_share']['tracking']:.0%}, mapping {r['busy_share']['mapping']:.0%}; "
                         f"{r['keyframes']} keyframes")
        if "loop_fps" in r:
            notes.append(f"{r['active_blocks']} blocks, {r['capacity_mb']:.0f} MB allocated; loop {r['loop_fps']:.2f} fps")
        if r.get("tracking_failures"):
            notes.append(f"{r['tracking_failures']} tracking failures")
        notes.append(f"load {r['load_before'].split()[2]} -> {r['load_after'].split()[2]}")
        lines.append([r["system"], r["sequence"], cell(r, "ate_cm"), cell(r, "accuracy_cm"), cell(r, "completion_cm"),
                      cell(r, "completion_ratio", 1), cell(r, "fps"), cell(r, "peak_rss_mb", 0), cell(r, "map_mb", 3),
                      "; ".join(notes)])
    return markdown_table(["system", "sequence", "ATE RMSE (cm)", "acc. (cm)", "comp. (cm)", "comp. ratio (%)",
                           "frames/s", "peak RSS (MB)", "map (MB)", "notes"], lines)


def target_figures(rows: list[dict], seqs: list[BenchSequence]) -> list[Figure]:
    figures = []
    for seq in seqs:
        for r in rows:
            if r["system"] != "voxfusion" or r["sequence"] != seq.name:
                continue
            err = r.get("error", "")
            if seq.ate_target_cm is not None:
                figures.append(Figure(f"{seq.name}: ATE RMSE", r.get("ate_cm"), "cm", f"<= {seq.ate_target_cm}", err))
            if seq.accuracy_target_cm is not None:
                figures.append(Figure(f"{seq.name}: mesh accuracy", r.get("accuracy_cm"), "cm",
                                      f"<= {seq.accuracy_target_cm}", err))
            if seq.synthetic_spec is None:
                figures.append(Figure(f"{seq.name}: frames/s, every frame tracked", r.get("fps"), "fps", ">= 1", err))
            for peer in ("open3d", "open3d-1cm"):
                other = next((o for o in rows if o["system"] == peer and o["sequence"] == seq.name), None)
                if other is None or "error" in other or "error" in r:
                    continue
                real = seq.synthetic_spec is None
                target = (">= 0.6" if peer == "open3d" else ">= 1.0") if real else ""
                figures.append(Figure(f"{seq.name}: frames/s against {peer} (same run)", r["fps"] / other["fps"],
                                      "x", target, f"{r['fps']:.2f} against {other['fps']:.2f} frames/s"))
            timings = r.get("timings_s") or {}
            if "tracking_end_of_run" in timings and timings.get("wall"):
                figures.append(Figure(f"{seq.name}: end-of-run phases, share of wall",
                                      100 * timings["tracking_end_of_run"] / timings["wall"], "%", "<= 10",
                                      "final bundle adjustment, re-tracking, colour fit, map and mesh"))
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: 10 frames per sequence")
    parser.add_argument("--systems", default=",".join(SYSTEMS))
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--work", type=Path, default=None, help="outputs of the runs (default: a temp folder)")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds per run")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--worker", choices=SYSTEMS, help=argparse.SUPPRESS)
    parser.add_argument("--source", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--max-frames", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--depth-max", type=float, default=3.0, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return worker_main(args)

    systems = args.systems.split(",")
    unknown = set(systems) - set(SYSTEMS)
    if unknown:
        parser.error(f"unknown systems {sorted(unknown)}; choose from {SYSTEMS}")
    work = args.work or Path(tempfile.gettempdir()) / "voxfusion-bench-slam"
    points = 20_000 if args.quick else 200_000
    print(f"# Whole SLAM loop: {', '.join(systems)} ({args.preset} preset)\n")
    print(f"start: {load_line()}; outputs in {work}\n", flush=True)
    t0 = time.perf_counter()
    try:
        seqs = sequences(args.quick, work)
    except MissingData as missing:
        print(f"skipped: {missing}")
        return 0
    rows = []
    for seq in seqs:
        for system in systems:
            row = run_system(system, seq, work, args.preset, points, args.timeout, args.quick)
            rows.append(row)
            status = row.get("error", f"ATE {cell(row, 'ate_cm')} cm, {cell(row, 'fps')} fps")
            print(f"{system} on {seq.name}: {row['child_seconds']:.0f} s, {status}; {row['load_after']}", flush=True)
    table = results_table(rows)
    figures = target_figures(rows, seqs)
    from common import figures_table

    print()
    print(table)
    print()
    print(figures_table(figures))
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; end: {load_line()}")
    write_json(args.json, figures_payload("Whole SLAM loop against Open3D (issue 4)", figures,
                                          {"rows": rows, "table": table, "quick": args.quick}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
