"""Untrusted input at the edge: dataset zips and streamed RGB-D frames.

Everything here is checked before any work starts, and every failure is an
:class:`UploadError` carrying the HTTP status and a message that says what is wrong:

* zips: no absolute paths, no ``..``, no links or devices, at most ``max_entries`` entries and
  ``max_unzipped_bytes`` uncompressed in total (checked from the directory, then enforced again
  while writing, so a lying header cannot fill the disk); no entry that the disk cannot hold
  (a name part over 255 bytes, a path over 1024 bytes or 32 folders deep, a file that another
  entry needs as a folder); extraction writes only regular files under the destination, with
  names rebuilt from validated parts. A write the disk refuses anyway is a 422 naming the
  entry, or 507 when the disk is full.
* frames: the colour image decodes, the depth is a single-channel 16-bit PNG of the same size,
  intrinsics are four positive numbers.
"""

from __future__ import annotations

import errno
import shutil
import stat
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import cv2
import numpy as np

from server.budget import DEPTH_SCALE_RANGE, FOCAL_RANGE, PRINCIPAL_POINT_LIMIT
from slam import DataError
from slam.data.images import MAX_IMAGE_SIDE, PNG_SIGNATURE, ImageTooLarge, decode_image, image_format

# Entries that archivers add and that are never part of a dataset.
_IGNORED_TOP_LEVEL = {"__MACOSX", ".DS_Store", "Thumbs.db"}
MAX_FRAME_SIDE = MAX_IMAGE_SIDE
"""Largest image side anywhere; bigger headers are refused before decoding (decompression bombs)."""
MAX_AGENTS = 16
"""Most agents (cameras) in one collaborative session: file parts of an upload, or stream agent ids."""


class UploadError(ValueError):
    """Bad upload; ``status`` is the HTTP status to answer with (400, 413, 422, or 507 when
    the server's disk is full)."""

    def __init__(self, message: str, status: int = 422) -> None:
        super().__init__(message)
        self.status = status


DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
"""What a write gets from a full disk (or a full quota)."""


def is_disk_full(error: BaseException) -> bool:
    return isinstance(error, OSError) and error.errno in DISK_FULL_ERRNOS


def disk_full_error(what: str) -> UploadError:
    """507: the server had no room for ``what`` (the request may be sent again once it has)."""
    return UploadError(f"the server's disk is full: no room to store {what}; nothing was kept, "
                       "try again once space is freed", status=507)


# ---------------------------------------------------------------------------------------------
# zips


@dataclass(frozen=True)
class ZipLimits:
    max_entries: int
    max_unzipped_bytes: int


MAX_ENTRY_PART_BYTES = 255
"""Longest file or folder name in an entry (UTF-8): NAME_MAX of every common file system."""
MAX_ENTRY_PATH_BYTES = 1024
"""Longest entry path (UTF-8), well inside PATH_MAX (4096) once the session folder is in front."""
MAX_ENTRY_DEPTH = 32
"""Most folders an entry lies in (a dataset needs three or four)."""


def shown_entry(name: str, limit: int = 80) -> str:
    """An entry name for an error message, its middle cut out when it is long."""
    return name if len(name) <= limit else f"{name[:limit - 25]}...{name[-20:]}"


def _check_entry_size(name: str, path: PurePosixPath) -> None:
    """UploadError (422) for an entry whose name no file system here can hold."""
    where = f"zip entry {shown_entry(name)!r}"
    longest = max(path.parts, key=lambda part: len(part.encode()))
    if len(longest.encode()) > MAX_ENTRY_PART_BYTES:
        raise UploadError(f"{where}: the name {shown_entry(longest, 40)!r} is {len(longest.encode())} bytes "
                          f"long; at most {MAX_ENTRY_PART_BYTES} are allowed")
    if len(path.parts) - 1 > MAX_ENTRY_DEPTH:
        raise UploadError(f"{where}: lies {len(path.parts) - 1} folders deep; at most {MAX_ENTRY_DEPTH} are allowed")
    if len(str(path).encode()) > MAX_ENTRY_PATH_BYTES:
        raise UploadError(f"{where}: the path is {len(str(path).encode())} bytes long; at most "
                          f"{MAX_ENTRY_PATH_BYTES} are allowed")


