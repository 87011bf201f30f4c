"""Reading and writing COLMAP sparse models as plain numpy dataclasses (:mod:`colmap_pvs.types`).

This module (with :mod:`colmap_pvs.io.workspace`) is the only place that touches pycolmap's
scene API. Only registered images are returned; tracks only reference those images.
"""

from __future__ import annotations

import functools
import logging
import os
import shutil
import struct
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import pycolmap

from ..errors import UnsupportedCameraError, WorkspaceError
from ..types import PINHOLE_MODELS, Camera, Image, Points3D, SparseModel
from .files import make_temp_dir

logger = logging.getLogger(__name__)

__all__ = [
    "read_sparse_model", "write_sparse_model", "find_model_files", "image_indices", "images_bin_order",
    "MODEL_FILE_STEMS",
]

MODEL_FILE_STEMS = ("cameras", "images", "points3D")
# Files that pycolmap >= 3.12 writes next to the three classic ones.
_EXTRA_MODEL_STEMS = ("rigs", "frames")


def find_model_files(path: Path) -> tuple[str | None, list[str]]:
    """Which COLMAP model format ``path`` holds.

    Returns:
        ``(ext, missing)``: ``ext`` is ``".bin"`` or ``".txt"`` when all of cameras/images/points3D
        exist in that format (binary preferred), else ``None`` and ``missing`` names the missing
        binary files (or the missing text files when the text model is the more complete one).
    """
    missing_by_ext = {}
    for ext in (".bin", ".txt"):
        missing = [stem + ext for stem in MODEL_FILE_STEMS if not (path / (stem + ext)).is_file()]
        if not missing:
            return ext, []
        missing_by_ext[ext] = missing
    best = min(missing_by_ext, key=lambda e: (len(missing_by_ext[e]), e != ".bin"))
    return None, missing_by_ext[best]


# --------------------------------------------------------------------------- reading


def _camera_matrix(camera: pycolmap.Camera, model: str, params: np.ndarray) -> np.ndarray:
    if model == "SIMPLE_PINHOLE":
        f, cx, cy = params
        return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    if model == "PINHOLE":
        fx, fy, cx, cy = params
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return np.asarray(camera.calibration_matrix(), dtype=np.float64)


def _model_file(path: Path, stem: str) -> str:
    """``path/stem.bin`` (or ``.txt`` when only the text model exists), for error messages."""
    ext = find_model_files(path)[0] or ".bin"
    return str(path / f"{stem}{ext}")


def _check_camera(camera: pycolmap.Camera, path: Path) -> None:
    """Refuse cameras that no projection can use: sizes <= 0, non-finite parameters, focal <= 0."""
    where = f"{_model_file(path, 'cameras')!r}: camera {camera.camera_id} ({camera.model.name})"
    if camera.width <= 0 or camera.height <= 0:
        raise WorkspaceError(f"{where} has the size {camera.width}x{camera.height}")
    params = np.asarray(camera.params, dtype=np.float64)
    for k in camera.focal_length_idxs():
        if not (np.isfinite(params[k]) and params[k] > 0):
            raise WorkspaceError(f"{where} has a non-positive or non-finite focal length {params[k]}")
    if not np.isfinite(params).all():
        raise WorkspaceError(f"{where} has non-finite parameters {params.tolist()}")


def _checked_pose(image, path: Path) -> np.ndarray:
    """``[3, 4]`` cam_from_world of a pycolmap image; refuses NaN / zero quaternions and translations."""
    pose = image.cam_from_world()
    quat = np.asarray(pose.rotation.quat, dtype=np.float64)  # x, y, z, w
    t = np.asarray(pose.translation, dtype=np.float64)
    matrix = np.asarray(pose.matrix(), dtype=np.float64)[:3, :4]
    R = matrix[:, :3]
    ok = np.isfinite(quat).all() and np.isfinite(matrix).all() and np.linalg.norm(quat) > 1e-12
    if ok:
        ok = bool(np.abs(R @ R.T - np.eye(3)).max() < 1e-6)
    if not ok:
        raise WorkspaceError(
            f"{_model_file(path, 'images')!r}: image {str(image.name)!r} (id {image.image_id}) has an "
            f"invalid pose: quaternion (w, x, y, z) {[quat[3], *quat[:3]]}, translation {t.tolist()}"
        )
    return matrix.copy()


