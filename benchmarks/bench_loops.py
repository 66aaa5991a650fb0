"""Multi-maps and loop closure (issue 17 figures): loops against ``--no-loops`` on the same data.

Scenarios (each a pair or set of ``slam.runtime.run_slam`` runs with the ``cpu`` preset,
tracking and mapping in separate processes; synthetic frames are rendered once into a frame
cache so that the ray caster is not timed):

- ``laps``: the synthetic hall, two laps around its central block (repeated identical
  furniture, plain walls), noisy depth, low resolution: ATE with loops / without; false
  loops (accepted loops whose frames GT puts > 1 m or 30 deg apart); the loop detector's
  precision and recall over keyframes; time per frame over the first and last 100 frames.
- ``loss``: the same path with a stretch of blank frames (a forced tracking loss): maps
  started, whether the floating map joined, ATE against the run without the loss.
- ``agents``: two agents in the synthetic room with unknown relative start poses: ATE of
  both trajectories with one alignment, against agent 0 alone; mesh accuracy merged / alone.
- ``real``: TUM fr1/rpy (150 frames) and fr1/desk: ATE and frames/s with loops / without.

    python benchmarks/bench_loops.py [--scenarios laps,loss,agents,real] [--frames N] [--quick]
                                     [--preset P] [--config F] [--width W] [--json FILE] [--out DIR]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (  # noqa: E402
    SHARED_DATA,
    TUM_RPY,
    Figure,
    cache_sequence,
    figures_payload,
    figures_table,
    load_line,
    mesh_in_gt_frame,
    write_json,
)

SCENARIOS = ("laps", "loss", "agents", "real")
TUM_DESK = SHARED_DATA / "rgbd_dataset_freiburg1_desk"
CACHE = Path("/tmp/voxfusion-bench-cache")


def laps_spec(frames: int, width: int, extra: str = "") -> str:
    height = width * 3 // 4
    return f"synthetic:laps?frames={frames}&width={width}&height={height}&noise=1{extra}"


def cached(spec: str):
    """The sequence of ``spec`` rendered once into a frame cache."""
    from slam.data import open_sequence

    key = hashlib.sha1(spec.encode()).hexdigest()[:12]
    return cache_sequence(open_sequence(spec), CACHE / key)


PRESET = "cpu"
OVERRIDES: dict = {}


def config_for(loops: bool, overrides: dict | None = None):
    from slam.config import config_from_dict, load_config

    config = load_config(PRESET)
    overrides = {**OVERRIDES, **(overrides or {})}
    if overrides:
        merged = config.to_dict()
        for section, fields in overrides.items():
            merged[section].update(fields)
        config = config_from_dict(merged)
    if not loops:
        config = replace(config, loop=replace(config.loop, enabled=False))
    return config


def run(sources, config, out: Path) -> dict:
    """One run: run.json plus the wall-clock arrival time of every frame's pose."""
    from slam.events import PoseEvent
    from slam.runtime import run_slam

    arrivals: list[float] = []

    def on_event(event) -> None:
        if isinstance(event, PoseEvent):
            arrivals.append(time.perf_counter())

    load = load_line()
    t0 = time.perf_counter()
    result = run_slam(sources, config, out, on_event=on_event)
    info = json.loads((out / "run.json").read_text())
    info["_wall"] = time.perf_counter() - t0
    info["_arrivals"] = arrivals
    info["_load"] = load
    if result.status != "finished":
        raise SystemExit(f"run in {out} {result.status}: {result.error}")
    return info


def gt_poses(sequence) -> dict[int, np.ndarray]:
    return {f.index: f.T_world_cam for f in sequence}


def _angle(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def is_true_match(Ta: np.ndarray, Tb: np.ndarray, max_m: float = 1.0, max_deg: float = 30.0) -> bool:
    return (np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]) <= max_m
            and _angle(Ta[:3, :3].T @ Tb[:3, :3]) <= max_deg)


