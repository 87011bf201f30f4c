"""Shared pytest fixtures (keep them generic: other test modules rely on them)."""

from __future__ import annotations

import errno
import os
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
    import pycolmap  # noqa: F401  (its import replaces the handler)

    _CRASH_REPORT_FD = os.dup(sys.__stderr__.fileno())
    _restore_crash_report()


def _restore_crash_report() -> None:
    import faulthandler

    if _CRASH_REPORT_FD is not None:
        faulthandler.disable()
        faulthandler.enable(file=_CRASH_REPORT_FD, all_threads=True)


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    """``ray.init`` (in a fixture or an earlier test) installs its own fatal-signal handlers too: put
    Python's back before every test's setup, call and teardown."""
    _restore_crash_report()


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_call(item: pytest.Item) -> None:
    _restore_crash_report()


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_teardown(item: pytest.Item) -> None:
    _restore_crash_report()


def pytest_unconfigure(config: pytest.Config) -> None:
    global _CRASH_REPORT_FD
    import faulthandler

    if _CRASH_REPORT_FD is not None:
        faulthandler.disable()
        os.close(_CRASH_REPORT_FD)
        _CRASH_REPORT_FD = None


#: Set in the child process that runs the tests marked ``own_process``.
OWN_PROCESS_ENV = "COLMAP_PVS_TESTS_OWN_PROCESS"
#: The longest the child of :class:`OwnProcess` may take (its tests have their own limits too).
OWN_PROCESS_SECONDS = 900


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(session: pytest.Session, config: pytest.Config, items: list) -> None:
    """The selected tests marked ``own_process`` (the Ray backend's) run together in a child pytest.

    ``ray.shutdown()`` leaves Ray's native threads (its GCS client's event loop, gRPC's) running in the
    process that started Ray, with Ray's fatal-signal handlers installed; in the suite's own process they
    would live on beside every later test. In a child they end with it.
    """
    if os.environ.get(OWN_PROCESS_ENV) or config.getoption("collectonly"):
        return
    own = [item for item in items if item.get_closest_marker("own_process")]
    if not own:
        return
    at = items.index(own[0])
    items[:] = [item for item in items if not item.get_closest_marker("own_process")]
    parent = own[0].getparent(pytest.Module) or session  # named after the (first) module it runs
    items.insert(at, OwnProcess.from_parent(parent, name="own_process", nodeids=[i.nodeid for i in own]))


class OwnProcess(pytest.Item):
    """The tests ``nodeids`` run by a child ``python -m pytest``: passes when all of them pass."""

    def __init__(self, *, nodeids: list[str], **kwargs) -> None:
        super().__init__(**kwargs)
        self.nodeids = nodeids

    def runtest(self) -> None:
        import subprocess

        env = {**os.environ, OWN_PROCESS_ENV: "1"}
        argv = [sys.executable, "-m", "pytest", "-q", "-ra", "-p", "no:cacheprovider", *self.nodeids]
        try:
            run = subprocess.run(argv, cwd=self.config.rootpath, env=env, capture_output=True, text=True,
                                 timeout=OWN_PROCESS_SECONDS)
        except subprocess.TimeoutExpired as exc:
            out = "\n".join(x.decode(errors="replace") if isinstance(x, bytes) else (x or "")
                            for x in (exc.stdout, exc.stderr))
            raise OwnProcessFailed(f"{len(self.nodeids)} test(s) in a child pytest ran over "
                                   f"{OWN_PROCESS_SECONDS} s; its output so far:\n{out[-20000:]}") from None
        lines = run.stdout.strip().splitlines() or ["(no output)"]
        if run.returncode != 0:
            raise OwnProcessFailed(f"{len(self.nodeids)} test(s) in a child pytest (exit {run.returncode}): "
                                   f"{lines[-1]}\n{run.stdout[-20000:]}\n{run.stderr[-5000:]}")
        skipped = [line for line in lines if line.startswith("SKIPPED")]
        for line in skipped:  # shown in the suite's own summary, as the child's skips
            self.warn(pytest.PytestWarning(f"in the child pytest: {line}"))
        self.add_report_section("call", "child", "\n".join([*skipped, lines[-1]]))

    def repr_failure(self, excinfo):
        if isinstance(excinfo.value, OwnProcessFailed):
            return str(excinfo.value)
        return super().repr_failure(excinfo)

    def reportinfo(self):
        return self.path, None, f"{len(self.nodeids)} test(s) marked own_process, in a child pytest"


