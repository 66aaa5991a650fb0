"""Events the SLAM runtime emits while it runs (pose, keyframe, map update, submap, loop, stats, phase).

They are plain frozen dataclasses of numbers and numpy arrays, so they pickle cheaply across
process boundaries; the server forwards them to the viewer and the session status.

Geometry travels in the frame of the map it belongs to (``T_map_cam``, mesh vertices in the map
frame), as the tracker and mapper hold it, together with the map's id; where the maps are in the
world comes separately (``T_world_map`` of ``SubmapEvent``, ``MapUpdateEvent`` and every map's in
``PosesUpdatedEvent``). A reader places map-frame geometry by the newest ``T_world_map`` it has
seen (``world = T_world_map @ map_frame``), so that a loop closure that moves a map moves
everything in it and nothing is converted to the world and back.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class PoseEvent:
    """A frame was tracked. ``T_map_cam`` (4, 4) float64 is the estimate in map ``map_id``'s frame."""

    agent: int
    frame_index: int
    timestamp: float
    T_map_cam: np.ndarray
    map_id: int
    tracking_ok: bool
    thumbnail: np.ndarray | None = None
    """(h, w, 3) uint8 small colour image for the viewer's frustum, or None."""
    K: np.ndarray | None = None
    """(3, 3) intrinsics at the frame's pipeline resolution."""
    image_size: tuple[int, int] | None = None
    """(width, height) at the pipeline resolution."""


@dataclass(frozen=True)
class KeyframeEvent:
    """A keyframe was taken; ``T_map_cam`` (4, 4) its pose in map ``map_id``'s frame."""

    agent: int
    frame_index: int
    map_id: int
    T_map_cam: np.ndarray


@dataclass(frozen=True)
class MapUpdateEvent:
    """A map changed; ``mesh_*`` is set when a fresh mesh was extracted (in the map's frame)."""

    map_id: int
    version: int
    T_world_map: np.ndarray
    num_voxels: int
    keyframe_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    """(K, 4, 4) optimised keyframe poses of this map in its frame (T_map_cam)."""
    mesh_vertices: np.ndarray | None = None
    """(V, 3) float32 map-frame coordinates."""
    mesh_faces: np.ndarray | None = None
    """(F, 3) int32."""
    mesh_colors: np.ndarray | None = None
    """(V, 3) uint8."""


@dataclass(frozen=True)
class SubmapEvent:
    """A new map (submap) was started."""

    map_id: int
    agent: int
    T_world_map: np.ndarray
    reason: str
    """``start`` (an agent's first map), ``region`` (left the map's bound) or
    ``tracking_failure`` (the new map floats in its own frame until a loop joins it)."""


@dataclass(frozen=True)
class LoopEvent:
    """A verified loop: keyframe ``frame_index`` of agent ``agent`` in map ``map_id`` matches
    keyframe ``match_frame_index`` of agent ``match_agent`` in map ``match_map``.

    ``T_map_cam`` / ``T_match_map_cam`` (4, 4) are both keyframes' poses in their maps' frames
    after the loop's pose optimisation (for drawing the loop edge); ``scores`` are the
    verification scores (similarity, PnP inliers, hit ratio, depth agreement, ...)."""

    agent: int
    map_id: int
    frame_index: int
    timestamp: float
    match_agent: int
    match_map: int
    match_frame_index: int
    match_timestamp: float
    T_map_cam: np.ndarray
    T_match_map_cam: np.ndarray
    scores: dict = field(default_factory=dict)


@dataclass(frozen=True)
class PosesUpdatedEvent:
    """Pose optimisation moved maps and keyframes (after a loop, or the final refinement).

    ``map_poses``: map id -> T_world_map (4, 4) of *every* map; ``keyframe_poses``: map id ->
    (K, 4, 4) poses of that map's keyframes in its frame, in keyframe order; ``agents``: map
    id -> agent. A viewer places each map's mesh and the frames tracked in it by the map's new
    ``T_world_map``."""

    map_poses: dict
    keyframe_poses: dict
    agents: dict
    reason: str
    """``loop`` or ``refinement``."""
    keyframe_indices: dict = field(default_factory=dict)
    """map id -> the frame indices (of the map's agent) of its keyframes, in the order of
    ``keyframe_poses``."""


@dataclass(frozen=True)
class StatsEvent:
    frames_done: int
    frames_total: int | None
    fps: float
    keyframes: int
    maps: int
    loops: int
    voxels: int
    tracking_busy: float = 0.0
    """Share of wall time the tracker spent working (0-1)."""
    mapping_busy: float = 0.0
    ate_rmse: float | None = None
    """Agent 0's ATE RMSE in metres so far (the final one in the last StatsEvent); None
    without ground truth."""


PHASES = ("tracking", "refining", "writing")

END_STEPS = ("bundle_adjustment", "retracking", "colour_fit", "mesh", "outputs")
"""The end-of-run steps in the order they start: the final global bundle adjustment, the
re-tracking of the frames against the final maps, the fine colour level's fit, the checkpoint
and mesh (these four while ``refining``), the trajectories and ``run.json`` (``writing``)."""


@dataclass(frozen=True)
class PhaseEvent:
    """The run entered a phase: ``tracking`` (frames are read and tracked, maps grow),
    ``refining`` (the input ended: the final global bundle adjustment, then the final map
    and mesh), ``writing`` (trajectories and ``run.json``). The last two take minutes on a
    long run with nothing else to report, so a client can tell a run that works from one
    that hangs: each end-of-run step sends its own event (``step``), with how long it should
    take where something bounds or predicts it."""

    phase: str
    step: str | None = None
    """The end-of-run step that starts now (one of END_STEPS), None for the phase's start."""
    estimate_s: float | None = None
    """About how many seconds the step should take (a time cap, or a forecast from the run so
    far); None where nothing predicts it. An estimate, not a promise: a step may run over."""


@dataclass(frozen=True)
class FinishedEvent:
    status: str
    """``finished``, ``failed`` or ``cancelled``."""
    error: str | None = None


Event = (PoseEvent | KeyframeEvent | MapUpdateEvent | SubmapEvent | LoopEvent | PosesUpdatedEvent | StatsEvent
         | PhaseEvent | FinishedEvent)
