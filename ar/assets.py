"""Loading user-supplied virtual objects (GLB / OBJ / PLY) into an ObjectMesh via trimesh.

Scenes (GLB nodes, multi-object OBJ) are flattened into one mesh in the asset's own frame
with their node transforms applied. Vertex colours are kept where the file has them (face
colours become per-corner colours; textures are sampled at the vertices by trimesh); the
mesh is flat shaded because files rarely say which edges are meant to be sharp.
Coordinates are kept as they are in the file: the object's ``scale`` and ``T_world_obj``
place it.

Sizes are checked before trimesh sees the bytes, from what the file says of itself: a PLY's
header element counts, an OBJ's ``v`` and ``f`` lines, a GLB's JSON chunk (its node count,
the depth of its node hierarchy, which must be a forest, and the faces and vertices its mesh
instances add up to). trimesh's scene graph costs far more than linear time in the depth of
a node chain, so a small file could otherwise keep a parser busy for minutes. The counts are
checked again on the parsed meshes (an OBJ polygon becomes several triangles).
"""

from __future__ import annotations

import io
import json
import struct
from pathlib import Path

import numpy as np
import trimesh

from ar.objects import ObjectMesh

SUPPORTED_EXTENSIONS = ("glb", "obj", "ply")
MAX_ASSET_FACES = 500_000
MAX_ASSET_VERTICES = 1_500_000
MAX_ASSET_BYTES = 64 * 1024 * 1024
MAX_GLTF_NODES = 4096
"""Nodes of a GLB (trimesh flattens that many instances in seconds)."""
MAX_GLTF_DEPTH = 64
"""Levels of a GLB's node hierarchy (real models nest a handful deep)."""
PLY_HEADER_BYTES = 64 * 1024
"""Where a PLY's ``end_header`` must appear."""


class AssetError(ValueError):
    """An asset file is corrupt, empty, of an unsupported type or too large; names the file."""


def load_asset(
    source: bytes | str | Path,
    filename: str | None = None,
    *,
    max_faces: int = MAX_ASSET_FACES,
    max_vertices: int = MAX_ASSET_VERTICES,
) -> ObjectMesh:
    """Load a GLB, OBJ or PLY file (bytes or a path) as one triangle mesh.

    Args:
        source: the file's bytes, or a path to it.
        filename: the name whose extension gives the format; defaults to the path's name
            (required for bytes).
        max_faces, max_vertices: larger meshes are refused (they would stall compositing).

    Raises:
        AssetError naming ``filename`` when the file cannot be read, has no triangles, has an
        unsupported extension or is over a limit.
    """
    data, name = _read_source(source, filename)
    extension = Path(name).suffix.lower().lstrip(".")
    if extension not in SUPPORTED_EXTENSIONS:
        expected = ", ".join(SUPPORTED_EXTENSIONS)
        raise AssetError(f"{name}: unsupported asset type {extension!r}, expected one of {expected}")
    if not data:
        raise AssetError(f"{name}: the file is empty")
    check_declared_size(data, extension, name, max_faces=max_faces, max_vertices=max_vertices)
    try:
        # process=False keeps the file's vertices as they are (no merging that would blend
        # the per-corner colours of a face-coloured mesh).
        loaded = trimesh.load(io.BytesIO(data), file_type=extension, process=False)
    except Exception as error:  # noqa: BLE001 - trimesh raises anything from its parsers
        # The parser's own words ("buffer size must be a multiple of element size") mean
        # nothing to the user; they stay on the chained exception.
        raise AssetError(f"{name} could not be read as a {extension.upper()} file: it is damaged or "
                         f"not a {extension.upper()} file") from error
    meshes = _triangle_meshes(loaded)
    if not meshes:
        raise AssetError(f"{name}: contains no triangles")
    _check_counts(name, sum(len(m.faces) for m in meshes), sum(len(m.vertices) for m in meshes),
                  max_faces, max_vertices)
    try:
        return _concatenate(meshes)
    except ValueError as error:
        raise AssetError(f"{name} holds mesh data that cannot be used (faces that point at missing "
                         f"vertices, or mismatched colours)") from error


def check_declared_size(data: bytes, extension: str, name: str, *, max_faces: int = MAX_ASSET_FACES,
                        max_vertices: int = MAX_ASSET_VERTICES) -> None:
    """Refuse a file whose own description (PLY header, OBJ lines, GLB JSON) is over a limit,
    without parsing its geometry; AssetError names the file and the limit."""
    if extension == "ply":
        _check_ply_header(data, name, max_faces, max_vertices)
    elif extension == "obj":
        _check_counts(name, _obj_lines(data, b"f"), _obj_lines(data, b"v"), max_faces, max_vertices)
    elif extension == "glb":
        _check_gltf(_glb_json(data, name), name, max_faces, max_vertices)


