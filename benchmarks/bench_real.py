"""Presets and preset changes on every real sequence we have, N runs each, accuracy and speed.

    python benchmarks/bench_real.py [--runs 3] [--variant NAME=PRESET[:JSON]]... [--peer]
                                    [--sequences rpy150,desk,...] [--max-frames N]
                                    [--extra-args "--single-process"] [--json FILE] [--markdown FILE]

Each run is ``voxfusion run`` (``python -m slam.cli run``) in a child process, the way users
run it: tracking and mapping in separate processes unless ``--extra-args`` says otherwise.
Variants alternate run by run (A B A B ..., the order rotated each round), so a slow hour
hits them alike. With ``--deterministic LAG`` the runs use the deterministic mode
(``runtime.deterministic_lag``), whose trajectory does not depend on load, and run r uses
seed r: the spread is then that of the ray sampling alone. A variant is a preset and optional JSON overrides of it, e.g.
``ray=cpu:{"loss": {"normalisation": "ray"}}``, and ``+calibration`` after the preset
(``cal=cpu+calibration``) runs with the sequence's ``calibration.json`` where it has one; the
first variant is the baseline. ``--peer``
adds the classical peer (Open3D's tensor SLAM at 1 cm voxels, ``benchmarks/peer_open3d.py``)
as one more variant.

Sequences: ``../shared/data`` (TUM fr1/rpy 150 frames, fr1/desk, Replica room0, SUN3D fragment 1) and every
dataset folder in the cache ``$VOXFUSION_DATA_CACHE`` (default ``~/.cache/voxfusion/data``;
how it was filled: ``benchmarks/README.md``, "Real data"). With the whole fr1/rpy there, its
frames 150-449 and 450-722 (which no setting was tuned on) become two more sequences, made
once as folders of hard links. With the shared fr1/rpy, ``freiburg1_rpy150_misregistered``: its
150 frames with colour from "another camera" (scaled 0.90 about the centre, shifted 8 px; its
``calibration.json`` names that camera), so that colour settings are judged where colour and
depth disagree too. Benchmarks may read the cache; tests never need it.

Per sequence and variant: ATE RMSE (cm) mean, sample standard deviation, min-max; frames/s
mean, and its ratio to the baseline's and (with ``--peer``) to Open3D's in the same sitting. Per
sequence and variant other than the baseline, the verdict of ``benchmarks/README.md``'s decision
rule: ``better`` / ``worse`` when the means differ by more than the larger of the two standard
deviations (and by more than 0.05 cm), else ``within spread``; ``slower`` when its frames/s falls
below 0.95x the baseline's. Then one line per variant: whether the rule, speed included, lets it
land.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPLICA, SHARED_DATA, TUM_RPY, markdown_table  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CACHE = Path(os.environ.get("VOXFUSION_DATA_CACHE", Path.home() / ".cache" / "voxfusion" / "data"))
MIN_DIFFERENCE_CM = 0.05
"""Means closer than this are within spread whatever the spreads (a tenth of a millimetre is noise)."""
SPEED_TOLERANCE = 0.95
"""A variant whose mean frames/s falls below this ratio of the baseline's on a sequence is slower there
(benchmarks/README.md, "The rule for speed")."""


@dataclass(frozen=True)
class RealSequence:
    name: str
    path: Path
    max_frames: int | None = None
    peer_depth_max: float = 3.0


@dataclass(frozen=True)
class Variant:
    name: str
    preset: str
    overrides: dict = field(default_factory=dict)
    calibrated: bool = False
    """``voxfusion run --calibration`` with the sequence's ``calibration.json`` where it has one
    (the misregistered sequences: their colour camera)."""

    @property
    def is_peer(self) -> bool:
        return self.preset == "open3d"


@dataclass
class Run:
    sequence: str
    variant: str
    round: int
    ate_cm: float | None
    fps: float | None
    frames: int
    seconds: float
    load: str
    error: str | None = None


RUN_LINE = re.compile(r"^round (\d+) (\S+) (\S+): ATE ([\d.]+) cm, ([\d.]+) frames/s \(([\d.]+) s, load ([\d.]+)\)$")


def earlier_runs(path: Path) -> list[Run]:
    """The runs of an earlier sitting: its ``--json``, or its printed log (the lines of the
    finished runs, for a sitting that was stopped before it wrote the JSON)."""
    text = path.read_text()
    if path.suffix == ".json":
        return [Run(**r) for r in json.loads(text)["runs"]]
    found = []
    for line in text.splitlines():
        match = RUN_LINE.match(line.strip())
        if match:
            r, seq, variant, ate, fps, seconds, load = match.groups()
            found.append(Run(seq, variant, int(r), float(ate), float(fps), 0, float(seconds), load))
    return found


def sequences(max_frames: int | None) -> list[RealSequence]:
    """The shared sequences, then every dataset folder of the cache (name order)."""
    found = []
    shared = [("rpy150", TUM_RPY, 150), ("desk", SHARED_DATA / "rgbd_dataset_freiburg1_desk", None),
              ("room0", REPLICA / "room0", None), ("sun3d", SHARED_DATA / "sun3d_fragment1", None)]
    for name, path, frames in shared:
        if path.is_dir():
            found.append(RealSequence(name, path, frames if max_frames is None else min(frames or max_frames,
                                                                                         max_frames)))
    full_rpy = CACHE / "rgbd_dataset_freiburg1_rpy_full"
    if (full_rpy / "rgb.txt").is_file():
        # Frames 0-149 are the shared fr1/rpy the presets were tuned on; the rest is unseen.
        make_window(full_rpy, 150, 450, "rgbd_dataset_freiburg1_rpy_150-449")
        make_window(full_rpy, 450, 723, "rgbd_dataset_freiburg1_rpy_450-722")
    if TUM_RPY.is_dir():
        # Colour from "another camera": what a two-camera sensor gives when nobody registers it.
        make_misregistered(TUM_RPY, 150, MISREGISTERED_SCALE, MISREGISTERED_SHIFT_PX,
                           "rgbd_dataset_freiburg1_rpy150_misregistered")
    if CACHE.is_dir():
        for path in sorted(p for p in CACHE.iterdir() if p.is_dir() and not p.name.endswith(".tmp")):
            if (path / "rgb.txt").is_file() or (path / "results").is_dir():
                found.append(RealSequence(path.name.removeprefix("rgbd_dataset_"), path, max_frames))
    return found


def make_window(source: Path, start: int, stop: int, name: str) -> Path:
    """A TUM folder in the cache holding frames [start, stop) of ``source`` (hard links to its
    images, the lists cut to the window, the whole ground truth): a stretch of a long sequence
    that nothing was tuned on, as its own sequence. Made once; returns its folder."""
    dest = CACHE / name
    if (dest / "rgb.txt").is_file():
        return dest
    from slam.data.tum import MAX_TIME_DIFFERENCE, associate, read_tum_list

    rgb = read_tum_list(source / "rgb.txt", columns=1)
    depth = read_tum_list(source / "depth.txt", columns=1)
    pairs = associate([t for t, _ in rgb], [t for t, _ in depth], MAX_TIME_DIFFERENCE)[start:stop]
    tmp = dest.with_name(dest.name + ".tmp")
    for folder in ("rgb", "depth"):
        (tmp / folder).mkdir(parents=True, exist_ok=True)
    lines = {"rgb": [], "depth": []}
    for i, j in pairs:
        for kind, (stamp, fields) in (("rgb", rgb[i]), ("depth", depth[j])):
            target = tmp / fields[0]
            if not target.exists():
                os.link(source / fields[0], target)
            lines[kind].append(f"{stamp:.6f} {fields[0]}\n")
    for kind, rows in lines.items():
        (tmp / f"{kind}.txt").write_text("".join(rows))
    (tmp / "groundtruth.txt").write_bytes((source / "groundtruth.txt").read_bytes())
    tmp.rename(dest)
    return dest


MISREGISTERED_SCALE = 0.90
MISREGISTERED_SHIFT_PX = (8.0, 0.0)
"""The misregistered variant's colour: scaled about the image centre, then shifted (x, y), as
a colour camera with a 10 % shorter focal length, its principal point 8 px off, would see it."""


def misregistered_colour_camera(K: np.ndarray, width: int, height: int, scale: float,
                                shift: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(2, 3) affine warp of a raw colour image and the colour camera's (3, 3) K that sees the
    warped image: ``u' = scale (u - centre) + centre + shift``, so K' = scale K with its
    principal point moved the same way (the lens distortion stays the raw camera's)."""
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    offset = (1.0 - scale) * centre + np.asarray(shift, np.float64)
    warp = np.array([[scale, 0.0, offset[0]], [0.0, scale, offset[1]]])
    K_color = np.array(K, np.float64, copy=True)
    K_color[:2, :2] *= scale
    K_color[:2, 2] = scale * K_color[:2, 2] + offset
    return warp, K_color


