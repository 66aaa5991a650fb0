"""The viewer's scene writer: a session's stale state (``server.viewer_state``) pushed to viser.

``SceneWriter`` owns viser's shared (server-scoped) scene nodes of every session, by path (the
tree in ``server.viewer``'s doc). What each browser chose to see is not here: the shared scene
shows the layers of ``server.viewer_views.SHARED_VISIBLE`` and every map, and a browser's own
choices shadow it (``server.viewer_clients``). Colour by map is a second, map-coloured variant
of the meshes and trajectories in the shared scene, written from the moment a browser first
asks for it (``tinted_wanted``, ``trajectory_maps_wanted``), so that no browser that never
asks pays for it before. It is called by the viewer's flusher under the viewer's lock; it
sends only what a :class:`~server.viewer_state.ViewerSession` marks stale and clears those marks.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import trimesh

from server.viewer_state import (
    LOOP_COLOR,
    ViewerSession,
    agent_color,
    box_segments,
    frustum_scale,
    frustum_segments,
    key_text,
    map_color,
    scene_bounds,
)
from server.viewer_views import LAYERS, SHARED_VISIBLE, VARIANT_LAYERS
from slam import matrix_to_quat_wxyz

if TYPE_CHECKING:
    import viser

PATH_COLOR = (0, 190, 255)
"""A camera path's preview: sky blue, unlike trajectories (agents' colours: red-orange for the
first), maps (their lighter hues, orange for the first) and loops (magenta)."""
LOOP_THICKNESS = 6.0
"""Pixels of a loop edge, twice a trajectory's: the edges a loop closure adds must stand out."""


def wxyz(T: np.ndarray) -> np.ndarray:
    """The rotation of a (4, 4) pose as viser's quaternion."""
    import torch

    return matrix_to_quat_wxyz(torch.as_tensor(np.asarray(T)[:3, :3], dtype=torch.float64)).numpy()


def place(handle, T: np.ndarray) -> None:
    handle.wxyz = wxyz(T)
    handle.position = T[:3, 3]


@dataclass
class ViewerStats:
    """Counters for the benchmark: how often the browsers were updated."""

    updates: int = 0
    mesh_updates: int = 0
    chunks_sent: int = 0
    chunks_skipped: int = 0
    events: int = 0


