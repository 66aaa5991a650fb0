"""The live 3D viewer: a viser server in the API process, fed with the workers' events.

Scene tree (slash paths; a parent's pose and visibility apply to its children)::

    /sessions/<id>                          one session (only the selected one is visible)
    /sessions/<id>/meshes/map_<m>           posed at T_world_map
    /sessions/<id>/meshes/map_<m>/c_<i>_<j>_<k>   a mesh chunk (map frame, vertex colours)
    /sessions/<id>/keyframes/map_<m>        keyframe frustums, in the map's colour
    /sessions/<id>/trajectory/part_<k>      tracked camera path in blocks of TRAJECTORY_BLOCK poses
    /sessions/<id>/camera                   the current camera frustum with its thumbnail
    /sessions/<id>/loops                    loop edges between the matched keyframes

Events only update the adapter's pending state (cheap, in the supervisor thread); a flusher
thread pushes that state to viser at most ``UPDATE_HZ`` times a second per session and meshes
at most ``MESH_HZ`` times a second, so a fast run cannot flood the browsers. Only parts that
changed are sent again: mesh chunks are kept in their map's frame (a loop correction moves the
map node, not the vertices) and a chunk is resent only when its triangles or colours changed
by more than a few millimetres; finished trajectory blocks are never resent. Only the selected
session streams; another session's pending state is sent when it is selected.

Conventions as viser's: OpenCV camera axes, quaternions ``wxyz``, metres.
"""

from __future__ import annotations

import colorsys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from slam.events import KeyframeEvent, LoopEvent, MapUpdateEvent, PoseEvent, StatsEvent, SubmapEvent
from slam.geometry import matrix_to_quat_wxyz, quat_wxyz_to_matrix

UPDATE_HZ = 5.0
MESH_HZ = 1.0
CHUNK_SIZE_M = 1.0
"""Edge of the cubes a map's mesh is cut into (metres): the unit that is resent when it changes."""
VERTEX_TOLERANCE_M = 0.005
COLOR_TOLERANCE = 8
TRAJECTORY_BLOCK = 256
NO_SESSION = "(no session yet)"
LAYERS = ("meshes", "trajectory", "camera", "keyframes", "loops")


def map_color(map_id: int) -> tuple[int, int, int]:
    """A distinct, saturated RGB colour per map id (golden-ratio hue steps)."""
    hue = (0.08 + 0.618034 * map_id) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.75, 0.95)
    return int(r * 255), int(g * 255), int(b * 255)


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
    keyframe_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    pending_chunks: dict | None = None
    """Chunks of the newest mesh not yet pushed (map frame)."""
    sent_chunks: dict = field(default_factory=dict)
    pose_dirty: bool = True
    keyframes_dirty: bool = False


