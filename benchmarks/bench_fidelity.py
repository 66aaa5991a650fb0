"""Issue 21 items 2-4: three deviations from the paper, each tried both ways.

Variants, one change at a time against today's defaults (``baseline``):

    current-pose   ``mapping.optimize_current_pose``: the newest non-keyframe frame's pose is
                   optimised in the mapper's window and the refined pose is its estimate (the
                   paper, the release); baseline holds it at the tracked pose (item 2)
    slots          ``loss.normalisation = "slots"``: the release's padded-slot means for the
                   mapper's free-space and SDF terms; baseline: the paper's per-ray means (item 3)
    no-front-mask  ``render.mask_in_front = false``: the renderer masks only samples more than
                   tr behind the first zero crossing (the paper); baseline also masks those
                   more than tr in front of it (item 4)

Scenes (``cpu`` preset, ``slam.runtime.run_slam``):

    rpy     TUM fr1/rpy, first 150 frames at 640x480 input: ATE RMSE
    walk    ``synthetic:walk?frames=200`` (320x240, rendered once into a frame cache): ATE RMSE
            and mesh accuracy / completion with the GT culled to what the cameras saw
            (``bench_slam.evaluate``)
    room0   Replica room0: SLAM on the even frames 0, 2, ..., 18, then the odd frames 1, ..., 19
            rendered at their GT poses (``slam.views.render_view``, the pipeline's 320 px
            width, as ``bench_mapping.py``): colour PSNR over every pixel, depth L1 over pixels
            valid in both; and the run's ATE. Tracked poses, not GT: with GT poses no pose is
            optimised and item 2 would be the baseline by construction. ``--room0-gt`` adds
            the GT-pose mapping of ``bench_mapping.py`` (``map_with_gt_poses``) for the other
            variants.

Every SLAM run is single-process (``runtime.processes = false``: tracking and mapping take
turns, every frame is mapped, no idle optimisation) and the final bundle adjustment's time
cap is off (``mapping.final_time_share = 0``; its iteration caps stay), so a run's result
depends on its seed (``runtime.seed``) only, not on the machine's load; the seconds do.
Each run is a child process (``--worker``); results are written to ``--json`` after every
run, so an interrupted benchmark keeps what finished. Seeds are the outer loop.

    python benchmarks/bench_fidelity.py [--variants baseline,current-pose,slots,no-front-mask]
        [--scenes rpy,walk,room0] [--seeds 0,1,2] [--rpy-frames 150] [--walk-frames 200]
        [--room0-frames 20] [--room0-gt] [--timeout S] [--json FILE] [--quick]
    python benchmarks/bench_fidelity.py --report FILE    (the tables of a --json FILE again)

``--quick``: one seed, 6 frames of fr1/rpy and of the walk, room0 frames 0-3: a smoke run
whose figures mean nothing.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (  # noqa: E402
    REPLICA,
    TUM_RPY,
    T_gt_run,
    cache_sequence,
    load_line,
    machine_state,
    map_with_gt_poses,
    markdown_table,
    pipeline_frame,
    run_child,
    write_json,
)

# Each variant changes one switch from the baseline, the cpu preset as it was before the
# measurement (held pose, per-ray means, front mask); cpu now takes the first two winners.
_BEFORE = {"mapping": {"optimize_current_pose": False}, "loss": {"normalisation": "ray"},
           "render": {"mask_in_front": True}}
VARIANTS: dict[str, dict] = {
    "baseline": _BEFORE,
    "current-pose": {**_BEFORE, "mapping": {"optimize_current_pose": True}},
    "slots": {**_BEFORE, "loss": {"normalisation": "slots"}},
    "no-front-mask": {**_BEFORE, "render": {"mask_in_front": False}},
}
PROTOCOL = {"runtime": {"processes": False}, "mapping": {"final_time_share": 0.0}}
"""Overrides of every run: one process, no time cap on the final bundle adjustment."""
SCENES = ("rpy", "walk", "room0")
WALK_SPEC = "synthetic:walk?frames=200"
MESH_POINTS = 200_000


def run_config(variant: str, seed: int, gt_poses: bool = False):
    from slam.config import apply_overrides, preset

    config = apply_overrides(preset("cpu"), PROTOCOL)
    config = apply_overrides(config, {"runtime": {"seed": seed}})
    return apply_overrides(config, VARIANTS[variant])


# ----------------------------------------------------------------- workers
def view_errors(maps, frames, T_map_gt=None) -> dict:
    """Held-out views at their GT poses (moved into the map's world by ``T_map_gt`` (4, 4) for a
    tracked run's map): colour PSNR over every pixel (unrendered pixels are black), depth L1 (cm)
    over pixels valid in both, coverage of the input's valid depth."""
    import numpy as np

    from slam.views import render_view

    T_map_gt = np.eye(4) if T_map_gt is None else T_map_gt
    abs_errors, sq_errors, covered, observed = [], [], 0, 0
    for frame in frames:
        view = render_view(maps, T_map_gt @ frame.T_world_cam, frame.K, frame.width, frame.height)
        valid = frame.depth > 0
        both = valid & view.valid
        abs_errors.append(np.abs(view.depth[both] - frame.depth[both]))
        covered, observed = covered + int(both.sum()), observed + int(valid.sum())
        sq_errors.append(((view.rgb - frame.rgb) ** 2).reshape(-1))
    errors = np.concatenate(abs_errors)
    mse = float(np.concatenate(sq_errors).mean())
    return {"psnr_db": float(-10 * np.log10(max(mse, 1e-12))),
            "depth_l1_cm": float(errors.mean()) * 100 if errors.size else float("nan"),
            "coverage": covered / max(observed, 1)}


def room0_frames(count: int):
    from slam.data import open_sequence

    sequence = open_sequence(REPLICA / "room0", max_frames=count)
    return [sequence[i] for i in range(0, count, 2)], [sequence[i] for i in range(1, count, 2)]


def worker(scene: str, variant: str, seed: int, frames: int, source: Path | None, out: Path) -> dict:
    from slam.checkpoint import load_checkpoint
    from slam.runtime import run_slam

    out.mkdir(parents=True, exist_ok=True)
    if scene == "room0-gt":
        config = run_config(variant, seed)
        mapped, held_out = room0_frames(frames)
        width = config.runtime.input_width
        t0 = time.perf_counter()
        mapper = map_with_gt_poses([pipeline_frame(f, width) for f in mapped], config)
        seconds = time.perf_counter() - t0
        return {"seconds": seconds, **view_errors(mapper.maps, [pipeline_frame(f, width) for f in held_out])}
    config = run_config(variant, seed)
    if scene == "room0":
        mapped, held_out = room0_frames(frames)
        result = run_slam([mapped], config, out)
    else:
        from bench_slam import open_source

        result = run_slam([open_source(source, frames)], config, out)
    info = json.loads((out / "run.json").read_text())
    if result.status != "finished":
        raise RuntimeError(f"run {result.status}: {result.error}")
    row = {"seconds": info["timings_s"]["wall"], "frames": result.frames, "keyframes": result.keyframes,
           "tracking_failures": info["tracking_failures"], "loops": result.loops,
           "run_ate_cm": None if result.ate_rmse is None else result.ate_rmse * 100,
           "final_ba": info["final_bundle_adjustment"]}
    if scene == "room0":
        width = config.runtime.input_width
        import numpy as np

        from slam.eval import Trajectory, read_trajectory

        truth = Trajectory(np.array([f.timestamp for f in mapped]), np.stack([f.T_world_cam for f in mapped]))
        T_map_gt = np.linalg.inv(T_gt_run(read_trajectory(out / "trajectory.txt"), truth))
        row.update(view_errors(load_checkpoint(out / "map.pt"), [pipeline_frame(f, width) for f in held_out], T_map_gt))
        row["ate_cm"] = row["run_ate_cm"]
        return row
    from bench_slam import BenchSequence, evaluate

    seq = BenchSequence(scene, source, frames, 0.0, WALK_SPEC if scene == "walk" else None)
    row.update(evaluate(seq, out, info, MESH_POINTS))
    return row


def worker_main(args) -> int:
    row = worker(args.worker, args.variant, args.seed, args.frames, args.source, args.out)
    (args.out / "result.json").write_text(json.dumps(row, indent=2))
    return 0


# ------------------------------------------------------------------ parent
def run_one(scene: str, variant: str, seed: int, frames: int, source: Path | None, out: Path,
            timeout: float) -> dict:
    args = ["benchmarks/bench_fidelity.py", "--worker", scene, "--variant", variant, "--seed", str(seed),
            "--frames", str(frames), "--out", str(out)]
    if source is not None:
        args += ["--source", str(source)]
    child = run_child(args, timeout=timeout)
    result = out / "result.json"
    if child.returncode != 0 or not result.exists():
        return {"error": "\n".join(child.output.strip().splitlines()[-8:]), "child_seconds": child.seconds}
    return {**json.loads(result.read_text()), "child_seconds": child.seconds}


METRICS = {
    "rpy": [("ate_cm", "ATE cm", 2)],
    "walk": [("ate_cm", "ATE cm", 2), ("accuracy_cm", "mesh acc. cm", 2), ("completion_ratio", "compl. %", 1)],
    "room0": [("psnr_db", "PSNR dB", 2), ("depth_l1_cm", "depth L1 cm", 2), ("ate_cm", "ATE cm", 2)],
    "room0-gt": [("psnr_db", "PSNR dB", 2), ("depth_l1_cm", "depth L1 cm", 2)],
}


def summary(values: list[float], digits: int) -> str:
    """``mean +- half the range (min-max)`` over seeds; one value alone as it is."""
    if not values:
        return "n/a"
    if len(values) == 1:
        return f"{values[0]:.{digits}f}"
    lo, hi = min(values), max(values)
    return f"{statistics.fmean(values):.{digits}f} +- {(hi - lo) / 2:.{digits}f} ({lo:.{digits}f}-{hi:.{digits}f})"


def paired(by_seed: dict, baseline: dict, key: str, digits: int) -> str:
    """The variant's metric minus the baseline's, seed by seed (the same seed draws the same
    rays until the variants' paths part): mean and each seed's difference."""
    diffs = [r[key] - baseline[seed][key] for seed, r in by_seed.items()
             if "error" not in r and r.get(key) is not None and seed in baseline
             and "error" not in baseline[seed] and baseline[seed].get(key) is not None]
    if not diffs:
        return ""
    return f"{statistics.fmean(diffs):+.{digits}f} ({', '.join(f'{d:+.{digits}f}' for d in diffs)})"


def results_table(results: dict) -> str:
    """A table per scene, a row per variant: each metric's mean and spread over the seeds that
    finished, its difference to the baseline seed by seed, seconds per run, and how many seeds."""
    tables = []
    for scene, by_variant in results.items():
        rows = []
        baseline = by_variant.get("baseline", {})
        for variant, by_seed in by_variant.items():
            done = [r for r in by_seed.values() if "error" not in r]
            cells = []
            for key, _, digits in METRICS[scene]:
                cells.append(summary([r[key] for r in done if r.get(key) is not None], digits))
                cells.append("" if variant == "baseline" else paired(by_seed, baseline, key, digits))
            failed = len(by_seed) - len(done)
            rows.append([variant, *cells, summary([r["seconds"] for r in done], 0),
                         f"{len(done)}" + (f" ({failed} failed)" if failed else "")])
        names = [name for _, label, _ in METRICS[scene] for name in (label, "- baseline, per seed")]
        tables.append(f"{scene}\n\n" + markdown_table(["variant", *names, "seconds", "seeds"], rows))
    return "\n\n".join(tables)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--variants", default=",".join(VARIANTS))
    p.add_argument("--scenes", default=",".join(SCENES))
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--rpy-frames", type=int, default=150)
    p.add_argument("--walk-frames", type=int, default=200)
    p.add_argument("--room0-frames", type=int, default=20, help="even ones mapped, odd ones held out")
    p.add_argument("--room0-gt", action="store_true", help="also room0 mapped with GT poses (bench_mapping.py)")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds per run")
    p.add_argument("--work", type=Path, default=None, help="outputs of the runs (default: a temp folder)")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--quick", action="store_true", help="smoke run: one seed, a few frames")
    p.add_argument("--report", type=Path, default=None, help="print the tables of a --json file and stop")
    p.add_argument("--worker", choices=(*SCENES, "room0-gt"), help=argparse.SUPPRESS)
    p.add_argument("--variant", choices=tuple(VARIANTS), help=argparse.SUPPRESS)
    p.add_argument("--seed", type=int, help=argparse.SUPPRESS)
    p.add_argument("--frames", type=int, help=argparse.SUPPRESS)
    p.add_argument("--source", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        return worker_main(args)
    if args.report:
        print(results_table(json.loads(args.report.read_text())["results"]))
        return 0
    if args.quick:
        args.seeds, args.rpy_frames, args.walk_frames, args.room0_frames = "0", 6, 6, 4
    variants = args.variants.split(",")
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        p.error(f"unknown variants {unknown}; known: {list(VARIANTS)}")
    scenes = args.scenes.split(",") + (["room0-gt"] if args.room0_gt else [])
    seeds = [int(s) for s in args.seeds.split(",")]
    print(load_line(), flush=True)
    started = time.perf_counter()
    results: dict[str, dict[str, dict[int, dict]]] = {}
    payload = {"title": "issue 21 items 2-4", "machine": machine_state(), "protocol": PROTOCOL,
               "variants": {v: VARIANTS[v] for v in variants}, "results": results}
    with tempfile.TemporaryDirectory(prefix="bench-fidelity-") as tmp:
        work = args.work or Path(tmp)
        sources: dict[str, tuple[Path | None, int]] = {}
        for scene in scenes:
            if scene == "rpy":
                if TUM_RPY.is_dir():
                    sources[scene] = (TUM_RPY, args.rpy_frames)
                else:
                    print("rpy: skipped, no TUM fr1/rpy in shared/data", flush=True)
            elif scene == "walk":
                from slam.data import open_sequence

                cache = cache_sequence(open_sequence(WALK_SPEC, max_frames=args.walk_frames),
                                       work / f"cache_walk200_{args.walk_frames}")
                sources[scene] = (cache.folder, args.walk_frames)
            elif scene in ("room0", "room0-gt"):
                if (REPLICA / "room0").is_dir():
                    sources[scene] = (None, args.room0_frames)
                else:
                    print(f"{scene}: skipped, no Replica room0 in shared/data", flush=True)
            else:
                p.error(f"unknown scene {scene!r}; known: {list(SCENES)}")
        for seed in seeds:
            for scene, (source, frames) in sources.items():
                for variant in variants:
                    if scene == "room0-gt" and variant == "current-pose":
                        continue  # no pose is optimised with GT poses: the baseline by construction
                    out = work / f"{scene}_{variant}_{seed}"
                    row = run_one(scene, variant, seed, frames, source, out, args.timeout)
                    row["load_after"] = load_line()
                    results.setdefault(scene, {}).setdefault(variant, {})[seed] = row
                    shown = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()
                             if k not in ("final_ba", "error")}
                    print(f"seed {seed} {scene} {variant}: {json.dumps(shown)}"
                          + (f"\n  error: {row['error']}" if "error" in row else ""), flush=True)
                    payload["elapsed_s"] = time.perf_counter() - started
                    write_json(args.json, payload)
    print()
    print(results_table(results))
    print()
    print(load_line())
    print(f"total {time.perf_counter() - started:.0f} s")
    payload["table"] = results_table(results)
    write_json(args.json, payload)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