def _check_clashes(files: list[tuple[zipfile.ZipInfo, PurePosixPath]]) -> None:
    """UploadError (422) when one entry is a file that another needs as a folder (``d/x``
    and ``d/x/y``), which no extraction could write."""
    names = {path: info.filename for info, path in files}
    for info, path in files:
        for folder in path.parents:
            if folder in names:
                raise UploadError(f"zip entry {shown_entry(info.filename)!r}: {shown_entry(names[folder])!r} "
                                  f"is a file in the zip, so it cannot also be a folder")


def member_path(name: str) -> PurePosixPath | None:
    """The safe relative path of a zip entry, or None for a directory entry.

    Raises UploadError (422) for absolute paths, drive letters, ``..`` parts and backslashes
    (Windows archivers write them as separators; we refuse rather than guess).
    """
    if "\\" in name:
        raise UploadError(f"zip entry {name!r}: backslashes in entry names are not allowed")
    if name.startswith("/") or (len(name) > 1 and name[1] == ":"):
        raise UploadError(f"zip entry {name!r}: absolute paths are not allowed")
    parts = [p for p in name.split("/") if p not in ("", ".")]
    if any(p == ".." for p in parts):
        raise UploadError(f"zip entry {name!r}: '..' would escape the archive root")
    if any("\x00" in p for p in parts):
        raise UploadError(f"zip entry {name!r}: NUL in entry name")
    if not parts or name.endswith("/"):
        return None
    return PurePosixPath(*parts)


def _is_link_or_special(info: zipfile.ZipInfo) -> bool:
    """True for symlinks, devices, fifos (Unix mode in the high 16 bits of external_attr)."""
    file_type = stat.S_IFMT(info.external_attr >> 16)
    # 0: no Unix type recorded (Windows archivers, Python's writestr): a plain file.
    return file_type not in (0, stat.S_IFREG, stat.S_IFDIR)


def check_zip(zip_path: Path, limits: ZipLimits) -> list[tuple[zipfile.ZipInfo, PurePosixPath]]:
    """Validate every entry of the zip at ``zip_path``; return (entry, safe path) for files.

    Raises UploadError: 400 when it is not a zip, 422 for an unsafe entry, 413 when over a limit.
    """
    try:
        archive = zipfile.ZipFile(zip_path)
    except (zipfile.BadZipFile, OSError) as error:
        raise UploadError(f"the upload is not a valid zip file ({error})", status=400) from None
    with archive:
        infos = archive.infolist()
    if len(infos) > limits.max_entries:
        raise UploadError(f"the zip has {len(infos)} entries; the limit is {limits.max_entries}", status=413)
    files: list[tuple[zipfile.ZipInfo, PurePosixPath]] = []
    total = 0
    for info in infos:
        path = member_path(info.filename)
        if _is_link_or_special(info):
            raise UploadError(f"zip entry {info.filename!r}: links and special files are not allowed")
        if path is None:
            continue
        if info.flag_bits & 0x1:
            raise UploadError(f"zip entry {info.filename!r}: encrypted entries are not supported")
        _check_entry_size(info.filename, path)
        total += info.file_size
        if total > limits.max_unzipped_bytes:
            raise UploadError(
                f"the zip unpacks to more than {limits.max_unzipped_bytes // (1024 * 1024)} MiB "
                f"(the uncompressed-size limit)", status=413)
        files.append((info, path))
    if not files:
        raise UploadError("the zip holds no files")
    _check_clashes(files)
    return files


def extract_zip(zip_path: Path, dest: Path, limits: ZipLimits) -> Path:
    """Check, then extract the zip into ``dest`` (created); returns ``dest``.

    Only regular files are written, at paths rebuilt from validated parts, and the bytes
    actually written are counted against the limit again.
    """
    files = check_zip(zip_path, limits)
    dest.mkdir(parents=True, exist_ok=True)
    root = dest.resolve()
    written = 0
    with zipfile.ZipFile(zip_path) as archive:
        for info, relative in files:
            target = root.joinpath(*relative.parts)
            if root not in target.parents:
                raise UploadError(f"zip entry {info.filename!r} would be written outside the archive root")
            try:
                target.parent.mkdir(parents=True, exist_ok=True)
                with archive.open(info) as source, open(target, "wb") as sink:
                    written += _copy_limited(source, sink, limits.max_unzipped_bytes - written, info.filename)
            except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, NotImplementedError) as error:
                raise UploadError(f"zip entry {info.filename!r} cannot be read ({error})", status=400) from None
            except OSError as error:
                raise _unwritable_entry(info.filename, error) from None
    return dest


