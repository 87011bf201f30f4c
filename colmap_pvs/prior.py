"""The sparse prior in the photometric maps: where the image has no texture, and how far to trust.

The network's coarse planes are centred on a dense prior fitted to the SfM points (an affine fit in
inverse depth, :func:`colmap_pvs.model.cost.affine_fill_inverse_depth`). Two uses of that prior after
the network, both chosen by measurement (``benchmarks/RESULTS.md``, "The sparse prior as a second
estimate"):

- **No texture, no matching.** Where the image is flat (grey-level standard deviation under a few
  levels), the cost volume is flat too and the network's depth is worse than the prior's.
  :func:`blend_with_prior` moves the depth
  towards the prior there, in log depth, by a weight that ramps with the texture
  (:func:`texture_weight`).
- **Two estimates that agree.** The network matches pixels; the prior interpolates SfM points. Where
  the two agree, both are likely right: :func:`prior_agreement` ranks errors far better than the
  network's probability mass, and it multiplies the confidence.

Arrays are numpy ``[H, W]`` (depth in the map's units, 0 = none).
"""

from __future__ import annotations

import numpy as np

from .errors import ShapeError
from .upsampling import resize_bilinear


def upsample_prior(prior: np.ndarray, net_size: tuple[int, int], map_size: tuple[int, int]) -> np.ndarray:
    """The network's coarse prior depth ``[ceil(h/4), ceil(w/4)]`` at the map size ``[H, W]``.

    ``net_size`` ``(w, h)`` is the network's input size, ``map_size`` ``(W, H)`` the map's. Coarse pixel
    ``(i, j)`` covers network pixels ``4i .. 4i+3``; the interpolation is bilinear in inverse depth.
    Pixels without a prior stay 0.
    """
    (w, h), (W, H) = net_size, map_size
    hc, wc = -(-h // 4), -(-w // 4)
    if prior.shape != (hc, wc):
        raise ShapeError(f"prior must be [{hc}, {wc}] for a {w}x{h} network input, got {prior.shape}")
    inv = np.where(prior > 0, 1.0 / np.maximum(prior, 1e-12), 0.0).astype(np.float32)
    has = (prior > 0).astype(np.float32)
    inv = resize_bilinear(inv, 4 * hc, 4 * wc)[:h, :w]
    has = resize_bilinear(has, 4 * hc, 4 * wc)[:h, :w]
    if (w, h) != (W, H):
        inv, has = resize_bilinear(inv, H, W), resize_bilinear(has, H, W)
    # Only where every contributing coarse pixel had a prior (an average with "none" is no depth).
    return np.where(has > 0.999, 1.0 / np.maximum(inv, 1e-12), 0.0).astype(np.float32)


def texture_weight(image: np.ndarray, window: int, threshold: float) -> np.ndarray:
    """``[H, W]`` in ``[0, 1]``: the grey-level std over ``window x window`` pixels, over ``threshold``.

    ``image`` ``[H, W]`` grey or ``[3, H, W]`` RGB (grey = Rec. 601 luma), in ``[0, 1]``. 1 means
    textured enough to match; ``threshold <= 0`` gives all ones.
    The clipped ratio is smoothed by a Gaussian of ``sigma = (window - 1) / 2``: unsmoothed, the edges
    of a flat door (textured, weight 1) kept the network's depth as thin lines across the blended door.
    """
    import cv2

    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 3 and image.shape[0] == 3:
        image = np.tensordot(np.array([0.299, 0.587, 0.114], np.float32), image, axes=1)
    if image.ndim != 2:
        raise ShapeError(f"image must be [H, W] or [3, H, W], got shape {image.shape}")
    if threshold <= 0:
        return np.ones(image.shape, np.float32)
    g = image
    mean = cv2.blur(g, (window, window), borderType=cv2.BORDER_REFLECT)
    sq = cv2.blur(g * g, (window, window), borderType=cv2.BORDER_REFLECT)
    std = np.sqrt(np.maximum(sq - mean * mean, 0.0))
    weight = np.clip(std / threshold, 0.0, 1.0).astype(np.float32)
    if window > 1:
        weight = cv2.GaussianBlur(weight, (0, 0), (window - 1) / 2.0, borderType=cv2.BORDER_REFLECT)
    return np.clip(weight, 0.0, 1.0)


def blend_with_prior(depth: np.ndarray, prior: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """``exp(w log d + (1 - w) log p)`` where both depths exist, else ``depth`` (all ``[H, W]``).

    ``weight`` 1 keeps the network's depth, 0 takes the prior's.
    """
    if not depth.shape == prior.shape == weight.shape:
        raise ShapeError(f"depth {depth.shape}, prior {prior.shape} and weight {weight.shape} differ")
    both = (depth > 0) & (prior > 0) & np.isfinite(depth)
    d, p = np.maximum(depth, 1e-12), np.maximum(prior, 1e-12)
    blended = np.exp(weight * np.log(d) + (1.0 - weight) * np.log(p))
    return np.where(both, blended, depth).astype(np.float32)


def prior_agreement(depth: np.ndarray, prior: np.ndarray, scale: float) -> np.ndarray:
    """``[H, W]`` ``exp(-|log(d / p)| / scale)``: 1 where the depth and the prior agree, 1 without a prior.

    ``scale`` is a relative depth difference (0.05: 5 % apart gives ``1/e``); ``scale <= 0`` gives all
    ones. Pixels without a depth get 1 too (they carry no confidence anyway).
    """
    if depth.shape != prior.shape:
        raise ShapeError(f"depth {depth.shape} and prior {prior.shape} differ")
    if scale <= 0:
        return np.ones(depth.shape, np.float32)
    both = (depth > 0) & (prior > 0) & np.isfinite(depth)
    diff = np.abs(np.log(np.maximum(depth, 1e-12)) - np.log(np.maximum(prior, 1e-12)))
    return np.where(both, np.exp(-diff / scale), 1.0).astype(np.float32)
