"""Reconstruction metrics between two meshes (NICE-SLAM protocol), pure: meshes in, numbers out.

Both meshes are optionally culled to what the ground-truth cameras saw, then sampled uniformly
on their surfaces; nearest-neighbour distances between the two samples give

- accuracy: mean distance from reconstructed points to the ground truth (lower is better),
- completion: mean distance from ground-truth points to the reconstruction (lower is better),
- completion ratio: share of ground-truth points within ``threshold`` of the reconstruction
  (= recall); precision is the same share the other way round, and F-score their harmonic mean.

All distances are metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Sequence

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from slam.data.frame import DataError


class CullCamera(NamedTuple):
    """One ground-truth view used for culling (a plain 4-tuple works as well).

    Attributes:
        K: (3, 3) pinhole intrinsics.
        T_world_cam: (4, 4) camera-to-world pose, OpenCV axes.
        width, height: image size in pixels.
    """

    K: np.ndarray
    T_world_cam: np.ndarray
    width: int
    height: int


@dataclass(frozen=True)
class MeshMetrics:
    """Distances in metres, ratios in [0, 1].

    Attributes:
        accuracy: mean distance reconstruction -> ground truth.
        completion: mean distance ground truth -> reconstruction.
        completion_ratio: share of ground-truth points closer than ``threshold``.
        precision: share of reconstructed points closer than ``threshold``.
        recall: equal to ``completion_ratio``.
        fscore: harmonic mean of precision and recall (0 when both are 0).
        threshold: the distance threshold used.
        num_points: points sampled on each mesh.
    """

    accuracy: float
    completion: float
    completion_ratio: float
    precision: float
    recall: float
    fscore: float
    threshold: float
    num_points: int


def mesh_metrics(
    rec: trimesh.Trimesh,
    gt: trimesh.Trimesh,
    *,
    num_points: int = 200_000,
    threshold: float = 0.05,
    cull_cameras: Sequence[CullCamera | tuple] | None = None,
    gt_depths: Sequence[np.ndarray] | None = None,
    depth_margin: float = 0.05,
    seed: int = 0,
) -> MeshMetrics:
    """Accuracy, completion and completion ratio of ``rec`` against ``gt`` (same world frame).

    Args:
        rec, gt: triangle meshes in metres.
        num_points: points sampled uniformly (by area) on each mesh.
        threshold: distance in metres for completion ratio, precision and recall.
        cull_cameras: if given, both meshes keep only faces seen by some camera (see
            ``cull_to_cameras``), so unobserved parts of the scene do not count.
        gt_depths: (H, W) depth maps in metres, one per camera, for occlusion-aware culling.
        depth_margin: how far behind the observed depth a vertex still counts as seen.
        seed: the samples are a deterministic function of the meshes and this seed.
    Raises:
        DataError: a mesh has no faces (before or after culling).
    """
    if num_points < 1:
        raise ValueError(f"num_points must be >= 1, got {num_points}")
    if threshold <= 0:
        raise ValueError(f"threshold must be > 0 metres, got {threshold}")
    if cull_cameras is not None:
        rec = cull_to_cameras(rec, cull_cameras, gt_depths, depth_margin)
        gt = cull_to_cameras(gt, cull_cameras, gt_depths, depth_margin)
    # Different streams for the two meshes, so identical meshes are not sampled identically.
    rec_seed, gt_seed = np.random.SeedSequence(seed).spawn(2)
    rec_points = sample_surface(rec, num_points, np.random.default_rng(rec_seed), "reconstructed")
    gt_points = sample_surface(gt, num_points, np.random.default_rng(gt_seed), "ground-truth")
    rec_to_gt = nearest_distances(rec_points, gt_points)
    gt_to_rec = nearest_distances(gt_points, rec_points)
    precision = float(np.mean(rec_to_gt < threshold))
    recall = float(np.mean(gt_to_rec < threshold))
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return MeshMetrics(
        accuracy=float(rec_to_gt.mean()),
        completion=float(gt_to_rec.mean()),
        completion_ratio=recall,
        precision=precision,
        recall=recall,
        fscore=fscore,
        threshold=float(threshold),
        num_points=int(num_points),
    )


def sample_surface(mesh: trimesh.Trimesh, count: int, rng: np.random.Generator, name: str = "mesh") -> np.ndarray:
    """(count, 3) float64 points uniform by area on ``mesh``; DataError if it has no area."""
    if len(mesh.faces) == 0 or not mesh.area > 0:
        raise DataError(f"the {name} mesh has no faces to sample (after culling, if any)")
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=rng)
    return np.asarray(points, dtype=np.float64)


def nearest_distances(query: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(N,) distance from each of (N, 3) ``query`` points to the closest of (M, 3) ``reference``."""
    distances, _ = cKDTree(reference).query(query, k=1)
    return distances


