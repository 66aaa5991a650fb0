"""The live 3D viewer: a viser server in the API process, fed with the workers' events.

Scene tree (slash paths; a parent's pose and visibility apply to its children)::

    /sessions/<id>                          one session (only the selected one is visible)
    /sessions/<id>/meshes/map_<m>           posed at T_world_map
    /sessions/<id>/meshes/map_<m>/c_<i>_<j>_<k>   a mesh chunk (map frame, vertex colours)
    /sessions/<id>/meshes/map_<m>/bounds    the map's extent in its colour (sessions with several maps)
    /sessions/<id>/keyframes/map_<m>        posed at T_world_map: keyframe frustums in the map's colour
    /sessions/<id>/trajectory/agent_<a>/part_<k>   an agent's camera path in its colour, in blocks
                                            of TRAJECTORY_BLOCK poses
    /sessions/<id>/camera/frustum[_<a>]     each agent's current camera frustum with its thumbnail
    /sessions/<id>/loops/edges              loop edges between the matched keyframes

Several agents (collaborative sessions) share the scene: each has its own trajectory colour
and camera frustum; map ids are unique across agents. Everything that belongs to a map is kept
in that map's frame: its mesh, its keyframes, the trajectory frames tracked in it (and so the
loop edges that end at them). A ``PosesUpdatedEvent`` (loop closure, final refinement) moves
the map nodes, which moves meshes and keyframes without resending them, and redraws the
trajectories and loop edges at ``T_world_map_new @ inv(T_world_map_at_tracking)``. A map's
first placement (its SubmapEvent, which comes after the pose of the frame that started it)
moves nothing. A loop edge ends at the two frames in the trajectories; frames the viewer never
saw are drawn at the LoopEvent's poses, which are kept in their maps' frames from the
PosesUpdatedEvent that follows the loop (the event's poses are already optimised ones).

Events only update the adapter's pending state (cheap, in the supervisor thread); a flusher
thread pushes that state to viser at most ``UPDATE_HZ`` times a second per session and meshes
at most ``MESH_HZ`` times a second, so a fast run cannot flood the browsers. Only parts that
changed are sent again: mesh chunks are kept in their map's frame (a loop correction moves the
map node, not the vertices) and a chunk is resent only when its triangles or colours changed
by more than a few millimetres; finished trajectory blocks are never resent. Only the selected
session streams; another session's pending state is sent when it is selected.

Only the API's token-checked relay (``GET /viewer`` WebSocket, ``server.routes_pages``) may
talk to viser: the relay sends a secret made at start in the ``RELAY_HEADER`` header, and any
other WebSocket on viser's port (any local user, or anyone when it is bound to a public
interface) is closed before viser sends it a byte of the scene. viser's port still serves
viser's own client files, which hold no data.

The browsers show the session our page shows (``select``, also for a session that has sent
no event yet) and are framed on it: the camera looks at the session's bounds from a distance
at which they fill the view, when it is shown, whenever its extent has grown by half since
(a live map grows from one camera pose to a room), and once more when it ends.

Conventions as viser's: OpenCV camera axes, quaternions ``wxyz``, metres.
"""

from __future__ import annotations

import colorsys
import contextlib
import io
import secrets
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from server.tracks import inverse, rigid, transform_points
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
    matrix_to_quat_wxyz,
    quat_wxyz_to_matrix,
)

UPDATE_HZ = 5.0
MESH_HZ = 1.0
CHUNK_SIZE_M = 1.0
"""Edge of the cubes a map's mesh is cut into (metres): the unit that is resent when it changes."""
VERTEX_TOLERANCE_M = 0.005
COLOR_TOLERANCE = 8
TRAJECTORY_BLOCK = 256
NO_SESSION = "(no session yet)"
LAYERS = ("meshes", "trajectory", "camera", "keyframes", "loops")
FRAME_DIRECTION = np.array([0.45, -0.6, 0.55]) / np.linalg.norm([0.45, -0.6, 0.55])
"""From the centre of a framed session towards the browser's camera: above it, from one side."""
MIN_FRAME_RADIUS_M = 0.25
"""Smallest radius framed (a session of one camera pose still shows its surroundings)."""
REFRAME_GROWTH = 1.5
"""A session is framed again when its bounds' diagonal has grown by this factor."""


RELAY_HEADER = "X-Voxfusion-Relay"
"""Header by which the API's relay proves itself to viser (its value: ``ViewerAdapter.relay_secret``)."""
RELAY_ONLY_CLOSE_CODE = 1008
"""WebSocket close code (policy violation) for a direct connection to viser's port."""

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


def _wxyz(T: np.ndarray) -> np.ndarray:
    import torch

    return matrix_to_quat_wxyz(torch.as_tensor(np.asarray(T)[:3, :3], dtype=torch.float64)).numpy()


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


