"""Server figures: API latency while a session runs, viewer update rate, concurrent sessions.

    python benchmarks/bench_server.py [--preset cpu] [--frames 150] [--max-sessions 4] [--out bench_server.json]

Starts ``voxfusion serve`` (``python -m server.cli serve``) in a subprocess on free ports, so
that the measuring client does not share a process with the server, then

1. runs one synthetic session and, while it runs, times ``GET /api/sessions/{id}`` and
   ``POST /api/sessions/{id}/render`` (160x120, at the session's latest tracked pose) and
   reports p50 / p95;
2. connects a WebSocket client to the viewer (``/viewer``, like a browser) and counts the
   messages and bytes it receives per second during the run: the viewer update rate;
3. runs k = 1, 2, ... sessions at once (``max_sessions = k``) and reports each one's frames/s,
   and the first k at which the mean frames/s falls below half of k = 1.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """``voxfusion serve`` in a subprocess."""

    def __init__(self, data_dir: Path, max_sessions: int) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
        self.process = subprocess.Popen(
            [sys.executable, "-m", "server.cli", "serve", "--port", str(self.port), "--data-dir", str(data_dir),
             "--viewer-port", "0", "--max-sessions", str(max_sessions)],
            cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.client = httpx.Client(base_url=self.url, timeout=600)
        deadline = time.monotonic() + 120
        while True:
            try:
                self.client.get("/api/sessions").raise_for_status()
                return
            except httpx.TransportError:
                if time.monotonic() > deadline or self.process.poll() is not None:
                    raise RuntimeError("the server did not start") from None
                time.sleep(0.5)

    def stop(self) -> None:
        self.process.terminate()
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()

    def start_synthetic(self, spec: str, preset: str) -> str:
        response = self.client.post("/api/sessions", json={"source": "synthetic", "spec": spec, "preset": preset})
        response.raise_for_status()
        return response.json()["id"]

    def status(self, session_id: str) -> dict:
        return self.client.get(f"/api/sessions/{session_id}").json()

    def wait(self, session_id: str, statuses=("finished", "failed", "cancelled"), timeout=1800.0) -> dict:
        deadline = time.monotonic() + timeout
        while (state := self.status(session_id))["status"] not in statuses:
            if time.monotonic() > deadline:
                raise RuntimeError(f"session {session_id} still {state['status']}")
            time.sleep(0.5)
        return state


def percentiles(samples_s: list[float]) -> dict:
    ms = np.array(samples_s) * 1000.0
    return {"n": len(ms), "p50_ms": round(float(np.percentile(ms, 50)), 2),
            "p95_ms": round(float(np.percentile(ms, 95)), 2), "max_ms": round(float(ms.max()), 2)}


def latest_pose_camera(server: Server, session_id: str) -> dict | None:
    from slam.eval.trajectory import parse_tum

    response = server.client.get(f"/api/sessions/{session_id}/trajectory")
    if response.status_code != 200:
        return None
    trajectory = parse_tum(response.text)
    if len(trajectory) == 0:
        return None
    return {"T_world_cam": trajectory.poses[-1].tolist(),
            "intrinsics": {"fx": 125.0, "fy": 125.0, "cx": 80.0, "cy": 60.0, "width": 160, "height": 120}}


class ViewerListener:
    """A WebSocket client of the viewer, counting what a browser would receive."""

    def __init__(self, url: str) -> None:
        self.url = url.replace("http://", "ws://") + "/viewer"
        self.times: list[float] = []
        self.bytes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._listen()), daemon=True)
        self._thread.start()

    async def _listen(self) -> None:
        import viser
        import websockets

        async with websockets.connect(self.url, subprotocols=[f"viser-v{viser.__version__}"], max_size=None) as ws:
            while not self._stop.is_set():
                try:
                    message = await asyncio.wait_for(ws.recv(), timeout=0.5)
                except asyncio.TimeoutError:
                    continue
                self.times.append(time.monotonic())
                self.bytes += len(message)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def rate(self, start: float, end: float) -> dict:
        inside = [t for t in self.times if start <= t <= end]
        seconds = max(end - start, 1e-6)
        return {"messages_per_s": round(len(inside) / seconds, 2), "kib_per_s": round(self.bytes / 1024 / seconds, 1),
                "seconds": round(seconds, 1)}


def latency_run(args, data_dir: Path) -> dict:
    server = Server(data_dir / "latency", max_sessions=1)
    try:
        listener = ViewerListener(server.url)
        spec = f"orbit?frames={args.frames}&width=320&height=240"
        session_id = server.start_synthetic(spec, args.preset)
        server.wait(session_id, statuses=("running",))
        started = time.monotonic()
        status_times, render_times = [], []
        render_statuses: dict[int, int] = {}
        while server.status(session_id)["status"] == "running":
            t0 = time.perf_counter()
            server.status(session_id)
            status_times.append(time.perf_counter() - t0)
            camera = latest_pose_camera(server, session_id) if len(status_times) % 10 == 0 else None
            if camera is not None:
                t0 = time.perf_counter()
                response = server.client.post(f"/api/sessions/{session_id}/render", json=camera)
                elapsed = time.perf_counter() - t0
                render_statuses[response.status_code] = render_statuses.get(response.status_code, 0) + 1
                if response.status_code == 200:
                    render_times.append(elapsed)
            time.sleep(0.1)
        ended = time.monotonic()
        final = server.wait(session_id)
        time.sleep(1.0)
        listener.stop()
        return {
            "session": {k: final[k] for k in ("status", "frames_done", "fps", "keyframes", "maps", "loops", "preset")},
            "status_latency_while_running": percentiles(status_times),
            "render_latency_while_running_160x120": percentiles(render_times) if render_times else None,
            "render_answers": render_statuses,
            "viewer_updates_during_run": listener.rate(started, ended),
        }
    finally:
        server.stop()


def concurrency_run(args, data_dir: Path) -> dict:
    results = {}
    baseline = None
    halved_at = None
    for k in range(1, args.max_sessions + 1):
        server = Server(data_dir / f"concurrent_{k}", max_sessions=k)
        try:
            spec = f"orbit?frames={args.concurrency_frames}&width=320&height=240"
            ids = [server.start_synthetic(spec, args.preset) for _ in range(k)]
            states = [server.wait(i) for i in ids]
        finally:
            server.stop()
        fps = [s["fps"] for s in states]
        mean = statistics.mean(fps)
        baseline = baseline or mean
        results[k] = {"fps_each": fps, "fps_mean": round(mean, 3), "fps_total": round(sum(fps), 3),
                      "statuses": [s["status"] for s in states]}
        print(f"  {k} session(s) at once: {mean:.2f} frames/s each, {sum(fps):.2f} in total", flush=True)
        if halved_at is None and mean < 0.5 * baseline:
            halved_at = k
            break
    return {"per_k": results, "frames_per_s_halves_at_k": halved_at}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="cpu", choices=("test", "cpu", "paper"))
    parser.add_argument("--frames", type=int, default=150, help="frames of the latency run")
    parser.add_argument("--concurrency-frames", type=int, default=60, help="frames per session of the concurrency run")
    parser.add_argument("--max-sessions", type=int, default=4)
    parser.add_argument("--skip-concurrency", action="store_true")
    parser.add_argument("--out", type=Path, default=None, help="write the figures as JSON here")
    args = parser.parse_args(argv)

    report = {"machine": {"cpus": os.cpu_count()}, "preset": args.preset}
    with tempfile.TemporaryDirectory(prefix="voxfusion-bench-") as tmp:
        print("latency and viewer rate while one session runs ...", flush=True)
        report["latency"] = latency_run(args, Path(tmp))
        print(json.dumps(report["latency"], indent=1), flush=True)
        if not args.skip_concurrency:
            print("concurrent sessions ...", flush=True)
            report["concurrency"] = concurrency_run(args, Path(tmp))
    text = json.dumps(report, indent=1)
    print(text)
    if args.out:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
