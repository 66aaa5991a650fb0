"""The SLAM runtime: tracking in the calling process, mapping in its own process.

The loop reads like the paper's system overview:

    for each frame:  track against the newest map snapshot  ->  hand the tracked frame to
                     the mapper  ->  the mapper selects keyframes, allocates voxels, runs the
                     windowed joint optimisation and publishes a new snapshot

Process layout (``config.runtime.processes``): the mapper runs in a spawned process fed by a
bounded queue (back-pressure instead of unbounded lag); it answers on one queue with
snapshots (numpy arrays, by version), keyframe events, map updates (live mesh) and, at the
end, its statistics. Start-up and shutdown are handshakes on those queues and on events, not
sleeps. A mapper that dies or raises ends the run as ``failed`` with its traceback. With
``processes=False`` the same ``Mapper`` runs inline (debugging and tests).

Outputs in ``out_dir``: ``trajectory.txt`` (TUM, input timestamps), ``mesh.ply``, ``map.pt``
(rewritten atomically every few keyframes while running), ``run.json``.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import time
import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterable, Protocol

import numpy as np
import torch

from .config import SLAMConfig, config_from_dict
from .data.frame import Frame
from .data.io import resize_rgbd
from .events import (Event, FinishedEvent, KeyframeEvent, MapUpdateEvent, PoseEvent, StatsEvent,
                     SubmapEvent)
from .frames import prepare_frame
from .mapping import Mapper, MapSnapshot, TrackedFrame
from .features import FeatureOdometry
from .tracking import FrozenMap, Tracker, constant_velocity_guess

_POLL_SECONDS = 0.2
_END = None
"""Frame-queue sentinel: the sequence ended; refine globally, then write the outputs."""
_END_NOW = "end-now"
"""Frame-queue sentinel: the run was stopped; write the outputs without the refinement."""
_STARTUP_TIMEOUT = 300.0


class StopFlag(Protocol):
    def is_set(self) -> bool: ...


@dataclass(frozen=True)
class RunResult:
    status: str
    """``finished``, ``failed`` or ``cancelled``."""
    error: str | None
    frames: int
    keyframes: int
    maps: int
    loops: int
    fps: float
    out_dir: Path
    ate_rmse: float | None = None


class MapperFailed(RuntimeError):
    """The mapping process raised or died; the message carries its traceback."""


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda was asked for but CUDA is not available")
    return torch.device(name)


def _set_threads(device: torch.device, processes: bool) -> None:
    """Two busy processes on a small CPU: give each its share of cores (oversubscribed torch
    threads spin and slow everything down several times)."""
    if device.type == "cpu":
        import cv2

        n = os.cpu_count() or 1
        threads = max(1, n // 2) if processes else n
        torch.set_num_threads(threads)
        cv2.setNumThreads(threads)  # the tracker's ORB matching (slam.features)


# ----------------------------------------------------------------- messages
@dataclass(frozen=True)
class _FrameMessage:
    """A tracked frame at pipeline resolution, as plain arrays (pickles by value)."""

    frame: Frame
    T_world_cam: np.ndarray
    tracking_ok: bool


@dataclass(frozen=True)
class _MapperStats:
    keyframes: int
    maps: int
    voxels: int
    map_bytes: int
    decoder_bytes: int
    busy_seconds: float
    timings: dict[str, float]
    keyframe_poses: dict[int, list[float]]


@dataclass
class _MapperState:
    """What the mapper side needs besides the Mapper: output policy and counters."""

    out_dir: Path
    emit_meshes: bool
    keyframes_since_mesh: int = 0
    keyframes_since_checkpoint: int = 0
    busy: float = 0.0


def _map_update_event(mapper: Mapper, with_mesh: bool) -> MapUpdateEvent:
    from .mesh import extract_submap_mesh

    submap = mapper.current
    assert submap is not None
    verts = faces = colors = None
    if with_mesh:
        mesh = extract_submap_mesh(submap, mapper.config.mesh.resolution)
        T = submap.T_world_map.detach().cpu().numpy().astype(np.float64)
        verts = (np.asarray(mesh.vertices) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        faces = np.asarray(mesh.faces, dtype=np.int32)
        colors = np.asarray(mesh.visual.vertex_colors)[:, :3].astype(np.uint8)
    return MapUpdateEvent(
        map_id=submap.map_id, version=mapper.version,
        T_world_map=submap.T_world_map.detach().cpu().numpy().astype(np.float64),
        num_voxels=submap.voxels.num_voxels,
        keyframe_poses=mapper.keyframe_poses_world(submap).numpy().astype(np.float64),
        mesh_vertices=verts, mesh_faces=faces, mesh_colors=colors)


def _save_map(mapper: Mapper, out_dir: Path) -> None:
    from .checkpoint import save_checkpoint

    save_checkpoint(mapper.maps, out_dir / "map.pt", extra={"version": mapper.version})


def _mapper_handle(mapper: Mapper, state: _MapperState, msg: _FrameMessage,
                   optimize: bool) -> list[tuple[str, object]]:
    """Integrate one tracked frame; returns the messages to send back."""
    t0 = time.perf_counter()
    tf = prepare_frame(msg.frame, None, mapper.device, mapper.config.voxel.max_depth)
    first = mapper.current is None
    step = mapper.process(TrackedFrame(tf, torch.from_numpy(msg.T_world_cam).float(), msg.tracking_ok),
                          optimize=optimize)
    out: list[tuple[str, object]] = []
    submap = mapper.current
    assert submap is not None
    if first:
        out.append(("event", SubmapEvent(submap.map_id, mapper.agent,
                                         submap.T_world_map.cpu().numpy().astype(np.float64), "start")))
    if step.is_keyframe:
        kf_pose = (submap.T_world_map @ submap.keyframes[-1].T_map_cam).detach().cpu().numpy()
        out.append(("event", KeyframeEvent(mapper.agent, step.frame_index, submap.map_id,
                                           kf_pose.astype(np.float64))))
        state.keyframes_since_mesh += 1
        state.keyframes_since_checkpoint += 1
    cfg = mapper.config
    if state.emit_meshes and (first or state.keyframes_since_mesh >= cfg.mesh.update_every_keyframes):
        state.keyframes_since_mesh = 0
        out.append(("event", _map_update_event(mapper, with_mesh=True)))
    elif step.is_keyframe:
        out.append(("event", _map_update_event(mapper, with_mesh=False)))
    every = cfg.runtime.checkpoint_every_keyframes
    if every > 0 and state.keyframes_since_checkpoint >= every:
        state.keyframes_since_checkpoint = 0
        _save_map(mapper, state.out_dir)
    state.busy += time.perf_counter() - t0
    return out


def _mapper_stats(mapper: Mapper, state: _MapperState) -> _MapperStats:
    kf_poses: dict[int, list[float]] = {}
    for submap in mapper.maps.maps:
        poses = mapper.keyframe_poses_world(submap).numpy()
        for kf, T in zip(submap.keyframes, poses):
            kf_poses[kf.frame_index] = T.reshape(-1).tolist()
    map_bytes = sum(m.voxels.embeddings.numel() * 4 for m in mapper.maps.maps)
    dec_bytes = sum(m.decoder.num_bytes() for m in mapper.maps.maps)
    return _MapperStats(mapper.maps.num_keyframes(), len(mapper.maps.maps), mapper.maps.num_voxels(),
                        map_bytes, dec_bytes, state.busy, dict(mapper.timer.totals), kf_poses)


def _mapper_finish(mapper: Mapper, state: _MapperState, refine: bool) -> list[tuple[str, object]]:
    """Final outputs of the mapper: the global bundle adjustment (``refine``; a stopped run
    skips it to stop promptly), checkpoint and mesh, then the statistics."""
    from .mesh import export_mesh, extract_mesh

    out: list[tuple[str, object]] = []
    if mapper.current is not None:
        m = mapper.config.mapping
        t0 = time.perf_counter()
        mapper.global_bundle_adjustment(mapper.current, m.final_iterations if refine else 0, m.final_rays)
        mapper.version += 1
        state.busy += time.perf_counter() - t0
        mapper.timer.add("final_bundle_adjustment", time.perf_counter() - t0)
        t0 = time.perf_counter()
        _save_map(mapper, state.out_dir)
        export_mesh(extract_mesh(mapper.maps), state.out_dir / "mesh.ply")
        mapper.timer.add("final_outputs", time.perf_counter() - t0)
        if state.emit_meshes:
            out.append(("event", _map_update_event(mapper, with_mesh=True)))
    out.append(("done", _mapper_stats(mapper, state)))
    return out


def _queued(frames: "queue.Queue") -> int:
    """Items in a multiprocessing queue (1 where the platform cannot count, e.g. macOS:
    the caller then drains until a get times out)."""
    try:
        return frames.qsize()
    except NotImplementedError:
        return 1


def _mapping_process(config_dict: dict, device_name: str, out_dir: str, emit_meshes: bool,
                     frames: "queue.Queue", replies: "queue.Queue", seed: int) -> None:
    """Entry point of the mapping process: mapper loop until the ``None`` sentinel."""
    import multiprocessing as mp

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is handled by the tracking side
    try:
        config = config_from_dict(config_dict)
        device = torch.device(device_name)
        _set_threads(device, processes=True)
        mapper = Mapper(config, device, seed=seed)
        state = _MapperState(Path(out_dir), emit_meshes)
        replies.put(("ready", None))
        parent = mp.parent_process()
        while True:
            if parent is not None and not parent.is_alive():
                # The tracking side was killed: nobody will read our outputs, and flushing
                # the reply pipe at exit would block this process forever.
                replies.cancel_join_thread()
                return
            try:
                msg = frames.get(timeout=0 if mapper.current is not None else _POLL_SECONDS)
            except queue.Empty:
                if mapper.current is None:
                    continue
                # Nothing new: keep optimising the window (the paper's mapper never idles),
                # so the tracker gets a better map by the time the next frame arrives.
                t0 = time.perf_counter()
                mapper.optimize(mapper.current, mapper.config.mapping.iterations)
                mapper.version += 1
                state.busy += time.perf_counter() - t0
                replies.put(("snapshot", mapper.snapshot()))
                continue
            batch = [msg]
            # Drain what queued up while we optimised: integrate all, optimise once. qsize
            # counts frames still in the queue's pipe, which get_nowait would miss (it then
            # took one frame per optimisation while the tracker sat on a full queue).
            while batch[-1] not in (_END, _END_NOW) and _queued(frames) > 0:
                try:
                    batch.append(frames.get(timeout=_POLL_SECONDS))
                except queue.Empty:
                    break
            done = batch[-1] in (_END, _END_NOW)
            work = [m for m in batch if m not in (_END, _END_NOW)]
            for i, m in enumerate(work):
                for reply in _mapper_handle(mapper, state, m, optimize=(i == len(work) - 1)):
                    replies.put(reply)
            if work:
                replies.put(("snapshot", mapper.snapshot()))
            if done:
                # The tracker has no frames left: the final bundle adjustment and the mesh
                # take every core (2 cores: 108 -> 80 ms per global-BA iteration).
                _set_threads(device, processes=False)
                for reply in _mapper_finish(mapper, state, refine=batch[-1] is _END):
                    replies.put(reply)
                return
    except BaseException:  # noqa: BLE001 - reported to the tracking side, which fails the run
        replies.put(("error", traceback.format_exc()))


# ---------------------------------------------------------- mapper channels
class _InlineMapper:
    """The mapper in this process (``processes=False``)."""

    def __init__(self, config: SLAMConfig, device: torch.device, out_dir: Path, emit_meshes: bool, seed: int):
        self.mapper = Mapper(config, device, seed=seed)
        self.state = _MapperState(out_dir, emit_meshes)
        self.pending: list[tuple[str, object]] = []

    def submit(self, msg: _FrameMessage) -> None:
        self.pending += _mapper_handle(self.mapper, self.state, msg, optimize=True)
        self.pending.append(("snapshot", self.mapper.snapshot()))

    def poll(self, block: bool = False) -> list[tuple[str, object]]:
        out, self.pending = self.pending, []
        return out

    def finish(self, refine: bool = True) -> list[tuple[str, object]]:
        return self.poll() + _mapper_finish(self.mapper, self.state, refine)

    def close(self) -> None:
        pass


class _ProcessMapper:
    """The mapper in a spawned process, behind a bounded frame queue."""

    def __init__(self, config: SLAMConfig, device: torch.device, out_dir: Path, emit_meshes: bool, seed: int):
        import multiprocessing as mp

        ctx = mp.get_context("spawn")
        self.frames = ctx.Queue(maxsize=max(1, config.runtime.queue_size))
        self.replies = ctx.Queue()
        self.process = ctx.Process(
            target=_mapping_process, name="voxfusion-mapping",
            args=(config.to_dict(), str(device), str(out_dir), emit_meshes, self.frames, self.replies, seed))
        self.process.start()
        self._early: list[tuple[str, object]] = []
        self._wait_for("ready", _STARTUP_TIMEOUT)

    def _get(self, timeout: float) -> tuple[str, object] | None:
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

    def submit(self, msg: _FrameMessage) -> None:
        while True:
            try:
                self.frames.put(msg, timeout=_POLL_SECONDS)
                return
            except queue.Full:
                if not self.process.is_alive():
                    raise MapperFailed(f"the mapping process died (exit code {self.process.exitcode})") from None

    def poll(self, block: bool = False) -> list[tuple[str, object]]:
        out, self._early = self._early, []
        reply = self._get(_POLL_SECONDS) if block else None
        if reply is not None:
            out.append(reply)
        while True:
            try:
                out.append(self.replies.get_nowait())
            except queue.Empty:
                return out

    def finish(self, refine: bool = True) -> list[tuple[str, object]]:
        self.submit(_END if refine else _END_NOW)  # type: ignore[arg-type]
        out: list[tuple[str, object]] = list(self._early)
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
                self.frames.put_nowait(_END_NOW)
            except queue.Full:
                pass
        self.process.join(timeout=10)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(timeout=5)


# ------------------------------------------------------------------- the run
@dataclass
class _RunState:
    poses: list[np.ndarray] = field(default_factory=list)
    timestamps: list[float] = field(default_factory=list)
    frame_indices: list[int] = field(default_factory=list)
    gt_poses: list[np.ndarray | None] = field(default_factory=list)
    tracking_failures: int = 0
    tracking_busy: float = 0.0
    good_poses: list[np.ndarray] = field(default_factory=list)
    last_ok: bool = True
    snapshot: MapSnapshot | None = None
    frozen: FrozenMap | None = None
    mapper_stats: _MapperStats | None = None
    features: FeatureOdometry | None = None


def _pipeline_frame(frame: Frame, width: int | None) -> Frame:
    """Resize a reader frame to the pipeline width once (tracker and mapper share it)."""
    if width is None or width >= frame.width:
        return frame
    rgb, depth, K = resize_rgbd(frame.rgb, frame.depth, frame.K, width)
    return Frame(frame.index, frame.timestamp, rgb, depth, K, frame.T_world_cam)


def _thumbnail(rgb: np.ndarray, width: int = 96) -> np.ndarray:
    import cv2

    h = max(1, int(round(rgb.shape[0] * width / rgb.shape[1])))
    return (cv2.resize(rgb, (width, h), interpolation=cv2.INTER_AREA) * 255).astype(np.uint8)


def _handle_replies(replies: list[tuple[str, object]], run: _RunState, emit: Callable[[Event], None],
                    config: SLAMConfig, device: torch.device) -> None:
    for kind, payload in replies:
        if kind == "error":
            raise MapperFailed(str(payload))
        if kind == "snapshot":
            run.snapshot = payload  # type: ignore[assignment]
        elif kind == "event":
            emit(payload)  # type: ignore[arg-type]
        elif kind == "done":
            run.mapper_stats = payload  # type: ignore[assignment]


def _frozen_map(run: _RunState, config: SLAMConfig, device: torch.device) -> FrozenMap:
    """The tracker's map copy, rebuilt only when a newer snapshot arrived."""
    assert run.snapshot is not None
    if run.frozen is None or run.frozen.version != run.snapshot.version:
        run.frozen = FrozenMap(run.snapshot, config, device)
    return run.frozen


