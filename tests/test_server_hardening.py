"""What an abuse test of a token-protected server found after the first round: the token in
WebSocket log lines, WebSocket handshakes from other sites' pages, connections that never
send their request head, 405 answers that name only one method, and schema-valid requests
refused or explained in the interpreter's words. Each test failed before its fix."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator
from urllib.parse import quote, quote_plus

import httpx
import numpy as np
import pytest
from starlette.requests import HTTPConnection
from starlette.websockets import WebSocketDisconnect

from tests.live_server import free_port, start_uvicorn
from tests.test_server_api import running_app

REPO = Path(__file__).resolve().parents[1]
TOKEN = "hx7-Secret_tok.en+9"
"""Holds characters a client percent-encodes (``+``) and ones it may (``.``, ``-``, ``_``)."""


def token_spellings(token: str = TOKEN) -> list[str]:
    """The token as written and as every encoder would write it (hex in both cases)."""
    every_byte = "".join(f"%{b:02X}" for b in token.encode())
    return [token, quote(token, safe=""), quote_plus(token), every_byte, every_byte.lower(), quote(quote(token, safe=""))]


@pytest.fixture(scope="module")
def served(tmp_path_factory) -> Iterator[tuple[str, Path]]:
    """``voxfusion serve`` with a token, in a subprocess on 127.0.0.1; (url, its log file)."""
    work = tmp_path_factory.mktemp("served")
    log, port = work / "server.log", free_port()
    env = {**os.environ, "VOXFUSION_TOKEN": TOKEN,
           "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    with open(log, "ab") as out:
        process = subprocess.Popen([sys.executable, "-m", "server.cli", "serve", "--host", "127.0.0.1", "--port",
                                    str(port), "--data-dir", str(work / "data"), "--viewer-port", "-1"],
                                   cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 90
        while True:
            try:
                httpx.get(f"{url}/api/sessions", timeout=5)
                break
            except httpx.TransportError:
                assert process.poll() is None and time.monotonic() < deadline, log.read_text()
                time.sleep(0.3)
        yield url, log
    finally:
        process.terminate()
        try:
            process.wait(30)
        except subprocess.TimeoutExpired:
            process.kill()


def open_socket(url: str, path: str, origin: str | None = None, **headers):
    """A WebSocket to the live server (raises ``InvalidStatus`` when the handshake is refused)."""
    from websockets.sync.client import connect

    return connect(url.replace("http://", "ws://") + path, origin=origin, additional_headers=headers,
                   open_timeout=10, close_timeout=2)


def stream_session(url: str) -> str:
    response = httpx.post(f"{url}/api/sessions", json={"source": "stream", "preset": "test"},
                          headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30)
    assert response.status_code == 201, response.text
    return response.json()["id"]


def test_the_token_reaches_no_log_line_in_any_spelling(served):
    from websockets.exceptions import InvalidStatus

    url, log = served
    session = stream_session(url)
    encoded = quote(TOKEN, safe="")
    with httpx.Client(base_url=url, timeout=30) as client:
        client.get("/api/sessions", params={"token": TOKEN})
        client.get(f"/api/sessions?TOKEN={encoded}&x=1")
        client.get("/api/sessions?token=" + "".join(f"%{b:02x}" for b in TOKEN.encode()))
        client.get("/api/sessions", headers={"Authorization": f"Bearer {TOKEN}"})
        client.get("/viewer", params={"token": TOKEN})
        client.get(f"/viewer%3Ftoken%3D{encoded}")
        client.get(f"/api/sessions/token%3D{encoded}")
        client.get(f"/api/sessions/{encoded}")  # the bare value in a path: only its own pattern finds it
        client.get("/", cookies={"voxfusion_token": TOKEN})
    with open_socket(url, f"/api/sessions/{session}/stream?token={encoded}") as accepted:
        accepted.send('{"type": "finish"}')
    for path in (f"/viewer?token={encoded}", f"/api/sessions/{session}/stream%3Ftoken%3D{encoded}",
                 f"/api/sessions/{encoded}/stream"):
        with pytest.raises(InvalidStatus):
            open_socket(url, path).close()
    time.sleep(0.5)  # the server writes its last lines
    text = log.read_text(errors="replace")
    assert '"WebSocket /api/sessions/' in text and "[accepted]" in text, "the WebSocket lines were logged"
    assert "token=***" in text
    leaks = {spelling: text.count(spelling) for spelling in token_spellings()}
    assert sum(leaks.values()) == 0, (leaks, [line for line in text.splitlines() if "Secret" in line])


def test_a_websocket_from_another_sites_page_is_refused(served):
    from websockets.exceptions import InvalidStatus

    url, _ = served
    port = url.rsplit(":", 1)[1]
    session = stream_session(url)
    path = f"/api/sessions/{session}/stream?token={quote(TOKEN, safe='')}"
    for origin in ("http://evil.example", f"http://evil.example:{port}", f"http://127.0.0.1:{free_port()}", "null"):
        with pytest.raises(InvalidStatus) as refused:
            open_socket(url, path, origin=origin).close()
        assert refused.value.response.status_code == 403, origin
    for origin in (None, f"http://127.0.0.1:{port}", f"http://localhost:{port}"):
        with open_socket(url, path, origin=origin) as socket_:
            socket_.send("{}")
            assert '"ready"' in socket_.recv(timeout=10), origin


def connection(host: str, origin: str | None, scheme: str = "ws") -> HTTPConnection:
    headers = [(b"host", host.encode())] + ([(b"origin", origin.encode())] if origin is not None else [])
    return HTTPConnection({"type": "websocket", "scheme": scheme, "server": ("127.0.0.1", 8000), "path": "/viewer",
                           "query_string": b"", "headers": headers})


def test_the_origin_check_compares_host_and_port():
    from server.deps import foreign_origin

    same = [("127.0.0.1:8000", None), ("127.0.0.1:8000", "http://127.0.0.1:8000"),
            ("localhost:8000", "http://127.0.0.1:8000"), ("[::1]:8000", "http://localhost:8000"),
            ("example.org", "https://example.org"),  # a TLS proxy in front: https page, plain ws behind
            ("example.org:80", "http://example.org"), ("Example.org:8000", "http://example.ORG:8000")]
    for host, origin in same:
        assert foreign_origin(connection(host, origin)) is None, (host, origin)
    assert foreign_origin(connection("example.org", "https://example.org:443", scheme="wss")) is None
    other = [("127.0.0.1:8000", "http://evil.example"), ("127.0.0.1:8000", "http://127.0.0.1:3000"),
             ("example.org", "http://example.org.evil.example"), ("127.0.0.1:8000", "null"),
             ("127.0.0.1:8000", "file://"), ("127.0.0.1:8000", "http://127.0.0.1:99999")]
    for host, origin in other:
        reason = foreign_origin(connection(host, origin))
        assert reason is not None and repr(origin) in reason, (host, origin)


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    with running_app(tmp_path_factory.mktemp("hardening"), token=TOKEN) as test_client:
        yield test_client


def test_both_websocket_routes_close_a_foreign_origin_with_1008(client):
    session = client.post("/api/sessions", json={"source": "stream", "preset": "test"},
                          headers={"Authorization": f"Bearer {TOKEN}"}).json()["id"]
    for path in ("/viewer", f"/api/sessions/{session}/stream"):
        with pytest.raises(WebSocketDisconnect) as closed:
            with client.websocket_connect(f"{path}?token={TOKEN}", headers={"origin": "http://evil.example"}):
                pass
        assert closed.value.code == 1008 and "evil.example" in closed.value.reason, (path, closed.value.reason)


def test_405_names_every_method_of_the_path(client):
    sessions = client.options("/api/sessions")
    assert sessions.status_code == 405
    assert set(sessions.headers["allow"].split(", ")) == {"GET", "POST"}
    assert "GET, POST" in sessions.json()["detail"]
    one = client.request("PUT", "/api/sessions/000000000000")
    assert set(one.headers["allow"].split(", ")) == {"GET", "DELETE"}
    assert client.options("/static/app.js").headers["allow"] == "GET, HEAD", "a mount's own Allow is kept"


def test_matrices_are_4x4_in_the_schema():
    from server.schemas import ARObject, CameraRequest, PathPreview

    for schema in (CameraRequest.model_json_schema()["properties"]["T_world_cam"],
                   ARObject.model_json_schema()["properties"]["T_world_obj"]["anyOf"][0],
                   PathPreview.model_json_schema()["properties"]["keyframes"]["items"]):
        assert (schema["minItems"], schema["maxItems"]) == (4, 4)
        assert (schema["items"]["minItems"], schema["items"]["maxItems"]) == (4, 4)


def test_bad_numbers_are_explained_in_our_words(client):
    headers = {"Authorization": f"Bearer {TOKEN}", "content-type": "application/json"}
    nan = client.post("/api/sessions", content=b'{"source": "stream", "depth_scale": NaN}', headers=headers)
    assert nan.status_code == 422 and nan.json()["detail"] == "body.depth_scale: must be a finite number"
    form = client.post("/api/sessions", data={"depth_scale": "NaN"}, files={"file": ("a.zip", b"PK")},
                       headers={"Authorization": f"Bearer {TOKEN}"})
    assert form.status_code == 422 and "depth_scale: must be a finite number" in form.json()["detail"]
    long = client.post("/api/sessions", content=b'{"source": "stream", "max_frames": ' + b"9" * 5000 + b"}",
                       headers=headers)
    assert long.status_code == 400
    assert "number too long" in long.json()["detail"] and "set_int_max_str_digits" not in long.json()["detail"]


def test_a_request_head_that_never_completes_is_cut_off():
    from starlette.applications import Starlette
    from starlette.responses import PlainTextResponse
    from starlette.routing import Route

    from server.connection_limits import HeadDeadlineProtocol

    quick = type("QuickDeadline", (HeadDeadlineProtocol,), {"head_timeout_s": 0.5, "max_head_bytes": 4096})
    app = Starlette(routes=[Route("/", lambda request: PlainTextResponse("ok"))])
    live = start_uvicorn(app, http=quick)
    port = int(live.url.rsplit(":", 1)[1])

    def answer(sent: bytes) -> bytes:
        with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
            sock.sendall(sent)
            data = b""
            while chunk := sock.recv(65536):  # the server closes: recv returns b""
                data += chunk
            return data

    try:
        started = time.monotonic()
        assert answer(b"") == b"", "a connection that sends nothing is closed"
        assert answer(b"GET / HTTP/1.1\r\nHost: x\r\n").startswith(b"HTTP/1.1 408")
        assert time.monotonic() - started < 4
        assert answer(b"GET / HTTP/1.1\r\nHost: x\r\nX-Pad: " + b"a" * 8000).startswith(b"HTTP/1.1 431")
        whole = answer(b"GET / HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        assert whole.startswith(b"HTTP/1.1 200") and whole.endswith(b"ok"), "a complete head is served as ever"
    finally:
        live.stop()


def test_serve_runs_uvicorn_with_the_connection_limits(tmp_path, monkeypatch):
    import uvicorn

    from server.cli import build_parser
    from server.connection_limits import KEEP_ALIVE_S, MAX_CONNECTIONS, HeadDeadlineProtocol

    seen = {}
    monkeypatch.setattr(uvicorn.Server, "run", lambda self: seen.setdefault("config", self.config))
    args = build_parser().parse_args(["serve", "--port", str(free_port()), "--data-dir", str(tmp_path),
                                      "--viewer-port", "-1"])
    args.handler(args)
    config = seen["config"]
    assert config.http is HeadDeadlineProtocol
    assert (config.timeout_keep_alive, config.limit_concurrency) == (KEEP_ALIVE_S, MAX_CONNECTIONS)


def test_one_given_end_of_the_depth_preview_range_is_never_refused():
    """A schema-valid ``depth_max`` below the view's automatic near end (or ``depth_min`` past
    its far end) moves the automatic end inside it; only two given ends that cross get 422."""
    import numpy as np

    from server.render_calls import RequestProblem, depth_range

    depth = np.full((4, 4), 2.0)
    near, far = depth_range(depth, None, 5e-324)
    assert near < far == 5e-324
    assert depth_range(depth, 7.0, None) == (7.0, 14.0)
    with pytest.raises(RequestProblem):
        depth_range(depth, 3.0, 1.0)
