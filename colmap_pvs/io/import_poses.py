"""Known camera poses and intrinsics -> a COLMAP sparse model with triangulated points.

For captures whose cameras are already known (a tracked headset, a calibrated rig, a
benchmark's GT cameras) no SfM is needed: SIFT features are extracted and matched on the
CPU with pycolmap, and points are triangulated with every pose **held fixed**
(``pycolmap.triangulate_points``, COLMAP's ``point_triangulator``). The result is an
ordinary COLMAP model (``cameras/images/points3D.bin``, PINHOLE cameras) for view selection,
depth ranges and ``undistort``.

The focal lengths are refined by default where every camera has at least
:data:`MIN_IMAGES_TO_REFINE_FOCAL` images (``refine_focal_length``: bundle adjustment with the poses,
the principal point and the other intrinsics held fixed, as ``point_triangulator
--refine_intrinsics 1`` with COLMAP's default ``--Mapper.ba_refine_focal_length 1``): with the poses
fixed a focal length that is off by 1 % scales every triangulated depth, and so every dense depth, by
about 1 %. A tracked headset's calibrated focal lengths can be off by that much, and refining them
makes every kind of depth map more accurate (``benchmarks/RESULTS.md``, "``import-poses`` refines the
focal length with the poses fixed"). The change is logged, and warned about above 5 %.

Input formats (``format``):

``hololens``
    a folder with ``K.txt`` (3x3), ``poses.txt`` (one row-major 4x4 **camera-to-world**
    matrix per line) and ``frames.txt`` (image names; line ``i`` belongs to pose ``i``).
``strecha``
    a folder with ``cameras/NAME.camera`` (or the ``cameras`` folder itself), 9 lines each:
    3 lines ``K``, 1 line distortion (must be zero), 3 lines ``R`` (camera-to-world rotation,
    its columns are the camera axes in world coordinates), 1 line camera centre ``C``, 1
    line ``W H``; projection ``x ~ K R^T (X - C)``. ``NAME`` is the image file name.
``json``
    ``{"images": [{"name": ..., "K": 3x3, "cam_from_world": 3x4 or 4x4}, ...]}`` (or the
    bare list); optional ``"width"``/``"height"`` are checked against the image files.
``csv``
    one image per row: ``name, fx, fy, cx, cy, r11, r12, r13, t1, r21, r22, r23, t2, r31,
    r32, r33, t3`` (row-major ``cam_from_world = [R | t]``); a header row and ``#`` comments
    are skipped.

Pixel convention: COLMAP's (pixel ``(c, r)`` has its centre at ``(c + 0.5, r + 0.5)``). A
principal point given in the "centre at 0" convention must be shifted by ``+0.5``:
``principal_point_offset`` does that; by default it is ``0.5`` for ``strecha`` (the Strecha
files, and the downscaling ``c' = (c + 0.5) s - 0.5`` used for ``../shared/data/fountain-P11``,
use the centre-at-0 convention; the shift lowers their median reprojection error:
``benchmarks/RESULTS.md``) and ``0`` for the other formats.

Rotations are re-orthonormalised (nearest rotation, SVD) because text files store them
rounded; the stored pose then differs from the input by the rounding only (~1e-6).

SIFT runs with a lower peak threshold than COLMAP's (``sift_peak_threshold`` 0.002 instead of
0.0067): with the poses known, every extra match that survives triangulation is a depth hint for
the network, and the depth maps improve (``benchmarks/RESULTS.md``, "Stop 25: denser SfM hints").

The settings that shape the model are recorded in ``output_path/import_poses.json``; a rerun reuses
the model only when they match, and otherwise refuses (or, with ``overwrite``, recomputes).
"""

from __future__ import annotations

import csv
import json
import logging
import os
import shutil
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from ..config import check_threads, config_json_bytes, config_to_dict
from ..errors import ConfigError, WorkspaceError
from .features import extract_features, match_features, resolve_matcher
from .files import atomic_write_bytes, make_temp_dir, remove_database
from .images import read_image_size
from .sparse import replace_directory

logger = logging.getLogger(__name__)

