"""Every preset runs on CUDA (issue 40 item 1): tensors are made on their inputs' device.

Without a GPU, ``slam.devicecheck.DeviceMixChecker`` replays CUDA's placement rules on the
CPU: a tensor made without ``device=`` is on the host, one made with the pipeline's device
is on the device, and an operator that meets both (beyond 0-dim host scalars) is where a
CUDA run raises "Expected all tensors to be on the same device". The tracker (both
optimisers, with features, the motion prior and the border margin), the mapper's iterations
and global bundle adjustment, views, the loop verification pieces, AR compositing and a whole
single-process run go through it on the plain torch kernels (what CUDA tensors take).

Tests marked ``cuda`` run the real pipeline on a GPU when one is present (skipped elsewhere).
"""

from __future__ import annotations

import json

from dataclasses import replace

import numpy as np
import pytest
import torch

from slam.config import PRESETS, preset
from slam.data import open_sequence
from slam.features import FeatureOdometry
from slam.frames import prepare_frame
from slam.geometry import se3_exp
from slam.mapping import Mapper, TrackedFrame
from slam.tracking import FrozenMap, Tracker

from slam.devicecheck import PIPELINE_DEVICE, DeviceMixChecker, place

SPEC = "synthetic:walk?frames=6&width=80&height=60"
cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


@pytest.fixture(autouse=True)
def torch_kernels(monkeypatch):
    monkeypatch.setenv("VOXFUSION_KERNELS", "torch")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _config(static="off", **tracking):
    base = preset("test")
    return replace(base, tracking=replace(base.tracking, **tracking),
                   render=replace(base.render, static_shapes=static),
                   mapping=replace(base.mapping, thin_samples=True, optimize_current_pose=True))


@pytest.fixture(scope="module")
def frames():
    return list(open_sequence(SPEC))


def test_the_checker_sees_a_host_tensor_meet_a_device_tensor():
    dev = PIPELINE_DEVICE
    with DeviceMixChecker() as checker:
        a = torch.ones(3, device=dev)
        b = torch.zeros(3)
        c = torch.zeros((), dtype=torch.float32)
        assert place(a) == "device" and place(b) == "host"
        a * c  # a 0-dim host scalar is allowed on CUDA
        a[torch.tensor([0, 1])]  # so is a host index
        (b * 2).to(dev) + a  # moved first: fine
        assert not checker.mixes
        a + b
        torch.stack([a, b])
    assert [m.op for m in checker.mixes] == ["add", "stack"]
    with pytest.raises(AssertionError, match="host tensors met device tensors"):
        checker.check()


def test_the_checker_catches_the_reported_motion_prior_bug(frames):
    """The bug of issue 40: ``torch.zeros(6, dtype=...)`` in the motion prior's start. The
    checker must see it (replayed here as the tracker's code had it)."""
    from slam.gauss_newton import Linearisation, MotionPrior

    dev = PIPELINE_DEVICE
    with DeviceMixChecker() as checker:
        H = torch.eye(6, device=dev) * 3
        lin = Linearisation(1.0, H, torch.zeros(6, device=dev), torch.zeros(2, device=dev),
                            torch.ones(2, dtype=torch.bool, device=dev), torch.zeros(2, device=dev))
        prior = MotionPrior.scaled_to(lin, 0.01)
        prior.added_to(lin, torch.zeros(6, dtype=torch.float32))
    assert checker.mixes, "the checker missed a host (6,) twist meeting device tensors"


def _mapped(frames, config, count=3):
    dev = PIPELINE_DEVICE
    mapper = Mapper(config, dev)
    tfs = [prepare_frame(f, None, dev, config.voxel.max_depth) for f in frames]
    for tf, f in zip(tfs[:count], frames):
        mapper.process(TrackedFrame(tf, torch.as_tensor(f.T_world_cam, dtype=torch.float32).to(dev)))
    return mapper, tfs


