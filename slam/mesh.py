"""Coloured meshes of the neural map: marching cubes inside allocated voxels only.

The SDF is sampled on a lattice of ``resolution`` cells per voxel edge. Lattice point ``g``
(integer, global to the map) sits at ``g * voxel_size / resolution`` in the map frame; the
points on a voxel's faces are shared with its neighbours and evaluated once per block. The
map is cut into cubic blocks of ``block_voxels``^3 voxels so that the dense grid handed to
scikit-image stays small whatever the size of the map (and shrinks to the bounding box of
the block's allocated voxels); within a block, lattice points of
unallocated voxels are never decoded and marching cubes skips the cubes of unallocated
voxels, so no surface appears in space that was never observed. Level 0 is the surface (the
SDF is in units of the truncation, see ``slam.render``, which does not move its zero).

Vertex colours come from the colour head at each vertex, plus the fine colour level's residual
there when the map has one (``slam.fine_color``); vertices on block boundaries are
merged, degenerate faces dropped. ``extract_mesh`` places every submap in the world frame by
its ``T_world_map``.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from skimage import measure

from .render import MapView, trilinear_weights
from .transfer import to_device
from .voxels import lookup_sorted, morton_decode, morton_encode, voxel_coords_of

MESH_FORMATS = ("ply", "glb", "obj")

# Vertices closer than 1/_MERGE_SCALE lattice cells are the same vertex. Marching cubes puts
# vertices on lattice edges, so a vertex seen by two blocks differs only by float rounding.
_MERGE_SCALE = 4096.0


@dataclass(frozen=True)
class _BlockSurface:
    """Marching-cubes output of one block, in global lattice units.

    vertices (V, 3) float64, faces (F, 3) int64 into ``vertices``, face_voxel (F,) int64 index
    into ``voxel_codes`` of the voxel that holds each face (used to colour its vertices).
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_voxel: np.ndarray


# ------------------------------------------------------------------ decoding
def _embeddings_at(lattice: torch.Tensor, voxel_index: torch.Tensor, voxel_ijk: torch.Tensor,
                   view: MapView, resolution: int) -> torch.Tensor:
    """Trilinear corner embeddings at lattice coordinates. (S, 3) float64, (S,) -> (S, D).

    Same numbers as ``slam.render.interpolate_embeddings`` at the points
    ``lattice * voxel_size / resolution``, but the position inside the voxel is taken from
    the exact lattice coordinates and the voxel coordinates are decoded once per voxel,
    not once per point (Morton decoding dominated otherwise).
    """
    local = (lattice / resolution - voxel_ijk[voxel_index]).clamp(0.0, 1.0).to(torch.float32)
    weights = trilinear_weights(local)                                  # (S, 8)
    corners = torch.nn.functional.embedding(view.voxel_corners[voxel_index], view.embeddings)
    return torch.einsum("sc,scd->sd", weights, corners)


