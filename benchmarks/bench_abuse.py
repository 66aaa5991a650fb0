"""Issue 39's abuse cases against a real server, with the API process's memory watched.

    python benchmarks/bench_abuse.py [--fuzz-minutes 10] [--out bench_abuse.json]

Starts ``voxfusion serve`` (``python -m server.cli serve``) on 127.0.0.1 with a token, in a
subprocess, then runs each case an attacker or an operator tried (uploads naming the server's
files, image bombs, huge sizes in small requests, a full queue, oversized and deeply nested
JSON, a slow body, out-of-range numbers, empty mesh exports, lists racing deletions, many
assets, a stream socket flooded with frames) and reports per case: the answers' status codes, whether any was a 5xx, whether one
hung (no answer within 30 s), and the API process's resident memory (peak so far, from
``/proc/PID/status`` ``VmHWM``). With ``--fuzz-minutes`` it then runs schemathesis's CLI
against the same server for that long (with the token) and counts server errors.

Verdict: 0 server errors, 0 hangs, peak API memory under 1 GB (issue 39's figures).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
TOKEN = "bench-abuse-token"
HANG_S = 30.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def png(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", image)[1].tobytes()


def png_bomb(width: int, height: int) -> bytes:
    """A valid grey PNG of zeros: kilobytes compressed, width * height bytes decoded."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    compressor = zlib.compressobj(9)
    row = b"\x00" * (width + 1)
    body = b"".join(compressor.compress(row) for _ in range(height)) + compressor.flush()
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", body) + chunk(b"IEND", b""))


TIMES = (1.0, 1.033, 1.066)
COLOR = png(np.full((48, 64, 3), 120, np.uint8))
DEPTH = png(np.full((48, 64), 5000, np.uint16))


def tum_zip(rgb_names: list[str] | None = None, replace: dict[str, bytes] | None = None) -> bytes:
    top = "rgbd_dataset_freiburg1_tiny/"
    names = rgb_names or [f"rgb/{t:.6f}.png" for t in TIMES]
    entries = {top + "rgb.txt": "".join(f"{t:.6f} {n}\n" for t, n in zip(TIMES, names)).encode(),
               top + "depth.txt": "".join(f"{t:.6f} depth/{t:.6f}.png\n" for t in TIMES).encode(),
               top + "intrinsics.txt": b"52 52 31.5 23.5\n"}
    for t in TIMES:
        entries[top + f"rgb/{t:.6f}.png"] = COLOR
        entries[top + f"depth/{t:.6f}.png"] = DEPTH
    for name, data in (replace or {}).items():
        entries[top + name] = data
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, data in entries.items():
            archive.writestr(name, data)
    return buffer.getvalue()


@dataclass
class CaseResult:
    name: str
    statuses: list[int] = field(default_factory=list)
    seconds: float = 0.0
    server_errors: int = 0
    hangs: int = 0
    peak_mb: float = 0.0
    note: str = ""


@dataclass(frozen=True)
class CaseNote:
    """What a case found beyond HTTP answers (a WebSocket's fate): ``text`` goes to the
    report, ``failed`` counts as a server error."""

    text: str
    failed: bool = False


class Server:
    """``voxfusion serve`` in a subprocess on 127.0.0.1, behind a token."""

    def __init__(self, data_dir: Path, extra_env: dict[str, str] | None = None) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        env = {**os.environ, "VOXFUSION_TOKEN": TOKEN, **(extra_env or {}),
               "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
        self.log = open(data_dir.parent / "server.log", "ab")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "server.cli", "serve", "--host", "127.0.0.1", "--port", str(self.port),
             "--data-dir", str(data_dir), "--viewer-port", "-1"],
            cwd=REPO, env=env, stdout=self.log, stderr=subprocess.STDOUT)
        self.headers = {"Authorization": f"Bearer {TOKEN}"}
        self.client = httpx.Client(base_url=self.url, timeout=HANG_S, headers=self.headers)
        deadline = time.monotonic() + 120
        while True:
            try:
                self.client.get("/api/sessions").raise_for_status()
                return
            except httpx.HTTPError:
                if time.monotonic() > deadline or self.process.poll() is not None:
                    raise RuntimeError(f"the server did not start (see {self.log.name})") from None
                time.sleep(0.5)

    def memory_mb(self) -> tuple[float, float]:
        """(resident now, peak resident) of the API process, MiB."""
        fields = {}
        with open(f"/proc/{self.process.pid}/status") as status:
            for line in status:
                key, _, value = line.partition(":")
                fields[key] = value
        return int(fields["VmRSS"].split()[0]) / 1024, int(fields["VmHWM"].split()[0]) / 1024

    def alive(self) -> bool:
        return self.process.poll() is None

    def stop(self) -> None:
        self.client.close()
        if self.alive():
            self.process.terminate()
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.process.kill()
        self.log.close()


