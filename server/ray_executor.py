"""The ``ray`` executor: each session is a Ray actor on a cluster node (``VOXFUSION_EXECUTOR=ray``).

How a session runs
    The API process is a Ray driver; it connects on the first session to
    ``VOXFUSION_RAY_ADDRESS``. A session becomes one :class:`SessionActor` that declares
    ``VOXFUSION_RAY_SESSION_CPUS`` CPUs (and ``VOXFUSION_RAY_SESSION_GPUS`` GPUs when its preset
    runs on ``auto``/``cuda``), so Ray places it on a node with room or keeps it pending; the
    session stays ``queued`` until the actor runs and says where (:class:`WorkerPlaced`). On its
    node the actor starts ``server.worker.run_worker`` in a spawn process, exactly as the local
    executor does here: the tracking process starts its mapping process, both in one process
    group that ends when the actor ends (the worker's parent watch), output in ``worker.log``.

Events, live
    The API keeps one ``drain`` call in flight per session; the actor answers as soon as it has
    events, or after :data:`DRAIN_WAIT_S` with none, so the status and the viewer follow a Ray
    session as they follow a local one, one round trip behind.

Data: Ray's object store, not a shared file system
    A worker node cannot read the API server's disk, and a storage both reach is one more
    thing to deploy, secure and size; Ray already moves objects between nodes. So: an upload's
    extracted ``input/`` goes to the node as one tar object (the upload limits,
    ``VOXFUSION_MAX_UPLOAD_MB`` and ``VOXFUSION_MAX_UNZIPPED_MB``, bound it; the nodes' object
    stores must hold it); a stream's frames go through the actor, one call per frame, after a
    bounded queue in the API (the same back-pressure and 503 as locally); the outputs come back
    in the ``drain`` replies: every file of the node's session folder (``trajectory*.txt``,
    ``mesh.ply``, ``map.pt``, ``run.json``, ``worker.log``) whose size or time changed, at most
    every :data:`SYNC_S` while it runs (the live map for renders) and all of them with the final
    ``WorkerDone``. They are written atomically into the session folder before the events of the
    same reply are applied, so a ``finished`` session has its files. The node's folder
    (``VOXFUSION_RAY_SCRATCH``) is removed once they are home.

Faults
    A cancel asks the actor to stop its worker (``cancel_grace_s`` later it is killed); killing
    the actor ends the worker's process group on the node. A session whose node dies fails
    alone, with a message naming the node, as soon as Ray reports the actor dead or after
    ``VOXFUSION_RAY_LOST_S`` without an answer, whichever comes first. A cluster that cannot be
    reached (``VOXFUSION_RAY_ADDRESS``) fails new sessions at once with that message: its GCS
    port is probed before each start, because Ray's own connect retries for minutes.
"""

from __future__ import annotations

import io
import os
import queue
import secrets
import shutil
import socket
import sys
import tarfile
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

from server.execution import ExecutorError, WorkerInfo, WorkerPlaced, describe_exit
from server.settings import Settings
from server.worker import END_OF_STREAM, WorkerDone, WorkerJob, run_worker

DRAIN_WAIT_S = 0.25
"""Longest time the actor holds a ``drain`` call that has no event to return."""
SYNC_S = 1.0
"""Shortest time between two looks for changed output files while a session runs."""
PROBE_TIMEOUT_S = 2.0
"""How long the GCS port probe before a start waits for a connection."""
FORWARD_POLL_S = 0.25
EXIT_GRACE_S = 30.0
"""How long a worker that sent its WorkerDone may take to exit before its process group is killed."""
INPUT_DIR = "input"


# -- connecting ------------------------------------------------------------------------------


def _host_port(address: str) -> tuple[str, int] | None:
    host, _, port = address.rpartition(":")
    try:
        return host.strip("[]"), int(port)
    except ValueError:
        return None


def _is_loopback(host: str) -> bool:
    return host in ("localhost", "::1") or host.startswith("127.")


def import_ray(address: str | None = None):
    """``import ray``, prepared for a server process.

    * ``RAY_gcs_rpc_server_reconnect_timeout_s``: a Ray driver whose cluster is gone for 60 s
      (the default) ends its own process; here that process is the API server, which must
      outlive the cluster and fail sessions instead (unless the variable is already set).
    * A loopback address (a cluster bound to 127.0.0.1, as in the tests): Ray rewrites
      ``127.0.0.1`` to the machine's interface address before it connects, where such a
      cluster does not listen; ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`` makes it keep loopback.
    """
    os.environ.setdefault("RAY_gcs_rpc_server_reconnect_timeout_s", str(10 * 365 * 24 * 3600))
    parsed = _host_port(address or "")
    if parsed is not None and _is_loopback(parsed[0]):
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    try:
        import ray
    except ImportError:
        raise ExecutorError("VOXFUSION_EXECUTOR=ray needs Ray: pip install 'voxfusion[ray]'") from None
    if parsed is not None and _is_loopback(parsed[0]):
        from ray._private import ray_constants

        ray_constants.ENABLE_RAY_CLUSTER = False  # read at call time; ray may have been imported before
    return ray


