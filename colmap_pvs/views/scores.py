"""MVSNet view scores of all image pairs at once, and the ranking of a reference's sources."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..errors import ShapeError
from ..types import Points3D, SparseModel
from .config import ViewSelectionConfig

logger = logging.getLogger(__name__)

# The pair scores are summed per chunk of at most this many observation pairs (one bincount per chunk:
# the chunking fixes the order of the float sums, hence the scores to the last bit).
_MAX_PAIRS_PER_CHUNK = 1 << 22
# Within a chunk, the pairs' angles are computed this many at a time (~150 B per pair while computed,
# 16 B per pair kept until the chunk's bincount): the peak memory, not the sums.
_MAX_PAIRS_PER_STEP = 1 << 18


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
        lins, gs = [], []
        q0 = p0
        while q0 < p1:  # the chunk's pairs in order, a step of points at a time
            q_done = cum_pairs[q0 - 1] if q0 else 0
            q1 = int(np.searchsorted(cum_pairs, q_done + _MAX_PAIRS_PER_STEP, side="right"))
            q1 = min(max(q1, q0 + 1), p1)
            a, b = _pair_indices(offsets, q0, q1)
            q0 = q1
            ok = valid[a] & valid[b]
            a, b = a[ok], b[ok]
            ra, rb = rays[a], rays[b]
            cos = np.einsum("ij,ij->i", ra, rb)
            sin = np.linalg.norm(np.cross(ra, rb), axis=1)
            theta = np.degrees(np.arctan2(sin, cos))
            gs.append(angle_weight(theta, config.theta0_deg, config.sigma1, config.sigma2))
            lins.append(obs_image[a] * n + obs_image[b])
        p0 = p1
        lin, g = np.concatenate(lins), np.concatenate(gs)
        del lins, gs
        if lin.shape[0] == 0:
            continue
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
