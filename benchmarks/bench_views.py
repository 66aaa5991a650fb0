"""Novel-view latency (issue 18): the ``banded`` view path against the ``full`` reference.

A map is built with ground-truth poses from the even frames of a sequence (as
``bench_mapping.py`` does, ``cpu`` preset, pipeline width 320), then the odd, held-out frames
are rendered at their poses with ``slam.views.render_view``'s defaults (``banded``, decoder
precision ``auto``) and its plain reference (``full``, ``float32``), at 640 and 320
pixels wide (the input's aspect: 640x480 and 320x240 for TUM), after one untimed view (warm).
Colour PSNR and depth L1 are against the held-out input at that size; the banded image is
also compared with the full one (PSNR between the two renders).

    (a) Replica room0: map frames 0, 2, ..., 18; views of 1, 3, ..., 19.
    (b) TUM fr1/rpy: map frames 0, 2, ..., 38; views of 1, 5, 9, ..., 37.

    python benchmarks/bench_views.py [--scenes room0,rpy] [--threads 2] [--json FILE]

With ``--quality`` it measures how the views look instead (issue 43; ``view_quality.py``):
PSNR, SSIM and sharpness of training views at tracked poses on every real sequence of
``bench_real.py``, and Replica room0's held-out views, per preset, with pictures:

    python benchmarks/bench_views.py --quality [--presets cpu] [--sequences desk,room0] [--out DIR]
                                     [--seeds N] [--reuse BENCH_REAL_WORK_DIR] [--fine-ablation]

``--seeds N`` runs each sequence with seeds 0..N-1 and prints mean ± std over them;
``--fine-ablation`` also renders each map without its fine colour level, a paired A/B of the
level (the coarse map and trajectory are the same with and without it); ``--reuse`` scores
the deterministic runs of a ``bench_real.py`` work folder instead of running again.
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
    SHARED_DATA,
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
from view_quality import psnr

SCENES = {
    "room0": (lambda: REPLICA / "room0", list(range(0, 20, 2)), list(range(1, 20, 2))),
    "rpy": (lambda: SHARED_DATA / "rgbd_dataset_freiburg1_rpy", list(range(0, 40, 2)), list(range(1, 40, 4))),
}
WIDTHS = {640: "<= 1.0", 320: "<= 0.3"}


@dataclass(frozen=True)
class ViewStats:
    """One method at one size over the held-out views: median seconds, PSNR and depth L1
    against the input (over every pixel / pixels valid in both), coverage of the input."""

    seconds: float
    psnr_db: float
    depth_l1_cm: float
    coverage: float


def render_stats(maps, frames, method: str, precision: str) -> tuple[ViewStats, list]:
    from slam.views import render_view

    seconds, sq, abs_err, covered, observed, views = [], [], [], 0, 0, []
    first = frames[0]
    render_view(maps, first.T_world_cam, first.K, first.width, first.height, method=method,
                precision=precision)  # warm
    for frame in frames:
        t0 = time.perf_counter()
        view = render_view(maps, frame.T_world_cam, frame.K, frame.width, frame.height, method=method,
                           precision=precision)
        seconds.append(time.perf_counter() - t0)
        observed_mask = frame.depth > 0
        both = observed_mask & view.valid
        abs_err.append(np.abs(view.depth[both] - frame.depth[both]))
        covered, observed = covered + int(both.sum()), observed + int(observed_mask.sum())
        sq.append(((view.rgb - frame.rgb) ** 2).reshape(-1))
        views.append(view)
    stats = ViewStats(statistics.median(seconds), float(-10 * np.log10(np.concatenate(sq).mean())),
                      float(np.concatenate(abs_err).mean() * 100), covered / max(observed, 1))
    return stats, views


def scene_figures(name: str, config) -> list[Figure]:
    from slam.data import open_sequence

    path_of, mapped_ids, held_ids = SCENES[name]
    path = require(path_of())
    sequence = open_sequence(path)
    mapped = [pipeline_frame(sequence[i], config.runtime.input_width) for i in mapped_ids]
    t0 = time.perf_counter()
    mapper = map_with_gt_poses(mapped, config)
    print(f"{name}: mapped {len(mapped)} frames in {time.perf_counter() - t0:.0f} s", flush=True)
    figures = []
    for width, target in WIDTHS.items():
        frames = [pipeline_frame(sequence[i], width) for i in held_ids]
        size = f"{frames[0].width}x{frames[0].height}"
        full, full_views = render_stats(mapper.maps, frames, "full", "float32")
        banded, banded_views = render_stats(mapper.maps, frames, "banded", "auto")
        agreement = statistics.mean(psnr(a.rgb, b.rgb) for a, b in zip(full_views, banded_views))
        print(f"{name} {size}: full {full}\n{name} {size}: banded {banded}", flush=True)
        figures += [
            Figure(f"{name} {size} view, banded", banded.seconds, "s", target,
                   f"median of {len(frames)} held-out views; full render {full.seconds:.2f} s "
                   f"({full.seconds / banded.seconds:.1f}x)"),
            Figure(f"{name} {size} PSNR, banded minus full", banded.psnr_db - full.psnr_db, "dB", ">= -0.5",
                   f"against the input: banded {banded.psnr_db:.2f}, full {full.psnr_db:.2f}; "
                   f"banded against full {agreement:.1f} dB; depth L1 {banded.depth_l1_cm:.2f} / "
                   f"{full.depth_l1_cm:.2f} cm, coverage {banded.coverage:.1%} / {full.coverage:.1%}"),
        ]
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--scenes", default=",".join(SCENES), help=f"comma list of {tuple(SCENES)}")
    parser.add_argument("--threads", type=int, default=2, help="torch threads while rendering")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    parser.add_argument("--quality", action="store_true", help="view quality (PSNR, SSIM, sharpness) instead")
    parser.add_argument("--presets", default="cpu", help="--quality: comma list of presets")
    parser.add_argument("--sequences", default="", help="--quality: comma list (default: all of bench_real.py)")
    parser.add_argument("--out", type=Path, default=Path("out/view-quality"), help="--quality: runs and pictures")
    parser.add_argument("--timeout", type=float, default=3600, help="--quality: seconds a run may take")
    parser.add_argument("--seeds", type=int, default=1, help="--quality: runs per sequence, seeds 0..N-1")
    parser.add_argument("--reuse", type=Path, default=None,
                        help="--quality: a bench_real.py work folder whose deterministic runs are scored")
    parser.add_argument("--fine-ablation", action="store_true",
                        help="--quality: also render every map without its fine colour level (paired A/B)")
    args = parser.parse_args(argv)
    if args.quality:
        import view_quality

        rows = view_quality.run([s for s in args.sequences.split(",") if s], args.presets.split(","), args.out,
                                args.timeout, seeds=args.seeds, reuse=args.reuse, fine_ablation=args.fine_ablation)
        print()
        print(view_quality.table(rows))
        print()
        print(view_quality.summary_table(rows))
        return 0

    import torch

    from slam.config import load_config

    config = load_config(args.preset)
    config = replace(config, runtime=replace(config.runtime, device="cpu", processes=False))
    print(f"# Novel views: banded against full ({args.preset} preset)\n")
    figures: list[Figure] = []
    t0 = time.perf_counter()
    for name in args.scenes.split(","):
        if name not in SCENES:
            parser.error(f"unknown scene {name!r}; choose from {tuple(SCENES)}")
        torch.set_num_threads(args.threads)
        try:
            print(f"start {name}: {load_line()}, torch threads {torch.get_num_threads()}", flush=True)
            figures += scene_figures(name, config)
        except MissingData as missing:
            figures.append(Figure(name, None, "", "", f"skipped: {missing}"))
    print()
    print(figures_table(figures))
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; end: {load_line()}")
    write_json(args.json, figures_payload("Novel views: banded against full (issue 18)", figures,
                                          {"preset": args.preset, "threads": args.threads}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
