"""The mapping side of the runtime: the mapper and the loop closer behind a frame queue.

For every tracked frame the mapping side integrates it into its agent's active map
(``slam.mapping.Mapper``); for every new keyframe the loop closer (``slam.loop.closing``)
runs the appearance check, geometric verification and, for an accepted loop, the
hierarchical pose optimisation. It answers with map snapshots (by version), events, map
poses after a loop, frame poses the window refined (``FramePose``), and at the end the
statistics. At the end of a sequence every map gets its global bundle adjustment before the
mesh and checkpoint are written.

``_ProcessMapper`` runs all of this in a spawned process fed by a bounded queue
(back-pressure instead of unbounded lag); ``_InlineMapper`` runs it in the caller
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
from typing import Callable

import numpy as np
import torch

from .config import SLAMConfig, config_from_dict
from .data.frame import Frame
from .events import KeyframeEvent, MapUpdateEvent, PosesUpdatedEvent
from .frames import prepare_frame
from .mapping import Mapper, MapSnapshot, NewMap, TrackedFrame

_POLL_SECONDS = 0.2
END = None
"""Frame-queue sentinel: the sequence ended; refine globally, then write the outputs."""
END_NOW = "end-now"
"""Frame-queue sentinel: the run was stopped; write the outputs without the refinement."""
_STARTUP_TIMEOUT = 300.0

Reply = tuple[str, object]


class MapperFailed(RuntimeError):
    """The mapping process raised or died; the message carries its traceback."""


def set_threads(device: torch.device, processes: bool) -> None:
    """Two busy processes on a small CPU: give each its share of cores (oversubscribed torch
    threads spin and slow everything down several times)."""
    if device.type == "cpu":
        import cv2

        n = os.cpu_count() or 1
        threads = max(1, n // 2) if processes else n
        torch.set_num_threads(threads)
        cv2.setNumThreads(threads)  # ORB matching (slam.features) and loop verification


# ----------------------------------------------------------------- messages
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
    new_map: tuple[str, int, np.ndarray] | None = None
    """(reason, map id, T_world_map) of a map this frame starts."""
    covariance: np.ndarray | None = None
    """(6, 6) the tracker's uncertainty of this frame's pose (``keyframe_graph.frame_covariance``)."""
    optimize: bool = True
    """Run the windowed optimisation after integrating it (deterministic mode integrates some
    frames only, as a free-running mapper optimises once per batch of queued frames)."""


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
class KeyframeRecord:
    """A keyframe's final pose for the outputs: its map and world pose (4, 4) as 16 numbers."""

    agent: int
    frame_index: int
    map_id: int
    T_world_cam: list[float]


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
    refinement: "FinalRefinement | None" = None
    """What the end-of-run global bundle adjustment did (None before it ran)."""
    keyframe_graph: dict | None = None
    """What the end-of-run keyframe pose graph did (``KeyframeGraphResult.summary``; None
    when it did not run: no verified loop, loops off, or a stopped run)."""


@dataclass(frozen=True)
class FinalBudget:
    """The end-of-run global bundle adjustment's budget: iterations over all maps, and
    seconds (None: no time cap)."""

    iterations: int
    seconds: float | None


@dataclass(frozen=True)
class FinalRefinement:
    """What the final bundle adjustment did: iterations asked and run, seconds, and whether
    its time cap stopped it."""

    iterations_budget: int
    iterations_run: int
    seconds: float
    seconds_budget: float | None
    stopped_by_time: bool


@dataclass
class _MapperSide:
    """The mapper, the loop closer and the output policy of the mapping side."""

    mapper: Mapper
    closer: "object | None"
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


