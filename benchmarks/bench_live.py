"""A live camera, replayed: ``voxfusion stream --live`` of a real recording at its own rate.

    python benchmarks/bench_live.py [--sequences rpy150,rpy_full] [--modes live,all] [--runs 1]
                                    [--preset cpu] [--json FILE]

Starts ``voxfusion serve`` on 127.0.0.1 (a free port) and, per sequence and mode, runs
``voxfusion stream FOLDER --live`` (the recording replayed at its recorded timestamps, newer
frames replacing the ones the server has no room for, as a camera sends them) or
``--all-frames`` (every frame, at the server's pace: the all-frames reference), each waiting
for the session's result. From the client's summary and the session's status it reports:
frames of the recording, frames tracked, frames dropped (by the client or the server), the
share tracked, the first frame's sent-to-tracked time (the first pose), the median
sent-to-tracked time (to within the client's status poll, 0.25 s), the session's ATE and, for
live runs, its ratio to the all-frames run's ATE of the same sitting.

Targets (issue on speed, item 4): at least 90 % of the frames tracked, ATE at most 1.2x the
all-frames run, the first pose within 1 s, the median sent-to-tracked within 0.1 s.
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_server import REPO, Server  # noqa: E402
from common import TUM_RPY, load_line, markdown_table, write_json  # noqa: E402

CACHE = Path.home() / ".cache" / "voxfusion" / "data"
SEQUENCES = {"rpy150": (TUM_RPY, 150), "rpy_full": (CACHE / "rgbd_dataset_freiburg1_rpy_full", None)}
STREAM_TIMEOUT_S = 1800.0


@dataclass(frozen=True)
class LiveRun:
    sequence: str
    mode: str
    frames: int
    tracked: int
    dropped: int
    first_pose_s: float | None
    median_latency_s: float | None
    ate_cm: float | None
    output: str

    @property
    def tracked_share(self) -> float:
        return self.tracked / self.frames if self.frames else 0.0


def _number(pattern: str, text: str, default=None):
    match = re.search(pattern, text)
    return float(match.group(1)) if match else default


def stream_once(server: Server, folder: Path, max_frames: int | None, mode: str, preset: str) -> LiveRun:
    """One ``voxfusion stream`` of ``folder``, waited for; its figures."""
    command = [sys.executable, "-m", "server.cli", "stream", str(folder), "--url", server.url,
               "--live" if mode == "live" else "--all-frames", "--quiet", "--wait", str(STREAM_TIMEOUT_S),
               "--preset", preset]
    if max_frames:
        command += ["--max-frames", str(max_frames)]
    done = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=STREAM_TIMEOUT_S + 120)
    out = done.stdout + done.stderr
    if done.returncode != 0:
        raise RuntimeError(f"voxfusion stream exited {done.returncode}:\n{out[-2000:]}")
    session = re.search(r"session (\S+) from", out).group(1)
    state = server.status(session)
    dropped = int(_number(r"dropped (\d+) \(", out, 0))
    ate = state.get("ate_rmse_m")
    first = _number(r"first frame tracked (\d+) ms", out)
    median = _number(r"sent to tracked: median (\d+) ms", out)
    return LiveRun(
        sequence=folder.name, mode=mode, frames=int(_number(r"frames sent (\d+)", out, 0)) + dropped,
        tracked=int(state.get("frames_done") or 0), dropped=dropped,
        first_pose_s=None if first is None else first / 1000,
        median_latency_s=None if median is None else median / 1000,
        ate_cm=None if ate is None else 100 * float(ate), output=out[-1500:])


def table(runs: list[LiveRun]) -> str:
    reference: dict[str, float] = {}
    for r in runs:
        if r.mode == "all" and r.ate_cm is not None:
            reference.setdefault(r.sequence, statistics.mean(
                x.ate_cm for x in runs if x.sequence == r.sequence and x.mode == "all" and x.ate_cm is not None))
    rows = []
    for r in runs:
        ref = reference.get(r.sequence)
        ratio = f"{r.ate_cm / ref:.2f}x" if r.mode == "live" and ref and r.ate_cm is not None else "-"
        rows.append([r.sequence.removeprefix("rgbd_dataset_"), r.mode, str(r.frames), str(r.tracked), str(r.dropped),
                     f"{100 * r.tracked_share:.0f} %",
                     "-" if r.first_pose_s is None else f"{r.first_pose_s:.2f} s",
                     "-" if r.median_latency_s is None else f"{1000 * r.median_latency_s:.0f} ms",
                     "-" if r.ate_cm is None else f"{r.ate_cm:.2f}", ratio])
    return markdown_table(["sequence", "mode", "frames", "tracked", "dropped", "tracked share", "first pose",
                           "median sent-to-tracked", "ATE cm", "ATE / all frames"], rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", default="rpy150", help="comma-separated: " + ", ".join(SEQUENCES))
    parser.add_argument("--modes", default="live,all", help="live (a camera's pace), all (every frame)")
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--work", type=Path, default=None, help="keep the server's sessions here")
    args = parser.parse_args(argv)
    print(f"start: {load_line()}", flush=True)
    runs: list[LiveRun] = []
    with tempfile.TemporaryDirectory(prefix="bench-live-") as work:
        if args.work is not None:
            args.work.mkdir(parents=True, exist_ok=True)
        server = Server(args.work or Path(work), max_sessions=1)
        try:
            for run in range(args.runs):
                for name in args.sequences.split(","):
                    folder, max_frames = SEQUENCES[name]
                    if not folder.is_dir():
                        print(f"{name}: {folder} missing, skipped", flush=True)
                        continue
                    for mode in args.modes.split(","):
                        r = stream_once(server, folder, max_frames, mode, args.preset)
                        runs.append(r)
                        print(f"round {run} {name} {mode}: {r.tracked}/{r.frames} tracked, ATE {r.ate_cm} cm, "
                              f"first pose {r.first_pose_s} s, median latency {r.median_latency_s} s", flush=True)
        finally:
            server.stop()
    print(f"end: {load_line()}\n")
    print(table(runs))
    write_json(args.json, {"runs": [asdict(r) | {"tracked_share": r.tracked_share} for r in runs]})
    return 0


if __name__ == "__main__":
    sys.exit(main())