def with_given_poses(config: SLAMConfig) -> SLAMConfig:
    """The config for mapping with given (ground-truth) poses: bundle adjustment off, since it
    could only move the keyframes away from poses that are right by definition."""
    return replace(config, mapping=replace(config.mapping, optimize_poses=False))


def run_slam(sources: list[Iterable[Frame]], config: SLAMConfig, out_dir: str | Path, *,
             use_gt_poses: bool = False, on_event: Callable[[Event], None] | None = None,
             stop: StopFlag | None = None, progress: bool = False) -> RunResult:
    """Run SLAM over ``sources`` and write the outputs to ``out_dir``. See the module doc.

    Exceptions inside the run (bad data, a mapper failure) end it as ``failed`` with the
    traceback in ``run.json``; Ctrl-C or ``stop`` end it as ``cancelled``; in both cases what
    was mapped so far is still written.
    """
    if len(sources) != 1:
        raise ValueError(
            "collaborative mapping of several sequences needs multi-map loop closure, which this "
            "version does not have yet; pass one sequence")
    if use_gt_poses:
        config = with_given_poses(config)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    device = resolve_device(config.runtime.device)
    processes = config.runtime.processes
    _set_threads(device, processes)
    torch.manual_seed(config.runtime.seed)
    emit = on_event or (lambda event: None)
    run = _RunState()
    source = sources[0]
    total = len(source) if hasattr(source, "__len__") else None  # type: ignore[arg-type]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, unit="frame", dynamic_ncols=True)
    status, error = "finished", None
    started = time.perf_counter()
    channel: _InlineMapper | _ProcessMapper | None = None
    try:
        mapper_cls = _ProcessMapper if processes else _InlineMapper
        channel = mapper_cls(config, device, out, on_event is not None, config.runtime.seed)
        tracker = Tracker(config, device, seed=config.runtime.seed)
        for raw in source:
            if stop is not None and stop.is_set():
                status = "cancelled"
                break
            frame = _pipeline_frame(raw, config.runtime.input_width)
            T, ok = _estimate_pose(frame, raw, run, tracker, channel, config, device, use_gt_poses, emit)
            run.poses.append(T)
            run.timestamps.append(float(frame.timestamp))
            run.frame_indices.append(int(frame.index))
            run.gt_poses.append(raw.T_world_cam)
            emit(PoseEvent(0, frame.index, float(frame.timestamp), T.astype(np.float64),
                           run.snapshot.map_id if run.snapshot else 0, ok,
                           thumbnail=_thumbnail(frame.rgb) if on_event else None,
                           K=np.asarray(frame.K, np.float64), image_size=(frame.width, frame.height)))
            channel.submit(_FrameMessage(frame, T.astype(np.float32), ok))
            _handle_replies(channel.poll(), run, emit, config, device)
            done = len(run.poses)
            fps = done / max(time.perf_counter() - started, 1e-9)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(_progress_fields(run, fps), refresh=False)
            if done % 10 == 0:
                emit(_stats_event(run, total, fps, started))
    except KeyboardInterrupt:
        status = "cancelled"
    except Exception:  # noqa: BLE001 - any failure ends this run only, with its traceback
        status, error = "failed", traceback.format_exc()
    finally:
        if bar is not None:
            bar.close()
    if channel is not None:
        try:
            if status != "failed" or run.snapshot is not None:
                _handle_replies(channel.finish(refine=status == "finished"), run, emit, config, device)
        except KeyboardInterrupt:
            status = "cancelled"
        except Exception:  # noqa: BLE001
            if error is None:
                status, error = "failed", traceback.format_exc()
        finally:
            channel.close()
    elapsed = time.perf_counter() - started
    if not use_gt_poses and run.mapper_stats is not None and run.poses:
        run.poses = list(refine_with_keyframes(np.stack(run.poses), run.frame_indices,
                                               run.mapper_stats.keyframe_poses))
    result = _write_outputs(out, config, run, status, error, elapsed, total)
    emit(_stats_event(run, total, result.fps, started))
    emit(FinishedEvent(status, error))
    return result


