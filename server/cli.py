"""``voxfusion serve`` and ``voxfusion demo``, added to the core command line (``slam.cli``).

``main`` is the installed console script: it builds the core parser (run, eval-ate, eval-mesh,
render), adds the server's subcommands, and calls the chosen subcommand's ``handler``.

Stopping (SIGTERM, Ctrl-C): the signal handler first asks the session manager to stop every
running session (``SessionManager.request_shutdown``), so workers write their trajectories and
maps at once; uvicorn then drains open connections for at most :data:`GRACEFUL_SHUTDOWN_S`
(a client that sends its body a byte a second no longer holds the server) and the app's
shutdown waits for the workers until ``min(VOXFUSION_CANCEL_GRACE_S, 5)`` seconds after the
signal, killing what is left. Everything is done well within the 10 s ``docker stop`` gives.

Slow and idle connections: uvicorn runs with ``server.connection_limits`` (a deadline and a
size cap on each request's head, the keep-alive timeout, a cap on connections at once).
"""

from __future__ import annotations

import argparse
import ipaddress
import socket
import sys
from pathlib import Path

DEFAULT_DEMO_SPEC = "orbit?frames=150&width=320&height=240"


def add_server_commands(subparsers) -> None:
    """Add ``serve``, ``demo`` and ``stream`` to an argparse subparsers action."""
    serve = subparsers.add_parser("serve", help="run the web application (API, page, live viewer)",
                                  description="Run the web application. Settings not given here come from "
                                              "VOXFUSION_* environment variables (see server/README.md).")
    _server_options(serve)
    serve.set_defaults(handler=serve_command)

    demo = subparsers.add_parser("demo", help="the web application with a synthetic session already running",
                                 description="Start the server and one session on the built-in synthetic scene, "
                                             "then print the URL to open.")
    _server_options(demo)
    demo.add_argument("--preset", choices=("test", "cpu", "paper", "gpu"), default=None,
                      help="config preset (default: paper with a GPU, else cpu)")
    demo.add_argument("--spec", default=DEFAULT_DEMO_SPEC,
                      help=f"synthetic scene spec (default {DEFAULT_DEMO_SPEC!r})")
    demo.set_defaults(handler=demo_command)

    from client.stream import add_stream_arguments

    stream = subparsers.add_parser("stream", help="send a camera or a replayed dataset folder to a running server",
                                   description="Create a stream session on a running server and send it frames "
                                               "over its WebSocket: a dataset folder replayed in time, 'realsense' "
                                               "or a RealSense .bag. Exit codes: 0 ok, 1 the stream failed, "
                                               "2 bad source, 3 server unreachable or refused, 130 Ctrl-C (the session is still finished).")
    add_stream_arguments(stream)
    stream.set_defaults(handler=stream_command)


def _server_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1",
                        help="interface to bind (default 127.0.0.1; use 0.0.0.0 only with VOXFUSION_TOKEN set)")
    parser.add_argument("--port", type=int, default=None, help="HTTP port (default VOXFUSION_PORT or 8000)")
    parser.add_argument("--data-dir", type=Path, default=None, help="sessions and assets (default VOXFUSION_DATA_DIR)")
    parser.add_argument("--viewer-port", type=int, default=None,
                        help="viser's own port (default VOXFUSION_VIEWER_PORT or 8080; -1 turns the viewer off)")
    parser.add_argument("--viewer-host", default=None,
                        help="interface viser binds to (default 127.0.0.1: browsers reach it through /viewer)")
    parser.add_argument("--max-sessions", type=int, default=None, help="sessions that run at once")


def _settings(args: argparse.Namespace):
    from server.settings import settings_from_env

    return settings_from_env().with_overrides(data_dir=args.data_dir, port=args.port, viewer_port=args.viewer_port,
                                              viewer_host=args.viewer_host, max_sessions=args.max_sessions)


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


GRACEFUL_SHUTDOWN_S = 3.0
"""Longest time uvicorn waits for open requests after SIGTERM before it cancels them."""

PORT_TRIES = 20
"""``voxfusion demo`` moves on to the next of this many ports when its port is taken."""


