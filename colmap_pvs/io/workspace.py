"""COLMAP dense workspaces: layout, detection, undistortion and the ``stereo/*.cfg`` files.

Layout (what COLMAP's ``image_undistorter`` writes, and what ``patch_match_stereo`` and
``stereo_fusion`` read with ``--workspace_format COLMAP``)::

    root/images/NAME                          undistorted images
    root/sparse/{cameras,images,points3D}.bin pinhole model (``sparse/0`` is accepted too, with a
                                              warning: COLMAP's own tools only read ``sparse/``)
    root/stereo/patch-match.cfg               reference image / source images, pairs of lines
    root/stereo/fusion.cfg                    one image name per line
    root/stereo/colmap_pvs_written.json       sha256 of the .cfg files colmap-pvs wrote (a .cfg
                                              COLMAP or the user wrote is kept as NAME.cfg.bak
                                              when colmap-pvs must replace it)
    root/stereo/depth_maps/NAME.{geometric,photometric}.bin
    root/stereo/normal_maps/NAME.{geometric,photometric}.bin

Maps written into ``stereo/`` are read by COLMAP's fusion with integer pixel centres (pixel
``(col, row)`` is the ray ``K^-1 [col, row, 1]``); see :func:`colmap_pvs.io.maps.fusion_intrinsics`
and ``docs/CONVENTIONS.md``.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Literal

import pycolmap

from ..errors import ConfigError, OutputError, WorkspaceError
from ..types import SparseModel
from .files import atomic_write_bytes, file_sha256, files_state_sha256, make_temp_dir
from .images import check_image_file, read_image_size
from .sparse import find_model_files, read_sparse_model, replace_directory

logger = logging.getLogger(__name__)

__all__ = [
    "fusion_inputs_sha256",
    "CFG_BACKUP_SUFFIX",
    "WRITTEN_RECORD",
    "move_aside",
    "record_written_output",
    "set_aside_foreign_output",
    "MAP_KINDS",
    "SourceSpec",
    "UndistortConfig",
    "Workspace",
    "detect_workspace",
    "load_workspace",
    "read_fusion_cfg",
    "read_patch_match_cfg",
    "undistort",
    "write_cfg_keeping_user_file",
    "write_fusion_cfg",
    "write_patch_match_cfg",
]

#: ``filled``: the geometric pass's dense completion (depth and confidence only; COLMAP never reads it).
MAP_KINDS = ("geometric", "photometric", "filled")


def _check_image_name(name: str) -> str:
    pure = PurePosixPath(name)
    if not name or pure.is_absolute() or ".." in pure.parts or "\\" in name:
        raise ConfigError(f"image name {name!r} must be a relative path inside images/ without '..'")
    return name


@dataclass(frozen=True)
class Workspace:
    """A COLMAP dense workspace rooted at ``root`` (see the module docstring for the layout)."""

    root: Path

    @property
    def images_dir(self) -> Path:
        return self.root / "images"

    @property
    def sparse_dir(self) -> Path:
        """``sparse/`` if it holds a model, else ``sparse/0`` if that does, else ``sparse/``."""
        sparse = self.root / "sparse"
        if find_model_files(sparse)[0] is None and find_model_files(sparse / "0")[0] is not None:
            return sparse / "0"
        return sparse

    @property
    def stereo_dir(self) -> Path:
        return self.root / "stereo"

    @property
    def depth_maps_dir(self) -> Path:
        return self.stereo_dir / "depth_maps"

    @property
    def normal_maps_dir(self) -> Path:
        return self.stereo_dir / "normal_maps"

    @property
    def patch_match_cfg(self) -> Path:
        return self.stereo_dir / "patch-match.cfg"

    @property
    def fusion_cfg(self) -> Path:
        return self.stereo_dir / "fusion.cfg"

    def image_path(self, name: str) -> Path:
        return self.images_dir / _check_image_name(name)

    def _map_path(self, folder: Path, name: str, kind: str) -> Path:
        if kind not in MAP_KINDS:
            raise ConfigError(f"map kind {kind!r} is not one of {list(MAP_KINDS)}")
        return folder / f"{_check_image_name(name)}.{kind}.bin"

    def confidence_map_path(self, name: str, kind: str | None = None) -> Path:
        """``stereo/confidence_maps/NAME.KIND.bin``: colmap-pvs's per-pixel confidence in ``[0, 1]`` of
        the ``kind`` maps (COLMAP ignores this folder); ``kind=None``: ``NAME.bin``, the one confidence
        map of every kind that older workspaces hold (Back-compat (dropped in 0.3): fusion reads it)."""
        if kind is None:
            return self.stereo_dir / "confidence_maps" / f"{_check_image_name(name)}.bin"
        return self._map_path(self.stereo_dir / "confidence_maps", name, kind)

    def depth_map_path(self, name: str, kind: str = "geometric") -> Path:
        """``stereo/depth_maps/NAME.KIND.bin`` with ``kind`` in ``MAP_KINDS``."""
        return self._map_path(self.depth_maps_dir, name, kind)

    def normal_map_path(self, name: str, kind: str = "geometric") -> Path:
        """``stereo/normal_maps/NAME.KIND.bin`` with ``kind`` in ``MAP_KINDS``."""
        return self._map_path(self.normal_maps_dir, name, kind)


def detect_workspace(path: str | os.PathLike, *, create_stereo_dirs: bool = True) -> Workspace:
    """Check that ``path`` is a dense workspace (``images/`` and a sparse model) and return it.

    With ``create_stereo_dirs``, missing ``stereo/depth_maps`` and ``stereo/normal_maps`` are
    created (a read-only workspace is accepted with a warning).

    Raises:
        WorkspaceError: naming everything that is missing.
    """
    root = Path(path)
    if not root.is_dir():
        raise WorkspaceError(f"workspace folder {str(root)!r} does not exist")
    ws = Workspace(root)
    problems = []
    if not ws.images_dir.is_dir():
        problems.append("the images/ folder")
    if not (root / "sparse").is_dir():
        problems.append("the sparse/ folder")
    else:
        ext, missing = find_model_files(ws.sparse_dir)
        if ext is None:
            problems.append(f"sparse model files in {str(ws.sparse_dir)!r} ({', '.join(missing)})")
    if problems:
        raise WorkspaceError(
            f"{str(root)!r} is not a dense workspace: missing {'; '.join(problems)}. "
            "Create one with `colmap-pvs undistort` (or COLMAP's image_undistorter)"
        )
    if ws.sparse_dir != root / "sparse":
        logger.warning(
            "the model is in %s; COLMAP's own stereo_fusion only reads %s", ws.sparse_dir, root / "sparse"
        )
    if create_stereo_dirs:
        try:
            ws.depth_maps_dir.mkdir(parents=True, exist_ok=True)
            ws.normal_maps_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            logger.warning("could not create the stereo folders in %s (%s)", root, exc)
    return ws


def load_workspace(
    path: str | os.PathLike, *, require_pinhole: bool = True, check_image_sizes: bool = False
) -> tuple[Workspace, SparseModel]:
    """:func:`detect_workspace` plus the sparse model, checking that every model image exists.

    Args:
        check_image_sizes: also decode every image and check that its size equals its camera's
            (slower: it reads every image).

    Raises:
        WorkspaceError: missing images (named), size mismatches, or any model problem.
        UnsupportedCameraError: a distorted camera while ``require_pinhole``.
    """
    ws = detect_workspace(path)
    model = read_sparse_model(ws.sparse_dir, require_pinhole=require_pinhole)
    names = sorted(model.image_ids_by_name)
    missing = [n for n in names if not ws.image_path(n).is_file()]
    if missing:
        raise WorkspaceError(
            f"{len(missing)} image(s) of the sparse model are missing from {str(ws.images_dir)!r}: "
            f"{', '.join(missing[:10])}{' ...' if len(missing) > 10 else ''}"
        )
    if check_image_sizes:
        for name in names:
            camera = model.camera_of(model.image_by_name(name))
            size = read_image_size(ws.image_path(name))
            if size != (camera.width, camera.height):
                raise WorkspaceError(
                    f"image {str(ws.image_path(name))!r} is {size[0]}x{size[1]} but its camera "
                    f"{camera.camera_id} is {camera.width}x{camera.height}"
                )
    return ws, model


# --------------------------------------------------------------------------- undistortion


@dataclass(frozen=True)
class UndistortConfig:
    """Undistort a COLMAP sparse model and its images into a new dense workspace."""

    image_path: Path = field(metadata={"help": "folder with the original (distorted) images"})
    input_path: Path = field(metadata={"help": "COLMAP sparse model folder (e.g. sparse/0)"})
    output_path: Path = field(metadata={"help": "new dense workspace folder (must not exist or be empty)"})
    max_image_size: int = field(
        default=-1, metadata={"help": "maximum width/height of the undistorted images; -1 keeps the size"}
    )


def undistort(config: UndistortConfig) -> Workspace:
    """Run COLMAP's image undistorter (``pycolmap.undistort_images``) into ``config.output_path``.

    The workspace is built in a temporary folder next to the output and renamed into place only
    after it was checked (every image written, all cameras pinhole), so a failed run leaves
    nothing behind. Also fine for an all-pinhole input (it then only copies/crops).

    Raises:
        WorkspaceError: bad input model, missing input images, non-empty output or a failed run.
    """
    image_path, output = Path(config.image_path), Path(config.output_path)
    if not image_path.is_dir():
        raise WorkspaceError(f"image folder {str(image_path)!r} does not exist")
    if output.exists() and (not output.is_dir() or any(output.iterdir())):
        raise WorkspaceError(f"output folder {str(output)!r} already exists and is not empty")
    # Distortion is not ignored: the images are undistorted below.
    model = read_sparse_model(config.input_path, require_pinhole=False, warn_distortion=False)
    missing = sorted(n for n in model.image_ids_by_name if not (image_path / n).is_file())
    if missing:
        raise WorkspaceError(
            f"{len(missing)} image(s) of the model are missing from {str(image_path)!r}: "
            f"{', '.join(missing[:10])}"
        )
    # COLMAP's undistorter re-encodes a cut-off photo as a valid image with its missing part black.
    broken = []
    for name in sorted(model.image_ids_by_name):
        try:
            check_image_file(image_path / name)
        except WorkspaceError as exc:
            broken.append(str(exc))
    if broken:
        raise WorkspaceError(f"{len(broken)} image(s) cannot be undistorted: {'; '.join(broken[:5])}")
    output.parent.mkdir(parents=True, exist_ok=True)
    tmp = make_temp_dir(prefix=f".{output.name}.", suffix=".tmp", parent=output.parent)
    try:
        options = pycolmap.UndistortCameraOptions()
        options.max_image_size = int(config.max_image_size)
        try:
            pycolmap.undistort_images(
                str(tmp), str(config.input_path), str(image_path), undistort_options=options
            )
        except Exception as exc:
            raise WorkspaceError(f"undistorting {str(config.input_path)!r} failed: {exc}") from exc
        load_workspace(tmp, require_pinhole=True)
        replace_directory(tmp, output, replaceable=())
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    logger.info("undistorted %d images into %s", len(model.images), output)
    return detect_workspace(output)


# --------------------------------------------------------------------------- stereo/*.cfg


@dataclass(frozen=True)
class SourceSpec:
    """The source-image line of one ``patch-match.cfg`` entry.

    Attributes:
        mode: ``"explicit"`` (a list of names), ``"auto"`` (``__auto__, N``: the ``N`` best views by
            view selection) or ``"all"`` (``__all__``: every other image).
        names: the explicit source names (empty for the other modes).
        num: ``N`` for ``"auto"``, ``len(names)`` for ``"explicit"``, ``0`` for ``"all"``.
    """

    mode: Literal["explicit", "auto", "all"]
    names: tuple[str, ...] = ()
    num: int = 0

    def resolve(
        self,
        reference: str,
        image_names: Sequence[str],
        auto: Callable[[str, int], Sequence[str]] | None = None,
    ) -> list[str]:
        """Source image names for ``reference``.

        Args:
            image_names: every image of the model.
            auto: ``auto(reference, num)`` returns the ``num`` best source views (view selection);
                required for ``mode == "auto"``.

        Raises:
            WorkspaceError: an explicit name that is not in ``image_names``.
        """
        if self.mode == "all":
            return [n for n in image_names if n != reference]
        if self.mode == "auto":
            if auto is None:
                raise ConfigError(
                    f"sources of {reference!r} are '__auto__, {self.num}' but no view selection was given"
                )
            return list(auto(reference, self.num))
        known = set(image_names)
        unknown = [n for n in self.names if n not in known]
        if unknown:
            raise WorkspaceError(
                f"source images {unknown} of reference {reference!r} are not in the sparse model"
            )
        return list(self.names)


def _split_csv(line: str) -> list[str]:
    """COLMAP's ``CSVToVector``: split on ',' and ';', trim, drop empty items."""
    return [item.strip() for item in line.replace(";", ",").split(",") if item.strip()]


