"""The tracking process (paper: Tracking Process).

The map and decoder are frozen; only the camera pose is optimised, as a twist
``xi in se(3)`` applied on the right of the initial guess (``T = T_init exp(xi)``, i.e. in
the camera frame, which keeps rotation and translation well conditioned far from the map
origin), on the paper's four losses over ``N_t`` pixels with valid depth. Rays whose depth
residual exceeds ``outlier_factor`` times the median are dropped.

Two optimisers: ``adam`` (the paper's; new pixels each iteration if ``resample_rays``; the
lowest-loss pose, or the last one with ``keep_best_iterate`` off, as in the release) and
``gauss_newton`` (Levenberg-Marquardt on the same loss with the closed-form model of
``slam.gauss_newton``; one ray set, steps accepted only when the loss falls; optionally a
prior towards the initial guess, ``tracking.motion_prior``, for the directions a plain wall
leaves unobserved; and ``tracking.border_margin``, which leaves out rays ending near the
map's border, whose misses would otherwise pull the pose back into the map). Tracking
reports failure when too few rays hit the map, the median depth residual stays too large or
the estimate jumped implausibly far (then the guess is returned).

Optionally (``tracking.feature_count`` > 0, the ``cpu`` preset) sparse ORB correspondences
to the previous frame (``slam.features``) start the optimisation at their PnP pose and add
their reprojection cost to the loss, for either optimiser; with ``feature_dense_check``
(Gauss-Newton) a frame's features are dropped when the dense loss prefers the motion model's
guess to their PnP pose.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import torch

from .config import SLAMConfig, TrackingConfig
from .decoder import Decoder
from .features import Correspondences, huber_threshold, reprojection_cost, reprojection_terms
from .frames import PixelBatch, TensorFrame, sample_pixels
from .gauss_newton import (Linearisation, MotionPrior, RenderedJacobians, damped_step, damped_step_tensor, limit_step,
                           limit_step_tensor, linearise_rendered, render_with_jacobians,
                           render_with_jacobians_padded)
from .geometry import se3_exp, se3_exp_compact, se3_inverse, se3_log
from .losses import LossWeights, compute_losses
from .mapping import MapSnapshot, training_far
from .profiling import TRACKING_ITERATION, scope
from .padded import band_grid_size, color_slots, grid_samples, grid_size, pack_samples, render_padded, round_up
from .render import MapView, render_rays
from .transfer import to_device
from .voxels import lookup_sorted, morton_encode, voxel_coords_of


@dataclass(frozen=True)
class TrackingResult:
    """T_world_cam (4, 4) float32; ok False means tracking failed (see ``reason``)."""

    T_world_cam: torch.Tensor
    ok: bool
    iterations: int
    loss: float
    hit_ratio: float
    depth_residual: float
    reason: str = ""
    information: np.ndarray | None = None
    """(6, 6) float64 curvature of the data terms (dense, and the features when used; not the
    motion prior) at the estimate, twist order (rho, omega): which directions the view fixed.
    None for the Adam tracker."""


class FrozenMap:
    """A map snapshot turned into something renderable, rebuilt only when its version changes."""

    def __init__(self, snapshot: MapSnapshot, config: SLAMConfig, device: torch.device):
        self.version = snapshot.version
        self.map_id = snapshot.map_id
        self.device = device
        codes, corners = snapshot.voxel_codes, snapshot.voxel_corners
        if snapshot.corner_updates is not None:
            # Only voxels whose eight corners the mapper has optimised: a freshly allocated
            # voxel holds random embeddings whose SDF means nothing yet, and rays landing in
            # one (the new border of a turning camera) would pull the pose anywhere. Chosen
            # on the host, where the snapshot is (``maps.optimised_voxel_mask``'s test).
            keep = (snapshot.corner_updates[corners] >= config.tracking.min_corner_updates).all(1)
            codes, corners = codes[keep], corners[keep]
        # One upload per dtype (``slam.transfer``).
        on_device = to_device({"T_world_map": snapshot.T_world_map, "codes": codes, "corners": corners,
                               "embeddings": snapshot.embeddings,
                               **{f"decoder.{k}": v for k, v in snapshot.decoder_state.items()}}, device)
        self.T_world_map = on_device["T_world_map"]
        self.T_map_world = se3_inverse(self.T_world_map)
        self.view = MapView(on_device["codes"], on_device["corners"], on_device["embeddings"], snapshot.voxel_size)
        self.decoder = Decoder(config.decoder, config.voxel.embed_dim).to(device)
        self.decoder.load_state_dict({k[len("decoder."):]: v for k, v in on_device.items() if k.startswith("decoder.")})
        self.decoder.requires_grad_(False)

    def place(self, T_world_map: np.ndarray) -> "FrozenMap":
        """Put the map at ``T_world_map`` (4, 4) (a map pose newer than its snapshot's): inverted
        on the host, where the pose is (``torch.linalg.inv`` on a device reads its error flag
        back twice), and uploaded with its inverse in one copy. Returns the map itself."""
        T_wm = np.asarray(T_world_map, np.float64)
        both = torch.from_numpy(np.stack([T_wm, np.linalg.inv(T_wm)])).float().to(self.device)
        self.T_world_map, self.T_map_world = both[0], both[1]
        return self


@dataclass(frozen=True)
class _SparseTerm:
    """Feature correspondences in the map frame: points (M, 3), pixels (M, 2), sigmas (M,), K (3, 3)."""

    points_map: torch.Tensor
    pixels: torch.Tensor
    sigmas: torch.Tensor
    K: torch.Tensor
    weight: float
    huber_px: float
    delta: float | None = None
    """The Huber threshold in milliradians, from the host's K (``huber_threshold``)."""

    @staticmethod
    def in_map(matches: Correspondences, T_map_world: torch.Tensor, c: TrackingConfig) -> "_SparseTerm":
        dtype, device = T_map_world.dtype, T_map_world.device
        points = torch.as_tensor(matches.points_world, dtype=dtype, device=device)
        points = points @ T_map_world[:3, :3].T + T_map_world[:3, 3]
        return _SparseTerm(points, torch.as_tensor(matches.pixels, dtype=dtype, device=device),
                           torch.as_tensor(matches.sigmas, dtype=dtype, device=device),
                           torch.as_tensor(matches.K, dtype=dtype, device=device),
                           c.feature_weight, c.feature_huber_px, huber_threshold(matches.K, c.feature_huber_px))

    def cost(self, T_map_cam: torch.Tensor) -> torch.Tensor:
        return reprojection_cost(T_map_cam, self.points_map, self.pixels, self.sigmas, self.K, self.weight,
                                 self.huber_px, self.delta)

    def added_to(self, lin: Linearisation, T_map_cam: torch.Tensor) -> Linearisation:
        """``lin`` plus the features' terms; a tensor ``lin.cost`` (the padded path) stays one."""
        cost, H, g = reprojection_terms(T_map_cam, self.points_map, self.pixels, self.sigmas, self.K, self.weight,
                                        self.huber_px, self.delta, tensor_cost=torch.is_tensor(lin.cost))
        return replace(lin, cost=lin.cost + cost, H=lin.H + H, g=lin.g + g)


def tracking_bounds(depth: torch.Tensor, truncation: float, band: float,
                    max_distance: float) -> tuple[torch.Tensor, torch.Tensor]:
    """near, far (R,) of tracking rays from their observed depth (R,).

    With ``band > 0`` only ``depth -+ band * tr`` is sampled. The renderer keeps weights only
    within tr of a ray's first zero crossing, and for a pose close enough to track that
    crossing lies within a few centimetres of the observed depth, so the samples outside the
    band carry no weight: rendered depth and colour are unchanged (5-6x fewer samples
    indoors). The free-space loss is not: it then sees only the band's front part
    (``depth - band * tr`` to ``depth - tr``) instead of the whole ray in front of the
    surface. The whole ray (``band = 0``, as in the paper) is the plain reference.
    """
    far = training_far(depth, truncation, max_distance)
    if band <= 0:
        return torch.full_like(depth, 0.05), far
    near = torch.clamp(depth - band * truncation, min=0.05)
    return near, torch.clamp(depth + band * truncation, max=max_distance)


def masked_median(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``values[mask].median()`` (the lower median, as torch's) over the last dimension of
    values (..., N) and mask (..., N) bool -> (...), inf where the mask is empty: nothing read
    back from the device. Example: values [3., 1., 2., 9.], mask [T, T, T, F] -> 2."""
    inf = torch.full_like(values, float("inf"))
    ordered = torch.sort(torch.where(mask, values, inf), dim=-1).values
    n = mask.sum(-1)
    k = torch.div((n - 1).clamp(min=0), 2, rounding_mode="floor")
    return torch.where(n > 0, ordered.gather(-1, k[..., None])[..., 0], inf[..., 0])


def interior_rays(T_map_cam: torch.Tensor, dirs_cam: torch.Tensor, depth: torch.Tensor, view: MapView,
                  margin: float) -> torch.Tensor:
    """Rays whose observed surface point lies at least ``margin`` (metres, along each axis)
    inside the map's voxels at pose T_map_cam (4, 4). dirs_cam (R, 3) with z = 1, depth (R,)
    -> (R,) bool.

    A ray that ends near the map's border hits at one pose and misses a little further on, so
    the tracking cost, which charges a miss, falls as the pose moves back into the map. Where
    the view fixes nothing else (a plain wall along the direction of travel) that alone
    decides the pose, and the camera lags behind its true motion frame after frame.
    """
    p = (dirs_cam * depth[:, None]) @ T_map_cam[:3, :3].T + T_map_cam[:3, 3]
    eye = torch.eye(3, dtype=p.dtype, device=p.device)
    shifts = torch.cat([torch.zeros_like(eye[:1]), eye * margin, -eye * margin])
    codes = morton_encode(voxel_coords_of((p[:, None, :] + shifts).reshape(-1, 3), view.voxel_size))
    return (lookup_sorted(view.voxel_codes, codes) >= 0).reshape(-1, shifts.shape[0]).all(1)


def _select(take: torch.Tensor, a: Linearisation, b: Linearisation) -> Linearisation:
    """``a`` where the 0-dim bool ``take`` holds, else ``b``, field by field, on the device."""
    def pick(x, y):
        return torch.where(take, x, y)

    return Linearisation(pick(a.cost, b.cost), pick(a.H, b.H), pick(a.g, b.g), pick(a.depth, b.depth),
                         pick(a.hit, b.hit), pick(a.residual, b.residual))


@dataclass
class _LMProblem:
    """One frame's damped Gauss-Newton problem: its rays (``batch``), the render at a pose
    (``render_at(T, jacobians=True)``, plain or padded), the loss's weights, depth limit and
    miss cost, and what the start fixes: the features (None without, or
    once the dense check dropped them), the start pose T0_map (4, 4) and the motion prior."""

    batch: PixelBatch
    render_at: Callable[..., RenderedJacobians]
    weights: LossWeights
    max_depth: float
    miss_cost: float
    sparse: _SparseTerm | None
    T0_map: torch.Tensor
    prior: MotionPrior | None = None

    def dense_of(self, rendered: RenderedJacobians, ray_weight: torch.Tensor | None) -> Linearisation:
        return linearise_rendered(rendered, self.batch.rgb, self.batch.depth, ray_weight, weights=self.weights,
                                  max_depth=self.max_depth, miss_cost=self.miss_cost)

    def linearise_at(self, T: torch.Tensor, ray_weight: torch.Tensor | None,
                     rendered: RenderedJacobians | None = None) -> Linearisation:
        """The loss at pose ``T`` (rendered there unless ``rendered`` is given), features and
        motion prior included."""
        lin = self.dense_of(rendered if rendered is not None else self.render_at(T), ray_weight)
        if self.sparse is not None:
            lin = self.sparse.added_to(lin, T)
        return lin if self.prior is None else self.prior.added_to(lin, se3_log(se3_inverse(self.T0_map) @ T))

    def curvature(self, best: Linearisation) -> torch.Tensor:
        """The data terms' (6, 6) curvature of ``best``: its H less the motion prior's."""
        return best.H if self.prior is None else best.H - torch.diag(2 * self.prior.w).to(best.H.dtype)


def _adam_static_step(opt: torch.optim.Optimizer, sched, rho: torch.Tensor, phi: torch.Tensor,
                      total: torch.Tensor, live: torch.Tensor, convergence_tol: float) -> torch.Tensor:
    """One Adam step of the static tracker on ``total``, undone where the iterate is not
    ``live``; returns whether the next iterate is alive (live and still moving)."""
    opt.zero_grad(set_to_none=True)
    total.backward()
    prev = torch.cat([rho, phi]).detach().clone()
    opt.step()
    sched.step()
    with torch.no_grad():
        # A stopped iteration (no ray hit, or after a stop) leaves the pose.
        rho.copy_(torch.where(live, rho, prev[:3]))
        phi.copy_(torch.where(live, phi, prev[3:]))
    moved = (torch.cat([rho, phi]).detach() - prev).norm()
    return live & ~(moved < convergence_tol)


class Tracker:
    def __init__(self, config: SLAMConfig, device: torch.device, seed: int = 0):
        self.config = config
        self.device = device
        # On the device: a CUDA generator draws the rays on the GPU (no upload, no sync); on
        # the CPU it is the generator it always was.
        self._gen = torch.Generator(device=device).manual_seed(seed + 1)
        self.static = config.render.uses_static_shapes(device)
        c = config.tracking
        self.weights = LossWeights(c.rgb_weight, c.depth_weight, c.sdf_weight, c.fs_weight)

    def track(self, frame: TensorFrame, fmap: FrozenMap, T_init: torch.Tensor,
              matches: Correspondences | None = None) -> TrackingResult:
        """Optimise the pose of ``frame`` against the frozen map from ``T_init`` (4, 4) world.

        ``matches``: sparse correspondences of this frame (``slam.features``); when given,
        their PnP pose replaces ``T_init`` and their reprojection cost joins the loss.
        """
        T_init = T_init.to(self.device)
        sparse = None
        T_guess_map = fmap.T_map_world @ T_init
        if matches is not None and self._plausible(matches, T_init):
            T_init = torch.as_tensor(matches.T_world_cam_pnp, dtype=T_init.dtype, device=self.device)
            sparse = _SparseTerm.in_map(matches, fmap.T_map_world, self.config.tracking)
        T0_map = fmap.T_map_world @ T_init
        if self.config.tracking.optimizer == "gauss_newton":
            # The start may fall back from the PnP pose to the guess (feature_dense_check):
            # the jump test and a diverged estimate's fallback use the start it took.
            lm = self._levenberg_marquardt_static if self.static else self._levenberg_marquardt
            it, loss, T_best_map, hit_ratio, residual_med, T0_map, information = lm(
                self._tracking_batch(frame), frame.depth_max, fmap, T0_map, sparse,
                T_guess_map if sparse is not None else None)
        else:
            adam = self._adam_static if self.static else self._adam
            it, loss, T_best_map, hit_ratio, residual_med = adam(frame, fmap, T0_map, sparse)
            information = None
        return self._result(fmap, T0_map, T_best_map, it, loss, hit_ratio, residual_med, information)

    def _plausible(self, matches: Correspondences, T_init: torch.Tensor) -> bool:
        """Whether the matches' PnP pose lies within the tracker's jump limits of the guess:
        RANSAC can agree on a wrong pose (repeated texture), and a far start would hand the
        dense loss a pose it cannot correct."""
        c = self.config.tracking
        T_pnp = torch.as_tensor(matches.T_world_cam_pnp, dtype=T_init.dtype, device=T_init.device)
        jump = se3_log(se3_inverse(T_init) @ T_pnp)
        return float(jump[:3].norm()) <= c.max_jump_m and float(jump[3:].norm()) <= c.max_jump_rad

    def retrack(self, rays: PixelBatch, fmap: FrozenMap, T_init: torch.Tensor) -> TrackingResult:
        """Optimise a pose again on pixels kept from its frame (``keep_rays``): the final
        re-tracking against a refined map (``tracking.retrack_iterations``), by Levenberg-Marquardt
        whatever ``tracking.optimizer`` says, from ``T_init`` (4, 4) world."""
        r = self.config.render
        rays = PixelBatch(*(t.to(self.device) for t in (rays.dirs_cam, rays.rgb, rays.depth)))
        depth_max = float(rays.depth.max())  # one read a frame, at the end of the run
        near, far = tracking_bounds(rays.depth, r.truncation, self.config.tracking.sample_band, r.max_distance)
        T0_map = fmap.T_map_world @ T_init.to(self.device)
        lm = self._levenberg_marquardt_static if self.static else self._levenberg_marquardt
        it, loss, T_best_map, hit_ratio, residual_med, T0_map, information = lm(
            (rays, near, far), depth_max, fmap, T0_map, None)
        return self._result(fmap, T0_map, T_best_map, it, loss, hit_ratio, residual_med, information)

    def keep_rays(self, frame: TensorFrame, num: int, generator: torch.Generator) -> PixelBatch:
        """``num`` pixels of ``frame`` for ``retrack`` (28 bytes a pixel), on the frame's device:
        a copy to the host would wait for the device every frame."""
        batch = sample_pixels(frame, num, generator)
        return PixelBatch(*(t.detach() for t in (batch.dirs_cam, batch.rgb, batch.depth)))

    def _levenberg_marquardt(self, rays: tuple[PixelBatch, torch.Tensor, torch.Tensor], depth_max: float | None,
                             fmap: FrozenMap, T0_map: torch.Tensor,
                             sparse: _SparseTerm | None, T_guess_map: torch.Tensor | None = None):
        """Damped Gauss-Newton on the paper's loss (``slam.gauss_newton``): one set of rays
        (``rays``: the pixels and their near, far bounds; ``depth_max`` their frame's largest
        depth, None: unknown), outliers fixed at the initial pose, a step accepted only if it
        lowers the loss. Returns
        (iterations, loss, pose, hit ratio, median depth residual, the pose it started from,
        the data terms' (6, 6) curvature at the pose or None)).

        ``T_guess_map``: the motion model's guess when ``T0_map`` is the features' PnP pose.
        With ``tracking.feature_dense_check`` the features are dropped for this frame when
        the dense loss is lower at the guess than at their pose: repeated texture can make
        RANSAC agree on a pose one period off, which the depth does not support."""
        c, r = self.config.tracking, self.config.render
        batch, near, far = rays

        def render_at(T: torch.Tensor, jacobians: bool = True) -> RenderedJacobians:
            return render_with_jacobians(T, batch.dirs_cam, fmap.view, fmap.decoder, near=near, far=far,
                                         step=self._step(fmap), truncation=r.truncation,
                                         max_hits=r.max_hits, color_weight_eps=c.color_weight_eps,
                                         mask_in_front=r.mask_in_front, jacobians=jacobians,
                                         renormalise_color=True)

        lm = self._lm_problem(batch, render_at, sparse, T0_map)
        rendered0, first = self._lm_first(lm, T_guess_map)
        if not bool(first.hit.any()):
            return 0, float("inf"), lm.T0_map, 0.0, float("inf"), lm.T0_map, None
        med = first.residual[first.hit].median()
        inlier = first.hit & (first.residual <= c.outlier_factor * med + 1e-6)
        if c.border_margin > 0:
            inner = inlier & interior_rays(lm.T0_map, batch.dirs_cam, batch.depth, fmap.view, c.border_margin)
            if int(inner.sum()) >= c.min_valid_ratio * inlier.numel():
                inlier = inner
        inlier = inlier.float()
        # The same render as ``first``, weighed again without the outliers.
        start = self._lm_start(lm, rendered0, inlier)
        it, T, best = self._lm_iterate(lm, start, inlier)
        hit_ratio = float(best.hit.float().mean())
        residual_med = float(best.residual[best.hit].median()) if bool(best.hit.any()) else float("inf")
        H = lm.curvature(best)
        return it, best.cost, T, hit_ratio, residual_med, lm.T0_map, H.detach().cpu().numpy().astype(np.float64)

    def _tracking_batch(self, frame: TensorFrame) -> tuple[PixelBatch, torch.Tensor, torch.Tensor]:
        """``tracking.num_rays`` pixels of ``frame`` and their near, far bounds (R,)."""
        c, r = self.config.tracking, self.config.render
        batch = sample_pixels(frame, c.num_rays, self._gen)
        near, far = tracking_bounds(batch.depth, r.truncation, c.sample_band, r.max_distance)
        return batch, near, far

    def _step(self, fmap: FrozenMap) -> float:
        """The sample step along a ray (metres)."""
        return self.config.render.step_ratio * fmap.view.voxel_size

    def _lm_problem(self, batch: PixelBatch, render_at, sparse: _SparseTerm | None,
                    T0_map: torch.Tensor) -> "_LMProblem":
        r = self.config.render
        # A ray that leaves the map costs as much as one off by the truncation in depth and SDF.
        miss_cost = self.weights.depth * r.truncation + self.weights.sdf * r.truncation ** 2
        return _LMProblem(batch, render_at, self.weights, r.max_distance, miss_cost, sparse, T0_map)

    def _lm_first(self, lm: "_LMProblem", T_guess_map: torch.Tensor | None
                  ) -> tuple[RenderedJacobians, Linearisation]:
        """The render at the start and its dense linearisation. With the features' pose as
        the start and ``tracking.feature_dense_check``, the guess replaces it (and the
        features are dropped: ``lm.sparse``, ``lm.T0_map``) when its dense loss is lower."""
        rendered0 = lm.render_at(lm.T0_map)
        first = lm.dense_of(rendered0, None)
        if lm.sparse is not None and T_guess_map is not None and self.config.tracking.feature_dense_check:
            # Only the loss decides; the guess's model is rendered only if the guess wins.
            if bool(lm.dense_of(lm.render_at(T_guess_map, jacobians=False), None).cost < first.cost):
                rendered0 = lm.render_at(T_guess_map)
                first = lm.dense_of(rendered0, None)
                lm.sparse, lm.T0_map = None, T_guess_map
        return rendered0, first

    def _lm_start(self, lm: "_LMProblem", rendered0: RenderedJacobians, inlier: torch.Tensor) -> Linearisation:
        """The linearisation the iterations start from: the first render weighed by ``inlier``
        (R,) float, with the motion prior (when ``tracking.motion_prior`` > 0) scaled to it
        and set in ``lm.prior``."""
        c = self.config.tracking
        start = lm.linearise_at(lm.T0_map, inlier, rendered0)
        if c.motion_prior > 0:
            lm.prior = MotionPrior.scaled_to(start, c.motion_prior)
            start = lm.prior.added_to(start, torch.zeros(6, dtype=lm.T0_map.dtype, device=lm.T0_map.device))
        return start

    def _lm_iterate(self, lm: "_LMProblem", start: Linearisation, inlier: torch.Tensor
                    ) -> tuple[int, torch.Tensor, Linearisation]:
        """Levenberg-Marquardt steps from ``start``, decided on the host: (iterations, pose,
        its linearisation)."""
        c = self.config.tracking
        T, best = lm.T0_map, start
        damping = c.lm_damping
        it = 0
        for it in range(1, c.iterations + 1):
            with scope(TRACKING_ITERATION):
                delta = limit_step(damped_step(best, damping), c.max_step_m, c.max_step_rad)
                if not bool(torch.isfinite(delta).all()):
                    break
                if float(delta.norm()) < c.convergence_tol:
                    # Converged: a step this small would change the pose by less than the
                    # tolerance whether it is accepted or not, so it is not worth a render (on
                    # fr1/rpy the third step is 1e-7-1e-5 and changes the loss by < 1e-5).
                    break
                T_new = T @ se3_exp(delta)
                cand = lm.linearise_at(T_new, inlier)
                if cand.cost < best.cost:
                    T, best = T_new, cand
                    damping = max(damping / 3.0, 1e-7)
                else:
                    damping *= 10.0
                    if damping > 1e3:
                        break
        return it, T, best

    def _adam(self, frame: TensorFrame, fmap: FrozenMap, T0_map: torch.Tensor, sparse: _SparseTerm | None):
        """The paper's optimiser: Adam on the twist, new rays every iteration if configured."""
        c, r = self.config.tracking, self.config.render
        rho = torch.zeros(3, device=self.device, requires_grad=True)
        phi = torch.zeros(3, device=self.device, requires_grad=True)
        opt = torch.optim.Adam([{"params": [rho], "lr": c.lr_trans}, {"params": [phi], "lr": c.lr_rot}])
        # Adam's steps are about lr per coordinate whatever the gradient, so a fixed lr either
        # crawls or rattles around the optimum; decay it geometrically by lr_decay overall.
        gamma = c.lr_decay ** (1.0 / max(c.iterations - 1, 1))
        sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma)
        best = (float("inf"), T0_map.clone(), 0.0, float("inf"))
        step = r.step_ratio * fmap.view.voxel_size
        it = 0
        batch = sample_pixels(frame, c.num_rays, self._gen)
        near, far = tracking_bounds(batch.depth, r.truncation, c.sample_band, r.max_distance)
        for it in range(1, c.iterations + 1):
            with scope(TRACKING_ITERATION):
                T = T0_map @ se3_exp(torch.cat([rho, phi]))
                if c.resample_rays and it > 1:
                    batch = sample_pixels(frame, c.num_rays, self._gen)
                    near, far = tracking_bounds(batch.depth, r.truncation, c.sample_band, r.max_distance)
                n = batch.depth.shape[0]
                dirs = batch.dirs_cam @ T[:3, :3].T
                origins = T[:3, 3].expand(n, 3)
                out = render_rays(origins, dirs, fmap.view, fmap.decoder, near=near, far=far,
                                  step=step, truncation=r.truncation, max_hits=r.max_hits,
                                  color_weight_eps=c.color_weight_eps, mask_in_front=r.mask_in_front,
                                  renormalise_color=True)
                residual = (out.depth.detach() - batch.depth).abs()
                hit = out.hit & (out.weight_sum.detach() > 1e-3)
                hit_ratio = float(hit.float().mean())
                if not bool(hit.any()):
                    break
                med = residual[hit].median()
                inlier = hit & (residual <= c.outlier_factor * med + 1e-6)
                losses = compute_losses(out, batch.rgb, batch.depth, r.truncation, self.weights,
                                        ray_weight=inlier.float(), max_depth=r.max_distance)
                total = losses.total if sparse is None else losses.total + sparse.cost(T)
                loss = float(total.detach())
                if loss < best[0]:
                    best = (loss, T.detach().clone(), hit_ratio, float(med))
                opt.zero_grad(set_to_none=True)
                total.backward()
                prev = torch.cat([rho, phi]).detach().clone()
                opt.step()
                sched.step()
                if float((torch.cat([rho, phi]).detach() - prev).norm()) < c.convergence_tol:
                    break
        if not c.keep_best_iterate and np.isfinite(best[0]):
            # The release's choice: the pose after the last step (its loss and ray statistics
            # are those of the last evaluated iterate, one step before).
            T_last = (T0_map @ se3_exp(torch.cat([rho, phi]))).detach()
            return it, loss, T_last, hit_ratio, float(med)
        loss, T_best_map, hit_ratio, residual_med = best
        return it, loss, T_best_map, hit_ratio, residual_med

    # ------------------------------------------------------------- static shapes
    def _sample_shape(self, depth_max: float | None, fmap: FrozenMap, dirs_cam: torch.Tensor, near: torch.Tensor,
                      far: torch.Tensor, T_map: torch.Tensor) -> tuple[int, int, int]:
        """(grid points G, slots N, colour slots C) of this frame's padded samples
        (``slam.padded``). Tracking's band needs no more slots than its grid; the whole ray
        (``sample_band = 0``) is sized once per frame by the most samples a ray of the first
        batch holds at ``T_map``, with a quarter more for the poses and rays to come (one
        read of the device per frame, outside the iterations)."""
        c, r = self.config.tracking, self.config.render
        step = r.step_ratio * fmap.view.voxel_size
        if c.sample_band > 0:
            G = band_grid_size(c.sample_band, r.truncation, step)
            N = G
        else:
            if depth_max is None:
                depth_max = float(far.max())  # unknown: the rays' far bound, a little past their depth
            G = grid_size(0.05, min(depth_max + 2.0 * r.truncation, r.max_distance), step)
            with torch.no_grad():
                dirs = dirs_cam @ T_map[:3, :3].T
                grid = grid_samples(T_map[:3, 3].expand_as(dirs), dirs, near, far, step, fmap.view, G,
                                    max_hits=r.max_hits)
                N = min(G, round_up(1.25 * int(grid.counts().max())))
        return G, N, color_slots(r.truncation, step, N, r.mask_in_front)

    def _levenberg_marquardt_static(self, rays: tuple[PixelBatch, torch.Tensor, torch.Tensor],
                                    depth_max: float | None, fmap: FrozenMap, T0_map: torch.Tensor,
                                    sparse: _SparseTerm | None, T_guess_map: torch.Tensor | None = None):
        """``_levenberg_marquardt`` on padded samples with its control on the device: the
        step, its acceptance, the damping and the stop conditions are tensors, so an
        iteration reads nothing back; the host reads the stop flag every
        ``tracking.check_every`` iterations (an iteration after a stop changes nothing).
        The reads before and after the loop are a few per frame."""
        c, r = self.config.tracking, self.config.render
        batch, near, far = rays
        G, N, C = self._sample_shape(depth_max, fmap, batch.dirs_cam, near, far, T0_map)

        def render_at(T: torch.Tensor, jacobians: bool = True) -> RenderedJacobians:
            return render_with_jacobians_padded(T, batch.dirs_cam, fmap.view, fmap.decoder, near=near, far=far,
                                                step=self._step(fmap), truncation=r.truncation,
                                                max_hits=r.max_hits, grid=G, slots=N, color_slots=C,
                                                color_weight_eps=c.color_weight_eps, mask_in_front=r.mask_in_front,
                                                jacobians=jacobians, renormalise_color=True)

        lm = self._lm_problem(batch, render_at, sparse, T0_map)
        rendered0, first = self._lm_first(lm, T_guess_map)
        if not bool(first.hit.any()):
            return 0, float("inf"), lm.T0_map, 0.0, float("inf"), lm.T0_map, None
        med = masked_median(first.residual, first.hit)
        inlier = first.hit & (first.residual <= c.outlier_factor * med + 1e-6)
        if c.border_margin > 0:
            inner = inlier & interior_rays(lm.T0_map, batch.dirs_cam, batch.depth, fmap.view, c.border_margin)
            inlier = torch.where(inner.sum() >= c.min_valid_ratio * inlier.numel(), inner, inlier)
        inlier = inlier.float()
        start = self._lm_start(lm, rendered0, inlier)
        T, best, count = self._lm_iterate_static(lm, start, inlier)
        H = lm.curvature(best)
        # One read of the device: the statistics ride along with the curvature.
        H = H.detach().to(torch.float64)
        stats = torch.stack([best.hit.float().mean().to(H.dtype), masked_median(best.residual, best.hit).to(H.dtype),
                             count.to(H.dtype), torch.as_tensor(best.cost).to(H.dtype)])
        host = torch.cat([H.reshape(-1), stats]).cpu().numpy()
        hit_ratio, residual_med, it, cost = (float(v) for v in host[36:])
        return int(it), cost, T, hit_ratio, residual_med, lm.T0_map, host[:36].reshape(6, 6).copy()

    def _lm_iterate_static(self, lm: "_LMProblem", start: Linearisation, inlier: torch.Tensor
                           ) -> tuple[torch.Tensor, Linearisation, torch.Tensor]:
        """Levenberg-Marquardt steps from ``start`` decided on the device: (pose, its
        linearisation, the 0-dim count of live iterations). An iteration reads nothing back;
        the host reads the stop flag every ``tracking.check_every`` iterations."""
        c = self.config.tracking
        device = lm.T0_map.device
        T, best = lm.T0_map, start
        damping = torch.tensor(c.lm_damping, dtype=torch.float64, device=device)
        done = torch.zeros((), dtype=torch.bool, device=device)
        count = torch.zeros((), dtype=torch.int64, device=device)
        for it in range(1, c.iterations + 1):
            with scope(TRACKING_ITERATION):
                delta = limit_step_tensor(damped_step_tensor(best, damping), c.max_step_m, c.max_step_rad)
                stop = done | ~torch.isfinite(delta).all() | (delta.norm() < c.convergence_tol)
                count = count + (~done).long()
                delta = torch.where(stop, torch.zeros_like(delta), delta)
                T_new = T @ se3_exp_compact(delta)
                cand = lm.linearise_at(T_new, inlier)
                accept = ~stop & (cand.cost < best.cost)
                T = torch.where(accept, T_new, T)
                best = _select(accept, cand, best)
                damping = torch.where(stop, damping, torch.where(accept, (damping / 3.0).clamp(min=1e-7), damping * 10.0))
                done = stop | (~accept & (damping > 1e3))
            if c.check_every > 0 and it % c.check_every == 0 and it < c.iterations and bool(done):
                break
        return T, best, count

    def _adam_static(self, frame: TensorFrame, fmap: FrozenMap, T0_map: torch.Tensor, sparse: _SparseTerm | None):
        """``_adam`` on padded samples with its bookkeeping on the device: the lowest loss
        and its pose, the last iterate's statistics and the stop conditions (no ray hits,
        convergence) are tensors; an iteration after a stop leaves the pose where it was.
        The host reads the stop flag every ``tracking.check_every`` iterations."""
        c = self.config.tracking
        device = T0_map.device
        rho = torch.zeros(3, device=device, requires_grad=True)
        phi = torch.zeros(3, device=device, requires_grad=True)
        opt = torch.optim.Adam([{"params": [rho], "lr": c.lr_trans}, {"params": [phi], "lr": c.lr_rot}], fused=True)
        gamma = c.lr_decay ** (1.0 / max(c.iterations - 1, 1))
        sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma)
        batch, near, far = self._tracking_batch(frame)
        shape = self._sample_shape(frame.depth_max, fmap, batch.dirs_cam, near, far, T0_map)
        # (loss, hit ratio, median residual) of the lowest-loss and of the last live iterate
        inf = float("inf")
        best = torch.full((3,), inf, dtype=torch.float64, device=device)
        best[1] = 0.0
        last = best.clone()
        best_T = T0_map.detach().clone()
        alive = torch.ones((), dtype=torch.bool, device=device)
        count = torch.zeros((), dtype=torch.int64, device=device)
        # Without a convergence test only a frame whose rays all miss stops early, and the
        # iterations after a stop change nothing: reading the flag would buy nothing but a
        # sync per check (the paper preset: 49 a frame).
        check = c.check_every if c.convergence_tol > 0 else 0
        for it in range(1, c.iterations + 1):
            with scope(TRACKING_ITERATION):
                count = count + alive.long()
                T = T0_map @ se3_exp_compact(torch.cat([rho, phi]))
                if c.resample_rays and it > 1:
                    batch, near, far = self._tracking_batch(frame)
                out = self._render_padded(fmap, T, batch, near, far, shape)
                total, now, live = self._adam_static_loss(out, batch, T, sparse, alive)
                better = live & (now[0] < best[0])
                best = torch.where(better, now, best)
                best_T = torch.where(better, T.detach(), best_T)
                last = torch.where(live, now, last)
                alive = _adam_static_step(opt, sched, rho, phi, total, live, c.convergence_tol)
            if check > 0 and it % check == 0 and it < c.iterations and not bool(alive):
                break
        it, best_loss, best_hit, best_med, last_loss, last_hit, last_med = (
            torch.cat([count.to(best.dtype)[None], best, last]).tolist())  # (one read)
        it = int(it)
        if not c.keep_best_iterate and np.isfinite(best_loss):
            T_last = (T0_map @ se3_exp_compact(torch.cat([rho, phi]))).detach()
            return it, last_loss, T_last, last_hit, last_med
        return it, best_loss, best_T, best_hit, best_med

    def _render_padded(self, fmap: FrozenMap, T: torch.Tensor, batch: PixelBatch, near: torch.Tensor,
                       far: torch.Tensor, shape: tuple[int, int, int]):
        """The batch's rays from pose ``T`` (4, 4) rendered on padded samples of ``shape``
        (grid points, slots, colour slots; ``_sample_shape``)."""
        r = self.config.render
        G, N, C = shape
        n = batch.depth.shape[0]
        dirs = batch.dirs_cam @ T[:3, :3].T
        origins = T[:3, 3].expand(n, 3)
        with torch.no_grad():
            samples = pack_samples(grid_samples(origins.detach(), dirs.detach(), near, far, self._step(fmap),
                                                fmap.view, G, max_hits=r.max_hits), N)
        return render_padded(origins, dirs, fmap.view, fmap.decoder, samples, truncation=r.truncation,
                             color_weight_eps=self.config.tracking.color_weight_eps, color_slots=C,
                             mask_in_front=r.mask_in_front, renormalise_color=True)

    def _adam_static_loss(self, out, batch: PixelBatch, T: torch.Tensor, sparse: _SparseTerm | None,
                          alive: torch.Tensor):
        """The loss of one static Adam iterate: (its total, (3,) float64 of its value, hit
        ratio and median depth residual, whether the iterate is live (alive with a hit))."""
        c, r = self.config.tracking, self.config.render
        residual = (out.depth.detach() - batch.depth).abs()
        hit = out.hit & (out.weight_sum.detach() > 1e-3)
        hit_ratio = hit.to(residual.dtype).mean()
        live = alive & hit.any()
        med = masked_median(residual, hit)
        inlier = hit & (residual <= c.outlier_factor * med + 1e-6)
        losses = compute_losses(out, batch.rgb, batch.depth, r.truncation, self.weights,
                                ray_weight=inlier.float(), max_depth=r.max_distance)
        total = losses.total if sparse is None else losses.total + sparse.cost(T)
        now = torch.stack([total.detach(), hit_ratio, med]).to(torch.float64)
        return total, now, live

    def _result(self, fmap: FrozenMap, T0_map: torch.Tensor, T_best_map: torch.Tensor, it: int,
                loss: float, hit_ratio: float, residual_med: float,
                information: np.ndarray | None = None) -> TrackingResult:
        """The checked result of an optimisation that started at ``T0_map`` and ended at
        ``T_best_map`` (4, 4, map frame), with its data terms' (6, 6) curvature or None."""
        c = self.config.tracking
        T_world = fmap.T_world_map @ T_best_map
        reason = ""
        jump = se3_log(se3_inverse(T0_map) @ T_best_map)
        # One read of the device for the three tests (finite, metres, radians).
        finite, jump_m, jump_rad = torch.stack([torch.isfinite(T_best_map).all().to(jump.dtype),
                                                jump[:3].norm(), jump[3:].norm()]).tolist()
        if not finite:
            reason = "the pose estimate is not finite"
        elif jump_m > c.max_jump_m or jump_rad > c.max_jump_rad:
            reason = f"the estimate jumped {jump_m:.2f} m / {jump_rad:.2f} rad from the guess"
        elif hit_ratio < c.min_valid_ratio:
            reason = f"only {hit_ratio:.0%} of rays hit the map"
        elif residual_med > c.max_depth_residual:
            reason = f"median depth residual {residual_med:.3f} m"
        if reason.startswith(("the pose estimate", "the estimate jumped")):
            T_world = fmap.T_world_map @ T0_map  # a diverged estimate is worse than the guess
        return TrackingResult(T_world.detach(), not reason, it, loss, hit_ratio, residual_med, reason,
                              information=information)
