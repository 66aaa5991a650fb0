"""How views of a map look (issue 43 item 1): PSNR, SSIM and sharpness of rendered views
against the input, with pictures (input | render | error).

``bench_views.py --quality`` runs this. Per real sequence of the real-data benchmark
(``bench_real.sequences``: fr1/rpy 150, fr1/desk, Replica room0 and the cache's unseen
fr1/rpy windows) and preset: one ``voxfusion run`` (process mode, ``--deterministic 1`` so
that the map does not depend on machine load), then **training views**: every k-th input
frame (at most ``VIEWS``) rendered at its *tracked* pose at 320 pixels wide, as a user of the
server sees them. For Replica room0 also **held-out views**: a map from the even frames at
their ground-truth poses, rendered at the odd ones (``bench_views.py``'s latency protocol).

Sharpness is the gradient energy ratio, mean squared Sobel gradient of the rendered grey
image over the input's: 1 is as sharp as the input, a smeared view is far below.

Every score counts only the pixels the camera **observed**: TUM fr1 frames are undistorted, and
the pixels whose source lies outside the raw image are black in the input (6-7 % of a fr1
frame, and their black edge holds much of its gradient energy); they are no observation, so
they are left out (``observed_mask``; before 2026-12-05 they counted and cost fr1/desk about
2 dB). A pixel the render does not reach (a hole) counts as black in ``psnr_db``, SSIM and
sharpness; ``psnr_hit_db`` is over the observed pixels the render reached, and ``holes`` their
share of the observed pixels, so both readings are there.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPLICA, pipeline_frame  # noqa: E402

VIEW_WIDTH = 320
VIEWS = 12
"""Training views per sequence (evenly spaced over the run)."""
PICTURE_VIEWS = 3
"""Views per picture (columns)."""


@dataclass(frozen=True)
class ViewScores:
    """Means over the views of one sequence, over the observed pixels (holes black, except in
    ``psnr_hit_db``)."""

    psnr_db: float
    psnr_hit_db: float
    ssim: float
    sharpness: float
    holes: float
    depth_l1_cm: float
    count: int


SSIM_WINDOW = 7
"""scikit-image's default window: the SSIM map is averaged this far (half of it) inside the mask."""


def psnr(rendered: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None) -> float:
    """(H, W, 3) colours in [0, 1], optional (H, W) bool mask -> dB over the (masked) pixels."""
    sq = (rendered - target) ** 2
    mse = float(np.mean(sq if mask is None else sq[mask]))
    return float(-10 * np.log10(max(mse, 1e-12)))


def erode(mask: np.ndarray, pixels: int) -> np.ndarray:
    """(H, W) bool -> the pixels at least ``pixels`` away from a False pixel or the border."""
    import cv2

    if pixels <= 0:
        return mask
    padded = np.pad(mask, pixels, constant_values=False).astype(np.uint8)
    kernel = np.ones((2 * pixels + 1, 2 * pixels + 1), np.uint8)
    return cv2.erode(padded, kernel)[pixels:-pixels, pixels:-pixels].astype(bool)


def ssim(rendered: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean structural similarity of (H, W, 3) colours in [0, 1] (scikit-image, 7x7 windows),
    over the pixels whose window lies inside ``mask`` (H, W) bool (all when None)."""
    from skimage.metrics import structural_similarity

    if mask is None:
        return float(structural_similarity(rendered, target, channel_axis=2, data_range=1.0))
    _, full = structural_similarity(rendered, target, channel_axis=2, data_range=1.0, full=True)
    inner = erode(mask, SSIM_WINDOW // 2)
    return float(full.mean(axis=2)[inner].mean())


def gradient_energy(rgb: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean squared Sobel gradient of the grey image of (H, W, 3) colours in [0, 1], over the
    pixels whose 3x3 stencil lies inside ``mask`` (H, W) bool (all when None)."""
    import cv2

    grey = cv2.cvtColor(rgb.astype(np.float32), cv2.COLOR_RGB2GRAY)
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3)
    energy = gx * gx + gy * gy
    return float(np.mean(energy if mask is None else energy[erode(mask, 1)]))


