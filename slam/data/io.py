"""Image loading and the lazy, file-backed sequence that every folder format shares.

A format reader (``tum.py``, ``replica.py``, ...) only finds files on disk and describes them
as a :class:`SequenceLayout`: one :class:`FrameFiles` per frame, the camera
(:class:`Intrinsics`) and the depth encoding. :class:`FileSequence` then does the rest the same
way for every format: frame selection (stride, max_frames), lazy decoding, invalid-depth
masking, lens undistortion and resizing.

Order of operations per frame: decode -> (ScanNet) colour resized to the depth size -> size
checks -> undistortion at the native resolution -> resize to the requested width.
"""

from __future__ import annotations

import math
import re
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Iterator, Sequence

import cv2
import numpy as np

from slam.data.frame import DataError, Frame
from slam.data.images import decode_image, read_image_bytes
from slam.data.registration import ColorCamera, register_color

if TYPE_CHECKING:
    from slam.data.selfcalibration import ColorWarp


# --------------------------------------------------------------------------------------------
# Camera


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics with optional OpenCV lens distortion.

    Attributes:
        fx, fy, cx, cy: pixels, OpenCV convention (pixel centres at integer coordinates).
        distortion: () or (k1, k2, p1, p2, k3), OpenCV's order.
        image_size: (width, height) these values were calibrated for, or None when unknown;
            frames of another size are rejected instead of silently using a wrong camera.
        source: where the values came from, for error messages.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()
    image_size: tuple[int, int] | None = None
    source: str = "defaults"

    @staticmethod
    def from_values(values: Sequence[float], source: str) -> "Intrinsics":
        """``(fx, fy, cx, cy)`` or ``(fx, fy, cx, cy, k1, k2, p1, p2, k3)`` -> Intrinsics."""
        try:
            numbers = [float(v) for v in values]
        except (TypeError, ValueError) as err:
            raise DataError(f"{source}: intrinsics must be numbers, got {values!r}") from err
        if len(numbers) not in (4, 9):
            raise DataError(
                f"{source}: expected 4 values (fx fy cx cy) or 9 (fx fy cx cy k1 k2 p1 p2 k3), "
                f"got {len(numbers)}"
            )
        if not all(math.isfinite(v) for v in numbers) or numbers[0] <= 0 or numbers[1] <= 0:
            raise DataError(f"{source}: intrinsics must be finite with fx, fy > 0, got {numbers}")
        distortion = tuple(numbers[4:])
        if not any(distortion):
            distortion = ()
        return Intrinsics(*numbers[:4], distortion=distortion, source=source)

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) float64 K."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )


def read_text(path: Path) -> str:
    """A text file's contents; DataError naming the file when it is missing or not text."""
    try:
        return Path(path).read_text()
    except FileNotFoundError as err:
        raise DataError(f"missing file: {path}") from err
    except UnicodeDecodeError as err:
        raise DataError(f"not a text file: {path}") from err


def read_intrinsics_txt(path: Path) -> Intrinsics:
    """Read ``fx fy cx cy [k1 k2 p1 p2 k3]`` (any whitespace, ``#`` comments) from a text file."""
    values: list[str] = []
    for line in read_text(path).splitlines():
        values += line.split("#", 1)[0].replace(",", " ").split()
    return Intrinsics.from_values(values, source=str(path))


