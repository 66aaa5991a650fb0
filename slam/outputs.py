"""What a run writes: trajectories, ``run.json`` (the mesh and ``map.pt`` come from the mapper).

Every frame is recorded in the frame of the map it was tracked against; its world pose is
composed at the end with that map's final ``T_world_map`` (so loop closure moves it with its
map), then moved by bundle adjustment's correction of its latest keyframe (or, with
``mapping.frame_correction`` "interpolated", the corrections of the keyframes either side
blended), and frames whose
tracking failed are interpolated between their well-tracked neighbours. With the final
re-tracking (``tracking.retrack_iterations``) a tracked frame then takes the pose found by
tracking it again against the final maps from that corrected pose.

While the run goes on, ``write_progress`` rewrites the trajectories so far (the poses as
tracked, each placed by its map's newest pose) and a ``run.json`` whose ``status`` is
``running`` at every keyframe (``slam.runtime``), so a killed run leaves the poses up to its
last keyframe. Every file here is written atomically (a temporary dot-file, then
``os.replace``): a reader, or a run killed mid-write, never sees half a file. They are not
fsynced: a killed process loses nothing the kernel has, a power cut may.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .config import SLAMConfig

if TYPE_CHECKING:
    from .messages import MapperStats
    from .runtime import AgentTrack


@dataclass(frozen=True)
class FrameRecord:
    """One input frame as tracked: T_map_cam (4, 4) float64 in map ``map_id``; ``tracked``
    False when tracking failed or the camera was lost; ``gt`` (4, 4) or None."""

    index: int
    timestamp: float
    map_id: int
    T_map_cam: np.ndarray
    tracked: bool
    gt: np.ndarray | None


PROGRESS_EVERY = 10
"""Frames between two samples of a run's course (``ProgressSample``)."""


@dataclass(frozen=True)
class ProgressSample:
    """A run's state after ``frames`` input frames, ``wall_s`` seconds in: the map's size as the
    mapper last reported it (``map_mb``: embeddings and decoders). ``run.json``'s ``progress``
    lists them, so a long sequence shows how frames/s and memory follow the map's growth."""

    frames: int
    wall_s: float
    voxels: int
    keyframes: int
    maps: int
    map_mb: float


def refine_with_keyframes(poses: np.ndarray, frame_indices: list[int],
                          keyframe_poses: dict[int, list[float]], interpolate: bool = False) -> np.ndarray:
    """Tracked world poses (N, 4, 4) moved by bundle adjustment's keyframe corrections.

    Each frame takes the correction ``T_kf_BA T_kf_tracked^-1`` of the latest keyframe at or
    before it (so keyframes get their bundle-adjusted pose and the frames tracked against them
    follow); frames before the first keyframe are unchanged. With ``interpolate`` a frame
    between two keyframes takes their corrections blended by its place between them (rotation
    by slerp, translation linearly; ``mapping.frame_correction`` "interpolated"): it was
    tracked against a map that bundle adjustment moved with both. ``keyframe_poses``: frame
    index -> the keyframe's optimised T_world_cam as 16 row-major numbers (``run.json``'s form).
    """
    out = np.array(poses, dtype=np.float64, copy=True)
    at = [i for i, index in enumerate(frame_indices) if index in keyframe_poses]
    corrections = [np.asarray(keyframe_poses[frame_indices[i]], np.float64).reshape(4, 4) @ np.linalg.inv(poses[i])
                   for i in at]
    for k, (start, correction) in enumerate(zip(at, corrections)):
        end = at[k + 1] if k + 1 < len(at) else len(poses)
        for i in range(start, end):
            if interpolate and end < len(poses) and i > start:
                out[i] = blend_poses(correction, corrections[k + 1], (i - start) / (end - start)) @ poses[i]
            else:
                out[i] = correction @ poses[i]
    return out


