"""RGB-D data readers: every format yields the same :class:`Frame`.

``open_sequence(path, format="auto", *, width, stride, max_frames, intrinsics, depth_scale)``
opens TUM RGB-D, Replica (NICE-SLAM layout), ScanNet and 7-Scenes folders lazily, or a
``synthetic:SPEC`` scene; ``detect_format(path)`` tells the format from a folder's layout.
"""

from slam.data.frame import DataError, Frame, RGBDSequence
from slam.data.io import FileSequence, Intrinsics
from slam.data.open import FORMATS, detect_format, open_sequence

__all__ = [
    "DataError",
    "FORMATS",
    "FileSequence",
    "Frame",
    "Intrinsics",
    "RGBDSequence",
    "detect_format",
    "open_sequence",
]