def make_misregistered(source: Path, frames: int, scale: float, shift: tuple[float, float], name: str) -> Path:
    """A TUM folder in the cache holding the first ``frames`` frames of ``source`` with every
    colour image warped by ``misregistered_colour_camera`` (depth hard-linked, ground truth
    copied) and ``calibration.json`` naming the colour camera that would see it (for
    ``voxfusion run --calibration``). Made once; returns its folder."""
    import cv2

    from slam.data.tum import MAX_TIME_DIFFERENCE, associate, read_tum_list, tum_layout

    dest = CACHE / name
    if (dest / "rgb.txt").is_file():
        return dest
    rgb = read_tum_list(source / "rgb.txt", columns=1)
    depth = read_tum_list(source / "depth.txt", columns=1)
    pairs = associate([t for t, _ in rgb], [t for t, _ in depth], MAX_TIME_DIFFERENCE)[:frames]
    intrinsics = tum_layout(source).intrinsics
    tmp = dest.with_name(dest.name + ".tmp")
    for folder in ("rgb", "depth"):
        (tmp / folder).mkdir(parents=True, exist_ok=True)
    lines = {"rgb": [], "depth": []}
    warp = K_color = None
    for i, j in pairs:
        (t_rgb, (rgb_name,)), (t_depth, (depth_name,)) = rgb[i], depth[j]
        image = cv2.imread(str(source / rgb_name), cv2.IMREAD_UNCHANGED)
        height, width = image.shape[:2]
        if warp is None:
            warp, K_color = misregistered_colour_camera(intrinsics.matrix, width, height, scale, shift)
        # Reflected at the border: a colour camera with a wider view sees real colour there,
        # not a black frame whose straight edges no real sensor has.
        cv2.imwrite(str(tmp / rgb_name), cv2.warpAffine(image, warp, (width, height), flags=cv2.INTER_LINEAR,
                                                        borderMode=cv2.BORDER_REFLECT_101))
        target = tmp / depth_name
        if not target.exists():
            os.link(source / depth_name, target)
        lines["rgb"].append(f"{t_rgb:.6f} {rgb_name}\n")
        lines["depth"].append(f"{t_depth:.6f} {depth_name}\n")
    for kind, rows in lines.items():
        (tmp / f"{kind}.txt").write_text("".join(rows))
    (tmp / "groundtruth.txt").write_bytes((source / "groundtruth.txt").read_bytes())
    calibration = {"color_intrinsics": [K_color[0, 0], K_color[1, 1], K_color[0, 2], K_color[1, 2], width, height,
                                        *intrinsics.distortion],
                   "T_color_depth": np.eye(4).tolist()}
    (tmp / "calibration.json").write_text(json.dumps(calibration, indent=1))
    tmp.rename(dest)
    return dest


