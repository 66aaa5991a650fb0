"""Record3D (iPhone/iPad LiDAR or TrueDepth) for ``voxfusion stream``: the app's live USB stream
(the ``record3d`` package) or a ``.r3d`` file it exported.

Both deliver what ARKit gives: an RGB image with its intrinsics, a float32 depth map in metres
at a lower resolution (LiDAR: 256x192 for a 1920x1440 or 960x720 image) over the same field
of view (ARKit registers ``sceneDepth`` to the captured image, so there is no extrinsic to
apply), and a confidence map (0 low, 1 medium, 2 high) beside the depth. "Aligned to colour"
therefore means resampling the depth onto the colour grid: nearest neighbour (interpolating
across an edge would invent depths between foreground and background), pixel centres lined
up (``INTER_NEAREST_EXACT``), and the intrinsics scaled with the same centre convention when
the colour image is resized (``--width``). Depth of low confidence, NaN or <= 0 becomes 0 (no
depth). Depth goes out as 16-bit PNG at ``FOLDER_DEPTH_SCALE`` units per metre.

``.r3d`` layout (a zip): ``metadata`` (JSON: ``w``/``h`` colour size, ``dw``/``dh`` depth size,
``K`` the 3x3 colour intrinsics column-major, ``fps``, ``frameTimestamps`` in seconds, poses),
``rgbd/N.jpg``, ``rgbd/N.depth`` (LZFSE-compressed float32 dh x dw) and ``rgbd/N.conf`` (LZFSE
uint8; absent for TrueDepth). The live stream: ``Record3DStream`` over usbmuxd; its callback
runs on the library's thread, so the frame is copied there (the library overwrites its buffers
with the next frame) and the newest one is handed to ``frames``.
"""

from __future__ import annotations

import json
import re
import threading
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np

from client.camera_sources import (FOLDER_DEPTH_SCALE, CameraInfo, EncodedFrame, PendingFrame, SourceError,
                                   encode_png, import_device_library, metric_depth_to_raw, paced)

RECORD3D_EXTRA = "pip install 'voxfusion[record3d]' (or: pip install record3d lzfse)"
DEVICE_TYPES = {0: "TrueDepth", 1: "LiDAR"}


def import_lzfse():
    """The ``lzfse`` module (Apple's LZFSE, which .r3d depth uses), or SourceError naming the extra."""
    return import_device_library("lzfse", "a Record3D .r3d file", RECORD3D_EXTRA)


def import_record3d():
    """The ``record3d`` module (the app's USB stream), or SourceError naming the extra."""
    return import_device_library("record3d", "the Record3D live stream", RECORD3D_EXTRA)


# --------------------------------------------------------------------------------------------
# Depth onto the colour grid


@dataclass(frozen=True)
class Record3DOptions:
    """How frames are turned into what the server gets.

    Attributes:
        width: colour width sent (height keeps the aspect); None: the RGB image's own.
        min_confidence: ARKit confidence kept (0 all, 1 medium and high, 2 high only). Low
            confidence marks depth ARKit itself calls unreliable (edges, dark or far surfaces).
    """

    width: int | None = None
    min_confidence: int = 1


@dataclass(frozen=True)
class RGBDFrame:
    """One frame as Record3D delivers it: (H, W, 3) uint8 RGB, (h, w) float32 metres,
    (h, w) uint8 confidence or None, seconds."""

    rgb: np.ndarray
    depth: np.ndarray
    confidence: np.ndarray | None
    timestamp: float


def output_size(rgb_size: tuple[int, int], width: int | None) -> tuple[int, int]:
    """(width, height) sent for an RGB image of ``rgb_size`` (w, h) asked to be ``width`` wide."""
    w, h = rgb_size
    if width is None or width == w:
        return w, h
    return int(width), max(1, int(round(h * width / w)))


