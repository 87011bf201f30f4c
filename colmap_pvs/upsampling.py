"""Image-guided upsampling of a depth map (joint bilateral, Kopf et al. 2007), pure numpy.

Used when the network runs below the map resolution (``StereoConfig.network_scale``): the depth
comes back to the map size following the reference image's edges, without mixing the depths of
the two sides of an edge (no flying pixels for fusion).
"""

from __future__ import annotations

import numpy as np

from .errors import ShapeError

__all__ = ["guided_upsample_depth", "resize_area", "resize_bilinear", "resize_nearest", "sample_depth_down"]


def resize_bilinear(values: np.ndarray, height: int, width: int) -> np.ndarray:
    """``[h, w]`` or ``[C, h, w]`` float array to ``[H, W]`` / ``[C, H, W]`` (bilinear, pixel centres)."""
    import cv2

    values = np.asarray(values, dtype=np.float32)
    if values.ndim == 2:
        return cv2.resize(values, (width, height), interpolation=cv2.INTER_LINEAR)
    if values.ndim == 3:
        if values.shape[0] == 0:
            return np.zeros((0, height, width), np.float32)
        return np.stack([cv2.resize(v, (width, height), interpolation=cv2.INTER_LINEAR) for v in values])
    raise ShapeError(f"resize_bilinear expects [h, w] or [C, h, w], got shape {values.shape}")


def resize_area(values: np.ndarray, height: int, width: int) -> np.ndarray:
    """``[h, w]`` float array to ``[height, width]``, each output pixel the mean of the input it covers
    (for shrinking a confidence; never for depth, which it would average across edges)."""
    import cv2

    values = np.asarray(values, dtype=np.float32)
    if values.ndim != 2:
        raise ShapeError(f"resize_area expects [h, w], got shape {values.shape}")
    return cv2.resize(values, (width, height), interpolation=cv2.INTER_AREA)


def resize_nearest(array: np.ndarray, height: int, width: int) -> np.ndarray:
    """Nearest-neighbour resize of ``[H, W]`` to ``[height, width]`` at pixel centres (no blending).

    Output pixel ``(c, r)`` takes input pixel ``(floor((c + 0.5) W / width), floor((r + 0.5) H / height))``.
    """
    array = np.asarray(array)
    if array.ndim != 2:
        raise ShapeError(f"resize_nearest expects an [H, W] array, got shape {array.shape}")
    h, w = array.shape
    if (h, w) == (height, width):
        return array
    rows = np.minimum(((np.arange(height) + 0.5) * h / height).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * w / width).astype(np.int64), w - 1)
    return array[rows[:, None], cols[None, :]]


def sample_depth_down(depth: np.ndarray, height: int, width: int) -> np.ndarray:
    """``depth`` ``[h, w]`` of a network run larger than its map, at the map's ``[height, width]``:
    each map pixel takes the depth of the network pixel on its own ray (no blend across an edge).

    Maps and network inputs share COLMAP's fusion convention (``io.maps.fusion_intrinsics``): pixel
    ``(c, r)`` of a map ``W`` wide looks along the ray of image coordinate ``c * W_image / W``, so map
    pixel ``(c, r)`` and network pixel ``(c * w / width, r * h / height)`` share a ray; the nearest
    network pixel to that position is taken (for ``w = 2 * width``, exactly ``(2c, 2r)``).
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ShapeError(f"sample_depth_down expects [h, w], got shape {depth.shape}")
    h, w = depth.shape
    rows = np.minimum(np.floor(np.arange(height) * (h / height) + 0.5).astype(np.int64), h - 1)
    cols = np.minimum(np.floor(np.arange(width) * (w / width) + 0.5).astype(np.int64), w - 1)
    return depth[rows[:, None], cols[None, :]]


def guided_upsample_depth(
    depth: np.ndarray,
    guide: np.ndarray,
    *,
    sigma_color: float = 0.1,
    max_relative_spread: float = 0.1,
) -> np.ndarray:
    """Upsample ``depth`` ``[h, w]`` to the size of ``guide`` ``[H, W, 3]`` (or ``[3, H, W]``).

    Each output pixel looks at the 2x2 low-resolution pixels around its position (pixel centres:
    output pixel ``x`` sits at ``(x + 0.5) w / W - 0.5``). A neighbour's weight is its bilinear
    weight times ``exp(-|I(x) - I_low(n)|^2 / 2 sigma_color^2)``, with ``I`` the guide (colours in
    ``[0, 1]``) and ``I_low`` the guide resized to ``[h, w]`` (area). The output is the weighted mean
    inverse depth of the neighbours within ``max_relative_spread`` of the heaviest neighbour's
    inverse depth: on a uniform image it is bilinear interpolation of the inverse depth (exact on a
    plane); across an edge a pixel takes the side its colour belongs to instead of a blend. Invalid
    depths (``<= 0`` or non-finite) never contribute; a pixel with no valid neighbour is 0.

    Returns ``[H, W]`` float32.
    """
    import cv2

    depth = np.asarray(depth, dtype=np.float32)
    guide = np.asarray(guide, dtype=np.float32)
    if guide.ndim == 3 and guide.shape[0] == 3 and guide.shape[2] != 3:
        guide = guide.transpose(1, 2, 0)
    if depth.ndim != 2 or guide.ndim != 3 or guide.shape[2] != 3:
        raise ShapeError(
            f"guided_upsample_depth expects depth [h, w] and guide [H, W, 3], got {depth.shape} and "
            f"{guide.shape}"
        )
    h, w = depth.shape
    H, W = guide.shape[:2]
    if (h, w) == (H, W):
        return depth.copy()
    guide = np.ascontiguousarray(guide)
    low = cv2.resize(guide, (w, h), interpolation=cv2.INTER_AREA)
    valid = np.isfinite(depth) & (depth > 0)
    inv = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0).astype(np.float32)
    u = np.clip((np.arange(W, dtype=np.float32) + 0.5) * (w / W) - 0.5, 0, w - 1)
    v = np.clip((np.arange(H, dtype=np.float32) + 0.5) * (h / H) - 0.5, 0, h - 1)
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    weights, values = [], []
    for dy in (0, 1):
        rows = np.minimum(v0 + dy, h - 1)
        wy = 1.0 - np.abs(v - (v0 + dy))
        for dx in (0, 1):
            cols = np.minimum(u0 + dx, w - 1)
            wx = 1.0 - np.abs(u - (u0 + dx))
            diff = guide - low[rows[:, None], cols[None, :]]
            wc = np.exp(-np.einsum("ijk,ijk->ij", diff, diff) / (2 * sigma_color**2))
            ok = valid[rows[:, None], cols[None, :]]
            weights.append(np.where(ok, wy[:, None] * wx[None, :] * wc, 0.0))  # u, v clipped: in [0, 1]
            values.append(inv[rows[:, None], cols[None, :]])
    wts, vals = np.stack(weights), np.stack(values)  # [4, H, W]
    best = np.take_along_axis(vals, np.argmax(wts, axis=0)[None], axis=0)[0]
    near = np.abs(vals - best[None]) <= max_relative_spread * best[None]
    wts = np.where(near, wts, 0.0)
    total = wts.sum(axis=0)
    out_inv = np.where(total > 0, (wts * vals).sum(axis=0) / np.maximum(total, 1e-30), 0.0)
    return np.where(out_inv > 0, 1.0 / np.maximum(out_inv, 1e-30), 0.0).astype(np.float32)
