"""Record3D without an iPhone: a ``.r3d`` export written in the app's layout, and a stand-in for
usbmuxd with a phone behind it that streams Record3D's USB messages.

The live stand-in lets the real ``record3d`` package run unchanged: its libusbmuxd reads the
daemon's socket from ``USBMUXD_SOCKET_ADDRESS=UNIX:/path``, asks it for devices (``ListDevices``)
and connects to the phone's port 1337 (``Connect``), both as XML plists after a 16-byte header;
the socket then carries the app's messages, each a PeerTalk header (body size big-endian) and a
body the library parses: eleven uint32 sizes and the device type, the colour intrinsics
(fx, fy, tx, ty), a pose (7 floats), a JPEG, LZFSE float32 depth and LZFSE uint8 confidence.
The JPEG decoding, LZFSE decompression and the callbacks are the package's own.
"""

from __future__ import annotations

import json
import plistlib
import socket
import struct
import threading
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

RECORD3D_PORT = 1337
USBMUX_PLIST = 8
DEVICE_ID = 7


@dataclass(frozen=True)
class PhoneFrame:
    """What the phone has for one frame: (H, W, 3) uint8 RGB, (h, w) float32 metres, (h, w)
    uint8 confidence or None (TrueDepth), colour intrinsics (fx, fy, cx, cy), 1 LiDAR / 0 TrueDepth."""

    rgb: np.ndarray
    depth: np.ndarray
    confidence: np.ndarray | None
    K: tuple[float, float, float, float]
    device_type: int = 1


def jpeg(rgb: np.ndarray) -> bytes:
    return cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()


def record3d_message(frame: PhoneFrame) -> bytes:
    """One USB message of the app (PeerTalk header + body)."""
    import lzfse

    depth = lzfse.compress(np.ascontiguousarray(frame.depth, np.float32).tobytes())
    confidence = b"" if frame.confidence is None else lzfse.compress(np.ascontiguousarray(frame.confidence).tobytes())
    image = jpeg(frame.rgb)
    (h, w), (dh, dw) = frame.rgb.shape[:2], frame.depth.shape
    ch, cw = (0, 0) if frame.confidence is None else frame.confidence.shape
    body = (struct.pack("<11I", w, h, dw, dh, cw, ch, len(image), len(depth), len(confidence), 0, frame.device_type)
            + struct.pack("<4f", *frame.K) + struct.pack("<7f", 0, 0, 0, 1, 0, 0, 0) + image + depth + confidence)
    return struct.pack(">4I", 1, 101, 0, len(body)) + body


class FakeUsbmuxd:
    """usbmuxd on a UNIX socket with one USB phone whose Record3D streams ``frames`` every
    ``interval_s``, then unplugs (closes the connection) after ``linger_s``.

    It runs in a process of its own: ``record3d``'s calls hold the GIL while they wait for the
    daemon's answer, so a daemon thread in the same interpreter could never answer them.
    """

    def __init__(self, path: Path, frames: list[PhoneFrame], udid: str = "00008101-000A1B2C3D4E5F60",
                 interval_s: float = 0.05, linger_s: float = 0.0) -> None:
        import multiprocessing

        context = multiprocessing.get_context("spawn")
        self.path, self.udid = path, udid
        self._sent = context.Value("i", 0)
        self._process = context.Process(target=serve_usbmuxd, daemon=True,
                                        args=(str(path), frames, udid, interval_s, linger_s, self._sent))
        self._process.start()
        deadline = time.monotonic() + 60
        while not path.exists():
            assert time.monotonic() < deadline and self._process.is_alive(), "the fake usbmuxd did not start"
            time.sleep(0.05)

    @property
    def address(self) -> str:
        """The value for ``USBMUXD_SOCKET_ADDRESS``."""
        return f"UNIX:{self.path}"

    @property
    def sent(self) -> int:
        """Frames the phone has sent so far."""
        return self._sent.value

    def close(self) -> None:
        self._process.kill()
        self._process.join(timeout=10)


