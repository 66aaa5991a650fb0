"""benchmarks/view_quality.py: its scores and the seed summary of a fine-level ablation."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from view_quality import psnr, summary  # noqa: E402


def _row(preset, seed, psnr_db, sequence="desk", kind="training"):
    return {"sequence": sequence, "kind": kind, "preset": preset, "seed": seed, "psnr_db": psnr_db,
            "ssim": 0.5, "sharpness": 0.4}


def test_psnr_counts_only_the_masked_pixels():
    target = np.zeros((4, 4, 3))
    rendered = target.copy()
    rendered[0, 0] = 1.0  # one wrong pixel, outside the mask
    mask = np.ones((4, 4), bool)
    mask[0, 0] = False
    assert psnr(rendered, target, mask) > 100
    assert abs(psnr(rendered, target) - 10 * np.log10(16)) < 1e-9


def test_summary_pairs_each_seed_with_its_coarse_twin():
    rows = [_row("cpu", 0, 18.0), _row("cpu", 1, 17.0), _row("cpu", 2, 19.0),
            _row("cpu coarse only", 0, 16.0), _row("cpu coarse only", 1, 15.5), _row("cpu coarse only", 2, 16.5)]
    by_preset = {r["preset"]: r for r in summary(rows)}
    fine = by_preset["cpu"]
    assert fine["runs"] == 3 and abs(fine["psnr_db"] - 18.0) < 1e-9 and abs(fine["psnr_db_std"] - 1.0) < 1e-9
    gain, gain_std = fine["paired_gain_db"]
    assert abs(gain - 2.0) < 1e-9 and abs(gain_std - 0.5) < 1e-9
    assert fine["verdict"] == "better"  # 18.0 against 16.0, spread 1.0
    assert "verdict" not in by_preset["cpu coarse only"]


def test_summary_says_within_spread_and_worse():
    close = [_row("cpu", 0, 16.2), _row("cpu", 1, 15.4), _row("cpu coarse only", 0, 16.0), _row("cpu coarse only", 1, 15.9)]
    assert summary(close)[0]["verdict"] == "within spread"
    lower = [_row("cpu", 0, 14.0), _row("cpu", 1, 14.1), _row("cpu coarse only", 0, 16.0), _row("cpu coarse only", 1, 16.1)]
    assert summary(lower)[0]["verdict"] == "worse"


def test_a_reused_folder_gives_its_runs_and_nothing_for_the_runs_it_lacks(tmp_path):
    from types import SimpleNamespace

    from view_quality import _run_dir

    seq = SimpleNamespace(name="desk")
    (tmp_path / "desk_fr_1").mkdir()
    (tmp_path / "desk_fr_1" / "map.pt").write_bytes(b"")
    assert _run_dir(seq, "fr", 1, tmp_path / "out", tmp_path, 1.0) == tmp_path / "desk_fr_1"
    assert _run_dir(seq, "fr", 2, tmp_path / "out", tmp_path, 1.0) is None  # not run anew
    assert not (tmp_path / "out").exists()
