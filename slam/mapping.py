"""The mapping process (paper: Mapping Process and Dynamic Voxel Management).

For every tracked frame the mapper
1. decides whether it is a keyframe: the ratio ``p_kf = N_c / N_o`` exceeds
   ``keyframe_ratio``, or no keyframe was taken for ``keyframe_max_interval`` frames. ``N_o``
   counts the voxels the frame observes and ``N_c`` those of them that no keyframe has
   observed yet: the paper's ``N_c`` is the voxels the frame would newly allocate, but here
   every tracked frame allocates (step 2), so counting allocations would starve the test;
2. allocates the voxels of every successfully tracked frame's back-projected depth (at depth
   and +-tr, so the truncation band around the surface lies inside allocated voxels);
3. jointly optimises embeddings, decoder and keyframe poses over a window of ``window_size``
   frames: random earlier keyframes, the newest keyframe and, when the frame is no keyframe,
   the frame itself with its tracked pose held fixed (the paper optimises that pose too, and
   so does ``mapping.optimize_current_pose``: the refined pose is then the frame's estimate,
   ``MappingStep.T_map_cam``). The first keyframe of a map is fixed to remove the gauge
   freedom;
4. at the end of a sequence, ``global_bundle_adjustment`` does the same over every keyframe
   of the submap (the paper's intra-map optimisation).

The ``Mapper`` is plain state with no process code; ``slam.runtime`` runs it in its own process.
"""

from __future__ import annotations

import math
import random
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import torch

from .config import SLAMConfig
from .fine_color import coarse_point_color, fine_loss, fit_loss
from .frames import (
    FrameStack,
    draw_device,
    PixelBatch,
    TensorFrame,
    backproject,
    sample_pixels,
    sample_stacked_pixels,
    stack_frames,
)
from .geometry import pose_moved, se3_exp, se3_exp_compact, se3_inverse
from .losses import LossWeights, Losses, compute_losses
from .optimizers import adam
from .maps import Keyframe, MapSet, SubMap
from .padded import color_slots, grid_samples, grid_size, pack_samples, render_padded, round_up
from .profiling import MAPPING_ITERATION, StageClock, scope
from .render import TrainingThinning, render_rays
from .transfer import to_host
from .voxels import grow_adam_state, lookup_sorted, morton_encode, voxel_coords_of


FIT_KEYFRAMES = 8
"""Keyframes a fit step of the fine colour level draws its points from (``Mapper.fit_fine``)."""
FIT_KEYFRAMES_FINAL = 1 << 30
"""... after the final bundle adjustment: every keyframe."""

FIT_KEYFRAMES_RENDERED = 16
"""Keyframes the rendered-surface fit renders at most (evenly spread): the renders are its
cost (decisions.md#fine_color)."""


@dataclass(frozen=True)
class TrackedFrame:
    """What tracking hands to mapping: the frame and its estimated world pose (4, 4) float32."""

    frame: TensorFrame
    T_world_cam: torch.Tensor
    tracking_ok: bool = True
    agent: int = 0
    new_map: "NewMap | None" = None
    """Start a new map of ``agent`` with this frame first; None: map into the agent's active
    map (an agent's first frame starts its first map either way)."""


@dataclass(frozen=True)
class NewMap:
    """The tracker's decision to start a map: why (``start``, ``region`` or
    ``tracking_failure``, see ``slam.events.SubmapEvent``), its id (the tracker numbers maps,
    so both processes agree without a round trip) and its pose T_world_map (4, 4)."""

    reason: str
    map_id: int
    T_world_map: torch.Tensor


@dataclass(frozen=True)
class MapSnapshot:
    """A read-only copy of one submap for the tracker, published by version.

    Plain numpy arrays, so it pickles by value between processes (no shared-memory file
    descriptors piling up, no manager): T_world_map (4, 4), voxel_codes (Nv,) int64,
    voxel_corners (Nv, 8) int64, embeddings (Nc, D) float32, decoder_state name -> array.
    """

    version: int
    map_id: int
    T_world_map: np.ndarray
    voxel_size: float
    voxel_codes: np.ndarray
    voxel_corners: np.ndarray
    embeddings: np.ndarray
    decoder_state: dict[str, np.ndarray]
    corner_updates: np.ndarray | None = None
    """(Nc,) int32: optimisation steps in which each embedding row received a gradient
    (None: unknown, every voxel counts as trained)."""
    frames_integrated: int = 0
    """Tracked frames the mapping side had integrated (all maps and agents) when this copy
    was taken: the tracker compares it with the frames it sent to know how old the map is."""


@dataclass(frozen=True)
class MappingStep:
    frame_index: int
    is_keyframe: bool
    new_voxel_ratio: float
    new_voxels: int
    losses: dict[str, float]
    seconds: float
    map_id: int = 0
    started_map: str | None = None
    """The reason a map was started with this frame (None: none was)."""
    T_map_cam: torch.Tensor | None = None
    """(4, 4) the frame's pose in map ``map_id`` as the window optimised it
    (``mapping.optimize_current_pose``; None: the tracked pose was held)."""


