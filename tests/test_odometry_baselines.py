"""benchmarks/odometry_baselines.py: its error measure and its ORB-PnP chain."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from odometry_baselines import chain_orb_pnp, errors_cm  # noqa: E402

from slam.geometry import se3_exp  # noqa: E402


def test_errors_ignore_a_rigid_offset_of_the_whole_trajectory():
    twists = torch.randn(20, 6, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 0.3
    gt = se3_exp(twists).numpy()
    offset = se3_exp(torch.tensor([1.0, -2.0, 0.5, 0.3, 0.1, -0.2], dtype=torch.float64)).numpy()
    assert errors_cm(offset @ gt, gt).max() < 1e-9
    shifted = gt.copy()
    shifted[5, :3, 3] += 0.1
    assert errors_cm(shifted, gt).max() > 5.0


@pytest.mark.shared_data
def test_the_orb_pnp_chain_follows_fr1_desk(shared_data):
    from slam.data import open_sequence

    sequence = open_sequence(str(shared_data / "rgbd_dataset_freiburg1_desk"))
    frames = [sequence[i] for i in range(len(sequence))]
    poses = chain_orb_pnp(frames)
    gt = np.stack([f.T_world_cam for f in frames])
    assert np.allclose(poses[0], gt[0])
    e = errors_cm(poses, gt)
    assert np.sqrt((e ** 2).mean()) < 1.5  # measured 0.48 cm over the 9 frames
