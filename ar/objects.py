"""Virtual objects: triangle meshes, their placement in the world, built-in shapes and the
object spec of the HTTP API / CLI.

An object's vertex ``v`` (object frame) lands in the world at
``p_world = R_world_obj @ (scale * v) + t_world_obj``; ``T_world_obj`` is rigid and the scale
is kept apart so that a JSON spec can say "a 20 cm cube" without touching the pose.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

DEFAULT_ALBEDO = (0.75, 0.75, 0.75)
"""Colour of a mesh that has neither vertex colours nor an object colour."""

SHAPES = ("cube", "sphere", "cylinder", "axes")

UPRIGHT = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""Rotation that stands an object upright in a run's world: its +z (the shapes' axis) along the
world's up, -y (a run's world is its first camera's frame, OpenCV axes: y points down)."""


class ObjectSpecError(ValueError):
    """An object spec entry is malformed; the message names the entry and the key."""


def _frozen_array(value: Any, dtype: type, shape_tail: tuple[int, ...], name: str) -> np.ndarray:
    """A read-only C-contiguous copy of ``value`` with shape ``(N, *shape_tail)``."""
    array = np.array(value, dtype=dtype, copy=True)
    if array.ndim != 1 + len(shape_tail) or array.shape[1:] != shape_tail:
        raise ValueError(f"{name}: expected shape (N, {', '.join(map(str, shape_tail))}), got {array.shape}")
    array.setflags(write=False)
    return array


