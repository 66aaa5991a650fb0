"""The four losses (slam.losses) on hand-made render outputs, and the decoder (slam.decoder)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from slam.config import DecoderConfig, preset
from slam.decoder import Decoder
from slam.losses import LossWeights, compute_losses
from slam.render import RaySamples, RenderOutput, TrainingThinning, thin_training_samples

TR = 0.1


@pytest.fixture(scope="module", autouse=True)
def single_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def hand_made():
    """Four rays, tr = 0.1, values worked out by hand in the tests below.

    ray 0: depth 1.0; samples at 0.5, 0.85 (free space: t < 0.9), 0.95, 1.05 (SDF band) and
           1.15 (past the band, in neither term).
    ray 1: invalid depth (0): counts for colour only.
    ray 2: no samples (hit False): counts nowhere even though its colour is far off.
    ray 3: depth 2.0; one free-space sample at 1.0 and one band sample at 2.05.
    """
    ray = torch.tensor([0, 0, 0, 0, 0, 1, 1, 3, 3])
    t = torch.tensor([0.5, 0.85, 0.95, 1.05, 1.15, 0.5, 0.95, 1.0, 2.05], dtype=torch.float64)
    sdf = torch.tensor([0.8, 0.4, 0.5, -0.3, -0.9, 1.0, 0.2, 0.6, -0.2], dtype=torch.float64, requires_grad=True)
    color = torch.tensor([[0.6, 0.5, 0.5], [0.1, 0.4, 0.1], [0.0, 0.0, 0.0], [0.2, 0.2, 0.5]],
                         dtype=torch.float64, requires_grad=True)
    depth = torch.tensor([1.1, 5.0, 0.0, 1.8], dtype=torch.float64, requires_grad=True)
    out = RenderOutput(color=color, depth=depth, weight_sum=torch.ones(4, dtype=torch.float64),
                       hit=torch.tensor([True, True, False, True]), depth_var=torch.zeros(4, dtype=torch.float64),
                       samples=RaySamples(ray, t, torch.zeros_like(ray)), sdf=sdf)
    rgb_gt = torch.tensor([[0.5, 0.5, 0.5], [0.1, 0.2, 0.1], [1.0, 1.0, 1.0], [0.2, 0.2, 0.2]], dtype=torch.float64)
    depth_gt = torch.tensor([1.0, 0.0, 2.0, 2.0], dtype=torch.float64)
    return out, rgb_gt, depth_gt


WEIGHTS = LossWeights(rgb=0.5, depth=1.0, sdf=5000.0, fs=10.0)


def test_each_loss_on_hand_worked_values():
    out, rgb_gt, depth_gt = hand_made()
    losses = compute_losses(out, rgb_gt, depth_gt, TR, WEIGHTS)
    # colour: rays 0, 1, 3; |diff| sums 0.1 + 0.2 + 0.3 over 9 channels
    assert losses.rgb.item() == pytest.approx(0.6 / 9)
    # depth: rays 0 and 3: |1.1 - 1| and |1.8 - 2|
    assert losses.depth.item() == pytest.approx(0.15)
    # free space, per ray then over rays: ray 0 ((0.8-1)^2 + (0.4-1)^2) / 2 = 0.2, ray 3 0.16
    assert losses.fs.item() == pytest.approx(0.18)
    # SDF: ray 0 ((0.95 + 0.05 - 1)^2 + (1.05 - 0.03 - 1)^2) / 2 = 0.0002, ray 3 0.03^2
    assert losses.sdf.item() == pytest.approx(0.00055)
    expected_total = 0.5 * 0.6 / 9 + 0.15 + 10 * 0.18 + 5000 * 0.00055
    assert losses.total.item() == pytest.approx(expected_total)
    assert set(losses.as_floats()) == {"total", "rgb", "depth", "fs", "sdf"}


def release_sdf_terms(out, depth_gt, tr, max_depth=10.0):
    """The Vox-Fusion release's free-space and SDF terms (``criterion.py``, ``get_sdf_loss``)
    as it computes them: (hit rays, most samples of any ray) tensors padded behind each ray
    with z = 10 m (its MAX_DEPTH) and s = 1, means over every slot, scaled by the other
    term's share of the front and band samples."""
    rays = torch.nonzero(out.hit, as_tuple=True)[0]
    r = out.samples.ray_index
    width = int(torch.bincount(r)[rays].max())
    z = torch.full((len(rays), width), 10.0, dtype=torch.float64)
    s = torch.ones(len(rays), width, dtype=torch.float64)
    for row, ray in enumerate(rays.tolist()):
        sel = r == ray
        z[row, : int(sel.sum())] = out.samples.t[sel]
        s[row, : int(sel.sum())] = out.sdf.detach()[sel]
    d = depth_gt[rays][:, None].expand_as(z)
    front = (z < d - tr).double()
    back = (z > d + tr).double()
    sdf_mask = (1 - front) * (1 - back) * ((d > 0) & (d < max_depth)).double()
    n_fs, n_sdf = front.sum(), sdf_mask.sum()
    fs = ((s * front - front) ** 2).mean() * (1 - n_fs / (n_fs + n_sdf))
    sdf = (((z + s * tr) * sdf_mask - d * sdf_mask) ** 2).mean() * (1 - n_sdf / (n_fs + n_sdf))
    return float(fs), float(sdf)


