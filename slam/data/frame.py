"""The one frame type every reader yields, and the dataset protocol."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Protocol, runtime_checkable

import numpy as np


class DataError(ValueError):
    """Input data is missing, corrupt or inconsistent. The message names the file."""


@dataclass(frozen=True)
class Frame:
    """One RGB-D frame.

    Attributes:
        index: position in the (strided) sequence, 0-based.
        timestamp: seconds (TUM) or the frame number as float where the format has no time.
        rgb: (H, W, 3) float32 in [0, 1].
        depth: (H, W) float32 metres, 0 = invalid.
        K: (3, 3) float64 pinhole intrinsics of rgb and depth (already undistorted/resized).
        T_world_cam: (4, 4) float64 camera-to-world ground truth, OpenCV axes, or None.
        color_valid: (H, W) bool, the pixels whose colour the camera observed, or None: all of
            them. Undistortion leaves black the pixels whose source lies outside the raw image
            (6-7 % of a TUM fr1 frame); they are no observation, though their depth is 0 too.
    """

    index: int
    timestamp: float
    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    T_world_cam: np.ndarray | None = None
    color_valid: np.ndarray | None = None

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])


@runtime_checkable
class RGBDSequence(Protocol):
    """What every reader returns: indexable, sized, iterable frames plus metadata."""

    name: str
    """Human-readable name (folder name, synthetic kind)."""

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> Frame: ...

    def __iter__(self) -> Iterator[Frame]: ...

    @property
    def has_gt(self) -> bool: ...
