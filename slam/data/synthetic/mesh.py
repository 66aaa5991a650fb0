"""Ground-truth triangle mesh of a synthetic scene, coloured by the same textures as the renders.

Flat faces are exact (the ray caster and the mesh agree to float precision there); spheres and
cylinder sides are tessellated finely enough that the chord error stays below ~0.1 mm for the
radii :func:`make_scene` uses. Each face of a box carries its own vertices (no sharing across an
edge), so every vertex has exactly one normal and its colour equals the render's colour at that
point. Triangles wind counter-clockwise seen from the visible side (outside objects, inside the
room), so trimesh's face normals point towards the cameras.

Surfaces hidden by construction are left out where cheap (bottoms of objects resting on a
support); the floor under furniture is kept, as in the GT meshes of real datasets. Boxes that
fill the room's full height (the ``hall``'s central block and its facade panels) are solid
pillars: their top and bottom faces and every triangle lying wholly inside or on another pillar
(the floor and ceiling under the block, the block's faces behind the facades) are dropped too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import trimesh

from slam.data.synthetic.scene import Box, Cylinder, Primitive, Room, Scene, Sphere, surface_colour

SPHERE_SUBDIVISIONS = 5
"""Icosphere level: 20 * 4^5 faces; chord error below 1e-4 * radius."""
CYLINDER_SEGMENTS = 160
"""Facets around the axis: chord error radius * (1 - cos(pi / 160)) ~ 2e-4 * radius."""


@dataclass(frozen=True)
class _Part:
    """One surface's triangles: (M, 3) vertices, (F, 3) int faces, (M, 3) unit normals."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    surface: int


def _grid_faces(n1: int, n2: int) -> np.ndarray:
    """Triangles of a (n1 + 1) x (n2 + 1) vertex grid indexed ``i * (n2 + 1) + j``.

    Counter-clockwise around ``cross(d/di, d/dj)``: two triangles per cell.
    """
    i, j = np.meshgrid(np.arange(n1), np.arange(n2), indexing="ij")
    a = (i * (n2 + 1) + j).ravel()
    b = a + (n2 + 1)  # (i + 1, j)
    return np.concatenate([np.stack([a, b, b + 1], 1), np.stack([a, b + 1, a + 1], 1)])


def _rectangle(corner: np.ndarray, e1: np.ndarray, e2: np.ndarray, spacing: float, surface: int) -> _Part:
    """Grid over ``corner + s e1 + t e2`` (s, t in [0, 1]), facing ``cross(e1, e2)``."""
    n1 = max(1, math.ceil(np.linalg.norm(e1) / spacing))
    n2 = max(1, math.ceil(np.linalg.norm(e2) / spacing))
    s, t = np.meshgrid(np.linspace(0, 1, n1 + 1), np.linspace(0, 1, n2 + 1), indexing="ij")
    vertices = corner + s.reshape(-1, 1) * e1 + t.reshape(-1, 1) * e2
    normal = np.cross(e1, e2)
    normals = np.broadcast_to(normal / np.linalg.norm(normal), vertices.shape).copy()
    return _Part(vertices, _grid_faces(n1, n2), normals, surface)


def _box_faces(lo: np.ndarray, hi: np.ndarray, *, inward: bool, skip_bottom: bool, spacing: float,
               surface_of_face: list[int]) -> list[_Part]:
    """The six faces of the box [lo, hi] (local axes), facing outwards or (``inward``) inwards.

    ``surface_of_face[2 * axis + side]`` gives each face's surface id (side 1 = the ``hi`` face).
    """
    parts = []
    size = hi - lo
    for axis in range(3):
        j, k = (axis + 1) % 3, (axis + 2) % 3
        e_j = np.eye(3)[j] * size[j]
        e_k = np.eye(3)[k] * size[k]
        for side in (0, 1):
            if skip_bottom and axis == 2 and side == 0:
                continue
            corner = lo.copy()
            corner[axis] = hi[axis] if side else lo[axis]
            # cross(e_j, e_k) = +e_axis: keep that order when the visible side is +axis.
            faces_plus = (side == 1) != inward
            e1, e2 = (e_j, e_k) if faces_plus else (e_k, e_j)
            parts.append(_rectangle(corner, e1, e2, spacing, surface_of_face[2 * axis + side]))
    return parts


def _room_parts(room: Room, spacing: float) -> list[_Part]:
    return _box_faces(np.asarray(room.lo, float), np.asarray(room.hi, float), inward=True, skip_bottom=False,
                      spacing=spacing, surface_of_face=list(range(6)))


def _box_parts(box: Box, surface: int, spacing: float) -> list[_Part]:
    h = np.asarray(box.half_size, float)
    local = _box_faces(-h, h, inward=False, skip_bottom=not box.mesh_bottom, spacing=spacing,
                       surface_of_face=[surface] * 6)
    R, c = box.rotation, np.asarray(box.centre, float)
    return [_Part(p.vertices @ R.T + c, p.faces, p.normals @ R.T, surface) for p in local]


def _sphere_parts(sphere: Sphere, surface: int) -> list[_Part]:
    unit = trimesh.creation.icosphere(subdivisions=SPHERE_SUBDIVISIONS, radius=1.0)
    normals = np.asarray(unit.vertices, float)
    return [_Part(normals * sphere.radius + np.asarray(sphere.centre, float), np.asarray(unit.faces), normals, surface)]


def _drop_degenerate(part: _Part) -> _Part:
    v = part.vertices[part.faces]
    area2 = np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    return _Part(part.vertices, part.faces[area2 > 1e-12], part.normals, part.surface)


