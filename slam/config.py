"""Configuration: a shallow tree of frozen dataclasses with named presets.

Presets:
    ``test``  seconds per run, for the test suite (tiny rays and iterations).
    ``cpu``   the default without a GPU: fewer rays and iterations than the paper.
    ``paper`` the paper's stated settings, the Vox-Fusion release's where the paper is silent
              (``_paper`` names each source).
    ``gpu``   the default with a GPU: the paper's settings on static shapes (``_gpu``).

A config file is JSON whose top-level keys are the section names below and whose values
override the preset field by field; an unknown section or field is an error
(``ConfigError``) so that typos never pass silently.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any


class ConfigError(ValueError):
    """A config file or override names something that does not exist or has a bad value."""


@dataclass(frozen=True)
class VoxelConfig:
    voxel_size: float = 0.2
    """Edge length of a voxel in metres (the paper uses 0.2 m everywhere)."""
    embed_dim: int = 16
    """Length of the learnable embedding stored at each voxel corner."""
    embed_init_std: float = 0.01
    """Embeddings are initialised from N(0, std^2)."""
    max_depth: float = 10.0
    """Depth beyond this (metres) is ignored when allocating voxels."""
    alloc_pixel_stride: int = 2
    """Back-project every k-th pixel in x and y when allocating (0.2 m voxels need few points)."""


@dataclass(frozen=True)
class DecoderConfig:
    hidden_dim: int = 128
    """Width of the shared FC layers."""
    num_layers: int = 2
    """Number of shared FC layers (paper: 2-4)."""
    feature_dim: int = 128
    """Length of the feature handed from the SDF head to the colour head."""
    color_hidden_dim: int = 256
    """Width of the colour head's FC layers (paper: two layers of 256)."""
    color_layers: int = 2


@dataclass(frozen=True)
class RenderConfig:
    step_ratio: float = 0.1
    """Sampling step as a fraction of the voxel size (paper: 0.05-0.1)."""
    max_hits: int = 24
    """M_h: how many voxels a ray may gather before the distance cap is applied."""
    max_distance: float = 10.0
    """D_max: samples farther than this along the ray are masked (metres)."""
    truncation: float = 0.1
    """tr: SDF truncation distance (metres)."""
    chunk_rays: int = 4096
    """Rays rendered at once when rendering whole images (bounds memory)."""
    mask_in_front: bool = True
    """The first-surface mask (``slam.render.first_surface_mask``) also drops samples more
    than tr in front of a ray's first zero crossing (True, ours: a young map's free space is
    not yet at s = 1 and those samples drag the rendered depth toward the camera), or only
    those more than tr behind it (False, the paper; the release masks behind the crossing
    too). Every renderer follows it: mapping, both trackers, views, loop verification.
    Issue 21 item 4 (``benchmarks/bench_fidelity.py``)."""

    static_shapes: str = "auto"
    """Tracking and mapping iterations on padded samples of a fixed count per ray
    (``slam.padded``): nothing in an iteration is read back from the device, so a GPU never
    waits on the host (issue 40). ``auto``: on CUDA devices; ``on``; ``off``: the flat
    samples of ``slam.render`` (its exact sample set, and the CPU's numba kernels, the faster
    there: a CPU does not wait for itself)."""

    def __post_init__(self) -> None:
        if not isinstance(self.mask_in_front, bool):
            raise ConfigError(f"render.mask_in_front must be true or false, got {self.mask_in_front!r}")
        if self.static_shapes not in STATIC_SHAPES:
            raise ConfigError(f"render.static_shapes must be one of {', '.join(map(repr, STATIC_SHAPES))}, "
                              f"got {self.static_shapes!r}")

    def uses_static_shapes(self, device) -> bool:
        """Whether the tracker and the mapper render padded samples on ``device``."""
        import torch

        if self.static_shapes == "auto":
            return torch.device(device).type == "cuda"
        return self.static_shapes == "on"


STATIC_SHAPES = ("auto", "on", "off")
LOSS_NORMALISATIONS = ("ray", "slots")


@dataclass(frozen=True)
class LossConfig:
    """The mapper's losses (the tracker has its own weights, ``tracking.*_weight``)."""

    rgb_weight: float = 0.5
    depth_weight: float = 1.0
    sdf_weight: float = 5000.0
    fs_weight: float = 10.0
    normalisation: str = "ray"
    """How the free-space and SDF terms are averaged (``slam.losses.compute_losses``).
    ``ray`` (ours, the paper's ``1/|P| sum_p 1/S_p sum_s``): over a ray's masked samples,
    then over rays. ``slots`` (the release's ``criterion.py``): the sum over masked samples
    divided by every slot of the padded (rays x most samples of any ray) sample tensor, the
    free-space term then scaled by the share of SDF-band samples and the SDF term by the
    share of free-space samples; the weights above are the release's, tuned for that. Here
    rays stop 2 tr behind the observed depth, so the padded width is the longest such ray's.
    The mapper only: the tracker keeps per-ray means (its Gauss-Newton model, miss cost and
    feature weight are written for them). Issue 21 item 3 (``benchmarks/bench_fidelity.py``)."""

    def __post_init__(self) -> None:
        if self.normalisation not in LOSS_NORMALISATIONS:
            raise ConfigError(f"loss.normalisation must be one of {', '.join(map(repr, LOSS_NORMALISATIONS))}, "
                              f"got {self.normalisation!r}")


