"""The live 3D viewer: a viser server in the API process, fed with the workers' events.

Scene tree (slash paths; a parent's pose and visibility apply to its children)::

    /sessions/<id>                          one session (only the selected one is visible)
    /sessions/<id>/meshes/map_<m>           posed at T_world_map
    /sessions/<id>/meshes/map_<m>/c_<i>_<j>_<k>   a mesh chunk (map frame, vertex colours)
    /sessions/<id>/regions/map_<m>/bounds   the map's extent in its colour (several maps; off by default)
    /sessions/<id>/keyframes/map_<m>        posed at T_world_map: keyframe frustums in the map's colour
    /sessions/<id>/trajectory/agent_<a>/part_<k>   an agent's camera path in its colour, in blocks
                                            of TRAJECTORY_BLOCK poses
    /sessions/<id>/camera/frustum[_<a>]     each agent's current camera frustum with its thumbnail
    /sessions/<id>/loops/edges              loop edges between the matched keyframes

Several agents (collaborative sessions) share the scene: each has its own trajectory colour
and camera frustum; map ids are unique across agents. Everything that belongs to a map comes
in that map's frame and is kept so: its mesh, its keyframes, the trajectory frames tracked in
it (and so the loop edges that end at them). A new ``T_world_map`` (a map's placement, a loop
closure, the final refinement) moves the map nodes, which moves meshes and keyframes without
resending them, and redraws the trajectories and loop edges where the map puts them now. A
loop edge ends at the two frames in the trajectories; frames the viewer never saw are drawn at
the LoopEvent's keyframe poses, in their maps' frames.

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
fold of them, ``server.session_state``; ``server.viewer_scene`` turns that state into scene
nodes; this facade holds the lock, the GUI handles and the flusher thread, and guards viser's
port.

Conventions as viser's: OpenCV camera axes, quaternions ``wxyz``, metres.
"""

from __future__ import annotations

import contextlib
import io
import secrets
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import trimesh

from server.viewer_neural import SURFACES, NeuralViews, client_camera
from server.viewer_scene import LAYERS, SceneWriter, ViewerStats
from server.viewer_state import (  # noqa: F401 - names this module has always exported
    FRAME_DIRECTION,
    MIN_FRAME_RADIUS_M,
    UP_DIRECTION,
    MeshChunk,
    ViewerCamera,
    ViewerSession,
    agent_color,
    chunk_changed,
    framing,
    frustum_segments,
    map_color,
    mesh_chunks,
    scene_bounds,
)

if TYPE_CHECKING:
    import viser

UPDATE_HZ = 5.0
MESH_HZ = 1.0
NO_SESSION = "(no session yet)"

RELAY_HEADER = "X-Voxfusion-Relay"
"""Header by which the API's relay proves itself to viser (its value: ``ViewerAdapter.relay_secret``)."""
RELAY_ONLY_CLOSE_CODE = 1008
"""WebSocket close code (policy violation) for a direct connection to viser's port."""

_scene_bounds = scene_bounds


