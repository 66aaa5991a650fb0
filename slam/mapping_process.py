"""The mapping side of the runtime: the mapper and the loop closer behind a frame queue.

For every tracked frame the mapping side integrates it into its agent's active map
(``slam.mapping.Mapper``); for every new keyframe the loop closer (``slam.loop.closing``)
runs the appearance check, geometric verification and, for an accepted loop, the
hierarchical pose optimisation. It answers (``slam.messages``) with map snapshots (by
version), events, map poses after a loop, frame poses the window refined (``FramePose``), and
at the end the statistics. At the end of a sequence every map gets its global bundle
adjustment before the mesh and checkpoint are written.

``ProcessMapper`` runs all of this in a spawned process fed by a bounded queue
(back-pressure instead of unbounded lag); ``InlineMapper`` runs it in the caller
(``runtime.processes = False``: debugging and tests). Start-up and shutdown are handshakes on
the queues, not sleeps. A mapper that dies or raises ends the run as ``failed``.
"""

from __future__ import annotations

import os
import queue
import signal
import time
import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator

import numpy as np
import torch

from .config import SLAMConfig, config_from_dict
from .events import KeyframeEvent, MapUpdateEvent, PhaseEvent, PosesUpdatedEvent
from .frames import prepare_frame
from .mapping import Mapper, MappingStep, MapSnapshot, NewMap, TrackedFrame
from .messages import (Done, EndOfInput, EventReply, Failed, FinalMaps, FinalRefinement, FrameMessage, FramePose,
                       KeyframeRecord, MapPosesReply, MapperStats, Ready, Reply, Request, SnapshotReply)

if TYPE_CHECKING:
    from .loop.closing import LoopCloser
    from .maps import SubMap

__all__ = ["END", "END_NOW", "FinalBudget", "InlineMapper", "MapperFailed", "ProcessMapper", "final_budget",
           "final_iterations_per_map", "map_poses", "map_update_event", "poses_event", "process_threads"]

_POLL_SECONDS = 0.2
END = EndOfInput(refine=True)
"""The last request when the sequence ended: refine globally, then write the outputs."""
END_NOW = EndOfInput(refine=False)
"""The last request when the run was stopped: write the outputs without the refinement."""
_STARTUP_TIMEOUT = 300.0


class MapperFailed(RuntimeError):
    """The mapping process raised or died; the message carries its traceback."""