def serve_usbmuxd(path: str, frames: list[PhoneFrame], udid: str, interval_s: float, linger_s: float,
                  sent) -> None:
    """The fake daemon's process: answer each client connection in a thread."""
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(path)
    listener.listen(4)
    phone = _Phone(frames, udid, interval_s, linger_s, sent)
    while True:
        connection, _ = listener.accept()
        threading.Thread(target=phone.serve, args=(connection,), daemon=True).start()


@dataclass
class _Phone:
    frames: list[PhoneFrame]
    udid: str
    interval_s: float
    linger_s: float
    sent: object

    def serve(self, connection: socket.socket) -> None:
        """One client connection: usbmuxd requests until a Connect, then the app's stream."""
        with connection:
            while (request := _receive(connection)) is not None:
                tag, message = request
                if message.get("MessageType") == "ListDevices":
                    properties = {"ConnectionType": "USB", "DeviceID": DEVICE_ID, "ProductID": 0x12A8,
                                  "SerialNumber": self.udid}
                    _reply(connection, tag, {"DeviceList": [
                        {"DeviceID": DEVICE_ID, "MessageType": "Attached", "Properties": properties}]})
                elif message.get("MessageType") == "Connect":
                    port = socket.ntohs(int(message["PortNumber"]))
                    ok = message.get("DeviceID") == DEVICE_ID and port == RECORD3D_PORT
                    _reply(connection, tag, {"MessageType": "Result", "Number": 0 if ok else 3})
                    if ok:
                        self.stream(connection)
                    return
                else:
                    _reply(connection, tag, {"MessageType": "Result", "Number": 1})

    def stream(self, connection: socket.socket) -> None:
        for frame in self.frames:
            try:
                connection.sendall(record3d_message(frame))
            except OSError:
                return
            with self.sent.get_lock():
                self.sent.value += 1
            time.sleep(self.interval_s)
        time.sleep(self.linger_s)


def _receive(connection: socket.socket) -> tuple[int, dict] | None:
    """One usbmuxd request: (tag, plist), or None when the client closed."""
    header = _read(connection, 16)
    if header is None:
        return None
    length, _version, _kind, tag = struct.unpack("<4I", header)
    payload = _read(connection, length - 16)
    return None if payload is None else (tag, plistlib.loads(payload))


def _reply(connection: socket.socket, tag: int, message: dict) -> None:
    payload = plistlib.dumps(message, fmt=plistlib.FMT_XML)
    connection.sendall(struct.pack("<4I", 16 + len(payload), 1, USBMUX_PLIST, tag) + payload)


def _read(connection: socket.socket, size: int) -> bytes | None:
    data = b""
    while len(data) < size:
        chunk = connection.recv(size - len(data))
        if not chunk:
            return None
        data += chunk
    return data


def write_r3d(path: Path, frames: list[PhoneFrame], timestamps: list[float], fps: int = 30,
              with_depth_size: bool = True) -> None:
    """A Record3D export: ``metadata`` JSON (K column-major), ``rgbd/N.jpg|.depth|.conf``."""
    import lzfse

    first = frames[0]
    (h, w), (dh, dw) = first.rgb.shape[:2], first.depth.shape
    fx, fy, cx, cy = first.K
    meta = {"w": w, "h": h, "K": [fx, 0, 0, 0, fy, 0, cx, cy, 1], "fps": fps, "cameraType": first.device_type,
            "frameTimestamps": timestamps, "poses": [[0, 0, 0, 1, 0, 0, 0]] * len(frames),
            "initPose": [0, 0, 0, 1, 0, 0, 0]}
    if with_depth_size:
        meta.update(dw=dw, dh=dh)
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("metadata", json.dumps(meta))
        for i, frame in enumerate(frames):
            archive.writestr(f"rgbd/{i}.jpg", jpeg(frame.rgb))
            archive.writestr(f"rgbd/{i}.depth", lzfse.compress(np.ascontiguousarray(frame.depth, np.float32).tobytes()))
            if frame.confidence is not None:
                archive.writestr(f"rgbd/{i}.conf", lzfse.compress(np.ascontiguousarray(frame.confidence).tobytes()))
