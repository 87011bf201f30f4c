"""The documents a user reads stay true: every test the conventions name exists, the README is a user
guide whose test command is CI's, and the model card is a model card."""

from __future__ import annotations

import ast
import importlib
import re
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


def test_readme_is_a_user_guide_whose_test_command_is_cis():
    text = (ROOT / "README.md").read_text()
    assert len(text.split()) <= 1800
    assert not re.search(r"\b(stop|issue) \d+\b", text, flags=re.IGNORECASE)
    assert not re.search(r"\b20\d\d-\d\d-\d\d\b", text)
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.S)
    test_command = next(b.strip() for b in blocks if "python -m pytest" in b)
    ci = (ROOT / ".ci" / "run").read_text()
    for part in test_command.split("&&"):  # CI runs each step of the README's test command
        assert part.strip().replace("pip install", "python3 -m pip install -q").replace(
            "python -m pytest -q", "python3 -m pytest -q") in ci, part
    assert "download.pytorch.org/whl/cpu" in text  # how a user elsewhere gets the CPU build


def test_model_card_is_a_model_card():
    card = (ROOT / "colmap_pvs" / "weights" / "MODEL_CARD.md").read_text()
    assert len(card.splitlines()) <= 300
    headings = [h.lower() for h in re.findall(r"^#+ (.+)$", card, flags=re.M)]
    for section in ("intended use", "training data", "evaluation", "limitations"):
        assert any(section in h for h in headings), section
    assert not re.search(r"\bstop \d+\b", card, flags=re.IGNORECASE)


@pytest.mark.parametrize("script", sorted(p.stem for p in (ROOT / "benchmarks").glob("*.py")))
def test_every_benchmark_script_imports(script, monkeypatch):
    """A benchmark that imports a moved or renamed name fails here, not months later."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    importlib.import_module(script)