def _cylinder_parts(cyl: Cylinder, surface: int, spacing: float) -> list[_Part]:
    base = np.asarray(cyl.base, float)
    theta = np.linspace(0.0, 2 * np.pi, CYLINDER_SEGMENTS + 1)
    theta[-1] = 0.0  # close the seam exactly
    ring = np.stack([np.cos(theta), np.sin(theta), np.zeros_like(theta)], 1)  # (S + 1, 3)
    # Side: grid over (angle i, height j); d/di x d/dj = tangent x z = outward.
    n_h = max(1, math.ceil(cyl.height / spacing))
    z = np.linspace(0.0, cyl.height, n_h + 1)
    side_v = (cyl.radius * ring[:, None, :] + z[None, :, None] * np.eye(3)[2]).reshape(-1, 3) + base
    side_n = np.repeat(ring, n_h + 1, axis=0)
    parts = [_Part(side_v, _grid_faces(CYLINDER_SEGMENTS, n_h), side_n, surface)]
    # Caps: polar grid over (ring k, angle i); d/dk x d/di = radial x tangent = +z.
    n_r = max(1, math.ceil(cyl.radius / spacing))
    radii = np.linspace(0.0, cyl.radius, n_r + 1)
    cap_xy = (radii[:, None, None] * ring[None, :, :]).reshape(-1, 3)
    for z_cap, up in ((cyl.height, True), (0.0, False)):
        if not up and not cyl.mesh_bottom:
            continue
        faces = _grid_faces(n_r, CYLINDER_SEGMENTS)
        if not up:
            faces = faces[:, ::-1]
        normals = np.broadcast_to([0.0, 0.0, 1.0 if up else -1.0], cap_xy.shape).copy()
        parts.append(_drop_degenerate(_Part(cap_xy + base + [0.0, 0.0, z_cap], faces, normals, surface)))
    return parts


def _primitive_parts(prim: Primitive, surface: int, spacing: float) -> list[_Part]:
    if isinstance(prim, Box):
        return _box_parts(prim, surface, spacing)
    if isinstance(prim, Sphere):
        return _sphere_parts(prim, surface)
    return _cylinder_parts(prim, surface, spacing)


_PILLAR_EPS = 1e-6
"""Tolerance (metres) of the pillar tests: spanning floor to ceiling, lying on a pillar."""


def _pillars(scene: Scene) -> list[tuple[int, Box]]:
    """(surface id, box) of every box spanning the room from floor to ceiling."""
    z0, z1 = scene.room.lo[2], scene.room.hi[2]
    return [(6 + i, p) for i, p in enumerate(scene.primitives)
            if isinstance(p, Box) and abs(p.centre[2] - p.half_size[2] - z0) < _PILLAR_EPS
            and abs(p.centre[2] + p.half_size[2] - z1) < _PILLAR_EPS]


def _inside_box(box: Box, points: np.ndarray) -> np.ndarray:
    """(M, 3) points -> (M,) bool, inside or on the closed ``box`` (within :data:`_PILLAR_EPS`)."""
    local = (points - np.asarray(box.centre, float)) @ box.rotation
    return np.all(np.abs(local) <= np.asarray(box.half_size, float) + _PILLAR_EPS, axis=1)


def _cull_hidden_by_pillars(parts: list[_Part], pillars: list[tuple[int, Box]]) -> list[_Part]:
    """Drop triangles wholly inside or on a pillar other than their own surface, and the pillars'
    horizontal faces (on the floor and ceiling); unused vertices go too."""
    out = []
    for part in parts:
        inside = np.zeros(len(part.vertices), dtype=bool)
        for surface, box in pillars:
            if surface != part.surface:
                inside |= _inside_box(box, part.vertices)
        hidden = inside[part.faces].all(axis=1)
        if part.surface in {surface for surface, _ in pillars} and abs(part.normals[0, 2]) > 0.5:
            hidden[:] = True  # a pillar's top or bottom face
        if not hidden.any():
            out.append(part)
            continue
        faces = part.faces[~hidden]
        used = np.unique(faces)
        if used.size == 0:
            continue
        remap = np.full(len(part.vertices), -1)
        remap[used] = np.arange(used.size)
        out.append(_Part(part.vertices[used], remap[faces], part.normals[used], part.surface))
    return out


def gt_mesh(scene: Scene, spacing: float = 0.1) -> trimesh.Trimesh:
    """Triangle mesh of every surface of ``scene`` with vertex colours from its textures.

    Args:
        spacing: target vertex spacing on flat faces and cylinder heights, metres.
    Returns:
        A trimesh in the world frame (z up, metres) with (V, 4) uint8 vertex colours; vertices
        are not merged (``process=False``) so each keeps its surface's colour and normal.
    """
    if spacing <= 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    parts = _room_parts(scene.room, spacing)
    for i, prim in enumerate(scene.primitives):
        parts.extend(_primitive_parts(prim, 6 + i, spacing))
    pillars = _pillars(scene)
    if pillars:
        parts = _cull_hidden_by_pillars(parts, pillars)
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    vertices = np.concatenate([p.vertices for p in parts])
    faces = np.concatenate([p.faces + off for p, off in zip(parts, offsets)])
    normals = np.concatenate([p.normals for p in parts])
    surface = np.concatenate([np.full(len(p.vertices), p.surface) for p in parts])
    rgb = surface_colour(scene, surface, np.ascontiguousarray(vertices.T), np.ascontiguousarray(normals.T)).T
    colours = np.concatenate([np.round(rgb * 255), np.full((len(rgb), 1), 255.0)], 1).astype(np.uint8)
    return trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=colours, process=False)
