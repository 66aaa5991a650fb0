"""The resource budget of a request: every size a client can name, bounded in one place.

``server/README.md`` ("Resource budget") lists the same table for operators. The limits on
request bodies are enforced here, by :class:`RequestBudget` (ASGI middleware, before any
route runs); the other limits are defined here and checked where the thing is made (the
session queue, the asset store, the image decoders, the synthetic spec parser), each citing
its constant.

| what | limit | where it is checked |
| --- | --- | --- |
| body of a dataset upload (multipart ``POST /api/sessions``) | ``VOXFUSION_MAX_UPLOAD_MB`` (2 GiB) | here |
| body of a streamed frame (``POST .../frames``) | 64 MiB | here |
| body of an asset upload (``POST /api/assets``) | 64 MiB + 1 MiB of form | here |
| any JSON body | 256 KiB, nested at most 32 deep | here |
| any other body | 64 KiB | here |
| pixels of an image, anywhere | 4096 a side, 12.6 Mpx | ``slam.data.images`` (header read before decoding) |
| memory of one decode of uploaded data | 1 GiB address space, in a helper process | ``server.decoding`` |
| frames of a synthetic session | 20,000, sides 16..2048 | ``slam.data.synthetic`` |
| ``stride`` / ``max_frames`` of an upload | 1..10,000 / 1..1,000,000 | ``server.upload`` |
| intrinsics | focal lengths 1..100,000 px, principal point within 100,000 px | ``server.upload`` |
| depth scale | 0.01..1,000,000 raw units per metre | ``server.upload`` |
| frames streamed to one session | 1,000,000 | ``server.stream`` |
| sessions waiting in the queue | ``VOXFUSION_MAX_QUEUED`` | ``server.sessions`` |
| assets stored by the server | 256 files, 1 GiB in all; at most 16 parsed meshes and 256 MiB in memory | ``server.assets`` |
| one asset | 500,000 faces, 1,500,000 vertices; a GLB: 4096 nodes nested at most 64 deep (counted before parsing) | ``ar.assets`` |
| parsing an asset | in the decode helper, 30 s (then 422); one at a time, a request waits at most 10 s more, then 503 + ``Retry-After`` | ``server.assets`` |
| a ground-truth file the series reads | 200,000 lines, 64 MiB (else the series says so); read in the decode helper, 60 s; 16 sources' times and camera centres, 64 MiB, kept | ``server.series`` |
| AR objects in one request | 64 | ``server.schemas`` |
| rendered views | 2048 a side | ``server.schemas`` |
| renders, picks, AR composites, mesh exports at once | 2 helper processes, 4 more wait up to 10 s, then 503 + ``Retry-After`` | ``server.render_pools`` |
| memory / time of one render, pick, AR composite or mesh export | 3 GiB address space / 120 s (then 504), in a helper process | ``server.helper_pool`` |
| camera-path video | 200 million rendered pixels (frames x width x height; else 422); 30 min | ``server.routes_paths`` |
| camera-path videos queued and rendering (all sessions) | 4 (then 429 + ``Retry-After``); one renders at a time, in a helper | ``server.path_jobs`` |
"""

from __future__ import annotations

import json
import re
import sys
from dataclasses import dataclass

import numpy as np
from fastapi.responses import JSONResponse

KIB = 1024
MIB = 1024 * KIB

FRAME_BODY_BYTES = 64 * MIB
"""A streamed frame: a colour image and a 16-bit depth PNG of at most 12.6 Mpx, compressed."""
ASSET_FORM_BYTES = 1 * MIB
"""Room for the multipart framing around an asset file (``ar.assets.MAX_ASSET_BYTES``)."""
JSON_BODY_BYTES = 256 * KIB
"""Any JSON body: the largest, an AR request with 64 objects, is a few KiB."""
OTHER_BODY_BYTES = 64 * KIB
"""A body where the route expects none or a small form."""
MAX_JSON_DEPTH = 32
"""Deepest nesting of a JSON body (ours nest 4 deep; Python's parser recurses per level)."""

