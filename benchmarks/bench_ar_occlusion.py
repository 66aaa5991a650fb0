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
    (d) Real frames with small occluders (TUM fr1/desk, 640x480): the map is a ``voxfusion run
        --preset cpu`` of its 9 frames (tracked poses; ``--maps DIR/desk_run`` keeps it). At
        input frames 2, 4 and 6 (their estimated poses, as ``frame:N`` takes), cubes of 8 cm
        are put 12 cm behind the near side of the sensor's occluding edges (depth jumps of
        >= 25 cm), one a cell of an 80 px grid, at most 8 a frame, each composited alone.
        The figure is the count of object pixels within 3 px of an occluder's edge whose
        hidden/shown state differs from the composite over the sensor depth (the reference),
        for each scene depth: the map's rendered depth (a rendered view, and ``voxfusion ar``
        without ``--background-depth``), the map's depth refined with its rendered colour
        (``ar.scene_depth.refined_render_depth``), and the sensor's depth with the map in its
        holes (``ar.scene_depth.sensor_depth_with_map``, ``frame:N``). Pixels in the sensor's
        holes have no reference there; they are scored against the neighbouring frames' sensor
        depth warped into the frame (frames +-1, +-2; hidden where any of them sees the scene in
        front), with the sensor's depth alone (holes far) as the before.
    (c) Time of ``ar.composite`` for a 640x480 view (synthetic frame 10, the figure's objects
        plus a sphere and a cylinder) with 1 torch thread, excluding the scene render; target
        <= 200 ms. The scene render (``slam.views.render_view`` at 640x480) is timed too.

    python benchmarks/bench_ar_occlusion.py [--part all|synthetic|replica|real|timing] [--quick]
        [--extra-iterations N] [--maps DIR] [--json FILE]

``--maps DIR`` keeps the trained maps (``DIR/synthetic.pt``, ``DIR/replica_room0.pt``, ``DIR/desk_run``) and
reuses them on the next run. Timings are taken on a shared machine: the load average is
printed with them.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (
    REPLICA,
    Figure,
    REPO_ROOT,
    SHARED_DATA,
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
DESK = SHARED_DATA / "rgbd_dataset_freiburg1_desk"
DESK_FRAMES = (2, 4, 6)
DESK_NEIGHBOURS = (-2, -1, 1, 2)
OCCLUDER_JUMP_M = 0.25
"""A sensor depth jump at least this large between pixels 3 px apart is an occluder's edge."""
EDGE_JUMP_M = 0.05
"""Depth jumps (between neighbouring pixels) that mark the edges the figure is scored along."""
EDGE_BAND_PX = 3
CUBE_SIDE_M, CUBE_BEHIND_M = 0.08, 0.12
PLACEMENT_CELL_PX, PLACEMENTS_PER_FRAME = 80, 8
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


# ------------------------------------------------------------------ real frames
def desk_map(maps_dir: Path | None) -> tuple[Path, float | None]:
    """(run folder, seconds): ``voxfusion run DESK --preset cpu``, reused from ``maps_dir/desk_run``."""
    out = (maps_dir or Path("/tmp")) / "desk_run"
    if (out / "map.pt").is_file() and (out / "trajectory.txt").is_file():
        print(f"desk: reusing {out}", flush=True)
        return out, None
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "slam.cli", "run", str(require(DESK)), "--preset", "cpu", "--out", str(out),
                    "--quiet"], check=True, cwd=REPO_ROOT)
    return out, time.perf_counter() - t0


