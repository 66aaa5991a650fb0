"""The FastAPI application: ``create_app(settings)``.

The lifespan starts what the app owns and stops it again: the viser viewer (its own thread and
port), the session manager (worker processes and their supervisor), the map cache and the
asset store. Run it with one uvicorn worker (sessions live in this process's memory):
``voxfusion serve`` does.
"""

from __future__ import annotations

from contextlib import asynccontextmanager
from dataclasses import dataclass

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match, Mount

from server.assets import AssetStore
from server.budget import RequestBudget
from server.decoding import shared_helper
from server.errors import error_text, validation_message
from server.log_redaction import RedactTokens, redact_logs  # noqa: F401 (RedactTokens: tests)
from server.path_jobs import PathJobs
from server.render_pools import render_pools
from server.rendering import MapCache, NoMapYet, with_threads
from server.routes_pages import STATIC_DIR
from server.sessions import SessionConflict, SessionManager, SessionNotFound, register_error_handlers
from server.settings import Settings, settings_from_env
from server.upload import UploadError
from server.viewer import ViewerAdapter
from server.worker import SourceSpec

DESCRIPTION = """
Neural implicit dense RGB-D SLAM (Vox-Fusion++) as a service.

* **Sessions** run the SLAM pipeline on a dataset zip (TUM RGB-D, Replica, ScanNet, 7-Scenes),
  on the built-in synthetic scene, or on frames streamed over HTTP or a WebSocket.
* **Collaborative mapping**: several `file` parts in one upload (or a list of synthetic specs)
  are one session, one agent per part; streamed frames name their `agent`. All agents share
  one world frame; `GET .../trajectory?agent=k` gives the k-th agent's trajectory.
* While a session runs: its status, trajectory, mesh (PLY/GLB/OBJ) and rendered colour/depth
  views for any camera; the live 3D viewer at `/viewer`; AR composites with occlusion.
* Poses are 4x4 camera-to-world matrices `T_world_cam` (OpenCV axes: x right, y down,
  z forward), in metres. Depth PNGs are 16-bit millimetres.

**Streaming over a WebSocket** (`/api/sessions/{id}/stream`): send a JSON header
`{"intrinsics": "fx,fy,cx,cy", "depth_scale": 5000, "agent": 0}` (answer `{"type": "ready"}`), then per frame
either a binary message (float64 LE timestamp, uint32 LE colour length n, n colour bytes, the
16-bit depth PNG) or a text message `{"timestamp": t, "color": base64, "depth": base64}`; each is
answered `{"type": "ack", "index": i}` or `{"type": "error", "status": 4xx, "detail": ...}`.
Send `{"type": "finish"}` to end the input.

When the server has a token (`VOXFUSION_TOKEN`), send `Authorization: Bearer <token>` (or
`?token=` for pages and WebSockets). Errors are JSON `{"detail": "what is wrong"}`.
"""


@dataclass(frozen=True)
class DemoSession:
    """A synthetic session that ``voxfusion demo`` starts with the server."""

    spec: str
    preset: str
    announce: str | None = None
    """Printed with the session id once the server is up (the URL to open)."""


HTTP_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


def allowed_methods(app, scope) -> list[str]:
    """Every method some route of ``app`` answers at ``scope``'s path (Starlette's 405 names
    only the first route that matches the path, and ``/api/sessions`` has one route per
    method). Asked through each route's ``matches``, which sees into included routers;
    mounts match any method and answer their own 405, so they are left out."""
    return [method for method in HTTP_METHODS
            if any(not isinstance(route, Mount) and route.matches({**scope, "type": "http", "method": method})[0]
                   is Match.FULL for route in app.router.routes)]


async def method_not_allowed(request: Request, error: StarletteHTTPException) -> JSONResponse:
    """405 with ``Allow`` naming every method of the path (RFC 9110 requires the header)."""
    methods = allowed_methods(request.app, request.scope) or [
        m.strip() for m in (error.headers or {}).get("Allow", "").split(",") if m.strip()]
    return JSONResponse({"detail": f"{request.method} is not allowed here; allowed: {', '.join(methods) or 'none'}"},
                        status_code=405, headers={**(error.headers or {}), "Allow": ", ".join(methods)})


def _error_handlers(app: FastAPI) -> None:
    def detail(status_code: int):
        async def handler(request: Request, error: Exception) -> JSONResponse:
            message = error_text(error)
            if isinstance(error, SessionNotFound):
                message = f"no session {message!r}"
            return JSONResponse({"detail": message}, status_code=status_code)
        return handler

    async def upload_error(request: Request, error: UploadError) -> JSONResponse:
        return JSONResponse({"detail": str(error)}, status_code=error.status)

    async def invalid_request(request: Request, error: RequestValidationError) -> JSONResponse:
        # One message, as every other error (FastAPI's default is a list of error objects).
        return JSONResponse({"detail": validation_message(error.errors())}, status_code=422)

    app.add_exception_handler(RequestValidationError, invalid_request)
    app.add_exception_handler(405, method_not_allowed)
    app.add_exception_handler(UploadError, upload_error)
    app.add_exception_handler(SessionNotFound, detail(404))
    app.add_exception_handler(SessionConflict, detail(409))
    app.add_exception_handler(NoMapYet, detail(409))
    register_error_handlers(app)  # QueueFull -> 429 with Retry-After