@dataclass(frozen=True)
class TrackingConfig:
    num_rays: int = 1024
    """N_t: pixels sampled per tracking iteration."""
    optimizer: str = "adam"
    """``adam`` (the paper) or ``gauss_newton`` (Levenberg-Marquardt on the same loss with
    closed-form Jacobians, ``slam.gauss_newton``: converges in a few steps)."""
    min_corner_updates: int = 1
    """Track only against voxels whose corners got a gradient in at least this many mapping
    steps (0: every allocated voxel)."""
    max_step_m: float = 0.05
    max_step_rad: float = 0.05
    """Trust region of one Gauss-Newton step (metres, radians)."""
    lm_damping: float = 1e-3
    """Initial Levenberg-Marquardt damping (relative to the diagonal)."""
    iterations: int = 30
    lr_rot: float = 1e-2
    lr_trans: float = 1e-2
    lr_decay: float = 0.1
    """The learning rate falls geometrically to lr * lr_decay by the last iteration."""
    constant_velocity: bool = False
    """Initialise from a constant-velocity guess instead of the last pose (the paper's zero
    motion model). Off by default: when an iteration budget leaves part of the error, the
    velocity guess feeds it back and it compounds (synthetic orbit, cpu preset: 0.8 cm ATE over
    40 frames with the last pose, divergence after 15 frames with constant velocity)."""
    motion_prior: float = 0.0
    """Gauss-Newton only: weight of a prior holding the pose at its initial guess, relative
    to the data term's mean curvature (per translation and rotation block, so it is free of
    units and of the ray count). Directions the view does not observe (a plain wall fixes 3
    of 6) then stay at the guess instead of following noise up to the step limit; observed
    directions, whose curvature is far larger, barely feel it (0: off)."""
    sample_band: float = 2.0
    """Sample only within this many truncations of the observed depth (0: the whole ray, as
    the paper; see ``slam.tracking.tracking_bounds`` for why this gives the same weights)."""
    color_weight_eps: float = 1e-3
    """The colour head runs only on samples whose weight exceeds this (of at most 0.25), and
    a ray's colour is their weighted mean (as the mapper's). The colour's Jacobian (three
    more trunk passes per coloured sample) is half of a Gauss-Newton render's cost, and
    samples below a fifth of the peak add little to it: ``cpu`` takes 5e-2."""
    resample_rays: bool = False
    """Draw new pixels every iteration (True, the release) or keep one set per frame, so that
    the losses of the iterations compare and the lowest-loss pose is meaningful (False)."""
    keep_best_iterate: bool = True
    """Adam only: return the lowest-loss iterate (True) or the pose after the last step, as
    the release does (False)."""
    border_margin: float = 0.0
    """Gauss-Newton only: leave out rays whose observed point lies within this many metres of
    the map's border at the initial pose (``slam.tracking.interior_rays``), unless that leaves
    fewer than ``min_valid_ratio`` of the rays (0: off)."""
    outlier_factor: float = 10.0
    """Rays whose depth error exceeds this times the median are dropped."""
    convergence_tol: float = 1e-5
    """Stop early when the next pose update (the twist's norm, m and rad together) falls
    below this: Gauss-Newton stops before rendering it, Adam after taking it."""
    check_every: int = 1
    """With static shapes (``render.static_shapes``), the stop conditions are kept on the
    device and the host reads them between iterations every this many iterations (0: never;
    the iterations after a stop are no-ops): each read is a sync on a GPU, each skipped one
    may cost an iteration that changes nothing."""
    min_valid_ratio: float = 0.3
    """Tracking fails when fewer than this share of sampled rays hit the map."""
    max_depth_residual: float = 0.2
    """Tracking fails when the median depth residual (m) stays above this."""
    max_jump_m: float = 0.3
    max_jump_rad: float = 0.5
    """Tracking fails when the optimised pose moved farther than this from the initial guess
    (a diverged optimisation, not camera motion at frame rate)."""
    rgb_weight: float = 0.5
    depth_weight: float = 1.0
    sdf_weight: float = 5000.0
    fs_weight: float = 10.0
    feature_count: int = 0
    """ORB features per frame matched to the previous frame (``slam.features``): their
    reprojection error joins the loss and a RANSAC PnP on them gives the initial pose (0: off,
    the paper's tracker). Features are detected on the frame as read, before any resizing."""
    feature_weight: float = 0.003
    """Weight of one match's Huber reprojection cost (milliradians squared) against the
    paper's losses (which are means over rays)."""
    feature_huber_px: float = 2.0
    feature_ransac_px: float = 2.0
    """RANSAC PnP inlier threshold (pixels): only its inliers enter the loss."""
    feature_min_inliers: int = 20
    """Fewer PnP inliers than this: the frame is tracked without features."""
    feature_dense_check: bool = False
    """Gauss-Newton only: drop a frame's features when the dense loss is lower at the motion
    model's guess than at their PnP pose (repeated texture lets RANSAC agree on a pose one
    period off, which the depth does not support)."""

    def __post_init__(self) -> None:
        if self.feature_count < 0 or self.feature_weight < 0 or self.feature_huber_px <= 0:
            raise ConfigError("tracking.feature_count and feature_weight must be >= 0 and feature_huber_px > 0")
        if self.motion_prior < 0:
            raise ConfigError("tracking.motion_prior must be >= 0")
        if self.check_every < 0:
            raise ConfigError("tracking.check_every must be >= 0")
        if self.optimizer not in ("adam", "gauss_newton"):
            raise ConfigError(f"tracking.optimizer must be 'adam' or 'gauss_newton', got {self.optimizer!r}")


