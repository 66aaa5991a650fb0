"""Decoding of uploaded data in a helper process, never in the API process's memory.

Opening an uploaded dataset and decoding its frames (to check an upload, or to put an input
frame behind an AR composite) runs untrusted bytes through image decoders. Image headers are
checked before any decoding (``slam.data.images``), and this module adds the second wall: the
work runs in a spawned helper process (``server.helper_pool.Helper``) whose address space is
capped at ``memory_limit_bytes`` above what it holds after start-up, with a time limit per
call. Whatever an input does to that process (a decoder bug, an allocation past the cap, a
hang), the API process and the sessions it supervises are untouched: the call fails with a
clear message and the helper is replaced.

One helper serves calls one at a time (each is short: a zip's headers and first frame); a
second caller waits for it. The helper starts on first use (it imports torch through
``slam.data``: about 2 s) and is reused.
"""

from __future__ import annotations

import threading

from server.helper_pool import Helper, HelperFailed, HelperKind

DEFAULT_MEMORY_LIMIT_BYTES = 1024 * 1024 * 1024
"""Address space a helper may take on top of its own start-up footprint (one decode's budget)."""
DEFAULT_CALL_TIMEOUT_S = 120.0
"""Longest one call may run (a zip of 2,000 frames checks its headers in seconds)."""

DecodeFailed = HelperFailed
"""The helper could not finish a call: it died (memory, a crash) or ran out of time."""


class DecodeHelper(Helper):
    """Runs picklable functions in a memory-capped helper process (module doc):
    ``call(function, *args, timeout_s=None)``."""

    def __init__(self, memory_limit_bytes: int = DEFAULT_MEMORY_LIMIT_BYTES,
                 timeout_s: float = DEFAULT_CALL_TIMEOUT_S) -> None:
        super().__init__(HelperKind("decode", "decoding", "decode", memory_limit_bytes, timeout_s,
                                    preload=("slam.data",)))
        self.memory_limit_bytes = memory_limit_bytes


_shared: DecodeHelper | None = None
_shared_lock = threading.Lock()


def shared_helper() -> DecodeHelper:
    """The process-wide helper (one per API process, made on first use)."""
    global _shared
    with _shared_lock:
        if _shared is None:
            _shared = DecodeHelper()
        return _shared
