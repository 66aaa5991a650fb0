"""Robust colour kernels and the adaptive colour weight (``slam.photometric``, issue 41
item 4) in tracking (Gauss-Newton and Adam), and the synthetic camera that needs them
(``exposure=``, ``color_shift=``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from slam.config import PRESETS, ConfigError, config_from_dict, preset
from slam.data import DataError
from slam.data.synthetic import camera_colour, open_synthetic, parse_synthetic_spec
from slam.gauss_newton import linearise_rendered, render_with_jacobians, render_with_jacobians_padded
from slam.geometry import se3_exp
from slam.losses import compute_losses
from slam.padded import band_grid_size, color_slots
from slam.photometric import ColourModel, kernel_cost, kernel_weight, masked_median, robust_sigma
from slam.render import render_rays
from tests.test_mapping_tracking import CONFIG, _linearisation_inputs, frames, gt_pose, single_thread, trained  # noqa: F401


def test_masked_median_and_robust_sigma_on_worked_values():
    v = torch.tensor([[3.0, 1.0, 2.0, 9.0], [5.0, 4.0, 0.0, 0.0]])
    m = torch.tensor([[True, True, True, False], [True, False, False, False]])
    assert masked_median(v, m).tolist() == [2.0, 5.0]
    assert float(masked_median(v[0], torch.zeros(4, dtype=torch.bool))) == float("inf")
    assert float(robust_sigma(torch.tensor([-1.0, 1.0, 2.0]), torch.ones(3, dtype=torch.bool), 0.0)) == pytest.approx(1.4826)
    assert float(robust_sigma(torch.zeros(3), torch.zeros(3, dtype=torch.bool), 0.01)) == pytest.approx(0.01)


@pytest.mark.parametrize("kernel", ["none", "huber", "cauchy"])
def test_kernel_weights_give_the_kernels_gradient(kernel):
    """omega = rho'(r) / 2r, so sum omega r^2 has rho's gradient (the IRLS model)."""
    r = torch.tensor([-0.3, -0.04, 0.02, 0.07, 0.5], dtype=torch.float64, requires_grad=True)
    c = 0.05
    kernel_cost(r, kernel, c).sum().backward()
    assert torch.allclose(2 * kernel_weight(r.detach(), kernel, c, 1e-9) * r.detach(), r.grad)
    assert kernel_cost(torch.tensor([0.1]), "huber", 0.05).item() == pytest.approx(0.075)
    assert kernel_cost(torch.tensor([0.1]), "cauchy", 0.05).item() == pytest.approx(0.025 * np.log(5.0))


# ----------------------------------------------------------------- the losses
def _render(trained, frames, n=128):
    fmap, batch, kwargs, weights = _linearisation_inputs(trained, frames, n)
    T0 = gt_pose(frames[0]) @ se3_exp(torch.tensor([0.01, -0.01, 0.005, 0.01, 0.0, -0.01]))
    return fmap, batch, kwargs, weights, T0


def test_inactive_colour_model_is_the_old_loss_bit_for_bit(trained, frames):
    fmap, batch, kwargs, weights, T0 = _render(trained, frames)
    n = batch.depth.shape[0]
    out = render_rays(T0[:3, 3].expand(n, 3), batch.dirs_cam @ T0[:3, :3].T, fmap.view, fmap.decoder, **kwargs)
    old = compute_losses(out, batch.rgb, batch.depth, CONFIG.render.truncation, weights)
    new = compute_losses(out, batch.rgb, batch.depth, CONFIG.render.truncation, weights, colour=ColourModel())
    assert torch.equal(old.total, new.total) and torch.equal(old.rgb, new.rgb)
    rendered = render_with_jacobians(T0, batch.dirs_cam, fmap.view, fmap.decoder, **kwargs)
    a = linearise_rendered(rendered, batch.rgb, batch.depth, None, weights=weights, miss_cost=0.5)
    b = linearise_rendered(rendered, batch.rgb, batch.depth, None, weights=weights, miss_cost=0.5, colour=ColourModel())
    assert a.cost == b.cost and torch.equal(a.H, b.H) and torch.equal(a.g, b.g)
    # an active model whose weight never falls (the L1 kernel) is the old term within float rounding
    never = ColourModel(adaptive=1e9)
    c = linearise_rendered(rendered, batch.rgb, batch.depth, None, weights=weights, miss_cost=0.5, colour=never)
    assert c.cost == pytest.approx(a.cost, rel=1e-6)
    assert torch.allclose(c.H, a.H, rtol=1e-4, atol=1e-6 * float(a.H.abs().max()))
    assert torch.allclose(c.g, a.g, rtol=1e-4, atol=1e-6 * float(a.g.abs().max()))


@pytest.mark.parametrize("model", [ColourModel(kernel="cauchy", adaptive=0.02), ColourModel(kernel="huber")],
                         ids=["cauchy_adaptive", "huber"])
def test_closed_form_model_matches_autograd_and_the_padded_path(trained, frames, model):
    """With kernel and weight fixed at one render, the closed-form cost and gradient against
    autograd through compute_losses, and the padded (fast) path against the flat one."""
    fmap, batch, kwargs, weights, T0 = _render(trained, frames)
    brighter = (batch.rgb * torch.tensor([1.2, 1.0, 0.9]) + 0.03).clamp(0, 1)
    rendered = render_with_jacobians(T0, batch.dirs_cam, fmap.view, fmap.decoder, **kwargs)
    fixed = model.fixed_at(rendered.color, brighter, rendered.hit.float(), 1e-2)
    lin = linearise_rendered(rendered, brighter, batch.depth, None, weights=weights, eps_depth=1e-12, colour=fixed)
    xi = torch.zeros(6, requires_grad=True)
    T = T0 @ se3_exp(xi)
    n = batch.depth.shape[0]
    out = render_rays(T[:3, 3].expand(n, 3), batch.dirs_cam @ T[:3, :3].T, fmap.view, fmap.decoder, **kwargs)
    losses = compute_losses(out, brighter, batch.depth, CONFIG.render.truncation, weights, colour=fixed)
    losses.total.backward()
    assert lin.cost == pytest.approx(float(losses.total.detach()), rel=1e-4)
    cos = float(torch.nn.functional.cosine_similarity(2 * lin.g, xi.grad, dim=0))
    assert cos > 0.99, (lin.g, xi.grad)
    step = CONFIG.render.step_ratio * fmap.view.voxel_size
    G = band_grid_size(2.0, CONFIG.render.truncation, step)
    padded = render_with_jacobians_padded(T0, batch.dirs_cam, fmap.view, fmap.decoder, grid=G, slots=G,
                                          color_slots=color_slots(CONFIG.render.truncation, step, G, True),
                                          **kwargs)
    fast = linearise_rendered(padded, brighter, batch.depth, None, weights=weights, eps_depth=1e-12, colour=fixed)
    assert float(fast.cost) == pytest.approx(lin.cost, rel=1e-3)
    assert torch.allclose(fast.g, lin.g, rtol=1e-2, atol=1e-3 * float(lin.g.abs().max()))


def test_adaptive_weight_falls_with_the_colour_disagreement():
    color = torch.rand(200, 3, generator=torch.Generator().manual_seed(0))
    use = torch.ones(200)
    model = ColourModel(adaptive=0.02)
    close = model.fixed_at(color, color + 0.01 * torch.randn(200, 3), use, 1e-2).factor
    far = model.fixed_at(color, color + 0.1 * torch.randn(200, 3), use, 1e-2).factor
    assert float(close) == 1.0 and 0.0 < float(far) < 0.1


# ---------------------------------------------------------- config and data
def test_config_fields_default_off_and_reject_bad_values():
    for name in PRESETS:
        c = preset(name)
        assert (c.tracking.color_robust, c.tracking.color_adaptive) == ("none", 0.0), name
    good = preset("cpu").to_dict()
    for section, key, value, words in (("tracking", "color_robust", "tukey", "tracking.color_robust must be one of"),
                                       ("tracking", "color_adaptive", -0.1, "tracking.color_adaptive")):
        bad = {**good, section: {**good[section], key: value}}
        with pytest.raises(ConfigError, match=words):
            config_from_dict(bad)


def test_synthetic_exposure_and_colour_shift_change_the_colour_as_specified():
    plain = open_synthetic("synthetic:walk?frames=20&width=64&height=48")
    exposed = open_synthetic("synthetic:walk?frames=20&width=64&height=48&exposure=0.3")
    shifted = open_synthetic("synthetic:walk?frames=20&width=64&height=48&color_shift=3")
    for i in (0, 7):
        gain, bias = exposed.exposure_of(i)
        assert np.all((gain > 0.7 * 0.94) & (gain < 1.3 * 1.06)) and abs(bias[0]) <= 0.06 and np.all(bias == bias[0])
        assert np.allclose(exposed[i].rgb, np.clip(plain[i].rgb * gain + bias, 0, 1), atol=1e-6)
        assert np.array_equal(exposed[i].depth, plain[i].depth) and np.array_equal(shifted[i].depth, plain[i].depth)
        assert np.array_equal(shifted[i].rgb[:, 3:], plain[i].rgb[:, :-3])
        assert np.array_equal(shifted[i].rgb[:, :3], np.repeat(plain[i].rgb[:, :1], 3, axis=1))
    assert not np.allclose(exposed.exposure_of(0)[0], exposed.exposure_of(1)[0])
    assert np.array_equal(camera_colour(plain[0].rgb, np.ones(3), np.zeros(3), 0), plain[0].rgb)
    spec = parse_synthetic_spec("laps?width=160&height=120&exposure=0.25&color_shift=2")
    assert spec.name.endswith("&exposure=0.25&color_shift=2") and parse_synthetic_spec(spec.name) == spec
    assert "exposure" not in parse_synthetic_spec("laps?width=160").name


@pytest.mark.parametrize("spec,words", [
    ("walk?exposure=1.5", "exposure=1.5 must be in [0, 0.9]"),
    ("walk?exposure=-0.1", "must be in"),
    ("walk?exposure=nan", "must be in"),
    ("walk?exposure=bright", "is not a number"),
    ("walk?color_shift=-1", "color_shift=-1 must be in 0..64"),
    ("walk?color_shift=65&width=1024", "must be in 0..64"),
    ("walk?color_shift=40&width=160", "below a quarter of the width"),
    ("walk?color_shift=1.5", "not an integer"),
])
def test_bad_camera_colour_options_raise(spec, words):
    with pytest.raises(DataError, match=words.replace("[", r"\[").replace("]", r"\]").replace(".", r"\.")):
        parse_synthetic_spec(spec)