@dataclass(frozen=True)
class MappingConfig:
    num_rays: int = 1024
    """N_m: rays sampled per keyframe in the window, per iteration."""
    iterations: int = 10
    """Optimisation iterations per mapped frame."""
    keyframe_iterations: int = 0
    """Iterations when the frames optimised together hold a new keyframe (0: ``iterations``).
    A keyframe brings voxels that no optimisation has seen; its fresh corner rows decode to
    a faint surface until trained. fr1/rpy, 50 frames, deterministic loop
    (``benchmarks/diagnose_drift.py``, seeds 1 and 2): raw ATE 7.42 / 8.12 cm with 24 per
    keyframe and 6 otherwise, against 8.98 / 10.02 cm with 12 per frame, at about the same
    cost over the 150 frames. In the process-mode pipeline, where the final bundle
    adjustment follows, six runs gave 5.24-7.16 cm (mean 5.97) against about 6 cm with the
    defaults, so it is not a preset default."""
    first_frame_iterations: int = 100
    """Iterations on the first frame (map initialisation)."""
    window_size: int = 5
    """N_kf: keyframes in the optimisation window, including the newest frame."""
    lr_embed: float = 1e-2
    lr_decoder: float = 1e-2
    lr_pose: float = 1e-3
    optimize_poses: bool = True
    """Bundle adjustment: optimise keyframe poses in the window (the first keyframe is fixed)."""
    optimize_current_pose: bool = False
    """With ``optimize_poses``: the newest frame, when it is no keyframe, joins the window with
    its pose optimised too (the paper; the release then keeps that pose as the frame's
    estimate), and its refined pose replaces the tracked one in the trajectory and in the
    tracker's motion history (``slam.runtime``). False (ours so far): it joins with its
    tracked pose held fixed. Issue 21 item 2 (``benchmarks/bench_fidelity.py``)."""
    keyframe_ratio: float = 0.05
    """p_kf threshold: new-voxel / observed-voxel ratio that makes a keyframe."""
    keyframe_max_interval: int = 50
    """N: a keyframe is forced after this many frames without one."""
    final_iterations: int = 0
    """Global bundle adjustment at the end of a sequence: iterations over all keyframes of the
    current submap (paper: intra-map optimisation), before the mesh and trajectory are written."""
    final_rays: int = 2048
    """Rays per global bundle-adjustment iteration, spread evenly over the keyframes."""
    final_iterations_per_keyframe: int = 0
    """Caps ``final_iterations`` at this many per keyframe of the run (0: no cap): a few
    keyframes need fewer passes to agree with one map than a long sequence does."""
    final_time_share: float = 0.0
    """Caps the final bundle adjustment's wall time at this multiple of the run's time before
    it (0: no cap), but never below ``final_min_seconds``: a short upload then does not spend
    most of its run refining (a 9-frame upload spent 106 of 114 s there)."""
    final_min_seconds: float = 10.0
    """The least wall time the time cap leaves the final bundle adjustment."""
    thin_samples: bool = False
    """Mapping iterations decode a thinned sample set (``slam.render.thin_training_samples``):
    none behind the observed surface's truncation band, every ``free_space_stride``-th in
    free space, weighted so the losses keep their expectation."""
    free_space_stride: int = 2
    """With ``thin_samples``: keep one free-space sample in this many (1: all)."""
    color_weight_eps: float = 1e-5
    """The colour head runs on the samples whose weight exceeds this (of at most 0.25), and a
    ray's colour is their weighted mean (``render_rays``' ``renormalise_color``)."""

    def __post_init__(self) -> None:
        if isinstance(self.free_space_stride, bool) or not isinstance(self.free_space_stride, int) \
                or self.free_space_stride < 1:
            raise ConfigError(f"mapping.free_space_stride must be an integer >= 1, got {self.free_space_stride!r}")
        if not isinstance(self.optimize_current_pose, bool):
            raise ConfigError("mapping.optimize_current_pose must be true or false, "
                              f"got {self.optimize_current_pose!r}")