def run_case(server: Server, name: str, requests) -> CaseResult:
    """Send ``requests(client)`` (a generator of responses or exceptions) and record them."""
    result = CaseResult(name)
    started = time.monotonic()
    for outcome in requests(server.client):
        if isinstance(outcome, httpx.TimeoutException):
            result.hangs += 1
            result.statuses.append(0)
        elif isinstance(outcome, CaseNote):
            result.note += outcome.text
            result.server_errors += outcome.failed
        elif isinstance(outcome, Exception):
            result.note = f"{type(outcome).__name__}: {outcome}"
            result.statuses.append(-1)
        else:
            result.statuses.append(outcome.status_code)
            result.server_errors += outcome.status_code >= 500
    result.seconds = round(time.monotonic() - started, 2)
    result.peak_mb = round(server.memory_mb()[1], 1)
    if not server.alive():
        result.note += " SERVER DIED"
        result.server_errors += 1
    return result


def _send(call):
    try:
        return call()
    except httpx.HTTPError as error:
        return error


def _upload(client, data: bytes, **form):
    return _send(lambda: client.post("/api/sessions", files={"file": ("d.zip", data, "application/zip")},
                                     data={"preset": "test", **form}))


FLOOD_FRAMES = 49
KEEPALIVE_HOLD_S = 45.0
"""Longer than uvicorn's keepalive round (a ping every 20 s, 20 s for its pong)."""


def stream_flood(client):
    """Case 8: a stream socket sends 49 frames as fast as it can, then reads the answers; every
    frame must get one (ack or dropped), and the socket must still take a frame after
    ``KEEPALIVE_HOLD_S`` with its session still behind, then finish."""
    created = _send(lambda: client.post("/api/sessions", json={
        "source": "stream", "preset": "test", "intrinsics": "52,52,31.5,23.5", "depth_scale": 5000}))
    yield created
    if isinstance(created, Exception) or created.status_code != 201:
        return
    session = created.json()["id"]
    yield flood_socket(str(client.base_url).replace("http", "ws", 1) + f"/api/sessions/{session}/stream?token={TOKEN}")
    yield _send(lambda: client.delete(f"/api/sessions/{session}"))


def flood_socket(url: str) -> CaseNote:
    """The socket half of case 8: acks / drops / errors of the frames sent, and whether it survived."""
    import websockets.sync.client as ws_client
    from websockets.exceptions import ConnectionClosed

    answers: list[str] = []
    survived, closed = False, ""
    try:
        with ws_client.connect(url, open_timeout=HANG_S, close_timeout=5) as sock:
            sock.send("{}")
            sock.recv(timeout=HANG_S)
            for i in range(FLOOD_FRAMES):
                sock.send(struct.pack("<dI", i / 30, len(COLOR)) + COLOR + DEPTH)
            for _ in range(FLOOD_FRAMES):
                answers.append(json.loads(sock.recv(timeout=HANG_S))["type"])
            time.sleep(KEEPALIVE_HOLD_S)
            sock.send(struct.pack("<dI", FLOOD_FRAMES / 30, len(COLOR)) + COLOR + DEPTH)
            late = json.loads(sock.recv(timeout=HANG_S))["type"]
            sock.send(json.dumps({"type": "finish"}))
            survived = late in ("ack", "dropped") and json.loads(sock.recv(timeout=HANG_S))["type"] == "finished"
    except ConnectionClosed as error:
        closed = f"; closed: {error.rcvd.code} {error.rcvd.reason}" if error.rcvd else "; connection lost"
    except TimeoutError:
        closed = f"; no answer within {HANG_S:g} s"
    counts = {kind: answers.count(kind) for kind in ("ack", "dropped", "error")}
    unanswered = FLOOD_FRAMES - len(answers)
    text = (f"sent {FLOOD_FRAMES}: acks {counts['ack']}, dropped {counts['dropped']}, errors {counts['error']}, "
            f"unanswered {unanswered}; socket {'survived' if survived else 'died'} a {KEEPALIVE_HOLD_S:g} s hold{closed}")
    return CaseNote(text, failed=unanswered > 0 or not survived)


@dataclass(frozen=True)
class Handshake:
    """A WebSocket handshake's answer as a status code: 101 accepted, else the refusal's."""

    status_code: int


