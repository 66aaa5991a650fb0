"""Mapping with ground-truth poses (issue 3 figures): mesh accuracy, rendered depth and colour,
completion, map memory.

Every scene is mapped by ``slam.mapping.Mapper.process`` on each frame, as the runtime's
mapper does for ``voxfusion run --gt-poses`` (frames resized to ``runtime.input_width``
first), with the ``cpu`` preset; ``--extra-iterations N`` then runs N more iterations of the
windowed optimisation (the default 0 is exactly what a user gets). Views are rendered with
``slam.views.render_view`` at the pipeline resolution and compared with the input at that
resolution.

    (a) Replica office0 frames 0-3: mesh accuracy against office0_mesh.ply, both culled to the
        GT camera frusta; median |rendered - input| depth on the 4 views; map memory.
    (b) Replica room0: map the 10 even frames, render the 10 odd ones: depth L1, colour PSNR.
    (c) synthetic:walk, 100 frames: accuracy and completion ratio (< 5 cm) against the GT
        mesh, both culled to what the cameras saw (occlusion-aware, with the GT depths).

    python benchmarks/bench_mapping.py [--quick] [--extra-iterations N] [--json FILE]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (
    REPLICA,
    Figure,
    MissingData,
    figures_payload,
    figures_table,
    load_line,
    map_memory_mb,
    map_with_gt_poses,
    pipeline_frame,
    require,
    write_json,
)

PAPER_MAP_MB = 0.35


@dataclass(frozen=True)
class ViewErrors:
    """Rendered vs input over a set of views.

    depth_median_cm / depth_l1_cm over pixels valid in both; coverage: share of input pixels
    with valid depth that the render covers; psnr_db over every pixel (uncovered pixels are
    black in the render and count as errors).
    """

    depth_median_cm: float
    depth_l1_cm: float
    coverage: float
    psnr_db: float


def view_errors(mapper, frames) -> ViewErrors:
    """Render every frame's pose with its K and size; compare with its depth and colour."""
    from slam.views import render_view

    abs_errors, covered, observed, sq_errors = [], 0, 0, []
    for frame in frames:
        view = render_view(mapper.maps, frame.T_world_cam, frame.K, frame.width, frame.height)
        observed_mask = frame.depth > 0
        both = observed_mask & view.valid
        abs_errors.append(np.abs(view.depth[both] - frame.depth[both]))
        covered += int(both.sum())
        observed += int(observed_mask.sum())
        sq_errors.append(((view.rgb - frame.rgb) ** 2).reshape(-1))
    errors = np.concatenate(abs_errors)
    mse = float(np.concatenate(sq_errors).mean())
    return ViewErrors(
        depth_median_cm=float(np.median(errors)) * 100 if errors.size else float("nan"),
        depth_l1_cm=float(errors.mean()) * 100 if errors.size else float("nan"),
        coverage=covered / max(observed, 1),
        psnr_db=float(-10 * np.log10(max(mse, 1e-12))),
    )


def cameras_of(frames):
    from slam.eval import CullCamera

    return [CullCamera(f.K, f.T_world_cam, f.width, f.height) for f in frames]


def load_frames(path, indices, width):
    from slam.data import open_sequence

    sequence = open_sequence(path)
    return [pipeline_frame(sequence[i], width) for i in indices]


# ------------------------------------------------------------------ scenes
def office0(config, extra: int, quick: bool, points: int) -> list[Figure]:
    import trimesh

    from slam.eval import mesh_metrics
    from slam.mesh import extract_mesh

    gt_path = require(REPLICA / "office0_mesh.ply")
    indices = [0, 1] if quick else [0, 1, 2, 3]
    frames = load_frames(require(REPLICA / "office0"), indices, config.runtime.input_width)
    t0 = time.perf_counter()
    mapper = map_with_gt_poses(frames, config, extra_iterations=extra)
    seconds = time.perf_counter() - t0
    t1 = time.perf_counter()
    rec = extract_mesh(mapper.maps)
    t2 = time.perf_counter()
    gt = trimesh.load(gt_path, force="mesh")
    frusta = mesh_metrics(rec, gt, num_points=points, cull_cameras=cameras_of(frames))
    seen = mesh_metrics(rec, gt, num_points=points, cull_cameras=cameras_of(frames),
                        gt_depths=[f.depth for f in frames])
    t3 = time.perf_counter()
    views = view_errors(mapper, frames)
    print(f"office0: mapping {t1 - t0:.0f} s, mesh {t2 - t1:.0f} s, metrics {t3 - t2:.0f} s, "
          f"rendering {len(frames)} views {time.perf_counter() - t3:.0f} s", flush=True)
    memory = map_memory_mb(mapper)
    total_mb = memory["embeddings"] + memory["decoder"] + memory["fine"]
    size = f"{frames[0].width}x{frames[0].height}"
    label = f"office0 frames {indices[0]}-{indices[-1]}"
    return [
        Figure(f"{label}: mesh accuracy (GT frusta)", frusta.accuracy * 100, "cm", "<= 2.0",
               f"mapped in {seconds:.0f} s; completion ratio {frusta.completion_ratio:.0%} of the frusta, "
               f"{seen.completion_ratio:.0%} of the visible surface"),
        Figure(f"{label}: median rendered depth error", views.depth_median_cm, "cm", "<= 1",
               f"{size}, {views.coverage:.0%} of pixels rendered; L1 {views.depth_l1_cm:.2f} cm"),
        Figure("office0: map memory (embeddings + decoder + fine colour)", total_mb, "MB", f"paper {PAPER_MAP_MB}",
               f"embeddings {memory['embeddings']:.3f} MB ({memory['voxels']} voxels), fine colour {memory['fine']:.3f} MB, "
               f"decoder {memory['decoder']:.3f} MB, voxel index {memory['voxel_index']:.3f} MB more"),
    ]


