"""Camera-facing unit normals from a depth map (conventions: ``docs/CONVENTIONS.md``)."""

from __future__ import annotations

import numpy as np

from .errors import ShapeError
from .geometry import backproject_depth


def depth_to_normals(depth: np.ndarray, K: np.ndarray, *, max_relative_jump: float = 0.05) -> np.ndarray:
    """Per-pixel normals of a depth map, in the camera frame.

    Each normal is the cross product of the horizontal and vertical tangents of the
    back-projected surface, taken from central differences (one-sided where a
    neighbour is invalid or across a depth discontinuity larger than
    ``max_relative_jump`` relative depth). Normals are unit length and face the
    camera: ``dot(n, x) < 0`` for the pixel's 3D point ``x``. Pixels without a valid
    tangent in both directions get a zero normal.

    Args:
        depth: ``[H, W]`` z-depth, 0 = invalid.
        K: ``[3, 3]`` intrinsics of this depth map's resolution.

    Returns:
        ``[H, W, 3]`` float32 normals (zero where undefined).
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ShapeError(f"depth must be [H, W], got shape {depth.shape}")
    points = backproject_depth(depth, K)
    valid = depth > 0

    def tangent(axis: int) -> tuple[np.ndarray, np.ndarray]:
        fwd = np.zeros_like(points)
        bwd = np.zeros_like(points)
        ok_f = np.zeros(depth.shape, dtype=bool)
        ok_b = np.zeros(depth.shape, dtype=bool)
        sl_a = [slice(None), slice(None)]
        sl_b = [slice(None), slice(None)]
        sl_a[axis] = slice(1, None)
        sl_b[axis] = slice(None, -1)
        sa, sb = tuple(sl_a), tuple(sl_b)
        diff = points[sa] - points[sb]
        d_a, d_b = depth[sa], depth[sb]
        smooth = (
            valid[sa]
            & valid[sb]
            & (np.abs(d_a - d_b) <= max_relative_jump * np.minimum(d_a, d_b).clip(min=1e-12))
        )
        fwd[sb] = diff
        ok_f[sb] = smooth
        bwd[sa] = diff
        ok_b[sa] = smooth
        both = ok_f & ok_b
        t = np.where(ok_f[..., None], fwd, bwd)
        t = np.where(both[..., None], 0.5 * (fwd + bwd), t)
        return t, (ok_f | ok_b) & valid

    tu, ok_u = tangent(1)
    tv, ok_v = tangent(0)
    n = np.cross(tu, tv)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    ok = ok_u & ok_v & (norm[..., 0] > 0)
    n = np.where(ok[..., None], n / np.maximum(norm, 1e-300), 0.0)
    facing = np.sum(n * points, axis=-1) > 0
    n[facing] *= -1.0
    return n.astype(np.float32)


def fit_normals(depth: np.ndarray, K: np.ndarray, *, window: int = 7, max_relative_jump: float = 0.05,
                min_support: float = 0.5) -> np.ndarray:
    """Camera-facing unit normals of a depth map from a local least-squares plane fit.

    The per-pixel tangent-plane normals of :func:`depth_to_normals` (before normalisation, i.e.
    area-weighted cross products of the tangents; none across a depth jump larger than
    ``max_relative_jump``) are summed over a ``window x window`` neighbourhood and normalised: for a
    locally planar patch this is the plane fit of the neighbourhood, and single-pixel noise of the
    depth averages out instead of tilting the normal. Pixels whose window has fewer than
    ``min_support`` of its pixels with a normal get none (zero).

    Args:
        depth: ``[H, W]`` z-depth, 0 = invalid; K: ``[3, 3]`` intrinsics of this resolution.

    Returns:
        ``[H, W, 3]`` float32 unit normals facing the camera (``dot(n, x) < 0``), zero where undefined.
    """
    import cv2

    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ShapeError(f"depth must be [H, W], got shape {depth.shape}")
    if window < 1 or window % 2 == 0:
        raise ShapeError(f"window must be a positive odd number, got {window}")
    base = depth_to_normals(depth, K, max_relative_jump=max_relative_jump).astype(np.float32)
    has = np.any(base != 0, axis=-1)
    points = backproject_depth(depth, K)
    weight = np.where(has, 1.0, 0.0).astype(np.float32)
    summed = cv2.boxFilter(base * weight[..., None], -1, (window, window), normalize=False,
                           borderType=cv2.BORDER_CONSTANT)
    support = cv2.boxFilter(weight, -1, (window, window), normalize=True, borderType=cv2.BORDER_CONSTANT)
    norm = np.linalg.norm(summed, axis=-1, keepdims=True)
    ok = (depth > 0) & has & (support >= min_support) & (norm[..., 0] > 1e-6)
    n = np.where(ok[..., None], summed / np.maximum(norm, 1e-12), 0.0)
    facing = np.sum(n * points, axis=-1) > 0
    n[facing] *= -1.0
    return n.astype(np.float32)


def plane_residual(depth: np.ndarray, window: int) -> np.ndarray:
    """``[H, W]`` float32 how far a depth map departs from a plane around each pixel: the RMS residual
    of the least-squares plane ``1/d = a u + b v + c`` (a 3D plane is linear in inverse depth) over
    the valid pixels of the ``window x window`` square centred on the pixel, divided by their mean
    inverse depth (so a relative depth deviation). 0 on invalid pixels and where fewer than 3 valid
    pixels or collinear ones leave the plane undetermined. Large at depth edges and on noisy or broken
    surfaces; 0 on any plane, however slanted.

    Args:
        depth: ``[H, W]`` z-depth, 0 = invalid; window: odd side in pixels.
    """
    import cv2

    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ShapeError(f"depth must be [H, W], got shape {depth.shape}")
    if window < 3 or window % 2 == 0:
        raise ValueError(f"window must be odd and at least 3, got {window}")
    valid = depth > 0
    weight = valid.astype(np.float64)
    z = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0)
    h, w = depth.shape
    v, u = np.mgrid[:h, :w].astype(np.float64)
    u -= w / 2.0  # centred coordinates: smaller sums, less cancellation
    v -= h / 2.0

    def total(a):  # the sum over the valid pixels of each window (zero outside the image)
        return cv2.boxFilter(a * weight, cv2.CV_64F, (window, window), normalize=False,
                             borderType=cv2.BORDER_CONSTANT)

    n = total(np.ones_like(z))
    m = np.maximum(n, 1.0)

    def mean(a):
        return total(a) / m

    mu, mv, mz = mean(u), mean(v), mean(z)
    cuu, cvv, cuv = mean(u * u) - mu * mu, mean(v * v) - mv * mv, mean(u * v) - mu * mv
    cuz, cvz, czz = mean(u * z) - mu * mz, mean(v * z) - mv * mz, mean(z * z) - mz * mz
    det = cuu * cvv - cuv * cuv
    ok = valid & (n >= 3) & (det > 1e-9)
    det = np.where(ok, det, 1.0)
    a = (cuz * cvv - cvz * cuv) / det
    b = (cvz * cuu - cuz * cuv) / det
    residual = np.sqrt(np.clip(czz - a * cuz - b * cvz, 0.0, None)) / np.maximum(np.abs(mz), 1e-12)
    return np.where(ok, residual, 0.0).astype(np.float32)