def _lattice_sdf(lattice_ids: np.ndarray, voxel_index: np.ndarray, view: MapView, decoder,
                 resolution: int, chunk_points: int) -> np.ndarray:
    """SDF at lattice points named by ``slot * P + p``: pattern point p of voxel ``voxel_index[slot]``.

    lattice_ids (S,) sorted int64, voxel_index (n,) rows of ``view.voxel_codes`` (both on the
    host) -> (S,) float32 on the host. The (resolution + 1)^3 embeddings of a voxel are one
    small matmul of fixed trilinear weights with its 8 corner embeddings (the numbers of
    ``interpolate_embeddings``), which is much cheaper than gathering 8 corners per point;
    voxels go in chunks of about ``chunk_points`` points, and every listed point is decoded
    once. The chunks' bounds are found on the host; one upload of the ids and one read of
    the values per call (``slam.transfer``).
    """
    device = view.embeddings.device
    pattern = _lattice_pattern(resolution, device)
    weights = trilinear_weights(pattern.to(torch.float32) / resolution)          # (P, 8)
    num_pattern = pattern.shape[0]
    slots = lattice_ids // num_pattern
    voxels_per_chunk = max(1, chunk_points // num_pattern)
    moved = to_device({"ids": lattice_ids, "voxels": voxel_index}, device)
    ids, voxels = moved["ids"], moved["voxels"]
    out = torch.empty(lattice_ids.shape[0], dtype=torch.float32, device=device)
    for first in range(0, voxel_index.shape[0], voxels_per_chunk):
        lo, hi = (int(i) for i in np.searchsorted(slots, [first, first + voxels_per_chunk]))
        if hi == lo:
            continue
        rows = view.voxel_corners[voxels[first:first + voxels_per_chunk]]
        corners = torch.nn.functional.embedding(rows, view.embeddings)           # (m, 8, D)
        emb = torch.matmul(weights, corners).reshape(-1, corners.shape[-1])      # (m * P, D)
        out[lo:hi] = decoder.sdf(emb[ids[lo:hi] - first * num_pattern])
    return out.cpu().numpy()


def _color_at(lattice: torch.Tensor, voxel_index: torch.Tensor, voxel_ijk: torch.Tensor,
              view: MapView, decoder, resolution: int, chunk_points: int, fine=None) -> torch.Tensor:
    """RGB in [0, 1] at (S, 3) float64 lattice coordinates -> (S, 3): the colour head's, plus
    the fine colour level's residual at the same map-frame points when ``fine`` is given
    (clamped to [0, 1], as views colour the same surface)."""
    out = torch.empty(lattice.shape[0], 3, dtype=torch.float32, device=lattice.device)
    metres_per_cell = view.voxel_size / resolution
    for start in range(0, lattice.shape[0], chunk_points):
        sl = slice(start, start + chunk_points)
        emb = _embeddings_at(lattice[sl], voxel_index[sl], voxel_ijk, view, resolution)
        _, feature = decoder.sdf_and_feature(emb)
        rgb = decoder.color(feature)
        out[sl] = rgb if fine is None else (rgb + fine(lattice[sl] * metres_per_cell)).clamp(0.0, 1.0)
    return out


# -------------------------------------------------------------------- blocks
def _blocks_of(voxel_ijk: np.ndarray, block_voxels: int) -> list[np.ndarray]:
    """Group (Nv, 3) voxel coordinates (host) into cubic blocks -> list of index arrays into Nv."""
    keys = np.floor_divide(voxel_ijk, block_voxels)
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    counts = np.bincount(inverse)
    return np.split(order, np.cumsum(counts)[:-1])


def _lattice_pattern(resolution: int, device: torch.device) -> torch.Tensor:
    """(P, 3) int64 offsets of the (resolution + 1)^3 lattice points of one voxel."""
    a = torch.arange(resolution + 1, device=device)
    return torch.stack(torch.meshgrid(a, a, a, indexing="ij"), -1).reshape(-1, 3)


def _block_surface(voxel_index: np.ndarray, all_ijk: np.ndarray, view: MapView, decoder,
                   resolution: int, chunk_points: int) -> _BlockSurface | None:
    """Marching cubes over one block of voxels; None when it holds no surface.

    voxel_index (n,) rows of ``view.voxel_codes`` in the block; all_ijk (Nv, 3) int64
    coordinates of every voxel of the map. The block's grids are built on the host, where
    marching cubes runs; only the decoding runs on the map's device (``_lattice_sdf``).
    """
    voxel_ijk = all_ijk[voxel_index]
    lo = voxel_ijk.min(0)
    local = voxel_ijk - lo                                            # (n, 3) voxels
    dims = local.max(0) + 1                                           # voxels per axis
    lattice_dims = dims * resolution + 1
    occupancy = np.full(tuple(dims), -1, dtype=np.int64)
    occupancy[local[:, 0], local[:, 1], local[:, 2]] = voxel_index

    # Every lattice point of every allocated voxel, each decoded once: a point shared by
    # neighbours takes one of them, which gives the same value up to rounding since corner
    # embeddings are shared. ``owner`` names it by slot * P + pattern index.
    pattern = _lattice_pattern(resolution, torch.device("cpu")).numpy()
    lattice = local[:, None, :] * resolution + pattern[None]                      # (n, P, 3)
    ids = np.arange(lattice.shape[0] * lattice.shape[1], dtype=np.int64).reshape(lattice.shape[:2])
    owner = np.full(tuple(lattice_dims), -1, dtype=np.int64)
    owner[lattice[..., 0], lattice[..., 1], lattice[..., 2]] = ids
    flat_owner = owner.reshape(-1)
    grid_pos = np.flatnonzero(flat_owner >= 0)
    order = np.argsort(flat_owner[grid_pos], kind="stable")
    lattice_ids = flat_owner[grid_pos][order]
    sdf = _lattice_sdf(lattice_ids, voxel_index, view, decoder, resolution, chunk_points)
    if not (sdf <= 0).any() or not (sdf >= 0).any():
        return None

    volume = np.ones(tuple(lattice_dims), dtype=np.float32)
    volume.reshape(-1)[grid_pos[order]] = sdf
    cube_voxel = _cube_owner(occupancy, resolution)                   # (L-1,)^3 voxel row or -1
    # scikit-image (0.26) runs a cube when ``mask`` is set at its far corner (origin + 1);
    # tests pin this down. Faces are also filtered by the cube they fall in, so a change of
    # convention could drop surface but never add any in unobserved space.
    mask = np.zeros(owner.shape, dtype=bool)
    mask[1:, 1:, 1:] = cube_voxel >= 0
    try:
        verts, faces, _, _ = measure.marching_cubes(volume, level=0.0, mask=mask, allow_degenerate=False)
    except RuntimeError:  # no crossing inside the masked cubes
        return None
    face_voxel = _face_voxel(verts, faces, cube_voxel)
    keep = face_voxel >= 0
    if not keep.any():
        return None
    offset = (lo * resolution).astype(np.float64)
    return _BlockSurface(verts.astype(np.float64) + offset, faces[keep].astype(np.int64), face_voxel[keep])


def _cube_owner(occupancy: np.ndarray, resolution: int) -> np.ndarray:
    """Voxel row (or -1) of every lattice cube. occupancy (X, Y, Z) -> (X*r, Y*r, Z*r)."""
    out = occupancy
    for axis in range(3):
        out = np.repeat(out, resolution, axis=axis)
    return out


def _face_voxel(verts: np.ndarray, faces: np.ndarray, cube_voxel: np.ndarray) -> np.ndarray:
    """Voxel row of the cube holding each face (its centroid), -1 for unallocated voxels.

    verts (V, 3) block-local lattice units, faces (F, 3), cube_voxel (Cx, Cy, Cz) -> (F,).
    """
    if faces.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    centroid = verts[faces].mean(1)
    cube = np.floor(centroid).astype(np.int64)
    cube = np.clip(cube, 0, np.array(cube_voxel.shape) - 1)
    return cube_voxel[cube[:, 0], cube[:, 1], cube[:, 2]]


# -------------------------------------------------------------------- meshes
def _merge_blocks(blocks: list[_BlockSurface]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Concatenate blocks, merge vertices that coincide, drop degenerate faces.

    -> vertices (V, 3) float64 lattice units, faces (F, 3) int64, vertex_voxel (V,) int64.
    """
    vertices, faces, face_voxel, base = [], [], [], 0
    for block in blocks:
        vertices.append(block.vertices)
        faces.append(block.faces + base)
        face_voxel.append(block.face_voxel)
        base += block.vertices.shape[0]
    vertices = np.concatenate(vertices)
    faces = np.concatenate(faces)
    face_voxel = np.concatenate(face_voxel)

    keys = np.round(vertices * _MERGE_SCALE).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    faces = inverse.reshape(-1)[faces]
    vertices = vertices[first]
    distinct = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    faces, face_voxel = faces[distinct], face_voxel[distinct]

    used, faces = np.unique(faces, return_inverse=True)
    faces = faces.reshape(-1, 3)
    vertices = vertices[used]
    vertex_voxel = np.full(vertices.shape[0], -1, dtype=np.int64)
    vertex_voxel[faces.reshape(-1)] = np.repeat(face_voxel, 3)
    return vertices, faces, vertex_voxel


def empty_mesh() -> trimesh.Trimesh:
    """A mesh with no vertices and no faces."""
    return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64), process=False)


@torch.no_grad()
def extract_submap_mesh(submap, resolution: int, *, block_voxels: int = 8,
                        chunk_points: int = 1 << 16, min_corner_updates: int = 1,
                        surface_only: bool = True) -> trimesh.Trimesh:
    """Coloured mesh of one submap's zero level set, in the map frame.

    ``resolution``: marching-cubes cells per voxel edge (>= 1). ``block_voxels``: edge of the
    cubic blocks the map is cut into (a block's grid has ``(block_voxels * resolution + 1)^3``
    points). ``chunk_points``: lattice points decoded at once; together they bound memory.
    Only voxels the mapper optimised (``SubMap.optimised_view(min_corner_updates)``) carry a
    surface: a voxel allocated but never sampled holds its random initial embeddings. With
    ``surface_only`` also only voxels that held an observed depth point: the voxels allocated
    for the truncation band in front of and behind a surface have no supervised zero level
    and grow spurious sheets there (decisions.md#mesh.surface_only).
    Returns a trimesh with (V, 4) uint8 vertex colours; empty when the map holds no surface.
    """
    if int(resolution) < 1:
        raise ValueError(f"mesh resolution must be >= 1, got {resolution}")
    if int(block_voxels) < 1 or int(chunk_points) < 1:
        raise ValueError("block_voxels and chunk_points must be positive")
    resolution = int(resolution)
    view = submap.optimised_view(min_corner_updates, surface_only)
    if view.voxel_codes.numel() == 0:
        return empty_mesh()
    decoder = submap.decoder
    voxel_ijk = morton_decode(view.voxel_codes)
    ijk_host = voxel_ijk.cpu().numpy()  # the blocks' grids are built on the host
    blocks = []
    for members in _blocks_of(ijk_host, int(block_voxels)):
        block = _block_surface(members, ijk_host, view, decoder, resolution, chunk_points)
        if block is not None:
            blocks.append(block)
    if not blocks:
        return empty_mesh()
    vertices, faces, vertex_voxel = _merge_blocks(blocks)
    moved = to_device({"vertices": vertices, "vertex_voxel": vertex_voxel}, view.voxel_codes.device)
    rgb = _color_at(moved["vertices"], moved["vertex_voxel"], voxel_ijk.to(torch.float64), view, decoder,
                    resolution, chunk_points, fine=submap.fine)
    colors = np.concatenate([
        np.round(rgb.cpu().numpy() * 255.0).clip(0, 255).astype(np.uint8),
        np.full((rgb.shape[0], 1), 255, dtype=np.uint8),
    ], 1)
    return trimesh.Trimesh(vertices=vertices * (view.voxel_size / resolution), faces=faces,
                           vertex_colors=colors, process=False)


def _as_matrix(T) -> np.ndarray:
    """(4, 4) tensor or array -> float64 numpy."""
    if torch.is_tensor(T):
        T = T.detach().cpu().numpy()
    return np.asarray(T, dtype=np.float64)


def _claimed_by(points_world: np.ndarray, owner, min_corner_updates: int = 1) -> np.ndarray:
    """(N,) bool: world points (N, 3) that fall in a voxel ``owner`` optimised. Not only its
    surface voxels: near the border of what it saw, a later map's mesh reaches up to a voxel
    farther (its own voxel grid is offset), into the earlier map's truncation band."""
    view = owner.optimised_view(min_corner_updates, surface_only=False)
    if view.voxel_codes.numel() == 0 or len(points_world) == 0:
        return np.zeros(len(points_world), bool)
    T = np.linalg.inv(_as_matrix(owner.T_world_map))
    local = torch.from_numpy(points_world @ T[:3, :3].T + T[:3, 3]).to(view.voxel_codes.device, torch.float32)
    codes = morton_encode(voxel_coords_of(local, view.voxel_size))
    return (lookup_sorted(view.voxel_codes, codes) >= 0).cpu().numpy()


def extract_mesh(mapset, resolution: int | None = None, *, dedupe: bool = True, **kwargs) -> trimesh.Trimesh:
    """World-frame mesh of every submap (placed by ``T_world_map``), concatenated.

    ``resolution`` defaults to ``mapset.config.mesh.resolution``; ``kwargs`` go to
    ``extract_submap_mesh``. Vertex colours (V, 4) uint8. With ``dedupe`` (paper: duplicate
    geometry removed) a region that several maps of one group reconstructed is kept from
    the oldest of them only: a later map's faces whose centre lies in voxels an earlier
    map optimised are dropped. Maps of different groups (not joined by a loop) are never
    compared: their relative placement is unknown.
    """
    if resolution is None:
        resolution = mapset.config.mesh.resolution
    groups = mapset.groups() if hasattr(mapset, "groups") else {}
    vertices, faces, colors, base = [], [], [], 0
    kept: list = []
    for submap in mapset.maps:
        mesh = extract_submap_mesh(submap, resolution, **kwargs)
        if len(mesh.faces) == 0:
            kept.append(submap)
            continue
        T = _as_matrix(submap.T_world_map)
        v = mesh.vertices @ T[:3, :3].T + T[:3, 3]
        f = np.asarray(mesh.faces)
        if dedupe:
            earlier = [m for m in kept if groups.get(m.map_id, m.map_id) == groups.get(submap.map_id, submap.map_id)]
            if earlier:
                centres = v[f].mean(1)
                drop = np.zeros(len(f), bool)
                for owner in earlier:
                    drop |= _claimed_by(centres, owner)
                f = f[~drop]
        kept.append(submap)
        if len(f) == 0:
            continue
        vertices.append(v)
        faces.append(f + base)
        colors.append(np.asarray(mesh.visual.vertex_colors))
        base += len(v)
    if not vertices:
        return empty_mesh()
    out = trimesh.Trimesh(vertices=np.concatenate(vertices), faces=np.concatenate(faces),
                          vertex_colors=np.concatenate(colors), process=False)
    if dedupe:
        out.remove_unreferenced_vertices()
    return out


# -------------------------------------------------------------------- export
def mesh_to_bytes(mesh: trimesh.Trimesh, file_format: str) -> bytes:
    """Encode as ``ply`` (binary, vertex colours), ``glb`` or ``obj`` (vertex colours)."""
    fmt = file_format.lower().lstrip(".")
    if fmt not in MESH_FORMATS:
        raise ValueError(f"unknown mesh format {file_format!r}; choose one of {list(MESH_FORMATS)}")
    if fmt == "ply":
        return mesh.export(file_type="ply", encoding="binary")
    if fmt == "obj":
        return mesh.export(file_type="obj", include_color=True, include_normals=False).encode("utf-8")
    buffer = io.BytesIO()
    trimesh.Scene(mesh).export(buffer, file_type="glb")
    return buffer.getvalue()


def crop_mesh(mesh: trimesh.Trimesh, box_min, box_max) -> trimesh.Trimesh:
    """The faces of ``mesh`` whose three vertices lie inside the axis-aligned box (3,) min,
    (3,) max, with their vertices and colours (unreferenced vertices dropped)."""
    box_min, box_max = np.asarray(box_min, np.float64), np.asarray(box_max, np.float64)
    vertices = np.asarray(mesh.vertices)
    inside = np.all((vertices >= box_min) & (vertices <= box_max), axis=1)
    faces = np.asarray(mesh.faces)
    kept = faces[inside[faces].all(axis=1)]
    used = np.unique(kept)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    colors = getattr(mesh.visual, "vertex_colors", None)
    return trimesh.Trimesh(vertices[used], remap[kept], process=False,
                           vertex_colors=None if colors is None or len(colors) != len(vertices) else colors[used])


def export_mesh(mesh: trimesh.Trimesh, path_or_format: str | Path) -> bytes | Path:
    """A format name (``"ply"``, ``"glb"``, ``"obj"``) returns bytes; a path writes the file.

    The file's format comes from its suffix; it is written to a temporary name first and
    then renamed, so a reader never sees half a mesh. Returns the path written.
    """
    if isinstance(path_or_format, str) and path_or_format.lower() in MESH_FORMATS:
        return mesh_to_bytes(mesh, path_or_format)
    path = Path(path_or_format)
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in MESH_FORMATS:
        raise ValueError(f"cannot tell the mesh format of {path}: use a .ply, .glb or .obj suffix")
    data = mesh_to_bytes(mesh, fmt)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    tmp.replace(path)
    return path
