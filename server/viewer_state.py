"""The live viewer's state, without viser: what each session shows and what must be resent.

``server.viewer`` (the viser facade) keeps one :class:`ViewerSession` per session and pushes
what it says to viser; everything here is plain data and numpy, testable without viser or a
server. A session's events are folded by the one fold of them, ``server.session_state``
(placement rule included: everything is kept in its map's frame and placed at the map's
current ``T_world_map``); this module adds what only a viewer needs: which map nodes, keyframe
frusta, trajectory blocks, cameras, loop edges and status line are stale (the ``*_dirty``
flags), which mesh chunks were sent (so a chunk is resent only when it changed), and when to
frame the browsers.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass, field

import numpy as np

from server.session_state import SessionState
from server.tracks import rigid
from slam import StatsEvent

CHUNK_SIZE_M = 1.0
"""Edge of the cubes a map's mesh is cut into (metres): the unit that is resent when it changes."""
VERTEX_TOLERANCE_M = 0.005
COLOR_TOLERANCE = 8
TRAJECTORY_BLOCK = 256
FRAME_DIRECTION = np.array([0.45, -0.55, -0.6]) / np.linalg.norm([0.45, -0.55, -0.6])
"""From the centre of a framed session towards the browser's camera: above it (-y), behind the
first camera (-z) and to one side, in the world of a run: its first camera's frame (OpenCV axes)."""
UP_DIRECTION = "-y"
"""The viewer's up: the first camera's up (OpenCV's y points down the image)."""
MIN_FRAME_RADIUS_M = 0.25
"""Smallest radius framed (a session of one camera pose still shows its surroundings)."""
REFRAME_GROWTH = 1.5
"""A session is framed again when its bounds' diagonal has grown by this factor."""

LOOP_COLOR = (255, 40, 200)
_AGENT_COLORS = ((230, 60, 40), (30, 110, 230), (30, 160, 70), (215, 140, 10), (140, 60, 200), (0, 160, 170),
                 (210, 70, 150), (90, 90, 90))


def map_color(map_id: int) -> tuple[int, int, int]:
    """A distinct, saturated RGB colour per map id (golden-ratio hue steps)."""
    hue = (0.08 + 0.618034 * map_id) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.75, 0.95)
    return int(r * 255), int(g * 255), int(b * 255)


def agent_color(agent: int) -> tuple[int, int, int]:
    """A distinct RGB colour per agent (camera) for its trajectory and frustum: a fixed
    palette of darker, strong colours (apart from the maps' lighter ones), then hue steps."""
    if 0 <= agent < len(_AGENT_COLORS):
        return _AGENT_COLORS[agent]
    hue = (0.6 + 0.381966 * agent) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.9, 0.7)
    return int(r * 255), int(g * 255), int(b * 255)


def _counted(n: int, noun: str) -> str:
    """``1 map``, ``2 maps``."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def box_segments(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(12, 2, 3) float32 edges of the axis-aligned box [lo, hi]."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    edges = [(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1]
    return corners[np.array(edges)].astype(np.float32)


def framing(lo: np.ndarray, hi: np.ndarray, fov_y: float) -> tuple[np.ndarray, np.ndarray]:
    """(camera position, look-at point) from which the box [lo, hi] fills a view of vertical
    field of view ``fov_y`` (radians): its bounding sphere spans the view's height at the
    centre, so a small mesh is not a speck in the middle (the box itself, smaller than its
    sphere from any side, is not cut)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre = (lo + hi) / 2
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), MIN_FRAME_RADIUS_M)
    distance = radius / np.tan(0.5 * float(np.clip(fov_y, np.radians(10.0), np.radians(150.0))))
    return centre + distance * FRAME_DIRECTION, centre


FRUSTUM_SHARE = 0.06
"""A live camera's frustum, as a share of the diagonal of what the session shows."""
FRUSTUM_MAX_M = 0.2
"""Largest frustum (metres): the size it has in a room-sized scene."""


