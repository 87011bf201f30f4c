"""Structure checks anyone can repeat: the import graph, its layers, file sizes, what loads what.

The import graph is read from the source with :mod:`ast` (nothing is imported): every ``import`` and
``from ... import`` of ``colmap_pvs`` counts, at module level and inside functions alike. The
top-level ``cli/`` folder is installed as ``colmap_pvs.cli`` and is read as such. An import names the
deepest module it reaches: ``from .views import select_views`` imports ``colmap_pvs.views`` (its
``__init__``), ``from . import config as settings`` imports the submodule ``config``, and
``import colmap_pvs.io.files`` imports ``colmap_pvs.io.files`` only (not ``colmap_pvs.io``'s
``__init__``, which Python also runs: counting it would make every re-exporting package a cycle).
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]

#: The most lines a library file (colmap_pvs/**/*.py, cli/*.py) may have.
MAX_LINES = 700

#: Layers, lower first; a module may import modules of its own layer or of lower ones, never of a
#: higher one. A module belongs to the entry with the longest matching prefix (``colmap_pvs.io.files``
#: before ``colmap_pvs.io``); every module must belong to one.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    # the package root (``__version__``), errors, plain data types, the stdlib-only atomic file
    # writes every layer uses, the shipped weights
    ("base", ("colmap_pvs", "colmap_pvs.errors", "colmap_pvs.types", "colmap_pvs.io.files",
              "colmap_pvs.weights")),
    ("config", ("colmap_pvs.config",)),
    # COLMAP's files (pycolmap) and the numpy core that works on maps
    ("io and numeric core", ("colmap_pvs.io", "colmap_pvs.geometry", "colmap_pvs.upsampling",
                             "colmap_pvs.normals", "colmap_pvs.consistency", "colmap_pvs.prior")),
    ("model", ("colmap_pvs.model",)),
    # completion fits the model's dense prior (colmap_pvs.model.cost) to the kept pixels
    ("completion, views, mesh, evaluation", ("colmap_pvs.completion", "colmap_pvs.views",
                                             "colmap_pvs.mesh", "colmap_pvs.evaluate")),
    ("synthetic data", ("colmap_pvs.synthetic",)),
    ("training", ("colmap_pvs.train",)),
    ("test-time adaptation", ("colmap_pvs.adapt",)),
    ("stereo", ("colmap_pvs.stereo",)),
    ("fusion", ("colmap_pvs.fusion",)),
    ("pipelines", ("colmap_pvs.reconstruct", "colmap_pvs.demo", "colmap_pvs.average_weights")),
    ("cli", ("colmap_pvs.cli",)),
]

#: The only module of ``colmap_pvs.io`` that ``colmap_pvs.model`` may import (stdlib only: atomic
#: writes of checkpoints); the model never reads COLMAP's files, images or maps.
MODEL_IO_ALLOWED = {"colmap_pvs.io.files"}

#: The modules of ``colmap_pvs.stereo`` that may import ``colmap_pvs.adapt`` (which trains), and only
#: inside a function, so that inference without test-time adaptation never loads the training code.
STEREO_ADAPT_HOOKS = {"colmap_pvs.stereo.adaptation"}


@dataclass(frozen=True)
class Import:
    target: str  # a module of LIBRARY_FILES
    lazy: bool  # inside a function
    line: int


def _library_files() -> dict[str, Path]:
    """Module name -> file, for colmap_pvs/**/*.py and cli/*.py (as ``colmap_pvs.cli``)."""
    files: dict[str, Path] = {}
    for base, package in ((REPO_ROOT / "colmap_pvs", "colmap_pvs"), (REPO_ROOT / "cli", "colmap_pvs.cli")):
        for path in sorted(base.rglob("*.py")):
            rel = path.relative_to(base)
            if package == "colmap_pvs" and rel.parts[0] == "cli":  # a link to ../cli in some checkouts
                continue
            parts = list(rel.with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            files[".".join([package, *parts])] = path
    return files


LIBRARY_FILES = _library_files()


def _known(name: str) -> str:
    """The deepest library module that ``name`` (a dotted name) is in, or ""."""
    while name and name not in LIBRARY_FILES:
        name = name.rpartition(".")[0]
    return name


def _imports(module: str) -> list[Import]:
    path = LIBRARY_FILES[module]
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: list[Import] = []

    def visit(node: ast.AST, lazy: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = lazy or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
            targets: list[str] = []
            if isinstance(child, ast.Import):
                targets = [_known(a.name) for a in child.names if a.name.split(".")[0] == "colmap_pvs"]
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package.rsplit(".", child.level - 1)[0] if child.level > 1 else package
                    base = f"{base}.{child.module}" if child.module else base
                else:
                    base = child.module or ""
                if base.split(".")[0] == "colmap_pvs":
                    for alias in child.names:  # `from . import config as settings`: the submodule
                        sub = f"{base}.{alias.name}"
                        targets.append(sub if sub in LIBRARY_FILES else _known(base))
            for target in targets:
                if target and target != module:
                    found.append(Import(target, lazy, child.lineno))
            visit(child, inner)

    visit(tree, False)
    return found


@cache
def _graph() -> dict[str, list[Import]]:
    return {module: _imports(module) for module in LIBRARY_FILES}


def _layer(module: str) -> int:
    best, index = "", -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > len(best):
                best, index = prefix, i
    return index


def _strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components (iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, edges = work[-1]
            for nxt in edges:
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph[nxt]))))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    components.append(sorted(component))
    return components


# --------------------------------------------------------------------------- the checker itself


def test_the_graph_reader_resolves_relative_and_lazy_imports():
    graph = _graph()
    assert len(graph) > 50 and "colmap_pvs.cli.main" in graph and "colmap_pvs.stereo" in graph
    targets = {i.target for i in graph["colmap_pvs.views.selection"]}
    assert {"colmap_pvs.views.config", "colmap_pvs.views.scores", "colmap_pvs.types"} <= targets
    lazy = {i.target for i in graph["colmap_pvs.adapt"] if i.lazy}
    assert "colmap_pvs.train" in lazy and "colmap_pvs.train.real_dataset" in lazy


def test_strongly_connected_components_find_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert sorted(map(tuple, _strongly_connected(graph))) == [("a", "b", "c"), ("d",), ("e",)]


# --------------------------------------------------------------------------- the checks


def test_no_import_cycle():
    graph = {m: {i.target for i in imports} for m, imports in _graph().items()}
    cycles = [c for c in _strongly_connected(graph) if len(c) > 1]
    assert not cycles, f"import cycles: {cycles}"


def test_every_module_has_a_layer():
    assert [m for m in LIBRARY_FILES if _layer(m) < 0] == [], "add the module to LAYERS"


def test_no_import_from_a_lower_layer_to_a_higher_one():
    upward = [
        f"{m} ({LAYERS[_layer(m)][0]}) imports {i.target} ({LAYERS[_layer(i.target)][0]}), line {i.line}"
        for m, imports in _graph().items()
        for i in imports
        if _layer(i.target) > _layer(m)
    ]
    assert not upward, "\n".join(upward)


def test_the_model_never_imports_io():
    found = [
        f"{m} imports {i.target}, line {i.line}"
        for m, imports in _graph().items()
        if m == "colmap_pvs.model" or m.startswith("colmap_pvs.model.")
        for i in imports
        if i.target.startswith("colmap_pvs.io") and i.target not in MODEL_IO_ALLOWED
    ]
    assert not found, "\n".join(found)


def test_inference_never_imports_training():
    found = []
    for m, imports in _graph().items():
        if not (m == "colmap_pvs.stereo" or m.startswith("colmap_pvs.stereo.")):
            continue
        for i in imports:
            if i.target == "colmap_pvs.train" or i.target.startswith("colmap_pvs.train."):
                found.append(f"{m} imports {i.target}, line {i.line}")
            elif i.target == "colmap_pvs.adapt" and (m not in STEREO_ADAPT_HOOKS or not i.lazy):
                found.append(f"{m} imports colmap_pvs.adapt (trains) outside its lazy hook, line {i.line}")
    assert not found, "\n".join(found)


def test_no_library_file_over_the_line_limit():
    long = {}
    for path in LIBRARY_FILES.values():
        with path.open(encoding="utf-8") as f:
            n = sum(1 for _ in f)
        if n > MAX_LINES:
            long[str(path.relative_to(REPO_ROOT))] = n
    assert not long, f"library files over {MAX_LINES} lines: {long}"


def test_every_package_is_installed():
    tomllib = pytest.importorskip("tomllib")
    with (REPO_ROOT / "pyproject.toml").open("rb") as f:
        installed = set(tomllib.load(f)["tool"]["setuptools"]["packages"])
    packages = {m for m, path in LIBRARY_FILES.items() if path.name == "__init__.py"}
    assert packages <= installed, f"packages missing from pyproject.toml: {sorted(packages - installed)}"


def _loaded_after(module: str, prefixes: tuple[str, ...]) -> list[str]:
    code = (
        f"import sys, {module}; prefixes = {prefixes!r}; "
        "print(sorted(m for m in sys.modules if any(m == p or m.startswith(p + '.') for p in prefixes)))"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True, text=True,
                         timeout=120, check=True)
    return ast.literal_eval(out.stdout.strip().splitlines()[-1])


def test_importing_stereo_loads_no_training_code():
    assert _loaded_after("colmap_pvs.stereo", ("colmap_pvs.train", "colmap_pvs.adapt")) == []


def test_importing_the_model_loads_no_pycolmap():
    assert _loaded_after("colmap_pvs.model", ("pycolmap",)) == []


def test_stereo_help_lists_at_most_46_flags(capsys):
    from colmap_pvs.cli.main import main

    with pytest.raises(SystemExit) as exit_info:
        main(["stereo", "--help"])
    assert exit_info.value.code == 0
    flags = re.findall(r"^\s+(?:-\w+, )?(--[\w.-]+)", capsys.readouterr().out, flags=re.MULTILINE)
    assert 0 < len(flags) <= 46, f"{len(flags)} flags: {flags}"
