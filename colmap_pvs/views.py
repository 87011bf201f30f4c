"""View selection and per-image depth ranges from a sparse model (pure numpy).

For every reference image we pick source images with the MVSNet score
(Yao et al., 2018), accumulated over the sparse points ``p`` both images observe::

    s(i, j) = sum_p G(theta_ij(p))
    theta_ij(p) = angle (degrees) between the rays from the centres of i and j to p
    G(theta) = exp(-(theta - theta0)^2 / (2 sigma1^2))   if theta <= theta0
               exp(-(theta - theta0)^2 / (2 sigma2^2))   otherwise

All pairwise scores are computed at once, in ``O(sum over points of track_length^2)``
time, without a Python loop over points or pairs: every pair of observations of
every track is generated with numpy from the CSR tracks of
:class:`~colmap_pvs.types.Points3D` and scatter-added into an ``[n, n]`` matrix.

Depth ranges are robust percentiles of the camera-frame z of the image's observed
sparse points, widened by a relative margin (see :class:`ViewSelectionConfig`).

Candidate sources: an image ``j`` is a candidate source for reference ``i`` when
``s(i, j) > 0`` and the two images share at least ``min_shared_points`` points.
Since ``G > 0`` everywhere, ``s(i, j) > 0`` exactly when they share a point.
Images skipped as references (too few points) remain usable as sources.

This module never imports pycolmap; it consumes :class:`~colmap_pvs.types.SparseModel`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from .errors import ConfigError, ShapeError, WorkspaceError
from .types import Image, Points3D, SparseModel

logger = logging.getLogger(__name__)

__all__ = [
    "PairStatistics",
    "ReferenceViews",
    "SkippedImage",
    "ViewSelection",
    "ViewSelectionConfig",
    "angle_weight",
    "best_and_worst",
    "compute_depth_range",
    "compute_pair_statistics",
    "compute_view_scores",
    "format_selection_table",
    "rank_sources",
    "reference_sources",
    "resolve_sources",
    "select_views",
]

# Upper bound on the number of observation pairs materialised at once (memory ~ 100 B per pair).
_MAX_PAIRS_PER_CHUNK = 1 << 22
# Candidates put in coverage-aware order per reference (the rest follow by score): the network's
# sources and the geometric pass's extra views come from this prefix.
_COVERAGE_PICKS = 16


# --------------------------------------------------------------------------- config


#: Help of ``wide_sources``, shared by the configs that pass it on (stereo, select-views).
WIDE_SOURCES_HELP = (
    "of the num_views-1 sources, this many (at most half, rounded down) are picked by the MVSNet score "
    "at wide_theta0_deg instead of theta0_deg: wider baselines make the geometric maps more accurate "
    "but sparser (e.g. 2 at N = 5; 0: off)"
)


@dataclass(frozen=True)
class ViewSelectionConfig:
    """Parameters of view selection and depth-range estimation."""

    num_views: int = field(
        default=5,
        metadata={
            "help": "views per reference, the reference included: each reference gets num_views-1 sources"
        },
    )
    theta0_deg: float = field(
        default=5.0,
        metadata={"help": "preferred triangulation angle theta0 (degrees) of the MVSNet view score"},
    )
    sigma1: float = field(
        default=1.0,
        metadata={"help": "width (degrees) of the view-score Gaussian for angles below theta0"},
    )
    sigma2: float = field(
        default=10.0,
        metadata={"help": "width (degrees) of the view-score Gaussian for angles above theta0"},
    )
    coverage_decay: float = field(
        default=0.1,
        metadata={
            "help": "coverage-aware source choice in [0, 1]: sources are picked one at a time by their "
            "MVSNet score over the reference's sparse points, a point already seen by k picked sources "
            "counting decay^k (1: the plain top-N by score; 0: only points no picked source sees)"
        },
    )
    wide_sources: int = field(default=0, metadata={"help": WIDE_SOURCES_HELP})
    wide_theta0_deg: float = field(
        default=15.0,
        metadata={"help": "preferred triangulation angle (degrees) of the wide_sources picks"},
    )
    min_shared_points: int = field(
        default=3,
        metadata={"help": "a source must share at least this many sparse points with the reference"},
    )
    min_points: int = field(
        default=10,
        metadata={
            "help": "an image observing fewer sparse points (in front of it) is skipped as a reference, "
            "with a warning"
        },
    )
    # ``tuple[float, ...]`` validated to two values: config._coerce mishandles fixed-length tuples
    # (``zip(args, value)`` is unpacked as ``(v, a)``), so ``tuple[float, float]`` fails to load.
    depth_percentiles: tuple[float, ...] = field(
        default=(1.0, 99.0),
        metadata={"help": "lower and upper percentiles (0-100) of the sparse points' depths, per image"},
    )
    depth_margin: float = field(
        default=0.25,
        metadata={
            "help": "relative margin m in [0, 1) applied to the percentile range [lo, hi]: "
            "depth range = [lo*(1-m), hi*(1+m)] (0.25 and the 1/99 percentiles are what COLMAP's "
            "own dense workspace uses)"
        },
    )
    min_depth_ratio: float = field(
        default=1e-3,
        metadata={"help": "guard in (0, 1): the minimum depth is at least min_depth_ratio * maximum depth"},
    )
    depth_outlier_sigmas: float = field(
        default=3.0,
        metadata={
            "help": "points whose log depth is more than this many robust sigmas (1.4826 MAD) and more than "
            "depth_outlier_min_factor away from the median depth are outliers, ignored for the range; "
            "0 disables"
        },
    )
    depth_outlier_min_factor: float = field(
        default=5.0,
        metadata={"help": "points within [median / f, median * f] are never outliers (f > 1)"},
    )
    depth_outlier_max_fraction: float = field(
        default=0.1,
        metadata={
            "help": "if more than this fraction of the points would be outliers they are scene structure "
            "(a background), and all points are kept"
        },
    )

    def __post_init__(self) -> None:
        if self.num_views < 2:
            raise ConfigError(
                f"num_views must be >= 2 (reference + at least one source), got {self.num_views}"
            )
        if not 0.0 <= self.theta0_deg <= 180.0:
            raise ConfigError(f"theta0_deg must be in [0, 180], got {self.theta0_deg}")
        for name in ("sigma1", "sigma2"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a positive number, got {value}")
        if not 0.0 <= self.wide_theta0_deg <= 180.0:
            raise ConfigError(f"wide_theta0_deg must be in [0, 180], got {self.wide_theta0_deg}")
        if self.wide_sources < 0:
            raise ConfigError(f"wide_sources must be >= 0, got {self.wide_sources}")
        if not 0.0 <= self.coverage_decay <= 1.0:
            raise ConfigError(f"coverage_decay must be in [0, 1], got {self.coverage_decay}")
        if self.min_shared_points < 1:
            raise ConfigError(f"min_shared_points must be >= 1, got {self.min_shared_points}")
        if self.min_points < 1:
            raise ConfigError(f"min_points must be >= 1, got {self.min_points}")
        try:
            percentiles = tuple(float(v) for v in self.depth_percentiles)
        except (TypeError, ValueError):
            raise ConfigError(
                f"depth_percentiles must be two numbers, got {self.depth_percentiles!r}"
            ) from None
        object.__setattr__(self, "depth_percentiles", percentiles)
        if len(self.depth_percentiles) != 2:
            raise ConfigError(
                f"depth_percentiles must be two numbers (lo, hi), got {self.depth_percentiles!r}"
            )
        lo, hi = self.depth_percentiles
        if not 0.0 <= lo < hi <= 100.0:
            raise ConfigError(
                f"depth_percentiles must satisfy 0 <= lo < hi <= 100, got {self.depth_percentiles!r}"
            )
        if not 0.0 <= self.depth_margin < 1.0:
            raise ConfigError(f"depth_margin must be in [0, 1), got {self.depth_margin}")
        if not 0.0 < self.min_depth_ratio < 1.0:
            raise ConfigError(f"min_depth_ratio must be in (0, 1), got {self.min_depth_ratio}")
        if not (np.isfinite(self.depth_outlier_sigmas) and self.depth_outlier_sigmas >= 0):
            raise ConfigError(f"depth_outlier_sigmas must be >= 0, got {self.depth_outlier_sigmas}")
        if not (np.isfinite(self.depth_outlier_min_factor) and self.depth_outlier_min_factor > 1):
            raise ConfigError(f"depth_outlier_min_factor must be > 1, got {self.depth_outlier_min_factor}")
        if not 0.0 <= self.depth_outlier_max_fraction < 0.5:
            raise ConfigError(
                f"depth_outlier_max_fraction must be in [0, 0.5), got {self.depth_outlier_max_fraction}"
            )


# --------------------------------------------------------------------------- scores


def angle_weight(
    theta_deg: np.ndarray | float, theta0_deg: float, sigma1: float, sigma2: float
) -> np.ndarray:
    """MVSNet's piecewise Gaussian ``G(theta)`` (element-wise, ``theta`` in degrees; any shape)."""
    theta = np.asarray(theta_deg, dtype=np.float64)
    sigma = np.where(theta <= theta0_deg, sigma1, sigma2)
    return np.exp(-((theta - theta0_deg) ** 2) / (2.0 * sigma**2))


