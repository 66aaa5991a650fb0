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
from hypothesis import HealthCheck, Phase, settings  # noqa: E402
from schemathesis.checks import not_a_server_error  # noqa: E402
from schemathesis.specs.openapi.checks import (  # noqa: E402
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

EXAMPLES = 12
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance]
pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def fuzz_server(tmp_path_factory) -> Iterator[str]:
    """The app (no viewer, no workers) served by uvicorn on 127.0.0.1; yields its base URL."""
    from server.main import create_app
    from server.sessions import SessionManager
    from server.settings import Settings

    patch = pytest.MonkeyPatch()
    patch.setattr(SessionManager, "_start_queued", lambda self: None)
    settings = Settings(data_dir=tmp_path_factory.mktemp("fuzz-data"), viewer_port=-1, max_upload_mb=4)
    live = start_uvicorn(create_app(settings), startup_timeout_s=30, lifespan="on")
    yield live.url
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
    case.call_and_validate(base_url=fuzz_server, checks=CHECKS, timeout=30)