class ViewerAdapter:
    """Owns the viser server. ``handle_event`` may be called from any thread."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080) -> None:
        self._host = host
        self._requested_port = port
        self._server: viser.ViserServer | None = None
        self._lock = threading.RLock()
        self._sessions: dict[str, ViewerSession] = {}
        self._selected: str | None = None
        self._user_selected = False
        self._sessions_changed = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.stats = ViewerStats()
        self._scene = SceneWriter(self.stats)
        self._session_dropdown: viser.GuiDropdownHandle | None = None
        self._maps_folder: viser.GuiFolderHandle | None = None
        self._map_boxes: dict[int, viser.GuiCheckboxHandle] = {}
        self._status_md: viser.GuiMarkdownHandle | None = None
        self.relay_secret = secrets.token_urlsafe(32)
        """What the relay sends in RELAY_HEADER; nobody else knows it."""
        self.refused_connections = 0
        self.map_source: Callable[[str], object | None] | None = None
        """session id -> its map set (or None): what the neural views render (set by the app)."""
        self.neural: NeuralViews | None = None
        self._meshes_wanted = True

    @property
    def _handles(self) -> dict[str, viser.SceneNodeHandle]:
        """The scene nodes by path (module doc)."""
        return self._scene.handles

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self) -> None:
        import viser

        # viser prints a box with its own URL, which a newcomer took for the one to open: the
        # way in is our page (its /viewer relay), whose URL the CLI prints.
        with contextlib.redirect_stdout(io.StringIO()):
            self._server = viser.ViserServer(host=self._host, port=self._requested_port, verbose=False)
        self._scene.server = self._server
        self._admit_relay_only()
        self._server.scene.set_up_direction(UP_DIRECTION)
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
        if self.neural is not None:
            self.neural.stop()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._server is not None:
            self._server.stop()
            self._server = None
            self._scene.server = None

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
        self.neural = NeuralViews(lambda sid: None if self.map_source is None else self.map_source(sid))
        surface = gui.add_dropdown("Surface", SURFACES, initial_value=SURFACES[0],
                                   hint="the mesh, or the neural map rendered from your camera")
        surface.on_update(lambda _: self._set_surface(surface.value))
        with gui.add_folder("Layers"):
            for name in LAYERS:
                label = "Region boxes" if name == "regions" else name.capitalize()
                box = gui.add_checkbox(label, self._scene.layers[name])
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
        self._sessions[session_id].shown()
        self._scene.show_only(self._sessions, session_id)
        self._refresh_map_boxes()
        if self._session_dropdown.value != session_id:
            self._session_dropdown.value = session_id

    def _set_follow(self, value: bool) -> None:
        self._scene.follow = bool(value)

    def _set_layer(self, name: str, value: bool) -> None:
        with self._lock:
            if name == "meshes":
                self._meshes_wanted = bool(value)
                value = value and self.neural.surface == "mesh"
            self._scene.set_layer(self._sessions, name, bool(value))

    def _set_surface(self, surface: str) -> None:
        """The mesh, or a neural view as each browser's background (the mesh hidden meanwhile)."""
        with self._lock:
            self.neural.surface = surface
            self._scene.set_layer(self._sessions, "meshes", self._meshes_wanted and surface == "mesh")

    def _set_tint(self, value: bool) -> None:
        with self._lock:
            self._scene.tint_by_map = bool(value)
            for state in self._sessions.values():
                state.resend_meshes()

    def _set_trajectory_tint(self, value: bool) -> None:
        with self._lock:
            self._scene.trajectory_by_map = bool(value)
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
                    box = self._server.gui.add_checkbox(f"Map {map_id}", map_id not in self._scene.hidden_maps,
                                                        hint=f"colour #{r:02x}{g:02x}{b:02x}")
                    box.on_update(lambda _, m=map_id, bx=box: self._set_map_visible(m, bx.value))
                    self._map_boxes[map_id] = box

    def _set_map_visible(self, map_id: int, visible: bool) -> None:
        with self._lock:
            self._scene.set_map_visible(self._sessions, map_id, visible)

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

    def show_path(self, session_id: str, poses: np.ndarray | None) -> None:
        """Draw a camera path's preview in the session's scene: its (N, 4, 4) frames as a line
        with a small frustum every tenth frame (``None`` or no frames: remove it)."""
        with self._lock:
            if self._server is None:
                return
            self._scene.root(session_id)
            self._scene.show_path(session_id, None if poses is None or not len(poses) else np.asarray(poses))

    def remove_session(self, session_id: str) -> None:
        with self._lock:
            self._sessions.pop(session_id, None)
            self._scene.remove_session(session_id)
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
        if self._scene.follow:
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
        seen = [c for c in (client_camera(client) for client in self._server.get_clients().values()) if c]
        return max(seen, key=lambda c: c[0])[1] if seen else None

    # -- flushing to viser (flusher thread) --------------------------------------------------

    def _flush_loop(self) -> None:
        while not self._stop.wait(0.05):
            try:
                self.flush()
                if self.neural is not None and self._server is not None:
                    self.neural.update(self._server.get_clients(), self.selected)
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
                if self._scene.flush_meshes(state):
                    state.last_mesh_update = now
                    self.stats.mesh_updates += 1
                    sent = True
            if sent or state.framed_size is None:
                self._frame_if_grown(state)

    def _flush_light(self, state: ViewerSession) -> bool:
        """Everything but meshes, and the status line; True if anything was sent."""
        sent, new_map = self._scene.flush_light(state)
        if new_map:
            self._refresh_map_boxes()
        if sent or state.status_dirty:
            state.status_dirty = False
            self._status_md.content = state.status_text()
        return sent

    def _update_session_list(self) -> None:
        options = list(self._sessions) or [NO_SESSION]
        newest = options[-1]
        self._session_dropdown.options = options
        if self._sessions and (self._selected not in self._sessions or not self._user_selected):
            self._select(newest)
        elif not self._sessions:
            self._session_dropdown.value = NO_SESSION