def parse_variant(text: str) -> Variant:
    """``NAME=PRESET[+calibration][:JSON]`` -> Variant (``+calibration``: ``Variant.calibrated``)."""
    name, sep, rest = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"variant {text!r}: expected NAME=PRESET[+calibration][:JSON]")
    preset, _, overrides = rest.partition(":")
    preset, plus, flag = preset.partition("+")
    if plus and flag != "calibration":
        raise argparse.ArgumentTypeError(f"variant {name}: after '+' only 'calibration', got {flag!r}")
    try:
        parsed = json.loads(overrides) if overrides else {}
    except json.JSONDecodeError as error:
        raise argparse.ArgumentTypeError(f"variant {name}: overrides are not JSON ({error})") from None
    return Variant(name, preset, parsed, calibrated=bool(plus))


def run_voxfusion(seq: RealSequence, variant: Variant, out: Path, extra: list[str], timeout: float,
                  seed: int | None = None) -> dict:
    """One ``voxfusion run``; returns run.json. ``seed`` replaces ``runtime.seed``."""
    out.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "slam.cli", "run", str(seq.path), "--out", str(out), "--preset", variant.preset,
               "--quiet", *extra]
    if seq.max_frames:
        command += ["--max-frames", str(seq.max_frames)]
    if variant.calibrated and (seq.path / "calibration.json").is_file():
        command += ["--calibration", str(seq.path / "calibration.json")]
    overrides = json.loads(json.dumps(variant.overrides))
    if seed is not None:
        overrides.setdefault("runtime", {})["seed"] = seed
    if overrides:
        (out / "overrides.json").write_text(json.dumps(overrides))
        command += ["--config", str(out / "overrides.json")]
    completed = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=timeout)
    if completed.returncode != 0 or not (out / "run.json").is_file():
        tail = " | ".join((completed.stdout + completed.stderr).strip().splitlines()[-4:])
        raise RuntimeError(f"exit {completed.returncode}: {tail}")
    return json.loads((out / "run.json").read_text())