def frustum_scale(bounds: tuple[np.ndarray, np.ndarray] | None) -> float:
    """The live camera frustum's size for a session of these bounds: a share of the scene as
    framed (at least MIN_FRAME_RADIUS_M across), so that a camera that barely moved (a short
    live stream) does not fill a view framed on its few poses."""
    diagonal = 0.0 if bounds is None else float(np.linalg.norm(np.asarray(bounds[1]) - np.asarray(bounds[0])))
    return round(min(FRUSTUM_MAX_M, FRUSTUM_SHARE * max(diagonal, 2 * MIN_FRAME_RADIUS_M)), 3)


def frustum_segments(T_world_cam: np.ndarray, K: np.ndarray, width: int, height: int,
                     depth: float = 0.15) -> np.ndarray:
    """Wireframe pyramids of cameras as line segments.

    Args:
        T_world_cam: (N, 4, 4) camera-to-world poses. K: (3, 3). width, height: image size.
        depth: distance of the image plane from the centre (metres).
    Returns:
        (N * 8, 2, 3) float32 segment end points in the world frame.
    """
    T = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
    corners_px = np.array([[0, 0], [width, 0], [width, height], [0, height]], dtype=np.float64)
    rays = np.stack([(corners_px[:, 0] - K[0, 2]) / K[0, 0], (corners_px[:, 1] - K[1, 2]) / K[1, 1],
                     np.ones(4)], axis=1) * depth                                       # (4, 3)
    corners = np.einsum("nij,kj->nki", T[:, :3, :3], rays) + T[:, None, :3, 3]      # (N, 4, 3)
    centre = np.broadcast_to(T[:, None, :3, 3], corners.shape)
    spokes = np.stack([centre, corners], axis=2)                                     # (N, 4, 2, 3)
    rim = np.stack([corners, np.roll(corners, -1, axis=1)], axis=2)                  # (N, 4, 2, 3)
    return np.concatenate([spokes, rim], axis=1).reshape(-1, 2, 3).astype(np.float32)


@dataclass(frozen=True)
class MeshChunk:
    """Part of a map's mesh inside one CHUNK_SIZE_M cube (map frame)."""

    vertices: np.ndarray
    """(V, 3) float32."""
    faces: np.ndarray
    """(F, 3) int32, indices into ``vertices``."""
    colors: np.ndarray
    """(V, 3) uint8."""


ChunkKey = tuple[int, int, int]


def mesh_chunks(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None,
                chunk_size: float = CHUNK_SIZE_M) -> dict[ChunkKey, MeshChunk]:
    """Cut a mesh into cubes by face centroid; each chunk gets its own compact vertex list.

    Args:
        vertices: (V, 3). faces: (F, 3) int. colors: (V, 3) uint8 or None (grey).
    Returns:
        {(i, j, k) cube index: chunk}.
    """
    vertices = np.asarray(vertices, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int64)
    if colors is None:
        colors = np.full((len(vertices), 3), 180, dtype=np.uint8)
    colors = np.asarray(colors, dtype=np.uint8)[:, :3]
    if len(faces) == 0:
        return {}
    keys = np.floor(vertices[faces].mean(axis=1) / chunk_size).astype(np.int64)       # (F, 3)
    unique_keys, face_group = np.unique(keys, axis=0, return_inverse=True)
    face_group = face_group.reshape(-1)
    order = np.argsort(face_group, kind="stable")
    bounds = np.searchsorted(face_group[order], np.arange(len(unique_keys) + 1))
    chunks = {}
    for g, key in enumerate(unique_keys):
        group_faces = faces[order[bounds[g]:bounds[g + 1]]]
        used, local = np.unique(group_faces, return_inverse=True)
        chunks[tuple(int(v) for v in key)] = MeshChunk(
            vertices=vertices[used], faces=local.reshape(-1, 3).astype(np.int32), colors=colors[used])
    return chunks


def chunk_changed(old: MeshChunk | None, new: MeshChunk) -> bool:
    """True when the chunk must be resent: other triangles, or vertices/colours that moved
    more than VERTEX_TOLERANCE_M / COLOR_TOLERANCE (mapping nudges every vertex slightly)."""
    if old is None or old.faces.shape != new.faces.shape or old.vertices.shape != new.vertices.shape:
        return True
    if not np.array_equal(old.faces, new.faces):
        return True
    if np.abs(old.vertices - new.vertices).max(initial=0.0) > VERTEX_TOLERANCE_M:
        return True
    return int(np.abs(old.colors.astype(np.int16) - new.colors.astype(np.int16)).max(initial=0)) > COLOR_TOLERANCE


