"""The sections of the configuration: one frozen dataclass per component, a docstring under
each field (what the setting is, its unit).

``slam.config`` assembles them into ``SLAMConfig`` and holds the presets; the measurements
behind the values are in ``benchmarks/decisions.md``, one entry per setting.
"""

from __future__ import annotations

from dataclasses import dataclass


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


STATIC_SHAPES = ("auto", "on", "off")


def _check_choice(name: str, value, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ConfigError(f"{name} must be one of {', '.join(map(repr, choices))}, got {value!r}")


def _check_non_negative(name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0:
        raise ConfigError(f"{name} must be a number >= 0, got {value!r}")
LOSS_NORMALISATIONS = ("ray", "slots")


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
    """The first-surface mask also drops samples more than tr in front of a ray's first zero
    crossing (ours), not only those more than tr behind it (False: the paper); every renderer."""
    static_shapes: str = "auto"
    """Iterations on padded samples of a fixed count per ray (``slam.padded``), no device reads:
    ``auto`` (on CUDA), ``on`` or ``off`` (the flat samples of ``slam.render``)."""

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


@dataclass(frozen=True)
class LossConfig:
    """The mapper's losses (the tracker has its own weights, ``tracking.*_weight``)."""

    rgb_weight: float = 0.5
    depth_weight: float = 1.0
    sdf_weight: float = 5000.0
    fs_weight: float = 10.0
    normalisation: str = "ray"
    """How the free-space and SDF terms are averaged (``slam.losses.compute_losses``): ``ray``
    (the paper: per ray, then over rays) or ``slots`` (the release: over the padded tensor)."""

    def __post_init__(self) -> None:
        if self.normalisation not in LOSS_NORMALISATIONS:
            raise ConfigError(f"loss.normalisation must be one of {', '.join(map(repr, LOSS_NORMALISATIONS))}, "
                              f"got {self.normalisation!r}")


@dataclass(frozen=True)
class TrackingConfig:
    num_rays: int = 1024
    """N_t: pixels sampled per tracking iteration."""
    optimizer: str = "adam"
    """``adam`` (the paper) or ``gauss_newton`` (Levenberg-Marquardt, ``slam.gauss_newton``)."""
    min_corner_updates: int = 1
    """Track only against voxels whose corners got a gradient in this many mapping steps (0: all)."""
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
    motion_prior: float = 0.0
    """Gauss-Newton only: weight of a prior holding the pose at its guess, relative to the data
    term's mean curvature per translation and rotation block (0: off)."""
    sample_band: float = 2.0
    """Sample only within this many truncations of the observed depth (0: the whole ray, as the
    paper; ``slam.tracking.tracking_bounds`` says why the weights are the same)."""
    color_weight_eps: float = 1e-3
    """The colour head runs only on samples whose weight exceeds this (of at most 0.25)."""
    resample_rays: bool = False
    """Draw new pixels every iteration (the release) or keep one set per frame (False), so that
    the iterations' losses compare and the lowest-loss pose is meaningful."""
    keep_best_iterate: bool = True
    """Adam only: return the lowest-loss iterate (True) or the last one, as the release (False)."""
    border_margin: float = 0.0
    """Gauss-Newton only: leave out rays ending within this many metres of the map's border at the
    initial pose (``slam.tracking.interior_rays``) unless under ``min_valid_ratio`` remain (0: off)."""
    outlier_factor: float = 10.0
    """Rays whose depth error exceeds this times the median are dropped."""
    convergence_tol: float = 1e-5
    """Stop when the next pose update (the twist's norm, m and rad together) falls below this:
    Gauss-Newton stops before rendering it, Adam after taking it."""
    check_every: int = 1
    """With static shapes, the host reads the stop conditions every this many iterations (0: never)."""
    min_valid_ratio: float = 0.3
    """Tracking fails when fewer than this share of sampled rays hit the map."""
    max_depth_residual: float = 0.2
    """Tracking fails when the median depth residual (m) stays above this."""
    max_jump_m: float = 0.3
    max_jump_rad: float = 0.5
    """Tracking fails when the pose moved farther than this from the guess (a diverged optimisation)."""
    rgb_weight: float = 0.5
    depth_weight: float = 1.0
    sdf_weight: float = 5000.0
    fs_weight: float = 10.0
    feature_count: int = 0
    """ORB features per frame matched to the previous frame (``slam.features``; 0: off, the paper),
    detected on the frame as read; their PnP gives the initial pose, their error joins the loss."""
    feature_weight: float = 0.003
    """Weight of one match's Huber reprojection cost (milliradians squared) against the losses."""
    feature_huber_px: float = 2.0
    feature_ransac_px: float = 2.0
    """RANSAC PnP inlier threshold (pixels): only its inliers enter the loss."""
    feature_min_inliers: int = 20
    """Fewer PnP inliers than this: the frame is tracked without features."""
    feature_dense_check: bool = False
    """Gauss-Newton only: drop the features when the dense loss prefers the guess to their PnP pose."""
    retrack_iterations: int = 0
    """Levenberg-Marquardt steps of the final re-tracking: once the final bundle adjustment has
    refined the maps, every tracked frame's pose is optimised again against its map, from its
    corrected pose, on ``retrack_rays`` pixels kept from tracking (0: off)."""
    retrack_rays: int = 512
    """Pixels a frame keeps for the final re-tracking (28 bytes each, on the device, to the end of the run)."""
    retrack_ray_budget: int = 0
    """When the run's length is known: pixels for the re-tracking over the whole run, shared
    among its frames, each keeping 1-4x ``retrack_rays`` (0: ``retrack_rays`` each)."""
    retrack_frame_budget: int = 0
    """Frames of a map the final re-tracking optimises at most, spread evenly over its frames
    (its first and last included); the frames between take their neighbours' corrections,
    blended by place (0: every frame). Keeps the phase's cost flat in the run's length."""

    def __post_init__(self) -> None:
        if (self.retrack_iterations < 0 or self.retrack_rays < 1 or self.retrack_ray_budget < 0
                or self.retrack_frame_budget < 0 or self.retrack_frame_budget == 1):
            raise ConfigError("tracking.retrack_iterations, retrack_ray_budget and retrack_frame_budget must be "
                              ">= 0 (retrack_frame_budget not 1: a map's first and last frame at least), "
                              "tracking.retrack_rays >= 1")
        if self.feature_count < 0 or self.feature_weight < 0 or self.feature_huber_px <= 0:
            raise ConfigError("tracking.feature_count and feature_weight must be >= 0 and feature_huber_px > 0")
        if self.motion_prior < 0:
            raise ConfigError("tracking.motion_prior must be >= 0")
        if self.check_every < 0:
            raise ConfigError("tracking.check_every must be >= 0")
        if self.optimizer not in ("adam", "gauss_newton"):
            raise ConfigError(f"tracking.optimizer must be 'adam' or 'gauss_newton', got {self.optimizer!r}")


FRAME_CORRECTIONS = ("latest", "interpolated")
"""How frames follow their keyframes' bundle adjustment (``MappingConfig.frame_correction``)."""


@dataclass(frozen=True)
class MappingConfig:
    num_rays: int = 1024
    """N_m: rays sampled per keyframe in the window, per iteration."""
    iterations: int = 10
    """Optimisation iterations per mapped frame."""
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
    """With ``optimize_poses``: a newest frame that is no keyframe has its pose optimised too (the
    paper), and that pose replaces the tracked one; False: its tracked pose is held fixed."""
    frame_correction: str = "latest"
    """How the trajectory's frames follow bundle adjustment's keyframe poses
    (``slam.outputs.refine_with_keyframes``): ``latest``, each frame the correction of the latest
    keyframe at or before it; ``interpolated``, a frame between two keyframes their two
    corrections blended by its place between them."""
    keyframe_ratio: float = 0.05
    """p_kf threshold: new-voxel / observed-voxel ratio that makes a keyframe."""
    keyframe_max_interval: int = 50
    """N: a keyframe is forced after this many frames without one."""
    keyframe_interval_min_metres: float = 0.0
    """The forced keyframe waits until the camera has moved this far (or turned
    ``keyframe_interval_min_degrees``) since the agent's last keyframe: a camera held still would
    otherwise keep adding keyframes, each holding its frame in RAM. 0 and 0: forced whatever
    the motion."""
    keyframe_interval_min_degrees: float = 0.0
    """With ``keyframe_interval_min_metres``: the turn that also lets the forced keyframe in."""
    final_iterations: int = 0
    """Iterations of the global bundle adjustment over the current submap's keyframes at the end of
    a sequence (paper: intra-map optimisation), before the mesh and trajectory are written."""
    final_rays: int = 2048
    """Rays per global bundle-adjustment iteration, spread evenly over the keyframes."""
    final_iterations_per_keyframe: int = 0
    """Caps ``final_iterations`` at this many per keyframe of the run (0: no cap)."""
    final_time_share: float = 0.0
    """Caps its wall time at this multiple of the run's time before it (0: no cap)."""
    final_min_seconds: float = 10.0
    """The least wall time (seconds) the time cap leaves the final bundle adjustment."""
    thin_samples: bool = False
    """Decode a thinned sample set (``slam.render.thin_training_samples``), losses kept in expectation."""
    free_space_stride: int = 2
    """With ``thin_samples``: keep one free-space sample in this many (1: all)."""
    color_weight_eps: float = 1e-5
    """The colour head runs on samples whose weight exceeds this; a ray's colour is their mean."""

    def __post_init__(self) -> None:
        _check_choice("mapping.frame_correction", self.frame_correction, FRAME_CORRECTIONS)
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
    """Edge (metres) of the cube around a map's first camera; leaving it starts a new map."""
    new_map_on_tracking_failure: bool = True
    failures_before_new_map: int = 2
    """Consecutive failed frames after which the camera is lost: the next frame with enough depth
    starts a map that floats in its own frame until a loop joins it."""
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
    """A TorchScript NetVLAD-style model (image in, global vector out) instead; never downloaded."""
    top_k: int = 3
    """Appearance candidates verified per keyframe, best first."""
    similarity_threshold: float = 0.35
    """Absolute floor of the cosine similarity a candidate must exceed."""
    neighbour_ratio: float = 0.65
    """...and this share of the keyframe's similarity to its own map's latest keyframes (the
    threshold adapts to how alike views of this scene are)."""
    same_map: bool = False
    """Also verify candidates in the query's own map."""
    min_frame_gap: int = 30
    """Same-map (and same-group, same-agent) candidates must be this many frames older."""
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
    """Global bundle-adjustment iterations of each joined map after a loop (the paper's intra-map
    step; 0: none online)."""
    sequential_sigma_m: float = 0.2
    sequential_sigma_rad: float = 0.05
    """Uncertainty (m, rad) of the tracking chain between a map and the one it continues."""
    loop_sigma_m: float = 0.02
    loop_sigma_rad: float = 0.01
    keyframe_graph: bool = True
    """End-of-run pose graph over every keyframe and loop (``slam.loop.keyframe_graph``)."""

    def __post_init__(self) -> None:
        if self.top_k < 1 or self.min_inliers < 6 or self.geometry_rays < 1:
            raise ConfigError("loop: top_k >= 1, min_inliers >= 6 and geometry_rays >= 1 are required")


FINE_FIT_SURFACES = ("observed", "rendered")
"""Where ``fine_color``'s final fit learns (``FineColorConfig.final_fit_surface``)."""

FINE_LEVEL_TABLES = ("equal", "surface")
"""How ``fine_color``'s levels share rows (``FineColorConfig.level_tables``)."""

FINE_FIT_PIXELS = ("measured", "observed")
"""Which keyframe pixels ``fine_color``'s rendered-surface fit learns from (``FineColorConfig.fit_pixels``)."""


@dataclass(frozen=True)
class FineColorConfig:
    """The fine level of colour (``slam.fine_color``): a hash grid of colour features queried at
    rendered surface points, a residual on the coarse colour of views and meshes, trained by
    mapping only (tracking never renders it)."""

    levels: int = 0
    """Grids from ``coarsest`` to ``finest`` (geometric steps); 0: no fine level."""
    features: int = 2
    """Floats per table row."""
    table_log2: int = 14
    """The finest level's table holds 2^table_log2 rows (hash collisions share a row)."""
    level_tables: str = "equal"
    """``equal``: every level's table is as large as the finest's; ``surface``: a coarser level's
    shrinks with the number of its cells a surface crosses, (cell / finest)^2 fewer rows
    (``slam.fine_color.level_rows``), so that the finest level gets the rows."""
    coarsest: float = 0.08
    """Cell edge of the coarsest level (metres)."""
    finest: float = 0.01
    """Cell edge of the finest level (metres)."""
    lr: float = 1e-2
    """Adam learning rate of the tables and the head."""
    fit_iterations: int = 4
    """After each windowed optimisation, this many steps of the fine level alone on observed
    surface points of the keyframes (one coarse decoder sample per point: no rendering)."""
    fit_rays: int = 2048
    """Points per fit step, drawn from up to ``FIT_KEYFRAMES`` random keyframes."""
    final_fit_iterations: int = 100
    """Fit steps after the final bundle adjustment, over every keyframe."""
    final_fit_surface: str = "observed"
    """Where the final fit learns: ``observed``, at each keyframe pixel's measured depth (against
    the decoder's colour there); ``rendered``, at the surface the coarse map renders for that
    pixel (against the rendered coarse colour), where views query the level, with an Adam of
    its own decaying to zero (``Mapper.fit_fine_rendered``)."""
    fit_render_block: int = 2
    """The rendered-surface fit renders each keyframe at 1/``fit_render_block`` of its size: a
    pixel of that image is a block of that many squared keyframe pixels, its colour their mean
    (1: every keyframe pixel, at 4x the render time of 2)."""
    fit_pixels: str = "measured"
    """The keyframe pixels the rendered-surface fit learns from: ``measured``, those with
    measured depth; ``observed``, every pixel whose colour the camera saw (``Frame.color_valid``),
    depth or not (``slam.mapping.fit_pixels``)."""

    def __post_init__(self) -> None:
        if isinstance(self.fit_render_block, bool) or not isinstance(self.fit_render_block, int) \
                or self.fit_render_block < 1:
            raise ConfigError(f"fine_color.fit_render_block must be an integer >= 1, got {self.fit_render_block!r}")
        for name in ("levels", "features", "table_log2", "fit_iterations", "fit_rays", "final_fit_iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ConfigError(f"fine_color.{name} must be an integer >= 0, got {value!r}")
        if self.levels and (self.features < 1 or not 1 <= self.table_log2 <= 24):
            raise ConfigError("fine_color.features must be >= 1 and table_log2 in 1-24 when levels > 0")
        if not 0 < self.finest <= self.coarsest:
            raise ConfigError(f"fine_color needs 0 < finest <= coarsest, got {self.finest} and {self.coarsest}")
        _check_non_negative("fine_color.lr", self.lr)
        _check_choice("fine_color.level_tables", self.level_tables, FINE_LEVEL_TABLES)
        _check_choice("fine_color.fit_pixels", self.fit_pixels, FINE_FIT_PIXELS)
        if self.final_fit_surface not in FINE_FIT_SURFACES:
            raise ConfigError(f"fine_color.final_fit_surface must be one of {FINE_FIT_SURFACES}, "
                              f"got {self.final_fit_surface!r}")


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
    """Bounded queue (frames) between tracking and mapping."""
    input_width: int | None = None
    """Resize input frames to this width inside the pipeline (intrinsics scaled)."""
    deterministic_lag: int = -1
    """Deterministic evaluation: track against the map of all frames sent but the newest K (-1: off)."""
    deterministic_every: int = 3
    """Deterministic mode: optimise the window at every this-many-th frame, integrate the others."""
    deterministic_final_iterations: int = 12
    """Deterministic mode: the final bundle adjustment's iterations instead of its time cap."""
    color_calibration: bool = True
    """Find the colour camera from the data when a source was given none
    (``slam.data.selfcalibration``: depth edges against colour edges), applied when confident."""
    checkpoint_every_keyframes: int = 10
    """Write map.pt every this many keyframes while running (0: only at the end)."""
    live: bool = False
    """A live camera, which does not wait: the tracker never waits for room in the mapper's
    queue. A frame that finds it full waits in one slot, where the next frame replaces it (the
    mapper maps the newest frames it can take; a frame that starts a map always goes), and the
    mapping process runs at a lower CPU priority, so that tracking keeps the camera's rate."""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.deterministic_lag < -1:
            raise ConfigError(f"runtime.deterministic_lag must be -1 (off) or >= 0, got {self.deterministic_lag}")
        if self.live and self.deterministic_lag >= 0:
            raise ConfigError("runtime.live and runtime.deterministic_lag exclude each other: a live run maps "
                              "what the mapper has time for, a deterministic one every frame in order")
        if self.deterministic_every < 1:
            raise ConfigError(f"runtime.deterministic_every must be >= 1, got {self.deterministic_every}")

    @property
    def deterministic(self) -> bool:
        return self.deterministic_lag >= 0
