"""Frames on the pipeline's device and resolution, and pixel/ray sampling from them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .data.frame import Frame
from .data.io import resize_frame
from .render import camera_rays


@dataclass(frozen=True)
class TensorFrame:
    """A frame ready for the pipeline.

    rgb (H, W, 3) float32, depth (H, W) float32 (0 = invalid), K (3, 3) float32,
    T_world_cam_gt (4, 4) float64 numpy or None. ``valid`` (P,) int64 flat indices of pixels
    with usable depth, from which rays are sampled.
    """

    index: int
    timestamp: float
    rgb: torch.Tensor
    depth: torch.Tensor
    K: torch.Tensor
    valid: torch.Tensor
    T_world_cam_gt: np.ndarray | None = None
    depth_max: float | None = None
    """The largest valid depth (metres), known on the host when the frame was prepared (the
    static-shape renderers size their sample grid with it); None: unknown."""
    color_valid: torch.Tensor | None = None
    """(H, W) bool: the pixels whose colour the camera observed (``Frame.color_valid``); None:
    all of them."""

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])


def prepare_frame(frame: Frame, width: int | None, device: torch.device, max_depth: float) -> TensorFrame:
    """Resize a reader's Frame to ``width`` (None keeps it) and move it to ``device``."""
    frame = resize_frame(frame, width)
    rgb, depth, K, seen = frame.rgb, frame.depth, frame.K, frame.color_valid
    depth = np.where((depth > 0) & (depth < max_depth), depth, 0).astype(np.float32)
    d = torch.from_numpy(np.ascontiguousarray(depth)).to(device)
    # Found on the host, which has the depth: a nonzero on the device would read it back.
    valid = torch.from_numpy(np.flatnonzero(depth.reshape(-1) > 0)).to(device)
    return TensorFrame(
        index=frame.index,
        timestamp=float(frame.timestamp),
        rgb=torch.from_numpy(np.ascontiguousarray(rgb, dtype=np.float32)).to(device),
        depth=d,
        K=torch.as_tensor(K, dtype=torch.float32).to(device),
        valid=valid,
        T_world_cam_gt=None if frame.T_world_cam is None else np.asarray(frame.T_world_cam, np.float64),
        depth_max=float(depth.max()) if depth.size else 0.0,
        color_valid=None if seen is None else torch.from_numpy(np.ascontiguousarray(seen, dtype=bool)).to(device),
    )


@dataclass(frozen=True)
class PixelBatch:
    """Sampled pixels of one frame: dirs_cam (R, 3) with z = 1, rgb (R, 3), depth (R,)."""

    dirs_cam: torch.Tensor
    rgb: torch.Tensor
    depth: torch.Tensor


def draw_device(generator: torch.Generator | None, device: torch.device) -> torch.device | None:
    """Where to draw random numbers for tensors on ``device``: there, when ``generator`` is of
    its kind (a CUDA generator draws on the GPU: no upload, which would wait for the queue);
    else the generator's own device (None: torch's default CPU generator)."""
    if generator is None:
        return None
    return device if generator.device.type == torch.device(device).type else generator.device


def sample_pixels(frame: TensorFrame, num: int, generator: torch.Generator | None = None) -> PixelBatch:
    """``num`` pixels drawn uniformly (with replacement) among those with valid depth."""
    if frame.valid.numel() == 0:
        raise ValueError(f"frame {frame.index} has no valid depth")
    pick = torch.randint(0, frame.valid.numel(), (num,), generator=generator,
                         device=draw_device(generator, frame.valid.device)).to(frame.valid.device)
    flat = frame.valid[pick]
    return pixels_at(frame, flat)


def pixels_at(frame: TensorFrame, flat: torch.Tensor) -> PixelBatch:
    """The pixels at flat indices (R,) of the image."""
    v = torch.div(flat, frame.width, rounding_mode="floor")
    u = flat - v * frame.width
    uv = torch.stack([u, v], -1).to(torch.float32)
    return PixelBatch(camera_rays(frame.K, uv), frame.rgb.reshape(-1, 3)[flat], frame.depth.reshape(-1)[flat])


