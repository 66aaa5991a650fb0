"""Colour residuals that real cameras do not fool: exposure, robust kernels, colour weight.

Auto-exposure and white balance change the colour of one surface from frame to frame, and
some sensors' colour is not registered to depth. Three remedies, all on the colour term:

* **exposure**: a per-frame affine map ``observed ~ a * rendered + b`` (one gain and bias for
  all channels, ``shared``, or one per channel, ``per_channel``) fitted in closed form by
  weighted least squares, robustly (a few Cauchy-reweighted passes, scale from the median
  absolute deviation), with a ridge prior ``prior * W * ((a - 1)^2 + b^2)`` (W: the weight
  sum) so that it stays near identity and cannot soak up a real misalignment
  (``fit_exposure``);
* **robust kernels** ``rho`` on each colour residual ``r``, with a scale ``c`` (a multiple
  of the residuals' MAD): ``none`` (the paper's L1 ``|r|``), ``huber``
  (``r^2 / 2c`` within c, ``|r| - c / 2`` beyond) and ``cauchy`` (``c/2 log(1 + (r/c)^2)``,
  whose influence falls for large residuals) (``kernel_cost``, ``kernel_weight``);
* **adaptive colour weight**: a frame whose colour disagrees with the rendered map more
  than ``adaptive`` (its robust residual scale sigma, after the exposure fit) has its colour
  term scaled by ``(adaptive / sigma)^2`` (inverse variance, at most 1).

Everything is tensor arithmetic on masks (medians by sorting, no boolean indexing), so a
tracking or mapping iteration that uses it reads nothing back from the device.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from .config_sections import COLOR_KERNELS, EXPOSURE_MODES

__all__ = ["COLOR_KERNELS", "EXPOSURE_MODES", "ColourModel", "Exposure", "fit_exposure", "kernel_cost",
           "kernel_weight", "masked_median", "robust_sigma"]
KERNEL_TUNING = {"huber": 1.345, "cauchy": 2.385}
"""The scale ``c`` is this many robust standard deviations (95 % efficiency under Gaussian noise)."""
MAD_TO_SIGMA = 1.4826


def masked_median(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``values[mask].median()`` (the lower median, as torch's) over the last dimension of
    values (..., N) and mask (..., N) bool -> (...), inf where the mask is empty: nothing read
    back from the device. Example: values [3., 1., 2., 9.], mask [T, T, T, F] -> 2."""
    inf = torch.full_like(values, float("inf"))
    ordered = torch.sort(torch.where(mask, values, inf), dim=-1).values
    n = mask.sum(-1)
    k = torch.div((n - 1).clamp(min=0), 2, rounding_mode="floor")
    return torch.where(n > 0, ordered.gather(-1, k[..., None])[..., 0], inf[..., 0])


def robust_sigma(residual: torch.Tensor, mask: torch.Tensor, floor: float) -> torch.Tensor:
    """1.4826 * median |residual| over ``mask`` along the last dimension ((..., N) -> (...)),
    at least ``floor``; the floor where the mask is empty. (A fit's residuals are centred, so
    the median of |r| is their median absolute deviation.)"""
    med = masked_median(residual.abs(), mask)
    sigma = torch.where(torch.isfinite(med), MAD_TO_SIGMA * med, torch.zeros_like(med))
    return sigma.clamp(min=floor)


def kernel_cost(r: torch.Tensor, kernel: str, c: torch.Tensor | float) -> torch.Tensor:
    """rho(r) elementwise: ``none`` |r|; ``huber`` r^2/2c within c, |r| - c/2 beyond;
    ``cauchy`` c/2 log(1 + (r/c)^2). Example: r = 0.1, c = 0.05 -> 0.1, 0.075, 0.0402."""
    a = r.abs()
    if kernel == "none":
        return a
    if kernel == "huber":
        return torch.where(a <= c, r * r / (2 * c), a - 0.5 * c)
    if kernel == "cauchy":
        return 0.5 * c * torch.log1p((r / c) ** 2)
    raise ValueError(f"unknown colour kernel {kernel!r}: one of {', '.join(COLOR_KERNELS)}")


