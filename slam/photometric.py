"""Colour residuals that real cameras do not fool: robust kernels, colour weight.

Auto-exposure and white balance change the colour of one surface from frame to frame, and
some sensors' colour is not registered to depth. Two remedies, both on the colour term:

* **robust kernels** ``rho`` on each colour residual ``r``, with a scale ``c`` (a multiple
  of the residuals' MAD): ``none`` (the paper's L1 ``|r|``), ``huber``
  (``r^2 / 2c`` within c, ``|r| - c / 2`` beyond) and ``cauchy`` (``c/2 log(1 + (r/c)^2)``,
  whose influence falls for large residuals) (``kernel_cost``, ``kernel_weight``);
* **adaptive colour weight**: a frame whose colour disagrees with the rendered map more
  than ``adaptive`` (its robust residual scale sigma) has its colour term scaled by
  ``(adaptive / sigma)^2`` (inverse variance, at most 1).

Everything is tensor arithmetic on masks (medians by sorting, no boolean indexing), so a
tracking or mapping iteration that uses it reads nothing back from the device.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from .config_sections import COLOR_KERNELS

__all__ = ["COLOR_KERNELS", "ColourModel", "kernel_cost", "kernel_weight", "masked_median", "robust_sigma"]
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
class ColourModel:
    """How a frame's colour residual is formed and weighed (the tracker's and Adam's colour
    term; ``none`` and 0 are the paper's L1 term exactly).

    kernel: ``COLOR_KERNELS``; adaptive: the colour residual scale (colour units) above which
    the frame's colour weight falls as (adaptive / sigma)^2 (0: off). ``scale`` (the kernel's
    c) and ``factor`` (the colour weight) are 0-dim tensors fixed per frame by ``fixed_at``
    (None: measured at each evaluation), so that the costs of one frame's iterations compare."""

    kernel: str = "none"
    adaptive: float = 0.0
    scale: torch.Tensor | None = None
    factor: torch.Tensor | None = None

    @property
    def active(self) -> bool:
        return self.kernel != "none" or self.adaptive > 0

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
        c, factor = self.measured(color - rgb_gt, use_f, eps)
        return replace(self, scale=c, factor=factor)

    def terms(self, color: torch.Tensor, rgb_gt: torch.Tensor, use_f: torch.Tensor, eps: float):
        """(residual (R, 3), rho (R, 3), omega (R, 3), factor 0-dim): the colour residual, the
        kernel's cost and IRLS weight per residual (before the loss weight, the mask and the
        denominator) and the frame's colour weight."""
        residual = color - rgb_gt
        if self.scale is None or self.factor is None:
            c, factor = self.measured(residual, use_f, eps)
        else:
            c, factor = self.scale, self.factor
        return residual, kernel_cost(residual, self.kernel, c), kernel_weight(residual, self.kernel, c, eps), factor
