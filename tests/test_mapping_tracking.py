"""Mapping (slam.mapping) and tracking (slam.tracking) on a tiny synthetic sequence.

One map is trained once per module on the first frame of an 80x60 synthetic orbit with its
ground-truth pose; the loss, snapshot and tracking tests share it. Keyframe and bundle
adjustment tests use fresh mappers and only a few iterations.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from slam.config import preset
from slam.data import open_sequence
from slam.features import Correspondences
from slam.frames import TensorFrame, pixels_at, prepare_frame, sample_pixels, sample_stacked_pixels, stack_frames
from slam.geometry import pose_moved, se3_inverse, se3_log, so3_exp
from slam.losses import LossWeights, compute_losses
from slam.mapping import Mapper, MapSnapshot, TrackedFrame
from slam.maps import SubMap
from slam.render import render_rays
from slam.gauss_newton import limit_step, linearise, linearise_rendered, render_with_jacobians
from slam.geometry import se3_exp
from slam.render import MapView
from slam.tracking import FrozenMap, Tracker, interior_rays, tracking_bounds
from slam.voxels import morton_encode

CPU = torch.device("cpu")
BASE = preset("test")
CONFIG = replace(BASE, tracking=replace(BASE.tracking, iterations=40, num_rays=256))
SPEC = "synthetic:orbit?frames=100&width=80&height=60"


@pytest.fixture(scope="module", autouse=True)
def single_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def frames() -> list[TensorFrame]:
    seq = open_sequence(SPEC, max_frames=2)
    return [prepare_frame(f, None, CPU, BASE.voxel.max_depth) for f in seq]


def gt_pose(frame: TensorFrame) -> torch.Tensor:
    return torch.from_numpy(frame.T_world_cam_gt).float()


def eval_losses(submap: SubMap, frame: TensorFrame, T_map_cam: torch.Tensor, config=CONFIG) -> dict[str, float]:
    """Losses of 512 fixed pixels rendered at fixed sample offsets (no randomness), plus the
    median absolute depth error ``depth_median`` (the L1 mean is dominated by depth edges)."""
    r = config.render
    batch = sample_pixels(frame, 512, torch.Generator().manual_seed(123))
    n = batch.depth.shape[0]
    with torch.no_grad():
        out = render_rays(T_map_cam[:3, 3].expand(n, 3), batch.dirs_cam @ T_map_cam[:3, :3].T, submap.view(),
                          submap.decoder, near=torch.full((n,), 0.05), far=torch.full((n,), r.max_distance),
                          step=r.step_ratio * submap.voxels.voxel_size, truncation=r.truncation,
                          max_hits=r.max_hits)
        c = config.loss
        losses = compute_losses(out, batch.rgb, batch.depth, r.truncation,
                                LossWeights(c.rgb_weight, c.depth_weight, c.sdf_weight, c.fs_weight))
    values = {k: float(getattr(losses, k)) for k in ("total", "rgb", "depth", "fs", "sdf")}
    values["depth_median"] = float((out.depth - batch.depth)[out.hit].abs().median())
    return values


@dataclasses.dataclass
class Trained:
    mapper: Mapper
    before: dict[str, float]
    after: dict[str, float]


@pytest.fixture(scope="module")
def trained(frames) -> Trained:
    mapper = Mapper(CONFIG, CPU, seed=0)
    step = mapper.process(TrackedFrame(frames[0], gt_pose(frames[0])), optimize=False)
    assert step.is_keyframe and step.new_voxels > 0 and not step.losses
    submap = mapper.current
    before = eval_losses(submap, frames[0], gt_pose(frames[0]))
    last = mapper.optimize(submap, 100)
    assert set(last) == {"total", "rgb", "depth", "fs", "sdf"} and all(np.isfinite(list(last.values())))
    return Trained(mapper, before, eval_losses(submap, frames[0], gt_pose(frames[0])))


# ------------------------------------------------------------- pixel sampling
def test_stacked_sampling_draws_valid_pixels_of_each_frame(frames):
    """The batched sampler of the joint optimisation against ``pixels_at`` (the plain
    per-frame path): row block i holds valid pixels of frame i, with their own K, colour
    and depth, spread over the whole valid set."""
    a = frames[0]
    # A second frame with a different K and a hole, so a wrong frame offset shows.
    depth_b = frames[1].depth.clone()
    depth_b[:, : a.width // 2] = 0
    b = dataclasses.replace(frames[1], depth=depth_b, K=frames[1].K * torch.tensor([[1.1], [1.1], [1.0]]),
                            valid=torch.nonzero(depth_b.reshape(-1) > 0, as_tuple=True)[0])
    stack = stack_frames([a, b, a])
    batch = sample_stacked_pixels(stack, 2000, torch.Generator().manual_seed(3))
    assert batch.dirs_cam.shape == (6000, 3) and batch.rgb.shape == (6000, 3) and batch.depth.shape == (6000,)
    for i, frame in enumerate([a, b, a]):
        rows = slice(2000 * i, 2000 * (i + 1))
        # Recover each row's pixel from its direction and compare with the reference lookup.
        u = torch.round(batch.dirs_cam[rows, 0] * frame.K[0, 0] + frame.K[0, 2]).long()
        v = torch.round(batch.dirs_cam[rows, 1] * frame.K[1, 1] + frame.K[1, 2]).long()
        ref = pixels_at(frame, v * frame.width + u)
        assert torch.allclose(batch.dirs_cam[rows], ref.dirs_cam, atol=1e-5)
        assert torch.equal(batch.rgb[rows], ref.rgb) and torch.equal(batch.depth[rows], ref.depth)
        assert bool((batch.depth[rows] > 0).all())
        assert len(torch.unique(v * frame.width + u)) > 1000  # spread, not a few pixels repeated
    assert int((batch.dirs_cam[2000:4000, 0] * b.K[0, 0] + b.K[0, 2]).min()) >= a.width // 2 - 1
    assert stack_frames([a, dataclasses.replace(a, depth=a.depth[:-1])]) is None


# ------------------------------------------------------------------ mapping
def test_mapping_with_gt_poses_reduces_the_losses(trained):
    b, a = trained.before, trained.after
    assert a["total"] < 0.3 * b["total"], (b, a)
    assert a["depth"] < 0.8 * b["depth"], (b, a)
    assert a["depth_median"] < 0.02 < b["depth_median"], (b, a)
    assert a["rgb"] < 0.95 * b["rgb"], (b, a)
    assert a["sdf"] < b["sdf"] and a["fs"] < b["fs"], (b, a)


def test_mapping_records_the_voxels_that_held_observed_surface(trained):
    submap = trained.mapper.current
    surface = submap.surface_voxels()
    # Allocation covers depth +- tr: the surface voxels are a strict, non-empty part of it.
    assert 0 < int(surface.sum()) < surface.numel()
    assert torch.equal(submap.surface_codes, torch.unique(submap.surface_codes))


def test_keyframe_selection(frames):
    config = replace(BASE, mapping=replace(BASE.mapping, keyframe_max_interval=1000))
    mapper = Mapper(config, CPU)
    f, T = frames[0], gt_pose(frames[0])
    first = mapper.process(TrackedFrame(f, T), optimize=False)
    assert first.is_keyframe and first.new_voxel_ratio == 1.0
    voxels = mapper.current.voxels.num_voxels
    same = mapper.process(TrackedFrame(f, T), optimize=False)
    assert not same.is_keyframe and same.new_voxel_ratio == 0.0 and same.new_voxels == 0
    assert mapper.current.voxels.num_voxels == voxels, "a non-keyframe allocates nothing"
    moved = T.clone()
    moved[:3, 3] += torch.tensor([1.5, 0.0, 0.0])
    far = mapper.process(TrackedFrame(f, moved), optimize=False)
    assert far.is_keyframe and far.new_voxel_ratio > config.mapping.keyframe_ratio and far.new_voxels > 0
    assert mapper.current.voxels.num_voxels == voxels + far.new_voxels
    assert [kf.frame_index for kf in mapper.current.keyframes] == [f.index, f.index]
    assert torch.equal(mapper.current.keyframes[-1].T_map_cam, moved)


def test_keyframe_max_interval_forces_a_keyframe(frames):
    config = replace(BASE, mapping=replace(BASE.mapping, keyframe_max_interval=3))
    mapper = Mapper(config, CPU)
    flags = [mapper.process(TrackedFrame(frames[0], gt_pose(frames[0])), optimize=False).is_keyframe
             for _ in range(7)]
    assert flags == [True, False, False, True, False, False, True]


def test_a_still_camera_gets_no_forced_keyframe_until_it_moves(frames):
    mapping = replace(BASE.mapping, keyframe_max_interval=3, keyframe_interval_min_metres=0.01,
                      keyframe_interval_min_degrees=1.0)
    mapper = Mapper(replace(BASE, mapping=mapping), CPU)
    T = gt_pose(frames[0])
    flags = [mapper.process(TrackedFrame(frames[0], T), optimize=False).is_keyframe for _ in range(7)]
    assert flags == [True] + [False] * 6, "the same pose over and over: only the first frame"
    stepped = T.clone()
    stepped[:3, 3] += torch.tensor([0.02, 0.0, 0.0])  # 2 cm: too little for a new-voxel keyframe
    step = mapper.process(TrackedFrame(frames[0], stepped), optimize=False)
    assert step.is_keyframe and step.new_voxel_ratio <= mapping.keyframe_ratio, "the interval's keyframe, once moved"


def test_pose_moved_asks_for_either_minimum():
    T = torch.eye(4)
    T[0, 3] = 0.02
    assert pose_moved(T, 0.01, 1.0) and not pose_moved(T, 0.05, 1.0) and pose_moved(T, 0.0, 0.0)
    turn = torch.eye(4)
    turn[:3, :3] = so3_exp(torch.tensor([0.0, math.radians(2.0), 0.0]))
    assert pose_moved(turn, 0.01, 1.0) and not pose_moved(turn, 0.01, 3.0) and not pose_moved(turn, 0.01, 0.0)


def test_window_holds_the_newest_keyframe_and_at_most_n_kf(frames):
    config = replace(BASE, mapping=replace(BASE.mapping, keyframe_max_interval=1, window_size=3))
    mapper = Mapper(config, CPU)
    for _ in range(6):
        mapper.process(TrackedFrame(frames[0], gt_pose(frames[0])), optimize=False)
    submap = mapper.current
    assert len(submap.keyframes) == 6
    for _ in range(5):
        window = mapper._window(submap)
        assert len(window) == 3 and window[-1] is submap.keyframes[-1]
        assert len({id(kf) for kf in window}) == 3


def _ba_mapper(frames, optimize_poses: bool) -> Mapper:
    m = replace(BASE.mapping, keyframe_max_interval=1, optimize_poses=optimize_poses, lr_pose=1e-2)
    mapper = Mapper(replace(BASE, mapping=m), CPU)
    for f in frames:
        mapper.process(TrackedFrame(f, gt_pose(f)), optimize=False)
    return mapper


def test_bundle_adjustment_moves_keyframes_but_not_the_first(frames):
    mapper = _ba_mapper(frames, optimize_poses=True)
    submap = mapper.current
    before = [kf.T_map_cam.clone() for kf in submap.keyframes]
    mapper.optimize(submap, 4)
    after = [kf.T_map_cam for kf in submap.keyframes]
    assert torch.equal(after[0], before[0]), "the first keyframe fixes the gauge"
    assert float((after[1] - before[1]).abs().max()) > 1e-4
    R = after[1][:3, :3]
    assert torch.allclose(R @ R.T, torch.eye(3), atol=1e-5), "poses stay rigid"
    world = mapper.keyframe_poses_world(submap)
    assert world.shape == (2, 4, 4) and torch.allclose(world[1], after[1])


def test_global_bundle_adjustment_moves_every_keyframe_but_the_first():
    seq = open_sequence(SPEC, max_frames=4)
    frames = [prepare_frame(f, None, CPU, BASE.voxel.max_depth) for f in seq]
    m = replace(BASE.mapping, keyframe_max_interval=1, lr_pose=1e-2, window_size=2)
    mapper = Mapper(replace(BASE, mapping=m), CPU)
    for f in frames:
        mapper.process(TrackedFrame(f, gt_pose(f)), optimize=False)
    submap = mapper.current
    before = [kf.T_map_cam.clone() for kf in submap.keyframes]
    assert len(before) == 4, "a window of 2 could not reach all of them"
    mapper.global_bundle_adjustment(submap, 2, num_rays=256)
    after = [kf.T_map_cam for kf in submap.keyframes]
    assert torch.equal(after[0], before[0])
    assert all(float((a - b).abs().max()) > 1e-4 for a, b in zip(after[1:], before[1:]))
    assert mapper.global_bundle_adjustment(submap, 0, num_rays=256) == {}
    assert mapper.last_iterations == 0
    mapper.global_bundle_adjustment(submap, 3, num_rays=64)
    assert mapper.last_iterations == 3
    # A deadline already passed stops it before the first iteration; poses stay.
    import time

    held = [kf.T_map_cam.clone() for kf in submap.keyframes]
    mapper.global_bundle_adjustment(submap, 50, num_rays=64, deadline=time.perf_counter() - 1)
    assert mapper.last_iterations == 0
    assert all(torch.equal(a, kf.T_map_cam) for a, kf in zip(held, submap.keyframes))


def test_an_interrupted_optimisation_stops_before_its_next_iteration(frames):
    # The mapping process's idle steps stop this way when a frame arrives.
    mapper = Mapper(CONFIG, CPU, seed=0)
    mapper.process(TrackedFrame(frames[0], gt_pose(frames[0])), optimize=False)
    asked: list[int] = []

    def interrupted() -> bool:
        asked.append(1)
        return len(asked) > 3

    losses = mapper.optimize(mapper.current, 10, interrupted=interrupted)
    assert mapper.last_iterations == 3 and len(asked) == 4 and losses
    mapper.optimize(mapper.current, 2)
    assert mapper.last_iterations == 2


def test_final_budget_caps_iterations_by_keyframes_and_time_by_the_run():
    from slam.mapping_process import final_budget

    m = replace(BASE.mapping, final_iterations=500, final_iterations_per_keyframe=50,
                final_time_share=1.0, final_min_seconds=10.0)
    assert final_budget(m, 4, 3.0).iterations == 200 and final_budget(m, 40, 3.0).iterations == 500
    assert final_budget(m, 4, 3.0).seconds == 10.0, "never below the floor"
    assert final_budget(m, 4, 60.0).seconds == 60.0, "as long as the run before it"
    plain = replace(m, final_iterations_per_keyframe=0, final_time_share=0.0)
    assert final_budget(plain, 4, 60.0) == final_budget(plain, 40, 1.0)
    assert final_budget(plain, 4, 60.0).iterations == 500 and final_budget(plain, 4, 60.0).seconds is None


@pytest.mark.parametrize("on", [True, False], ids=["optimised", "held"])
def test_the_current_frame_pose_is_optimised_in_the_window_only_when_asked(frames, on):
    # mapping.optimize_current_pose (issue 21 item 2): the newest non-keyframe frame joins the
    # window with a free pose, the mapper reports its refined pose; the first keyframe stays.
    m = replace(BASE.mapping, optimize_current_pose=on, keyframe_ratio=2.0, lr_pose=1e-2, iterations=20,
                first_frame_iterations=60)
    mapper = Mapper(replace(BASE, mapping=m), CPU, seed=0)
    mapper.process(TrackedFrame(frames[0], gt_pose(frames[0])))
    first = mapper.current.keyframes[0].T_map_cam.clone()
    tracked = gt_pose(frames[1]) @ se3_exp(torch.tensor([0.03, -0.02, 0.0, 0.0, 0.0, 0.0]))
    step = mapper.process(TrackedFrame(frames[1], tracked))
    assert not step.is_keyframe and torch.equal(mapper.current.keyframes[0].T_map_cam, first)
    if not on:
        assert step.T_map_cam is None
        return
    refined = step.T_map_cam
    assert refined is not None and float((refined - tracked).abs().max()) > 1e-3
    assert torch.allclose(refined[:3, :3] @ refined[:3, :3].T, torch.eye(3), atol=1e-5), "rigid"
    truth = gt_pose(frames[1])[:3, 3]
    assert float((refined[:3, 3] - truth).norm()) < float((tracked[:3, 3] - truth).norm()), "towards the truth"
    # With given poses (optimize_poses off) nothing moves, whatever the switch says.
    held = Mapper(replace(BASE, mapping=replace(m, optimize_poses=False)), CPU, seed=0)
    held.process(TrackedFrame(frames[0], gt_pose(frames[0])))
    assert held.process(TrackedFrame(frames[1], tracked)).T_map_cam is None


def test_without_pose_optimisation_no_keyframe_moves(frames):
    mapper = _ba_mapper(frames, optimize_poses=False)
    submap = mapper.current
    before = [kf.T_map_cam.clone() for kf in submap.keyframes]
    emb = submap.voxels.embeddings.detach().clone()
    mapper.optimize(submap, 2)
    assert all(torch.equal(a.T_map_cam, b) for a, b in zip(submap.keyframes, before))
    assert not torch.equal(submap.voxels.embeddings.detach(), emb), "the map itself is optimised"


def test_snapshot_is_a_detached_copy_that_renders_like_the_map(trained, frames):
    mapper = trained.mapper
    snap = mapper.snapshot()
    assert isinstance(snap, MapSnapshot) and snap.version == mapper.version
    assert isinstance(snap.embeddings, np.ndarray) and snap.embeddings.shape == tuple(mapper.current.voxels.embeddings.shape)
    fmap = FrozenMap(snap, CONFIG, CPU)
    assert not any(p.requires_grad for p in fmap.decoder.parameters())
    T = gt_pose(frames[0])
    batch = sample_pixels(frames[0], 64, torch.Generator().manual_seed(0))
    kwargs = dict(near=torch.full((64,), 0.05), far=torch.full((64,), 5.0), step=0.04, truncation=0.1, max_hits=8)
    o, d = T[:3, 3].expand(64, 3), batch.dirs_cam @ T[:3, :3].T
    with torch.no_grad():
        a = render_rays(o, d, mapper.current.view(), mapper.current.decoder, **kwargs)
        b = render_rays(o, d, fmap.view, fmap.decoder, **kwargs)
    assert torch.allclose(a.depth, b.depth) and torch.allclose(a.color, b.color)
    emb = mapper.current.voxels.embeddings
    with torch.no_grad():
        emb.add_(1.0)
        assert not np.allclose(snap.embeddings, emb.numpy()), "the snapshot does not share memory"
        emb.sub_(1.0)


# ----------------------------------------------------------------- tracking
def pose_error(T: torch.Tensor, T_ref: torch.Tensor) -> tuple[float, float]:
    """(translation metres, rotation degrees) of T relative to T_ref."""
    D = se3_inverse(T_ref.double()) @ T.double()
    cos = ((torch.diagonal(D[:3, :3]).sum() - 1) / 2).clamp(-1, 1)
    return float(D[:3, 3].norm()), float(torch.rad2deg(torch.acos(cos)))


@pytest.mark.parametrize("optimizer", ["adam", "gauss_newton"])
def test_tracking_recovers_a_perturbed_pose(trained, frames, optimizer):
    config = replace(CONFIG, tracking=replace(CONFIG.tracking, optimizer=optimizer))
    fmap = FrozenMap(trained.mapper.snapshot(), config, CPU)
    T_gt = gt_pose(frames[0])
    delta = torch.eye(4)
    delta[:3, :3] = so3_exp(torch.deg2rad(torch.tensor([0.0, 1.0, 0.0])))
    delta[:3, 3] = torch.tensor([0.02, 0.0, 0.0])
    T_init = T_gt @ delta
    t0, r0 = pose_error(T_init, T_gt)
    assert t0 == pytest.approx(0.02, abs=1e-6) and r0 == pytest.approx(1.0, abs=1e-2)
    result = Tracker(config, CPU).track(frames[0], fmap, T_init)
    t1, r1 = pose_error(result.T_world_cam, T_gt)
    assert result.ok and not result.reason
    assert t1 < 0.7 * t0 and r1 < 0.7 * r0, (t1, r1)
    if optimizer == "gauss_newton":
        # Converges, where Adam only improves: to the pose it finds when started at GT. That
        # pose is itself ~1 cm from GT on this briefly trained 80x60 map (0.8-1.5 cm over
        # mapper seeds), so GT is the wrong yardstick for convergence.
        optimum = Tracker(config, CPU).track(frames[0], fmap, T_gt).T_world_cam
        t2, r2 = pose_error(result.T_world_cam, optimum)
        assert t2 < 0.35 * t0 and r2 < 0.25 * r0, (t2, r2)
    assert result.hit_ratio > 0.9 and result.depth_residual < 0.05
    assert 1 <= result.iterations <= CONFIG.tracking.iterations


def assert_recovers_2cm(config, trained, frames) -> None:
    """Tracking frame 0 from 2 cm off its GT pose ends well within 2 cm of it."""
    fmap = FrozenMap(trained.mapper.snapshot(), config, CPU)
    T_gt = gt_pose(frames[0])
    delta = torch.eye(4)
    delta[:3, 3] = torch.tensor([0.02, 0.0, 0.0])
    result = Tracker(config, CPU).track(frames[0], fmap, T_gt @ delta)
    assert result.ok and pose_error(result.T_world_cam, T_gt)[0] < 0.7 * 0.02


@pytest.mark.parametrize("static", ["off", "on"])
def test_retracking_kept_pixels_is_tracking_the_frame_on_them(trained, frames, static):
    # The final re-tracking (tracking.retrack_iterations) keeps a frame's pixels and tracks
    # them again later: with the pixels the tracker itself would draw, it is the same
    # Levenberg-Marquardt run, pose for pose.
    config = replace(CONFIG, tracking=replace(CONFIG.tracking, optimizer="gauss_newton"),
                     render=replace(CONFIG.render, static_shapes=static))
    fmap = FrozenMap(trained.mapper.snapshot(), config, CPU)
    T_gt = gt_pose(frames[0])
    delta = torch.eye(4)
    delta[:3, 3] = torch.tensor([0.02, 0.0, 0.0])
    tracked = Tracker(config, CPU, seed=3).track(frames[0], fmap, T_gt @ delta)
    tracker = Tracker(config, CPU, seed=3)
    rays = tracker.keep_rays(frames[0], config.tracking.num_rays, torch.Generator().manual_seed(4))
    assert rays.dirs_cam.shape == (config.tracking.num_rays, 3) and rays.depth.device.type == "cpu"
    again = tracker.retrack(rays, fmap, T_gt @ delta)
    assert again.ok and again.iterations == tracked.iterations
    assert torch.allclose(again.T_world_cam, tracked.T_world_cam, atol=1e-5)
    assert pose_error(again.T_world_cam, T_gt)[0] < 0.7 * 0.02


def test_gauss_newton_renders_no_step_below_the_convergence_tolerance(trained, frames, monkeypatch):
    """Once the next step is below ``convergence_tol`` the tracker stops without rendering it,
    and the first pose is rendered once for both of its weightings."""
    import slam.tracking as tracking

    renders: list[torch.Tensor] = []
    real = tracking.render_with_jacobians
    monkeypatch.setattr(tracking, "render_with_jacobians", lambda T, *a, **k: renders.append(T) or real(T, *a, **k))
    gn = replace(CONFIG.tracking, optimizer="gauss_newton", iterations=20, convergence_tol=1e-4, motion_prior=0.0)
    config = replace(CONFIG, tracking=gn)
    fmap = FrozenMap(trained.mapper.snapshot(), config, CPU)
    T_gt = gt_pose(frames[0])
    delta = torch.eye(4)
    delta[:3, 3] = torch.tensor([0.01, 0.0, 0.0])
    result = Tracker(config, CPU).track(frames[0], fmap, T_gt @ delta)
    assert result.ok and pose_error(result.T_world_cam, T_gt)[0] < 0.01, "closer than it started"
    assert result.iterations < gn.iterations, "stopped by the tolerance, not the iteration cap"
    # The start pose once, then one render per step taken: the last, tiny step is not rendered.
    assert len(renders) == result.iterations


@pytest.mark.parametrize("keep_best", [True, False])
def test_adam_returns_the_best_iterate_or_the_last_one_as_the_release(trained, frames, keep_best):
    # One evaluated iterate: the best is the start itself; the last is the pose after Adam's
    # one step, which moves each twist coordinate by about lr whatever the gradient.
    lr = 1e-3
    config = replace(CONFIG, tracking=replace(CONFIG.tracking, optimizer="adam", iterations=1, lr_rot=lr,
                                              lr_trans=lr, keep_best_iterate=keep_best))
    fmap = FrozenMap(trained.mapper.snapshot(), config, CPU)
    T_init = gt_pose(frames[0])
    result = Tracker(config, CPU).track(frames[0], fmap, T_init)
    moved = float(se3_log(se3_inverse(T_init.double()) @ result.T_world_cam.double()).abs().max())
    if keep_best:
        assert moved < 1e-6
    else:
        assert lr * 0.5 < moved < lr * 1.5, moved


def test_the_paper_preset_tracker_recovers_a_perturbed_pose(trained, frames):
    # The paper's tracker (Adam, new rays each iteration, the last iterate, whole rays, every
    # voxel) on the test map; only the ray count is cut to keep the test fast.
    paper = preset("paper").tracking
    assert_recovers_2cm(replace(CONFIG, tracking=replace(paper, num_rays=256, iterations=30)), trained, frames)


def test_interior_rays_leave_out_points_near_the_map_border():
    # A 5 x 5 x 1 slab of 0.2 m voxels: x, y in [0, 1) m, z in [0, 0.2) m.
    ijk = torch.tensor([[i, j, 0] for i in range(5) for j in range(5)])
    view = MapView(torch.sort(morton_encode(ijk))[0], torch.zeros(25, 8, dtype=torch.long), torch.zeros(1, 16), 0.2)
    T = torch.eye(4)
    T[:3, 3] = torch.tensor([0.0, 0.0, -0.9])  # camera 0.9 m in front of the slab, looking along +z
    dirs = torch.tensor([[0.50, 0.50, 1.0], [0.03, 0.50, 1.0], [0.97, 0.50, 1.0], [0.50, 0.50, 1.0]])
    depth = torch.tensor([1.0, 1.0, 1.0, 1.4])  # points at z = 0.1, except the last (z = 0.5: outside)
    assert interior_rays(T, dirs, depth, view, 0.05).tolist() == [True, False, False, False]
    # 3 cm from the border: inside with a 2 cm margin, not with 5 cm.
    assert interior_rays(T, dirs, depth, view, 0.02).tolist() == [True, True, True, False]


@pytest.mark.parametrize("margin", [0.0, 0.05])
def test_tracking_with_a_border_margin_recovers_a_perturbed_pose(trained, frames, margin):
    config = replace(CONFIG, tracking=replace(CONFIG.tracking, optimizer="gauss_newton", border_margin=margin))
    assert_recovers_2cm(config, trained, frames)


def test_tracking_fails_far_outside_the_map(trained, frames):
    fmap = FrozenMap(trained.mapper.snapshot(), CONFIG, CPU)
    T = gt_pose(frames[0]).clone()
    T[:3, 3] += torch.tensor([50.0, 0.0, 0.0])
    result = Tracker(CONFIG, CPU).track(frames[0], fmap, T)
    assert not result.ok
    assert "hit the map" in result.reason and result.hit_ratio < CONFIG.tracking.min_valid_ratio
    assert torch.allclose(result.T_world_cam, T), "a failed track keeps the initial pose"


def test_tracking_fails_when_the_depth_residual_stays_high(trained, frames):
    config = replace(CONFIG, tracking=replace(CONFIG.tracking, iterations=2, max_depth_residual=1e-6))
    fmap = FrozenMap(trained.mapper.snapshot(), config, CPU)
    result = Tracker(config, CPU).track(frames[0], fmap, gt_pose(frames[0]))
    assert not result.ok and "median depth residual" in result.reason


# ------------------------------------------------------ Gauss-Newton tracking
def _linearisation_inputs(trained, frames, n=128):
    r = CONFIG.render
    fmap = FrozenMap(trained.mapper.snapshot(), CONFIG, CPU)
    batch = sample_pixels(frames[0], n, torch.Generator().manual_seed(7))
    near, far = tracking_bounds(batch.depth, r.truncation, 2.0, r.max_distance)
    kwargs = dict(near=near, far=far, step=r.step_ratio * fmap.view.voxel_size, truncation=r.truncation,
                  max_hits=r.max_hits)
    c = CONFIG.loss
    return fmap, batch, kwargs, LossWeights(c.rgb_weight, c.depth_weight, c.sdf_weight, c.fs_weight)


@pytest.mark.parametrize("mask_in_front,renormalise", [(True, False), (False, False), (True, True)])
def test_linearisation_cost_and_gradient_match_autograd_through_render_rays(trained, frames, mask_in_front,
                                                                            renormalise):
    """The closed-form model against the reference: the paper's losses on render_rays, and
    their autograd gradient with respect to the twist (IRLS makes g half of it), with either
    first-surface mask (``render.mask_in_front``), and with the colour renormalised over
    samples above the ``cpu`` tracker's weight threshold (a fifth of the peak)."""
    fmap, batch, kwargs, weights = _linearisation_inputs(trained, frames)
    kwargs["mask_in_front"] = mask_in_front
    if renormalise:
        kwargs.update(renormalise_color=True, color_weight_eps=0.05)
    T0 = gt_pose(frames[0]) @ se3_exp(torch.tensor([0.01, -0.01, 0.005, 0.01, 0.0, -0.01]))
    lin = linearise(T0, batch.dirs_cam, batch.rgb, batch.depth, None, fmap.view, fmap.decoder, weights=weights,
                    eps_depth=1e-12, eps_color=1e-12, **kwargs)
    xi = torch.zeros(6, requires_grad=True)
    T = T0 @ se3_exp(xi)
    n = batch.depth.shape[0]
    out = render_rays(T[:3, 3].expand(n, 3), batch.dirs_cam @ T[:3, :3].T, fmap.view, fmap.decoder, **kwargs)
    losses = compute_losses(out, batch.rgb, batch.depth, CONFIG.render.truncation, weights)
    losses.total.backward()
    assert lin.cost == pytest.approx(float(losses.total.detach()), rel=1e-4)
    cos = float(torch.nn.functional.cosine_similarity(2 * lin.g, xi.grad, dim=0))
    assert cos > 0.99 and float((2 * lin.g).norm() / xi.grad.norm()) == pytest.approx(1.0, abs=0.1), (lin.g, xi.grad)
    assert torch.allclose(lin.H, lin.H.T, atol=1e-3 * float(lin.H.abs().max()))
    assert float(torch.linalg.eigvalsh(lin.H.double()).min()) > 0
    other = linearise(T0, batch.dirs_cam, batch.rgb, batch.depth, None, fmap.view, fmap.decoder, weights=weights,
                      eps_depth=1e-12, eps_color=1e-12, **{**kwargs, "mask_in_front": not mask_in_front})
    assert other.cost != lin.cost, "the switch reaches the closed-form model"


