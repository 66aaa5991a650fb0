"""Core command line: ``run``, ``eval-ate``, ``eval-mesh``, ``render``.

The installed ``voxfusion`` script is ``server.cli:main``, which adds ``serve``, ``demo`` and
``ar`` to this parser (imports point inward: ``slam`` never imports ``server``).

Each ``voxfusion`` command is a fresh process, so building the parser imports nothing heavy
(the eval subcommands add their arguments, and import trimesh, only when chosen:
``DeferredParser``), and the commands that render views pick their torch threads from the
machine's load (``view_threads``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path


class DeferredParser(argparse.ArgumentParser):
    """A subcommand's parser whose arguments ``fill`` adds on its first parse or help, so that
    building the command line imports only what the chosen subcommand needs (eval: trimesh)."""

    fill: Callable[[argparse.ArgumentParser], None] | None = None

    def _filled(self) -> None:
        fill, self.fill = self.fill, None
        if fill is not None:
            fill(self)

    def parse_known_args(self, args=None, namespace=None):
        self._filled()
        return super().parse_known_args(args, namespace)

    def format_usage(self) -> str:
        self._filled()
        return super().format_usage()

    def format_help(self) -> str:
        self._filled()
        return super().format_help()


def _eval_ate_arguments(p: argparse.ArgumentParser) -> None:
    from .eval.commands import add_eval_ate_arguments, cmd_eval_ate

    add_eval_ate_arguments(p)
    p.set_defaults(handler=cmd_eval_ate)


def _eval_mesh_arguments(p: argparse.ArgumentParser) -> None:
    from .eval.commands import add_eval_mesh_arguments, cmd_eval_mesh

    add_eval_mesh_arguments(p)
    p.set_defaults(handler=cmd_eval_mesh)


def _floats(text: str, n: tuple[int, ...], what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.replace(" ", "").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what} must be comma-separated numbers, got {text!r}") from None
    if len(values) not in n:
        raise argparse.ArgumentTypeError(f"{what} needs {' or '.join(map(str, n))} numbers, got {len(values)}")
    return values


def _intrinsics(text: str) -> tuple[float, ...]:
    return _floats(text, (4, 9), "--intrinsics (fx,fy,cx,cy[,k1,k2,p1,p2,k3])")


def _color_intrinsics(text: str) -> tuple[float, ...]:
    return _floats(text, (6, 10, 11), "--color-intrinsics (fx,fy,cx,cy,width,height[,k1,k2,p1,p2[,k3]])")


def _depth_to_color(text: str) -> tuple[float, ...]:
    return _floats(text, (12, 16), "--depth-to-color (4x4 or 3x4, row-major)")


def color_camera_of(args: argparse.Namespace):
    """The colour camera the arguments give (``--calibration``, or ``--color-intrinsics`` with
    ``--depth-to-color``), or None: colour and depth registered already."""
    from .data.frame import DataError
    from .data.registration import color_camera_from_values, read_color_calibration

    if args.calibration is not None:
        if args.color_intrinsics is not None or args.depth_to_color is not None:
            raise DataError("give either --calibration or --color-intrinsics/--depth-to-color, not both")
        return read_color_calibration(args.calibration)
    if args.color_intrinsics is None:
        if args.depth_to_color is not None:
            raise DataError("--depth-to-color needs --color-intrinsics (the colour camera's own intrinsics)")
        return None
    return color_camera_from_values(args.color_intrinsics, args.depth_to_color)


def add_color_camera_arguments(p: argparse.ArgumentParser) -> None:
    """``--color-intrinsics``, ``--depth-to-color`` and ``--calibration`` (``color_camera_of``
    reads them): ``voxfusion run``'s and ``voxfusion stream``'s."""
    p.add_argument("--color-intrinsics", type=_color_intrinsics, default=None,
                   metavar="fx,fy,cx,cy,width,height[,k1,k2,p1,p2[,k3]]",
                   help="colour from its own camera: its intrinsics; colour is registered onto the depth camera")
    p.add_argument("--depth-to-color", type=_depth_to_color, default=None, metavar="16 numbers",
                   help="with --color-intrinsics: the depth camera's frame in the colour camera's, 4x4 row-major "
                        "(default: identity)")
    p.add_argument("--calibration", type=Path, default=None,
                   help='JSON with "color_intrinsics" and "T_color_depth" (instead of the two options above)')


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("paths", nargs="+", metavar="PATH",
                   help="dataset folder(s), or a synthetic spec such as synthetic:orbit?frames=100")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument("--format", default="auto", choices=["auto", "tum", "replica", "scannet", "7scenes", "synthetic"])
    p.add_argument("--preset", default=None, choices=["test", "cpu", "paper", "gpu"],
                   help="default: gpu with CUDA, cpu otherwise")
    p.add_argument("--config", type=Path, default=None, help="JSON overrides of the preset")
    p.add_argument("--device", default=None, choices=["auto", "cpu", "cuda"])
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--stride", type=int, default=1)
    p.add_argument("--intrinsics", type=_intrinsics, default=None, metavar="fx,fy,cx,cy")
    p.add_argument("--depth-scale", type=float, default=None)
    add_color_camera_arguments(p)
    p.add_argument("--gt-poses", action="store_true", help="map with the dataset's poses (no tracking)")
    p.add_argument("--no-loops", action="store_true", help="multi-maps without loop closure")
    p.add_argument("--single-process", action="store_true", help="tracking and mapping in one process")
    p.add_argument("--deterministic", type=int, nargs="?", const=1, default=None, metavar="LAG",
                   help="track every frame against exactly the map of all frames but the newest LAG (default 1), "
                        "so the trajectory does not depend on machine load (runtime.deterministic_lag)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def cmd_run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from .config import ConfigError, default_preset_name, load_config
    from .data import DataError, open_sequence
    from .runtime import run_slam

    try:
        config = load_config(args.preset or default_preset_name(), args.config)
        runtime = config.runtime
        if args.device:
            runtime = replace(runtime, device=args.device)
        if args.single_process:
            runtime = replace(runtime, processes=False)
        if args.deterministic is not None:
            runtime = replace(runtime, deterministic_lag=args.deterministic)
        config = replace(config, runtime=runtime)
        if args.no_loops:
            config = replace(config, loop=replace(config.loop, enabled=False))
        color_camera = color_camera_of(args)
        sources = []
        for k, path in enumerate(args.paths):
            try:
                sources.append(open_sequence(path, args.format, stride=args.stride, max_frames=args.max_frames,
                                             intrinsics=args.intrinsics, depth_scale=args.depth_scale,
                                             color_camera=color_camera))
            except (DataError, ValueError) as exc:
                # Every PATH is opened before anything starts, and a bad one is named.
                where = f"PATH {k + 1} ({path})" if len(args.paths) > 1 else str(path)
                raise DataError(exc if str(path) in str(exc) and len(args.paths) == 1 else f"{where}: {exc}") from exc
    except (ConfigError, DataError, ValueError) as exc:
        print(f"voxfusion run: {exc}", file=sys.stderr)
        return 2
    result = run_slam(sources, config, args.out, use_gt_poses=args.gt_poses, progress=not args.quiet)
    counts = ", ".join(_count(n, word) for n, word in ((result.frames, "frame"), (result.keyframes, "keyframe"),
                                                        (result.maps, "map"), (result.loops, "loop")))
    line = f"{result.status}: {counts}, {result.fps:.2f} frames/s"
    if result.ate_rmse is not None:
        line += f", ATE RMSE {result.ate_rmse * 100:.2f} cm (refined poses)"
    print(line + f" -> {result.out_dir}")
    if result.agents > 1:
        print(_agents_summary(result.out_dir / "run.json"))
    if result.error:
        print(result.error, file=sys.stderr)
    return {"finished": 0, "cancelled": 130}.get(result.status, 1)


def _count(n: int, word: str) -> str:
    """``1 map``, ``2 maps``."""
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def _agents_summary(run_json: Path) -> str:
    """One line per agent: frames, ATE, and whether its maps joined agent 0's world."""
    import json

    try:
        agents = json.loads(run_json.read_text()).get("agents", [])
    except (OSError, ValueError):
        return ""
    lines = []
    for a in agents:
        ate = "" if a.get("ate_rmse_m") is None else f", ATE RMSE {a['ate_rmse_m'] * 100:.2f} cm"
        joined = "joined the world" if a.get("joined") else "never met the others: its own frame"
        lines.append(f"  agent {a['agent']}: {a['frames']} frames -> {a['trajectory']}{ate}; {joined}")
    return "\n".join(lines)