def _unwritable_entry(name: str, error: OSError) -> UploadError:
    """A write of entry ``name`` that the disk refused: 507 when it is full, else 422 with the
    reason (never the server's path)."""
    if is_disk_full(error):
        return disk_full_error("the unpacked dataset")
    reason = error.strerror or type(error).__name__
    return UploadError(f"zip entry {shown_entry(name)!r} cannot be unpacked here ({reason})")


def _copy_limited(source, sink, budget: int, name: str, chunk: int = 1 << 20) -> int:
    copied = 0
    while True:
        block = source.read(chunk)
        if not block:
            return copied
        copied += len(block)
        if copied > budget:
            raise UploadError(f"zip entry {name!r} unpacks past the uncompressed-size limit", status=413)
        sink.write(block)


def dataset_root(extracted: Path) -> Path:
    """The folder holding the dataset: ``extracted`` itself, or its single top-level folder
    when the zip was made from a folder (archiver litter such as ``__MACOSX`` is ignored);
    and in NICE-SLAM's Replica layout, ``cam_params.json`` beside one scene folder (at the top
    of the zip or in its single folder), that scene folder (the reader finds
    ``cam_params.json`` in its parent)."""
    root = extracted
    entries = _entries(root)
    if len(entries) == 1 and entries[0].is_dir():
        root = entries[0]
    if (root / "cam_params.json").is_file():
        scenes = [p for p in _entries(root) if p.is_dir()]
        if len(scenes) == 1:
            return scenes[0]
    return root


def _entries(folder: Path) -> list[Path]:
    return [p for p in folder.iterdir() if p.name not in _IGNORED_TOP_LEVEL]


def save_upload(source, target: Path, max_bytes: int) -> int:
    """Copy a file-like upload to ``target``; 413 past ``max_bytes``. Returns the size."""
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        with open(target, "wb") as sink:
            return _copy_limited(source, sink, max_bytes, target.name)
    except UploadError:
        raise UploadError(f"the upload is larger than {max_bytes // (1024 * 1024)} MiB", status=413) from None
    except OSError as error:
        if is_disk_full(error):
            target.unlink(missing_ok=True)
            raise disk_full_error("the upload") from None
        raise


def inspect_dataset(root: str, spec) -> str:
    """Check an extracted dataset before its session is queued; returns its format.

    Opens it as the worker will (``spec``: a ``server.worker.SourceSpec``), reads the header of
    every selected frame's images (a decompression bomb anywhere in the zip is refused now,
    not at frame 500) and decodes the first frame. Meant to run in the decode helper
    (``server.decoding``); raises DataError (ImageTooLarge for a header over the limits).
    """
    from slam import detect_format, open_sequence
    from slam.data.images import check_image_size, header_of

    fmt = detect_format(root) if spec.format == "auto" else spec.format
    sequence = open_sequence(root, fmt, stride=spec.stride, max_frames=spec.max_frames,
                             intrinsics=spec.intrinsics, depth_scale=spec.depth_scale,
                             color_camera=spec.color_camera())
    if len(sequence) == 0:
        raise DataError("the dataset has no frames")
    for files in getattr(sequence, "frames", ()):
        for path in (files.rgb, files.depth):
            what = str(Path(path).relative_to(root)) if Path(path).is_relative_to(root) else Path(path).name
            check_image_size(header_of(path, what), what)
    sequence[0]
    return fmt


def remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)


# ---------------------------------------------------------------------------------------------
# streamed frames


@dataclass(frozen=True)
class StreamFrame:
    """One validated streamed frame, still in its raw units (cheap to pickle to a worker).

    Attributes:
        timestamp: seconds.
        rgb: (H, W, 3) uint8 RGB.
        depth_raw: (H, W) uint16 raw depth units; metres = depth_raw / depth_scale, 0 = invalid.
        depth_scale: raw units per metre.
        K: (3, 3) float64 intrinsics.
        agent: the camera (agent) of a collaborative stream, 0 for a single one.
        T_world_cam: (4, 4) float64 ground-truth pose the client sent for this time, or None.
    """

    timestamp: float
    rgb: np.ndarray
    depth_raw: np.ndarray
    depth_scale: float
    K: np.ndarray
    agent: int = 0
    T_world_cam: np.ndarray | None = None
    color_valid: np.ndarray | None = None
    """(H, W) bool where colour came from another camera and was registered: the pixels it saw."""


