"""pycolmap's own log and progress: its log to a file in the workspace, tqdm bars for SfM stages.

pycolmap logs through glog, to the terminal by default (``reconstruct`` printed ~230 lines). Inside
:func:`pycolmap_log_to_file` its messages go to ``FOLDER/pycolmap.log.DATE-TIME.PID`` instead (errors
still reach the terminal). The long pycolmap calls (feature extraction, matching) get a
:class:`DatabaseProgress` bar: elapsed time while they run, the count of rows they wrote to COLMAP's
database once they return (the database is never read while COLMAP writes it).
"""

from __future__ import annotations

import contextlib
import logging
import os
import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path

import pycolmap
from tqdm import tqdm

logger = logging.getLogger(__name__)

__all__ = ["DatabaseProgress", "pycolmap_log_to_file"]

LOG_PREFIX = "pycolmap.log."


@contextlib.contextmanager
def pycolmap_log_to_file(folder: str | os.PathLike, *, enabled: bool = True) -> Iterator[Path | None]:
    """Send pycolmap's log to ``folder/pycolmap.log.*`` while inside; yields the folder (or ``None``).

    ``enabled=False`` leaves pycolmap logging to the terminal (``--log_level DEBUG``).
    """
    if not enabled:
        yield None
        return
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    log = pycolmap.logging
    saved = (log.alsologtostderr, log.logtostderr, log.stderrthreshold)
    log.alsologtostderr = False
    log.logtostderr = False
    log.stderrthreshold = 2  # errors still reach the terminal
    log.set_log_destination(log.INFO, str(folder / LOG_PREFIX))  # the INFO file holds every severity
    for level in (log.WARNING, log.ERROR, log.FATAL):
        log.set_log_destination(level, "")  # no extra per-severity files (glog would put them in /tmp)
    try:
        yield folder
    finally:
        log.set_log_destination(log.INFO, "")  # closes (and flushes) the file
        log.alsologtostderr, log.logtostderr, log.stderrthreshold = saved


class DatabaseProgress:
    """A tqdm bar for the pycolmap call that fills ``table`` of a COLMAP database.

    Use as a context manager around that call. While it runs, a thread only refreshes the bar
    (elapsed time); the count (``SELECT COUNT(*) FROM table``) is read once the call returned.
    Reading the database while COLMAP writes it is not safe: a reader's lock made COLMAP abort
    with "SQLite error: database is locked" (seen on a loaded 2-core machine).
    """

    def __init__(self, database: str | os.PathLike, table: str, total: int, desc: str, unit: str,
                 interval_s: float = 0.5) -> None:
        self.database = Path(database)
        self.query = f"SELECT COUNT(*) FROM {table}"
        self.bar = tqdm(total=total, desc=desc, unit=unit)
        self.interval_s = interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)

    def count(self) -> int | None:
        if not self.database.is_file():
            return None
        try:
            with contextlib.closing(
                sqlite3.connect(f"file:{self.database}?mode=ro", uri=True, timeout=0.2)
            ) as db:
                return int(db.execute(self.query).fetchone()[0])
        except sqlite3.Error:  # not created yet, or busy: try again later
            return None

    def _update(self) -> None:
        n = self.count()
        if n is not None:
            self.bar.n = min(n, self.bar.total)
            self.bar.refresh()

    def _poll(self) -> None:
        while not self._stop.wait(self.interval_s):
            self.bar.refresh()  # never touch the database while COLMAP writes it

    def __enter__(self) -> DatabaseProgress:
        self._thread.start()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self._stop.set()
        self._thread.join()
        if exc_type is None:
            self._update()
        self.bar.close()
