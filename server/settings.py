"""Server settings: one frozen dataclass, read from the environment (``VOXFUSION_*``).

| variable | default | meaning |
| --- | --- | --- |
| ``VOXFUSION_PORT`` | 8000 | HTTP port of ``voxfusion serve`` / ``demo`` (the page, the API, the viewer relay) |
| ``VOXFUSION_DATA_DIR`` | ``$XDG_DATA_HOME/voxfusion`` (``~/.local/share/voxfusion``) | sessions, uploads, assets |
| ``VOXFUSION_TOKEN`` | unset | when set, every API call and the viewer page need it |
| ``VOXFUSION_MAX_UPLOAD_MB`` | 2048 | largest request body (a dataset zip) |
| ``VOXFUSION_MAX_UNZIPPED_MB`` | 8192 | largest total uncompressed size of a zip |
| ``VOXFUSION_MAX_ZIP_ENTRIES`` | 200000 | most entries in a zip |
| ``VOXFUSION_MAX_SESSIONS`` | cpu_count // 4, at least 1 (64 with ``ray``) | sessions running at once; more wait in a queue (with ``ray``: sessions handed to the cluster, which queues what does not fit) |
| ``VOXFUSION_MAX_QUEUED`` | 32 | sessions waiting to start; a create beyond gets 429 (``Retry-After``) |
| ``VOXFUSION_VIEWER_PORT`` | 8080 | viser's own port (0: any free port; -1: no viewer) |
| ``VOXFUSION_CANCEL_GRACE_S`` | 10 | seconds a cancelled worker gets before it is killed |
| ``VOXFUSION_RENDER_THREADS`` | 1 | torch threads of the API process (renders, meshes) |
| ``VOXFUSION_STREAM_IDLE_S`` | 300 | a running stream without a frame for this long is finished (failed if it has none); 0: never |
| ``VOXFUSION_EXECUTOR`` | ``local`` | where sessions run: ``local`` (worker processes on this machine) or ``ray`` (actors on a Ray cluster, ``pip install '.[ray]'``) |
| ``VOXFUSION_RAY_ADDRESS`` | ``auto`` | the Ray cluster's GCS address (``host:port``), or ``auto`` (the cluster ``ray start`` began on this machine) |
| ``VOXFUSION_RAY_SESSION_CPUS`` | 2 | CPUs a Ray session declares (its tracking and mapping processes) |
| ``VOXFUSION_RAY_SESSION_GPUS`` | 0 | GPUs a Ray session declares when its preset runs on ``auto``/``cuda`` (``paper``); 0: none |
| ``VOXFUSION_RAY_LOST_S`` | 20 | a Ray session whose node gives no answer for this long fails (its node died or is cut off) |
| ``VOXFUSION_RAY_SCRATCH`` | ``$TMPDIR/voxfusion-ray`` | folder on each Ray node where sessions write before their files are shipped back |

The data directory is outside the working directory on purpose: sessions survive restarts
and do not depend on where the server was started (Docker sets ``/data``, a volume).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Mapping


class SettingsError(ValueError):
    """An environment variable has a value that cannot be used; names the variable."""


def default_data_dir(env: Mapping[str, str]) -> Path:
    """``$XDG_DATA_HOME/voxfusion``, or ``~/.local/share/voxfusion`` (the XDG default)."""
    base = env.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "voxfusion"


def default_max_sessions() -> int:
    """One session per four cores: a session runs a tracking and a mapping process, and each
    uses several torch threads, so more sessions than that mostly share the same cores."""
    return max(1, (os.cpu_count() or 1) // 4)


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS tells it)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def render_threads_now(render_threads: int, running_sessions: int, cores: int) -> int:
    """torch threads for the API process's next render: ``render_threads`` when set (>= 1);
    automatic (0): ``cores`` while no session runs, 1 while any does."""
    if render_threads >= 1:
        return render_threads
    return max(1, cores) if running_sessions == 0 else 1


EXECUTORS = ("local", "ray")
RAY_MAX_SESSIONS = 64
"""Default ``max_sessions`` with the ``ray`` executor: sessions handed to the cluster at once.
Ray queues those its nodes have no room for, so this only bounds what the API process tracks."""


@dataclass(frozen=True)
class Settings:
    data_dir: Path
    """Root of ``sessions/<id>/``, ``assets/`` and ``uploads/`` (temporary)."""
    port: int = 8000
    """HTTP port the CLI serves on (the app itself does not bind: uvicorn does)."""
    token: str | None = None
    """Bearer token every API call and the viewer need; None = open (loopback use)."""
    max_upload_mb: int = 2048
    """Largest request body in MiB; a larger one gets 413 before it is read."""
    max_unzipped_mb: int = 8192
    """Largest total uncompressed size of a dataset zip in MiB."""
    max_zip_entries: int = 200_000
    max_sessions: int = 1
    """Sessions that run at once; later ones wait in a FIFO queue."""
    max_queued: int = 32
    """Sessions that may wait in that queue; one more gets 429 with ``Retry-After``."""
    viewer_host: str = "127.0.0.1"
    """Interface viser binds to. The page reaches it through the API's ``/viewer`` proxy, the
    only client its WebSocket admits (``server.viewer``)."""
    viewer_port: int = 8080
    """viser's port (it moves to the next free one if taken); 0 = any free port, -1 = no viewer."""
    cancel_grace_s: float = 10.0
    """Seconds a cancelled worker may take to stop before its process group is killed."""
    stream_queue_frames: int = 16
    """Streamed frames buffered between the API and a worker (back-pressure beyond that)."""
    stream_put_timeout_s: float = 30.0
    """How long a streamed frame waits for room in that buffer before 503."""
    stream_idle_timeout_s: float = 300.0
    """A running stream session that gets no frame for this long is finished with the frames it
    has (failed when it has none), so that a forgotten stream does not hold a running slot
    forever; 0 = never."""
    render_threads: int = 0
    """torch intra-op threads in the API process for renders, meshes and AR; 0: automatic
    (``render_threads_now``), every core while no session runs and one while any does. One
    while sessions run: a running session's two processes take every core between them, and
    oversubscribed cores made a 160x120 render 3-6x slower (2 s -> 7-12 s); every core while
    none runs: a 640x480 view 0.90 s at two threads against 1.40 s at one (benchmarks/README.md)."""
    executor: str = "local"
    """``local`` (spawned worker processes here) or ``ray`` (``server.ray_executor``)."""
    ray_address: str = "auto"
    """GCS address of the Ray cluster (``host:port``) or ``auto``."""
    ray_session_cpus: float = 2.0
    """CPUs a Ray session reserves: Ray places it on a node with that many free, or queues it."""
    ray_session_gpus: float = 0.0
    """GPUs a Ray session reserves when its preset's device is not ``cpu``."""
    ray_lost_s: float = 20.0
    """Seconds without an answer from a Ray session's node before the session fails."""
    ray_scratch: str | None = None
    """Folder on the Ray nodes for sessions' working files; None: ``$TMPDIR/voxfusion-ray``."""

    @property
    def max_upload_bytes(self) -> int:
        return self.max_upload_mb * 1024 * 1024

    @property
    def max_unzipped_bytes(self) -> int:
        return self.max_unzipped_mb * 1024 * 1024

    @property
    def viewer_enabled(self) -> bool:
        return self.viewer_port >= 0

    @property
    def sessions_dir(self) -> Path:
        return self.data_dir / "sessions"

    @property
    def assets_dir(self) -> Path:
        return self.data_dir / "assets"

    @property
    def uploads_dir(self) -> Path:
        return self.data_dir / "uploads"

    def with_overrides(self, **changes: object) -> "Settings":
        """A copy with some fields replaced (the CLI's flags win over the environment)."""
        return replace(self, **{k: v for k, v in changes.items() if v is not None})


