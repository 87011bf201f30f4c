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
#: before ``colmap_pvs.io``); every module must belong to one. The package root ``colmap_pvs`` is the
#: root module only (PACKAGE_ROOT), not a prefix of every module.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    # the package root (``__version__``), errors, plain data types, the stdlib-only atomic file
    # writes every layer uses, the shipped weights
    ("base", ("colmap_pvs", "colmap_pvs.errors", "colmap_pvs.types", "colmap_pvs.io.files",
              "colmap_pvs.weights", "colmap_pvs.openmp")),
    ("config", ("colmap_pvs.config",)),
    # COLMAP's files (pycolmap) and the numpy core that works on maps (confidence: its calibration)
    ("io and numeric core", ("colmap_pvs.io", "colmap_pvs.geometry", "colmap_pvs.upsampling",
                             "colmap_pvs.normals", "colmap_pvs.consistency", "colmap_pvs.prior",
                             "colmap_pvs.confidence")),
    ("model", ("colmap_pvs.model",)),
    # completion fits the model's dense prior (colmap_pvs.model.cost) to the kept pixels
    ("completion, views, mesh, evaluation", ("colmap_pvs.completion", "colmap_pvs.views",
                                             "colmap_pvs.mesh", "colmap_pvs.evaluate")),
    # inference: runs the weights it is given, knows nothing of training
    ("stereo", ("colmap_pvs.stereo",)),
    ("synthetic data", ("colmap_pvs.synthetic",)),
    ("training", ("colmap_pvs.train",)),
    # the stereo command's --adapt_* step: trains a copy of the checkpoint, then runs stereo with it
    ("test-time adaptation", ("colmap_pvs.adapt",)),
    ("fusion", ("colmap_pvs.fusion",)),
    ("pipelines", ("colmap_pvs.reconstruct", "colmap_pvs.demo", "colmap_pvs.average_weights")),
    ("cli", ("colmap_pvs.cli",)),
]

#: The only module of ``colmap_pvs.io`` that ``colmap_pvs.model`` may import (stdlib only: atomic
#: writes of checkpoints); the model never reads COLMAP's files, images or maps.
MODEL_IO_ALLOWED = {"colmap_pvs.io.files"}

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
            elif isinstance(child, ast.Call):  # importlib.import_module("colmap_pvs.x"), __import__(...)
                name = _imported_by_call(child, package)
                if name.split(".")[0] == "colmap_pvs":
                    targets = [_known(name)]
            for target in targets:
                if target and target != module:
                    found.append(Import(target, lazy, child.lineno))
            visit(child, inner)

    visit(tree, False)
    return found


def _imported_by_call(call: ast.Call, package: str) -> str:
    """The module that ``import_module(NAME[, package])`` or ``__import__(NAME)`` imports, when NAME is a
    string constant (a relative NAME counts from this module's package); else ""."""
    func = call.func
    callee = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
    if callee not in ("import_module", "__import__") or not call.args:
        return ""
    name = call.args[0]
    if not (isinstance(name, ast.Constant) and isinstance(name.value, str)):
        return ""
    dots = len(name.value) - len(name.value.lstrip("."))
    if callee == "__import__" or not dots:
        return name.value
    base = package.rsplit(".", dots - 1)[0] if dots > 1 else package
    rest = name.value[dots:]
    return f"{base}.{rest}" if rest else base


@cache
def _graph() -> dict[str, list[Import]]:
    return {module: _imports(module) for module in LIBRARY_FILES}


#: The package's root module: in LAYERS it names ``colmap_pvs/__init__.py`` alone.
PACKAGE_ROOT = "colmap_pvs"


def _layer(module: str) -> int:
    best, index = "", -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            below = prefix != PACKAGE_ROOT and module.startswith(prefix + ".")
            if (module == prefix or below) and len(prefix) > len(best):
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
    lazy = {i.target for i in graph["colmap_pvs.adapt.checkpoint"] if i.lazy}
    assert "colmap_pvs.train" in lazy and "colmap_pvs.train.real_dataset" in lazy


def test_the_graph_reader_follows_import_module_calls(tmp_path, monkeypatch):
    source = (
        "import importlib\n"
        "from importlib import import_module\n"
        "def run():\n"
        "    importlib.import_module('colmap_pvs.train')\n"
        "    import_module('.network', __package__)\n"
        "    __import__('colmap_pvs.adapt')\n"
        "    importlib.import_module(name_from_a_table)\n"
    )
    (tmp_path / "probe.py").write_text(source)
    monkeypatch.setitem(LIBRARY_FILES, "colmap_pvs.stereo.probe", tmp_path / "probe.py")
    found = {(i.target, i.lazy, i.line) for i in _imports("colmap_pvs.stereo.probe")}
    assert found == {("colmap_pvs.train", True, 4), ("colmap_pvs.stereo.network", True, 5),
                     ("colmap_pvs.adapt", True, 6)}


def test_the_package_root_is_no_prefix_of_every_module():
    assert _layer("colmap_pvs") == 0 and _layer("colmap_pvs.errors") == 0
    assert _layer("colmap_pvs.new_stage") < 0  # a new top-level module must be added to LAYERS
    assert _layer("colmap_pvs.io.new_reader") == _layer("colmap_pvs.io")


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


