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

The module is the viser facade only: what each session shows and what is stale lives in
``server.viewer_state`` (plain data, no viser), whose sessions fold their events with the one
fold of them, ``server.session_state``; this facade turns that state into scene nodes and GUI
handles, holds the lock, runs the flusher and guards viser's port.

Conventions as viser's: OpenCV camera axes, quaternions ``wxyz``, metres.
"""

from __future__ import annotations

import contextlib
import io
import secrets
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import trimesh

from server.viewer_state import (  # noqa: F401 - names this module has always exported
    FRAME_DIRECTION,
    LOOP_COLOR,
    MIN_FRAME_RADIUS_M,
    REFRAME_GROWTH,
    TRAJECTORY_BLOCK,
    MeshChunk,
    ViewerCamera,
    ViewerSession,
    agent_color,
    box_segments,
    chunk_changed,
    framing,
    frustum_segments,
    key_text,
    map_color,
    mesh_chunks,
    scene_bounds,
)
from slam import matrix_to_quat_wxyz, quat_wxyz_to_matrix

if TYPE_CHECKING:
    import viser

UPDATE_HZ = 5.0
MESH_HZ = 1.0
NO_SESSION = "(no session yet)"
LAYERS = ("meshes", "trajectory", "camera", "keyframes", "loops")

RELAY_HEADER = "X-Voxfusion-Relay"
"""Header by which the API's relay proves itself to viser (its value: ``ViewerAdapter.relay_secret``)."""
RELAY_ONLY_CLOSE_CODE = 1008
"""WebSocket close code (policy violation) for a direct connection to viser's port."""

_scene_bounds = scene_bounds


def _wxyz(T: np.ndarray) -> np.ndarray:
    import torch

    return matrix_to_quat_wxyz(torch.as_tensor(np.asarray(T)[:3, :3], dtype=torch.float64)).numpy()