def _world_mesh_arrays(submap, resolution: int):
    from .mesh import extract_submap_mesh

    mesh = extract_submap_mesh(submap, resolution)
    T = submap.T_world_map.detach().cpu().numpy().astype(np.float64)
    verts = (np.asarray(mesh.vertices) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
    return verts, np.asarray(mesh.faces, dtype=np.int32), np.asarray(mesh.visual.vertex_colors)[:, :3].astype(np.uint8)


def map_update_event(mapper: Mapper, submap, with_mesh: bool) -> MapUpdateEvent:
    verts = faces = colors = None
    if with_mesh:
        verts, faces, colors = _world_mesh_arrays(submap, mapper.config.mesh.resolution)
    return MapUpdateEvent(
        map_id=submap.map_id, version=mapper.version,
        T_world_map=submap.T_world_map.detach().cpu().numpy().astype(np.float64),
        num_voxels=submap.voxels.num_voxels,
        keyframe_poses=mapper.keyframe_poses_world(submap).numpy().astype(np.float64),
        mesh_vertices=verts, mesh_faces=faces, mesh_colors=colors)


def poses_event(mapper: Mapper, reason: str) -> PosesUpdatedEvent:
    maps = mapper.maps.maps
    return PosesUpdatedEvent(
        map_poses={m.map_id: m.T_world_map.detach().cpu().numpy().astype(np.float64) for m in maps},
        keyframe_poses={m.map_id: mapper.keyframe_poses_world(m).numpy().astype(np.float64) for m in maps},
        agents={m.map_id: m.agent for m in maps}, reason=reason,
        keyframe_indices={m.map_id: [kf.frame_index for kf in m.keyframes] for m in maps})


def map_poses(mapper: Mapper) -> dict[int, np.ndarray]:
    return {m.map_id: m.T_world_map.detach().cpu().numpy().astype(np.float64) for m in mapper.maps.maps}


def _save_map(side: _MapperSide) -> None:
    from .checkpoint import save_checkpoint

    save_checkpoint(side.mapper.maps, side.out_dir / "map.pt", extra={"version": side.mapper.version})


def _integrate(side: _MapperSide, msg: FrameMessage, optimize: bool) -> list[Reply]:
    """Integrate one tracked frame (and close loops at a new keyframe); returns the replies."""
    t0 = time.perf_counter()
    mapper = side.mapper
    tf = prepare_frame(msg.frame, None, mapper.device, mapper.config.voxel.max_depth)
    new_map = None
    if msg.new_map is not None:
        reason, map_id, T_wm = msg.new_map
        new_map = NewMap(reason, map_id, torch.from_numpy(np.asarray(T_wm, np.float32)))
    T_map_cam = torch.from_numpy(np.asarray(msg.T_map_cam, np.float32)).to(mapper.device)
    if new_map is not None and new_map.map_id == msg.map_id:
        T_world_cam = new_map.T_world_map.to(mapper.device) @ T_map_cam
    else:
        T_world_cam = mapper.maps.by_id(msg.map_id).T_world_map @ T_map_cam
    step = mapper.process(TrackedFrame(tf, T_world_cam, msg.tracking_ok, msg.agent, new_map), optimize=optimize)
    out: list[Reply] = []
    if step.T_map_cam is not None:
        out.append(("frame_pose", FramePose(msg.agent, step.frame_index, step.map_id,
                                            step.T_map_cam.detach().cpu().numpy().astype(np.float64))))
    submap = mapper.active[msg.agent]
    cfg = mapper.config
    if msg.covariance is not None:
        side.odometry_covariance[msg.agent] = side.odometry_covariance.get(msg.agent, 0.0) + msg.covariance
    if step.is_keyframe:
        # The frames since the camera's previous keyframe: this keyframe's odometry uncertainty.
        summed = side.odometry_covariance.pop(msg.agent, None)
        submap.keyframes[-1].odometry_covariance = None if summed is None else np.asarray(summed, np.float64)
        kf_pose = (submap.T_world_map @ submap.keyframes[-1].T_map_cam).detach().cpu().numpy()
        out.append(("event", KeyframeEvent(msg.agent, step.frame_index, submap.map_id, kf_pose.astype(np.float64))))
        side.keyframes_since_mesh += 1
        side.keyframes_since_checkpoint += 1
        if side.closer is not None:
            out += _close_loops(side, submap, msg.frame)
    if side.emit_meshes and (step.started_map is not None or side.keyframes_since_mesh >= cfg.mesh.update_every_keyframes):
        side.keyframes_since_mesh = 0
        out.append(("event", map_update_event(mapper, submap, with_mesh=True)))
    elif step.is_keyframe:
        out.append(("event", map_update_event(mapper, submap, with_mesh=False)))
    every = cfg.runtime.checkpoint_every_keyframes
    if every > 0 and side.keyframes_since_checkpoint >= every:
        side.keyframes_since_checkpoint = 0
        _save_map(side)
    side.busy += time.perf_counter() - t0
    side.frames_integrated += 1
    return out


def _close_loops(side: _MapperSide, submap, frame: Frame) -> list[Reply]:
    """Loop detection for the keyframe just added to ``submap``; for an accepted loop the
    events, the new map poses and fresh snapshots of every active map."""
    mapper = side.mapper
    closures = side.closer.add_keyframe(mapper, submap, submap.keyframes[-1], frame)  # type: ignore[union-attr]
    out: list[Reply] = []
    if closures:
        # Poses first, so that a viewer already holds the moved maps when it draws the edge.
        mapper.version += 1
        out.append(("map_poses", map_poses(mapper)))
        out.append(("event", poses_event(mapper, "loop")))
    out += [("event", c) for c in closures]
    if closures:
        for active in mapper.active.values():
            out.append(("snapshot", side.snapshot(active)))
        if side.emit_meshes:
            moved = {c.map_id for c in closures} | {c.match_map for c in closures}
            for map_id in sorted(moved):
                out.append(("event", map_update_event(mapper, mapper.maps.by_id(map_id), with_mesh=True)))
    return out


def _stats(side: _MapperSide) -> MapperStats:
    mapper = side.mapper
    records: list[KeyframeRecord] = []
    for submap in mapper.maps.maps:
        poses = mapper.keyframe_poses_world(submap).numpy()
        for kf, T in zip(submap.keyframes, poses):
            records.append(KeyframeRecord(submap.agent, kf.frame_index, submap.map_id, T.reshape(-1).tolist()))
    maps = mapper.maps.maps
    closer = side.closer
    return MapperStats(
        mapper.maps.num_keyframes(), len(maps), mapper.maps.num_voxels(),
        sum(m.voxels.embeddings.numel() * 4 for m in maps), sum(m.decoder.num_bytes() for m in maps),
        side.busy, dict(mapper.timer.totals), records, map_poses(mapper),
        {m.map_id: m.agent for m in maps}, mapper.maps.groups(), {m.map_id: m.reason for m in maps},
        closer.closures_json() if closer is not None else [],  # type: ignore[union-attr]
        list(closer.candidates) if closer is not None else [],  # type: ignore[union-attr]
        closer.rejected if closer is not None else 0,  # type: ignore[union-attr]
        closer.timings_ms() if closer is not None else {},  # type: ignore[union-attr]
        side.refinement, side.keyframe_graph)


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


def _finish(side: _MapperSide, refine: bool) -> list[Reply]:
    """Final outputs: the global bundle adjustment of every map (``refine``; a stopped run
    skips it to stop promptly), checkpoint and mesh, then the statistics."""
    from .mesh import export_mesh, extract_mesh

    mapper = side.mapper
    out: list[Reply] = []
    if mapper.maps.maps:
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
            mapper.global_bundle_adjustment(submap, iterations, m.final_rays, deadline=deadline)
            ran += mapper.last_iterations  # 0 when it had nothing to do
        mapper.version += 1
        seconds = time.perf_counter() - t0
        side.busy += seconds
        mapper.timer.add("final_bundle_adjustment", seconds)
        side.refinement = FinalRefinement(sum(shares), ran, seconds, budget.seconds, ran < sum(shares))
        if refine and side.closer is not None:
            # After the bundle adjustment: its keyframe poses are the odometry the graph keeps.
            solved = side.closer.optimise_keyframes(mapper)  # type: ignore[union-attr]
            if solved is not None:
                side.keyframe_graph = solved.summary()
                mapper.version += 1
        t0 = time.perf_counter()
        _save_map(side)
        export_mesh(extract_mesh(mapper.maps), side.out_dir / "mesh.ply")
        mapper.timer.add("final_outputs", time.perf_counter() - t0)
        out.append(("event", poses_event(mapper, "refinement")))
        if side.emit_meshes:
            for submap in maps:
                out.append(("event", map_update_event(mapper, submap, with_mesh=True)))
    out.append(("done", _stats(side)))
    return out


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
        out.append(("snapshot", side.snapshot(side.mapper.active[agent])))
    return out


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
        out.append(("snapshot", side.snapshot(submap)))
    side.busy += time.perf_counter() - t0
    return out


def _mapping_process(config_dict: dict, device_name: str, out_dir: str, emit_meshes: bool,
                     frames: "queue.Queue", replies: "queue.Queue", seed: int) -> None:
    """Entry point of the mapping process: mapper loop until an end sentinel."""
    import multiprocessing as mp

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is handled by the tracking side
    try:
        config = config_from_dict(config_dict)
        device = torch.device(device_name)
        set_threads(device, processes=True)
        side = _make_side(config, device, Path(out_dir), emit_meshes, seed)
        replies.put(("ready", None))
        parent = mp.parent_process()
        while True:
            if parent is not None and not parent.is_alive():
                # The tracking side was killed: nobody will read our outputs, and flushing
                # the reply pipe at exit would block this process forever.
                replies.cancel_join_thread()
                return
            idle_steps = side.mapper.active and not config.runtime.deterministic
            try:
                msg = frames.get(timeout=0 if idle_steps else _POLL_SECONDS)
            except queue.Empty:
                for reply in _idle_step(side, lambda: not frames.empty()) if idle_steps else ():
                    replies.put(reply)
                continue
            batch = [msg]
            # Drain what queued up while we optimised: integrate all, optimise once. qsize
            # counts frames still in the queue's pipe, which get_nowait would miss. At most
            # what was queued when we looked: a producer faster than us would otherwise keep
            # this loop draining forever.
            waiting = 0 if config.runtime.deterministic else _queued(frames)  # one frame at a time
            while batch[-1] not in (END, END_NOW) and waiting > 0 and len(batch) <= config.runtime.queue_size + 1:
                waiting -= 1
                try:
                    batch.append(frames.get(timeout=_POLL_SECONDS))
                except queue.Empty:
                    break
            done = batch[-1] in (END, END_NOW)
            work = [m for m in batch if m not in (END, END_NOW)]
            for reply in _integrate_batch(side, work) if work else []:
                replies.put(reply)
            if done:
                # The tracker has no frames left: the final bundle adjustment and the mesh
                # take every core (2 cores: 108 -> 80 ms per global-BA iteration).
                set_threads(device, processes=False)
                for reply in _finish(side, refine=batch[-1] is END):
                    replies.put(reply)
                return
    except BaseException:  # noqa: BLE001 - reported to the tracking side, which fails the run
        replies.put(("error", traceback.format_exc()))


# ---------------------------------------------------------- mapper channels
class InlineMapper:
    """The mapping side in this process (``processes=False``)."""

    def __init__(self, config: SLAMConfig, device: torch.device, out_dir: Path, emit_meshes: bool, seed: int):
        self.side = _make_side(config, device, out_dir, emit_meshes, seed)
        self.pending: list[Reply] = []

    def submit(self, msg: FrameMessage) -> None:
        self.pending += _integrate_batch(self.side, [msg])

    def poll(self, block: bool = False) -> list[Reply]:
        out, self.pending = self.pending, []
        return out

    def finish(self, refine: bool = True) -> list[Reply]:
        return self.poll() + _finish(self.side, refine)

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
        self._wait_for("ready", _STARTUP_TIMEOUT)

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

    def _wait_for(self, kind: str, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            reply = self._get(_POLL_SECONDS)
            if reply is None:
                continue
            if reply[0] == "error":
                raise MapperFailed(str(reply[1]))
            if reply[0] == kind:
                return
            self._early.append(reply)
        raise MapperFailed(f"the mapping process did not answer '{kind}' within {timeout:.0f} s")

    def submit(self, msg: FrameMessage | None | str) -> None:
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
                for kind, payload in self._early:
                    if kind == "error":
                        raise MapperFailed(str(payload))

    def _raise_dead(self) -> None:
        """The mapping process is gone: raise with its traceback if it sent one."""
        while True:
            try:
                reply = self.replies.get(timeout=_POLL_SECONDS)
            except queue.Empty:
                break
            if reply[0] == "error":
                raise MapperFailed(str(reply[1]))
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

    def finish(self, refine: bool = True) -> list[Reply]:
        self.submit(END if refine else END_NOW)
        out: list[Reply] = list(self._early)
        self._early = []
        while True:
            reply = self._get(_POLL_SECONDS)
            if reply is None:
                continue
            out.append(reply)
            if reply[0] in ("done", "error"):
                return out

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
