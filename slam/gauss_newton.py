"""Tracking's objective linearised in closed form, for Gauss-Newton / Levenberg-Marquardt.

The tracker minimises the paper's four losses over the camera pose only. Adam needs tens of
steps for that because each of its steps moves about ``lr`` per coordinate whatever the
gradient says; Gauss-Newton uses the curvature and converges in a handful of steps. Its cost is
one Jacobian of every residual with respect to the 6-D twist, which we build without autograd:

* every sample's SDF and colour depend only on its own point ``p_i``, so their spatial
  gradients are per sample: the trilinear features' derivative is exact, the SDF's goes
  back through the decoder in one reverse pass, and the colour's forward, one tangent per
  axis (only where a sample has weight);
* the renderer's per-ray sums (``D = sum w t / sum w``, ``C = sum w c / sum w`` with
  ``w = sigmoid(s/tr) sigmoid(-s/tr)``) are differentiated by hand;
* a sample at camera-frame point ``x`` moves with the right-perturbed pose ``T exp(xi)`` as
  ``dp/d(rho, phi) = R [I | -[x]_x]``, so a map-frame gradient ``g`` becomes the row
  ``[R^T g, x x R^T g]``.

The L1 colour and depth terms are handled by iteratively reweighted least squares
(``|r| ~ r^2 / (2 |r_0|)``), so the quadratic model matches the paper's loss at the current
pose; ``cost`` is that loss exactly (``slam.losses.compute_losses`` on the same rays is the
reference it is tested against, and ``render_rays`` under autograd for the Jacobian).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from .losses import LossWeights
from .padded import PaddedSamples, color_window, grid_samples, pack_samples, sdf_weights_padded
from .render import (
    MapView,
    RaySamples,
    Segments,
    color_of_hidden,
    decode_samples,
    interpolate_with_gradient,
    ray_voxel_intersections,
    sample_points_from_hits,
    sdf_weights_and_slope,
)


@dataclass(frozen=True)
class Linearisation:
    """The tracking loss at one pose and its Gauss-Newton model.

    cost: the paper's weighted loss (float; a 0-dim float64 tensor from the padded path,
    which reads nothing back from the device). H (6, 6), g (6,): normal equations of the
    reweighted least-squares model, so the step is ``-(H + damping)^-1 g``.
    depth (R,) rendered depth, hit (R,) rays with weight, residual (R,) |depth error|.
    """

    cost: float
    H: torch.Tensor
    g: torch.Tensor
    depth: torch.Tensor
    hit: torch.Tensor
    residual: torch.Tensor


@dataclass(frozen=True)
class FieldValues:
    """sdf (S,) in units of tr and grad_sdf (S, 3) per metre (map frame), plus what the
    colour pass needs: the features (S, D), their spatial derivative (S, 3, D) and each
    trunk layer's output after its ReLU (S, H)."""

    sdf: torch.Tensor
    grad_sdf: torch.Tensor
    feats: torch.Tensor
    dfeats: torch.Tensor
    hidden: tuple[torch.Tensor, ...] = ()


def field_with_gradients(points: torch.Tensor, voxel_index: torch.Tensor, view: MapView, decoder,
                         segments: Segments | None = None) -> FieldValues:
    """SDF at points (S, 3) and its spatial gradient.

    The trilinear features and their spatial derivative are exact
    (``interpolate_with_gradient``); the SDF's derivative in feature space comes from one
    reverse pass through the trunk, written out (the SDF is one number per sample, so
    reverse mode costs a third of differencing the three axes forward; by hand it needs no
    autograd graph: each layer's ReLU mask and one product), and the chain rule gives its
    spatial gradient. ``field_with_gradients_autograd`` is the same through autograd.
    """
    feats, dfeats = interpolate_with_gradient(points, voxel_index, view, segments)
    layers = decoder.trunk_linears()
    hidden, h = [], feats
    for layer in layers:
        h = torch.addmm(layer.bias, h, layer.weight.t()).relu_()
        hidden.append(h)
    w0, b0 = decoder.sdf_head.weight[0], decoder.sdf_head.bias[0]
    sdf = torch.mv(h, w0) + b0
    # d sdf / d (last layer's pre-activation), (S, H): the ReLU's mask in one pass (the op
    # autograd runs for a ReLU's backward), then back layer by layer.
    g = torch.ops.aten.threshold_backward(w0.expand_as(h), h, 0)
    for k in range(len(layers) - 1, -1, -1):
        g = g @ layers[k].weight  # d sdf / d (layer k's input)
        if k > 0:
            g = torch.ops.aten.threshold_backward(g, hidden[k - 1], 0)
    grad_sdf = (dfeats @ g[:, :, None])[..., 0]
    return FieldValues(sdf, grad_sdf, feats, dfeats, tuple(hidden))


