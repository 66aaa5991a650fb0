"""The decision rule of benchmarks/README.md as bench_real.py applies it: accuracy and speed."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_real import Run, Variant, lands, lands_for_speed, summary  # noqa: E402

BASE, OTHER, PEER = Variant("cpu", "cpu"), Variant("other", "cpu"), Variant("open3d-1cm", "open3d")


def rows_for(ate_factor: float, fps_factor: float) -> list[dict]:
    """Two sequences, 3 runs each: the baseline, a variant at ``ate_factor`` x its ATE and
    ``fps_factor`` x its frames/s, and the peer."""
    runs = []
    for sequence, ate, fps in (("a", 2.0, 4.0), ("b", 1.0, 3.0)):
        for r in range(3):
            runs.append(Run(sequence, "cpu", r, ate + 0.01 * r, fps, 10, 1.0, "1"))
            runs.append(Run(sequence, "other", r, ate * ate_factor + 0.01 * r, fps * fps_factor, 10, 1.0, "1"))
            runs.append(Run(sequence, "open3d-1cm", r, ate, fps * 2, 10, 1.0, "1"))
    return summary(runs, [BASE, OTHER, PEER])


def test_ratios_against_baseline_and_peer():
    rows = {(r["sequence"], r["variant"]): r for r in rows_for(1.0, 0.5)}
    assert abs(rows["a", "other"]["fps_ratio"] - 0.5) < 1e-9
    assert abs(rows["a", "cpu"]["fps_vs_peer"] - 0.5) < 1e-9
    assert rows["a", "other"]["speed"] == "slower"
    assert rows["a", "open3d-1cm"]["fps_vs_peer"] is None


def test_faster_and_better_lands():
    assert lands(rows_for(0.8, 1.2), "other")[0]


def test_within_spread_everywhere_does_not_land():
    ok, why = lands(rows_for(1.0, 1.5), "other")
    assert not ok and "better beyond spread on no sequence" in why


def test_slower_lands_only_when_the_accuracy_pays_for_it():
    assert lands(rows_for(0.8, 0.9), "other")[0]  # 20 % of ATE for 10 % of frames/s
    ok, why = lands(rows_for(0.9, 0.7), "other")  # 10 % of ATE for 30 % of frames/s
    assert not ok and "slower" in why


def test_worse_anywhere_does_not_land():
    ok, why = lands(rows_for(1.2, 2.0), "other")
    assert not ok and "worse" in why


def test_a_speed_change_lands_when_faster_and_no_worse():
    ok, why = lands_for_speed(rows_for(1.0, 1.2), "other")
    assert ok and "1.20x" in why
    ok, why = lands_for_speed(rows_for(1.0, 1.02), "other")  # within spread but no faster
    assert not ok and "needs 1.05x" in why
    ok, why = lands_for_speed(rows_for(1.5, 1.5), "other")  # faster but worse
    assert not ok and "worse beyond spread" in why
    ok, why = lands_for_speed(rows_for(1.0, 0.9), "other")
    assert not ok and "slower" in why