_BODY_ERRORS = {"400": "the body cannot be parsed (not JSON, not UTF-8, nested too deeply, a broken form)",
                "413": "the body is larger than the route's limit (server/README.md, 'Resource budget')"}


def _one_error_shape(schema: dict) -> dict:
    """The OpenAPI schema with every error documented as it is sent: ``ErrorOut``
    (``{"detail": str}``) as JSON, also for 422 (FastAPI documents its list form) and for
    routes whose success is not JSON (FastAPI gives their errors the success's media type);
    an operation with a body also lists 400 and 413, which the body parser and the size
    limit answer for any of them. In place, idempotent."""
    error = {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorOut"}}}
    for operations in schema.get("paths", {}).values():
        for operation in operations.values():
            if not isinstance(operation, dict):
                continue
            responses = operation.setdefault("responses", {})
            if "requestBody" in operation:
                for code, description in _BODY_ERRORS.items():
                    responses.setdefault(code, {"description": description})
            for code, response in responses.items():
                if code.isdigit() and int(code) >= 400:
                    response["content"] = dict(error)
    components = schema.get("components", {}).get("schemas", {})
    for name in ("HTTPValidationError", "ValidationError"):
        components.pop(name, None)
    return schema


def cached_map(maps: MapCache, manager: SessionManager, session_id: str):
    """A session's newest map set from the cache, or None while it has none (the viewer's
    neural views ask from their own thread)."""
    try:  # this thread renders what it gets: its thread count is set here
        return with_threads(manager.render_threads(), maps.get, session_id, manager.session_dir(session_id) / "map.pt")
    except (NoMapYet, SessionNotFound):
        return None


def create_app(settings: Settings | None = None, demo: DemoSession | None = None) -> FastAPI:
    """The application; ``settings`` default to the environment's (``settings_from_env``)."""
    from server import (
        routes_ar,
        routes_assets,
        routes_docs,
        routes_pages,
        routes_paths,
        routes_render,
        routes_series,
        routes_sessions,
        routes_stream,
    )

    settings = settings or settings_from_env()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        import torch

        settings.data_dir.mkdir(parents=True, exist_ok=True)
        redact_logs(settings.token)  # here: uvicorn has configured its loggers by now
        threads_before = torch.get_num_threads()
        viewer = None
        if settings.viewer_enabled:
            viewer = ViewerAdapter(settings.viewer_host, settings.viewer_port)
            viewer.start()
        map_cache = MapCache()
        hooks = [map_cache.evict] + ([viewer.remove_session] if viewer else [])
        manager = SessionManager(settings, event_sinks=[viewer.handle_event] if viewer else [], removal_hooks=hooks)
        manager.start()
        torch.set_num_threads(manager.render_threads())
        if viewer is not None:
            viewer.map_source = lambda session_id: cached_map(map_cache, manager, session_id)
        app.state.settings = settings
        app.state.viewer = viewer
        app.state.manager = manager
        app.state.map_cache = map_cache
        app.state.assets = AssetStore(settings.assets_dir)
        app.state.render_pools = render_pools()  # renders, AR, meshes, videos: in helper processes
        app.state.path_jobs = PathJobs(app.state.render_pools.video)
        if demo is not None:
            from server.sessions import new_session_id

            spec = SourceSpec(kind="synthetic", path=demo.spec, format="synthetic")
            app.state.demo_session = manager.create(new_session_id(), spec, demo.preset).id
            if demo.announce:
                print(f"{demo.announce} (session {app.state.demo_session}, preset {demo.preset})", flush=True)
        try:
            yield
        finally:
            app.state.path_jobs.close()
            app.state.render_pools.close()
            manager.stop(grace_s=min(settings.cancel_grace_s, 5.0))
            if viewer is not None:
                viewer.stop()
            shared_helper().close()
            torch.set_num_threads(threads_before)

    # FastAPI's own /docs, /redoc and /openapi.json are off: routes_docs serves them with
    # local assets (no CDN) and behind the token.
    app = FastAPI(title="voxfusion", version="0.1.0", description=DESCRIPTION, lifespan=lifespan,
                  docs_url=None, redoc_url=None, openapi_url=None,
                  openapi_tags=[{"name": "sessions"}, {"name": "streaming"}, {"name": "render"},
                                {"name": "ar"}, {"name": "viewer"}])
    app.openapi = lambda: _one_error_shape(FastAPI.openapi(app))  # type: ignore[method-assign]
    app.state.settings = settings
    app.add_middleware(RequestBudget, max_upload_bytes=settings.max_upload_bytes)
    _error_handlers(app)
    for module in (routes_sessions, routes_series, routes_stream, routes_render, routes_paths, routes_ar, routes_assets,
                   routes_pages, routes_docs):
        app.include_router(module.router)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    routes_docs.mount_assets(app)
    return app
