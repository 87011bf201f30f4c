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