def run_peer(seq: RealSequence, out: Path, timeout: float) -> dict:
    """Open3D's tensor SLAM at 1 cm voxels through bench_slam.py's worker; ATE against GT."""
    from slam.eval import ate, read_trajectory

    command = [sys.executable, "benchmarks/bench_slam.py", "--worker", "open3d-1cm", "--source", str(seq.path),
               "--max-frames", str(seq.max_frames or 100_000), "--out", str(out), "--depth-max",
               str(seq.peer_depth_max)]
    completed = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=timeout)
    if completed.returncode != 0 or not (out / "result.json").is_file():
        tail = " | ".join((completed.stdout + completed.stderr).strip().splitlines()[-4:])
        raise RuntimeError(f"exit {completed.returncode}: {tail}")
    info = json.loads((out / "result.json").read_text())
    gt = ground_truth(seq)
    info["ate_rmse_m"] = ate(gt, read_trajectory(out / "trajectory.txt")).rmse
    return info


def ground_truth(seq: RealSequence):
    """The sequence's ground truth as a Trajectory (frames with a GT pose)."""
    import numpy as np

    from slam.data import open_sequence
    from slam.eval import Trajectory

    sequence = open_sequence(seq.path, max_frames=seq.max_frames)
    pairs = [(t, T) for t, T in zip(sequence.timestamps, sequence.gt_poses) if T is not None]
    return Trajectory(np.array([t for t, _ in pairs]), np.stack([T for _, T in pairs]))


def summary(runs: list[Run], variants: list[Variant]) -> list[dict]:
    """Per sequence and variant: mean / std / min / max ATE, mean fps, verdict against the baseline."""
    rows = []
    for seq in dict.fromkeys(r.sequence for r in runs):
        stats = {}
        for variant in variants:
            ates = [r.ate_cm for r in runs if r.sequence == seq and r.variant == variant.name and r.ate_cm is not None]
            fps = [r.fps for r in runs if r.sequence == seq and r.variant == variant.name and r.fps is not None]
            failed = sum(1 for r in runs if r.sequence == seq and r.variant == variant.name and r.error)
            stats[variant.name] = {
                "sequence": seq, "variant": variant.name, "runs": len(ates), "failed": failed,
                "ate_mean": statistics.fmean(ates) if ates else None,
                "ate_std": statistics.stdev(ates) if len(ates) > 1 else 0.0,
                "ate_min": min(ates) if ates else None, "ate_max": max(ates) if ates else None,
                "fps_mean": statistics.fmean(fps) if fps else None}
        base = stats[variants[0].name]
        peer = next((stats[v.name] for v in variants if v.is_peer), None)
        for variant in variants:
            row = stats[variant.name]
            row["verdict"] = "baseline" if variant is variants[0] else verdict(base, row)
            row["fps_ratio"] = fps_ratio(row, base)
            row["fps_vs_peer"] = fps_ratio(row, peer) if peer is not None and not variant.is_peer else None
            row["speed"] = "baseline" if variant is variants[0] else speed_verdict(row["fps_ratio"])
            rows.append(row)
    return rows


def fps_ratio(row: dict, reference: dict | None) -> float | None:
    """``row``'s mean frames/s over ``reference``'s (None when either has none)."""
    if reference is None or not row["fps_mean"] or not reference["fps_mean"]:
        return None
    return row["fps_mean"] / reference["fps_mean"]


def speed_verdict(ratio: float | None) -> str:
    """``slower`` below SPEED_TOLERANCE of the baseline's frames/s, else ``as fast``."""
    if ratio is None:
        return "no data"
    return "slower" if ratio < SPEED_TOLERANCE else "as fast"