def _place(handle, T: np.ndarray) -> None:
    handle.wxyz = _wxyz(T)
    handle.position = T[:3, 3]


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
        self._server: viser.ViserServer | None = None
        self._lock = threading.RLock()
        self._sessions: dict[str, ViewerSession] = {}
        self._handles: dict[str, viser.SceneNodeHandle] = {}
        """Scene nodes by path (module doc)."""
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
        self._session_dropdown: viser.GuiDropdownHandle | None = None
        self._maps_folder: viser.GuiFolderHandle | None = None
        self._map_boxes: dict[int, viser.GuiCheckboxHandle] = {}
        self._status_md: viser.GuiMarkdownHandle | None = None
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
        follow = gui.add_checkbox("Follow camera", False)
        follow.on_update(lambda _: self._set_follow(follow.value))
        with gui.add_folder("Layers"):
            for name in LAYERS:
                box = gui.add_checkbox(name.capitalize(), True)
                box.on_update(lambda _, n=name, b=box: self._set_layer(n, b.value))
            tint = gui.add_checkbox("Colour meshes by map", False)
            tint.on_update(lambda _: self._set_tint(tint.value))
            trajectory_tint = gui.add_checkbox("Colour trajectories by map", False,
                                               hint="otherwise each agent (camera) has its own colour")
            trajectory_tint.on_update(lambda _: self._set_trajectory_tint(trajectory_tint.value))
        self._maps_folder = gui.add_folder("Maps")
        self._map_boxes = {}
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
                self._sessions[session_id] = ViewerSession(session_id)
                self._session_dropdown.options = list(self._sessions)
            self._select(session_id)

    def _select(self, session_id: str) -> None:
        """Show ``session_id`` only; everything it has pending is flushed at the next tick."""
        self._selected = session_id
        for sid in self._sessions:
            handle = self._handles.get(f"/sessions/{sid}")
            if handle is not None:
                handle.visible = sid == session_id
        self._sessions[session_id].shown()
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
                state.resend_meshes()

    def _set_trajectory_tint(self, value: bool) -> None:
        with self._lock:
            self._trajectory_by_map = bool(value)
            for state in self._sessions.values():
                state.redraw_trajectories()

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
                state = self._sessions[session_id] = ViewerSession(session_id)
                self._sessions_changed = True
            state.apply(event)

    def loop_segments(self, session_id: str) -> np.ndarray:
        """(L, 2, 3) world end points of the session's loop edges as they are drawn now."""
        with self._lock:
            state = self._sessions.get(session_id)
            return np.zeros((0, 2, 3)) if state is None else state.loop_points()

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
        if trajectory_positions is None:
            trajectory_positions = {}
        elif not isinstance(trajectory_positions, dict):
            trajectory_positions = {0: trajectory_positions}
        with self._lock:
            if session_id in self._sessions:
                return
            state = self._sessions[session_id] = ViewerSession(session_id)
            self._sessions_changed = True
            state.load_finished(chunks, trajectory_positions)

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

    def _frame_if_grown(self, state: ViewerSession) -> None:
        """Frame the selected session in every browser when it is first shown and whenever
        its extent has grown by REFRAME_GROWTH since; never while "Follow camera" is on."""
        if self._follow:
            return
        bounds = state.bounds_to_frame()
        if bounds is None:
            return
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

    def _move_browsers_behind(self, T_world_cam: np.ndarray) -> None:
        """Put every browser's camera a little behind and above the tracked camera."""
        forward, down = T_world_cam[:3, 2], T_world_cam[:3, 1]
        eye = T_world_cam[:3, 3] - 0.8 * forward - 0.3 * down
        target = T_world_cam[:3, 3] + 1.0 * forward
        for client in self._server.get_clients().values():
            with client.atomic():
                client.camera.position = eye
                client.camera.look_at = target

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

    def _ensure_root(self, session_id: str) -> viser.FrameHandle:
        name = f"/sessions/{session_id}"
        if name not in self._handles:
            self._handles[name] = self._server.scene.add_frame(name, show_axes=False)
            for layer in LAYERS:
                path = f"{name}/{layer}"
                self._handles[path] = self._server.scene.add_frame(path, show_axes=False,
                                                                    visible=self._layers[layer])
        return self._handles[name]

    def _map_node(self, state: ViewerSession, layer: str, map_id: int) -> viser.FrameHandle:
        """The node of a map in a layer (made on first use), placed at the map's T_world_map."""
        name = f"/sessions/{state.session_id}/{layer}/map_{map_id}"
        handle = self._handles.get(name)
        if handle is None:
            handle = self._server.scene.add_frame(name, show_axes=False, visible=map_id not in self._hidden_maps)
            self._handles[name] = handle
        _place(handle, state.T_world_map(map_id))
        return handle

    def _add_segments(self, name: str, segments: np.ndarray, colors, thickness: float) -> None:
        self._handles[name] = self._server.scene.add_line_segments(name, segments, colors=colors,
                                                                    thickness=thickness, thickness_units="screen")

    def _flush_light(self, state: ViewerSession) -> bool:
        """Camera, trajectory, keyframes, loops, map poses; True if anything was sent."""
        self._ensure_root(state.session_id)
        sent = self._flush_maps(state)
        for agent in sorted(state.agents):
            view = state.agents[agent]
            if view.dirty:
                self._send_trajectory(state, agent)
                view.dirty, sent = False, True
            if view.camera_dirty and state.camera(agent) is not None:
                self._send_camera(state, agent)
                view.camera_dirty, sent = False, True
        if state.loops_dirty:
            points = state.loop_points().astype(np.float32)
            if len(points):
                self._add_segments(f"/sessions/{state.session_id}/loops/edges", points, LOOP_COLOR, 3.0)
            state.loops_dirty, sent = False, True
        if sent or state.status_dirty:
            state.status_dirty = False
            self._status_md.content = state.status_text()
        return sent

    def _flush_maps(self, state: ViewerSession) -> bool:
        """Map nodes' poses, keyframe frusta, map outlines; True if anything was sent."""
        root = f"/sessions/{state.session_id}"
        sent = new_map = False
        several_maps = len(state.maps) > 1
        for map_id, view in state.maps.items():
            new_map = new_map or f"{root}/meshes/map_{map_id}" not in self._handles
            if view.pose_dirty:
                self._map_node(state, "meshes", map_id)
                if f"{root}/keyframes/map_{map_id}" in self._handles:
                    self._map_node(state, "keyframes", map_id)
                view.pose_dirty, sent = False, True
            frusta = state.keyframe_frusta(map_id) if view.keyframes_dirty else None
            if frusta is not None:
                self._map_node(state, "keyframes", map_id)
                self._add_segments(f"{root}/keyframes/map_{map_id}/frusta", frusta, map_color(map_id), 1.5)
                view.keyframes_dirty, sent = False, True
            if view.bounds_dirty and several_maps and view.bounds is not None:
                self._map_node(state, "meshes", map_id)
                self._add_segments(f"{root}/meshes/map_{map_id}/bounds", box_segments(*view.bounds),
                                   map_color(map_id), 1.0)
                view.bounds_dirty, sent = False, True
        if new_map:
            self._refresh_map_boxes()
            if several_maps:  # the first map's outline too, now that there are several
                for view in state.maps.values():
                    view.bounds_dirty = view.bounds is not None
        return sent

    def _send_trajectory(self, state: ViewerSession, agent: int) -> None:
        """Resend the open blocks of one agent's path (``ViewerSession.trajectory_blocks``)."""
        base = f"/sessions/{state.session_id}/trajectory/agent_{agent}"
        if base not in self._handles:
            self._handles[base] = self._server.scene.add_frame(base, show_axes=False)
        for block in state.trajectory_blocks(agent, by_map=self._trajectory_by_map):
            if len(block.segments):
                colors = np.repeat(np.asarray(block.colors)[:, None, :], 2, axis=1)
                self._add_segments(f"{base}/part_{block.part}", block.segments, colors, 2.0)

    def _send_camera(self, state: ViewerSession, agent: int) -> None:
        T, thumbnail = state.camera(agent)
        name = f"/sessions/{state.session_id}/camera/frustum" + ("" if agent == 0 else f"_{agent}")
        handle = self._handles.get(name)
        intrinsics = state.scene.intrinsics.get(agent)
        if handle is None and intrinsics is not None:
            K, (w, h) = intrinsics
            fov = 2.0 * np.arctan(0.5 * h / K[1, 1])
            self._handles[name] = self._server.scene.add_camera_frustum(
                name, fov=float(fov), aspect=w / h, scale=0.2, color=agent_color(agent), image=thumbnail,
                wxyz=_wxyz(T), position=T[:3, 3])
        elif handle is not None:
            _place(handle, T)
            if thumbnail is not None:
                handle.image = thumbnail
        if self._follow and agent == min(state.agents):
            self._move_browsers_behind(T)

    def _flush_meshes(self, state: ViewerSession) -> bool:
        sent_any = False
        for map_id in list(state.maps):
            update = state.take_chunk_update(map_id)
            if update is None:
                continue
            self._map_node(state, "meshes", map_id)
            base = f"/sessions/{state.session_id}/meshes/map_{map_id}"
            for key in update.removed:
                handle = self._handles.pop(f"{base}/c_{key_text(key)}", None)
                if handle is not None:
                    handle.remove()
            self.stats.chunks_skipped += update.skipped
            for key, chunk in update.changed.items():
                colors = chunk.colors
                if self._tint_by_map:
                    colors = np.broadcast_to(np.array(map_color(map_id), dtype=np.uint8), colors.shape)
                mesh = trimesh.Trimesh(chunk.vertices, chunk.faces, vertex_colors=colors, process=False)
                name = f"{base}/c_{key_text(key)}"
                self._handles[name] = self._server.scene.add_mesh_trimesh(name, mesh)
                self.stats.chunks_sent += 1
                sent_any = True
        return sent_any