def fit_pixels(frame: TensorFrame, which: str) -> torch.Tensor:
    """(H, W) bool: the pixels of ``frame`` the fine colour level's rendered-surface fit learns
    from (``fine_color.fit_pixels``): ``observed``, every pixel whose colour the camera saw
    (``TensorFrame.color_valid``); ``measured``, those with measured depth. The fit reads the
    surface the coarse map renders, not the depth, so a pixel without depth (Kinect's shadow
    and border, far or dark surfaces: a fifth of a fr1/rpy frame) still tells the colour a
    view shows there. A frame without ``color_valid`` (a stream's: the wire carries no mask)
    leaves out the pixels that are pure black without depth, what undistortion's border
    looks like; a real black surface without depth loses little by it."""
    if which == "measured":
        return frame.depth > 0
    if frame.color_valid is None:
        return (frame.rgb > 0).any(-1) | (frame.depth > 0)
    return frame.color_valid


def training_far(depth: torch.Tensor, truncation: float, max_distance: float) -> torch.Tensor:
    """Far bound of training rays (R,): just past the truncation band behind the observed
    depth. Samples farther back are masked by the renderer anyway, so not generating them
    saves their cost."""
    return torch.clamp(depth + 2.0 * truncation, max=max_distance)



@dataclass(frozen=True)
class _JointWindow:
    """What the iterations of one joint optimisation share (``Mapper._joint_optimisation``):
    the S source frames (stacked) and their starting T_map_cam (S, 4, 4); the indices ``free``
    (P) of the free poses, as a tensor in ``free_rows``, their twists (P, 6) and optimiser
    (None when none is free); the loss weights; the map's view and sample step;
    where the generator draws; the padded samples' shape with static shapes, else None."""

    sources: list[TensorFrame]
    stack: FrameStack | None
    rays_per_frame: int
    T_start: torch.Tensor
    free: list[int]
    free_rows: torch.Tensor
    twists: torch.Tensor
    pose_opt: torch.optim.Optimizer | None
    weights: LossWeights
    view: object
    step: float
    gen_device: torch.device
    shape: tuple[int, int, int] | None


