"""A browser's crop box in the 3D viewer, as plain data: no viser.

The box is axis-aligned in the world frame, as the HTTP API's (``crop=`` of the renders and
``GET /api/sessions/{id}/mesh?crop=``): a face is kept when its three vertices lie inside, as
``slam.crop_mesh`` keeps it. In the viewer it crops what one browser sees of the meshes without
copying the shared mesh per browser: a chunk wholly inside stays the shared one, a chunk wholly
outside is hidden by a client-scoped frame of its name, and only a chunk the box cuts is sent
to that browser again, as its part inside (:func:`crop_meshes`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from server.viewer_state import MeshChunk, box_segments, key_text

CROP_COLOR = (0, 170, 220)
"""The crop box's outline: cyan, unlike maps, agents, loops (magenta) and paths (orange)."""


@dataclass(frozen=True)
class CropBox:
    """An axis-aligned box in the world frame (metres)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def __post_init__(self) -> None:
        if not all(np.isfinite(self.lo + self.hi)) or not all(a < b for a, b in zip(self.lo, self.hi)):
            raise ValueError(f"crop box: every min must be below its max, got {self.lo} and {self.hi}")

    @classmethod
    def of(cls, lo, hi) -> CropBox:
        return cls(tuple(float(v) for v in lo), tuple(float(v) for v in hi))

    def query(self) -> str:
        """``xmin,ymin,zmin,xmax,ymax,zmax`` as the mesh route's ``crop=`` takes it."""
        return ",".join(f"{v:g}" for v in self.lo + self.hi)

    def segments(self) -> np.ndarray:
        """(12, 2, 3) float32 edges of the box."""
        return box_segments(np.array(self.lo), np.array(self.hi))

    def inside(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: which (N, 3) world points lie inside (on the faces counts)."""
        return np.all((points >= np.array(self.lo)) & (points <= np.array(self.hi)), axis=1)


def crop_chunk(box: CropBox, T_world_map: np.ndarray, chunk: MeshChunk) -> MeshChunk | None | bool:
    """What of a chunk (map frame) shows through the box: True all of it, None nothing, else its
    part inside (a chunk of its own, map frame, compact vertices)."""
    world = chunk.vertices.astype(np.float64) @ T_world_map[:3, :3].T + T_world_map[:3, 3]
    kept = box.inside(world)[chunk.faces].all(axis=1)
    if kept.all():
        return True
    if not kept.any():
        return None
    used, local = np.unique(chunk.faces[kept], return_inverse=True)
    return MeshChunk(vertices=chunk.vertices[used], faces=local.reshape(-1, 3).astype(np.int32),
                     colors=chunk.colors[used])


@dataclass(frozen=True)
class CroppedChunk:
    """A chunk the box cuts, as one browser's variant of a shared chunk node."""

    token: tuple
    """What it was cut from and how (source chunk's id, box, map pose): equal tokens, same mesh."""
    chunk: MeshChunk
    source: MeshChunk
    """The shared chunk it was cut from (held, so that its id names no other chunk meanwhile)."""
    color: tuple[int, int, int] | None
    """One colour for the whole chunk (a map-coloured variant), or None: its vertex colours."""


def crop_meshes(box: CropBox, base: str, T_world_map: np.ndarray, chunks: dict, color=None
                ) -> tuple[dict[str, bool], dict[str, CroppedChunk]]:
    """For one map's chunks under the node ``base`` (``/sessions/<id>/<layer>/map_<m>``): the
    chunk nodes to hide (path -> False) and the cut ones (path -> their part inside)."""
    hidden, cut = {}, {}
    pose = np.asarray(T_world_map, np.float64).round(9).tobytes()
    for key, chunk in chunks.items():
        part = crop_chunk(box, T_world_map, chunk)
        path = f"{base}/c_{key_text(key)}"
        if part is None:
            hidden[path] = False
        elif part is not True:
            cut[path] = CroppedChunk((id(chunk), box, pose, color), part, chunk, color)
    return hidden, cut
