"""The SLAM runtime: tracking in the calling process, mapping and loop closing in their own.

The loop (``_process_frame``) reads like the paper's system overview:

    for each frame of each agent:
        track it against the agent's active map (the newest snapshot)
        -> lost, or out of the map's region?  then the frame starts a new map
        -> publish its pose
        -> hand the tracked frame to the mapping side, which selects keyframes, allocates
           voxels, runs the windowed joint optimisation, and for every new keyframe looks
           for loops (appearance check, geometric verification, hierarchical pose
           optimisation), publishing new snapshots and map poses
        -> apply what the mapping side sent back (keyframes, loops, moved maps, snapshots)
    at the end: global bundle adjustment of every map, mesh, trajectories

The two sides talk in the typed messages of ``slam.messages``. A frame is prepared for the
pipeline once on the tracking side; its ORB features go with it to the loop closer when the
closer's detector would find the same ones (``features.tracking_features_serve_loops``).

Several sequences (agents, collaborative mapping) are read round-robin, or as one
``AgentStream``; each agent has its own tracking state and active map, all maps live on the
mapping side (``slam.mapping_process``). The tracker numbers new maps itself, so both
sides agree on ids without a round trip. Poses are kept per frame in the frame of the map
they were tracked against: when a loop moves maps, each frame moves with its map. With
``mapping.optimize_current_pose`` the mapper sends back the pose its window refined, in the
frame of the map it integrated the frame into, and that replaces the tracked one.

Outputs in ``out_dir`` (``slam.outputs``): ``trajectory.txt`` (agent 0; and
``trajectory_<k>.txt`` per agent when there are several), ``mesh.ply``, ``map.pt``, ``run.json``.
While running, the trajectories so far and a ``run.json`` that says ``running`` are rewritten
atomically at every keyframe (before its KeyframeEvent goes out, so whoever counted a keyframe
finds its poses on disk), and again as soon as tracking ends (the input's end, a stop or a
failure), before the final refinement or a stop's checkpoint and mesh. ``map.pt`` is
rewritten atomically every ``runtime.checkpoint_every_keyframes`` keyframes (10) by the mapping
process. A run killed outright (SIGKILL) thus leaves every pose tracked up to its last
keyframe (all of them once tracking has ended) and a map that lacks at most its last 9
keyframes.
"""

from __future__ import annotations

import errno
import sys
import threading
import time
import traceback
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterable, Iterator, Protocol

import numpy as np
import torch

from .config import SLAMConfig
from .data.frame import Frame
from .data.io import resize_frame
from .events import Event, FinishedEvent, KeyframeEvent, LoopEvent, PhaseEvent, PoseEvent, StatsEvent, SubmapEvent
from .features import FeatureOdometry, tracking_features_serve_loops
from .frames import PixelBatch, prepare_frame
from .mapping import MapSnapshot
from .mapping_process import InlineMapper, MapperFailed, ProcessMapper
from .mapping_process import process_threads
from .messages import (Done, EventReply, Failed, FinalMaps, FrameMessage, FramePose, MapPosesReply, MapperStats,
                       MapStart, Reply, SnapshotReply)
from .profiling import StageClock
from .outputs import (PROGRESS_EVERY, FrameRecord, ProgressSample, RunResult, corrected_poses, refine_with_keyframes,
                      retrack_anchors, running_ate, spread_corrections, write_outputs, write_progress)
from .loop.keyframe_graph import frame_covariance
from .tracking import FrozenMap, Tracker

if TYPE_CHECKING:
    from tqdm import tqdm

__all__ = ["AgentStream", "MapperFailed", "RunResult", "refine_with_keyframes", "resolve_device", "run_slam",
           "with_given_poses", "Tracker"]


class StopFlag(Protocol):
    def is_set(self) -> bool: ...


class AgentStream:
    """A source whose frames come from several agents in arrival order (a live stream where
    each frame names its camera). Iterating yields ``(agent, Frame)``; agents are numbered
    from 0 and may appear at any time. Pass it as the only element of ``run_slam``'s
    ``sources``. A list of plain frame iterables is read round-robin instead."""

    def __iter__(self) -> Iterator[tuple[int, Frame]]:
        raise NotImplementedError


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda was asked for but CUDA is not available")
    return torch.device(name)


def with_given_poses(config: SLAMConfig) -> SLAMConfig:
    """The config for mapping with given (ground-truth) poses: bundle adjustment, new maps
    on tracking failure and loop closure off, since they could only move poses that are
    right by definition."""
    return replace(config, mapping=replace(config.mapping, optimize_poses=False),
                   multimap=replace(config.multimap, new_map_on_tracking_failure=False),
                   loop=replace(config.loop, enabled=False))


# ------------------------------------------------------------ tracking side
@dataclass
class AgentTrack:
    """One agent's tracking state."""

    agent: int
    records: list[FrameRecord] = field(default_factory=list)
    good_poses: list[np.ndarray] = field(default_factory=list)
    """World poses of recent well-tracked frames (the motion model's history)."""
    good_frames: list[int] = field(default_factory=list)
    """The frame indices of ``good_poses``."""
    last_ok: bool = True
    failures_in_row: int = 0
    lost: bool = False
    active_map: int = -1
    features: FeatureOdometry | None = None
    tracking_failures: int = 0
    kept_rays: dict[int, PixelBatch] = field(default_factory=dict)
    """Frame index -> pixels kept for the final re-tracking (``tracking.retrack_iterations``)."""
    retracked: dict[int, np.ndarray] = field(default_factory=dict)
    """Frame index -> T_world_cam (4, 4) float64 the final re-tracking found (replaces the
    corrected tracked pose in the outputs)."""


