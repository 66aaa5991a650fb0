"""Geometric verification of a loop candidate (paper: Robust Loop Detection, Geometry Verification).

An appearance candidate (a keyframe of the *target* map that looks like the query keyframe)
becomes a loop only when geometry agrees, in three steps, cheapest first:

1. **Relative pose from features.** The query's ORB features are matched to the
   candidate's (mutual nearest neighbours), the candidate's features are placed in its
   camera frame by its depth, and a RANSAC PnP gives the query camera's pose in the
   candidate camera's frame ``T_match_query`` with an inlier count. Repeated furniture
   matches in appearance but rarely yields many inliers on one rigid pose together with
   the walls and floor around it.
2. **Refinement against the target map.** The query frame is tracked against the target
   map's rendering (the tracker's loss, the map and decoder frozen) from the PnP pose: the
   paper's inter-map optimisation objective. A refinement that moves far from the PnP pose
   means the two disagree.
3. **The paper's voxel check, and depth agreement.** Rays of the query frame at the refined
   pose must land in the target map's allocated voxels (the paper's intersection test) and
   the depth the map renders along them must agree with the observed depth.

Every score is kept in ``LoopVerification`` so a user can see why a candidate was or was
not accepted. Pure functions of frames, features and a frozen map view.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import torch

from ..config import SLAMConfig
from ..features import FrameFeatures, match_features, pnp_ransac
from ..frames import TensorFrame, sample_pixels
from ..geometry import se3_inverse, se3_log
from ..mapping import MapSnapshot, training_far
from ..render import MapView, render_rays
from ..tracking import FrozenMap, Tracker
from ..voxels import lookup_sorted, morton_encode, voxel_coords_of


@dataclass(frozen=True)
class LoopVerification:
    """The outcome of verifying one candidate, with every score that decided it.

    ``T_match_query`` (4, 4): PnP pose of the query camera in the candidate camera's frame;
    ``T_map_query`` (4, 4): the refined pose of the query camera in the target map's frame
    (None when a step before the refinement rejected the candidate).
    """

    accepted: bool
    reason: str
    """Why it was rejected ("" when accepted)."""
    matches: int = 0
    pnp_inliers: int = 0
    refinement_m: float = float("nan")
    refinement_rad: float = float("nan")
    hit_ratio: float = float("nan")
    depth_agreement: float = float("nan")
    """Share of the query's rays whose rendered depth is within ``loop.depth_tolerance``."""
    depth_error_m: float = float("nan")
    """Median |rendered - observed| depth over the rays that hit the map."""
    T_match_query: np.ndarray | None = None
    T_map_query: np.ndarray | None = None

    def scores(self) -> dict[str, float | int | str]:
        """The scores as plain numbers (for run.json and events)."""
        def num(x: float) -> float | None:
            return None if not np.isfinite(x) else round(float(x), 4)

        return {"matches": self.matches, "pnp_inliers": self.pnp_inliers,
                "refinement_m": num(self.refinement_m), "refinement_rad": num(self.refinement_rad),
                "hit_ratio": num(self.hit_ratio), "depth_agreement": num(self.depth_agreement),
                "depth_error_m": num(self.depth_error_m), "reason": self.reason}


def relative_pose(query: FrameFeatures, match: FrameFeatures, K_query: np.ndarray, reprojection_px: float,
                  min_inliers: int) -> tuple[int, int, np.ndarray | None]:
    """(matches, inliers, T_match_query (4, 4) or None): PnP of the candidate's 3-D features
    (its camera frame) seen at the query's pixels (intrinsics K_query (3, 3))."""
    im, iq = match_features(match, query)
    if len(im) < max(min_inliers, 6):
        return len(im), 0, None
    solved = pnp_ransac(match.points_cam[im], query.pixels[iq], np.asarray(K_query, np.float64),
                        reprojection_px, min_inliers)
    if solved is None:
        return len(im), 0, None
    T, inliers = solved
    return len(im), int(inliers.sum()), T


