"""Decoding of uploaded data in a helper process, never in the API process's memory.

Opening an uploaded dataset and decoding its frames (to check an upload, or to put an input
frame behind an AR composite) runs untrusted bytes through image decoders. Image headers are
checked before any decoding (``slam.data.images``), and this module adds the second wall: the
work runs in a spawned helper process whose address space is capped at
``memory_limit_bytes`` above what it holds after start-up, with a time limit per call. Whatever
an input does to that process (a decoder bug, an allocation past the cap, a hang), the API
process and the sessions it supervises are untouched: the call fails with a clear message and
the helper is replaced.

One helper serves calls one at a time (each is short: a zip's headers and first frame); a
second caller waits for it. The helper starts on first use (it imports torch through
``slam.data``: about 2 s) and is reused.
"""

from __future__ import annotations

import multiprocessing as mp
import resource
import threading
import traceback
from dataclasses import dataclass
from typing import Any, Callable

DEFAULT_MEMORY_LIMIT_BYTES = 1024 * 1024 * 1024
"""Address space a helper may take on top of its own start-up footprint (one decode's budget)."""
DEFAULT_CALL_TIMEOUT_S = 120.0
"""Longest one call may run (a zip of 2,000 frames checks its headers in seconds)."""


class DecodeFailed(RuntimeError):
    """The helper could not finish a call: it died (memory, a crash) or ran out of time."""


@dataclass(frozen=True)
class _Raised:
    """An exception raised by the called function, sent back whole when it pickles."""

    error: BaseException | None
    text: str


def _limit_address_space(extra_bytes: int) -> None:
    """Cap this process's address space at what it maps now plus ``extra_bytes``."""
    with open("/proc/self/status") as status:
        size_kb = next(int(line.split()[1]) for line in status if line.startswith("VmSize:"))
    limit = size_kb * 1024 + extra_bytes
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))


def _serve(connection, extra_bytes: int) -> None:
    """The helper's loop: (function, args) in, result or _Raised out, until the pipe closes."""
    import slam.data  # noqa: F401 - the heavy imports happen before the cap is set

    try:
        _limit_address_space(extra_bytes)
    except (OSError, ValueError, StopIteration):
        pass  # no /proc or no rlimit here: the header checks still bound every decode
    while True:
        try:
            function, args = connection.recv()
        except EOFError:
            return
        try:
            reply: Any = function(*args)
        except MemoryError:
            reply = _Raised(None, "MemoryError: the data needs more memory than a decode may take")
        except BaseException as error:  # noqa: BLE001 - every error goes back to the caller
            try:
                import pickle

                pickle.dumps(error)
                reply = _Raised(error, "".join(traceback.format_exception_only(type(error), error)).strip())
            except Exception:  # noqa: BLE001
                reply = _Raised(None, f"{type(error).__name__}: {error}")
        connection.send(reply)


class DecodeHelper:
    """Runs picklable functions in a memory-capped helper process (module doc)."""

    def __init__(self, memory_limit_bytes: int = DEFAULT_MEMORY_LIMIT_BYTES,
                 timeout_s: float = DEFAULT_CALL_TIMEOUT_S) -> None:
        self.memory_limit_bytes = memory_limit_bytes
        self.timeout_s = timeout_s
        self._lock = threading.Lock()
        self._process: mp.Process | None = None
        self._connection = None

    def _ensure_started(self) -> None:
        if self._process is not None and self._process.is_alive():
            return
        self._discard()
        context = mp.get_context("spawn")
        parent, child = context.Pipe()
        process = context.Process(target=_serve, args=(child, self.memory_limit_bytes), name="voxfusion-decode",
                                  daemon=True)
        process.start()
        child.close()
        self._process, self._connection = process, parent

    def _discard(self) -> None:
        if self._process is not None and self._process.is_alive():
            self._process.kill()
            self._process.join(timeout=5)
        if self._connection is not None:
            self._connection.close()
        self._process = self._connection = None

    def call(self, function: Callable[..., Any], *args: Any, timeout_s: float | None = None) -> Any:
        """``function(*args)`` in the helper; its exceptions are raised here again (those that
        do not pickle as RuntimeError with their text). DecodeFailed when the helper dies or
        the call outlives ``timeout_s``."""
        timeout = self.timeout_s if timeout_s is None else timeout_s
        with self._lock:
            self._ensure_started()
            try:
                self._connection.send((function, args))
                if not self._connection.poll(timeout):
                    self._discard()
                    raise DecodeFailed(f"decoding took longer than {timeout:g} s")
                reply = self._connection.recv()
            except (EOFError, OSError, BrokenPipeError):
                code = self._process.exitcode if self._process is not None else None
                self._discard()
                raise DecodeFailed("the decoder process ended while reading the data "
                                   f"(exit code {code}; likely over its memory budget)") from None
        if isinstance(reply, _Raised):
            if reply.error is not None:
                raise reply.error
            if reply.text.startswith("MemoryError"):
                raise DecodeFailed(f"decoding needs more than the {self.memory_limit_bytes // 2**20} MiB a decode "
                                   "may take")
            raise RuntimeError(reply.text)
        return reply

    def close(self) -> None:
        with self._lock:
            if self._connection is not None:
                try:
                    self._connection.close()
                except OSError:
                    pass
            if self._process is not None:
                self._process.join(timeout=2)
            self._discard()


_shared: DecodeHelper | None = None
_shared_lock = threading.Lock()


def shared_helper() -> DecodeHelper:
    """The process-wide helper (one per API process, made on first use)."""
    global _shared
    with _shared_lock:
        if _shared is None:
            _shared = DecodeHelper()
        return _shared