@dataclass(frozen=True)
class MultiMapConfig:
    """When a new map starts (paper: Incremental Mapping with Multi-Maps)."""

    enabled: bool = True
    region_size: float = 8.0
    """A new map starts when the camera leaves a cube of this edge (metres) centred on the
    camera position of the map's first frame: it bounds a map's voxels, so the
    cost of mapping and of publishing a map to the tracker stays constant."""
    new_map_on_tracking_failure: bool = True
    failures_before_new_map: int = 2
    """Consecutive failed frames after which the camera counts as lost: the next frame with
    enough valid depth starts a new map that floats in its own frame until a loop joins it."""
    min_valid_depth: float = 0.2
    """Share of pixels with valid depth a frame needs to start a map."""

    def __post_init__(self) -> None:
        if self.region_size <= 0 or self.failures_before_new_map < 1 or not 0 <= self.min_valid_depth <= 1:
            raise ConfigError("multimap: region_size must be > 0, failures_before_new_map >= 1, "
                              "min_valid_depth in [0, 1]")


@dataclass(frozen=True)
class LoopConfig:
    """Loop detection and hierarchical pose optimisation (paper: Robust Loop Detection,
    Hierarchical Pose Optimization); the thresholds are explained in ``slam.loop``."""

    enabled: bool = True
    descriptor: str = "orb-bow+thumbnail"
    """Global keyframe descriptor of the appearance check (``slam.loop.database``)."""
    netvlad_weights: str | None = None
    """A TorchScript NetVLAD-style model (image in, global vector out) to use instead of the
    offline descriptor; never downloaded."""
    top_k: int = 3
    """Appearance candidates verified per keyframe, best first."""
    similarity_threshold: float = 0.35
    """Absolute floor of the cosine similarity a candidate must exceed."""
    neighbour_ratio: float = 0.65
    """...and this share of the keyframe's similarity to its own map's latest keyframes (the
    threshold adapts to how alike views of this scene are)."""
    same_map: bool = False
    """Also verify candidates in the query's own map. Off: a revisit inside one map is
    tracked against the map that already holds it (the loop is closed by tracking and
    bundle adjustment), and with bounded regions a drifting revisit comes back in another
    map; on fr1/rpy (one map) in-map loops cost 29 % of frames/s for no ATE gain."""
    min_frame_gap: int = 30
    """Same-map (and same-group, same-agent) candidates must be at least this many frames
    older than the query."""
    min_inliers: int = 25
    """PnP inliers the relative pose from features needs."""
    pnp_reprojection_px: float = 3.0
    geometry_rays: int = 512
    """Rays of the query frame cast into the candidate map for the geometry check."""
    geometry_min_hit_ratio: float = 0.5
    """Share of the query's surface points that must land in the candidate map's voxels."""
    depth_tolerance: float = 0.05
    min_depth_agreement: float = 0.5
    """Share of rays whose rendered depth must be within ``depth_tolerance`` (m)."""
    max_refinement_m: float = 0.15
    max_refinement_rad: float = 0.15
    """Tracking the query against the candidate map may move it this far from the PnP pose."""
    inter_map_iterations: int = 10
    """Tracker steps of the refinement against the target map (the inter-map optimisation)."""
    keyframes_between_loops: int = 5
    """After a loop between two maps, candidates between them wait this many keyframes."""
    intra_map_iterations: int = 20
    """Global bundle-adjustment iterations of each joined map after a loop (the paper's
    intra-map step; 0: none online, see the cpu preset for why)."""
    sequential_sigma_m: float = 0.2
    sequential_sigma_rad: float = 0.05
    """Uncertainty of the tracking chain between a map and the one it continues: the drift
    accumulated over one map, which loop edges correct. Tighter than the real drift, and the
    robust kernel rejects the first loop of a lap as an outlier (laps, test preset: 86 of
    90 verified loops rejected at 5 cm / 0.02 rad)."""
    loop_sigma_m: float = 0.02
    loop_sigma_rad: float = 0.01
    keyframe_graph: bool = True
    """At the end of the run, a pose graph over every keyframe with odometry and every
    verified loop corrects the drift inside maps (``slam.loop.keyframe_graph``)."""

    def __post_init__(self) -> None:
        if self.top_k < 1 or self.min_inliers < 6 or self.geometry_rays < 1:
            raise ConfigError("loop: top_k >= 1, min_inliers >= 6 and geometry_rays >= 1 are required")


@dataclass(frozen=True)
class MeshConfig:
    resolution: int = 8
    """Marching-cubes cells per voxel edge."""
    update_every_keyframes: int = 5
    """The runtime extracts a live mesh after this many new keyframes."""


