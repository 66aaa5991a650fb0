"""One browser's viewer panel: its own controls, built when it connects.

A :class:`ClientPanel` holds a viser client's GUI handles (session, follow, surface, layers,
colour by map, maps, status line), its :class:`~server.viewer_views.ClientView` and the
client-scoped frames that shadow the shared scene for it (``server.viewer_views.shadows``).
Every control calls back into its owner (the facade, ``server.viewer.ViewerAdapter``) with a
change of view; the owner decides, under its lock, what that change means for the shared scene,
and ``sync`` brings the panel's frames and lists in step on every flush.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, Protocol

import trimesh

from server.viewer_crop import CROP_COLOR, CropBox
from server.viewer_state import map_color
from server.viewer_views import LAYERS, SURFACES, ClientView, Shadows

if TYPE_CHECKING:
    import viser

NO_SESSION = "(no session yet)"

ViewChange = Callable[[ClientView, "str | None"], ClientView]
"""(a browser's view, the page's selection) -> its new view."""


class PanelOwner(Protocol):
    def change(self, panel: ClientPanel, update: ViewChange) -> None:
        """Apply ``update`` to the panel's view (a control was used in its browser)."""

    def fit_crop(self, panel: ClientPanel) -> None:
        """Set the panel's crop fields to the bounds of the session it shows."""


def _label(layer: str) -> str:
    return "Region boxes" if layer == "regions" else layer.capitalize()


