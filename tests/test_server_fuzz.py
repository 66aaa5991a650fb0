"""Property-based requests from the OpenAPI schema (schemathesis): no operation answers 5xx,
and every answer has a documented status, content type and body shape. New endpoints are
fuzzed the day they land, since the operations come from the schema.

The server is a real uvicorn on 127.0.0.1 in a thread of this process. Sessions that the
fuzzer creates stay queued (the session manager starts no worker): this tests the HTTP
edge, not SLAM runs, and keeps the run to a few seconds. Bounded: EXAMPLES per operation,
no shrinking, one seed (the same requests every run).
"""

from __future__ import annotations

from typing import Iterator

import pytest

from tests.live_server import start_uvicorn

schemathesis = pytest.importorskip("schemathesis")
from hypothesis import HealthCheck, Phase, given, settings  # noqa: E402
from schemathesis import GenerationMode  # noqa: E402
from schemathesis.checks import not_a_server_error  # noqa: E402
from schemathesis.specs.openapi.checks import (  # noqa: E402
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

EXAMPLES = 12
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance]
pytestmark = pytest.mark.timeout(120)


TOKEN = "fuzz-token"


@pytest.fixture(scope="module", params=["open", "token"])
def fuzz_server(request, tmp_path_factory) -> Iterator[tuple[str, dict]]:
    """The app (no viewer, no workers) served by uvicorn on 127.0.0.1, open or behind a token;
    yields its base URL and the headers every call sends."""
    from server.main import create_app
    from server.sessions import SessionManager
    from server.settings import Settings

    patch = pytest.MonkeyPatch()
    patch.setattr(SessionManager, "_start_queued", lambda self: None)
    token = TOKEN if request.param == "token" else None
    settings = Settings(data_dir=tmp_path_factory.mktemp("fuzz-data"), viewer_port=-1, max_upload_mb=4, token=token)
    live = start_uvicorn(create_app(settings), startup_timeout_s=30, lifespan="on")
    yield live.url, ({"Authorization": f"Bearer {TOKEN}"} if token else {})
    live.stop()
    patch.undo()


def _schema():
    """The app's OpenAPI schema, built without starting the app (so pytest can list the operations)."""
    import tempfile
    from pathlib import Path

    from server.main import create_app
    from server.settings import Settings

    return schemathesis.openapi.from_dict(create_app(Settings(data_dir=Path(tempfile.gettempdir()))).openapi())


schema = _schema()


@schema.parametrize()
@settings(max_examples=EXAMPLES, deadline=None, derandomize=True, phases=[Phase.explicit, Phase.generate],
          suppress_health_check=list(HealthCheck))
def test_every_operation_answers_as_documented(case, fuzz_server):
    url, headers = fuzz_server
    case.call_and_validate(base_url=url, headers=headers, checks=CHECKS, timeout=30)


CREATE = schema["/api/sessions"]["POST"]


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
def test_create_session_with_json_bodies(fuzz_server, mode):
    """``POST /api/sessions`` takes JSON as well as a form: fuzz that body on its own (the
    schema-wide run may pick the form for most of its examples), valid and invalid."""
    url, headers = fuzz_server

    # as_strategy's media_type does not pin the body's type (schemathesis 4.32): filter instead.
    @given(CREATE.as_strategy(mode).filter(lambda case: case.media_type == "application/json"))
    @settings(max_examples=EXAMPLES * 3, deadline=None, derandomize=True, phases=[Phase.generate],
              suppress_health_check=list(HealthCheck))
    def check(case):
        assert case.media_type == "application/json"
        case.call_and_validate(base_url=url, headers=headers, checks=CHECKS, timeout=30)

    check()


def test_the_token_is_required_where_set(fuzz_server):
    """Behind a token, a call without it is refused (401) and one with a wrong token too."""
    import httpx

    url, headers = fuzz_server
    if not headers:
        pytest.skip("the open server takes calls without a token")
    with httpx.Client(base_url=url, timeout=30) as client:
        assert client.get("/api/sessions").status_code == 401
        assert client.get("/api/sessions", headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert client.post("/api/sessions", json={"source": "stream"}).status_code == 401
        assert client.get("/api/sessions", headers=headers).status_code == 200
