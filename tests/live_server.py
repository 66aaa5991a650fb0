"""A real uvicorn on 127.0.0.1 in a thread, for tests that need a live server (browsers,
WebSockets, clients in other processes)."""

from __future__ import annotations

import socket
import threading
import time
from dataclasses import dataclass


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@dataclass
class LiveServer:
    url: str
    server: object
    """The ``uvicorn.Server`` (set ``should_exit`` to stop it early)."""
    thread: threading.Thread

    def stop(self) -> None:
        self.server.should_exit = True  # type: ignore[attr-defined]
        self.thread.join(timeout=30)


def start_uvicorn(app, startup_timeout_s: float = 60.0, **config) -> LiveServer:
    """Serve ``app`` on a free 127.0.0.1 port until ``stop``; returns once it accepts requests."""
    import uvicorn

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", **config))
    thread = threading.Thread(target=server.run, name="test-uvicorn", daemon=True)
    thread.start()
    deadline = time.monotonic() + startup_timeout_s
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "uvicorn did not start"
        time.sleep(0.05)
    return LiveServer(f"http://127.0.0.1:{port}", server, thread)