def test_slot_normalisation_is_the_releases_padded_mean():
    # loss.normalisation = "slots" (issue 21 item 3). Hit rays 0, 1, 3 with 5, 2, 2 samples:
    # 15 slots; front sums 0.04 + 0.36 + 0.16 over 3 samples, band 0 + 0.0004 + 0.0009 over 3.
    out, rgb_gt, depth_gt = hand_made()
    ray = compute_losses(out, rgb_gt, depth_gt, TR, WEIGHTS)
    slots = compute_losses(out, rgb_gt, depth_gt, TR, WEIGHTS, normalisation="slots")
    assert slots.fs.item() == pytest.approx(0.56 / 15 * 3 / 6)
    assert slots.sdf.item() == pytest.approx(0.0013 / 15 * 3 / 6)
    assert (slots.fs.item(), slots.sdf.item()) == pytest.approx(release_sdf_terms(out, depth_gt, TR))
    assert slots.rgb.item() == ray.rgb.item() and slots.depth.item() == ray.depth.item()
    # Rays with different sample counts: the two differ, and not by one common factor.
    assert slots.fs.item() / ray.fs.item() != pytest.approx(slots.sdf.item() / ray.sdf.item(), rel=0.01)
    assert slots.total.item() != pytest.approx(ray.total.item())
    slots.total.backward()
    assert bool((out.sdf.grad[[0, 1, 3, 7, 8]] != 0).all()) and out.sdf.grad[[4, 5, 6]].tolist() == [0.0] * 3


def test_with_equal_counts_slot_means_are_per_ray_means_times_one_factor():
    # Every ray with N samples, f of them in front and b in the band: per ray the means are
    # sum / f and sum / b, per slot sum / N times b / (f + b) and f / (f + b), so both terms
    # shrink by the same f b / (N (f + b)) and only their weight against colour and depth moves.
    gen = torch.Generator().manual_seed(0)
    rays, N, f, b = 6, 8, 4, 2
    depth_gt = 1.0 + torch.rand(rays, generator=gen, dtype=torch.float64)
    offsets = torch.tensor([-0.5, -0.4, -0.3, -0.2, -0.05, 0.05, 0.15, 0.3], dtype=torch.float64)
    t = (depth_gt[:, None] + offsets[None]).reshape(-1)
    ray_index = torch.arange(rays).repeat_interleave(N)
    sdf = torch.rand(rays * N, generator=gen, dtype=torch.float64) * 2 - 1
    out = RenderOutput(color=torch.zeros(rays, 3, dtype=torch.float64), depth=depth_gt.clone(),
                       weight_sum=torch.ones(rays, dtype=torch.float64), hit=torch.ones(rays, dtype=torch.bool),
                       depth_var=torch.zeros(rays, dtype=torch.float64),
                       samples=RaySamples(ray_index, t, torch.zeros_like(ray_index)), sdf=sdf)
    rgb_gt = torch.zeros(rays, 3, dtype=torch.float64)
    ray = compute_losses(out, rgb_gt, depth_gt, TR, WEIGHTS)
    slots = compute_losses(out, rgb_gt, depth_gt, TR, WEIGHTS, normalisation="slots")
    factor = f * b / (N * (f + b))
    assert slots.fs.item() == pytest.approx(ray.fs.item() * factor)
    assert slots.sdf.item() == pytest.approx(ray.sdf.item() * factor)
    with pytest.raises(ValueError, match="normalisation"):
        compute_losses(out, rgb_gt, depth_gt, TR, WEIGHTS, normalisation="padded")