#: Written next to the model: the resolved config and the settings the model depends on.
SETTINGS_FILENAME = "import_poses.json"
#: Config fields that do not change the model (everything else does).
_NOT_MODEL_SETTINGS = ("output_path", "num_threads", "overwrite")
#: Fewest images of a camera for ``refine_focal_length`` to move its focal lengths: on fewer frames the
#: refinement fits the noise (``benchmarks/RESULTS.md``, "``import-poses`` refines the focal length").
MIN_IMAGES_TO_REFINE_FOCAL = 10
#: What a record from before a setting existed means for it (the behaviour of that older version).
#: Back-compat (dropped in 0.3): the ``import_poses.json`` beside a user's model may lack them.
_SETTINGS_BEFORE_RECORDED = {"refine_focal_length": False}

__all__ = [
    "ImportPosesConfig",
    "KnownCamera",
    "import_poses",
    "read_known_cameras",
    "reprojection_errors",
]


@dataclass(frozen=True)
class ImportPosesConfig:
    """Settings of ``import-poses`` (the single source of its defaults and CLI flags)."""

    image_path: Path = field(metadata={"help": "folder with the images"})
    poses_path: Path = field(
        metadata={
            "help": "poses: a folder (hololens: K.txt/poses.txt/frames.txt; strecha: cameras/) "
            "or a .json / .csv file"
        }
    )
    output_path: Path = field(
        metadata={"help": "output folder: database.db and the model in sparse/ (cameras/images/points3D.bin)"}
    )
    format: Literal["auto", "hololens", "strecha", "json", "csv"] = field(
        default="auto", metadata={"help": "input format; auto detects it from poses_path"}
    )
    principal_point_offset: float | None = field(
        default=None,
        metadata={
            "help": "added to cx and cy (px) to reach COLMAP's pixel-centre-at-0.5 convention; "
            "default: 0.5 for strecha, 0 otherwise"
        },
    )
    frame_step: int = field(default=1, metadata={"help": "use every N-th image of the input list"})
    max_images: int = field(
        default=0, metadata={"help": "use at most this many images (after frame_step); 0 = all"}
    )
    max_num_features: int = field(default=4096, metadata={"help": "SIFT features per image"})
    sift_peak_threshold: float = field(
        default=0.002,
        metadata={
            "help": "SIFT peak (contrast) threshold; lower finds more keypoints on weak texture "
            "(COLMAP's default is 0.0067)"
        },
    )
    feature_max_image_size: int = field(
        default=1600, metadata={"help": "SIFT runs on images downscaled to this longest side; -1 = full size"}
    )
    matcher: Literal["auto", "exhaustive", "sequential"] = field(
        default="auto", metadata={"help": "pair selection; auto: exhaustive up to 50 images, else sequential"}
    )
    sequential_overlap: int = field(
        default=10, metadata={"help": "sequential matcher: match each image with this many following ones"}
    )
    refine_focal_length: bool = field(
        default=True,
        metadata={
            "help": "refine the focal lengths by bundle adjustment with the poses held fixed (COLMAP's "
            f"point_triangulator --refine_intrinsics), where every camera has {MIN_IMAGES_TO_REFINE_FOCAL} "
            "images or more: a focal length 1 % off biases every depth by about 1 %"
        },
    )
    num_threads: int = field(default=-1, metadata={"help": "CPU threads for SIFT and matching; -1 = all"})
    overwrite: bool = field(
        default=False, metadata={"help": "recompute even if output_path/sparse already holds a model"}
    )

    def __post_init__(self) -> None:
        check_threads("num_threads", self.num_threads, auto=-1)
        if self.frame_step < 1:
            raise ConfigError(f"frame_step must be >= 1, got {self.frame_step}")
        if self.max_images < 0:
            raise ConfigError(f"max_images must be >= 0, got {self.max_images}")
        if self.max_num_features < 16:
            raise ConfigError(f"max_num_features must be >= 16, got {self.max_num_features}")
        if not 0.0 < self.sift_peak_threshold < 1.0:
            raise ConfigError(f"sift_peak_threshold must be in (0, 1), got {self.sift_peak_threshold}")
        if self.sequential_overlap < 1:
            raise ConfigError(f"sequential_overlap must be >= 1, got {self.sequential_overlap}")


