"""Static-shape rendering (slam.padded) against the flat renderer it twins (slam.render).

One small map is trained once per module (synthetic orbit, test preset, GT poses); the
padded samples, renders, losses and gradients are compared with ``render_rays`` on the
same rays and sample offsets.
"""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from slam.config import preset
from slam.data import open_sequence
from slam.frames import prepare_frame, sample_pixels
from slam.losses import LossWeights, compute_losses
from slam.mapping import Mapper, TrackedFrame, training_far
from slam.padded import (
    band_grid_size,
    color_slots,
    color_window,
    first_zero_crossing_padded,
    grid_samples,
    grid_size,
    pack_samples,
    render_padded,
)
from slam.render import TrainingThinning, ray_voxel_intersections, render_rays, sample_points_from_hits

CPU = torch.device("cpu")
CONFIG = preset("test")
R_ = CONFIG.render
WEIGHTS = LossWeights(0.5, 1.0, 5000.0, 10.0)


@pytest.fixture(scope="module", autouse=True)
def single_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def scene():
    frames = list(open_sequence("synthetic:orbit?frames=100&width=80&height=60", max_frames=3))
    config = replace(CONFIG, mapping=replace(CONFIG.mapping, first_frame_iterations=40))
    mapper = Mapper(config, CPU)
    tfs = [prepare_frame(f, None, CPU, config.voxel.max_depth) for f in frames]
    for tf, f in zip(tfs[:2], frames):
        mapper.process(TrackedFrame(tf, torch.from_numpy(f.T_world_cam_gt if hasattr(f, "T_world_cam_gt")
                                                         else f.T_world_cam).float()))
    return mapper, tfs, frames


def _rays(scene, num=256, seed=0):
    mapper, tfs, frames = scene
    batch = sample_pixels(tfs[2], num, torch.Generator().manual_seed(seed))
    T = torch.from_numpy(frames[2].T_world_cam).float()
    n = batch.depth.shape[0]
    dirs = batch.dirs_cam @ T[:3, :3].T
    origins = T[:3, 3].expand(n, 3)
    near = torch.full((n,), 0.05)
    far = training_far(batch.depth, R_.truncation, R_.max_distance)
    return batch, origins, dirs, near, far


def _step(mapper):
    return R_.step_ratio * mapper.current.voxels.voxel_size


def _flat_set(samples):
    return {(int(r), round(float(t), 5), int(v)) for r, t, v in zip(samples.ray_index, samples.t, samples.voxel_index)}


def _padded_set(p):
    r = torch.arange(p.num_rays)[:, None].expand_as(p.t)
    v = p.valid
    return {(int(a), round(float(b), 5), int(c)) for a, b, c in zip(r[v], p.t[v], p.voxel_index[v])}


@pytest.mark.parametrize("max_hits", [0, R_.max_hits, 2])
def test_grid_samples_are_the_traversals_samples(scene, max_hits):
    mapper, _, _ = scene
    _, o, d, near, far = _rays(scene)
    view = mapper.current.view()
    step = _step(mapper)
    offsets = torch.rand(o.shape[0], generator=torch.Generator().manual_seed(1))
    hits = ray_voxel_intersections(o, d, near, far, view.voxel_codes, view.voxel_size, max_hits)
    flat = _flat_set(sample_points_from_hits(hits, step, offsets))
    G = grid_size(0.05, float(far.max()), step)
    grid = grid_samples(o, d, near, far, step, view, G, max_hits=max_hits, offsets=offsets)
    padded = pack_samples(grid, int(grid.counts().max()))
    assert int(padded.dropped.sum()) == 0
    got = _padded_set(padded)
    assert len(flat) > 1000
    # A voxel corner clipped by less than a step is a traversal hit without samples: with a
    # cap of M_h voxels the grid then reaches one voxel further on that ray (a superset).
    assert flat <= got
    extra = len(got - flat) / len(flat)
    assert extra <= {0: 0.0, R_.max_hits: 0.02}.get(max_hits, 1.0), extra
    assert torch.equal(grid.grid_counts, grid.counts())


def test_packing_keeps_the_last_samples_in_order_and_counts_the_dropped(scene):
    mapper, _, _ = scene
    _, o, d, near, far = _rays(scene, 64)
    view = mapper.current.view()
    step = _step(mapper)
    grid = grid_samples(o, d, near, far, step, view, grid_size(0.05, float(far.max()), step))
    counts = grid.counts()
    full = pack_samples(grid, int(counts.max()))
    cut = pack_samples(grid, 5)
    assert torch.equal(cut.dropped, (counts - 5).clamp(min=0))
    assert torch.equal(cut.t[cut.valid], full.t[:, -5:][full.valid[:, -5:]])
    # right-aligned: valid slots are a suffix, in increasing t
    assert bool((cut.valid[:, 1:] >= cut.valid[:, :-1]).all())
    t = torch.where(full.valid, full.t, torch.full_like(full.t, -1.0))
    assert bool((t[:, 1:] >= t[:, :-1]).all())