def handshake(url: str, origin: str | None = None):
    """Open and close a WebSocket: a :class:`Handshake`, or the exception that ended it."""
    from websockets.exceptions import InvalidStatus, WebSocketException
    from websockets.sync.client import connect

    try:
        with connect(url, origin=origin, open_timeout=HANG_S, close_timeout=2):
            return Handshake(101)
    except InvalidStatus as refused:
        return Handshake(refused.response.status_code)
    except (OSError, WebSocketException) as error:
        return error


def _stream_session(client):
    created = _send(lambda: client.post("/api/sessions", json={"source": "stream", "preset": "test"}))
    ok = not isinstance(created, Exception) and created.status_code == 201
    return created, (created.json()["id"] if ok else "000000000000")


def token_everywhere(client):
    """Case 9: the token in every spelling a client may use, over HTTP and WebSockets (the log
    is scanned for it once every case has run: :func:`token_leaks`)."""
    created, session = _stream_session(client)
    yield created
    bare = httpx.Client(base_url=str(client.base_url), timeout=HANG_S)
    encoded = "".join(f"%{b:02X}" for b in TOKEN.encode())
    for path in (f"/api/sessions?token={TOKEN}", f"/api/sessions?TOKEN={encoded.lower()}&x=1", f"/?token={TOKEN}",
                 f"/viewer%3Ftoken%3D{TOKEN}", f"/api/sessions/token%3D{encoded}", f"/api/sessions/{TOKEN}"):
        yield _send(lambda: bare.get(path))
    yield _send(lambda: bare.get("/api/sessions", headers={"Authorization": f"Bearer {TOKEN}"}))
    ws = str(client.base_url).replace("http", "ws", 1)
    for path in (f"/api/sessions/{session}/stream?token={TOKEN}", f"/api/sessions/{session}/stream?token={encoded}",
                 f"/viewer?token={TOKEN}", f"/api/sessions/{session}/stream%3Ftoken%3D{TOKEN}"):
        yield handshake(ws + path)
    bare.close()
    yield _send(lambda: client.delete(f"/api/sessions/{session}"))


def foreign_origins(client):
    """Case 9: WebSocket handshakes from other sites' pages (each must get 403), then from our
    own page and from a program without ``Origin`` (both 101)."""
    created, session = _stream_session(client)
    yield created
    base = str(client.base_url)
    url = base.replace("http", "ws", 1) + f"/api/sessions/{session}/stream?token={TOKEN}"
    port = base.rsplit(":", 1)[1]
    for origin in ("http://evil.example", f"http://evil.example:{port}", f"http://127.0.0.1:{free_port()}", "null"):
        yield handshake(url, origin)
    for origin in (base, None):
        yield handshake(url, origin)
    yield _send(lambda: client.delete(f"/api/sessions/{session}"))


ORIGIN_CASE = "9 WebSockets from another site's page"


def foreign_accepted(result: CaseResult) -> int:
    """Handshakes from foreign origins that were accepted (the first 101s before our own two)."""
    return result.statuses[1:5].count(101)


def token_spellings(token: str = TOKEN) -> list[str]:
    from urllib.parse import quote, quote_plus

    every_byte = "".join(f"%{b:02X}" for b in token.encode())
    return [token, quote(token, safe=""), quote_plus(token), every_byte, every_byte.lower()]


def token_leaks(log: Path) -> int:
    """How often the token appears in the server's log, in any spelling (target 0)."""
    text = log.read_text(errors="replace")
    return sum(text.count(spelling) for spelling in set(token_spellings()))


RENDER_FLOOD_RENDERS = 16
RENDER_FLOOD_VIDEOS = 20
RENDER_FLOOD_WAIT_S = 300.0
"""Longest the render flood waits for its session's first map, and for one answer (a render
waits for a helper, then renders for up to its time limit)."""


def _map_session(client) -> str | None:
    """A small synthetic session once it has written a map (None if it never does)."""
    created = _send(lambda: client.post("/api/sessions", json={"source": "synthetic", "preset": "test",
                                                               "spec": "orbit?frames=12&width=160&height=120"}))
    if isinstance(created, Exception) or created.status_code != 201:
        return None
    session = created.json()["id"]
    deadline = time.monotonic() + RENDER_FLOOD_WAIT_S
    while time.monotonic() < deadline:
        state = client.get(f"/api/sessions/{session}").json()
        if state["outputs"]["map"] or state["status"] in ("finished", "failed", "cancelled"):
            return session if state["outputs"]["map"] else None
        time.sleep(1.0)
    return None


