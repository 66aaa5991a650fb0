"""Imports point inward: ``slam`` never imports server, ar, fastapi, viser or uvicorn; ``client``
(the stream client) never imports the server, the web stack or the viewer."""

from __future__ import annotations

import ast
import subprocess
import sys
from dataclasses import dataclass
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


def test_the_slam_face_exports_its_names_on_first_use():
    code = (
        "import importlib, sys, slam\n"
        "assert 'torch' not in sys.modules, 'import slam loaded torch'\n"
        "loaded = sorted(n for n in sys.modules if n.startswith('slam.'))\n"
        "assert not loaded, loaded\n"
        "for name in slam.__all__:\n"
        "    assert getattr(slam, name) is getattr(importlib.import_module(slam._MODULE_OF[name]), name), name\n"
        "assert set(slam.__all__) <= set(dir(slam))\n"
        "try:\n"
        "    slam.no_such_name\n"
        "except AttributeError:\n"
        "    pass\n"
        "else:\n"
        "    raise AssertionError('an unknown name must be an AttributeError')\n"
        "from slam import kernels  # a submodule still imports by name\n"
        "print('ok', len(slam.__all__))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("ok ")


def test_the_slam_face_lists_for_type_checkers_what_it_exports():
    import slam

    tree = ast.parse((SLAM / "__init__.py").read_text())
    block = next(node for node in tree.body if _is_type_checking_block(node))
    typed = {alias.name: node.module for node in block.body if isinstance(node, ast.ImportFrom)
             for alias in node.names}
    assert typed == slam._MODULE_OF


def test_no_slam_module_imports_the_slam_face():
    # The face's names are imported on first use, which the circle finder cannot see: inside
    # the package, modules import each other, never ``from slam import name``.
    modules = project_modules(packages=("slam",))
    offences = [f"{e.importer}:{e.line}" for name, path in modules.items() if name != "slam"
                for e in import_edges(name, path.read_text(), path.name == "__init__.py", modules)
                if e.imported == "slam"]
    assert not offences, offences


# ------------------------------------------------------------------------------------------
# Import circles among the product's modules (issue 42): none, but for lazy factory imports
# listed here, each with a comment on its line saying why it is lazy.

PRODUCT = ("slam", "ar", "server", "client")

LAZY_CYCLE_EDGES: dict[tuple[str, str], str] = {}
"""(importer, imported) -> why: lazy imports (inside a function) allowed to close a circle.
Only a factory that imports an optional implementation on first use belongs here. Empty:
``server.executors.make_executor`` imports ``server.ray_executor`` lazily, but that closes no
circle since the executors' shared types live in ``server.execution``."""


@dataclass(frozen=True)
class ImportEdge:
    importer: str
    imported: str
    line: int
    lazy: bool
    """Inside a function: runs on the first call, not when ``importer`` is imported."""


def project_modules(root: Path = ROOT, packages: tuple[str, ...] = PRODUCT) -> dict[str, Path]:
    """Dotted module name -> file, for every module of ``packages`` (a package is its __init__)."""
    modules = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join(parts)] = path
    return modules


