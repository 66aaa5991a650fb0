"""Crash safety (issue 39): what a session has computed survives a SIGKILL of the server.

    python benchmarks/bench_crash.py [--runs 10] [--preset test] [--spec 'orbit?frames=150&width=160&height=120']
                                     [--kill-min-s 2] [--kill-max-s 35] [--seed 0] [--json bench_crash.json]
                                     [--quick]   (2 runs of 60 frames, killed 2-8 s in: a smoke run)

Each run starts ``voxfusion serve`` (``python -m server.cli serve``) on 127.0.0.1 with a fresh
data folder, starts one synthetic session, polls its status every 0.1 s, and SIGKILLs the
server (``kill -9`` of the API process; its worker and mapping process end themselves) at a
random moment between ``--kill-min-s`` and ``--kill-max-s`` after the first tracked frame.
Then it reads the session folder and restarts the server on it. Per run it reports

* ``reported``: the frames (and keyframes) the server's status said were tracked at the last
  poll before the kill;
* ``on disk``: the poses in ``trajectory.txt`` and the keyframes of the ``run.json`` the run
  left, with ``last kf``, the frame index of the newest keyframe written;
* ``lost``: reported frames that are not on disk, and ``after kf``: the frames the server had
  reported after the newest keyframe on disk (at most these may be lost);
* ``map kf``: the keyframes in ``map.pt`` (written every 10 keyframes), or ``-`` without one;
* ``restart``: whether the restarted server's status agrees with the folder (``failed``,
  ``interrupted: ...``, ``frames_done`` = poses on disk, ``run.json``'s status and frames).

The verdict holds when in every run every keyframe the server had counted is on disk, the lost
frames all come after the newest keyframe on disk, and the restarted status agrees.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.common import machine_state, markdown_table, write_json  # noqa: E402


def free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def serve(data_dir: Path, log: Path) -> tuple[subprocess.Popen, str]:
    port = free_port()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    with open(log, "ab") as out:
        process = subprocess.Popen([sys.executable, "-m", "server.cli", "serve", "--host", "127.0.0.1",
                                    "--port", str(port), "--data-dir", str(data_dir), "--viewer-port", "-1"],
                                   cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while True:
        try:
            httpx.get(f"{url}/api/sessions", timeout=5).raise_for_status()
            return process, url
        except httpx.HTTPError:
            if process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the server did not come up; see {log}") from None
            time.sleep(0.3)


def tum_rows(path: Path) -> int:
    try:
        return sum(1 for line in path.read_text().splitlines() if line.strip() and not line.startswith("#"))
    except OSError:
        return 0


def map_keyframes(path: Path) -> int | None:
    if not path.is_file():
        return None
    from slam.checkpoint import load_checkpoint

    return load_checkpoint(path).num_keyframes()


def one_run(k: int, args, rng: random.Random, root: Path) -> dict:
    data = root / f"run{k}"
    data.mkdir()
    log = data / "server.log"
    server, url = serve(data, log)
    kill_after = rng.uniform(args.kill_min_s, args.kill_max_s)
    reported = {"frames_done": 0, "keyframes": 0, "status": "queued"}
    try:
        with httpx.Client(base_url=url, timeout=30) as client:
            created = client.post("/api/sessions", json={"source": "synthetic", "spec": args.spec,
                                                         "preset": args.preset})
            created.raise_for_status()
            session_id = created.json()["id"]
            tracking_since = None
            deadline = time.monotonic() + 300
            while time.monotonic() < deadline:
                state = client.get(f"/api/sessions/{session_id}").json()
                reported = state
                if state["status"] in ("finished", "failed", "cancelled"):
                    break
                if tracking_since is None and state["frames_done"] >= 1:
                    tracking_since = time.monotonic()
                if tracking_since is not None and time.monotonic() - tracking_since >= kill_after:
                    break
                time.sleep(0.1)
        server.send_signal(signal.SIGKILL)
        server.wait(timeout=30)
        killed_at = None if tracking_since is None else time.monotonic() - tracking_since
    finally:
        if server.poll() is None:
            server.kill()
            server.wait(timeout=30)
    time.sleep(1.0)  # the worker and its mapping process notice their server is gone
    folder = data / "sessions" / session_id
    run = json.loads((folder / "run.json").read_text()) if (folder / "run.json").is_file() else {}
    on_disk = tum_rows(folder / "trajectory.txt")
    disk_keyframes = int(run.get("keyframes") or 0)
    last_kf = (run.get("last_keyframe") or {}).get("frame")
    map_kf = map_keyframes(folder / "map.pt")
    again, url = serve(data, log)
    try:
        after = httpx.get(f"{url}/api/sessions/{session_id}", timeout=30).json()
    finally:
        again.terminate()
        again.wait(timeout=60)
    settled = json.loads((folder / "run.json").read_text()) if (folder / "run.json").is_file() else {}
    frames = int(reported["frames_done"])
    lost = max(0, frames - on_disk)
    after_kf = max(0, frames - (last_kf + 1)) if last_kf is not None else frames
    consistent = (after["status"] == "failed" and str(after["error"]).startswith("interrupted:")
                  and after["frames_done"] == on_disk and settled.get("frames") == on_disk
                  and settled.get("status") == "failed" and after["outputs"]["trajectory"] == (on_disk > 0)
                  and after["outputs"]["map"] == (folder / "map.pt").is_file())
    ok = (reported["status"] == "running" and disk_keyframes >= int(reported["keyframes"])
          and lost <= after_kf and consistent)
    return {"run": k, "kill_after_s": round(killed_at or 0.0, 1), "reported_frames": frames,
            "reported_keyframes": int(reported["keyframes"]), "status_at_kill": reported["status"],
            "frames_on_disk": on_disk, "keyframes_on_disk": disk_keyframes, "last_keyframe": last_kf,
            "lost": lost, "after_last_keyframe": after_kf, "map_keyframes": map_kf,
            "restart_consistent": consistent, "ok": ok}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--preset", default="test")
    parser.add_argument("--spec", default="orbit?frames=150&width=160&height=120")
    parser.add_argument("--kill-min-s", type=float, default=2.0)
    parser.add_argument("--kill-max-s", type=float, default=35.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", "--out", dest="out", type=Path, default=None)
    parser.add_argument("--quick", action="store_true", help="2 runs of 60 frames, killed 2-8 s in")
    args = parser.parse_args()
    if args.quick:
        args.runs, args.spec, args.kill_min_s, args.kill_max_s = 2, "orbit?frames=60&width=160&height=120", 2.0, 8.0
    rng = random.Random(args.seed)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-crash-") as tmp:
        for k in range(args.runs):
            row = one_run(k, args, rng, Path(tmp))
            rows.append(row)
            print(f"run {k}: {row}", flush=True)
    headers = ["run", "kill at (s)", "reported frames / kf", "on disk frames / kf", "last kf",
               "lost", "after kf", "map.pt kf", "restart agrees"]
    print()
    print(markdown_table(headers, [[
        str(r["run"]), f"{r['kill_after_s']:.1f}", f"{r['reported_frames']} / {r['reported_keyframes']}",
        f"{r['frames_on_disk']} / {r['keyframes_on_disk']}", str(r["last_keyframe"]), str(r["lost"]),
        str(r["after_last_keyframe"]), "-" if r["map_keyframes"] is None else str(r["map_keyframes"]),
        "yes" if r["restart_consistent"] else "NO"] for r in rows]))
    bad = [r["run"] for r in rows if not r["ok"]]
    lost = [r["lost"] for r in rows]
    print()
    if bad:
        print(f"verdict: FAIL in runs {bad} (a keyframe the server counted is not on disk, frames before the "
              f"newest keyframe were lost, the session was not running at the kill, or the restart disagrees)")
    else:
        print(f"verdict: PASS: in all {len(rows)} runs only frames after the newest keyframe on disk were lost "
              f"(lost {min(lost)}-{max(lost)} frames, mean {sum(lost) / len(lost):.1f}); every keyframe the server "
              f"had counted was on disk; the restarted status agreed with the folder")
    write_json(args.out, {"title": "bench_crash", "args": {k: str(v) for k, v in vars(args).items()},
                          "machine": machine_state(), "runs": rows})
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
