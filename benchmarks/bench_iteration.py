"""Time of one mapping iteration with 1024 rays on this CPU, broken down as the paper's Table
(voxel allocation, ray-voxel intersection, point sampling, volume rendering, back-propagation).

A realistic map first: Replica office0 frames 0-3 mapped with GT poses by the ``cpu`` preset
(the synthetic walk when Replica is absent). Then each timed iteration draws 1024 rays from
those frames and runs the pure functions of ``slam/render.py`` in the order ``render_rays``
calls them, with a timer around each stage, then the losses, ``backward`` and the Adam step
on embeddings and decoder. Before timing, the staged pipeline is checked against
``render_rays`` on the same rays (same colour and depth), so the breakdown cannot drift
from the real renderer unnoticed. Two end-to-end rows time the real thing:
``render_rays`` + losses + backward + step on the same 1024 rays, and one call of
``Mapper.optimize`` with the preset's window (window_size x num_rays rays, keyframe poses
optimised). Medians over ``--iterations`` after 3 warm-up iterations, with 1 torch thread and
with torch's default.

``--kernels torch|numba`` forces the field's kernels (``VOXFUSION_KERNELS``; default: numba
where it imports). With numba's fused kernels the interpolation runs inside the SDF decoder's
stage. ``--ab ROUNDS`` adds a same-run comparison: rounds that alternate the two backends on
the end-to-end rows, medians of wall and of thread CPU time (the machine is shared, so CPU
time is the steadier of the two), and their ratios. ``--ab-step ROUNDS`` alternates the same
way between the mapping step with every sample decoded and coloured and the preset's
(``mapping.thin_samples``, ``mapping.color_weight_eps``); ``--ab-total ROUNDS`` between the
plain path (torch kernels, every sample) and the selected kernels with the preset's step. Every row follows the preset's
mapping step (thinning, colour threshold, loss normalisation), as ``Mapper`` runs it.

    python benchmarks/bench_iteration.py [--quick] [--rays 1024] [--iterations 20] [--json FILE]
        [--kernels torch|numba] [--ab 8] [--ab-step 8] [--ab-total 8] [--threads 1,2]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (
    REPLICA,
    Figure,
    MissingData,
    figures_payload,
    figures_table,
    load_line,
    map_with_gt_poses,
    markdown_table,
    pipeline_frame,
    write_json,
)

from slam import kernels
from slam.frames import backproject, prepare_frame, sample_pixels
from slam.losses import LossWeights, compute_losses
from slam.mapping import training_far
from slam.render import (
    RenderOutput,
    accumulate_along_rays,
    color_of_hidden,
    decode_samples,
    interpolate_embeddings,
    ray_voxel_intersections,
    TrainingThinning,
    render_rays,
    sample_points_from_hits,
    sdf_weights,
    thin_training_samples,
)
from slam.voxels import SparseVoxelMap

TARGET_MS = 200.0
STAGES = ("ray generation", "ray-voxel intersection", "point sampling", "interpolation", "decoder (SDF)",
          "weights + accumulation", "decoder (colour)", "losses", "back-propagation")


class StageTimer:
    """Wall-clock seconds per stage name for one iteration."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._name, self._t0 = "", 0.0

    def __call__(self, name: str) -> StageTimer:
        self._name = name
        return self

    def __enter__(self) -> None:
        self._t0 = time.perf_counter()

    def __exit__(self, *exc) -> None:
        self.seconds[self._name] = self.seconds.get(self._name, 0.0) + time.perf_counter() - self._t0


