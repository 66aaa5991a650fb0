"""The classical peer: Open3D's tensor dense SLAM (``open3d.t.pipelines.slam.Model``).

Frame-to-model odometry against a ray-cast model frame, plus voxel-block TSDF integration,
in the order of Open3D's ``t_reconstruction_system/dense_slam.py``: for each frame, track it
against the model frame ray-cast at the previous pose, update the pose, integrate, ray-cast.
Parameters default to that script's configuration (5.86 mm voxels = 3/512 m, 16^3 blocks,
truncation 8 voxels, point-to-plane odometry with a 7 cm correspondence distance).

Open3D is a bench-only extra (``scripts/bench-deps.sh``); importing this module does not need
it, ``run_open3d_slam`` raises ``PeerUnavailable`` with the install hint when it is missing.
Frames come from our readers (same undistortion, same depth) so both systems see equal input;
depth is handed over as 16-bit at ``depth_scale`` units per metre (0.2 mm steps).
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

INSTALL_HINT = "Open3D is not installed: run `bash scripts/bench-deps.sh` (pip install open3d + libgl1 libusb-1.0-0 libgomp1)"


class PeerUnavailable(RuntimeError):
    """Open3D cannot be imported here; the message says how to install it."""


@dataclass(frozen=True)
class Open3DParams:
    voxel_size: float = 3.0 / 512
    """Metres (Open3D's default, 5.86 mm)."""
    block_resolution: int = 16
    block_count: int = 40000
    """Initial hash-map capacity in blocks (it grows when exceeded)."""
    depth_scale: float = 5000.0
    depth_min: float = 0.1
    depth_max: float = 3.0
    """Depth beyond this is ignored by tracking, integration and ray-casting (metres)."""
    odometry_distance: float = 0.07
    trunc_voxel_multiplier: float = 8.0
    device: str = "CPU:0"


@dataclass(frozen=True)
class Open3DResult:
    """timestamps (N,), poses (N, 4, 4) float64 T_world_cam; mesh vertices (V, 3) float64,
    faces (F, 3) int64, colors (V, 3) uint8; seconds of the SLAM loop and of mesh extraction."""

    timestamps: np.ndarray
    poses: np.ndarray
    loop_seconds: float
    mesh_seconds: float
    tracking_failures: int
    active_blocks: int
    capacity_blocks: int
    bytes_per_block: int
    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray

    @property
    def map_mb(self) -> float:
        return self.active_blocks * self.bytes_per_block / 2**20


def import_open3d():
    try:
        import open3d
        import open3d.core
        return open3d
    except ImportError as error:  # also the missing-libGL case, which raises ImportError/OSError
        raise PeerUnavailable(f"{INSTALL_HINT} ({error})") from error
    except OSError as error:
        raise PeerUnavailable(f"{INSTALL_HINT} ({error})") from error


def _bytes_per_block(voxel_grid) -> int:
    """Bytes of one block over every attribute (tsdf, weight, colour) plus its key."""
    total = 0
    for name in ("tsdf", "weight", "color"):
        try:
            values = voxel_grid.attribute(name)
        except RuntimeError:
            continue
        shape = list(values.shape)
        total += int(np.prod(shape[1:])) * values.dtype.byte_size()
    keys = voxel_grid.hashmap().key_tensor()
    return total + int(np.prod(list(keys.shape)[1:])) * keys.dtype.byte_size()


def run_open3d_slam(frames: Iterable, params: Open3DParams = Open3DParams()) -> Open3DResult:
    """Track and fuse ``frames`` (``slam.data.Frame``). The first pose is the first frame's GT
    (identity without GT), as in voxfusion, so maps and trajectories share the world frame."""
    o3d = import_open3d()
    o3c = o3d.core
    device = o3c.Device(params.device)
    model = input_frame = raycast_frame = None
    T_frame_to_model = None
    timestamps, poses, failures = [], [], 0
    started = time.perf_counter()
    for i, frame in enumerate(frames):
        if model is None:
            first = frame.T_world_cam if frame.T_world_cam is not None else np.eye(4)
            T_frame_to_model = o3c.Tensor(np.asarray(first, np.float64))
            model = o3d.t.pipelines.slam.Model(params.voxel_size, params.block_resolution, params.block_count,
                                               T_frame_to_model, device)
            K = o3c.Tensor(np.asarray(frame.K, np.float64))
            input_frame = o3d.t.pipelines.slam.Frame(frame.height, frame.width, K, device)
            raycast_frame = o3d.t.pipelines.slam.Frame(frame.height, frame.width, K, device)
        depth = np.round(np.clip(frame.depth, 0, 65535 / params.depth_scale) * params.depth_scale).astype(np.uint16)
        color = np.round(np.clip(frame.rgb, 0, 1) * 255).astype(np.uint8)
        input_frame.set_data_from_image("depth", o3d.t.geometry.Image(o3c.Tensor(depth)).to(device))
        input_frame.set_data_from_image("color", o3d.t.geometry.Image(o3c.Tensor(color)).to(device))
        if i > 0:
            try:
                result = model.track_frame_to_model(input_frame, raycast_frame, params.depth_scale,
                                                    params.depth_max, params.odometry_distance)
                T_frame_to_model = T_frame_to_model @ result.transformation
            except RuntimeError:  # too few correspondences: keep the last pose, as a failure
                failures += 1
        poses.append(T_frame_to_model.cpu().numpy().copy())
        timestamps.append(float(frame.timestamp))
        model.update_frame_pose(i, T_frame_to_model)
        model.integrate(input_frame, params.depth_scale, params.depth_max, params.trunc_voxel_multiplier)
        model.synthesize_model_frame(raycast_frame, params.depth_scale, params.depth_min, params.depth_max,
                                     params.trunc_voxel_multiplier, False)
    loop_seconds = time.perf_counter() - started
    if model is None:
        raise ValueError("run_open3d_slam: the sequence has no frames")
    t0 = time.perf_counter()
    mesh = model.extract_trianglemesh().to_legacy()
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    colors = np.round(np.asarray(mesh.vertex_colors) * 255).clip(0, 255).astype(np.uint8)
    faces = np.asarray(mesh.triangles, dtype=np.int64)
    mesh_seconds = time.perf_counter() - t0
    hashmap = model.voxel_grid.hashmap()
    return Open3DResult(np.array(timestamps), np.stack(poses), loop_seconds, mesh_seconds, failures,
                        int(hashmap.size()), int(hashmap.capacity()), _bytes_per_block(model.voxel_grid),
                        vertices, faces, colors)
