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

This package never imports pycolmap; it consumes :class:`~colmap_pvs.types.SparseModel`.

One concern a module: :mod:`.config` (:class:`ViewSelectionConfig`), :mod:`.scores` (the pairwise
scores and the ranking of sources), :mod:`.depth_range` (per-image depth ranges), :mod:`.selection`
(:func:`select_views` and the lookups of its result) and :mod:`.step` (the ``select-views`` step on
a workspace).
"""

from __future__ import annotations

from .config import WIDE_SOURCES_HELP, ViewSelectionConfig
from .depth_range import compute_depth_range
from .scores import (
    PairStatistics,
    angle_weight,
    best_and_worst,
    compute_pair_statistics,
    compute_view_scores,
    coverage_order,
    rank_sources,
)
from .selection import (
    ReferenceViews,
    SkippedImage,
    ViewSelection,
    reference_sources,
    resolve_sources,
    select_views,
)
from .step import SelectViewsConfig, format_selection_table, run_select_views

__all__ = [
    "WIDE_SOURCES_HELP",
    "PairStatistics",
    "ReferenceViews",
    "SelectViewsConfig",
    "SkippedImage",
    "ViewSelection",
    "ViewSelectionConfig",
    "angle_weight",
    "best_and_worst",
    "compute_depth_range",
    "compute_pair_statistics",
    "compute_view_scores",
    "coverage_order",
    "format_selection_table",
    "rank_sources",
    "reference_sources",
    "resolve_sources",
    "run_select_views",
    "select_views",
]