def lands(rows: list[dict], variant: str) -> tuple[bool, str]:
    """benchmarks/README.md's rule for ``variant`` over every sequence: no sequence worse beyond
    spread, one better; and no sequence slower (below SPEED_TOLERANCE) unless the accuracy it buys
    pays for it: better beyond spread on that very sequence, by at least as many per cent of ATE
    as the per cent of frames/s it costs there. Returns (lands, why)."""
    mine = [r for r in rows if r["variant"] == variant]
    if not mine or any(r["verdict"] == "no data" for r in mine):
        return False, "not every sequence has data"
    worse = [r["sequence"] for r in mine if r["verdict"] == "worse"]
    if worse:
        return False, f"worse beyond spread on {', '.join(worse)}"
    if not any(r["verdict"] == "better" for r in mine):
        return False, "better beyond spread on no sequence"
    base = {r["sequence"]: r for r in rows if r["verdict"] == "baseline"}
    for r in mine:
        if r["speed"] != "slower":
            continue
        cost = 1.0 - r["fps_ratio"]
        gain = 1.0 - r["ate_mean"] / base[r["sequence"]]["ate_mean"]
        if r["verdict"] != "better" or gain < cost:
            return False, (f"{r['sequence']}: {100 * cost:.0f} % slower for {100 * gain:.0f} % of ATE "
                           f"({r['verdict']})")
    return True, "no sequence worse or slower beyond what it gains, one better"


SPEED_GAIN = 1.05
"""A change made for speed must be at least this much faster (geometric mean of its frames/s
ratios over the sequences) to land (benchmarks/README.md, "The rule for speed")."""


def lands_for_speed(rows: list[dict], variant: str) -> tuple[bool, str]:
    """benchmarks/README.md's rule for a change made for speed: no sequence worse beyond
    spread, none slower (below SPEED_TOLERANCE), and frames/s at least SPEED_GAIN x the
    baseline's over the sequences (geometric mean). Returns (lands, why)."""
    mine = [r for r in rows if r["variant"] == variant]
    if not mine or any(r["verdict"] == "no data" or r.get("fps_ratio") is None for r in mine):
        return False, "not every sequence has data"
    worse = [r["sequence"] for r in mine if r["verdict"] == "worse"]
    if worse:
        return False, f"worse beyond spread on {', '.join(worse)}"
    slower = [f"{r['sequence']} ({r['fps_ratio']:.2f}x)" for r in mine if r["speed"] == "slower"]
    if slower:
        return False, f"slower on {', '.join(slower)}"
    gain = float(statistics.geometric_mean([r["fps_ratio"] for r in mine]))
    if gain < SPEED_GAIN:
        return False, f"{gain:.2f}x the frames/s over the sequences (needs {SPEED_GAIN:.2f}x)"
    return True, f"no sequence worse or slower, {gain:.2f}x the frames/s over the sequences"


def verdict(base: dict, other: dict) -> str:
    """The decision rule of benchmarks/README.md ("Real data") for lower-is-better ATE."""
    if base["ate_mean"] is None or other["ate_mean"] is None:
        return "no data"
    difference = other["ate_mean"] - base["ate_mean"]
    spread = max(base["ate_std"], other["ate_std"], MIN_DIFFERENCE_CM)
    if difference < -spread:
        return "better"
    if difference > spread:
        return "worse"
    return "within spread"


def table(rows: list[dict]) -> str:
    def number(value, digits=2):
        return "-" if value is None else f"{value:.{digits}f}"

    def ratio(value):
        return "-" if value is None else f"{value:.2f}x"

    return markdown_table(
        ["sequence", "variant", "runs", "ATE cm mean", "std", "min-max", "frames/s", "vs baseline", "vs Open3D",
         "verdict", "speed"],
        [[r["sequence"], r["variant"], f"{r['runs']}" + (f" ({r['failed']} failed)" if r["failed"] else ""),
          number(r["ate_mean"]), number(r["ate_std"]), f"{number(r['ate_min'])}-{number(r['ate_max'])}",
          number(r["fps_mean"]), ratio(r.get("fps_ratio")), ratio(r.get("fps_vs_peer")), r["verdict"],
          r.get("speed", "-")] for r in rows])


