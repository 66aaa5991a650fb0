"""The messages between the tracking side (``slam.runtime``) and the mapping side
(``slam.mapping_process``): requests to the mapper and its replies.

Frozen dataclasses of plain values and numpy arrays, so that they pickle by value across the
mapping process's queues; the tracking side dispatches replies by their type. Requests:
``FrameMessage`` (a tracked frame) and ``EndOfInput`` (the last one). Replies: ``Ready``,
``SnapshotReply``, ``MapPosesReply``, ``FramePose``, ``EventReply``, ``FinalMaps``, ``Done``
and ``Failed`` (``Reply`` is their union).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Union

import numpy as np

from .data.frame import Frame

if TYPE_CHECKING:
    from .events import Event
    from .features import FrameFeatures
    from .frames import TensorFrame
    from .mapping import MapSnapshot


# ----------------------------------------------------------------- requests
@dataclass(frozen=True)
class MapStart:
    """A map that a frame starts: why (``start``, ``region`` or ``tracking_failure``, see
    ``slam.events.SubmapEvent``), its id (the tracker numbers maps) and T_world_map (4, 4)."""

    reason: str
    map_id: int
    T_world_map: np.ndarray


@dataclass(frozen=True)
class FrameMessage:
    """A tracked frame at pipeline resolution, as plain arrays (pickles by value).

    The pose is sent in the frame of the map it was tracked against (``map_id``,
    ``T_map_cam`` (4, 4)): a loop may move that map while the message is queued, and the
    mapper places the frame with the map's pose at the time it integrates it.
    """

    agent: int
    frame: Frame
    map_id: int
    T_map_cam: np.ndarray
    tracking_ok: bool
    new_map: MapStart | None = None
    """The map this frame starts."""
    covariance: np.ndarray | None = None
    """(6, 6) the tracker's uncertainty of this frame's pose (``keyframe_graph.frame_covariance``)."""
    optimize: bool = True
    """Run the windowed optimisation after integrating it (deterministic mode integrates some
    frames only, as a free-running mapper optimises once per batch of queued frames)."""
    prepared: "TensorFrame | None" = None
    """``frame`` as the tracker prepared it (``slam.frames.prepare_frame``), for a mapper in
    the same process; None where it was not prepared or crosses to the mapping process."""
    features: "FrameFeatures | None" = None
    """``frame``'s ORB features as the tracker detected them, when the loop closer's
    appearance check would detect the very same ones (``features.same_detection``)."""


@dataclass(frozen=True)
class EndOfInput:
    """No frames follow. ``refine``: the sequence ended, so refine globally before the
    outputs; False: the run was stopped, write the outputs without the refinement."""

    refine: bool = True


Request = Union[FrameMessage, EndOfInput]


# ------------------------------------------------------------------ replies
@dataclass(frozen=True)
class Ready:
    """The mapping process has started and waits for frames."""


@dataclass(frozen=True)
class SnapshotReply:
    """A newer copy of one map for the tracker."""

    snapshot: "MapSnapshot"


@dataclass(frozen=True)
class MapPosesReply:
    """A loop moved maps: map id -> T_world_map (4, 4) float64 of every map."""

    poses: dict[int, np.ndarray]


@dataclass(frozen=True)
class FramePose:
    """A frame's pose as the mapper's window optimised it (``mapping.optimize_current_pose``),
    in the frame of the map it was integrated into: ``map_id``, ``T_map_cam`` (4, 4) float64.
    The tracking side puts it in place of the tracked pose (``slam.runtime``)."""

    agent: int
    frame_index: int
    map_id: int
    T_map_cam: np.ndarray


@dataclass(frozen=True)
class EventReply:
    """An event for the run's listeners (keyframes, loops, map updates, moved poses)."""

    event: "Event"


@dataclass(frozen=True)
class KeyframeRecord:
    """A keyframe's final pose for the outputs: its map and world pose (4, 4) as 16 numbers."""

    agent: int
    frame_index: int
    map_id: int
    T_world_cam: list[float]


@dataclass(frozen=True)
class FinalMaps:
    """The maps as the final bundle adjustment and pose graph left them, sent before the
    mapping side's last outputs (colour fit, checkpoint, mesh) so that the tracking side can
    re-track every frame against them meanwhile (``tracking.retrack_iterations``): a
    snapshot of every map, map id -> T_world_map (4, 4) float64, and the keyframes' poses."""

    snapshots: list["MapSnapshot"]
    map_poses: dict[int, np.ndarray]
    keyframes: list[KeyframeRecord]


@dataclass(frozen=True)
class FinalRefinement:
    """What the final bundle adjustment did: iterations asked and run, seconds, and whether
    its time cap stopped it."""

    iterations_budget: int
    iterations_run: int
    seconds: float
    seconds_budget: float | None
    stopped_by_time: bool


@dataclass(frozen=True)
class MapperStats:
    keyframes: int
    maps: int
    voxels: int
    map_bytes: int
    decoder_bytes: int
    busy_seconds: float
    timings: dict[str, float]
    keyframe_records: list[KeyframeRecord]
    map_poses: dict[int, np.ndarray]
    map_agents: dict[int, int]
    map_groups: dict[int, int]
    map_reasons: dict[int, str]
    loop_closures: list[dict]
    loop_candidates: list[dict]
    """Every verified loop candidate with its scores, accepted or not."""
    loop_candidates_rejected: int
    loop_timings_ms: dict[str, float]
    refinement: FinalRefinement | None = None
    """What the end-of-run global bundle adjustment did (None before it ran)."""
    keyframe_graph: dict | None = None
    """What the end-of-run keyframe pose graph did (``KeyframeGraphResult.summary``; None
    when it did not run: no verified loop, loops off, or a stopped run)."""
    fine_color_bytes: int = 0
    """Bytes of the maps' fine colour levels (``slam.fine_color``; 0 without one)."""


@dataclass(frozen=True)
class Done:
    """The mapping side finished its outputs: the run's mapping statistics (the last reply)."""

    stats: MapperStats


@dataclass(frozen=True)
class Failed:
    """The mapping side raised: its traceback (the last reply)."""

    traceback: str


Reply = Union[Ready, SnapshotReply, MapPosesReply, FramePose, EventReply, FinalMaps, Done, Failed]
