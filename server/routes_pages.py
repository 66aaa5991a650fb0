"""Our web page, and the viser client behind the API's own port and token.

viser serves its client and its WebSocket on a port of its own and cannot be mounted in
FastAPI. The page therefore loads viser's (single-file) client from ``GET /viewer`` and the
client connects back to ``ws://<api host>/viewer`` (its default: the page's own URL), which is
relayed byte for byte to viser on loopback. One port to expose, and the token protects the
viewer too: a page opened with ``?token=`` gets it as an HttpOnly cookie, which the browser
then sends with the viewer's WebSocket handshake. viser's own port refuses every WebSocket
but this relay's (``server.viewer``: the relay proves itself with a secret header), so the
scene is reached only through the token check.
"""

from __future__ import annotations

import asyncio
import contextlib
from functools import lru_cache
from pathlib import Path

from fastapi import APIRouter, Request, WebSocket, status
from fastapi.responses import FileResponse, HTMLResponse, Response

from server.deps import TOKEN_COOKIE, refuse_foreign_origin, token_ok
from server.viewer import RELAY_HEADER

router = APIRouter(include_in_schema=False)

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"
_LOCKED_PAGE = """<!doctype html><meta charset="utf-8"><title>voxfusion: token needed</title>
<body style="font-family:sans-serif;max-width:40em;margin:4em auto">
<h1>This server needs a token</h1>
<p>Open this page with <code>?token=YOUR_TOKEN</code> (the value of <code>VOXFUSION_TOKEN</code> on the server).</p>
<form method="get"><input name="token" type="password" placeholder="token" autofocus> <button>Open</button></form>
</body>"""


def locked_page() -> HTMLResponse:
    """401 for a browser: a page that says how to give the token."""
    return HTMLResponse(_LOCKED_PAGE, status_code=status.HTTP_401_UNAUTHORIZED)


def with_token_cookie(response: Response, request: Request) -> Response:
    """Remember a ``?token=`` in a cookie so that the viewer's WebSocket carries it."""
    token = request.query_params.get("token")
    if token and request.app.state.settings.token is not None:
        response.set_cookie(TOKEN_COOKIE, token, httponly=True, samesite="strict")
    return response


@router.get("/")
def index(request: Request) -> Response:
    if not token_ok(request):
        return locked_page()
    return with_token_cookie(FileResponse(STATIC_DIR / "index.html", media_type="text/html"), request)


@lru_cache(maxsize=1)
def _viser_client_html() -> bytes:
    import viser

    return (Path(viser.__file__).resolve().parent / "client" / "build" / "index.html").read_bytes()


@router.get("/viewer")
def viewer_page(request: Request) -> Response:
    if not token_ok(request):
        return locked_page()
    viewer = request.app.state.viewer
    if viewer is None or not viewer.running:
        return HTMLResponse("<p style='font-family:sans-serif'>The 3D viewer is switched off on this server.</p>",
                            status_code=status.HTTP_503_SERVICE_UNAVAILABLE)
    return with_token_cookie(HTMLResponse(_viser_client_html()), request)


@router.websocket("/viewer")
async def viewer_socket(websocket: WebSocket) -> None:
    """Relay the viser client's WebSocket to the viser server on loopback."""
    import websockets

    if await refuse_foreign_origin(websocket):
        return
    if not token_ok(websocket):
        await websocket.close(code=status.WS_1008_POLICY_VIOLATION, reason="missing or wrong token")
        return
    viewer = websocket.app.state.viewer
    if viewer is None or not viewer.running:
        await websocket.close(code=status.WS_1011_INTERNAL_ERROR, reason="the viewer is not running")
        return
    offered = websocket.scope.get("subprotocols") or []
    protocol = next((p for p in offered if p.startswith("viser-v")), None)
    try:
        upstream = await websockets.connect(f"ws://127.0.0.1:{viewer.port}",
                                            subprotocols=[protocol] if protocol else None,
                                            additional_headers={RELAY_HEADER: viewer.relay_secret},
                                            max_size=None, compression=None, open_timeout=10)
    except (OSError, websockets.WebSocketException, asyncio.TimeoutError) as error:
        await websocket.close(code=status.WS_1011_INTERNAL_ERROR, reason=f"viewer unreachable: {error}")
        return
    await websocket.accept(subprotocol=protocol)
    async with upstream:
        to_viser = asyncio.create_task(_browser_to_viser(websocket, upstream))
        to_browser = asyncio.create_task(_viser_to_browser(websocket, upstream))
        _, pending = await asyncio.wait({to_viser, to_browser}, return_when=asyncio.FIRST_COMPLETED)
        for task in pending:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
    with contextlib.suppress(Exception):
        await websocket.close()


async def _browser_to_viser(websocket: WebSocket, upstream) -> None:
    while True:
        message = await websocket.receive()
        if message["type"] == "websocket.disconnect":
            return
        if message.get("bytes") is not None:
            await upstream.send(message["bytes"])
        elif message.get("text") is not None:
            await upstream.send(message["text"])


async def _viser_to_browser(websocket: WebSocket, upstream) -> None:
    async for message in upstream:
        if isinstance(message, bytes):
            await websocket.send_bytes(message)
        else:
            await websocket.send_text(message)