def mesh_chunks(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None,
                chunk_size: float = CHUNK_SIZE_M) -> dict[tuple[int, int, int], MeshChunk]:
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
class _MapState:
    T_world_map: np.ndarray = field(default_factory=lambda: np.eye(4))
    placed: bool = False
    """An event has said where the map is (until then T_world_map is the identity)."""
    agent: int | None = None
    reason: str = "start"
    """Why the map started (SubmapEvent.reason)."""
    keyframe_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    """(K, 4, 4) keyframe poses in the map's frame."""
    pending_chunks: dict | None = None
    """Chunks of the newest mesh not yet pushed (map frame)."""
    sent_chunks: dict = field(default_factory=dict)
    bounds: tuple[np.ndarray, np.ndarray] | None = None
    """(lo, hi) of the newest mesh in the map frame."""
    pose_dirty: bool = True
    keyframes_dirty: bool = False
    bounds_dirty: bool = False


@dataclass
class _AgentTrack:
    """One agent's tracked frames in arrival order, each in the frame of the map it was tracked in."""

    points: list[np.ndarray] = field(default_factory=list)
    """(3,) camera centres in their map's frame."""
    maps: list[int] = field(default_factory=list)
    slots: dict[int, int] = field(default_factory=dict)
    """frame index -> position in ``points``."""
    sent_blocks: int = 0
    """Trajectory blocks (of TRAJECTORY_BLOCK poses) that are complete and sent."""
    dirty: bool = False
    latest: tuple[int, np.ndarray, np.ndarray | None] | None = None
    """(map id, (4, 4) T_map_cam, thumbnail) of the newest frame."""
    camera_dirty: bool = False
    K: np.ndarray | None = None
    image_size: tuple[int, int] | None = None


@dataclass
class _Loop:
    """A loop edge: two keyframes, each found by (agent, frame index) in the trajectories (so it
    moves with them), else at its event pose. The event's poses are those after the loop's
    optimisation, whose map poses come in the PosesUpdatedEvent that follows: until then they
    are world points; from then on they are kept in their maps' frames."""

    agent: int
    frame_index: int
    map_id: int
    point: np.ndarray
    match_agent: int
    match_frame_index: int
    match_map: int
    match_point: np.ndarray
    anchored: bool = False
    """``point``/``match_point`` are in their maps' frames (else in the world frame)."""


@dataclass
class _SessionState:
    session_id: str
    maps: dict[int, _MapState] = field(default_factory=dict)
    agents: dict[int, _AgentTrack] = field(default_factory=dict)
    loops: list[_Loop] = field(default_factory=list)
    loops_dirty: bool = False
    last_update: float = 0.0
    last_mesh_update: float = 0.0
    framed_size: float | None = None
    """Diagonal (metres) of the bounds the browsers were last framed on; None: frame it next."""
    stats: StatsEvent | None = None
    phase: str | None = None
    status_dirty: bool = False

    def map(self, map_id: int) -> _MapState:
        return self.maps.setdefault(int(map_id), _MapState())

    def agent(self, agent: int) -> _AgentTrack:
        return self.agents.setdefault(int(agent), _AgentTrack())

    @property
    def pose_count(self) -> int:
        return sum(len(track.points) for track in self.agents.values())

    @property
    def K(self) -> np.ndarray | None:
        """Intrinsics of the first agent that reported them (for keyframe frustums)."""
        return next((t.K for _, t in sorted(self.agents.items()) if t.K is not None), None)

    @property
    def image_size(self) -> tuple[int, int] | None:
        return next((t.image_size for _, t in sorted(self.agents.items()) if t.K is not None), None)

    def world_point(self, map_id: int, point_map: np.ndarray) -> np.ndarray:
        T = self.maps[map_id].T_world_map if map_id in self.maps else np.eye(4)
        return T[:3, :3] @ point_map + T[:3, 3]

    def frame_position(self, agent: int, frame_index: int) -> np.ndarray | None:
        """World position now of an agent's tracked frame, or None if it was not seen."""
        track = self.agents.get(agent)
        slot = None if track is None else track.slots.get(frame_index)
        if slot is None:
            return None
        return self.world_point(track.maps[slot], track.points[slot])

    def world_positions(self, agent: int) -> np.ndarray:
        """(N, 3) world positions now of an agent's frames, in arrival order."""
        track = self.agents[agent]
        if not track.points:
            return np.zeros((0, 3))
        points = np.asarray(track.points, dtype=np.float64)
        maps = np.asarray(track.maps)
        out = np.empty_like(points)
        for map_id in np.unique(maps):
            rows = maps == map_id
            out[rows] = transform_points(self.maps[int(map_id)].T_world_map if int(map_id) in self.maps
                                         else np.eye(4), points[rows])
        return out


@dataclass
class ViewerStats:
    """Counters for the benchmark: how often the browsers were updated."""

    updates: int = 0
    mesh_updates: int = 0
    chunks_sent: int = 0
    chunks_skipped: int = 0
    events: int = 0


