"""CPU-heavy work behind the render, mesh, pick and AR endpoints. The routes run it in the
render helpers (``server.render_calls``, out of the API process); the viewer's own neural
views call it from their thread.

Maps are read from a session's ``map.pt``, which the runtime rewrites atomically while it runs;
loaded maps are cached by the file's modification time and size, so repeated renders of a
running session reload only after the map changed. Everything returns encoded bytes or plain
arrays.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, TypeVar

import cv2
import numpy as np

T = TypeVar("T")

CACHED_MAPS = 4
"""Loaded maps kept in memory (least recently used first out)."""


def with_threads(threads: int, work: Callable[..., T], *args, **kwargs) -> T:
    """``work(*args, **kwargs)`` with torch's intra-op threads at ``threads`` in the calling
    thread (OpenMP keeps the count per thread: a pool thread must set it itself)."""
    import torch

    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    return work(*args, **kwargs)


class NoMapYet(RuntimeError):
    """The session has not written a map (or mesh) yet: 409."""


@dataclass(frozen=True)
class Camera:
    """A pinhole camera in the world."""

    T_world_cam: np.ndarray
    """(4, 4) float64 camera-to-world, OpenCV axes."""
    K: np.ndarray
    """(3, 3) float64."""
    width: int
    height: int


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


MAX_POSITION_M = 1e5
"""Farthest camera position from the world origin a render accepts (100 km): beyond, ray
arithmetic in float32 loses the scene entirely and may overflow."""


def check_pose(T: np.ndarray, what: str = "T_world_cam") -> np.ndarray:
    """(4, 4) rigid transform or ValueError saying what is wrong."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"{what}: expected a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{what}: contains NaN or infinity")
    if np.abs(T[:3, 3]).max() > MAX_POSITION_M:
        raise ValueError(f"{what}: the position is more than {MAX_POSITION_M:g} m from the world origin")
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6):
        raise ValueError(f"{what}: the last row must be [0, 0, 0, 1]")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
        raise ValueError(f"{what}: the upper-left 3x3 block is not a rotation")
    return T


class MapCache:
    """Loaded ``map.pt`` checkpoints per session, reloaded when the file changes."""

    def __init__(self, max_entries: int = CACHED_MAPS) -> None:
        self._entries: OrderedDict[str, tuple[tuple[int, int], object]] = OrderedDict()
        self._lock = threading.Lock()
        self._load_locks: dict[str, threading.Lock] = {}
        self._max_entries = max_entries

    def get(self, session_id: str, map_path: Path):
        """The session's MapSet (``slam.maps.MapSet``). Raises NoMapYet without a map file."""
        try:
            info = map_path.stat()
        except FileNotFoundError:
            raise NoMapYet("the session has no map yet: map.pt is written after the first keyframes") from None
        stamp = (info.st_mtime_ns, info.st_size)
        with self._lock:
            load_lock = self._load_locks.setdefault(session_id, threading.Lock())
        with load_lock:  # one load per session at a time; others wait and reuse it
            with self._lock:
                entry = self._entries.get(session_id)
                if entry is not None and entry[0] == stamp:
                    self._entries.move_to_end(session_id)
                    return entry[1]
            from slam import load_checkpoint

            mapset = load_checkpoint(map_path, device="cpu")
            with self._lock:
                self._entries[session_id] = (stamp, mapset)
                self._entries.move_to_end(session_id)
                while len(self._entries) > self._max_entries:
                    self._entries.popitem(last=False)
            return mapset

    def evict(self, session_id: str) -> None:
        with self._lock:
            self._entries.pop(session_id, None)
            self._load_locks.pop(session_id, None)


def render(mapset, camera: Camera, **options):
    """Neural render of ``camera``'s view -> ``slam.views.RenderedView`` (rgb, depth); ``options``
    go to ``render_view`` (method, precision)."""
    from slam import render_view

    return render_view(mapset, camera.T_world_cam, camera.K, camera.width, camera.height, **options)


def png_from_rgb(rgb: np.ndarray) -> bytes:
    """(H, W, 3) float in [0, 1] -> PNG bytes."""
    image = np.clip(np.round(np.asarray(rgb) * 255.0), 0, 255).astype(np.uint8)
    ok, data = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    assert ok, "PNG encoding of a uint8 image cannot fail"
    return data.tobytes()