def render_flood(client):
    """Case 11: 16 concurrent 2048x2048 renders and 20 camera-path videos (half of them over
    the pixel budget) while a second client polls ``GET /api/sessions``: the answers (200, or
    503/504/429/422 from the budget), the second client's p95 latency, and (run_case) the API
    process's peak memory."""
    session = _map_session(client)
    if session is None:
        yield CaseNote("no session with a map: nothing rendered", failed=True)
        return
    camera = client.get(f"/api/sessions/{session}/camera").json()
    big = {"T_world_cam": camera["T_world_cam"],
           "intrinsics": {"fx": 1400.0, "fy": 1400.0, "cx": 1024.0, "cy": 1024.0, "width": 2048, "height": 2048}}
    video = {"keyframes": [camera["T_world_cam"]] * 2, "fps": 24.0,
             "intrinsics": {"fx": 450.0, "fy": 450.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480}}
    url = f"/api/sessions/{session}"
    answers: list = []
    latencies: list[float] = []
    done = threading.Event()
    flood = httpx.Client(base_url=str(client.base_url), headers=client.headers, timeout=RENDER_FLOOD_WAIT_S)

    def render() -> None:
        answers.append(_send(lambda: flood.post(f"{url}/render", json=big)))

    def path_video(k: int) -> None:  # even k: 3600 frames (over the budget); odd: 600 frames (within)
        body = {**video, "duration_s": 60.0 if k % 2 == 0 else 25.0, "fps": 60.0 if k % 2 == 0 else 24.0}
        answers.append(_send(lambda: flood.post(f"{url}/render/path", json=body)))

    def poll() -> None:
        with httpx.Client(base_url=str(client.base_url), headers=client.headers, timeout=HANG_S) as second:
            while not done.is_set():
                started = time.monotonic()
                answers.append(_send(lambda: second.get("/api/sessions")))
                latencies.append(time.monotonic() - started)
                time.sleep(0.1)

    poller = threading.Thread(target=poll)
    poller.start()
    workers = [threading.Thread(target=render) for _ in range(RENDER_FLOOD_RENDERS)]
    workers += [threading.Thread(target=path_video, args=(k,)) for k in range(RENDER_FLOOD_VIDEOS)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    done.set()
    poller.join()
    flood.close()
    codes = [a.status_code if isinstance(a, httpx.Response) else -1 for a in answers]
    unexpected = sum(c not in (200, 202, 422, 429, 503, 504) for c in codes)
    p95_ms = 1000 * float(np.percentile(latencies, 95)) if latencies else float("nan")
    counts = {c: codes.count(c) for c in sorted(set(codes))}
    yield CaseNote(f"answers {counts}; GET /api/sessions p95 {p95_ms:.0f} ms over {len(latencies)} polls "
                   f"(max {1000 * max(latencies, default=0):.0f} ms)", failed=unexpected > 0)
    yield _send(lambda: client.delete(f"/api/sessions/{session}"))


RENDER_FLOOD_CASE = "11 16 renders 2048x2048 + 20 videos while a client polls"


def deep_glb(depth: int = 5000) -> bytes:
    """A GLB of one triangle held by a chain of ``depth`` nodes, each the only child of the
    one before and each an instance of the triangle."""
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32).tobytes()
    binary = positions + np.array([0, 1, 2, 0], np.uint16).tobytes()
    nodes = [{"mesh": 0, "children": [i + 1]} for i in range(depth - 1)] + [{"mesh": 0}]
    document = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": nodes,
                "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
                "buffers": [{"byteLength": len(binary)}],
                "bufferViews": [{"buffer": 0, "byteLength": 36}, {"buffer": 0, "byteOffset": 36, "byteLength": 6}],
                "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                               "min": [0, 0, 0], "max": [1, 1, 0]},
                              {"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"}]}
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<I4s", len(text), b"JSON") + text + struct.pack("<I4s", len(binary), b"BIN\0") + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def replica_zip_long_traj(lines: int = 2_000_000, frames: int = 3) -> bytes:
    """A Replica scene of ``frames`` frames whose ``traj.txt`` has ``lines`` poses (distinct
    rows, so the zip is megabytes, not kilobytes)."""
    entries = {"cam_params.json": json.dumps({"camera": {"w": 64, "h": 48, "fx": 50.0, "fy": 50.0, "cx": 31.5,
                                                         "cy": 23.5, "scale": 6553.5}}).encode()}
    for n in range(frames):
        entries[f"room0/results/frame{n:06d}.jpg"] = cv2.imencode(".jpg", np.full((48, 64, 3), 100, np.uint8))[1].tobytes()
        entries[f"room0/results/depth{n:06d}.png"] = png(np.full((48, 64), 6553, np.uint16))
    rows = (f"1 0 0 {0.001 * i:.3f} 0 1 0 0 0 0 1 1 0 0 0 1\n" for i in range(lines))
    entries["room0/traj.txt"] = "".join(rows).encode()
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, data in entries.items():
            archive.writestr(name, data)
    return buffer.getvalue()