class ViewerAdapter:
    """Owns the viser server. ``handle_event`` may be called from any thread."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080) -> None:
        self._host = host
        self._requested_port = port
        self._server = None
        self._lock = threading.RLock()
        self._sessions: dict[str, _SessionState] = {}
        self._handles: dict[str, object] = {}
        self._selected: str | None = None
        self._user_selected = False
        self._layers = {name: True for name in LAYERS}
        self._hidden_maps: set[int] = set()
        self._tint_by_map = False
        self._trajectory_by_map = False
        self._follow = False
        self._sessions_changed = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.stats = ViewerStats()
        self.relay_secret = secrets.token_urlsafe(32)
        """What the relay sends in RELAY_HEADER; nobody else knows it."""
        self.refused_connections = 0

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self) -> None:
        import viser

        # viser prints a box with its own URL, which a newcomer took for the one to open: the
        # way in is our page (its /viewer relay), whose URL the CLI prints.
        with contextlib.redirect_stdout(io.StringIO()):
            self._server = viser.ViserServer(host=self._host, port=self._requested_port, verbose=False)
        self._admit_relay_only()
        self._server.scene.set_up_direction("+z")
        self._server.gui.configure_theme(show_share_button=False, brand_color=(40, 110, 200), control_width="small")
        # Docked beside the scene instead of floating over it: the middle of the view, where
        # a session is framed, is then the middle of what one sees.
        self._server.gui.main_panel.dock_right()
        self._build_gui()
        self._thread = threading.Thread(target=self._flush_loop, name="viewer-flush", daemon=True)
        self._thread.start()

    def _admit_relay_only(self) -> None:
        """Close every WebSocket on viser's port that does not carry the relay's secret.

        viser has no hook for this, so this reaches into its WebSocket server: a connect
        callback there runs before viser sends a client anything, and the server's raw
        connections carry the request headers. If a viser upgrade moves either, the check
        fails closed (every connection is refused, and the viewer tests say so)."""
        websock = self._server._websock_server
        secret = self.relay_secret.encode()

        async def check(connection) -> None:
            raw = getattr(websock, "_live_connections", {}).get(connection.client_id)
            request = getattr(raw, "request", None)
            given = request.headers.get(RELAY_HEADER, "") if request is not None else ""
            if secrets.compare_digest(given.encode(), secret):
                return
            self.refused_connections += 1
            if raw is None:
                raise ConnectionRefusedError("viser: cannot check a connection; refused")
            await raw.close(RELAY_ONLY_CLOSE_CODE, "connect through the voxfusion API's /viewer")

        websock.on_client_connect(check)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._server is not None:
            self._server.stop()
            self._server = None

    @property
    def port(self) -> int | None:
        return None if self._server is None else self._server.get_port()

    @property
    def running(self) -> bool:
        return self._server is not None

    def client_count(self) -> int:
        return 0 if self._server is None else len(self._server.get_clients())

    # -- GUI ---------------------------------------------------------------------------------

    def _build_gui(self) -> None:
        gui = self._server.gui
        self._session_dropdown = gui.add_dropdown("Session", [NO_SESSION], initial_value=NO_SESSION)
        self._session_dropdown.on_update(lambda _: self._on_select(self._session_dropdown.value))
        self._follow_box = gui.add_checkbox("Follow camera", False)
        self._follow_box.on_update(lambda _: self._set_follow(self._follow_box.value))
        with gui.add_folder("Layers"):
            for name in LAYERS:
                box = gui.add_checkbox(name.capitalize(), True)
                box.on_update(lambda _, n=name, b=box: self._set_layer(n, b.value))
            self._tint_box = gui.add_checkbox("Colour meshes by map", False)
            self._tint_box.on_update(lambda _: self._set_tint(self._tint_box.value))
            self._trajectory_tint_box = gui.add_checkbox("Colour trajectories by map", False,
                                                         hint="otherwise each agent (camera) has its own colour")
            self._trajectory_tint_box.on_update(lambda _: self._set_trajectory_tint(self._trajectory_tint_box.value))
        self._maps_folder = gui.add_folder("Maps")
        self._map_boxes: dict[int, object] = {}
        self._status_md = gui.add_markdown("Waiting for a session.")

    def _on_select(self, value: str) -> None:
        with self._lock:
            if value == NO_SESSION or value not in self._sessions or value == self._selected:
                return
            self._user_selected = True
            self._select(value)

    def has_session(self, session_id: str) -> bool:
        with self._lock:
            return session_id in self._sessions

    @property
    def selected(self) -> str | None:
        """The session the browsers show."""
        with self._lock:
            return self._selected

    def select(self, session_id: str) -> None:
        """Show ``session_id`` in every browser (from our page, which names sessions that
        exist). One that has sent no event yet (queued, starting) gets an empty scene that
        fills as its events come, so the viewer follows a session the moment it is created."""
        with self._lock:
            if self._server is None:
                return
            self._user_selected = True
            if session_id not in self._sessions:
                self._sessions[session_id] = _SessionState(session_id)
                self._session_dropdown.options = list(self._sessions)
            self._select(session_id)

    def _select(self, session_id: str) -> None:
        """Show ``session_id`` only; everything it has pending is flushed at the next tick."""
        self._selected = session_id
        for sid in self._sessions:
            handle = self._handles.get(f"/sessions/{sid}")
            if handle is not None:
                handle.visible = sid == session_id
        state = self._sessions[session_id]
        state.last_update = state.last_mesh_update = 0.0
        state.framed_size = None
        state.status_dirty = True
        self._ensure_root(session_id).visible = True
        self._refresh_map_boxes()
        if self._session_dropdown.value != session_id:
            self._session_dropdown.value = session_id

    def _set_follow(self, value: bool) -> None:
        self._follow = bool(value)

    def _set_layer(self, name: str, value: bool) -> None:
        with self._lock:
            self._layers[name] = bool(value)
            for sid in self._sessions:
                handle = self._handles.get(f"/sessions/{sid}/{name}")
                if handle is not None:
                    handle.visible = bool(value)

    def _set_tint(self, value: bool) -> None:
        with self._lock:
            self._tint_by_map = bool(value)
            for state in self._sessions.values():
                for map_state in state.maps.values():
                    # Resend every chunk in the new colouring.
                    if map_state.pending_chunks is None:
                        map_state.pending_chunks = map_state.sent_chunks
                    map_state.sent_chunks = {}
                state.last_mesh_update = 0.0

    def _set_trajectory_tint(self, value: bool) -> None:
        with self._lock:
            self._trajectory_by_map = bool(value)
            for state in self._sessions.values():
                self._redraw_trajectories(state)

    @staticmethod
    def _redraw_trajectories(state: _SessionState, agents=None) -> None:
        """Resend every block of these agents' trajectories (all agents by default)."""
        for agent, track in state.agents.items():
            if agents is None or agent in agents:
                track.sent_blocks = 0
                track.dirty = track.camera_dirty = True

    def _refresh_map_boxes(self) -> None:
        state = self._sessions.get(self._selected) if self._selected else None
        wanted = sorted(state.maps) if state else []
        for map_id in list(self._map_boxes):
            if map_id not in wanted:
                self._map_boxes.pop(map_id).remove()
        with self._maps_folder:
            for map_id in wanted:
                if map_id not in self._map_boxes:
                    r, g, b = map_color(map_id)
                    box = self._server.gui.add_checkbox(f"Map {map_id}", map_id not in self._hidden_maps,
                                                        hint=f"colour #{r:02x}{g:02x}{b:02x}")
                    box.on_update(lambda _, m=map_id, bx=box: self._set_map_visible(m, bx.value))
                    self._map_boxes[map_id] = box

    def _set_map_visible(self, map_id: int, visible: bool) -> None:
        with self._lock:
            if visible:
                self._hidden_maps.discard(map_id)
            else:
                self._hidden_maps.add(map_id)
            for sid in self._sessions:
                for layer in ("meshes", "keyframes"):
                    handle = self._handles.get(f"/sessions/{sid}/{layer}/map_{map_id}")
                    if handle is not None:
                        handle.visible = visible

    # -- events (any thread) -----------------------------------------------------------------

    def handle_event(self, session_id: str, event: object) -> None:
        """Fold one runtime event into the session's pending state (no viser calls here)."""
        with self._lock:
            self.stats.events += 1
            state = self._sessions.get(session_id)
            if state is None:
                state = self._sessions[session_id] = _SessionState(session_id)
                self._sessions_changed = True
            if isinstance(event, PoseEvent):
                self._on_pose(state, event)
            elif isinstance(event, KeyframeEvent):
                map_state = state.map(event.map_id)
                T_map_cam = inverse(map_state.T_world_map) @ rigid(event.T_world_cam)
                map_state.keyframe_poses = np.concatenate([map_state.keyframe_poses, T_map_cam[None]])
                map_state.keyframes_dirty = True
            elif isinstance(event, MapUpdateEvent):
                self._on_map_update(state, event)
            elif isinstance(event, SubmapEvent):
                map_state = state.map(event.map_id)
                map_state.agent, map_state.reason = int(event.agent), str(event.reason)
                self._move_map(state, event.map_id, event.T_world_map)
                map_state.pose_dirty = True
            elif isinstance(event, PosesUpdatedEvent):
                self._on_poses_updated(state, event)
            elif isinstance(event, LoopEvent):
                self._on_loop(state, event)
            elif isinstance(event, StatsEvent):
                state.stats, state.status_dirty = event, True
            elif isinstance(event, PhaseEvent):
                state.phase, state.status_dirty = event.phase, True
            elif isinstance(event, FinishedEvent):
                state.phase, state.status_dirty = event.status, True
                state.framed_size = None  # framed on what it ended with

    def _move_map(self, state: _SessionState, map_id: int, T_world_map) -> bool:
        """Place a map at ``T_world_map``: its nodes move, and the trajectory frames tracked in
        it and the loop edges are redrawn where the map now puts them. True if it moved.

        The first placement of a map (its SubmapEvent comes after the pose of the frame that
        started it) moves nothing: what was seen in the map stays where it was reported."""
        map_state = state.map(map_id)
        T = rigid(T_world_map)
        if not map_state.placed:
            map_state.placed = True
            T_map_world = inverse(T)
            for track in state.agents.values():
                for i, m in enumerate(track.maps):
                    if m == map_id:
                        track.points[i] = T_map_world[:3, :3] @ track.points[i] + T_map_world[:3, 3]
                if track.latest is not None and track.latest[0] == map_id:
                    track.latest = (map_id, T_map_world @ track.latest[1], track.latest[2])
            map_state.keyframe_poses = T_map_world[None] @ map_state.keyframe_poses
            map_state.T_world_map = T
            map_state.pose_dirty = True
            return False
        if np.allclose(T, map_state.T_world_map, atol=1e-9):
            return False
        map_state.T_world_map = T
        map_state.pose_dirty = True
        moved_agents = {agent for agent, track in state.agents.items() if map_id in set(track.maps)}
        self._redraw_trajectories(state, moved_agents)
        state.loops_dirty = state.loops_dirty or bool(state.loops)
        return True

    def _on_pose(self, state: _SessionState, event: PoseEvent) -> None:
        map_state = state.map(event.map_id)
        if map_state.agent is None:
            map_state.agent = int(event.agent)
        track = state.agent(event.agent)
        T_map_cam = inverse(map_state.T_world_map) @ rigid(event.T_world_cam)
        slot = track.slots.get(int(event.frame_index))
        if slot is None:
            track.slots[int(event.frame_index)] = len(track.points)
            track.points.append(T_map_cam[:3, 3].copy())
            track.maps.append(int(event.map_id))
        else:  # the same frame again (re-tracked): replace it, resend its block
            track.points[slot], track.maps[slot] = T_map_cam[:3, 3].copy(), int(event.map_id)
            track.sent_blocks = min(track.sent_blocks, slot // TRAJECTORY_BLOCK)
        track.latest = (int(event.map_id), T_map_cam, event.thumbnail)
        track.dirty = track.camera_dirty = True
        if event.K is not None and event.image_size is not None:
            track.K, track.image_size = np.asarray(event.K), tuple(event.image_size)

    def _on_map_update(self, state: _SessionState, event: MapUpdateEvent) -> None:
        map_state = state.map(event.map_id)
        T_world_map = rigid(event.T_world_map)
        self._move_map(state, event.map_id, T_world_map)
        T_map_world = inverse(T_world_map)
        if len(event.keyframe_poses):
            map_state.keyframe_poses = T_map_world[None] @ np.asarray(event.keyframe_poses, dtype=np.float64)
            map_state.keyframes_dirty = True
        if event.mesh_vertices is not None and event.mesh_faces is not None:
            # Into the map frame, so that a later correction of T_world_map moves the node only.
            vertices = transform_points(T_map_world, event.mesh_vertices)
            map_state.pending_chunks = mesh_chunks(vertices, event.mesh_faces, event.mesh_colors)
            if len(vertices):
                map_state.bounds = (vertices.min(axis=0), vertices.max(axis=0))
                map_state.bounds_dirty = True

    def _on_poses_updated(self, state: _SessionState, event: PosesUpdatedEvent) -> None:
        for map_id, agent in (event.agents or {}).items():
            state.map(map_id).agent = int(agent)
        for map_id, T in (event.map_poses or {}).items():
            self._move_map(state, int(map_id), T)
        for loop in state.loops:  # the loops this optimisation closed: their poses are in these placements
            if not loop.anchored:
                loop.point = self._to_map(state, loop.map_id, loop.point)
                loop.match_point = self._to_map(state, loop.match_map, loop.match_point)
                loop.anchored = True
        for map_id, poses in (event.keyframe_poses or {}).items():
            map_state = state.map(map_id)
            poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
            map_state.keyframe_poses = inverse(map_state.T_world_map)[None] @ poses
            map_state.keyframes_dirty = True

    @staticmethod
    def _to_map(state: _SessionState, map_id: int, point: np.ndarray) -> np.ndarray:
        return transform_points(inverse(state.map(map_id).T_world_map), point[None])[0]

    def _on_loop(self, state: _SessionState, event: LoopEvent) -> None:
        state.map(event.map_id)
        state.map(event.match_map)
        state.loops.append(_Loop(
            int(event.agent), int(event.frame_index), int(event.map_id), rigid(event.T_world_cam)[:3, 3].copy(),
            int(event.match_agent), int(event.match_frame_index), int(event.match_map),
            rigid(event.T_world_match)[:3, 3].copy()))
        state.loops_dirty = True

    def loop_segments(self, session_id: str) -> np.ndarray:
        """(L, 2, 3) world end points of the session's loop edges as they are drawn now."""
        with self._lock:
            state = self._sessions.get(session_id)
            return np.zeros((0, 2, 3)) if state is None else self._loop_points(state)

    @staticmethod
    def _loop_points(state: _SessionState) -> np.ndarray:
        points = []
        for loop in state.loops:
            a = state.frame_position(loop.agent, loop.frame_index)
            b = state.frame_position(loop.match_agent, loop.match_frame_index)
            if a is None:
                a = state.world_point(loop.map_id, loop.point) if loop.anchored else loop.point
            if b is None:
                b = state.world_point(loop.match_map, loop.match_point) if loop.anchored else loop.match_point
            points.append([a, b])
        return np.asarray(points, dtype=np.float64).reshape(-1, 2, 3)

    def trajectory_positions(self, session_id: str, agent: int = 0) -> np.ndarray:
        """(N, 3) world camera centres of one agent as they are drawn now (arrival order)."""
        with self._lock:
            state = self._sessions.get(session_id)
            if state is None or agent not in state.agents:
                return np.zeros((0, 3))
            return state.world_positions(agent)

    def remove_session(self, session_id: str) -> None:
        with self._lock:
            self._sessions.pop(session_id, None)
            for name in [n for n in self._handles if n == f"/sessions/{session_id}"
                         or n.startswith(f"/sessions/{session_id}/")]:
                handle = self._handles.pop(name)
                if name == f"/sessions/{session_id}":
                    handle.remove()
            if self._selected == session_id:
                self._selected = None
            self._sessions_changed = True

    def load_finished(self, session_id: str, mesh_path: Path,
                      trajectory_positions: np.ndarray | dict[int, np.ndarray] | None) -> None:
        """Show a finished session read back from disk (after a restart): its mesh as map 0.

        Args:
            mesh_path: the session's ``mesh.ply`` (world frame; may be missing).
            trajectory_positions: (N, 3) camera centres (agent 0), {agent: (N, 3)}, or None.
        """
        chunks = None
        if mesh_path.is_file():
            mesh = trimesh.load(mesh_path, file_type="ply", process=False)
            colors = getattr(mesh.visual, "vertex_colors", None)
            chunks = mesh_chunks(mesh.vertices, mesh.faces, None if colors is None else colors[:, :3])
        with self._lock:
            if session_id in self._sessions:
                return
            state = self._sessions[session_id] = _SessionState(session_id)
            self._sessions_changed = True
            if chunks is not None:
                state.map(0).pending_chunks = chunks
            if trajectory_positions is None:
                trajectory_positions = {}
            elif not isinstance(trajectory_positions, dict):
                trajectory_positions = {0: trajectory_positions}
            for agent, positions in sorted(trajectory_positions.items()):
                if positions is None or not len(positions):
                    continue
                track = state.agent(agent)
                track.points = list(np.asarray(positions, dtype=np.float64).reshape(-1, 3))
                track.maps = [0] * len(track.points)
                track.slots = {i: i for i in range(len(track.points))}
                track.dirty = True

    # -- the browser camera ------------------------------------------------------------------

    @staticmethod
    def _frame_client(client, bounds: tuple[np.ndarray, np.ndarray]) -> None:
        try:
            fov = float(client.camera.fov)
        except AssertionError:  # it has not reported its camera yet: it starts at the initial one
            return
        position, look_at = framing(*bounds, fov)
        with client.atomic():
            client.camera.position = position
            client.camera.look_at = look_at

    def _frame_if_grown(self, state: _SessionState) -> None:
        """Frame the selected session in every browser when it is first shown and whenever
        its extent has grown by REFRAME_GROWTH since; never while "Follow camera" is on."""
        if self._follow:
            return
        bounds = _scene_bounds(state)
        if bounds is None:
            return
        size = float(np.linalg.norm(bounds[1] - bounds[0]))
        if state.framed_size is not None and size <= REFRAME_GROWTH * max(state.framed_size, MIN_FRAME_RADIUS_M):
            return
        state.framed_size = size
        # Browsers that connect later (or have not reported their camera) start there, and
        # viser's "Reset View" returns there.
        initial = self._server.initial_camera
        initial.position, initial.look_at = framing(*bounds, initial.fov)
        for client in self._server.get_clients().values():
            self._frame_client(client, bounds)

    def current_camera(self) -> ViewerCamera | None:
        """The viewpoint of the browser that moved its camera last, or None without one."""
        if self._server is None:
            return None
        best = None
        for client in self._server.get_clients().values():
            camera = client.camera
            try:
                stamp = camera.update_timestamp
                wxyz, position, fov = camera.wxyz, camera.position, camera.fov
                width, height = camera.image_width, camera.image_height
            except AssertionError:  # the client has not reported its camera yet
                continue
            if best is None or stamp > best[0]:
                best = (stamp, wxyz, position, fov, width, height)
        if best is None:
            return None
        import torch

        _, wxyz, position, fov, width, height = best
        T = np.eye(4)
        T[:3, :3] = quat_wxyz_to_matrix(torch.as_tensor(np.asarray(wxyz, dtype=np.float64))).numpy()
        T[:3, 3] = position
        return ViewerCamera(T_world_cam=T, fov_y=float(fov), width=int(width), height=int(height))

    # -- flushing to viser (flusher thread) --------------------------------------------------

    def _flush_loop(self) -> None:
        while not self._stop.wait(0.05):
            try:
                self.flush()
            except Exception as error:  # noqa: BLE001 - a bad update must not stop the viewer
                import traceback

                traceback.print_exc()
                print(f"voxfusion viewer: flush failed: {error}")

    def flush(self, force: bool = False) -> None:
        """Push pending state of the selected session, within the rate limits (or now: force)."""
        with self._lock:
            if self._server is None:
                return
            if self._sessions_changed:
                self._sessions_changed = False
                self._update_session_list()
            if self._selected is None:
                return
            state = self._sessions[self._selected]
            now = time.monotonic()
            sent = False
            if force or now - state.last_update >= 1.0 / UPDATE_HZ:
                if self._flush_light(state):
                    state.last_update = now
                    self.stats.updates += 1
                    sent = True
            if force or now - state.last_mesh_update >= 1.0 / MESH_HZ:
                if self._flush_meshes(state):
                    state.last_mesh_update = now
                    self.stats.mesh_updates += 1
                    sent = True
            if sent or state.framed_size is None:
                self._frame_if_grown(state)

    def _update_session_list(self) -> None:
        options = list(self._sessions) or [NO_SESSION]
        newest = options[-1]
        self._session_dropdown.options = options
        if self._sessions and (self._selected not in self._sessions or not self._user_selected):
            self._select(newest)
        elif not self._sessions:
            self._session_dropdown.value = NO_SESSION

    def _ensure_root(self, session_id: str):
        name = f"/sessions/{session_id}"
        if name not in self._handles:
            self._handles[name] = self._server.scene.add_frame(name, show_axes=False)
            for layer in LAYERS:
                path = f"{name}/{layer}"
                self._handles[path] = self._server.scene.add_frame(path, show_axes=False,
                                                                    visible=self._layers[layer])
        return self._handles[name]

    def _map_node(self, state: _SessionState, layer: str, map_id: int, T: np.ndarray | None):
        name = f"/sessions/{state.session_id}/{layer}/map_{map_id}"
        handle = self._handles.get(name)
        if handle is None:
            handle = self._server.scene.add_frame(name, show_axes=False, visible=map_id not in self._hidden_maps)
            self._handles[name] = handle
        if T is not None:
            handle.wxyz = _wxyz(T)
            handle.position = T[:3, 3]
        return handle

    def _flush_light(self, state: _SessionState) -> bool:
        """Camera, trajectory, keyframes, loops, map poses; True if anything was sent."""
        scene = self._server.scene
        root = f"/sessions/{state.session_id}"
        self._ensure_root(state.session_id)
        sent = False
        new_map = False
        several_maps = len(state.maps) > 1
        for map_id, map_state in state.maps.items():
            if f"{root}/meshes/map_{map_id}" not in self._handles:
                new_map = True
            if map_state.pose_dirty:
                self._map_node(state, "meshes", map_id, map_state.T_world_map)
                if f"{root}/keyframes/map_{map_id}" in self._handles:
                    self._map_node(state, "keyframes", map_id, map_state.T_world_map)
                map_state.pose_dirty, sent = False, True
            if map_state.keyframes_dirty and len(map_state.keyframe_poses) and state.K is not None:
                self._map_node(state, "keyframes", map_id, map_state.T_world_map)
                w, h = state.image_size
                segments = frustum_segments(map_state.keyframe_poses, state.K, w, h, depth=0.1)
                name = f"{root}/keyframes/map_{map_id}/frusta"
                self._handles[name] = scene.add_line_segments(name, segments, colors=map_color(map_id),
                                                              thickness=1.5, thickness_units="screen")
                map_state.keyframes_dirty, sent = False, True
            if map_state.bounds_dirty and several_maps and map_state.bounds is not None:
                self._map_node(state, "meshes", map_id, map_state.T_world_map)
                name = f"{root}/meshes/map_{map_id}/bounds"
                self._handles[name] = scene.add_line_segments(name, box_segments(*map_state.bounds),
                                                              colors=map_color(map_id), thickness=1.0,
                                                              thickness_units="screen")
                map_state.bounds_dirty, sent = False, True
        if new_map:
            self._refresh_map_boxes()
            if several_maps:  # the first map's outline too, now that there are several
                for map_state in state.maps.values():
                    map_state.bounds_dirty = map_state.bounds is not None
        for agent in sorted(state.agents):
            track = state.agents[agent]
            if track.dirty:
                self._send_trajectory(state, agent)
                track.dirty, sent = False, True
            if track.camera_dirty and track.latest is not None:
                self._send_camera(state, agent)
                track.camera_dirty, sent = False, True
        if state.loops_dirty:
            name = f"{root}/loops/edges"
            points = self._loop_points(state).astype(np.float32)
            if len(points):
                self._handles[name] = scene.add_line_segments(name, points, colors=LOOP_COLOR, thickness=3.0,
                                                              thickness_units="screen")
            state.loops_dirty, sent = False, True
        if sent or state.status_dirty:
            self._update_status_text(state)
        return sent

    def _send_trajectory(self, state: _SessionState, agent: int) -> None:
        """Resend only the open blocks of one agent's path; complete blocks stay as they are in the
        browser (until a map they pass through moves). No segment joins a frame to one in a map
        that started after a tracking failure: such a map floats apart until a loop joins it."""
        track = state.agents[agent]
        positions = state.world_positions(agent).astype(np.float32)
        maps = np.asarray(track.maps)
        base = f"/sessions/{state.session_id}/trajectory/agent_{agent}"
        if base not in self._handles:
            self._handles[base] = self._server.scene.add_frame(base, show_axes=False)
        first_open = track.sent_blocks * TRAJECTORY_BLOCK
        for start in range(first_open, max(len(positions) - 1, first_open), TRAJECTORY_BLOCK):
            stop = min(start + TRAJECTORY_BLOCK + 1, len(positions))
            if stop - start < 2:
                break
            keep = np.array([maps[i] == maps[i + 1] or state.map(int(maps[i + 1])).reason != "tracking_failure"
                             for i in range(start, stop - 1)], dtype=bool)
            points = np.stack([positions[start:stop - 1], positions[start + 1:stop]], axis=1)[keep]
            if self._trajectory_by_map:
                colors = np.array([map_color(int(m)) for m in maps[start + 1:stop]], dtype=np.uint8)[keep]
            else:
                colors = np.broadcast_to(np.array(agent_color(agent), dtype=np.uint8), (len(points), 3))
            name = f"{base}/part_{start // TRAJECTORY_BLOCK}"
            if len(points):
                self._handles[name] = self._server.scene.add_line_segments(
                    name, points, colors=np.repeat(colors[:, None, :], 2, axis=1), thickness=2.0,
                    thickness_units="screen")
            if stop - start == TRAJECTORY_BLOCK + 1:
                track.sent_blocks += 1

    def _send_camera(self, state: _SessionState, agent: int) -> None:
        track = state.agents[agent]
        map_id, T_map_cam, thumbnail = track.latest
        T = state.maps[map_id].T_world_map @ T_map_cam if map_id in state.maps else T_map_cam
        name = f"/sessions/{state.session_id}/camera/frustum" + ("" if agent == 0 else f"_{agent}")
        handle = self._handles.get(name)
        if handle is None and track.K is not None:
            w, h = track.image_size
            fov = 2.0 * np.arctan(0.5 * h / track.K[1, 1])
            handle = self._server.scene.add_camera_frustum(
                name, fov=float(fov), aspect=w / h, scale=0.2, color=agent_color(agent), image=thumbnail,
                wxyz=_wxyz(T), position=T[:3, 3])
            self._handles[name] = handle
        elif handle is not None:
            handle.wxyz = _wxyz(T)
            handle.position = T[:3, 3]
            if thumbnail is not None:
                handle.image = thumbnail
        if self._follow and agent == min(state.agents):
            self._move_browsers_behind(T)

    def _move_browsers_behind(self, T_world_cam: np.ndarray) -> None:
        """Put every browser's camera a little behind and above the tracked camera."""
        forward, down = T_world_cam[:3, 2], T_world_cam[:3, 1]
        eye = T_world_cam[:3, 3] - 0.8 * forward - 0.3 * down
        target = T_world_cam[:3, 3] + 1.0 * forward
        for client in self._server.get_clients().values():
            with client.atomic():
                client.camera.position = eye
                client.camera.look_at = target

    def _flush_meshes(self, state: _SessionState) -> bool:
        sent_any = False
        for map_id, map_state in state.maps.items():
            chunks = map_state.pending_chunks
            if chunks is None:
                continue
            map_state.pending_chunks = None
            self._map_node(state, "meshes", map_id, map_state.T_world_map)
            base = f"/sessions/{state.session_id}/meshes/map_{map_id}"
            for key in [k for k in map_state.sent_chunks if k not in chunks]:
                handle = self._handles.pop(f"{base}/c_{_key_text(key)}", None)
                if handle is not None:
                    handle.remove()
                del map_state.sent_chunks[key]
            for key, chunk in chunks.items():
                if not chunk_changed(map_state.sent_chunks.get(key), chunk):
                    self.stats.chunks_skipped += 1
                    continue
                colors = chunk.colors
                if self._tint_by_map:
                    colors = np.broadcast_to(np.array(map_color(map_id), dtype=np.uint8), colors.shape)
                mesh = trimesh.Trimesh(chunk.vertices, chunk.faces, vertex_colors=colors, process=False)
                name = f"{base}/c_{_key_text(key)}"
                self._handles[name] = self._server.scene.add_mesh_trimesh(name, mesh)
                map_state.sent_chunks[key] = chunk
                self.stats.chunks_sent += 1
                sent_any = True
        return sent_any

    def _update_status_text(self, state: _SessionState) -> None:
        """The panel's line; its frames/s is the status API's (the session manager forwards
        StatsEvents with that value), so page and viewer agree."""
        state.status_dirty = False
        agents = max(1, len(state.agents))
        phase = f" ({state.phase})" if state.phase else ""
        text = f"**{state.session_id}**{phase}: {state.pose_count} poses, {len(state.maps)} map(s), " \
               f"{len(state.loops)} loop(s)"
        if agents > 1:
            text += f", {agents} agents"
        if state.stats is not None:
            text += f", {state.stats.fps:.1f} frames/s"
        self._status_md.content = text


def _scene_bounds(state: _SessionState) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo, hi) world corners around the session's trajectories and mesh chunks, or None if empty."""
    points = [np.zeros((0, 3))] + [state.world_positions(agent) for agent in state.agents]
    for map_state in state.maps.values():
        T = map_state.T_world_map
        chunks = {**map_state.sent_chunks, **(map_state.pending_chunks or {})}
        for chunk in list(chunks.values())[:200]:
            points.append(chunk.vertices[:: max(1, len(chunk.vertices) // 50)] @ T[:3, :3].T + T[:3, 3])
    points = np.concatenate(points)
    if len(points) == 0:
        return None
    return points.min(axis=0), points.max(axis=0)


def _key_text(key: tuple[int, int, int]) -> str:
    return "_".join(str(v).replace("-", "m") for v in key)
