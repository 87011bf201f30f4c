"""Small geometry helpers shared by every step. Conventions: ``docs/CONVENTIONS.md``.

- ``cam_from_world`` is ``[R | t]`` with ``x_cam = R x_world + t`` (COLMAP).
- Camera axes are OpenCV's: +x right, +y down, +z forward.
- Depth is the camera-frame z coordinate; 0 marks an invalid pixel.
- Pixel ``(col, row)`` has its centre at continuous coordinate ``(col + 0.5, row + 0.5)``,
  the convention of COLMAP's SfM and of its ``K``. Resizing an image by ``(sx, sy)``
  therefore scales ``K`` exactly as ``diag(sx, sy, 1) @ K``.
- ``torch.nn.functional.grid_sample`` is always called with ``align_corners=False``:
  continuous coordinate ``u`` in ``[0, W]`` maps to ``2 u / W - 1`` in ``[-1, 1]``.
"""

from __future__ import annotations

import numpy as np


def affine_row(m: np.ndarray, b: float, x: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """``m . x + b`` for one row ``m`` ``[3]`` of an affine map and the components ``x`` of ``[P]``
    points: an affine map of many points one output row at a time, without BLAS (whose threads stall
    on thin matrices, the more so when the cores are busy: ``benchmarks/RESULTS.md``)."""
    return m[0] * x[0] + m[1] * x[1] + m[2] * x[2] + b


def rowmul(points: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``points @ M`` for ``[N, 3]`` points and a ``[3, 3]`` matrix.

    ``np.einsum`` instead of ``@``: BLAS gemm on ``[N, 3] x [3, 3]`` is much slower (its threads stall
    on thin matrices, as in :func:`affine_row`).
    """
    return np.einsum("ij,jk->ik", points, M)


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """``K`` of an image resized by ``(sx, sy)`` (new size = old size * s), exact for our pixel convention."""
    S = np.diag([sx, sy, 1.0])
    return S @ np.asarray(K, dtype=np.float64)


def pixel_centers(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous coordinates ``(u, v)`` of every pixel centre, each ``[H, W]`` float64."""
    v, u = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    return u, v


def backproject_depth(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points ``[H, W, 3]`` of a depth map ``[H, W]`` (z = depth)."""
    h, w = depth.shape
    u, v = pixel_centers(h, w)
    Kinv = np.linalg.inv(K)
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ Kinv.T
    return rays * depth[..., None]


def to_homogeneous(cam_from_world: np.ndarray) -> np.ndarray:
    """``[3, 4]`` or ``[4, 4]`` pose to ``[4, 4]``."""
    T = np.eye(4)
    T[:3, :] = np.asarray(cam_from_world, dtype=np.float64)[:3, :]
    return T


def sparse_depth_map(
    xyz: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int
) -> np.ndarray:
    """``[H, W]`` float32 camera depth of the world points ``xyz`` ``[P, 3]`` at the pixels they
    project into (``cam_from_world`` ``[3|4, 4]``), 0 elsewhere.

    Pixel ``(col, row)`` receives the points with ``floor(u) = col, floor(v) = row`` for ``(u, v)``
    the projection with ``K``; points behind the camera or outside the map are dropped; the nearest
    point wins.
    """
    out = np.zeros((height, width), np.float32)
    if xyz.shape[0] == 0:
        return out
    cam = xyz @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = cam @ K.T
        uv = uvw[:, :2] / uvw[:, 2:3]
    ok = (z > 0) & np.all(np.isfinite(uv), axis=1)
    col = np.floor(np.where(ok, uv[:, 0], -1)).astype(np.int64)
    row = np.floor(np.where(ok, uv[:, 1], -1)).astype(np.int64)
    ok &= (col >= 0) & (col < width) & (row >= 0) & (row < height)
    order = np.argsort(-z[ok], kind="stable")  # farthest first, nearest written last
    out[row[ok][order], col[ok][order]] = z[ok][order]
    return out