class SessionsPoller:
    """A second client that lists the sessions every 0.1 s on its own thread until stopped;
    ``p95_ms`` of its answers' latencies."""

    def __init__(self, client) -> None:
        self._second = httpx.Client(base_url=str(client.base_url), headers=client.headers, timeout=HANG_S)
        self._stop = threading.Event()
        self.latencies: list[float] = []
        self.answers: list = []
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.wait(0.1):
            started = time.monotonic()
            self.answers.append(_send(lambda: self._second.get("/api/sessions")))
            self.latencies.append(time.monotonic() - started)

    def stop(self) -> str:
        self._stop.set()
        self._thread.join()
        self._second.close()
        p95 = 1000 * float(np.percentile(self.latencies, 95)) if self.latencies else float("nan")
        return f"GET /api/sessions p95 {p95:.0f} ms over {len(self.latencies)} polls"


def deep_node_glb(client):
    """Case 12: a GLB whose 5,000 nodes nest 5,000 deep (422 within seconds, not minutes),
    then the server still answers."""
    data = deep_glb()
    started = time.monotonic()
    response = _send(lambda: client.post("/api/assets", files={"file": ("tower.glb", data)}))
    yield response
    detail = response.json().get("detail", "") if isinstance(response, httpx.Response) else ""
    yield CaseNote(f"{len(data) // 1024} KiB GLB answered in {time.monotonic() - started:.2f} s: {detail[:90]}")
    yield _send(lambda: client.get("/api/sessions"))


def huge_obj(client):
    """Case 13: an OBJ of 7 million faces (56 MB) is refused from its line counts."""
    data = b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * 7_000_000
    started = time.monotonic()
    response = _send(lambda: client.post("/api/assets", files={"file": ("big.obj", data)}))
    yield response
    detail = response.json().get("detail", "") if isinstance(response, httpx.Response) else ""
    yield CaseNote(f"{len(data) // 2**20} MiB OBJ answered in {time.monotonic() - started:.2f} s: {detail[:90]}")


def long_ground_truth(client):
    """Case 14: a Replica upload whose traj.txt has 2 million lines, then its series (asked
    three times) while a second client polls ``GET /api/sessions``."""
    data = replica_zip_long_traj()
    poller = SessionsPoller(client)
    started = time.monotonic()
    # The upload's own check reads traj.txt whole (in the decode helper): minutes, not a hang.
    created = _send(lambda: client.post("/api/sessions", files={"file": ("d.zip", data, "application/zip")},
                                        data={"preset": "test"}, timeout=300.0))
    yield created
    notes = [f"upload {time.monotonic() - started:.1f} s"]
    if isinstance(created, httpx.Response) and created.status_code == 201:
        session = created.json()["id"]
        for _ in range(3):
            started = time.monotonic()
            series = _send(lambda: client.get(f"/api/sessions/{session}/series"))
            yield series
            note = series.json().get("ground_truth_note") if isinstance(series, httpx.Response) else None
            notes.append(f"{time.monotonic() - started:.2f} s ({note})")
            time.sleep(1.0)
        yield _send(lambda: client.delete(f"/api/sessions/{session}"))
    yield CaseNote(f"{len(data) // 2**20} MiB zip; {'; series: '.join(notes)}; {poller.stop()}")
    yield from poller.answers