@dataclass
class _TrackingSide:
    config: SLAMConfig
    device: torch.device
    tracker: Tracker
    agents: dict[int, AgentTrack] = field(default_factory=dict)
    snapshots: dict[int, MapSnapshot] = field(default_factory=dict)
    frozen: dict[int, FrozenMap] = field(default_factory=dict)
    map_poses: dict[int, np.ndarray] = field(default_factory=dict)
    """map id -> T_world_map (4, 4) as the tracker knows it."""
    map_parent: dict[int, int | None] = field(default_factory=dict)
    map_centre: dict[int, np.ndarray] = field(default_factory=dict)
    """map id -> the centre of its region in the map frame: its first camera's position (the
    world's first map is the world frame, and its first camera is wherever GT puts it)."""
    next_map_id: int = 0
    busy: float = 0.0
    mapper_stats: MapperStats | None = None
    loops: int = 0
    frames_sent: int = 0
    """Frames handed to the mapping side; ``frames_integrated`` of them are in the newest snapshots."""
    frames_integrated: int = 0
    map_waits: int = 0
    map_wait_seconds: float = 0.0
    keyframes_seen: int = 0
    """KeyframeEvents the mapper has sent so far."""
    last_keyframe: tuple[int, int] | None = None
    """(agent, frame index) of the newest of them."""
    on_keyframe: Callable[[], None] | None = None
    """Called for each KeyframeEvent before it is emitted (``run_slam`` writes the progress)."""
    progress: list[ProgressSample] = field(default_factory=list)
    """The run's course, one sample every ``PROGRESS_EVERY`` frames (``run.json``'s ``progress``)."""
    held: deque[FrameMessage] = field(default_factory=deque)
    """Deterministic mode (``runtime.deterministic_lag``): tracked frames not yet handed to the
    mapper, newest last."""
    waiting: FrameMessage | None = None
    """Live mode (``runtime.live``): the newest tracked frame that found the mapper's queue full."""
    frames_unmapped: int = 0
    """Live mode: tracked frames the mapper never got (a newer frame took their place)."""
    retracker: Tracker | None = None
    """The final re-tracking's tracker (``tracking.retrack_iterations`` > 0), else None."""
    rays_generator: torch.Generator | None = None
    """Draws the pixels each tracked frame keeps for it (apart from the tracker's own draws)."""
    retrack_rays: int = 0
    """Pixels each tracked frame keeps for it (``retrack_rays_per_frame``)."""
    retracking: tuple[int, float] = (0, 0.0)
    """Frames the final re-tracking moved, and its seconds."""
    stages: StageClock = field(default_factory=StageClock)
    """Where the tracking side's wall time goes, stage by stage (``run.json``'s ``timings_s``)."""
    stopped: Callable[[], bool] = lambda: False
    """Whether the run was asked to stop: ends any wait for the mapper (``_poll_mapper``)."""

    def frozen_map(self, map_id: int) -> FrozenMap:
        """The tracker's copy of a map, rebuilt only when a newer snapshot arrived, placed
        by the newest map pose."""
        snap = self.snapshots[map_id]
        fmap = self.frozen.get(map_id)
        if fmap is None or fmap.version != snap.version:
            fmap = FrozenMap(snap, self.config, self.device)
            self.frozen[map_id] = fmap
        return fmap.place(self.map_poses[map_id])

    def move_maps(self, poses: dict[int, np.ndarray]) -> None:
        """Loop optimisation moved maps: the agents' motion history moves with its map."""
        for track in self.agents.values():
            old = self.map_poses.get(track.active_map)
            new = poses.get(track.active_map)
            if old is None or new is None:
                continue
            delta = new @ np.linalg.inv(old)
            track.good_poses = [delta @ p for p in track.good_poses]
            if track.features is not None:
                track.features.transform(delta)
        self.map_poses.update({k: np.asarray(v, np.float64) for k, v in poses.items()})

    def refine_frame(self, pose: FramePose) -> None:
        """The mapper's window optimised a frame's pose (``mapping.optimize_current_pose``): it
        replaces the tracked pose in the frame's record (so in the trajectory), in the motion
        history and, when it is the frame the feature odometry remembers, there too."""
        track = self.agents.get(pose.agent)
        if track is None:
            return
        i = next((i for i in range(len(track.records) - 1, -1, -1) if track.records[i].index == pose.frame_index), None)
        if i is None:
            return
        rec = track.records[i]
        T_map_cam = np.asarray(pose.T_map_cam, np.float64)
        before = self.map_poses[rec.map_id] @ rec.T_map_cam
        after = self.map_poses[pose.map_id] @ T_map_cam
        track.records[i] = replace(rec, map_id=pose.map_id, T_map_cam=T_map_cam)
        track.good_poses = [after if k == pose.frame_index else p for k, p in zip(track.good_frames, track.good_poses)]
        if track.features is not None and i == len(track.records) - 1 and rec.tracked:
            track.features.transform(after @ np.linalg.inv(before))


RETRACK_RAYS_MAX_FACTOR = 4
"""A frame keeps at most this many times ``tracking.retrack_rays`` pixels for the re-tracking."""