def _port_free(host: str, port: int) -> bool:
    """Whether ``port`` can be bound on ``host`` now (uvicorn binds it a moment later)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError:
            return False
    return True


def _choose_port(host: str, port: int, move_on: bool) -> int | None:
    """``port``, or with ``move_on`` the next free one after it; None when none is free.
    A taken port is said in one line instead of uvicorn's traceback."""
    for candidate in range(port, port + (PORT_TRIES if move_on else 1)):
        if candidate <= 65535 and _port_free(host, candidate):
            if candidate != port:
                print(f"voxfusion: port {port} is in use; using {candidate}", flush=True)
            return candidate
    tried = f"ports {port} to {port + PORT_TRIES - 1} are" if move_on else f"port {port} is"
    print(f"voxfusion: {tried} in use on {host}: stop what uses it, or choose another with --port or "
          f"VOXFUSION_PORT", file=sys.stderr)
    return None


def _serve(args: argparse.Namespace, demo_spec: tuple[str, str] | None = None) -> int:
    """Serve the app; ``demo_spec`` (spec, preset) also starts a synthetic session and prints
    the URL to open (after viser is up, so that it is the last URL a newcomer reads)."""
    import uvicorn

    from server.connection_limits import uvicorn_limits
    from server.main import DemoSession, create_app

    settings = _settings(args)
    if not _is_loopback(args.host) and settings.token is None:
        print(f"voxfusion: WARNING: listening on {args.host} without VOXFUSION_TOKEN: anyone who can reach this "
              f"port can upload data and run sessions", file=sys.stderr)
    port = _choose_port(args.host, settings.port, move_on=demo_spec is not None)
    if port is None:
        return 1
    demo = None
    if demo_spec is not None:
        host = "127.0.0.1" if args.host in ("0.0.0.0", "::") else args.host
        demo = DemoSession(spec=demo_spec[0], preset=demo_spec[1],
                           announce=f"voxfusion demo: open http://{host}:{port}/ in a browser")
    print(f"voxfusion: data in {settings.data_dir}", flush=True)
    app = create_app(settings, demo=demo)
    # One worker: sessions, their worker processes and the viewer live in this process.
    config = uvicorn.Config(app, host=args.host, port=port, workers=1, log_level="info",
                            timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S, **uvicorn_limits())

    class StoppingServer(uvicorn.Server):
        """uvicorn's server whose exit signal first stops the sessions (module doc)."""

        def handle_exit(self, sig, frame) -> None:
            _stop_sessions(app)
            super().handle_exit(sig, frame)

    server = StoppingServer(config)
    server.run()
    return 0 if server.started else 3


def _stop_sessions(app) -> None:
    """From the signal handler: the sessions start writing their outputs now (module doc).
    Only sets an event: safe whatever the interrupted code was doing."""
    manager = getattr(app.state, "manager", None)
    if manager is not None:
        manager.request_shutdown()


def serve_command(args: argparse.Namespace) -> int:
    return _serve(args)


def demo_command(args: argparse.Namespace) -> int:
    from slam import default_preset_name

    return _serve(args, (args.spec, args.preset or default_preset_name()))


def stream_command(args: argparse.Namespace) -> int:
    from client.stream import stream_command as run_stream

    return run_stream(args)


def _subparsers_action(parser: argparse.ArgumentParser):
    for action in parser._actions:  # argparse offers no public accessor for it
        if isinstance(action, argparse._SubParsersAction):
            return action
    return parser.add_subparsers(dest="command", required=True)


def build_parser() -> argparse.ArgumentParser:
    """The core parser from ``slam.cli`` plus ``ar`` (from ``ar.cli``), ``serve`` and ``demo``."""
    from ar.cli import add_ar_arguments, cmd_ar
    from slam.cli import build_parser as build_core_parser

    parser = build_core_parser()
    subparsers = _subparsers_action(parser)
    ar_parser = subparsers.add_parser("ar", help="composite virtual objects into a rendered view of a map")
    add_ar_arguments(ar_parser)
    ar_parser.set_defaults(handler=cmd_ar)
    add_server_commands(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Parse and run: every subcommand (core or server) sets ``handler`` (as in ``slam.cli``)."""
    args = build_parser().parse_args(argv)
    return int(args.handler(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