def _convert_camera(
    camera: pycolmap.Camera, path: Path, require_pinhole: bool, warn_distortion: bool = True
) -> Camera:
    _check_camera(camera, path)
    model = camera.model.name
    if model not in PINHOLE_MODELS:
        if require_pinhole:
            raise UnsupportedCameraError(
                f"camera {camera.camera_id} in {str(path)!r} uses the {model} model, which has lens "
                f"distortion; only {' and '.join(PINHOLE_MODELS)} are supported. Undistort the images first "
                "with `colmap-pvs undistort` (or COLMAP's `colmap image_undistorter`)"
            )
        if warn_distortion:
            logger.debug("camera %d in %s is %s; its distortion is ignored", camera.camera_id, path, model)
    params = np.asarray(camera.params, dtype=np.float64).copy()
    return Camera(
        camera_id=int(camera.camera_id),
        model=model,
        width=int(camera.width),
        height=int(camera.height),
        K=_camera_matrix(camera, model, params),
        params=params,
    )


def _convert_points(
    rec: pycolmap.Reconstruction, registered: set[int], path: Path | None = None
) -> Points3D:
    ids, xyz, rgb, error, lengths, track_ids = [], [], [], [], [], []
    non_finite = 0
    for point_id in sorted(rec.points3D):
        point = rec.points3D[point_id]
        track = [el.image_id for el in point.track.elements if el.image_id in registered]
        if not track:
            continue
        if not np.isfinite(point.xyz).all():
            non_finite += 1
            continue
        ids.append(point_id)
        xyz.append(point.xyz)
        rgb.append(point.color)
        error.append(point.error)
        lengths.append(len(track))
        track_ids.extend(track)
    if non_finite:
        where = _model_file(path, "points3D") if path is not None else "the sparse model"
        logger.warning("%d sparse point(s) with non-finite coordinates in %s are ignored", non_finite, where)
    offsets = np.zeros(len(ids) + 1, dtype=np.int64)
    np.cumsum(lengths, out=offsets[1:])
    return Points3D(
        ids=np.asarray(ids, dtype=np.int64),
        xyz=np.asarray(xyz, dtype=np.float64).reshape(-1, 3),
        rgb=np.asarray(rgb, dtype=np.uint8).reshape(-1, 3),
        error=np.asarray(error, dtype=np.float64),
        track_offsets=offsets,
        track_image_ids=np.asarray(track_ids, dtype=np.int64),
    )


def _point_ids_per_image(points: Points3D) -> dict[int, np.ndarray]:
    """Sorted unique point ids observed by each image id (inverse of the CSR tracks)."""
    rows = np.repeat(np.arange(len(points)), np.diff(points.track_offsets))
    image_ids = points.track_image_ids
    order = np.lexsort((points.ids[rows], image_ids))
    image_ids, point_ids = image_ids[order], points.ids[rows][order]
    result: dict[int, np.ndarray] = {}
    starts = np.flatnonzero(np.r_[True, image_ids[1:] != image_ids[:-1]]) if image_ids.size else []
    bounds = list(starts) + [image_ids.size]
    for begin, end in zip(bounds[:-1], bounds[1:], strict=False):
        result[int(image_ids[begin])] = np.unique(point_ids[begin:end])
    return result


@functools.cache
def _num_camera_params(model_id: int) -> int:
    try:
        model = pycolmap.CameraModelId(model_id)
        return len(pycolmap.Camera.create_from_model_id(0, model, 1.0, 1, 1).params)
    except Exception:
        return -1


def _walk_records(data: bytes, record_size: Callable[[int], int]) -> str | None:
    """Check ``uint64 count`` + ``count`` records; ``record_size(offset)`` is -1 for a bad record."""
    if len(data) < 8:
        return f"{len(data)} bytes, too short for the record count"
    (count,) = struct.unpack_from("<Q", data, 0)
    offset = 8
    for index in range(count):
        size = record_size(offset) if offset < len(data) else -1
        if size < 0 or offset + size > len(data):
            return f"record {index} of {count} is truncated or corrupt at byte {offset} of {len(data)}"
        offset += size
    if offset != len(data):
        return f"{len(data) - offset} unexpected trailing bytes after {count} records"
    return None