def field_with_gradients_autograd(points: torch.Tensor, voxel_index: torch.Tensor, view: MapView, decoder,
                                  segments: Segments | None = None) -> FieldValues:
    """``field_with_gradients`` with the SDF's feature-space derivative from autograd: the
    plain twin it is tested against (no trunk outputs kept: the colour pass recomputes them)."""
    feats, dfeats = interpolate_with_gradient(points, voxel_index, view, segments)
    with torch.enable_grad():
        f = feats.detach().requires_grad_(True)
        sdf = decoder.sdf(f)
        (d_sdf,) = torch.autograd.grad(sdf.sum(), f)
    grad_sdf = (dfeats @ d_sdf[:, :, None])[..., 0]
    return FieldValues(sdf.detach(), grad_sdf, feats, dfeats)


def _linear_with_tangents(x: torch.Tensor, dx: torch.Tensor, weight: torch.Tensor,
                          bias: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """x (A, n) -> x W^T + b, and its tangents dx (3, A, n) -> dx W^T."""
    return torch.nn.functional.linear(x, weight, bias), dx @ weight.T


def _relu_with_tangents(x: torch.Tensor, dx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """ReLU of x (A, n) and its tangents dx (3, A, n): each masked where x <= 0, in one pass
    each (``threshold_backward`` masks by another tensor's sign without a bool temporary)."""
    return torch.relu(x), torch.ops.aten.threshold_backward(dx, x.expand_as(dx), 0)


def color_with_gradients(field: FieldValues, decoder, active: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Colour (A, 3) at the ``active`` samples (A,) and its spatial gradient (A, 3, 3)
    (channel, axis), exact: forward mode through the decoder, one tangent per axis (three
    colour channels make reverse mode no cheaper), with each ReLU's mask from the samples'
    own activations. The feature rows of the SDF head and the colour head's first layer have
    no activation between them and run as one product, as ``Decoder.color_from_hidden``."""
    x, dx = field.feats[active], field.dfeats[active].transpose(0, 1)  # (A, D), (3, A, D)
    layers = decoder.trunk_linears()
    if len(field.hidden) == len(layers):
        # The trunk's outputs are known (``field_with_gradients``): only the tangents go through.
        for layer, h in zip(layers, field.hidden):
            x = h[active]
            dx = dx @ layer.weight.T
            dx = torch.ops.aten.threshold_backward(dx, x.expand_as(dx), 0)
    else:
        for layer in layers:
            x, dx = _relu_with_tangents(*_linear_with_tangents(x, dx, layer.weight, layer.bias))
    head = [m for m in decoder.color_head if isinstance(m, torch.nn.Linear)]
    w, b = decoder.sdf_head.weight[1:], decoder.sdf_head.bias[1:]
    x, dx = _linear_with_tangents(x, dx, head[0].weight @ w, head[0].weight @ b + head[0].bias)
    for layer in head[1:]:
        x, dx = _relu_with_tangents(x, dx)
        x, dx = _linear_with_tangents(x, dx, layer.weight, layer.bias)
    rgb = torch.sigmoid(x)
    grad = (rgb * (1 - rgb))[None] * dx  # (3 axes, A, 3 channels)
    return rgb, grad.permute(1, 2, 0)


def twist_rows(grad_map: torch.Tensor, x_cam: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """d(value)/d(xi) (..., 6) from its map-frame spatial gradient (..., 3) at camera-frame
    points x_cam (broadcastable to (..., 3)), for the pose ``T exp(xi)`` with rotation R."""
    g_cam = grad_map @ R
    return torch.cat([g_cam, torch.linalg.cross(x_cam.expand_as(g_cam), g_cam, dim=-1)], -1)


def linearise(T_map_cam: torch.Tensor, dirs_cam: torch.Tensor, rgb_gt: torch.Tensor,
              depth_gt: torch.Tensor, ray_weight: torch.Tensor | None, view: MapView, decoder, *,
              near: torch.Tensor, far: torch.Tensor, step: float, truncation: float,
              max_hits: int, weights: LossWeights, max_depth: float = 10.0,
              color_weight_eps: float = 1e-5, eps_depth: float = 5e-3,
              eps_color: float = 1e-2, miss_cost: float | None = None,
              mask_in_front: bool = True, renormalise_color: bool = False) -> Linearisation:
    """The tracking loss of R rays at pose T_map_cam (4, 4) and its Gauss-Newton model.

    dirs_cam (R, 3) camera-frame directions with z = 1, rgb_gt (R, 3), depth_gt (R,),
    ray_weight (R,) in {0, 1} (outliers) or None; near, far (R,) sampling bounds.
    ``eps_depth`` / ``eps_color`` floor the residuals in the IRLS weights of the L1 terms;
    ``miss_cost``: see the denominators below (None: the losses exactly as compute_losses).
    Renders exactly as ``slam.render.render_rays`` (mid-step samples, the same
    ``mask_in_front`` and ``renormalise_color``) with no autograd.
    """
    with torch.no_grad():
        rendered = render_with_jacobians(T_map_cam, dirs_cam, view, decoder, near=near, far=far, step=step,
                                         truncation=truncation, max_hits=max_hits,
                                         color_weight_eps=color_weight_eps, mask_in_front=mask_in_front,
                                         renormalise_color=renormalise_color)
        return linearise_rendered(rendered, rgb_gt, depth_gt, ray_weight, weights=weights, max_depth=max_depth,
                                  eps_depth=eps_depth, eps_color=eps_color, miss_cost=miss_cost)


@dataclass(frozen=True)
class RenderedJacobians:
    """What ``linearise`` computes at one pose before it looks at the observations or the
    ray weights, so that one render serves several ray weightings (the tracker's first
    linearisation, without and then with its outliers dropped).

    Per ray (R,): depth, W (weight sum), color (R, 3), hit, J_depth (R, 6), J_color (R, 3, 6).
    Per sample (S,): ray r, t, sdf s, J_s (S, 6) (the SDF's twist rows). truncation: tr."""

    T: torch.Tensor
    depth: torch.Tensor
    W: torch.Tensor
    color: torch.Tensor
    hit: torch.Tensor
    J_depth: torch.Tensor
    J_color: torch.Tensor
    r: torch.Tensor
    t: torch.Tensor
    s: torch.Tensor
    J_s: torch.Tensor
    truncation: float
    valid: torch.Tensor | None = None
    """Padded samples (``render_with_jacobians_padded``): (S,) bool, the slots that hold a
    sample (None: every sample is one)."""


@torch.no_grad()
def render_with_jacobians(T: torch.Tensor, dirs_cam: torch.Tensor, view: MapView, decoder, *,
                          near: torch.Tensor, far: torch.Tensor, step: float, truncation: float,
                          max_hits: int, color_weight_eps: float = 1e-5,
                          mask_in_front: bool = True, jacobians: bool = True,
                          renormalise_color: bool = False) -> RenderedJacobians:
    """Render R rays (``dirs_cam`` (R, 3), z = 1) at pose T (4, 4) with the twist Jacobians of
    their depth and colour and of every sample's SDF (no autograd; see ``linearise``).

    ``jacobians=False`` renders the values only and leaves the Jacobians zero, at about half
    the cost: enough for the loss at a pose whose model may never be needed.
    ``renormalise_color``: a ray's colour is the weighted mean over the coloured samples
    (weight above ``color_weight_eps``), as ``render_rays`` renders it with the same switch,
    so that a high threshold does not darken it; its Jacobian is then exact for that set."""
    tr = truncation
    R_, o = T[:3, :3], T[:3, 3]
    num_rays = dirs_cam.shape[0]
    dirs = dirs_cam @ R_.T
    origins = o.expand(num_rays, 3)
    hits = ray_voxel_intersections(origins, dirs, near, far, view.voxel_codes, view.voxel_size, max_hits)
    samples: RaySamples = sample_points_from_hits(hits, step, torch.full((num_rays,), 0.5, device=T.device))
    r, t = samples.ray_index, samples.t
    x_cam = t[:, None] * dirs_cam[r]
    points = origins[r] + t[:, None] * dirs[r]

    if jacobians:
        field = field_with_gradients(points, samples.voxel_index, view, decoder, segments=samples.segments)
        s = field.sdf
    else:
        s, hidden = decode_samples(points, samples.voxel_index, view, decoder)
    w, dw_ds = sdf_weights_and_slope(s, t, r, num_rays, tr, mask_in_front)
    # The colour head only where a sample has weight, as in render_rays.
    active = torch.nonzero(w > color_weight_eps, as_tuple=True)[0]
    if jacobians:
        rgb, grad_rgb = color_with_gradients(field, decoder, active)
    else:
        rgb = color_of_hidden(decoder, hidden[active])

    W = torch.zeros(num_rays, dtype=t.dtype, device=t.device).index_add(0, r, w)
    inv_W = 1.0 / (W + 1e-8)
    depth = torch.zeros_like(W).index_add(0, r, w * t) * inv_W
    ra = r[active]
    # The colour's normaliser: every sample's weight, or only the coloured samples'.
    inv_Wc = 1.0 / (torch.zeros_like(W).index_add(0, ra, w[active]) + 1e-8) if renormalise_color else inv_W
    color = torch.zeros(num_rays, 3, dtype=t.dtype, device=t.device).index_add(
        0, ra, w[active, None] * rgb) * inv_Wc[:, None]
    hit = torch.zeros(num_rays, dtype=torch.bool, device=t.device)
    hit[r] = True
    if not jacobians:
        return RenderedJacobians(T, depth, W, color, hit, W.new_zeros(num_rays, 6), W.new_zeros(num_rays, 3, 6),
                                 r, t, s, t.new_zeros(t.shape[0], 6), tr)

    # d(ray depth)/d(sample point) = (t - D)/W * dw/ds * grad s; colour adds w/W * grad c
    # (W: the colour's normaliser; with it over the coloured samples only, the samples left
    # out of the colour leave its derivative too, and the expression stays exact).
    J_s = twist_rows(field.grad_sdf, x_cam, R_)  # (S, 6)
    a = (t - depth[r]) * inv_W[r] * dw_ds
    J_depth = torch.zeros(num_rays, 6, dtype=t.dtype, device=t.device).index_add(0, r, a[:, None] * J_s)
    J_rgb_c = twist_rows(grad_rgb, x_cam[active][:, None, :], R_)  # (A, 3, 6)
    b = (rgb - color[ra]) * (inv_Wc[ra] * dw_ds[active])[:, None]  # (A, 3)
    per_sample = b[..., None] * J_s[active][:, None, :] + (w[active] * inv_Wc[ra])[:, None, None] * J_rgb_c
    J_color = torch.zeros(num_rays, 3, 6, dtype=t.dtype, device=t.device).index_add(0, ra, per_sample)
    return RenderedJacobians(T, depth, W, color, hit, J_depth, J_color, r, t, s, J_s, tr)


@torch.no_grad()
def render_with_jacobians_padded(T: torch.Tensor, dirs_cam: torch.Tensor, view: MapView, decoder, *,
                                 near: torch.Tensor, far: torch.Tensor, step: float, truncation: float,
                                 max_hits: int, grid: int, slots: int, color_slots: int,
                                 color_weight_eps: float = 1e-5, mask_in_front: bool = True,
                                 jacobians: bool = True, renormalise_color: bool = False) -> RenderedJacobians:
    """``render_with_jacobians`` on padded samples (``slam.padded``): R rays of ``grid`` grid
    points packed into ``slots`` slots, the colour on a window of ``color_slots`` slots, and
    nothing read back from the device. dirs_cam (R, 3) with z = 1, T (4, 4), near, far (R,).
    The per-sample fields (S = R * slots) carry ``valid``; ``linearise_rendered`` reads it."""
    tr = truncation
    R_, o = T[:3, :3], T[:3, 3]
    R = dirs_cam.shape[0]
    dirs = dirs_cam @ R_.T
    origins = o.expand(R, 3)
    samples: PaddedSamples = pack_samples(grid_samples(origins, dirs, near, far, step, view, grid,
                                                      max_hits=max_hits), slots)
    N = samples.slots
    t = samples.t                                                          # (R, N)
    valid = samples.valid
    x_cam = t[..., None] * dirs_cam[:, None, :]                            # (R, N, 3)
    points = (origins[:, None, :] + t[..., None] * dirs[:, None, :]).reshape(-1, 3)
    voxel = samples.voxel_index.reshape(-1)
    r = torch.arange(R, device=t.device)[:, None].expand(R, N).reshape(-1)
    if jacobians:
        field = field_with_gradients(points, voxel, view, decoder)
        s = field.sdf.view(R, N)
    else:
        sdf, hidden = decode_samples(points, voxel, view, decoder)
        s = sdf.view(R, N)
    w, dw_ds = sdf_weights_padded(s, t, valid, tr, mask_in_front)
    C = min(int(color_slots), N)
    index, active = color_window(w, color_weight_eps, C)                 # (R, C)
    flat_index = (torch.arange(R, device=t.device)[:, None] * N + index).reshape(-1)
    if jacobians:
        rgb, grad_rgb = color_with_gradients(field, decoder, flat_index)
    else:
        rgb = color_of_hidden(decoder, hidden[flat_index])
    rgb = rgb.view(R, C, 3)
    wc = w.gather(1, index) * active
    W = w.sum(1)
    inv_W = 1.0 / (W + 1e-8)
    depth = (w * t).sum(1) * inv_W
    inv_Wc = 1.0 / (wc.sum(1) + 1e-8) if renormalise_color else inv_W
    color = (wc[..., None] * rgb).sum(1) * inv_Wc[:, None]
    hit = valid.any(1)
    flat_t, flat_s, flat_valid = t.reshape(-1), s.reshape(-1), valid.reshape(-1)
    if not jacobians:
        return RenderedJacobians(T, depth, W, color, hit, W.new_zeros(R, 6), W.new_zeros(R, 3, 6),
                                 r, flat_t, flat_s, flat_t.new_zeros(R * N, 6), tr, flat_valid)
    J_s = twist_rows(field.grad_sdf, x_cam.reshape(-1, 3), R_)            # (S, 6)
    a = (t - depth[:, None]) * inv_W[:, None] * dw_ds                     # (R, N)
    J_depth = (a[..., None] * J_s.view(R, N, 6)).sum(1)
    x_win = x_cam.gather(1, index[..., None].expand(R, C, 3)).reshape(-1, 3)
    J_rgb_c = twist_rows(grad_rgb, x_win[:, None, :], R_).view(R, C, 3, 6)
    dw_win = dw_ds.gather(1, index) * active
    b = (rgb - color[:, None, :]) * (inv_Wc[:, None] * dw_win)[..., None]   # (R, C, 3)
    J_s_win = J_s.view(R, N, 6).gather(1, index[..., None].expand(R, C, 6))
    per_sample = b[..., None] * J_s_win[:, :, None, :] + (wc * inv_Wc[:, None])[..., None, None] * J_rgb_c
    J_color = per_sample.sum(1)                                            # (R, 3, 6)
    return RenderedJacobians(T, depth, W, color, hit, J_depth, J_color, r, flat_t, flat_s, J_s, tr, flat_valid)


def linearise_rendered(rendered: RenderedJacobians, rgb_gt: torch.Tensor, depth_gt: torch.Tensor,
                       ray_weight: torch.Tensor | None, *, weights: LossWeights, max_depth: float = 10.0,
                       eps_depth: float = 5e-3, eps_color: float = 1e-2,
                       miss_cost: float | None = None) -> Linearisation:
    """``linearise`` from a render at its pose: the loss against rgb_gt (R, 3), depth_gt (R,)
    over the rays ray_weight (R,) keeps (None: all), and its Gauss-Newton model."""
    with torch.no_grad():
        if rendered.valid is not None:
            return _assemble_padded(rendered, rgb_gt, depth_gt, ray_weight, weights, max_depth, eps_depth,
                                    eps_color, miss_cost)
        return _assemble(rendered, rgb_gt, depth_gt, ray_weight, weights, max_depth, eps_depth, eps_color, miss_cost)


def _assemble(rendered: RenderedJacobians, rgb_gt, depth_gt, ray_weight, lw: LossWeights, max_depth,
              eps_depth, eps_color, miss_cost) -> Linearisation:
    T, depth, W, color, hit = rendered.T, rendered.depth, rendered.W, rendered.color, rendered.hit
    J_depth, J_color, r, t, s, J_s = (rendered.J_depth, rendered.J_color, rendered.r, rendered.t,
                                      rendered.s, rendered.J_s)
    tr = rendered.truncation
    num_rays = depth.shape[0]
    use = hit if ray_weight is None else hit & (ray_weight > 0)
    valid = use & (depth_gt > 0.01) & (depth_gt < max_depth)
    n_use, n_valid = int(use.sum()), int(valid.sum())
    # Denominators: the rays that hit (as compute_losses), or with ``miss_cost`` the fixed ray
    # set, each of its rays that misses costing miss_cost. Otherwise a pose that makes the
    # worst rays leave the map lowers the mean and the optimiser runs off (seen on fr1/rpy).
    den_use, den_valid = n_use, n_valid
    cost = 0.0
    if miss_cost is not None:
        in_set = torch.ones_like(hit) if ray_weight is None else ray_weight > 0
        den_use = max(int(in_set.sum()), 1)
        den_valid = max(int((in_set & (depth_gt > 0.01) & (depth_gt < max_depth)).sum()), 1)
        cost += miss_cost * int((in_set & ~hit).sum()) / den_use

    H = T.new_zeros(6, 6)
    g = T.new_zeros(6)

    def add(J: torch.Tensor, res: torch.Tensor, omega: torch.Tensor) -> None:
        nonlocal H, g
        H = H + (J * omega[:, None]).T @ J
        g = g + (J * (omega * res)[:, None]).sum(0)

    if n_use:
        res_c = (color[use] - rgb_gt[use]).reshape(-1)
        cost += lw.rgb * float(res_c.abs().sum()) / (3 * den_use)
        omega = lw.rgb / (3 * den_use * 2.0 * res_c.abs().clamp(min=eps_color))
        add(J_color[use].reshape(-1, 6), res_c, omega)
    if n_valid:
        res_d = depth[valid] - depth_gt[valid]
        cost += lw.depth * float(res_d.abs().sum()) / den_valid
        omega = lw.depth / (den_valid * 2.0 * res_d.abs().clamp(min=eps_depth))
        add(J_depth[valid], res_d, omega)

    d = depth_gt[r]
    ok = valid[r]
    for mask, res, J, lam in (
        (ok & (t < d - tr), s - 1.0, J_s, lw.fs),
        (ok & ((t - d).abs() <= tr), t + s * tr - d, tr * J_s, lw.sdf),
    ):
        if not bool(mask.any()):
            continue
        counts = torch.zeros(num_rays, dtype=t.dtype, device=t.device).index_add(0, r, mask.to(t.dtype))
        rays_with = int((counts > 0).sum()) if miss_cost is None else den_valid
        omega = lam / (rays_with * counts[r][mask])
        cost += float((omega * res[mask] ** 2).sum())
        add(J[mask], res[mask], omega)
    residual = (depth - depth_gt).abs()
    return Linearisation(cost, H, g, depth, hit & (W > 1e-3), residual)


def _assemble_padded(rendered: RenderedJacobians, rgb_gt, depth_gt, ray_weight, lw: LossWeights, max_depth,
                     eps_depth, eps_color, miss_cost) -> Linearisation:
    """``_assemble`` with masks instead of boolean indexing and every count and the cost kept
    as tensors (the cost in float64, as ``_assemble`` sums it in Python floats): the same
    numbers up to the order of float32 sums, and nothing read back from the device."""
    T, depth, W, color, hit = rendered.T, rendered.depth, rendered.W, rendered.color, rendered.hit
    J_depth, J_color, r, t, s, J_s = (rendered.J_depth, rendered.J_color, rendered.r, rendered.t,
                                      rendered.s, rendered.J_s)
    tr = rendered.truncation
    num_rays = depth.shape[0]
    f64 = torch.float64
    use = hit if ray_weight is None else hit & (ray_weight > 0)
    in_range = (depth_gt > 0.01) & (depth_gt < max_depth)
    valid = use & in_range
    n_use, n_valid = use.sum().to(f64), valid.sum().to(f64)
    den_use, den_valid = n_use, n_valid
    cost = torch.zeros((), dtype=f64, device=depth.device)
    if miss_cost is not None:
        in_set = torch.ones_like(hit) if ray_weight is None else ray_weight > 0
        den_use = in_set.sum().to(f64).clamp(min=1.0)
        den_valid = (in_set & in_range).sum().to(f64).clamp(min=1.0)
        cost = cost + miss_cost * (in_set & ~hit).sum().to(f64) / den_use
    den_use_c, den_valid_c = den_use.clamp(min=1.0), den_valid.clamp(min=1.0)
    H = T.new_zeros(6, 6)
    g = T.new_zeros(6)

    def add(J: torch.Tensor, res: torch.Tensor, omega: torch.Tensor) -> None:
        nonlocal H, g
        H = H + (J * omega[:, None]).T @ J
        g = g + (J * (omega * res)[:, None]).sum(0)

    use_f = use.to(depth.dtype)
    res_c = (color - rgb_gt) * use_f[:, None]                                     # (R, 3)
    cost = cost + lw.rgb * res_c.abs().sum().to(f64) / (3 * den_use_c)
    omega = (lw.rgb / (3 * den_use_c * 2.0 * res_c.abs().clamp(min=eps_color))).to(depth.dtype) * use_f[:, None]
    add(J_color.reshape(-1, 6), res_c.reshape(-1), omega.reshape(-1))
    valid_f = valid.to(depth.dtype)
    res_d = (depth - depth_gt) * valid_f
    cost = cost + lw.depth * res_d.abs().sum().to(f64) / den_valid_c
    omega = (lw.depth / (den_valid_c * 2.0 * res_d.abs().clamp(min=eps_depth))).to(depth.dtype) * valid_f
    add(J_depth, res_d, omega)

    d = depth_gt[r]
    ok = valid[r] & rendered.valid
    for mask, res, J, lam in (
        (ok & (t < d - tr), s - 1.0, J_s, lw.fs),
        (ok & ((t - d).abs() <= tr), t + s * tr - d, tr * J_s, lw.sdf),
    ):
        m = mask.to(t.dtype)
        counts = torch.zeros(num_rays, dtype=t.dtype, device=t.device).index_add(0, r, m)
        rays_with = (counts > 0).sum().to(f64) if miss_cost is None else den_valid
        per = counts[r]
        omega = (lam / (rays_with.clamp(min=1.0) * torch.where(mask, per, torch.ones_like(per)))).to(t.dtype) * m
        res = res * m
        cost = cost + (omega * res ** 2).sum().to(f64)
        add(J, res, omega)
    residual = (depth - depth_gt).abs()
    return Linearisation(cost, H, g, depth, hit & (W > 1e-3), residual)


def damped_step(lin: Linearisation, damping: float) -> torch.Tensor:
    """The Levenberg-Marquardt step (6,): -(H + damping * diag(H))^-1 g."""
    H = lin.H + damping * torch.diag(torch.diagonal(lin.H)) + 1e-9 * torch.eye(6, dtype=lin.H.dtype, device=lin.H.device)
    return -torch.linalg.solve(H, lin.g)


def damped_step_tensor(lin: Linearisation, damping: torch.Tensor) -> torch.Tensor:
    """``damped_step`` with a 0-dim tensor ``damping``, solved by Cholesky and two triangular
    solves: the system is symmetric positive definite, and these read nothing back from the
    device (LU's solve checks its pivots on the host). A system that is not gives a
    non-finite step."""
    H = lin.H + damping * torch.diag(torch.diagonal(lin.H)) + 1e-9 * torch.eye(6, dtype=lin.H.dtype, device=lin.H.device)
    L = torch.linalg.cholesky_ex(H)[0]
    y = torch.linalg.solve_triangular(L, lin.g[:, None], upper=False)
    return -torch.linalg.solve_triangular(L.T, y, upper=True)[:, 0]


@dataclass(frozen=True)
class MotionPrior:
    """A quadratic prior ``sum_k w_k xi_k^2`` on the twist ``xi = log(T0^-1 T)`` from the
    initial pose, w (6,) per coordinate (translation first)."""

    w: torch.Tensor

    @staticmethod
    def scaled_to(lin: Linearisation, ratio: float) -> "MotionPrior":
        """Weights ``ratio`` times the mean diagonal curvature of the data term's translation
        and rotation blocks at ``lin``."""
        d = torch.diagonal(lin.H)
        w = torch.cat([d[:3].mean().expand(3), d[3:].mean().expand(3)]) * ratio
        return MotionPrior(w)

    def cost(self, xi: torch.Tensor) -> float:
        return float((self.w * xi * xi).sum())

    def added_to(self, lin: Linearisation, xi: torch.Tensor) -> Linearisation:
        """``lin`` with the prior at twist ``xi`` (6,) added: the step is taken on the right
        of the current pose, and for the small twists of one frame d log / d step ~ I.
        A tensor ``lin.cost`` (the padded path) stays a tensor."""
        prior = (self.w * xi * xi).sum()
        cost = lin.cost + prior.to(lin.cost.dtype) if torch.is_tensor(lin.cost) else lin.cost + float(prior)
        return replace(lin, cost=cost, H=lin.H + torch.diag(2 * self.w).to(lin.H.dtype),
                       g=lin.g + (2 * self.w * xi).to(lin.g.dtype))


def limit_step(delta: torch.Tensor, max_m: float, max_rad: float) -> torch.Tensor:
    """Scale a twist (6,) down so its translation <= max_m and its rotation <= max_rad (a
    trust region: at frame rate one step never needs to be large, and a far step taken
    where the linear model is wrong lands where the map cannot say so)."""
    scale = min(1.0, max_m / max(float(delta[:3].norm()), 1e-12), max_rad / max(float(delta[3:].norm()), 1e-12))
    return delta * scale


def limit_step_tensor(delta: torch.Tensor, max_m: float, max_rad: float) -> torch.Tensor:
    """``limit_step`` in tensor operations only (nothing read back from the device)."""
    scale = torch.minimum(max_m / delta[:3].norm().clamp(min=1e-12), max_rad / delta[3:].norm().clamp(min=1e-12))
    return delta * scale.clamp(max=1.0)