def _parse_source_line(items: list[str], reference: str, where: str) -> SourceSpec:
    if items == ["__all__"]:
        return SourceSpec("all")
    if items and items[0] == "__auto__":
        if len(items) != 2 or not items[1].isdigit() or int(items[1]) <= 0:
            raise WorkspaceError(f"{where}: expected '__auto__, N' with N > 0")
        return SourceSpec("auto", (), int(items[1]))
    if not items or any(n in ("__auto__", "__all__") for n in items):
        raise WorkspaceError(f"{where}: expected image names, '__auto__, N' or '__all__'")
    if reference in items:
        raise WorkspaceError(f"{where}: the reference image {reference!r} is listed as its own source")
    if len(set(items)) != len(items):
        raise WorkspaceError(f"{where}: duplicate source images")
    return SourceSpec("explicit", tuple(items), len(items))


def read_patch_match_cfg(path: str | os.PathLike) -> dict[str, SourceSpec]:
    """Parse ``stereo/patch-match.cfg`` as COLMAP does (blank lines and ``#`` comments skipped).

    Returns:
        ``{reference name: SourceSpec}`` in file order. Whether the names exist in the model is
        checked by the caller (:meth:`SourceSpec.resolve`).

    Raises:
        WorkspaceError: missing file, a file without any entry, or a malformed/duplicate entry (naming
            line number and content).
    """
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()  # a BOM (Windows editors) is skipped
    except FileNotFoundError:
        raise WorkspaceError(f"patch-match config {str(path)!r} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise WorkspaceError(f"cannot read patch-match config {str(path)!r}: {exc}") from None
    specs: dict[str, SourceSpec] = {}
    first_line: dict[str, int] = {}
    reference: tuple[int, str] | None = None
    for number, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{path}:{number}: {line!r}"
        if reference is None:
            if "," in line or line in ("__auto__", "__all__"):
                raise WorkspaceError(f"{where}: expected a reference image name")
            if line in specs:
                raise WorkspaceError(
                    f"{where}: reference image listed twice (first on line {first_line[line]})"
                )
            reference = (number, line)
            continue
        specs[reference[1]] = _parse_source_line(_split_csv(line), reference[1], where)
        first_line[reference[1]] = reference[0]
        reference = None
    if reference is not None:
        raise WorkspaceError(f"{path}:{reference[0]}: reference image {reference[1]!r} has no source line")
    if not specs:
        raise WorkspaceError(
            f"patch-match config {str(path)!r} lists no reference image; delete it to use every image, "
            "or run `colmap-pvs select-views`"
        )
    return specs


#: Beside the files colmap-pvs writes under COLMAP's names (``.cfg`` files, ``fused.ply``,
#: ``meshed-poisson.ply``): ``{file name: sha256 of the content we wrote}``, so that a later write can
#: tell our own file (replaced silently) from one COLMAP or the user wrote (kept as a backup). The
#: ``.cfg`` files themselves carry no header: COLMAP's parser has no comments.
WRITTEN_RECORD = "colmap_pvs_written.json"
#: Suffix of the backup of a replaced ``.cfg`` colmap-pvs did not write: ``fusion.cfg.bak``, then
#: ``fusion.cfg.bak.2``, ``fusion.cfg.bak.3``, ... when an earlier backup with other content exists.
CFG_BACKUP_SUFFIX = ".bak"


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _read_written_record(folder: Path) -> dict[str, str]:
    try:
        record = json.loads((folder / WRITTEN_RECORD).read_text())
    except (OSError, ValueError):
        return {}
    return {str(k): str(v) for k, v in record.items()} if isinstance(record, dict) else {}


def cfg_backup_path(path: str | os.PathLike, content: bytes | None = None) -> tuple[Path, bool]:
    """Where the backup of ``path`` holding ``content`` goes: ``(backup, already_there)``.

    An existing backup with the same content is reused (``content=None``: never compared); one with
    other content is never overwritten (the next free numbered name is taken instead).
    """
    path = Path(path)
    number = 1
    while True:
        suffix = CFG_BACKUP_SUFFIX if number == 1 else f"{CFG_BACKUP_SUFFIX}.{number}"
        backup = path.with_name(path.name + suffix)
        if not os.path.lexists(backup):
            return backup, False
        try:
            if content is not None and backup.is_file() and backup.read_bytes() == content:
                return backup, True
        except OSError:
            pass
        number += 1


def write_cfg_keeping_user_file(path: str | os.PathLike, data: bytes) -> Path:
    """Write a COLMAP ``.cfg`` atomically without losing one that COLMAP or the user wrote.

    * the file already holds ``data``: nothing is written;
    * it holds what colmap-pvs last wrote there (its sha256 is in ``WRITTEN_RECORD`` beside it): replaced;
    * it holds anything else (``image_undistorter``'s file, a hand-edited one, or one of an older
      colmap-pvs that kept no record): copied to ``NAME.bak`` first (``NAME.bak.N`` when a different
      ``NAME.bak`` exists), with a warning naming the copy, then replaced.

    The sha256 of ``data`` is recorded in ``WRITTEN_RECORD`` so that a rerun replaces its own file silently.
    """
    path = Path(path)
    if os.path.lexists(path):
        if not path.is_file():
            raise OutputError(f"cannot write {str(path)!r}: it exists and is not a file")
        try:
            old = path.read_bytes()
        except OSError as exc:
            raise OutputError(
                f"cannot read {str(path)!r} before replacing it: {exc.strerror or exc}"
            ) from None
        if old == data:
            return path
        record = _read_written_record(path.parent)
        if record.get(path.name) != _sha256(old):
            backup, already = cfg_backup_path(path, old)
            if not already:
                atomic_write_bytes(backup, old)
            logger.warning(
                "%s was not written by colmap-pvs (COLMAP's or yours): kept it as %s before replacing it",
                path,
                backup,
            )
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, data)
    record = _read_written_record(path.parent)
    record[path.name] = _sha256(data)
    atomic_write_bytes(
        path.parent / WRITTEN_RECORD, (json.dumps(record, indent=2, sort_keys=True) + "\n").encode()
    )
    return path


