"""Events the SLAM runtime emits while it runs (pose, keyframe, map update, submap, loop, stats).

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
    """``start``, ``region`` (left the map's bound) or ``tracking_failure``."""


@dataclass(frozen=True)
class LoopEvent:
    """A verified loop between a frame of map ``src_map`` and a keyframe of ``tar_map``."""

    src_map: int
    tar_map: int
    frame_index: int
    keyframe_index: int
    similarity: float
    T_world_src: np.ndarray
    T_world_tar: np.ndarray


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


@dataclass(frozen=True)
class FinishedEvent:
    status: str
    """``finished``, ``failed`` or ``cancelled``."""
    error: str | None = None


Event = PoseEvent | KeyframeEvent | MapUpdateEvent | SubmapEvent | LoopEvent | StatsEvent | FinishedEvent