def _window_rays(batch: PixelBatch, T: torch.Tensor, frames: int, rays_per_frame: int,
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """World (map) origins and directions (R, 3) of a batch of ``rays_per_frame`` rays of each
    of ``frames`` frames posed at ``T`` (frames, 4, 4)."""
    dirs_cam = batch.dirs_cam.reshape(frames, rays_per_frame, 3)
    d = (dirs_cam @ T[:, :3, :3].transpose(1, 2)).reshape(-1, 3)
    o = T[:, None, :3, 3].expand(-1, rays_per_frame, 3).reshape(-1, 3)
    return o, d


class Mapper:
    """Owns the map set and optimises it as tracked frames arrive.

    Multi-maps (paper: Incremental Mapping with Multi-Maps): every agent maps into its active
    map; a frame flagged ``new_map`` starts a new one, placed at the frame's world pose, and
    the agent's previous map is frozen from then on (its optimiser state is dropped, its
    keyframes kept for loop closing and the final refinement).
    """

    def __init__(self, config: SLAMConfig, device: torch.device, agent: int = 0, seed: int = 0):
        self.config = config
        self.device = device
        self.agent = agent
        self.maps = MapSet(config)
        self.version = 0
        self.timer = StageClock()
        self.last_iterations = 0
        """Iterations the last joint optimisation ran (fewer than asked when its deadline passed)."""
        self.active: dict[int, SubMap] = {}
        """agent -> the map it is mapping into."""
        self._rng = random.Random(seed)
        # On the device: rays and offsets are drawn where they are used (on a GPU: no upload,
        # which would wait for the queue); on the CPU it is the generator it always was.
        self._gen = torch.Generator(device=device).manual_seed(seed)
        # The fine colour level's fits draw from their own streams (``fit_fine``).
        self._fine_rng = random.Random(seed + 1)
        self._fine_gen = torch.Generator(device=device).manual_seed(seed + 1)
        self.static = config.render.uses_static_shapes(device)
        """Iterations render padded samples (``slam.padded``; ``render.static_shapes``)."""
        self._optimizers: dict[int, torch.optim.Optimizer] = {}
        """map id -> Adam over its embeddings and decoder (active maps only)."""
        self._seed = seed
        self._frames_since_keyframe: dict[int, int] = {}
        self._last_keyframe: dict[int, tuple[int, torch.Tensor]] = {}
        """agent -> (map id, T_map_cam (4, 4)) of its latest keyframe, as tracked."""
        self._kf_codes: dict[int, torch.Tensor] = {}
        """Sorted Morton codes of the voxels observed by each submap's keyframes."""

    # ---------------------------------------------------------------- helpers
    @property
    def current(self) -> SubMap | None:
        """The active map of the agent that was mapped last (the newest map if none)."""
        if self.agent in self.active:
            return self.active[self.agent]
        return self.maps.maps[-1] if self.maps.maps else None

    @property
    def frames_since_keyframe(self) -> int:
        return self._frames_since_keyframe.get(self.agent, 0)

    def _loss_weights(self) -> LossWeights:
        c = self.config.loss
        return LossWeights(c.rgb_weight, c.depth_weight, c.sdf_weight, c.fs_weight)

    def _moved_since_keyframe(self, agent: int, map_id: int, T_map_cam: torch.Tensor) -> bool:
        """Whether the camera (T_map_cam (4, 4)) moved or turned at least
        ``mapping.keyframe_interval_min_metres`` / ``_degrees`` since ``agent``'s latest keyframe
        in map ``map_id`` (true without one there, or with no minimum)."""
        m = self.config.mapping
        min_metres, min_degrees = m.keyframe_interval_min_metres, m.keyframe_interval_min_degrees
        last = self._last_keyframe.get(agent)
        if (min_metres <= 0 and min_degrees <= 0) or last is None or last[0] != map_id:
            return True  # no sync on the pose where nothing is asked
        relative = se3_inverse(last[1]) @ T_map_cam
        return pose_moved(relative, min_metres, min_degrees)

    def _T_map_cam(self, submap: SubMap, T_world_cam: torch.Tensor) -> torch.Tensor:
        return se3_inverse(submap.T_world_map) @ T_world_cam.to(self.device)

    def _points(self, frame: TensorFrame, T_map_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Map-frame points at depth - tr, depth, depth + tr (all allocated) and the surface
        points alone (at the measured depth)."""
        tr = self.config.render.truncation
        points = backproject(frame, T_map_cam, self.config.voxel.alloc_pixel_stride, (-tr, 0.0, tr))
        n = points.shape[0] // 3  # backproject stacks one block per offset
        return points, points[n:2 * n]

    def _ensure_optimizer(self, submap: SubMap) -> torch.optim.Optimizer:
        opt = self._optimizers.get(submap.map_id)
        if opt is None:
            m = self.config.mapping
            groups = [
                {"params": [submap.voxels.embeddings], "lr": m.lr_embed},
                {"params": list(submap.decoder.parameters()), "lr": m.lr_decoder},
            ]
            if submap.fine is not None:
                groups.append({"params": list(submap.fine.parameters()), "lr": self.config.fine_color.lr})
            opt = adam(groups)
            self._optimizers[submap.map_id] = opt
        return opt

    def _allocate(self, submap: SubMap, points: torch.Tensor) -> int:
        old = submap.voxels.embeddings
        result = submap.voxels.allocate(points)
        opt = self._optimizers.get(submap.map_id)
        if opt is not None and submap.voxels.embeddings is not old:
            grow_adam_state(opt, old, submap.voxels.embeddings)
        return result.new_voxels

    # ------------------------------------------------------------------ steps
    def start_map(self, T_world_map: torch.Tensor | None = None, agent: int | None = None,
                  reason: str = "start", map_id: int | None = None) -> SubMap:
        """A new map for ``agent`` (default: the mapper's current agent) with its origin at
        ``T_world_map`` (default: the world origin); the agent's previous map is frozen."""
        agent = self.agent if agent is None else agent
        previous = self.active.get(agent)
        map_id = len(self.maps.maps) if map_id is None else map_id
        if map_id != len(self.maps.maps):
            raise ValueError(f"map ids are given in creation order: expected {len(self.maps.maps)}, got {map_id}")
        submap = SubMap.create(map_id, agent, self.config, self.device, T_world_map, seed=self._seed)
        submap.reason = reason
        if previous is not None and reason == "region":
            submap.parent = previous.map_id
            submap.T_parent_map = se3_inverse(previous.T_world_map) @ submap.T_world_map
        self.maps.maps.append(submap)
        if previous is not None:
            # Frozen from now on (paper: earlier maps' parameters stay unchanged); loop
            # closing makes new optimisers for its intra-map refinement.
            self._optimizers.pop(previous.map_id, None)
        self.active[agent] = submap
        self._frames_since_keyframe[agent] = 0
        return submap

    def process(self, tracked: TrackedFrame, optimize: bool = True,
                first_iterations: int | None = None) -> MappingStep:
        """Keyframe test, allocation and (optionally) one round of windowed optimisation of
        the frame's agent's active map (a new one first when ``tracked.new_map`` says so);
        ``first_iterations``: that round's iterations for a map's first frame (default
        ``mapping.first_frame_iterations``)."""
        t0 = time.perf_counter()
        self.agent = tracked.agent
        started = None
        if tracked.new_map is not None:
            nm = tracked.new_map
            started = nm.reason
            self.start_map(nm.T_world_map.to(self.device), tracked.agent, nm.reason, nm.map_id)
        elif tracked.agent not in self.active:
            started = "start"
            self.start_map(None, tracked.agent, started)
        first = started is not None
        submap = self.active[tracked.agent]
        T_map_cam = self._T_map_cam(submap, tracked.T_world_cam)
        ta = time.perf_counter()
        points, surface = self._points(tracked.frame, T_map_cam)
        observed, new, codes = self._keyframe_coverage(submap, points)
        ratio = new / max(observed, 1)
        m = self.config.mapping
        # A frame whose tracking failed is not fused: its pose would corrupt the map.
        is_kf = first or (tracked.tracking_ok and (
            ratio > m.keyframe_ratio or (self.frames_since_keyframe + 1 >= m.keyframe_max_interval
                                         and self._moved_since_keyframe(tracked.agent, submap.map_id, T_map_cam))))
        agent = tracked.agent
        new_voxels = 0
        tb = time.perf_counter()
        self.timer.add("keyframe_decision", tb - ta)
        if first or tracked.tracking_ok:
            # Every successfully tracked frame allocates (paper: Voxel Allocation), so that the
            # newest frame in the window always has voxels where it looks.
            new_voxels = self._allocate(submap, points)
            submap.observe_surface(torch.unique(morton_encode(voxel_coords_of(surface, submap.voxels.voxel_size))))
        if is_kf:
            self._kf_codes[submap.map_id] = torch.unique(torch.cat([self._kf_codes.get(submap.map_id, codes), codes]))
            submap.keyframes.append(Keyframe(
                tracked.frame.index, tracked.frame.timestamp, tracked.frame, tracked.frame.K,
                T_map_cam.detach().clone()))
            self._frames_since_keyframe[agent] = 0
            self._last_keyframe[agent] = (submap.map_id, T_map_cam.detach().clone())
        else:
            self._frames_since_keyframe[agent] = self.frames_since_keyframe + 1
        self.timer.add("voxel_allocation", time.perf_counter() - tb)
        losses: dict[str, float] = {}
        if optimize:
            first_iters = m.first_frame_iterations if first_iterations is None else first_iterations
            iters = first_iters if first else m.iterations
            current = None if is_kf or not tracked.tracking_ok else (tracked.frame, T_map_cam)
            losses, T_current = self._optimize_window(submap, iters, current)
            self.fit_fine(submap, self.config.fine_color.fit_iterations)
        else:
            T_current = None
        self.version += 1
        return MappingStep(tracked.frame.index, is_kf, ratio, new_voxels, losses, time.perf_counter() - t0,
                           submap.map_id, started, T_current)

    def _keyframe_coverage(self, submap: SubMap, points: torch.Tensor) -> tuple[int, int, torch.Tensor]:
        """(N_o, N_c, codes): voxels the frame observes, how many of them no keyframe has
        observed yet, and their Morton codes. Every tracked frame allocates voxels, so the
        keyframe test compares against the keyframes' voxels, not the allocated ones."""
        codes = torch.unique(morton_encode(voxel_coords_of(points, submap.voxels.voxel_size)))
        covered = self._kf_codes.get(submap.map_id)
        if covered is None:
            return int(codes.numel()), int(codes.numel()), codes
        new = int((lookup_sorted(covered, codes) < 0).sum())
        return int(codes.numel()), new, codes

    def _window(self, submap: SubMap) -> list[Keyframe]:
        """N_kf - 1 random earlier keyframes plus the newest keyframe."""
        k = self.config.mapping.window_size
        older = submap.keyframes[:-1]
        chosen = self._rng.sample(older, min(len(older), max(k - 1, 0)))
        return chosen + [submap.keyframes[-1]]

    def optimize(self, submap: SubMap, iterations: int,
                 current: tuple[TensorFrame, torch.Tensor] | None = None,
                 interrupted: Callable[[], bool] | None = None) -> dict[str, float]:
        """Joint optimisation over the window; ``current`` adds the newest non-keyframe, with a
        fixed pose unless ``mapping.optimize_current_pose``; ``interrupted`` is asked before
        each iteration whether to stop (new work arrived). Returns the last iteration's losses."""
        return self._optimize_window(submap, iterations, current, interrupted)[0]

    def _optimize_window(self, submap: SubMap, iterations: int,
                         current: tuple[TensorFrame, torch.Tensor] | None = None,
                         interrupted: Callable[[], bool] | None = None,
                         ) -> tuple[dict[str, float], torch.Tensor | None]:
        """``optimize``, also returning ``current``'s optimised T_map_cam (4, 4) when its pose
        was free (``mapping.optimize_current_pose``), else None."""
        m = self.config.mapping
        window = self._window(submap)
        if current is not None:
            window = window[-(m.window_size - 1):] if m.window_size > 1 else []
        frames = [] if current is None else [current]
        free_frames = current is not None and m.optimize_poses and m.optimize_current_pose
        losses, frame_poses = self._joint_optimisation(submap, window, frames, iterations, m.num_rays,
                                                       interrupted=interrupted, free_frames=free_frames)
        return losses, (frame_poses[0] if free_frames else None)

    def global_bundle_adjustment(self, submap: SubMap, iterations: int, num_rays: int,
                                 deadline: float | None = None, fit_colour: bool = True) -> dict[str, float]:
        """The paper's intra-map optimisation: embeddings, decoder and the poses of *all*
        keyframes of ``submap`` (the first fixed), ``num_rays`` rays per iteration spread evenly
        over the keyframes (at least 4 each). The windowed mapper only ever sees N_kf keyframes
        at once; this pass makes every keyframe agree with one map. Stops early once
        ``time.perf_counter()`` passes ``deadline``; ``last_iterations`` says how many ran.
        Then the final fit of the fine colour level (``fit_final_colour``), unless not
        ``fit_colour``. Returns the last iteration's losses."""
        kfs = submap.keyframes
        self.last_iterations = 0
        if not kfs or iterations <= 0:
            return {}
        # At least a few rays per keyframe: long sequences cost a little more per iteration
        # rather than leaving keyframes out.
        per_frame = max(num_rays // len(kfs), 4)
        losses = self._joint_optimisation(submap, list(kfs), [], iterations, per_frame, deadline)[0]
        if fit_colour:
            self.fit_final_colour(submap)
        return losses

    def fit_final_colour(self, submap: SubMap) -> None:
        """The fine colour level's fit after a global bundle adjustment (``fine_color.final_*``)."""
        if not submap.keyframes:
            return
        if self.config.fine_color.final_fit_surface == "rendered":
            self.fit_fine_rendered(submap, self.config.fine_color.final_fit_iterations)
        else:
            self.fit_fine(submap, self.config.fine_color.final_fit_iterations, FIT_KEYFRAMES_FINAL)

    def fit_fine(self, submap: SubMap, iterations: int, keyframes: int = 0) -> None:
        """``iterations`` Adam steps of the fine colour level alone (``slam.fine_color``) on
        ``fine_color.fit_rays`` observed surface points of random keyframes (at most
        ``keyframes``, default ``FIT_KEYFRAMES``); nothing when the map has no fine level. Its
        own random stream: the coarse map's draws are those of a run without it."""
        kfs = [kf for kf in submap.keyframes if kf.frame is not None]
        if submap.fine is None or iterations <= 0 or not kfs:
            return
        t0 = time.perf_counter()
        optimizer = self._ensure_optimizer(submap)
        view, cfg = submap.view(), self.config.fine_color
        for _ in range(iterations):
            chosen = self._fine_rng.sample(kfs, min(len(kfs), keyframes or FIT_KEYFRAMES))
            points, rgb_gt = self._fine_points(chosen, max(cfg.fit_rays // len(chosen), 1))
            with torch.no_grad():
                coarse, inside = coarse_point_color(points, view, submap.decoder)
            optimizer.zero_grad(set_to_none=True)
            fit_loss(submap.fine, points, coarse, inside, rgb_gt).backward()
            optimizer.step()  # only the fine level has gradients; Adam skips the rest
        self.timer.add("fine_fit", time.perf_counter() - t0)

    def fit_fine_rendered(self, submap: SubMap, iterations: int) -> None:
        """``iterations`` steps of the fine colour level alone on the surface the coarse map
        renders for the keyframes (``fine_color.final_fit_surface`` "rendered"): each keyframe
        (at most ``FIT_KEYFRAMES_RENDERED``, evenly spread) is rendered at 1/``fine_color.fit_render_block``
        of its size, and the level learns ``input - rendered coarse colour`` at each pixel's
        rendered surface point, the very point a view adds it at. Where the coarse surface lies
        centimetres off the measured one (0.2 m voxels on real data), a fit at the measured
        depth puts the colour where no view looks (fr1/desk training views 17.9 -> 20.1 dB,
        3 seeds; decisions.md#fine_color).
        Its own Adam, cosine-decayed to zero: a decaying step leaves less sampling noise."""
        kfs = [kf for kf in submap.keyframes if kf.frame is not None]
        if submap.fine is None or iterations <= 0 or not kfs:
            return
        t0 = time.perf_counter()
        if len(kfs) > FIT_KEYFRAMES_RENDERED:
            kfs = [kfs[i] for i in np.linspace(0, len(kfs) - 1, FIT_KEYFRAMES_RENDERED).round().astype(int)]
        points, residual = self._rendered_residuals(submap, kfs)
        if points.shape[0] == 0:
            return
        cfg = self.config.fine_color
        optimizer = adam(submap.fine.parameters(), lr=cfg.lr)
        decay = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda k: 0.5 * (1.0 + math.cos(math.pi * k / iterations)))
        draw = draw_device(self._fine_gen, self.device)
        for _ in range(iterations):
            pick = torch.randint(0, points.shape[0], (max(cfg.fit_rays, 1),), generator=self._fine_gen,
                                 device=draw).to(points.device)
            optimizer.zero_grad(set_to_none=True)
            (submap.fine(points[pick]) - residual[pick]).abs().mean().backward()
            optimizer.step()
            decay.step()
        self.timer.add("fine_fit", time.perf_counter() - t0)

    def _rendered_residuals(self, submap: SubMap, keyframes: list[Keyframe]) -> tuple[torch.Tensor, torch.Tensor]:
        """Map-frame surface points (N, 3) and colour residuals (N, 3) of ``keyframes`` rendered
        at 1/b of their size (b = ``fine_color.fit_render_block``): each pixel of the small image is a
        b x b block of the keyframe, its colour the block's mean, used where all of the block
        counts (``fine_color.fit_pixels``: observed colour, or measured depth) and the coarse
        map renders a surface."""
        from .views import coarse_surface, rendered_voxels, view_decoder

        b = self.config.fine_color.fit_render_block
        decoder, view = view_decoder(submap.decoder, self.device, "auto"), rendered_voxels(submap)
        points, residuals = [], []
        for kf in keyframes:
            frame = kf.frame
            h, w = frame.height // b, frame.width // b
            if h == 0 or w == 0:
                continue
            K = frame.K.clone()
            K[:2] /= b  # the small image's pixel (i + 0.5) is the centre of the block bi .. bi + b - 1
            color, point, surface = coarse_surface(submap, kf.T_map_cam.detach(), K, w, h, self.config,
                                                   decoder=decoder, view=view)
            rgb = frame.rgb[:b * h, :b * w].reshape(h, b, w, b, 3).mean((1, 3)).reshape(-1, 3)
            counts = fit_pixels(frame, self.config.fine_color.fit_pixels)[:b * h, :b * w]
            counted = counts.reshape(h, b, w, b).all(3).all(1).reshape(-1)
            use = torch.nonzero(surface & counted, as_tuple=True)[0]
            points.append(point[use])
            residuals.append(rgb[use] - color[use])
        if not points:
            return torch.zeros(0, 3, device=self.device), torch.zeros(0, 3, device=self.device)
        return torch.cat(points), torch.cat(residuals)

    def _fine_points(self, keyframes: list[Keyframe], per_frame: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``per_frame`` observed pixels of each keyframe -> map-frame points (N, 3) at their
        depth and their colours (N, 3)."""
        points, colours = [], []
        for kf in keyframes:
            batch = sample_pixels(kf.frame, per_frame, self._fine_gen)
            cam = batch.dirs_cam * batch.depth[:, None]
            T = kf.T_map_cam.detach()
            points.append(cam @ T[:3, :3].T + T[:3, 3])
            colours.append(batch.rgb)
        return torch.cat(points), torch.cat(colours)

    def _joint_optimisation(self, submap: SubMap, keyframes: list[Keyframe],
                            fixed: list[tuple[TensorFrame, torch.Tensor]], iterations: int,
                            rays_per_frame: int, deadline: float | None = None,
                            interrupted: Callable[[], bool] | None = None,
                            free_frames: bool = False) -> tuple[dict[str, float], list[torch.Tensor]]:
        """Adam on embeddings and decoder (and, with ``optimize_poses``, a twist per keyframe
        but the submap's first) over ``rays_per_frame`` rays of every keyframe and of every
        ``fixed`` (frame, T_map_cam). Keyframe poses take their twists at the end; with
        ``free_frames`` the ``fixed`` frames' poses get twists too. Returns the last
        iteration's losses and the ``fixed`` frames' T_map_cam (4, 4) after it (moved only
        with ``free_frames``)."""
        optimizer = self._ensure_optimizer(submap)
        w = self._joint_window(submap, keyframes, fixed, rays_per_frame, free_frames)
        losses: Losses | None = None
        self.last_iterations = 0
        for _ in range(iterations):
            with scope(MAPPING_ITERATION):
                tq = time.perf_counter()
                if (deadline is not None and tq > deadline) or (interrupted is not None and interrupted()):
                    break
                self.last_iterations += 1
                losses = self._joint_losses(submap, w)
                tb = time.perf_counter()
                self._joint_step(submap, optimizer, w, losses)
                self.timer.add("render", tb - tq)
                self.timer.add("backward", time.perf_counter() - tb)
        frame_poses = [T for _, T in fixed]
        if w.free:
            self._move_free_poses(w, keyframes, frame_poses)
        return ({} if losses is None else losses.as_floats()), frame_poses

    def _joint_window(self, submap: SubMap, keyframes: list[Keyframe],
                      fixed: list[tuple[TensorFrame, torch.Tensor]], rays_per_frame: int,
                      free_frames: bool) -> "_JointWindow":
        """What the iterations of ``_joint_optimisation`` share (``_JointWindow``); with static
        shapes this reads the device once (``_sample_shape``)."""
        m, r = self.config.mapping, self.config.render
        sources = [kf.frame for kf in keyframes] + [frame for frame, _ in fixed]
        T_start = torch.stack([kf.T_map_cam for kf in keyframes] + [T for _, T in fixed])  # (S, 4, 4)
        first_kf = submap.keyframes[0]
        free = [i for i, kf in enumerate(keyframes) if m.optimize_poses and kf is not first_kf]
        if free_frames:
            free += range(len(keyframes), len(sources))
        free_rows = torch.tensor(free, dtype=torch.long, device=self.device)
        # One (P, 6) tensor for all free poses: Adam is per coordinate, so this is the same
        # update as one optimiser per keyframe, at one batched exp map per iteration.
        twists = torch.zeros(len(free), 6, device=self.device, requires_grad=True)
        pose_opt = adam([twists], lr=m.lr_pose) if free else None
        weights = self._loss_weights()
        stack = stack_frames(sources)
        view = submap.view()  # the map does not change inside the loop (no allocation)
        step = r.step_ratio * submap.voxels.voxel_size
        gen_device = draw_device(self._gen, self.device)
        shape = self._sample_shape(sources, stack, rays_per_frame, T_start, view) if self.static else None
        return _JointWindow(sources, stack, rays_per_frame, T_start, free, free_rows, twists, pose_opt, weights,
                            view, step, gen_device, shape)

    def _joint_losses(self, submap: SubMap, w: "_JointWindow") -> Losses:
        """One iteration's forward pass: a batch of rays of every source from its pose with the
        twists applied, rendered and scored."""
        batch = self._sample(w.sources, w.stack, w.rays_per_frame)
        T = w.T_start
        if w.free:
            xi = torch.zeros(len(w.sources), 6, device=self.device).index_copy(0, w.free_rows, w.twists)
            T = w.T_start @ (se3_exp_compact(xi) if self.static else se3_exp(xi))
        o, d = _window_rays(batch, T, len(w.sources), w.rays_per_frame)
        c_gt, d_gt = batch.rgb, batch.depth
        out = self._render_window(submap, w, o, d, d_gt)
        r = self.config.render
        losses = compute_losses(out, c_gt, d_gt, r.truncation, w.weights, max_depth=r.max_distance,
                                normalisation=self.config.loss.normalisation)
        if submap.fine is not None:  # the fine level learns the residual; nothing else gets its gradient
            use = out.hit & (d_gt > 0)
            fine = fine_loss(submap.fine, o, d, out.color, out.depth, use, c_gt)
            losses = replace(losses, total=losses.total + w.weights.rgb * fine)
        return losses

    def _render_window(self, submap: SubMap, w: "_JointWindow", o: torch.Tensor, d: torch.Tensor,
                       d_gt: torch.Tensor):
        """The window's rays ``o``, ``d`` (R, 3) rendered for training: thinned free space
        (``mapping.thin_samples``), random sample offsets; padded samples with static shapes."""
        m, r = self.config.mapping, self.config.render
        n = o.shape[0]
        thinning = None
        if m.thin_samples:
            phase = torch.randint(m.free_space_stride, (n,), generator=self._gen, device=w.gen_device).to(self.device)
            thinning = TrainingThinning(d_gt, r.truncation, r.max_distance, m.free_space_stride, phase)
        near = torch.full((n,), 0.05, device=self.device)
        far = training_far(d_gt, r.truncation, r.max_distance)
        offsets = torch.rand(n, generator=self._gen, device=w.gen_device).to(self.device)
        if w.shape is not None:
            grid, slots, colour = w.shape
            with torch.no_grad():
                samples = pack_samples(grid_samples(o.detach(), d.detach(), near, far, w.step, w.view, grid,
                                                    max_hits=r.max_hits, offsets=offsets,
                                                    thinning=thinning), slots)
            return render_padded(o, d, w.view, submap.decoder, samples, truncation=r.truncation,
                                 color_weight_eps=m.color_weight_eps, color_slots=colour,
                                 mask_in_front=r.mask_in_front, renormalise_color=True)
        return render_rays(o, d, w.view, submap.decoder, near=near, far=far,
                           step=w.step, truncation=r.truncation,
                           max_hits=r.max_hits, offsets=offsets,
                           mask_in_front=r.mask_in_front, thinning=thinning,
                           color_weight_eps=m.color_weight_eps, renormalise_color=True)

    def _joint_step(self, submap: SubMap, optimizer, w: "_JointWindow", losses: Losses) -> None:
        """One iteration's backward pass and the steps of the map's and the poses' optimisers."""
        optimizer.zero_grad(set_to_none=True)
        if w.pose_opt is not None:
            w.pose_opt.zero_grad(set_to_none=True)
        losses.total.backward()
        self._count_corner_updates(submap)
        optimizer.step()
        if w.pose_opt is not None:
            w.pose_opt.step()

    @staticmethod
    def _move_free_poses(w: "_JointWindow", keyframes: list[Keyframe], frame_poses: list[torch.Tensor]) -> None:
        """The free poses take their twists: keyframes' in place, the other frames' in
        ``frame_poses``."""
        with torch.no_grad():
            moved = w.T_start[w.free_rows] @ se3_exp(w.twists.detach())
            for i, T_new in zip(w.free, moved):
                if i < len(keyframes):
                    keyframes[i].T_map_cam = T_new
                else:
                    frame_poses[i - len(keyframes)] = T_new

    def _sample_shape(self, sources: list[TensorFrame], stack: FrameStack | None, rays_per_frame: int,
                      T_start: torch.Tensor, view) -> tuple[int, int, int]:
        """(grid points G, slots N, colour slots C) of a window's padded samples: G covers
        the sources' deepest ray, N is the most samples a ray of one batch drawn for it holds
        (before thinning: an upper bound), with a quarter more for the batches to come. One
        read of the device per window, outside the iterations."""
        r = self.config.render
        step = r.step_ratio * view.voxel_size
        depth_max = max(f.depth_max if f.depth_max is not None else float(f.depth.max()) for f in sources)
        G = grid_size(0.05, min(depth_max + 2.0 * r.truncation, r.max_distance), step)
        with torch.no_grad():
            batch = self._sample(sources, stack, rays_per_frame)
            dirs_cam = batch.dirs_cam.reshape(len(sources), rays_per_frame, 3)
            d = (dirs_cam @ T_start[:, :3, :3].transpose(1, 2)).reshape(-1, 3)
            o = T_start[:, None, :3, 3].expand(-1, rays_per_frame, 3).reshape(-1, 3)
            n = o.shape[0]
            grid = grid_samples(o, d, torch.full((n,), 0.05, device=self.device),
                                training_far(batch.depth, r.truncation, r.max_distance), step, view, G,
                                max_hits=r.max_hits)
            N = min(G, round_up(1.25 * int(grid.counts().max())))
        return G, N, color_slots(r.truncation, step, N, r.mask_in_front)

    def _sample(self, sources: list[TensorFrame], stack: FrameStack | None, num: int) -> PixelBatch:
        """``num`` pixels of each source frame, frame by frame."""
        if stack is not None:
            return sample_stacked_pixels(stack, num, self._gen)
        batches = [sample_pixels(frame, num, self._gen) for frame in sources]
        return PixelBatch(torch.cat([b.dirs_cam for b in batches]), torch.cat([b.rgb for b in batches]),
                          torch.cat([b.depth for b in batches]))

    def _count_corner_updates(self, submap: SubMap) -> None:
        grad = submap.voxels.embeddings.grad
        if grad is not None:
            counts = submap.updates()
            counts += (grad.abs().amax(1) > 0).to(torch.int32)

    # --------------------------------------------------------------- outputs
    def snapshot(self, submap: SubMap | None = None) -> MapSnapshot:
        """Detached copies of a submap's tensors (default: the current one) for the tracker."""
        submap = submap or self.current
        assert submap is not None, "no map yet"
        v = submap.voxels
        # One read per dtype instead of one per tensor (``slam.transfer``).
        decoder = {f"decoder.{k}": t for k, t in submap.decoder.state_dict().items()}
        host = to_host({"T_world_map": submap.T_world_map, "voxel_codes": v.voxel_codes,
                        "voxel_corners": v.voxel_corners, "embeddings": v.embeddings,
                        "corner_updates": submap.updates(), **decoder})
        return MapSnapshot(
            version=self.version,
            map_id=submap.map_id,
            T_world_map=host["T_world_map"],
            voxel_size=v.voxel_size,
            voxel_codes=host["voxel_codes"],
            voxel_corners=host["voxel_corners"],
            embeddings=host["embeddings"],
            decoder_state={k[len("decoder."):]: a for k, a in host.items() if k.startswith("decoder.")},
            corner_updates=host["corner_updates"],
        )

    def refine_map(self, submap: SubMap, iterations: int, num_rays: int) -> dict[str, float]:
        """Global bundle adjustment of any map, frozen or active (loop closing's intra-map
        step); a frozen map's optimiser state is dropped again afterwards."""
        active = any(m is submap for m in self.active.values())
        losses = self.global_bundle_adjustment(submap, iterations, num_rays)
        if not active:
            self._optimizers.pop(submap.map_id, None)
        self.version += 1
        return losses

    def keyframe_poses_world(self, submap: SubMap) -> torch.Tensor:
        """(K, 4, 4) optimised keyframe poses of ``submap`` in the world frame."""
        if not submap.keyframes:
            return torch.zeros(0, 4, 4)
        poses = torch.stack([kf.T_map_cam for kf in submap.keyframes])
        return (submap.T_world_map @ poses).detach().cpu()

