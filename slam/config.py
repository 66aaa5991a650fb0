"""Configuration: a shallow tree of frozen dataclasses with named presets.

The sections (``VoxelConfig`` ... ``RuntimeConfig``, each field documented) are defined in
``slam.config_sections`` and re-exported here. The presets:

    ``test``  seconds per run, for the test suite (tiny rays and iterations).
    ``cpu``   the default without a GPU: fewer rays and iterations than the paper.
    ``paper`` the paper's stated settings, the Vox-Fusion release's where the paper is silent.
    ``gpu``   the default with a GPU: ``paper`` on static shapes.

Each preset is a table of the values it changes, a line of why next to each, and a key into
``benchmarks/decisions.md`` (``decisions.md#section.field``), where the measurements are.

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

from .config_sections import (
    LOSS_NORMALISATIONS,
    STATIC_SHAPES,
    ConfigError,
    DecoderConfig,
    FineColorConfig,
    LoopConfig,
    LossConfig,
    MappingConfig,
    MeshConfig,
    MultiMapConfig,
    RenderConfig,
    RuntimeConfig,
    TrackingConfig,
    VoxelConfig,
)

__all__ = [
    "LOSS_NORMALISATIONS", "PRESETS", "RETIRED_FIELDS", "STATIC_SHAPES", "ConfigError", "DecoderConfig",
    "FineColorConfig", "LoopConfig", "LossConfig", "MappingConfig", "MeshConfig", "MultiMapConfig", "RenderConfig",
    "RuntimeConfig", "SLAMConfig", "TrackingConfig", "VoxelConfig", "apply_overrides", "config_from_dict",
    "default_preset_name", "load_config", "preset",
]


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
    fine_color: FineColorConfig = field(default_factory=FineColorConfig)
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _paper() -> SLAMConfig:
    """The paper's stated settings: 0.2 m voxels, 16-D embeddings, the decoder's widths (the field
    defaults), a step ratio in 0.05-0.1, the zero motion model, Adam on the pose, the keyframe
    test. Where it gives none, the authors' Vox-Fusion release (github.com/zju3dv/Vox-Fusion,
    ``configs/replica_all.yaml`` and its code); ours where neither says (decisions.md#preset.paper).
    """
    return SLAMConfig(
        preset="paper",
        render=RenderConfig(
            step_ratio=0.05,               # the release's (paper: 0.05-0.1)
            max_hits=10,                   # M_h, the release's
            max_distance=10.0,             # D_max, the release's
            truncation=0.05,               # the release's
        ),
        tracking=TrackingConfig(
            optimizer="adam",              # the paper's
            num_rays=2048,                 # the release's
            iterations=50,                 # the release's
            lr_rot=1e-2,                   # the release's
            lr_trans=1e-2,                 # the release's
            lr_decay=1.0,                  # the release: no decay
            resample_rays=True,            # the release: new rays every iteration
            keep_best_iterate=False,       # the release: the last iterate
            sample_band=0.0,               # the paper: the whole ray
            min_corner_updates=0,          # the release tracks against every allocated voxel
            convergence_tol=0.0,           # no early stop, as the release
        ),
        mapping=MappingConfig(
            num_rays=2048,                 # the release's, per frame
            iterations=20,                 # the release's
            window_size=5,                 # the release: four random keyframes plus the newest frame
            lr_embed=5e-3,                 # the release's
            lr_decoder=5e-3,               # the release's
            lr_pose=1e-2,                  # the release's (the tracker's, kept by the mapper)
            keyframe_max_interval=50,      # the release: a keyframe at least every 50 frames
            optimize_current_pose=True,    # paper, release (decisions.md#mapping.optimize_current_pose)
        ),
        runtime=RuntimeConfig(
            device="auto",                 # a GPU where there is one
        ),
    )


def _cpu() -> SLAMConfig:
    """The default without a GPU: the paper's system within a 2-core CPU's budget
    (decisions.md#preset.cpu)."""
    return SLAMConfig(
        preset="cpu",
        decoder=DecoderConfig(
            hidden_dim=64,                 # the MLP dominates a CPU iteration (decisions.md#decoder.hidden_dim)
            feature_dim=64,                # as hidden_dim (decisions.md#decoder.hidden_dim)
            color_hidden_dim=64,           # as hidden_dim (decisions.md#decoder.hidden_dim)
        ),
        render=RenderConfig(
            step_ratio=0.1,                # the paper's coarse end (decisions.md#preset.cpu)
            max_hits=16,                   # a 2-core budget, not A/B'd yet (decisions.md#preset.cpu)
            truncation=0.1,                # 0.05 worse on 3 real sequences (decisions.md#preset.cpu)
        ),
        loss=LossConfig(
            rgb_weight=10.0,               # 0.5 leaves colour near the mean (decisions.md#loss.rgb_weight)
            normalisation="slots",         # the release's means with its weights (decisions.md#loss.normalisation)
        ),
        tracking=TrackingConfig(
            optimizer="gauss_newton",      # 6 LM steps beat 40 Adam steps (decisions.md#tracking.optimizer)
            num_rays=512,                  # 1024 within spread everywhere at 0.9x (decisions.md#preset.cpu)
            iterations=4,                  # as accurate as 6 at 0.54-0.74x the time (decisions.md#tracking.iterations)
            rgb_weight=20.0,               # colour alone sees along a plain wall (decisions.md#tracking.rgb_weight)
            color_weight_eps=5e-2,         # a fifth of the peak (decisions.md#tracking.color_weight_eps)
            convergence_tol=1e-4,          # stop below 0.1 mm a step (decisions.md#tracking.convergence_tol)
            feature_count=1000,            # ORB matches fix the fast turns (decisions.md#tracking.feature_count)
            feature_weight=0.003,          # 0.001-0.0045 all alike (decisions.md#tracking.feature_weight)
            motion_prior=0.01,             # holds what the view does not see (decisions.md#tracking.motion_prior)
            feature_dense_check=True,      # no PnP pose a period off (decisions.md#tracking.feature_dense_check)
            border_margin=0.1,             # no pull back into a lagging map (decisions.md#tracking.border_margin)
            retrack_iterations=2,          # every frame again on the final map: 5 real sequences better (decisions.md#tracking.retrack_iterations)
            retrack_ray_budget=76_800,     # 150 frames' 512 pixels: short runs get up to 2048 (decisions.md#tracking.retrack_iterations)
            retrack_frame_budget=300,      # whole fr1/rpy within spread at 1.17x; 150 lost on 450-722 (decisions.md#tracking.retrack_frame_budget)
        ),
        mapping=MappingConfig(
            num_rays=192,                  # many small steps beat few large (decisions.md#mapping.num_rays)
            iterations=8,                  # 12 no better, 1.2-1.3x slower on real data (decisions.md#mapping.iterations)
            window_size=4,                 # 6 no better on fr1/rpy and fr1/desk (decisions.md#preset.cpu)
            keyframe_max_interval=10,      # 450-722 2.90 -> 2.58 cm, its views +0.3 dB (decisions.md#mapping.keyframe_max_interval)
            keyframe_interval_min_metres=0.01,  # a still camera adds no keyframes (decisions.md#mapping.keyframe_max_interval)
            keyframe_interval_min_degrees=1.0,  # with keyframe_interval_min_metres
            first_frame_iterations=100,    # the field default, ours (decisions.md#preset.paper)
            final_iterations=500,          # what the window never gave (decisions.md#mapping.final_iterations)
            final_rays=512,                # iterations count more than rays (decisions.md#mapping.final_iterations)
            final_iterations_per_keyframe=50,  # a budget for short runs (decisions.md#mapping.final_time_share)
            final_time_share=0.15,         # 10 s of a minute's run (decisions.md#mapping.final_time_share)
            optimize_current_pose=True,    # the paper's way (decisions.md#mapping.optimize_current_pose)
            frame_correction="interpolated",  # better on all 5 real sequences, paired (decisions.md#mapping.frame_correction)
            thin_samples=True,             # 1.5x faster mapping step (decisions.md#mapping.thin_samples)
            free_space_stride=2,           # with thin_samples (decisions.md#mapping.thin_samples)
            color_weight_eps=5e-2,         # with thin_samples (decisions.md#mapping.thin_samples)
        ),
        mesh=MeshConfig(
            resolution=6,                  # a 2-core budget, not A/B'd yet (decisions.md#preset.cpu)
        ),
        multimap=MultiMapConfig(
            region_size=3.0,               # laps return to other maps (decisions.md#multimap.region_size)
        ),
        fine_color=FineColorConfig(
            levels=4,                      # colour detail below 0.2 m voxels, no cost to tracking (decisions.md#fine_color)
            coarsest=0.16,                 # 0.16-0.02 m beat 0.08-0.01 m on fr1/desk (decisions.md#fine_color)
            finest=0.02,                   # with coarsest (decisions.md#fine_color)
            features=1,                    # rows count more than features a row (decisions.md#fine_color)
            table_log2=17,                 # the finest level's rows: 0.7 MB in all (decisions.md#fine_color)
            level_tables="surface",        # coarser levels cross fewer cells (decisions.md#fine_color)
            fit_iterations=0,              # fits during the run cost tracking 26 % of its frames/s (decisions.md#fine_color)
            fit_rays=4096,                 # many small final steps beat few large (decisions.md#fine_color)
            final_fit_iterations=600,      # room0 held-out +1.8 dB, fr1/desk +0.23 over 200, 0.98x frames/s (decisions.md#fine_color)
            final_fit_surface="rendered",  # where views query it: +0.2-2.1 dB (decisions.md#fine_color)
            fit_render_block=1,            # keyframes rendered whole: room0 held-out +1.0 dB at 0.98x frames/s (decisions.md#fine_color)
            fit_pixels="observed",         # pixels without depth too: fr1/desk +1.0 dB, fr1/rpy +0.6 (decisions.md#fine_color)
        ),
        loop=LoopConfig(
            intra_map_iterations=0,        # a rigid move changes nothing inside (decisions.md#loop.intra_map_iterations)
        ),
        runtime=RuntimeConfig(
            device="auto",                 # a GPU where there is one
            input_width=320,               # a 2-core budget, not A/B'd yet (decisions.md#runtime.input_width)
        ),
    )


def _test() -> SLAMConfig:
    """Seconds per run for the test suite; every value is small for speed (decisions.md#preset.test)."""
    return SLAMConfig(
        preset="test",
        decoder=DecoderConfig(
            hidden_dim=32,                 # tiny MLP: speed
            feature_dim=32,                # tiny MLP: speed
            color_hidden_dim=32,           # tiny MLP: speed
        ),
        render=RenderConfig(
            step_ratio=0.2,                # few samples a ray: speed
            max_hits=8,                    # few voxels a ray: speed
            truncation=0.1,                # the field default, as cpu
            chunk_rays=2048,               # small chunks: a test's memory
        ),
        tracking=TrackingConfig(
            optimizer="gauss_newton",      # cpu's path, tested (decisions.md#preset.test)
            num_rays=128,                  # speed
            iterations=4,                  # speed
        ),
        mapping=MappingConfig(
            num_rays=128,                  # speed
            iterations=2,                  # speed
            window_size=3,                 # speed
            first_frame_iterations=10,     # speed
            final_iterations=2,            # runs the final bundle adjustment's code, briefly
            final_rays=128,                # speed
        ),
        loop=LoopConfig(
            inter_map_iterations=5,        # speed
            intra_map_iterations=3,        # runs the intra-map step's code, briefly
            geometry_rays=64,              # speed
        ),
        mesh=MeshConfig(
            resolution=4,                  # coarse meshes: speed
            update_every_keyframes=2,      # live meshes within a short test run
        ),
        runtime=RuntimeConfig(
            device="cpu",                  # the same device wherever the tests run
            input_width=160,               # small frames: speed
            processes=True,                # the production layout (tracker and mapper processes)
        ),
    )


def _gpu() -> SLAMConfig:
    """The default with a GPU: ``paper`` with every iteration on static shapes;
    unmeasured on a GPU so far (decisions.md#preset.gpu)."""
    paper = _paper()
    return replace(
        paper,
        preset="gpu",
        # no device reads inside the loops (decisions.md#render.static_shapes)
        render=replace(paper.render, static_shapes="on"),
        # its Adam has no stop test to read (decisions.md#tracking.check_every)
        tracking=replace(paper.tracking, check_every=0),
        # 640-wide input at most (decisions.md#preset.gpu)
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


def _rejected(entry: str, commit: str) -> str:
    """Why a setting the decision rule rejected is gone, and where its figures and code are."""
    return f"off in every preset, it lost its A/B (decisions.md#{entry}; its code is in commit {commit} and before)"


RETIRED_FIELDS = {
    ("mapping", "map_every"): "it never changed anything: every tracked frame is mapped, and the "
                              "mapper optimises once over the frames that queued up",
    ("runtime", "max_map_lag"): _rejected("runtime.max_map_lag", "a86dcd1"),
    ("tracking", "constant_velocity"): _rejected("tracking.constant_velocity", "a86dcd1"),
    ("mapping", "keyframe_iterations"): _rejected("mapping.keyframe_iterations", "a86dcd1"),
    ("fine_color", "fit_extra_block"): _rejected("fine_color.fit_extra_block", "a86dcd1"),
    ("tracking", "exposure"): _rejected("tracking.exposure", "a86dcd1"),
    ("tracking", "exposure_prior"): _rejected("tracking.exposure", "a86dcd1"),
    ("mapping", "exposure"): _rejected("mapping.exposure", "a86dcd1"),
    ("mapping", "exposure_prior"): _rejected("mapping.exposure", "a86dcd1"),
    ("mapping", "exposure_lr"): _rejected("mapping.exposure", "a86dcd1"),
    ("tracking", "color_robust"): _rejected("tracking.color_robust", "1c8d5fb"),
    ("tracking", "color_adaptive"): _rejected("tracking.color_adaptive", "1c8d5fb"),
    ("runtime", "color_to_depth_time"): _rejected("runtime.color_to_depth_time", "2f559e5"),
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