def cases() -> dict[str, object]:
    def outside_paths(client):
        for name in ("/etc/hostname", "/no/such/file.png", "../../../../etc/passwd", "rgb/../../x.png"):
            yield _upload(client, tum_zip([name, f"rgb/{TIMES[1]:.6f}.png", f"rgb/{TIMES[2]:.6f}.png"]))
        first = _upload(client, tum_zip())
        yield first
        if not isinstance(first, Exception) and first.status_code == 201:
            victim = first.json()["id"]
            stolen = f"../../../{victim}/input/rgbd_dataset_freiburg1_tiny/rgb/{TIMES[0]:.6f}.png"
            yield _upload(client, tum_zip([stolen, f"rgb/{TIMES[1]:.6f}.png", f"rgb/{TIMES[2]:.6f}.png"]))

    def image_bombs(client):
        for side in (10_000, 30_000):
            yield _upload(client, tum_zip(replace={f"rgb/{TIMES[1]:.6f}.png": png_bomb(side, side)}))

    def huge_sizes(client):
        for spec in ("orbit?frames=100000000000", "orbit?frames=1000000", "orbit?width=100000"):
            yield _send(lambda: client.post("/api/sessions", json={"source": "synthetic", "spec": spec}))
        created = _send(lambda: client.post("/api/sessions", json={"source": "synthetic", "preset": "test",
                                                                   "spec": "orbit?frames=20000&width=64"}))
        yield created
        if not isinstance(created, Exception) and created.status_code == 201:
            session = created.json()["id"]
            yield _send(lambda: client.get(f"/api/sessions/{session}/series"))
            yield _send(lambda: client.post(f"/api/sessions/{session}/ar",
                                            json={"background": "frame:19999", "objects": []}))
            yield _send(lambda: client.delete(f"/api/sessions/{session}"))

    def full_queue(client):
        created = []
        for _ in range(150):
            response = _send(lambda: client.post("/api/sessions", json={"source": "stream", "preset": "test"}))
            yield response
            if not isinstance(response, Exception) and response.status_code == 201:
                created.append(response.json()["id"])
        for session in created:
            yield _send(lambda: client.delete(f"/api/sessions/{session}"))

    def big_and_deep_json(client):
        body = b'{"source": "synthetic", "spec": "' + b"x" * (200 * 1024 * 1024) + b'"}'
        yield _send(lambda: client.post("/api/sessions", content=body, headers={"content-type": "application/json"}))
        deep = b"[" * 200_000 + b"]" * 200_000
        for route in ("/api/sessions", "/api/sessions/000000000000/render"):
            yield _send(lambda: client.post(route, content=deep, headers={"content-type": "application/json"}))

    def out_of_range(client):
        for value in ("1e-300", "1e300"):
            yield _upload(client, tum_zip(), depth_scale=value)
            yield _upload(client, tum_zip(), intrinsics=f"{value},{value},0,0")
            yield _send(lambda: client.post("/api/sessions", json={"source": "stream", "depth_scale": float(value)}))

    def operator(client):
        for _ in range(20):  # list while creating and deleting
            created = _send(lambda: client.post("/api/sessions", json={"source": "stream", "preset": "test"}))
            yield created
            results = []
            thread = threading.Thread(target=lambda: results.append(_send(lambda: client.get("/api/sessions"))))
            thread.start()
            if not isinstance(created, Exception) and created.status_code == 201:
                yield _send(lambda: client.delete(f"/api/sessions/{created.json()['id']}"))
            thread.join()
            yield from results
        yield _send(lambda: client.get("/api/sessions/000000000000/mesh", params={"format": "glb"}))

    def many_assets(client):
        cube = "".join(f"v {x} {y} {z}\n" for x in (0, 1) for y in (0, 1) for z in (0, 1)) + "f 1 2 4\nf 1 4 3\n"
        ids = []
        for k in range(300):
            response = _send(lambda: client.post("/api/assets", files={"file": (f"c{k}.obj", cube.encode())}))
            yield response
            if not isinstance(response, Exception) and response.status_code == 201:
                ids.append(response.json()["id"])
        for asset in ids:
            yield _send(lambda: client.delete(f"/api/assets/{asset}"))

    return {"1 upload names files outside itself": outside_paths, "2 image bombs in a zip": image_bombs,
            "3 huge sizes in small requests": huge_sizes, "4 150 creates at a full queue": full_queue,
            "5 200 MiB and 200k-deep JSON": big_and_deep_json, "7 values out of range": out_of_range,
            "7 lists racing deletions, empty mesh": operator, "7 300 assets": many_assets,
            "8 a stream sending 49 frames as fast as it can": stream_flood,
            "9 the token in every spelling, HTTP and WebSocket": token_everywhere, ORIGIN_CASE: foreign_origins,
            "10 zips the disk cannot unpack": unpackable_zips, RENDER_FLOOD_CASE: render_flood,
            "12 a GLB whose nodes nest 5,000 deep": deep_node_glb, "13 an OBJ of 7 million faces": huge_obj,
            "14 a 2M-line traj.txt and its series while a client polls": long_ground_truth}


