"""Encoded images from untrusted sources: the size read from the header before any decoding.

A PNG or JPEG of a few kilobytes can declare 65535 x 65535 pixels and take gigabytes to decode
(a decompression bomb), so every image this project decodes, from a dataset folder, an
uploaded zip or a streamed frame, goes through :func:`decode_image`: it reads the width and
height from the header (PNG's IHDR chunk, JPEG's start-of-frame segment), refuses what is
over :data:`MAX_IMAGE_SIDE` or :data:`MAX_IMAGE_PIXELS`, and only then decodes. Formats
other than PNG and JPEG are refused: every supported dataset stores its frames as one of them.
"""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np

from slam.data.frame import DataError

MAX_IMAGE_SIDE = 4096
"""Longest image side (pixels) decoded anywhere."""
MAX_IMAGE_PIXELS = 4096 * 3072
"""Most pixels of one image (an Azure Kinect's largest colour mode; Kinect/RealSense/Replica
frames are 0.3-2 Mpx): a 16-bit RGBA image this size decodes to 100 MB, float RGB to 150 MB."""
MAX_IMAGE_FILE_BYTES = 128 * 1024 * 1024
"""Largest encoded image file read (a 16-bit RGBA PNG of MAX_IMAGE_PIXELS stored uncompressed)."""

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SIGNATURE = b"\xff\xd8"
# JPEG start-of-frame markers (C0-CF) except DHT (C4), JPG (C8) and DAC (CC).
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# Markers without a length field: TEM, RST0-7, SOI.
_JPEG_STANDALONE = frozenset([0x01, *range(0xD0, 0xD9)])


class ImageTooLarge(DataError):
    """An image's header declares more pixels than :data:`MAX_IMAGE_PIXELS` (or a longer side)."""


def image_format(data: bytes) -> str | None:
    """``"png"``, ``"jpeg"`` or None, from the first bytes."""
    if data.startswith(PNG_SIGNATURE):
        return "png"
    if data.startswith(JPEG_SIGNATURE):
        return "jpeg"
    return None


def _png_size(data: bytes) -> tuple[int, int] | None:
    # Signature (8), IHDR length (4), "IHDR" (4), width (4), height (4).
    if len(data) < 24 or data[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", data[16:24])


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) of the first start-of-frame segment, walking segments by their lengths."""
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in _JPEG_STANDALONE:
            i += 2
            continue
        if marker == 0xDA:  # start of scan: no frame header before it
            return None
        (length,) = struct.unpack(">H", data[i + 2:i + 4])
        if marker in _JPEG_SOF:
            if i + 9 > len(data):
                return None
            height, width = struct.unpack(">HH", data[i + 5:i + 9])
            return width, height
        i += 2 + length
    return None


def image_size(data: bytes, what: str) -> tuple[int, int]:
    """(width, height) from a PNG or JPEG header; DataError naming ``what`` otherwise.

    Example: the 33 first bytes of a 640x480 PNG -> (640, 480).
    """
    kind = image_format(data)
    if kind is None:
        raise DataError(f"{what}: not a PNG or JPEG image")
    size = _png_size(data) if kind == "png" else _jpeg_size(data)
    if size is None:
        raise DataError(f"{what}: cannot read the image size from its {kind.upper()} header (corrupt or truncated)")
    return size


def check_image_size(size: tuple[int, int], what: str) -> None:
    """ImageTooLarge past the limits, DataError for an empty image."""
    width, height = size
    if width < 1 or height < 1:
        raise DataError(f"{what}: the header says {width}x{height} pixels: an empty image")
    if max(width, height) > MAX_IMAGE_SIDE or width * height > MAX_IMAGE_PIXELS:
        raise ImageTooLarge(f"{what}: {width}x{height} pixels is over the limit of {MAX_IMAGE_SIDE} pixels a side "
                            f"and {MAX_IMAGE_PIXELS / 1e6:.1f} Mpx an image")


def decode_image(data: bytes, what: str) -> np.ndarray:
    """Encoded PNG/JPEG bytes -> the image as cv2 decodes it unchanged ((H, W) or (H, W, C),
    BGR order, 8 or 16 bits), after the header's size passed :func:`check_image_size`."""
    if not data:
        raise DataError(f"{what}: the image is empty")
    check_image_size(image_size(data, what), what)
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DataError(f"{what}: cannot decode the image (corrupt or truncated)")
    return image


def read_image_bytes(path: Path, what: str) -> bytes:
    """The bytes of an image file (at most MAX_IMAGE_FILE_BYTES); DataError when missing."""
    try:
        with open(path, "rb") as file:
            data = file.read(MAX_IMAGE_FILE_BYTES + 1)
    except FileNotFoundError:
        raise DataError(f"missing file: {what}") from None
    except IsADirectoryError:
        raise DataError(f"not a file: {what}") from None
    if len(data) > MAX_IMAGE_FILE_BYTES:
        raise ImageTooLarge(f"{what}: the file is larger than {MAX_IMAGE_FILE_BYTES // (1024 * 1024)} MiB")
    return data


def header_of(path: Path, what: str, head_bytes: int = 1 << 16) -> tuple[int, int]:
    """(width, height) of an image file from its first ``head_bytes`` (a JPEG's EXIF block
    can push its frame header that far), without decoding it."""
    try:
        with open(path, "rb") as file:
            head = file.read(head_bytes)
    except FileNotFoundError:
        raise DataError(f"missing file: {what}") from None
    except IsADirectoryError:
        raise DataError(f"not a file: {what}") from None
    return image_size(head, what)