def test_first_zero_crossing_and_colour_window_examples():
    sdf = torch.tensor([[9.0, 0.5, -0.5], [1.0, 1.0, 1.0]])
    t = torch.tensor([[0.5, 1.0, 1.2], [1.0, 1.1, 1.2]])
    valid = torch.tensor([[False, True, True], [True, True, True]])
    crossing = first_zero_crossing_padded(sdf, t, valid)
    assert torch.allclose(crossing, torch.tensor([1.1, float("inf")]))
    # a sign change into an invalid slot is no crossing
    assert torch.isinf(first_zero_crossing_padded(torch.tensor([[-1.0, 1.0]]), t[:1, :2],
                                                  torch.tensor([[False, True]]))).all()
    w = torch.tensor([[0.0, 0.2, 0.1, 0.0], [0.0, 0.0, 0.0, 0.3], [0.0, 0.0, 0.0, 0.0]])
    index, active = color_window(w, 0.05, 3)
    assert index.tolist() == [[0, 1, 2], [1, 2, 3], [0, 1, 2]]
    assert active.tolist() == [[False, True, True], [False, False, True], [False, False, False]]


@pytest.mark.parametrize("renormalise", [False, True])
def test_render_padded_matches_render_rays(scene, renormalise):
    mapper, _, _ = scene
    batch, o, d, near, far = _rays(scene)
    submap = mapper.current
    view = submap.view()
    step = _step(mapper)
    offsets = torch.full((o.shape[0],), 0.5)
    kw = dict(truncation=R_.truncation, mask_in_front=True, renormalise_color=renormalise, color_weight_eps=1e-5)
    with torch.no_grad():
        ref = render_rays(o, d, view, submap.decoder, near=near, far=far, step=step, max_hits=0, offsets=offsets, **kw)
        grid = grid_samples(o, d, near, far, step, view, grid_size(0.05, float(far.max()), step), offsets=offsets)
        padded = pack_samples(grid, int(grid.counts().max()))
        out = render_padded(o, d, view, submap.decoder, padded,
                            color_slots=color_slots(R_.truncation, step, padded.slots), **kw)
    assert torch.equal(out.hit, ref.hit)
    assert torch.allclose(out.weight_sum, ref.weight_sum, atol=1e-5)
    assert torch.allclose(out.depth, ref.depth, atol=1e-4)
    assert torch.allclose(out.depth_var, ref.depth_var, atol=1e-5)
    # Rays without a surface crossing colour only a window of their weighted samples.
    crossing = torch.isfinite(first_zero_crossing_padded(out.sdf.view(padded.t.shape), padded.t, padded.valid))
    assert int(crossing.sum()) > 0.5 * o.shape[0]
    assert torch.allclose(out.color[crossing], ref.color[crossing], atol=1e-5)
    assert (out.color - ref.color).abs().mean() < 0.01


@pytest.mark.parametrize("normalisation", ["ray", "slots"])
@pytest.mark.parametrize("thin", [False, True])
def test_padded_losses_and_gradients_match_the_flat_ones(scene, normalisation, thin):
    mapper, _, _ = scene
    batch, o, d, near, far = _rays(scene)
    submap = mapper.current
    view = submap.view()
    step = _step(mapper)
    n = o.shape[0]
    offsets = torch.rand(n, generator=torch.Generator().manual_seed(3))
    thinning = None
    if thin:
        phase = torch.randint(2, (n,), generator=torch.Generator().manual_seed(4))
        thinning = TrainingThinning(batch.depth, R_.truncation, R_.max_distance, 2, phase)
    kw = dict(truncation=R_.truncation, mask_in_front=True, renormalise_color=True, color_weight_eps=1e-5)

    def grads(render):
        submap.decoder.zero_grad()
        emb = submap.voxels.embeddings
        emb.grad = None
        out = render()
        losses = compute_losses(out, batch.rgb, batch.depth, R_.truncation, WEIGHTS, max_depth=R_.max_distance,
                                normalisation=normalisation)
        losses.total.backward()
        return losses, emb.grad.clone(), submap.decoder.sdf_head.weight.grad.clone()

    ref, g_emb_ref, g_dec_ref = grads(lambda: render_rays(o, d, view, submap.decoder, near=near, far=far, step=step,
                                                          max_hits=0, offsets=offsets, thinning=thinning, **kw))

    def padded():
        grid = grid_samples(o, d, near, far, step, view, grid_size(0.05, float(far.max()), step), offsets=offsets,
                            thinning=thinning)
        p = pack_samples(grid, int(grid.counts().max()))
        return render_padded(o, d, view, submap.decoder, p, color_slots=color_slots(R_.truncation, step, p.slots), **kw)

    got, g_emb, g_dec = grads(padded)
    for name in ("total", "rgb", "depth", "fs", "sdf"):
        a, b = float(getattr(got, name).detach()), float(getattr(ref, name).detach())
        assert a == pytest.approx(b, rel=2e-3, abs=1e-6), name
    # The colour of rays without a crossing (a window of their samples) differs a little.
    for g, g_ref in ((g_emb, g_emb_ref), (g_dec, g_dec_ref)):
        assert float((g - g_ref).norm() / g_ref.norm()) < 0.02


def test_band_grid_covers_the_tracking_band():
    assert band_grid_size(2.0, 0.1, 0.02) >= 2 * 2.0 * 0.1 / 0.02 + 1
    assert grid_size(0.05, 1.0, 0.1) == 16


def test_map_view_find_is_lookup_of_the_morton_code(scene):
    from slam.render import MapView
    from slam.voxels import lookup_sorted, morton_encode

    view = scene[0].current.view()
    ijk = torch.randint(-40, 40, (20000, 3), generator=torch.Generator().manual_seed(5))
    found = view.find(ijk)
    assert torch.equal(found, lookup_sorted(view.voxel_codes, morton_encode(ijk)))
    assert int((found >= 0).sum()) > 0
    empty = MapView(view.voxel_codes[:0], view.voxel_corners[:0], view.embeddings, view.voxel_size)
    assert bool((empty.find(ijk) == -1).all())
