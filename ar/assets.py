"""Loading user-supplied virtual objects (GLB / OBJ / PLY) into an ObjectMesh via trimesh.

Scenes (GLB nodes, multi-object OBJ) are flattened into one mesh in the asset's own frame
with their node transforms applied. Vertex colours are kept where the file has them (face
colours become per-corner colours; textures are sampled at the vertices by trimesh); the
mesh is flat shaded because files rarely say which edges are meant to be sharp.
Coordinates are kept as they are in the file: the object's ``scale`` and ``T_world_obj``
place it.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import trimesh

from ar.objects import ObjectMesh

SUPPORTED_EXTENSIONS = ("glb", "obj", "ply")
MAX_ASSET_FACES = 500_000
MAX_ASSET_VERTICES = 1_500_000
MAX_ASSET_BYTES = 64 * 1024 * 1024


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
    num_faces = sum(len(m.faces) for m in meshes)
    num_vertices = sum(len(m.vertices) for m in meshes)
    if num_faces > max_faces or num_vertices > max_vertices:
        raise AssetError(
            f"{name}: too large ({num_faces} faces, {num_vertices} vertices; limits {max_faces} and {max_vertices})"
        )
    try:
        return _concatenate(meshes)
    except ValueError as error:
        raise AssetError(f"{name} holds mesh data that cannot be used (faces that point at missing "
                         f"vertices, or mismatched colours)") from error


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
