"""The documents a user reads stay true: every test the conventions name exists, the README is a user
guide whose test command is CI's, and the model card is a model card."""

from __future__ import annotations

import ast
import importlib
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _tests_defined() -> set[str]:
    names = set()
    for path in (ROOT / "tests").glob("test_*.py"):
        tree = ast.parse(path.read_text())
        names.add(f"tests/{path.name}")
        names |= {f"tests/{path.name}::{node.name}" for node in ast.walk(tree)
                  if isinstance(node, ast.FunctionDef) and node.name.startswith("test_")}
    return names


def test_every_test_the_conventions_name_exists():
    text = (ROOT / "docs" / "CONVENTIONS.md").read_text()
    named = set(re.findall(r"`(tests/test_\w+\.py(?:::\w+)?)", text))
    assert len(named) > 20
    missing = sorted(named - _tests_defined())
    assert not missing, f"docs/CONVENTIONS.md names tests that do not exist: {missing}"


# ------------------------------------------------------------------ the README's test command is CI's
#
# CI's script (.ci/run) is run as it is, with python, pip, pytest and apt-get replaced by stand-ins that
# record each command line (and make ``python -m venv DIR`` a folder of stand-ins with an ``activate``):
# what it runs is compared with the README's test command, step by step, with the same meaning
# (``pip`` = ``python -m pip``, ``python`` = ``python3``, pip's ``-q`` dropped).

#: Tools the stand-ins replace; CI must call them by name (on PATH), so that the test can stand in.
STAND_INS = ("python", "python3", "pip", "pip3", "pytest", "apt-get", "apt", "sudo")

STAND_IN = """#!{python}
import json, os, shutil, sys

name, args = os.path.basename(sys.argv[0]), sys.argv[1:]
if name == "sudo":
    os.execvp(args[0], args)
with open(os.environ["CI_STAND_IN_LOG"], "a") as log:
    log.write(json.dumps({{"argv": sys.argv, "cwd": os.getcwd()}}) + "\\n")
if name.startswith("python") and args[:2] == ["-m", "venv"]:
    env = os.path.abspath([a for a in args[2:] if not a.startswith("-")][-1])
    os.makedirs(os.path.join(env, "bin"), exist_ok=True)
    for tool in ("python", "python3", "pip", "pip3", "pytest"):
        shutil.copy(__file__, os.path.join(env, "bin", tool))
    with open(os.path.join(env, "bin", "activate"), "w") as f:
        f.write(f'VIRTUAL_ENV="{{env}}"; export VIRTUAL_ENV; PATH="{{env}}/bin:$PATH"; export PATH\\n'
                "deactivate () {{ :; }}\\nhash -r 2>/dev/null || true\\n")
    sys.exit(0)
if name.startswith("python") and args[:2] == ["-m", "pytest"] or name == "pytest":
    sys.exit(int(os.environ["CI_STAND_IN_PYTEST_RC"]))
if name.startswith("python") and args[:2] == ["-m", "pip"] or name.startswith("pip"):
    sys.exit(int(os.environ["CI_STAND_IN_PIP_RC"]))
sys.exit(0)
"""