def rule_lines(rows: list[dict], variants: list[Variant]) -> list[str]:
    """One line per variant but the baseline and the peer: whether the rule lets it land."""
    lines = []
    for variant in variants[1:]:
        if not variant.is_peer:
            ok, why = lands(rows, variant.name)
            fast, fast_why = lands_for_speed(rows, variant.name)
            if ok:
                lines.append(f"{variant.name}: lands for accuracy ({why})")
            elif fast:
                lines.append(f"{variant.name}: lands for speed ({fast_why})")
            else:
                lines.append(f"{variant.name}: does not land (for accuracy: {why}; for speed: {fast_why})")
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--variant", type=parse_variant, action="append", default=None,
                        help="NAME=PRESET[:JSON overrides]; the first is the baseline (default: cpu=cpu)")
    parser.add_argument("--peer", action="store_true", help="add Open3D at 1 cm voxels as a variant")
    parser.add_argument("--sequences", default=None, help="comma-separated names (default: all found)")
    parser.add_argument("--max-frames", type=int, default=None, help="cap every sequence at N frames")
    parser.add_argument("--extra-args", default="", help="more arguments for 'voxfusion run'")
    parser.add_argument("--deterministic", type=int, default=None, metavar="LAG",
                        help="runs in deterministic mode (runtime.deterministic_lag = LAG): the same run gives "
                             "the same trajectory on any load, so run r uses runtime.seed = r and the spread is "
                             "the sampling's, not the machine's")
    parser.add_argument("--first-round", type=int, default=0,
                        help="number the rounds from here (with --deterministic, round r runs seed r): more "
                             "seeds for a sitting whose first rounds are in another --json")
    parser.add_argument("--merge", type=Path, action="append", default=[],
                        help="add the runs of an earlier sitting (its --json or its log) to the summary")
    parser.add_argument("--timeout", type=float, default=3600.0)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--markdown", type=Path, default=None)
    args = parser.parse_args()
    variants = args.variant or [Variant("cpu", "cpu")]
    if args.peer:
        variants.append(Variant("open3d-1cm", "open3d"))
    seqs = sequences(args.max_frames)
    if args.sequences:
        wanted = args.sequences.split(",")
        seqs = [s for s in seqs if s.name in wanted]
    if not seqs:
        print("no real sequences found", file=sys.stderr)
        return 2
    extra = shlex.split(args.extra_args)
    if args.deterministic is not None:
        extra += ["--deterministic", str(args.deterministic)]
    work = Path(tempfile.mkdtemp(prefix="bench-real-"))
    listed = ", ".join(f"{s.name} ({s.max_frames or 'all'} frames)" for s in seqs)
    print(f"sequences: {listed}; "
          f"variants: {', '.join(v.name for v in variants)}; {args.runs} runs; work in {work}", flush=True)
    runs: list[Run] = [run for path in args.merge for run in earlier_runs(path)]
    for round_ in range(args.first_round, args.first_round + args.runs):
        for seq in seqs:
            order = variants[round_ % len(variants):] + variants[:round_ % len(variants)]
            for variant in order:
                out = work / f"{seq.name}_{variant.name}_{round_}"
                load, started = f"{os.getloadavg()[0]:.1f}", time.perf_counter()
                try:
                    info = run_peer(seq, out, args.timeout) if variant.is_peer else \
                        run_voxfusion(seq, variant, out, extra, args.timeout,
                                      seed=round_ if args.deterministic is not None else None)
                    ate = info.get("ate_rmse_m")
                    run = Run(seq.name, variant.name, round_, None if ate is None else ate * 100, info.get("fps"),
                              int(info.get("frames", 0)), round(time.perf_counter() - started, 1), load)
                except (RuntimeError, subprocess.TimeoutExpired) as error:
                    run = Run(seq.name, variant.name, round_, None, None, 0, round(time.perf_counter() - started, 1),
                              load, error=str(error)[:400])
                runs.append(run)
                ate = "no ATE (no ground truth?)" if run.ate_cm is None else f"ATE {run.ate_cm:.2f} cm"
                shown = "failed: " + run.error if run.error else f"{ate}, {run.fps or 0:.2f} frames/s"
                print(f"round {round_} {seq.name} {variant.name}: {shown} ({run.seconds} s, load {load})", flush=True)
    # A round run twice (merged sittings) counts once: the later run stands (deterministic
    # runs of one seed repeat exactly, so the spread would shrink for nothing).
    runs = list({(r.sequence, r.variant, r.round): r for r in runs}.values())
    rows = summary(runs, variants)
    print("\n" + table(rows))
    for line in rule_lines(rows, variants):
        print(line)
    if args.json:
        args.json.write_text(json.dumps({"runs": [asdict(r) for r in runs], "summary": rows,
                                         "variants": [asdict(v) for v in variants]}, indent=1))
    if args.markdown:
        args.markdown.write_text(table(rows) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