@dataclass(frozen=True)
class RuntimeConfig:
    device: str = "auto"
    """auto, cpu or cuda."""
    processes: bool = True
    """Tracking and mapping in separate processes (False: one process, for debugging)."""
    queue_size: int = 2
    """Bounded queue between tracking and mapping. The mapper is the slower process, so a
    longer queue buys no throughput; it only lets the tracker run ahead against an older map
    (fr1/rpy, 150 frames, 6 x 384 mapping rays: 5.3 and 5.4 cm ATE with 2, 5.0-9.0 cm with 8;
    the run-to-run spread is about as large, so this is a direction, not a proof)."""
    input_width: int | None = None
    """Resize input frames to this width inside the pipeline (intrinsics scaled)."""
    max_map_lag: int = -1
    """Process mode: before tracking a frame, wait until the mapper has integrated all but
    this many of the frames sent to it, so the frame is tracked against a map at most this
    many frames old (0: every frame sees the map with its predecessor; -1: no wait, only the
    queue bounds how far the tracker runs ahead). Accuracy for speed where the map is young
    everywhere the camera looks: synthetic laps hall, 780 frames, loops on, one run each,
    -1 / 1 / 0: 7.44 / 6.24 / 4.88 cm ATE at 3.08 / 1.55 / 1.25 frames/s (a second lag-0
    run: 5.35 cm at 0.92; two more without a wait: 5.86 and 6.42 cm); TUM fr1/rpy 150
    frames, -1 / 0: 4.37 / 4.71 cm at 2.00 / 0.88 frames/s. Off in every preset: real
    sequences pay the speed and gain nothing."""
    deterministic_lag: int = -1
    """Deterministic evaluation (-1: off, free-running). With K >= 0, every frame is tracked
    against exactly the map of all frames sent to the mapper but the newest K (the tracker
    waits where the mapper is behind and holds frames back where it would be ahead), the
    mapper takes one frame at a time and never optimises while idle, and the final bundle
    adjustment is budgeted by iterations only: a run's trajectory is the same on a busy or a
    quiet machine. K >= 1 keeps tracking and mapping overlapped (the mapper integrates frame
    i - K while frame i is tracked); K = 0 alternates them. The final bundle adjustment's time
    cap becomes ``deterministic_final_iterations``. For A/Bs (benchmarks/README.md)."""
    deterministic_every: int = 3
    """Deterministic mode: the mapper runs its windowed optimisation at every this-many-th
    frame and only integrates the others, as a free-running mapper optimises once per batch
    of the frames that queued up (at most ``queue_size`` + 1 = 3). 1 optimises every frame
    (fr1/rpy 150, cpu preset, lag 1: 0.24x the free-running frame rate)."""
    deterministic_final_iterations: int = 12
    """Deterministic mode, for a preset whose final bundle adjustment has a time cap: its
    iterations instead of the cap (the cpu preset's 10-11 s ran 12 of its 500 iterations on
    fr1/rpy 150 on the 2-core machine; without a cap the 500 took 400 s)."""
    checkpoint_every_keyframes: int = 10
    """Write map.pt every this many keyframes while running (0: only at the end)."""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.max_map_lag < -1:
            raise ConfigError(f"runtime.max_map_lag must be -1 (no wait) or >= 0, got {self.max_map_lag}")
        if self.deterministic_lag < -1:
            raise ConfigError(f"runtime.deterministic_lag must be -1 (off) or >= 0, got {self.deterministic_lag}")
        if self.deterministic_every < 1:
            raise ConfigError(f"runtime.deterministic_every must be >= 1, got {self.deterministic_every}")

    @property
    def deterministic(self) -> bool:
        return self.deterministic_lag >= 0


