"""Source views and depth ranges of every reference image (:func:`select_views`), and their lookup."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..errors import ShapeError, WorkspaceError
from ..types import SparseModel
from .config import ViewSelectionConfig
from .depth_range import _observed_depths, _robust_depth_range
from .scores import _group_by_image, _pair_statistics, coverage_order, rank_sources

logger = logging.getLogger(__name__)

# Candidates put in coverage-aware order per reference (the rest follow by score): the network's
# sources and the geometric pass's extra views come from this prefix.
_COVERAGE_PICKS = 16


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