def _estimate_pose(frame: Frame, raw: Frame, run: _RunState, tracker: Tracker, channel, config: SLAMConfig,
                   device: torch.device, use_gt_poses: bool,
                   emit: Callable[[Event], None]) -> tuple[np.ndarray, bool]:
    """The frame's world pose: GT (``--gt-poses``), the first frame's GT or identity, or tracked.

    ``frame`` is ``raw`` resized to the pipeline's width; sparse features use ``raw``.
    """
    if use_gt_poses:
        if frame.T_world_cam is None:
            raise ValueError(f"--gt-poses: frame {frame.index} has no ground-truth pose")
        return np.asarray(frame.T_world_cam, np.float64), True
    if not run.poses:
        run.features = FeatureOdometry.from_config(config)
        first = np.asarray(frame.T_world_cam if frame.T_world_cam is not None else np.eye(4), np.float64)
        run.good_poses.append(first)
        if run.features is not None:
            run.features.correspondences(raw)
            run.features.remember(first)
        return first, True
    while run.snapshot is None:  # the map is initialised from the first frame
        _handle_replies(channel.poll(block=True), run, emit, config, device)
    t0 = time.perf_counter()
    fmap = _frozen_map(run, config, device)
    tf = prepare_frame(frame, None, device, config.voxel.max_depth)
    # Velocity only from two consecutive good poses: extrapolating from a failed estimate
    # would compound the error frame after frame.
    good = run.good_poses[-2:] if run.last_ok else run.good_poses[-1:]
    history = [torch.from_numpy(p).float().to(device) for p in good]
    matches = run.features.correspondences(raw) if run.features is not None else None
    result = tracker.track(tf, fmap, constant_velocity_guess(history, config.tracking.constant_velocity), matches)
    T = result.T_world_cam.detach().cpu().numpy().astype(np.float64)
    if run.features is not None:
        run.features.remember(T if result.ok else None)
    run.tracking_busy += time.perf_counter() - t0
    run.last_ok = result.ok
    if result.ok:
        run.good_poses.append(T)
    else:
        run.tracking_failures += 1
    return T, result.ok