def retrack_anchors(map_ids: list[int], budget: int) -> list[int]:
    """Positions (ascending) of the frames the final re-tracking optimises among frames in
    ``map_ids`` (each frame's map, in order): every one with ``budget`` 0; else per map at
    most ``budget``, spread evenly over its frames, its first and last included
    (``tracking.retrack_frame_budget``)."""
    by_map: dict[int, list[int]] = {}
    for i, map_id in enumerate(map_ids):
        by_map.setdefault(map_id, []).append(i)
    out: list[int] = []
    for positions in by_map.values():
        if budget <= 0 or len(positions) <= budget:
            out += positions
        else:
            picks = np.unique(np.linspace(0, len(positions) - 1, budget).round().astype(int))
            out += [positions[j] for j in picks]
    return sorted(out)


def spread_corrections(start: np.ndarray, map_ids: list[int], moved: dict[int, np.ndarray],
                       targets: list[int]) -> dict[int, np.ndarray]:
    """Poses for the ``targets`` positions of ``start`` (N, 4, 4), which the re-tracking left
    out: each takes the corrections ``T_moved T_start^-1`` of the nearest ``moved`` frames
    (position -> re-tracked pose) of its own map before and after it, blended by place as
    ``refine_with_keyframes`` blends keyframes' (one side only: that side's correction; none:
    left out)."""
    corrections: dict[int, list[tuple[int, np.ndarray]]] = {}
    for i in sorted(moved):
        corrections.setdefault(map_ids[i], []).append((i, moved[i] @ np.linalg.inv(start[i])))
    out: dict[int, np.ndarray] = {}
    for i in targets:
        known = corrections.get(map_ids[i], [])
        before = [(j, c) for j, c in known if j < i]
        after = [(j, c) for j, c in known if j > i]
        if before and after:
            (a, ca), (b, cb) = before[-1], after[0]
            correction = blend_poses(ca, cb, (i - a) / (b - a))
        elif before or after:
            correction = (before[-1] if before else after[0])[1]
        else:
            continue
        out[i] = correction @ start[i]
    return out


def blend_poses(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    """(4, 4) rigid transforms ``a`` at s = 0 to ``b`` at s = 1: rotation by slerp, translation
    linearly."""
    from scipy.spatial.transform import Rotation, Slerp

    out = np.eye(4)
    out[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))([s]).as_matrix()[0]
    out[:3, 3] = (1.0 - s) * a[:3, 3] + s * b[:3, 3]
    return out


