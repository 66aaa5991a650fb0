"""Poses that follow their map: where every map is, and the frames tracked in each.

The runtime reports camera poses, keyframes and meshes in the frame of the map they belong to
(``slam.events``); loop closure and the final refinement later move whole maps
(``PosesUpdatedEvent`` with every map's new ``T_world_map``). Everything is therefore kept as
it came, in its map's frame, and placed in the world by that map's *current* ``T_world_map``.

The placement rule, in one place (:class:`MapPlacements`), for everyone who draws or reports
poses (the session's status and trajectories, the viewer's state; both through
``server.session_state.SessionState``)::

    world = T_world_map @ map_frame

with ``T_world_map`` the identity until an event places the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def rigid(T) -> np.ndarray:
    """(4, 4) float64 copy."""
    return np.array(T, dtype=np.float64).reshape(4, 4)


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) points through the (4, 4) transform T; float64."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return points @ T[:3, :3].T + T[:3, 3]


@dataclass(frozen=True)
class TrackedPose:
    """The pose an agent's frame was tracked at, as the server keeps it (``slam.mapping.TrackedFrame``
    is the frame itself with its pose, on its way to the mapper)."""

    agent: int
    index: int
    timestamp: float
    map_id: int
    T_map_cam: np.ndarray
    """(4, 4) camera pose in its map's frame."""


class MapPlacements:
    """map id -> current ``T_world_map`` (identity until an event places it), map -> agent."""

    def __init__(self) -> None:
        self.poses: dict[int, np.ndarray] = {}
        """map id -> T_world_map, for maps an event has placed."""
        self.agents: dict[int, int] = {}

    def T_world_map(self, map_id: int) -> np.ndarray:
        T = self.poses.get(map_id)
        return np.eye(4) if T is None else T

    def set(self, map_id: int, T) -> bool:
        """Record a map's pose; True if that moves the map (from the identity, the first time)."""
        T = rigid(T)
        old = self.T_world_map(map_id)
        self.poses[map_id] = T
        return not np.allclose(old, T, atol=1e-9)

    def to_world(self, map_id: int, T_map) -> np.ndarray:
        """A map-frame pose (4, 4), or poses (N, 4, 4), in the world as the map is placed now."""
        return self.T_world_map(map_id) @ np.asarray(T_map, dtype=np.float64)

    def point_to_world(self, map_id: int, point) -> np.ndarray:
        return transform_points(self.T_world_map(map_id), point)[0]


@dataclass(frozen=True)
class FrameCamera:
    """A camera as an agent's frames were tracked with it (or as the input gives it)."""

    K: np.ndarray
    """(3, 3) intrinsics."""
    width: int
    height: int


class Tracks:
    """Tracked poses per agent and frame index (in arrival order; a re-tracked frame keeps its
    place), each in the frame of the map it was tracked in."""

    def __init__(self, maps: MapPlacements | None = None) -> None:
        self.maps = maps if maps is not None else MapPlacements()
        self.by_agent: dict[int, dict[int, TrackedPose]] = {}

    def add(self, agent: int, index: int, timestamp: float, map_id: int, T_map_cam) -> bool:
        """Add (or replace) a frame tracked at ``T_map_cam`` in map ``map_id``; True if it was seen before."""
        frames = self.by_agent.setdefault(int(agent), {})
        seen = int(index) in frames
        frames[int(index)] = TrackedPose(int(agent), int(index), float(timestamp), int(map_id), rigid(T_map_cam))
        return seen

    def __len__(self) -> int:
        return sum(len(frames) for frames in self.by_agent.values())

    def agents(self) -> list[int]:
        return sorted(agent for agent, frames in self.by_agent.items() if frames)

    def agents_in(self, map_ids) -> set[int]:
        """Agents with a frame tracked in one of these maps."""
        map_ids = set(map_ids)
        return {agent for agent, frames in self.by_agent.items()
                if any(f.map_id in map_ids for f in frames.values())}

    def slot(self, agent: int, index: int) -> int | None:
        """Position of a frame in its agent's arrival order, or None."""
        frames = self.by_agent.get(agent, {})
        return list(frames).index(index) if index in frames else None

    def world_pose(self, agent: int, index: int) -> np.ndarray | None:
        frame = self.by_agent.get(agent, {}).get(index)
        return None if frame is None else self.maps.to_world(frame.map_id, frame.T_map_cam)

    def world_positions(self, agent: int) -> np.ndarray:
        """(N, 3) world camera centres now of an agent's frames, in arrival order."""
        frames = list(self.by_agent.get(agent, {}).values())
        if not frames:
            return np.zeros((0, 3))
        points = np.stack([f.T_map_cam[:3, 3] for f in frames])
        maps = np.array([f.map_id for f in frames])
        out = np.empty_like(points)
        for map_id in np.unique(maps):
            rows = maps == map_id
            out[rows] = transform_points(self.maps.T_world_map(int(map_id)), points[rows])
        return out

    def map_ids(self, agent: int) -> np.ndarray:
        """(N,) the map of each of an agent's frames, in arrival order."""
        return np.array([f.map_id for f in self.by_agent.get(agent, {}).values()], dtype=np.int64)

    def world_poses(self, agent: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(N,) frame indices, (N,) timestamps, (N, 4, 4) current T_world_cam of one agent,
        sorted by frame index."""
        frames = sorted(self.by_agent.get(agent, {}).values(), key=lambda f: f.index)
        if not frames:
            return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros((0, 4, 4))
        indices = np.array([f.index for f in frames], dtype=np.int64)
        stamps = np.array([f.timestamp for f in frames])
        poses = np.stack([self.maps.to_world(f.map_id, f.T_map_cam) for f in frames])
        return indices, stamps, poses
