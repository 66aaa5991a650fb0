"""FastAPI dependencies: the objects the app owns, and the optional bearer token."""

from __future__ import annotations

import secrets

from fastapi import HTTPException, status
from starlette.requests import HTTPConnection

from server.assets import AssetStore
from server.path_jobs import PathJobs
from server.render_pools import RenderPools
from server.rendering import MapCache, MeshFiles
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


def get_map_cache(conn: HTTPConnection) -> MapCache:
    return conn.app.state.map_cache


def get_mesh_files(conn: HTTPConnection) -> MeshFiles:
    return conn.app.state.mesh_files


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
