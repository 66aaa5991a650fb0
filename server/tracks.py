"""Poses and meshes that follow their map: the API process's copy of where every map is.

The runtime reports camera poses and meshes in the world frame *at the time of the event*;
loop closure and the final refinement later move whole maps (``PosesUpdatedEvent`` with every
map's new ``T_world_map``). Everything here is therefore kept in the frame of the map it
belongs to and placed in the world by that map's *current* ``T_world_map``, which moves a
frame tracked in map ``m`` by ``T_world_map_new @ inv(T_world_map_at_tracking)``.

A map's first placement (its ``SubmapEvent``, which the runtime sends after the pose of the
frame that started the map) only says where the map is; poses already seen in it stay where
they were reported. Later changes of ``T_world_map`` move them. Assumes events arrive in the
order the runtime emitted them (a ``PosesUpdatedEvent`` before poses tracked against the moved
maps).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from slam import MapUpdateEvent, PoseEvent, PosesUpdatedEvent, SubmapEvent


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
class TrackedFrame:
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

    def set(self, map_id: int, T) -> str:
        """Record a map's pose: ``placed`` (the first time), ``moved`` or ``same``."""
        T = rigid(T)
        old = self.poses.get(map_id)
        self.poses[map_id] = T
        if old is None:
            return "placed"
        return "same" if np.allclose(old, T, atol=1e-9) else "moved"

    def apply(self, event: object) -> dict[int, str]:
        """Fold in the map poses an event carries; returns {map id: ``placed`` or ``moved``}."""
        placements: list[tuple[int, np.ndarray]] = []
        if isinstance(event, SubmapEvent):
            self.agents[int(event.map_id)] = int(event.agent)
            placements.append((int(event.map_id), event.T_world_map))
        elif isinstance(event, MapUpdateEvent):
            placements.append((int(event.map_id), event.T_world_map))
        elif isinstance(event, PosesUpdatedEvent):
            for map_id, agent in (event.agents or {}).items():
                self.agents[int(map_id)] = int(agent)
            placements += [(int(m), T) for m, T in (event.map_poses or {}).items()]
        elif isinstance(event, PoseEvent):
            self.agents.setdefault(int(event.map_id), int(event.agent))
        changes: dict[int, str] = {}
        for map_id, T in placements:
            change = self.set(map_id, T)
            if change != "same":
                changes[map_id] = change
        return changes


@dataclass(frozen=True)
class FrameCamera:
    """The camera of an agent's newest tracked frame, at the resolution it was tracked."""

    K: np.ndarray
    """(3, 3) intrinsics."""
    width: int
    height: int


class Tracks:
    """Tracked poses per (agent, frame index), each in the frame of the map it was tracked in."""

    def __init__(self) -> None:
        self.maps = MapPlacements()
        self.frames: dict[tuple[int, int], TrackedFrame] = {}
        self.cameras: dict[int, FrameCamera] = {}
        """agent -> the camera of its newest frame that carried one."""

    def apply(self, event: object) -> dict[int, str]:
        """Fold in an event; returns {map id: ``placed`` or ``moved``} of the maps it placed."""
        changes = self.maps.apply(event)
        for map_id, change in changes.items():
            if change == "placed":  # frames seen before the map's placement stay where they were reported
                T_map_world = inverse(self.maps.T_world_map(map_id))
                for key, frame in self.frames.items():
                    if frame.map_id == map_id:
                        self.frames[key] = replace(frame, T_map_cam=T_map_world @ frame.T_map_cam)
        if isinstance(event, PoseEvent):
            self.add(event)
        return changes

    def add(self, event: PoseEvent) -> None:
        map_id = int(event.map_id)
        T_map_cam = inverse(self.maps.T_world_map(map_id)) @ rigid(event.T_world_cam)
        key = (int(event.agent), int(event.frame_index))
        self.frames[key] = TrackedFrame(key[0], key[1], float(event.timestamp), map_id, T_map_cam)
        if event.K is not None and event.image_size is not None:
            width, height = event.image_size
            self.cameras[key[0]] = FrameCamera(np.asarray(event.K, np.float64), int(width), int(height))

    def newest(self, agent: int) -> tuple[TrackedFrame, np.ndarray] | None:
        """The agent's newest tracked frame (highest index) and its current T_world_cam."""
        frames = [f for f in self.frames.values() if f.agent == agent]
        if not frames:
            return None
        frame = max(frames, key=lambda f: f.index)
        return frame, self.maps.T_world_map(frame.map_id) @ frame.T_map_cam

    def __len__(self) -> int:
        return len(self.frames)

    def agents(self) -> list[int]:
        return sorted({agent for agent, _ in self.frames})

    def world_pose(self, agent: int, index: int) -> np.ndarray | None:
        frame = self.frames.get((agent, index))
        if frame is None:
            return None
        return self.maps.T_world_map(frame.map_id) @ frame.T_map_cam

    def world_poses(self, agent: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(N,) frame indices, (N,) timestamps, (N, 4, 4) current T_world_cam of one agent,
        sorted by frame index."""
        frames = sorted((f for f in self.frames.values() if f.agent == agent), key=lambda f: f.index)
        if not frames:
            return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros((0, 4, 4))
        indices = np.array([f.index for f in frames], dtype=np.int64)
        stamps = np.array([f.timestamp for f in frames])
        poses = np.stack([self.maps.T_world_map(f.map_id) @ f.T_map_cam for f in frames])
        return indices, stamps, poses