def _image_record_size(data: bytes, offset: int) -> int:
    """Bytes of the ``images.bin`` record at ``offset`` (id, quaternion, translation, camera id, name,
    2D points), -1 where it is cut short."""
    name_end = data.find(b"\0", offset + 64)
    if name_end < 0 or name_end + 9 > len(data):
        return -1
    return name_end + 9 - offset + 24 * struct.unpack_from("<Q", data, name_end + 1)[0]


def _check_binary_model(path: Path) -> None:
    """Validate the record structure of a binary model before pycolmap reads it.

    pycolmap does not check for truncation: a truncated ``points3D.bin`` can make it loop for
    minutes on a garbage track length, and a truncated ``cameras.bin`` may be read silently.
    """

    def camera_size(data: bytes, offset: int) -> int:
        if offset + 24 > len(data):
            return -1
        n_params = _num_camera_params(struct.unpack_from("<i", data, offset + 4)[0])
        return 24 + 8 * n_params if n_params >= 0 else -1

    def point_size(data: bytes, offset: int) -> int:
        if offset + 51 > len(data):
            return -1
        return 51 + 8 * struct.unpack_from("<Q", data, offset + 43)[0]

    for stem, size_fn in (("cameras", camera_size), ("images", _image_record_size), ("points3D", point_size)):
        file = path / f"{stem}.bin"
        data = file.read_bytes()
        problem = _walk_records(data, lambda offset, d=data, f=size_fn: f(d, offset))
        if problem:
            raise WorkspaceError(
                f"could not read the sparse model in {str(path)!r}: {file.name} is corrupt: {problem}"
            )


def _read_reconstruction(path: Path) -> pycolmap.Reconstruction:
    if not path.is_dir():
        raise WorkspaceError(f"sparse model folder {str(path)!r} does not exist")
    ext, missing = find_model_files(path)
    if ext is None:
        raise WorkspaceError(f"sparse model folder {str(path)!r} is incomplete: missing {', '.join(missing)}")
    if ext == ".bin":
        _check_binary_model(path)
    rec = pycolmap.Reconstruction()
    try:
        rec.read(str(path))
    except Exception as exc:  # pycolmap raises ValueError/RuntimeError for corrupt files
        raise WorkspaceError(f"could not read the sparse model in {str(path)!r} (corrupt?): {exc}") from exc
    return rec


def read_sparse_model(
    path: str | os.PathLike, *, require_pinhole: bool = True, warn_distortion: bool = True
) -> SparseModel:
    """Read a binary or text COLMAP model folder.

    Args:
        path: folder with ``cameras``, ``images`` and ``points3D`` (``.bin`` preferred over ``.txt``).
        require_pinhole: raise :class:`UnsupportedCameraError` for a registered image whose camera is
            not SIMPLE_PINHOLE/PINHOLE (distortion is never dropped silently).
        warn_distortion: with ``require_pinhole=False``, warn that a distorted camera's distortion is
            ignored; callers that undistort the images themselves pass ``False``.

    Returns:
        the model with the registered images, the cameras they use, and the points observed by
        them (``Image.point3D_ids`` is derived from the tracks, so it only names existing points).

    Raises:
        WorkspaceError: missing folder or files, unreadable/corrupt files, or no registered images.
    """
    path = Path(path)
    rec = _read_reconstruction(path)
    registered = sorted(int(i) for i in rec.reg_image_ids())
    if not registered:
        raise WorkspaceError(f"sparse model {str(path)!r} is empty: it has no registered images")
    camera_ids = sorted({int(rec.images[i].camera_id) for i in registered})
    cameras = {
        cid: _convert_camera(rec.cameras[cid], path, require_pinhole, warn_distortion) for cid in camera_ids
    }
    distorted = sorted({c.model for c in cameras.values() if c.model not in PINHOLE_MODELS})
    if warn_distortion and distorted:  # one line, not one per camera; each camera at DEBUG
        n = sum(c.model not in PINHOLE_MODELS for c in cameras.values())
        logger.warning(
            "%d of %d camera(s) in %s are %s; their distortion is ignored",
            n, len(cameras), path, ", ".join(distorted),
        )
    points = _convert_points(rec, set(registered), path)
    observed = _point_ids_per_image(points)
    images: dict[int, Image] = {}
    for image_id in registered:
        image = rec.images[image_id]
        images[image_id] = Image(
            image_id=image_id,
            name=str(image.name),
            camera_id=int(image.camera_id),
            cam_from_world=_checked_pose(image, path),
            point3D_ids=observed.get(image_id, np.zeros(0, dtype=np.int64)),
        )
    logger.info("read %d images, %d cameras, %d points from %s", len(images), len(cameras), len(points), path)
    return SparseModel(
        cameras=cameras,
        images=images,
        points=points,
        image_ids_by_name={im.name: im.image_id for im in images.values()},
    )


