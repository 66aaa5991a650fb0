"""Frame sources for ``voxfusion stream``: a dataset folder replayed like a camera, a RealSense
(Record3D: ``client/record3d.py``; ``client.open.open_source`` picks one by name).

A source says what its camera is (``CameraInfo``) before the first frame, then yields
``PendingFrame`` items at the pace frames arrive: a live camera as the device delivers them, a
folder at its recorded timestamps (or ``--fps``). A pending frame is encoded only when the
client actually sends it (``encode``), so frames dropped by back-pressure cost no PNG encoding
(and, for a folder, no image decoding).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Protocol

import cv2
import numpy as np

DEFAULT_FPS = 30.0
"""Replay rate of a folder whose format has no recorded time (frame numbers only)."""

FOLDER_DEPTH_SCALE = 5000.0
"""Raw units per metre of the 16-bit depth PNGs made from a folder's metric depth (13.1 m max)."""


class SourceError(RuntimeError):
    """A source that cannot be opened or stopped delivering; the message is one line for users."""


@dataclass(frozen=True)
class CameraInfo:
    """What the server is told when the session is created.

    Attributes:
        intrinsics: (fx, fy, cx, cy) in pixels of the colour image (depth is aligned to it).
        depth_scale: raw depth units per metre of the depth PNGs sent.
        width, height: image size in pixels.
        live: True for a camera (frames come whether or not we keep up), False for a replay.
        name: what to show the user.
    """

    intrinsics: tuple[float, float, float, float]
    depth_scale: float
    width: int
    height: int
    live: bool
    name: str

    def intrinsics_text(self) -> str:
        """``"fx,fy,cx,cy"`` as the server's API takes it."""
        return ",".join(f"{v:.6g}" for v in self.intrinsics)


@dataclass(frozen=True)
class EncodedFrame:
    """One frame as it goes over the wire: timestamp (s), colour PNG/JPEG, 16-bit depth PNG."""

    timestamp: float
    color: bytes
    depth: bytes


@dataclass(frozen=True)
class PendingFrame:
    """A frame that has arrived but is not encoded yet.

    Attributes:
        index: position in the source (0, 1, ...; dropped frames leave gaps in what is sent).
        arrived: ``time.monotonic()`` when the source delivered it.
        encode: makes the wire form (reads/encodes images; called only for frames sent).
    """

    index: int
    arrived: float
    encode: Callable[[], EncodedFrame]


class FrameSource(Protocol):
    """What the stream client reads from."""

    info: CameraInfo

    def frames(self, stop: Callable[[], bool]) -> Iterator[PendingFrame]:
        """Yield frames as they arrive until the source ends or ``stop()`` is true."""
        ...

    def close(self) -> None:
        """Release the device or files (idempotent)."""
        ...


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an (H, W) uint16 or (H, W, 3) uint8 RGB image."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, data = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise SourceError("could not encode a frame as PNG")
    return data.tobytes()


