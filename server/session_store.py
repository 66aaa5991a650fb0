"""A session's folder on disk: its status, its frames/s history, its worker's pid.

Outputs live in ``DATA_DIR/sessions/<id>/`` (``session.json`` metadata, ``input/``, and the
runtime's ``trajectory.txt``, ``mesh.ply``, ``map.pt``, ``run.json``), so finished sessions are
listed again after a restart. ``worker.pid`` names the worker's process group while it runs, so
that a restart can end a worker that outlived its server (:func:`end_orphaned_worker`).

Once a session has ended (and for an interrupted one, at the restart) the status is settled
against the folder (:func:`settle_outputs`): ``frames_done`` is the number of poses in its
trajectory files, ``keyframes``/``maps``/``loops`` are ``run.json``'s, and ``run.json`` gets the
session's ``status`` and ``error`` (it is written when the run left none), so the three agree.
The runtime rewrites the trajectory and a ``run.json`` that says ``running`` atomically at each
keyframe, so a SIGKILL loses at most the frames tracked after the last keyframe.

Nothing here raises on a folder it cannot read or write: the log says so.
"""

from __future__ import annotations

import json
import os
import signal
from dataclasses import replace
from pathlib import Path

from server.session_status import SessionStatus

STATUS_FILE = "session.json"
PROGRESS_FILE = "progress.json"
"""In a session folder once it ended: ``{"fps_samples": [[seconds, frames], ...]}``."""
WORKER_PID_FILE = "worker.pid"
"""In a session folder while its worker runs: the worker's pid, which is its process group."""


def log_line(message: str) -> None:
    """One line on the server's log; a log the disk has no room for loses it (never raises)."""
    try:
        print(message, flush=True)
    except OSError:
        pass


DISK_ROOM_BYTES = 1 << 20
"""Free space under which a session's folder counts as on a full disk (``disk_is_full``)."""


def disk_is_full(directory: Path) -> bool:
    """Whether the file system holding ``directory`` has less than ``DISK_ROOM_BYTES`` left
    for this process (False when it cannot tell)."""
    try:
        stats = os.statvfs(directory)
    except OSError:
        return False
    return stats.f_bavail * stats.f_frsize < DISK_ROOM_BYTES


def _write_logged(path: Path, data: dict) -> None:
    """``path`` replaced by ``data`` atomically (``slam.outputs.write_json_atomic``: a write that
    fails, on a full disk say, leaves the old file and no temporary one); a failure is logged."""
    from slam import write_json_atomic

    try:
        write_json_atomic(path, data)
    except OSError as error:
        log_line(f"voxfusion: cannot write {path}: {error}")


def write_status(directory: Path, status: SessionStatus) -> None:
    """``session.json`` (when the folder still exists)."""
    if directory.is_dir():
        _write_logged(directory / STATUS_FILE, status.to_json())


def write_progress(directory: Path, samples: list[tuple[float, int]]) -> None:
    """Keep the frames/s history of an ended session for the page's plot after a restart."""
    if samples and directory.is_dir():
        _write_logged(directory / PROGRESS_FILE, {"fps_samples": samples})


def read_progress(directory: Path) -> list[tuple[float, int]]:
    """The frames/s history :func:`write_progress` kept; empty without one."""
    try:
        data = json.loads((directory / PROGRESS_FILE).read_text())
        return [(float(t), int(n)) for t, n in data.get("fps_samples", [])]
    except (OSError, ValueError, TypeError, AttributeError):
        return []


def describe_color_camera(run: dict | None) -> str | None:
    """``run.json``'s first ``color_cameras`` entry in words, or None when there is none."""
    cameras = (run or {}).get("color_cameras") or []
    first = cameras[0] if isinstance(cameras, list) and cameras and isinstance(cameras[0], dict) else None
    if first is None:
        return None
    if first.get("source") == "given":
        return f"given: {first.get('width')}x{first.get('height')} colour camera, registered onto depth"
    try:
        warp = (f"scale {float(first['scale']):.3f}, shift {float(first['shift_x']):+.1f}, "
                f"{float(first['shift_y']):+.1f} px, confidence {float(first['confidence']):.2f}")
    except (KeyError, TypeError, ValueError):
        return None
    verdict = "applied" if first.get("applied") else "not applied"
    return f"estimated from the data ({warp}): {verdict}, {first.get('reason', '')}".rstrip(", ")


def settle_outputs(directory: Path, state: SessionStatus, frames_refused: int | None = None) -> SessionStatus:
    """An ended session's status against its folder (module doc): ``frames_done`` the poses
    in its trajectory files, ``keyframes``/``maps``/``loops`` from ``run.json``, whose
    ``status`` and ``error`` become the session's (a minimal ``run.json`` is written when
    there is none). ``frames_refused``: a stream's refused frames (else ``run.json``'s
    ``frames_skipped``). Returns the settled status (``state`` without a folder)."""
    from slam import read_run_json, trajectory_frames

    if not directory.is_dir():
        return state
    frames = trajectory_frames(directory)
    run = read_run_json(directory)
    if run is not None:
        counts = {key: int(run[key]) for key in ("keyframes", "maps", "loops")
                  if isinstance(run.get(key), (int, float)) and not isinstance(run.get(key), bool)}
    elif frames:
        counts = {"keyframes": state.keyframes, "maps": state.maps, "loops": state.loops}
    else:
        counts = {"keyframes": 0, "maps": 0, "loops": 0}
    skipped = frames_refused if frames_refused is not None else int((run or {}).get("frames_skipped") or 0)
    settled = replace(state, frames_done=frames, frames_skipped=skipped, **counts,
                      color_camera=describe_color_camera(run) or state.color_camera)
    wanted = {"status": state.status, "error": state.error, "frames": frames}
    if run is not None and all(run.get(k) == v for k, v in wanted.items()):
        return settled
    if run is None:
        run = {"frames_total": state.frames_total, **counts, "preset": state.preset}
    elif run.get("status") not in (state.status, "running"):
        run["run_status"] = run.get("status")  # what the runtime said (a stop reads "cancelled")
    run.update(wanted)
    _write_logged(directory / "run.json", run)
    return settled


def write_pid(path: Path, pid: int | None) -> None:
    try:
        path.write_text(f"{pid}\n")
    except OSError as error:
        log_line(f"voxfusion: cannot write {path}: {error}")


def _stdout_target(pid: int) -> str | None:
    try:
        return os.readlink(f"/proc/{pid}/fd/1")
    except OSError:
        return None


def _group_of(pid: int) -> int | None:
    try:
        return os.getpgid(pid)
    except OSError:
        return None


def end_orphaned_worker(directory: Path) -> bool:
    """SIGKILL what is left of the worker group named in ``directory/worker.pid`` (a worker
    and mapping process that outlived a killed server). A process counts only if it is in
    that group and its stdout is this session's ``worker.log`` (as every process of the group
    has), so a reused pid is never hit. Linux (``/proc``); elsewhere it finds nothing.
    Returns True when something was killed."""
    pid_file = directory / WORKER_PID_FILE
    try:
        group = int(pid_file.read_text().strip())
    except (OSError, ValueError):
        return False
    pid_file.unlink(missing_ok=True)
    log = str((directory / "worker.log").resolve())
    members = [int(p.name) for p in Path("/proc").glob("[0-9]*") if _group_of(int(p.name)) == group]
    ours = [pid for pid in members if _stdout_target(pid) == log]
    for pid in ours:
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
    if ours:
        log_line(f"voxfusion: ended {len(ours)} leftover process(es) of session {directory.name}")
    return bool(ours)