def retrack_rays_per_frame(tracking, total_frames: int | None) -> int:
    """Pixels a frame keeps for the final re-tracking: ``tracking.retrack_rays``, or, when the
    run's length is known and ``tracking.retrack_ray_budget`` set, the budget shared among
    its frames within 1-4x that (a short run is re-tracked on more pixels at the same cost)."""
    rays = tracking.retrack_rays
    if total_frames and tracking.retrack_ray_budget > 0:
        rays = min(max(rays, tracking.retrack_ray_budget // total_frames), RETRACK_RAYS_MAX_FACTOR * rays)
    return rays


def _prepare_retracking(side: _TrackingSide, total_frames: int | None) -> None:
    """The final re-tracking's tracker and pixel draws, when ``tracking.retrack_iterations`` > 0:
    Levenberg-Marquardt for that many steps (the pixels are drawn once per frame)."""
    c = side.config.tracking
    if c.retrack_iterations <= 0:
        return
    config = replace(side.config, tracking=replace(c, optimizer="gauss_newton", iterations=c.retrack_iterations))
    side.retracker = Tracker(config, side.device, seed=side.config.runtime.seed)
    # On the device, as the tracker's own: a CUDA generator draws there without an upload.
    side.rays_generator = torch.Generator(device=side.device).manual_seed(side.config.runtime.seed + 7919)
    side.retrack_rays = retrack_rays_per_frame(c, total_frames)


def _retrack(side: _TrackingSide, final: FinalMaps) -> None:
    """The final re-tracking: every frame that kept pixels is tracked again against its map as
    the final refinement left it, from its corrected pose (``slam.outputs.corrected_poses``).
    The maps then hold every keyframe jointly optimised, which the map a frame was tracked
    against in the run did not; a pose the tracker's checks reject keeps its corrected one.
    Runs while the mapping side fits colour and writes its outputs."""
    if side.retracker is None:
        return
    t0 = time.perf_counter()
    fmaps = {snap.map_id: FrozenMap(snap, side.config, side.device).place(final.map_poses[snap.map_id])
             for snap in final.snapshots}
    interpolate = side.config.mapping.frame_correction == "interpolated"
    moved = 0
    for track in side.agents.values():
        if not track.kept_rays:
            continue
        keyframes = {k.frame_index: k.T_world_cam for k in final.keyframes if k.agent == track.agent}
        start = corrected_poses(track.records, final.map_poses, keyframes, interpolate)
        candidates = [i for i, rec in enumerate(track.records)
                      if rec.index in track.kept_rays and rec.map_id in fmaps]
        map_ids = [track.records[i].map_id for i in candidates]
        chosen = {candidates[j] for j in retrack_anchors(map_ids, side.config.tracking.retrack_frame_budget)}
        found: dict[int, np.ndarray] = {}
        for i in sorted(chosen):
            rec = track.records[i]
            result = side.retracker.retrack(track.kept_rays[rec.index], fmaps[rec.map_id],
                                            torch.from_numpy(start[i]).float())
            if result.ok:
                found[i] = result.T_world_cam.cpu().numpy().astype(np.float64)
        left_out = [i for i in candidates if i not in chosen]
        spread = spread_corrections(start, [r.map_id for r in track.records], found, left_out)
        for i, T in {**found, **spread}.items():
            track.retracked[track.records[i].index] = T
        moved += len(found)
        track.kept_rays.clear()
    seconds = time.perf_counter() - t0
    side.busy += seconds
    side.retracking = (moved, seconds)


def _retrack_estimate(side: _TrackingSide) -> float | None:
    """About how long the final re-tracking takes: its frames at the run's tracking time per
    frame, scaled by its iterations to the tracker's; None before any frame was tracked."""
    c = side.config.tracking
    frames = sum(len(retrack_anchors([r.map_id for r in t.records if r.index in t.kept_rays], c.retrack_frame_budget))
                 for t in side.agents.values())
    tracked = sum(len(t.records) for t in side.agents.values())
    if not tracked or c.iterations <= 0:
        return None
    per_frame = side.stages.totals.get("track", 0.0) / tracked
    return round(frames * per_frame * c.retrack_iterations / c.iterations, 1)


def _thumbnail(rgb: np.ndarray, width: int = 96) -> np.ndarray:
    import cv2

    h = max(1, int(round(rgb.shape[0] * width / rgb.shape[1])))
    return (cv2.resize(rgb, (width, h), interpolation=cv2.INTER_AREA) * 255).astype(np.uint8)


def _handle_replies(replies: list[Reply], side: _TrackingSide, emit: Callable[[Event], None]) -> None:
    """Apply the mapping side's replies in order (``slam.messages``); a ``Failed`` one raises
    ``MapperFailed`` with its traceback."""
    for reply in replies:
        if isinstance(reply, Failed):
            raise MapperFailed(reply.traceback)
        if isinstance(reply, SnapshotReply):
            side.snapshots[reply.snapshot.map_id] = reply.snapshot
            side.frames_integrated = max(side.frames_integrated, reply.snapshot.frames_integrated)
        elif isinstance(reply, MapPosesReply):
            side.move_maps(reply.poses)
        elif isinstance(reply, FramePose):
            side.refine_frame(reply)
        elif isinstance(reply, EventReply):
            _count_event(side, reply.event)
            emit(reply.event)
        elif isinstance(reply, FinalMaps):
            if side.retracker is not None:
                emit(PhaseEvent("refining", "retracking", _retrack_estimate(side)))
            _retrack(side, reply)
        elif isinstance(reply, Done):
            side.mapper_stats = reply.stats


class RunStopped(Exception):
    """The run was asked to stop while the tracker waited for the mapper."""


def _poll_mapper(side: _TrackingSide, channel, emit: Callable[[Event], None]) -> None:
    """Wait a poll interval for the mapper's replies and apply them. A stop request ends the
    wait (``RunStopped``): a stopped run writes the frames tracked so far at once instead of
    after the mapper's work in hand (a first frame's mapping takes seconds)."""
    if side.stopped():
        raise RunStopped
    _handle_replies(channel.poll(block=True), side, emit)


def _count_event(side: _TrackingSide, event: Event) -> None:
    """Loops and keyframes as the mapping side announces them; a keyframe's progress is
    written before its event goes out (module doc)."""
    if isinstance(event, LoopEvent):
        side.loops += 1
    elif isinstance(event, KeyframeEvent):
        side.keyframes_seen += 1
        side.last_keyframe = (int(event.agent), int(event.frame_index))
        if side.on_keyframe is not None:
            side.on_keyframe()


def _valid_depth_share(frame: Frame) -> float:
    return float((frame.depth > 0).mean()) if frame.depth.size else 0.0


def _start_map(side: _TrackingSide, track: AgentTrack, reason: str, T_world_cam: np.ndarray,
               first_ever: bool) -> tuple[int, np.ndarray, np.ndarray]:
    """Number a new map for ``track``: (map id, T_world_map, T_map_cam of this frame). The
    world's first map is the world frame; any later map's frame is its first camera's."""
    map_id = side.next_map_id
    side.next_map_id += 1
    T_world_map = np.eye(4) if first_ever else np.asarray(T_world_cam, np.float64)
    side.map_poses[map_id] = T_world_map
    side.map_parent[map_id] = track.active_map if reason == "region" else None
    track.active_map = map_id
    T_map_cam = np.linalg.inv(T_world_map) @ T_world_cam
    side.map_centre[map_id] = T_map_cam[:3, 3].copy()
    return map_id, T_world_map, T_map_cam


def _track_map(side: _TrackingSide, track: AgentTrack, channel, emit) -> int:
    """The map to track the agent's next frame against: its active map once the mapper has
    published it; until then a region map's predecessor (still right around the border);
    otherwise wait for the first snapshot (a map's first frame initialises it)."""
    while track.active_map not in side.snapshots:
        parent = side.map_parent.get(track.active_map)
        if parent is not None and parent in side.snapshots:
            return parent
        if side.config.runtime.deterministic:
            _send_until_map(side, channel, track.active_map, emit)
            if track.active_map in side.snapshots:
                break
        _poll_mapper(side, channel, emit)
    return track.active_map


def _hand_over(side: _TrackingSide, msg: FrameMessage, channel) -> None:
    """A tracked frame for the mapper: sent now, or in deterministic mode held until the
    lag says (``_deterministic_map``)."""
    runtime = side.config.runtime
    if runtime.deterministic:
        # The mapper optimises at every deterministic_every-th frame (a map's first frame
        # always), as a free-running one optimises once per batch of the frames it found queued.
        handed = side.frames_sent + len(side.held)
        optimize = msg.new_map is not None or (handed + 1) % runtime.deterministic_every == 0
        side.held.append(replace(msg, optimize=optimize))
        return
    if runtime.live:
        _offer_newest(side, msg, channel)
        return
    channel.submit(msg)
    side.frames_sent += 1


def _offer_newest(side: _TrackingSide, msg: FrameMessage, channel) -> None:
    """Live mode: hand the mapper the newest frames it has room for, never waiting, except
    for a frame that starts a map (the map exists only once the mapper has it). The frame that
    waited since the last call goes first if there is room now; if not, it is left out."""
    waiting, side.waiting = side.waiting, None
    if waiting is not None and not _offer(side, waiting, channel):
        side.frames_unmapped += 1
    if msg.new_map is not None:
        channel.submit(msg)
        side.frames_sent += 1
    elif not _offer(side, msg, channel):
        side.waiting = msg


def _offer(side: _TrackingSide, msg: FrameMessage, channel) -> bool:
    """``msg`` to the mapper if its queue has room now (counted); whether it went."""
    sent = channel.offer(msg)
    side.frames_sent += sent
    return sent


def _send_waiting(side: _TrackingSide, channel) -> None:
    """Live mode, at the end of the input: the frame still waiting goes to the mapper."""
    if side.waiting is not None:
        channel.submit(side.waiting)
        side.frames_sent += 1
        side.waiting = None


def _send_held(side: _TrackingSide, channel, count: int) -> None:
    for _ in range(min(count, len(side.held))):
        channel.submit(side.held.popleft())
        side.frames_sent += 1


def _wait_integrated(side: _TrackingSide, channel, emit) -> None:
    """Block until the mapper has integrated every frame sent to it (and its replies are applied)."""
    if side.frames_integrated >= side.frames_sent:
        return
    t0 = time.perf_counter()
    side.map_waits += 1
    while side.frames_integrated < side.frames_sent:
        _poll_mapper(side, channel, emit)
    side.map_wait_seconds += time.perf_counter() - t0


def _deterministic_map(side: _TrackingSide, channel, emit) -> None:
    """Deterministic mode, before a frame is tracked: the tracker's maps hold exactly the
    frames tracked so far but the newest ``lag`` (config doc). Frames past that are sent and
    waited for; then, with a lag, the oldest held frame goes to the mapper, which integrates it
    while this frame is tracked (its map is applied only after: nothing polls meanwhile)."""
    lag = side.config.runtime.deterministic_lag
    _send_held(side, channel, len(side.held) - lag)
    _wait_integrated(side, channel, emit)
    if lag > 0:
        _send_held(side, channel, 1)


def _send_until_map(side: _TrackingSide, channel, map_id: int, emit) -> None:
    """Deterministic mode: a map the tracker needs starts with a frame it still holds; send the
    held frames up to that one and wait for them (the same frames every run)."""
    position = next((i for i, msg in enumerate(side.held) if msg.map_id == map_id), None)
    if position is not None:
        _send_held(side, channel, position + 1)
    _wait_integrated(side, channel, emit)


_MIN_TRACKABLE_DEPTH = 0.01
"""Share of pixels with valid depth below which a frame is not tracked at all."""


def _count_failure(track: AgentTrack, config: SLAMConfig) -> None:
    """A failed frame; enough of them in a row and the camera is lost."""
    mm = config.multimap
    track.tracking_failures += 1
    track.failures_in_row += 1
    track.last_ok = False
    if mm.enabled and mm.new_map_on_tracking_failure and track.failures_in_row >= mm.failures_before_new_map:
        track.lost = True
        if track.features is not None:
            track.features.remember(None)


def _estimate_pose(side: _TrackingSide, track: AgentTrack, frame: Frame, raw: Frame, channel,
                   use_gt_poses: bool, emit) -> tuple[FrameMessage | None, FrameRecord]:
    """Track one frame of one agent: its record and the message for the mapper (None: the
    frame is not mapped, e.g. a lost camera's frame without depth)."""
    gt = _ground_truth(track, raw, use_gt_poses)
    min_depth = side.config.multimap.min_valid_depth
    if not track.records or (track.lost and _valid_depth_share(frame) >= min_depth):
        return _start_frame(side, track, frame, raw, gt, use_gt_poses)
    if use_gt_poses:
        return _given_pose_frame(side, track, frame, gt)
    if track.lost:
        # No depth to start a map with: hold the last pose; the outputs interpolate it.
        T_mc = np.linalg.inv(side.map_poses[track.active_map]) @ track.good_poses[-1]
        track.tracking_failures += 1
        return None, FrameRecord(frame.index, float(frame.timestamp), track.active_map, T_mc, False, gt)
    if _valid_depth_share(frame) < _MIN_TRACKABLE_DEPTH:
        # Nothing to track with (a blank or dropped-out frame): a failure at the guess, not
        # sent to the mapper.
        T = track.good_poses[-1]
        _count_failure(track, side.config)
        T_mc = np.linalg.inv(side.map_poses[track.active_map]) @ T
        return None, FrameRecord(frame.index, float(frame.timestamp), track.active_map, T_mc, False, gt)
    return _track_frame(side, track, frame, raw, gt, channel, emit)


def _ground_truth(track: AgentTrack, raw: Frame, use_gt_poses: bool) -> np.ndarray | None:
    """The frame's ground-truth pose (4, 4) float64, if it has one; required by --gt-poses."""
    if raw.T_world_cam is not None:
        return np.asarray(raw.T_world_cam, np.float64)
    if use_gt_poses:
        agent = f" of agent {track.agent}" if track.agent else ""
        raise ValueError(f"--gt-poses: frame {raw.index}{agent} has no ground-truth pose")
    return None


def _start_frame(side: _TrackingSide, track: AgentTrack, frame: Frame, raw: Frame, gt: np.ndarray | None,
                 use_gt_poses: bool) -> tuple[FrameMessage, FrameRecord]:
    """An agent's first frame starts its first map at the origin: the world is the first
    camera's frame whether or not the input has ground truth (the ATE aligns onto it; with
    ``use_gt_poses`` the ground truth's frame). A lost camera's first frame with depth starts a
    floating map at the last pose it knew."""
    first_frame = not track.records
    reason = "start" if first_frame else "tracking_failure"
    if use_gt_poses:
        T = gt
    elif first_frame:
        T = np.eye(4)
    else:
        T = track.good_poses[-1]
    map_id, T_wm, T_mc = _start_map(side, track, reason, T, first_ever=side.next_map_id == 0)
    track.lost, track.failures_in_row, track.last_ok = False, 0, True
    track.good_poses, track.good_frames = [T], [frame.index]
    features = None
    if not use_gt_poses:
        track.features = track.features or FeatureOdometry.from_config(side.config)
        if track.features is not None:
            track.features.correspondences(raw)
            features = _features_for_loops(side.config, track, frame, raw)
            track.features.remember(T)
    rec = FrameRecord(frame.index, float(frame.timestamp), map_id, T_mc, True, gt)
    start = MapStart(reason, map_id, T_wm.astype(np.float32))
    tf = prepare_frame(frame, None, side.device, side.config.voxel.max_depth)
    if side.retracker is not None and not use_gt_poses:
        # Re-tracked like every other frame: the final maps no longer hold it exactly at the
        # pose it started them with, and frames 1 onward are placed by them.
        track.kept_rays[frame.index] = side.tracker.keep_rays(tf, side.retrack_rays, side.rays_generator)
    return FrameMessage(track.agent, frame, map_id, T_mc.astype(np.float32), True, start, prepared=tf,
                        features=features), rec


def _given_pose_frame(side: _TrackingSide, track: AgentTrack, frame: Frame,
                      gt: np.ndarray) -> tuple[FrameMessage, FrameRecord]:
    """--gt-poses: the frame at its ground-truth pose, in the agent's active map."""
    map_id = track.active_map
    T_mc = np.linalg.inv(side.map_poses[map_id]) @ gt
    return (FrameMessage(track.agent, frame, map_id, T_mc.astype(np.float32), True),
            FrameRecord(frame.index, float(frame.timestamp), map_id, T_mc, True, gt))


def _track_frame(side: _TrackingSide, track: AgentTrack, frame: Frame, raw: Frame, gt: np.ndarray | None,
                 channel, emit) -> tuple[FrameMessage, FrameRecord]:
    """Track a frame against the newest map the agent may use, from the last good pose (the
    paper's zero motion model; or the PnP pose of its ORB matches with the previous frame); a good pose that
    left the active map's region starts the next map."""
    config = side.config
    if config.runtime.deterministic:
        _deterministic_map(side, channel, emit)
    t0 = time.perf_counter()
    with side.stages.stage("map_update"):
        map_id = _track_map(side, track, channel, emit)
        fmap = side.frozen_map(map_id)
    tf = prepare_frame(frame, None, side.device, config.voxel.max_depth)
    T_init = torch.from_numpy(track.good_poses[-1]).float().to(side.device)
    with side.stages.stage("features"):
        matches = track.features.correspondences(raw) if track.features is not None else None
        features = _features_for_loops(config, track, frame, raw)
    with side.stages.stage("track"):
        result = side.tracker.track(tf, fmap, T_init, matches)
    T = result.T_world_cam.detach().cpu().numpy().astype(np.float64)
    if track.features is not None:
        track.features.remember(T if result.ok else None)
    side.busy += time.perf_counter() - t0
    track.last_ok = result.ok
    map_id, T_mc, new_map = _place_tracked(side, track, frame.index, map_id, T, result.ok)
    rec = FrameRecord(frame.index, float(frame.timestamp), map_id, T_mc, result.ok, gt)
    covariance = frame_covariance(result.information) if result.ok and result.information is not None else None
    if side.retracker is not None and result.ok and new_map is None:
        with side.stages.stage("keep_rays"):
            track.kept_rays[frame.index] = side.tracker.keep_rays(tf, side.retrack_rays, side.rays_generator)
    return FrameMessage(track.agent, frame, map_id, T_mc.astype(np.float32), result.ok, new_map, covariance,
                        prepared=tf, features=features), rec


def _place_tracked(side: _TrackingSide, track: AgentTrack, index: int, map_id: int, T: np.ndarray,
                   ok: bool) -> tuple[int, np.ndarray, MapStart | None]:
    """A tracked world pose T in the map it was tracked against (map id, T_map_cam); a good
    one joins the motion history and, outside the active map's region, starts the next map
    (then its id, the pose in it, and the ``MapStart``); a bad one counts as a failure."""
    T_mc = np.linalg.inv(side.map_poses[map_id]) @ T
    if not ok:
        _count_failure(track, side.config)
        return map_id, T_mc, None
    track.failures_in_row = 0
    track.good_poses = (track.good_poses + [T])[-3:]
    track.good_frames = (track.good_frames + [index])[-3:]
    mm = side.config.multimap
    offset = (np.linalg.inv(side.map_poses[track.active_map]) @ T)[:3, 3] - side.map_centre[track.active_map]
    if mm.enabled and float(np.abs(offset).max()) > mm.region_size / 2:
        # The camera left the active map's region: this frame starts the next map.
        new_id, T_wm, T_mc = _start_map(side, track, "region", T, first_ever=False)
        return new_id, T_mc, MapStart("region", new_id, T_wm.astype(np.float32))
    return map_id, T_mc, None


def _features_for_loops(config: SLAMConfig, track: AgentTrack, frame: Frame, raw: Frame):
    """The ORB features the tracker just detected on ``raw``, when the loop closer's
    appearance check would detect the same ones (same detector, and ``raw`` is the pipeline
    frame): they travel with the frame instead of being detected again. None otherwise."""
    if track.features is None or frame is not raw or not config.loop.enabled:
        return None
    return track.features.detected if tracking_features_serve_loops(config) else None


def _interleave(sources: list[Iterable[Frame]]) -> Iterator[tuple[int, Frame]]:
    """(agent, frame) pairs: an AgentStream as it comes, plain sources round-robin."""
    if len(sources) == 1 and isinstance(sources[0], AgentStream):
        yield from sources[0]
        return
    iterators = [iter(s) for s in sources]
    alive = list(range(len(iterators)))
    while alive:
        for k in list(alive):
            try:
                yield k, next(iterators[k])
            except StopIteration:
                alive.remove(k)


def _timed(items: Iterable, clock: StageClock, name: str) -> Iterator:
    """``items`` as they come, the time each takes to come (reading and decoding a frame)
    added to ``clock``'s ``name``."""
    iterator = iter(items)
    while True:
        with clock.stage(name):
            try:
                item = next(iterator)
            except StopIteration:
                return
        yield item


def _skipped_frames(sources: list[Iterable[Frame]]) -> list[dict]:
    """Frames the sources left out because they could not be read (``FileSequence.skipped``):
    agent, index and why, for ``run.json``."""
    return [{"agent": agent if skipped.agent is None else skipped.agent, "index": skipped.index,
             "reason": skipped.reason}
            for agent, source in enumerate(sources) for skipped in getattr(source, "skipped", ())]


def _total_frames(sources: list[Iterable[Frame]]) -> int | None:
    try:
        return sum(len(s) for s in sources)  # type: ignore[arg-type]
    except TypeError:
        return None


def run_slam(sources: list[Iterable[Frame]], config: SLAMConfig, out_dir: str | Path, *,
             use_gt_poses: bool = False, on_event: Callable[[Event], None] | None = None,
             stop: StopFlag | None = None, progress: bool = False) -> RunResult:
    """Run SLAM over ``sources`` (one per agent, or one ``AgentStream``) and write the
    outputs to ``out_dir``. See the module doc.

    Exceptions inside the run (bad data, a mapper failure) end it as ``failed`` with the
    traceback in ``run.json``; Ctrl-C or ``stop`` end it as ``cancelled``; in both cases what
    was mapped so far is still written.
    """
    if not sources:
        raise ValueError("run_slam needs at least one source")
    if use_gt_poses:
        config = with_given_poses(config)
    run = _open_run(sources, config, Path(out_dir), on_event, stop, progress)
    _track_all(run, sources, use_gt_poses)
    run.tracking_ended = time.perf_counter()
    if run.side is not None:
        # Tracking is over (the input ended, a stop, a failure): every pose on disk first, in
        # milliseconds, before the final refinement (minutes) or a stop's checkpoint and mesh,
        # which a kill may cut short.
        try:
            _write_progress(run.out, run.side, run.total, run.started)
        except OSError:
            run.status, run.error = "failed", run.error or traceback.format_exc()
    _finish_mapping(run, progress)
    return _write_results(run, sources, use_gt_poses)


@dataclass
class _Run:
    """One ``run_slam`` call: where it writes, whom it tells, and how far it got."""

    out: Path
    config: SLAMConfig
    device: torch.device
    emit: Callable[[Event], None]
    thumbnails: bool
    """Whether PoseEvents carry a thumbnail (someone listens)."""
    stop: StopFlag | None
    total: int | None
    started: float
    bar: "tqdm | None" = None
    """The progress bar (``progress``)."""
    done: int = 0
    """Frames processed so far."""
    status: str = "finished"
    error: str | None = None
    side: _TrackingSide | None = None
    channel: InlineMapper | ProcessMapper | None = None
    tracking_ended: float | None = None
    """When the last frame was tracked (perf_counter): the end-of-run phases start."""

    def stopped(self) -> bool:
        return self.stop is not None and self.stop.is_set()


def _open_run(sources: list[Iterable[Frame]], config: SLAMConfig, out: Path,
              on_event: Callable[[Event], None] | None, stop: StopFlag | None, progress: bool) -> _Run:
    """The output folder, the device and its threads, the seed, the progress bar."""
    out.mkdir(parents=True, exist_ok=True)
    # The trajectory writer's modules (seconds to import) now: a stop must not wait for them.
    from .eval import trajectory  # noqa: F401
    device = resolve_device(config.runtime.device)
    process_threads(device, config.runtime.processes)
    torch.manual_seed(config.runtime.seed)
    total = _total_frames(sources)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, unit="frame", dynamic_ncols=True)
    return _Run(out, config, device, on_event or (lambda event: None), on_event is not None, stop, total,
                time.perf_counter(), bar)


def _track_all(run: _Run, sources: list[Iterable[Frame]], use_gt_poses: bool) -> None:
    """Start the mapping side and the tracker, then every frame in arrival order until the
    input ends, a stop, or a failure (``run.status``, ``run.error``)."""
    config = run.config
    try:
        mapper_cls = ProcessMapper if config.runtime.processes else InlineMapper
        # While the mapping process starts (seconds: it imports torch), the sources find their
        # colour cameras (numpy and OpenCV, which let the thread run beside it).
        calibration = _calibrate_colour(sources) if config.runtime.color_calibration else None
        try:
            run.channel = mapper_cls(config, run.device, run.out, run.thumbnails, config.runtime.seed)
        finally:
            if calibration is not None:
                calibration.join()
        side = run.side = _TrackingSide(config, run.device, Tracker(config, run.device, seed=config.runtime.seed))
        _prepare_retracking(side, run.total)
        side.on_keyframe = lambda: _write_progress(run.out, side, run.total, run.started)
        side.stopped = run.stopped
        run.emit(PhaseEvent("tracking"))
        for agent, raw in _timed(_interleave(sources), side.stages, "read"):
            if run.stopped():
                run.status = "cancelled"
                break
            _process_frame(run, agent, raw, use_gt_poses)
    except (KeyboardInterrupt, RunStopped):
        run.status = "cancelled"
    except Exception:  # noqa: BLE001 - any failure ends this run only, with its traceback
        run.status, run.error = "failed", traceback.format_exc()
    finally:
        if run.bar is not None:
            run.bar.close()
    if run.status == "finished" and run.stopped():
        # A source that ends because of the stop (a live stream) is a stop, not the end of the
        # input: skip the final refinement, which would hold up the stop for minutes.
        run.status = "cancelled"


def _calibrate_colour(sources: list[Iterable[Frame]]) -> threading.Thread:
    """A started thread in which every source that can (``FileSequence.calibrate_colour``)
    estimates its colour camera; a failure there leaves that source's colour as it is."""
    def calibrate() -> None:
        for source in sources:
            method = getattr(source, "calibrate_colour", None)
            if method is None:
                continue
            try:
                method()
            except Exception:  # noqa: BLE001 - a guess that failed must not fail the run
                traceback.print_exc()
    thread = threading.Thread(target=calibrate, name="colour-calibration", daemon=True)
    thread.start()
    return thread


def _colour_cameras(sources: list[Iterable[Frame]]) -> list[dict | None]:
    """Per source: how its colour came onto the depth camera, for ``run.json``."""
    out: list[dict | None] = []
    for source in sources:
        camera, warp = getattr(source, "color_camera", None), getattr(source, "color_warp", None)
        if camera is not None:
            out.append({"source": "given", "K": camera.K.tolist(), "width": camera.width, "height": camera.height,
                        "T_color_depth": camera.T_color_depth.tolist()})
        elif warp is not None:
            out.append({"source": "estimated", **warp.as_dict()})
        else:
            out.append(None)
    return out


def _process_frame(run: _Run, agent: int, raw: Frame, use_gt_poses: bool) -> None:
    """One frame of one agent, as the paper's system overview goes (module doc)."""
    side, channel = run.side, run.channel
    assert side is not None and channel is not None
    track = side.agents.setdefault(agent, AgentTrack(agent))
    with side.stages.stage("prepare"):
        frame = resize_frame(raw, run.config.runtime.input_width)  # once: tracker and mapper share it
    # Track it against the agent's active map; lost, or out of the map's region: a new map.
    msg, rec = _estimate_pose(side, track, frame, raw, channel, use_gt_poses, run.emit)
    track.records.append(rec)
    with side.stages.stage("publish"):
        _publish_pose(run, track.agent, frame, msg, rec)
    # Hand it to the mapping side: it decides keyframes, maps the frame, and looks for loops
    # at every new keyframe.
    if msg is not None:
        with side.stages.stage("hand_over"):
            _hand_over(side, msg, channel)
    # What the mapping side sent back meanwhile: keyframes, loops, moved maps, snapshots.
    with side.stages.stage("replies"):
        _handle_replies(channel.poll(), side, run.emit)
    _count_frame(run)


def _publish_pose(run: _Run, agent: int, frame: Frame, msg: FrameMessage | None, rec: FrameRecord) -> None:
    """The frame's events: the map it starts, if any, and its pose in its map."""
    if msg is not None and msg.new_map is not None:
        start = msg.new_map
        run.emit(SubmapEvent(start.map_id, agent, np.asarray(start.T_world_map, np.float64), start.reason))
    run.emit(PoseEvent(agent, frame.index, float(frame.timestamp), np.asarray(rec.T_map_cam, np.float64),
                       rec.map_id, rec.tracked,
                       thumbnail=_thumbnail(frame.rgb) if run.thumbnails else None,
                       K=np.asarray(frame.K, np.float64), image_size=(frame.width, frame.height)))


def _count_frame(run: _Run) -> None:
    """One more frame done: the progress bar, and every ``PROGRESS_EVERY`` frames the
    statistics (a StatsEvent and a sample of ``run.json``'s progress)."""
    side = run.side
    assert side is not None
    run.done += 1
    fps = run.done / max(time.perf_counter() - run.started, 1e-9)
    if run.bar is not None:
        run.bar.update(1)
        run.bar.set_postfix(_progress_fields(side, fps, run.done), refresh=False)
    if run.done % PROGRESS_EVERY == 0:
        event = _stats_event(side, run.total, fps, run.started, run.done)
        side.progress.append(_progress_sample(side, event, run.started))
        run.emit(event)


def _finish_mapping(run: _Run, progress: bool) -> None:
    """Send deterministic mode's last frames and let the mapping side finish: the final
    refinement for a finished run, the checkpoint and mesh for any with a map; then close it."""
    side, channel = run.side, run.channel
    if channel is None:
        return
    try:
        if side is not None and run.status != "failed":
            _send_held(side, channel, len(side.held))  # deterministic mode's last frames
            _send_waiting(side, channel)  # live mode's
        if side is not None and (run.status != "failed" or side.snapshots):
            _final_refinement(run, side, channel, progress)
    except KeyboardInterrupt:
        run.status = "cancelled"
    except Exception:  # noqa: BLE001
        if run.error is None:
            run.status, run.error = "failed", traceback.format_exc()
    finally:
        channel.close()


def _final_refinement(run: _Run, side: _TrackingSide, channel, progress: bool) -> None:
    """The mapping side's end of run (``refine`` only when finished), its replies applied."""
    refine = run.status == "finished"
    if refine:
        run.emit(PhaseEvent("refining"))
        if progress:
            print("refining: the final bundle adjustment, then the map and the mesh", file=sys.stderr, flush=True)
    _handle_replies(channel.finish(refine=refine), side, run.emit)
    if progress and side.mapper_stats is not None and side.mapper_stats.refinement is not None:
        print(f"refining: {describe_refinement(side.mapper_stats.refinement)}", file=sys.stderr, flush=True)
    if progress and side.retracking[0]:
        print(f"refining: {side.retracking[0]} frames tracked again against the final maps in "
              f"{side.retracking[1]:.1f} s", file=sys.stderr, flush=True)


def _write_results(run: _Run, sources: list[Iterable[Frame]], use_gt_poses: bool) -> RunResult:
    """The outputs (``slam.outputs.write_outputs``) and the last events."""
    elapsed = time.perf_counter() - run.started
    run.emit(PhaseEvent("writing", "outputs"))
    side = run.side
    if side is not None and run.tracking_ended is not None:
        side.stages.add("end_of_run", elapsed - (run.tracking_ended - run.started))
    tracks = sorted(side.agents.values(), key=lambda t: t.agent) if side is not None else []
    result = write_outputs(run.out, run.config, tracks, side.mapper_stats if side else None, run.status, run.error,
                           elapsed, run.total, side.busy if side else 0.0, use_gt_poses,
                           side.map_poses if side else None,
                           (side.map_waits, side.map_wait_seconds) if side else (0, 0.0),
                           frames_skipped=_skipped_frames(sources),
                           colour_cameras=_colour_cameras(sources),
                           progress=side.progress if side else None,
                           retracking=side.retracking if side else (0, 0.0),
                           tracking_stages=side.stages.totals if side else None,
                           frames_unmapped=side.frames_unmapped if side else 0)
    if side is not None:
        run.emit(_stats_event(side, run.total, result.fps, run.started, run.done, ate=result.ate_rmse))
    run.emit(FinishedEvent(run.status, run.error))
    return result


def _write_progress(out: Path, side: _TrackingSide, total: int | None, started: float) -> None:
    """The trajectories so far and a ``running`` run.json (``slam.outputs.write_progress``);
    a write that fails is said on stderr and the run goes on, unless the disk is full: a run
    that can keep nothing it does fails (the OSError is raised)."""
    tracks = sorted(side.agents.values(), key=lambda t: t.agent)
    try:
        write_progress(out, side.config, tracks, side.map_poses, keyframes=side.keyframes_seen,
                       maps=max(side.next_map_id, 1), loops=side.loops, total=total,
                       elapsed=time.perf_counter() - started, last_keyframe=side.last_keyframe)
    except OSError as error:
        if error.errno in (errno.ENOSPC, errno.EDQUOT):
            raise
        print(f"voxfusion: cannot write the progress to {out}: {error}", file=sys.stderr, flush=True)


def describe_refinement(refinement) -> str:
    """One line on what the final bundle adjustment did (``messages.FinalRefinement``)."""
    cap = f", stopped by its {refinement.seconds_budget:.0f} s cap" if refinement.stopped_by_time else ""
    return f"{refinement.iterations_run} of {refinement.iterations_budget} iterations in {refinement.seconds:.1f} s{cap}"


def _progress_fields(side: _TrackingSide, fps: float, done: int) -> dict[str, str]:
    fields = {"fps": f"{fps:.2f}"}
    track = side.agents.get(0)
    ate = running_ate(track.records, side.map_poses) if track is not None and done % 5 == 0 else None
    if ate is not None:  # the tracked poses': the summary's ATE comes after the final bundle adjustment
        fields["ATE tracked"] = f"{ate * 100:.2f}cm"
    lost = sum(t.tracking_failures for t in side.agents.values())
    if lost:
        fields["lost"] = str(lost)
    maps = side.next_map_id
    if maps > 1:
        fields["maps"] = str(maps)
    if side.loops:
        fields["loops"] = str(side.loops)
    return fields


def _progress_sample(side: _TrackingSide, event: StatsEvent, started: float) -> ProgressSample:
    """Where the run stands at ``event``: frames, seconds, and the map as the tracker's newest
    copies of it hold it (embeddings and decoders)."""
    nbytes = sum(s.embeddings.nbytes + sum(a.nbytes for a in s.decoder_state.values())
                 for s in side.snapshots.values())
    return ProgressSample(frames=event.frames_done, wall_s=time.perf_counter() - started, voxels=event.voxels,
                          keyframes=side.keyframes_seen, maps=event.maps, map_mb=nbytes / 2**20)


def _stats_event(side: _TrackingSide, total: int | None, fps: float, started: float, done: int,
                 ate: float | None = None) -> StatsEvent:
    """Progress so far; ``ate`` (the final one) replaces agent 0's running ATE when given."""
    stats = side.mapper_stats
    if ate is None:
        track = side.agents.get(0)
        ate = running_ate(track.records, side.map_poses) if track is not None else None
    wall = max(time.perf_counter() - started, 1e-9)
    voxels = stats.voxels if stats else sum(len(s.voxel_codes) for s in side.snapshots.values())
    return StatsEvent(
        frames_done=done, frames_total=total, fps=fps,
        keyframes=stats.keyframes if stats else 0, maps=max(side.next_map_id, 1), loops=side.loops,
        voxels=voxels, tracking_busy=min(1.0, side.busy / wall),
        mapping_busy=min(1.0, stats.busy_seconds / wall) if stats else 0.0, ate_rmse=ate)