def _in(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def test_stereo_never_imports_training_or_adaptation():
    """Inference stands on its own: no module of ``colmap_pvs.stereo`` imports the trainer or the
    adaptation step above it, not even inside a function or through ``import_module``."""
    found = [
        f"{m} imports {i.target}{' (inside a function)' if i.lazy else ''}, line {i.line}"
        for m, imports in _graph().items()
        if _in(m, "colmap_pvs.stereo")
        for i in imports
        if _in(i.target, "colmap_pvs.train") or _in(i.target, "colmap_pvs.adapt")
    ]
    assert not found, "\n".join(found)
    assert _layer("colmap_pvs.stereo") < _layer("colmap_pvs.train") < _layer("colmap_pvs.adapt.stereo")


def test_no_library_file_over_the_line_limit():
    long = {}
    for path in LIBRARY_FILES.values():
        with path.open(encoding="utf-8") as f:
            n = sum(1 for _ in f)
        if n > MAX_LINES:
            long[str(path.relative_to(REPO_ROOT))] = n
    assert not long, f"library files over {MAX_LINES} lines: {long}"


def test_every_package_is_installed():
    from test_dependencies import read_pyproject  # tomllib, or tomli (the test extra's) on Python 3.10

    installed = read_pyproject()["tool"]["setuptools"]["packages"]
    packages = {m for m, path in LIBRARY_FILES.items() if path.name == "__init__.py"}
    missing = sorted(packages - set(installed))
    assert len(installed) > 5 and not missing, f"packages missing from pyproject.toml: {missing}"


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


def test_stereo_help_lists_at_most_47_flags(capsys):
    from colmap_pvs.cli.main import main

    with pytest.raises(SystemExit) as exit_info:
        main(["stereo", "--help"])
    assert exit_info.value.code == 0
    flags = re.findall(r"^\s+(?:-\w+, )?(--[\w.-]+)", capsys.readouterr().out, flags=re.MULTILINE)
    assert 0 < len(flags) <= 47, f"{len(flags)} flags: {flags}"


#: What ``colmap_pvs.config`` (the config layer) may import of the package: the base layer's errors.
CONFIG_IMPORTS_ALLOWED = {"colmap_pvs.errors"}


def test_the_config_layer_imports_only_the_errors():
    found = [f"colmap_pvs.config imports {i.target}, line {i.line}" for i in _graph()["colmap_pvs.config"]
             if i.target not in CONFIG_IMPORTS_ALLOWED]
    assert not found, "\n".join(found)


#: Names of the back-compat entries (what a user's saved file from an older version needs): each is
#: preceded by a comment that says ``Back-compat (dropped in X.Y)``. Remove a name once it is dropped.
BACK_COMPAT_NAMES = {"REMOVED_OPTIONS", "FIXED_SETTINGS", "RETIRED_FIELDS", "ABSENT_FIELDS",
                     "_SETTINGS_BEFORE_RECORDED", "LEGACY_STEREO_KEYS", "_UNTAGGED"}
_BACK_COMPAT = re.compile(r"back-?compat", re.IGNORECASE)
_DROPPED_IN = re.compile(r"Back-compat \(dropped in (\d+)\.(\d+)\)")


def _drop_version_problem(text: str, where: str) -> str | None:
    """Why ``text`` (a comment or docstring) does not name a later version that drops it, or None."""
    from colmap_pvs import __version__

    match = _DROPPED_IN.search(text)
    if match is None:
        return f"{where}: no 'Back-compat (dropped in X.Y)'"
    if (int(match[1]), int(match[2])) <= tuple(int(p) for p in __version__.split(".")[:2]):
        return f"{where}: dropped in {match[1]}.{match[2]}, not after this version {__version__}"
    return None


def test_every_back_compat_entry_names_the_version_that_drops_it():
    problems, found = [], set()
    for module, path in LIBRARY_FILES.items():
        source = path.read_text(encoding="utf-8")
        lines = source.splitlines()
        for line_no, line in enumerate(lines, 1):  # every mention is the phrase, with a later version
            for mention in _BACK_COMPAT.finditer(line):
                problem = _drop_version_problem(line[mention.start():], f"{module}:{line_no}")
                if problem:
                    problems.append(problem)
        for node in ast.walk(ast.parse(source)):
            targets = node.targets if isinstance(node, ast.Assign) else [getattr(node, "target", None)]
            for target in targets:
                if not (isinstance(target, ast.Name) and target.id in BACK_COMPAT_NAMES):
                    continue
                found.add(target.id)
                above, n = [], node.lineno - 2
                while n >= 0 and lines[n].strip().startswith("#"):
                    above.insert(0, lines[n].strip().lstrip("#:").strip())
                    n -= 1
                problem = _drop_version_problem(" ".join(above), f"{module}:{node.lineno} {target.id}")
                if problem:
                    problems.append(problem)
    assert not problems, "\n".join(problems)
    assert found == BACK_COMPAT_NAMES, f"not found (dropped? remove them here): {BACK_COMPAT_NAMES - found}"