def _int(env: Mapping[str, str], name: str, default: int, minimum: int) -> int:
    text = env.get(name)
    if text is None or text == "":
        return default
    try:
        value = int(text)
    except ValueError:
        raise SettingsError(f"{name}={text!r} is not an integer") from None
    if value < minimum:
        raise SettingsError(f"{name}={value} must be >= {minimum}")
    return value


def _float(env: Mapping[str, str], name: str, default: float, minimum: float) -> float:
    text = env.get(name)
    if text is None or text == "":
        return default
    try:
        value = float(text)
    except ValueError:
        raise SettingsError(f"{name}={text!r} is not a number") from None
    if not value >= minimum:
        raise SettingsError(f"{name}={value} must be >= {minimum}")
    return value


def _port(env: Mapping[str, str], name: str, default: int) -> int:
    value = _int(env, name, default, 1)
    if value > 65535:
        raise SettingsError(f"{name}={value} is not a TCP port (1 to 65535)")
    return value


def _choice(env: Mapping[str, str], name: str, default: str, choices: tuple[str, ...]) -> str:
    value = (env.get(name) or default).strip().lower()
    if value not in choices:
        raise SettingsError(f"{name}={env.get(name)!r} must be one of {', '.join(choices)}")
    return value


def settings_from_env(env: Mapping[str, str] | None = None) -> Settings:
    """Settings from ``VOXFUSION_*`` variables (see the module docstring for the table)."""
    env = os.environ if env is None else env
    data_dir = env.get("VOXFUSION_DATA_DIR") or default_data_dir(env)
    executor = _choice(env, "VOXFUSION_EXECUTOR", "local", EXECUTORS)
    sessions_default = RAY_MAX_SESSIONS if executor == "ray" else default_max_sessions()
    return Settings(
        data_dir=Path(data_dir).expanduser(),
        port=_port(env, "VOXFUSION_PORT", 8000),
        token=env.get("VOXFUSION_TOKEN") or None,
        max_upload_mb=_int(env, "VOXFUSION_MAX_UPLOAD_MB", 2048, 1),
        max_unzipped_mb=_int(env, "VOXFUSION_MAX_UNZIPPED_MB", 8192, 1),
        max_zip_entries=_int(env, "VOXFUSION_MAX_ZIP_ENTRIES", 200_000, 1),
        max_sessions=_int(env, "VOXFUSION_MAX_SESSIONS", sessions_default, 1),
        max_queued=_int(env, "VOXFUSION_MAX_QUEUED", 32, 1),
        viewer_port=_int(env, "VOXFUSION_VIEWER_PORT", 8080, -1),
        cancel_grace_s=_float(env, "VOXFUSION_CANCEL_GRACE_S", 10.0, 0.0),
        render_threads=_int(env, "VOXFUSION_RENDER_THREADS", 0, 0),
        stream_idle_timeout_s=_float(env, "VOXFUSION_STREAM_IDLE_S", 300.0, 0.0),
        executor=executor,
        ray_address=env.get("VOXFUSION_RAY_ADDRESS") or "auto",
        ray_session_cpus=_float(env, "VOXFUSION_RAY_SESSION_CPUS", 2.0, 0.0),
        ray_session_gpus=_float(env, "VOXFUSION_RAY_SESSION_GPUS", 0.0, 0.0),
        ray_lost_s=_float(env, "VOXFUSION_RAY_LOST_S", 20.0, 1.0),
        ray_scratch=env.get("VOXFUSION_RAY_SCRATCH") or None,
    )