@pytest.mark.parametrize("renormalise", [False, True])
def test_colour_jacobian_matches_autograd_through_render_rays(trained, frames, renormalise):
    """The rendered colour's twist Jacobian (R, 3, 6) against autograd through render_rays,
    with the colour over every sample's weight or renormalised over the samples above a
    high threshold (the cpu tracker's): the weights' part and the colour field's part both."""
    fmap, batch, kwargs, _ = _linearisation_inputs(trained, frames, n=48)
    kwargs.update(color_weight_eps=0.05 if renormalise else 1e-5, renormalise_color=renormalise)
    T0 = gt_pose(frames[0]) @ se3_exp(torch.tensor([0.01, -0.01, 0.005, 0.01, 0.0, -0.01]))
    rendered = render_with_jacobians(T0, batch.dirs_cam, fmap.view, fmap.decoder, **kwargs)
    n = batch.depth.shape[0]

    def color_at(xi: torch.Tensor) -> torch.Tensor:
        T = T0 @ se3_exp(xi)
        return render_rays(T[:3, 3].expand(n, 3), batch.dirs_cam @ T[:3, :3].T, fmap.view, fmap.decoder,
                           **kwargs).color

    reference = torch.autograd.functional.jacobian(color_at, torch.zeros(6))  # (R, 3, 6)
    assert torch.allclose(rendered.color, color_at(torch.zeros(6)).detach(), atol=1e-5)
    hit = rendered.hit
    err = (rendered.J_color[hit] - reference[hit]).norm() / reference[hit].norm()
    assert float(err) < 1e-3, float(err)