@dataclass(frozen=True, eq=False)
class KnownCamera:
    """One image with known calibration.

    Attributes:
        name: image file name relative to the image folder.
        K: ``[3, 3]`` float64 intrinsics in COLMAP's pixel convention (offset already applied).
        cam_from_world: ``[3, 4]`` float64 ``[R | t]``, ``R`` orthonormal.
        size: ``(W, H)`` declared by the input, or ``None``.
    """

    name: str
    K: np.ndarray
    cam_from_world: np.ndarray
    size: tuple[int, int] | None = None


# --------------------------------------------------------------------------- readers


def _nearest_rotation(R: np.ndarray, where: str) -> np.ndarray:
    U, _, Vt = np.linalg.svd(R)
    Rn = U @ Vt
    if np.linalg.det(Rn) < 0:
        raise WorkspaceError(f"{where}: the rotation has determinant {np.linalg.det(R):.3g} (a reflection)")
    err = np.abs(Rn - R).max()
    if err > 1e-2:
        raise WorkspaceError(f"{where}: the 3x3 rotation is not orthonormal (off by {err:.3g})")
    return Rn


def _check_K(K: np.ndarray, where: str) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise WorkspaceError(f"{where}: K must be a finite 3x3 matrix, got {K.tolist()!r}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[0, 1]) > 1e-9 * K[0, 0] or not np.allclose(K[2], [0, 0, 1]):
        raise WorkspaceError(
            f"{where}: K must be [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0, got {K.tolist()}"
        )
    return K


def _pose(cam_from_world: np.ndarray, where: str) -> np.ndarray:
    T = np.asarray(cam_from_world, dtype=np.float64)
    if T.shape == (4, 4):
        if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6):
            raise WorkspaceError(
                f"{where}: the last row of a 4x4 pose must be [0, 0, 0, 1], got {T[3].tolist()}"
            )
        T = T[:3]
    if T.shape != (3, 4) or not np.isfinite(T).all():
        raise WorkspaceError(f"{where}: a pose must be a finite 3x4 or 4x4 matrix, got shape {T.shape}")
    out = T.copy()
    out[:, :3] = _nearest_rotation(T[:, :3], where)
    return out


def _read_matrix(path: Path, shape: tuple[int, ...] | None = None) -> np.ndarray:
    try:
        data = np.loadtxt(path, dtype=np.float64, ndmin=2, encoding="utf-8-sig")
    except FileNotFoundError:
        raise WorkspaceError(f"{str(path)!r} does not exist") from None
    except ValueError as exc:
        raise WorkspaceError(f"{str(path)!r} is not a numeric matrix: {exc}") from None
    if shape is not None and data.shape != shape:
        raise WorkspaceError(f"{str(path)!r} must hold a {shape} matrix, got shape {data.shape}")
    return data


def _read_hololens(folder: Path, offset: float) -> list[KnownCamera]:
    K = _check_K(_read_matrix(folder / "K.txt", (3, 3)), str(folder / "K.txt"))
    K = K.copy()
    K[:2, 2] += offset
    poses = _read_matrix(folder / "poses.txt")
    if poses.shape[1] != 16:
        raise WorkspaceError(
            f"{str(folder / 'poses.txt')!r}: expected 16 numbers per line (a row-major 4x4), "
            f"got {poses.shape[1]}"
        )
    frames_file = folder / "frames.txt"
    if not frames_file.is_file():
        raise WorkspaceError(f"{str(frames_file)!r} does not exist")
    names = [ln.strip() for ln in frames_file.read_text(encoding="utf-8-sig").splitlines() if ln.strip()]
    if len(names) != poses.shape[0]:
        raise WorkspaceError(
            f"{str(frames_file)!r} lists {len(names)} frames but {str(folder / 'poses.txt')!r} has "
            f"{poses.shape[0]} poses"
        )
    out = []
    for i, (name, row) in enumerate(zip(names, poses, strict=True)):
        world_from_cam = row.reshape(4, 4)
        where = f"{folder / 'poses.txt'}:{i + 1} ({name})"
        wfc = _pose(world_from_cam, where)
        R, C = wfc[:, :3], wfc[:, 3]
        out.append(KnownCamera(name, K, np.concatenate([R.T, (-R.T @ C)[:, None]], axis=1)))
    return out