def scale_intrinsics_matrix(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """(3, 3) K of an image -> K of the same image resized by (sx, sy).

    The principal point maps as ``(c + 0.5) * s - 0.5`` because pixel centres, not pixel
    corners, sit at integer coordinates (and cv2.resize aligns pixel areas, not centres).
    """
    out = K.astype(np.float64).copy()
    out[0, 0] *= sx
    out[1, 1] *= sy
    out[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    out[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return out


# --------------------------------------------------------------------------------------------
# Paths: every file a dataset names stays inside its folder


def confined(path: Path, root: Path, what: str | None = None) -> Path:
    """``path`` when it lies inside ``root`` once symlinks are followed; DataError otherwise.

    A dataset (an uploaded zip above all) must not make the reader open the server's files, so
    list entries and links that lead out of the folder are refused before anything is opened,
    and the message names the path as the dataset wrote it, not where it leads.
    """
    resolved, base = Path(path).resolve(), Path(root).resolve()
    if resolved != base and base not in resolved.parents:
        shown = what or str(path)
        raise DataError(f"{shown}: leads outside the dataset folder (every file a dataset names must lie inside it)")
    return Path(path)


def dataset_entry(root: Path, name: str, where: str) -> Path:
    """The file a dataset's list names (``rgb/1.png`` in TUM's ``rgb.txt``), as a path under
    ``root``. Absolute paths, drive letters and ``..`` are refused from the text alone (so an
    error never depends on what exists on the machine), then links by :func:`confined`."""
    text = name.replace("\\", "/")
    if not text or text.startswith("/") or re.match(r"^[A-Za-z]:", text) or ".." in text.split("/"):
        raise DataError(f"{where}: {name!r} is not a path inside the dataset folder "
                        f"(absolute paths and '..' are not allowed)")
    return confined(Path(root) / text, root, f"{where}: {name!r}")


# --------------------------------------------------------------------------------------------
# Images


def _imread(path: Path) -> np.ndarray:
    """Decode an image file, its size checked from the header first (``slam.data.images``)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"missing file: {path}")
    return decode_image(read_image_bytes(path, str(path)), str(path))


def read_color(path: Path) -> np.ndarray:
    """Decode a colour image -> (H, W, 3) float32 RGB in [0, 1] (grey and alpha handled)."""
    image = _imread(path)
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    elif image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    elif image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    else:
        raise DataError(f"colour image must have 1, 3 or 4 channels, got {image.shape[2]}: {path}")
    if image.dtype == np.uint8:
        return image.astype(np.float32) / 255.0
    if image.dtype == np.uint16:
        return image.astype(np.float32) / 65535.0
    raise DataError(f"colour image must be 8- or 16-bit, got {image.dtype}: {path}")


def sanitize_depth(depth: np.ndarray) -> np.ndarray:
    """(H, W) float depth in metres -> float32 copy with NaN, inf and negatives set to 0."""
    out = np.asarray(depth, dtype=np.float32).copy()
    out[~np.isfinite(out) | (out < 0)] = 0.0
    return out


def read_depth(path: Path, depth_scale: float, invalid_raw: Sequence[int] = ()) -> np.ndarray:
    """Decode a 16-bit depth PNG -> (H, W) float32 metres, 0 = invalid.

    Args:
        depth_scale: raw units per metre (TUM 5000, Replica 6553.5, ScanNet/7-Scenes 1000).
        invalid_raw: raw values besides 0 that mean "no measurement" (7-Scenes: 65535).
    """
    raw = _imread(path)
    if raw.dtype != np.uint16 or raw.ndim != 2:
        channels = 1 if raw.ndim == 2 else raw.shape[2]
        raise DataError(
            f"depth must be a 16-bit PNG (one uint16 channel), got {raw.dtype} with "
            f"{channels} channel(s): {path}"
        )
    invalid = raw == 0
    for value in invalid_raw:
        invalid |= raw == value
    depth = raw.astype(np.float32) / np.float32(depth_scale)
    depth[invalid] = 0.0
    return sanitize_depth(depth)


def resize_color(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, 3) float32 -> (height, width, 3): area-average when shrinking, bilinear else."""
    if rgb.shape[1] == width and rgb.shape[0] == height:
        return rgb
    shrink = width < rgb.shape[1] or height < rgb.shape[0]
    interpolation = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    return cv2.resize(rgb, (width, height), interpolation=interpolation)


def resize_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) float32 -> (height, width) by nearest neighbour.

    Never averages: a mean across a depth edge invents surfaces floating between objects.
    INTER_NEAREST_EXACT samples the source pixel under each target pixel's centre (plain
    INTER_NEAREST is shifted by half a pixel).
    """
    if depth.shape[1] == width and depth.shape[0] == height:
        return depth
    return cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST_EXACT)


def resize_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) bool -> (height, width) bool, as colour is resized (area mean when shrinking):
    a pixel is True when all of what it averages was."""
    if mask.shape[1] == width and mask.shape[0] == height:
        return mask
    return resize_color(mask.astype(np.float32), width, height) >= 1.0 - 1e-6


def resize_rgbd(
    rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, width: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Resize (H, W, 3) rgb and (H, W) depth to ``width`` keeping the aspect ratio.

    Returns (h, width, 3) rgb, (h, width) depth and the matching (3, 3) K, with
    ``h = round(H * width / W)``.
    """
    H, W = depth.shape
    height = max(1, int(round(H * width / W)))
    K_out = scale_intrinsics_matrix(K, width / W, height / H)
    return resize_color(rgb, width, height), resize_depth(depth, width, height), K_out


def resize_frame(frame: Frame, width: int | None) -> Frame:
    """``frame`` shrunk to ``width`` (``resize_rgbd``, its ``color_valid`` with it); the frame
    itself when ``width`` is None or not smaller."""
    if width is None or width >= frame.width:
        return frame
    rgb, depth, K = resize_rgbd(frame.rgb, frame.depth, frame.K, width)
    seen = None if frame.color_valid is None else resize_mask(frame.color_valid, depth.shape[1], depth.shape[0])
    return replace(frame, rgb=rgb, depth=depth, K=K, color_valid=seen)


@dataclass(frozen=True)
class UndistortMaps:
    """Pixel look-up maps from an undistorted pinhole image (same K) into the raw image."""

    map_x: np.ndarray  # (H, W) float32
    map_y: np.ndarray  # (H, W) float32

    @staticmethod
    def build(K: np.ndarray, distortion: Sequence[float], width: int, height: int) -> "UndistortMaps":
        """(3, 3) K, OpenCV distortion -> maps for a (height, width) image; K is kept."""
        map_x, map_y = cv2.initUndistortRectifyMap(
            K, np.asarray(distortion, dtype=np.float64), None, K, (width, height), cv2.CV_32FC1
        )
        return UndistortMaps(map_x, map_y)

    def observed(self) -> np.ndarray:
        """(H, W) bool: the pixels whose source lies inside the raw image, a pixel in from its
        edge (bilinear sampling mixes the black border into the outermost one)."""
        height, width = self.map_x.shape
        return (self.map_x >= 1) & (self.map_x <= width - 2) & (self.map_y >= 1) & (self.map_y <= height - 2)

    def apply(self, rgb: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistort (H, W, 3) rgb bilinearly and (H, W) depth by nearest neighbour.

        Depth is never interpolated, so no pixel mixes a foreground and a background depth.
        Pixels whose source falls outside the raw image become black / invalid (0).
        """
        border = dict(borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        rgb_out = cv2.remap(rgb, self.map_x, self.map_y, cv2.INTER_LINEAR, **border)
        return rgb_out, self.apply_depth(depth)

    def apply_depth(self, depth: np.ndarray) -> np.ndarray:
        """Undistort (H, W) depth alone, by nearest neighbour (``apply``)."""
        return cv2.remap(depth, self.map_x, self.map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=0)


# --------------------------------------------------------------------------------------------
# Poses


def valid_pose_or_none(T: np.ndarray) -> np.ndarray | None:
    """(4, 4) pose -> float64 copy, or None when it holds inf/NaN (ScanNet marks lost poses so)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return None
    return T.copy()


def read_matrix_file(path: Path) -> np.ndarray:
    """Read a text file of 16 numbers (a row-major 4x4 matrix) -> (4, 4) float64."""
    try:
        numbers = [float(v) for v in read_text(path).split()]
    except ValueError as err:
        raise DataError(f"not a 4x4 matrix of numbers: {path} ({err})") from err
    if len(numbers) != 16:
        raise DataError(f"expected 16 numbers (a 4x4 matrix), got {len(numbers)}: {path}")
    return np.array(numbers, dtype=np.float64).reshape(4, 4)


def numbered_files(folder: Path, pattern: str) -> list[tuple[int, Path]]:
    """Files in ``folder`` whose name fully matches ``pattern`` (one group: the frame number),
    as (number, path) sorted by number (so ``10.jpg`` comes after ``9.jpg``)."""
    regex = re.compile(pattern)
    found = []
    for path in Path(folder).iterdir():
        match = regex.fullmatch(path.name)
        if match and path.is_file():
            found.append((int(match.group(1)), path))
    return sorted(found)


def resolve_depth_scale(depth_scale: float | None, default: float) -> float:
    """The user's depth scale when given (validated), else the format's default."""
    if depth_scale is None:
        return default
    return check_depth_scale(depth_scale, "depth_scale argument")


# --------------------------------------------------------------------------------------------
# The shared sequence


@dataclass(frozen=True)
class FrameFiles:
    """Where one frame lives on disk, its time and its ground-truth pose (or None)."""

    rgb: Path
    depth: Path
    timestamp: float
    T_world_cam: np.ndarray | None = None


@dataclass(frozen=True)
class SequenceLayout:
    """What a format reader found: frames in order, camera and depth encoding."""

    name: str
    root: Path
    frames: tuple[FrameFiles, ...]
    intrinsics: Intrinsics
    depth_scale: float
    """Raw depth units per metre."""
    invalid_depth_raw: tuple[int, ...] = ()
    """Raw depth values besides 0 that mean "no measurement"."""
    color_to_depth_size: bool = False
    """Resize colour to the depth image's size (ScanNet's colour camera has more pixels)."""


def check_depth_scale(depth_scale: float, source: str) -> float:
    """Return ``depth_scale`` as float, or raise DataError naming ``source`` if not > 0."""
    try:
        value = float(depth_scale)
    except (TypeError, ValueError) as err:
        raise DataError(f"{source}: depth_scale must be a number, got {depth_scale!r}") from err
    if not math.isfinite(value) or value <= 0:
        raise DataError(f"{source}: depth_scale must be a positive number, got {depth_scale!r}")
    return value


def select_frames(frames: Sequence[FrameFiles], stride: int, max_frames: int | None) -> tuple[FrameFiles, ...]:
    """Every ``stride``-th frame, then the first ``max_frames`` of those."""
    if not isinstance(stride, int) or stride < 1:
        raise DataError(f"stride must be an integer >= 1, got {stride!r}")
    if max_frames is not None and (not isinstance(max_frames, int) or max_frames < 1):
        raise DataError(f"max_frames must be an integer >= 1 or None, got {max_frames!r}")
    chosen = tuple(frames[::stride])
    return chosen if max_frames is None else chosen[:max_frames]


@dataclass(frozen=True)
class SkippedFrame:
    """A frame left out of an iteration: its index and why (and its agent in a stream
    whose frames name theirs)."""

    index: int
    reason: str
    agent: int | None = None


@dataclass(repr=False)
class FileSequence:
    """An :class:`~slam.data.frame.RGBDSequence` over files; decodes a frame only when asked.

    Frame ``i`` of this sequence is ``layout.frames[::stride][:max_frames][i]``; its
    ``Frame.index`` is ``i``. With ``width`` set, colour and depth are resized to that width
    (aspect ratio kept) and K scaled to match.
    """

    layout: SequenceLayout
    width: int | None = None
    stride: int = 1
    max_frames: int | None = None
    color_camera: ColorCamera | None = None
    """The colour camera when colour and depth come from two cameras: each frame's colour is
    registered onto the depth camera at input (``slam.data.registration``)."""
    color_warp: "ColorWarp | None" = None
    """The colour camera found from the data (``calibrate_colour``); its warp is applied to
    every frame when it was confident (``ColorWarp.applied``)."""
    frames: tuple[FrameFiles, ...] = field(init=False)
    skipped: list["SkippedFrame"] = field(init=False, default_factory=list)
    """Frames the last iteration skipped because they could not be read."""
    _undistort: dict[tuple[int, int], UndistortMaps] = field(init=False, default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.width is not None and (not isinstance(self.width, int) or self.width < 1):
            raise DataError(f"width must be a positive integer or None, got {self.width!r}")
        self.frames = select_frames(self.layout.frames, self.stride, self.max_frames)
        if not self.frames:
            raise DataError(f"no frames found in {self.layout.root}")
        # Fail before any work starts rather than at frame 500; never open a file outside the folder.
        for files in self.frames:
            for path in (files.rgb, files.depth):
                confined(path, self.layout.root, self._relative(path))
                if not path.is_file():
                    raise DataError(f"missing file: {path}")
        if self.color_camera is not None:
            # A wrong calibration would fail every frame: refused before the run starts.
            self._check_color_size(read_color(self.frames[0].rgb), self.frames[0].rgb)

    def _check_color_size(self, rgb: np.ndarray, path: Path) -> None:
        """DataError when colour image ``rgb`` (read from ``path``) is not of the size the
        colour camera's intrinsics are for."""
        camera = self.color_camera
        if rgb.shape[:2] != (camera.height, camera.width):
            raise DataError(f"{path} is {rgb.shape[1]}x{rgb.shape[0]} but the colour camera's intrinsics "
                            f"are for {camera.width}x{camera.height}")

    def _relative(self, path: Path) -> str:
        """``path`` as the dataset names it (relative to its folder), for messages."""
        try:
            return str(Path(path).relative_to(self.layout.root))
        except ValueError:
            return Path(path).name

    def __repr__(self) -> str:
        return (
            f"FileSequence(name={self.name!r}, frames={len(self)}, root={str(self.layout.root)!r}, "
            f"width={self.width}, stride={self.stride}, max_frames={self.max_frames})"
        )

    @property
    def name(self) -> str:
        return self.layout.name

    @property
    def has_gt(self) -> bool:
        return any(files.T_world_cam is not None for files in self.frames)

    @property
    def timestamps(self) -> list[float]:
        """Timestamps of the selected frames, without decoding any image."""
        return [files.timestamp for files in self.frames]

    @property
    def gt_poses(self) -> list[np.ndarray | None]:
        """(4, 4) ground-truth camera-to-world pose (or None) per selected frame."""
        return [files.T_world_cam for files in self.frames]

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[Frame]:
        """Every frame in order; a frame that cannot be read (corrupt, over the size limit,
        sizes that disagree) is skipped and recorded in ``skipped``, as a stream skips a bad
        frame, instead of ending the run at frame 500. ``self[i]`` raises instead."""
        self.skipped = []
        for i in range(len(self)):
            try:
                frame = self[i]
            except DataError as error:
                self.skipped.append(SkippedFrame(index=i, reason=str(error)))
                print(f"skipping frame {i} of {self.name}: {error}", file=sys.stderr, flush=True)
                continue
            yield frame

    def __getitem__(self, i: int) -> Frame:
        if not isinstance(i, (int, np.integer)):
            raise TypeError(f"frame index must be an integer, got {type(i).__name__}")
        n = len(self.frames)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for {n} frames of {self.name}")
        index = int(i) % n
        files = self.frames[index]
        rgb, depth = self._decode(files)
        K = self.layout.intrinsics.matrix
        color_valid = None
        if self.layout.intrinsics.distortion:
            maps = self._undistort_maps(K, depth.shape)
            rgb, depth = (rgb, maps.apply_depth(depth)) if self.color_camera is not None else maps.apply(rgb, depth)
            color_valid = maps.observed()
        if self.color_camera is not None:
            rgb, seen = register_color(rgb, depth, K, self.color_camera)
            color_valid = seen if color_valid is None else color_valid & seen
        if self.width is not None and self.width != depth.shape[1]:
            rgb, depth, K = resize_rgbd(rgb, depth, K, self.width)
            if color_valid is not None:
                color_valid = resize_mask(color_valid, depth.shape[1], depth.shape[0])
        if self.color_warp is not None and self.color_warp.applied:
            rgb, seen = self.color_warp.apply(rgb)
            color_valid = seen if color_valid is None else color_valid & seen
        pose = None if files.T_world_cam is None else files.T_world_cam.copy()
        return Frame(index=index, timestamp=files.timestamp, rgb=rgb, depth=depth, K=K, T_world_cam=pose,
                     color_valid=color_valid)

    def calibrate_colour(self) -> "ColorWarp | None":
        """Estimate how the colour image lies on the depth image from ``CALIBRATION_FRAMES``
        frames spread over the sequence (``slam.data.selfcalibration``) and keep it in
        ``color_warp`` (applied to every frame from now on when confident). None when the
        colour camera was given (``color_camera``): nothing to find."""
        from slam.data.selfcalibration import CALIBRATION_FRAMES, estimate_color_warp

        if self.color_camera is not None:
            return None
        self.color_warp = None
        picks = np.unique(np.linspace(0, len(self) - 1, min(CALIBRATION_FRAMES, len(self))).round().astype(int))
        sample = []
        for i in picks:
            try:
                sample.append(self[int(i)])
            except DataError:
                continue  # a frame the run will skip and report
        self.color_warp = estimate_color_warp(sample)
        return self.color_warp

    def _decode(self, files: FrameFiles) -> tuple[np.ndarray, np.ndarray]:
        """Read one frame's images and check their sizes -> (H, W, 3) rgb, (H, W) depth."""
        rgb = read_color(files.rgb)
        depth = read_depth(files.depth, self.layout.depth_scale, self.layout.invalid_depth_raw)
        if self.color_camera is not None:
            self._check_color_size(rgb, files.rgb)
        elif self.layout.color_to_depth_size:
            rgb = resize_color(rgb, depth.shape[1], depth.shape[0])
        if self.color_camera is None and rgb.shape[:2] != depth.shape:
            raise DataError(
                f"rgb and depth sizes differ: {files.rgb} is {rgb.shape[1]}x{rgb.shape[0]}, "
                f"{files.depth} is {depth.shape[1]}x{depth.shape[0]}"
            )
        expected = self.layout.intrinsics.image_size
        if expected is not None and expected != (depth.shape[1], depth.shape[0]):
            raise DataError(
                f"{files.depth} is {depth.shape[1]}x{depth.shape[0]} but the intrinsics from "
                f"{self.layout.intrinsics.source} are for {expected[0]}x{expected[1]}; "
                "give intrinsics for this image size"
            )
        return rgb, depth

    def _undistort_maps(self, K: np.ndarray, shape: tuple[int, int]) -> UndistortMaps:
        # Built once per image size (i.e. once per sequence): the maps cost ~20 ms each.
        key = (shape[1], shape[0])
        if key not in self._undistort:
            self._undistort[key] = UndistortMaps.build(K, self.layout.intrinsics.distortion, *key)
        return self._undistort[key]