def images_bin_order(path: str | os.PathLike) -> list[int] | None:
    """Image ids in the order a binary ``images.bin`` stores them; ``None`` where the file cannot be
    read or is corrupt.

    Read by hand: pycolmap's ``Reconstruction`` keeps its images in a map keyed by id and does not
    tell the order of the file, which COLMAP <= 3.9 used to number images (see :func:`image_indices`).
    """
    try:
        data = Path(path).read_bytes()
    except OSError:
        return None
    ids: list[int] = []

    def record_size(offset: int) -> int:
        size = _image_record_size(data, offset)
        if size >= 0:
            ids.append(struct.unpack_from("<I", data, offset)[0])
        return size

    return None if _walk_records(data, record_size) else ids


def image_indices(sparse_dir: str | os.PathLike, model: SparseModel) -> dict[str, int]:
    """``{name: index}`` as COLMAP's ``mvs::Model`` numbers images (``.vis`` files use it).

    COLMAP (pycolmap 4.x) numbers the registered images in ascending image-id order. COLMAP <= 3.9
    used the order of ``images.bin``; we warn when the two differ.
    """
    ids = sorted(model.images)
    index = {model.images[i].name: k for k, i in enumerate(ids)}
    bin_path = Path(sparse_dir) / "images.bin"
    order = images_bin_order(bin_path) if bin_path.is_file() else None
    if order is not None:
        reg = [i for i in order if i in model.images]
        if reg != ids:
            logger.warning(
                "%s lists images out of id order: COLMAP <= 3.9 tools will misread the .vis image indices",
                bin_path,
            )
    return index


# --------------------------------------------------------------------------- writing


def _project(xyz: np.ndarray, image: Image, camera: Camera) -> np.ndarray:
    """Pixel coordinates ``[M, 2]`` of world points ``[M, 3]`` (COLMAP convention, no distortion)."""
    cam = xyz @ image.R.T + image.t
    if cam.size and (cam[:, 2] <= 0).any():
        raise WorkspaceError(
            f"cannot write the model: {int((cam[:, 2] <= 0).sum())} points in the track of image "
            f"{image.name!r} (id {image.image_id}) are behind its camera"
        )
    uvw = cam @ camera.K.T
    return uvw[:, :2] / uvw[:, 2:3]