def resolve_address(address: str) -> str | None:
    """``host:port`` of the GCS: the address itself, or for ``auto`` the one Ray would use
    (``RAY_ADDRESS``, else the cluster last started on this machine); None when none is known."""
    if address != "auto":
        return address
    try:
        from ray._private.services import canonicalize_bootstrap_address

        return canonicalize_bootstrap_address("auto")
    except Exception:  # noqa: BLE001 - a private helper; without it, ray.init says what is wrong
        return None


def probe(address: str, timeout_s: float = PROBE_TIMEOUT_S) -> str | None:
    """None when something accepts connections at ``host:port``, else why not."""
    parsed = _host_port(address)
    if parsed is None:
        return f"{address!r} is not host:port"
    try:
        with socket.create_connection(parsed, timeout=timeout_s):
            return None
    except OSError as error:
        return error.strerror or str(error)


class RayExecutor:
    """Sessions as Ray actors (module doc)."""

    name = "ray"

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._lock = threading.Lock()
        self._ray = None
        self._gcs: str | None = None
        self._actor_class = None
        self._initialized_here = False

    def connect(self):
        """The ``ray`` module, connected; ExecutorError when the cluster cannot be reached."""
        with self._lock:
            address = self.settings.ray_address
            gcs = self._gcs or resolve_address(address)
            where = f"the Ray cluster at {gcs or address} (VOXFUSION_RAY_ADDRESS={address})"
            if gcs is not None and (why := probe(gcs)) is not None:
                raise ExecutorError(f"{where} cannot be reached: {why}")
            ray = import_ray(gcs)
            if ray.is_initialized() and gcs is not None and ray.get_runtime_context().gcs_address != gcs:
                ray.shutdown()  # connected to another cluster (an earlier server in this process)
            if not ray.is_initialized():
                options = {"_node_ip_address": "127.0.0.1"} if gcs and _is_loopback(_host_port(gcs)[0]) else {}
                try:
                    ray.init(address=gcs or address, namespace="voxfusion", log_to_driver=False,
                             configure_logging=False, **options)
                except (ConnectionError, RuntimeError, ValueError) as error:
                    raise ExecutorError(f"{where} cannot be reached: {error}") from None
                self._initialized_here = True
            self._gcs = ray.get_runtime_context().gcs_address
            if self._actor_class is None:
                self._actor_class = ray.remote(SessionActor)
            self._ray = ray
            return ray

    @property
    def actor_class(self):
        """``SessionActor`` as a Ray actor class (made once: each one is exported to the cluster)."""
        return self._actor_class

    def prepare(self, job: WorkerJob, directory: Path, stream: bool) -> "RayExecution":
        frames = queue.Queue(maxsize=self.settings.stream_queue_frames) if stream else None
        return RayExecution(self, job, directory, frames)

    def resources(self, preset: str) -> dict[str, float]:
        """What a session of ``preset`` declares to Ray."""
        from slam import ConfigError, preset as preset_config

        try:
            device = preset_config(preset).runtime.device
        except ConfigError:
            device = "auto"
        gpus = self.settings.ray_session_gpus if device != "cpu" else 0.0
        return {"num_cpus": self.settings.ray_session_cpus, "num_gpus": gpus}

    def cluster_gone(self) -> str | None:
        """Why the connected cluster's GCS cannot be reached now, or None when it can."""
        gcs = self._gcs or resolve_address(self.settings.ray_address)
        if gcs is None:
            return None
        why = probe(gcs)
        return None if why is None else f"the Ray cluster at {gcs} cannot be reached: {why}"

    def close(self) -> None:
        """Disconnect when this executor connected: the session actors, owned by this driver,
        end with the connection."""
        if self._initialized_here and self._ray is not None and self._ray.is_initialized():
            self._ray.shutdown()
        self._initialized_here = False


