"""Place recognition: the appearance check of loop detection (``slam.loop.database``).

On sequences with ground truth, keyframes are every ``--stride``-th frame (5). Each keyframe
queries a ``KeyframeDatabase`` of the keyframes before it, with candidates at least ``--gap``
frames older (30), and is then added, as the loop closer does. A candidate is a **true
match** when the two GT camera centres are < 1 m apart and the viewing directions < 30 deg.
Per sequence and descriptor:

* **P@1**: of the queries whose top-1 candidate passes the database's threshold, the share
  whose top-1 is a true match (the precision of what goes on to geometric verification);
* **R**: of the queries that have a true match among their candidates, the share whose top-1
  passes and is true (recall at the threshold rule);
* **R@5**: of those, the share whose top-5 (no threshold) holds a true match;
* **top-1**: top-1 accuracy with no threshold;
* **rev. R / P@1**: the same on *revisits*: candidates at least ``--revisit-gap`` (150) frames
  older, which on a lap is the return to its start;
* **ms/describe** (the descriptor alone; ORB detection, which the loop closer needs for the
  geometric verification anyway, is given per sequence) and **ms/query**
  (``KeyframeDatabase.query`` against all the sequence's keyframes): wall time, the best of
  3 passes over every keyframe.

On the ``laps`` hall (four identical cabinet sets, two in the south corridor, two in the
north), **conf.** counts top-1 candidates that are false and show a *different* copy of the
repeated furniture than the query (each sees >= 3 % of its pixels on a copy); in brackets,
how many of those passed the threshold.

Descriptors: the library's ``orb-bow+thumbnail`` (default), ``orb-bow`` and ``thumbnail``;
benchmark-only candidates: ``orb-bow+idf`` (the words with an idf learnt online from the
keyframes before the query), ``thumbnail-grey`` (16 x 12 grey) and ``orb-vlad`` (VLAD over
ORB, 32 centres by k-majority on the run's first 10 keyframes). ``--sweep`` also compares
threshold rules for the default descriptor, pooled over the sequences.

    python benchmarks/bench_place_recognition.py [--quick] [--sweep] [--json FILE]

About 3 minutes on two cores (``--quick``: loop, orbit and fr1/rpy, half a minute).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import TUM_RPY, markdown_table, write_json  # noqa: E402

from slam.features import FrameFeatures, detect_features  # noqa: E402
from slam.loop.database import (  # noqa: E402
    BinaryWordsDescriptor, KeyframeDatabase, KeyframeEntry, ThumbnailDescriptor, make_descriptor)

SEQUENCES = {
    "loop": "synthetic:loop?frames=500&width=320&height=240&noise=1",
    "orbit": "synthetic:orbit?frames=200",
    "fr1/rpy": str(TUM_RPY),
    "room-2laps": "room-2laps",
    "laps": "synthetic:laps?frames=2200&noise=1&size=large",
}
"""``room-2laps`` is built here: synthetic:loop (seed 0, 500 frames, noise) and then the same
lap again 15 % wider and 8 cm higher, aimed at the same points, so the second lap revisits the
first from shifted viewpoints."""
QUICK = ("loop", "orbit", "fr1/rpy")
MAX_DIST_M, MAX_ANGLE_DEG = 1.0, 30.0
ORB_COUNT, MAX_DEPTH = 1000, 10.0  # as slam.loop.closing detects keyframe features
REPEAT_MIN_SHARE = 0.03


# ----------------------------------------------------------------------------- sequences
def _room_two_laps():
    from slam.data.synthetic import (DepthNoiseModel, SyntheticSequence, default_intrinsics, look_at,
                                     make_scene, make_trajectory)

    T1 = make_trajectory("loop", 500, 0)
    p2 = T1[:, :3, 3] * np.array([1.15, 1.15, 1.0]) + np.array([0.0, 0.0, 0.08])
    T2 = look_at(p2, T1[:, :3, 3] + 1.5 * T1[:, :3, 2])
    return SyntheticSequence(make_scene("room", 0), np.concatenate([T1, T2]), default_intrinsics(320, 240), 320, 240,
                             name="room-2laps", noise=DepthNoiseModel(), seed=0)


def open_bench_sequence(name: str):
    from slam.data import open_sequence

    spec = SEQUENCES[name]
    if spec == "room-2laps":
        return _room_two_laps()
    if spec.startswith("synthetic:laps"):
        from slam.data.synthetic import TRAJECTORY_KINDS
        if "laps" not in TRAJECTORY_KINDS:
            return None
    elif not spec.startswith("synthetic:") and not Path(spec).exists():
        return None
    return open_sequence(spec, "auto")


@dataclass
class Keyframes:
    frames: list
    features: list
    feature_ms: float
    repeats: list | None  # per keyframe: the set of repeated-furniture copies it shows (laps only)


def load_keyframes(sequence, stride: int) -> Keyframes:
    import cv2

    orb = cv2.ORB_create(ORB_COUNT)
    frames, features, t = [], [], 0.0
    for i in range(0, len(sequence), stride):
        f = sequence[i]
        t0 = time.perf_counter()
        features.append(detect_features(f, ORB_COUNT, MAX_DEPTH, orb))
        t += time.perf_counter() - t0
        frames.append(f)
    repeats = None
    scene = getattr(sequence, "scene", None)
    if scene is not None and any(k.startswith("repeat_") for k, _ in scene.groups):
        from slam.data.synthetic import rasterise_view

        groups = [(k, np.array(ids)) for k, ids in scene.groups if k.startswith("repeat_")]
        repeats = []
        for f in frames:
            surface = rasterise_view(scene, sequence.K, f.T_world_cam, sequence.width, sequence.height).surface
            repeats.append({k for k, ids in groups if np.isin(surface, ids).mean() >= REPEAT_MIN_SHARE})
    return Keyframes(frames, features, t / len(frames) * 1e3, repeats)


def truth_matrix(frames) -> np.ndarray:
    P = np.stack([f.T_world_cam[:3, 3] for f in frames])
    Z = np.stack([f.T_world_cam[:3, 2] for f in frames])
    dist = np.linalg.norm(P[:, None] - P[None], axis=-1)
    return (dist < MAX_DIST_M) & (Z @ Z.T > np.cos(np.radians(MAX_ANGLE_DEG)))


# ---------------------------------------------------------------------------- descriptors
def _hamming_argmin(bits: np.ndarray, centres: np.ndarray) -> np.ndarray:
    d = bits.astype(np.int32) @ (1 - 2 * centres.astype(np.int32)).T + centres.sum(1)
    return d.argmin(1)


class OrbVLAD:
    """VLAD over ORB: k centres by k-majority on the first keyframes' descriptors; per centre the
    summed bit residuals, signed sqrt, L2-normalised. Benchmark-only candidate."""

    name = "orb-vlad"

    def __init__(self, train: list[FrameFeatures], k: int = 32, iterations: int = 10, seed: int = 0):
        bits = np.concatenate([np.unpackbits(f.descriptors, axis=1) for f in train if len(f.descriptors)])
        rng = np.random.default_rng(seed)
        centres = bits[rng.choice(len(bits), k, replace=False)].copy()
        for _ in range(iterations):
            a = _hamming_argmin(bits, centres)
            for j in range(k):
                if (a == j).any():
                    centres[j] = bits[a == j].mean(0) > 0.5
        self.centres = centres

    def describe(self, frame, features: FrameFeatures) -> np.ndarray:
        v = np.zeros(self.centres.shape, np.float64)
        if len(features.descriptors):
            bits = np.unpackbits(features.descriptors, axis=1)
            a = _hamming_argmin(bits, self.centres)
            np.add.at(v, a, bits.astype(np.float64) - self.centres[a])
        v = (np.sign(v) * np.sqrt(np.abs(v))).ravel()
        n = np.linalg.norm(v)
        return (v / n if n > 0 else v).astype(np.float32)


def descriptors_for(names: list[str], kf: Keyframes) -> dict:
    out = {}
    for name in names:
        if name in ("orb-bow+thumbnail", "orb-bow", "thumbnail"):
            out[name] = make_descriptor(name)
        elif name == "orb-bow+idf":
            out[name] = BinaryWordsDescriptor(name="orb-bow+idf")
        elif name == "thumbnail-grey":
            out[name] = ThumbnailDescriptor(16, 12, colour=False, name="thumbnail-grey")
        elif name == "orb-vlad":
            out[name] = OrbVLAD(kf.features[:10])
    return out


# ----------------------------------------------------------------------------- evaluation
@dataclass
class Queries:
    """Every query of one run (a keyframe with at least one eligible candidate), as arrays."""

    q: np.ndarray           # (R,) keyframe index of the query
    top: np.ndarray         # (R, 5) keyframe indices of the top-5 eligible, best first (-1: fewer)
    top_sim: np.ndarray     # (R,) similarity of the top-1
    has_match: np.ndarray   # (R,) a true match is among the eligible
    ok: np.ndarray          # (R, 5) each of the top-5 is a true match
    refs: np.ndarray        # (R, 3) similarities to the latest 3 keyframes, most recent first (NaN: none)
    db_passed: np.ndarray   # (R,) the database's own verdict on the top-1 (its default rule)


def idf_similarities(X: np.ndarray, q: int) -> np.ndarray:
    """(q,) similarities of keyframe q to keyframes 0..q-1, terms weighted by log(N / df) of the
    keyframes before q (the online idf)."""
    if q == 0:
        return np.zeros(0)
    df = (X[:q] > 0).sum(0)
    w = np.log((q + 1) / (df + 1)) + 1e-3
    Y = X[: q + 1] * w
    Y /= np.maximum(np.linalg.norm(Y, axis=1, keepdims=True), 1e-12)
    return Y[:q] @ Y[q]


def run_descriptor(desc, kf: Keyframes, truth: np.ndarray, gap: int, idf: bool = False,
                   timed: bool = False) -> tuple[Queries, float, float]:
    """Describe every keyframe, then query and add them in order. Returns the queries and,
    when ``timed``, ms per describe and per ``KeyframeDatabase.query`` of the full database
    (each the best of 3 passes over all keyframes: a shared machine's scheduler otherwise
    decides much of a sub-ms call's wall time); NaN otherwise."""
    X = np.stack([desc.describe(f, ft) for f, ft in zip(kf.frames, kf.features)]).astype(np.float32)
    describe_ms = query_ms = float("nan")
    if timed:
        passes = []
        for _ in range(3):
            t0 = time.perf_counter()
            for f, ft in zip(kf.frames, kf.features):
                desc.describe(f, ft)
            passes.append((time.perf_counter() - t0) / len(X) * 1e3)
        describe_ms = min(passes)
    idx = np.array([f.index for f in kf.frames])
    pos = {int(e): i for i, e in enumerate(idx)}
    db = KeyframeDatabase()
    rows = []
    for q, (f, ft) in enumerate(zip(kf.frames, kf.features)):
        cands = db.query(X[q], map_id=0, agent=0, frame_index=int(idx[q]), top_k=5, min_frame_gap=gap)
        sims = idf_similarities(X, q) if idf else db.similarities(X[q])
        db.add(KeyframeEntry(0, 0, int(idx[q]), f.timestamp, X[q], ft))
        eligible = np.flatnonzero(idx[:q] <= idx[q] - gap)
        if len(eligible) == 0:
            continue
        if idf:  # rank by the idf-weighted similarities
            top = eligible[np.argsort(-sims[eligible], kind="stable")[:5]]
        else:
            top = np.array([pos[c.entry.frame_index] for c in cands])
        refs = np.full(3, np.nan)
        latest = sims[max(0, q - 3):q][::-1]
        refs[:len(latest)] = latest
        top5 = np.full(5, -1)
        top5[:len(top)] = top
        rows.append((q, top5, sims[top[0]], truth[q, eligible].any(), np.where(top5 >= 0, truth[q, top5], False),
                     refs, cands[0].passed if not idf else False))
    if timed:
        passes = []
        for _ in range(3):
            t0 = time.perf_counter()
            for q in range(len(X)):
                db.query(X[q], map_id=0, agent=0, frame_index=int(idx[-1]) + 1, top_k=5, min_frame_gap=gap)
            passes.append((time.perf_counter() - t0) / len(X) * 1e3)
        query_ms = min(passes)
    if not rows:
        queries = Queries(np.zeros(0, int), np.zeros((0, 5), int), np.zeros(0), np.zeros(0, bool),
                          np.zeros((0, 5), bool), np.zeros((0, 3)), np.zeros(0, bool))
    else:
        queries = Queries(*(np.array(c) for c in zip(*rows)))
    return queries, describe_ms, query_ms


RULES = {"fixed": (0, None), "latest": (1, np.nanmax), "min of 2": (2, np.nanmin), "min of 3": (3, np.nanmin),
         "median of 3": (3, np.nanmedian), "mean of 3": (3, np.nanmean), "max of 3": (3, np.nanmax)}
"""s_ref rules: (how many of the latest keyframes, how they are reduced)."""


def passed(Q: Queries, rule: str, ratio: float, floor: float) -> np.ndarray:
    """(R,) whether each top-1 passes ``max(floor, ratio * s_ref)`` (``floor`` without s_ref)."""
    n, reduce = RULES[rule]
    if n == 0 or len(Q.q) == 0:
        return Q.top_sim > floor
    refs = Q.refs[:, :n]
    none = np.isnan(refs).all(1)
    with np.errstate(all="ignore"):
        s_ref = np.where(none, 0.0, reduce(np.where(none[:, None], 0.0, refs), axis=1))
    return Q.top_sim > np.maximum(floor, ratio * s_ref)


def pooled(runs: list[Queries], rule: str, ratio: float, floor: float) -> tuple[float, float]:
    """Pooled (precision, recall) of the thresholded top-1 over runs."""
    acc = ok = has = 0
    for Q in runs:
        p = passed(Q, rule, ratio, floor)
        acc, ok, has = acc + p.sum(), ok + (p & Q.ok[:, 0]).sum(), has + Q.has_match.sum()
    return (ok / acc if acc else float("nan")), (ok / has if has else float("nan"))


def calibrate(runs: list[Queries], revisits: list[Queries], rule: str, min_precision: float,
              min_revisit_precision: float):
    """(ratio, floor, P, R, rev. P, rev. R) of the rule's parameters with pooled precision >=
    ``min_precision`` on all queries and >= ``min_revisit_precision`` on revisits (where false
    loops come from) that recall the most revisits, then the most of all queries; or None."""
    best = None
    for ratio in ([0.0] if RULES[rule][0] == 0 else np.round(np.arange(0.3, 1.21, 0.05), 2)):
        for floor in np.round(np.arange(0.0, 0.9, 0.01), 2):
            pa, ra = pooled(runs, rule, ratio, floor)
            pb, rb = pooled(revisits, rule, ratio, floor)
            if pa >= min_precision and (np.isnan(pb) or pb >= min_revisit_precision):
                score = (0.0 if np.isnan(rb) else round(rb, 6), round(ra, 6))
                if best is None or score > best[0]:
                    best = (score, float(ratio), float(floor), pa, ra, pb, rb)
    return None if best is None else best[1:]


def metrics(Q: Queries, ok_passed: np.ndarray, repeats: list | None) -> dict:
    """P@1, R, R@5, top-1 (see the module docstring) and the repeated-furniture confusions."""
    has = Q.has_match
    nan = float("nan")
    out = {
        "queries": int(len(Q.q)), "with_match": int(has.sum()), "accepted": int(ok_passed.sum()),
        "p_at_1": float(Q.ok[ok_passed, 0].mean()) if ok_passed.any() else nan,
        "recall": float((ok_passed & Q.ok[:, 0])[has].mean()) if has.any() else nan,
        "recall_at_5": float(Q.ok[has].any(1).mean()) if has.any() else nan,
        "top1": float(Q.ok[has, 0].mean()) if has.any() else nan,
    }
    if repeats is not None:
        conf = [i for i in range(len(Q.q)) if not Q.ok[i, 0] and repeats[Q.q[i]] and repeats[Q.top[i, 0]]
                and not repeats[Q.q[i]] & repeats[Q.top[i, 0]]]
        out["confusions"] = len(conf)
        out["confusions_passed"] = int(sum(ok_passed[i] for i in conf))
    return out


def fmt(x: float, digits: int = 2) -> str:
    return "n/a" if x is None or (isinstance(x, float) and np.isnan(x)) else f"{x:.{digits}f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK)}")
    ap.add_argument("--sequences", nargs="*", default=None, help=f"names among {', '.join(SEQUENCES)}")
    ap.add_argument("--descriptors", nargs="*",
                    default=["orb-bow+thumbnail", "orb-bow", "orb-bow+idf", "thumbnail", "thumbnail-grey", "orb-vlad"])
    ap.add_argument("--stride", type=int, default=5)
    ap.add_argument("--gap", type=int, default=30)
    ap.add_argument("--revisit-gap", type=int, default=150)
    ap.add_argument("--min-precision", type=float, default=0.95,
                    help="pooled top-1 precision each descriptor's threshold is calibrated to")
    ap.add_argument("--min-revisit-precision", type=float, default=0.98,
                    help="...and its pooled precision on revisits")
    ap.add_argument("--sweep", action="store_true", help="compare s_ref rules for the default descriptor")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    names = args.sequences or (list(QUICK) if args.quick else list(SEQUENCES))

    results: dict[str, list] = {}  # descriptor -> [(sequence, Queries, revisit Queries, ms, ms, repeats)]
    for name in names:
        sequence = open_bench_sequence(name)
        if sequence is None:
            print(f"{name}: not available here, skipped", file=sys.stderr)
            continue
        kf = load_keyframes(sequence, args.stride)
        truth = truth_matrix(kf.frames)
        feats = np.mean([len(f.pixels) for f in kf.features])
        print(f"{name}: {len(kf.frames)} keyframes, {feats:.0f} ORB features with depth, "
              f"{kf.feature_ms:.1f} ms/detection", file=sys.stderr)
        for dname, desc in descriptors_for(args.descriptors, kf).items():
            idf = dname == "orb-bow+idf"
            Q, describe_ms, query_ms = run_descriptor(desc, kf, truth, args.gap, idf, timed=True)
            R, _, _ = run_descriptor(desc, kf, truth, args.revisit_gap, idf)
            results.setdefault(dname, []).append((name, Q, R, describe_ms, query_ms, kf.repeats))

    default = KeyframeDatabase()
    rows, payload = [], {}
    for dname, runs in results.items():
        if dname == "orb-bow+thumbnail":
            # The database's own rule; check that the sweep's re-implementation agrees with it.
            rule = ("latest", default.ratio, default.min_similarity)
            for _, Q, R, *_ in runs:
                assert np.array_equal(passed(Q, *rule), Q.db_passed), "bench rule != KeyframeDatabase rule"
            how = f"database default: {default.ratio:g} x latest, floor {default.min_similarity:g}"
        else:
            cal = calibrate([r[1] for r in runs], [r[2] for r in runs], "latest", args.min_precision,
                            args.min_revisit_precision)
            rule = ("latest", cal[0], cal[1]) if cal else ("fixed", 0.0, 1.0)
            how = f"calibrated: {rule[1]:g} x latest, floor {rule[2]:g}" if cal else "no rule reaches the precisions"
        for name, Q, R, describe_ms, query_ms, repeats in runs:
            m, mr = metrics(Q, passed(Q, *rule), repeats), metrics(R, passed(R, *rule), repeats)
            conf = f"{m['confusions']} ({m['confusions_passed']})" if "confusions" in m else ""
            rows.append([name, dname, f"{m['queries']}/{m['with_match']}", fmt(m["p_at_1"]), fmt(m["recall"]),
                         fmt(m["recall_at_5"]), fmt(m["top1"]), f"{mr['with_match']}", fmt(mr["p_at_1"]),
                         fmt(mr["recall"]), conf, fmt(describe_ms), fmt(query_ms)])
            payload[f"{name}/{dname}"] = {"all": m, "revisits": mr, "describe_ms": describe_ms, "query_ms": query_ms,
                                          "rule": how}
        all_p, all_r = pooled([r[1] for r in runs], *rule)
        rev_p, rev_r = pooled([r[2] for r in runs], *rule)
        has = np.concatenate([r[1].has_match for r in runs])
        ok = np.concatenate([r[1].ok for r in runs])[has]
        rows.append(["**pooled**", dname, how, fmt(all_p), fmt(all_r), fmt(ok.any(1).mean()), fmt(ok[:, 0].mean()), "",
                     fmt(rev_p), fmt(rev_r), "", "", ""])
    rows.sort(key=lambda r: (list(results).index(r[1]), r[0] == "**pooled**"))
    print(f"\nKeyframes every {args.stride} frames; candidates >= {args.gap} frames older "
          f"(revisits: >= {args.revisit_gap}); true match: < {MAX_DIST_M:g} m and < {MAX_ANGLE_DEG:g} deg. "
          f"Thresholds: the database's default rule for the default descriptor; for the others the "
          f"'latest' rule calibrated to pooled precision >= {args.min_precision:g} "
          f"(revisits >= {args.min_revisit_precision:g}).\n")
    print(markdown_table(["sequence", "descriptor", "queries/with match", "P@1", "R", "R@5", "top-1",
                          "rev. with match", "rev. P@1", "rev. R", "conf. (passed)", "ms/describe", "ms/query"], rows))
    if args.sweep and "orb-bow+thumbnail" in results:
        runs = results["orb-bow+thumbnail"]
        table = []
        for rule in RULES:
            cal = calibrate([r[1] for r in runs], [r[2] for r in runs], rule, args.min_precision,
                            args.min_revisit_precision)
            table.append([rule, *(["-"] * 6 if cal is None else [f"{cal[0]:g}", f"{cal[1]:g}", *map(fmt, cal[2:])])])
        print(f"\ns_ref rules for orb-bow+thumbnail, pooled over {len(runs)} sequences: the best revisit recall "
              f"(then recall) with pooled precision >= {args.min_precision:g} (revisits: "
              f">= {args.min_revisit_precision:g})\n")
        print(markdown_table(["s_ref rule", "ratio", "floor", "P@1", "R", "rev. P@1", "rev. R"], table))
        payload["sweep"] = table
    write_json(args.json, {"title": "place recognition", "results": payload})


if __name__ == "__main__":
    main()