@dataclass(frozen=True)
class SLAMConfig:
    preset: str = "cpu"
    voxel: VoxelConfig = field(default_factory=VoxelConfig)
    decoder: DecoderConfig = field(default_factory=DecoderConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    multimap: MultiMapConfig = field(default_factory=MultiMapConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _paper() -> SLAMConfig:
    """The paper's stated settings; where it gives none, the authors' Vox-Fusion release
    (github.com/zju3dv/Vox-Fusion): ``configs/replica_all.yaml``, the config its README names
    for reproducing the paper's results, over the ``replica.yaml`` base, and its code
    (``src/tracking.py``, ``src/mapping.py``, ``src/criterion.py``).

    Paper: 0.2 m voxels, 16-D embeddings, FC layers of 128 with a 128-D feature, a colour head
    of two FC layers of 256 (the field defaults), a step ratio in 0.05-0.1, the zero motion
    model, Adam on the pose, the keyframe ratio test with a maximum interval. Release:
    2048 tracking rays, 50 Adam iterations at lr 0.01, new rays every iteration, the last
    iterate, no decay; 2048 mapping rays per frame, 20 iterations, four random keyframes plus
    the newest frame, Adam at 5e-3 on embeddings and decoder and 1e-2 on poses (the tracker's
    optimiser, which the mapper keeps); step ratio 0.05, M_h = 10 voxels, D_max = 10 m,
    truncation 0.05 m; loss weights 0.5 / 1 / 5000 / 10 (the field defaults); a keyframe at
    least every 50 frames; every allocated voxel is tracked against; the newest frame's pose
    optimised in the window (paper and release). The losses keep the paper's per-ray means
    (``loss.normalisation = "ray"``) although the release's padded-slot means measured better
    with these weights (``cpu`` takes them). Ours, where neither says:
    the keyframe ratio 0.05, 100 iterations on the first frame (the release maps it until
    the second frame arrives), the tracking-failure tests and the multi-map region.
    """
    return SLAMConfig(
        preset="paper",
        render=RenderConfig(step_ratio=0.05, max_hits=10, max_distance=10.0, truncation=0.05),
        tracking=TrackingConfig(optimizer="adam", num_rays=2048, iterations=50, lr_rot=1e-2,
                                lr_trans=1e-2, lr_decay=1.0, resample_rays=True,
                                keep_best_iterate=False, sample_band=0.0, min_corner_updates=0,
                                convergence_tol=0.0),
        mapping=MappingConfig(num_rays=2048, iterations=20, window_size=5, lr_embed=5e-3,
                              lr_decoder=5e-3, lr_pose=1e-2, keyframe_max_interval=50,
                              optimize_current_pose=True),
        runtime=RuntimeConfig(device="auto"),
    )


def _cpu() -> SLAMConfig:
    # A narrower decoder than the paper's: on a 2-core CPU the MLP dominates an iteration
    # (paper sizes: ~134k multiply-adds per sample, these: ~18k).
    return SLAMConfig(
        preset="cpu",
        decoder=DecoderConfig(hidden_dim=64, feature_dim=64, color_hidden_dim=64),
        render=RenderConfig(step_ratio=0.1, max_hits=16, truncation=0.1),
        # Colour has to share the embeddings with an SDF term 10^4 times heavier, and Adam's
        # per-coordinate steps follow the larger gradient: at this preset's few iterations
        # the paper's 0.5 leaves colour near the mean (Replica room0, 10 frames: 14 dB), 10
        # gets 21-24 dB with the same depth error (2.0-2.1 cm) and mesh accuracy.
        # The release's padded-slot means (issue 21 item 3, benchmarks/README.md): fr1/rpy 150
        # frames, process mode, two runs each: 2.92 / 3.65 cm against 5.25 / 4.73 cm with per-ray
        # means (one process, 3 seeds: 3.41 against 4.30 cm); room0 held-out +0.84 dB; the
        # synthetic walk's mesh accuracy 0.92 against 0.85 cm.
        loss=LossConfig(rgb_weight=10.0, normalisation="slots"),
        # Gauss-Newton: 6 steps reach what 40 Adam steps do not (synthetic walk, 60 frames:
        # ATE 0.39 cm at 0.36 s/frame against 1.02 cm at 0.81 s/frame with Adam x 20).
        # ORB matches to the previous frame join the loss: on real Kinect data the depth-led
        # loss under-rotates in fast turns (fr1/rpy 150 frames, process mode: 4.2-4.9 cm ATE
        # over 5 runs against 5-9 cm without; per-match weights from 0.001 to 0.0045 all gave
        # 4.1-4.8 cm; slam.features and benchmarks/README.md).
        # The motion prior (1 % of the data's curvature) and the dense check on the features'
        # PnP pose keep textureless walls and a checkerboard from rattling the pose: synthetic
        # laps hall, 780 frames, no loops: frame-to-frame error 2.66 -> 1.35 cm, ATE 39.6 ->
        # 36.8 cm; fr1/rpy 150 frames: 3.8-4.6 cm over 3 runs (4.2-4.9 before over 5).
        # The border margin: in process mode the tracker works against a map a few frames old,
        # and rays ending near its border hit at one pose and miss a little further on, so a
        # step forward costs and a step back is kept, frame after frame where nothing else
        # fixes the direction of travel. Same-load A/B, one bench_loops.py run each: laps hall
        # 16.2 -> 7.0 cm with loops (41.4 -> 19.7 cm without); fr1/rpy 150 frames 4.0 -> 4.5 cm
        # (earlier runs without it: 3.8-4.6 cm), fr1/desk 0.29 -> 0.31 cm, synthetic walk 200
        # frames 0.69 -> 0.83 cm (a young map's border is near everything the camera sees).
        # 4 steps, the colour's Jacobian only on samples above a fifth of the peak weight,
        # and a stop once a step would move the pose < 0.1 mm (issue 18). Tracking frame i+1
        # against a map of frames 0..i with GT poses, 40 frames each: 4 steps and the
        # threshold cost 0.54x (laps hall) and 0.74x (fr1/rpy) of 6 steps at 1e-3 with the
        # same error (4.36 / 10.67 mm against 4.37 / 10.69 mm); the stop 0.95x / 0.77x more,
        # the error unchanged (benchmarks/README.md).
        # Colour weight 20 (paper: 0.5). At the laps hall's corners the view is a textured
        # plain wall: depth fixes three directions, only colour sees the other three, and
        # at 0.5 the motion prior (scaled by the SDF-dominated mean curvature) held back
        # about half of each frame's motion there. Same harness, GT maps, weights 0.5 / 5 /
        # 20: laps corner (frames 336-360) 10.53 / 8.55 / 7.92 mm, laps 21-60 4.36 / 3.65 /
        # 3.75 mm, fr1/rpy 21-60 10.68 / 10.46 / 9.38 mm at the same cost. The default laps
        # path, alternating runs on one host: 5 -> 4.82 / 5.87 / 4.44 / 5.74 cm, 20 -> 4.54 /
        # 5.05 / 5.13 / 3.93 cm (nine runs at 20: mean 4.59 cm); 5.64-7.85 cm at 0.5
        # (benchmarks/README.md, issue 17).
        tracking=TrackingConfig(optimizer="gauss_newton", num_rays=512, iterations=4, rgb_weight=20.0,
                                color_weight_eps=5e-2, convergence_tol=1e-4,
                                feature_count=1000, feature_weight=0.003, motion_prior=0.01,
                                feature_dense_check=True, border_margin=0.1),
        # The end-of-sequence global bundle adjustment gives every keyframe iterations the
        # window never had. Replica room0, 10 frames mapped, 10 held-out views: 21.4 dB
        # without it; 23.3 with 150 x 512 rays, 23.8-24.0 with 300-400, 24.2-24.35 with 500
        # (two seeds); iterations count more than rays (250 x 768: 24.0). 500 x 512 takes
        # about 30 s on fr1/rpy's 55 keyframes with both cores (the tracker is done by then).
        # 12 iterations of 192 rays per frame cost what 6 of 384 did and converge the newest
        # voxels further: tracking a frame from the previous GT pose against the map of the
        # frames before it (fr1/rpy 6-59, GT poses) errs 0.96 deg instead of 1.16 deg.
        # The final bundle adjustment is budgeted: 500 iterations at most, 50 per keyframe, and
        # no longer than 0.15x the run before it but at least 10 s, so that it is at most about
        # half of a short run's wall time (fr1/desk, 9 frames, 6 keyframes: 500 iterations took
        # 16.8 of 28.8 s, ATE 0.26 cm; capped, 279 took 10.0 of 23.3 s, ATE 0.38 cm) and a
        # minute's run spends 10 s there, not 12-18 (time share 1.0 before; bench_slam, 2-3
        # runs each, alternating: fr1/rpy 150 2.08-2.45 -> 2.67-3.05 frames/s, ATE 2.84-3.68
        # -> 3.19-3.24 cm; walk 200 ATE 0.67-0.79 -> 0.65-0.75 cm, mesh accuracy 0.91-0.96 ->
        # 0.95-0.98 cm).
        # The newest frame's pose optimised with the window (issue 21 item 2; the paper's way):
        # walk 200 frames 0.71 -> 0.57 cm ATE over 3 seeds in one process; with slots, fr1/rpy
        # process mode as above, synthetic laps 5.67 / 7.85 cm against 7.01 (within that
        # scenario's run-to-run spread).
        # A mapping iteration decodes a thinned sample set (none behind the observed surface's
        # band, every 2nd in free space) and colours only samples above a fifth of the peak
        # weight: office0 map, 1024 rays, 1 thread, 79.7 -> 53.1 ms; fr1/rpy 150 frames,
        # process mode, two runs each, alternating: 1.14 / 1.15 -> 1.45 / 1.74 frames/s,
        # ATE 3.02 / 4.57 -> 3.07 / 4.02 cm (benchmarks/README.md, issue 18).
        mapping=MappingConfig(num_rays=192, iterations=12, window_size=4, first_frame_iterations=100,
                              final_iterations=500, final_rays=512, final_iterations_per_keyframe=50,
                              final_time_share=0.15, optimize_current_pose=True, thin_samples=True,
                              free_space_stride=2, color_weight_eps=5e-2),
        mesh=MeshConfig(resolution=6),
        # Maps of a 3 m region: a lap around a room then comes back into other maps than the
        # ones it left, and loops between maps can correct the drift (synthetic laps hall, 780
        # frames, 160 x 120: ATE 20.0 cm with loops, 35.1 cm without; one map of 100 m drifts
        # to 59.9 cm; in one map of 8 m the revisit is fused into the drifted map itself, and
        # verification against it fails).
        multimap=MultiMapConfig(region_size=3.0),
        # No bundle adjustment of the two joined maps at each loop: moving a map rigidly leaves
        # its own bundle-adjustment problem (its keyframes against its voxels, in its frame)
        # unchanged, so those iterations carry nothing of the loop; the loop's correction inside
        # maps is the end-of-run keyframe graph's (``loop.keyframe_graph``), and the final
        # global bundle adjustment still covers every map. Synthetic laps, 780 frames, one
        # bench_loops.py run each: 20 iterations 17.4 cm at 2.48 frames/s, the last 100 frames
        # costing 1.53x the first 100; none 17.1 cm at 2.86 frames/s, 1.22x.
        loop=LoopConfig(intra_map_iterations=0),
        runtime=RuntimeConfig(device="auto", input_width=320),
    )


def _test() -> SLAMConfig:
    return SLAMConfig(
        preset="test",
        decoder=DecoderConfig(hidden_dim=32, feature_dim=32, color_hidden_dim=32),
        render=RenderConfig(step_ratio=0.2, max_hits=8, truncation=0.1, chunk_rays=2048),
        tracking=TrackingConfig(optimizer="gauss_newton", num_rays=128, iterations=4),
        mapping=MappingConfig(num_rays=128, iterations=2, window_size=3, first_frame_iterations=10,
                              final_iterations=2, final_rays=128),
        loop=LoopConfig(inter_map_iterations=5, intra_map_iterations=3, geometry_rays=64),
        mesh=MeshConfig(resolution=4, update_every_keyframes=2),
        runtime=RuntimeConfig(device="cpu", input_width=160, processes=True),
    )


def _gpu() -> SLAMConfig:
    """The default with a GPU (issue 40 item 5): the paper's decoder, voxel size, losses and
    tracker (``_paper``), with every iteration on static shapes (``render.static_shapes``:
    nothing read back from the device inside the loops), the tracker's stop flag never read
    (its Adam has no convergence test, as the paper's), and 640-wide input at most.

    Unmeasured: no GPU has run it yet. Its tracker is the paper's until one measures which
    is best there (the ``cpu`` preset's Gauss-Newton converges in 4 steps where Adam takes
    50, but each step renders with Jacobians); its speed, accuracy and SM share are to be
    measured with ``benchmarks/bench_gpu.py`` (benchmarks/README.md, issue 40).
    """
    paper = _paper()
    return replace(
        paper,
        preset="gpu",
        render=replace(paper.render, static_shapes="on"),
        tracking=replace(paper.tracking, check_every=0),
        runtime=replace(paper.runtime, device="auto", input_width=640),
    )


PRESETS = {"test": _test, "cpu": _cpu, "paper": _paper, "gpu": _gpu}


def preset(name: str) -> SLAMConfig:
    """The named preset (``test``, ``cpu``, ``paper`` or ``gpu``)."""
    try:
        return PRESETS[name]()
    except KeyError:
        raise ConfigError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}") from None


def default_preset_name() -> str:
    """``gpu`` when CUDA is present, else ``cpu``."""
    import torch

    return "gpu" if torch.cuda.is_available() else "cpu"


def _check_type(name: str, hint: Any, value: Any) -> Any:
    """``value`` converted to the field's declared type, or ConfigError.

    bool is not accepted for int/float fields (JSON ``true`` is no number); int is widened to
    float; ``X | None`` accepts null.
    """
    options = typing.get_args(hint) if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union else (hint,)
    if value is None and type(None) in options:
        return None
    for option in options:
        if option is type(None):
            continue
        if option is bool and isinstance(value, bool):
            return value
        if option is int and isinstance(value, int) and not isinstance(value, bool):
            return value
        if option is float and isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if option is str and isinstance(value, str):
            return value
    names = " or ".join(getattr(o, "__name__", str(o)) for o in options)
    raise ConfigError(f"{name} must be {names}, got {type(value).__name__} {value!r}")


RETIRED_FIELDS = {
    ("mapping", "map_every"): "it never changed anything: every tracked frame is mapped, and the "
                              "mapper optimises once over the frames that queued up",
}
"""Fields that configs written by earlier versions (checkpoints, run.json) may still hold."""


def apply_overrides(config: SLAMConfig, overrides: dict[str, Any]) -> SLAMConfig:
    """Return ``config`` with ``{"section": {"field": value}}`` overrides applied.

    Raises ConfigError for an unknown section or field, or a value of the wrong type.
    """
    section_names = {f.name for f in fields(config)} - {"preset"}
    changes: dict[str, Any] = {}
    for section, values in overrides.items():
        if section not in section_names:
            raise ConfigError(f"unknown config section {section!r}; known: {sorted(section_names)}")
        if not isinstance(values, dict):
            raise ConfigError(f"config section {section!r} must be a mapping of fields")
        current = getattr(config, section)
        known = {f.name: f for f in fields(current)}
        hints = typing.get_type_hints(type(current))
        clean: dict[str, Any] = {}
        for key, value in values.items():
            if key not in known:
                retired = RETIRED_FIELDS.get((section, key))
                if retired is not None:
                    raise ConfigError(f"{section}.{key} was removed: {retired}")
                raise ConfigError(f"unknown field {section}.{key}; known: {sorted(known)}")
            clean[key] = _check_type(f"{section}.{key}", hints[key], value)
        values = clean
        changes[section] = replace(current, **values)
    return replace(config, **changes)


def load_config(preset_name: str, path: str | Path | None = None) -> SLAMConfig:
    """The preset, overridden by the JSON file at ``path`` if given."""
    config = preset(preset_name)
    if path is None:
        return config
    try:
        overrides = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ConfigError(f"cannot read config file {path}: {exc}") from exc
    if not isinstance(overrides, dict):
        raise ConfigError(f"config file {path} must hold a JSON object")
    overrides.pop("preset", None)
    return apply_overrides(config, overrides)


def config_from_dict(data: dict[str, Any]) -> SLAMConfig:
    """Rebuild a config from ``SLAMConfig.to_dict()`` output (checkpoints, run.json)."""
    data = {k: dict(v) if isinstance(v, dict) else v for k, v in data.items()}
    base = preset(data.pop("preset", "cpu"))
    for section, key in RETIRED_FIELDS:
        if isinstance(data.get(section), dict):
            data[section].pop(key, None)
    return apply_overrides(base, data)