@pytest.mark.parametrize("normalisation", ["ray", "slots"])
def test_thinned_samples_give_the_full_losses_on_average_over_the_phases(normalisation):
    """``thin_training_samples`` (mapping.thin_samples) keeps each free-space sample in one
    phase of the stride and weights it by the stride; with free-space counts that are
    multiples of the stride, the mean over the phases is the full free-space term, and the
    band's term (every sample kept, the width from the counts before thinning) is exact."""
    tr, stride = 0.1, 3
    gen = torch.Generator().manual_seed(0)
    depth_gt = torch.tensor([1.0, 2.0, 0.0, 1.5], dtype=torch.float64)
    # ray 0: 6 free, 3 band, 2 behind; ray 1: 9 free, 5 band; ray 2: invalid; ray 3: 3 free, 4 band, 1 behind
    per_ray = [(torch.linspace(0.2, 0.85, 6), torch.tensor([0.92, 1.0, 1.08]), torch.tensor([1.2, 1.3])),
               (torch.linspace(0.3, 1.85, 9), torch.tensor([1.91, 1.95, 2.0, 2.05, 2.09]), torch.tensor([])),
               (torch.tensor([0.5, 0.7]), torch.tensor([]), torch.tensor([])),
               (torch.tensor([0.4, 0.8, 1.2]), torch.tensor([1.45, 1.5, 1.55, 1.58]), torch.tensor([1.7]))]
    t = torch.cat([torch.cat(parts) for parts in per_ray]).to(torch.float64)
    ray = torch.cat([torch.full((sum(len(p) for p in parts),), i) for i, parts in enumerate(per_ray)])
    sdf = torch.rand(t.numel(), generator=gen, dtype=torch.float64) * 2 - 1
    rgb_gt = torch.rand(4, 3, generator=gen, dtype=torch.float64)

    def losses(samples, sdf_values):
        out = RenderOutput(color=rgb_gt * 0.9, depth=depth_gt + 0.01, weight_sum=torch.ones(4, dtype=torch.float64),
                           hit=torch.ones(4, dtype=torch.bool), depth_var=torch.zeros(4, dtype=torch.float64),
                           samples=samples, sdf=sdf_values)
        return compute_losses(out, rgb_gt, depth_gt, tr, WEIGHTS, normalisation=normalisation)

    full = losses(RaySamples(ray, t, torch.zeros_like(ray)), sdf)
    value_of = {(r, round(v, 9)): s for r, v, s in zip(ray.tolist(), t.tolist(), sdf.tolist())}
    fs, sdf_terms = [], []
    for phase in range(stride):
        th = thin_training_samples(RaySamples(ray, t, torch.zeros_like(ray)),
                                   TrainingThinning(depth_gt, tr, 10.0, stride, torch.full((4,), phase)))
        assert th.t.numel() == t.numel() - 3 - 2 * (18 // 3)
        kept_sdf = torch.tensor([value_of[(r, round(v, 9))] for r, v in zip(th.ray_index.tolist(), th.t.tolist())],
                                dtype=torch.float64)
        thinned = losses(th, kept_sdf)
        fs.append(thinned.fs.item())
        sdf_terms.append(thinned.sdf.item())
        assert thinned.rgb.item() == full.rgb.item() and thinned.depth.item() == full.depth.item()
    assert sum(fs) / stride == pytest.approx(full.fs.item(), rel=1e-12)
    assert sdf_terms == pytest.approx([full.sdf.item()] * stride, rel=1e-12)
    assert max(fs) - min(fs) > 1e-3 * full.fs.item()  # each phase alone is a different estimate


def test_samples_outside_the_terms_get_no_gradient():
    out, rgb_gt, depth_gt = hand_made()
    losses = compute_losses(out, rgb_gt, depth_gt, TR, LossWeights(rgb=0.0, depth=0.0, sdf=1.0, fs=1.0))
    losses.total.backward()
    grad = out.sdf.grad
    # Sample 4 (past the band), ray 1's samples (invalid depth) feed neither SDF term.
    assert grad[[4, 5, 6]].tolist() == [0.0, 0.0, 0.0]
    assert bool((grad[[0, 1, 3, 7, 8]] != 0).all())
    assert abs(float(grad[2])) < 1e-9, "sample 2 sits on its target (zero residual)"


def test_ray_weight_drops_rays_from_every_term():
    out, rgb_gt, depth_gt = hand_made()
    losses = compute_losses(out, rgb_gt, depth_gt, TR, WEIGHTS, ray_weight=torch.tensor([1.0, 1.0, 1.0, 0.0]))
    assert losses.rgb.item() == pytest.approx(0.3 / 6)
    assert losses.depth.item() == pytest.approx(0.1)
    assert losses.fs.item() == pytest.approx(0.2)
    assert losses.sdf.item() == pytest.approx(0.0002)


def test_depth_beyond_max_depth_is_invalid_but_colour_still_counts():
    out, rgb_gt, depth_gt = hand_made()
    losses = compute_losses(out, rgb_gt, depth_gt, TR, WEIGHTS, max_depth=1.5)
    assert losses.rgb.item() == pytest.approx(0.6 / 9)
    assert losses.depth.item() == pytest.approx(0.1)
    assert losses.fs.item() == pytest.approx(0.2)
    assert losses.sdf.item() == pytest.approx(0.0002)


def test_no_usable_ray_gives_zero_losses_that_still_backpropagate():
    out, rgb_gt, depth_gt = hand_made()
    losses = compute_losses(out, rgb_gt, torch.zeros(4, dtype=torch.float64), TR, WEIGHTS,
                            ray_weight=torch.tensor([0.0, 0.0, 1.0, 0.0]))
    assert losses.as_floats() == {"total": 0.0, "rgb": 0.0, "depth": 0.0, "fs": 0.0, "sdf": 0.0}
    losses.total.backward()  # must not raise: the tracker calls backward unconditionally


def test_loss_gradients_point_the_right_way():
    out, rgb_gt, depth_gt = hand_made()
    compute_losses(out, rgb_gt, depth_gt, TR, WEIGHTS).total.backward()
    assert out.depth.grad[0] > 0 and out.depth.grad[3] < 0, "rendered depth pulled towards the target"
    assert out.depth.grad[1] == 0 and out.depth.grad[2] == 0
    assert out.sdf.grad[0] < 0, "free-space SDF below 1 is pushed up"
    assert not bool(out.color.grad[2].any())


# ------------------------------------------------------------------ decoder
@pytest.fixture(scope="module")
def decoder():
    torch.manual_seed(0)
    cfg = preset("test")
    return Decoder(cfg.decoder, cfg.voxel.embed_dim)


def test_decoder_shapes_and_colour_range(decoder):
    emb = torch.randn(37, 16)
    sdf, feature = decoder.sdf_and_feature(emb)
    assert sdf.shape == (37,) and feature.shape == (37, decoder.config.feature_dim)
    rgb = decoder.color(feature)
    assert rgb.shape == (37, 3) and bool((rgb > 0).all()) and bool((rgb < 1).all())
    assert decoder.sdf(emb).shape == (37,)
    assert decoder.sdf_and_feature(torch.zeros(0, 16))[0].shape == (0,)


def test_split_calls_equal_the_full_head(decoder):
    emb = torch.randn(50, 16, requires_grad=True)
    sdf, feature = decoder.sdf_and_feature(emb)
    sdf2, hidden = decoder.sdf_and_hidden(emb)
    feature2 = decoder.feature_from_hidden(hidden)
    assert torch.allclose(sdf, sdf2, atol=1e-6) and torch.allclose(feature, feature2, atol=1e-6)
    assert torch.allclose(decoder.sdf(emb), sdf, atol=1e-6)
    g1 = torch.autograd.grad(sdf.sum() + decoder.color(feature).sum(), emb)[0]
    g2 = torch.autograd.grad(sdf2.sum() + decoder.color(feature2).sum(), emb)[0]
    assert torch.allclose(g1, g2, atol=1e-6)


def linear_sizes(module: torch.nn.Module) -> list[tuple[int, int]]:
    return [(m.in_features, m.out_features) for m in module.modules() if isinstance(m, torch.nn.Linear)]


def test_paper_decoder_layout():
    dec = Decoder(DecoderConfig(), embed_dim=16)
    assert linear_sizes(dec.trunk) == [(16, 128), (128, 128)]
    assert linear_sizes(dec.sdf_head) == [(128, 1 + 128)]
    assert linear_sizes(dec.color_head) == [(128, 256), (256, 256), (256, 3)]
    n_params = sum(p.numel() for p in dec.parameters())
    assert dec.num_bytes() == 4 * n_params


def test_decoder_sizes_are_configurable():
    cfg = dataclasses.replace(DecoderConfig(), hidden_dim=24, num_layers=4, feature_dim=8,
                              color_hidden_dim=12, color_layers=1)
    dec = Decoder(cfg, embed_dim=5)
    assert linear_sizes(dec.trunk) == [(5, 24)] + [(24, 24)] * 3
    assert linear_sizes(dec.sdf_head) == [(24, 9)]
    assert linear_sizes(dec.color_head) == [(8, 12), (12, 3)]
    sdf, feature = dec.sdf_and_feature(torch.randn(4, 5))
    assert sdf.shape == (4,) and feature.shape == (4, 8)
