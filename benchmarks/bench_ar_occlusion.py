"""AR occlusion figures of issue 6: virtual objects hidden by the neural map's rendered depth
as they are by the exact (synthetic) or input (Replica) depth, and the time to composite.

Maps are built with GT poses by ``Mapper.process`` on every frame (``common.map_with_gt_poses``,
as ``voxfusion run --gt-poses`` maps), ``cpu`` preset, frames at its 320 px pipeline width,
then ``--extra-iterations`` rounds of windowed optimisation ("properly trained": the mapper
keeps optimising while the camera rests). Objects are composited once over the map's
rendered depth and once over the reference depth (``ar.occlusion.compare_occlusion``: same
object layer, same per-sample test, 1 cm tolerance, 2x2 supersampling); the figure is the IoU
of the occlusion masks (object pixels hidden by the scene). Each object is placed so that
30-70 % of it is hidden in the reference and clear of every surface by a few centimetres (so
the figure measures occluding edges, not contact).

    (a) synthetic:orbit (320x240): map the 10 even frames of 20; a 0.5 m cube under the table
        (its top hidden by the table top) and a 0.6 m cube behind the table's far edge; at an
        input view (frame 10) and a held-out one (frame 13). Target IoU >= 0.95.
    (b) Replica room0: map the 10 even frames; a 0.4 m cube behind the left ottoman; views
        rendered at half resolution (600x340) at frame 10 (input) and 13 (held out) against
        the input depth resized the same way. Target IoU >= 0.90.
    (c) Time of ``ar.composite`` for a 640x480 view (synthetic frame 10, the figure's objects
        plus a sphere and a cylinder) with 1 torch thread, excluding the scene render; target
        <= 200 ms. The scene render (``slam.views.render_view`` at 640x480) is timed too.

    python benchmarks/bench_ar_occlusion.py [--part all|synthetic|replica|timing] [--quick]
        [--extra-iterations N] [--maps DIR] [--json FILE]

``--maps DIR`` keeps the trained maps (``DIR/synthetic.pt``, ``DIR/replica_room0.pt``) and
reuses them on the next run. Timings are taken on a shared machine: the load average is
printed with them.
"""

from __future__ import annotations

import argparse
import statistics
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
    map_with_gt_poses,
    pipeline_frame,
    require,
    write_json,
)

SYNTHETIC = "synthetic:orbit?frames=20&width=320&height=240"
SYNTHETIC_VIEWS = {"input view (frame 10)": 10, "held-out view (frame 13)": 13}
REPLICA_VIEWS = {"input view (frame 10)": 10, "held-out view (frame 13)": 13}
MAP_FRAMES = tuple(range(0, 20, 2))
REPLICA_EVAL_WIDTH = 600
"""Half of Replica's 1200x680."""
HIDDEN_RANGE = (0.3, 0.7)
SYNTHETIC_TARGET, REPLICA_TARGET, COMPOSITE_TARGET_MS = 0.95, 0.90, 200.0
TIMING_SIZE = (640, 480)


@dataclass(frozen=True)
class Placement:
    """A built-in shape at a world position (no rotation)."""

    name: str
    shape: str
    position: tuple[float, float, float]
    scale: float
    color: tuple[float, float, float] = (0.9, 0.2, 0.2)

    def object(self):
        from ar import VirtualObject, make_shape

        T_world_obj = np.eye(4)
        T_world_obj[:3, 3] = self.position
        return VirtualObject(make_shape(self.shape), T_world_obj, scale=self.scale, color=self.color)


def synthetic_placements(scene) -> list[Placement]:
    """Around the synthetic table (world z up; the orbit's cameras look at it from -y)."""
    table = scene.objects[0]
    (cx, cy), (_, half_y), top = table.centre, table.top_half_size, table.height
    return [
        Placement("cube under the table", "cube", (cx, cy, top - 0.36), 0.5),
        Placement("cube behind the table", "cube", (cx, cy + half_y + 0.35, top - 0.1), 0.6),
    ]


REPLICA_PLACEMENTS = [Placement("cube behind the left ottoman", "cube", (1.2, 0.6, -1.25), 0.4)]
"""room0's world is z up, floor at z = -1.5; the left ottoman's top is at about (1.65, 0.64, -1.03)."""


