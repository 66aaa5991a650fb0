"""The live 3D viewer: a viser server in the API process, fed with the workers' events.

Scene tree (slash paths; a parent's pose and visibility apply to its children)::

    /sessions/<id>                          one session (only the page's one is visible)
    /sessions/<id>/meshes/map_<m>           posed at T_world_map
    /sessions/<id>/meshes/map_<m>/c_<i>_<j>_<k>   a mesh chunk (map frame, vertex colours)
    /sessions/<id>/tinted/map_<m>/c_<i>_<j>_<k>   the same chunk in its map's colour (hidden; written
                                            once a browser colours meshes by map)
    /sessions/<id>/regions/map_<m>/bounds   the map's extent in its colour (several maps; off by default)
    /sessions/<id>/keyframes/map_<m>        posed at T_world_map: keyframe frustums in the map's colour
    /sessions/<id>/trajectory/agent_<a>/part_<k>   an agent's camera path in its colour, in blocks
                                            of TRAJECTORY_BLOCK poses
    /sessions/<id>/trajectory_maps/...      the same in the maps' colours (hidden; as ``tinted``)
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
by more than a few millimetres; finished trajectory blocks are never resent. Only the sessions
some browser shows stream; another session's pending state is sent when one shows it.

That tree is shared: sent once, to every browser. Each browser (viser client) has its own
controls, built when it connects and gone with its connection (``server.viewer_clients``), and
its own view (``server.viewer_views.ClientView``: session, layers, maps, colour by map, follow,
surface, crop box). Where a view differs from the shared scene, that browser gets client-scoped frames of
the same names (a hidden layer or map, a session root, a shown variant) that shadow the shared
ones for it alone; the heavy nodes are never copied per browser (a crop box sends that browser
only the parts of the chunks it cuts: ``server.viewer_crop``).

Only the API's token-checked relay (``GET /viewer`` WebSocket, ``server.routes_pages``) may
talk to viser: the relay sends a secret made at start in the ``RELAY_HEADER`` header, and any
other WebSocket on viser's port (any local user, or anyone when it is bound to a public
interface) is closed before viser sends it a byte of the scene. viser's port still serves
viser's own client files, which hold no data.

The browsers show the session our page shows (``select``, also for a session that has sent
no event yet), but for a browser that picked another one in its own dropdown (until it picks
the page's again), and are framed on what they show: the camera looks at the session's bounds
from a distance at which they fill the view, when it is shown, whenever its extent has grown by
half since (a live map grows from one camera pose to a room), and once more when it ends.

The module is the viser facade only: what each session shows and what is stale lives in
``server.viewer_state`` (plain data, no viser), whose sessions fold their events with the one
fold of them, ``server.session_state``; ``server.viewer_scene`` turns that state into scene
nodes; each browser's panel and view are ``server.viewer_clients`` and ``server.viewer_views``;
this facade holds the lock, the panels and the flusher thread, and guards viser's port.

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

from server.viewer_clients import ClientPanel, ViewChange
from server.viewer_neural import NeuralViews, Wanted, client_camera
from server.viewer_scene import SceneWriter, ViewerStats
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
from server.viewer_crop import CropBox
from server.viewer_views import ClientView, Shadows, shadows

if TYPE_CHECKING:
    import viser

UPDATE_HZ = 5.0
MESH_HZ = 1.0

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
        self._scene = SceneWriter(self.stats, followers=self._followers)
        self._panels: dict[int, ClientPanel] = {}
        """client id -> that browser's panel (its controls and view)."""
        self._mesh_versions: dict[str, int] = {}
        """session id -> how many times its meshes were sent (what a crop box cuts changes)."""
        self.relay_secret = secrets.token_urlsafe(32)
        """What the relay sends in RELAY_HEADER; nobody else knows it."""
        self.refused_connections = 0
        self.map_source: Callable[[str], object | None] | None = None
        """session id -> its map set (or None): what the neural views render (set by the app)."""
        self.neural: NeuralViews | None = None

    @property
    def nodes(self) -> dict[str, viser.SceneNodeHandle]:
        """The shared scene nodes by path (module doc), to read: what the browsers are sent."""
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
        self.neural = NeuralViews(lambda sid: None if self.map_source is None else self.map_source(sid))
        self._server.on_client_connect(self._connected)
        self._server.on_client_disconnect(self._disconnected)
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

    # -- each browser's panel ------------------------------------------------------------------

    def _connected(self, client: viser.ClientHandle) -> None:
        """A browser connected (or reloaded): its own controls, at their defaults."""
        with self._lock:
            if self._server is None:
                return
            panel = ClientPanel(client, self)
            self._panels[client.client_id] = panel
            self._sync_panel(panel)

    def _disconnected(self, client: viser.ClientHandle) -> None:
        with self._lock:
            self._panels.pop(client.client_id, None)

    def change(self, panel: ClientPanel, update: ViewChange) -> None:
        """A control was used in ``panel``'s browser: its new view, shown at once."""
        with self._lock:
            if panel.client_id not in self._panels:
                return
            before, panel.view = panel.view, update(panel.view, self._selected)
            if panel.view == before:
                return
            self._want_variants(panel.view)
            shown = panel.view.shown(self._selected)
            if shown != before.shown(self._selected) and shown in self._sessions:
                self._sessions[shown].last_update = self._sessions[shown].last_mesh_update = 0.0
            self._sync_panel(panel)

    def _want_variants(self, view: ClientView) -> None:
        """The first browser to colour by map makes the shared scene write the map-coloured
        variants from then on (everything so far is sent again in both colourings)."""
        if view.tint_by_map and not self._scene.tinted_wanted:
            self._scene.tinted_wanted = True
            for state in self._sessions.values():
                state.resend_meshes()
        if view.trajectory_by_map and not self._scene.trajectory_maps_wanted:
            self._scene.trajectory_maps_wanted = True
            for state in self._sessions.values():
                state.redraw_trajectories()

    def _sync_panel(self, panel: ClientPanel) -> None:
        """Bring one browser's lists, status line, shadow nodes and camera in step."""
        shown = panel.view.shown(self._selected)
        state = self._sessions.get(shown) if shown else None
        status = "Waiting for a session." if state is None else state.status_text()
        if state is not None and panel.view.session is not None and self._selected:
            status += f" (this browser's choice; the page shows {self._selected})"
        panel.sync(list(self._sessions), shown, sorted(state.maps) if state else [], status,
                   self._shadows(panel, state))
        if state is not None and panel.framed_on != shown and not panel.view.follow:
            bounds = scene_bounds(state)
            if bounds is not None and self._frame_client(panel.client, bounds):
                panel.framed_on = shown

    def _shadows(self, panel: ClientPanel, state: ViewerSession | None) -> Shadows:
        """What ``panel``'s browser needs of its own; with a crop box, worked out again only
        when the view, the sessions, the session's meshes or its maps' poses changed."""
        meshes = None
        key: tuple = (panel.view, self._selected, tuple(self._sessions))
        if panel.view.crop is not None and state is not None:
            meshes = {m: (state.T_world_map(m), view.sent_chunks) for m, view in state.maps.items()}
            key += (self._mesh_versions.get(state.session_id, 0),
                    tuple(T.round(9).tobytes() for T, _ in meshes.values()))
        if panel.shadows_key != key:
            panel.shadows_key, panel.shadows = key, shadows(panel.view, self._selected, set(self._sessions), meshes)
        return panel.shadows

    def fit_crop(self, panel: ClientPanel) -> None:
        """The crop fields of ``panel`` around the session it shows (its trajectories and mesh)."""
        with self._lock:
            state = self._sessions.get(panel.view.shown(self._selected) or "")
            bounds = None if state is None else scene_bounds(state)
            if bounds is None:
                return
            margin = 0.02 * max(1.0, float(np.linalg.norm(bounds[1] - bounds[0])))
            # whole centimetres, outwards: the fields show two decimals
            panel.set_crop_fields(np.floor((bounds[0] - margin) * 100) / 100, np.ceil((bounds[1] + margin) * 100) / 100)
            self.change(panel, panel.crop_update)

    def current_crop(self) -> CropBox | None:
        """The crop box of the browser that changed its crop last, of those that crop; or None."""
        with self._lock:
            cropping = [p for p in self._panels.values() if p.view.crop is not None]
            return max(cropping, key=lambda p: p.crop_changed_at).view.crop if cropping else None

    def _followers(self, session_id: str) -> list[viser.ClientHandle]:
        """The browsers that show ``session_id`` with "Follow camera" on."""
        return [p.client for p in self._panels.values()
                if p.view.follow and p.view.shown(self._selected) == session_id]

    def views(self) -> dict[int, ClientView]:
        """client id -> what that browser chose to see."""
        with self._lock:
            return {client_id: panel.view for client_id, panel in self._panels.items()}

    def shadow_frames(self, client_id: int) -> dict[str, bool]:
        """The frames by which one browser's scene differs from the shared one: path -> visible."""
        with self._lock:
            panel = self._panels.get(client_id)
            return {} if panel is None else panel.frames

    def status_line(self, session_id: str | None = None) -> str:
        """The status line of a session (the page's by default) as the browsers show it."""
        with self._lock:
            state = self._sessions.get(session_id or self._selected)
            return "" if state is None else state.status_text()

    def session_ids(self) -> list[str]:
        """The sessions the viewer has, as the browsers' dropdowns list them."""
        with self._lock:
            return list(self._sessions)

    def has_session(self, session_id: str) -> bool:
        with self._lock:
            return session_id in self._sessions

    @property
    def selected(self) -> str | None:
        """The page's session: what every browser shows that has not picked one of its own."""
        with self._lock:
            return self._selected

    def select(self, session_id: str) -> None:
        """Show ``session_id`` in every browser that follows the page (from our page, which
        names sessions that exist); a browser that picked its own session in its dropdown keeps
        it. One that has sent no event yet (queued, starting) gets an empty scene that fills as
        its events come, so the viewer follows a session the moment it is created."""
        with self._lock:
            if self._server is None:
                return
            self._user_selected = True
            if session_id not in self._sessions:
                self._sessions[session_id] = ViewerSession(session_id)
            self._select(session_id)

    def _select(self, session_id: str) -> None:
        """The page's session is ``session_id``; everything it has pending is flushed at the next
        tick, and the browsers that follow the page forget the maps they hid in the last one."""
        if session_id != self._selected:
            for panel in self._panels.values():
                panel.view = panel.view.page_moved()
        self._selected = session_id
        self._sessions[session_id].shown()
        self._scene.show_only(self._sessions, session_id)
        for panel in self._panels.values():
            self._sync_panel(panel)

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
            for panel in self._panels.values():
                if panel.view.session == session_id:  # its own choice is gone: back to the page's
                    panel.view = panel.view.with_session(None, self._selected)
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
    def _frame_client(client, bounds: tuple[np.ndarray, np.ndarray]) -> bool:
        """Frame ``bounds`` in one browser; False before it has reported its camera."""
        try:
            fov = float(client.camera.fov)
        except AssertionError:  # it has not reported its camera yet: it starts at the initial one
            return False
        position, look_at = framing(*bounds, fov)
        with client.atomic():
            client.camera.position = position
            client.camera.look_at = look_at
        return True

    def _frame_if_grown(self, state: ViewerSession) -> None:
        """Frame a session in the browsers that show it when it is first shown and whenever its
        extent has grown by REFRAME_GROWTH since; never a browser with "Follow camera" on."""
        bounds = state.bounds_to_frame()
        if bounds is None:
            return
        if state.session_id == self._selected:
            # Browsers that connect later (or have not reported their camera) start there, and
            # viser's "Reset View" returns there.
            initial = self._server.initial_camera
            initial.position, initial.look_at = framing(*bounds, initial.fov)
        for panel in self._panels.values():
            if panel.view.shown(self._selected) == state.session_id and not panel.view.follow:
                if self._frame_client(panel.client, bounds):
                    panel.framed_on = state.session_id

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
                if self.neural is not None:
                    self.neural.update(self._neural_wanted())
            except Exception as error:  # noqa: BLE001 - a bad update must not stop the viewer
                import traceback

                traceback.print_exc()
                print(f"voxfusion viewer: flush failed: {error}")

    def _neural_wanted(self) -> dict[int, Wanted]:
        with self._lock:
            return {client_id: Wanted(panel.client, panel.view.shown(self._selected), panel.view.surface,
                                      panel.view.crop) for client_id, panel in self._panels.items()}

    def _watched(self) -> list[str]:
        """The sessions some browser shows: the page's, then the browsers' own choices."""
        shown = [self._selected] + [panel.view.shown(self._selected) for panel in self._panels.values()]
        return [sid for sid in dict.fromkeys(shown) if sid in self._sessions]

    def flush(self, force: bool = False) -> None:
        """Push pending state of the sessions the browsers show, within the rate limits (or now:
        force), and bring every browser's panel in step."""
        with self._lock:
            if self._server is None:
                return
            if self._sessions_changed:
                self._sessions_changed = False
                self._update_session_list()
            for session_id in self._watched():
                self._flush_session(self._sessions[session_id], force)
            for panel in self._panels.values():
                self._sync_panel(panel)

    def _flush_session(self, state: ViewerSession, force: bool) -> None:
        now = time.monotonic()
        sent = False
        if force or now - state.last_update >= 1.0 / UPDATE_HZ:
            if self._scene.flush_light(state)[0]:
                state.last_update = now
                self.stats.updates += 1
                sent = True
        if force or now - state.last_mesh_update >= 1.0 / MESH_HZ:
            if self._scene.flush_meshes(state):
                self._mesh_versions[state.session_id] = self._mesh_versions.get(state.session_id, 0) + 1
                state.last_mesh_update = now
                self.stats.mesh_updates += 1
                sent = True
        state.status_dirty = False  # each browser's status line is compared with what it has
        if sent or state.framed_size is None:
            self._frame_if_grown(state)

    def _update_session_list(self) -> None:
        if self._sessions and (self._selected not in self._sessions or not self._user_selected):
            self._select(list(self._sessions)[-1])