def kernel_weight(r: torch.Tensor, kernel: str, c: torch.Tensor | float, eps: float) -> torch.Tensor:
    """The iteratively-reweighted least-squares weight ``rho'(r) / (2 r)`` (so that
    ``sum omega r^2`` has rho's gradient at r); ``none`` floors |r| at ``eps``, as the
    tracker's L1 term always did."""
    a = r.abs()
    if kernel == "none":
        return 1.0 / (2.0 * a.clamp(min=eps))
    if kernel == "huber":
        return 1.0 / (2.0 * torch.maximum(a, torch.as_tensor(c, dtype=r.dtype, device=r.device)))
    if kernel == "cauchy":
        return 1.0 / (2.0 * c * (1.0 + (r / c) ** 2))
    raise ValueError(f"unknown colour kernel {kernel!r}: one of {', '.join(COLOR_KERNELS)}")


@dataclass(frozen=True)
class Exposure:
    """observed ~ gain * rendered + bias; gain, bias (..., C) with C = 1 (shared) or 3."""

    gain: torch.Tensor
    bias: torch.Tensor

    def apply(self, color: torch.Tensor) -> torch.Tensor:
        """color (..., R, 3) -> gain * color + bias, broadcasting over the rays."""
        return color * self.gain[..., None, :] + self.bias[..., None, :]


def fit_exposure(rendered: torch.Tensor, observed: torch.Tensor, weight: torch.Tensor, *,
                 per_channel: bool, prior: float, passes: int = 3, floor: float = 1e-3) -> Exposure:
    """The affine map (gain, bias) from rendered to observed colour, by weighted least squares.

    rendered, observed (..., R, 3), weight (..., R) >= 0 (0: ray left out); leading
    dimensions are independent fits (the mapper's frames). Minimises, per channel or over
    the three pooled (``per_channel`` False),
    ``sum_i w_i u_i (a x_i + b - y_i)^2 + prior * sum_i w_i ((a - 1)^2 + b^2)``
    in closed form (2x2 normal equations). ``u_i`` are Cauchy weights of the previous pass's
    residuals at 2.385 robust sigmas (MAD, at least ``floor``), 1 on the first pass from
    identity; ``passes`` fits in all. No data: identity. Gains are clamped to [0.1, 10].
    Example: observed = 2 * rendered + 0.1 exactly, prior 0 -> gain 2, bias 0.1.
    """
    x, y = rendered.detach(), observed.detach()
    w = weight.detach().to(x.dtype)[..., None].expand_as(x)                # (..., R, 3)
    C = 3 if per_channel else 1
    shape = x.shape[:-2] + (C,)
    gain, bias = torch.ones(shape, dtype=x.dtype, device=x.device), torch.zeros(shape, dtype=x.dtype, device=x.device)
    u = torch.ones_like(x)
    dims = (-2,) if per_channel else (-2, -1)

    def total(t: torch.Tensor) -> torch.Tensor:
        s = t.sum(dims)
        return s if per_channel else s[..., None]

    for k in range(passes):
        if k > 0:
            r = Exposure(gain, bias).apply(x) - y
            sigma = robust_sigma(r.flatten(-2), (w > 0).flatten(-2), floor)   # (...)
            c = KERNEL_TUNING["cauchy"] * sigma[..., None, None]
            u = 1.0 / (1.0 + (r / c) ** 2)
        v = w * u
        W, Sx, Sy, Sxx, Sxy = total(v), total(v * x), total(v * y), total(v * x * x), total(v * x * y)
        P = prior * total(w)
        a11, a12, a22 = Sxx + P, Sx, W + P
        b1, b2 = Sxy + P, Sy
        det = a11 * a22 - a12 * a12
        ok = det > 1e-12 * (a11 * a22).clamp(min=1e-30)
        safe = torch.where(ok, det, torch.ones_like(det))
        gain = torch.where(ok, (a22 * b1 - a12 * b2) / safe, torch.ones_like(det)).clamp(0.1, 10.0)
        bias = torch.where(ok, (a11 * b2 - a12 * b1) / safe, torch.zeros_like(det))
    return Exposure(gain, bias)


