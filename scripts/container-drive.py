"""Drive a voxfusion server in a container over HTTP (``scripts/container-build.sh``): the page,
a synthetic session to the end, a render of it. Standard library only (runs on the host's
python3). Every loop is bounded in time; exits 1 with the reason on the first failure.

    python3 scripts/container-drive.py --port 8000 [--label TEXT] [--ray] [--token TOKEN]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import urllib.error
import urllib.request

SPEC = "orbit?frames=20&width=80&height=60"
START_TIMEOUT_S = 300.0
SESSION_TIMEOUT_S = 600.0
HEADERS = {"Content-Type": "application/json"}


def call(base: str, path: str, body: dict | None = None, timeout: float = 30.0) -> tuple[int, bytes]:
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(base + path, data=data, headers=HEADERS)
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return response.status, response.read()
    except urllib.error.HTTPError as error:
        return error.code, error.read()


def wait_until_up(base: str) -> float:
    start = time.monotonic()
    while time.monotonic() - start < START_TIMEOUT_S:
        try:
            if call(base, "/openapi.json", timeout=5)[0] == 200:
                return time.monotonic() - start
        except OSError:
            pass
        time.sleep(1.0)
    raise SystemExit(f"FAIL: the server did not answer within {START_TIMEOUT_S:.0f} s")


def run_session(base: str) -> dict:
    status, body = call(base, "/api/sessions", {"source": "synthetic", "spec": SPEC, "preset": "test"})
    if status != 201:
        raise SystemExit(f"FAIL: POST /api/sessions -> {status} {body[:300]!r}")
    session_id = json.loads(body)["id"]
    start = time.monotonic()
    while time.monotonic() - start < SESSION_TIMEOUT_S:
        state = json.loads(call(base, f"/api/sessions/{session_id}")[1])
        if state["status"] in ("finished", "failed", "cancelled"):
            state["seconds"] = round(time.monotonic() - start, 1)
            return state
        time.sleep(1.0)
    raise SystemExit(f"FAIL: session {session_id} did not end within {SESSION_TIMEOUT_S:.0f} s")


def render(base: str, session_id: str) -> int:
    camera = {"T_world_cam": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
              "intrinsics": {"fx": 60, "fy": 60, "cx": 40, "cy": 30, "width": 80, "height": 60}}
    trajectory = call(base, f"/api/sessions/{session_id}/trajectory")[1].decode().splitlines()
    rows = [line.split() for line in trajectory if line and not line.startswith("#")]
    if rows:  # from the first tracked camera: the map is in front of it
        tx, ty, tz = (float(v) for v in rows[0][1:4])
        qx, qy, qz, qw = (float(v) for v in rows[0][4:8])
        camera["T_world_cam"] = _pose(tx, ty, tz, qx, qy, qz, qw)
    status, body = call(base, f"/api/sessions/{session_id}/render", camera, timeout=120)
    if status != 200 or not body.startswith(b"\x89PNG"):
        raise SystemExit(f"FAIL: render -> {status} {body[:300]!r}")
    return len(body)


def _pose(tx, ty, tz, qx, qy, qz, qw) -> list[list[float]]:
    return [[1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw), tx],
            [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw), ty],
            [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy), tz],
            [0.0, 0.0, 0.0, 1.0]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--label", default="container")
    parser.add_argument("--ray", action="store_true", help="expect the session to run on a Ray node")
    parser.add_argument("--token", default=None, help="the server's VOXFUSION_TOKEN, if it has one")
    args = parser.parse_args()
    if args.token:
        HEADERS["Authorization"] = f"Bearer {args.token}"
    base = f"http://127.0.0.1:{args.port}"
    up = wait_until_up(base)
    status, page = call(base, "/")
    if status != 200 or b"<html" not in page.lower():
        raise SystemExit(f"FAIL: GET / -> {status}")
    state = run_session(base)
    if state["status"] != "finished":
        raise SystemExit(f"FAIL: session {state['status']}: {state['error']}")
    worker = state.get("worker") or {}
    if args.ray and worker.get("executor") != "ray":
        raise SystemExit(f"FAIL: the session did not run on Ray: {worker}")
    png = render(base, state["id"])
    print(f"OK {args.label}: up in {up:.0f} s; page {len(page)} B; session {SPEC} finished in {state['seconds']} s "
          f"({state['frames_done']} frames, ATE {state['ate_rmse_m']} m, worker {worker}); render PNG {png} B",
          flush=True)


if __name__ == "__main__":
    sys.exit(main())
