"""What a fresh ``voxfusion render`` / ``ar`` process pays for besides its view: the modules
building the command line imports, the thread count its views take, and the help's note."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from slam.cli import FIRST_CALL_NOTE, build_parser, idle_cores, main, threads_for_views, view_threads

ROOT = Path(__file__).resolve().parents[1]

PROBE = """
import json, sys
import server.cli
parser = server.cli.build_parser()
after_parser = {m: m in sys.modules for m in ("trimesh", "slam.eval", "numba", "scipy.spatial")}
from ar.objects import load_objects_json
load_objects_json([{"shape": "cube"}, {"shape": "axes"}])
print(json.dumps({"parser": after_parser, "cube": "trimesh" in sys.modules}))
"""


@pytest.fixture(scope="module")
def probe() -> dict:
    """Which heavy modules a fresh process has imported after building the command line, and
    after reading a cube and axes object spec."""
    done = subprocess.run([sys.executable, "-c", PROBE], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_building_the_command_line_imports_no_mesh_or_kernel_code(probe):
    assert probe["parser"] == {"trimesh": False, "slam.eval": False, "numba": False, "scipy.spatial": False}


def test_a_cube_and_axes_need_no_trimesh(probe):
    assert probe["cube"] is False


@pytest.mark.parametrize("extents", [(1.0, 1.0, 1.0), (0.04, 1.0, 0.04), (0.3, 0.2, 0.1)])
def test_the_box_is_trimeshs(extents):
    import trimesh

    from ar.objects import _box

    vertices, faces = _box(extents)
    box = trimesh.creation.box(extents=extents)
    assert np.array_equal(vertices, box.vertices) and np.array_equal(faces, box.faces)


@pytest.mark.parametrize(("cores", "load", "threads"), [(2, 0.0, 2), (2, 0.4, 2), (2, 0.6, 1), (2, 9.0, 1),
                                                         (16, 4.2, 12), (4, -1.0, 4)])
def test_idle_cores(cores, load, threads):
    assert idle_cores(cores, load) == threads


def test_threads_given_are_taken_and_restored():
    before = torch.get_num_threads()
    assert view_threads(3) == 3
    with threads_for_views(1) as threads:
        assert threads == 1 and torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    assert 1 <= view_threads() <= max(before, 1)


@pytest.mark.parametrize("value", ["0", "-2", "two"])
def test_a_bad_thread_count_exits_2(value, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["render", "map.pt", "--pose", "1", "--intrinsics", "1,1,1,1,2,2", "--out", "x.png", "--threads", value])
    assert exit_info.value.code == 2
    assert "--threads" in capsys.readouterr().err


def test_the_render_help_says_what_a_fresh_process_costs(capsys):
    with pytest.raises(SystemExit):
        main(["render", "--help"])
    assert "numba kernels" in " ".join(capsys.readouterr().out.split())
    assert "torch" in FIRST_CALL_NOTE


def test_the_ar_help_says_it_too(capsys):
    from server.cli import main as voxfusion

    with pytest.raises(SystemExit):
        voxfusion(["ar", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "numba kernels" in out and "--threads" in out


def test_eval_commands_get_their_arguments_when_chosen(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["eval-ate", "--help"])
    assert exit_info.value.code == 0
    assert "--no-align" in capsys.readouterr().out
    args = build_parser().parse_args(["eval-mesh", "a.ply", "b.ply", "--threshold", "0.05"])
    assert args.handler.__name__ == "cmd_eval_mesh" and args.threshold == 0.05