def set_aside_foreign_output(path: str | os.PathLike) -> Path | None:
    """Before colmap-pvs writes the large output ``path`` (a fused cloud, a mesh): a file there that
    colmap-pvs did not write (its sha256 is not the one recorded in ``WRITTEN_RECORD`` beside it:
    COLMAP's ``stereo_fusion`` output, or the user's) is moved to ``NAME.bak`` (``NAME.bak.N`` when a
    different backup exists), with a warning naming it. Returns the backup, or ``None``."""
    from .files import file_sha256

    path = Path(path)
    if not path.is_file():
        return None
    if _read_written_record(path.parent).get(path.name) == file_sha256(path):
        return None
    backup = move_aside(path)
    logger.warning("%s was not written by colmap-pvs (COLMAP's or yours): moved it to %s", path, backup)
    return backup


def move_aside(path: str | os.PathLike) -> Path:
    """Rename ``path`` to its first free backup name (:func:`cfg_backup_path`); returns the backup."""
    path = Path(path)
    backup, _ = cfg_backup_path(path)
    try:
        os.replace(path, backup)
    except OSError as exc:
        raise OutputError(
            f"cannot move {str(path)!r} aside before replacing it: {exc.strerror or exc}"
        ) from None
    return backup


def record_written_output(*paths: str | os.PathLike) -> None:
    """Record the sha256 of outputs colmap-pvs just wrote (see :func:`set_aside_foreign_output`)."""
    from .files import file_sha256

    for path in map(Path, paths):
        record = _read_written_record(path.parent)
        record[path.name] = file_sha256(path)
        atomic_write_bytes(path.parent / WRITTEN_RECORD,
                           (json.dumps(record, indent=2, sort_keys=True) + "\n").encode())