@pytest.mark.parametrize("tracking", [
    dict(optimizer="gauss_newton", motion_prior=0.01, border_margin=0.1, feature_count=500,
         feature_dense_check=True, feature_min_inliers=6),
    dict(optimizer="adam", iterations=3, resample_rays=True, keep_best_iterate=False, sample_band=0.0),
    dict(optimizer="adam", iterations=3, keep_best_iterate=True),
], ids=["gauss_newton", "adam_release", "adam_best"])
@pytest.mark.parametrize("static", ["off", "on"], ids=["flat", "static"])
def test_tracking_and_mapping_keep_to_the_device(frames, tracking, static):
    config = _config(static, **tracking)
    dev = PIPELINE_DEVICE
    with DeviceMixChecker() as checker:
        mapper, tfs = _mapped(frames, config)
        fmap = FrozenMap(mapper.snapshot(), config, dev)
        tracker = Tracker(config, dev)
        odometry = FeatureOdometry.from_config(config)
        matches = None
        if odometry is not None:
            odometry.correspondences(frames[2])
            odometry.remember(np.asarray(frames[2].T_world_cam, np.float64))
            matches = odometry.correspondences(frames[3])
        T_init = torch.as_tensor(frames[2].T_world_cam, dtype=torch.float32).to(dev)
        T_init = T_init @ se3_exp(torch.tensor([0.01, 0.0, 0.0, 0.0, 0.01, 0.0], device=dev))
        result = tracker.track(tfs[3], fmap, T_init, matches)
        mapper.process(TrackedFrame(tfs[3], result.T_world_cam))
        mapper.global_bundle_adjustment(mapper.current, 2, 64)
    checker.check()


def test_views_and_loop_verification_keep_to_the_device(frames):
    from slam.loop.verification import frozen_in_map_frame, geometry_check, refinement_tracker
    from slam.views import render_view

    config = _config()
    dev = PIPELINE_DEVICE
    mapper, tfs = _mapped(frames, config)
    with DeviceMixChecker() as checker:
        mapper, tfs = _mapped(frames, config)
        K = frames[0].K
        for method in ("banded", "full"):
            render_view(mapper.maps, frames[1].T_world_cam, K, 40, 30, device=dev, method=method,
                        precision="float32")
        target = frozen_in_map_frame(mapper.snapshot(), config, dev)
        T = torch.as_tensor(frames[2].T_world_cam, dtype=torch.float32).to(dev)
        result = refinement_tracker(config, dev).track(tfs[4], target, T)
        geometry_check(tfs[4], result.T_world_cam, target.view, target.decoder, config, 64,
                       torch.Generator().manual_seed(0))
    checker.check()


def test_ar_compositing_keeps_to_the_device():
    from ar.composite import composite
    from ar.objects import VirtualObject, make_shape

    dev = PIPELINE_DEVICE
    K = np.array([[60.0, 0, 40], [0, 60.0, 30], [0, 0, 1]])
    T_obj = np.eye(4)
    T_obj[:3, 3] = [0, 0, 1.5]
    with DeviceMixChecker() as checker:
        objects = [VirtualObject(make_shape("cube"), T_obj, 0.3), VirtualObject(make_shape("sphere"), T_obj, 0.2)]
        composite(np.zeros((60, 80, 3), np.float32), np.full((60, 80), 1.4, np.float32), objects, K, np.eye(4),
                  device=dev)
    checker.check()


def test_a_single_process_run_keeps_to_the_device(tmp_path):
    from slam.runtime import run_slam

    config = preset("test")
    config = replace(config, runtime=replace(config.runtime, processes=False, device=str(PIPELINE_DEVICE)),
                     tracking=replace(config.tracking, motion_prior=0.01, border_margin=0.1, retrack_iterations=1))
    with DeviceMixChecker() as checker:
        result = run_slam([open_sequence(SPEC)], config, tmp_path)
    assert result.status == "finished", result.error
    assert json.loads((tmp_path / "run.json").read_text())["frames_retracked"] > 0  # the final re-tracking too
    checker.check()


# --------------------------------------------------------------------- on a GPU
@cuda
@pytest.mark.cuda
@pytest.mark.parametrize("processes", [False, True], ids=["one_process", "two_processes"])
@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_runs_on_cuda(tmp_path, name, processes):
    """The whole pipeline on the GPU, each preset shrunk to a few frames and iterations."""
    from slam.runtime import run_slam

    from .test_config import shrunk

    config = shrunk(preset(name))
    config = replace(config, runtime=replace(config.runtime, device="cuda", processes=processes))
    result = run_slam([open_sequence("synthetic:loop?frames=8&width=160&height=120")], config, tmp_path)
    assert result.status == "finished", result.error
    assert result.frames == 8
