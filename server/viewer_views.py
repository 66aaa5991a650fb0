"""What one browser chose to see in the 3D viewer, as plain data: no viser.

Every browser (viser client) has its own controls and its own :class:`ClientView`: the session
it shows, which layers, which maps, colour by map, follow the camera, the surface, a crop box. The heavy
scene (mesh chunks, trajectories) is shared: the server sends it once to every browser, in
frames whose shared visibility is :data:`SHARED_VISIBLE`. A browser whose choice differs from
that gets client-scoped frames of the same names that shadow the shared ones for it alone
(viser's display rule: a client's own node of a name wins over the server's, children
included); :func:`shadows` lists those frames, and the facade (``server.viewer_clients``) adds
and removes them. Colour by map is no recolouring per browser either: the shared scene holds a
second, map-coloured variant of the meshes (``tinted``) and of the trajectories
(``trajectory_maps``), hidden for everyone, made visible by a browser's shadow. A crop box
shadows the chunks it hides or cuts (``server.viewer_crop``).

A browser's state dies with its connection (a reload starts from :class:`ClientView`'s
defaults). It outlives a change of session: the layers, colouring, surface and follow it chose
apply to whatever session it shows next, so a new session comes up as that browser left the
last one; only the maps it hid are forgotten, since map ids name other maps in another session.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from server.viewer_crop import CropBox, CroppedChunk, crop_meshes
from server.viewer_state import map_color

LAYERS = ("meshes", "trajectory", "camera", "keyframes", "loops", "regions")
"""The layers a browser can switch (its "Layers" folder)."""
VARIANT_LAYERS = ("tinted", "trajectory_maps")
"""The map-coloured variants of ``meshes`` and ``trajectory`` in the shared scene."""
SHARED_VISIBLE = frozenset({"meshes", "trajectory", "camera", "keyframes", "loops"})
"""The layers the shared scene shows; the maps' region outlines (several metres each) would
dwarf a collaborative session's meshes, and the variants are for the browsers that ask."""
MAP_LAYERS = ("meshes", "tinted", "keyframes", "regions")
"""Layers that hold a node per map (``<layer>/map_<m>``): what hiding a map hides."""
SURFACES = ("mesh", "neural colour", "neural depth", "neural normals", "colour | depth")
"""What the viewer shows of the surface: the mesh, or one of the neural renders."""


@dataclass(frozen=True)
class ClientView:
    """One browser's choices (module doc); a change makes a new one (``with_*``)."""

    session: str | None = None
    """The session this browser picked in its own dropdown; None: the page's selection."""
    layers: frozenset[str] = SHARED_VISIBLE
    """The switched-on layers of :data:`LAYERS`."""
    hidden_maps: frozenset[int] = frozenset()
    """Maps of the shown session this browser hid."""
    tint_by_map: bool = False
    trajectory_by_map: bool = False
    follow: bool = False
    """Keep this browser's camera behind the tracked camera."""
    surface: str = SURFACES[0]
    crop: CropBox | None = None
    """The box this browser crops the meshes (and neural views) to, or None."""

    def shown(self, selected: str | None) -> str | None:
        """The session this browser shows, given the page's selection."""
        return self.session or selected

    def with_session(self, session: str | None, selected: str | None) -> ClientView:
        """Picked ``session``; picking the page's selection puts the browser back in step with
        the page. The maps hidden in the session it leaves are forgotten."""
        own = None if session == selected else session
        if self.shown(selected) == (own or selected):
            return replace(self, session=own)
        return replace(self, session=own, hidden_maps=frozenset())

    def page_moved(self) -> ClientView:
        """The page selected another session: a browser in step with it forgets its hidden maps."""
        return self if self.session is not None else replace(self, hidden_maps=frozenset())

    def with_layer(self, name: str, on: bool) -> ClientView:
        if name not in LAYERS:
            raise ValueError(f"layer must be one of {LAYERS}, got {name!r}")
        return replace(self, layers=self.layers | {name} if on else self.layers - {name})

    def with_map(self, map_id: int, visible: bool) -> ClientView:
        hidden = self.hidden_maps - {map_id} if visible else self.hidden_maps | {map_id}
        return replace(self, hidden_maps=frozenset(hidden))

    def with_surface(self, surface: str) -> ClientView:
        if surface not in SURFACES:
            raise ValueError(f"surface must be one of {SURFACES}, got {surface!r}")
        return replace(self, surface=surface)

    def with_crop(self, on: bool, lo, hi) -> ClientView:
        """Crop to the box [lo, hi] (ValueError unless every min is below its max), or not."""
        return replace(self, crop=CropBox.of(lo, hi) if on else None)

    def layer_visible(self, layer: str) -> bool:
        """Whether this browser sees a shared layer or variant (module doc)."""
        meshes = "meshes" in self.layers and self.surface == "mesh"
        trajectory = "trajectory" in self.layers
        derived = {"meshes": meshes and not self.tint_by_map, "tinted": meshes and self.tint_by_map,
                   "trajectory": trajectory and not self.trajectory_by_map,
                   "trajectory_maps": trajectory and self.trajectory_by_map}
        return derived.get(layer, layer in self.layers)