def _read_strecha(folder: Path, offset: float) -> list[KnownCamera]:
    cam_dir = folder / "cameras" if (folder / "cameras").is_dir() else folder
    files = sorted(cam_dir.glob("*.camera"))
    if not files:
        raise WorkspaceError(f"no Strecha *.camera files in {str(cam_dir)!r}")
    out = []
    for path in files:
        rows = [ln.split() for ln in path.read_text(encoding="utf-8-sig").splitlines() if ln.strip()]
        try:
            nums = [[float(v) for v in r] for r in rows]
        except ValueError as exc:
            raise WorkspaceError(f"{str(path)!r}: not a Strecha camera file: {exc}") from None
        if len(nums) != 9 or [len(r) for r in nums] != [3, 3, 3, 3, 3, 3, 3, 3, 2]:
            raise WorkspaceError(
                f"{str(path)!r}: expected 9 lines (3x K, distortion, 3x R, C, 'W H'), got row lengths "
                f"{[len(r) for r in nums]}"
            )
        K = _check_K(np.array(nums[0:3]), str(path)).copy()
        K[:2, 2] += offset
        if any(abs(v) > 1e-12 for v in nums[3]):
            raise WorkspaceError(f"{str(path)!r}: non-zero distortion {nums[3]} is not supported")
        R_wc = _nearest_rotation(np.array(nums[4:7]), str(path))
        C = np.array(nums[7])
        size = (int(nums[8][0]), int(nums[8][1]))
        cfw = np.concatenate([R_wc.T, (-R_wc.T @ C)[:, None]], axis=1)
        out.append(KnownCamera(path.name[: -len(".camera")], K, cfw, size))
    return out


def _read_json(path: Path, offset: float) -> list[KnownCamera]:
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
    except json.JSONDecodeError as exc:
        raise WorkspaceError(f"{str(path)!r} is not valid JSON: {exc}") from None
    entries = data.get("images") if isinstance(data, dict) else data
    if not isinstance(entries, list):
        raise WorkspaceError(f"{str(path)!r}: expected a list of images or {{'images': [...]}}")
    out = []
    for i, e in enumerate(entries):
        where = f"{path}: images[{i}]"
        if not isinstance(e, dict) or not {"name", "K", "cam_from_world"} <= set(e):
            raise WorkspaceError(f"{where}: needs 'name', 'K' and 'cam_from_world'")
        K = _check_K(np.array(e["K"], dtype=np.float64), where).copy()
        K[:2, 2] += offset
        size = (int(e["width"]), int(e["height"])) if "width" in e and "height" in e else None
        out.append(
            KnownCamera(
                str(e["name"]), K, _pose(np.array(e["cam_from_world"], dtype=np.float64), where), size
            )
        )
    return out


def _read_csv(path: Path, offset: float) -> list[KnownCamera]:
    out = []
    with path.open(newline="", encoding="utf-8-sig") as f:
        for line_no, row in enumerate(csv.reader(f), start=1):
            row = [c.strip() for c in row]
            if not row or not row[0] or row[0].startswith("#"):
                continue
            where = f"{path}:{line_no}"
            if len(row) != 17:
                raise WorkspaceError(
                    f"{where}: expected 17 columns (name, fx, fy, cx, cy, 12 pose values), got {len(row)}"
                )
            try:
                vals = np.array([float(v) for v in row[1:]])
            except ValueError:
                if line_no == 1:  # header
                    continue
                raise WorkspaceError(f"{where}: non-numeric value in {row[1:]!r}") from None
            fx, fy, cx, cy = vals[:4]
            K = _check_K(np.array([[fx, 0, cx + offset], [0, fy, cy + offset], [0, 0, 1.0]]), where)
            out.append(KnownCamera(row[0], K, _pose(vals[4:].reshape(3, 4), where)))
    return out