# ------------------------------------------------------------------------- maps
def trained_map(name: str, frames, config, extra_iterations: int, maps_dir: Path | None):
    """(MapSet, seconds): loaded from ``maps_dir/name.pt`` when there, else mapped (and saved)."""
    from slam.checkpoint import load_checkpoint, save_checkpoint

    path = None if maps_dir is None else maps_dir / f"{name}.pt"
    if path is not None and path.is_file():
        print(f"{name}: reusing {path}", flush=True)
        return load_checkpoint(path), None
    t0 = time.perf_counter()
    mapper = map_with_gt_poses(frames, config, extra_iterations=extra_iterations)
    seconds = time.perf_counter() - t0
    print(f"{name}: mapped {len(frames)} frames + {extra_iterations} iterations in {seconds:.0f} s ({load_line()})",
          flush=True)
    if path is not None:
        save_checkpoint(mapper.maps, path)
    return mapper.maps, seconds


def clearance(placement: Placement, frames) -> float:
    """Metres between the (axis-aligned) cube and the nearest back-projected input point."""
    nearest = np.inf
    half = placement.scale / 2
    for frame in frames:
        v, u = np.nonzero(frame.depth > 0)
        z = frame.depth[v, u]
        K, T = frame.K, frame.T_world_cam
        cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], 1)
        world = cam @ T[:3, :3].T + T[:3, 3]
        outside = np.abs(world - np.asarray(placement.position)) - half
        distance = np.linalg.norm(np.maximum(outside, 0.0), axis=1) + np.minimum(outside.max(1), 0.0)
        nearest = min(nearest, float(distance.min()))
    return nearest


def occlusion_figures(label: str, mapset, views: dict[str, object], placements, target: float) -> list[Figure]:
    from ar.occlusion import compare_occlusion
    from slam.views import render_view

    figures = []
    for view_name, frame in views.items():
        view = render_view(mapset, frame.T_world_cam, frame.K, frame.width, frame.height)
        for placement in placements:
            result = compare_occlusion(frame.rgb, frame.depth, view.depth, [placement.object()], frame.K,
                                       frame.T_world_cam)
            hidden_ok = HIDDEN_RANGE[0] <= result.hidden_fraction <= HIDDEN_RANGE[1]
            note = (f"{frame.width}x{frame.height}; {100 * result.hidden_fraction:.0f} % hidden "
                    f"({int(result.reference.occlusion_mask.sum())} px); visible-mask IoU {result.object_iou:.3f}")
            if not hidden_ok:
                note += f"; hidden share outside {HIDDEN_RANGE}: figure not meaningful"
            figures.append(Figure(f"{label}: {placement.name}, {view_name}, occlusion IoU",
                                  result.occlusion_iou if hidden_ok else None, "", f">= {target}", note))
    return figures


# ------------------------------------------------------------------------ parts
def part_synthetic(config, extra: int, maps_dir: Path | None, quick: bool) -> tuple[list[Figure], object]:
    from slam.data import open_sequence

    sequence = open_sequence(SYNTHETIC)
    frames = [pipeline_frame(sequence[i], config.runtime.input_width) for i in (MAP_FRAMES[:3] if quick else MAP_FRAMES)]
    mapset, seconds = trained_map("synthetic", frames, config, extra, maps_dir)
    placements = synthetic_placements(sequence.scene)
    gaps = ", ".join(f"{p.name} {100 * clearance(p, frames):.0f} cm" for p in placements)
    views = {name: pipeline_frame(sequence[i], config.runtime.input_width) for name, i in SYNTHETIC_VIEWS.items()}
    figures = occlusion_figures("synthetic", mapset, views, placements, SYNTHETIC_TARGET)
    figures.append(Figure("synthetic: mapping time", seconds, "s", "", f"{len(frames)} frames; clearance: {gaps}"))
    return figures, mapset


def part_replica(config, extra: int, maps_dir: Path | None, quick: bool) -> list[Figure]:
    from slam.data import open_sequence

    folder = require(REPLICA / "room0")
    sequence = open_sequence(folder)
    indices = MAP_FRAMES[:3] if quick else MAP_FRAMES
    frames = [pipeline_frame(sequence[i], config.runtime.input_width) for i in indices]
    mapset, seconds = trained_map("replica_room0", frames, config, extra, maps_dir)
    half = open_sequence(folder, width=REPLICA_EVAL_WIDTH)
    views = {name: half[i] for name, i in REPLICA_VIEWS.items()}
    gaps = ", ".join(f"{p.name} {100 * clearance(p, list(views.values())):.0f} cm" for p in REPLICA_PLACEMENTS)
    figures = occlusion_figures("Replica room0", mapset, views, REPLICA_PLACEMENTS, REPLICA_TARGET)
    figures.append(Figure("Replica room0: mapping time", seconds, "s", "", f"{len(frames)} frames; clearance: {gaps}"))
    return figures