class ClientPanel:
    """One browser's controls, view and shadow frames (module doc)."""

    def __init__(self, client: viser.ClientHandle, owner: PanelOwner) -> None:
        self.client = client
        self.owner = owner
        self.view = ClientView()
        self.shadows_key: tuple | None = None
        self.shadows = Shadows()
        """What this browser needs of its own, and for which state (the owner's cache)."""
        self.framed_on: str | None = None
        """The session this browser's camera was last framed on."""
        self._frames: dict[str, object] = {}
        """path -> token of this browser's shadow nodes (``Shadows.tokens``)."""
        self._frame_handles: dict[str, viser.SceneNodeHandle] = {}
        self._cut: dict = {}
        """The cut chunks shown now (their sources held: see ``CroppedChunk.source``)."""
        self._box_handle: viser.LineSegmentsHandle | None = None
        self._box: tuple[CropBox | None, str | None] | None = None
        """(box, session) the outline and links were made for."""
        self.crop_changed_at = 0.0
        """When this browser last changed its crop box (monotonic seconds; 0: never)."""
        self._map_boxes: dict[int, viser.GuiCheckboxHandle] = {}
        self._status = ""
        self._build()

    @property
    def client_id(self) -> int:
        return self.client.client_id

    def _on(self, handle, update: Callable[[object], ViewChange]) -> None:
        """Call the owner when this browser's user changes ``handle`` (not when code sets it)."""
        handle.on_update(lambda event: None if event.client is None
                         else self.owner.change(self, update(handle.value)))

    def _build(self) -> None:
        gui = self.client.gui
        self.session = gui.add_dropdown("Session", [NO_SESSION], initial_value=NO_SESSION,
                                        hint="this browser's session; the page's session puts it back in step")
        self._on(self.session, lambda value: lambda view, selected: view if value == NO_SESSION
                 else view.with_session(value, selected))
        follow = gui.add_checkbox("Follow camera", False)
        self._on(follow, lambda value: lambda view, _: replace(view, follow=bool(value)))
        surface = gui.add_dropdown("Surface", SURFACES, initial_value=SURFACES[0],
                                   hint="the mesh, or the neural map rendered from your camera")
        self._on(surface, lambda value: lambda view, _: view.with_surface(value))
        with gui.add_folder("Layers"):
            for name in LAYERS:
                box = gui.add_checkbox(_label(name), name in self.view.layers)
                self._on(box, lambda value, n=name: lambda view, _: view.with_layer(n, bool(value)))
            tint = gui.add_checkbox("Colour meshes by map", False)
            self._on(tint, lambda value: lambda view, _: replace(view, tint_by_map=bool(value)))
            by_map = gui.add_checkbox("Colour trajectories by map", False,
                                      hint="otherwise each agent (camera) has its own colour")
            self._on(by_map, lambda value: lambda view, _: replace(view, trajectory_by_map=bool(value)))
        self.maps_folder = gui.add_folder("Maps")
        self._build_crop()
        self.status = gui.add_markdown("Waiting for a session.")

    def _build_crop(self) -> None:
        """The crop box: on or off, its corners (world frame), a fit, the cropped mesh's links."""
        gui = self.client.gui
        with gui.add_folder("Crop box", expand_by_default=False):
            self.crop_on = gui.add_checkbox("Crop", False, hint="show only what lies inside the box")
            self.crop_min = gui.add_vector3("Min", (-1.0, -1.0, -1.0), step=0.05)
            self.crop_max = gui.add_vector3("Max", (1.0, 1.0, 1.0), step=0.05)
            fit = gui.add_button("Fit to the session")
            fit.on_click(lambda event: None if event.client is None else self.owner.fit_crop(self))
            self.crop_note = gui.add_markdown("")
        for handle in (self.crop_on, self.crop_min, self.crop_max):
            self._on(handle, lambda _: self.crop_update)

    def crop_update(self, view: ClientView, _selected) -> ClientView:
        """The view with the crop fields' box (unchanged, with a note, when the box is empty)."""
        try:
            new = view.with_crop(self.crop_on.value, self.crop_min.value, self.crop_max.value)
        except ValueError as error:
            self.crop_note.content = str(error)
            return view
        self.crop_changed_at = time.monotonic()
        return new

    # -- brought in step by the owner (under its lock) ------------------------------------------

    def sync(self, sessions: list[str], shown: str | None, maps: list[int], status: str,
             shadows: Shadows) -> None:
        """The session list and choice, the map boxes, the status line and the shadow frames."""
        options = sessions or [NO_SESSION]
        if list(self.session.options) != options:
            self.session.options = options
        value = shown if shown in sessions else options[-1] if sessions else NO_SESSION
        if self.session.value != value:
            self.session.value = value
        self._sync_maps(maps)
        if status != self._status:
            self._status = self.status.content = status
        self._sync_frames(shadows)
        self._sync_box(shown)

    def _sync_maps(self, maps: list[int]) -> None:
        for map_id in [m for m in self._map_boxes if m not in maps]:
            self._map_boxes.pop(map_id).remove()
        with self.maps_folder:
            for map_id in [m for m in maps if m not in self._map_boxes]:
                r, g, b = map_color(map_id)
                box = self.client.gui.add_checkbox(f"Map {map_id}", map_id not in self.view.hidden_maps,
                                                   hint=f"colour #{r:02x}{g:02x}{b:02x}")
                self._on(box, lambda value, m=map_id: lambda view, _: view.with_map(m, bool(value)))
                self._map_boxes[map_id] = box
        for map_id, box in self._map_boxes.items():
            if box.value != (map_id not in self.view.hidden_maps):
                box.value = map_id not in self.view.hidden_maps

    def _sync_frames(self, shadows: Shadows) -> None:
        """Add and remove this browser's shadow frames. Removing a frame removes this browser's
        frames below it too (viser's scope-local cascade): those are added again if still wanted."""
        remove, add = shadows.changes(self._frames)
        for path in remove:
            if path not in self._frames:
                continue  # went with a parent removed before it
            self._frames.pop(path)
            self._frame_handles.pop(path).remove()
            for below in [p for p in self._frames if p.startswith(path + "/")]:
                self._frames.pop(below)
                self._frame_handles.pop(below)
                if below in shadows.frames:
                    add[below] = shadows.frames[below]
        for path, token in sorted(add.items(), key=lambda item: item[0].count("/")):
            self._frame_handles[path] = self._add_shadow(path, shadows)
            self._frames[path] = token
        self._cut = shadows.meshes

    def _add_shadow(self, path: str, shadows: Shadows) -> viser.SceneNodeHandle:
        """This browser's node at ``path``: a frame (shown or hidden), or the part of a chunk
        its crop box cuts (in its vertex colours or its map's)."""
        if path in shadows.frames:
            return self.client.scene.add_frame(path, show_axes=False, visible=shadows.frames[path])
        cut = shadows.meshes[path]
        if cut.color is not None:
            return self.client.scene.add_mesh_simple(path, cut.chunk.vertices, cut.chunk.faces, color=cut.color)
        mesh = trimesh.Trimesh(cut.chunk.vertices, cut.chunk.faces, vertex_colors=cut.chunk.colors, process=False)
        return self.client.scene.add_mesh_trimesh(path, mesh)

    def _sync_box(self, shown: str | None) -> None:
        """The crop box's outline in this browser's scene, and its cropped mesh's links."""
        box = self.view.crop
        if (box, shown) == self._box:
            return
        self._box = (box, shown)
        if self._box_handle is not None:
            self._box_handle.remove()
            self._box_handle = None
        if box is None:
            self.crop_note.content = ""
            return
        self._box_handle = self.client.scene.add_line_segments("/crop_box", box.segments(), colors=CROP_COLOR,
                                                               thickness=2.0, thickness_units="screen")
        if shown is not None:
            links = " · ".join(f"[{f.upper()}](/api/sessions/{shown}/mesh?format={f}&crop={box.query()})"
                               for f in ("ply", "glb", "obj"))
            self.crop_note.content = f"Cropped mesh: {links}"

    def set_crop_fields(self, lo, hi) -> None:
        """Put a box in the crop fields (and in the view, if cropping is on)."""
        self.crop_min.value, self.crop_max.value = tuple(map(float, lo)), tuple(map(float, hi))

    @property
    def frames(self) -> dict[str, bool]:
        """The shadow frames this browser has now: path -> visible."""
        return dict(self._frames)
