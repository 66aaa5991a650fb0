"""Tracker variants side by side, one frame at a time against a fresh map (issue 18 item 3).

The map holds frames 0..i mapped with their GT poses (``map_with_gt_poses``: no pose error in
the map, and no lag: the tracker sees every frame before the one it tracks). Each variant
then tracks frame i+1 from frame i's GT pose, with the ORB correspondences the runtime would
give it (the features of frame i remembered at its GT pose). The variants run on the same
frames in turn, so their error against GT (translation, rotation) and their thread CPU time
per frame compare within one run. A variant is a set of config overrides.

    python benchmarks/bench_tracking.py [--sequence fr1_rpy|laps|PATH|SPEC] [--start 20]
        [--frames 40] [--variants JSON] [--map-config JSON] [--json FILE] [--per-frame]

``--map-config`` overrides the mapper's config (the ``cpu`` preset's), e.g.
``{"mapping": {"window_size": 6}}`` to compare the trackers against a map built
another way (one map per run: run it once per map setting).

The default variants are the ``cpu`` preset against its tracker before issue 18's cuts (6
steps, colour Jacobian on samples > 1e-3, stop below 1e-5).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import TUM_RPY, frames_with_gt, pipeline_frame, write_json  # noqa: E402

LAPS = "synthetic:laps?frames=780&width=160&height=120&noise=1"
SEQUENCES = {"fr1_rpy": str(TUM_RPY), "laps": LAPS}
DEFAULT_VARIANTS = {
    "cpu": {},
    "before": {"tracking": {"iterations": 6, "color_weight_eps": 1e-3, "convergence_tol": 1e-5}},
}


def config_of(base, overrides: dict):
    from slam.config import config_from_dict

    merged = base.to_dict()
    for section, fields in overrides.items():
        merged[section].update(fields)
    return config_from_dict(merged)


def read_frames(sequence: str, count: int) -> list:
    spec = SEQUENCES.get(sequence, sequence)
    if spec.startswith("synthetic:"):
        import bench_loops

        cached = bench_loops.cached(spec)
        return [cached[i] for i in range(min(count, len(cached)))]
    return frames_with_gt(spec, count, "bench_tracking.py")


def run(sequence: str, start: int, count: int, variants: dict, map_overrides: dict | None = None) -> dict:
    import torch

    import slam.kernels
    from common import map_with_gt_poses
    from slam.config import preset
    from slam.features import FeatureOdometry
    from slam.frames import prepare_frame
    from slam.geometry import se3_inverse, se3_log
    from slam.mapping import Mapper
    from slam.tracking import FrozenMap, Tracker

    torch.set_num_threads(1)
    slam.kernels.warm_up()
    base = preset("cpu")
    base = replace(base, mapping=replace(base.mapping, final_iterations=0))
    map_config = config_of(base, map_overrides or {})
    configs = {name: config_of(base, o) for name, o in variants.items()}
    raw = read_frames(sequence, start + count + 1)
    if len(raw) < start + 2:
        raise SystemExit(f"bench_tracking.py: {sequence} has {len(raw)} frames, fewer than --start + 2")
    frames = [pipeline_frame(f, base.runtime.input_width) for f in raw]
    device = torch.device("cpu")
    features = FeatureOdometry.from_config(base)
    results = {name: {"seconds": [], "error_mm": [], "error_deg": [], "ok": 0} for name in variants}

    def pose(i: int) -> torch.Tensor:
        return torch.as_tensor(raw[i].T_world_cam, dtype=torch.float32)

    def after_mapping(i: int, mapper: Mapper) -> None:
        j = i + 1
        if i < start or j >= len(frames):
            return
        fmap = FrozenMap(mapper.snapshot(), map_config, device)
        frame = prepare_frame(frames[j], None, device, base.voxel.max_depth)
        features.correspondences(raw[i])
        features.remember(np.asarray(raw[i].T_world_cam, np.float64))
        matches = features.correspondences(raw[j])
        for name, config in configs.items():
            tracker = Tracker(config, device, seed=j)
            guess = pose(i)
            t0 = time.thread_time()
            result = tracker.track(frame, fmap, guess, matches if config.tracking.feature_count else None)
            seconds = time.thread_time() - t0
            xi = se3_log(se3_inverse(pose(j)) @ result.T_world_cam)
            r = results[name]
            r["seconds"].append(seconds)
            r["error_mm"].append(float(xi[:3].norm()) * 1000)
            r["error_deg"].append(float(xi[3:].norm()) * 180 / np.pi)
            r["ok"] += int(result.ok)

    map_with_gt_poses(frames[: start + count + 1], map_config, on_frame=after_mapping)
    return results


def summary(results: dict) -> list[dict]:
    first = next(iter(results.values()))
    rows = []
    for name, r in results.items():
        ratio = statistics.median(a / b for a, b in zip(r["seconds"], first["seconds"]))
        rows.append({"variant": name, "ms_per_frame": 1000 * statistics.mean(r["seconds"]),
                     "time_ratio": ratio, "error_mm": statistics.mean(r["error_mm"]),
                     "error_deg": statistics.mean(r["error_deg"]),
                     "median_error_mm": statistics.median(r["error_mm"]),
                     "ok": r["ok"], "frames": len(r["seconds"])})
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequence", default="fr1_rpy", help="fr1_rpy, laps, a folder or a synthetic: spec")
    parser.add_argument("--start", type=int, default=20, help="frames mapped before the first one tracked")
    parser.add_argument("--frames", type=int, default=40, help="frames tracked")
    parser.add_argument("--variants", default=None, help="JSON: {name: {section: {field: value}}}")
    parser.add_argument("--map-config", default=None, help="JSON: {section: {field: value}} for the mapper")
    parser.add_argument("--per-frame", action="store_true", help="print every frame's error")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    if args.start < 1 or args.frames < 1:
        parser.error("--start and --frames must be >= 1")
    variants = json.loads(args.variants) if args.variants else DEFAULT_VARIANTS
    results = run(args.sequence, args.start, args.frames, variants,
                  json.loads(args.map_config) if args.map_config else None)
    rows = summary(results)
    print(f"# Tracking frame i+1 against a GT map of frames 0..i: {args.sequence}, "
          f"frames {args.start + 1}-{args.start + args.frames}, 1 thread\n")
    print("| variant | ms / frame | time ratio | error | rotation | median error | ok |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['variant']} | {r['ms_per_frame']:.1f} | {r['time_ratio']:.2f}x | {r['error_mm']:.2f} mm | "
              f"{r['error_deg']:.3f} deg | {r['median_error_mm']:.2f} mm | {r['ok']}/{r['frames']} |")
    if args.per_frame:
        for name, r in results.items():
            print(name, [round(e, 1) for e in r["error_mm"]])
    if args.json:
        write_json(args.json, {"sequence": args.sequence, "start": args.start, "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