def _running_ate(run: _RunState) -> float | None:
    if len(run.poses) < 3 or any(g is None for g in run.gt_poses):
        return None
    from .eval.ate import umeyama_alignment

    est = np.stack([p[:3, 3] for p in run.poses])
    gt = np.stack([g[:3, 3] for g in run.gt_poses])  # type: ignore[index]
    try:
        R, t, _ = umeyama_alignment(est, gt)
    except ValueError:
        return None
    err = np.linalg.norm(est @ R.T + t - gt, axis=1)
    return float(np.sqrt((err ** 2).mean()))


def _progress_fields(run: _RunState, fps: float) -> dict[str, str]:
    fields = {"fps": f"{fps:.2f}"}
    ate = _running_ate(run) if len(run.poses) % 5 == 0 else None
    if ate is not None:
        fields["ATE"] = f"{ate * 100:.2f}cm"
    if run.tracking_failures:
        fields["lost"] = str(run.tracking_failures)
    return fields


def _stats_event(run: _RunState, total: int | None, fps: float, started: float) -> StatsEvent:
    stats = run.mapper_stats
    wall = max(time.perf_counter() - started, 1e-9)
    return StatsEvent(
        frames_done=len(run.poses), frames_total=total, fps=fps,
        keyframes=stats.keyframes if stats else 0, maps=stats.maps if stats else 1, loops=0,
        voxels=stats.voxels if stats else (len(run.snapshot.voxel_codes) if run.snapshot else 0),
        tracking_busy=min(1.0, run.tracking_busy / wall),
        mapping_busy=min(1.0, stats.busy_seconds / wall) if stats else 0.0)