def _check_counts(name: str, faces: int, vertices: int, max_faces: int, max_vertices: int) -> None:
    if faces > max_faces:
        raise AssetError(f"{name}: {faces} faces; the limit is {max_faces} (too large)")
    if vertices > max_vertices:
        raise AssetError(f"{name}: {vertices} vertices; the limit is {max_vertices} (too large)")


def _obj_lines(data: bytes, keyword: bytes) -> int:
    """Lines of an OBJ that start with ``keyword`` and a space or tab (C-speed byte counts)."""
    return sum(data.startswith(keyword + gap) + data.count(b"\n" + keyword + gap) for gap in (b" ", b"\t"))


def _check_ply_header(data: bytes, name: str, max_faces: int, max_vertices: int) -> None:
    """Every ``element NAME COUNT`` of the header within its limit (faces, else vertices)."""
    end = data.find(b"end_header", 0, PLY_HEADER_BYTES)
    if not data.startswith(b"ply") or end < 0:
        raise AssetError(f"{name} could not be read as a PLY file: no PLY header in its first "
                         f"{PLY_HEADER_BYTES // 1024} KiB")
    for line in data[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if len(words) != 3 or words[0] != "element":
            continue
        try:
            count = int(words[2])
        except ValueError:
            raise AssetError(f"{name} could not be read as a PLY file: bad element line {line!r}") from None
        if words[1] == "face":
            _check_counts(name, count, 0, max_faces, max_vertices)
        elif words[1] == "vertex":
            _check_counts(name, 0, count, max_faces, max_vertices)
        elif count > max_vertices:
            raise AssetError(f"{name}: {count} {words[1]} elements; the limit is {max_vertices} (too large)")


def _glb_json(data: bytes, name: str) -> dict:
    """The JSON chunk of a binary glTF (header: magic, version, length; then the chunk)."""
    damaged = AssetError(f"{name} could not be read as a GLB file: it is damaged or not a GLB file")
    if len(data) < 20 or data[:4] != b"glTF":
        raise damaged
    length, kind = struct.unpack_from("<I4s", data, 12)
    if kind != b"JSON" or 20 + length > len(data):
        raise damaged
    try:
        document = json.loads(data[20:20 + length])
    except (ValueError, RecursionError):
        raise damaged from None
    if not isinstance(document, dict):
        raise damaged
    return document


def _check_gltf(document: dict, name: str, max_faces: int, max_vertices: int) -> None:
    """Node count, hierarchy depth (a forest: one parent each, no cycles) and the faces and
    vertices of every mesh instance, from the glTF JSON alone."""
    nodes = document.get("nodes") or []
    if not isinstance(nodes, list) or not all(isinstance(n, dict) for n in nodes):
        raise AssetError(f"{name} could not be read as a GLB file: its nodes are not a list of objects")
    depth = _hierarchy_depth([_children(n, len(nodes), name) for n in nodes], name)
    if depth > MAX_GLTF_DEPTH:
        raise AssetError(f"{name}: its nodes nest {depth} levels deep; the limit is {MAX_GLTF_DEPTH}")
    if len(nodes) > MAX_GLTF_NODES:
        raise AssetError(f"{name}: {len(nodes)} nodes; the limit is {MAX_GLTF_NODES}")
    mesh_sizes = _gltf_mesh_sizes(document)
    instances = [mesh_sizes.get(n["mesh"], (0, 0)) for n in nodes if isinstance(n.get("mesh"), int)]
    _check_counts(name, sum(f for f, _ in instances), sum(v for _, v in instances), max_faces, max_vertices)


def _children(node: dict, count: int, name: str) -> list[int]:
    children = node.get("children", [])
    if not isinstance(children, list) or not all(isinstance(c, int) and 0 <= c < count for c in children):
        raise AssetError(f"{name} could not be read as a GLB file: a node names children that do not exist")
    return children


def _hierarchy_depth(children: list[list[int]], name: str) -> int:
    """Levels of the node forest (1 for nodes without children), walked breadth first."""
    parents = [0] * len(children)
    for child in (c for kids in children for c in kids):
        parents[child] += 1
        if parents[child] > 1:
            raise AssetError(f"{name}: node {child} has more than one parent; glTF nodes form trees")
    level = [i for i, count in enumerate(parents) if count == 0]
    depth = seen = 0
    while level:
        depth, seen = depth + 1, seen + len(level)
        level = [c for i in level for c in children[i]]
    if seen < len(children):
        raise AssetError(f"{name}: its nodes form a cycle; glTF nodes form trees")
    return depth


def _gltf_mesh_sizes(document: dict) -> dict[int, tuple[int, int]]:
    """Mesh index -> (triangles, vertices) its primitives declare (accessor counts; a
    primitive without indices counts its vertices as corners)."""
    accessors = document.get("accessors") or []

    def count(index: object) -> int:
        ok = isinstance(index, int) and 0 <= index < len(accessors) and isinstance(accessors[index], dict)
        value = accessors[index].get("count", 0) if ok else 0
        return value if isinstance(value, int) and value > 0 else 0

    sizes = {}
    for index, mesh in enumerate(document.get("meshes") or []):
        primitives = mesh.get("primitives", []) if isinstance(mesh, dict) else []
        faces = vertices = 0
        for primitive in (p for p in primitives if isinstance(p, dict)):
            attributes = primitive.get("attributes")
            corners = count(attributes.get("POSITION")) if isinstance(attributes, dict) else 0
            vertices += corners
            faces += count(primitive["indices"]) // 3 if "indices" in primitive else corners // 3
        sizes[index] = (faces, vertices)
    return sizes


def _read_source(source: bytes | str | Path, filename: str | None) -> tuple[bytes, str]:
    if isinstance(source, (bytes, bytearray, memoryview)):
        if filename is None:
            raise AssetError("load_asset: a filename (for its extension) is required with bytes")
        data = bytes(source)
        name = filename
    else:
        if isinstance(source, str) and ("\n" in source or len(source) > 4096):
            raise AssetError("load_asset: got text that is not a path; pass file contents as bytes")
        path = Path(source)
        name = filename or path.name
        try:
            if path.stat().st_size > MAX_ASSET_BYTES:
                raise AssetError(f"{path}: larger than {MAX_ASSET_BYTES // (1024 * 1024)} MiB")
            data = path.read_bytes()
        except OSError as error:
            raise AssetError(f"{path}: cannot read ({error})") from error
    if len(data) > MAX_ASSET_BYTES:
        raise AssetError(f"{name}: larger than {MAX_ASSET_BYTES // (1024 * 1024)} MiB")
    return data, name


def _triangle_meshes(loaded: object) -> list[trimesh.Trimesh]:
    """The non-empty triangle meshes of a load result, scene node transforms applied."""
    if isinstance(loaded, trimesh.Scene):
        # dump() returns a copy of every geometry instance moved by its node transform.
        candidates = loaded.dump(concatenate=False)
    else:
        candidates = [loaded]
    return [m for m in candidates if isinstance(m, trimesh.Trimesh) and len(m.faces) > 0 and len(m.vertices) > 0]


def _concatenate(meshes: list[trimesh.Trimesh]) -> ObjectMesh:
    """One ObjectMesh; colours only if at least one part has them (the rest get grey)."""
    parts = [_vertices_faces_colors(m) for m in meshes]
    has_colors = any(colors is not None for _, _, colors in parts)
    vertices, faces, colors = [], [], []
    offset = 0
    for part_vertices, part_faces, part_colors in parts:
        vertices.append(part_vertices)
        faces.append(part_faces + offset)
        if has_colors:
            colors.append(part_colors if part_colors is not None else np.full((len(part_vertices), 3), 0.75))
        offset += len(part_vertices)
    return ObjectMesh(
        vertices=np.concatenate(vertices),
        faces=np.concatenate(faces),
        vertex_colors=np.concatenate(colors) if has_colors else None,
    )


def _vertices_faces_colors(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(V, 3) vertices, (F, 3) faces and (V, 3) colours in [0, 1] or None."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    visual = mesh.visual
    if isinstance(visual, trimesh.visual.texture.TextureVisuals):
        try:
            visual = visual.to_color()
        except Exception:  # noqa: BLE001 - a broken texture leaves the mesh uncoloured
            return vertices, faces, None
    kind = getattr(visual, "kind", None)
    if kind == "vertex":
        return vertices, faces, np.asarray(visual.vertex_colors, dtype=np.float32)[:, :3] / 255.0
    if kind == "face":
        # Give every face its own three vertices so each keeps its exact colour.
        face_colors = np.asarray(visual.face_colors, dtype=np.float32)[:, :3] / 255.0
        corner_vertices = vertices[faces.reshape(-1)]
        corner_faces = np.arange(len(faces) * 3).reshape(-1, 3)
        return corner_vertices, corner_faces, np.repeat(face_colors, 3, axis=0)
    return vertices, faces, None