def test_the_hand_written_reverse_pass_matches_autograd(trained, frames):
    """``field_with_gradients`` (the trunk's reverse pass by hand, its outputs kept for the
    colour pass) against its autograd twin, and the colour pass with and without them."""
    from slam.gauss_newton import color_with_gradients, field_with_gradients, field_with_gradients_autograd
    from slam.render import ray_voxel_intersections, sample_points_from_hits

    fmap, batch, kwargs, _ = _linearisation_inputs(trained, frames, n=96)
    T = gt_pose(frames[0])
    dirs = batch.dirs_cam @ T[:3, :3].T
    origins = T[:3, 3].expand(dirs.shape[0], 3)
    hits = ray_voxel_intersections(origins, dirs, kwargs["near"], kwargs["far"], fmap.view.voxel_codes,
                                   fmap.view.voxel_size, kwargs["max_hits"])
    samples = sample_points_from_hits(hits, kwargs["step"], torch.full((dirs.shape[0],), 0.5))
    points = origins[samples.ray_index] + samples.t[:, None] * dirs[samples.ray_index]
    with torch.no_grad():
        fast = field_with_gradients(points, samples.voxel_index, fmap.view, fmap.decoder, samples.segments)
    plain = field_with_gradients_autograd(points, samples.voxel_index, fmap.view, fmap.decoder, samples.segments)
    assert points.shape[0] > 500 and len(fast.hidden) == len(fmap.decoder.trunk_linears())
    torch.testing.assert_close(fast.sdf, plain.sdf, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(fast.grad_sdf, plain.grad_sdf, rtol=1e-4, atol=1e-4)
    active = torch.arange(0, points.shape[0], 3)
    with torch.no_grad():
        rgb_fast, grad_fast = color_with_gradients(fast, fmap.decoder, active)
        rgb_plain, grad_plain = color_with_gradients(plain, fmap.decoder, active)
    torch.testing.assert_close(rgb_fast, rgb_plain, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(grad_fast, grad_plain, rtol=1e-4, atol=1e-5)


def test_one_render_serves_several_ray_weightings(trained, frames):
    """The tracker renders its first pose once and weighs it twice (all rays, then without
    the outliers): the same model as linearising from scratch each time."""
    fmap, batch, kwargs, weights = _linearisation_inputs(trained, frames)
    T0 = gt_pose(frames[0]) @ se3_exp(torch.tensor([0.01, -0.01, 0.005, 0.01, 0.0, -0.01]))
    rendered = render_with_jacobians(T0, batch.dirs_cam, fmap.view, fmap.decoder, **kwargs)
    keep = (torch.arange(batch.depth.shape[0]) % 3 != 0).float()
    for ray_weight in (None, keep):
        plain = linearise(T0, batch.dirs_cam, batch.rgb, batch.depth, ray_weight, fmap.view, fmap.decoder,
                          weights=weights, miss_cost=0.5, **kwargs)
        reused = linearise_rendered(rendered, batch.rgb, batch.depth, ray_weight, weights=weights, miss_cost=0.5)
        assert reused.cost == pytest.approx(plain.cost, rel=1e-6)
        assert torch.allclose(reused.H, plain.H, rtol=1e-5, atol=1e-6 * float(plain.H.abs().max()))
        assert torch.allclose(reused.g, plain.g, rtol=1e-5, atol=1e-6 * float(plain.g.abs().max()))
        assert torch.equal(reused.hit, plain.hit)


def test_a_render_without_jacobians_has_the_same_values_and_loss(trained, frames):
    """The tracker's feature check compares losses only: ``jacobians=False`` renders the same
    depth, colour and SDF (through the decoder's fast path) and so the same cost."""
    fmap, batch, kwargs, weights = _linearisation_inputs(trained, frames)
    T0 = gt_pose(frames[0]) @ se3_exp(torch.tensor([0.01, -0.01, 0.005, 0.01, 0.0, -0.01]))
    full = render_with_jacobians(T0, batch.dirs_cam, fmap.view, fmap.decoder, **kwargs)
    values = render_with_jacobians(T0, batch.dirs_cam, fmap.view, fmap.decoder, jacobians=False, **kwargs)
    assert torch.equal(values.hit, full.hit) and torch.equal(values.t, full.t)
    for name in ("depth", "W", "color", "s"):
        assert torch.allclose(getattr(values, name), getattr(full, name), atol=1e-5), name
    assert not bool(values.J_depth.any()) and not bool(values.J_s.any())
    cost = linearise_rendered(values, batch.rgb, batch.depth, None, weights=weights, miss_cost=0.5).cost
    assert cost == pytest.approx(linearise_rendered(full, batch.rgb, batch.depth, None, weights=weights,
                                                    miss_cost=0.5).cost, rel=1e-5)


def test_a_ray_that_leaves_the_map_costs_miss_cost(trained, frames):
    fmap, batch, kwargs, weights = _linearisation_inputs(trained, frames, n=64)
    T = gt_pose(frames[0])
    args = (batch.dirs_cam, batch.rgb, batch.depth)
    keep = torch.ones(64)
    base = linearise(T, *args, keep, fmap.view, fmap.decoder, weights=weights, miss_cost=10.0, **kwargs)
    assert bool(base.hit.all())
    far = T.clone()
    far[:3, 3] += torch.tensor([50.0, 0.0, 0.0])
    gone = linearise(far, *args, keep, fmap.view, fmap.decoder, weights=weights, miss_cost=10.0, **kwargs)
    assert not bool(gone.hit.any()) and gone.cost == pytest.approx(10.0)
    reference = linearise(far, *args, keep, fmap.view, fmap.decoder, weights=weights, **kwargs)
    assert reference.cost == 0.0, "without miss_cost a pose off the map looks perfect: why it exists"


def test_limit_step_scales_the_whole_twist():
    delta = torch.tensor([0.3, 0.0, 0.4, 0.0, 0.02, 0.0])
    out = limit_step(delta, 0.05, 0.05)
    assert torch.allclose(out, delta * 0.1) and float(out[:3].norm()) == pytest.approx(0.05)
    small = torch.tensor([0.01, 0.0, 0.0, 0.0, 0.0, 0.01])
    assert torch.equal(limit_step(small, 0.05, 0.05), small)
    assert float(limit_step(torch.tensor([0.0, 0, 0, 0.5, 0, 0]), 0.05, 0.05)[3]) == pytest.approx(0.05)


def test_tracking_ignores_voxels_the_mapper_never_optimised(trained, frames):
    snap = trained.mapper.snapshot()
    full = FrozenMap(snap, CONFIG, CPU)
    assert snap.corner_updates is not None and int(snap.corner_updates.max()) > 0
    # After 100 steps nearly every voxel was sampled (a few lie behind surfaces, past every ray).
    kept = full.view.voxel_codes.numel()
    assert 0.9 * snap.voxel_codes.size < kept == int((snap.corner_updates[snap.voxel_corners] > 0).all(1).sum())
    untouched = dataclasses.replace(snap, corner_updates=np.zeros_like(snap.corner_updates))
    assert FrozenMap(untouched, CONFIG, CPU).view.voxel_codes.numel() == 0
    one_new = snap.corner_updates.copy()
    one_new[snap.voxel_corners[3, 0]] = 0
    expected = int((one_new[snap.voxel_corners] > 0).all(1).sum())
    partial = FrozenMap(dataclasses.replace(snap, corner_updates=one_new), CONFIG, CPU)
    assert partial.view.voxel_codes.numel() == expected < snap.voxel_codes.size
    everything = replace(CONFIG, tracking=replace(CONFIG.tracking, min_corner_updates=0))
    assert FrozenMap(untouched, everything, CPU).view.voxel_codes.numel() == snap.voxel_codes.size


def _exact_matches(frame: TensorFrame, T_guess: torch.Tensor, n: int = 60) -> Correspondences:
    """n pixels of ``frame`` with their GT world points: what a perfect feature matcher gives."""
    pick = frame.valid[torch.randperm(frame.valid.numel(), generator=torch.Generator().manual_seed(5))[:n]]
    v, u = pick // frame.width, pick % frame.width
    z = frame.depth.reshape(-1)[pick].double()
    K = frame.K.double()
    x_cam = torch.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
    T_gt = gt_pose(frame).double()
    points = x_cam @ T_gt[:3, :3].T + T_gt[:3, 3]
    return Correspondences(points.numpy(), torch.stack([u, v], -1).double().numpy(), K.numpy(),
                           np.ones(n), T_guess.double().numpy())


def _offset(T: torch.Tensor, metres: float, degrees: float) -> torch.Tensor:
    delta = torch.eye(4)
    delta[:3, :3] = so3_exp(torch.deg2rad(torch.tensor([0.0, degrees, 0.0])))
    delta[:3, 3] = torch.tensor([metres, 0.0, 0.0])
    return T @ delta


@pytest.mark.parametrize("optimizer", ["adam", "gauss_newton"])
def test_feature_matches_start_tracking_at_their_pnp_pose_and_pull_it_to_them(trained, frames, optimizer):
    config = replace(CONFIG, tracking=replace(CONFIG.tracking, optimizer=optimizer, feature_weight=0.02))
    fmap = FrozenMap(trained.mapper.snapshot(), config, CPU)
    T_gt = gt_pose(frames[0])
    T_near = _offset(T_gt, 0.02, 1.0)
    # The PnP pose replaces a guess the dense loss alone would not come back from ...
    with_matches = Tracker(config, CPU).track(frames[0], fmap, _offset(T_gt, 0.2, 10.0),
                                              _exact_matches(frames[0], T_near))
    assert with_matches.ok, with_matches.reason
    # ... and exact correspondences pull the estimate closer to GT than the map alone does.
    without = Tracker(config, CPU).track(frames[0], fmap, T_near)
    t1, r1 = pose_error(with_matches.T_world_cam, T_gt)
    t0, r0 = pose_error(without.T_world_cam, T_gt)
    assert t1 < 0.6 * t0 and t1 < 0.006, (t1, t0, r1, r0)


def test_feature_matches_with_an_implausible_pnp_pose_are_ignored(trained, frames):
    config = replace(CONFIG, tracking=replace(CONFIG.tracking, feature_weight=0.02))
    fmap = FrozenMap(trained.mapper.snapshot(), config, CPU)
    T_near = _offset(gt_pose(frames[0]), 0.02, 1.0)
    far_away = T_near.clone()
    far_away[:3, 3] += 50.0  # RANSAC agreed on a wrong pose
    result = Tracker(config, CPU).track(frames[0], fmap, T_near, _exact_matches(frames[0], far_away))
    without = Tracker(config, CPU).track(frames[0], fmap, T_near)
    assert result.ok and torch.allclose(result.T_world_cam, without.T_world_cam)


def test_motion_prior_holds_directions_the_data_does_not_observe():
    """A plain wall: the data term fixes depth (z) and the two tilts, not x, y and roll. With
    a (noisy) gradient in every direction, the undamped step follows the noise along the
    unobserved ones; the prior keeps them near zero and leaves the observed ones alone."""
    from slam.gauss_newton import Linearisation, MotionPrior, damped_step

    H = torch.diag(torch.tensor([1e-6, 1e-6, 100.0, 30.0, 30.0, 1e-6]))
    g = torch.tensor([1e-4, -1e-4, -1.0, 0.3, -0.3, 1e-4])
    empty = torch.zeros(0)
    lin = Linearisation(1.0, H, g, empty, empty.bool(), empty)
    free = damped_step(lin, 1e-3)
    prior = MotionPrior.scaled_to(lin, 0.01)
    held = damped_step(prior.added_to(lin, torch.zeros(6)), 1e-3)
    assert float(free[[0, 1, 5]].abs().min()) > 10.0, "the noise direction runs away without the prior"
    assert float(held[[0, 1, 5]].abs().max()) < 0.1
    observed = [2, 3, 4]
    assert torch.allclose(held[observed], free[observed], rtol=0.02)
    # The prior's own terms: cost w xi^2, gradient 2 w xi, curvature 2 w.
    xi = torch.tensor([0.01, 0.0, 0.0, 0.0, 0.02, 0.0])
    at = prior.added_to(lin, xi)
    assert at.cost == pytest.approx(1.0 + float((prior.w * xi * xi).sum()))
    assert torch.allclose(at.g - g, 2 * prior.w * xi) and torch.allclose(at.H - H, torch.diag(2 * prior.w))
    from slam.config import ConfigError, TrackingConfig

    with pytest.raises(ConfigError, match="motion_prior"):
        TrackingConfig(motion_prior=-0.1)


def test_tracking_with_a_motion_prior_still_recovers_a_perturbed_pose(trained, frames):
    """On a view that observes all six directions the prior (1 % of the curvature) must not
    hold the pose back from the data's optimum."""
    config = replace(CONFIG, tracking=replace(CONFIG.tracking, optimizer="gauss_newton", motion_prior=0.01))
    fmap = FrozenMap(trained.mapper.snapshot(), config, CPU)
    T_gt = gt_pose(frames[0])
    T_init = _offset(T_gt, 0.02, 1.0)
    with_prior = Tracker(config, CPU).track(frames[0], fmap, T_init)
    plain = Tracker(replace(config, tracking=replace(config.tracking, motion_prior=0.0)), CPU).track(
        frames[0], fmap, T_init)
    assert with_prior.ok
    t0, r0 = pose_error(T_init, T_gt)
    t1, r1 = pose_error(with_prior.T_world_cam, plain.T_world_cam)
    assert t1 < 0.25 * t0 and r1 < 0.25 * r0, (t1, r1)


def _matches_seen_from(frame: TensorFrame, T_cam: torch.Tensor, n: int = 60) -> Correspondences:
    """Matches that agree with each other on the camera pose ``T_cam`` (their PnP pose)
    rather than the frame's GT: RANSAC agreeing on a wrong pose (repeated texture)."""
    exact = _exact_matches(frame, T_cam, n)
    D = (T_cam.double() @ se3_inverse(gt_pose(frame).double())).numpy()
    return replace(exact, points_world=exact.points_world @ D[:3, :3].T + D[:3, 3])


def test_dense_check_drops_features_whose_pose_the_depth_does_not_support(trained, frames):
    config = replace(CONFIG, tracking=replace(CONFIG.tracking, optimizer="gauss_newton", feature_weight=0.02,
                                              feature_dense_check=True))
    unchecked = replace(config, tracking=replace(config.tracking, feature_dense_check=False))
    fmap = FrozenMap(trained.mapper.snapshot(), config, CPU)
    T_gt = gt_pose(frames[0])
    guess = _offset(T_gt, 0.01, 0.5)
    wrong = _matches_seen_from(frames[0], _offset(T_gt, 0.08, 0.0))
    checked = Tracker(config, CPU).track(frames[0], fmap, guess, wrong)
    pulled = Tracker(unchecked, CPU).track(frames[0], fmap, guess, wrong)
    dense_only = Tracker(config, CPU).track(frames[0], fmap, guess)
    assert torch.allclose(checked.T_world_cam, dense_only.T_world_cam)
    assert pose_error(pulled.T_world_cam, T_gt)[0] > 2 * pose_error(checked.T_world_cam, T_gt)[0]
    # Right matches and a far guess (fast motion): the check keeps them.
    right = _exact_matches(frames[0], _offset(T_gt, 0.005, 0.2))
    kept = Tracker(config, CPU).track(frames[0], fmap, _offset(T_gt, 0.15, 6.0), right)
    assert kept.ok and pose_error(kept.T_world_cam, T_gt)[0] < 0.01


def test_masked_median_on_worked_values():
    from slam.tracking import masked_median

    v = torch.tensor([[3.0, 1.0, 2.0, 9.0], [5.0, 4.0, 0.0, 0.0]])
    m = torch.tensor([[True, True, True, False], [True, False, False, False]])
    assert masked_median(v, m).tolist() == [2.0, 5.0]
    assert float(masked_median(v[0], torch.zeros(4, dtype=torch.bool))) == float("inf")
