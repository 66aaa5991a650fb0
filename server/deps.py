"""FastAPI dependencies: the objects the app owns, the optional bearer token, and the
``Origin`` check of every WebSocket route."""

from __future__ import annotations

import secrets
from urllib.parse import urlsplit

from fastapi import HTTPException, WebSocket, status
from starlette.requests import HTTPConnection

from server.assets import AssetStore
from server.path_jobs import PathJobs
from server.render_pools import RenderPools
from server.sessions import SessionManager
from server.settings import Settings
from server.viewer import ViewerAdapter

TOKEN_COOKIE = "voxfusion_token"


def get_settings(conn: HTTPConnection) -> Settings:
    return conn.app.state.settings


def get_manager(conn: HTTPConnection) -> SessionManager:
    return conn.app.state.manager


def get_viewer(conn: HTTPConnection) -> ViewerAdapter | None:
    return conn.app.state.viewer


def get_path_jobs(conn: HTTPConnection) -> PathJobs:
    return conn.app.state.path_jobs


def get_assets(conn: HTTPConnection) -> AssetStore:
    return conn.app.state.assets


def get_render_pools(conn: HTTPConnection) -> RenderPools:
    return conn.app.state.render_pools


def presented_token(conn: HTTPConnection) -> str | None:
    """The token a request carries: ``Authorization: Bearer``, ``?token=`` or the page's cookie."""
    header = conn.headers.get("authorization", "")
    if header.lower().startswith("bearer "):
        return header[7:].strip()
    return conn.query_params.get("token") or conn.cookies.get(TOKEN_COOKIE)


def token_ok(conn: HTTPConnection) -> bool:
    expected = conn.app.state.settings.token
    if expected is None:
        return True
    given = presented_token(conn)
    return given is not None and secrets.compare_digest(given.encode(), expected.encode())


def require_token(conn: HTTPConnection) -> None:
    """401 unless the server has no token or the request carries the right one."""
    if not token_ok(conn):
        raise HTTPException(status.HTTP_401_UNAUTHORIZED,
                            "missing or wrong token: send 'Authorization: Bearer <token>' or ?token=<token>",
                            headers={"WWW-Authenticate": "Bearer"})


LOOPBACK_HOSTS = frozenset({"localhost", "127.0.0.1", "::1"})


def _same_host(a: str, b: str) -> bool:
    return a == b or (a in LOOPBACK_HOSTS and b in LOOPBACK_HOSTS)


def foreign_origin(conn: HTTPConnection) -> str | None:
    """Why the request's ``Origin`` is not this server's, or None when it is or is absent.

    A browser sends ``Origin`` with every WebSocket handshake, also from another site's page,
    and it sends our SameSite cookie only to our own pages: the origin is what tells a page of
    ours from another. A request without one comes from a program, not a browser (allowed).
    Same origin: the host of the request's ``Host`` (localhost and loopback addresses count as
    one host) and its port; a side that names no port uses its scheme's default (http and ws
    80, https and wss 443), and two sides that both name none match, so a TLS proxy in front
    (``https`` page, plain ``ws`` behind it) is still the same origin."""
    origin = conn.headers.get("origin")
    if origin is None:
        return None
    try:
        parts = urlsplit(origin)
        origin_host, origin_port = (parts.hostname or "").lower(), parts.port
    except ValueError:
        return f"origin {origin!r} is not a URL"
    if parts.scheme not in ("http", "https") or not origin_host:
        return f"origin {origin!r} is not a web page's"
    own_host, own_port = (conn.url.hostname or "").lower(), conn.url.port
    defaults = {"http": 80, "ws": 80, "https": 443, "wss": 443}
    same_port = (origin_port is None and own_port is None) or (
        (origin_port or defaults[parts.scheme]) == (own_port or defaults.get(conn.url.scheme, 80)))
    if _same_host(origin_host, own_host) and same_port:
        return None
    return f"origin {origin!r} is not this server's: open the page from this server"


async def refuse_foreign_origin(websocket: WebSocket) -> bool:
    """Close the handshake (403, before accept) when the origin is another site's
    (:func:`foreign_origin`); True when it did."""
    reason = foreign_origin(websocket)
    if reason is None:
        return False
    await websocket.close(code=status.WS_1008_POLICY_VIOLATION, reason=reason.encode()[:123].decode(errors="ignore"))
    return True