MAX_STRIDE = 10_000
MAX_FRAMES_OPTION = 1_000_000
MAX_STREAM_FRAMES = 1_000_000
"""Frames one stream session may receive (all agents); more get 413."""
FOCAL_RANGE = (1.0, 100_000.0)
"""Focal lengths (pixels) accepted anywhere a client gives intrinsics."""
PRINCIPAL_POINT_LIMIT = 100_000.0
"""|cx|, |cy| (pixels) at most."""
DEPTH_SCALE_RANGE = (0.01, 1_000_000.0)
"""Raw depth units per metre: 1000 (mm), 5000 (TUM), 6553.5 (Replica) lie well inside."""
MAX_ASSETS = 256
MAX_ASSET_STORE_BYTES = 1024 * MIB
ASSET_CACHE_ENTRIES = 16
ASSET_CACHE_BYTES = 256 * MIB
"""Parsed asset meshes kept in memory (one is at most ~60 MB: ``ar.assets.MAX_ASSET_VERTICES``)."""

RENDER_HELPERS = 2
"""Render helper processes: renders, picks, AR composites and mesh exports that run at once."""
RENDER_QUEUE = 4
"""Requests that may wait for a render helper; one more gets 503 at once."""
RENDER_WAIT_S = 10.0
"""Longest a request waits for a render helper before 503."""
RENDER_RETRY_AFTER_S = 5
"""``Retry-After`` of a 503 from a full render pool."""
RENDER_HELPER_MEMORY_BYTES = 3 * 1024 * MIB
"""Address space of a render or video helper above its start-up footprint: a 2048x2048 view
and two loaded maps."""
RENDER_TIMEOUT_S = 120.0
"""Longest one render, pick, AR composite or mesh export runs: the largest view (2048x2048)
takes minutes only on a CPU shared with running sessions, and a longer call is a hang."""
VIDEO_HELPERS = 1
"""Camera-path videos rendered at once (each in a helper process)."""
MAX_VIDEO_JOBS = 4
"""Camera-path videos queued and rendering, all sessions together; one more gets 429."""
MAX_VIDEO_PIXELS = 200_000_000
"""Rendered pixels of one video, frames x width x height (651 frames of 640x480, 27 s at 24 fps)."""
VIDEO_TIMEOUT_S = 1800.0
"""Longest one video renders: a video at MAX_VIDEO_PIXELS needs 110,000 pixels a second, a
slow CPU's rate."""
VIDEO_RETRY_AFTER_S = 60
"""``Retry-After`` of a 429 when MAX_VIDEO_JOBS are queued or rendering."""


@dataclass(frozen=True)
class BodyRule:
    """Bodies of ``method`` requests whose path matches ``path`` (and whose content type
    starts with ``content_type`` when given) may carry at most ``max_bytes``."""

    method: str
    path: re.Pattern
    max_bytes: int
    content_type: str | None = None
    what: str = ""


def body_rules(max_upload_bytes: int) -> tuple[BodyRule, ...]:
    """The per-route body limits, first match wins (JSON and the fallback come after)."""
    from ar.assets import MAX_ASSET_BYTES

    session = r"/api/sessions/[^/]+"
    return (
        BodyRule("POST", re.compile(r"/api/sessions/?"), max_upload_bytes, "multipart/form-data",
                 "a dataset upload (VOXFUSION_MAX_UPLOAD_MB)"),
        BodyRule("POST", re.compile(session + r"/frames/?"), FRAME_BODY_BYTES, "multipart/form-data",
                 "a streamed frame"),
        BodyRule("POST", re.compile(r"/api/assets/?"), MAX_ASSET_BYTES + ASSET_FORM_BYTES, "multipart/form-data",
                 "an asset upload"),
    )


def _headers(scope) -> dict[bytes, bytes]:
    return {key.lower(): value for key, value in scope.get("headers") or []}