def png_from_depth(depth: np.ndarray) -> bytes:
    """(H, W) float metres -> 16-bit PNG in millimetres (0 = no surface; clipped at 65.535 m)."""
    depth = np.nan_to_num(np.asarray(depth, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    millimetres = np.clip(np.round(depth * 1000.0), 0, 65535).astype(np.uint16)
    ok, data = cv2.imencode(".png", millimetres)
    assert ok, "PNG encoding of a uint16 image cannot fail"
    return data.tobytes()


def png_from_depth_preview(depth: np.ndarray, depth_range: tuple[float, float] | None = None) -> bytes:
    """(H, W) float metres -> colour-mapped 8-bit PNG for display (turbo over ``depth_range``,
    default the view's 2nd-98th percentile: near red, far blue, no surface black)."""
    from slam.path_video import auto_depth_range, depth_image

    depth = np.nan_to_num(np.asarray(depth, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    return png_from_rgb(depth_image(depth, depth_range or auto_depth_range(depth)))


def png_from_normals(depth: np.ndarray, K: np.ndarray) -> bytes:
    """(H, W) float metres and its (3, 3) intrinsics -> the normals image as PNG (facing the
    camera blue, up green, no surface black)."""
    from slam.camera_path import normals_from_depth, normals_image

    return png_from_rgb(normals_image(normals_from_depth(np.asarray(depth, dtype=np.float64), K)))


@dataclass(frozen=True)
class PickResult:
    """The surface under one pixel."""

    point: np.ndarray
    """(3,) world coordinates (metres)."""
    normal: np.ndarray
    """(3,) unit surface normal in the world, facing the camera."""
    depth: float


PICK_PATCH = 7
"""Side of the small image rendered around a picked pixel (for the normal estimate)."""


def pick_surface(mapset, camera: Camera, u: float, v: float) -> PickResult | None:
    """Back-project pixel (u, v) of ``camera`` onto the map's surface; None where it sees nothing.

    Only a PICK_PATCH^2 image centred on the pixel is rendered (the principal point is shifted),
    and the normal comes from the cross product of the patch's depth gradients.
    """
    half = PICK_PATCH // 2
    K = camera.K.copy()
    # Pixel centres are at (i + 0.5): put the patch's centre pixel centre on (u, v).
    K[0, 2] -= u - half - 0.5
    K[1, 2] -= v - half - 0.5
    # A patch of a few pixels: the plain float32 render costs nothing here and is the reference.
    view = render(mapset, Camera(camera.T_world_cam, K, PICK_PATCH, PICK_PATCH), method="full", precision="float32")
    depth = np.asarray(view.depth, dtype=np.float64)
    if depth[half, half] <= 0:
        return None
    ys, xs = np.mgrid[0:PICK_PATCH, 0:PICK_PATCH].astype(np.float64)
    points = np.stack([(xs + 0.5 - K[0, 2]) / K[0, 0] * depth, (ys + 0.5 - K[1, 2]) / K[1, 1] * depth, depth], -1)
    centre = points[half, half]
    normal_cam = _patch_normal(points, depth > 0, half)
    if normal_cam @ centre > 0:  # face the camera
        normal_cam = -normal_cam
    R, t = camera.T_world_cam[:3, :3], camera.T_world_cam[:3, 3]
    return PickResult(point=R @ centre + t, normal=R @ normal_cam, depth=float(depth[half, half]))


def _patch_normal(points: np.ndarray, valid: np.ndarray, half: int) -> np.ndarray:
    """Unit normal of (P, P, 3) camera-frame points around the centre; -z when undetermined."""
    left, right = points[half, max(0, half - 2)], points[half, min(points.shape[1] - 1, half + 2)]
    up, down = points[max(0, half - 2), half], points[min(points.shape[0] - 1, half + 2), half]
    if not (valid[half, max(0, half - 2)] and valid[half, min(points.shape[1] - 1, half + 2)]
            and valid[max(0, half - 2), half] and valid[min(points.shape[0] - 1, half + 2), half]):
        return np.array([0.0, 0.0, -1.0])
    normal = np.cross(right - left, down - up)
    norm = np.linalg.norm(normal)
    return normal / norm if norm > 1e-12 else np.array([0.0, 0.0, -1.0])


def mesh_bytes_from_arrays(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]], file_format: str) -> bytes:
    """Concatenate per-map world-frame meshes (V,3 / F,3 / V,3 uint8) and encode them."""
    from slam import mesh_to_bytes

    return mesh_to_bytes(mesh_from_arrays(parts), file_format)


def mesh_from_arrays(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]):
    """One ``trimesh.Trimesh`` of per-map world-frame meshes (V,3 / F,3 / V,3 uint8 or None);
    NoMapYet when they hold no face."""
    import trimesh

    vertices, faces, colors, base = [], [], [], 0
    if not any(len(f) for _, f, _ in parts):
        raise NoMapYet("the mesh is empty: nothing has been mapped yet")
    for v, f, c in parts:
        vertices.append(np.asarray(v, dtype=np.float64))
        faces.append(np.asarray(f, dtype=np.int64) + base)
        colors.append(np.asarray(c, dtype=np.uint8)[:, :3] if c is not None
                      else np.full((len(v), 3), 180, dtype=np.uint8))
        base += len(v)
    return trimesh.Trimesh(np.concatenate(vertices), np.concatenate(faces), vertex_colors=np.concatenate(colors),
                           process=False)


class MeshFiles:
    """Meshes of finished sessions converted to GLB/OBJ once (cached by the PLY's mtime)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._cache: dict[tuple[str, str], tuple[int, bytes]] = {}

    def convert(self, ply_path: Path, file_format: str) -> bytes:
        import trimesh

        from slam import mesh_to_bytes

        stamp = ply_path.stat().st_mtime_ns
        key = (str(ply_path), file_format)
        with self._lock:
            hit = self._cache.get(key)
            if hit is not None and hit[0] == stamp:
                return hit[1]
        mesh = trimesh.load(ply_path, file_type="ply", process=False)
        if len(getattr(mesh, "faces", ())) == 0:  # GLB/OBJ exporters fail on an empty mesh
            raise NoMapYet("the mesh is empty: nothing was mapped")
        data = mesh_to_bytes(mesh, file_format)
        with self._lock:
            self._cache[key] = (stamp, data)
            if len(self._cache) > 16:
                self._cache.pop(next(iter(self._cache)))
        return data

    def extract_from_map(self, mapset, file_format: str) -> bytes:
        from slam import extract_mesh, mesh_to_bytes

        mesh = extract_mesh(mapset)
        if len(mesh.faces) == 0:
            raise NoMapYet("the map has no surface yet")
        return mesh_to_bytes(mesh, file_format)
