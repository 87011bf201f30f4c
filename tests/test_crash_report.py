"""A native crash in the suite leaves a readable report: which test, which thread (tests/conftest.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

TESTS_DIR = Path(__file__).resolve().parent

PROBE = '''
import os
import threading


def test_a_native_abort_in_a_worker_thread():
    import pycolmap

    pycolmap.Reconstruction()
    worker = threading.Thread(target=os.abort, name="crashing-worker")
    worker.start()
    worker.join()
'''


def test_a_native_crash_after_importing_pycolmap_names_the_test_and_the_thread(tmp_path):
    """pycolmap's import puts glog's signal handlers in place of Python's, which wrote nothing readable;
    the suite's conftest puts Python's back."""
    (tmp_path / "test_probe.py").write_text(PROBE)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS_DIR), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "conftest", "-p", "no:cacheprovider",
         "--rootdir", str(tmp_path), "-c", os.devnull, str(tmp_path / "test_probe.py")],
        capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path,
    )
    assert run.returncode != 0
    report = run.stderr
    assert "Fatal Python error: Aborted" in report, report[-2000:]
    assert "test_a_native_abort_in_a_worker_thread" in report  # the test
    assert "Current thread" in report and "_bootstrap_inner" in report  # the crashing thread, not only main


OWN_PROCESS_PROBE = '''
import os

import pytest


def test_in_the_suite():
    with open(os.path.join(os.environ["PROBE_DIR"], "suite.pid"), "w") as f:
        f.write(str(os.getpid()))


@pytest.mark.own_process
def test_marked_a():
    with open(os.path.join(os.environ["PROBE_DIR"], "a.pid"), "w") as f:
        f.write(str(os.getpid()))


@pytest.mark.own_process
def test_marked_b():
    assert os.environ.get("PROBE_FAIL") != "1", "the marked test failed"
'''


def _run_probe(tmp_path: Path, fail: bool) -> subprocess.CompletedProcess:
    (tmp_path / "test_probe.py").write_text(OWN_PROCESS_PROBE)
    (tmp_path / "conftest.py").write_text("from conftest_under_test import *  # noqa: F401,F403\n"
                                          "from conftest_under_test import pytest_collection_modifyitems\n")
    (tmp_path / "conftest_under_test.py").write_text((TESTS_DIR / "conftest.py").read_text())
    (tmp_path / "pytest.ini").write_text("[pytest]\nmarkers =\n    own_process: a child pytest\n")
    env = {**os.environ, "PROBE_FAIL": "1" if fail else "0", "PYTHONPATH": str(tmp_path),
           "PROBE_DIR": str(tmp_path)}
    env.pop("COLMAP_PVS_TESTS_OWN_PROCESS", None)
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_probe.py"],
                          capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path)


def test_tests_marked_own_process_run_in_a_child_pytest_that_reports_their_failures(tmp_path):
    """The Ray tests (``own_process``) run in a child pytest, so that Ray's threads, which outlive
    ``ray.shutdown()``, never share the suite's process; a failure there fails the suite, naming the test."""
    run = _run_probe(tmp_path, fail=False)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "2 passed" in run.stdout  # the unmarked test and the child's item
    pids = {name: (tmp_path / name).read_text() for name in ("suite.pid", "a.pid")}
    assert pids["suite.pid"] != pids["a.pid"]
    (tmp_path / "failing").mkdir()
    run = _run_probe(tmp_path / "failing", fail=True)
    assert run.returncode == 1
    assert "test_marked_b" in run.stdout and "the marked test failed" in run.stdout