@dataclass
class _SessionState:
    session_id: str
    maps: dict[int, _MapState] = field(default_factory=dict)
    positions: list[np.ndarray] = field(default_factory=list)
    position_maps: list[int] = field(default_factory=list)
    sent_blocks: int = 0
    """Trajectory blocks (of TRAJECTORY_BLOCK poses) that are complete and sent."""
    latest_pose: PoseEvent | None = None
    camera_dirty: bool = False
    trajectory_dirty: bool = False
    loops: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    loops_dirty: bool = False
    last_update: float = 0.0
    last_mesh_update: float = 0.0
    K: np.ndarray | None = None
    image_size: tuple[int, int] | None = None

    def map(self, map_id: int) -> _MapState:
        return self.maps.setdefault(map_id, _MapState())


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
        self._follow = False
        self._sessions_changed = False
        self._last_stats: tuple[str, StatsEvent] | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.stats = ViewerStats()

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self) -> None:
        import viser

        self._server = viser.ViserServer(host=self._host, port=self._requested_port, verbose=False)
        self._server.scene.set_up_direction("+z")
        self._server.gui.configure_theme(show_share_button=False, brand_color=(40, 110, 200))
        self._build_gui()
        self._server.on_client_connect(self._on_client_connect)
        self._thread = threading.Thread(target=self._flush_loop, name="viewer-flush", daemon=True)
        self._thread.start()

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

    def select(self, session_id: str) -> None:
        """Show ``session_id`` in every browser (from our page); unknown ids are ignored."""
        with self._lock:
            if session_id in self._sessions and self._server is not None:
                self._user_selected = True
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
                poses = state.map(event.map_id).keyframe_poses
                state.map(event.map_id).keyframe_poses = np.concatenate([poses, event.T_world_cam[None]])
                state.map(event.map_id).keyframes_dirty = True
            elif isinstance(event, MapUpdateEvent):
                self._on_map_update(state, event)
            elif isinstance(event, SubmapEvent):
                map_state = state.map(event.map_id)
                map_state.T_world_map = np.asarray(event.T_world_map, dtype=np.float64)
                map_state.pose_dirty = True
            elif isinstance(event, LoopEvent):
                state.loops.append((np.asarray(event.T_world_src)[:3, 3], np.asarray(event.T_world_tar)[:3, 3]))
                state.loops_dirty = True
            elif isinstance(event, StatsEvent):
                self._last_stats = (session_id, event)

    def _on_pose(self, state: _SessionState, event: PoseEvent) -> None:
        state.latest_pose = event
        state.positions.append(np.asarray(event.T_world_cam, dtype=np.float64)[:3, 3].copy())
        state.position_maps.append(event.map_id)
        state.camera_dirty = state.trajectory_dirty = True
        state.map(event.map_id)
        if event.K is not None and event.image_size is not None:
            state.K, state.image_size = np.asarray(event.K), tuple(event.image_size)

    def _on_map_update(self, state: _SessionState, event: MapUpdateEvent) -> None:
        map_state = state.map(event.map_id)
        T_world_map = np.asarray(event.T_world_map, dtype=np.float64)
        if not np.allclose(T_world_map, map_state.T_world_map):
            map_state.T_world_map = T_world_map
            map_state.pose_dirty = True
        if len(event.keyframe_poses):
            map_state.keyframe_poses = np.asarray(event.keyframe_poses, dtype=np.float64)
            map_state.keyframes_dirty = True
        if event.mesh_vertices is not None and event.mesh_faces is not None:
            # Into the map frame, so that a later correction of T_world_map moves the node only.
            T_map_world = np.linalg.inv(T_world_map)
            vertices = np.asarray(event.mesh_vertices, dtype=np.float64) @ T_map_world[:3, :3].T + T_map_world[:3, 3]
            map_state.pending_chunks = mesh_chunks(vertices, event.mesh_faces, event.mesh_colors)

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

    def load_finished(self, session_id: str, mesh_path: Path, trajectory_positions: np.ndarray | None) -> None:
        """Show a finished session read back from disk (after a restart): its mesh as map 0.

        Args:
            mesh_path: the session's ``mesh.ply`` (world frame; may be missing).
            trajectory_positions: (N, 3) camera centres, or None.
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
            if trajectory_positions is not None and len(trajectory_positions):
                state.positions = list(np.asarray(trajectory_positions, dtype=np.float64))
                state.position_maps = [0] * len(state.positions)
                state.trajectory_dirty = True

    # -- the browser camera ------------------------------------------------------------------

    def _on_client_connect(self, client) -> None:
        """Point a new browser at the selected session's scene (viser's default looks at the origin)."""
        with self._lock:
            state = self._sessions.get(self._selected) if self._selected else None
            bounds = None if state is None else _scene_bounds(state)
        if bounds is None:
            return
        lo, hi = bounds
        centre = (lo + hi) / 2
        extent = max(float(np.linalg.norm(hi - lo)), 1.0)
        with client.atomic():
            client.camera.position = centre + extent * np.array([0.45, -0.6, 0.55])
            client.camera.look_at = centre

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
            if force or now - state.last_update >= 1.0 / UPDATE_HZ:
                if self._flush_light(state):
                    state.last_update = now
                    self.stats.updates += 1
            if force or now - state.last_mesh_update >= 1.0 / MESH_HZ:
                if self._flush_meshes(state):
                    state.last_mesh_update = now
                    self.stats.mesh_updates += 1

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
        for map_id, map_state in state.maps.items():
            if f"{root}/meshes/map_{map_id}" not in self._handles:
                new_map = True
            if map_state.pose_dirty:
                self._map_node(state, "meshes", map_id, map_state.T_world_map)
                map_state.pose_dirty, sent = False, True
            if map_state.keyframes_dirty and len(map_state.keyframe_poses) and state.K is not None:
                self._map_node(state, "keyframes", map_id, None)
                w, h = state.image_size
                segments = frustum_segments(map_state.keyframe_poses, state.K, w, h, depth=0.1)
                scene.add_line_segments(f"{root}/keyframes/map_{map_id}/frusta", segments,
                                        colors=map_color(map_id), thickness=1.5, thickness_units="screen")
                map_state.keyframes_dirty, sent = False, True
        if new_map:
            self._refresh_map_boxes()
        if state.trajectory_dirty:
            self._send_trajectory(state)
            state.trajectory_dirty, sent = False, True
        if state.camera_dirty and state.latest_pose is not None:
            self._send_camera(state)
            state.camera_dirty, sent = False, True
        if state.loops_dirty:
            points = np.array([[a, b] for a, b in state.loops], dtype=np.float32)
            scene.add_line_segments(f"{root}/loops/edges", points, colors=(255, 40, 200), thickness=3.0,
                                    thickness_units="screen")
            state.loops_dirty, sent = False, True
        if sent:
            self._update_status_text(state)
        return sent

    def _send_trajectory(self, state: _SessionState) -> None:
        """Resend only the open block; complete blocks stay as they are in the browser."""
        positions = np.asarray(state.positions, dtype=np.float32)
        maps = np.asarray(state.position_maps)
        first_open = state.sent_blocks * TRAJECTORY_BLOCK
        for start in range(first_open, max(len(positions) - 1, first_open), TRAJECTORY_BLOCK):
            stop = min(start + TRAJECTORY_BLOCK + 1, len(positions))
            if stop - start < 2:
                break
            points = np.stack([positions[start:stop - 1], positions[start + 1:stop]], axis=1)
            colors = np.array([map_color(int(m)) for m in maps[start + 1:stop]], dtype=np.uint8)
            self._server.scene.add_line_segments(
                f"/sessions/{state.session_id}/trajectory/part_{start // TRAJECTORY_BLOCK}", points,
                colors=np.repeat(colors[:, None, :], 2, axis=1), thickness=2.0, thickness_units="screen")
            if stop - start == TRAJECTORY_BLOCK + 1:
                state.sent_blocks += 1

    def _send_camera(self, state: _SessionState) -> None:
        pose = state.latest_pose
        T = np.asarray(pose.T_world_cam, dtype=np.float64)
        name = f"/sessions/{state.session_id}/camera/frustum"
        handle = self._handles.get(name)
        if handle is None and state.K is not None:
            w, h = state.image_size
            fov = 2.0 * np.arctan(0.5 * h / state.K[1, 1])
            handle = self._server.scene.add_camera_frustum(
                name, fov=float(fov), aspect=w / h, scale=0.2, color=(230, 60, 40), image=pose.thumbnail,
                wxyz=_wxyz(T), position=T[:3, 3])
            self._handles[name] = handle
        elif handle is not None:
            handle.wxyz = _wxyz(T)
            handle.position = T[:3, 3]
            if pose.thumbnail is not None:
                handle.image = pose.thumbnail
        if self._follow:
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
        stats = self._last_stats[1] if self._last_stats and self._last_stats[0] == state.session_id else None
        text = f"**{state.session_id}**: {len(state.positions)} poses, {len(state.maps)} map(s), " \
               f"{len(state.loops)} loop(s)"
        if stats is not None:
            text += f", {stats.fps:.1f} frames/s"
        self._status_md.content = text


def _scene_bounds(state: _SessionState) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo, hi) world corners around the session's trajectory and mesh chunks, or None if empty."""
    points = [np.asarray(state.positions, dtype=np.float64).reshape(-1, 3)]
    for map_state in state.maps.values():
        T = map_state.T_world_map
        for chunk in list(map_state.sent_chunks.values())[:200]:
            points.append(chunk.vertices[:: max(1, len(chunk.vertices) // 50)] @ T[:3, :3].T + T[:3, 3])
    points = np.concatenate(points)
    if len(points) == 0:
        return None
    return points.min(axis=0), points.max(axis=0)


def _key_text(key: tuple[int, int, int]) -> str:
    return "_".join(str(v).replace("-", "m") for v in key)