def metric_depth_to_raw(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """(H, W) float metres (0 = invalid) -> (H, W) uint16 raw units (``depth_scale`` per metre)."""
    raw = np.round(np.nan_to_num(depth_m, nan=0.0, posinf=0.0) * depth_scale)
    return np.clip(raw, 0, 65535).astype(np.uint16)


def paced(offsets: np.ndarray, stop: Callable[[], bool]) -> Iterator[tuple[int, float]]:
    """(index, ``time.monotonic()``) as each offset (s after the start) comes due: a recording
    released at its recorded rate, like a camera; ends early when ``stop()``."""
    start = time.monotonic()
    for i, offset in enumerate(offsets):
        while not stop():
            wait = start + float(offset) - time.monotonic()
            if wait <= 0:
                break
            time.sleep(min(wait, 0.05))
        if stop():
            return
        yield i, time.monotonic()


# --------------------------------------------------------------------------------------------
# A dataset folder (or a synthetic spec), replayed like a camera


class FolderSource:
    """A dataset folder in any layout ``slam.data.open_sequence`` knows, replayed in time.

    TUM folders are paced by their recorded timestamps; other formats (whose timestamps are
    frame numbers) at ``DEFAULT_FPS``; ``fps`` overrides both. The timestamps sent are the
    dataset's own, so the trajectory that comes back lines up with its ground truth. With
    ``color_camera`` (colour from a camera of its own) the colour sent is registered onto the
    depth camera first, as ``voxfusion run`` registers it.
    """

    def __init__(self, path: str, *, fps: float | None = None, max_frames: int | None = None,
                 width: int | None = None, color_camera=None) -> None:
        from slam import DataError, detect_format, open_sequence

        try:
            self.format = detect_format(path)
            self.sequence = open_sequence(path, width=width, max_frames=max_frames, color_camera=color_camera)
            if len(self.sequence) == 0:
                raise SourceError(f"{path}: the dataset has no frames")
            first = self.sequence[0]
        except (DataError, OSError, ValueError) as error:
            raise SourceError(str(error)) from None
        K = first.K
        self.info = CameraInfo(intrinsics=(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])),
                               depth_scale=FOLDER_DEPTH_SCALE, width=first.width, height=first.height,
                               live=False, name=f"{path} ({self.format}, {len(self.sequence)} frames)")
        self.offsets = self._schedule(fps)

    def _schedule(self, fps: float | None) -> np.ndarray:
        """(N,) seconds after the first frame at which each frame arrives."""
        n = len(self.sequence)
        stamps = getattr(self.sequence, "timestamps", None)
        if fps is None and self.format == "tum" and stamps is not None:
            offsets = np.asarray(stamps, dtype=np.float64) - float(stamps[0])
            return np.maximum.accumulate(np.maximum(offsets, 0.0))
        return np.arange(n, dtype=np.float64) / float(fps or DEFAULT_FPS)

    def _encoder(self, i: int) -> Callable[[], EncodedFrame]:
        def encode() -> EncodedFrame:
            frame = self.sequence[i]
            rgb = np.round(np.clip(frame.rgb, 0.0, 1.0) * 255).astype(np.uint8)
            return EncodedFrame(float(frame.timestamp), encode_png(rgb),
                                encode_png(metric_depth_to_raw(frame.depth, self.info.depth_scale)))
        return encode

    def frames(self, stop: Callable[[], bool]) -> Iterator[PendingFrame]:
        for i, arrived in paced(self.offsets, stop):
            yield PendingFrame(index=i, arrived=arrived, encode=self._encoder(i))

    def close(self) -> None:
        pass


# --------------------------------------------------------------------------------------------
# Intel RealSense (pyrealsense2): a live camera or a .bag recording

REALSENSE_EXTRA = "pip install 'voxfusion[realsense]' (or: pip install pyrealsense2)"


