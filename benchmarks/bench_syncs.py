"""Host syncs and operator counts of the inner loops (issue 40 item 2), on the CPU.

Per preset, with ``torch.profiler`` (``slam.profiling.aten_counts``) and a torch-function
mode (``slam.profiling.HostReadCounter``):

* a tracking iteration: frame 3 of the synthetic walk tracked from frame 2's GT pose, moved
  by 2 cm and 0.02 rad, against a map of frames 0-2 built with GT poses, with the ORB
  correspondences the runtime would give it where the preset uses them;
* a mapping iteration: frame 3 handed to ``Mapper.process`` as the runtime does (keyframe
  test, allocation, the window's optimisation with the frame's pose free where the preset
  says so);
* a frame of the whole pipeline: ``run_slam`` on ``synthetic:walk?frames=3&width=160&height=120``
  in one process, loops off (``--no-loops``), everything from start to the written outputs,
  divided by 3.

Counted: aten operators (nested ones included, as the profiler lists them), device-to-host
reads among them (``aten::_local_scalar_dense`` + ``aten::nonzero``) and Python-level host
reads (``bool``/``float``/``int``/``.item()``/``.tolist()``/``.numpy()``/``.cpu()``: what a
CPU profile cannot see but a GPU pays for).

Kernels: ``--kernels torch`` (default) is the plain torch path, the one CUDA tensors take;
``numba`` is the CPU's fused host kernels (``slam.kernels``), which hand numpy arrays to
numba and so read the host by design (reported, not held to zero). ``both`` runs both.

    python benchmarks/bench_syncs.py [--presets test,cpu,paper,gpu] [--kernels torch|numba|both]
        [--no-run] [--json FILE] [--quick]
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
from slam.profiling import MAPPING_ITERATION, TRACKING_ITERATION, HostReadCounter, aten_counts  # noqa: E402

WALK = "synthetic:walk?frames=4&width=160&height=120"
RUN = "synthetic:walk?frames=3&width=160&height=120"


def _frames(spec: str) -> list:
    from slam.data import open_sequence

    return list(open_sequence(spec))


def _small(config: SLAMConfig) -> SLAMConfig:
    """The preset at the synthetic frames' size, with a short map initialisation."""
    return replace(config, runtime=replace(config.runtime, device="cpu", input_width=None),
                   mapping=replace(config.mapping, first_frame_iterations=20, final_iterations=0))


def _profiled(fn):
    """Run fn() under the profiler and a host-read counter -> (result, aten counts, reads)."""
    from torch.profiler import ProfilerActivity, profile

    with HostReadCounter() as reads, profile(activities=[ProfilerActivity.CPU]) as prof:
        result = fn()
    return result, aten_counts(prof.events()), reads


def _row(counts, reads, name) -> dict:
    c = counts[name]
    n = max(c.ranges, 1)
    return {"iterations": c.ranges, "aten_ops": c.aten_ops / n, "syncs": c.syncs / n,
            "host_reads": reads.reads[name] / n, "sync_ops": dict(c.by_op),
            "host_read_kinds": dict(reads.where.get(name, {}))}


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
    mapper = map_with_gt_poses(frames[:3], config)
    device = torch.device("cpu")
    fmap = FrozenMap(mapper.snapshot(), config, device)
    tracker = Tracker(config, device)
    odometry = FeatureOdometry.from_config(config)
    matches = None
    if odometry is not None:
        odometry.correspondences(frames[2])
        odometry.remember(np.asarray(frames[2].T_world_cam, np.float64))
        matches = odometry.correspondences(frames[3])
    tf = prepare_frame(frames[3], None, device, config.voxel.max_depth)
    T_prev = torch.as_tensor(frames[2].T_world_cam, dtype=torch.float32)
    T_init = T_prev @ se3_exp(torch.tensor([0.02, 0.0, 0.0, 0.0, 0.02, 0.0]))
    _, counts, reads = _profiled(lambda: tracker.track(tf, fmap, T_init, matches))
    tracking = _row(counts, reads, TRACKING_ITERATION)
    tracking["whole_call"] = {"aten_ops": counts[None].aten_ops, "syncs": counts[None].syncs,
                              "host_reads": reads.reads[None]}
    T3 = torch.as_tensor(frames[3].T_world_cam, dtype=torch.float32)
    _, counts, reads = _profiled(lambda: mapper.process(TrackedFrame(tf, T3)))
    mapping = _row(counts, reads, MAPPING_ITERATION)
    mapping["whole_call"] = {"aten_ops": counts[None].aten_ops, "syncs": counts[None].syncs,
                             "host_reads": reads.reads[None]}
    return {"tracking": tracking, "mapping": mapping}


def whole_run(name: str) -> dict:
    """Counts per frame of a 3-frame single-process run without loops."""
    from slam.data import open_sequence
    from slam.runtime import run_slam

    config = preset(name)
    config = replace(config, runtime=replace(config.runtime, device="cpu", processes=False),
                     loop=replace(config.loop, enabled=False))
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        result, counts, reads = _profiled(lambda: run_slam([open_sequence(RUN)], config, out))
        seconds = time.perf_counter() - t0
    frames = max(result.frames, 1)
    c = counts[None]
    return {"frames": result.frames, "status": result.status, "aten_ops": c.aten_ops / frames,
            "syncs": c.syncs / frames, "host_reads": reads.reads[None] / frames,
            "in_tracking_iterations": counts[TRACKING_ITERATION].syncs / frames,
            "in_mapping_iterations": counts[MAPPING_ITERATION].syncs / frames,
            "sync_ops": {k: v / frames for k, v in c.by_op.items()}, "seconds_profiled": seconds}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", default=",".join(PRESETS))
    parser.add_argument("--kernels", choices=("torch", "numba", "both"), default="torch")
    parser.add_argument("--no-run", action="store_true", help="skip the 3-frame whole runs")
    parser.add_argument("--quick", action="store_true", help="test preset only")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    names = ["test"] if args.quick else [p for p in args.presets.split(",") if p]
    backends = ["torch", "numba"] if args.kernels == "both" else [args.kernels]
    torch.set_num_threads(max(1, torch.get_num_threads()))
    results: dict = {}
    for backend in backends:
        os.environ["VOXFUSION_KERNELS"] = backend
        for name in names:
            key = f"{name}/{backend}"
            results[key] = {"inner": inner_loops(name)}
            if not args.no_run:
                results[key]["run"] = whole_run(name)
            print(f"done {key}", file=sys.stderr, flush=True)
    rows = []
    for key, r in results.items():
        t, m = r["inner"]["tracking"], r["inner"]["mapping"]
        run = r.get("run")
        rows.append([key, f"{t['syncs']:.1f} / {t['host_reads']:.1f}", f"{t['aten_ops']:.0f}",
                     f"{m['syncs']:.1f} / {m['host_reads']:.1f}", f"{m['aten_ops']:.0f}",
                     "-" if run is None else f"{run['syncs']:.0f} / {run['host_reads']:.0f}",
                     "-" if run is None else f"{run['aten_ops'] / 1000:.1f}k"])
    print(markdown_table(["preset/kernels", "tracking it.: syncs / host reads", "aten ops",
                          "mapping it.: syncs / host reads", "aten ops", "run, a frame: syncs / host reads",
                          "aten ops"], rows))
    write_json(args.json, {"results": results})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