def depth_edges(depth: np.ndarray, jump: float, gap: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(near side, both sides): (H, W) bool masks of valid pixels with a valid pixel ``gap``
    away (along a row or column) at least ``jump`` metres farther (near) or either way (both)."""
    valid = depth > 0
    near, both = np.zeros_like(valid), np.zeros_like(valid)
    for axis in (0, 1):
        a = np.take(depth, range(depth.shape[axis] - gap), axis=axis)
        b = np.take(depth, range(gap, depth.shape[axis]), axis=axis)
        ok = np.take(valid, range(depth.shape[axis] - gap), axis=axis) & np.take(valid, range(gap, depth.shape[axis]), axis=axis)
        a_near, b_near = ok & (b - a >= jump), ok & (a - b >= jump)
        lead = (slice(None, -gap), slice(None)) if axis == 0 else (slice(None), slice(None, -gap))
        tail = (slice(gap, None), slice(None)) if axis == 0 else (slice(None), slice(gap, None))
        near[lead] |= a_near
        near[tail] |= b_near
        both[lead] |= a_near | b_near
        both[tail] |= a_near | b_near
    return near, both


def edge_placements(frame, T_world_cam: np.ndarray) -> list[Placement]:
    """Cubes just behind the near side of the sensor's occluding edges (see (d))."""
    near, _ = depth_edges(frame.depth, OCCLUDER_JUMP_M, gap=EDGE_BAND_PX)
    placements, taken = [], set()
    for v, u in zip(*np.nonzero(near)):
        cell = (v // PLACEMENT_CELL_PX, u // PLACEMENT_CELL_PX)
        if cell in taken or len(placements) == PLACEMENTS_PER_FRAME:
            continue
        taken.add(cell)
        z = float(frame.depth[v, u]) + CUBE_BEHIND_M + CUBE_SIDE_M / 2
        K = frame.K
        cam = np.array([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
        world = T_world_cam[:3, :3] @ cam + T_world_cam[:3, 3]
        placements.append(Placement(f"cube at ({u}, {v})", "cube", tuple(float(c) for c in world), CUBE_SIDE_M))
    return placements


def warped_depth(frames, poses, target: int) -> np.ndarray:
    """(H, W) nearest depth that the other frames' sensors saw along the target frame's pixels
    (forward-warped points, z-buffered); 0 where none landed."""
    frame = frames[target]
    K, height, width = frame.K, frame.height, frame.width
    out = np.full(height * width, np.inf, dtype=np.float32)
    T_target_world = np.linalg.inv(poses[target])
    for offset in DESK_NEIGHBOURS:
        other = target + offset
        if other not in frames:
            continue
        source = frames[other]
        v, u = np.nonzero(source.depth > 0)
        z = source.depth[v, u]
        cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], 1)
        T = T_target_world @ poses[other]
        p = cam @ T[:3, :3].T + T[:3, 3]
        ok = p[:, 2] > 0.1
        x = np.rint(p[ok, 0] / p[ok, 2] * K[0, 0] + K[0, 2]).astype(int)
        y = np.rint(p[ok, 1] / p[ok, 2] * K[1, 1] + K[1, 2]).astype(int)
        inside = (x >= 0) & (x < width) & (y >= 0) & (y < height)
        np.minimum.at(out, y[inside] * width + x[inside], p[ok, 2][inside].astype(np.float32))
    return np.where(np.isfinite(out), out, 0.0).reshape(height, width)


def part_real(maps_dir: Path | None, quick: bool) -> list[Figure]:
    """Occlusion errors along small occluders' edges on real frames (see (d))."""
    from functools import partial

    from ar.occlusion import compare_occlusion
    from ar.scene_depth import grow, refined_render_depth, sensor_depth_with_map, valid_depth
    from slam import load_checkpoint, open_sequence, read_tum
    from slam.views import render_view

    run, seconds = desk_map(maps_dir)
    sequence = open_sequence(require(DESK))
    trajectory, mapset = read_tum(run / "trajectory.txt"), load_checkpoint(run / "map.pt")
    targets = DESK_FRAMES[1:2] if quick else DESK_FRAMES
    needed = sorted({t + o for t in targets for o in (0, *DESK_NEIGHBOURS) if 0 <= t + o < len(sequence)})
    frames = {i: sequence[i] for i in needed}
    poses = {i: trajectory.poses[int(np.argmin(np.abs(trajectory.timestamps - f.timestamp)))] for i, f in frames.items()}
    names = ("map depth", "map depth refined with its colour", "sensor depth, holes far",
             "sensor depth, map in its holes")
    wrong = dict.fromkeys(names, 0)
    scored = holes_scored = cubes = 0
    for target in targets:
        frame, T = frames[target], poses[target]
        view = render_view(mapset, T, frame.K, frame.width, frame.height)
        map_depth, map_rgb = np.asarray(view.depth), np.asarray(view.rgb)
        sensed = valid_depth(frame.depth)
        warped = warped_depth(frames, poses, target)
        _, edges = depth_edges(np.where(sensed, frame.depth, 0.0), EDGE_JUMP_M)
        # The holes' own borders are edges too: a hole beside an occluder is its depth shadow.
        band = grow(edges | (grow(~sensed, 1) & sensed), EDGE_BAND_PX)
        reference_depth = np.where(sensed, frame.depth, warped)
        known = sensed | (warped > 0)

        def window(K, width, height):
            return np.asarray(render_view(mapset, T, K, width, height).depth)

        for placement in edge_placements(frame, T):
            objects = [placement.object()]
            candidates = {
                names[0]: map_depth,
                names[1]: refined_render_depth(map_depth, map_rgb, objects, frame.K, T),
                names[2]: np.where(sensed, frame.depth, 0.0),
                names[3]: sensor_depth_with_map(frame.depth, objects, frame.K, T, partial(window)).depth,
            }
            cubes += 1
            for name, depth in candidates.items():
                result = compare_occlusion(frame.rgb, reference_depth, depth, objects, frame.K, T)
                ref, cand = result.reference, result.candidate
                covered = ref.object_mask | ref.occlusion_mask | cand.object_mask | cand.occlusion_mask
                differs = (ref.occlusion_mask != cand.occlusion_mask) & covered & band & known
                wrong[name] += int(differs.sum())
                if name == names[0]:
                    scored += int((covered & band & known).sum())
                    holes_scored += int((covered & band & known & ~sensed).sum())
    note = (f"{cubes} cubes of {100 * CUBE_SIDE_M:.0f} cm at frames {list(targets)}; {scored} object px within "
            f"{EDGE_BAND_PX} px of an edge ({holes_scored} in sensor holes, scored against frames +-1, +-2)")
    figures = [Figure(f"TUM fr1/desk: occlusion errors at small occluders, {name}", wrong[name], "px", "", note)
               for name in names]
    figures.append(Figure("TUM fr1/desk: voxfusion run --preset cpu", seconds, "s", "", str(run)))
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
    parser.add_argument("--part", choices=["all", "synthetic", "replica", "real", "timing"], default="all")
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
    if args.part in ("all", "real"):
        try:
            figures += part_real(args.maps, args.quick)
        except MissingData as error:
            figures.append(Figure("TUM fr1/desk", None, "", "", f"skipped: {error}"))
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
