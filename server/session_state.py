"""The one fold of a session's SLAM events: ``SessionState.apply(event)``.

Three consumers read the same events: the session's status (``server.session_status``), its
trajectories (``Tracks``, for the trajectory and AR endpoints) and the live viewer's state
(``server.viewer_state``). Each used to fold them itself, with its own chain of ``isinstance``
branches and its own copy of the map-placement rule. Now one fold keeps what the events say,
in their maps' frames as the events carry them, placed by the rule of ``server.tracks``: where
every map is, every tracked frame, every map's keyframes, the loops, the newest mesh per map,
the counters, the phase. ``apply`` returns a :class:`Change` that names what moved, and each consumer derives
its own view from the fold and the change: the status its counts and frames/s, the viewer
what to resend.

Why a shared state and not one dispatch that three handlers register with: the hard part is
not the dispatch but the geometry behind it (a map that moves moves everything tracked in it;
keyframes, loop ends and meshes kept in map frames). With
registered handlers each consumer would still keep and re-express its own copy of that
state, three places to get the rule wrong, as before. With one state they cannot disagree,
and the consumers keep only their own concerns (persistence, rate limits, sent chunks).
The fold is plain data (numpy, no viser, no server): each consumer owns its own instance
under its own lock, so nothing is shared across threads.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from server.tracks import FrameCamera, MapPlacements, Tracks, rigid, transform_points
from slam import (
    FinishedEvent,
    KeyframeEvent,
    LoopEvent,
    MapUpdateEvent,
    PhaseEvent,
    PoseEvent,
    PosesUpdatedEvent,
    StatsEvent,
    SubmapEvent,
)


@dataclass
class Loop:
    """A loop edge: two keyframes, each found by (agent, frame index) in the tracks (so it moves
    with them), else at its event position in its map's frame."""

    agent: int
    frame_index: int
    map_id: int
    point: np.ndarray
    match_agent: int
    match_frame_index: int
    match_map: int
    match_point: np.ndarray


@dataclass
class Mesh:
    """A map's newest mesh in the map's frame."""

    vertices: np.ndarray
    """(V, 3) float32, in the map's frame."""
    faces: np.ndarray
    """(F, 3) int."""
    colors: np.ndarray | None
    """(V, 3) uint8 or None."""


@dataclass
class Change:
    """What one event changed in a :class:`SessionState`."""

    maps: set[int] = field(default_factory=set)
    """Maps the event names (new ones among them)."""
    moved: set[int] = field(default_factory=set)
    """Maps whose placement changed, the first one included (everything in them moved)."""
    submap: int | None = None
    """The map a SubmapEvent started."""
    frame: tuple[int, int] | None = None
    """(agent, frame index) of a tracked frame."""
    retracked_slot: int | None = None
    """The frame was seen before: its position in the agent's arrival order."""
    keyframes: set[int] = field(default_factory=set)
    """Maps whose keyframe poses changed."""
    keyframe: bool = False
    """A keyframe was taken (KeyframeEvent)."""
    mesh: tuple[int, "Mesh"] | None = None
    """(map id, its new mesh in the map's frame) when the event carried a mesh (even an empty one)."""
    loop: bool = False
    stats: StatsEvent | None = None
    phase: str | None = None
    """The phase a PhaseEvent entered."""
    step: str | None = None
    """The end-of-run step it started (``slam.events.END_STEPS``), None for a phase's start."""
    estimate_s: float | None = None
    """About how long that step should take (seconds), None when nothing predicts it."""
    finished: FinishedEvent | None = None