class RayExecution:
    """One session's actor, seen from the API process (``server.execution.Execution``)."""

    def __init__(self, executor: RayExecutor, job: WorkerJob, directory: Path, frame_queue) -> None:
        self.executor = executor
        self.job = job
        self.directory = directory
        self.frame_queue = frame_queue
        self._actor = None
        self._ray = None
        self._pending = None
        self._pending_since = 0.0
        self._unavailable_since: float | None = None
        self._worker: WorkerInfo | None = None
        self._ended = False
        self._error: str | None = None
        self._exitcode: int | None = None
        self._forwarder: threading.Thread | None = None
        self._closing = threading.Event()
        self._launch_began = 0.0

    # -- starting --------------------------------------------------------------------------

    def start(self) -> None:
        """Launch in a thread of its own and return at once: connecting and shipping the input
        take seconds (forever, when a cluster stops answering mid-connect), and the manager calls
        this under its lock, which every API request takes. The session is running once the actor
        reports its node (WorkerPlaced); a launch that fails or does not finish within
        ``ray_lost_s`` fails the session with the reason."""
        self._launch_began = time.monotonic()
        threading.Thread(target=self._launch, daemon=True, name=f"ray-start-{self.job.session_id}").start()
        return None

    def _launch(self) -> None:
        try:
            ray = self._ray = self.executor.connect()
            package = pack_input(self.directory / INPUT_DIR) if _reads_files(self.job) else None
            try:
                package_ref = None if package is None else ray.put(package)
            except Exception as error:  # noqa: BLE001 - e.g. ObjectStoreFullError; the message says which
                raise ExecutorError(f"could not ship the input to the Ray cluster: {type(error).__name__}: "
                                    f"{error}") from None
            options = dict(self.executor.resources(self.job.preset), max_concurrency=4, max_restarts=0)
            actor = self.executor.actor_class.options(**options).remote(
                self.job, str(self.directory), package_ref, self.executor.settings.ray_scratch)
        except ExecutorError as error:
            self._end(str(error))
            return
        except Exception as error:  # noqa: BLE001 - anything Ray raises fails this session, with its text
            self._end(f"could not start the session on the Ray cluster: {type(error).__name__}: {error}")
            return
        self._actor = actor
        if self._ended:  # cancelled or timed out meanwhile
            self.finish(None)
            return
        self._submit_drain()
        if self.frame_queue is not None:
            self._forwarder = threading.Thread(target=self._forward_frames, daemon=True,
                                               name=f"ray-frames-{self.job.session_id}")
            self._forwarder.start()

    # -- events ----------------------------------------------------------------------------

    def _submit_drain(self) -> None:
        self._pending = self._actor.drain.remote(DRAIN_WAIT_S)
        self._pending_since = time.monotonic()

    def poll(self, limit: int) -> list[object]:
        if self._ended:
            return []
        if self._pending is None:  # still launching
            waited = time.monotonic() - self._launch_began
            if waited > self.executor.settings.ray_lost_s:
                self._end(f"could not start the session on the Ray cluster within {waited:.0f} s "
                          f"(VOXFUSION_RAY_ADDRESS={self.executor.settings.ray_address}: connecting or shipping "
                          f"the input did not finish; VOXFUSION_RAY_LOST_S)")
            return []
        ray = self._ray
        ready, _ = ray.wait([self._pending], timeout=0)
        if not ready:
            self._check_lost()
            return []
        try:
            reply = ray.get(ready[0])
        except ray.exceptions.ActorUnavailableError:
            # The node does not answer (yet): it may come back; _check_lost decides when not.
            self._unavailable_since = self._unavailable_since or time.monotonic()
            self._check_lost(since=self._unavailable_since)
            if not self._ended:
                self._submit_drain()
            return []
        except ray.exceptions.RayActorError as error:
            self._end(self._died_message(error))
            return []
        self._unavailable_since = None
        write_files(self.directory, reply["files"])
        events = list(reply["events"])
        for event in events:
            if isinstance(event, WorkerPlaced):
                self._worker = event.worker
        if reply["ended"]:
            self._ended = True
            self._exitcode = reply["exitcode"]
        else:
            self._submit_drain()
        return events

    def _check_lost(self, since: float | None = None) -> None:
        """Fail the session when its node has not answered for ``ray_lost_s`` (or, while it is not
        placed yet, when the cluster itself is gone)."""
        lost_s = self.executor.settings.ray_lost_s
        waited = time.monotonic() - (since or self._pending_since)
        if waited < lost_s + DRAIN_WAIT_S:
            return
        gone = self.executor.cluster_gone()
        if self._worker is not None:
            why = gone or "the node died or is cut off"
            self._end(f"lost the Ray node {self._where()} that ran this session: no answer for {waited:.0f} s "
                      f"({why}; VOXFUSION_RAY_LOST_S={lost_s:g})")
            return
        if gone is not None:
            self._end(f"{gone}; the session never started")
        else:
            self._pending_since = time.monotonic()  # still waiting for room on the cluster: fine

    def _died_message(self, error: Exception) -> str:
        text = str(error)
        if "node" in text.lower() and ("died" in text.lower() or "dead" in text.lower()):
            return f"the Ray node {self._where()} that ran this session died; the session is lost"
        first = next((line.strip() for line in text.splitlines() if line.strip()), type(error).__name__)
        return f"the session's Ray actor on node {self._where()} died: {first}"

    def _where(self) -> str:
        worker = self._worker
        if worker is None:
            return "(not placed yet)"
        return f"{(worker.node or '?')[:12]} ({worker.address})"

    def _end(self, error: str | None) -> None:
        self._ended = True
        self._error = self._error or error
        self._closing.set()

    # -- frames of a stream ----------------------------------------------------------------

    def _forward_frames(self) -> None:
        """Move frames from the API's bounded queue to the actor, one call at a time (calls to
        a threaded actor may run out of order, frames must not)."""
        ray = self._ray
        while not self._closing.is_set():
            try:
                item = self.frame_queue.get(timeout=FORWARD_POLL_S)
            except queue.Empty:
                continue
            ref = self._actor.put_frame.remote(item)
            while not self._closing.is_set():
                ready, _ = ray.wait([ref], timeout=FORWARD_POLL_S)
                if ready:
                    break
            if item is END_OF_STREAM:
                return

    # -- stopping --------------------------------------------------------------------------

    def is_alive(self) -> bool:
        return not self._ended

    def request_stop(self) -> None:
        if self._ended:
            return
        if self._actor is None:  # still launching: the launch thread ends what it made
            self._end(None)
            return
        if self._worker is None:  # still waiting for a node: nothing runs yet
            self.kill()
            return
        self._actor.stop.remote()

    def kill(self) -> None:
        if self._actor is not None and self._ray is not None:
            try:
                self._ray.kill(self._actor, no_restart=True)
            except Exception as error:  # noqa: BLE001 - an actor already gone with its node
                print(f"voxfusion: ray.kill of session {self.job.session_id}: {error}")
        self._end("the session's Ray actor was killed")

    def exit_error(self) -> str:
        if self._error is not None:
            return self._error
        return describe_exit(self._exitcode) + f" (on Ray node {self._where()})"

    def finish(self, worker_pid: int | None) -> None:
        self._closing.set()
        if self._actor is not None and self._ray is not None:
            try:
                self._ray.kill(self._actor, no_restart=True)  # its worker's process group ends with it
            except Exception:  # noqa: BLE001 - gone already
                pass

    def release(self) -> None:
        self._closing.set()
        self._actor = self._pending = None


