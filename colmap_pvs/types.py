"""Plain numpy dataclasses for a COLMAP sparse model (no pycolmap objects).

These are produced by :mod:`colmap_pvs.io.sparse` (the only module that touches
pycolmap's scene API) and consumed by view selection, inference and fusion.
See ``docs/CONVENTIONS.md`` for the geometric conventions.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera.

    Attributes:
        camera_id: COLMAP camera id.
        model: COLMAP model name, e.g. ``"PINHOLE"``.
        width, height: image size in pixels.
        K: ``[3, 3]`` float64 intrinsics in COLMAP's pixel convention (the centre of
            pixel ``(col, row)`` is at ``(col + 0.5, row + 0.5)``).
        params: the raw COLMAP parameter vector.
    """

    camera_id: int
    model: str
    width: int
    height: int
    K: np.ndarray
    params: np.ndarray

    @property
    def is_pinhole(self) -> bool:
        return self.model in PINHOLE_MODELS


@dataclass(frozen=True, eq=False)
class Image:
    """A registered image.

    Attributes:
        image_id: COLMAP image id.
        name: image file name relative to the image folder.
        camera_id: id of its :class:`Camera`.
        cam_from_world: ``[3, 4]`` float64 ``[R | t]`` with ``x_cam = R @ x_world + t``.
        point3D_ids: ``[M]`` int64 ids of the 3D points this image observes (no invalid ids).
    """

    image_id: int
    name: str
    camera_id: int
    cam_from_world: np.ndarray
    point3D_ids: np.ndarray

    @property
    def R(self) -> np.ndarray:
        return self.cam_from_world[:, :3]

    @property
    def t(self) -> np.ndarray:
        return self.cam_from_world[:, 3]

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, ``-R^T t``."""
        return -self.R.T @ self.t


@dataclass(frozen=True, eq=False)
class Points3D:
    """All 3D points, with tracks in CSR layout.

    Attributes:
        ids: ``[P]`` int64 point ids.
        xyz: ``[P, 3]`` float64 world coordinates.
        rgb: ``[P, 3]`` uint8 colours.
        error: ``[P]`` float64 mean reprojection error in pixels.
        track_offsets: ``[P + 1]`` int64; the track of point ``i`` is
            ``track_image_ids[track_offsets[i]:track_offsets[i + 1]]``.
        track_image_ids: ``[T]`` int64 image ids (one entry per observation).
    """

    ids: np.ndarray
    xyz: np.ndarray
    rgb: np.ndarray
    error: np.ndarray
    track_offsets: np.ndarray
    track_image_ids: np.ndarray

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def track(self, index: int) -> np.ndarray:
        """Image ids observing the point at row ``index`` (not its id)."""
        return self.track_image_ids[self.track_offsets[index] : self.track_offsets[index + 1]]


@dataclass(frozen=True, eq=False)
class SparseModel:
    """A COLMAP reconstruction as plain numpy data."""

    cameras: dict[int, Camera]
    images: dict[int, Image]
    points: Points3D
    image_ids_by_name: dict[str, int] = field(default_factory=dict)

    def image_by_name(self, name: str) -> Image:
        try:
            return self.images[self.image_ids_by_name[name]]
        except KeyError:
            raise KeyError(f"image {name!r} is not in the sparse model") from None

    def camera_of(self, image: Image) -> Camera:
        return self.cameras[image.camera_id]
