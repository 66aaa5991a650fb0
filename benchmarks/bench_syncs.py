"""Host syncs and operator counts of the inner loops (issue 40 item 2), on the CPU.

Per preset, with ``torch.profiler`` (``slam.profiling.aten_counts``) and the device-placement
replay of ``slam.devicecheck`` (the pipeline runs on ``cpu:0``, which stands for the GPU):

* a tracking iteration: frame 3 of the synthetic walk (160 x 120) tracked from frame 2's GT
  pose moved by 2 cm and 0.02 rad, against a map of frames 0-2 built with GT poses, with the
  ORB correspondences the runtime would give it where the preset uses them;
* a mapping iteration: frame 3 handed to ``Mapper.process`` as the runtime does (keyframe
  test, allocation, the window's optimisation with the frame's pose free where the preset
  says so);
* a frame of the whole pipeline: ``run_slam`` on ``synthetic:walk?frames=3&width=160&height=120``
  in one process, loops off (``--no-loops``), everything from start to the written outputs
  (the final bundle adjustment, checkpoint and mesh included), divided by 3.

Counted: aten operators (nested ones included, as the profiler lists them); device-to-host
reads among them (``aten::_local_scalar_dense`` + ``aten::nonzero``: "syncs"), but for those
inside a torch optimiser's step, which read its CPU step counter (``opt``: no device sync on
a GPU); Python-level reads of device tensors (``bool``/``float``/``.item()``/``.tolist()``/
``.numpy()``/``.cpu()``: "reads", what a CPU profile cannot see but a GPU pays for) and
uploads of host data ("uploads").

``--static on`` renders padded samples (``render.static_shapes``: the path CUDA devices take);
``off`` the flat samples (the CPU's default); ``default`` leaves the preset's setting (and
runs code that predates the switch, for a before/after); ``on,off`` measures both, a row each.
The second table holds issue 40's per-frame figures of the whole run: device-to-host reads a
frame (``aten::_local_scalar_dense`` + ``aten::nonzero``; in brackets those of fused Adam's
CPU kernel, which reads its step count where CUDA's does not), aten ops a frame, and the
per-iteration syncs of tracking and mapping. ``--kernels torch`` (default) is the
plain torch path, the one CUDA tensors take; ``numba`` the CPU's fused host kernels, which
hand numpy arrays to numba and so read the host by design.

    python benchmarks/bench_syncs.py [--presets test,cpu,paper,gpu] [--static on|off|on,off|default]
        [--kernels torch|numba] [--no-run] [--json FILE] [--quick]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import map_with_gt_poses, markdown_table, write_json  # noqa: E402

from slam.config import PRESETS, SLAMConfig, preset  # noqa: E402
from slam.devicecheck import PIPELINE_DEVICE, DeviceMixChecker  # noqa: E402
from slam.profiling import MAPPING_ITERATION, TRACKING_ITERATION, aten_counts  # noqa: E402

STATIC = "default"

WALK = "synthetic:walk?frames=100&width=160&height=120"
RUN = "synthetic:walk?frames=3&width=160&height=120"


def _frames(spec: str) -> list:
    from slam.data import open_sequence

    return list(open_sequence(spec, max_frames=4))


def _configured(config: SLAMConfig, **runtime) -> SLAMConfig:
    """The preset on the device stand-in, with ``--static`` applied."""
    config = replace(config, runtime=replace(config.runtime, device=str(PIPELINE_DEVICE), **runtime))
    if STATIC != "default":
        config = replace(config, render=replace(config.render, static_shapes=STATIC))
    return config


def _small(config: SLAMConfig) -> SLAMConfig:
    """The preset at the synthetic frames' size, with a short map initialisation."""
    return _configured(replace(config, mapping=replace(config.mapping, first_frame_iterations=20, final_iterations=0)),
                       input_width=None)


def _profiled(fn):
    """Run fn() under the profiler and the device replay -> (result, aten counts, checker)."""
    from torch.profiler import ProfilerActivity, profile

    with DeviceMixChecker() as checker, profile(activities=[ProfilerActivity.CPU]) as prof:
        result = fn()
    return result, aten_counts(prof.events()), checker


def _row(counts, checker, name) -> dict:
    c = counts[name]
    n = max(c.ranges, 1)
    return {"iterations": c.ranges, "aten_ops": c.aten_ops / n, "syncs": c.syncs / n,
            "optimizer_reads": c.optimizer_reads / n, "reads": checker.reads[name] / n,
            "uploads": checker.uploads[name] / n, "shape_ops": checker.shapes[name] / n, "sync_ops": dict(c.by_op),
            "sites": dict(checker.sites.get(name, {}))}


def _whole(counts, checker) -> dict:
    c = counts[None]
    return {"aten_ops": c.aten_ops, "syncs": c.syncs, "optimizer_reads": c.optimizer_reads,
            "reads": sum(checker.reads.values()), "uploads": sum(checker.uploads.values()),
            "shape_ops": sum(checker.shapes.values()),
            "mixes": len(checker.mixes)}