def slow_body_then_sigterm(data_dir: Path) -> CaseResult:
    """Case 6: a body at 1 byte/s holds a request open; SIGTERM must still end the server
    within Docker's 10 s."""
    server = Server(data_dir)
    result = CaseResult("6 SIGTERM during a 1 byte/s body")
    sock = socket.create_connection(("127.0.0.1", server.port))
    sock.sendall(f"POST /api/sessions HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {TOKEN}\r\n"
                 f"Content-Type: application/json\r\nContent-Length: 1000\r\n\r\n{{".encode())
    time.sleep(1.0)
    result.peak_mb = round(server.memory_mb()[1], 1)
    started = time.monotonic()
    server.process.terminate()
    try:
        server.process.wait(timeout=HANG_S)
        result.statuses.append(server.process.returncode)
    except subprocess.TimeoutExpired:
        result.hangs += 1
        server.process.kill()
    result.seconds = round(time.monotonic() - started, 2)
    result.note = f"exited {result.seconds} s after SIGTERM"
    sock.close()
    server.stop()
    return result


def unpackable_zips(client):
    """Case 10: zips no disk can unpack as they are (a file that another entry needs as a folder,
    either order; a 300-character name; 2000 folders deep), at the top and in a folder: 422 each."""
    deep = "/".join(["d"] * 2000) + "/x.png"
    for names in (["d/x", "d/x/y"], ["d/x/y", "d/x"], ["rgb/" + "n" * 300 + ".png"], [deep]):
        for top in ("", "rgbd_dataset_freiburg1_tiny/"):
            buffer = io.BytesIO()
            with zipfile.ZipFile(buffer, "w") as archive:
                for name in names + ["rgb.txt"]:
                    archive.writestr(top + name, b"x")
            yield _upload(client, buffer.getvalue())


def worker_processes(server_pid: int) -> int:
    """Spawned processes of the server now (its session workers, and its decode helper when
    one runs): direct children started by multiprocessing's spawn."""
    count = 0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) != server_pid:
                continue
            count += b"spawn_main" in (stat.parent / "cmdline").read_bytes()
        except (OSError, ValueError):
            continue
    return count


SLOT_SESSIONS = 34


def cancel_queued_under_one_slot(data_dir: Path) -> CaseResult:
    """Case 11: VOXFUSION_MAX_SESSIONS=1, 34 synthetic sessions (one running, 33 queued), then
    all deleted at once; the worker processes alive at once are counted every 0.1 s until none
    is left (target: never more than 1)."""
    server = Server(data_dir, {"VOXFUSION_MAX_SESSIONS": "1", "VOXFUSION_MAX_QUEUED": str(SLOT_SESSIONS)})
    result = CaseResult(f"15 {SLOT_SESSIONS} sessions deleted at once under MAX_SESSIONS=1")
    started = time.monotonic()
    baseline = worker_processes(server.process.pid)  # no session yet
    spec = {"source": "synthetic", "preset": "test", "spec": "orbit?frames=400&width=64&height=48"}
    ids = []
    for _ in range(SLOT_SESSIONS):
        response = _send(lambda: server.client.post("/api/sessions", json=spec))
        result.statuses.append(getattr(response, "status_code", -1))
        if getattr(response, "status_code", 0) == 201:
            ids.append(response.json()["id"])
    while worker_processes(server.process.pid) == baseline and time.monotonic() - started < HANG_S:
        time.sleep(0.1)
    peak = [0]
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            peak[0] = max(peak[0], worker_processes(server.process.pid) - baseline)
            time.sleep(0.1)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    threads = [threading.Thread(target=lambda s=s: result.statuses.append(
        getattr(_send(lambda: server.client.delete(f"/api/sessions/{s}")), "status_code", -1))) for s in ids]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    deadline = time.monotonic() + 60
    while worker_processes(server.process.pid) > baseline and time.monotonic() < deadline:
        time.sleep(0.2)
    done.set()
    sampler.join()
    result.seconds = round(time.monotonic() - started, 2)
    result.server_errors = sum(s >= 500 for s in result.statuses) + (peak[0] > 1)
    result.peak_mb = round(server.memory_mb()[1], 1)
    result.note = f"at most {peak[0]} worker processes alive at once (target 1)"
    server.stop()
    return result


