"""Dense completion of a geometric map: the pixels it drops, filled by a plane fit of those it keeps.

The geometric pass keeps the pixels that its sources confirm (on hololens-dev 66 % of them, 75 %
within 5 % of the ground truth) and drops the rest, mostly untextured walls and cupboards where the
network's photometric depth is wrong (26 % within 5 % there). Those regions are mostly planes whose
textured borders *are* kept, so a local plane fit of the kept pixels extends the borders into the
wall; planar-prior stereo (ACMP, Xu & Tao 2020) builds its prior from its reliable pixels the same
way. Measured on hololens-dev (``benchmarks/RESULTS.md``, 2026-12-02): the filled pixels are 35 %
within 5 % (against the photometric depth's 26 %), and the whole map 61.5 % (58.3 % photometric).

:func:`complete_depth` returns the dense map, :func:`completed_confidence` a confidence that ranks
every kept pixel above every filled one. The stereo step writes both as ``NAME.filled.bin`` in
``stereo/depth_maps`` and ``stereo/confidence_maps`` (``docs/CONVENTIONS.md``); COLMAP's fusion never
reads them. Arrays are numpy ``[H, W]`` (depth in the map's units, 0 = none).
"""

from __future__ import annotations

import numpy as np
import torch

from .errors import ShapeError
from .model.cost import affine_fill_inverse_depth
from .upsampling import resize_bilinear

#: Scales of the plane fit, in cells of the pooled grid (a cell is ``factor`` pixels).
FILL_SIGMAS = (2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0, 48.0)


def _pooled_inverse_depth(kept: np.ndarray, factor: int) -> np.ndarray:
    """``[ceil(H/f), ceil(W/f)]`` depth of the mean inverse depth of each cell's kept pixels (0: none)."""
    H, W = kept.shape
    hc, wc = -(-H // factor), -(-W // factor)
    pad = np.zeros((hc * factor, wc * factor), np.float64)
    pad[:H, :W] = kept
    valid = pad > 0
    inv = np.where(valid, 1.0 / np.where(valid, pad, 1.0), 0.0)
    cells = (hc, factor, wc, factor)
    count = valid.reshape(cells).sum((1, 3))
    total = inv.reshape(cells).sum((1, 3))
    return np.where(count > 0, count / np.maximum(total, 1e-300), 0.0).astype(np.float32)


def complete_depth(
    kept: np.ndarray, fallback: np.ndarray, factor: int = 4, min_weight: float = 6.0
) -> np.ndarray:
    """``[H, W]`` dense depth: ``kept`` where it is > 0, a local plane fit of it elsewhere.

    The kept pixels are pooled into cells of ``factor`` x ``factor`` pixels (mean inverse depth);
    :func:`~colmap_pvs.model.cost.affine_fill_inverse_depth` fits each cell a plane in inverse depth
    to the cells around it (Gaussian weights at the smallest scale of :data:`FILL_SIGMAS` that holds
    ``min_weight`` cells, clipped near the local range), and the fit is interpolated bilinearly in
    inverse depth back to the pixels. Pixels the fit cannot give a positive depth (an image without a
    single kept pixel) take ``fallback`` (the photometric depth).

    Args:
        kept: ``[H, W]`` geometric depth, 0 where dropped.
        fallback: ``[H, W]`` depth for pixels without a fit.
        factor: pooling factor (>= 1).
        min_weight: cells' worth of weight a scale needs (see the fit).

    Returns:
        ``[H, W]`` float32 depth, > 0 wherever ``kept`` or ``fallback`` is.
    """
    if kept.ndim != 2 or fallback.shape != kept.shape:
        raise ShapeError(f"kept and fallback must be the same [H, W], got {kept.shape} and {fallback.shape}")
    if factor < 1:
        raise ValueError(f"factor must be >= 1, got {factor}")
    H, W = kept.shape
    hint = _pooled_inverse_depth(kept, factor)
    if not (hint > 0).any():
        return np.where(kept > 0, kept, fallback).astype(np.float32)
    with torch.no_grad():
        inv = affine_fill_inverse_depth(torch.from_numpy(hint)[None, None], sigmas=FILL_SIGMAS,
                                        min_weight=min_weight)[0, 0].numpy()
    hc, wc = hint.shape
    inv = resize_bilinear(inv.astype(np.float32), hc * factor, wc * factor)[:H, :W]
    fill = np.where(inv > 0, 1.0 / np.maximum(inv, 1e-12), fallback)
    return np.where(kept > 0, kept, fill).astype(np.float32)


def completed_confidence(kept: np.ndarray, geometric: np.ndarray, photometric: np.ndarray) -> np.ndarray:
    """``[H, W]`` confidence of a completed map in ``[0, 1]``: every kept pixel above every filled one.

    ``0.5 + 0.5 * geometric`` where ``kept`` (bool ``[H, W]``), ``0.5 * photometric`` elsewhere (both
    confidences in ``[0, 1]``). The sources confirmed the kept pixels and nobody confirmed the filled
    ones, so the kept ones rank first (on hololens-dev the 50 % most confident pixels then have 0.49
    of the map's AbsRel); within each group the pass's own confidence ranks.
    """
    if not (kept.shape == geometric.shape == photometric.shape) or kept.ndim != 2:
        raise ShapeError(
            f"kept, geometric and photometric must be the same [H, W], got {kept.shape}, "
            f"{geometric.shape} and {photometric.shape}"
        )
    geo = np.clip(np.nan_to_num(geometric), 0.0, 1.0)
    photo = np.clip(np.nan_to_num(photometric), 0.0, 1.0)
    return np.where(kept, 0.5 + 0.5 * geo, 0.5 * photo).astype(np.float32)