def scale_intrinsics(K: tuple[float, float, float, float], src: tuple[int, int],
                     dst: tuple[int, int]) -> tuple[float, float, float, float]:
    """Intrinsics of an image of size ``src`` (w, h) resized to ``dst``: pixel centres stay
    on the same rays, so c' = (c + 0.5) s - 0.5 (as cv2.resize samples)."""
    fx, fy, cx, cy = K
    sx, sy = dst[0] / src[0], dst[1] / src[1]
    return fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5


def depth_on_colour_grid(frame: RGBDFrame, size: tuple[int, int], min_confidence: int) -> np.ndarray:
    """(H, W) float32 metres on the colour grid of ``size`` (w, h); 0 where there is no depth."""
    depth = np.nan_to_num(frame.depth.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    depth[depth < 0] = 0.0
    if frame.confidence is not None and frame.confidence.shape == depth.shape:
        depth[frame.confidence < min_confidence] = 0.0
    if depth.shape[::-1] == tuple(size):
        return depth
    return cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST_EXACT)


def encode_frame(frame: RGBDFrame, size: tuple[int, int], options: Record3DOptions) -> EncodedFrame:
    """The wire form: colour resized to ``size``, depth resampled onto it, 16-bit PNGs."""
    rgb = frame.rgb
    if rgb.shape[1::-1] != tuple(size):
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    depth = depth_on_colour_grid(frame, size, options.min_confidence)
    return EncodedFrame(frame.timestamp, encode_png(np.ascontiguousarray(rgb)),
                        encode_png(metric_depth_to_raw(depth, FOLDER_DEPTH_SCALE)))


def camera_info(K: tuple[float, float, float, float], rgb_size: tuple[int, int], options: Record3DOptions,
                live: bool, name: str) -> CameraInfo:
    """What the server is told: the colour intrinsics at the size sent, depth in 1/5000 m."""
    size = output_size(rgb_size, options.width)
    return CameraInfo(intrinsics=scale_intrinsics(K, rgb_size, size), depth_scale=FOLDER_DEPTH_SCALE,
                      width=size[0], height=size[1], live=live, name=name)


# --------------------------------------------------------------------------------------------
# An exported .r3d file, replayed like a camera


@dataclass(frozen=True)
class R3DMetadata:
    """What a .r3d's ``metadata`` says: colour size (w, h), depth size (w, h) or None when the
    file does not say (older exports), colour intrinsics (fx, fy, cx, cy), fps, timestamps."""

    rgb_size: tuple[int, int]
    depth_size: tuple[int, int] | None
    K: tuple[float, float, float, float]
    fps: float
    timestamps: tuple[float, ...]
    device: str


def read_r3d_metadata(archive: zipfile.ZipFile) -> R3DMetadata:
    """Parse ``metadata``; SourceError naming what is missing."""
    try:
        meta = json.loads(archive.read("metadata"))
        K = np.asarray(meta["K"], dtype=np.float64).reshape(3, 3).T  # stored column-major
        rgb_size = (int(meta["w"]), int(meta["h"]))
    except KeyError as error:
        raise SourceError(f"not a Record3D .r3d file: no {error} in its metadata") from None
    except (ValueError, TypeError) as error:
        raise SourceError(f"unreadable .r3d metadata: {error}") from None
    depth_size = (int(meta["dw"]), int(meta["dh"])) if "dw" in meta and "dh" in meta else None
    return R3DMetadata(rgb_size=rgb_size, depth_size=depth_size,
                       K=(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])),
                       fps=float(meta.get("fps") or 30.0),
                       timestamps=tuple(float(t) for t in meta.get("frameTimestamps") or ()),
                       device=DEVICE_TYPES.get(meta.get("cameraType"), "camera"))


def depth_shape(values: int, meta: R3DMetadata) -> tuple[int, int]:
    """(h, w) of a depth map of ``values`` pixels: the metadata's, else the colour aspect."""
    if meta.depth_size is not None:
        return meta.depth_size[1], meta.depth_size[0]
    w, h = meta.rgb_size
    dw = int(round(np.sqrt(values * w / h)))
    if dw == 0 or values % dw:
        raise SourceError(f"a .r3d depth map of {values} values does not fit the colour aspect {w}x{h}")
    return values // dw, dw


