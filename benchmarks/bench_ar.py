"""Time AR compositing of one 640x480 view with three objects (cube, sphere, ~5k-face asset).

The scene depth and background are given arrays (their rendering is not timed): this measures
``ar.composite`` alone, i.e. object shading, rasterisation with 2x2 supersampling, the
per-sample depth test and blending. Target: <= 200 ms median on the project's CPU.

    python benchmarks/bench_ar.py [--runs 15] [--threads N] [--device cpu|cuda] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from ar import CompositeResult, VirtualObject, composite, load_asset, make_shape

WIDTH, HEIGHT = 640, 480
K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])


def translation(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def bench_scene() -> tuple[np.ndarray, np.ndarray, list[VirtualObject]]:
    """Background (H, W, 3), scene depth (H, W) and the three objects, about 30 % coverage."""
    torus = trimesh.creation.torus(major_radius=0.35, minor_radius=0.15, major_sections=64, minor_sections=40)
    asset = load_asset(torus.export(file_type="glb"), "torus.glb")  # 5120 faces, via the GLB path
    objects = [
        VirtualObject(make_shape("cube"), translation(-0.6, 0.1, 2.0), scale=0.5, color=(0.8, 0.3, 0.2)),
        VirtualObject(make_shape("sphere"), translation(0.0, 0.0, 2.2), scale=0.6),
        VirtualObject(asset, translation(0.6, -0.1, 1.8), scale=1.0, color=(0.2, 0.5, 0.9)),
    ]
    rng = np.random.default_rng(0)
    background = rng.uniform(0.0, 1.0, (HEIGHT, WIDTH, 3)).astype(np.float32)
    # A wall that cuts through the sphere, so the depth test has work on both sides.
    u = np.arange(WIDTH, dtype=np.float32)[None, :]
    scene_depth = np.broadcast_to(2.1 + 0.002 * (u - WIDTH / 2), (HEIGHT, WIDTH)).astype(np.float32)
    return background, scene_depth, objects


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=15, help="timed runs after 2 warm-up runs")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    parser.add_argument("--device", default="cpu", help="torch device for the per-sample work")
    parser.add_argument("--supersample", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None, help="also write the result as JSON here")
    args = parser.parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    background, scene_depth, objects = bench_scene()

    def timed_composite() -> tuple[float, float, CompositeResult]:
        """Wall and process CPU milliseconds of one call (numpy out, so CUDA is synchronised)."""
        start, start_cpu = time.perf_counter(), time.process_time()
        result = composite(
            background, scene_depth, objects, K, np.eye(4), supersample=args.supersample, device=args.device
        )
        return 1000.0 * (time.perf_counter() - start), 1000.0 * (time.process_time() - start_cpu), result

    for _ in range(2):
        timed_composite()
    runs = [timed_composite() for _ in range(args.runs)]
    times_ms, cpu_ms, result = [r[0] for r in runs], [r[1] for r in runs], runs[-1][2]
    report = {
        "benchmark": "ar.composite",
        "image": f"{WIDTH}x{HEIGHT}",
        "supersample": args.supersample,
        "object_faces": [o.mesh.num_faces for o in objects],
        "device": args.device,
        "torch_threads": torch.get_num_threads(),
        "runs": args.runs,
        "median_ms": round(statistics.median(times_ms), 1),
        "min_ms": round(min(times_ms), 1),
        "max_ms": round(max(times_ms), 1),
        # CPU time over all threads: with --threads 1 on a shared machine this is close to the
        # wall time the call would take with a core to itself.
        "median_cpu_ms": round(statistics.median(cpu_ms), 1),
        "load_average_1min": round(os.getloadavg()[0], 2),
        "visible_fraction": round(float(result.alpha.mean()), 3),
        "occluded_fraction": round(float(result.occlusion_mask.mean()), 3),
        "target_ms": 200,
    }
    print(json.dumps(report, indent=2))
    if args.out is not None:
        args.out.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
