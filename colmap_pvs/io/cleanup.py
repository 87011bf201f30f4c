"""Removing the temporary files and folders that a killed run left behind.

Every temporary output of colmap-pvs is named ``.NAME.pvs-HOST-PID.XXXXXXXX.tmp``
(:func:`colmap_pvs.io.files.temp_tag`: ``HOST`` a hash of the host name, ``PID`` the writing
process). One is an *orphan*, and is removed, when its process no longer runs on this host, or when
it is older than ``max_age_s`` (a process on another host sharing the folder, e.g. a Ray worker,
is never interrupted: its files are only removed once they are that old). Untagged temporaries of
older versions (``.NAME.XXXXXXXX.tmp``) are removed once older than ``max_age_s`` too
(:data:`_UNTAGGED`). Backups of
replaced folders (``.NAME.old.*``) are never touched.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import time
from pathlib import Path

from .files import host_tag

logger = logging.getLogger(__name__)

__all__ = ["remove_orphan_temps"]

_TAGGED = re.compile(r"^\..+\.pvs-(?P<host>[0-9a-f]{8})-(?P<pid>\d+)\.[A-Za-z0-9_]+\.tmp$")
#: A temporary of an older colmap-pvs, before they were tagged. Back-compat (dropped in 0.3): a killed
#: run of that version may have left them in a user's workspace.
_UNTAGGED = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.tmp$")
DEFAULT_MAX_AGE_S = 24 * 3600.0


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    except OSError:
        return False
    return True


def _is_orphan(entry: os.DirEntry, host: str, now: float, max_age_s: float) -> bool:
    if ".old." in entry.name:
        return False
    try:
        age = now - entry.stat(follow_symlinks=False).st_mtime
    except OSError:
        return False
    match = _TAGGED.match(entry.name)
    if match is not None:
        if match["host"] == host and int(match["pid"]) != os.getpid() and not _alive(int(match["pid"])):
            return True
        return age > max_age_s
    return _UNTAGGED.match(entry.name) is not None and age > max_age_s


def remove_orphan_temps(
    folder: str | os.PathLike, *, recursive: bool = False, max_age_s: float = DEFAULT_MAX_AGE_S
) -> list[Path]:
    """Remove orphaned temporary files / folders in ``folder`` (see the module docstring).

    Returns the removed paths (logged at INFO). A missing or unreadable folder is not an error.
    """
    host = host_tag()
    now = time.time()
    removed: list[Path] = []
    stack = [Path(folder)]
    while stack:
        current = stack.pop()
        try:
            entries = list(os.scandir(current))
        except OSError:
            continue
        for entry in entries:
            if _is_orphan(entry, host, now, max_age_s):
                try:
                    if entry.is_dir(follow_symlinks=False):
                        shutil.rmtree(entry.path)
                    else:
                        os.unlink(entry.path)
                except OSError as exc:
                    logger.warning("could not remove the orphaned temporary %s: %s", entry.path, exc)
                    continue
                removed.append(Path(entry.path))
            elif recursive and entry.is_dir(follow_symlinks=False) and not entry.name.startswith("."):
                stack.append(Path(entry.path))
    if removed:
        logger.info("removed %d orphaned temporary file(s) of an interrupted run in %s", len(removed), folder)
    return removed