def _build_reconstruction(model: SparseModel) -> pycolmap.Reconstruction:
    rec = pycolmap.Reconstruction()
    for cam in model.cameras.values():
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(
                camera_id=cam.camera_id,
                model=cam.model,
                width=cam.width,
                height=cam.height,
                params=cam.params,
            )
        )
    points = model.points
    rows = np.repeat(np.arange(len(points)), np.diff(points.track_offsets))
    # point2D index of every track entry inside its image's keypoint list
    point2d_idx = np.zeros(rows.size, dtype=np.int64)
    for image_id, image in model.images.items():
        if image.camera_id not in model.cameras:
            raise WorkspaceError(
                f"image {image.name!r} refers to camera {image.camera_id}, which is not in the model"
            )
        entries = np.flatnonzero(points.track_image_ids == image_id)
        point2d_idx[entries] = np.arange(entries.size)
        keypoints = _project(points.xyz[rows[entries]], image, model.cameras[image.camera_id])
        _warn_if_inconsistent(image, points.ids[rows[entries]])
        rec.add_image_with_trivial_frame(
            pycolmap.Image(
                name=image.name, keypoints=keypoints, camera_id=image.camera_id, image_id=image_id
            ),
            pycolmap.Rigid3d(np.asarray(image.cam_from_world, dtype=np.float64)[:3, :4]),
        )
    unknown = set(np.unique(points.track_image_ids).tolist()) - set(model.images)
    if unknown:
        raise WorkspaceError(
            f"cannot write the model: tracks refer to unknown image ids {sorted(unknown)[:10]}"
        )
    for i in range(len(points)):
        begin, end = points.track_offsets[i], points.track_offsets[i + 1]
        point = pycolmap.Point3D()
        point.xyz = points.xyz[i]
        point.color = points.rgb[i]
        point.error = float(points.error[i])
        point.track = pycolmap.Track(
            [
                pycolmap.TrackElement(int(points.track_image_ids[k]), int(point2d_idx[k]))
                for k in range(begin, end)
            ]
        )
        rec.add_point3D_with_id(int(points.ids[i]), point)
    return rec


def _warn_if_inconsistent(image: Image, track_point_ids: np.ndarray) -> None:
    if image.point3D_ids.size and not np.array_equal(
        np.unique(image.point3D_ids), np.unique(track_point_ids)
    ):
        logger.warning(
            "image %r: its point3D_ids (%d) differ from the points whose tracks contain it (%d); "
            "the tracks are written",
            image.name,
            np.unique(image.point3D_ids).size,
            np.unique(track_point_ids).size,
        )


def _is_model_file(name: str) -> bool:
    stem, _, ext = name.partition(".")
    return ext in ("bin", "txt") and stem in MODEL_FILE_STEMS + _EXTRA_MODEL_STEMS


def replace_directory(src: Path, dst: Path, *, replaceable: Iterable[str] | None = None) -> None:
    """Move the finished folder ``src`` to ``dst`` (same file system), replacing an old ``dst``.

    ``dst`` may be missing or empty; otherwise every entry in it must be in ``replaceable``
    (``None`` = anything may be replaced). The old folder is only deleted once ``src`` is in place.
    """
    if dst.exists():
        if not dst.is_dir():
            raise WorkspaceError(f"{str(dst)!r} exists and is not a folder")
        entries = sorted(p.name for p in dst.iterdir())
        if replaceable is not None:
            allowed = set(replaceable)
            extra = [e for e in entries if e not in allowed]
            if extra:
                raise WorkspaceError(
                    f"refusing to overwrite {str(dst)!r}: it contains other files {extra[:10]}"
                )
        backup = make_temp_dir(prefix=f".{dst.name}.old.", parent=dst.parent)
        backup.rmdir()
        os.replace(dst, backup)
        try:
            os.replace(src, dst)
        except BaseException:
            os.replace(backup, dst)
            raise
        shutil.rmtree(backup, ignore_errors=True)
    else:
        os.replace(src, dst)


def write_sparse_model(model: SparseModel, path: str | os.PathLike, *, binary: bool = True) -> Path:
    """Write ``model`` as a COLMAP model folder (binary or text) and return its path.

    2D observations are the exact projections of each point into every image of its track;
    the tracks (not ``Image.point3D_ids``) are authoritative. The model is written to a temporary
    folder next to ``path`` and renamed into place, so no half-written model is ever left. An
    existing ``path`` may only contain COLMAP model files (they are replaced).
    """
    path = Path(path)
    rec = _build_reconstruction(model)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = make_temp_dir(prefix=f".{path.name}.", suffix=".tmp", parent=path.parent)
    try:
        if binary:
            rec.write_binary(str(tmp))
        else:
            rec.write_text(str(tmp))
        existing = [p.name for p in path.iterdir()] if path.is_dir() else []
        replace_directory(tmp, path, replaceable=[n for n in existing if _is_model_file(n)])
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    logger.info("wrote %d images, %d points to %s", len(model.images), len(model.points), path)
    return path
