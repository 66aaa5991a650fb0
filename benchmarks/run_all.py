"""Run every core benchmark one after the other and write one markdown report.

    python benchmarks/run_all.py [--quick] [--only mapping,iteration,slam,loops] [--out FILE]

Each script runs in its own process with ``--json``; the report holds a summary of every
figure against its target, then each script's own output (its tables), with the time it took
and the load average around it: the machine is shared, and timings move with the load.
Default output: ``benchmarks/results/report.md`` (``report-quick.md`` with ``--quick``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO_ROOT, Figure, figures_table, load_line, machine_state

SCRIPTS = {
    "mapping": "benchmarks/bench_mapping.py",
    "iteration": "benchmarks/bench_iteration.py",
    "slam": "benchmarks/bench_slam.py",
    "loops": "benchmarks/bench_loops.py",
}


def run_script(name: str, quick: bool, json_dir: Path) -> dict:
    json_path = json_dir / f"{name}.json"
    args = [sys.executable, SCRIPTS[name], "--json", str(json_path)] + (["--quick"] if quick else [])
    load_before = load_line()
    started = time.perf_counter()
    proc = subprocess.run(args, cwd=REPO_ROOT, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - started
    payload = json.loads(json_path.read_text()) if json_path.is_file() else None
    print(f"{name}: {seconds:.0f} s, exit code {proc.returncode}; {load_line()}", flush=True)
    return {"name": name, "seconds": seconds, "returncode": proc.returncode, "stdout": proc.stdout,
            "stderr_tail": "\n".join(proc.stderr.strip().splitlines()[-15:]), "payload": payload,
            "load_before": load_before, "load_after": load_line()}


def report(results: list[dict], quick: bool) -> str:
    state = machine_state()
    figures = [Figure(**f) for r in results if r["payload"] for f in r["payload"]["figures"]]
    parts = [
        f"# voxfusion core benchmarks{' (quick smoke run: figures are not meaningful)' if quick else ''}",
        "",
        (f"Run {state['time']}, commit {state['commit']}, {state['cpus']} CPUs, torch {state['torch']}. "
         "The machine is shared with other work: the load average is given next to every timing."),
        "",
        "## Figures against targets",
        "",
        figures_table(figures),
    ]
    for r in results:
        parts += ["", f"## {SCRIPTS[r['name']]}", "",
                  (f"{r['seconds']:.0f} s, exit code {r['returncode']}; before: {r['load_before']}; "
                   f"after: {r['load_after']}"), "", r["stdout"].strip()]
        if r["returncode"] != 0:
            parts += ["", "```", r["stderr_tail"], "```"]
    return "\n".join(parts) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run of every script")
    parser.add_argument("--only", default=",".join(SCRIPTS), help=f"comma list of {list(SCRIPTS)}")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    names = args.only.split(",")
    unknown = set(names) - set(SCRIPTS)
    if unknown:
        parser.error(f"unknown benchmarks {sorted(unknown)}; choose from {list(SCRIPTS)}")
    out = args.out or REPO_ROOT / "benchmarks" / "results" / ("report-quick.md" if args.quick else "report.md")
    with tempfile.TemporaryDirectory() as tmp:
        results = [run_script(name, args.quick, Path(tmp)) for name in names]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(report(results, args.quick))
    print(f"report: {out}")
    return max(r["returncode"] for r in results)


if __name__ == "__main__":
    sys.exit(main())
