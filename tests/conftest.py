"""Shared pytest fixtures (keep them generic: other test modules rely on them)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

TESTS_DIR = Path(__file__).resolve().parent
if str(TESTS_DIR) not in sys.path:  # make `import scenes` work in every import mode
    sys.path.insert(0, str(TESTS_DIR))

REPO_ROOT = TESTS_DIR.parent
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


_CRASH_REPORT_FD: int | None = None


@pytest.hookimpl(trylast=True)
def pytest_configure(config: pytest.Config) -> None:
    """A native crash (SIGSEGV, SIGABRT) prints every thread's Python stack, the running test among them.

    pytest's faulthandler plugin writes that report, but importing pycolmap (glog) and starting Ray install
    their own fatal-signal handlers over it, which write to the captured stderr, lost when the process
    dies: a crash left no report at all. So pycolmap is imported here, once, and Python's handler is put
    back on a copy of the real stderr, now and before every test.
    """
    global _CRASH_REPORT_FD
    import os

    import pycolmap  # noqa: F401  (its import replaces the handler)

    _CRASH_REPORT_FD = os.dup(sys.__stderr__.fileno())
    _restore_crash_report()


def _restore_crash_report() -> None:
    import faulthandler

    if _CRASH_REPORT_FD is not None:
        faulthandler.disable()
        faulthandler.enable(file=_CRASH_REPORT_FD, all_threads=True)


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_call(item: pytest.Item) -> None:
    """``ray.init`` (in a fixture or an earlier test) installs its own fatal-signal handlers too: put
    Python's back before every test."""
    _restore_crash_report()


def pytest_unconfigure(config: pytest.Config) -> None:
    global _CRASH_REPORT_FD
    import faulthandler
    import os

    if _CRASH_REPORT_FD is not None:
        faulthandler.disable()
        os.close(_CRASH_REPORT_FD)
        _CRASH_REPORT_FD = None


def load_tool(name: str):
    """The script ``tools/NAME.py`` as a module (``tools/`` is not a package), registered as ``NAME``."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, REPO_ROOT / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def shared_data_dir() -> Path:
    """``../shared/data`` next to the repository (real captures; read-only). Skips if absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is missing")
    return SHARED_DATA


@pytest.fixture(scope="session")
def statue_workspace(shared_data_dir: Path) -> Path:
    """The real COLMAP dense workspace ``colmap-statue`` (read-only). Skips if absent."""
    path = shared_data_dir / "colmap-statue"
    if not (path / "sparse").is_dir():
        pytest.skip(f"real dense workspace {path} is missing")
    return path


@pytest.fixture(scope="session")
def analytic_scene(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A complete analytic dense workspace (see ``tests/scenes.py``) built once per session.

    Returns the GT dict of :func:`scenes.make_analytic_workspace`; ``gt["root"]`` is the
    workspace. Treat it as read-only: copy it (``shutil.copytree``) before modifying anything.
    """
    from scenes import make_analytic_workspace

    return make_analytic_workspace(tmp_path_factory.mktemp("analytic") / "workspace")


def make_tiny_checkpoint(path: Path, *, seed: int = 0, step: int = 0, perturb: bool = False,
                         **overrides) -> Path:
    """A tiny randomly initialised PVSNet checkpoint (for plumbing tests, not accuracy), seeded by
    ``seed``. ``perturb``: every tensor (BatchNorm statistics and integer buffers too) is moved by a
    ``seed``-dependent amount, so that two seeds differ everywhere."""
    import torch
    from tiny_models import TINY_COARSE_KWARGS

    from colmap_pvs.model import PVSNet, PVSNetConfig, save_checkpoint

    torch.manual_seed(seed)
    model = PVSNet(PVSNetConfig(**{**TINY_COARSE_KWARGS, **overrides}))
    if perturb:
        with torch.no_grad():
            for value in model.state_dict().values():  # the state dict's tensors share the storage
                if value.is_floating_point():
                    value.add_(torch.rand_like(value))  # > 0: BatchNorm variances stay positive
                else:
                    value.fill_(100 + seed)
    return save_checkpoint(path, model, step=step)


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Path of a tiny random checkpoint, built once per session."""
    return make_tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt")


@pytest.fixture
def one_torch_thread():
    """Run a test on one torch thread (tiny tensors: more threads only add synchronisation cost)."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
