"""A fresh machine has everything the repository imports: every third-party import in the library, the CLI,
the tests, the benchmarks and the tools comes from a dependency or an extra that ``pyproject.toml`` declares,
and the README's test command (``.[test]``) installs every extra the tests import through."""

from __future__ import annotations

import ast
import importlib.metadata
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("colmap_pvs", "cli", "tests", "benchmarks", "tools", "examples")
#: Calls whose first string argument names a module (``importlib.import_module("x")``,
#: ``pytest.importorskip("x")``, ``__import__("x")``).
DYNAMIC_IMPORTS = {"import_module", "importorskip", "__import__"}


#: Runtimes measured against torch (issue 57) that the package does not ship: ``benchmarks/onnx_runtime.py``
#: needs them installed by hand and ``tests/test_onnx_export.py`` skips without them. Only those two files
#: may import them.
MEASURED_NOT_SHIPPED = {"onnxruntime", "onnxscript", "onnx", "openvino"}
MEASURED_BY = {"benchmarks/onnx_runtime.py", "tests/test_onnx_export.py"}


def _measured_only(name: str, files: set[str]) -> bool:
    return name in MEASURED_NOT_SHIPPED and files <= MEASURED_BY


def _requirement_name(requirement: str) -> str:
    return _normalise(re.split(r"[\s\[<>=!~;(]", requirement.strip(), maxsplit=1)[0])


def _normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def read_pyproject() -> dict:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10: the test extra brings tomli
        import tomli as tomllib
    with (ROOT / "pyproject.toml").open("rb") as f:
        return tomllib.load(f)


def _imports(path: Path) -> set[str]:
    """The top-level names ``path`` imports: ``import``/``from`` statements at any depth (absolute ones)
    and the dynamic imports of a literal module name."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            func = node.func
            called = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
            if called in DYNAMIC_IMPORTS and isinstance(node.args[0].value, str):
                if not node.args[0].value.startswith("."):
                    names.add(node.args[0].value)
    return {name.split(".")[0] for name in names}


def _local_modules() -> set[str]:
    """Names that resolve inside the repository: the package, and the scripts and helpers that sit beside
    their importers (``benchmarks/real_depth.py``, ``tests/scenes.py``, ``tools/teacher_labels.py``)."""
    local = {"colmap_pvs"}
    for folder in SCANNED:
        local |= {p.stem for p in (ROOT / folder).glob("*.py")}
    return local


def third_party_imports() -> dict[str, set[str]]:
    """``{top-level module: {repository file, ...}}`` for every import outside the standard library and
    the repository."""
    local, found = _local_modules(), {}
    for folder in SCANNED:
        for path in sorted((ROOT / folder).rglob("*.py")):
            for name in _imports(path) - local - set(sys.stdlib_module_names):
                found.setdefault(name, set()).add(str(path.relative_to(ROOT)))
    return found


def declared() -> dict[str, set[str]]:
    """``{"": core dependencies, EXTRA: its requirements}``, as normalised distribution names."""
    project = read_pyproject()["project"]
    out = {"": {_requirement_name(r) for r in project["dependencies"]}}
    for extra, requirements in project.get("optional-dependencies", {}).items():
        out[extra] = {_requirement_name(r) for r in requirements}
    return out


def conditional() -> set[str]:
    """Requirements with an environment marker (``tomli>=2; python_version < '3.11'``): their module may be
    absent where the marker does not hold."""
    project = read_pyproject()["project"]
    requirements = [*project["dependencies"], *sum(project.get("optional-dependencies", {}).values(), [])]
    return {_requirement_name(r) for r in requirements if ";" in r}


def test_the_scan_finds_nested_and_dynamic_imports(tmp_path):
    script = tmp_path / "script.py"
    script.write_text(
        "import os\nimport numpy.linalg\n\n\ndef f():\n    from scipy.spatial import cKDTree\n"
        "    import importlib\n    importlib.import_module('skimage.data')\n"
        "    pytest.importorskip('ray')\n    from . import sibling\n"
    )
    assert _imports(script) - set(sys.stdlib_module_names) == {"numpy", "scipy", "skimage", "ray"}


def test_every_import_is_a_declared_dependency():
    """An import that only a hand-installed package satisfies fails here, naming the file, instead of on a
    new user's machine. A tool's import declared only in an extra that the test command does not install
    (``dev``: ``tools/mutation_test.py``) may be absent."""
    providers = importlib.metadata.packages_distributions()
    extras = declared()
    everything = set().union(*extras.values())
    not_tested = everything - extras[""] - extras["test"]
    problems = []
    for name, files in sorted(third_party_imports().items()):
        dists = {_normalise(d) for d in providers.get(name, [])}
        if _measured_only(name, files):
            continue
        if not dists and _normalise(name) in conditional():
            continue  # declared for other Pythons only (tomli below 3.11)
        if not dists and _normalise(name) in not_tested and all(f.startswith("tools/") for f in files):
            continue  # a development tool's, outside the test command (cosmic-ray)
        if not dists:
            problems.append(f"{name} (imported by {sorted(files)}) is installed by no distribution here")
        elif not dists & everything:
            problems.append(f"{name} (imported by {sorted(files)}) comes from {sorted(dists)}, which "
                            "pyproject.toml declares nowhere")
    assert not problems, "\n".join(problems)


def test_the_test_extra_brings_every_extra_the_suite_imports_through():
    """The README's test command installs ``.[test]`` only; the tests import the benchmarks (``bench``) and
    run the Ray backend (``ray``), so ``test`` must contain both."""
    extras = declared()
    for extra in ("ray", "bench"):
        missing = extras[extra] - extras["test"]
        assert not missing, f"the test extra lacks {sorted(missing)} of the {extra!r} extra"
    tests_and_benchmarks = {n for n, files in third_party_imports().items()
                            if any(f.startswith(("tests/", "benchmarks/")) for f in files)
                            and not _measured_only(n, files)}
    providers = importlib.metadata.packages_distributions()
    for name in sorted(tests_and_benchmarks):
        dists = {_normalise(d) for d in providers.get(name, [])} or {_normalise(name)}
        assert dists & (extras[""] | extras["test"]), f"{name}: not brought by the core or the test extra"


@pytest.mark.parametrize("requirement, name", [
    ("opencv-python-headless>=4.8", "opencv-python-headless"),
    ("ray[default]>=2.10", "ray"),
    ("tomli>=2; python_version < '3.11'", "tomli"),
    ("Scikit_Image >= 0.21", "scikit-image"),
])
def test_requirement_names_are_normalised(requirement, name):
    assert _requirement_name(requirement) == name
