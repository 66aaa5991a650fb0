"""Events the SLAM runtime emits while it runs (pose, keyframe, map update, submap, loop, stats, phase).

They are plain frozen dataclasses of numbers and numpy arrays, so they pickle cheaply across
process boundaries; the server forwards them to the viewer and the session status.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class PoseEvent:
    """A frame was tracked. ``T_world_cam`` (4, 4) float64 is the estimate in the world frame."""

    agent: int
    frame_index: int
    timestamp: float
    T_world_cam: np.ndarray
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
    agent: int
    frame_index: int
    map_id: int
    T_world_cam: np.ndarray


@dataclass(frozen=True)
class MapUpdateEvent:
    """A map changed; ``mesh_*`` is set when a fresh mesh was extracted (in the world frame)."""

    map_id: int
    version: int
    T_world_map: np.ndarray
    num_voxels: int
    keyframe_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    """(K, 4, 4) optimised keyframe poses of this map, world frame."""
    mesh_vertices: np.ndarray | None = None
    """(V, 3) float32 world coordinates."""
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

    ``T_world_cam`` / ``T_world_match`` (4, 4) are both keyframes' world poses after the
    loop's pose optimisation (for drawing the loop edge); ``scores`` are the verification
    scores (similarity, PnP inliers, hit ratio, depth agreement, ...)."""

    agent: int
    map_id: int
    frame_index: int
    timestamp: float
    match_agent: int
    match_map: int
    match_frame_index: int
    match_timestamp: float
    T_world_cam: np.ndarray
    T_world_match: np.ndarray
    scores: dict = field(default_factory=dict)


@dataclass(frozen=True)
class PosesUpdatedEvent:
    """Pose optimisation moved maps and keyframes (after a loop, or the final refinement).

    ``map_poses``: map id -> T_world_map (4, 4) of *every* map; ``keyframe_poses``: map id ->
    (K, 4, 4) world poses of that map's keyframes in keyframe order; ``agents``: map id ->
    agent. A viewer re-places each map's mesh by the change of its ``T_world_map`` and moves
    the trajectory frames tracked in that map with it."""

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


@dataclass(frozen=True)
class PhaseEvent:
    """The run entered a phase: ``tracking`` (frames are read and tracked, maps grow),
    ``refining`` (the input ended: the final global bundle adjustment, then the final map
    and mesh), ``writing`` (trajectories and ``run.json``). The last two take minutes on a
    long run with nothing else to report, so a client can tell a run that works from one
    that hangs."""

    phase: str


@dataclass(frozen=True)
class FinishedEvent:
    status: str
    """``finished``, ``failed`` or ``cancelled``."""
    error: str | None = None


Event = (PoseEvent | KeyframeEvent | MapUpdateEvent | SubmapEvent | LoopEvent | PosesUpdatedEvent | StatsEvent
         | PhaseEvent | FinishedEvent)
