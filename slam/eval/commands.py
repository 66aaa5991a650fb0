"""``voxfusion eval-ate`` and ``voxfusion eval-mesh``: thin command-line handlers.

Each command has an ``add_*_arguments(parser)`` and a ``cmd_*(args) -> int``; ``slam/cli.py``
wires them into subcommands. Bad input (missing file, bad line, no pairs, empty mesh) prints
one clear message to stderr and returns exit code 2; results go to stdout in centimetres and,
with ``--json``, to a file in metres.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import trimesh

from slam.data.frame import DataError
from slam.eval.ate import ATEResult, ate
from slam.eval.mesh_metrics import CullCamera, MeshMetrics, mesh_metrics
from slam.eval.trajectory import read_trajectory, read_tum

EXIT_BAD_INPUT = 2


# ---------------------------------------------------------------- eval-ate


def add_eval_ate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("gt_traj", type=Path, help="ground-truth TUM trajectory (timestamp tx ty tz qx qy qz qw)")
    parser.add_argument("est_traj", type=Path, help="estimated TUM trajectory")
    parser.add_argument("--json", type=Path, default=None, metavar="OUT", help="also write the result as JSON (metres)")
    parser.add_argument("--no-align", action="store_true", help="compare in the given frames (no Umeyama alignment)")
    parser.add_argument(
        "--max-dt", type=_non_negative_float, default=0.02, help="largest timestamp difference to associate (s)"
    )


def cmd_eval_ate(args: argparse.Namespace) -> int:
    try:
        result = ate(read_tum(args.gt_traj), read_tum(args.est_traj), align=not args.no_align, max_dt=args.max_dt)
        _write_json(args.json, ate_summary(result, aligned=not args.no_align))
    except (DataError, OSError) as error:
        return _fail("eval-ate", error)
    print(format_ate_table(result, aligned=not args.no_align))
    return 0


def ate_summary(result: ATEResult, aligned: bool) -> dict:
    """JSON-ready dict of an ATEResult (metres; per-pair errors left out)."""
    summary = {key: value for key, value in asdict(result).items() if key not in ("errors", "T_gt_est")}
    summary["T_gt_est"] = result.T_gt_est.tolist()
    summary["aligned"] = aligned
    summary["units"] = "m"
    return summary


def format_ate_table(result: ATEResult, aligned: bool) -> str:
    title = f"ATE ({'rigid alignment' if aligned else 'no alignment'}, {result.num_pairs} pose pairs)"
    rows = [(name, getattr(result, name) * 100, "cm") for name in ("rmse", "mean", "median", "std", "min", "max")]
    return _table(title, rows)


# ---------------------------------------------------------------- eval-mesh


def add_eval_mesh_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("rec_mesh", type=Path, help="reconstructed mesh (PLY/OBJ/GLB)")
    parser.add_argument("gt_mesh", type=Path, help="ground-truth mesh, same world frame")
    parser.add_argument("--json", type=Path, default=None, metavar="OUT", help="also write the result as JSON (metres)")
    parser.add_argument("--num-points", type=_positive_int, default=200_000, help="points sampled on each mesh")
    parser.add_argument("--threshold", type=_positive_float, default=0.05, help="completion-ratio threshold (m)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the surface sampling")
    parser.add_argument(
        "--cull-traj", type=Path, default=None, metavar="TRAJ",
        help="cull both meshes to the frusta of these camera-to-world poses (TUM file or Replica traj.txt)",
    )
    parser.add_argument(
        "--cull-frames", type=_slice, default=slice(None), metavar="START:STOP[:STEP]",
        help="use only these rows of --cull-traj (python slice, e.g. 0:4)",
    )
    parser.add_argument("--intrinsics", type=_float_list(4), default=None, metavar="FX,FY,CX,CY")
    parser.add_argument("--size", type=_int_list(2), default=None, metavar="W,H", help="image size in pixels")


def cmd_eval_mesh(args: argparse.Namespace) -> int:
    try:
        cameras = _cull_cameras(args)
        metrics = mesh_metrics(
            load_mesh(args.rec_mesh), load_mesh(args.gt_mesh),
            num_points=args.num_points, threshold=args.threshold, cull_cameras=cameras, seed=args.seed,
        )
        _write_json(args.json, {**asdict(metrics), "culled": cameras is not None, "units": "m"})
    except (DataError, OSError) as error:
        return _fail("eval-mesh", error)
    print(format_mesh_table(metrics))
    return 0


def format_mesh_table(metrics: MeshMetrics) -> str:
    title = f"Mesh metrics ({metrics.num_points} points per mesh, threshold {metrics.threshold * 100:g} cm)"
    rows = [
        ("accuracy", metrics.accuracy * 100, "cm"),
        ("completion", metrics.completion * 100, "cm"),
        ("completion ratio", metrics.completion_ratio * 100, "%"),
        ("precision", metrics.precision * 100, "%"),
        ("recall", metrics.recall * 100, "%"),
        ("F-score", metrics.fscore * 100, "%"),
    ]
    return _table(title, rows)


def load_mesh(path: Path) -> trimesh.Trimesh:
    """Read a triangle mesh; DataError naming the file when it is missing, unreadable or has no faces."""
    if not Path(path).is_file():
        raise DataError(f"{path}: no such mesh file")
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as error:  # trimesh raises many types for corrupt files; keep the cause
        raise DataError(f"{path}: cannot read mesh: {error}") from error
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise DataError(f"{path}: holds no triangle faces")
    return mesh


def _cull_cameras(args: argparse.Namespace) -> list[CullCamera] | None:
    if args.cull_traj is None:
        if args.intrinsics is not None or args.size is not None:
            raise DataError("--intrinsics and --size only make sense with --cull-traj")
        return None
    if args.intrinsics is None or args.size is None:
        raise DataError("--cull-traj needs --intrinsics fx,fy,cx,cy and --size W,H")
    poses = read_trajectory(args.cull_traj).poses[args.cull_frames]
    if len(poses) == 0:
        raise DataError(f"{args.cull_traj}: --cull-frames selects no poses")
    fx, fy, cx, cy = args.intrinsics
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    width, height = args.size
    return [CullCamera(K, pose, width, height) for pose in poses]


# ---------------------------------------------------------------- shared helpers


def _table(title: str, rows: list[tuple[str, float, str]]) -> str:
    width = max(len(name) for name, _, _ in rows)
    return "\n".join([title] + [f"  {name:<{width}}  {value:10.4f} {unit}" for name, value, unit in rows])


def _write_json(path: Path | None, payload: dict) -> None:
    if path is not None:
        Path(path).write_text(json.dumps(payload, indent=2) + "\n")


def _fail(command: str, error: Exception) -> int:
    print(f"voxfusion {command}: error: {error}", file=sys.stderr)
    return EXIT_BAD_INPUT


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def _non_negative_float(text: str) -> float:
    value = float(text)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def _float_list(count: int):
    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(part) for part in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {count} comma-separated numbers, got {text!r}") from None
        if len(values) != count or not all(np.isfinite(values)):
            raise argparse.ArgumentTypeError(f"expected {count} comma-separated numbers, got {text!r}")
        return values

    return parse


def _int_list(count: int):
    def parse(text: str) -> tuple[int, ...]:
        try:
            values = tuple(int(part) for part in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {count} comma-separated integers, got {text!r}") from None
        if len(values) != count or min(values) < 1:
            raise argparse.ArgumentTypeError(f"expected {count} comma-separated positive integers, got {text!r}")
        return values

    return parse


def _slice(text: str) -> slice:
    parts = text.split(":")
    try:
        numbers = [int(part) if part.strip() else None for part in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START:STOP[:STEP], got {text!r}") from None
    if not 2 <= len(numbers) <= 3 or numbers[2:] == [0]:
        raise argparse.ArgumentTypeError(f"expected START:STOP[:STEP] with STEP != 0, got {text!r}")
    return slice(*numbers)