def json_depth(body: bytes) -> int:
    """How deep a JSON text nests (``[[1]]`` -> 2), counted outside strings; no parsing."""
    text = re.sub(rb'"(?:[^"\\]|\\.)*"', b'""', body)
    codes = np.frombuffer(text, dtype=np.uint8)
    steps = np.isin(codes, (ord("["), ord("{"))).astype(np.int32) - np.isin(codes, (ord("]"), ord("}")))
    return int(np.cumsum(steps).max()) if len(steps) else 0


class RequestBudget:
    """Pure ASGI middleware enforcing the body limits of :func:`body_rules`: 413 as soon as a
    declared or streamed body passes its route's limit (before the route reads it), and for
    JSON bodies 400 when they nest deeper than MAX_JSON_DEPTH or do not parse (so that no
    parser recursion or oversized number reaches a route)."""

    def __init__(self, app, max_upload_bytes: int) -> None:
        self.app = app
        self.rules = body_rules(max_upload_bytes)

    def limit_for(self, method: str, path: str, content_type: str) -> tuple[int, str]:
        for rule in self.rules:
            if (rule.method == method and rule.path.fullmatch(path)
                    and (rule.content_type is None or content_type.startswith(rule.content_type))):
                return rule.max_bytes, rule.what
        if content_type.startswith("application/json"):
            return JSON_BODY_BYTES, "a JSON body"
        return OTHER_BODY_BYTES, f"a {content_type.split(';')[0] or 'request'} body on this route"

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = _headers(scope)
        content_type = headers.get(b"content-type", b"").decode("latin-1").strip().lower()
        limit, what = self.limit_for(scope["method"], scope["path"], content_type)
        declared = headers.get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            await _answer(send, 413, _too_large(limit, what))
            return
        if content_type.startswith("application/json"):
            await self._json(scope, receive, send, limit, what)
            return
        await self._streamed(scope, receive, send, limit, what)

    async def _streamed(self, scope, receive, send, limit: int, what: str) -> None:
        received = 0
        started = False

        async def limited_receive():
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    raise _BodyTooLarge()
            return message

        async def tracking_send(message):
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except _BodyTooLarge:
            if not started:
                await _answer(send, 413, _too_large(limit, what))

    async def _json(self, scope, receive, send, limit: int, what: str) -> None:
        """Read the whole (bounded) body, check it, then replay it to the app."""
        chunks, size = [], 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > limit:
                await _answer(send, 413, _too_large(limit, what))
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        problem = _json_problem(body)
        if problem is not None:
            await _answer(send, 400, problem)
            return
        replayed = False

        async def replay():
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


def _json_problem(body: bytes) -> str | None:
    """Why a JSON body is refused before any route sees it, or None (empty bodies pass:
    the route says what it expected)."""
    if not body.strip():
        return None
    depth = json_depth(body)
    if depth > MAX_JSON_DEPTH:
        return f"the JSON body nests {depth} levels deep; at most {MAX_JSON_DEPTH} are accepted"
    try:
        json.loads(body)
    except UnicodeDecodeError:
        return "the body is not valid JSON: it is not UTF-8 text"
    except (json.JSONDecodeError, RecursionError) as error:
        return f"the body is not valid JSON ({error})"
    except ValueError:  # an integer past Python's digit limit: its message names interpreter internals
        return (f"the body is not valid JSON here: it holds a number too long "
                f"(at most {sys.get_int_max_str_digits()} digits)")
    return None


def _too_large(limit: int, what: str) -> str:
    size = f"{limit // MIB} MiB" if limit >= MIB else f"{limit // KIB} KiB"
    return f"request body larger than {size}, the limit for {what}"


async def _answer(send, status: int, detail: str) -> None:
    response = JSONResponse({"detail": detail}, status_code=status)
    await response({"type": "http"}, None, send)


class _BodyTooLarge(Exception):
    pass