def key_text(key: ChunkKey) -> str:
    """A chunk key as a scene-node name part (``c_<i>_<j>_<k>``, minus as ``m``)."""
    return "_".join(str(v).replace("-", "m") for v in key)


@dataclass(frozen=True)
class ViewerCamera:
    """A browser's viewpoint, as the render endpoint wants it."""

    T_world_cam: np.ndarray
    """(4, 4) float64 camera-to-world, OpenCV axes."""
    fov_y: float
    """vertical field of view, radians."""
    width: int
    height: int

    def intrinsics(self, width: int | None = None) -> tuple[float, float, float, float, int, int]:
        """(fx, fy, cx, cy, width, height) for this view at ``width`` pixels (aspect kept)."""
        w = width or self.width
        h = max(1, round(w * self.height / max(1, self.width)))
        f = 0.5 * h / np.tan(0.5 * self.fov_y)
        return f, f, w / 2.0, h / 2.0, w, h


@dataclass
class MapView:
    """What the browsers have of one map, and what is stale."""

    pending_chunks: dict[ChunkKey, MeshChunk] | None = None
    """Chunks of the newest mesh not yet pushed (map frame)."""
    sent_chunks: dict[ChunkKey, MeshChunk] = field(default_factory=dict)
    bounds: tuple[np.ndarray, np.ndarray] | None = None
    """(lo, hi) of the newest mesh in the map frame."""
    pose_dirty: bool = True
    keyframes_dirty: bool = False
    bounds_dirty: bool = False


@dataclass
class AgentView:
    """What the browsers have of one agent's trajectory and camera."""

    sent_blocks: int = 0
    """Trajectory blocks (of TRAJECTORY_BLOCK poses) that are complete and sent."""
    dirty: bool = False
    camera_dirty: bool = False


@dataclass(frozen=True)
class TrajectoryBlock:
    """One block of an agent's path to (re)send as the scene node ``part_<part>``."""

    part: int
    segments: np.ndarray
    """(S, 2, 3) float32 world end points (none across a jump into a map started after a
    tracking failure)."""
    colors: np.ndarray
    """(S, 3) uint8, one per segment."""


@dataclass(frozen=True)
class ChunkUpdate:
    """How to bring a map's chunks in the browsers up to its newest mesh."""

    removed: list[ChunkKey]
    changed: dict[ChunkKey, MeshChunk]
    skipped: int
    """Chunks that changed too little to resend."""


