"""The API process's pools of render and video helpers, and how their failures are answered.

Renders, picks, AR composites and mesh exports share the ``render`` pool; camera-path videos
have the ``video`` pool (``server.path_jobs`` queues them). The sizes, queues, memory caps and
time limits are the resource budget's (``server.budget``). Every heavy call of those routes
goes through :func:`http_answers`, which turns a helper's failure into an answer that says
what happened: 503 with ``Retry-After`` when the pool is full, 504 when the call ran out of
time, 503 when the helper died, the call's own status for a :class:`RequestProblem`.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

from fastapi import HTTPException, status

from server import budget
from server.helper_pool import HelperFailed, HelperKind, HelperPool, HelperTimedOut, PoolBusy
from server.render_calls import PRELOAD, RequestProblem
from server.schemas import ErrorOut

HELPER_NICENESS = 10
"""Render and video helpers run below the API process's priority, so that its event loop
answers while they render."""
RENDER_KIND = HelperKind("render", "rendering", "render", budget.RENDER_HELPER_MEMORY_BYTES, budget.RENDER_TIMEOUT_S,
                         PRELOAD, HELPER_NICENESS)
VIDEO_KIND = HelperKind("video", "the video", "video", budget.RENDER_HELPER_MEMORY_BYTES, budget.VIDEO_TIMEOUT_S,
                        PRELOAD, HELPER_NICENESS)


HELPER_RESPONSES = {
    503: {"model": ErrorOut, "description": "every render helper is busy and the queue is full (retry after "
                                            "Retry-After seconds), or the helper ended (over its memory budget)",
          "headers": {"Retry-After": {"schema": {"type": "integer"}, "description": "seconds to wait"}}},
    504: {"model": ErrorOut, "description": "the call took longer than its time limit (server/README.md, "
                                            "'Resource budget')"}}
"""OpenAPI answers of a route whose work runs in a render helper."""


@dataclass(frozen=True)
class RenderPools:
    """The app's helper pools (``app.state.render_pools``)."""

    render: HelperPool
    video: HelperPool

    def close(self) -> None:
        self.render.close()
        self.video.close()


def render_pools(render_timeout_s: float = budget.RENDER_TIMEOUT_S) -> RenderPools:
    """Pools sized by the budget (helpers start on first use)."""
    from dataclasses import replace

    return RenderPools(
        render=HelperPool(replace(RENDER_KIND, timeout_s=render_timeout_s), budget.RENDER_HELPERS,
                          budget.RENDER_QUEUE, budget.RENDER_WAIT_S, budget.RENDER_RETRY_AFTER_S),
        video=HelperPool(VIDEO_KIND, budget.VIDEO_HELPERS, 0, 0.0, budget.VIDEO_RETRY_AFTER_S))


@contextmanager
def http_answers(what: str) -> Iterator[None]:
    """Helper failures inside as HTTPExceptions (module doc); ``what`` names the request."""
    try:
        yield
    except PoolBusy as error:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, f"{what}: {error}",
                            headers={"Retry-After": str(error.retry_after_s)}) from None
    except HelperTimedOut as error:
        raise HTTPException(status.HTTP_504_GATEWAY_TIMEOUT,
                            f"{what}: {error}; ask for a smaller image (the helper was replaced)") from None
    except HelperFailed as error:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, f"{what}: {error}") from None
    except RequestProblem as error:
        raise HTTPException(error.status, error.detail) from None