def _check_cfg_name(name: str, path: Path) -> str:
    if not name or name != name.strip() or any(c in name for c in ",;\n\r") or name.startswith("#"):
        raise ConfigError(
            f"cannot write {str(path)!r}: image name {name!r} cannot be stored in a COLMAP .cfg"
        )
    return name


def write_patch_match_cfg(path: str | os.PathLike, sources: Mapping[str, Iterable[str]]) -> Path:
    """Write ``{reference: [source, ...]}`` as an explicit ``patch-match.cfg``, atomically.

    A ``patch-match.cfg`` that colmap-pvs did not write (``image_undistorter``'s, or the user's) is
    kept beside it first (see :func:`write_cfg_keeping_user_file`).
    """
    path = Path(path)
    lines = []
    for reference, names in sources.items():
        names = [_check_cfg_name(n, path) for n in names]
        if not names:
            raise ConfigError(f"cannot write {str(path)!r}: reference {reference!r} has no source images")
        if reference in names:
            raise ConfigError(
                f"cannot write {str(path)!r}: reference {reference!r} is listed as its own source"
            )
        lines += [_check_cfg_name(reference, path), ", ".join(names)]
    return write_cfg_keeping_user_file(path, ("\n".join(lines) + "\n").encode())


def write_fusion_cfg(path: str | os.PathLike, names: Iterable[str]) -> Path:
    """Write ``fusion.cfg`` (one image name per line: the maps ``stereo_fusion`` fuses), atomically.

    A ``fusion.cfg`` that colmap-pvs did not write is kept beside it first (see
    :func:`write_cfg_keeping_user_file`).
    """
    path = Path(path)
    lines = [_check_cfg_name(n, path) for n in names]
    return write_cfg_keeping_user_file(path, "".join(line + "\n" for line in lines).encode())