@dataclass(frozen=True, eq=False)
class ObjectMesh:
    """A triangle mesh in its own object frame (metres before the object's scale).

    Attributes:
        vertices: (V, 3) float32 positions.
        faces: (F, 3) int32 vertex indices; winding does not matter (two-sided shading).
        vertex_colors: (V, 3) float32 RGB in [0, 1], or None (the object's colour or grey).
        vertex_normals: (V, 3) float32 unit normals for smooth shading, or None for flat
            shading by face normals (right for boxes and for assets whose shared vertices
            would otherwise round off hard edges).
        outward_winding: derived, not passed: +1 if the mesh is closed and its faces wind
            counter-clockwise seen from outside (right-hand normal points out), -1 if closed
            and wound the other way, 0 if not closed. The rasteriser may skip the back faces
            of closed meshes, which cannot be seen from outside.
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_colors: np.ndarray | None = None
    vertex_normals: np.ndarray | None = None
    outward_winding: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        vertices = _frozen_array(self.vertices, np.float32, (3,), "ObjectMesh.vertices")
        faces = _frozen_array(self.faces, np.int32, (3,), "ObjectMesh.faces")
        if len(vertices) == 0 or len(faces) == 0:
            raise ValueError("ObjectMesh: needs at least one vertex and one face")
        if not np.isfinite(vertices).all():
            raise ValueError("ObjectMesh.vertices: contains NaN or inf")
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise ValueError(f"ObjectMesh.faces: indices must lie in [0, {len(vertices) - 1}]")
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "faces", faces)
        for name in ("vertex_colors", "vertex_normals"):
            value = getattr(self, name)
            if value is None:
                continue
            array = _frozen_array(value, np.float32, (3,), f"ObjectMesh.{name}")
            if len(array) != len(vertices):
                raise ValueError(f"ObjectMesh.{name}: {len(array)} rows for {len(vertices)} vertices")
            if not np.isfinite(array).all():
                raise ValueError(f"ObjectMesh.{name}: contains NaN or inf")
            object.__setattr__(self, name, array)
        object.__setattr__(self, "outward_winding", _outward_winding(vertices, faces))

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])


def _outward_winding(vertices: np.ndarray, faces: np.ndarray) -> int:
    """+1 / -1 / 0 as ``ObjectMesh.outward_winding``.

    Closed means: with vertices identified by position (meshes often split vertices to carry
    normals or colours), every directed edge occurs once and its reverse once. The sign of
    the enclosed volume then says which way the faces wind; it must agree between the
    connected parts, since one inside-out part would otherwise be culled from the front.
    """
    _, position_id = np.unique(vertices, axis=0, return_inverse=True)
    corners = position_id.reshape(-1)[faces].astype(np.int64)
    if (corners == np.roll(corners, 1, axis=1)).any():  # a face with a repeated corner
        return 0
    start = corners.reshape(-1)
    end = np.roll(corners, -1, axis=1).reshape(-1)
    num_ids = int(position_id.max()) + 1
    directed = start * num_ids + end
    reverse = end * num_ids + start
    if len(np.unique(directed)) != len(directed) or not np.array_equal(np.sort(directed), np.sort(reverse)):
        return 0
    import scipy.sparse.csgraph  # here, not at import: ``voxfusion render`` imports this module too

    graph = scipy.sparse.coo_matrix((np.ones(len(start)), (start, end)), shape=(num_ids, num_ids))
    _, part_of_id = scipy.sparse.csgraph.connected_components(graph, directed=False)
    a, b, c = vertices.astype(np.float64)[faces].transpose(1, 0, 2)
    face_volume = np.einsum("ti,ti->t", a, np.cross(b, c))  # 6x signed volume of the cone to 0
    part_volume = np.bincount(part_of_id[corners[:, 0]], weights=face_volume)
    part_volume = part_volume[np.bincount(part_of_id[corners[:, 0]]) > 0]
    extent = np.ptp(vertices, axis=0).max()
    if (np.abs(part_volume) <= 1e-9 * extent**3).any():
        return 0
    if (part_volume > 0).all():
        return 1
    return -1 if (part_volume < 0).all() else 0


@dataclass(frozen=True, eq=False)
class VirtualObject:
    """A mesh placed in the world.

    Attributes:
        mesh: the shape in its object frame.
        T_world_obj: (4, 4) float64 rigid object-to-world transform.
        scale: uniform scale applied in the object frame, > 0.
        color: (3,) float32 RGB in [0, 1] painted over the whole mesh, or None to use the
            mesh's vertex colours.
    """

    mesh: ObjectMesh
    T_world_obj: np.ndarray
    scale: float = 1.0
    color: np.ndarray | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.mesh, ObjectMesh):
            raise TypeError(f"VirtualObject.mesh: expected ObjectMesh, got {type(self.mesh).__name__}")
        T = np.array(self.T_world_obj, dtype=np.float64, copy=True)
        _check_rigid(T, "VirtualObject.T_world_obj")
        T.setflags(write=False)
        object.__setattr__(self, "T_world_obj", T)
        scale = float(self.scale)
        if not np.isfinite(scale) or scale <= 0:
            raise ValueError(f"VirtualObject.scale: must be a positive finite number, got {self.scale!r}")
        object.__setattr__(self, "scale", scale)
        if self.color is not None:
            color = np.array(self.color, dtype=np.float32, copy=True)
            if color.shape != (3,) or not np.isfinite(color).all() or color.min() < 0 or color.max() > 1:
                raise ValueError(f"VirtualObject.color: expected 3 numbers in [0, 1], got {self.color!r}")
            color.setflags(write=False)
            object.__setattr__(self, "color", color)

    def world_vertices(self) -> np.ndarray:
        """(V, 3) float64 vertex positions in the world frame."""
        R, t = self.T_world_obj[:3, :3], self.T_world_obj[:3, 3]
        return (self.mesh.vertices.astype(np.float64) * self.scale) @ R.T + t

    def world_vertex_normals(self) -> np.ndarray | None:
        """(V, 3) float64 unit normals in the world frame, or None for flat shading."""
        if self.mesh.vertex_normals is None:
            return None
        return self.mesh.vertex_normals.astype(np.float64) @ self.T_world_obj[:3, :3].T

    def vertex_albedo(self) -> np.ndarray:
        """(V, 3) float32 base colour per vertex: object colour > vertex colours > grey."""
        num_vertices = len(self.mesh.vertices)
        if self.color is not None:
            return np.broadcast_to(self.color, (num_vertices, 3)).astype(np.float32)
        if self.mesh.vertex_colors is not None:
            return self.mesh.vertex_colors
        return np.broadcast_to(np.float32(DEFAULT_ALBEDO), (num_vertices, 3)).astype(np.float32)


def _check_rigid(T: np.ndarray, name: str, tolerance: float = 1e-3) -> None:
    """Raise ValueError unless T is a finite (4, 4) rotation + translation.

    The tolerance is loose on purpose: poses typed into JSON carry a few decimals only.
    """
    if T.shape != (4, 4):
        raise ValueError(f"{name}: expected a 4x4 matrix, got shape {T.shape}")
    if not np.isfinite(T).all():
        raise ValueError(f"{name}: contains NaN or inf")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=tolerance):
        raise ValueError(f"{name}: last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=tolerance) or np.linalg.det(R) < 0:
        raise ValueError(f"{name}: the 3x3 block must be a rotation (use 'scale' for size)")


# ---------------------------------------------------------------------------------------
# Built-in shapes: unit size, centred at the origin.


def make_shape(name: str) -> ObjectMesh:
    """A built-in unit shape centred at the origin of its object frame (built once, shared:
    meshes are immutable).

    ``cube``: side 1 (flat shaded). ``sphere``: diameter 1 (icosphere, smooth).
    ``cylinder``: diameter 1, height 1 along the object z axis (smooth side, flat caps).
    ``axes``: three boxes of length 1 from the origin along +x (red), +y (green), +z (blue),
    0.04 thick.
    """
    builders: dict[str, Callable[[], ObjectMesh]] = {
        "cube": _make_cube,
        "sphere": _make_sphere,
        "cylinder": _make_cylinder,
        "axes": _make_axes,
    }
    if name not in builders:
        raise ValueError(f"make_shape: unknown shape {name!r}, expected one of {', '.join(SHAPES)}")
    return _cached_shape(name, builders[name])


@functools.lru_cache(maxsize=None)
def _cached_shape(name: str, builder: Callable[[], ObjectMesh]) -> ObjectMesh:
    return builder()


# trimesh.creation.box's corners (x, y, z in {0, 1}, z fastest) and outward faces, kept here
# so that a cube or axes needs no trimesh import (seconds in a command-line run).
_BOX_FACES = np.array([[1, 3, 0], [4, 1, 0], [0, 3, 2], [2, 4, 0], [1, 7, 3], [5, 1, 4],
                       [5, 7, 1], [3, 7, 2], [6, 4, 2], [2, 7, 6], [6, 5, 4], [7, 5, 6]], dtype=np.int64)


def _box(extents) -> tuple[np.ndarray, np.ndarray]:
    """(8, 3) vertices and (12, 3) faces of a box of these extents centred at 0, as
    ``trimesh.creation.box(extents=extents)`` makes them."""
    corners = np.array([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)], dtype=np.float64)
    return (corners - 0.5) * np.asarray(extents, dtype=np.float64), _BOX_FACES.copy()


def _make_cube() -> ObjectMesh:
    vertices, faces = _box((1.0, 1.0, 1.0))
    return ObjectMesh(vertices=vertices, faces=faces)


def _make_sphere(subdivisions: int = 3) -> ObjectMesh:
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.5)
    vertices = np.asarray(sphere.vertices)
    return ObjectMesh(
        vertices=vertices,
        faces=sphere.faces,
        vertex_normals=vertices / np.linalg.norm(vertices, axis=1, keepdims=True),
    )


def _make_cylinder(sections: int = 48) -> ObjectMesh:
    """Side and caps get their own vertices so the side is smooth and the rims stay sharp."""
    angles = np.linspace(0.0, 2 * np.pi, sections, endpoint=False)
    ring = np.stack([0.5 * np.cos(angles), 0.5 * np.sin(angles), np.zeros(sections)], axis=1)
    bottom, top = ring + [0, 0, -0.5], ring + [0, 0, 0.5]
    radial = np.stack([np.cos(angles), np.sin(angles), np.zeros(sections)], axis=1)
    i = np.arange(sections)
    j = (i + 1) % sections
    # Side: vertices [bottom ring | top ring].
    side_faces = np.concatenate([np.stack([i, j, sections + j], 1), np.stack([i, sections + j, sections + i], 1)])
    # Caps: ring copies plus a centre vertex each.
    base = 2 * sections
    cap_bottom = np.stack([np.full(sections, base + sections), base + j, base + i], 1)
    top_base = base + sections + 1
    cap_top = np.stack([np.full(sections, top_base + sections), top_base + i, top_base + j], 1)
    vertices = np.concatenate([bottom, top, bottom, [[0, 0, -0.5]], top, [[0, 0, 0.5]]])
    normals = np.concatenate(
        [radial, radial, np.tile([0, 0, -1.0], (sections + 1, 1)), np.tile([0, 0, 1.0], (sections + 1, 1))]
    )
    faces = np.concatenate([side_faces, cap_bottom, cap_top])
    return ObjectMesh(vertices=vertices, faces=faces, vertex_normals=normals)


def _make_axes(length: float = 1.0, thickness: float = 0.04) -> ObjectMesh:
    """Three boxes; with no vertex normals they are flat shaded, which keeps their edges crisp."""
    vertices, faces, colors = [], [], []
    offset = 0
    for axis, color in enumerate(np.eye(3)):
        extents = np.full(3, thickness)
        extents[axis] = length
        centre = np.zeros(3)
        centre[axis] = length / 2
        box_vertices, box_faces = _box(extents)
        vertices.append(box_vertices + centre)
        faces.append(box_faces + offset)
        colors.append(np.tile(color, (len(box_vertices), 1)))
        offset += len(box_vertices)
    return ObjectMesh(
        vertices=np.concatenate(vertices), faces=np.concatenate(faces), vertex_colors=np.concatenate(colors)
    )


# ---------------------------------------------------------------------------------------
# The object spec of the HTTP API and the CLI (DESIGN.md):
#   [{"shape": "cube"} | {"asset": id}, "T_world_obj": 4x4, "scale": s, "color": [r, g, b]]

_SPEC_KEYS = {"shape", "asset", "T_world_obj", "scale", "color"}

AssetResolver = Callable[[str], ObjectMesh]
"""Maps an uploaded asset id to its mesh; raises KeyError (or any error) for unknown ids."""


def load_objects_json(
    spec: str | Path | Sequence[Mapping[str, Any]] | Mapping[str, Any],
    asset_resolver: AssetResolver | None = None,
) -> list[VirtualObject]:
    """Parse the object spec into virtual objects.

    Args:
        spec: a path to a JSON file, a list of object entries, or a dict ``{"objects": [...]}``.
            Each entry has exactly one of ``shape`` (one of SHAPES) or ``asset`` (an id);
            ``T_world_obj`` (4x4 nested list, default identity), ``scale`` (default 1),
            ``color`` ([r, g, b] in [0, 1], default: the mesh's own colours). Unknown keys
            are an error, so a misspelt key does not silently do nothing.
        asset_resolver: turns an ``asset`` id into a mesh; required when an entry uses one.

    Raises:
        ObjectSpecError naming the entry (``objects[i].key``) or the file.
    """
    entries = _spec_entries(spec)
    shapes: dict[str, ObjectMesh] = {}
    assets: dict[str, ObjectMesh] = {}
    objects = []
    for index, entry in enumerate(entries):
        where = f"objects[{index}]"
        if not isinstance(entry, Mapping):
            raise ObjectSpecError(f"{where}: expected an object (dict), got {type(entry).__name__}")
        unknown = set(entry) - _SPEC_KEYS
        if unknown:
            raise ObjectSpecError(f"{where}: unknown key(s) {sorted(unknown)}, allowed: {sorted(_SPEC_KEYS)}")
        mesh = _spec_mesh(entry, where, shapes, assets, asset_resolver)
        try:
            objects.append(
                VirtualObject(
                    mesh=mesh,
                    T_world_obj=_spec_matrix(entry.get("T_world_obj"), f"{where}.T_world_obj"),
                    scale=_spec_scale(entry.get("scale", 1.0), f"{where}.scale"),
                    color=_spec_color(entry.get("color"), f"{where}.color"),
                )
            )
        except ValueError as error:
            raise ObjectSpecError(f"{where}: {error}") from error
    return objects


def _spec_entries(spec: Any) -> Sequence[Any]:
    if isinstance(spec, (str, Path)):
        path = Path(spec)
        try:
            spec = json.loads(path.read_text())
        except OSError as error:
            raise ObjectSpecError(f"{path}: cannot read object spec ({error})") from error
        except json.JSONDecodeError as error:
            raise ObjectSpecError(f"{path}: not valid JSON ({error})") from error
    if isinstance(spec, Mapping):
        if "objects" not in spec:
            raise ObjectSpecError("object spec: a dict must hold the list under 'objects'")
        spec = spec["objects"]
    if not isinstance(spec, Sequence) or isinstance(spec, (str, bytes)):
        raise ObjectSpecError(f"object spec: expected a list of objects, got {type(spec).__name__}")
    return spec


def _spec_mesh(
    entry: Mapping[str, Any],
    where: str,
    shapes: dict[str, ObjectMesh],
    assets: dict[str, ObjectMesh],
    asset_resolver: AssetResolver | None,
) -> ObjectMesh:
    """The entry's mesh; each shape or asset id is built or resolved once per spec."""
    if ("shape" in entry) == ("asset" in entry):
        raise ObjectSpecError(f"{where}: needs exactly one of 'shape' or 'asset'")
    if "shape" in entry:
        shape = entry["shape"]
        if shape not in SHAPES:
            raise ObjectSpecError(f"{where}.shape: unknown shape {shape!r}, expected one of {', '.join(SHAPES)}")
        if shape not in shapes:
            shapes[shape] = make_shape(shape)
        return shapes[shape]
    asset_id = entry["asset"]
    if not isinstance(asset_id, str) or not asset_id:
        raise ObjectSpecError(f"{where}.asset: expected a non-empty id string, got {asset_id!r}")
    if asset_resolver is None:
        raise ObjectSpecError(f"{where}.asset: assets are not available here (no asset resolver)")
    if asset_id not in assets:
        try:
            mesh = asset_resolver(asset_id)
        except KeyError as error:
            raise ObjectSpecError(f"{where}.asset: unknown asset id {asset_id!r}") from error
        if not isinstance(mesh, ObjectMesh):
            raise TypeError(f"asset resolver returned {type(mesh).__name__} for {asset_id!r}, expected ObjectMesh")
        assets[asset_id] = mesh
    return assets[asset_id]


def _spec_matrix(value: Any, where: str) -> np.ndarray:
    if value is None:
        return np.eye(4)
    try:
        matrix = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ObjectSpecError(f"{where}: expected a 4x4 list of numbers ({error})") from error
    if matrix.shape != (4, 4):
        raise ObjectSpecError(f"{where}: expected a 4x4 list of numbers, got shape {matrix.shape}")
    return matrix


def _spec_scale(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ObjectSpecError(f"{where}: expected a positive number, got {value!r}")
    return float(value)


def _spec_color(value: Any, where: str) -> np.ndarray | None:
    if value is None:
        return None
    if not isinstance(value, Sequence) or len(value) != 3 or not all(
        isinstance(c, (int, float)) and not isinstance(c, bool) for c in value
    ):
        raise ObjectSpecError(f"{where}: expected [r, g, b] with numbers in [0, 1], got {value!r}")
    return np.array(value, dtype=np.float32)
