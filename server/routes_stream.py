"""Streamed RGB-D input: one frame per HTTP request, or many over a WebSocket.

WebSocket protocol at ``/api/sessions/{id}/stream`` (token as ``?token=`` when one is set):

1. The client sends a JSON header: ``{"intrinsics": "fx,fy,cx,cy", "depth_scale": 5000}``;
   both are optional when the session was created with them (``{}`` is a valid header).
   ``"agent": k`` (default 0) says which camera of a collaborative session this socket's
   frames come from. The server answers ``{"type": "ready", "frames_received": n}`` (all
   agents together).
2. Each frame is either
   * one **binary** message: 8-byte little-endian float64 timestamp, 4-byte little-endian
     uint32 length ``n`` of the colour image, the ``n`` colour bytes (PNG/JPEG), then the depth
     PNG bytes (16-bit) up to the end of the message; or
   * one **text** message ``{"timestamp": t, "color": "<base64>", "depth": "<base64>"}``
     (``intrinsics`` / ``depth_scale`` / ``agent`` may be added as in the header).
   The server answers each at once, in order, with one of
   * ``{"type": "ack", "index": i}``: accepted (``i`` counts that agent's frames from 0;
     ``"agent": k`` is added for agents other than 0, ``"dropped": d`` once the stream has
     dropped any frame);
   * ``{"type": "dropped", "status": 503, "detail": "...", "dropped": d, "retry_after_s": s}``:
     the session's frame buffer is full, the frame was dropped (``d`` dropped so far, all
     sockets of the session together). A live camera sends its next frame; a replay that must
     not lose one sends it again after ``s`` seconds. The socket never waits for room: it goes
     on reading, so the keepalive pings are answered however far behind the session is;
   * ``{"type": "error", "status": 422, "detail": "..."}`` for a bad frame (the socket stays open).
3. ``{"type": "finish"}`` ends the input; the server answers ``{"type": "finished", "frames": n}``
   and closes. Closing without it leaves the stream open (reconnect, or POST ``/finish``).

When the stream stops accepting frames otherwise (its session failed or was cancelled, it idled
out, the server stops, another client finished it) the server sends
``{"type": "error", "status": 409, "detail": "the stream does not accept frames: <why>"}`` and
closes the socket with code :data:`WS_STREAM_CLOSED` (4409) and the reason in the close frame
(cut to the 123 bytes a close frame holds); it notices within :data:`CLOSED_POLL_S`, whether or
not the client is sending. A socket opened on such a session gets the same in answer to its
header (or after :data:`CLOSED_POLL_S` without one), and so does one opened on a session that
is not a stream (an upload, a synthetic scene). HTTP frames get the same detail with a 409; an
HTTP frame that finds the buffer full waits up to ``stream_put_timeout_s`` for room, then gets
503 with ``Retry-After``.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import json
import struct

from fastapi import APIRouter, Depends, File, Form, UploadFile, WebSocket, WebSocketDisconnect, status
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

from server.deps import get_manager, refuse_foreign_origin, require_token, token_ok
from server.schemas import ErrorOut, FrameAccepted, StreamFinished
from server.sessions import SessionConflict, SessionManager, SessionNotFound, check_session_id
from server.stream import StreamBusy, StreamClosed, StreamInput
from server.upload import MAX_AGENTS, UploadError, parse_agent

router = APIRouter(prefix="/api/sessions", tags=["streaming"],
                   responses={401: {"model": ErrorOut}, 404: {"model": ErrorOut}})

BINARY_PREFIX = struct.Struct("<dI")
WS_STREAM_CLOSED = 4409
"""Close code of a socket whose stream accepts no more frames (an application code, after HTTP's 409)."""
CLOSED_POLL_S = 0.25
"""How often a socket waiting for the client looks whether its stream still accepts frames."""
MAX_CLOSE_REASON_BYTES = 123
FINISH = object()
"""What :func:`answer_message` returns for ``{"type": "finish"}``."""


@router.post("/{session_id}/frames", response_model=FrameAccepted, dependencies=[Depends(require_token)],
             responses={409: {"model": ErrorOut}, 413: {"model": ErrorOut}, 422: {"model": ErrorOut},
                        503: {"model": ErrorOut}},
             summary="Send one frame to a stream session")
async def post_frame(
    session_id: str,
    color: UploadFile = File(description="colour image, PNG or JPEG"),
    depth: UploadFile = File(description="depth, 16-bit single-channel PNG"),
    timestamp: str | None = Form(None, description="seconds (default: index / 30)", examples=["1305031453.36"]),
    depth_scale: str | None = Form(None, description="raw depth units per metre (default: the session's, or 1000)",
                                   examples=["5000"]),
    intrinsics: str | None = Form(None, description="fx,fy,cx,cy: required on the first frame (of each agent) "
                                                    "unless given when the session was created",
                                  examples=["525,525,319.5,239.5"]),
    agent: str | None = Form(None, description=f"the camera (agent) of a collaborative stream, 0..{MAX_AGENTS - 1}; "
                                               "default 0. Each agent's frames are indexed from 0",
                             examples=["0"]),
    manager: SessionManager = Depends(get_manager),
) -> FrameAccepted:
    stream = manager.stream(check_session_id(session_id))
    agent_id = 0 if agent in (None, "") else parse_agent(agent)
    color_bytes, depth_bytes = await color.read(), await depth.read()
    try:
        index = await run_in_threadpool(stream.add_frame, color_bytes, depth_bytes, timestamp=timestamp,
                                        depth_scale=depth_scale, intrinsics=intrinsics, agent=agent_id)
    except StreamBusy as busy:
        return JSONResponse({"detail": str(busy)}, status_code=503, headers={"Retry-After": str(busy.retry_after_s)})
    return FrameAccepted(index=index, frames_received=stream.frames_received, agent=agent_id)


@router.post("/{session_id}/finish", response_model=StreamFinished, dependencies=[Depends(require_token)],
             responses={409: {"model": ErrorOut}}, summary="End the input of a stream session")
async def finish_stream(session_id: str, manager: SessionManager = Depends(get_manager)) -> StreamFinished:
    stream = manager.stream(check_session_id(session_id))
    return StreamFinished(frames=await run_in_threadpool(stream.finish))


def decode_binary_frame(message: bytes) -> tuple[float, bytes, bytes]:
    """Binary frame message -> (timestamp, colour bytes, depth bytes); see the module docstring."""
    if len(message) < BINARY_PREFIX.size:
        raise UploadError(f"binary frame: {len(message)} bytes is shorter than the {BINARY_PREFIX.size}-byte prefix")
    timestamp, color_size = BINARY_PREFIX.unpack_from(message)
    start = BINARY_PREFIX.size
    if start + color_size >= len(message):
        raise UploadError(f"binary frame: colour length {color_size} leaves no bytes for the depth image")
    return timestamp, message[start:start + color_size], message[start + color_size:]


def decode_json_frame(data: dict) -> tuple[object, bytes, bytes, dict]:
    """Text frame message -> (timestamp, colour bytes, depth bytes, extra options)."""
    unknown = set(data) - {"timestamp", "color", "depth", "intrinsics", "depth_scale", "agent", "type"}
    if unknown:
        raise UploadError(f"frame: unknown key(s) {sorted(unknown)}")
    images = []
    for key in ("color", "depth"):
        if not isinstance(data.get(key), str):
            raise UploadError(f"frame: '{key}' must be a base64 string")
        try:
            images.append(base64.b64decode(data[key], validate=True))
        except (binascii.Error, ValueError):
            raise UploadError(f"frame: '{key}' is not valid base64") from None
    options = {k: data[k] for k in ("intrinsics", "depth_scale") if k in data}
    if "agent" in data:
        options["agent"] = parse_agent(data["agent"], "frame: agent")
    return data.get("timestamp"), images[0], images[1], options


def _error_answer(error: UploadError) -> dict:
    return {"type": "error", "status": error.status, "detail": str(error)}


async def _send_error(websocket: WebSocket, error: UploadError) -> None:
    await websocket.send_json(_error_answer(error))


@router.websocket("/{session_id}/stream")
async def stream_socket(websocket: WebSocket, session_id: str) -> None:
    """Frames over a WebSocket; the protocol is in this module's docstring and the README."""
    if await refuse_foreign_origin(websocket):
        return
    if not token_ok(websocket):
        await websocket.close(code=status.WS_1008_POLICY_VIOLATION, reason="missing or wrong token")
        return
    manager: SessionManager = websocket.app.state.manager
    try:
        stream = manager.stream(check_session_id(session_id))
    except SessionNotFound as error:
        await websocket.close(code=status.WS_1008_POLICY_VIOLATION, reason=f"no stream session {session_id}: {error}")
        return
    except SessionConflict as error:
        await websocket.accept()
        await _refuse_not_a_stream(websocket, str(error))
        return
    await websocket.accept()
    try:
        # On a stream that takes no more frames the header is still read when it comes within a
        # poll (a client sends it first and then reads the answer: the error, not a broken pipe).
        header = await _read_header(websocket, stream)
        if header is None:
            return
        if stream.finished:
            await _close_stream_ended(websocket, stream)
            return
        await _serve_frames(websocket, stream, header)
    except WebSocketDisconnect:
        return


def _close_reason(text: str) -> str:
    """``text`` cut to what a close frame holds (123 bytes of UTF-8)."""
    data = text.encode()
    if len(data) <= MAX_CLOSE_REASON_BYTES:
        return text
    return data[:MAX_CLOSE_REASON_BYTES - 3].decode(errors="ignore") + "..."


async def _close_stream_ended(websocket: WebSocket, stream: StreamInput) -> None:
    """The stream accepts no more frames: one error that says why, then close (module doc)."""
    await _close_409(websocket, stream.closed_reason or "the session has ended")


async def _close_409(websocket: WebSocket, reason: str) -> None:
    await websocket.send_json({"type": "error", "status": 409, "detail": f"the stream does not accept frames: {reason}"})
    await websocket.close(code=WS_STREAM_CLOSED, reason=_close_reason(reason))


async def _refuse_not_a_stream(websocket: WebSocket, reason: str) -> None:
    """A socket on a session that takes no frames: its header is read when it comes within
    CLOSED_POLL_S (so the client reads the error, not a broken pipe), then 409 and close 4409."""
    try:
        message = await asyncio.wait_for(websocket.receive(), timeout=CLOSED_POLL_S)
    except asyncio.TimeoutError:
        message = None
    if message is not None and message["type"] == "websocket.disconnect":
        return
    try:
        await _close_409(websocket, reason)
    except WebSocketDisconnect:
        return


async def _receive(websocket: WebSocket, stream: StreamInput) -> dict | None:
    """The client's next message, or None as soon as the stream stops accepting frames (looked
    at every CLOSED_POLL_S while the client is quiet)."""
    receiving = asyncio.ensure_future(websocket.receive())
    try:
        while True:
            done, _ = await asyncio.wait({receiving}, timeout=CLOSED_POLL_S)
            if done:
                return receiving.result()
            if stream.finished:
                return None
    finally:
        if not receiving.done():
            receiving.cancel()


async def _read_header(websocket: WebSocket, stream: StreamInput) -> dict | None:
    message = await _receive(websocket, stream)
    if message is None:
        await _close_stream_ended(websocket, stream)
        return None
    if message["type"] == "websocket.disconnect":
        raise WebSocketDisconnect(message.get("code", 1000))
    try:
        if message.get("text") is None:
            raise ValueError("a binary message")
        header = json.loads(message["text"])
        if not isinstance(header, dict):
            raise ValueError("not an object")
    except ValueError as error:
        await websocket.send_json({"type": "error", "status": 400, "detail": f"header: expected a JSON object ({error})"})
        await websocket.close(code=status.WS_1003_UNSUPPORTED_DATA)
        return None
    unknown = set(header) - {"intrinsics", "depth_scale", "agent", "type"}
    if unknown:
        await websocket.send_json({"type": "error", "status": 422, "detail": f"header: unknown key(s) {sorted(unknown)}"})
        await websocket.close(code=status.WS_1003_UNSUPPORTED_DATA)
        return None
    options = {k: header[k] for k in ("intrinsics", "depth_scale") if k in header}
    if header.get("agent") is not None:
        try:
            options["agent"] = parse_agent(header["agent"], "header: agent")
        except UploadError as error:
            await _send_error(websocket, error)
            await websocket.close(code=status.WS_1003_UNSUPPORTED_DATA)
            return None
    return options


async def _serve_frames(websocket: WebSocket, stream: StreamInput, options: dict) -> None:
    await websocket.send_json({"type": "ready", "frames_received": stream.frames_received})
    while True:
        message = await _receive(websocket, stream)
        if message is None:
            await _close_stream_ended(websocket, stream)
            return
        if message["type"] == "websocket.disconnect":
            return
        try:
            # Parsing, decoding and queueing run off the event loop, and never wait for room.
            answer = await run_in_threadpool(answer_message, stream, message, options)
            if answer is FINISH:
                frames = await run_in_threadpool(stream.finish)
                await websocket.send_json({"type": "finished", "frames": frames})
                await websocket.close()
                return
        except StreamClosed:
            await _close_stream_ended(websocket, stream)
            return
        except UploadError as error:
            answer = _error_answer(error)
        await websocket.send_json(answer)


def answer_message(stream: StreamInput, message: dict, options: dict) -> dict | object:
    """One frame message of a socket (``options``: its header's) -> the answer to send: an
    ack, a drop (the buffer is full) or an error (module doc); :data:`FINISH` for a finish.
    Blocking work (a worker thread's); raises StreamClosed when the stream takes no frames."""
    try:
        if message.get("bytes") is not None:
            timestamp, color, depth = decode_binary_frame(message["bytes"])
            extra = {}
        else:
            data = json.loads(message.get("text") or "null")
            if not isinstance(data, dict):
                raise UploadError("frame: expected a JSON object", status=400)
            if data.get("type") == "finish":
                return FINISH
            if data.get("type") == "ground_truth":  # once, before the frames: the run's ATE (server.stream)
                kept = stream.set_ground_truth(data.get("poses"), options.get("agent", 0))
                return {"type": "ground_truth", "poses": kept}
            timestamp, color, depth, extra = decode_json_frame(data)
        frame_options = {**options, **extra}
        agent = frame_options.get("agent", 0)
        # Intrinsics and scale are remembered by the stream after each agent's first frame.
        index = stream.add_frame(color, depth, timestamp=timestamp, depth_scale=frame_options.get("depth_scale"),
                                 intrinsics=frame_options.get("intrinsics"), agent=agent, wait=False)
    except json.JSONDecodeError as error:
        return _error_answer(UploadError(f"frame: not valid JSON ({error})", status=400))
    except StreamBusy as busy:
        return {"type": "dropped", "status": 503, "detail": str(busy), "dropped": busy.dropped,
                "retry_after_s": busy.retry_after_s}
    except StreamClosed:
        raise
    except UploadError as error:
        return _error_answer(error)
    ack = {"type": "ack", "index": index}
    if agent != 0:
        ack["agent"] = agent
    if stream.frames_dropped:
        ack["dropped"] = stream.frames_dropped
    return ack