def loop_quality(info: dict, gts: list[dict[int, np.ndarray]], min_gap: int) -> dict:
    """False loops and the detector's keyframe-level precision / recall.

    A keyframe has a true loop opportunity when an earlier keyframe (another agent's, or the
    same agent's at least ``min_gap`` frames older) is within 1 m and 30 deg by GT; recall =
    keyframes with an accepted true loop / keyframes with an opportunity."""
    closures = info.get("loop_closures", [])
    false = [c for c in closures if not is_true_match(gts[c["agent"]][c["frame_index"]],
                                                       gts[c["match_agent"]][c["match_frame_index"]])]
    kfs = [(0, int(k)) for k in info.get("keyframe_poses", {})]
    for cand in info.get("loop_candidates", []):  # other agents' keyframes appear as candidates
        kfs += [(cand["agent"], cand["frame_index"]), (cand["match_agent"], cand["match_frame_index"])]
    kfs = sorted(set(kfs), key=lambda ak: (ak[1], ak[0]))
    opportunities = 0
    for i, (a, f) in enumerate(kfs):
        earlier = [(b, g) for b, g in kfs[:i] if b != a or f - g >= min_gap]
        if any(is_true_match(gts[a][f], gts[b][g]) for b, g in earlier):
            opportunities += 1
    detected = {(c["agent"], c["frame_index"]) for c in closures if c not in false}
    accepted = len(closures)
    # Verified loops the map-level kernel refused still join the keyframe graph: none may be false either.
    verified = [c for c in info.get("loop_candidates", []) if c.get("verified")]
    false_verified = [c for c in verified if not is_true_match(gts[c["agent"]][c["frame_index"]],
                                                                gts[c["match_agent"]][c["match_frame_index"]])]
    from slam.eval.loops import loop_pose_errors

    pose_errors = loop_pose_errors(verified, lambda agent, index: gts[agent].get(index))
    worst = max(pose_errors, key=lambda e: e.translation_m, default=None)
    return {"loop_pose_error_max_m": None if worst is None else worst.translation_m,
            "loop_pose_error_max_deg": None if worst is None else max(e.rotation_deg for e in pose_errors),
            "loops": accepted, "false_loops": len(false), "verified_loops": len(verified),
            "false_verified_loops": len(false_verified),
            "precision": (accepted - len(false)) / accepted if accepted else None,
            "recall": len(detected) / opportunities if opportunities else None,
            "opportunities": opportunities, "candidates_rejected": info.get("loop_candidates_rejected", 0)}


def frame_times(info: dict, skip: int = 10) -> tuple[float, float]:
    """Mean seconds per frame over frames [skip, skip + 100) and over the last 100."""
    t = np.diff(np.asarray(info["_arrivals"]))
    return float(t[skip:skip + 100].mean()), float(t[-100:].mean())


def ate_cm(path: Path, sequence) -> float:
    from slam.eval import ate, read_trajectory
    from slam.eval.trajectory import Trajectory

    gt = Trajectory(np.array([f.timestamp for f in sequence]), np.stack([f.T_world_cam for f in sequence]))
    return ate(gt, read_trajectory(path)).rmse * 100


# ---------------------------------------------------------------- scenarios
def scenario_laps(args, out: Path) -> dict:
    seq = cached(laps_spec(args.frames, args.width))
    gts = [gt_poses(seq)]
    rows = {}
    for loops in (True, False):
        info = run([seq], config_for(loops), out / f"laps_{'loops' if loops else 'noloops'}")
        first, last = frame_times(info)
        rows[loops] = {"ate_cm": info["ate_rmse_m"] * 100, "fps": info["fps"], "maps": info["maps"],
                       "first100_s": first, "last100_s": last, "load": info["_load"],
                       "loop_ms": info.get("loop_timings_ms", {}),
                       **loop_quality(info, gts, config_for(True).loop.min_frame_gap)}
    return {"frames": len(seq), "with_loops": rows[True], "no_loops": rows[False],
            "ate_ratio": rows[True]["ate_cm"] / rows[False]["ate_cm"]}