def sharpness(rendered: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Gradient energy of the render over the input's (1: as sharp as the input)."""
    return gradient_energy(rendered, mask) / max(gradient_energy(target, mask), 1e-12)


def observed_mask(sequence, frame) -> np.ndarray:
    """(h, w) bool for a pipeline-size ``frame`` of ``sequence``: the pixels the camera saw.
    With lens distortion (TUM fr1/fr2) those whose undistortion source lies inside the raw
    image, a pixel in from its edge (bilinear sampling mixes in the black border there),
    shrunk to the frame's size as the pipeline shrinks colour (area mean; a pixel counts
    when all of it was seen). Everything without distortion."""
    from slam.data.io import UndistortMaps, resize_mask

    intrinsics = getattr(getattr(sequence, "layout", None), "intrinsics", None)
    if intrinsics is None or not intrinsics.distortion:
        return np.ones((frame.height, frame.width), bool)
    width, height = intrinsics.image_size or (sequence[0].width, sequence[0].height)
    maps = UndistortMaps.build(intrinsics.matrix, intrinsics.distortion, width, height)
    return resize_mask(maps.observed(), frame.width, frame.height)


def score_views(pairs: list[tuple[object, object]], mask: np.ndarray | None = None) -> ViewScores:
    """``pairs`` of (RenderedView, input Frame) of the same size, ``mask`` (H, W) bool of the
    observed pixels (``observed_mask``; None: all) -> their mean scores."""
    p, p_hit, s, g, holes, l1 = [], [], [], [], [], []
    for view, frame in pairs:
        seen = np.ones(view.valid.shape, bool) if mask is None else mask
        rgb = np.clip(view.rgb, 0, 1).astype(np.float32)
        target = frame.rgb.astype(np.float32)
        p.append(psnr(rgb, target, seen))
        p_hit.append(psnr(rgb, target, seen & view.valid))
        s.append(ssim(rgb, target, seen))
        g.append(sharpness(rgb, target, seen))
        holes.append(float(1 - view.valid[seen].mean()))
        both = (frame.depth > 0) & view.valid
        if both.any():
            l1.append(float(np.abs(view.depth[both] - frame.depth[both]).mean() * 100))
    return ViewScores(float(np.mean(p)), float(np.mean(p_hit)), float(np.mean(s)), float(np.mean(g)),
                      float(np.mean(holes)), float(np.mean(l1)) if l1 else float("nan"), len(pairs))


def picture(pairs: list[tuple[object, object]], path: Path, mask: np.ndarray | None = None) -> Path:
    """Rows input | render | error (absolute colour difference x3, 0 black; black outside
    ``mask`` (H, W) bool, the observed pixels) of a few views, side by side, as a PNG."""
    import cv2

    picks = [pairs[i] for i in np.linspace(0, len(pairs) - 1, min(PICTURE_VIEWS, len(pairs))).round().astype(int)]
    columns = []
    for view, frame in picks:
        rgb = np.clip(view.rgb, 0, 1)
        error = np.clip(3 * np.abs(rgb - frame.rgb), 0, 1) * (1 if mask is None else mask[..., None])
        columns.append(np.concatenate([frame.rgb, rgb, error], axis=0))
    sheet = (np.concatenate(columns, axis=1) * 255).round().astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    return path


def without_fine(mapset):
    """``mapset`` with every submap's fine colour level dropped (the coarse map alone); the same
    objects, changed in place."""
    for submap in mapset.maps:
        submap.fine = None
    return mapset


def tracked_views(run_dir: Path, sequence, width: int = VIEW_WIDTH, views: int = VIEWS) -> list[tuple[object, np.ndarray]]:
    """(input Frame at ``width``, its tracked T_world_cam (4, 4)) of every k-th frame of
    ``run_dir``'s ``trajectory.txt`` (at most ``views``, evenly spaced over the run)."""
    from slam import read_tum
    from slam.eval.trajectory import associate

    trajectory = read_tum(run_dir / "trajectory.txt")
    estimate_idx, frame_idx = associate(trajectory.timestamps, np.asarray(sequence.timestamps, np.float64), max_dt=1e-3)
    order = np.argsort(frame_idx)
    estimate_idx, frame_idx = estimate_idx[order], frame_idx[order]
    chosen = np.linspace(0, len(frame_idx) - 1, min(views, len(frame_idx))).round().astype(int)
    out = []
    for c in chosen:
        frame = pipeline_frame(sequence[int(frame_idx[c])], width)
        assert abs(frame.timestamp - trajectory.timestamps[estimate_idx[c]]) < 1e-3, "view paired with another frame"
        out.append((frame, trajectory.poses[estimate_idx[c]]))
    return out


def training_views(run_dir: Path, sequence, width: int = VIEW_WIDTH, views: int = VIEWS, fine: bool = True):
    """(RenderedView, input Frame) pairs of ``tracked_views``, rendered from ``run_dir``'s
    ``map.pt``; ``fine`` False: without the map's fine colour level."""
    from slam import load_checkpoint
    from slam.views import render_view

    mapset = load_checkpoint(run_dir / "map.pt")
    if not fine:
        without_fine(mapset)
    return [(render_view(mapset, T, frame.K, frame.width, frame.height), frame)
            for frame, T in tracked_views(run_dir, sequence, width, views)]


def held_out_views(config, width: int = VIEW_WIDTH, fine_too: bool = False):
    """Replica room0: a map of frames 0, 2, ..., 18 at their GT poses, views of 1, 3, ..., 19.
    Returns the pairs, and with ``fine_too`` also the pairs of the same map without its fine
    colour level (else None)."""
    from common import map_with_gt_poses

    from slam.data import open_sequence
    from slam.views import render_view

    sequence = open_sequence(REPLICA / "room0")
    mapped = [pipeline_frame(sequence[i], config.runtime.input_width) for i in range(0, 20, 2)]
    mapper = map_with_gt_poses(mapped, config)
    views = [pipeline_frame(sequence[i], width) for i in range(1, 20, 2)]

    def render_all():
        return [(render_view(mapper.maps, f.T_world_cam, f.K, f.width, f.height), f) for f in views]

    pairs = render_all()
    if not fine_too:
        return pairs, None
    without_fine(mapper.maps)
    return pairs, render_all()


def scores_row(name: str, preset: str, kind: str, scores: ViewScores, picture_path: Path | None,
               seed: int = 0) -> dict:
    return {"sequence": name, "preset": preset, "kind": kind, "seed": seed, **scores.__dict__,
            "picture": str(picture_path) if picture_path else None}


def table(rows: list[dict]) -> str:
    lines = ["| sequence | preset | views | n | PSNR dB | PSNR hit dB | holes | SSIM | sharpness | depth L1 cm | picture |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r['sequence']} | {r['preset']} | {r['kind']} | {r['count']} | {r['psnr_db']:.2f} | "
                     f"{r['psnr_hit_db']:.2f} | {r['holes']:.1%} | {r['ssim']:.3f} | {r['sharpness']:.2f} | "
                     f"{r['depth_l1_cm']:.2f} | {r['picture'] or ''} |")
    return "\n".join(lines)


def run(sequence_names: list[str] | None, presets: list[str], out: Path, timeout: float,
        seeds: int = 1, reuse: Path | None = None, fine_ablation: bool = False) -> list[dict]:
    """Every sequence x preset x seed: one deterministic run (``runtime.seed`` = seed), its
    training views (and room0's held-out views); prints a line per result and returns the rows.

    ``reuse``: a ``bench_real.py`` work folder whose ``{sequence}_{name}_{seed}`` runs
    (``--variant name=... --deterministic 1``) are scored instead of running again (a run it
    lacks is skipped); ``presets`` may then name its variants (room0's held-out map takes the
    run's config).
    ``fine_ablation``: every map is also rendered without its fine colour level, a paired A/B
    of the level on the very same coarse map and trajectory (the level leaves both untouched).
    """
    from bench_real import sequences

    from slam import load_checkpoint
    from slam.data import open_sequence

    rows = []
    for seq in sequences(None):
        if sequence_names and seq.name not in sequence_names:
            continue
        sequence = open_sequence(seq.path, max_frames=seq.max_frames)
        for preset in presets:
            for seed in range(seeds):
                run_dir = _run_dir(seq, preset, seed, out, reuse, timeout)
                if run_dir is None:
                    print(f"{seq.name} {preset} seed {seed}: no run in {reuse}, skipped", flush=True)
                    continue
                tag = f"{seq.name}-{preset}-s{seed}"
                for fine in (True, False) if fine_ablation else (True,):
                    pairs = training_views(run_dir, sequence, fine=fine)
                    seen = observed_mask(sequence, pairs[0][1])
                    name = preset if fine else f"{preset} coarse only"
                    row = scores_row(seq.name, name, "training", score_views(pairs, seen),
                                     picture(pairs, out / f"{tag}{'' if fine else '-coarse'}.png", seen), seed)
                    _record(rows, row, out)
                if seq.name == "room0":
                    config = load_checkpoint(run_dir / "map.pt").config  # a reused variant's overrides too
                    config = replace(config, runtime=replace(config.runtime, seed=seed))
                    pairs, coarse = held_out_views(config, fine_too=fine_ablation)
                    for name, views in ((preset, pairs), (f"{preset} coarse only", coarse)):
                        if views is None:
                            continue
                        suffix = "" if name == preset else "-coarse"
                        row = scores_row(seq.name, name, "held-out", score_views(views),
                                         picture(views, out / f"{tag}-held-out{suffix}.png"), seed)
                        _record(rows, row, out)
    return rows


def _record(rows: list[dict], row: dict, out: Path) -> None:
    """Adds ``row``, prints it and rewrites ``out``/quality.json (a stopped run keeps its rows)."""
    rows.append(row)
    print(_line(row), flush=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "quality.json").write_text(json.dumps(rows, indent=1))


def _run_dir(seq, preset: str, seed: int, out: Path, reuse: Path | None, timeout: float) -> Path | None:
    """The run to score: with ``reuse``, its run (None when it has none: a reused folder's
    variants need not be presets, and a sequence it lacks is not run anew); else a new
    deterministic run in ``out``."""
    from bench_real import Variant, run_voxfusion

    if reuse is not None:
        found = reuse / f"{seq.name}_{preset}_{seed}"
        return found if (found / "map.pt").is_file() else None
    run_dir = out / f"{seq.name}-{preset}-s{seed}"
    run_voxfusion(seq, Variant(preset, preset), run_dir, ["--deterministic", "1"], timeout, seed=seed)
    return run_dir


def summary(rows: list[dict]) -> list[dict]:
    """Per sequence, kind and preset: mean and sample std over seeds of PSNR, SSIM, sharpness;
    with an ablation (``"<preset> coarse only"`` rows), the verdict of the decision rule for the
    preset against its coarse-only twin (higher is better): ``better`` / ``worse`` when the
    means differ by more than the larger spread (and 0.05 dB), and the paired PSNR gain."""
    import statistics

    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["sequence"], r["kind"], r["preset"]), []).append(r)

    def stats(values):
        return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else 0.0

    out = []
    for (seq, kind, preset), members in groups.items():
        row = {"sequence": seq, "kind": kind, "preset": preset, "runs": len(members)}
        for key in ("psnr_db", "ssim", "sharpness"):
            row[key], row[key + "_std"] = stats([m[key] for m in members])
        twin = groups.get((seq, kind, f"{preset} coarse only"))
        if twin:
            base, base_std = stats([m["psnr_db"] for m in twin])
            spread = max(row["psnr_db_std"], base_std, 0.05)
            gain = row["psnr_db"] - base
            row["verdict"] = "better" if gain > spread else "worse" if gain < -spread else "within spread"
            by_seed = {m["seed"]: m["psnr_db"] for m in twin}
            row["paired_gain_db"] = stats([m["psnr_db"] - by_seed[m["seed"]] for m in members if m["seed"] in by_seed])
        out.append(row)
    return out


def summary_table(rows: list[dict]) -> str:
    lines = ["| sequence | views | preset | runs | PSNR dB | SSIM | sharpness | paired gain dB | verdict |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in summary(rows):
        gain = r.get("paired_gain_db")
        lines.append(f"| {r['sequence']} | {r['kind']} | {r['preset']} | {r['runs']} | "
                     f"{r['psnr_db']:.2f} ± {r['psnr_db_std']:.2f} | {r['ssim']:.3f} ± {r['ssim_std']:.3f} | "
                     f"{r['sharpness']:.2f} ± {r['sharpness_std']:.2f} | "
                     f"{'' if gain is None else f'{gain[0]:+.2f} ± {gain[1]:.2f}'} | {r.get('verdict', '')} |")
    return "\n".join(lines)


def _line(row: dict) -> str:
    return (f"{row['sequence']} {row['preset']} seed {row['seed']} {row['kind']} views: PSNR {row['psnr_db']:.2f} dB "
            f"({row['psnr_hit_db']:.2f} where hit, {row['holes']:.1%} holes), SSIM "
            f"{row['ssim']:.3f}, sharpness {row['sharpness']:.2f}, depth L1 {row['depth_l1_cm']:.2f} cm -> "
            f"{row['picture']}")
