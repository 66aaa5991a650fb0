"""Helper processes for work whose cost a client chooses, and pools of them per kind of work.

A :class:`Helper` is one spawned process that serves picklable calls one at a time: it
imports its kind's modules, caps its own address space at ``memory_limit_bytes`` above that
start-up footprint, says it is ready, then runs ``function(*args)`` per message and sends the
result back. A call that outlives its time limit, or a helper that dies (an allocation past
the cap, a crash), fails that call with :class:`HelperFailed` saying so, and the helper is
replaced on the next call. The time limit counts from the call, not from the helper's start.

A :class:`HelperPool` holds ``size`` helpers of one kind. A caller takes an idle one; when
all are busy it waits (at most ``max_waiting`` callers wait, each at most ``wait_s``) and
beyond that gets :class:`PoolBusy` at once, which routes answer 503 with ``Retry-After``. So
the API process runs none of the work and holds none of its memory: it only waits on pipes,
with a bounded number of threads (``size + max_waiting`` per pool).

A call may report progress while it runs (:func:`report_progress`, e.g. a video's frames):
the caller's ``on_progress(done, total)`` gets each report.
"""

from __future__ import annotations

import importlib
import multiprocessing as mp
import os
import pickle
import resource
import threading
import time
import traceback
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Callable, Iterator

from starlette.concurrency import run_in_threadpool

STARTUP_TIMEOUT_S = 120.0
"""Longest a helper may take to import its modules (torch: seconds on a loaded machine)."""


@dataclass(frozen=True)
class HelperKind:
    """What a helper does, as its messages name it, and its limits."""

    name: str
    """Short name: the process is ``voxfusion-<name>``."""
    task: str
    """The work, as a message's subject: "decoding", "rendering"."""
    unit: str
    """One call, as a noun: "decode", "render"."""
    memory_limit_bytes: int
    """Address space a helper may take on top of its start-up footprint."""
    timeout_s: float
    """Longest one call may run (a call may ask for another)."""
    preload: tuple[str, ...] = ()
    """Modules imported before the cap is set (the heavy imports)."""
    niceness: int = 0
    """Added to the helper's nice value: long work yields the CPU to the API process."""


class HelperFailed(RuntimeError):
    """The helper could not finish a call: it died (memory, a crash) or ran out of time."""


class HelperTimedOut(HelperFailed):
    """The call outlived its time limit (the helper was stopped and will be replaced)."""


class PoolBusy(RuntimeError):
    """Every helper of the pool is busy and the callers' queue is full (or the wait ran out)."""

    def __init__(self, message: str, retry_after_s: int) -> None:
        super().__init__(message, retry_after_s)
        self.message, self.retry_after_s = message, retry_after_s

    def __str__(self) -> str:
        return self.message


@dataclass(frozen=True)
class _Raised:
    """An exception raised by the called function, sent back whole when it pickles."""

    error: BaseException | None
    text: str


@dataclass(frozen=True)
class _Progress:
    done: int
    total: int


_READY = "ready"
_connection = None
"""In a helper process: its end of the pipe (for :func:`report_progress`)."""


def report_progress(done: int, total: int) -> None:
    """Called by work running in a helper: the caller's ``on_progress(done, total)`` gets it.
    Does nothing outside a helper (the same function runs in tests in-process)."""
    if _connection is not None:
        _connection.send(_Progress(int(done), int(total)))


def _limit_address_space(extra_bytes: int) -> None:
    """Cap this process's address space at what it maps now plus ``extra_bytes``."""
    with open("/proc/self/status") as status:
        size_kb = next(int(line.split()[1]) for line in status if line.startswith("VmSize:"))
    limit = size_kb * 1024 + extra_bytes
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))


def _raised(error: BaseException) -> _Raised:
    text = "".join(traceback.format_exception_only(type(error), error)).strip()
    try:
        pickle.dumps(error)
        return _Raised(error, text)
    except Exception:  # noqa: BLE001 - an exception that does not pickle goes back as text
        return _Raised(None, f"{type(error).__name__}: {error}")