def scenario_loss(args, out: Path) -> dict:
    n = args.frames
    a, b = int(n * 0.55), int(n * 0.55) + max(20, n // 25)
    seq_loss = cached(laps_spec(n, args.width, f"&blank={a}-{b}"))
    seq = cached(laps_spec(n, args.width))
    info_loss = run([seq_loss], config_for(True), out / "loss_loops")
    info_ref = run([seq], config_for(True), out / "loss_reference")
    reasons = list(info_loss.get("map_reasons", {}).values())
    return {"blank_frames": [a, b], "maps": info_loss["maps"], "map_reasons": reasons,
            "tracking_failure_maps": reasons.count("tracking_failure"), "map_groups": info_loss["map_groups"],
            "loops": info_loss["loops"], "ate_cm": info_loss["ate_rmse_m"] * 100,
            "reference_ate_cm": info_ref["ate_rmse_m"] * 100,
            "ate_ratio": info_loss["ate_rmse_m"] / info_ref["ate_rmse_m"],
            "false_loops": loop_quality(info_loss, [gt_poses(seq_loss)], 30)["false_loops"]}


def _mesh_accuracy_cm(mesh_path: Path, spec: str, sequences) -> float:
    import trimesh

    from slam.data import open_sequence
    from slam.eval import CullCamera, mesh_metrics

    from slam.eval import Trajectory, read_trajectory

    frames = [f for s in sequences for f in s]
    cameras = [CullCamera(f.K, f.T_world_cam, f.width, f.height) for f in frames[::2]]
    first = list(sequences[0])
    truth = Trajectory(np.array([f.timestamp for f in first]), np.stack([f.T_world_cam for f in first]))
    estimate = read_trajectory(mesh_path.parent / "trajectory.txt")  # agent 0's, whose first camera is the world
    rec = mesh_in_gt_frame(trimesh.load(mesh_path, force="mesh", process=False), estimate, truth)
    m = mesh_metrics(rec, open_sequence(spec).gt_mesh(), num_points=100_000, cull_cameras=cameras,
                     gt_depths=[f.depth for f in frames[::2]])
    return m.accuracy * 100


def scenario_agents(args, out: Path) -> dict:
    from slam.eval import ate, read_trajectory
    from slam.eval.trajectory import Trajectory

    frames = args.agent_frames
    specs = [f"synthetic:agents?agent={k}&agents=2&frames={frames}&width={args.width}&height={args.width * 3 // 4}"
             f"&noise=1" for k in range(2)]
    seqs = [cached(s) for s in specs]
    joint = run(seqs, config_for(True), out / "agents_joint")
    alone = run([seqs[0]], config_for(True), out / "agents_alone")
    est = [read_trajectory(out / "agents_joint" / f"trajectory_{k}.txt") for k in range(2)]
    # One alignment for both: concatenate the agents (timestamps offset so they stay apart).
    offset = 1e4
    gt_all = Trajectory(np.concatenate([[f.timestamp + k * offset for f in s] for k, s in enumerate(seqs)]),
                        np.concatenate([np.stack([f.T_world_cam for f in s]) for s in seqs]))
    est_all = Trajectory(np.concatenate([e.timestamps + k * offset for k, e in enumerate(est)]),
                         np.concatenate([e.poses for e in est]))
    joint_ate = ate(gt_all, est_all).rmse * 100
    alone_ate = ate_cm(out / "agents_alone" / "trajectory.txt", seqs[0])
    return {"frames_per_agent": frames, "joined": [a["joined"] for a in joint["agents"]], "loops": joint["loops"],
            "joint_ate_cm": joint_ate, "agent0_alone_ate_cm": alone_ate, "ate_ratio": joint_ate / alone_ate,
            "false_loops": loop_quality(joint, [gt_poses(s) for s in seqs], 30)["false_loops"],
            "joint_accuracy_cm": _mesh_accuracy_cm(out / "agents_joint" / "mesh.ply", specs[0], seqs),
            "alone_accuracy_cm": _mesh_accuracy_cm(out / "agents_alone" / "mesh.ply", specs[0], seqs[:1])}


def scenario_real(args, out: Path) -> dict:
    from slam.data import open_sequence

    rows = {}
    for name, path, frames in (("fr1/rpy", TUM_RPY, args.real_frames), ("fr1/desk", TUM_DESK, None)):
        if not path.is_dir():
            rows[name] = {"missing": str(path)}
            continue
        seq = open_sequence(str(path), max_frames=frames)
        row = {}
        for loops in (True, False):
            info = run([seq], config_for(loops), out / f"real_{path.name}_{'loops' if loops else 'noloops'}")
            row["loops" if loops else "no_loops"] = {"ate_cm": info["ate_rmse_m"] * 100, "fps": info["fps"],
                                                     "maps": info["maps"], "loops": info["loops"],
                                                     "load": info["_load"]}
        row["fps_ratio"] = row["loops"]["fps"] / row["no_loops"]["fps"]
        rows[name] = row
    return rows


def target_figures(results: dict) -> list[Figure]:
    """Issue 17's figures from the scenarios that ran."""
    figs: list[Figure] = []
    laps = results.get("laps")
    if laps:
        on, off = laps["with_loops"], laps["no_loops"]
        figs += [Figure("laps: ATE with loops / --no-loops", laps["ate_ratio"], "", "<= 0.5"),
                 Figure("laps: ATE with loops", on["ate_cm"], "cm", "<= 5"),
                 Figure("laps: false loops", on["false_loops"], "", "<= 0"),
                 Figure("laps: false verified loops (keyframe graph)", on["false_verified_loops"], "", "<= 0"),
                 Figure("laps: s/frame, last 100 / first 100 (loops)", on["last100_s"] / on["first100_s"], "",
                        "<= 1.25"),
                 Figure("laps: loop precision", on["precision"], "", "report"),
                 Figure("laps: loop recall (keyframes)", on["recall"], "", "report")]
    loss = results.get("loss")
    if loss:
        figs += [Figure("loss: ATE / run without the loss", loss["ate_ratio"], "", "<= 2"),
                 Figure("loss: map groups at the end", loss["map_groups"], "", "<= 1"),
                 Figure("loss: false loops", loss["false_loops"], "", "<= 0")]
    agents = results.get("agents")
    if agents:
        figs += [Figure("agents: joint ATE / agent 0 alone", agents["ate_ratio"], "", "<= 2"),
                 Figure("agents: mesh accuracy joint - alone", agents["joint_accuracy_cm"] - agents["alone_accuracy_cm"],
                        "cm", "<= 1"),
                 Figure("agents: false loops", agents["false_loops"], "", "<= 0")]
    for name, row in (results.get("real") or {}).items():
        if not isinstance(row, dict):  # bench_seconds
            continue
        if "missing" in row:
            figs.append(Figure(f"{name}: frames/s loops / no loops", None, "", ">= 0.9", f"missing {row['missing']}"))
            continue
        figs += [Figure(f"{name}: frames/s loops / no loops", row["fps_ratio"], "", ">= 0.9"),
                 Figure(f"{name}: ATE loops - no loops", row["loops"]["ate_cm"] - row["no_loops"]["ate_cm"], "cm",
                        "report", "not worse: <= 0 within run-to-run noise")]
    return figs


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenarios", default=",".join(SCENARIOS))
    p.add_argument("--frames", type=int, default=780, help="frames of the laps path (780: its nominal speed)")
    p.add_argument("--agent-frames", type=int, default=100)
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--preset", default="cpu", choices=["test", "cpu", "paper"])
    p.add_argument("--config", type=Path, default=None, help="JSON overrides of the preset, for every run")
    p.add_argument("--real-frames", type=int, default=150, help="frames of TUM fr1/rpy")
    p.add_argument("--quick", action="store_true", help="test preset, short sequences: a smoke run")
    p.add_argument("--out", type=Path, default=Path("/tmp/voxfusion-bench-loops"))
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args()
    global PRESET, OVERRIDES
    PRESET = "test" if args.quick else args.preset
    if args.config is not None:
        OVERRIDES = json.loads(args.config.read_text())
    if args.quick:
        args.frames, args.agent_frames, args.real_frames = 200, 40, 20
    chosen = [s for s in args.scenarios.split(",") if s]
    unknown = set(chosen) - set(SCENARIOS)
    if unknown:
        p.error(f"unknown scenarios {sorted(unknown)}; valid: {', '.join(SCENARIOS)}")
    results = {}
    for name in chosen:
        t0 = time.perf_counter()
        results[name] = globals()[f"scenario_{name}"](args, args.out)
        results[name]["bench_seconds"] = time.perf_counter() - t0
        print(f"## {name}\n{json.dumps(results[name], indent=2, default=float)}", flush=True)
    figures = target_figures(results)
    print(figures_table(figures))
    write_json(args.json, figures_payload("Multi-maps and loop closure (issue 17)", figures,
                                          {"bench_loops": results, "quick": args.quick}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
