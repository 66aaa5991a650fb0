"""Refit a run's fine colour level at the rendered surface, offline, and score its training views.

    python benchmarks/refit_fine.py RUN_DIR SEQUENCE CAPS

RUN_DIR is a ``voxfusion run --out`` folder (``map.pt``, ``trajectory.txt``) of the
``bench_real.py`` sequence named SEQUENCE; CAPS a comma list of ``FIT_KEYFRAMES_RENDERED``
values. The checkpoint's keyframes get their frames back from the sequence, then
``Mapper.fit_fine_rendered`` runs on the loaded map (its coarse map is the run's final one) with
each cap, and the 12 training views of ``view_quality.py`` are scored as run and after each refit.
Used to choose the cap (decisions.md#fine_color) without a run per value: the fit changes
colour only, so the run's trajectory and coarse map stand.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_real import sequences  # noqa: E402
from view_quality import observed_mask, score_views, tracked_views  # noqa: E402


def main(argv: list[str]) -> int:
    import slam.mapping as mapping
    from slam import load_checkpoint
    from slam.data import open_sequence
    from slam.frames import prepare_frame
    from slam.views import render_view

    run_dir, name, caps = Path(argv[0]), argv[1], [int(c) for c in argv[2].split(",")]
    torch.set_num_threads(1)
    seq = next(s for s in sequences(None) if s.name == name)
    sequence = open_sequence(seq.path, max_frames=seq.max_frames)
    stamps = np.asarray(sequence.timestamps, np.float64)
    views = tracked_views(run_dir, sequence)
    seen = observed_mask(sequence, views[0][0])

    def score(mapset, tag: str) -> None:
        s = score_views([(render_view(mapset, T, f.K, f.width, f.height), f) for f, T in views], seen)
        print(f"{name} {run_dir.name} {tag}: PSNR {s.psnr_db:.2f} dB, SSIM {s.ssim:.3f}, sharpness {s.sharpness:.2f}",
              flush=True)

    score(load_checkpoint(run_dir / "map.pt"), "as run")
    for cap in caps:
        mapset = load_checkpoint(run_dir / "map.pt")
        for submap in mapset.maps:
            for kf in submap.keyframes:
                index = int(np.argmin(np.abs(stamps - kf.timestamp)))
                kf.frame = prepare_frame(sequence[index], mapset.config.runtime.input_width, torch.device("cpu"),
                                         mapset.config.voxel.max_depth)
        mapping.FIT_KEYFRAMES_RENDERED = cap
        mapper = mapping.Mapper(mapset.config, torch.device("cpu"), seed=mapset.config.runtime.seed)
        started = time.perf_counter()
        for submap in mapset.maps:
            mapper.fit_fine_rendered(submap, mapset.config.fine_color.final_fit_iterations)
        keyframes = sum(len(m.keyframes) for m in mapset.maps)
        score(mapset, f"refit at the rendered surface, cap {cap} of {keyframes} keyframes "
                      f"({time.perf_counter() - started:.1f} s)")
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 4:
        print(__doc__, file=sys.stderr)
        sys.exit(2)
    sys.exit(main(sys.argv[1:]))
