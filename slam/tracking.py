"""The tracking process (paper: Tracking Process).

The map and decoder are frozen; only the camera pose is optimised, as a twist
``xi in se(3)`` applied on the right of the initial guess (``T = T_init exp(xi)``, i.e. in
the camera frame, which keeps rotation and translation well conditioned far from the map
origin). Each iteration samples ``N_t`` fresh pixels with valid depth, renders them, drops
rays whose depth residual exceeds ``outlier_factor`` times the median, and takes an Adam step
on the four losses. The pose with the lowest loss is returned. Tracking reports failure when
too few rays hit the map or the median depth residual stays too large.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .config import SLAMConfig
from .decoder import Decoder
from .frames import TensorFrame, sample_pixels
from .geometry import se3_exp, se3_inverse, se3_log
from .losses import LossWeights, compute_losses
from .mapping import MapSnapshot, training_far
from .render import MapView, render_rays


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


class FrozenMap:
    """A map snapshot turned into something renderable, rebuilt only when its version changes."""

    def __init__(self, snapshot: MapSnapshot, config: SLAMConfig, device: torch.device):
        self.version = snapshot.version
        self.map_id = snapshot.map_id
        def t(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(a).to(device)

        self.T_world_map = t(snapshot.T_world_map)
        self.T_map_world = se3_inverse(self.T_world_map)
        self.view = MapView(t(snapshot.voxel_codes), t(snapshot.voxel_corners),
                            t(snapshot.embeddings), snapshot.voxel_size)
        self.decoder = Decoder(config.decoder, config.voxel.embed_dim).to(device)
        self.decoder.load_state_dict({k: t(v) for k, v in snapshot.decoder_state.items()})
        self.decoder.requires_grad_(False)


def constant_velocity_guess(previous: list[torch.Tensor], enabled: bool) -> torch.Tensor:
    """Initial pose (4, 4) from the last two poses (constant velocity) or the last one."""
    if len(previous) >= 2 and enabled:
        return previous[-1] @ (se3_inverse(previous[-2]) @ previous[-1])
    return previous[-1].clone()


class Tracker:
    def __init__(self, config: SLAMConfig, device: torch.device, seed: int = 0):
        self.config = config
        self.device = device
        self._gen = torch.Generator().manual_seed(seed + 1)
        c = config.tracking
        self.weights = LossWeights(c.rgb_weight, c.depth_weight, c.sdf_weight, c.fs_weight)

    def track(self, frame: TensorFrame, fmap: FrozenMap, T_init: torch.Tensor) -> TrackingResult:
        c, r = self.config.tracking, self.config.render
        T0_map = fmap.T_map_world @ T_init.to(self.device)
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
        for it in range(1, c.iterations + 1):
            T = T0_map @ se3_exp(torch.cat([rho, phi]))
            batch = sample_pixels(frame, c.num_rays, self._gen)
            n = batch.depth.shape[0]
            dirs = batch.dirs_cam @ T[:3, :3].T
            origins = T[:3, 3].expand(n, 3)
            out = render_rays(origins, dirs, fmap.view, fmap.decoder,
                              near=torch.full((n,), 0.05, device=self.device),
                              far=training_far(batch.depth, r.truncation, r.max_distance),
                              step=step, truncation=r.truncation, max_hits=r.max_hits)
            residual = (out.depth.detach() - batch.depth).abs()
            hit = out.hit & (out.weight_sum.detach() > 1e-3)
            hit_ratio = float(hit.float().mean())
            if not bool(hit.any()):
                break
            med = residual[hit].median()
            inlier = hit & (residual <= c.outlier_factor * med + 1e-6)
            losses = compute_losses(out, batch.rgb, batch.depth, r.truncation, self.weights,
                                    ray_weight=inlier.float(), max_depth=r.max_distance)
            loss = float(losses.total.detach())
            if loss < best[0]:
                best = (loss, T.detach().clone(), hit_ratio, float(med))
            opt.zero_grad(set_to_none=True)
            losses.total.backward()
            prev = torch.cat([rho, phi]).detach().clone()
            opt.step()
            sched.step()
            if float((torch.cat([rho, phi]).detach() - prev).norm()) < c.convergence_tol:
                break
        loss, T_best_map, hit_ratio, residual_med = best
        T_world = fmap.T_world_map @ T_best_map
        reason = ""
        jump = se3_log(se3_inverse(T0_map) @ T_best_map)
        if not bool(torch.isfinite(T_best_map).all()):
            reason = "the pose estimate is not finite"
        elif float(jump[:3].norm()) > c.max_jump_m or float(jump[3:].norm()) > c.max_jump_rad:
            reason = f"the estimate jumped {float(jump[:3].norm()):.2f} m / {float(jump[3:].norm()):.2f} rad from the guess"
        elif hit_ratio < c.min_valid_ratio:
            reason = f"only {hit_ratio:.0%} of rays hit the map"
        elif residual_med > c.max_depth_residual:
            reason = f"median depth residual {residual_med:.3f} m"
        return TrackingResult(T_world.detach(), not reason, it, loss, hit_ratio, residual_med, reason)
