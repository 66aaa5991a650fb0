"""Calls into the decode helper (``server.decoding``) with a bounded wait, for one kind of
work (parsing assets, reading a session's ground truth).

A request must not wait on the helper for as long as another request keeps it busy: each
queue runs its calls one after the other on a thread of its own, and a caller waits for its
answer at most ``wait_s`` (for its turn) plus ``timeout_s`` (the call's own time limit). Past
that it gets ``server.helper_pool.PoolBusy`` (the API's 503 with ``Retry-After``, as a full
helper pool answers); its call is dropped if
it has not started, or else finishes in the background (its result can still be kept, by the
function queued, for the next request).
"""

from __future__ import annotations

import concurrent.futures
import math
from typing import Any, Callable

from server.helper_pool import PoolBusy


class HelperQueue:
    """Runs ``function(*args)`` calls of one kind one at a time, each answered or refused
    within ``wait_s + timeout_s`` seconds (module doc). ``timeout_s`` is also the time limit the
    queued functions should give their helper call (read when the call starts)."""

    def __init__(self, what: str, wait_s: float, timeout_s: float) -> None:
        self.what = what
        self.wait_s = wait_s
        self.timeout_s = timeout_s
        self._runner = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"helper-{what}")

    def run(self, function: Callable[..., Any], *args: Any) -> Any:
        """``function(*args)`` on the queue's thread; its exceptions are raised here. PoolBusy
        when it has not finished within the bounded wait."""
        future = self._runner.submit(function, *args)
        try:
            return future.result(timeout=self.wait_s + self.timeout_s)
        except concurrent.futures.TimeoutError:
            future.cancel()
            raise PoolBusy(f"the server is busy {self.what}: no answer within {self.wait_s + self.timeout_s:g} s; "
                           "try again in a little while", max(1, math.ceil(self.timeout_s))) from None

    def close(self) -> None:
        """Drop the calls that have not started; one that runs finishes on its own."""
        self._runner.shutdown(wait=False, cancel_futures=True)