def _reads_files(job: WorkerJob) -> bool:
    return any(spec.kind == "dataset" for spec in job.sources)


def pack_input(input_dir: Path) -> bytes:
    """The session's ``input/`` folder as an uncompressed tar (images are compressed already)."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        tar.add(input_dir, arcname=INPUT_DIR)
    return buffer.getvalue()


def write_files(directory: Path, files: dict[str, bytes]) -> None:
    """Write shipped output files into the session folder, each atomically (readers never see
    half a ``map.pt``). Names are plain file names (checked: they come over the network)."""
    for name, data in files.items():
        if Path(name).name != name or name.startswith("."):
            print(f"voxfusion: ignoring a shipped file with an odd name: {name!r}")
            continue
        tmp = directory / f".{name}.ray-tmp"
        tmp.write_bytes(data)
        os.replace(tmp, directory / name)


# -- the node side ---------------------------------------------------------------------------


class SessionActor:
    """Runs on the node Ray chose: the session's worker process and the transfers (module doc).
    Threaded (``max_concurrency``): ``drain``, ``put_frame`` and ``stop`` come concurrently."""

    def __init__(self, job: WorkerJob, api_dir: str, package: bytes | None, scratch_root: str | None) -> None:
        import multiprocessing as mp

        import ray

        root = Path(scratch_root or Path(tempfile.gettempdir()) / "voxfusion-ray")
        self.scratch = root / f"{job.session_id}-{secrets.token_hex(4)}"
        self.scratch.mkdir(parents=True)
        if package is not None:
            unpack_input(package, self.scratch)
        self.job = relocate(job, api_dir, str(self.scratch))
        context = ray.get_runtime_context()
        node_id = context.get_node_id()
        address = next((n["NodeManagerAddress"] for n in ray.nodes() if n["NodeID"] == node_id), None)
        self._placed: WorkerPlaced | None = WorkerPlaced(WorkerInfo(executor="ray", node=node_id, address=address))
        ctx = mp.get_context("spawn")
        self._stop = ctx.Event()
        self._events = ctx.Queue()
        self._frames = ctx.Queue(maxsize=4) if job.source.kind == "stream" else None
        self._process = ctx.Process(target=run_worker, args=(self.job, self._stop, self._events, self._frames),
                                    name=f"voxfusion-session-{job.session_id}", daemon=False)
        _spawn_with_plain_main(self._process)
        self._events._writer.close()
        self._synced: dict[str, tuple[int, int]] = {}
        self._synced_at = 0.0
        self._done_at: float | None = None

    def drain(self, wait_s: float, limit: int = 200) -> dict:
        """Events so far (waits up to ``wait_s`` for the first), changed files, and whether the
        worker has ended with everything sent."""
        exited = not self._process.is_alive()
        events: list[object] = []
        if self._placed is not None:
            events.append(self._placed)
            self._placed = None
        deadline = time.monotonic() + wait_s
        while len(events) < limit:
            timeout = 0.0 if events or exited else max(0.0, deadline - time.monotonic())
            try:
                events.append(self._events.get(timeout=timeout) if timeout else self._events.get_nowait())
            except queue.Empty:
                break
            except (EOFError, OSError, ValueError):
                break
        if any(isinstance(e, WorkerDone) for e in events):
            self._done_at = time.monotonic()  # its outputs are complete: ship them all now
        elif self._done_at is not None and not exited and time.monotonic() - self._done_at > EXIT_GRACE_S:
            _kill_group(self._process.pid)  # reported its end but does not exit: end it
        files = self._changed_files(force=exited or self._done_at is not None)
        # Never wait here for the process to exit (a slow exit would read as a lost node in the
        # API): a later drain sees it gone.
        ended = exited and len(events) < limit
        if ended:
            shutil.rmtree(self.scratch, ignore_errors=True)
        return {"events": events, "files": files, "ended": ended, "exitcode": self._process.exitcode}

    def _changed_files(self, force: bool) -> dict[str, bytes]:
        now = time.monotonic()
        if not force and now - self._synced_at < SYNC_S:
            return {}
        self._synced_at = now
        files: dict[str, bytes] = {}
        for path in sorted(self.scratch.iterdir()):
            if not path.is_file() or path.name.startswith("."):
                continue
            try:
                stat = path.stat()
                key = (stat.st_mtime_ns, stat.st_size)
                if self._synced.get(path.name) == key:
                    continue
                files[path.name] = path.read_bytes()
                self._synced[path.name] = key
            except OSError:
                continue  # replaced while read: the next look takes it
        return files

    def put_frame(self, item) -> bool:
        """Hand one stream frame (or END_OF_STREAM) to the worker; waits while its buffer is full."""
        while not self._stop.is_set() and self._process.is_alive():
            try:
                self._frames.put(item, timeout=FORWARD_POLL_S)
                return True
            except queue.Full:
                continue
        return False

    def stop(self) -> None:
        self._stop.set()


def _kill_group(group: int | None) -> None:
    import signal

    if group is None:
        return
    try:
        os.killpg(group, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def _spawn_with_plain_main(process) -> None:
    """Start a spawn process from a Ray worker. Spawn re-runs the parent's ``__main__`` file in
    the child; a Ray worker's ``__main__`` is Ray's worker script, which must not run there."""
    main = sys.modules.get("__main__")
    saved = getattr(main, "__file__", None)
    if saved is not None:
        del main.__file__
    try:
        process.start()
    finally:
        if saved is not None:
            main.__file__ = saved


def unpack_input(package: bytes, scratch: Path) -> None:
    with tarfile.open(fileobj=io.BytesIO(package), mode="r") as tar:
        tar.extractall(scratch, filter="data")


def relocate(job: WorkerJob, api_dir: str, node_dir: str) -> WorkerJob:
    """The job with its folder and its input paths moved from the API's session folder to the
    node's."""
    def moved(path: str | None) -> str | None:
        if path is None or not path.startswith(api_dir):
            return path
        return node_dir + path[len(api_dir):]

    sources = tuple(replace(s, path=moved(s.path)) if s.kind == "dataset" else s for s in job.sources)
    return replace(job, sources=sources, out_dir=node_dir)