FIRST_CALL_NOTE = ("A fresh process pays for importing torch and for loading the numba kernels from their disk "
                   "cache (seconds on a slow or busy machine; compiling them instead, after an upgrade or "
                   "without 'make setup', takes a minute once).")
"""What a view from a fresh process costs besides the render itself (the render commands' help)."""


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def add_threads_argument(p: argparse.ArgumentParser) -> None:
    """``--threads`` of the commands that render views (render, render-path, ar)."""
    p.add_argument("--threads", type=_positive_int, default=None, metavar="N",
                   help="torch threads (default: the cores the 1-minute load average leaves idle, at least 1; "
                        "on a busy machine a thread that waits for a core stalls every operation it shares)")


def idle_cores(cores: int, load: float) -> int:
    """The cores a 1-minute load average of ``load`` leaves idle, rounded, at least 1."""
    return max(1, min(cores, round(cores - load)))


def view_threads(requested: int | None = None) -> int:
    """torch threads for a command's views: ``requested``, else ``idle_cores`` of this process's
    cores. OpenMP's threads spin while they wait, so on a loaded machine a second thread that
    has no core of its own makes each of the render's many small operations wait for it."""
    if requested is not None:
        return requested
    import torch

    try:
        cores = len(os.sched_getaffinity(0))
        load = os.getloadavg()[0]
    except (AttributeError, OSError):  # neither exists everywhere; without them keep torch's choice
        return torch.get_num_threads()
    return idle_cores(min(cores, torch.get_num_threads()), load)


