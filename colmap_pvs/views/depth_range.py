"""Per-image depth ranges: robust percentiles of the observed sparse points' depths."""

from __future__ import annotations

import logging

import numpy as np

from ..types import Image, Points3D, SparseModel
from .config import ViewSelectionConfig

logger = logging.getLogger(__name__)


def _point_rows(points: Points3D, point_ids: np.ndarray, order: np.ndarray | None = None) -> np.ndarray:
    """Rows in ``points`` of the ids ``point_ids`` ``[M]``; ids that are not present are dropped."""
    ids = np.asarray(points.ids, dtype=np.int64)
    query = np.asarray(point_ids, dtype=np.int64).reshape(-1)
    if ids.shape[0] == 0 or query.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    if order is None:
        order = np.argsort(ids, kind="stable")
    sorted_ids = ids[order]
    pos = np.minimum(np.searchsorted(sorted_ids, query), ids.shape[0] - 1)
    found = sorted_ids[pos] == query
    if not np.all(found):
        logger.debug("%d observed point ids are not in the model's points", int(np.count_nonzero(~found)))
    return order[pos[found]]


def _observed_depths(model: SparseModel, image: Image, order: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame z ``[M']`` of the points ``image`` observes: finite, positive, one per point id."""
    rows = np.unique(_point_rows(model.points, image.point3D_ids, order))
    xyz = np.asarray(model.points.xyz, dtype=np.float64)[rows]
    cam = np.asarray(image.cam_from_world, dtype=np.float64)
    z = xyz @ cam[2, :3] + cam[2, 3]
    return z[np.isfinite(z) & (z > 0)]


def _outlier_mask(depths: np.ndarray, config: ViewSelectionConfig) -> np.ndarray:
    """``[M]`` bool, True for far outliers among positive depths ``[M]`` (see :func:`compute_depth_range`)."""
    none = np.zeros(depths.shape, dtype=bool)
    if config.depth_outlier_sigmas <= 0 or depths.shape[0] < 4:
        return none
    log_z = np.log(depths)
    median = np.median(log_z)
    sigma = 1.4826 * np.median(np.abs(log_z - median))
    half_width = max(config.depth_outlier_sigmas * sigma, np.log(config.depth_outlier_min_factor))
    outliers = np.abs(log_z - median) > half_width
    if outliers.mean() > config.depth_outlier_max_fraction:
        return none
    return outliers


def _robust_depth_range(
    depths: np.ndarray, config: ViewSelectionConfig, name: str
) -> tuple[tuple[float, float], str | None]:
    """Depth range of one image and, when outliers were ignored, a note naming how many."""
    outliers = _outlier_mask(depths, config)
    note = None
    if outliers.any():
        kept = depths[~outliers]
        note = (
            f"{name}: {int(outliers.sum())} of {depths.shape[0]} sparse points are depth outliers "
            f"(outside {kept.min():.4g}..{kept.max():.4g}, median {np.median(depths):.4g}; farthest "
            f"{depths[outliers].max():.4g}, nearest {depths[outliers].min():.4g}), "
            "ignored for the depth range"
        )
        depths = kept
    dmin, dmax = _depth_range_from_depths(depths, config)
    if config.depth_near_factor < 1.0:
        dmin = max(dmin * config.depth_near_factor, min(dmin, config.min_depth_ratio * dmax))
    return (dmin, dmax), note


def _depth_range_from_depths(depths: np.ndarray, config: ViewSelectionConfig) -> tuple[float, float]:
    lo, hi = np.percentile(depths, config.depth_percentiles)
    dmax = float(hi) * (1.0 + config.depth_margin)
    dmin = max(float(lo) * (1.0 - config.depth_margin), config.min_depth_ratio * dmax)
    if not dmin < dmax:  # every point at one depth and no margin: widen by 1 %
        dmin, dmax = dmin * 0.99, dmax * 1.01
    return dmin, dmax


def compute_depth_range(
    model: SparseModel,
    image: Image,
    config: ViewSelectionConfig | None = None,
    *,
    _order: np.ndarray | None = None,
) -> tuple[float, float] | None:
    """Robust depth range ``(dmin, dmax)`` of ``image`` from the sparse points it observes.

    First, far outliers are set aside (a DEBUG message names how many): with ``z`` the positive
    camera-frame depths of the observed points, ``med`` the median of ``log z`` and
    ``sigma = 1.4826 * median(|log z - med|)``, a point is an outlier when
    ``|log z - med| > max(depth_outlier_sigmas * sigma, log(depth_outlier_min_factor))`` -- unless
    more than ``depth_outlier_max_fraction`` of the points are, then none is (a background is
    structure, not noise). With ``lo, hi`` the ``config.depth_percentiles`` of the remaining depths
    and ``m = config.depth_margin``::

        dmax = hi * (1 + m)
        dmin = max(lo * (1 - m), min_depth_ratio * dmax)      # always > 0

    ``config.depth_near_factor`` then multiplies ``dmin``, never below that guard.

    Returns ``None``, with a warning, when fewer than ``config.min_points`` observed
    points lie in front of the camera.
    """
    config = config or ViewSelectionConfig()
    depths = _observed_depths(model, image, _order)
    if depths.shape[0] < config.min_points:
        logger.warning(
            "image %r observes %d sparse point(s) in front of the camera (min_points=%d): no depth range",
            image.name,
            depths.shape[0],
            config.min_points,
        )
        return None
    depth_range, note = _robust_depth_range(depths, config, repr(image.name))
    if note is not None:  # harmless and expected (SfM noise): a detail, not a warning
        logger.debug("image %s", note)
    return depth_range