def _detect_format(path: Path) -> str:
    if path.is_file():
        if path.suffix.lower() == ".json":
            return "json"
        if path.suffix.lower() in (".csv", ".txt"):
            return "csv"
    elif path.is_dir():
        if (path / "poses.txt").is_file() and (path / "K.txt").is_file():
            return "hololens"
        if any((path / "cameras").glob("*.camera")) or any(path.glob("*.camera")):
            return "strecha"
    else:
        raise WorkspaceError(f"poses path {str(path)!r} does not exist")
    raise WorkspaceError(
        f"cannot tell the format of {str(path)!r}: expected K.txt+poses.txt+frames.txt, cameras/*.camera, "
        "a .json or a .csv file (or pass --format)"
    )


def read_known_cameras(
    path: str | os.PathLike, format: str = "auto", principal_point_offset: float | None = None
) -> tuple[str, list[KnownCamera]]:
    """Read known cameras in one of the supported formats; returns ``(format, cameras)``."""
    path = Path(path)
    fmt = _detect_format(path) if format == "auto" else format
    offset = (
        principal_point_offset if principal_point_offset is not None else (0.5 if fmt == "strecha" else 0.0)
    )
    readers = {"hololens": _read_hololens, "strecha": _read_strecha, "json": _read_json, "csv": _read_csv}
    if fmt not in readers:
        raise ConfigError(f"unknown poses format {fmt!r}; expected one of {sorted(readers)}")
    cams = readers[fmt](path, float(offset))
    names = [c.name for c in cams]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise WorkspaceError(f"{str(path)!r}: image(s) listed twice: {dup[:5]}")
    if not cams:
        raise WorkspaceError(f"{str(path)!r} lists no cameras")
    return fmt, cams


# --------------------------------------------------------------------------- pipeline


def _camera_groups(cams: list[KnownCamera], sizes: dict[str, tuple[int, int]]) -> list[list[KnownCamera]]:
    """Images sharing exactly the same ``K`` and size share one COLMAP camera."""
    groups: dict[tuple, list[KnownCamera]] = {}
    for c in cams:
        key = (sizes[c.name], tuple(np.round(c.K.ravel(), 9)))
        groups.setdefault(key, []).append(c)
    return list(groups.values())