class ViewerSession:
    """One session as the viewer shows it: the events' fold plus the viewer's bookkeeping."""

    def __init__(self, session_id: str) -> None:
        self.session_id = session_id
        self.scene = SessionState(keep_meshes=False)
        self.maps: dict[int, MapView] = {}
        self.agents: dict[int, AgentView] = {}
        self.loops_dirty = False
        self.last_update = 0.0
        self.last_mesh_update = 0.0
        self.framed_size: float | None = None
        """Diagonal (metres) of the bounds the browsers were last framed on; None: frame it next."""
        self.phase: str | None = None
        """The run's phase, or how it ended."""
        self.status_dirty = False

    def map(self, map_id: int) -> MapView:
        return self.maps.setdefault(int(map_id), MapView())

    def agent(self, agent: int) -> AgentView:
        return self.agents.setdefault(int(agent), AgentView())

    # -- events ------------------------------------------------------------------------------

    def apply(self, event: object) -> None:
        """Fold in one event and mark what it made stale (no viser here)."""
        change = self.scene.apply(event)
        for map_id in change.maps:
            self.map(map_id)
        for map_id in change.moved | ({change.submap} - {None}):
            self.map(map_id).pose_dirty = True
        if change.moved:  # what was tracked in a moved map is redrawn where the map puts it now
            self.redraw_trajectories(self.scene.tracks.agents_in(change.moved))
            self.loops_dirty = self.loops_dirty or bool(self.scene.loops)
        if change.frame is not None:
            view = self.agent(change.frame[0])
            if change.retracked_slot is not None:  # the same frame again: resend its block
                view.sent_blocks = min(view.sent_blocks, change.retracked_slot // TRAJECTORY_BLOCK)
            view.dirty = view.camera_dirty = True
        for map_id in change.keyframes:
            self.map(map_id).keyframes_dirty = True
        if change.mesh is not None:
            map_id, mesh = change.mesh
            view = self.map(map_id)
            view.pending_chunks = mesh_chunks(mesh.vertices, mesh.faces, mesh.colors)
            if len(mesh.vertices):
                view.bounds = (mesh.vertices.min(axis=0), mesh.vertices.max(axis=0))
                view.bounds_dirty = True
        self.loops_dirty = self.loops_dirty or change.loop
        if change.stats is not None or change.phase is not None:
            self.status_dirty = True
        if change.phase is not None:  # with the end-of-run step that runs, where one does
            self.phase = change.phase if change.step is None else f"{change.phase}: {change.step.replace('_', ' ')}"
        if change.finished is not None:
            self.phase, self.status_dirty = change.finished.status, True
            self.framed_size = None  # framed on what it ended with

    def load_finished(self, chunks: dict[ChunkKey, MeshChunk] | None,
                      trajectory_positions: dict[int, np.ndarray]) -> None:
        """A finished session read back from disk: its mesh as map 0 (world frame), each
        agent's camera centres as frames of map 0."""
        if chunks is not None:
            self.map(0).pending_chunks = chunks
        for agent, positions in sorted(trajectory_positions.items()):
            if positions is None or not len(positions):
                continue
            for index, position in enumerate(np.asarray(positions, dtype=np.float64).reshape(-1, 3)):
                T = np.eye(4)
                T[:3, 3] = position
                self.scene.tracks.add(agent, index, 0.0, 0, T)
            self.agent(agent).dirty = True

    def redraw_trajectories(self, agents=None) -> None:
        """Resend every block of these agents' trajectories (all agents by default)."""
        for agent, view in self.agents.items():
            if agents is None or agent in agents:
                view.sent_blocks = 0
                view.dirty = view.camera_dirty = True

    def resend_meshes(self) -> None:
        """Send every chunk again (in another colouring)."""
        for view in self.maps.values():
            if view.pending_chunks is None:
                view.pending_chunks = view.sent_chunks
            view.sent_chunks = {}
        self.last_mesh_update = 0.0

    def shown(self) -> None:
        """The session was selected: everything pending goes at the next flush, framed anew."""
        self.last_update = self.last_mesh_update = 0.0
        self.framed_size = None
        self.status_dirty = True

    # -- reading -----------------------------------------------------------------------------

    @property
    def stats(self) -> StatsEvent | None:
        return self.scene.stats

    @property
    def loops(self) -> list:
        return self.scene.loops

    @property
    def pose_count(self) -> int:
        return len(self.scene.tracks)

    @property
    def K(self) -> np.ndarray | None:
        """Intrinsics of the first agent that reported them (for keyframe frustums)."""
        cameras = self.scene.cameras
        return cameras[min(cameras)].K if cameras else None

    @property
    def image_size(self) -> tuple[int, int] | None:
        cameras = self.scene.cameras
        return (cameras[min(cameras)].width, cameras[min(cameras)].height) if cameras else None

    def T_world_map(self, map_id: int) -> np.ndarray:
        return self.scene.maps.T_world_map(map_id)

    def world_positions(self, agent: int) -> np.ndarray:
        """(N, 3) world positions now of an agent's frames, in arrival order."""
        return self.scene.tracks.world_positions(agent)

    def loop_points(self) -> np.ndarray:
        """(L, 2, 3) world end points of the loop edges as they are drawn now."""
        return self.scene.loop_points()

    def camera(self, agent: int) -> tuple[np.ndarray, np.ndarray | None] | None:
        """(T_world_cam (4, 4), thumbnail) of an agent's newest frame, or None."""
        T = self.scene.camera_pose(agent)
        return None if T is None else (rigid(T), self.scene.latest[agent][1])

    def keyframe_frusta(self, map_id: int) -> np.ndarray | None:
        """(K * 8, 2, 3) keyframe frustum segments of a map in its frame, or None (no
        keyframes, or no intrinsics yet)."""
        poses = self.scene.keyframe_poses(map_id)
        if not len(poses) or self.K is None:
            return None
        w, h = self.image_size
        return frustum_segments(poses, self.K, w, h, depth=0.1)

    def trajectory_blocks(self, agent: int, by_map: bool) -> list[TrajectoryBlock]:
        """The open blocks of one agent's path (complete blocks stay as they are in the browser
        until a map they pass through moves); counts the blocks it completes as sent. No segment
        joins a frame to one in a map that started after a tracking failure: such a map floats
        apart until a loop joins it. ``by_map``: coloured by map, else in the agent's colour."""
        view = self.agents[agent]
        positions = self.world_positions(agent).astype(np.float32)
        maps = self.scene.tracks.map_ids(agent)
        blocks = []
        first_open = view.sent_blocks * TRAJECTORY_BLOCK
        for start in range(first_open, max(len(positions) - 1, first_open), TRAJECTORY_BLOCK):
            stop = min(start + TRAJECTORY_BLOCK + 1, len(positions))
            if stop - start < 2:
                break
            keep = np.array([maps[i] == maps[i + 1]
                             or self.scene.reasons.get(int(maps[i + 1]), "start") != "tracking_failure"
                             for i in range(start, stop - 1)], dtype=bool)
            segments = np.stack([positions[start:stop - 1], positions[start + 1:stop]], axis=1)[keep]
            if by_map:
                colors = np.array([map_color(int(m)) for m in maps[start + 1:stop]], dtype=np.uint8)[keep]
            else:
                colors = np.broadcast_to(np.array(agent_color(agent), dtype=np.uint8), (len(segments), 3))
            blocks.append(TrajectoryBlock(start // TRAJECTORY_BLOCK, segments, colors))
            if stop - start == TRAJECTORY_BLOCK + 1:
                view.sent_blocks += 1
        return blocks

    def take_chunk_update(self, map_id: int) -> ChunkUpdate | None:
        """The chunks to remove and (re)send for a map's pending mesh, counted as sent; None
        when nothing is pending."""
        view = self.maps[map_id]
        chunks = view.pending_chunks
        if chunks is None:
            return None
        view.pending_chunks = None
        removed = [key for key in view.sent_chunks if key not in chunks]
        for key in removed:
            del view.sent_chunks[key]
        changed = {key: chunk for key, chunk in chunks.items() if chunk_changed(view.sent_chunks.get(key), chunk)}
        view.sent_chunks.update(changed)
        return ChunkUpdate(removed, changed, len(chunks) - len(changed))

    def status_text(self) -> str:
        """The panel's line; its frames/s is the status API's (the session manager forwards
        StatsEvents with that value), so page and viewer agree."""
        agents = max(1, len(self.agents))
        phase = f" ({self.phase})" if self.phase else ""
        text = f"**{self.session_id}**{phase}: {_counted(self.pose_count, 'pose')}, " \
               f"{_counted(len(self.maps), 'map')}, {_counted(len(self.loops), 'loop')}"
        if agents > 1:
            text += f", {agents} agents"
        if self.stats is not None:
            text += f", {self.stats.fps:.1f} frames/s"
        return text

    def bounds_to_frame(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The bounds to frame the browsers on now: when the session is first shown and
        whenever its extent has grown by REFRAME_GROWTH since (counted as framed); else None."""
        bounds = scene_bounds(self)
        if bounds is None:
            return None
        size = float(np.linalg.norm(bounds[1] - bounds[0]))
        if self.framed_size is not None and size <= REFRAME_GROWTH * max(self.framed_size, MIN_FRAME_RADIUS_M):
            return None
        self.framed_size = size
        return bounds


def scene_bounds(state: ViewerSession) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo, hi) world corners around the session's trajectories and mesh chunks, or None if empty."""
    points = [np.zeros((0, 3))] + [state.world_positions(agent) for agent in state.agents]
    for map_id, view in state.maps.items():
        T = state.T_world_map(map_id)
        chunks = {**view.sent_chunks, **(view.pending_chunks or {})}
        for chunk in list(chunks.values())[:200]:
            points.append(chunk.vertices[:: max(1, len(chunk.vertices) // 50)] @ T[:3, :3].T + T[:3, 3])
    points = np.concatenate(points)
    if len(points) == 0:
        return None
    return points.min(axis=0), points.max(axis=0)
