"""Imports point inward: ``slam`` never imports server, ar, fastapi, viser or uvicorn; ``client``
(the stream client) never imports the server, the web stack or the viewer."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SLAM = ROOT / "slam"
CLIENT = ROOT / "client"
FORBIDDEN = {"server", "ar", "fastapi", "viser", "uvicorn"}
FORBIDDEN_IN_CLIENT = {"server", "ar", "fastapi", "starlette", "viser", "uvicorn"}


def imported_top_level_names(source: str, package: list[str]) -> list[tuple[int, str]]:
    """(line, top-level module) of every import in ``source``, a module of ``package`` (e.g.
    ["slam", "data"]); relative imports are resolved, so ``from .. import x`` that leaves
    ``slam`` shows up as the module it names."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name.split(".")[0]) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                found.append((node.lineno, (node.module or "").split(".")[0]))
                continue
            base = package[: max(len(package) - (node.level - 1), 0)]
            target = base + (node.module.split(".") if node.module else [])
            if target:
                found.append((node.lineno, target[0]))
            else:  # "from ... import x" above the top level: x itself is a top-level module
                found += [(node.lineno, alias.name) for alias in node.names]
    return sorted(found)


def imports_of_file(path: Path) -> list[tuple[int, str]]:
    package = list(path.relative_to(ROOT).parent.parts)
    return imported_top_level_names(path.read_text(), package)


def test_the_checker_sees_every_kind_of_import():
    source = ("import os\nimport fastapi.routing\nfrom viser import ViserServer\n"
              "def f():\n    import uvicorn\nfrom . import geometry\nfrom .. import server\n"
              "from ..ar.compose import x\n")
    names = [name for _, name in imported_top_level_names(source, ["slam", "data"])]
    assert names == ["os", "fastapi", "viser", "uvicorn", "slam", "slam", "slam"]
    names = [name for _, name in imported_top_level_names(source, ["slam"])]
    assert names[-2:] == ["server", "ar"]


def test_no_slam_module_imports_the_outer_layers():
    files = sorted(SLAM.rglob("*.py"))
    assert len(files) > 20, "the walk must see the whole package"
    offences = [f"{f.relative_to(SLAM.parent)}:{line} imports {name}"
                for f in files for line, name in imports_of_file(f) if name in FORBIDDEN]
    assert not offences, "\n".join(offences)


def test_the_client_imports_no_server_web_or_viewer_module():
    files = sorted(CLIENT.rglob("*.py"))
    assert len(files) >= 4, "the walk must see the whole package"
    offences = [f"{f.relative_to(ROOT)}:{line} imports {name}"
                for f in files for line, name in imports_of_file(f) if name in FORBIDDEN_IN_CLIENT]
    assert not offences, "\n".join(offences)


def test_importing_slam_loads_no_web_or_viewer_package():
    code = (
        "import importlib, pkgutil, sys, slam\n"
        "bad = {'fastapi', 'viser', 'uvicorn', 'server', 'ar'}\n"
        "assert not bad & set(sys.modules), sorted(bad & set(sys.modules))\n"
        "for m in pkgutil.walk_packages(slam.__path__, 'slam.'):\n"
        "    importlib.import_module(m.name)\n"
        "loaded = sorted(n for n in sys.modules if n.split('.')[0] in bad)\n"
        "assert not loaded, loaded\n"
        "print('ok', len([n for n in sys.modules if n.startswith('slam')]))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          cwd=SLAM.parent)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("ok ") and int(proc.stdout.split()[1]) > 20