def refine_with_keyframes(poses: np.ndarray, frame_indices: list[int],
                          keyframe_poses: dict[int, list[float]]) -> np.ndarray:
    """Tracked world poses (N, 4, 4) moved by bundle adjustment's keyframe corrections.

    Each frame takes the correction ``T_kf_BA T_kf_tracked^-1`` of the latest keyframe at or
    before it (so keyframes get their bundle-adjusted pose and the frames tracked against them
    follow); frames before the first keyframe are unchanged. ``keyframe_poses``: frame index ->
    the keyframe's optimised T_world_cam as 16 row-major numbers (``run.json``'s form).
    """
    out = np.array(poses, dtype=np.float64, copy=True)
    correction = None
    for i, index in enumerate(frame_indices):
        refined = keyframe_poses.get(index)
        if refined is not None:
            correction = np.asarray(refined, np.float64).reshape(4, 4) @ np.linalg.inv(poses[i])
        if correction is not None:
            out[i] = correction @ poses[i]
    return out


def _write_outputs(out: Path, config: SLAMConfig, run: _RunState, status: str, error: str | None,
                   elapsed: float, total: int | None) -> RunResult:
    from .eval.trajectory import Trajectory, write_tum

    if run.poses:
        write_tum(out / "trajectory.txt", Trajectory(np.array(run.timestamps), np.stack(run.poses)))
    stats = run.mapper_stats
    ate_rmse = None
    if run.poses and all(g is not None for g in run.gt_poses) and len(run.poses) >= 3:
        from .eval.ate import ate
        from .eval.trajectory import Trajectory as Traj

        ts = np.array(run.timestamps)
        try:
            ate_rmse = ate(Traj(ts, np.stack(run.gt_poses)), Traj(ts, np.stack(run.poses))).rmse
        except ValueError:
            ate_rmse = None
    fps = len(run.poses) / max(elapsed, 1e-9)
    info = {
        "status": status,
        "error": error,
        "config": config.to_dict(),
        "frames": len(run.poses),
        "frames_total": total,
        "keyframes": stats.keyframes if stats else 0,
        "keyframe_poses": stats.keyframe_poses if stats else {},
        "maps": stats.maps if stats else 0,
        "loops": 0,
        "voxels": stats.voxels if stats else 0,
        "map_memory_mb": {
            "embeddings": (stats.map_bytes if stats else 0) / 2**20,
            "decoder": (stats.decoder_bytes if stats else 0) / 2**20,
        },
        "tracking_failures": run.tracking_failures,
        "timings_s": {
            "wall": elapsed,
            "tracking_busy": run.tracking_busy,
            "mapping_busy": stats.busy_seconds if stats else 0.0,
            **({f"mapping_{k}": v for k, v in stats.timings.items()} if stats else {}),
        },
        "busy_share": {
            "tracking": run.tracking_busy / max(elapsed, 1e-9),
            "mapping": (stats.busy_seconds if stats else 0.0) / max(elapsed, 1e-9),
        },
        "fps": fps,
        "ate_rmse_m": ate_rmse,
    }
    (out / "run.json").write_text(json.dumps(info, indent=2))
    return RunResult(status, error, len(run.poses), info["keyframes"], info["maps"], 0, fps, out, ate_rmse)