def part_timing(mapset, runs: int, render_runs: int) -> list[Figure]:
    """Composite and render times of a 640x480 view of the synthetic scene."""
    import torch

    from ar import composite
    from slam.data import open_sequence
    from slam.views import render_view

    width, height = TIMING_SIZE
    sequence = open_sequence(f"synthetic:orbit?frames=20&width={width}&height={height}")
    frame = sequence[10]
    placements = synthetic_placements(sequence.scene)
    table = sequence.scene.objects[0]
    (cx, cy), top = table.centre, table.height
    placements += [Placement("sphere", "sphere", (cx - 0.3, cy - 0.1, top + 0.25), 0.3, (0.2, 0.5, 0.9)),
                   Placement("cylinder", "cylinder", (cx + 0.3, cy - 0.1, top + 0.2), 0.25, (0.3, 0.8, 0.3))]
    objects = [p.object() for p in placements]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        render_s, render_cpu_s = [], []
        for _ in range(render_runs):
            t0, c0 = time.perf_counter(), time.process_time()
            view = render_view(mapset, frame.T_world_cam, frame.K, width, height)
            render_s.append(time.perf_counter() - t0)
            render_cpu_s.append(time.process_time() - c0)
        composite(view.rgb, view.depth, objects, frame.K, frame.T_world_cam)  # warm-up
        wall_ms, cpu_ms = [], []
        for _ in range(runs):
            t0, c0 = time.perf_counter(), time.process_time()
            result = composite(view.rgb, view.depth, objects, frame.K, frame.T_world_cam)
            wall_ms.append(1000 * (time.perf_counter() - t0))
            cpu_ms.append(1000 * (time.process_time() - c0))
    finally:
        torch.set_num_threads(threads)
    faces = sum(o.mesh.num_faces for o in objects)
    note = (f"1 torch thread, median of {runs}; CPU time {statistics.median(cpu_ms):.0f} ms; {len(objects)} objects, "
            f"{faces} faces, {100 * result.alpha.mean():.0f} % of the view covered; {load_line()}")
    return [
        Figure("composite 640x480, excluding the scene render", statistics.median(wall_ms), "ms",
               f"<= {COMPOSITE_TARGET_MS:g}", note),
        Figure("scene render (render_view) 640x480", statistics.median(render_s), "s", "",
               f"1 torch thread, median of {render_runs}; CPU time {statistics.median(render_cpu_s):.1f} s; "
               f"{load_line()}"),
    ]


# ------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=["all", "synthetic", "replica", "timing"], default="all")
    parser.add_argument("--quick", action="store_true", help="smoke run: 3 frames, few iterations; its figures mean nothing")
    parser.add_argument("--extra-iterations", type=int, default=None,
                        help="windowed optimisation after the last frame (default 300, --quick 10)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads for mapping (timing always uses 1)")
    parser.add_argument("--maps", type=Path, default=None, help="folder to keep and reuse trained maps")
    parser.add_argument("--runs", type=int, default=15, help="timed composite runs")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)

    import torch

    from slam.config import preset

    torch.set_num_threads(args.threads)
    config = preset("cpu")
    config = replace(config, runtime=replace(config.runtime, device="cpu"))
    extra = args.extra_iterations if args.extra_iterations is not None else (10 if args.quick else 300)
    if args.maps is not None:
        args.maps.mkdir(parents=True, exist_ok=True)
    print(f"bench_ar_occlusion: {load_line()}", flush=True)
    figures: list[Figure] = []
    synthetic_map = None
    if args.part in ("all", "synthetic", "timing"):
        synthetic_figures, synthetic_map = part_synthetic(config, extra, args.maps, args.quick)
        if args.part != "timing":
            figures += synthetic_figures
    if args.part in ("all", "replica"):
        try:
            figures += part_replica(config, extra, args.maps, args.quick)
        except MissingData as error:
            figures.append(Figure("Replica room0", None, "", f">= {REPLICA_TARGET}", f"skipped: {error}"))
    if args.part in ("all", "timing"):
        figures += part_timing(synthetic_map, 3 if args.quick else args.runs, 1 if args.quick else 3)
    print()
    print(figures_table(figures))
    print(f"\n{load_line()}")
    write_json(args.json, figures_payload("AR occlusion (issue 6)", figures,
                                          {"extra_iterations": extra, "quick": args.quick}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