def read_fusion_cfg(path: str | os.PathLike) -> list[str]:
    """Image names listed in ``fusion.cfg`` (blank lines skipped)."""
    path = Path(path)
    try:
        return [line.strip() for line in path.read_text(encoding="utf-8-sig").splitlines() if line.strip()]
    except FileNotFoundError:
        raise WorkspaceError(f"fusion config {str(path)!r} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise WorkspaceError(f"cannot read fusion config {str(path)!r}: {exc}") from None


def fusion_inputs_sha256(workspace_path: str | os.PathLike) -> str:
    """What ``fuse`` reads from the workspace: the images, the sparse model and the depth, normal and
    confidence maps by file size and time (:func:`files_state_sha256`), ``stereo/fusion.cfg`` and
    ``patch-match.cfg`` by content. A cloud whose record holds another value was fused from other maps."""
    ws = Workspace(Path(workspace_path))
    files = files_state_sha256([ws.images_dir, ws.sparse_dir, ws.depth_maps_dir, ws.normal_maps_dir,
                                ws.stereo_dir / "confidence_maps"])
    digest = hashlib.sha256(files.encode())
    for cfg in (ws.fusion_cfg, ws.patch_match_cfg):
        digest.update(file_sha256(cfg).encode() if cfg.is_file() else b"none")
    return digest.hexdigest()