def interpolate_untracked(poses: np.ndarray, timestamps: np.ndarray, tracked: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) where frames with ``tracked`` (N,) False are replaced by the pose
    interpolated in time between the nearest tracked frames before and after (rotation by
    slerp, translation linearly); held at the nearest one at either end."""
    out = np.array(poses, dtype=np.float64, copy=True)
    good = np.flatnonzero(tracked)
    if len(good) == 0 or len(good) == len(poses):
        return out
    for i in np.flatnonzero(~np.asarray(tracked, bool)):
        before, after = good[good < i], good[good > i]
        if len(before) == 0 or len(after) == 0:
            out[i] = poses[after[0] if len(before) == 0 else before[-1]]
            continue
        a, b = before[-1], after[0]
        span = timestamps[b] - timestamps[a]
        s = 0.5 if span <= 0 else float(np.clip((timestamps[i] - timestamps[a]) / span, 0.0, 1.0))
        out[i] = blend_poses(poses[a], poses[b], s)
    return out


def world_poses(records: list[FrameRecord], map_poses: dict[int, np.ndarray]) -> np.ndarray:
    """(N, 4, 4) world poses of ``records`` with the given map poses."""
    return np.stack([np.asarray(map_poses[r.map_id], np.float64) @ r.T_map_cam for r in records])


def aligned_rmse(est: np.ndarray, gt: np.ndarray) -> float | None:
    """RMSE (m) of positions est (N, 3) against gt (N, 3) after one rigid alignment
    (``slam.eval.ate.ate_from_pairs``); None when fewer than 3 or degenerate."""
    from .eval.ate import ate_from_pairs

    if len(est) < 3:
        return None
    try:
        return ate_from_pairs(gt, est).rmse
    except ValueError:  # DataError too: collinear positions
        return None


def running_ate(records: list[FrameRecord], map_poses: dict[int, np.ndarray]) -> float | None:
    """ATE RMSE (m) of the raw world poses so far (None without GT)."""
    if len(records) < 3 or any(r.gt is None for r in records):
        return None
    gt = np.stack([r.gt[:3, 3] for r in records])  # type: ignore[index]
    return aligned_rmse(world_poses(records, map_poses)[:, :3, 3], gt)


@dataclass(frozen=True)
class AgentTrajectory:
    agent: int
    timestamps: np.ndarray
    poses: np.ndarray
    gt: list[np.ndarray | None]
    interpolated: int


def corrected_poses(records: list[FrameRecord], map_poses: dict[int, np.ndarray],
                    keyframe_poses: dict[int, list[float]], interpolate_corrections: bool) -> np.ndarray:
    """(N, 4, 4) world poses of an agent's ``records``: placed by ``map_poses``, moved by the
    keyframes' corrections (``refine_with_keyframes``; ``keyframe_poses``: frame index -> 16
    numbers), untracked frames interpolated in time between tracked ones."""
    poses = world_poses(records, map_poses)
    poses = refine_with_keyframes(poses, [r.index for r in records], keyframe_poses, interpolate_corrections)
    return interpolate_untracked(poses, np.array([r.timestamp for r in records]), np.array([r.tracked for r in records]))


def agent_trajectory(track: "AgentTrack", stats: "MapperStats | None", fallback_poses: dict[int, np.ndarray],
                     use_gt_poses: bool, interpolate_corrections: bool = False) -> AgentTrajectory:
    """An agent's final world trajectory (see the module doc): the poses the final re-tracking
    found (``AgentTrack.retracked``) where it found one."""
    records = track.records
    map_poses = stats.map_poses if stats is not None else fallback_poses
    ts = np.array([r.timestamp for r in records])
    tracked = np.array([r.tracked for r in records])
    if not use_gt_poses and stats is not None:
        kf = {k.frame_index: k.T_world_cam for k in stats.keyframe_records if k.agent == track.agent}
        poses = corrected_poses(records, map_poses, kf, interpolate_corrections)
        for i, r in enumerate(records):
            if r.index in track.retracked:
                poses[i] = track.retracked[r.index]
    else:
        poses = world_poses(records, map_poses)
    return AgentTrajectory(track.agent, ts, poses, [r.gt for r in records], int((~tracked).sum()))


def _ate(trajectories: list[AgentTrajectory]) -> float | None:
    """ATE RMSE (m) of the trajectories together, one rigid alignment for all, over the frames
    that have a GT pose (as TUM's evaluation pairs only frames with ground truth; a real
    sequence lacks it for a few frames where the motion capture had no sample within 20 ms).
    None when fewer than 3 frames have one."""
    pairs = [(T[:3, 3], g[:3, 3]) for t in trajectories for T, g in zip(t.poses, t.gt) if g is not None]
    if len(pairs) < 3:
        return None
    return aligned_rmse(np.stack([e for e, _ in pairs]), np.stack([g for _, g in pairs]))


def _agent_joined(agent: int, stats: "MapperStats | None") -> bool:
    """Whether any of the agent's maps shares a group with the world's first map."""
    if stats is None or not stats.map_groups:
        return agent == 0
    world = stats.map_groups.get(0, 0)
    return any(stats.map_groups.get(m) == world for m, a in stats.map_agents.items() if a == agent)


def write_text_atomic(path: Path, text: str) -> None:
    """Replace ``path`` by ``text`` in one step (a dot-file next to it, then ``os.replace``)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_json_atomic(path: Path, data: dict) -> None:
    write_text_atomic(path, json.dumps(data, indent=2))


