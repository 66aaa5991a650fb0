"""Who reaches what: the API reference works offline, and with a token set every route but the
static assets needs it, including the reference, the schema and viser's own port."""

from __future__ import annotations

import re

import pytest
from starlette.routing import WebSocketRoute
from starlette.websockets import WebSocketDisconnect

from tests.test_server_api import running_app

TOKEN = "s3cret"
pytestmark = pytest.mark.timeout(120)


def test_api_reference_pages_load_only_local_assets(tmp_path):
    with running_app(tmp_path) as client:
        for path in ("/docs", "/redoc"):
            page = client.get(path)
            assert page.status_code == 200, path
            references = re.findall(r'(?:src|href)="([^"]+)"', page.text)
            assert references and all(r.startswith("/") for r in references), references
            assert "http://" not in page.text and "https://" not in page.text, f"{path} reaches out of the server"
            for reference in references:
                asset = client.get(reference)
                assert asset.status_code == 200 and len(asset.content) > 1000, reference
        assert "javascript" in client.get("/docs-assets/swagger-ui-bundle.js").headers["content-type"]
        assert client.get("/docs/oauth2-redirect").status_code == 200
        assert client.get("/openapi.json").json()["info"]["title"] == "voxfusion"


def concrete(path: str) -> str:
    return re.sub(r"\{[^}]+\}", "000000000000", path)


def every_route() -> list:
    """The routes of every ``server/routes_*.py`` module (a new module is covered the day it lands)."""
    import importlib
    import pkgutil

    import server

    names = [m.name for m in pkgutil.iter_modules(server.__path__) if m.name.startswith("routes_")]
    return [route for name in names for route in importlib.import_module(f"server.{name}").router.routes]


def test_with_a_token_every_route_but_static_assets_needs_it(tmp_path):
    with running_app(tmp_path, token=TOKEN) as client:
        checked = set()
        for route in every_route():
            path = concrete(route.path)
            if isinstance(route, WebSocketRoute) or type(route).__name__ == "APIWebSocketRoute":
                with pytest.raises(WebSocketDisconnect) as refused:
                    with client.websocket_connect(path):
                        pass
                assert refused.value.code == 1008, path
                checked.add(f"WS {route.path}")
                continue
            for method in sorted(route.methods - {"HEAD"}):
                response = client.request(method, path)
                assert response.status_code == 401, f"{method} {route.path} answered {response.status_code}"
                checked.add(f"{method} {route.path}")
        assert {"GET /docs", "GET /redoc", "GET /docs/oauth2-redirect", "GET /openapi.json", "GET /",
                "GET /viewer", "WS /viewer", "POST /api/sessions", "WS /api/sessions/{session_id}/stream"} <= checked
        headers = {"Authorization": f"Bearer {TOKEN}"}
        assert client.get("/openapi.json", headers=headers).status_code == 200
        docs = client.get("/docs", params={"token": TOKEN})
        assert docs.status_code == 200 and client.cookies.get("voxfusion_token") == TOKEN
        assert client.get("/openapi.json").status_code == 200, "the docs page's cookie opens the schema"
        client.cookies.clear()
        # The page's own assets and the reference's are public: they hold no data.
        assert client.get("/static/app.js").status_code == 200
        assert client.get("/docs-assets/redoc.standalone.js").status_code == 200


def test_viser_port_admits_only_the_token_checked_relay(tmp_path):
    import viser
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    protocol = f"viser-v{viser.__version__}"
    with running_app(tmp_path, viewer_port=0, token=TOKEN) as client:
        viewer = client.app.state.viewer
        with connect(f"ws://127.0.0.1:{viewer.port}", subprotocols=[protocol], open_timeout=10) as direct:
            with pytest.raises(ConnectionClosed) as closed:
                direct.recv(timeout=10)
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008, "a direct connection gets nothing"
        with pytest.raises(WebSocketDisconnect):
            with client.websocket_connect("/viewer", subprotocols=[protocol]):
                pass
        with client.websocket_connect(f"/viewer?token={TOKEN}", subprotocols=[protocol]) as relayed:
            assert len(relayed.receive_bytes()) > 0, "the relay reaches viser and its scene comes through"
        assert viewer.refused_connections == 1