def cull_to_cameras(
    mesh: trimesh.Trimesh,
    cameras: Sequence[CullCamera | tuple],
    depths: Sequence[np.ndarray] | None = None,
    depth_margin: float = 0.05,
) -> trimesh.Trimesh:
    """Keep the faces of ``mesh`` that some camera saw.

    A vertex is seen by a camera when it lies in front of it (z > 0) and projects inside the
    image; with ``depths`` it must also be at most ``depth_margin`` metres behind the depth
    observed at its pixel (so surfaces hidden behind others are dropped). A face is kept when
    any of its vertices is seen, so faces crossing the image border survive.

    Args:
        mesh: triangle mesh in the world frame.
        cameras: (K (3, 3), T_world_cam (4, 4), width, height) per view.
        depths: optional (height, width) metres per camera, 0 = invalid (never seen).
    Returns:
        A new mesh with the kept faces and the vertices they use.
    """
    cameras = [CullCamera(*camera) for camera in cameras]
    if not cameras:
        raise ValueError("cull_to_cameras needs at least one camera")
    if depths is not None and len(depths) != len(cameras):
        raise ValueError(f"got {len(depths)} depth maps for {len(cameras)} cameras")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    seen = np.zeros(len(vertices), dtype=bool)
    for i, camera in enumerate(cameras):
        depth = None if depths is None else np.asarray(depths[i], dtype=np.float64)
        seen |= vertices_seen(vertices, camera, depth, depth_margin)
    keep = seen[mesh.faces].any(axis=1)
    culled = mesh.submesh([np.flatnonzero(keep)], append=True) if keep.any() else _empty_like(mesh)
    return culled


def vertices_seen(
    vertices: np.ndarray, camera: CullCamera, depth: np.ndarray | None = None, depth_margin: float = 0.05
) -> np.ndarray:
    """(N,) bool: which of (N, 3) world ``vertices`` ``camera`` sees (see ``cull_to_cameras``).

    Pixel (u, v) covers [u - 0.5, u + 0.5) x [v - 0.5, v + 0.5), the OpenCV centre convention.
    """
    K = np.asarray(camera.K, dtype=np.float64)
    T_world_cam = np.asarray(camera.T_world_cam, dtype=np.float64)
    if K.shape != (3, 3) or T_world_cam.shape != (4, 4):
        raise ValueError(f"camera needs K (3, 3) and T_world_cam (4, 4), got {K.shape} and {T_world_cam.shape}")
    width, height = int(camera.width), int(camera.height)
    if depth is not None and depth.shape != (height, width):
        raise ValueError(f"depth map shape {depth.shape} differs from camera size (H, W) = {(height, width)}")
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    p_cam = (vertices - t) @ R  # R^T (p - t), row-vector form
    z = p_cam[:, 2]
    in_front = z > 1e-6
    z_safe = np.where(in_front, z, 1.0)
    u = K[0, 0] * p_cam[:, 0] / z_safe + K[0, 2]
    v = K[1, 1] * p_cam[:, 1] / z_safe + K[1, 2]
    col, row = np.floor(u + 0.5), np.floor(v + 0.5)
    seen = in_front & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    if depth is not None:
        observed = np.zeros(len(vertices))
        observed[seen] = depth[row[seen].astype(np.int64), col[seen].astype(np.int64)]
        seen &= (observed > 0) & (z <= observed + depth_margin)
    return seen


def _empty_like(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64), process=False)