def inner_loops(name: str) -> dict:
    """Counts per tracking iteration and per mapping iteration of preset ``name``."""
    from slam.features import FeatureOdometry
    from slam.frames import prepare_frame
    from slam.geometry import se3_exp
    from slam.mapping import TrackedFrame
    from slam.tracking import FrozenMap, Tracker

    config = _small(preset(name))
    frames = _frames(WALK)
    torch.manual_seed(0)
    device = PIPELINE_DEVICE
    odometry = FeatureOdometry.from_config(config)
    matches = None
    if odometry is not None:
        odometry.correspondences(frames[2])
        odometry.remember(np.asarray(frames[2].T_world_cam, np.float64))
        matches = odometry.correspondences(frames[3])
    state = {}

    def build():
        state["mapper"] = map_with_gt_poses(frames[:3], config, device=device)
        state["fmap"] = FrozenMap(state["mapper"].snapshot(), config, device)
        state["tf"] = prepare_frame(frames[3], None, device, config.voxel.max_depth)

    _profiled(build)  # under the replay, so that every tensor has its place
    mapper, fmap, tf = state["mapper"], state["fmap"], state["tf"]
    tracker = Tracker(config, device)
    T_prev = torch.as_tensor(frames[2].T_world_cam, dtype=torch.float32)
    T_init = T_prev @ se3_exp(torch.tensor([0.02, 0.0, 0.0, 0.0, 0.02, 0.0]))
    result, counts, checker = _profiled(lambda: tracker.track(tf, fmap, T_init.to(device), matches))
    tracking = _row(counts, checker, TRACKING_ITERATION)
    tracking["whole_call"] = _whole(counts, checker)
    tracking["error_cm"] = float((result.T_world_cam[:3, 3].cpu()
                                  - torch.as_tensor(frames[3].T_world_cam[:3, 3])).norm()) * 100
    T3 = torch.as_tensor(frames[3].T_world_cam, dtype=torch.float32)
    _, counts, checker = _profiled(lambda: mapper.process(TrackedFrame(tf, T3.to(device))))
    mapping = _row(counts, checker, MAPPING_ITERATION)
    mapping["whole_call"] = _whole(counts, checker)
    return {"tracking": tracking, "mapping": mapping}


def whole_run(name: str) -> dict:
    """Counts per frame of a 3-frame single-process run without loops."""
    from slam.data import open_sequence
    from slam.runtime import run_slam

    config = _configured(preset(name), processes=False)
    config = replace(config, loop=replace(config.loop, enabled=False))
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        result, counts, checker = _profiled(lambda: run_slam([open_sequence(RUN)], config, out))
        seconds = time.perf_counter() - t0
    frames = max(result.frames, 1)
    c = counts[None]
    whole = _whole(counts, checker)
    return {"frames": result.frames, "status": result.status, "error": result.error,
            **{k: v / frames for k, v in whole.items() if k != "mixes"}, "mixes": whole["mixes"],
            "in_tracking_iterations": counts[TRACKING_ITERATION].syncs / frames,
            "in_mapping_iterations": counts[MAPPING_ITERATION].syncs / frames,
            "sync_ops": {k: v / frames for k, v in c.by_op.items()},
            "read_sites": {str(k): dict(v.most_common(12)) for k, v in checker.sites.items()},
            "seconds_profiled": seconds}


def main(argv: list[str] | None = None) -> int:
    global STATIC
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", default=",".join(PRESETS))
    parser.add_argument("--static", default="on", help="on, off, default, or several joined by commas")
    parser.add_argument("--kernels", choices=("torch", "numba"), default="torch")
    parser.add_argument("--no-run", action="store_true", help="skip the 3-frame whole runs")
    parser.add_argument("--no-inner", action="store_true", help="skip the single iterations (whole runs only)")
    parser.add_argument("--quick", action="store_true", help="test preset only")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    modes = [m for m in args.static.split(",") if m]
    if not modes or any(m not in ("on", "off", "default") for m in modes):
        parser.error("--static takes on, off or default, joined by commas")
    os.environ["VOXFUSION_KERNELS"] = args.kernels
    names = ["test"] if args.quick else [p for p in args.presets.split(",") if p]
    results: dict = {}
    for mode in modes:
        STATIC = mode
        for name in names:
            r = results.setdefault(mode, {}).setdefault(name, {})
            if not args.no_inner:
                r["inner"] = inner_loops(name)
            if not args.no_run:
                r["run"] = whole_run(name)
            print(f"done {name}, static {mode}", file=sys.stderr, flush=True)
    print(f"kernels: {args.kernels}")
    if not args.no_inner:
        rows = []
        for mode, by_name in results.items():
            for name, r in by_name.items():
                t, m = r["inner"]["tracking"], r["inner"]["mapping"]

                def three(d):
                    return f"{d['syncs']:.1f} / {d['reads']:.1f} / {d['uploads']:.1f}"

                rows.append([name, mode, three(t), f"{t['aten_ops']:.0f}", three(m), f"{m['aten_ops']:.0f}"])
        print(markdown_table(["preset", "static", "tracking it.: syncs / reads / uploads", "aten ops",
                              "mapping it.: syncs / reads / uploads", "aten ops"], rows))
    if not args.no_run:
        rows = []
        for mode, by_name in results.items():
            for name, r in by_name.items():
                run = r["run"]
                rows.append([name, mode, f"{run['syncs']:.1f} ({run['optimizer_reads']:.0f})",
                             f"{run['aten_ops'] / 1000:.1f}k",
                             f"{run['in_tracking_iterations']:.1f} / {run['in_mapping_iterations']:.1f}",
                             f"{run['reads']:.0f} / {run['uploads']:.0f}", run["status"]])
        print(f"\nA frame of {RUN}, one process, no loops (issue 40's figures):")
        print(markdown_table(["preset", "static", "device-to-host reads a frame (fused Adam's CPU)",
                              "aten ops a frame", "syncs a frame inside tracking / mapping iterations",
                              "Python reads / uploads a frame", "status"], rows))
    write_json(args.json, {"static": modes, "kernels": args.kernels, "results": results})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