def sigterm_in_first_seconds(data_dir: Path) -> CaseResult:
    """Case 12: SIGTERM as soon as a session has reported its first frame: the server must be
    gone within 10 s with the session's trajectory.txt written and run.json's frames > 0."""
    server = Server(data_dir)
    result = CaseResult("16 SIGTERM in a session's first seconds")
    created = server.client.post("/api/sessions", json={"source": "synthetic", "preset": "test",
                                                        "spec": "orbit?frames=60&width=64&height=48"})
    session = created.json()["id"]
    deadline = time.monotonic() + 120
    while server.client.get(f"/api/sessions/{session}").json()["frames_done"] < 1 and time.monotonic() < deadline:
        time.sleep(0.05)
    started = time.monotonic()
    server.process.terminate()
    try:
        server.process.wait(timeout=HANG_S)
    except subprocess.TimeoutExpired:
        result.hangs += 1
    result.seconds = round(time.monotonic() - started, 2)
    server.stop()
    folder = data_dir / "sessions" / session
    trajectory = folder / "trajectory.txt"
    rows = sum(1 for line in trajectory.read_text().splitlines() if line and line[0] != "#") if trajectory.is_file() else 0
    try:
        frames = json.loads((folder / "run.json").read_text()).get("frames", 0)
    except (OSError, ValueError):
        frames = 0
    result.server_errors = int(rows == 0 or frames == 0 or result.seconds >= 10)
    result.note = (f"gone {result.seconds} s after SIGTERM; trajectory.txt {rows} rows, run.json frames {frames} "
                   f"(targets: < 10 s, > 0, > 0)")
    return result


def fuzz(server: Server, minutes: float) -> CaseResult:
    """schemathesis's CLI against the server for ``minutes``, with the token."""
    result = CaseResult(f"schemathesis {minutes:g} min")
    report = Path(tempfile.mkdtemp()) / "junit.xml"
    command = [str(Path(sys.executable).with_name("st")), "run", f"{server.url}/openapi.json",
               "-H", f"Authorization: Bearer {TOKEN}", "--max-time", str(int(minutes * 60)),
               "--checks", "not_a_server_error", "--request-timeout", str(HANG_S), "--report", "junit",
               "--report-junit-path", str(report), "--generation-deterministic"]
    started = time.monotonic()
    completed = subprocess.run(command, cwd=REPO, capture_output=True, text=True)
    result.seconds = round(time.monotonic() - started, 1)
    tail = completed.stdout.strip().splitlines()[-12:]
    result.note = " | ".join(tail)
    result.statuses.append(completed.returncode)
    result.server_errors = int("not_a_server_error" in completed.stdout and completed.returncode != 0)
    result.peak_mb = round(server.memory_mb()[1], 1)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fuzz-minutes", type=float, default=0.0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench-abuse-"))
    server = Server(work / "data")
    results = []
    try:
        print(f"server up: {server.memory_mb()[0]:.0f} MiB resident", flush=True)
        for name, requests in cases().items():
            result = run_case(server, name, requests)
            results.append(result)
            print(f"{name}: {result.seconds} s, statuses {sorted(set(result.statuses))}, 5xx {result.server_errors}, "
                  f"hangs {result.hangs}, peak {result.peak_mb} MiB {result.note}", flush=True)
        if args.fuzz_minutes > 0:
            results.append(fuzz(server, args.fuzz_minutes))
            print(f"fuzz: {results[-1]}", flush=True)
    finally:
        server.stop()
    results.append(slow_body_then_sigterm(work / "data2"))
    print(f"{results[-1].name}: {results[-1].note}, hangs {results[-1].hangs}", flush=True)
    for case, data in ((cancel_queued_under_one_slot, "data3"), (sigterm_in_first_seconds, "data4")):
        results.append(case(work / data))
        print(f"{results[-1].name}: {results[-1].note}, 5xx/failed {results[-1].server_errors}", flush=True)
    leaks = token_leaks(Path(server.log.name))
    accepted = sum(foreign_accepted(r) for r in results if r.name == ORIGIN_CASE)
    print(f"token in the server's log: {leaks} times (target 0); foreign-origin WebSockets accepted: {accepted} "
          f"(target 0)", flush=True)
    errors = sum(r.server_errors for r in results)
    hangs = sum(r.hangs for r in results)
    peak = max(r.peak_mb for r in results)
    verdict = errors == 0 and hangs == 0 and peak < 1024 and leaks == 0 and accepted == 0
    print(f"\nserver errors {errors}, hangs {hangs}, peak API memory {peak:.0f} MiB: "
          f"{'PASS' if verdict else 'FAIL'} (0, 0, < 1024)")
    if args.out:
        args.out.write_text(json.dumps([asdict(r) for r in results], indent=1))
    return 0 if verdict else 1


if __name__ == "__main__":
    sys.exit(main())