def _readme_test_command() -> list[list[str]]:
    """The README's test command (its bash block that runs pytest) as the argv of each ``&&`` step."""
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.S)
    command = next(b for b in blocks if re.search(r"-m pytest\b", b)).replace("\\\n", " ")
    lexer = shlex.shlex(command, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    steps: list[list[str]] = [[]]
    for token in lexer:
        if token == "&&":
            steps.append([])
        else:
            assert token not in (";", "|", "||", "&", "\n"), f"not one && chain: {token!r}"
            steps[-1].append(token)
    return steps


def _meaning(argv: list[str]) -> tuple[str, ...]:
    """A command line as what it does: ``python3 -m pip install -q X`` and ``pip install X`` are the same."""
    prog, args = os.path.basename(argv[0]), list(argv[1:])
    if re.fullmatch(r"python(3(\.\d+)?)?", prog):
        prog = "python"
        if len(args) >= 2 and args[0] == "-m":
            prog, args = args[1], args[2:]
    if re.fullmatch(r"pip(3(\.\d+)?)?", prog):
        prog, args = "pip", [a for a in args if a not in ("-q", "-qq", "-qqq", "--quiet")]
    return (prog, *args)


def _run_ci(tmp_path: Path, pytest_rc: int = 0, pip_rc: int = 0) -> tuple[int, list[dict], Path, str]:
    """``.ci/run`` with the stand-ins first on PATH: (its exit status, the commands the stand-ins ran as
    ``{"argv", "cwd"}`` in order, the repository root it ran in, its output)."""
    script = (ROOT / ".ci" / "run").read_text()
    tools = "|".join(map(re.escape, STAND_INS))
    absolute = re.findall(rf"(?<![\w.-])/(?:usr/)?(?:local/)?s?bin/(?:{tools})\b", script)
    assert not absolute, f".ci/run calls {absolute}: call them by name, so that this test can stand in"
    run = tmp_path / f"ci-{pytest_rc}-{pip_rc}"
    repo, bin_dir, log = run / "repo", run / "bin", run / "commands.jsonl"
    (repo / ".ci").mkdir(parents=True)
    (repo / ".ci" / "run").write_text(script)
    bin_dir.mkdir()
    stand_in = bin_dir / "stand-in"
    stand_in.write_text(STAND_IN.format(python=sys.executable))
    stand_in.chmod(0o755)
    for tool in STAND_INS:
        (bin_dir / tool).symlink_to(stand_in)
    env = {"PATH": f"{bin_dir}{os.pathsep}/usr/bin{os.pathsep}/bin", "HOME": str(run), "TMPDIR": str(run),
           "LANG": "C.UTF-8", "CI_STAND_IN_LOG": str(log), "CI_STAND_IN_PYTEST_RC": str(pytest_rc),
           "CI_STAND_IN_PIP_RC": str(pip_rc)}
    proc = subprocess.run(["bash", str(repo / ".ci" / "run")], env=env, cwd=run, capture_output=True,
                          text=True, timeout=60)
    commands = [json.loads(line) for line in log.read_text().splitlines()] if log.is_file() else []
    return proc.returncode, commands, repo, proc.stdout[-2000:] + proc.stderr[-2000:]


def _test_steps(commands: list[dict]) -> list[dict]:
    """The commands of the README's kind (pip, pytest, python): not apt-get, not making the venv."""
    return [c for c in commands if _meaning(c["argv"])[0] not in ("apt-get", "apt", "venv")]


def test_readme_is_a_user_guide_whose_test_command_is_cis(tmp_path):
    text = (ROOT / "README.md").read_text()
    assert len(text.split()) <= 1800
    assert not re.search(r"\b(stop|issue) \d+\b", text, flags=re.IGNORECASE)
    assert not re.search(r"\b20\d\d-\d\d-\d\d\b", text)
    assert "download.pytorch.org/whl/cpu" in text  # how a user elsewhere gets the CPU build
    readme = [_meaning(step) for step in _readme_test_command()]
    assert readme[-1][0] == "pytest" and any(step[:2] == ("pip", "install") for step in readme)
    code, commands, repo, output = _run_ci(tmp_path)
    assert code == 0, output
    steps = _test_steps(commands)
    assert [_meaning(c["argv"]) for c in steps] == readme, "CI does not run the README's test command"
    # in the repository, and in one environment: pytest runs where the package was installed
    assert {os.path.realpath(c["cwd"]) for c in steps} == {os.path.realpath(repo)}
    envs = {os.path.realpath(os.path.join(c["cwd"], os.path.dirname(c["argv"][0]))) for c in steps}
    assert len(envs) == 1, f"CI installs and tests in different environments: {[c['argv'] for c in steps]}"
    # a failed install fails CI before the tests run
    code, commands, _, output = _run_ci(tmp_path, pip_rc=1)
    assert code != 0 and not [c for c in commands if _meaning(c["argv"])[0] == "pytest"], output


def test_ci_fails_when_no_test_is_collected(tmp_path):
    """pytest's exit status 5 (no tests collected: a wrong path, a broken conftest) is a failure of CI."""
    code, commands, _, output = _run_ci(tmp_path, pytest_rc=5)
    assert [c for c in commands if _meaning(c["argv"])[0] == "pytest"], output
    assert code != 0, ".ci/run turns pytest's 'no tests collected' (exit status 5) into success"


def test_model_card_is_a_model_card():
    card = (ROOT / "colmap_pvs" / "weights" / "MODEL_CARD.md").read_text()
    assert len(card.splitlines()) <= 300
    headings = [h.lower() for h in re.findall(r"^#+ (.+)$", card, flags=re.M)]
    for section in ("intended use", "training data", "evaluation", "limitations"):
        assert any(section in h for h in headings), section
    assert not re.search(r"\bstop \d+\b", card, flags=re.IGNORECASE)


BENCHMARKS = sorted(p.stem for p in (ROOT / "benchmarks").glob("*.py"))


def _imports_inside_functions(path: Path) -> list[tuple[int, str, str | None]]:
    """``(line, module, name or None)`` of every absolute ``import`` inside a function of ``path``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for inner in ast.walk(node):
            if isinstance(inner, ast.Import):
                found += [(inner.lineno, alias.name, None) for alias in inner.names]
            elif isinstance(inner, ast.ImportFrom) and inner.level == 0 and inner.module:
                found += [(inner.lineno, inner.module, alias.name) for alias in inner.names]
    return sorted(set(found))


@pytest.mark.parametrize("script", BENCHMARKS)
def test_every_benchmark_script_imports(script, monkeypatch):
    """A benchmark that imports a moved or renamed name fails here, not months later: its module-level
    code runs, and every import of the library or of another benchmark inside its functions resolves
    (other packages there are optional: open3d, scikit-image)."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    importlib.import_module(script)
    broken = []
    for line, module, name in _imports_inside_functions(ROOT / "benchmarks" / f"{script}.py"):
        if module.split(".")[0] not in ("colmap_pvs", *BENCHMARKS):
            continue
        try:
            imported = importlib.import_module(module)
            if name is not None and not hasattr(imported, name):
                importlib.import_module(f"{module}.{name}")
        except ImportError as exc:
            what = f"from {module} import {name}" if name else f"import {module}"
            broken.append(f"benchmarks/{script}.py:{line}: {what} fails ({exc})")
    assert not broken, "\n".join(broken)


def _developing_guide_problems(text: str) -> list[str]:
    """What the developer guide names in backquotes that does not exist: a path (``a/b.py``, a folder
    ``a/``), a dotted ``colmap_pvs.`` name (module, then attributes), a ``tests/x.py::test`` name."""
    problems = []
    for token in re.findall(r"`([^`\s]+)`", text):
        path, _, test = token.partition("::")
        if "/" in path and not path.startswith("--"):
            if not (ROOT / path.rstrip("/")).exists():
                problems.append(f"no file {path}")
            elif test and not re.search(rf"^def {re.escape(test)}\(", (ROOT / path).read_text(), re.M):
                problems.append(f"no test {token}")
        elif token.startswith("colmap_pvs."):
            parts = token.split(".")
            for cut in range(len(parts), 0, -1):  # the longest importable module, then its attributes
                try:
                    obj = importlib.import_module(".".join(parts[:cut]))
                except ImportError:
                    continue
                try:
                    for attr in parts[cut:]:
                        obj = getattr(obj, attr)
                except AttributeError:
                    problems.append(f"no name {token}")
                break
    return problems


def test_developing_guide_names_what_exists():
    """docs/DEVELOPING.md's paths, modules, functions and tests exist (the guide follows the code)."""
    text = (ROOT / "docs" / "DEVELOPING.md").read_text()
    assert _developing_guide_problems(text) == []
    stale = "`colmap_pvs/stereo/adaptation.py`, `colmap_pvs.stereo.local.run_localized`, " \
            "`tests/test_docs.py::test_no_such_test`"
    assert len(_developing_guide_problems(stale)) == 3
    assert "docs/DEVELOPING.md" in (ROOT / "README.md").read_text()


#: What the library's docstrings, comments and help strings may not say: the development sets'
#: names and measured results (those live in benchmarks/RESULTS.md; a design choice names its entry).
DEV_SET_HISTORY = re.compile(r"hololens-dev|colmap-statue|\bF1 \d|\d+(\.\d+)? (to|->) \d+(\.\d+)? ?(%|mm|px)")


def test_library_text_quotes_no_development_set_results():
    found = [f"{path.relative_to(ROOT)}:{n}: {line.strip()}"
             for folder in ("colmap_pvs", "cli") for path in sorted((ROOT / folder).rglob("*.py"))
             for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
             if DEV_SET_HISTORY.search(line)]
    assert not found, "move these to benchmarks/RESULTS.md:\n" + "\n".join(found)