class R3DSource:
    """A Record3D export (``.r3d``) replayed at its recorded timestamps (or ``fps``)."""

    FRAME = re.compile(r"^rgbd/(\d+)\.jpg$")

    def __init__(self, path: Path, *, fps: float | None = None, max_frames: int | None = None,
                 options: Record3DOptions = Record3DOptions()) -> None:
        self.lzfse = import_lzfse()
        try:
            self.archive = zipfile.ZipFile(path)
        except (OSError, zipfile.BadZipFile) as error:
            raise SourceError(f"cannot open the Record3D file {path}: {error}") from None
        self.meta = read_r3d_metadata(self.archive)
        self.options = options
        names = set(self.archive.namelist())
        numbers = sorted(int(m.group(1)) for m in map(self.FRAME.match, names) if m)
        self.numbers = [n for n in numbers if f"rgbd/{n}.depth" in names][:max_frames]
        if not self.numbers:
            raise SourceError(f"{path}: the Record3D file has no frames with depth")
        self.size = output_size(self.meta.rgb_size, options.width)
        self.info = camera_info(self.meta.K, self.meta.rgb_size, options, live=False,
                                name=f"{path} (Record3D {self.meta.device}, {len(self.numbers)} frames)")
        self.stamps = self._timestamps(fps)

    def _timestamps(self, fps: float | None) -> np.ndarray:
        """(N,) seconds of each frame: the recorded ones, else frame / fps."""
        stamps = self.meta.timestamps
        if fps is None and len(stamps) > max(self.numbers):
            return np.asarray([stamps[n] for n in self.numbers], dtype=np.float64)
        return np.asarray(self.numbers, dtype=np.float64) / float(fps or self.meta.fps)

    def read(self, number: int) -> RGBDFrame:
        """Frame ``number`` of the file, decoded (JPEG, LZFSE)."""
        jpeg = np.frombuffer(self.archive.read(f"rgbd/{number}.jpg"), np.uint8)
        bgr = cv2.imdecode(jpeg, cv2.IMREAD_COLOR)
        if bgr is None or bgr.shape[1::-1] != self.meta.rgb_size:
            raise SourceError(f"rgbd/{number}.jpg is not a {self.meta.rgb_size[0]}x{self.meta.rgb_size[1]} JPEG")
        depth = np.frombuffer(self.lzfse.decompress(self.archive.read(f"rgbd/{number}.depth")), np.float32)
        depth = depth.reshape(depth_shape(depth.size, self.meta))
        confidence = None
        if f"rgbd/{number}.conf" in self.archive.namelist():
            raw = np.frombuffer(self.lzfse.decompress(self.archive.read(f"rgbd/{number}.conf")), np.uint8)
            confidence = raw.reshape(depth.shape) if raw.size == depth.size else None
        stamp = float(self.stamps[self.numbers.index(number)])
        return RGBDFrame(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth, confidence, stamp)

    def frames(self, stop: Callable[[], bool]) -> Iterator[PendingFrame]:
        for i, arrived in paced(self.stamps - self.stamps[0], stop):
            number = self.numbers[i]
            yield PendingFrame(index=i, arrived=arrived,
                               encode=lambda n=number: encode_frame(self.read(n), self.size, self.options))

    def close(self) -> None:
        self.archive.close()


# --------------------------------------------------------------------------------------------
# The live USB stream

_STREAMS_KEPT: list = []
"""Every ``Record3DStream`` made: the library's receiving thread is detached and uses its
stream object until it notices the end, so the object is never freed while the process runs."""


