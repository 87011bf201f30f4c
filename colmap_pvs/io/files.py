"""File utilities: content hashes and atomic writes (temporary file or folder, then rename).

Every output of colmap-pvs is written through a temporary name beside its final path
(:func:`atomic_write_bytes`, :func:`make_temp_dir`), so that an interrupted run never leaves a
half-written file under the final name. Temporary names carry :func:`temp_tag` so that a later run
can tell orphans from files a running process is still writing (:mod:`colmap_pvs.io.cleanup`).

This module depends only on the standard library and :mod:`colmap_pvs.errors`: it is imported by
:mod:`colmap_pvs.config` and by the model package.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import tempfile
from collections.abc import Callable
from pathlib import Path

from ..errors import OutputError

__all__ = [
    "atomic_write_bytes",
    "cached_file_hashes",
    "current_umask",
    "file_sha256",
    "files_state_sha256",
    "host_tag",
    "make_temp_dir",
    "remove_database",
    "temp_tag",
    "write_files_together",
    "write_temp_file",
]


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file, read in chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def files_state_sha256(paths: list[str | Path]) -> str:
    """sha256 of the name, size and modification time of every file under ``paths`` (files or folders,
    recursively; a missing path counts as missing): changes whenever one of them is written, added or
    removed, without reading their content."""
    digest = hashlib.sha256()
    for i, root in enumerate(map(Path, paths)):  # names relative to each path: a moved folder is the same
        found = sorted(root.rglob("*")) if root.is_dir() else [root]
        for path in found:
            name = f"{i}/{path.relative_to(root).as_posix()}"
            try:
                st = path.stat()
            except OSError:
                digest.update(f"{name}\0missing\n".encode())
                continue
            if path.is_file():
                digest.update(f"{name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return digest.hexdigest()


def cached_file_hashes(folder: Path, names: list[str], record: Path) -> dict[str, list]:
    """``{name: [size, mtime_ns, sha256]}`` of the files ``names`` in ``folder``, the hash taken from
    ``record`` (a JSON file of the same form, written by the caller) where a file's size and time are
    unchanged: a resume reads no file again."""
    try:
        known = json.loads(record.read_text())
    except (OSError, ValueError):
        known = {}
    hashes = {}
    for name in names:
        st = (folder / name).stat()
        entry = known.get(name) if isinstance(known, dict) else None
        if not (isinstance(entry, list) and entry[:2] == [st.st_size, st.st_mtime_ns]):
            entry = [st.st_size, st.st_mtime_ns, file_sha256(folder / name)]
        hashes[name] = entry
    return hashes


def remove_database(path: str | Path) -> None:
    """Remove a COLMAP database (SQLite) and its journal files (``-wal``, ``-shm``)."""
    for p in (Path(path), Path(f"{path}-wal"), Path(f"{path}-shm")):
        p.unlink(missing_ok=True)


def current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def host_tag() -> str:
    """8 hex digits identifying this host in temporary file names."""
    return hashlib.sha1(socket.gethostname().encode()).hexdigest()[:8]


def temp_tag() -> str:
    """``pvs-HOST-PID``: marks our temporary files so that a later run can tell orphans (their process is
    gone) from files a running process is still writing (:mod:`colmap_pvs.io.cleanup`)."""
    return f"pvs-{host_tag()}-{os.getpid()}"


def write_temp_file(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to a new temporary file beside ``path`` (usual permissions) and return its path.

    The caller renames it into place (``os.replace``) or removes it.

    Raises:
        OutputError: the folder is not writable or the disk is full (nothing is left behind).
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{temp_tag()}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise OutputError(f"cannot write {str(path)!r}: {exc.strerror or exc}") from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp creates 0600; give the usual permissions
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise OutputError(f"cannot write {str(path)!r}: {exc.strerror or exc}") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return Path(tmp)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder, then rename.

    Raises:
        OutputError: the folder is not writable or the disk is full (nothing is left behind).
    """
    path = Path(path)
    tmp = write_temp_file(path, data)
    try:
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OutputError(f"cannot write {str(path)!r}: {exc.strerror or exc}") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def write_files_together(files: list[tuple[Path, bytes]],
                         before_commit: Callable[[], None] | None = None) -> None:
    """Write every ``(path, data)`` to a temporary file beside its path first (where a full disk or a
    read-only folder fails: the old files stay as they were and nothing is left behind), then call
    ``before_commit`` (to drop what the new files replace) and rename each into place in order, so the
    last one can mark the set done.

    Raises:
        OutputError: a file could not be written or renamed into place.
    """
    staged: list[tuple[Path, Path]] = []
    try:
        for path, data in files:
            staged.append((write_temp_file(path, data), Path(path)))
        if before_commit is not None:
            before_commit()
        while staged:
            tmp, path = staged[0]
            try:
                os.replace(tmp, path)
            except OSError as exc:
                raise OutputError(f"cannot write {str(path)!r}: {exc.strerror or exc}") from None
            staged.pop(0)
    finally:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)


def make_temp_dir(parent: str | os.PathLike, prefix: str, suffix: str = ".tmp") -> Path:
    """A temporary folder inside ``parent`` (to be renamed into place) with the usual permissions.

    ``tempfile.mkdtemp`` creates ``0700`` folders; outputs renamed from it would be private.
    """
    try:
        path = Path(tempfile.mkdtemp(prefix=f"{prefix}{temp_tag()}.", suffix=suffix, dir=parent))
    except OSError as exc:
        raise OutputError(f"cannot create a folder in {str(parent)!r}: {exc.strerror or exc}") from None
    os.chmod(path, 0o777 & ~current_umask())
    return path