def draw_rays(frames, num_rays: int, generator: torch.Generator):
    """``num_rays`` rays spread over the frames (map frame = world here). -> o, d, rgb, depth."""
    per_frame = [num_rays // len(frames) + (i < num_rays % len(frames)) for i in range(len(frames))]
    origins, dirs, rgb, depth = [], [], [], []
    for (frame, T), n in zip(frames, per_frame):
        batch = sample_pixels(frame, n, generator)
        dirs.append(batch.dirs_cam @ T[:3, :3].T)
        origins.append(T[:3, 3].expand(n, 3))
        rgb.append(batch.rgb)
        depth.append(batch.depth)
    return torch.cat(origins), torch.cat(dirs), torch.cat(rgb), torch.cat(depth)


def staged_render(o, d, view, decoder, *, near, far, step, truncation, max_hits, offsets,
                  timer: StageTimer, color_weight_eps: float = 1e-5, renormalise_color: bool = False,
                  thinning: TrainingThinning | None = None) -> RenderOutput:
    """``slam.render.render_rays`` stage by stage, each under ``timer``."""
    num_rays = o.shape[0]
    with timer("ray-voxel intersection"):
        hits = ray_voxel_intersections(o, d, near, far, view.voxel_codes, view.voxel_size, max_hits)
    with timer("point sampling"):
        samples = sample_points_from_hits(hits, step, offsets)
        if thinning is not None:
            samples = thin_training_samples(samples, thinning)
        r = samples.ray_index
        points = o[r] + samples.t[:, None] * d[r]
    if kernels.use_numba(points, view.embeddings):
        with timer("decoder (SDF)"):  # the fused kernels interpolate inside the decoder
            sdf, hidden = decode_samples(points, samples.voxel_index, view, decoder)
    else:
        with timer("interpolation"):
            feats = interpolate_embeddings(points, samples.voxel_index, view)
        with timer("decoder (SDF)"):
            sdf, hidden = decoder.sdf_and_hidden(feats)
    with timer("weights + accumulation"):
        w = sdf_weights(sdf, samples.t, r, num_rays, truncation)
        wsum = torch.zeros(num_rays, dtype=w.dtype).index_add(0, r, w)
        norm = 1.0 / (wsum + 1e-8)
        depth = torch.zeros_like(wsum).index_add(0, r, w * samples.t) * norm
        depth_var = torch.zeros_like(wsum).index_add(0, r, w * (samples.t - depth.detach()[r]) ** 2) * norm
        active = torch.nonzero(w.detach() > color_weight_eps, as_tuple=True)[0]
    with timer("decoder (colour)"):
        rgb_active = color_of_hidden(decoder, hidden[active])
    with timer("weights + accumulation"):
        color = accumulate_along_rays(w[active], rgb_active, r[active], num_rays)
        if renormalise_color:
            color = color / (torch.zeros_like(wsum).index_add(0, r[active], w[active]) + 1e-8)[:, None]
        else:
            color = color * norm[:, None]
        hit = torch.zeros(num_rays, dtype=torch.bool)
        hit[r] = True
    return RenderOutput(color, depth, wsum, hit, depth_var, samples, sdf)


class IterationBench:
    """A mapped submap, its frames and an optimiser, ready for timed iterations."""

    def __init__(self, mapper, frames, num_rays: int, seed: int = 0):
        self.mapper = mapper
        self.submap = mapper.current
        self.config = mapper.config
        # Rays come from every mapped frame (keyframes or not), at its GT pose.
        self.frames = [(prepare_frame(f, None, torch.device("cpu"), self.config.voxel.max_depth),
                        torch.as_tensor(f.T_world_cam, dtype=torch.float32)) for f in frames]
        self.num_rays = num_rays
        self.generator = torch.Generator().manual_seed(seed)
        m = self.config.mapping
        self.optimizer = torch.optim.Adam([
            {"params": [self.submap.voxels.embeddings], "lr": m.lr_embed},
            {"params": list(self.submap.decoder.parameters()), "lr": m.lr_decoder}])
        c = self.config.loss
        self.weights = LossWeights(c.rgb_weight, c.depth_weight, c.sdf_weight, c.fs_weight)

    def use_config(self, config) -> None:
        """Time iterations with ``config``'s mapping step (the A/B of ``--ab-step``)."""
        self.config = self.mapper.config = config

    def _render_args(self, d_gt):
        """The mapper's render arguments (``Mapper._joint_optimisation``) for rays of depth d_gt."""
        r, m = self.config.render, self.config.mapping
        n = d_gt.shape[0]
        thinning = None
        if m.thin_samples:
            thinning = TrainingThinning(d_gt, r.truncation, r.max_distance, m.free_space_stride,
                                        torch.randint(m.free_space_stride, (n,), generator=self.generator))
        return {"near": torch.full((n,), 0.05), "far": training_far(d_gt, r.truncation, r.max_distance),
                "step": r.step_ratio * self.submap.voxels.voxel_size, "truncation": r.truncation,
                "max_hits": r.max_hits, "offsets": torch.rand(n, generator=self.generator),
                "color_weight_eps": m.color_weight_eps, "renormalise_color": True, "thinning": thinning}

    def _losses(self, out, rgb, depth):
        r = self.config.render
        return compute_losses(out, rgb, depth, r.truncation, self.weights, max_depth=r.max_distance,
                              normalisation=self.config.loss.normalisation)

    def staged_iteration(self) -> dict[str, float]:
        timer = StageTimer()
        with timer("ray generation"):
            o, d, rgb, depth = draw_rays(self.frames, self.num_rays, self.generator)
        out = staged_render(o, d, self.submap.view(), self.submap.decoder, timer=timer, **self._render_args(depth))
        with timer("losses"):
            losses = self._losses(out, rgb, depth)
        with timer("back-propagation"):
            self.optimizer.zero_grad(set_to_none=True)
            losses.total.backward()
            self.optimizer.step()
        timer.seconds["samples"] = float(out.samples.t.numel())
        return timer.seconds

    def render_rays_iteration(self) -> float:
        return self.timed_render_rays_iteration()[0]

    def timed_render_rays_iteration(self) -> tuple[float, float]:
        """Wall and thread CPU seconds of one render_rays + losses + backward + step."""
        c0 = time.thread_time()
        t0 = time.perf_counter()
        o, d, rgb, depth = draw_rays(self.frames, self.num_rays, self.generator)
        out = render_rays(o, d, self.submap.view(), self.submap.decoder, **self._render_args(depth))
        losses = self._losses(out, rgb, depth)
        self.optimizer.zero_grad(set_to_none=True)
        losses.total.backward()
        self.optimizer.step()
        return time.perf_counter() - t0, time.thread_time() - c0

    def mapper_iteration(self) -> float:
        return self.timed_mapper_iteration()[0]

    def timed_mapper_iteration(self) -> tuple[float, float]:
        c0 = time.thread_time()
        t0 = time.perf_counter()
        self.mapper.optimize(self.submap, 1)
        return time.perf_counter() - t0, time.thread_time() - c0

    def allocation(self) -> float:
        """Back-projection, keyframe test and allocation of one frame into an empty map."""
        frame, T = self.frames[-1]
        v = self.config.voxel
        vmap = SparseVoxelMap(v.voxel_size, v.embed_dim, v.embed_init_std)
        t0 = time.perf_counter()
        tr = self.config.render.truncation
        points = backproject(frame, T, v.alloc_pixel_stride, (-tr, 0.0, tr))
        vmap.count_new(points)
        vmap.allocate(points)
        return time.perf_counter() - t0

    def check_staged_matches(self) -> float:
        """Largest |difference| of colour and depth between staged and real rendering."""
        o, d, _, depth = draw_rays(self.frames, self.num_rays, self.generator)
        args = self._render_args(depth)
        with torch.no_grad():
            real = render_rays(o, d, self.submap.view(), self.submap.decoder, **args)
            staged = staged_render(o, d, self.submap.view(), self.submap.decoder, timer=StageTimer(), **args)
        return max(float((real.color - staged.color).abs().max()), float((real.depth - staged.depth).abs().max()))


def build_map(config, quick: bool):
    """office0 frames 0-3 (or the synthetic walk) mapped with GT poses."""
    from slam.data import open_sequence

    width = config.runtime.input_width
    if (REPLICA / "office0").is_dir():
        sequence, label = open_sequence(REPLICA / "office0"), "Replica office0 frames 0-3"
        frames = [pipeline_frame(sequence[i], width) for i in range(2 if quick else 4)]
    else:
        sequence, label = open_sequence("synthetic:walk?frames=100"), "synthetic walk frames 0-19"
        frames = [pipeline_frame(sequence[i], width) for i in range(10 if quick else 20)]
    mapper = map_with_gt_poses(frames, config)
    return mapper, frames, label


def median_ms(values: list[float]) -> float:
    return statistics.median(values) * 1000


def run(bench: IterationBench, threads: int, warmup: int, iterations: int) -> dict[str, float]:
    torch.set_num_threads(threads)
    for _ in range(warmup):
        bench.staged_iteration()
    staged = [bench.staged_iteration() for _ in range(iterations)]
    result = {name: median_ms([s.get(name, 0.0) for s in staged]) for name in STAGES}
    result["staged total"] = median_ms([sum(s.get(n, 0.0) for n in STAGES) for s in staged])
    result["samples per iteration"] = statistics.median(s["samples"] for s in staged)
    result["voxel allocation (one frame, empty map)"] = median_ms([bench.allocation() for _ in range(5)])
    for _ in range(warmup):
        bench.render_rays_iteration()
    result["render_rays + losses + backward + step"] = median_ms(
        [bench.render_rays_iteration() for _ in range(iterations)])
    bench.mapper_iteration()
    result["Mapper.optimize, one iteration"] = median_ms([bench.mapper_iteration() for _ in range(iterations)])
    return result


def kernel_variants() -> dict[str, Callable[[], None]]:
    """``--ab``: the field's kernels, ``VOXFUSION_KERNELS=torch`` against ``numba``."""
    def use(backend: str) -> Callable[[], None]:
        return lambda: os.environ.__setitem__("VOXFUSION_KERNELS", backend)
    return {"torch": use("torch"), "numba": use("numba")}


def step_variants(bench: IterationBench, config) -> dict[str, Callable[[], None]]:
    """``--ab-step``: every sample decoded and coloured (before issue 18's thinning) against the
    preset's mapping step (``mapping.thin_samples``, ``mapping.color_weight_eps``)."""
    plain = replace(config, mapping=replace(config.mapping, thin_samples=False, color_weight_eps=1e-5))
    return {"all samples": lambda: bench.use_config(plain), "preset": lambda: bench.use_config(config)}


def total_variants(bench: IterationBench, config) -> dict[str, Callable[[], None]]:
    """``--ab-total``: the plain path (torch kernels, every sample) against what runs now (the
    selected kernels with the preset's mapping step): issue 18's 2x figure in one run."""
    plain = replace(config, mapping=replace(config.mapping, thin_samples=False, color_weight_eps=1e-5))
    chosen = os.environ.get("VOXFUSION_KERNELS", "auto")

    def before() -> None:
        os.environ["VOXFUSION_KERNELS"] = "torch"
        bench.use_config(plain)

    def now() -> None:
        os.environ["VOXFUSION_KERNELS"] = chosen
        bench.use_config(config)
    return {"torch, every sample": before, "preset": now}


def ab_rounds(bench: IterationBench, threads: int, rounds: int, per_round: int,
              variants: dict[str, Callable[[], None]]) -> dict[str, dict[str, list[float]]]:
    """Rounds alternating two ``variants`` (label -> a call that switches to it; which goes
    first alternates too); per round and variant the median wall and CPU seconds of each
    end-to-end row and the staged iterations. -> {row: {"<label> wall": [...], ...}, "stages":
    {label: [...]}}."""
    torch.set_num_threads(threads)
    rows = {"render_rays + losses + backward + step": bench.timed_render_rays_iteration,
            "Mapper.optimize, 1 iteration": bench.timed_mapper_iteration}
    out: dict[str, dict[str, list[float]]] = {row: {} for row in rows}
    labels = list(variants)
    before_env, before_config = os.environ.get("VOXFUSION_KERNELS"), bench.config
    try:
        for k in range(rounds):
            for label in labels if k % 2 == 0 else labels[::-1]:
                variants[label]()
                for row, fn in rows.items():
                    fn()  # one untimed: the other variant ran last
                    walls, cpus = zip(*[fn() for _ in range(per_round)])
                    out[row].setdefault(f"{label} wall", []).append(statistics.median(walls))
                    out[row].setdefault(f"{label} cpu", []).append(statistics.median(cpus))
                staged = [bench.staged_iteration() for _ in range(per_round)]
                out.setdefault("stages", {}).setdefault(label, []).extend(staged)
    finally:
        bench.use_config(before_config)
        if before_env is None:
            os.environ.pop("VOXFUSION_KERNELS", None)
        else:
            os.environ["VOXFUSION_KERNELS"] = before_env
    return out


def ab_stage_table(results: dict[int, dict]) -> str:
    """Markdown: the paper-style stages (median ms over the A/B rounds' staged iterations),
    the two variants side by side per thread count."""
    headers, columns = ["stage (median ms)"], []
    for threads, per_row in results.items():
        for label, staged in per_row["stages"].items():
            result = {name: median_ms([x.get(name, 0.0) for x in staged]) for name in STAGES}
            result["staged total"] = median_ms([sum(x.get(n, 0.0) for n in STAGES) for x in staged])
            columns.append(dict(paper_rows({**result, "voxel allocation (one frame, empty map)": float("nan"),
                                            "render_rays + losses + backward + step": float("nan"),
                                            "Mapper.optimize, one iteration": float("nan")})))
            columns[-1]["samples per iteration"] = statistics.median(x["samples"] for x in staged)
            headers.append(f"{label}, {threads} thread{'s' if threads > 1 else ''}")
    names = [n for n in columns[0] if columns[0][n] == columns[0][n]]  # the staged rows (not NaN)
    return markdown_table(headers, [[n] + [f"{c[n]:.1f}" for c in columns] for n in names])


def ab_table(results: dict[int, dict]) -> str:
    """Markdown: per thread count and row, both variants' medians (ms) and first / second."""
    rows, labels = [], []
    for threads, per_row in results.items():
        labels = list(per_row["stages"])
        a, b = labels
        for row, series in per_row.items():
            if row == "stages":
                continue
            cells = [f"{row}, {threads} thread{'s' if threads > 1 else ''}"]
            for kind in ("wall", "cpu"):
                t, n = series[f"{a} {kind}"], series[f"{b} {kind}"]
                ratios = [x / y for x, y in zip(t, n)]
                cells += [f"{median_ms(t):.1f}", f"{median_ms(n):.1f}",
                          f"{statistics.median(ratios):.2f}x ({min(ratios):.2f}-{max(ratios):.2f})"]
            rows.append(cells)
    a, b = labels
    return markdown_table([f"row (median ms over rounds)", f"{a} wall", f"{b} wall", "wall ratio (range)",
                           f"{a} CPU", f"{b} CPU", "CPU ratio (range)"], rows)


def profile_table(bench: IterationBench, iterations: int, rows: int = 15) -> str:
    """torch.profiler's top operators by self CPU time over a few staged iterations."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(iterations):
            bench.staged_iteration()
    return prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows)


def paper_rows(result: dict[str, float]) -> list[tuple[str, float]]:
    """The paper's Table rows from the measured stages (ms)."""
    rendering = sum(result[k] for k in ("interpolation", "decoder (SDF)", "weights + accumulation",
                                        "decoder (colour)"))
    return [("voxel allocation (per keyframe)", result["voxel allocation (one frame, empty map)"]),
            ("ray generation", result["ray generation"]),
            ("ray-voxel intersection", result["ray-voxel intersection"]),
            ("point sampling", result["point sampling"]),
            ("volume rendering (interp + decoder + weights)", rendering),
            ("  interpolation", result["interpolation"]),
            ("  decoder SDF / colour", result["decoder (SDF)"] + result["decoder (colour)"]),
            ("  weights + accumulation", result["weights + accumulation"]),
            ("losses", result["losses"]),
            ("back-propagation (backward + Adam)", result["back-propagation"]),
            ("**iteration total (staged, without allocation)**", result["staged total"]),
            ("render_rays + losses + backward + step (same rays)", result["render_rays + losses + backward + step"]),
            ("Mapper.optimize, 1 iteration (preset window, poses)", result["Mapper.optimize, one iteration"])]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: smaller map, 3 iterations")
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--rays", type=int, default=1024)
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--profile", action="store_true", help="also print torch.profiler's top operators (1 thread)")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--kernels", choices=("torch", "numba"), default=None,
                        help="force the field's kernels (VOXFUSION_KERNELS); default: numba where it imports")
    parser.add_argument("--threads", default=None, help="comma-separated torch thread counts (default: 1 and torch's)")
    parser.add_argument("--ab", type=int, default=0, metavar="ROUNDS",
                        help="also alternate torch and numba kernels for ROUNDS rounds (same run, medians, ratios)")
    parser.add_argument("--ab-step", type=int, default=0, metavar="ROUNDS",
                        help="also alternate the mapping step with every sample decoded and coloured and the "
                             "preset's (thinned samples, colour threshold) for ROUNDS rounds")
    parser.add_argument("--ab-total", type=int, default=0, metavar="ROUNDS",
                        help="also alternate the plain path (torch kernels, every sample) and the "
                             "selected kernels with the preset's step for ROUNDS rounds")
    args = parser.parse_args(argv)
    if args.kernels:
        os.environ["VOXFUSION_KERNELS"] = args.kernels
    from slam.config import preset

    default_threads = torch.get_num_threads()
    config = preset(args.preset)
    if args.quick:
        config = replace(config, mapping=replace(config.mapping, first_frame_iterations=10))
    iterations = 3 if args.quick else args.iterations
    print(f"# One mapping iteration, {args.rays} rays, {args.preset} preset\n")
    print(f"start: {load_line()}")
    warm = kernels.warm_up()
    print(f"kernels: {'numba' if kernels.use_numba(torch.zeros(1)) else 'torch'}"
          + (f" (warm-up {warm:.1f} s)" if warm else ""))
    t0 = time.perf_counter()
    try:
        mapper, frames, label = build_map(config, args.quick)
    except MissingData as missing:
        print(f"skipped: {missing}")
        return 0
    bench = IterationBench(mapper, frames, args.rays)
    mismatch = bench.check_staged_matches()
    print(f"map: {label}, {mapper.maps.num_voxels()} voxels, built in {time.perf_counter() - t0:.0f} s")
    print(f"staged vs render_rays: max |difference| {mismatch:.2e}"
          + ("" if mismatch < 1e-4 else "  WARNING: render_rays changed; update staged_render"))
    results = {}
    thread_counts = sorted({int(t) for t in args.threads.split(",")} if args.threads else {1, default_threads})
    for threads in thread_counts:
        results[threads] = run(bench, threads, 1 if args.quick else 3, iterations)
        print(f"threads {threads}: done, {load_line()}", flush=True)
    comparisons: dict[str, dict[int, dict]] = {}
    per_round = 3 if args.quick else 6
    for name, rounds, variants in (("kernels", args.ab, kernel_variants()),
                                   ("mapping step", args.ab_step, step_variants(bench, config)),
                                   ("whole iteration", args.ab_total, total_variants(bench, config))):
        if rounds:
            comparisons[name] = {t: ab_rounds(bench, t, rounds, per_round, variants) for t in thread_counts}
            print(f"A/B {name}: done, {load_line()}", flush=True)
    if args.profile:
        torch.set_num_threads(1)
        print(profile_table(bench, iterations=5))
    torch.set_num_threads(default_threads)
    headers = ["stage (median ms)"] + [f"{t} thread{'s' if t > 1 else ''}" for t in results]
    names = [name for name, _ in paper_rows(next(iter(results.values())))]
    rows = [[name] + [f"{dict(paper_rows(r))[name]:.1f}" for r in results.values()] for name in names]
    rows.append(["samples per iteration"] + [f"{r['samples per iteration']:.0f}" for r in results.values()])
    print()
    print(markdown_table(headers, rows))
    figures = [Figure(f"mapping iteration, {args.rays} rays, {t} thread(s)", r["render_rays + losses + backward + step"],
                      "ms", f"<= {TARGET_MS:.0f}", f"staged sum {r['staged total']:.0f} ms; Mapper.optimize "
                      f"({config.mapping.window_size}x{config.mapping.num_rays} rays) {r['Mapper.optimize, one iteration']:.0f} ms")
               for t, r in results.items()]
    for name, ab in comparisons.items():
        rounds = {"kernels": args.ab, "mapping step": args.ab_step, "whole iteration": args.ab_total}[name]
        print(f"\nSame-run A/B of the {name}, {rounds} alternating rounds of 1 + {per_round} iterations each:\n")
        print(ab_table(ab))
        print(f"\nStages in the same rounds ({rounds} x {per_round} staged iterations each):\n")
        print(ab_stage_table(ab))
    print()
    print(figures_table(figures))
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; end: {load_line()}")
    write_json(args.json, figures_payload("One mapping iteration (issue 3)", figures, {
        "map": label, "rays": args.rays, "breakdown_ms": {str(t): r for t, r in results.items()},
        "table": markdown_table(headers, rows), "staged_mismatch": mismatch,
        "ab_ms": {name: {str(t): {row: {k: [v * 1000 for v in vs] for k, vs in series.items()}
                                      for row, series in r.items() if row != "stages"} for t, r in ab.items()}
                  for name, ab in comparisons.items()},
        "ab_stages": {name: {str(t): ab_stage_table({t: r}) for t, r in ab.items()}
                      for name, ab in comparisons.items()}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