def process_threads(device: torch.device, processes: bool) -> None:
    """Two busy processes on a small CPU: give each its share of cores (oversubscribed torch
    threads spin and slow everything down several times)."""
    if device.type == "cpu":
        import cv2

        n = os.cpu_count() or 1
        threads = max(1, n // 2) if processes else n
        torch.set_num_threads(threads)
        cv2.setNumThreads(threads)  # ORB matching (slam.features) and loop verification


@dataclass(frozen=True)
class FinalBudget:
    """The end-of-run global bundle adjustment's budget: iterations over all maps, and
    seconds (None: no time cap)."""

    iterations: int
    seconds: float | None


@dataclass
class _MapperSide:
    """The mapper, the loop closer and the output policy of the mapping side."""

    mapper: Mapper
    closer: "LoopCloser | None"
    out_dir: Path
    emit_meshes: bool
    keyframes_since_mesh: int = 0
    keyframes_since_checkpoint: int = 0
    busy: float = 0.0
    started: float = field(default_factory=time.perf_counter)
    """When the mapping side started (the final bundle adjustment's time cap is relative)."""
    refinement: FinalRefinement | None = None
    keyframe_graph: dict | None = None
    odometry_covariance: dict[int, np.ndarray] = field(default_factory=dict)
    """agent -> covariances of its frames tracked since its last keyframe, summed."""
    frames_integrated: int = 0
    first_frame_debt: dict[int, int] = field(default_factory=dict)
    """``runtime.live``: map id -> iterations its first frame is still owed (``_pay_first_frames``)."""

    def snapshot(self, submap) -> MapSnapshot:
        """The tracker's copy of ``submap``, stamped with the frames integrated so far."""
        return replace(self.mapper.snapshot(submap), frames_integrated=self.frames_integrated)


def _make_side(config: SLAMConfig, device: torch.device, out_dir: Path, emit_meshes: bool, seed: int) -> _MapperSide:
    mapper = Mapper(config, device, seed=seed)
    closer = None
    if config.loop.enabled:
        from .loop.closing import LoopCloser

        closer = LoopCloser(config, device, seed=seed)
    return _MapperSide(mapper, closer, out_dir, emit_meshes)


def _mesh_arrays(submap, resolution: int):
    """The submap's mesh in its own frame: (V, 3) float32 vertices, (F, 3) int32, (V, 3) uint8."""
    from .mesh import extract_submap_mesh

    mesh = extract_submap_mesh(submap, resolution)
    verts = np.asarray(mesh.vertices, dtype=np.float32)
    return verts, np.asarray(mesh.faces, dtype=np.int32), np.asarray(mesh.visual.vertex_colors)[:, :3].astype(np.uint8)


def map_update_event(mapper: Mapper, submap, with_mesh: bool) -> MapUpdateEvent:
    verts = faces = colors = None
    if with_mesh:
        verts, faces, colors = _mesh_arrays(submap, mapper.config.mesh.resolution)
    return MapUpdateEvent(
        map_id=submap.map_id, version=mapper.version,
        T_world_map=submap.T_world_map.detach().cpu().numpy().astype(np.float64),
        num_voxels=submap.voxels.num_voxels,
        keyframe_poses=_keyframe_poses(submap),
        mesh_vertices=verts, mesh_faces=faces, mesh_colors=colors)


def poses_event(mapper: Mapper, reason: str) -> PosesUpdatedEvent:
    maps = mapper.maps.maps
    return PosesUpdatedEvent(
        map_poses={m.map_id: m.T_world_map.detach().cpu().numpy().astype(np.float64) for m in maps},
        keyframe_poses={m.map_id: _keyframe_poses(m) for m in maps},
        agents={m.map_id: m.agent for m in maps}, reason=reason,
        keyframe_indices={m.map_id: [kf.frame_index for kf in m.keyframes] for m in maps})


def _keyframe_poses(submap) -> np.ndarray:
    """(K, 4, 4) float64 keyframe poses of a submap in its frame."""
    if not submap.keyframes:
        return np.zeros((0, 4, 4))
    return torch.stack([kf.T_map_cam for kf in submap.keyframes]).detach().cpu().numpy().astype(np.float64)


def map_poses(mapper: Mapper) -> dict[int, np.ndarray]:
    return {m.map_id: m.T_world_map.detach().cpu().numpy().astype(np.float64) for m in mapper.maps.maps}


def _save_map(side: _MapperSide) -> None:
    from .checkpoint import save_checkpoint

    save_checkpoint(side.mapper.maps, side.out_dir / "map.pt", extra={"version": side.mapper.version})


def _integrate(side: _MapperSide, msg: FrameMessage, optimize: bool) -> list[Reply]:
    """Integrate one tracked frame into its agent's active map, as the paper's mapper does:
    the mapper decides whether it becomes a keyframe; a keyframe is announced and looked for
    loops; then the map's updates for the viewers and the checkpoint when one is due."""
    t0 = time.perf_counter()
    mapper = side.mapper
    m = mapper.config.mapping
    # Live: a map's first frame gets a window's iterations now, so that the tracker has a
    # map at once; the rest follow in steps, each one published (_pay_first_frames).
    first_iterations = min(m.iterations, m.first_frame_iterations) if mapper.config.runtime.live else None
    step = mapper.process(_tracked_frame(mapper, msg), optimize=optimize, first_iterations=first_iterations)
    if step.started_map is not None and first_iterations is not None and optimize \
            and m.first_frame_iterations > first_iterations:
        side.first_frame_debt[step.map_id] = m.first_frame_iterations - first_iterations
    out: list[Reply] = []
    if step.T_map_cam is not None:
        out.append(FramePose(msg.agent, step.frame_index, step.map_id,
                             step.T_map_cam.detach().cpu().numpy().astype(np.float64)))
    if msg.covariance is not None:
        side.odometry_covariance[msg.agent] = side.odometry_covariance.get(msg.agent, 0.0) + msg.covariance
    submap = mapper.active[msg.agent]
    if step.is_keyframe:
        out += _new_keyframe(side, msg, step, submap)
    with mapper.timer.stage("publish"):
        out += _map_updates(side, step, submap)
    with mapper.timer.stage("checkpoint"):
        _checkpoint_if_due(side)
    side.busy += time.perf_counter() - t0
    side.frames_integrated += 1
    return out


def _tracked_frame(mapper: Mapper, msg: FrameMessage) -> TrackedFrame:
    """The mapper's view of a tracked frame: on its device, placed in the world by its map's
    pose now (or the pose of the map it starts)."""
    tf = msg.prepared
    if tf is None:
        tf = prepare_frame(msg.frame, None, mapper.device, mapper.config.voxel.max_depth)
    new_map = None
    if msg.new_map is not None:
        start = msg.new_map
        new_map = NewMap(start.reason, start.map_id, torch.from_numpy(np.asarray(start.T_world_map, np.float32)))
    T_map_cam = torch.from_numpy(np.asarray(msg.T_map_cam, np.float32)).to(mapper.device)
    if new_map is not None and new_map.map_id == msg.map_id:
        T_world_cam = new_map.T_world_map.to(mapper.device) @ T_map_cam
    else:
        T_world_cam = mapper.maps.by_id(msg.map_id).T_world_map @ T_map_cam
    return TrackedFrame(tf, T_world_cam, msg.tracking_ok, msg.agent, new_map)


def _new_keyframe(side: _MapperSide, msg: FrameMessage, step: MappingStep, submap: "SubMap") -> list[Reply]:
    """The frame just integrated became ``submap``'s newest keyframe: its odometry
    uncertainty (the frames since the camera's previous keyframe), its event, and loop
    detection for it."""
    summed = side.odometry_covariance.pop(msg.agent, None)
    keyframe = submap.keyframes[-1]
    keyframe.odometry_covariance = None if summed is None else np.asarray(summed, np.float64)
    kf_pose = keyframe.T_map_cam.detach().cpu().numpy().astype(np.float64)
    out: list[Reply] = [EventReply(KeyframeEvent(msg.agent, step.frame_index, submap.map_id, kf_pose))]
    side.keyframes_since_mesh += 1
    side.keyframes_since_checkpoint += 1
    if side.closer is not None:
        with side.mapper.timer.stage("loop_detection"):
            out += _close_loops(side, side.closer, submap, msg)
    return out


def _map_updates(side: _MapperSide, step: MappingStep, submap: "SubMap") -> list[Reply]:
    """The viewers' update of ``submap``: with its mesh for a new map and every
    ``mesh.update_every_keyframes`` keyframes (when meshes are wanted), else at a keyframe
    without."""
    every = side.mapper.config.mesh.update_every_keyframes
    if side.emit_meshes and (step.started_map is not None or side.keyframes_since_mesh >= every):
        side.keyframes_since_mesh = 0
        return [EventReply(map_update_event(side.mapper, submap, with_mesh=True))]
    if step.is_keyframe:
        return [EventReply(map_update_event(side.mapper, submap, with_mesh=False))]
    return []


def _checkpoint_if_due(side: _MapperSide) -> None:
    """``map.pt`` every ``runtime.checkpoint_every_keyframes`` keyframes."""
    every = side.mapper.config.runtime.checkpoint_every_keyframes
    if every > 0 and side.keyframes_since_checkpoint >= every:
        side.keyframes_since_checkpoint = 0
        _save_map(side)


def _close_loops(side: _MapperSide, closer: "LoopCloser", submap: "SubMap", msg: FrameMessage) -> list[Reply]:
    """Loop detection for the keyframe just added to ``submap``; for an accepted loop the
    events, the new map poses and fresh snapshots of every active map."""
    mapper = side.mapper
    closures = closer.add_keyframe(mapper, submap, submap.keyframes[-1], msg.frame, features=msg.features)
    if not closures:
        return []
    # Poses first, so that a viewer already holds the moved maps when it draws the edge.
    mapper.version += 1
    out: list[Reply] = [MapPosesReply(map_poses(mapper)), EventReply(poses_event(mapper, "loop"))]
    out += [EventReply(c) for c in closures]
    out += [SnapshotReply(side.snapshot(active)) for active in mapper.active.values()]
    if side.emit_meshes:
        moved = {c.map_id for c in closures} | {c.match_map for c in closures}
        for map_id in sorted(moved):
            out.append(EventReply(map_update_event(mapper, mapper.maps.by_id(map_id), with_mesh=True)))
    return out


def _keyframe_records(mapper: Mapper) -> list[KeyframeRecord]:
    """Every keyframe's map and world pose, map by map."""
    records: list[KeyframeRecord] = []
    for submap in mapper.maps.maps:
        poses = mapper.keyframe_poses_world(submap).numpy()
        for kf, T in zip(submap.keyframes, poses):
            records.append(KeyframeRecord(submap.agent, kf.frame_index, submap.map_id, T.reshape(-1).tolist()))
    return records


def _stats(side: _MapperSide) -> MapperStats:
    mapper = side.mapper
    records = _keyframe_records(mapper)
    maps = mapper.maps.maps
    closer = side.closer
    return MapperStats(
        mapper.maps.num_keyframes(), len(maps), mapper.maps.num_voxels(),
        sum(m.voxels.embeddings.numel() * 4 for m in maps), sum(m.decoder.num_bytes() for m in maps),
        side.busy, dict(mapper.timer.totals), records, map_poses(mapper),
        {m.map_id: m.agent for m in maps}, mapper.maps.groups(), {m.map_id: m.reason for m in maps},
        closer.closures_json() if closer is not None else [],
        list(closer.candidates) if closer is not None else [],
        closer.rejected if closer is not None else 0,
        closer.timings_ms() if closer is not None else {},
        side.refinement, side.keyframe_graph,
        sum(m.fine.num_bytes() for m in maps if m.fine is not None))


def final_budget(mapping, keyframes: int, elapsed: float) -> FinalBudget:
    """The final bundle adjustment's budget for a run of ``keyframes`` keyframes that has taken
    ``elapsed`` seconds so far (``MappingConfig.final_*``)."""
    iterations = mapping.final_iterations
    if mapping.final_iterations_per_keyframe > 0:
        iterations = min(iterations, mapping.final_iterations_per_keyframe * keyframes)
    seconds = None
    if mapping.final_time_share > 0:
        seconds = max(mapping.final_min_seconds, mapping.final_time_share * elapsed)
    return FinalBudget(max(iterations, 0), seconds)


def final_iterations_per_map(keyframes: list[int], total: int) -> list[int]:
    """The end-of-run global bundle adjustment's iterations shared among maps by keyframe
    count (each map with keyframes gets at least a fifth of ``total``, capped at ``total``),
    so that the refinement covers every map at about the cost of one map's."""
    n = sum(keyframes)
    if n == 0 or total <= 0:
        return [0] * len(keyframes)
    floor = max(1, total // 5)
    return [0 if k == 0 else min(total, max(floor, round(total * k / n))) for k in keyframes]


def _finish(side: _MapperSide, refine: bool) -> Iterator[Reply]:
    """Final outputs, replies yielded as they are ready: the global bundle adjustment of every
    map (``refine``; a stopped run skips it to stop promptly) and the keyframe pose graph; the
    maps as they left them (``FinalMaps``, when the tracking side re-tracks its frames:
    ``tracking.retrack_iterations``), then the fine colour fit, checkpoint and mesh, then the
    statistics (the last reply)."""
    mapper = side.mapper
    if mapper.maps.maps:
        if refine:  # each step says it starts, so a client sees which one runs (PhaseEvent)
            yield EventReply(PhaseEvent("refining", "bundle_adjustment", _bundle_adjustment_estimate(side)))
        side.refinement, refined = _final_bundle_adjustment(side, refine)
        if refine and side.closer is not None:
            # After the bundle adjustment: its keyframe poses are the odometry the graph keeps.
            solved = side.closer.optimise_keyframes(mapper)
            if solved is not None:
                side.keyframe_graph = solved.summary()
                mapper.version += 1
        if refine and mapper.config.tracking.retrack_iterations > 0:
            yield _final_maps(side)
        if refined and mapper.config.fine_color.final_fit_iterations > 0 and any(s.fine is not None for s in refined):
            yield EventReply(PhaseEvent("refining", "colour_fit"))
        for submap in refined:
            t0 = time.perf_counter()
            mapper.fit_final_colour(submap)
            side.busy += time.perf_counter() - t0
        if refine:
            yield EventReply(PhaseEvent("refining", "mesh"))
        _write_final_map(side)
        yield EventReply(poses_event(mapper, "refinement"))
        if side.emit_meshes:
            for submap in mapper.maps.maps:
                yield EventReply(map_update_event(mapper, submap, with_mesh=True))
    yield Done(_stats(side))


def _final_maps(side: _MapperSide) -> FinalMaps:
    """Every map's snapshot, pose and keyframe poses after the final refinement."""
    mapper = side.mapper
    return FinalMaps([side.snapshot(m) for m in mapper.maps.maps], map_poses(mapper), _keyframe_records(mapper))


def _bundle_adjustment_estimate(side: _MapperSide) -> float | None:
    """The final bundle adjustment's time cap in seconds (``final_budget``), None without one."""
    mapper = side.mapper
    if mapper.config.runtime.deterministic:
        return None  # an iteration count, not a time cap (``_final_bundle_adjustment``)
    elapsed = time.perf_counter() - side.started
    seconds = final_budget(mapper.config.mapping, mapper.maps.num_keyframes(), elapsed).seconds
    return None if seconds is None else round(seconds, 1)


def _final_bundle_adjustment(side: _MapperSide, refine: bool) -> tuple[FinalRefinement, list["SubMap"]]:
    """The global bundle adjustment of every map within ``final_budget`` (no iterations
    unless ``refine``), its iterations shared among the maps by keyframes; with the maps it
    refined (their fine colour level is fitted next, ``Mapper.fit_final_colour``)."""
    mapper = side.mapper
    m = mapper.config.mapping
    t0 = time.perf_counter()
    maps = mapper.maps.maps
    budget = final_budget(m, mapper.maps.num_keyframes(), t0 - side.started)
    runtime = mapper.config.runtime
    if runtime.deterministic and budget.seconds is not None:
        # A time cap would make the result depend on load: an iteration count instead.
        budget = FinalBudget(min(budget.iterations, runtime.deterministic_final_iterations), None)
    shares = final_iterations_per_map([len(s.keyframes) for s in maps], budget.iterations if refine else 0)
    ran = 0
    for submap, iterations in zip(maps, shares):
        # Each map gets the share of the time that it gets of the iterations.
        deadline = (None if budget.seconds is None or not sum(shares)
                    else time.perf_counter() + budget.seconds * iterations / sum(shares))
        mapper.global_bundle_adjustment(submap, iterations, m.final_rays, deadline=deadline, fit_colour=False)
        ran += mapper.last_iterations  # 0 when it had nothing to do
    mapper.version += 1
    seconds = time.perf_counter() - t0
    side.busy += seconds
    mapper.timer.add("final_bundle_adjustment", seconds)
    refined = [submap for submap, iterations in zip(maps, shares) if iterations > 0 and submap.keyframes]
    return FinalRefinement(sum(shares), ran, seconds, budget.seconds, ran < sum(shares)), refined


def _write_final_map(side: _MapperSide) -> None:
    """``map.pt`` and ``mesh.ply`` of every map."""
    from .mesh import export_mesh, extract_mesh

    t0 = time.perf_counter()
    _save_map(side)
    export_mesh(extract_mesh(side.mapper.maps), side.out_dir / "mesh.ply")
    side.mapper.timer.add("final_outputs", time.perf_counter() - t0)


def _queued(frames: "queue.Queue") -> int:
    """Items in a multiprocessing queue (1 where the platform cannot count, e.g. macOS:
    the caller then drains until a get times out)."""
    try:
        return frames.qsize()
    except NotImplementedError:
        return 1


def _integrate_batch(side: _MapperSide, work: list[FrameMessage]) -> list[Reply]:
    """Integrate every frame; optimise once per agent, with its newest frame; snapshots of
    the maps that changed."""
    last = {msg.agent: i for i, msg in enumerate(work)}
    out: list[Reply] = []
    for i, msg in enumerate(work):
        out += _integrate(side, msg, optimize=last[msg.agent] == i and msg.optimize)
    for agent in sorted(last):
        out.append(SnapshotReply(side.snapshot(side.mapper.active[agent])))
    return out


def _pay_first_frames(side: _MapperSide) -> list[Reply]:
    """Live mode: one more step of the first owed map's first-frame iterations (a window's
    worth), and its snapshot. Only called while ``side.first_frame_debt`` holds a map."""
    map_id, owed = next(iter(side.first_frame_debt.items()))
    submap = next((s for s in side.mapper.active.values() if s.map_id == map_id), None)
    step = min(owed, side.mapper.config.mapping.iterations)
    if owed == step or submap is None:
        del side.first_frame_debt[map_id]
    else:
        side.first_frame_debt[map_id] = owed - step
    if submap is None:
        return []  # the map is no longer active: its frames map it now
    t0 = time.perf_counter()
    side.mapper.optimize(submap, step)
    side.mapper.version += 1
    side.busy += time.perf_counter() - t0
    return [SnapshotReply(side.snapshot(submap))]


def _idle_step(side: _MapperSide, frame_waiting: Callable[[], bool]) -> list[Reply]:
    """Nothing queued: keep optimising the active maps (the paper's mapper never idles), so
    the tracker gets a better map by the time the next frame arrives; a frame that arrives
    meanwhile stops the step, rather than wait for it and reach the tracker's map later."""
    mapper = side.mapper
    t0 = time.perf_counter()
    out: list[Reply] = []
    for submap in list(mapper.active.values()):
        mapper.optimize(submap, mapper.config.mapping.iterations, interrupted=frame_waiting)
        mapper.version += 1
        out.append(SnapshotReply(side.snapshot(submap)))
    seconds = time.perf_counter() - t0
    side.busy += seconds
    mapper.timer.add("idle_optimisation", seconds)
    return out


LIVE_NICENESS = 10
"""``runtime.live``: the mapping process's niceness (Linux: 0 normal, 19 lowest): the tracker and
the server, which take frames at the camera's rate, come first; the mapper takes what is left."""


def _lower_priority() -> None:
    try:
        os.nice(LIVE_NICENESS)
    except (AttributeError, OSError):  # no os.nice (Windows), or not allowed: mapping as usual
        pass


def _warm_up() -> None:
    """Pay the first call's imports and compiles before the first frame comes, not inside
    its mapping (which the tracker waits for): numba's kernels from their cache, and torch's
    optimiser machinery, whose first Adam imports the compiler stack (decisions.md#optimizers)."""
    from . import kernels
    from .optimizers import adam

    kernels.warm_up()
    scratch = torch.nn.Parameter(torch.zeros(8))
    scratch.grad = torch.ones(8)
    adam([scratch]).step()


def _next_batch(frames: "queue.Queue", first: Request, config: SLAMConfig) -> list[Request]:
    """``first`` and what queued up behind it while the mapper optimised (integrate all,
    optimise once). qsize counts frames still in the queue's pipe, which get_nowait would
    miss. At most what was queued when we looked: a producer faster than us would otherwise
    keep this loop draining forever. Deterministic mode takes one frame at a time."""
    batch = [first]
    waiting = 0 if config.runtime.deterministic else _queued(frames)
    while not isinstance(batch[-1], EndOfInput) and waiting > 0 and len(batch) <= config.runtime.queue_size + 1:
        waiting -= 1
        try:
            batch.append(frames.get(timeout=_POLL_SECONDS))
        except queue.Empty:
            break
    return batch


def _mapping_process(config_dict: dict, device_name: str, out_dir: str, emit_meshes: bool,
                     frames: "queue.Queue", replies: "queue.Queue", seed: int) -> None:
    """Entry point of the mapping process: mapper loop until an ``EndOfInput``."""
    import multiprocessing as mp

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is handled by the tracking side
    try:
        config = config_from_dict(config_dict)
        device = torch.device(device_name)
        process_threads(device, processes=True)
        if config.runtime.live:
            _lower_priority()
        side = _make_side(config, device, Path(out_dir), emit_meshes, seed)
        replies.put(Ready())
        _warm_up()
        parent = mp.parent_process()
        while True:
            if parent is not None and not parent.is_alive():
                # The tracking side was killed: nobody will read our outputs, and flushing
                # the reply pipe at exit would block this process forever.
                replies.cancel_join_thread()
                return
            if side.first_frame_debt:
                for reply in _pay_first_frames(side):
                    replies.put(reply)
                continue
            idle_steps = side.mapper.active and not config.runtime.deterministic
            try:
                first = frames.get(timeout=0 if idle_steps else _POLL_SECONDS)
            except queue.Empty:
                for reply in _idle_step(side, lambda: not frames.empty()) if idle_steps else ():
                    replies.put(reply)
                continue
            batch = _next_batch(frames, first, config)
            work = [m for m in batch if isinstance(m, FrameMessage)]
            for reply in _integrate_batch(side, work) if work else []:
                replies.put(reply)
            end = batch[-1]
            if isinstance(end, EndOfInput):
                # The tracker has no frames left: the final bundle adjustment and the mesh
                # take every core (decisions.md#mapping.final_iterations).
                process_threads(device, processes=False)
                for reply in _finish(side, refine=end.refine):
                    replies.put(reply)
                    if isinstance(reply, FinalMaps):
                        # The tracker re-tracks its frames meanwhile: share the cores again, or
                        # the two sides slow each other (decisions.md#tracking.retrack_iterations).
                        process_threads(device, processes=True)
                return
    except BaseException:  # noqa: BLE001 - reported to the tracking side, which fails the run
        replies.put(Failed(traceback.format_exc()))


# ---------------------------------------------------------- mapper channels
class InlineMapper:
    """The mapping side in this process (``processes=False``)."""

    def __init__(self, config: SLAMConfig, device: torch.device, out_dir: Path, emit_meshes: bool, seed: int):
        self.side = _make_side(config, device, out_dir, emit_meshes, seed)
        self.pending: list[Reply] = []

    def submit(self, msg: FrameMessage) -> None:
        self.pending += _integrate_batch(self.side, [msg])
        while self.side.first_frame_debt:  # no loop here to pay a live first frame later
            self.pending += _pay_first_frames(self.side)

    def offer(self, msg: FrameMessage) -> bool:
        """``submit`` without waiting: in this process there is always room."""
        self.submit(msg)
        return True

    def poll(self, block: bool = False) -> list[Reply]:
        out, self.pending = self.pending, []
        return out

    def finish(self, refine: bool = True) -> Iterator[Reply]:
        """The replies still pending, then the end of run's as they come (``_finish``)."""
        yield from self.poll()
        yield from _finish(self.side, refine)

    def close(self) -> None:
        pass


class ProcessMapper:
    """The mapping side in a spawned process, behind a bounded frame queue."""

    def __init__(self, config: SLAMConfig, device: torch.device, out_dir: Path, emit_meshes: bool, seed: int):
        import multiprocessing as mp

        ctx = mp.get_context("spawn")
        self.frames = ctx.Queue(maxsize=max(1, config.runtime.queue_size))
        self.replies = ctx.Queue()
        self.process = ctx.Process(
            target=_mapping_process, name="voxfusion-mapping",
            args=(config.to_dict(), str(device), str(out_dir), emit_meshes, self.frames, self.replies, seed))
        self.process.start()
        self._early: list[Reply] = []
        self._wait_for_ready(_STARTUP_TIMEOUT)

    def _get(self, timeout: float) -> Reply | None:
        try:
            return self.replies.get(timeout=timeout)
        except queue.Empty:
            if not self.process.is_alive():
                # Drain anything it managed to send before dying.
                try:
                    return self.replies.get_nowait()
                except queue.Empty:
                    raise MapperFailed(f"the mapping process died (exit code {self.process.exitcode})") from None
            return None

    def _wait_for_ready(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            reply = self._get(_POLL_SECONDS)
            if isinstance(reply, Failed):
                raise MapperFailed(reply.traceback)
            if isinstance(reply, Ready):
                return
            if reply is not None:
                self._early.append(reply)
        raise MapperFailed(f"the mapping process did not answer 'ready' within {timeout:.0f} s")

    def submit(self, msg: Request) -> None:
        msg = self._portable(msg)
        while True:
            try:
                self.frames.put(msg, timeout=_POLL_SECONDS)
                return
            except queue.Full:
                if not self.process.is_alive():
                    self._raise_dead()
                # While we wait, read what the mapper sent: a mapper that failed is flushing
                # its traceback at exit and would wait for us forever.
                self._early += self.poll()
                for reply in self._early:
                    if isinstance(reply, Failed):
                        raise MapperFailed(reply.traceback)

    def offer(self, msg: FrameMessage) -> bool:
        """``submit`` if the queue has room now; False (nothing sent) if it has none."""
        if not self.process.is_alive():
            self._raise_dead()
        try:
            self.frames.put_nowait(self._portable(msg))
            return True
        except queue.Full:
            return False

    @staticmethod
    def _portable(msg: Request) -> Request:
        if isinstance(msg, FrameMessage) and msg.prepared is not None:
            # Tensors pickle as shared-memory files: re-preparing them there is cheaper.
            return replace(msg, prepared=None)
        return msg

    def _raise_dead(self) -> None:
        """The mapping process is gone: raise with its traceback if it sent one."""
        while True:
            try:
                reply = self.replies.get(timeout=_POLL_SECONDS)
            except queue.Empty:
                break
            if isinstance(reply, Failed):
                raise MapperFailed(reply.traceback)
        raise MapperFailed(f"the mapping process died (exit code {self.process.exitcode})")

    def poll(self, block: bool = False) -> list[Reply]:
        out, self._early = self._early, []
        reply = self._get(_POLL_SECONDS) if block else None
        if reply is not None:
            out.append(reply)
        while True:
            try:
                out.append(self.replies.get_nowait())
            except queue.Empty:
                return out

    def finish(self, refine: bool = True) -> Iterator[Reply]:
        """Ends the input; yields the replies as they arrive, up to ``Done`` or ``Failed`` (so
        the caller can act on ``FinalMaps`` while the mapping process writes its outputs)."""
        self.submit(EndOfInput(refine))
        early, self._early = self._early, []
        yield from early
        while True:
            reply = self._get(_POLL_SECONDS)
            if reply is None:
                continue
            yield reply
            if isinstance(reply, (Done, Failed)):
                return

    def close(self) -> None:
        if self.process.is_alive():
            try:  # a mapper still waiting for frames (the run failed early) gets its sentinel
                self.frames.put_nowait(END_NOW)
            except queue.Full:
                pass
        self.process.join(timeout=10)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(timeout=5)
        # Frames still buffered for a reader that is gone would block this process's exit.
        self.frames.cancel_join_thread()