def room0(config, extra: int, quick: bool) -> list[Figure]:
    count = 4 if quick else 20
    path = require(REPLICA / "room0")
    mapped = load_frames(path, list(range(0, count, 2)), config.runtime.input_width)
    held_out = load_frames(path, list(range(1, count, 2)), config.runtime.input_width)
    t0 = time.perf_counter()
    mapper = map_with_gt_poses(mapped, config, extra_iterations=extra)
    seconds = time.perf_counter() - t0
    views = view_errors(mapper, held_out)
    print(f"room0: mapping {seconds:.0f} s, rendering {len(held_out)} views "
          f"{time.perf_counter() - t0 - seconds:.0f} s", flush=True)
    size = f"{held_out[0].width}x{held_out[0].height}"
    return [
        Figure(f"room0 {len(held_out)} odd views: depth L1", views.depth_l1_cm, "cm", "<= 2",
               f"{size}, {views.coverage:.0%} of pixels rendered; mapped {len(mapped)} even frames in {seconds:.0f} s"),
        Figure(f"room0 {len(held_out)} odd views: colour PSNR", views.psnr_db, "dB", ">= 24",
               "over every pixel (unrendered ones count as black)"),
    ]


def synthetic(config, extra: int, quick: bool, points: int) -> list[Figure]:
    from slam.data import open_sequence
    from slam.eval import mesh_metrics
    from slam.mesh import extract_mesh

    count = 10 if quick else 100
    spec = "synthetic:walk?frames=100"
    t_load = time.perf_counter()
    sequence = open_sequence(spec, max_frames=count)  # --quick: the start of the same path
    frames = [pipeline_frame(f, config.runtime.input_width) for f in sequence]
    t0 = time.perf_counter()
    mapper = map_with_gt_poses(frames, config, extra_iterations=extra)
    seconds = time.perf_counter() - t0
    t1 = time.perf_counter()
    rec = extract_mesh(mapper.maps)
    t2 = time.perf_counter()
    metrics = mesh_metrics(rec, sequence.gt_mesh(), num_points=points, cull_cameras=cameras_of(frames),
                           gt_depths=[f.depth for f in frames])
    print(f"synthetic: frames {t0 - t_load:.0f} s, mapping {seconds:.0f} s, mesh {t2 - t1:.0f} s, "
          f"metrics {time.perf_counter() - t2:.0f} s", flush=True)
    note = (f"{spec}, mapped in {seconds:.0f} s, {mapper.maps.num_keyframes()} keyframes; "
            f"completion {metrics.completion * 100:.2f} cm")
    return [
        Figure(f"synthetic walk {count} frames: mesh accuracy", metrics.accuracy * 100, "cm", "<= 1.5", note),
        Figure(f"synthetic walk {count} frames: completion ratio < 5 cm", metrics.completion_ratio * 100, "%",
               ">= 90", "GT culled to the cameras' frusta and depth (occlusion-aware)"),
    ]


SCENES = ("office0", "room0", "synthetic")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: few frames, few mesh samples")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--config", type=Path, default=None, help="JSON overrides of the preset (as voxfusion run)")
    parser.add_argument("--extra-iterations", type=int, default=0,
                        help="optimisation iterations after the single pass over the frames")
    parser.add_argument("--scenes", default=",".join(SCENES), help=f"comma list of {SCENES}")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads (1: on a loaded 2-core machine more threads spin and slow down)")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)

    from slam.config import load_config

    config = load_config(args.preset, args.config)
    config = replace(config, runtime=replace(config.runtime, device="cpu", processes=False))
    if args.quick:  # a smoke run: the figures mean nothing, the code paths are the same
        config = replace(config, mapping=replace(config.mapping, first_frame_iterations=20))
    points = 20_000 if args.quick else 200_000
    print(f"# Mapping with GT poses ({args.preset} preset, +{args.extra_iterations} iterations)\n")
    print(f"start: {load_line()}, torch threads {torch.get_num_threads()}\n", flush=True)
    figures: list[Figure] = []
    t0 = time.perf_counter()
    for scene in args.scenes.split(","):
        started = time.perf_counter()
        try:
            if scene == "office0":
                figures += office0(config, args.extra_iterations, args.quick, points)
            elif scene == "room0":
                figures += room0(config, args.extra_iterations, args.quick)
            elif scene == "synthetic":
                figures += synthetic(config, args.extra_iterations, args.quick, points)
            else:
                parser.error(f"unknown scene {scene!r}; choose from {SCENES}")
        except MissingData as missing:
            figures.append(Figure(scene, None, "", "", f"skipped: {missing}"))
        print(f"{scene}: {time.perf_counter() - started:.0f} s, {load_line()}", flush=True)
    print()
    print(figures_table(figures))
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; end: {load_line()}")
    write_json(args.json, figures_payload("Mapping with ground-truth poses (issue 3)", figures, {
        "preset": args.preset, "extra_iterations": args.extra_iterations, "quick": args.quick,
        "seconds": time.perf_counter() - t0}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