class Record3DLiveSource:
    """The Record3D app streaming over USB (Settings: USB streaming; usbmuxd must run).

    The intrinsics are those of the first frame (the server takes one camera per session);
    timestamps are the computer's clock on arrival (the stream carries none).
    """

    FRAME_TIMEOUT_S = 5.0

    def __init__(self, *, udid: str | None = None, max_frames: int | None = None,
                 options: Record3DOptions = Record3DOptions()) -> None:
        record3d = import_record3d()
        self.options, self.max_frames = options, max_frames
        self._cond = threading.Condition()
        self._frame: RGBDFrame | None = None
        self._count, self._stopped = 0, False
        self._K, self._device_type = (0.0, 0.0, 0.0, 0.0), -1
        device = self._pick(record3d.Record3DStream.get_connected_devices(), udid)
        self.stream = record3d.Record3DStream()
        _STREAMS_KEPT.append(self.stream)
        self.stream.on_new_frame = self._on_frame
        self.stream.on_stream_stopped = self._on_stopped
        if not self.stream.connect(device):
            raise SourceError(f"Record3D: cannot connect to {device.udid} (is the app streaming over USB, "
                              "and no other program connected?)")
        first, _ = self._wait_frame(0)
        self.size = output_size(first.rgb.shape[1::-1], options.width)
        kind = DEVICE_TYPES.get(self._device_type, "camera")
        self.info = camera_info(self._K, first.rgb.shape[1::-1], options, live=True,
                                name=f"Record3D {kind} {device.udid}")

    @staticmethod
    def _pick(devices: list, udid: str | None):
        if not devices:
            raise SourceError("Record3D: no iPhone/iPad found over USB (plug it in, trust this computer, start "
                              "USB streaming in the Record3D app; on Linux usbmuxd must be running)")
        if udid is None:
            return devices[0]
        for device in devices:
            if device.udid == udid:
                return device
        raise SourceError(f"Record3D: no device {udid}; connected: {', '.join(d.udid for d in devices)}")

    def _on_frame(self) -> None:
        """On the library's thread: copy the frame now (the buffers are reused for the next)."""
        stream = self.stream
        confidence = stream.get_confidence_frame()
        frame = RGBDFrame(rgb=np.array(stream.get_rgb_frame(), copy=True),
                          depth=np.array(stream.get_depth_frame(), copy=True),
                          confidence=np.array(confidence, copy=True) if confidence.size else None,
                          timestamp=time.time())
        k = stream.get_intrinsic_mat()
        with self._cond:
            self._K = (float(k.fx), float(k.fy), float(k.tx), float(k.ty))
            self._device_type = int(stream.get_device_type())
            self._frame, self._count = frame, self._count + 1
            self._cond.notify_all()

    def _on_stopped(self) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify_all()

    def _wait_frame(self, seen: int) -> tuple[RGBDFrame, int]:
        """The newest frame after the ``seen``-th and its number; SourceError when the stream
        stops or stalls."""
        deadline = time.monotonic() + self.FRAME_TIMEOUT_S
        with self._cond:
            while self._count <= seen:
                if self._stopped:
                    raise SourceError("Record3D: the stream stopped (device unplugged, or streaming "
                                      "stopped in the app)")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise SourceError(f"Record3D: no frame for {self.FRAME_TIMEOUT_S:g} s (device unplugged?)")
                self._cond.wait(min(left, 0.2))
            return self._frame, self._count

    def frames(self, stop: Callable[[], bool]) -> Iterator[PendingFrame]:
        index, seen = 0, 0
        while not stop() and (self.max_frames is None or index < self.max_frames):
            frame, seen = self._wait_frame(seen)
            yield PendingFrame(index=index, arrived=time.monotonic(),
                               encode=lambda f=frame: encode_frame(f, self.size, self.options))
            index += 1

    def close(self) -> None:
        """Disconnect; the callbacks are dropped first so none runs into a closed source."""
        if getattr(self, "stream", None) is not None and not self._stopped:
            self.stream.on_new_frame = None
            self.stream.disconnect()
            self._stopped = True