def import_device_library(module: str, needed_for: str, extra: str):
    """A device library imported on first use (they are optional extras), or SourceError
    naming the extra to install: ``needed_for`` says what wanted it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise SourceError(f"{needed_for} needs {module}: {extra}") from None


def import_realsense():
    """The ``pyrealsense2`` module, or SourceError naming the extra to install."""
    return import_device_library("pyrealsense2", "the RealSense source", REALSENSE_EXTRA)


@dataclass(frozen=True)
class RealSenseOptions:
    """Stream settings of a RealSense camera (ignored for a .bag, which has its own)."""

    serial: str | None = None
    width: int = 640
    height: int = 480
    fps: int = 30
    real_time: bool = True
    """.bag only: play at the recorded rate (False: as fast as frames are taken)."""


class RealSenseSource:
    """Colour + depth from a RealSense (or a .bag): depth aligned to colour by the SDK.

    Intrinsics are the colour stream's (the aligned depth shares them); the depth scale is the
    depth sensor's (metres per unit), sent as its inverse (units per metre). The 16-bit depth
    goes out as recorded, without conversion.
    """

    FRAME_TIMEOUT_MS = 5000
    POLL_MS = 200

    def __init__(self, bag: Path | None = None, options: RealSenseOptions = RealSenseOptions(),
                 max_frames: int | None = None) -> None:
        rs = import_realsense()
        self.rs = rs
        self.max_frames = max_frames
        self.pipeline = rs.pipeline()
        config = rs.config()
        if bag is not None:
            if not Path(bag).is_file():
                raise SourceError(f"no such RealSense recording: {bag}")
            config.enable_device_from_file(str(bag), repeat_playback=False)
        else:
            if options.serial:
                config.enable_device(options.serial)
            config.enable_stream(rs.stream.depth, options.width, options.height, rs.format.z16, options.fps)
            config.enable_stream(rs.stream.color, options.width, options.height, rs.format.rgb8, options.fps)
        try:
            profile = self.pipeline.start(config)
        except RuntimeError as error:
            what = f"recording {bag}" if bag else (f"camera {options.serial}" if options.serial else "a camera")
            raise SourceError(f"RealSense: cannot start {what}: {error}") from None
        device = profile.get_device()
        self.playback = None
        if bag is not None:
            self.playback = device.as_playback()
            self.playback.set_real_time(options.real_time)
        self.align = rs.align(rs.stream.color)
        color = profile.get_stream(rs.stream.color).as_video_stream_profile()
        k = color.get_intrinsics()
        # A frameset whose colour and depth lie more than half a frame apart is mispaired:
        # each has a nearer partner. pyrealsense2's playback syncer sometimes pairs colour k
        # with depth k + 1 (seen in about 1 run in 50 of the recording test); SLAM must not
        # get such a frame.
        self.max_pairing_gap_ms = 500.0 / max(color.fps(), 1)
        self.mispaired = 0
        scale = device.first_depth_sensor().get_depth_scale()
        what = f"recording {bag}" if bag else device.get_info(rs.camera_info.serial_number)
        self.info = CameraInfo(intrinsics=(k.fx, k.fy, k.ppx, k.ppy), depth_scale=1.0 / scale, width=k.width,
                               height=k.height, live=bag is None or options.real_time, name=f"RealSense {what}")
        self.bag = bag
        self._stopped = False

    def _next(self):
        """The next frameset, or None at the end of a recording; SourceError when a camera stops."""
        waited_ms = 0
        while waited_ms < self.FRAME_TIMEOUT_MS:
            ok, frameset = self.pipeline.try_wait_for_frames(self.POLL_MS)
            if ok:
                return frameset
            if self.playback is not None and self.playback.current_status() == self.rs.playback_status.stopped:
                return None
            waited_ms += self.POLL_MS
        if self.playback is not None:
            return None
        raise SourceError(f"RealSense: no frame for {self.FRAME_TIMEOUT_MS / 1000:g} s (camera unplugged?)")

    def frames(self, stop: Callable[[], bool]) -> Iterator[PendingFrame]:
        index = 0
        while not stop() and (self.max_frames is None or index < self.max_frames):
            frameset = self._next()
            if frameset is None:
                return
            raw_color, raw_depth = frameset.get_color_frame(), frameset.get_depth_frame()
            if not raw_color or not raw_depth:
                continue
            if abs(raw_color.get_timestamp() - raw_depth.get_timestamp()) > self.max_pairing_gap_ms:
                self.mispaired += 1
                continue
            aligned = self.align.process(frameset)
            color, depth = aligned.get_color_frame(), aligned.get_depth_frame()
            if not color or not depth:
                continue
            rgb = np.asanyarray(color.get_data()).copy()
            raw = np.asanyarray(depth.get_data()).copy()
            stamp = color.get_timestamp() / 1000.0

            def encode(rgb=rgb, raw=raw, stamp=stamp) -> EncodedFrame:
                return EncodedFrame(stamp, encode_png(rgb), encode_png(raw.astype(np.uint16)))

            yield PendingFrame(index=index, arrived=time.monotonic(), encode=encode)
            index += 1

    def close(self) -> None:
        if not self._stopped:
            self._stopped = True
            try:
                self.pipeline.stop()
            except RuntimeError:
                pass