@dataclass(frozen=True)
class Shadows:
    """Client-scoped nodes one browser needs (see :func:`shadows`): frames (path -> visible)
    and the mesh chunks its crop box cuts (path -> the part inside)."""

    frames: dict[str, bool] = field(default_factory=dict)
    meshes: dict[str, CroppedChunk] = field(default_factory=dict)

    def tokens(self) -> dict[str, object]:
        """path -> what stands there: a frame's visibility, a cut chunk's token."""
        return {**self.frames, **{path: mesh.token for path, mesh in self.meshes.items()}}

    def changes(self, have: dict[str, object]) -> tuple[list[str], dict[str, object]]:
        """(paths to remove, deepest first; paths to add with their tokens, parents first) to turn
        the nodes a browser ``have`` (path -> token) into these."""
        want = self.tokens()
        remove = [p for p in have if p not in want or want[p] != have[p]]
        add = {p: v for p, v in want.items() if p not in have or have[p] != v}
        return sorted(remove, key=_depth, reverse=True), dict(sorted(add.items(), key=lambda item: _depth(item[0])))


def _depth(path: str) -> int:
    return path.count("/")


MapMeshes = dict[int, tuple[np.ndarray, dict]]
"""map id -> (T_world_map (4, 4), {chunk key: MeshChunk in the map frame}) of the shown session."""


def shadows(view: ClientView, selected: str | None, sessions: set[str] | list[str],
            meshes: MapMeshes | None = None) -> Shadows:
    """The nodes that make the shared scene look as ``view`` wants in one browser.

    The shared scene shows the page's session ``selected`` (of ``sessions``) with the layers of
    :data:`SHARED_VISIBLE` and every map. A browser that picked another session shadows both
    session roots; a layer it sees otherwise than the shared scene gets a frame of its own, and
    so does each hidden map in each map layer it sees (under a hidden layer it needs none).
    With a crop box, the chunks of ``meshes`` (the shown session's) that it hides or cuts in the
    mesh layer it sees are shadowed too (``server.viewer_crop``)."""
    frames: dict[str, bool] = {}
    shown = view.shown(selected)
    if shown not in sessions:
        return Shadows(frames)
    if shown != selected:
        frames[f"/sessions/{shown}"] = True
        if selected in sessions:
            frames[f"/sessions/{selected}"] = False
    for layer in LAYERS + VARIANT_LAYERS:
        visible = view.layer_visible(layer)
        if visible != (layer in SHARED_VISIBLE):
            frames[f"/sessions/{shown}/{layer}"] = visible
        if visible and layer in MAP_LAYERS:
            frames.update({f"/sessions/{shown}/{layer}/map_{m}": False for m in sorted(view.hidden_maps)})
    cut: dict[str, CroppedChunk] = {}
    for layer in ("meshes", "tinted"):
        if view.crop is None or not meshes or not view.layer_visible(layer):
            continue
        for map_id, (T_world_map, chunks) in sorted(meshes.items()):
            if map_id not in view.hidden_maps:
                hidden, parts = crop_meshes(view.crop, f"/sessions/{shown}/{layer}/map_{map_id}", T_world_map,
                                            chunks, map_color(map_id) if layer == "tinted" else None)
                frames.update(hidden)
                cut.update(parts)
    return Shadows(frames, cut)
