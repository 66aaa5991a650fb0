"""A session's input frames read back for the API (AR ``frame:N`` backgrounds).

:func:`input_frame` runs in the decode helper (``server.decoding``), not in the API process:
the frames are untrusted images (an upload's, a stream's) or a synthetic render of a size
the request chose. Frames larger than :data:`MAX_BACKGROUND_SIDE` a side are refused, as
render requests are, so what comes back to the API process stays small.
"""

from __future__ import annotations

from pathlib import Path

from slam import DataError

MAX_BACKGROUND_SIDE = 2048
"""Largest side of an input frame used as an AR background (as ``server.schemas.MAX_SIDE``)."""


def input_frame(sources: tuple, session_dir: Path, index: int, agent: int = 0):
    """(rgb, depth, K, timestamp) of ``agent``'s ``index``-th input frame (the agent's source,
    or its frames in a stream). KeyError if absent, DataError if unreadable or too large."""
    if sources[0].kind == "stream":
        from server.stream import read_recorded_frame
        from server.upload import UploadError

        try:
            frame = read_recorded_frame(Path(session_dir) / "input", index, agent)
        except UploadError as error:  # a recorded file that no longer decodes
            raise DataError(str(error)) from None
        rgb, depth, K, stamp = frame.rgb, frame.depth, frame.K, frame.timestamp
    else:
        rgb, depth, K, stamp = _sequence_frame(sources, index, agent)
    height, width = depth.shape
    if max(height, width) > MAX_BACKGROUND_SIDE:
        raise DataError(f"frame {index} is {width}x{height}: an AR background has at most "
                        f"{MAX_BACKGROUND_SIDE} pixels a side")
    return rgb, depth, K, stamp


def _sequence_frame(sources: tuple, index: int, agent: int):
    if agent >= len(sources):
        raise KeyError(f"agent {agent} does not exist (the session has {len(sources)} source"
                       f"{'s' if len(sources) > 1 else ''})")
    from server.worker import open_source

    sequence = open_source(sources[agent])  # as the worker opened it
    if not 0 <= index < len(sequence):
        raise KeyError(f"frame {index} does not exist (the input has {len(sequence)} frames)")
    frame = sequence[index]
    return frame.rgb, frame.depth, frame.K, frame.timestamp