def read_run_json(out: Path) -> dict | None:
    """``out/run.json`` as a dict, None when it is missing or unreadable."""
    try:
        data = json.loads((Path(out) / "run.json").read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


_AGENT_TRAJECTORY = re.compile(r"^trajectory_(\d+)\.txt$")


def trajectory_frames(out: Path) -> int:
    """Poses in a run's trajectory files: every ``trajectory_<k>.txt`` (several agents), else
    ``trajectory.txt``; 0 when there is none (as ``run.json``'s ``frames`` counts them)."""
    out = Path(out)
    files = [p for p in out.glob("trajectory_*.txt") if _AGENT_TRAJECTORY.match(p.name)] or [out / "trajectory.txt"]
    frames = 0
    for path in files:
        try:
            text = path.read_text()
        except OSError:
            continue
        frames += sum(1 for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#"))
    return frames


def _write_trajectories(out: Path, trajectories: list[AgentTrajectory], several: bool) -> None:
    """``trajectory.txt`` (agent 0) and with ``several`` agents ``trajectory_<k>.txt`` each."""
    from .eval.trajectory import Trajectory, format_tum

    for traj in trajectories:
        text = format_tum(Trajectory(traj.timestamps, traj.poses))
        if traj.agent == 0:
            write_text_atomic(out / "trajectory.txt", text)
        if several:
            write_text_atomic(out / f"trajectory_{traj.agent}.txt", text)


def write_progress(out: Path, config: SLAMConfig, tracks: list["AgentTrack"], map_poses: dict[int, np.ndarray],
                   *, keyframes: int, maps: int, loops: int, total: int | None, elapsed: float,
                   last_keyframe: tuple[int, int] | None = None) -> int:
    """The run so far (module doc): each agent's trajectory as tracked, then a ``run.json``
    with ``status`` ``running``, the frames in those trajectories, ``keyframes`` seen so far
    and ``last_keyframe`` (agent, frame index). Returns the frames written."""
    trajectories = [agent_trajectory(t, None, map_poses, True) for t in tracks if t.records]
    several = len(tracks) > 1
    _write_trajectories(out, trajectories, several)
    frames = sum(len(t.poses) for t in trajectories)
    write_json_atomic(out / "run.json", {
        "status": "running",
        "error": None,
        "partial": True,
        "config": config.to_dict(),
        "frames": frames,
        "frames_total": total,
        "keyframes": keyframes,
        "last_keyframe": None if last_keyframe is None else {"agent": last_keyframe[0], "frame": last_keyframe[1]},
        "maps": maps,
        "loops": loops,
        "agents": [{"agent": t.agent, "frames": len(t.poses),
                    "trajectory": f"trajectory_{t.agent}.txt" if several else "trajectory.txt"} for t in trajectories],
        "timings_s": {"wall": elapsed},
    })
    return frames


MAX_LISTED_SKIPPED = 100
"""Skipped frames listed in run.json by index and reason (all are counted)."""


@dataclass(frozen=True)
class RunResult:
    """What ``slam.runtime.run_slam`` returns once the outputs are written (``run.json`` in
    ``out_dir`` has the rest)."""

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
    agents: int = 1


def write_outputs(out: Path, config: SLAMConfig, tracks: list["AgentTrack"], stats: "MapperStats | None",
                  status: str, error: str | None, elapsed: float, total: int | None, tracking_busy: float,
                  use_gt_poses: bool, map_poses: dict[int, np.ndarray] | None = None,
                  map_waits: tuple[int, float] = (0, 0.0), frames_skipped: list[dict] | None = None,
                  colour_cameras: list[dict | None] | None = None,
                  progress: list[ProgressSample] | None = None,
                  retracking: tuple[int, float] = (0, 0.0),
                  tracking_stages: dict[str, float] | None = None, frames_unmapped: int = 0) -> RunResult:
    interpolate = config.mapping.frame_correction == "interpolated"
    trajectories = [agent_trajectory(t, stats, map_poses or {}, use_gt_poses, interpolate) for t in tracks if t.records]
    _write_trajectories(out, trajectories, len(tracks) > 1)
    agents = [{
        "agent": t.agent, "frames": len(t.poses), "trajectory": "trajectory.txt" if len(tracks) == 1 else f"trajectory_{t.agent}.txt",
        "ate_rmse_m": _ate([t]), "joined": _agent_joined(t.agent, stats),
        "frames_interpolated": t.interpolated,
        "tracking_failures": next(tr.tracking_failures for tr in tracks if tr.agent == t.agent),
    } for t in trajectories]
    frames = sum(len(t.poses) for t in trajectories)
    ate_rmse = next((a["ate_rmse_m"] for a in agents if a["agent"] == 0), None)
    kf0 = {str(k.frame_index): k.T_world_cam for k in (stats.keyframe_records if stats else []) if k.agent == 0}
    closures = stats.loop_closures if stats else []
    fps = frames / max(elapsed, 1e-9)
    mapping_busy = stats.busy_seconds if stats else 0.0
    info = {
        "status": status,
        "error": error,
        "config": config.to_dict(),
        "frames": frames,
        "frames_total": total,
        "keyframes": stats.keyframes if stats else 0,
        "keyframe_poses": kf0,
        "maps": stats.maps if stats else 0,
        "map_poses": {str(k): np.asarray(v).reshape(-1).tolist() for k, v in (stats.map_poses if stats else {}).items()},
        "map_agents": {str(k): v for k, v in (stats.map_agents if stats else {}).items()},
        "map_reasons": {str(k): v for k, v in (stats.map_reasons if stats else {}).items()},
        "map_groups": len(set(stats.map_groups.values())) if stats and stats.map_groups else 0,
        "loops": len(closures),
        "loop_closures": closures,
        "loop_candidates_rejected": stats.loop_candidates_rejected if stats else 0,
        "loop_candidates": stats.loop_candidates if stats else [],
        "loop_timings_ms": stats.loop_timings_ms if stats else {},
        "agents": agents,
        "ate_rmse_m_all_agents": _ate(trajectories) if len(trajectories) > 1 else ate_rmse,
        "voxels": stats.voxels if stats else 0,
        "map_memory_mb": {
            "embeddings": (stats.map_bytes if stats else 0) / 2**20,
            "decoder": (stats.decoder_bytes if stats else 0) / 2**20,
            "fine_color": (stats.fine_color_bytes if stats else 0) / 2**20,
        },
        "final_bundle_adjustment": (asdict(stats.refinement)
                                    if stats and stats.refinement else None),
        "keyframe_graph": stats.keyframe_graph if stats else None,
        "tracking_failures": sum(t.tracking_failures for t in tracks),
        "color_cameras": colour_cameras or [],
        "frames_skipped": len(frames_skipped or ()),
        "skipped_frames": (frames_skipped or [])[:MAX_LISTED_SKIPPED],
        "map_waits": map_waits[0],
        "frames_unmapped": frames_unmapped,
        "frames_interpolated": sum(t.interpolated for t in trajectories),
        "frames_retracked": retracking[0],
        "timings_s": {
            "wall": elapsed,
            "tracking_busy": tracking_busy,
            "mapping_busy": mapping_busy,
            "tracking_waited_for_map": map_waits[1],
            "tracking_retracking": retracking[1],
            **({f"mapping_{k}": v for k, v in stats.timings.items()} if stats else {}),
            **{f"tracking_{k}": v for k, v in (tracking_stages or {}).items()},
        },
        "busy_share": {
            "tracking": tracking_busy / max(elapsed, 1e-9),
            "mapping": mapping_busy / max(elapsed, 1e-9),
        },
        "fps": fps,
        "ate_rmse_m": ate_rmse,
        "progress": [asdict(sample) for sample in progress or ()],
    }
    write_json_atomic(out / "run.json", info)
    return RunResult(status, error, frames, info["keyframes"], info["maps"], len(closures), fps, out, ate_rmse,
                     agents=max(len(tracks), 1))