@contextmanager
def threads_for_views(requested: int | None = None) -> Iterator[int]:
    """torch's thread count at ``view_threads(requested)`` inside, restored after (``main`` is
    also called in-process, by tests and scripts)."""
    import torch

    before = torch.get_num_threads()
    threads = view_threads(requested)
    torch.set_num_threads(threads)
    try:
        yield threads
    finally:
        torch.set_num_threads(before)


def add_render_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("checkpoint", type=Path, help="map.pt of a run")
    p.add_argument("--pose", required=True,
                   help="4x4 T_world_cam: 16 numbers (row-major, commas or spaces) or a JSON 4x4 list, given "
                        "here or in a file named here")
    p.add_argument("--intrinsics", required=True, metavar="fx,fy,cx,cy,width,height",
                   type=lambda s: _floats(s, (6,), "--intrinsics"))
    p.add_argument("--out", required=True, type=Path, help="colour PNG")
    p.add_argument("--depth", type=Path, default=None, help="16-bit depth PNG in millimetres")
    add_threads_argument(p)


def cmd_render(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np

    from .checkpoint import CheckpointError, load_checkpoint
    from .geometry import parse_pose
    from .views import render_view

    try:
        maps = load_checkpoint(args.checkpoint)
        T = parse_pose(args.pose)
    except (CheckpointError, ValueError, OSError) as exc:
        print(f"voxfusion render: {exc}", file=sys.stderr)
        return 2
    fx, fy, cx, cy, w, h = args.intrinsics
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    with threads_for_views(args.threads):
        view = render_view(maps, T, K, int(w), int(h))
    cv2.imwrite(str(args.out), cv2.cvtColor((view.rgb * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))
    if args.depth:
        cv2.imwrite(str(args.depth), np.clip(view.depth * 1000, 0, 65535).round().astype(np.uint16))
    print(f"wrote {args.out}" + (f" and {args.depth}" if args.depth else ""))
    return 0


def add_render_path_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", type=Path, help="a run's output folder (map.pt, trajectory.txt)")
    p.add_argument("--out", required=True, type=Path, help="MP4 file")
    p.add_argument("--keyframes", default=None,
                   help="JSON file: a list of 4x4 T_world_cam the path passes through (default: --every-th pose "
                        "of the run's trajectory, a fly-through of the run)")
    p.add_argument("--every", type=int, default=30, help="without --keyframes: every N-th tracked pose (default 30)")
    p.add_argument("--duration", type=float, default=None, help="seconds (default: 1 s per keyframe gap)")
    p.add_argument("--fps", type=float, default=24.0)
    p.add_argument("--loop", action="store_true", help="return to the first keyframe")
    p.add_argument("--intrinsics", default="262.5,262.5,160,120,320,240", metavar="fx,fy,cx,cy,width,height",
                   type=lambda s: _floats(s, (6,), "--intrinsics"), help="each panel's camera (default 320x240, "
                                                                         "a Kinect's field of view)")
    p.add_argument("--outputs", default="color,depth,normals", help="panels side by side: color, depth, normals")
    add_threads_argument(p)


def cmd_render_path(args: argparse.Namespace) -> int:
    import json

    import numpy as np
    from tqdm import tqdm

    from .camera_path import CameraPath
    from .checkpoint import CheckpointError, load_checkpoint
    from .eval.trajectory import read_tum
    from .path_video import path_frames, write_mp4

    try:
        maps = load_checkpoint(args.run_dir / "map.pt")
        if args.keyframes:
            keyframes = np.array(json.loads(Path(args.keyframes).read_text()), dtype=np.float64)
        else:
            poses = read_tum(args.run_dir / "trajectory.txt").poses
            keyframes = poses[:: max(args.every, 1)]
            if len(poses) > 1 and (len(poses) - 1) % max(args.every, 1):
                keyframes = np.concatenate([keyframes, poses[-1:]])
        gaps = len(keyframes) - (0 if args.loop else 1)
        path = CameraPath(keyframes, args.duration or float(max(gaps, 1)), args.fps, args.loop)
        outputs = tuple(o.strip() for o in args.outputs.split(",") if o.strip())
        fx, fy, cx, cy, w, h = args.intrinsics
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
        bar = tqdm(total=path.frame_count, unit="frame")
        frames = path_frames(maps, path, K, int(w), int(h), outputs, on_frame=lambda done, total: bar.update(1))
        with threads_for_views(args.threads):
            write_mp4(frames, args.out, args.fps)
        bar.close()
    except (CheckpointError, ValueError, OSError) as exc:
        print(f"voxfusion render-path: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}: {path.frame_count} frames through {len(keyframes)} keyframes, "
          f"{' | '.join(outputs)}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="voxfusion", description="Vox-Fusion++ neural implicit RGB-D SLAM")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=DeferredParser)
    p = sub.add_parser("run", help="run SLAM on a dataset and write trajectory, mesh and map")
    add_run_arguments(p)
    p.set_defaults(handler=cmd_run)
    sub.add_parser("eval-ate", help="absolute trajectory error of TUM files").fill = _eval_ate_arguments
    sub.add_parser("eval-mesh", help="mesh accuracy / completion against a GT mesh").fill = _eval_mesh_arguments
    p = sub.add_parser("render", help="render a view of a saved map",
                       description=f"Render the colour (and depth) a camera sees of a saved map. {FIRST_CALL_NOTE}")
    add_render_arguments(p)
    p.set_defaults(handler=cmd_render)
    p = sub.add_parser("render-path", help="render a fly-through video (MP4) of a saved map along a camera path")
    add_render_path_arguments(p)
    p.set_defaults(handler=cmd_render_path)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.handler(args) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