@dataclass(frozen=True)
class ColourModel:
    """How a frame's colour residual is formed and weighed (the tracker's and Adam's colour
    term; ``none``/``off``/0 everywhere is the paper's L1 term exactly).

    exposure: ``off``, ``shared`` or ``per_channel`` (``fit_exposure`` against each
    evaluation's render, with ridge ``prior``); kernel: ``COLOR_KERNELS``; adaptive: the
    colour residual scale (colour units) above which the frame's colour weight falls as
    (adaptive / sigma)^2 (0: off). ``scale`` (the kernel's c) and ``factor`` (the colour
    weight) are 0-dim tensors fixed per frame by ``fixed_at`` (None: measured at each
    evaluation), so that the costs of one frame's iterations compare."""

    exposure: str = "off"
    prior: float = 0.01
    kernel: str = "none"
    adaptive: float = 0.0
    scale: torch.Tensor | None = None
    factor: torch.Tensor | None = None

    @property
    def active(self) -> bool:
        return self.exposure != "off" or self.kernel != "none" or self.adaptive > 0

    def fit(self, color: torch.Tensor, rgb_gt: torch.Tensor, use_f: torch.Tensor) -> Exposure:
        """The exposure for rendered ``color`` (R, 3) against ``rgb_gt`` over the rays ``use_f``
        (R,) weighs; identity when exposure is off."""
        if self.exposure == "off":
            one = color.new_ones(1)
            return Exposure(one, one * 0.0)
        return fit_exposure(color, rgb_gt, use_f, per_channel=self.exposure == "per_channel", prior=self.prior)

    def measured(self, residual: torch.Tensor, use_f: torch.Tensor, eps: float) -> tuple[torch.Tensor, torch.Tensor]:
        """(kernel scale c, colour weight factor) of residuals (R, 3) over the rays use_f (R,)."""
        sigma = robust_sigma(residual.detach().flatten(), (use_f > 0)[:, None].expand_as(residual).flatten(), eps)
        c = KERNEL_TUNING.get(self.kernel, 1.0) * sigma
        factor = ((self.adaptive / sigma) ** 2).clamp(max=1.0) if self.adaptive > 0 else torch.ones_like(sigma)
        return c.clamp(min=eps), factor

    def fixed_at(self, color: torch.Tensor, rgb_gt: torch.Tensor, use_f: torch.Tensor, eps: float) -> "ColourModel":
        """This model with ``scale`` and ``factor`` measured at one render (the frame's first)."""
        if not self.active:
            return self
        residual = self.fit(color, rgb_gt, use_f).apply(color) - rgb_gt
        c, factor = self.measured(residual, use_f, eps)
        return replace(self, scale=c, factor=factor)

    def terms(self, color: torch.Tensor, rgb_gt: torch.Tensor, use_f: torch.Tensor, eps: float):
        """(residual (R, 3), gain (1 or 3,), rho (R, 3), omega (R, 3), factor 0-dim): the colour
        residual after exposure, the gain its Jacobian takes, the kernel's cost and IRLS weight
        per residual (before the loss weight, the mask and the denominator) and the frame's
        colour weight."""
        exposure = self.fit(color, rgb_gt, use_f)
        residual = exposure.apply(color) - rgb_gt
        if self.scale is None or self.factor is None:
            c, factor = self.measured(residual, use_f, eps)
        else:
            c, factor = self.scale, self.factor
        return (residual, exposure.gain, kernel_cost(residual, self.kernel, c),
                kernel_weight(residual, self.kernel, c, eps), factor)