class OwnProcessFailed(Exception):
    """A test :class:`OwnProcess` ran failed (the message holds the child's report)."""


def disk_full_after_writing_half(path, *args, **kwargs):
    """A stand-in for a writer of ``path`` (its first argument) on a full disk: it leaves half a file there
    and raises ``ENOSPC``."""
    Path(path).write_bytes(b"half")
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))


def load_tool(name: str):
    """The script ``tools/NAME.py`` as a module (``tools/`` is not a package), registered as ``NAME``."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, REPO_ROOT / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


#: Audit events that change a file or folder (``open``: only for writing), and their path arguments.
_WRITE_EVENTS = {"os.mkdir": (0,), "os.rename": (0, 1), "os.remove": (0,), "os.rmdir": (0,),
                 "os.symlink": (1,), "os.link": (1,), "os.truncate": (0,), "os.chmod": (0,), "os.chown": (0,),
                 "os.utime": (0,), "shutil.rmtree": (0,), "shutil.copyfile": (1,), "shutil.copytree": (1,)}
_WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND


def _read_only_folders() -> list[str]:
    """The folders (real paths) that this test process may not change; one list per process (kept on
    :mod:`sys`, as its audit hook is)."""
    if not hasattr(sys, "_colmap_pvs_read_only_folders"):
        sys._colmap_pvs_read_only_folders = []
        sys.addaudithook(_refuse_writes)  # audit hooks stay for the process: installed once
    return sys._colmap_pvs_read_only_folders


def _refuse_writes(event: str, args: tuple) -> None:
    """Audit hook: a write, folder made, rename or removal under a read-only folder raises PermissionError,
    as on a read-only file system (also to root, which the tests may run as)."""
    folders = getattr(sys, "_colmap_pvs_read_only_folders", None)
    if not folders:
        return
    if event == "open":
        path, mode, flags = args
        writes = any(c in mode for c in "wax+") if isinstance(mode, str) else bool(flags & _WRITE_FLAGS)
        paths = (path,) if writes else ()
    elif event == "os.mkdir" and args and os.path.isdir(os.fsdecode(args[0])):
        paths = ()  # as on a read-only disk: an existing folder is only "exists" (mkdir(exist_ok=True))
    else:
        paths = tuple(args[i] for i in _WRITE_EVENTS.get(event, ()) if i < len(args))
    for path in paths:
        if isinstance(path, int) or path is None:
            continue
        full = os.path.realpath(os.fsdecode(path))
        if any(full == top or full.startswith(top + os.sep) for top in folders):
            raise PermissionError(errno.EACCES, "read-only to the tests", os.fsdecode(path))


@pytest.fixture
def read_only():
    """``read_only(path)``: until the test ends, changing anything under ``path`` raises PermissionError."""
    added: list[str] = []

    def make(path: Path) -> None:
        added.append(os.path.realpath(path))
        _read_only_folders().append(added[-1])

    yield make
    for top in added:
        _read_only_folders().remove(top)


@pytest.fixture(scope="session")
def shared_data_dir() -> Path:
    """``../shared/data`` next to the repository (real captures; read-only, also to a test run as root:
    changing anything under it raises PermissionError). Skips if absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is missing")
    if os.path.realpath(SHARED_DATA) not in _read_only_folders():
        _read_only_folders().append(os.path.realpath(SHARED_DATA))
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