def reprojection_errors(model_path: str | os.PathLike) -> np.ndarray:
    """Reprojection error (px) of every observation of every 3D point of a COLMAP model, ``[T]``."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(model_path))
    errs = []
    for p in rec.points3D.values():
        for el in p.track.elements:
            im = rec.image(el.image_id)
            proj = im.project_point(p.xyz)
            if proj is not None:
                errs.append(float(np.linalg.norm(np.asarray(proj) - im.points2D[el.point2D_idx].xy)))
    return np.asarray(errs, dtype=np.float64)


def _model_settings(config: ImportPosesConfig) -> dict:
    """The settings the model depends on (paths resolved, so a relative path from elsewhere matches)."""
    values = config_to_dict(config)
    for key in ("image_path", "poses_path"):
        values[key] = str(Path(values[key]).resolve())
    return {k: v for k, v in values.items() if k not in _NOT_MODEL_SETTINGS}


def _check_recorded_settings(config: ImportPosesConfig, out: Path) -> None:
    """Refuse to reuse a model made with other settings (a model without a record is reused, logged)."""
    path = out / SETTINGS_FILENAME
    try:
        recorded = json.loads(path.read_text()).get("model_settings")
    except FileNotFoundError:
        logger.warning("import-poses: %s has no record of its settings; reusing the model as it is", out)
        return
    except (json.JSONDecodeError, AttributeError):
        raise WorkspaceError(f"settings record {str(path)!r} is unreadable; pass --overwrite true") from None
    if not isinstance(recorded, dict):
        raise WorkspaceError(f"settings record {str(path)!r} has no 'model_settings'; pass --overwrite true")
    current = _model_settings(config)
    recorded = {**_SETTINGS_BEFORE_RECORDED, **recorded}
    changed = [f"{k} {recorded.get(k)!r} -> {v!r}" for k, v in current.items() if recorded.get(k) != v]
    if changed:
        raise ConfigError(
            f"the model in {str(out / 'sparse')!r} was made with other settings: {'; '.join(changed)}; pass "
            "--overwrite true to recompute it, or use another --output_path"
        )


def _enough_images_to_refine(db_images) -> bool:
    """Whether every camera has :data:`MIN_IMAGES_TO_REFINE_FOCAL` images (else one line says why not)."""
    counts = Counter(im.camera_id for im in db_images)
    few = {cid: n for cid, n in counts.items() if n < MIN_IMAGES_TO_REFINE_FOCAL}
    if few:
        cid, n = min(few.items(), key=lambda item: item[1])
        # where other cameras could have been refined, the user may want to know why none was
        level = logging.WARNING if len(few) < len(counts) else logging.INFO
        logger.log(level, "import-poses: focal lengths kept as given: camera %d has %d image(s), the "
                   "refinement needs %d per camera", cid, n, MIN_IMAGES_TO_REFINE_FOCAL)
    return not few


def _log_focal_changes(given: dict[int, np.ndarray], refined) -> None:
    """Log how far the bundle adjustment moved each camera's focal lengths ``given`` (``{camera id: [fx,
    fy]}``) in ``refined``; a warning above 5 %."""
    for camera_id, cam in refined.cameras.items():
        before = given[camera_id]
        after = np.asarray(cam.params[:2], dtype=np.float64)
        change = 100.0 * (after / before - 1.0)
        level = logging.WARNING if np.abs(change).max() > 5.0 else logging.INFO
        logger.log(level, "import-poses: camera %d focal length refined from %.2f, %.2f to %.2f, %.2f px "
                   "(%+.2f %%, %+.2f %%)%s", camera_id, *before, *after, *change,
                   "; check the calibration" if level == logging.WARNING else "")


def import_poses(config: ImportPosesConfig) -> Path:
    """Build a COLMAP model from known poses; returns the model folder (``output_path/sparse``).

    Steps: read the cameras, check that every image exists (and its size where declared),
    extract SIFT (one COLMAP camera per distinct ``K``/size, PINHOLE), match (exhaustive or
    sequential), triangulate with the poses fixed, refining the focal lengths (``refine_focal_length``,
    where every camera has :data:`MIN_IMAGES_TO_REFINE_FOCAL` images).
    Resumable: an existing model in ``output_path/sparse`` made with the same settings
    (``output_path/import_poses.json``) is returned unless ``overwrite``. The model is written to a
    temporary folder and renamed into place.

    Raises:
        WorkspaceError: malformed pose files, missing images, size mismatches, or no points.
        ConfigError: ``output_path`` holds a model made with other settings (and not ``overwrite``).
    """
    import pycolmap

    image_dir = Path(config.image_path)
    out = Path(config.output_path)
    model_dir = out / "sparse"
    final_db, db_path = out / "database.db", out / "database.db.new"  # the new one replaces the old
    remove_database(db_path)  # what a killed run left
    if not config.overwrite and all(
        (model_dir / f"{n}.bin").is_file() for n in ("cameras", "images", "points3D")
    ):
        _check_recorded_settings(config, out)
        logger.info("import-poses: %s already holds a model (use --overwrite true to recompute)", model_dir)
        return model_dir
    if not image_dir.is_dir():
        raise WorkspaceError(f"image folder {str(image_dir)!r} does not exist")
    fmt, cams = read_known_cameras(config.poses_path, config.format, config.principal_point_offset)
    cams = cams[:: config.frame_step]
    if config.max_images:
        cams = cams[: config.max_images]
    missing = [c.name for c in cams if not (image_dir / c.name).is_file()]
    if missing:
        raise WorkspaceError(
            f"{len(missing)} image(s) listed in {str(config.poses_path)!r} are missing from "
            f"{str(image_dir)!r}: "
            f"{', '.join(missing[:5])}"
        )
    sizes = {}
    for c in cams:
        sizes[c.name] = read_image_size(image_dir / c.name)
        if c.size is not None and c.size != sizes[c.name]:
            raise WorkspaceError(
                f"image {str(image_dir / c.name)!r} is {sizes[c.name][0]}x{sizes[c.name][1]} but its camera "
                f"declares {c.size[0]}x{c.size[1]}"
            )
    logger.info("import-poses: %d images (%s format) from %s", len(cams), fmt, config.poses_path)
    out.mkdir(parents=True, exist_ok=True)
    # The old model, its record and database stay until the new ones are complete (a failure, a full
    # disk, keeps them as they were): the new database is built beside the old one.
    try:
        t0 = time.perf_counter()
        groups = _camera_groups(cams, sizes)
        for group in groups:
            K = group[0].K
            extract_features(
                db_path,
                image_dir,
                [c.name for c in group],
                camera_model="PINHOLE",
                camera_params=(K[0, 0], K[1, 1], K[0, 2], K[1, 2]),
                single_camera=True,
                num_threads=config.num_threads,
                max_image_size=config.feature_max_image_size,
                max_num_features=config.max_num_features,
                peak_threshold=config.sift_peak_threshold,
            )
        t1 = time.perf_counter()
        logger.info("import-poses: SIFT on %d images (%d camera(s)) in %.1f s", len(cams), len(groups),
                    t1 - t0)

        matcher = resolve_matcher(config.matcher, len(cams), 50)
        match_features(
            db_path,
            matcher,
            num_images=len(cams),
            num_threads=config.num_threads,
            sequential_overlap=config.sequential_overlap,
        )
        t2 = time.perf_counter()
        logger.info("import-poses: %s matching in %.1f s", matcher, t2 - t1)

        by_name = {c.name: c for c in cams}
        rec = pycolmap.Reconstruction()
        with pycolmap.Database.open(str(db_path)) as db:
            db_images = db.read_all_images()
            added_cams = set()
            for im in db_images:
                c = by_name.get(im.name)
                if c is None:
                    raise WorkspaceError(f"database image {im.name!r} has no known pose")
                cam = db.read_camera(im.camera_id)
                want = [c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]]
                if cam.model_name != "PINHOLE" or not np.allclose(cam.params, want, rtol=0, atol=1e-9):
                    cam.model = pycolmap.CameraModelId.PINHOLE
                    cam.params = want
                    db.update_camera(cam)
                if im.camera_id not in added_cams:
                    rec.add_camera_with_trivial_rig(cam)
                    added_cams.add(im.camera_id)
                image = pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=im.image_id)
                rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(c.cam_from_world))
        if len(db_images) != len(cams):
            raise WorkspaceError(
                f"feature extraction stored {len(db_images)} of {len(cams)} images in {db_path}")

        tmp = make_temp_dir(prefix=".sparse.", suffix=".tmp", parent=out)
        try:
            given = {i: np.array(c.params[:2], dtype=np.float64) for i, c in rec.cameras.items()}
            refine = config.refine_focal_length and _enough_images_to_refine(db_images)
            options = pycolmap.IncrementalPipelineOptions()
            options.ba_refine_focal_length = refine
            options.ba_refine_principal_point = False
            options.ba_refine_extra_params = False
            result = pycolmap.triangulate_points(rec, str(db_path), str(image_dir), str(tmp), options=options,
                                                 refine_intrinsics=refine)
            if result.num_points3D() == 0:
                raise WorkspaceError(
                    f"no points could be triangulated from {len(cams)} images: too few matches (check the "
                    "poses, the image overlap or --max_num_features)"
                )
            result.write(str(tmp))
            (out / SETTINGS_FILENAME).unlink(missing_ok=True)  # written again below, for the new model
            replace_directory(tmp, model_dir)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    except BaseException:
        remove_database(db_path)
        raise
    for journal in (f"{final_db}-wal", f"{final_db}-shm"):  # the old database's; os.replace swaps the file
        Path(journal).unlink(missing_ok=True)
    os.replace(db_path, final_db)
    atomic_write_bytes(out / SETTINGS_FILENAME, config_json_bytes(
        config, model_settings=_model_settings(config), focal_lengths_refined=refine))
    if refine:
        _log_focal_changes(given, result)
    t3 = time.perf_counter()
    errs = reprojection_errors(model_dir)
    logger.info(
        "import-poses: %d points, %d observations, median reprojection error %.3f px (triangulation %.1f s); "
        "model in %s",
        result.num_points3D(),
        errs.size,
        float(np.median(errs)) if errs.size else float("nan"),
        t3 - t2,
        model_dir,
    )
    return model_dir
