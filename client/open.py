"""``open_source``: a source name from the command line -> the frame source that reads it.

It sits above the sources (``client.camera_sources``: folder, RealSense; ``client.record3d``),
so that they never import each other in a circle.
"""

from __future__ import annotations

from pathlib import Path

from client.camera_sources import FolderSource, FrameSource, RealSenseOptions, RealSenseSource, SourceError
from client.record3d import R3DSource, Record3DLiveSource, Record3DOptions

NOT_YET = {
    "oak": "Luxonis OAK-D (depthai)",
    "k4a": "Azure Kinect (pyk4a)",
    "orbbec": "Orbbec (pyorbbecsdk)",
}
CAMERAS = ("record3d", "realsense")
RECORDINGS = (".r3d", ".bag", ".db3")
"""Files a device library reads; any other source is a dataset folder or a synthetic scene."""


def open_source(spec: str, *, fps: float | None = None, max_frames: int | None = None, width: int | None = None,
                serial: str | None = None, all_frames: bool = False, min_confidence: int = 1,
                color_camera=None) -> FrameSource:
    """``realsense``, a ``.bag`` file, ``record3d``, a ``.r3d`` file, or a dataset folder /
    ``synthetic:SPEC`` -> a source. ``color_camera`` (``slam.data.registration.ColorCamera``):
    a folder whose colour comes from its own camera; its frames are registered onto the depth
    camera as ``voxfusion run`` registers them, before they are sent.

    Raises SourceError with one line for the user (missing library, bad folder, no camera).
    """
    if color_camera is not None and (spec in NOT_YET or spec in CAMERAS or spec.endswith(RECORDINGS)
                                     or spec.startswith("synthetic:")):
        raise SourceError(f"{spec}: a colour camera of its own is for dataset folders (RealSense and Record3D "
                          f"register colour themselves; a synthetic scene's colour is registered)")
    if spec in NOT_YET:
        raise SourceError(f"{NOT_YET[spec]} is not supported yet; record to a dataset folder "
                          f"(TUM layout) and stream that, or use a RealSense or Record3D")
    if spec == "record3d" or spec.endswith(".r3d"):
        options = Record3DOptions(width=width, min_confidence=min_confidence)
        if spec == "record3d":
            return Record3DLiveSource(udid=serial, max_frames=max_frames, options=options)
        return R3DSource(Path(spec), fps=fps, max_frames=max_frames, options=options)
    if spec == "realsense":
        return RealSenseSource(options=RealSenseOptions(serial=serial), max_frames=max_frames)
    if spec.endswith((".bag", ".db3")):
        return RealSenseSource(bag=Path(spec), options=RealSenseOptions(real_time=not all_frames),
                               max_frames=max_frames)
    return FolderSource(spec, fps=fps, max_frames=max_frames, width=width, color_camera=color_camera)