def _is_type_checking_block(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and ast.unparse(node.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING")


def import_edges(name: str, source: str, is_package: bool, modules: set[str] | dict) -> list[ImportEdge]:
    """Every import of module ``name`` that names a module of ``modules``: the deepest module a
    dotted name reaches (``from a.b import c`` is ``a.b.c`` when that is a module, else
    ``a.b``), relative imports resolved. Imports under ``if TYPE_CHECKING:`` never run and are
    left out. The packages Python imports on the way (``a`` for ``a.b``) are not edges: each
    package is a module of its own here, with its own imports."""
    package = name.split(".") if is_package else name.split(".")[:-1]

    def resolve(dotted: str) -> str | None:
        while dotted and dotted not in modules:
            dotted = dotted.rpartition(".")[0]
        return dotted or None

    edges: list[ImportEdge] = []

    def visit(node: ast.AST, lazy: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if _is_type_checking_block(child):
                continue
            targets: list[str | None] = []
            if isinstance(child, ast.Import):
                targets = [resolve(alias.name) for alias in child.names]
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = ".".join(package[: len(package) - child.level + 1] + ([child.module] if child.module else []))
                else:
                    base = child.module or ""
                targets = [resolve(f"{base}.{alias.name}") if f"{base}.{alias.name}" in modules else resolve(base)
                           for alias in child.names]
            for target in dict.fromkeys(targets):
                if target is not None and target != name:
                    edges.append(ImportEdge(name, target, child.lineno, lazy))
            visit(child, lazy or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    visit(ast.parse(source), False)
    return edges


def import_cycles(edges: list[ImportEdge], allowed: set[tuple[str, str]] = frozenset()) -> list[list[str]]:
    """The circles (strongly connected components of more than one module) of the import
    graph without the ``allowed`` lazy edges, each sorted, in sorted order."""
    graph: dict[str, set[str]] = {}
    for edge in edges:
        if not (edge.lazy and (edge.importer, edge.imported) in allowed):
            graph.setdefault(edge.importer, set()).add(edge.imported)
            graph.setdefault(edge.imported, set())
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def connect(v: str) -> None:  # Tarjan
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return sorted(cycles)


def product_import_edges() -> list[ImportEdge]:
    modules = project_modules()
    return [edge for name, path in modules.items()
            for edge in import_edges(name, path.read_text(), path.name == "__init__.py", modules)]


def test_the_cycle_finder_sees_circles_top_level_and_lazy():
    sources = {
        "p": (True, "from . import a\n"),
        "p.a": (False, "from .b import f\nif TYPE_CHECKING:\n    from p.c import C\n"),
        "p.b": (False, "import os\ndef f():\n    from p import a  # lazy\n"),
        "p.c": (False, "from p.a import x\nclass K:\n    from . import b\n"),
        "p.d": (False, "import p.c.nothing\nfrom p import c\n"),
    }
    edges = [edge for name, (is_package, source) in sources.items()
             for edge in import_edges(name, source, is_package, set(sources))]
    found = {(e.importer, e.imported, e.lazy) for e in edges}
    assert found == {("p", "p.a", False), ("p.a", "p.b", False), ("p.b", "p.a", True), ("p.c", "p.a", False),
                     ("p.c", "p.b", False), ("p.d", "p.c", False)}
    # a -> b -(lazy)-> a is a circle; a's TYPE_CHECKING import of c is none.
    assert import_cycles(edges) == [["p.a", "p.b"]]
    assert import_cycles(edges, {("p.b", "p.a")}) == []
    # An allowed pair that is a top-level import still counts.
    assert import_cycles(edges, {("p.a", "p.b")}) == [["p.a", "p.b"]]


def test_no_import_circles_in_the_product():
    edges = product_import_edges()
    assert {e.importer.split(".")[0] for e in edges} == set(PRODUCT), "the walk must see every package"
    assert len({e.importer for e in edges}) > 70
    cycles = import_cycles(edges, set(LAZY_CYCLE_EDGES))
    report = []
    for cycle in cycles:
        members = set(cycle)
        report.append(" <-> ".join(cycle) + ":")
        report += [f"    {e.importer} -> {e.imported} (line {e.line}{', lazy' if e.lazy else ''})"
                   for e in edges if e.importer in members and e.imported in members]
    assert not cycles, "import circles (move the shared part below both, or list a lazy factory " \
                       "import in LAZY_CYCLE_EDGES with a comment on its line):\n" + "\n".join(report)


def test_each_allowed_lazy_import_exists_is_lazy_and_says_why():
    modules = project_modules()
    edges = product_import_edges()
    for (importer, imported), why in LAZY_CYCLE_EDGES.items():
        assert why.strip(), (importer, imported)
        lines = modules[importer].read_text().splitlines()
        found = [e for e in edges if (e.importer, e.imported) == (importer, imported)]
        assert found, f"{importer} no longer imports {imported}: drop it from LAZY_CYCLE_EDGES"
        for edge in found:
            assert edge.lazy, f"{importer}:{edge.line} imports {imported} at the top level"
            assert "#" in lines[edge.line - 1], f"{importer}:{edge.line}: say on the line why it is lazy"