def _serve(connection, kind: HelperKind) -> None:
    """The helper's loop: (function, args) in, progress then result or _Raised out, until the
    pipe closes."""
    global _connection
    if kind.niceness:
        os.nice(kind.niceness)
    # Before torch loads OpenMP: idle threads sleep instead of spinning, since helpers share the
    # cores with each other, the sessions and the API (a spinning thread without a core of its
    # own stalls every operation of a render).
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    for module in kind.preload:  # the heavy imports happen before the cap is set
        importlib.import_module(module)
    try:
        _limit_address_space(kind.memory_limit_bytes)
    except (OSError, ValueError, StopIteration):
        pass  # no /proc or no rlimit here: the request-side limits still bound every call
    _connection = connection
    connection.send(_READY)
    while True:
        try:
            function, args = connection.recv()
        except EOFError:
            return
        try:
            reply: Any = function(*args)
        except MemoryError:
            reply = _Raised(None, "MemoryError")
        except BaseException as error:  # noqa: BLE001 - every error goes back to the caller
            reply = _raised(error)
        try:
            connection.send(reply)
        except Exception as error:  # noqa: BLE001 - a result that does not pickle
            connection.send(_raised(error))


class Helper:
    """One helper process of ``kind`` (module doc); thread-safe, one call at a time."""

    def __init__(self, kind: HelperKind) -> None:
        self.kind = kind
        self.timeout_s = kind.timeout_s
        self._lock = threading.Lock()
        self._process: mp.Process | None = None
        self._connection = None

    @property
    def pid(self) -> int | None:
        return self._process.pid if self._process is not None and self._process.is_alive() else None

    def _ensure_started(self) -> None:
        if self._process is not None and self._process.is_alive():
            return
        self._discard()
        context = mp.get_context("spawn")
        parent, child = context.Pipe()
        process = context.Process(target=_serve, args=(child, self.kind), name=f"voxfusion-{self.kind.name}",
                                  daemon=True)
        process.start()
        child.close()
        self._process, self._connection = process, parent
        try:
            ready = parent.poll(STARTUP_TIMEOUT_S) and parent.recv() == _READY
        except (EOFError, OSError):
            ready = False
        if not ready:
            code = process.exitcode
            self._discard()
            raise HelperFailed(f"the {self.kind.name} helper did not start (exit code {code})")

    def _discard(self) -> None:
        if self._process is not None and self._process.is_alive():
            self._process.kill()
            self._process.join(timeout=5)
        if self._connection is not None:
            self._connection.close()
        self._process = self._connection = None

    def _died(self) -> HelperFailed:
        code = self._process.exitcode if self._process is not None else None
        self._discard()
        return HelperFailed(f"the {self.kind.name} helper ended during the {self.kind.unit} (exit code {code}; "
                            f"likely over its memory budget of {self.kind.memory_limit_bytes // 2**20} MiB)")

    def _receive(self, timeout: float, on_progress: Callable[[int, int], None] | None) -> Any:
        """The call's reply, passing progress reports on; HelperTimedOut after ``timeout``."""
        deadline = time.monotonic() + timeout
        while True:
            if not self._connection.poll(max(0.0, deadline - time.monotonic())):
                self._discard()
                raise HelperTimedOut(f"{self.kind.task} took longer than {timeout:g} s, the limit for one "
                                     f"{self.kind.unit}")
            reply = self._connection.recv()
            if not isinstance(reply, _Progress):
                return reply
            if on_progress is not None:
                on_progress(reply.done, reply.total)

    def call(self, function: Callable[..., Any], *args: Any, timeout_s: float | None = None,
             on_progress: Callable[[int, int], None] | None = None) -> Any:
        """``function(*args)`` in the helper; its exceptions are raised here again (those that
        do not pickle as RuntimeError with their text). HelperFailed when the helper dies,
        HelperTimedOut when the call outlives ``timeout_s`` (default the kind's)."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        with self._lock:
            self._ensure_started()
            try:
                self._connection.send((function, args))
                reply = self._receive(timeout, on_progress)
            except (EOFError, OSError, BrokenPipeError):
                raise self._died() from None
        if isinstance(reply, _Raised):
            if reply.error is not None:
                raise reply.error
            if reply.text == "MemoryError":
                raise HelperFailed(f"{self.kind.task} needs more than the {self.kind.memory_limit_bytes // 2**20} MiB "
                                   f"a {self.kind.unit} may take")
            raise RuntimeError(reply.text)
        return reply

    def close(self) -> None:
        """Stop the helper (a call in flight fails); the next call starts a new one."""
        connection, process = self._connection, self._process
        if connection is not None:
            try:
                connection.close()
            except OSError:
                pass
        if process is not None:
            process.join(timeout=2)
            if process.is_alive():
                process.kill()
                process.join(timeout=5)


class HelperPool:
    """``size`` helpers of ``kind``, with a bounded queue of callers (module doc)."""

    def __init__(self, kind: HelperKind, size: int, max_waiting: int, wait_s: float, retry_after_s: int) -> None:
        if size < 1 or max_waiting < 0:
            raise ValueError(f"a pool needs at least one helper and a queue of 0 or more, got {size}, {max_waiting}")
        self.kind, self.size, self.max_waiting = kind, size, max_waiting
        self.wait_s, self.retry_after_s = wait_s, retry_after_s
        self._helpers = [Helper(kind) for _ in range(size)]
        self._idle = list(self._helpers)
        self._waiting = 0
        self._condition = threading.Condition()

    @property
    def timeout_s(self) -> float:
        """The time limit of one call in this pool's helpers."""
        return self._helpers[0].timeout_s

    @timeout_s.setter
    def timeout_s(self, seconds: float) -> None:
        for helper in self._helpers:
            helper.timeout_s = seconds

    def _busy(self, why: str) -> PoolBusy:
        return PoolBusy(f"the server is busy: {why} ({self.size} {self.kind.unit}s run at once, {self.max_waiting} "
                        f"may wait); retry after {self.retry_after_s} s", self.retry_after_s)

    @contextmanager
    def lease(self) -> Iterator[Helper]:
        """An idle helper for the caller's calls, waiting at most ``wait_s`` for one;
        PoolBusy at once when ``max_waiting`` callers already wait."""
        with self._condition:
            if not self._idle and self._waiting >= self.max_waiting:
                raise self._busy(f"every {self.kind.name} helper is busy and the queue is full")
            self._waiting += 1
            try:
                deadline = time.monotonic() + self.wait_s
                while not self._idle:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        raise self._busy(f"no {self.kind.name} helper came free within {self.wait_s:g} s")
                    self._condition.wait(remaining)
            finally:
                self._waiting -= 1
            helper = self._idle.pop()
        try:
            yield helper
        finally:
            with self._condition:
                self._idle.append(helper)
                self._condition.notify()

    def call(self, function: Callable[..., Any], *args: Any, timeout_s: float | None = None,
             on_progress: Callable[[int, int], None] | None = None) -> Any:
        """``function(*args)`` in one of the pool's helpers (blocking; ``Helper.call``)."""
        with self.lease() as helper:
            return helper.call(function, *args, timeout_s=timeout_s, on_progress=on_progress)

    async def run(self, function: Callable[..., Any], *args: Any, timeout_s: float | None = None) -> Any:
        """:meth:`call` from the event loop: a thread of the API process waits on the pipe."""
        return await run_in_threadpool(self.call, function, *args, timeout_s=timeout_s)

    def pids(self) -> list[int]:
        """Process ids of the helpers that are running now."""
        return [pid for pid in (helper.pid for helper in self._helpers) if pid is not None]

    def close(self) -> None:
        for helper in self._helpers:
            helper.close()
