"""How long and how large a client may make the part of a request uvicorn reads itself.

uvicorn closes a keep-alive connection that sends nothing for ``timeout_keep_alive`` seconds
after a response, and answers 503 past ``limit_concurrency`` connections and tasks, but it
sets no deadline on a request's head (request line and headers) and its default parser
(httptools) no bound on the head's size: a client that opens connections and sends a header
byte now and then holds each of them for good. :class:`HeadDeadlineProtocol` is uvicorn's
httptools protocol with both bounds; :func:`uvicorn_limits` is the set ``voxfusion serve``
gives uvicorn.

Not covered here: a body sent slowly once its head is complete (a dataset upload may
legitimately take minutes; the body's size is bounded by ``server.budget``), and WebSockets,
which uvicorn pings (``ws_ping_interval``) and closes when the pong does not come.
"""

from __future__ import annotations

import asyncio

HEAD_TIMEOUT_S = 20.0
"""A request's line and headers must arrive within this many seconds of its first byte (or
of the connection, for its first request)."""
MAX_HEAD_BYTES = 64 * 1024
"""Largest request head; browsers send a few KiB, cookies included."""
KEEP_ALIVE_S = 5
"""An idle keep-alive connection is closed after this many seconds (uvicorn's own limit)."""
MAX_CONNECTIONS = 1000
"""Connections and requests at once; more get 503 (a file descriptor each, and the
sessions' files need theirs too)."""

try:
    from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
except ImportError:  # uvicorn without httptools: h11 bounds the head's size, not its time
    HttpToolsProtocol = None


def _response(status: int, reason: str, text: str) -> bytes:
    body = text.encode()
    return (f"HTTP/1.1 {status} {reason}\r\ncontent-type: text/plain; charset=utf-8\r\nconnection: close\r\n"
            f"content-length: {len(body)}\r\n\r\n").encode() + body


if HttpToolsProtocol is not None:
    class HeadDeadlineProtocol(HttpToolsProtocol):
        """uvicorn's httptools protocol that closes a connection whose request head takes
        longer than :attr:`head_timeout_s` (408 once part of it came) or grows past
        :attr:`max_head_bytes` (431)."""

        head_timeout_s = HEAD_TIMEOUT_S
        max_head_bytes = MAX_HEAD_BYTES

        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            self._head_timer: asyncio.TimerHandle | None = None
            self._head_bytes = 0
            self._in_head = True  # the connection's first request starts with it

        def connection_made(self, transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            self._start_head_clock()

        def connection_lost(self, exc: Exception | None) -> None:
            self._stop_head_clock()
            super().connection_lost(exc)

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            if not self._in_head or self.transport.is_closing():
                return
            self._head_bytes += len(data)  # all of it is head: the parser has not finished one
            if self._head_bytes > self.max_head_bytes:
                self._refuse(_response(431, "Request Header Fields Too Large",
                                       f"the request line and headers are larger than {self.max_head_bytes} bytes"))

        def on_message_begin(self) -> None:
            super().on_message_begin()
            self._in_head, self._head_bytes = True, 0
            if self._head_timer is None:
                self._start_head_clock()

        def on_headers_complete(self) -> None:
            self._in_head = False
            self._stop_head_clock()
            super().on_headers_complete()

        def _start_head_clock(self) -> None:
            self._head_timer = self.loop.call_later(self.head_timeout_s, self._head_timed_out)

        def _stop_head_clock(self) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
                self._head_timer = None

        def _head_timed_out(self) -> None:
            self._head_timer = None
            if not self._in_head:
                return
            # Silence is closed silently (a browser's spare connection); a partial head gets 408.
            answer = _response(408, "Request Timeout", f"the request line and headers did not arrive within "
                                                       f"{self.head_timeout_s:g} s") if self._head_bytes else b""
            self._refuse(answer)

        def _refuse(self, answer: bytes) -> None:
            self._stop_head_clock()
            self._in_head = False
            if self.transport.is_closing():
                return
            if answer and (self.cycle is None or self.cycle.response_complete):
                self.transport.write(answer)
            self.transport.close()
else:
    HeadDeadlineProtocol = None


def uvicorn_limits() -> dict:
    """Keyword arguments for ``uvicorn.Config``: the limits above (module doc)."""
    limits = {"timeout_keep_alive": KEEP_ALIVE_S, "limit_concurrency": MAX_CONNECTIONS}
    if HeadDeadlineProtocol is not None:
        return {**limits, "http": HeadDeadlineProtocol}
    return {**limits, "http": "h11", "h11_max_incomplete_event_size": MAX_HEAD_BYTES}