def encode_png_rgb(rgb: np.ndarray) -> bytes:
    """(H, W, 3) uint8 RGB -> PNG bytes."""
    ok, data = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise UploadError("could not encode the registered colour image", status=500)
    return data.tobytes()


def parse_agent(value: int | str, what: str = "agent") -> int:
    """An agent id (``0``, ``"1"``, ...) -> int in 0..MAX_AGENTS-1; UploadError (422) otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, str)):
        raise UploadError(f"{what}: expected a whole number >= 0 (the camera of a collaborative stream), "
                          f"got {value!r}")
    if isinstance(value, str):
        text = value.strip()
        if not (text.isascii() and text.isdigit()):
            raise UploadError(f"{what}: expected a whole number >= 0 (the camera of a collaborative stream), "
                              f"got {value!r}")
        value = int(text)
    if not 0 <= value < MAX_AGENTS:
        raise UploadError(f"{what}: must be between 0 and {MAX_AGENTS - 1}, got {value}")
    return value


def parse_color_camera(color_intrinsics: str | None, depth_to_color: str | None
                       ) -> tuple[tuple[float, ...] | None, tuple[float, ...] | None]:
    """The upload's ``color_intrinsics`` ("fx,fy,cx,cy,width,height[,k1,k2,p1,p2[,k3]]") and
    ``depth_to_color`` (16 or 12 numbers, row-major) -> the numbers, checked as the run will
    use them (a wrong camera is refused now, not in the worker)."""
    if color_intrinsics is None:
        if depth_to_color is not None:
            raise UploadError("depth_to_color: needs color_intrinsics (the colour camera's own intrinsics)")
        return None, None
    from slam.data.frame import DataError
    from slam.data.registration import color_camera_from_values

    def numbers(text: str, what: str) -> tuple[float, ...]:
        if len(text) > 400:
            raise UploadError(f"{what}: at most 16 numbers, got {len(text)} characters")
        try:
            return tuple(float(v) for v in text.replace(" ", "").split(","))
        except ValueError:
            raise UploadError(f"{what}: expected comma-separated numbers, got {text[:80]!r}") from None

    intrinsics = numbers(color_intrinsics, "color_intrinsics")
    transform = None if depth_to_color is None else numbers(depth_to_color, "depth_to_color")
    try:
        color_camera_from_values(intrinsics, transform, source="color_intrinsics")
    except DataError as error:
        raise UploadError(str(error)) from None
    return intrinsics, transform


def parse_intrinsics(text: str | list | tuple, what: str = "intrinsics") -> tuple[float, float, float, float]:
    """``"fx,fy,cx,cy"`` (or a list of four numbers) -> four floats; fx, fy > 0."""
    values = text.replace(" ", "").split(",") if isinstance(text, str) else list(text)
    if len(values) != 4:
        raise UploadError(f"{what}: expected 'fx,fy,cx,cy' (four numbers), got {text!r}")
    try:
        fx, fy, cx, cy = (float(v) for v in values)
    except (TypeError, ValueError):
        raise UploadError(f"{what}: expected four numbers 'fx,fy,cx,cy', got {text!r}") from None
    if not all(np.isfinite([fx, fy, cx, cy])) or fx <= 0 or fy <= 0:
        raise UploadError(f"{what}: fx and fy must be positive and all values finite, got {text!r}")
    low, high = FOCAL_RANGE
    if not (low <= fx <= high and low <= fy <= high):
        raise UploadError(f"{what}: focal lengths fx, fy must lie in {low:g}..{high:g} pixels, got {fx:g}, {fy:g}")
    if max(abs(cx), abs(cy)) > PRINCIPAL_POINT_LIMIT:
        raise UploadError(f"{what}: the principal point cx, cy must lie within {PRINCIPAL_POINT_LIMIT:g} pixels "
                          f"of the image corner, got {cx:g}, {cy:g}")
    return fx, fy, cx, cy


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(3, 3) float64 pinhole matrix."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def parse_depth_scale(value: float | str, what: str = "depth_scale") -> float:
    try:
        scale = float(value)
    except (TypeError, ValueError):
        raise UploadError(f"{what}: expected a number (raw depth units per metre), got {value!r}") from None
    if not np.isfinite(scale):
        raise UploadError(f"{what}: must be a finite number (raw depth units per metre), got {value!r}")
    if scale <= 0:
        raise UploadError(f"{what}: must be a positive number (raw depth units per metre), got {value!r}")
    low, high = DEPTH_SCALE_RANGE
    if not low <= scale <= high:
        raise UploadError(f"{what}: must lie in {low:g}..{high:g} raw depth units per metre "
                          f"(1000: millimetres, 5000: TUM), got {scale:g}")
    return scale


def _decode(data: bytes, what: str) -> np.ndarray:
    """Checked header, then decode (``slam.data.images``); errors as UploadError (413 when too large)."""
    try:
        return decode_image(data, what)
    except ImageTooLarge as error:
        raise UploadError(str(error), status=413) from None
    except DataError as error:
        raise UploadError(str(error)) from None


def decode_color(data: bytes, what: str = "color") -> np.ndarray:
    """Encoded PNG/JPEG bytes -> (H, W, 3) uint8 RGB. Grey images are repeated, alpha dropped."""
    image = _decode(data, what)
    if image.dtype != np.uint8:
        raise UploadError(f"{what}: colour must be 8 bits per channel, got {image.dtype}")
    if image.ndim == 2:
        return np.repeat(image[:, :, None], 3, axis=2)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    if image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    raise UploadError(f"{what}: unexpected {image.shape[2]} channels")


def decode_depth(data: bytes, what: str = "depth") -> np.ndarray:
    """16-bit single-channel PNG bytes -> (H, W) uint16 raw depth."""
    if data and image_format(data) != "png":
        raise UploadError(f"{what}: depth must be a 16-bit PNG (the data is not a PNG)")
    image = _decode(data, what)
    if image.ndim != 2:
        raise UploadError(f"{what}: depth must be single-channel, got {image.shape[2]} channels")
    if image.dtype != np.uint16:
        bits = image.dtype.itemsize * 8
        raise UploadError(f"{what}: depth must be a 16-bit PNG, got {bits}-bit")
    return image


def decode_stream_frame(color: bytes, depth: bytes, timestamp: float, depth_scale: float,
                        K: np.ndarray, agent: int = 0, color_camera=None) -> StreamFrame:
    """Decode and cross-check one streamed frame (see :class:`StreamFrame`); with
    ``color_camera`` (``slam.data.registration.ColorCamera``) its colour, of that camera's
    size, is registered onto the depth camera."""
    if not np.isfinite(timestamp):
        raise UploadError(f"timestamp: must be a finite number, got {timestamp!r}")
    rgb = decode_color(color)
    depth_raw = decode_depth(depth)
    if color_camera is not None:
        from slam.data.registration import register_color

        if rgb.shape[:2] != (color_camera.height, color_camera.width):
            raise UploadError(f"color is {rgb.shape[1]}x{rgb.shape[0]} but the session's colour camera is "
                              f"{color_camera.width}x{color_camera.height}")
        depth_m = depth_raw.astype(np.float32) / np.float32(depth_scale)
        registered, seen = register_color(rgb.astype(np.float32) / 255.0, depth_m, K, color_camera)
        rgb = np.round(np.clip(registered, 0.0, 1.0) * 255).astype(np.uint8)
        return StreamFrame(timestamp=float(timestamp), rgb=rgb, depth_raw=depth_raw, depth_scale=depth_scale, K=K,
                           agent=agent, color_valid=seen)
    if rgb.shape[:2] != depth_raw.shape:
        raise UploadError(
            f"color is {rgb.shape[1]}x{rgb.shape[0]} but depth is {depth_raw.shape[1]}x{depth_raw.shape[0]}: "
            f"they must have the same size")
    return StreamFrame(timestamp=float(timestamp), rgb=rgb, depth_raw=depth_raw, depth_scale=depth_scale, K=K,
                       agent=agent)