class SessionState:
    """What a session's events have said so far (module doc). Not thread-safe: its owner locks."""

    def __init__(self, keep_meshes: bool = True) -> None:
        self.maps = MapPlacements()
        self.tracks = Tracks(self.maps)
        self.reasons: dict[int, str] = {}
        """map id -> why it started (SubmapEvent.reason)."""
        self.keyframes: dict[int, np.ndarray] = {}
        """map id -> (K, 4, 4) keyframe poses in the map's frame."""
        self.loops: list[Loop] = []
        self.keep_meshes = keep_meshes
        self.meshes: dict[int, Mesh] = {}
        """map id -> newest non-empty mesh (with ``keep_meshes``)."""
        self.cameras: dict[int, FrameCamera] = {}
        """agent -> its camera as its poses report it."""
        self.latest: dict[int, tuple[int, np.ndarray | None]] = {}
        """agent -> (frame index, thumbnail) of its newest pose."""
        self.keyframe_events = 0
        self.loop_events = 0
        self.stats: StatsEvent | None = None
        self.phase: str | None = None
        self.finished: FinishedEvent | None = None

    # -- the fold ----------------------------------------------------------------------------

    def apply(self, event: object) -> Change:
        """Fold in one event (others than the runtime's are ignored); says what changed."""
        change = Change()
        handler = _HANDLERS.get(type(event))
        if handler is not None:
            handler(self, event, change)
        return change

    def _place(self, map_id: int, T_world_map, change: Change) -> None:
        """Where the map is now (``server.tracks``): what it holds moves with it."""
        if self.maps.set(map_id, T_world_map):
            change.moved.add(map_id)

    def _on_pose(self, event: PoseEvent, change: Change) -> None:
        map_id, agent, index = int(event.map_id), int(event.agent), int(event.frame_index)
        change.maps.add(map_id)
        self.maps.agents.setdefault(map_id, agent)
        slot = self.tracks.slot(agent, index)
        self.tracks.add(agent, index, event.timestamp, map_id, event.T_map_cam)
        change.frame, change.retracked_slot = (agent, index), slot
        self.latest[agent] = (index, event.thumbnail)
        if event.K is not None and event.image_size is not None:
            width, height = event.image_size
            self.cameras[agent] = FrameCamera(np.asarray(event.K, np.float64), int(width), int(height))

    def _on_keyframe(self, event: KeyframeEvent, change: Change) -> None:
        map_id = int(event.map_id)
        change.maps.add(map_id)
        self.keyframe_events += 1
        change.keyframe = True
        T_map_cam = rigid(event.T_map_cam)
        self.keyframes[map_id] = np.concatenate([self.keyframes.get(map_id, np.zeros((0, 4, 4))), T_map_cam[None]])
        change.keyframes.add(map_id)

    def _on_map_update(self, event: MapUpdateEvent, change: Change) -> None:
        map_id = int(event.map_id)
        change.maps.add(map_id)
        self._place(map_id, event.T_world_map, change)
        if len(event.keyframe_poses):
            self.keyframes[map_id] = np.asarray(event.keyframe_poses, dtype=np.float64).reshape(-1, 4, 4)
            change.keyframes.add(map_id)
        if event.mesh_vertices is not None and event.mesh_faces is not None:
            mesh = Mesh(np.asarray(event.mesh_vertices, dtype=np.float32).reshape(-1, 3), event.mesh_faces,
                        event.mesh_colors)
            change.mesh = (map_id, mesh)
            if self.keep_meshes and len(event.mesh_faces):
                self.meshes[map_id] = mesh

    def _on_submap(self, event: SubmapEvent, change: Change) -> None:
        map_id = int(event.map_id)
        change.maps.add(map_id)
        change.submap = map_id
        self.maps.agents[map_id] = int(event.agent)
        self.reasons[map_id] = str(event.reason)
        self._place(map_id, event.T_world_map, change)

    def _on_poses_updated(self, event: PosesUpdatedEvent, change: Change) -> None:
        for map_id, agent in (event.agents or {}).items():
            change.maps.add(int(map_id))
            self.maps.agents[int(map_id)] = int(agent)
        for map_id, T in (event.map_poses or {}).items():
            change.maps.add(int(map_id))
            self._place(int(map_id), T, change)
        for map_id, poses in (event.keyframe_poses or {}).items():
            map_id = int(map_id)
            change.maps.add(map_id)
            self.keyframes[map_id] = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
            change.keyframes.add(map_id)

    def _on_loop(self, event: LoopEvent, change: Change) -> None:
        change.maps |= {int(event.map_id), int(event.match_map)}
        self.loop_events += 1
        self.loops.append(Loop(
            int(event.agent), int(event.frame_index), int(event.map_id), rigid(event.T_map_cam)[:3, 3].copy(),
            int(event.match_agent), int(event.match_frame_index), int(event.match_map),
            rigid(event.T_match_map_cam)[:3, 3].copy()))
        change.loop = True

    def _on_stats(self, event: StatsEvent, change: Change) -> None:
        self.stats = change.stats = event

    def _on_phase(self, event: PhaseEvent, change: Change) -> None:
        self.phase = change.phase = event.phase
        change.step = getattr(event, "step", None)  # events pickled by an older runtime lack it
        change.estimate_s = getattr(event, "estimate_s", None)

    def _on_finished(self, event: FinishedEvent, change: Change) -> None:
        self.finished = change.finished = event

    # -- reading -----------------------------------------------------------------------------

    def keyframe_poses(self, map_id: int) -> np.ndarray:
        """(K, 4, 4) keyframe poses of a map in its frame."""
        return self.keyframes.get(map_id, np.zeros((0, 4, 4)))

    def frame_position(self, agent: int, frame_index: int) -> np.ndarray | None:
        """World position now of an agent's tracked frame, or None if it was not seen."""
        pose = self.tracks.world_pose(agent, frame_index)
        return None if pose is None else pose[:3, 3]

    def camera_pose(self, agent: int) -> np.ndarray | None:
        """(4, 4) world pose now of an agent's newest frame, or None."""
        latest = self.latest.get(agent)
        return None if latest is None else self.tracks.world_pose(agent, latest[0])

    def loop_points(self) -> np.ndarray:
        """(L, 2, 3) world end points of the loop edges now: at their tracked frames where
        those were seen, else at the loop's keyframe poses in their maps."""
        points = []
        for loop in self.loops:
            a = self.frame_position(loop.agent, loop.frame_index)
            b = self.frame_position(loop.match_agent, loop.match_frame_index)
            if a is None:
                a = self.maps.point_to_world(loop.map_id, loop.point)
            if b is None:
                b = self.maps.point_to_world(loop.match_map, loop.match_point)
            points.append([a, b])
        return np.asarray(points, dtype=np.float64).reshape(-1, 2, 3)

    def world_mesh(self, map_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
        """A map's newest kept mesh in the world as the map is placed now: (V, 3) float32
        vertices, faces, colours; None without one."""
        mesh = self.meshes.get(map_id)
        if mesh is None:
            return None
        vertices = transform_points(self.maps.T_world_map(map_id), mesh.vertices).astype(np.float32)
        return vertices, mesh.faces, mesh.colors


_HANDLERS = {
    PoseEvent: SessionState._on_pose,
    KeyframeEvent: SessionState._on_keyframe,
    MapUpdateEvent: SessionState._on_map_update,
    SubmapEvent: SessionState._on_submap,
    PosesUpdatedEvent: SessionState._on_poses_updated,
    LoopEvent: SessionState._on_loop,
    StatsEvent: SessionState._on_stats,
    PhaseEvent: SessionState._on_phase,
    FinishedEvent: SessionState._on_finished,
}
"""The one dispatch on event type."""