@dataclass(frozen=True, eq=False)
class PairStatistics:
    """Pairwise statistics of all registered images.

    Attributes:
        image_ids: ``[n]`` int64 image ids in ascending order; row/column ``k`` of the
            matrices below is image ``image_ids[k]``.
        scores: ``[n, n]`` float64 MVSNet scores, symmetric, zero diagonal.
        shared_points: ``[n, n]`` int64 number of sparse points both images observe
            (symmetric, zero diagonal).
    """

    image_ids: np.ndarray
    scores: np.ndarray
    shared_points: np.ndarray


def _clean_tracks(points: Points3D, image_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observations as a clean CSR: each (point, image) once, only registered images, finite points.

    Returns ``(offsets [P + 1], obs_image_index [T'], obs_point_row [T'])`` where
    ``obs_image_index`` indexes ``image_ids`` and observations are sorted by point row, then image.
    """
    n_points = len(points)
    offsets = np.asarray(points.track_offsets, dtype=np.int64)
    track = np.asarray(points.track_image_ids, dtype=np.int64)
    if offsets.shape != (n_points + 1,):
        raise ShapeError(f"track_offsets has shape {offsets.shape}, expected [{n_points + 1}] (P + 1)")
    if offsets[0] != 0 or offsets[-1] != track.shape[0]:
        raise ShapeError(
            f"track_offsets runs from {offsets[0]} to {offsets[-1]}, expected 0 to {track.shape[0]} "
            "(the number of track entries)"
        )
    lengths = np.diff(offsets)
    if np.any(lengths < 0):
        raise ShapeError("track_offsets must be non-decreasing")
    obs_point = np.repeat(np.arange(n_points, dtype=np.int64), lengths)
    n = image_ids.shape[0]
    pos = np.searchsorted(image_ids, track)
    pos_c = np.minimum(pos, max(n - 1, 0))
    known = (pos < n) & (image_ids[pos_c] == track) if n else np.zeros(track.shape, dtype=bool)
    finite = np.all(np.isfinite(np.asarray(points.xyz, dtype=np.float64)), axis=1)
    keep = known & finite[obs_point]
    n_unknown = int(np.count_nonzero(~known))
    if n_unknown:
        logger.debug("ignoring %d track entries of unregistered images", n_unknown)
    key = np.sort(obs_point[keep] * max(n, 1) + pos_c[keep])  # (point, image) pairs, sorted
    if key.shape[0] > 1:
        key = key[np.concatenate([[True], key[1:] != key[:-1]])]  # drop repeated observations
    obs_point = key // max(n, 1)
    obs_image = key % max(n, 1)
    new_offsets = np.zeros(n_points + 1, dtype=np.int64)
    np.cumsum(np.bincount(obs_point, minlength=n_points), out=new_offsets[1:])
    return new_offsets, obs_image, obs_point


def _pair_indices(offsets: np.ndarray, p0: int, p1: int) -> tuple[np.ndarray, np.ndarray]:
    """All unordered observation pairs ``(a, b)``, ``a < b``, within the tracks of points ``p0..p1-1``.

    Returns two ``[K]`` int64 arrays of observation indices, ``K = sum_p L_p (L_p - 1) / 2``.
    """
    lengths = np.diff(offsets[p0 : p1 + 1])
    obs = np.arange(offsets[p0], offsets[p1], dtype=np.int64)
    pos = obs - np.repeat(offsets[p0:p1], lengths)
    after = np.repeat(lengths, lengths) - 1 - pos  # observations that follow in the same track
    first = np.repeat(obs, after)
    run_start = np.cumsum(after) - after
    second = first + 1 + (np.arange(first.shape[0], dtype=np.int64) - np.repeat(run_start, after))
    return first, second


@dataclass(frozen=True, eq=False)
class _Observations:
    """Clean observations (see :func:`_clean_tracks`) with one unit ray each, camera centre -> point.

    ``offsets [P + 1]``, ``image [T]`` (index into the image ids), ``point [T]`` (point row),
    ``rays [T, 3]``, ``valid [T]`` (False for a point at the camera centre).
    """

    offsets: np.ndarray
    image: np.ndarray
    point: np.ndarray
    rays: np.ndarray
    valid: np.ndarray
    num_images: int


def _observations(model: SparseModel, image_ids: np.ndarray) -> _Observations:
    centers = np.stack([model.images[int(i)].center for i in image_ids]).astype(np.float64)  # [n, 3]
    xyz = np.asarray(model.points.xyz, dtype=np.float64)  # [P, 3]
    offsets, obs_image, obs_point = _clean_tracks(model.points, image_ids)
    rays = xyz[obs_point] - centers[obs_image]
    norms = np.linalg.norm(rays, axis=1)
    valid = norms > 0
    rays = rays / np.where(valid, norms, 1.0)[:, None]
    return _Observations(offsets, obs_image, obs_point, rays, valid, int(image_ids.shape[0]))


def coverage_order(
    obs: _Observations,
    reference: int,
    candidates: np.ndarray,
    count: int,
    config: ViewSelectionConfig,
    *,
    theta0_deg: float | None = None,
    _by_image: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """The first ``count`` of ``candidates`` in coverage-aware order (greedy, best first).

    Each step picks the candidate ``j`` with the largest ``sum_p G(theta_rj(p)) decay^c(p)`` over
    the sparse points ``p`` that the reference ``r`` and ``j`` both observe, where ``c(p)`` counts
    the picks so far that observe ``p`` (``decay = config.coverage_decay``). The first pick is the
    best by MVSNet score; later picks prefer views of the parts of the reference the picked views
    miss. Ties go to the earlier candidate. ``decay = 1`` returns ``candidates[:count]``.
    ``theta0_deg`` (default: ``config.theta0_deg``) replaces the score's preferred angle; then
    ``candidates`` need not be in that score's order (``decay = 1``: the top ``count`` by it).

    Args:
        obs: the model's observations; ``reference`` and ``candidates`` ``[k]`` index its images.
        _by_image: ``(order, offsets)``, observations grouped by image (computed when ``None``).

    Returns:
        ``[min(count, k)]`` int64 indices, a reordering of a subset of ``candidates``.
    """
    candidates = np.asarray(candidates, dtype=np.int64)
    count = min(int(count), candidates.shape[0])
    if theta0_deg is None and (config.coverage_decay >= 1.0 or count <= 1):
        return candidates[:count]  # already in the order of the config's own score
    theta0 = config.theta0_deg if theta0_deg is None else theta0_deg
    if _by_image is None:
        _by_image = _group_by_image(obs)
    order, image_offsets = _by_image
    ref_obs = order[image_offsets[reference] : image_offsets[reference + 1]]
    ref_obs = ref_obs[obs.valid[ref_obs]]
    pts = obs.point[ref_obs]  # the reference's points, one observation each
    lengths = obs.offsets[pts + 1] - obs.offsets[pts]
    other = np.repeat(obs.offsets[pts], lengths) + (
        np.arange(int(lengths.sum()), dtype=np.int64) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    )
    mine = np.repeat(ref_obs, lengths)
    local = np.repeat(np.arange(pts.shape[0], dtype=np.int64), lengths)  # which reference point
    keep = obs.valid[other] & (obs.image[other] != reference)
    other, mine, local = other[keep], mine[keep], local[keep]
    cos = np.einsum("ij,ij->i", obs.rays[mine], obs.rays[other])
    sin = np.linalg.norm(np.cross(obs.rays[mine], obs.rays[other]), axis=1)
    g = angle_weight(np.degrees(np.arctan2(sin, cos)), theta0, config.sigma1, config.sigma2)
    slot = np.full(obs.num_images, -1, dtype=np.int64)
    slot[candidates] = np.arange(candidates.shape[0])
    cand = slot[obs.image[other]]
    ok = cand >= 0
    g, cand, local = g[ok], cand[ok], local[ok]
    seen = np.zeros(pts.shape[0], dtype=np.float64)  # picks observing each reference point
    picked: list[int] = []
    free = np.ones(candidates.shape[0], dtype=bool)
    for _ in range(count):
        weights = g * config.coverage_decay ** seen[local]
        gain = np.bincount(cand, weights=weights, minlength=candidates.shape[0])
        gain[~free] = -np.inf
        best = int(np.argmax(gain))
        picked.append(best)
        free[best] = False
        seen[np.unique(local[cand == best])] += 1.0
    return candidates[np.asarray(picked, dtype=np.int64)]


def _group_by_image(obs: _Observations) -> tuple[np.ndarray, np.ndarray]:
    n = obs.num_images
    order = np.argsort(obs.image, kind="stable")
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(obs.image, minlength=n), out=offsets[1:])
    return order, offsets


def compute_pair_statistics(model: SparseModel, config: ViewSelectionConfig | None = None) -> PairStatistics:
    """MVSNet scores and shared-point counts of all image pairs (see the module docstring).

    Track entries of images that are not in ``model.images``, repeated observations of
    a point by one image and points with non-finite coordinates are ignored.
    A point at a camera centre (zero-length ray) contributes nothing to that camera.
    """
    return _pair_statistics(model, config or ViewSelectionConfig())[0]


def _pair_statistics(
    model: SparseModel, config: ViewSelectionConfig
) -> tuple[PairStatistics, _Observations | None]:
    image_ids = np.array(sorted(model.images), dtype=np.int64)
    n = image_ids.shape[0]
    scores = np.zeros((n, n), dtype=np.float64)
    shared = np.zeros((n, n), dtype=np.int64)
    if n < 2 or len(model.points) == 0:
        return PairStatistics(image_ids, scores, shared), None

    obs = _observations(model, image_ids)
    offsets, obs_image, rays, valid = obs.offsets, obs.image, obs.rays, obs.valid
    lengths = np.diff(offsets)
    pairs_per_point = lengths * (lengths - 1) // 2
    cum_pairs = np.cumsum(pairs_per_point)
    flat_scores = np.zeros(n * n, dtype=np.float64)
    flat_shared = np.zeros(n * n, dtype=np.int64)
    n_points = lengths.shape[0]
    p0 = 0
    while p0 < n_points:
        done = cum_pairs[p0 - 1] if p0 else 0
        # Largest p1 with pairs(p0..p1-1) <= budget, but always at least one point.
        p1 = int(np.searchsorted(cum_pairs, done + _MAX_PAIRS_PER_CHUNK, side="right"))
        p1 = max(p1, p0 + 1)
        a, b = _pair_indices(offsets, p0, p1)
        p0 = p1
        if a.shape[0] == 0:
            continue
        ok = valid[a] & valid[b]
        a, b = a[ok], b[ok]
        ra, rb = rays[a], rays[b]
        cos = np.einsum("ij,ij->i", ra, rb)
        sin = np.linalg.norm(np.cross(ra, rb), axis=1)
        theta = np.degrees(np.arctan2(sin, cos))
        g = angle_weight(theta, config.theta0_deg, config.sigma1, config.sigma2)
        lin = obs_image[a] * n + obs_image[b]
        flat_scores += np.bincount(lin, weights=g, minlength=n * n)
        flat_shared += np.bincount(lin, minlength=n * n)

    scores = flat_scores.reshape(n, n)
    shared = flat_shared.reshape(n, n)
    scores = scores + scores.T
    shared = shared + shared.T
    np.fill_diagonal(scores, 0.0)
    np.fill_diagonal(shared, 0)
    return PairStatistics(image_ids, scores, shared), obs


def compute_view_scores(
    model: SparseModel, config: ViewSelectionConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """MVSNet view scores of all image pairs.

    Returns:
        ``(image_ids [n] int64 ascending, scores [n, n] float64)``; symmetric, zero diagonal.
    """
    stats = compute_pair_statistics(model, config)
    return stats.image_ids, stats.scores


# --------------------------------------------------------------------------- depth ranges


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
    return _depth_range_from_depths(depths, config), note


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


# --------------------------------------------------------------------------- ranking


def _as_score_row(scores: np.ndarray) -> np.ndarray:
    """A ``[n]`` float64 copy of a score row where masked / NaN / -inf entries become -inf."""
    if isinstance(scores, np.ma.MaskedArray):
        row = scores.astype(np.float64).filled(-np.inf)
    else:
        row = np.array(scores, dtype=np.float64)
    if row.ndim != 1:
        raise ShapeError(f"expected one score row of shape [n], got shape {row.shape}")
    row[~np.isfinite(row)] = -np.inf
    return row


def rank_sources(
    scores: np.ndarray,
    shared_points: np.ndarray | None = None,
    min_shared_points: int = 1,
) -> np.ndarray:
    """Candidate sources of one reference, best first.

    Args:
        scores: ``[n]`` scores of one reference against every image. The reference itself
            must be excluded: ``-inf``, NaN or masked (``np.ma``) entries are never candidates.
        shared_points: optional ``[n]`` shared-point counts; entries below
            ``min_shared_points`` are not candidates.
        min_shared_points: see ``shared_points``.

    Returns:
        ``[k]`` int64 indices of the candidates (finite score ``> 0``, enough shared points),
        ordered by decreasing score; ties by increasing index.
    """
    row = _as_score_row(scores)
    ok = row > 0
    if shared_points is not None:
        shared = np.asarray(shared_points)
        if shared.shape != row.shape:
            raise ShapeError(f"shared_points has shape {shared.shape}, expected {row.shape} like scores")
        ok &= shared >= min_shared_points
    idx = np.flatnonzero(ok)
    return idx[np.lexsort((idx, -row[idx]))].astype(np.int64)


def best_and_worst(scores: np.ndarray, n_best: int = 2, n_worst: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """The ``n_best`` best and ``n_worst`` worst candidate sources of one reference.

    Used by training's anti-noise strategy. Candidates are the images with a finite
    score ``> 0``, i.e. that share at least one sparse point with the reference (an image
    sharing nothing is not a "bad view", it is not a view of the scene at all).
    The reference must be excluded as ``-inf``, NaN or a masked entry.

    The best are taken first; the worst are the lowest-scoring remaining candidates, so
    the two sets never overlap. With fewer than ``n_best + n_worst`` candidates the worst
    set is shorter (possibly empty); with fewer than ``n_best`` the best set is too.

    Args:
        scores: ``[n]`` float scores of one reference against every image.

    Returns:
        ``(best_idx [<= n_best], worst_idx [<= n_worst])`` int64; best by decreasing score,
        worst by increasing score (the very worst first); ties by increasing index.
    """
    if n_best < 0 or n_worst < 0:
        raise ValueError(f"n_best and n_worst must be >= 0, got n_best={n_best}, n_worst={n_worst}")
    ranked = rank_sources(scores)
    best = ranked[:n_best]
    rest = ranked[n_best:]
    row = _as_score_row(scores)
    worst = rest[np.lexsort((rest, row[rest]))][:n_worst]
    return best.astype(np.int64), worst.astype(np.int64)


# --------------------------------------------------------------------------- selection


@dataclass(frozen=True, eq=False)
class ReferenceViews:
    """View selection of one reference image.

    Attributes:
        name, image_id: the reference image.
        num_points: observed sparse points in front of the camera (used for the depth range).
        depth_range: ``(dmin, dmax)``, both ``> 0``.
        source_names: the first ``num_views - 1`` of ``ranked_names``.
        source_scores: their MVSNet scores.
        ranked_names: every candidate source (score ``> 0``, at least
            ``min_shared_points`` shared points) in selection order: the first picks in
            coverage-aware order (:func:`coverage_order`; the very first is the best by score),
            the others by decreasing score; ``source_names`` is a prefix.
        ranked_scores: ``[k]`` float64 their scores.
    """

    name: str
    image_id: int
    num_points: int
    depth_range: tuple[float, float]
    source_names: tuple[str, ...]
    source_scores: tuple[float, ...]
    ranked_names: tuple[str, ...]
    ranked_scores: np.ndarray


@dataclass(frozen=True)
class SkippedImage:
    """An image that gets no depth map, and why."""

    name: str
    image_id: int
    num_points: int
    reason: str


@dataclass(frozen=True, eq=False)
class ViewSelection:
    """Result of :func:`select_views`.

    Attributes:
        names: ``n`` image names, in the order of ``image_ids`` (ascending ids).
        image_ids: ``[n]`` int64.
        scores: ``[n, n]`` float64 MVSNet scores (symmetric, zero diagonal).
        shared_points: ``[n, n]`` int64 shared sparse points (symmetric, zero diagonal).
        references: reference name -> :class:`ReferenceViews`, for every image that was not skipped,
            in ascending image-id order.
        skipped: images that are not references, with the reason.
        config: the config used.
    """

    names: tuple[str, ...]
    image_ids: np.ndarray
    scores: np.ndarray
    shared_points: np.ndarray
    references: dict[str, ReferenceViews]
    skipped: tuple[SkippedImage, ...]
    config: ViewSelectionConfig

    def index_of(self, name: str) -> int:
        """Row of image ``name`` in ``scores``; :class:`WorkspaceError` if unknown."""
        try:
            return self._index[name]
        except KeyError:
            raise WorkspaceError(f"image {name!r} is not in the sparse model") from None

    @property
    def _index(self) -> dict[str, int]:
        cached = self.__dict__.get("_index_cache")
        if cached is None:
            cached = {name: k for k, name in enumerate(self.names)}
            object.__setattr__(self, "_index_cache", cached)
        return cached

    def score_row(self, name: str) -> np.ndarray:
        """``[n]`` float64 scores of ``name`` against every image, ``-inf`` at ``name`` itself."""
        k = self.index_of(name)
        row = self.scores[k].copy()
        row[k] = -np.inf
        return row

    def sources(self, name: str) -> tuple[str, ...]:
        """Selected source names of reference ``name`` (``()`` if it was skipped)."""
        self.index_of(name)
        ref = self.references.get(name)
        return ref.source_names if ref is not None else ()


def _names_preview(names: Sequence[str], limit: int = 3) -> str:
    shown = ", ".join(repr(n) for n in names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


def _log_selection_summary(
    n_images: int, skipped: Sequence[SkippedImage], few_sources: Sequence[str], n_sources: int,
    n_outliers: int,
) -> None:
    """One short line per kind of per-image note of :func:`select_views` (the details of
    each image are at DEBUG, which ``--log_level DEBUG`` shows)."""
    if skipped:  # the user may want to act: these images get no depth map
        logger.warning(
            "view selection skips %d of %d image(s), which get no depth map (too few sparse points or no "
            "overlapping view): %s",
            len(skipped), n_images, _names_preview([s.name for s in skipped]),
        )
    if few_sources:
        logger.info(
            "%d of %d image(s) have fewer than num_views-1=%d candidate sources (details: --log_level DEBUG)",
            len(few_sources), n_images, n_sources,
        )
    if n_outliers:  # harmless and expected: SfM noise
        logger.info(
            "depth ranges of %d of %d image(s) leave out a few far outlier sparse points "
            "(details: --log_level DEBUG)",
            n_outliers, n_images,
        )


def select_views(model: SparseModel, config: ViewSelectionConfig | None = None) -> ViewSelection:
    """Select sources and a depth range for every registered image.

    An image is skipped (never an exception) when it observes fewer than
    ``config.min_points`` sparse points in front of it, or when no other image is a
    candidate source (score ``> 0`` and at least ``config.min_shared_points`` shared points).
    Each kind of per-image note (skipped, few candidate sources, depth outliers left out) is logged
    as one summary line; the per-image details are at DEBUG.
    """
    config = config or ViewSelectionConfig()
    stats, obs = _pair_statistics(model, config)
    wide = min(config.wide_sources, (config.num_views - 1) // 2)
    by_image = (_group_by_image(obs) if obs is not None and (config.coverage_decay < 1.0 or wide > 0)
                else None)
    names = tuple(model.images[int(i)].name for i in stats.image_ids)
    order = np.argsort(np.asarray(model.points.ids, dtype=np.int64), kind="stable")
    n_sources = config.num_views - 1
    references: dict[str, ReferenceViews] = {}
    skipped: list[SkippedImage] = []
    outlier_notes: list[str] = []
    few_sources: list[str] = []
    for k, image_id in enumerate(stats.image_ids):
        image = model.images[int(image_id)]
        depths = _observed_depths(model, image, order)
        if depths.shape[0] < config.min_points:
            reason = (
                f"{depths.shape[0]} sparse point(s) in front of the camera, fewer than "
                f"min_points={config.min_points}"
            )
            logger.debug("skipping image %r: %s", image.name, reason)
            skipped.append(SkippedImage(image.name, int(image_id), int(depths.shape[0]), reason))
            continue
        row = stats.scores[k].copy()
        row[k] = -np.inf
        ranked = rank_sources(row, stats.shared_points[k], config.min_shared_points)
        if ranked.shape[0] == 0:
            reason = f"no other image shares >= min_shared_points={config.min_shared_points} sparse points"
            logger.debug("skipping image %r: %s", image.name, reason)
            skipped.append(SkippedImage(image.name, int(image_id), int(depths.shape[0]), reason))
            continue
        if ranked.shape[0] < n_sources:
            few_sources.append(image.name)
            logger.debug(
                "image %r has only %d candidate source(s) (num_views-1=%d)",
                image.name,
                ranked.shape[0],
                n_sources,
            )
        if by_image is not None and config.coverage_decay < 1.0:
            # coverage-aware order of the first picks (the geometric pass: 10)
            picks = max(n_sources, _COVERAGE_PICKS)
            first = coverage_order(obs, k, ranked, picks, config, _by_image=by_image)
            ranked = np.concatenate([first, ranked[~np.isin(ranked, first)]])
        if by_image is not None and wide > 0 and ranked.shape[0] > n_sources - wide:
            # the last `wide` sources: the best of the rest by the score at wide_theta0_deg
            near = ranked[: n_sources - wide]
            rest = ranked[n_sources - wide :]
            far = coverage_order(obs, k, rest, wide, config, theta0_deg=config.wide_theta0_deg,
                                 _by_image=by_image)
            ranked = np.concatenate([near, far, rest[~np.isin(rest, far)]])
        ranked_names = tuple(names[j] for j in ranked)
        ranked_scores = row[ranked]
        depth_range, note = _robust_depth_range(depths, config, repr(image.name))
        if note is not None:
            outlier_notes.append(note)
            logger.debug("image %s", note)
        references[image.name] = ReferenceViews(
            name=image.name,
            image_id=int(image_id),
            num_points=int(depths.shape[0]),
            depth_range=depth_range,
            source_names=ranked_names[:n_sources],
            source_scores=tuple(float(s) for s in ranked_scores[:n_sources]),
            ranked_names=ranked_names,
            ranked_scores=ranked_scores,
        )
    _log_selection_summary(len(names), skipped, few_sources, n_sources, len(outlier_notes))
    return ViewSelection(
        names=names,
        image_ids=stats.image_ids,
        scores=stats.scores,
        shared_points=stats.shared_points,
        references=references,
        skipped=tuple(skipped),
        config=config,
    )


def reference_sources(
    selection: ViewSelection, ref_name: str, spec: object | None, num: int
) -> tuple[str, ...]:
    """Source images of ``ref_name`` as ``stereo`` and ``fuse`` use them.

    ``spec`` is the reference's ``patch-match.cfg`` entry (``colmap_pvs.io.workspace.SourceSpec``:
    ``mode``, ``names``, ``num``) or ``None`` (no file: the ``num`` best by view score). An
    ``__auto__``/``__all__`` entry is capped at ``num``; an explicit list is used as written.
    Raises what :func:`resolve_sources` raises.
    """
    if spec is None:
        return resolve_sources(selection, ref_name, "auto", num=num)
    sources = resolve_sources(selection, ref_name, spec.mode, names=spec.names, num=spec.num)
    return sources if spec.mode == "explicit" else sources[:num]


def resolve_sources(
    selection_or_scores: ViewSelection | tuple[Sequence[str], np.ndarray],
    ref_name: str,
    mode: Literal["explicit", "auto", "all"],
    names: Sequence[str] = (),
    num: int = 0,
) -> tuple[str, ...]:
    """Source images of ``ref_name`` for one entry of a COLMAP ``patch-match.cfg``.

    The fields are those of ``colmap_pvs.io.workspace.SourceSpec``:

    - ``"explicit"``: ``names`` as given (duplicates dropped with a warning); every
      name must be an image of the model, and not the reference itself.
    - ``"auto"`` (``__auto__, num``): the ``num`` best candidate sources by score (score
      ``> 0``); with a :class:`ViewSelection`, the first ``num`` of the reference's
      ``ranked_names`` (coverage-aware order, ``>= min_shared_points``).
    - ``"all"`` (``__all__``): every other image, by decreasing score (ties by name order);
      with a :class:`ViewSelection`, the reference's ``ranked_names`` come first.

    Args:
        selection_or_scores: a :class:`ViewSelection`, or ``(image_names [n], scores [n, n])``.

    Raises:
        WorkspaceError: unknown reference or source name, the reference listed as its own
            source, an empty explicit list, or ``num < 1`` in ``"auto"`` mode.
    """
    if isinstance(selection_or_scores, ViewSelection):
        all_names = selection_or_scores.names
        scores = selection_or_scores.scores
        shared = selection_or_scores.shared_points
        min_shared = selection_or_scores.config.min_shared_points
    else:
        all_names, scores = selection_or_scores
        all_names = tuple(all_names)
        scores = np.asarray(scores, dtype=np.float64)
        shared, min_shared = None, 1
        if scores.shape != (len(all_names), len(all_names)):
            raise ShapeError(
                f"scores has shape {scores.shape}, expected [{len(all_names)}, {len(all_names)}]"
            )
    selected = None
    if isinstance(selection_or_scores, ViewSelection):
        selected = selection_or_scores.references.get(ref_name)
    index = {name: k for k, name in enumerate(all_names)}
    if ref_name not in index:
        raise WorkspaceError(f"reference image {ref_name!r} is not in the sparse model")
    k = index[ref_name]
    if mode == "explicit":
        if len(names) == 0:
            raise WorkspaceError(f"no source images listed for reference {ref_name!r}")
        out: list[str] = []
        for name in names:
            if name not in index:
                raise WorkspaceError(
                    f"source image {name!r} of reference {ref_name!r} is not in the sparse model"
                )
            if name == ref_name:
                raise WorkspaceError(f"reference image {ref_name!r} is listed as its own source")
            if name in out:
                logger.warning("source image %r listed twice for reference %r", name, ref_name)
                continue
            out.append(name)
        return tuple(out)
    row = np.array(scores[k], dtype=np.float64)
    row[k] = -np.inf
    if mode == "auto":
        if isinstance(num, bool) or int(num) != num or num < 1:
            raise WorkspaceError(f"__auto__ needs a positive number of sources for {ref_name!r}, got {num!r}")
        if selected is not None:
            return selected.ranked_names[: int(num)]
        ranked = rank_sources(row, None if shared is None else shared[k], min_shared)
        return tuple(all_names[j] for j in ranked[: int(num)])
    if mode == "all":
        others = np.array([j for j in range(len(all_names)) if j != k], dtype=np.int64)
        ordered = tuple(all_names[j] for j in others[np.lexsort((others, -row[others]))])
        if selected is not None:  # the selection's order first (coverage-aware), then the rest
            first = set(selected.ranked_names)
            ordered = selected.ranked_names + tuple(n for n in ordered if n not in first)
        return ordered
    raise WorkspaceError(f"unknown source mode {mode!r}; expected 'explicit', 'auto' or 'all'")


# --------------------------------------------------------------------------- reporting


def format_selection_table(selection: ViewSelection) -> str:
    """A plain-text table of ``selection`` for the CLI: one row per image, skipped ones included."""
    header = ("reference", "#points", "depth range", "sources (score)")
    rows: list[tuple[str, str, str, str]] = []
    skipped = {s.name: s for s in selection.skipped}
    for name in selection.names:
        ref = selection.references.get(name)
        if ref is not None:
            dmin, dmax = ref.depth_range
            sources = ", ".join(
                f"{s} ({v:.1f})" for s, v in zip(ref.source_names, ref.source_scores, strict=True)
            )
            rows.append((name, str(ref.num_points), f"{dmin:.4g} .. {dmax:.4g}", sources))
        elif name in skipped:
            s = skipped[name]
            rows.append((name, str(s.num_points), "-", f"SKIPPED: {s.reason}"))
    widths = [max(len(r[c]) for r in [header, *rows]) for c in range(3)]

    def line(r: tuple[str, str, str, str]) -> str:
        return f"{r[0]:<{widths[0]}}  {r[1]:>{widths[1]}}  {r[2]:<{widths[2]}}  {r[3]}".rstrip()

    lines = [line(r) for r in rows]
    rule = "-" * max(len(x) for x in [line(header), *lines])
    summary = (
        f"{len(selection.references)} reference(s), {len(selection.skipped)} skipped, "
        f"num_views={selection.config.num_views}"
    )
    return "\n".join([line(header), rule, *lines, rule, summary])


# --------------------------------------------------------------------------- workspace step


@dataclass(frozen=True)
class SelectViewsConfig:
    """The ``select-views`` step on a dense workspace (writes ``stereo/patch-match.cfg``)."""

    workspace_path: Path = field(metadata={"help": "COLMAP dense workspace (images/, sparse/, stereo/)"})
    num_views: int = field(default=5, metadata={"help": "views per reference: reference + N-1 sources"})
    write_cfg: bool = field(
        default=True, metadata={"help": "write stereo/patch-match.cfg with the explicit source lists"}
    )
    wide_sources: int = field(default=0, metadata={"help": WIDE_SOURCES_HELP})


def run_select_views(config: SelectViewsConfig) -> ViewSelection:
    """Select source views and depth ranges for every image of a workspace.

    Writes ``stereo/patch-match.cfg`` (COLMAP's format: the reference name on one line,
    its comma-separated sources on the next) for the images that were not skipped. A
    ``patch-match.cfg`` that colmap-pvs did not write (``image_undistorter``'s ``__auto__, 20``, or a
    hand-made one) is kept as ``stereo/patch-match.cfg.bak`` first, with a warning.
    """
    from .io.workspace import load_workspace, write_patch_match_cfg

    ws, model = load_workspace(config.workspace_path)
    selection = select_views(
        model, ViewSelectionConfig(num_views=config.num_views, wide_sources=config.wide_sources)
    )
    if config.write_cfg:
        write_patch_match_cfg(
            ws.patch_match_cfg, {name: ref.source_names for name, ref in selection.references.items()}
        )
        logger.info("wrote %s (%d references)", ws.patch_match_cfg, len(selection.references))
    return selection
