"""Fly-through videos of a map: the frames of a ``CameraPath`` rendered as colour | depth |
normals side by side, and their MP4 (H.264, the one codec every browser plays).

    frames = path_frames(mapset, path, K, 320, 240, ("color", "depth", "normals"))
    write_mp4(frames, "path.mp4", fps=path.fps)
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from slam.camera_path import CameraPath, normals_from_depth, normals_image, path_poses

OUTPUTS = ("color", "depth", "normals")


def depth_image(depth: np.ndarray, depth_range: tuple[float, float]) -> np.ndarray:
    """(H, W) metres -> (H, W, 3) colours in [0, 1] (turbo colour map over ``depth_range``,
    near red, far blue, as the page's depth previews), black where there is no surface."""
    import cv2

    near, far = depth_range
    scaled = np.clip((far - depth) / max(far - near, 1e-6), 0, 1)
    colours = cv2.applyColorMap((255 * scaled).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1] / 255.0
    return np.where((depth > 0)[..., None], colours, 0.0)


def auto_depth_range(depth: np.ndarray) -> tuple[float, float]:
    """The 2nd to 98th percentile of the valid depths of a view (0.1-5 m when it has none)."""
    valid = depth[depth > 0]
    if valid.size < 16:
        return 0.1, 5.0
    near, far = np.percentile(valid, [2, 98])
    return float(near), float(max(far, near + 0.05))


def path_frames(mapset, path: CameraPath, K: np.ndarray, width: int, height: int,
                outputs: Sequence[str] = OUTPUTS, *, depth_range: tuple[float, float] | None = None,
                crop: tuple | None = None, on_frame: Callable[[int, int], None] | None = None
                ) -> Iterator[np.ndarray]:
    """Render every frame of ``path`` with intrinsics K (3, 3) of a ``width`` x ``height``
    image; yields (height, width * len(outputs), 3) uint8 frames, the outputs side by side in
    the order given. The depth colours keep one range for the whole video (``depth_range``,
    else the first view's). ``crop``: (min, max) world box, as ``render_view``'s.
    ``on_frame(done, total)`` after each frame."""
    from slam.views import render_view

    unknown = [o for o in outputs if o not in OUTPUTS]
    if not outputs or unknown:
        raise ValueError(f"outputs must be some of {OUTPUTS}, got {list(outputs)}")
    poses = path_poses(path)
    for i, T_world_cam in enumerate(poses):
        view = render_view(mapset, T_world_cam, K, width, height, crop=crop)
        depth = np.where(view.valid, view.depth, 0.0)
        if depth_range is None:
            depth_range = auto_depth_range(depth)
        panels = {"color": lambda: np.clip(view.rgb, 0, 1),
                  "depth": lambda: depth_image(depth, depth_range),
                  "normals": lambda: normals_image(normals_from_depth(depth, np.asarray(K, np.float64)))}
        frame = np.concatenate([panels[o]() for o in outputs], axis=1)
        yield np.round(frame * 255).astype(np.uint8)
        if on_frame is not None:
            on_frame(i + 1, len(poses))


def write_mp4(frames: Iterator[np.ndarray], out: str | Path, fps: float) -> Path:
    """Encode (H, W, 3) uint8 RGB frames as H.264 MP4 (yuv420p; an odd side is padded by a
    pixel) with ``imageio-ffmpeg``'s bundled ffmpeg. Returns ``out``."""
    import imageio_ffmpeg

    out = Path(out)
    writer = None
    try:
        for frame in frames:
            h, w = frame.shape[:2]
            frame = np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
            if writer is None:
                writer = imageio_ffmpeg.write_frames(str(out), (frame.shape[1], frame.shape[0]), fps=fps,
                                                     codec="libx264", pix_fmt_out="yuv420p", quality=7,
                                                     macro_block_size=1, ffmpeg_log_level="error")
                writer.send(None)
            writer.send(np.ascontiguousarray(frame))
    finally:
        if writer is not None:
            writer.close()
    if writer is None:
        raise ValueError("no frames to encode")
    return out