@dataclass
class SceneWriter:
    """viser's scene nodes of every session, and how they are shown (module doc)."""

    stats: ViewerStats
    server: viser.ViserServer | None = None
    handles: dict[str, viser.SceneNodeHandle] = field(default_factory=dict)
    tinted_wanted: bool = False
    """Write the map-coloured meshes (``tinted``) too: a browser has asked for them."""
    trajectory_maps_wanted: bool = False
    """Write the map-coloured trajectories (``trajectory_maps``) too."""
    followers: Callable[[str], list[viser.ClientHandle]] = lambda session_id: []
    """session id -> the browsers that show it with "Follow camera" on (set by the facade)."""

    # -- nodes -------------------------------------------------------------------------------

    def root(self, session_id: str) -> viser.FrameHandle:
        """The session's node, with one child per layer and variant (made on first use)."""
        name = f"/sessions/{session_id}"
        if name not in self.handles:
            self.handles[name] = self.server.scene.add_frame(name, show_axes=False)
            for layer in LAYERS + VARIANT_LAYERS:
                path = f"{name}/{layer}"
                self.handles[path] = self.server.scene.add_frame(path, show_axes=False,
                                                                 visible=layer in SHARED_VISIBLE)
        return self.handles[name]

    def map_node(self, state: ViewerSession, layer: str, map_id: int) -> viser.FrameHandle:
        """The node of a map in a layer (made on first use), placed at the map's T_world_map."""
        name = f"/sessions/{state.session_id}/{layer}/map_{map_id}"
        handle = self.handles.get(name)
        if handle is None:
            handle = self.server.scene.add_frame(name, show_axes=False)
            self.handles[name] = handle
        place(handle, state.T_world_map(map_id))
        return handle

    def add_segments(self, name: str, segments: np.ndarray, colors, thickness: float) -> None:
        self.handles[name] = self.server.scene.add_line_segments(name, segments, colors=colors,
                                                                 thickness=thickness, thickness_units="screen")

    def show_only(self, session_ids, selected: str) -> None:
        for sid in session_ids:
            handle = self.handles.get(f"/sessions/{sid}")
            if handle is not None:
                handle.visible = sid == selected
        self.root(selected).visible = True

    def show_path(self, session_id: str, poses: np.ndarray | None) -> None:
        """A camera path's preview (``ViewerAdapter.show_path``): ``/sessions/<id>/path``."""
        name = f"/sessions/{session_id}/path"
        for part in (f"{name}/line", f"{name}/cameras"):
            handle = self.handles.pop(part, None)
            if handle is not None:
                handle.remove()
        if poses is None:
            return
        centres = poses[:, :3, 3].astype(np.float32)
        line = np.stack([centres[:-1], centres[1:]], axis=1)
        self.add_segments(f"{name}/line", line, PATH_COLOR, 3.0)
        cameras = poses[:: max(1, len(poses) // 10)]
        K = np.array([[50.0, 0, 40], [0, 50.0, 30], [0, 0, 1]])  # a 4:3 frustum, only to show the heading
        self.add_segments(f"{name}/cameras", frustum_segments(cameras, K, 80, 60, depth=0.08), PATH_COLOR, 1.5)

    def remove_session(self, session_id: str) -> None:
        root = f"/sessions/{session_id}"
        for name in [n for n in self.handles if n == root or n.startswith(f"{root}/")]:
            handle = self.handles.pop(name)
            if name == root:
                handle.remove()

    # -- pushing a session's stale state -------------------------------------------------------

    def flush_light(self, state: ViewerSession) -> tuple[bool, bool]:
        """Camera, trajectory, keyframes, loops, map poses: (anything sent, a new map seen)."""
        self.root(state.session_id)
        sent, new_map = self.flush_maps(state)
        for agent in sorted(state.agents):
            view = state.agents[agent]
            if view.dirty:
                self.send_trajectory(state, agent)
                view.dirty, sent = False, True
            if view.camera_dirty and state.camera(agent) is not None:
                self.send_camera(state, agent)
                view.camera_dirty, sent = False, True
        if state.loops_dirty:
            points = state.loop_points().astype(np.float32)
            if len(points):
                self.add_segments(f"/sessions/{state.session_id}/loops/edges", points, LOOP_COLOR, LOOP_THICKNESS)
                ends = points.reshape(-1, 3)
                self.handles[f"/sessions/{state.session_id}/loops/ends"] = self.server.scene.add_point_cloud(
                    f"/sessions/{state.session_id}/loops/ends", ends, colors=np.tile(np.array(LOOP_COLOR, np.uint8),
                                                                                     (len(ends), 1)),
                    point_size=0.04, point_shape="circle", precision="float32")
            state.loops_dirty, sent = False, True
        return sent, new_map

    def flush_maps(self, state: ViewerSession) -> tuple[bool, bool]:
        """Map nodes' poses, keyframe frusta, map outlines: (anything sent, a new map seen)."""
        root = f"/sessions/{state.session_id}"
        sent = new_map = False
        several_maps = len(state.maps) > 1
        for map_id, view in state.maps.items():
            new_map = new_map or f"{root}/meshes/map_{map_id}" not in self.handles
            if view.pose_dirty:
                self.map_node(state, "meshes", map_id)
                for layer in ("tinted", "keyframes"):
                    if f"{root}/{layer}/map_{map_id}" in self.handles:
                        self.map_node(state, layer, map_id)
                view.pose_dirty, sent = False, True
            frusta = state.keyframe_frusta(map_id) if view.keyframes_dirty else None
            if frusta is not None:
                self.map_node(state, "keyframes", map_id)
                self.add_segments(f"{root}/keyframes/map_{map_id}/frusta", frusta, map_color(map_id), 1.5)
                view.keyframes_dirty, sent = False, True
            if view.bounds_dirty and several_maps and view.bounds is not None:
                self.map_node(state, "regions", map_id)
                self.add_segments(f"{root}/regions/map_{map_id}/bounds", box_segments(*view.bounds),
                                  map_color(map_id), 1.0)
                view.bounds_dirty, sent = False, True
        if new_map and several_maps:  # the first map's outline too, now that there are several
            for view in state.maps.values():
                view.bounds_dirty = view.bounds is not None
        return sent, new_map

    def send_trajectory(self, state: ViewerSession, agent: int) -> None:
        """Resend the open blocks of one agent's path (``ViewerSession.trajectory_blocks``) in the
        agent's colour, and in the maps' colours while a browser wants them."""
        first_open = state.agents[agent].sent_blocks
        self.send_blocks(state, agent, "trajectory", by_map=False)
        if self.trajectory_maps_wanted:
            # the same blocks again, counted again as sent from the same start
            state.agents[agent].sent_blocks = first_open
            self.send_blocks(state, agent, "trajectory_maps", by_map=True)

    def send_blocks(self, state: ViewerSession, agent: int, layer: str, by_map: bool) -> None:
        base = f"/sessions/{state.session_id}/{layer}/agent_{agent}"
        if base not in self.handles:
            self.handles[base] = self.server.scene.add_frame(base, show_axes=False)
        for block in state.trajectory_blocks(agent, by_map=by_map):
            if len(block.segments):
                colors = np.repeat(np.asarray(block.colors)[:, None, :], 2, axis=1)
                self.add_segments(f"{base}/part_{block.part}", block.segments, colors, 2.0)

    def send_camera(self, state: ViewerSession, agent: int) -> None:
        T, thumbnail = state.camera(agent)
        name = f"/sessions/{state.session_id}/camera/frustum" + ("" if agent == 0 else f"_{agent}")
        handle = self.handles.get(name)
        camera = state.scene.cameras.get(agent)
        scale = frustum_scale(scene_bounds(state))
        if handle is None and camera is not None:
            fov = 2.0 * np.arctan(0.5 * camera.height / camera.K[1, 1])
            self.handles[name] = self.server.scene.add_camera_frustum(
                name, fov=float(fov), aspect=camera.width / camera.height, scale=scale, color=agent_color(agent),
                image=thumbnail, wxyz=wxyz(T), position=T[:3, 3],
                thickness=2.0, thickness_units="screen")  # lines in world units would swell with a small frustum
        elif handle is not None:
            place(handle, T)
            if abs(float(np.mean(handle.scale)) - scale) > 0.2 * scale:  # the scene grew (or started small)
                handle.scale = scale
            if thumbnail is not None:
                handle.image = thumbnail
        if agent == min(state.agents):
            self.move_browsers_behind(T, self.followers(state.session_id))

    @staticmethod
    def move_browsers_behind(T_world_cam: np.ndarray, clients) -> None:
        """Put these browsers' cameras a little behind and above the tracked camera."""
        forward, down = T_world_cam[:3, 2], T_world_cam[:3, 1]
        eye = T_world_cam[:3, 3] - 0.8 * forward - 0.3 * down
        target = T_world_cam[:3, 3] + 1.0 * forward
        for client in clients:
            with client.atomic():
                client.camera.position = eye
                client.camera.look_at = target

    def flush_meshes(self, state: ViewerSession) -> bool:
        """The changed chunks of every map's pending mesh (and their map-coloured variant while
        a browser wants it); True if any was sent."""
        sent_any = False
        layers = ("meshes", "tinted") if self.tinted_wanted else ("meshes",)
        for map_id in list(state.maps):
            update = state.take_chunk_update(map_id)
            if update is None:
                continue
            for layer in layers:
                self.map_node(state, layer, map_id)
                base = f"/sessions/{state.session_id}/{layer}/map_{map_id}"
                for key in update.removed:
                    handle = self.handles.pop(f"{base}/c_{key_text(key)}", None)
                    if handle is not None:
                        handle.remove()
            self.stats.chunks_skipped += update.skipped
            for key, chunk in update.changed.items():
                self.send_chunk(state.session_id, map_id, key, chunk, tinted="tinted" in layers)
                sent_any = True
        return sent_any

    def send_chunk(self, session_id: str, map_id: int, key, chunk, tinted: bool) -> None:
        """One mesh chunk in its vertex colours, and in its map's colour (``tinted``)."""
        name = f"/sessions/{session_id}/meshes/map_{map_id}/c_{key_text(key)}"
        mesh = trimesh.Trimesh(chunk.vertices, chunk.faces, vertex_colors=chunk.colors, process=False)
        self.handles[name] = self.server.scene.add_mesh_trimesh(name, mesh)
        self.stats.chunks_sent += 1
        if tinted:  # one colour for the whole chunk: no vertex colours to send
            name = f"/sessions/{session_id}/tinted/map_{map_id}/c_{key_text(key)}"
            self.handles[name] = self.server.scene.add_mesh_simple(name, chunk.vertices, chunk.faces,
                                                                   color=map_color(map_id))