def geometry_check(frame: TensorFrame, T_map_cam: torch.Tensor, view: MapView, decoder, config: SLAMConfig,
                   num_rays: int, generator: torch.Generator | None = None) -> tuple[float, float, float]:
    """(hit_ratio, depth_agreement, depth_error_m) of ``num_rays`` rays of ``frame`` at
    ``T_map_cam`` (4, 4) in a map.

    hit_ratio: share of the rays' observed surface points that lie in allocated voxels of
    ``view`` (the paper's intersection test); depth_agreement: share of rays whose rendered
    depth is within ``loop.depth_tolerance`` of the observed one (a ray that misses counts
    as disagreeing); depth_error_m: median |error| over the rays that render.
    """
    r, lc = config.render, config.loop
    batch = sample_pixels(frame, num_rays, generator)
    n = batch.depth.shape[0]
    if n == 0:
        return 0.0, 0.0, float("inf")
    with torch.no_grad():
        dirs = batch.dirs_cam @ T_map_cam[:3, :3].T
        origins = T_map_cam[:3, 3].expand(n, 3)
        surface = origins + dirs * batch.depth[:, None]
        codes = morton_encode(voxel_coords_of(surface, view.voxel_size))
        hit_ratio = float((lookup_sorted(view.voxel_codes, codes) >= 0).float().mean())
        out = render_rays(origins, dirs, view, decoder, near=torch.full((n,), 0.05, device=dirs.device),
                          far=training_far(batch.depth, r.truncation, r.max_distance),
                          step=r.step_ratio * view.voxel_size, truncation=r.truncation, max_hits=r.max_hits,
                          mask_in_front=r.mask_in_front)
    rendered = out.hit & (out.weight_sum > 1e-3)
    error = (out.depth - batch.depth).abs()
    agree = rendered & (error <= lc.depth_tolerance)
    median = float(error[rendered].median()) if bool(rendered.any()) else float("inf")
    return hit_ratio, float(agree.float().mean()), median


def frozen_in_map_frame(snapshot: MapSnapshot, config: SLAMConfig, device: torch.device) -> FrozenMap:
    """A frozen map whose 'world' is the map's own frame (T_world_map = I), so that poses
    tracked against it come out in the map frame."""
    return FrozenMap(replace(snapshot, T_world_map=np.eye(4, dtype=np.float32)), config, device)


def verify_candidate(query_frame: TensorFrame, query_features: FrameFeatures, match_features_: FrameFeatures,
                     T_map_match: torch.Tensor, target: "FrozenMap | Callable[[], FrozenMap]", config: SLAMConfig,
                     tracker: Tracker, generator: torch.Generator | None = None) -> LoopVerification:
    """Verify that the query keyframe sees the place of a candidate keyframe of the target map.

    ``T_map_match`` (4, 4): the candidate keyframe's pose in the target map; ``target``: the
    target map frozen in its own frame (:func:`frozen_in_map_frame`), or a function that
    builds it, called only once the features agree (most candidates stop at PnP, and
    freezing a map copies its snapshot and rebuilds its view); ``tracker``: a tracker
    set up for the refinement (``loop.inter_map_iterations`` steps).
    """
    lc = config.loop
    K = query_frame.K.detach().cpu().numpy().astype(np.float64)
    matches, inliers, T_mq = relative_pose(query_features, match_features_, K, lc.pnp_reprojection_px,
                                           lc.min_inliers)
    if T_mq is None or inliers < lc.min_inliers:
        return LoopVerification(False, f"{inliers} PnP inliers < {lc.min_inliers}", matches, inliers)
    if callable(target):
        target = target()
    device = T_map_match.device
    T_pnp = T_map_match @ torch.as_tensor(T_mq, dtype=torch.float32, device=device)
    result = tracker.track(query_frame, target, T_pnp)
    T_ref = result.T_world_cam.to(device)
    moved = se3_log(se3_inverse(T_pnp) @ T_ref)
    dt, dr = float(moved[:3].norm()), float(moved[3:].norm())
    hit, agree, err = geometry_check(query_frame, T_ref, target.view, target.decoder, config, lc.geometry_rays,
                                     generator)
    base = dict(matches=matches, pnp_inliers=inliers, refinement_m=dt, refinement_rad=dr, hit_ratio=hit,
                depth_agreement=agree, depth_error_m=err, T_match_query=T_mq,
                T_map_query=T_ref.detach().cpu().numpy().astype(np.float64))
    if not result.ok:
        return LoopVerification(False, f"refinement against the map failed: {result.reason}", **base)
    if dt > lc.max_refinement_m or dr > lc.max_refinement_rad:
        return LoopVerification(False, f"refinement moved {dt:.3f} m / {dr:.3f} rad from the PnP pose", **base)
    if hit < lc.geometry_min_hit_ratio:
        return LoopVerification(False, f"only {hit:.0%} of rays end in the map's voxels", **base)
    if agree < lc.min_depth_agreement:
        return LoopVerification(False, f"rendered depth agrees on only {agree:.0%} of rays", **base)
    return LoopVerification(True, "", **base)


def refinement_tracker(config: SLAMConfig, device: torch.device, seed: int = 0) -> Tracker:
    """A tracker for loop refinement: the configured tracker without sparse features (there
    is no previous frame), ``loop.inter_map_iterations`` steps, and a jump limit wide
    enough for a PnP start that is a few centimetres off."""
    t = replace(config.tracking, iterations=config.loop.inter_map_iterations, feature_count=0,
                max_jump_m=max(config.tracking.max_jump_m, 2 * config.loop.max_refinement_m),
                max_jump_rad=max(config.tracking.max_jump_rad, 2 * config.loop.max_refinement_rad))
    return Tracker(replace(config, tracking=t), device, seed=seed)