@dataclass(frozen=True)
class FrameStack:
    """Several frames of one size stacked, to sample pixels of all of them at once.

    rgb (F * H * W, 3), depth (F * H * W,), K (F, 3, 3); valid (V,) flat indices into the
    stacked pixels of those with usable depth, frame by frame; valid_start, valid_count (F,).
    """

    width: int
    height: int
    rgb: torch.Tensor
    depth: torch.Tensor
    K: torch.Tensor
    valid: torch.Tensor
    valid_start: torch.Tensor
    valid_count: torch.Tensor

    @property
    def num_frames(self) -> int:
        return int(self.K.shape[0])


def stack_frames(frames: list[TensorFrame]) -> FrameStack | None:
    """The frames stacked (None if their sizes differ)."""
    if not frames or len({(f.height, f.width) for f in frames}) > 1:
        return None
    for f in frames:
        if f.valid.numel() == 0:
            raise ValueError(f"frame {f.index} has no valid depth")
    pixels = frames[0].height * frames[0].width
    counts = torch.tensor([f.valid.numel() for f in frames], device=frames[0].valid.device)
    return FrameStack(
        width=frames[0].width, height=frames[0].height,
        rgb=torch.cat([f.rgb.reshape(-1, 3) for f in frames]),
        depth=torch.cat([f.depth.reshape(-1) for f in frames]),
        K=torch.stack([f.K for f in frames]),
        valid=torch.cat([f.valid + i * pixels for i, f in enumerate(frames)]),
        valid_start=torch.cumsum(counts, 0) - counts,
        valid_count=counts,
    )


def sample_stacked_pixels(stack: FrameStack, num: int, generator: torch.Generator | None = None) -> PixelBatch:
    """``num`` pixels of every frame of ``stack``, drawn uniformly (with replacement) among
    those with valid depth: (F * num) rows, frame by frame. One batch of tensor operations
    instead of F calls of ``sample_pixels`` (global bundle adjustment: 60 keyframes cost
    10 ms a step in Python overhead)."""
    F = stack.num_frames
    u01 = torch.rand(F, num, generator=generator, device=draw_device(generator, stack.valid.device)).to(stack.valid.device)
    # min(): u01 * count can round up to count in float32.
    pick = torch.minimum((u01 * stack.valid_count[:, None]).long(), stack.valid_count[:, None] - 1)
    pick = pick + stack.valid_start[:, None]
    flat = stack.valid[pick.reshape(-1)]
    pixel = flat % (stack.height * stack.width)
    v = torch.div(pixel, stack.width, rounding_mode="floor")
    u = pixel - v * stack.width
    uv = torch.stack([u, v], -1).to(torch.float32)
    dirs = camera_rays(stack.K.repeat_interleave(num, 0), uv)  # one K per row
    return PixelBatch(dirs, stack.rgb[flat], stack.depth[flat])


def backproject(frame: TensorFrame, T_map_cam: torch.Tensor, stride: int,
                depth_offsets: tuple[float, ...] = (0.0,)) -> torch.Tensor:
    """Map-frame points of every ``stride``-th valid pixel, at depth + each offset. -> (N, 3)."""
    H, W = frame.height, frame.width
    vs = torch.arange(0, H, stride, device=frame.depth.device)
    us = torch.arange(0, W, stride, device=frame.depth.device)
    vv, uu = torch.meshgrid(vs, us, indexing="ij")
    flat = (vv * W + uu).reshape(-1)
    d = frame.depth.reshape(-1)[flat]
    keep = torch.nonzero(d > 0).squeeze(1)  # one data-dependent read for both
    flat, d = flat[keep], d[keep]
    batch = pixels_at(frame, flat)
    pts = []
    for off in depth_offsets:
        cam = batch.dirs_cam * (d + off)[:, None]
        pts.append(cam @ T_map_cam[:3, :3].T + T_map_cam[:3, 3])
    return torch.cat(pts, 0)
