"""Ray executor figures (issue 19) on a two-node Ray cluster on this machine (127.0.0.1).

    python benchmarks/bench_ray.py [--frames 30] [--out benchmarks/results/bench_ray.json]

1. Spread and sameness: 4 synthetic sessions (seeds 0-3) submitted at once to the ``ray``
   executor (nodes of 2 CPUs, sessions of 2: one per node, the other two wait in Ray's queue),
   then the same 4 to the ``local`` executor (2 at a time); per session its node, status, ATE,
   and the largest distance between its Ray and local camera positions.
2. Overhead: one 60-frame synthetic session alone, ``ray`` against ``local``: seconds from
   ``POST /api/sessions`` to the first tracked pose in the status (polled every 20 ms), and
   to ``finished``.
3. A killed node: two sessions, one per node; the node of the first is removed mid-tracking;
   seconds until that session is ``failed``, its message, and the other's end.

The API runs in this process (a TestClient with its lifespan); the cluster in a child process
(``tests/ray_cluster.py``), so this process is a Ray driver as a deployed server is.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.ray_cluster import LocalRayCluster  # noqa: E402
from tests.test_server_api import running_app  # noqa: E402

ENDED = ("finished", "failed", "cancelled")
POLL_S = 0.02


def wait(client, session_id: str, until, timeout_s: float = 900.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        state = client.get(f"/api/sessions/{session_id}").json()
        if until(state):
            return state
        time.sleep(POLL_S)
    raise TimeoutError(f"session {session_id}: {state}")


def ended(state: dict) -> bool:
    return state["status"] in ENDED


def post(client, spec: str) -> str:
    response = client.post("/api/sessions", json={"source": "synthetic", "spec": spec, "preset": "test"})
    response.raise_for_status()
    return response.json()["id"]


def positions(client, session_id: str) -> dict[float, np.ndarray]:
    rows = [line.split() for line in client.get(f"/api/sessions/{session_id}/trajectory").text.splitlines()
            if line and not line.startswith("#")]
    return {round(float(r[0]), 6): np.array([float(v) for v in r[1:4]]) for r in rows}


def run_batch(client, specs: list[str]) -> list[dict]:
    ids = [post(client, spec) for spec in specs]
    states = [wait(client, i, ended) for i in ids]
    return [{"id": s["id"], "status": s["status"], "error": s["error"], "ate_rmse_m": s["ate_rmse_m"],
             "node": (s["worker"] or {}).get("node"), "positions": positions(client, s["id"])} for s in states]


def overhead(client, spec: str) -> dict:
    t0 = time.monotonic()
    session_id = post(client, spec)
    first = wait(client, session_id, lambda s: s["frames_done"] > 0 or ended(s))
    t_first = time.monotonic() - t0
    final = wait(client, session_id, ended)
    return {"first_pose_s": round(t_first, 2), "end_to_end_s": round(time.monotonic() - t0, 2),
            "status": final["status"], "frames": final["frames_done"], "first_status": first["status"]}


def killed_node(client, cluster: LocalRayCluster, frames: int) -> dict:
    doomed = post(client, "orbit?frames=400&width=80&height=60")
    other = post(client, f"orbit?frames={frames}&width=80&height=60&seed=7")
    victim = wait(client, doomed, lambda s: s["frames_done"] > 0 or ended(s))
    cluster.kill_node(victim["worker"]["node"])
    t0 = time.monotonic()
    failed = wait(client, doomed, ended, timeout_s=120)
    took = time.monotonic() - t0
    final = wait(client, other, ended)
    return {"fail_after_s": round(took, 1), "status": failed["status"], "error": failed["error"],
            "other_status": final["status"], "other_node": final["worker"]["node"]}


def trajectory_gap(a: dict[float, np.ndarray], b: dict[float, np.ndarray]) -> float | None:
    common = sorted(set(a) & set(b))
    if not common:
        return None
    return float(max(np.linalg.norm(a[t] - b[t]) for t in common))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30, help="frames of each of the 4 spread sessions")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "bench_ray.json")
    args = parser.parse_args()
    specs = [f"orbit?frames={args.frames}&width=80&height=60&seed={k}" for k in range(4)]
    long_spec = "orbit?frames=60&width=160&height=120"
    results: dict = {}
    root = Path(tempfile.mkdtemp(prefix="bench-ray-"))
    with running_app(root / "local", max_sessions=2) as client:
        results["local_overhead"] = overhead(client, long_spec)
        print("local overhead", results["local_overhead"], flush=True)
        local = run_batch(client, specs)
    t0 = time.monotonic()
    with LocalRayCluster(nodes=2, cpus=2) as cluster:
        results["cluster_start_s"] = round(time.monotonic() - t0, 1)
        with running_app(root / "ray", executor="ray", ray_address=cluster.info.address, ray_session_cpus=2,
                         max_sessions=8, ray_scratch=str(root / "scratch")) as client:
            results["ray_overhead_cold"] = overhead(client, long_spec)  # includes connecting, first actor
            print("ray overhead (cold)", results["ray_overhead_cold"], flush=True)
            results["ray_overhead"] = overhead(client, long_spec)
            print("ray overhead", results["ray_overhead"], flush=True)
            ray_runs = run_batch(client, specs)
            results["killed_node"] = killed_node(client, cluster, args.frames)
            print("killed node", results["killed_node"], flush=True)
    results["spread"] = [
        {"spec": spec, "ray_node": r["node"], "ray_status": r["status"], "local_status": lo["status"],
         "ray_ate_m": r["ate_rmse_m"], "local_ate_m": lo["ate_rmse_m"],
         "max_position_gap_m": trajectory_gap(r["positions"], lo["positions"])}
        for spec, r, lo in zip(specs, ray_runs, local)]
    results["nodes_used"] = len({r["node"] for r in ray_runs})
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1))
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
