"""Issue 11: depth ranges are robust to far outlier sparse points (rule in docs/CONVENTIONS.md)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from test_views import depths_model, make_model

from colmap_pvs.views import ViewSelectionConfig, compute_depth_range, select_views


def _scene(n_inliers: int, outliers: int, factor: float, seed: int = 0):
    """Image 1 at (10, 0, 0) looks at the origin; inliers at depths 4..7, outliers ``factor`` x farther."""
    rng = np.random.default_rng(seed)
    depth = rng.uniform(4.0, 7.0, n_inliers)
    lateral = rng.uniform(-0.5, 0.5, (n_inliers, 2))
    center = np.array([10.0, 0.0, 0.0])
    inl = np.stack([center[0] - depth, lateral[:, 0], lateral[:, 1]], axis=1)
    idx = rng.choice(n_inliers, outliers, replace=False)
    far = center + (inl[idx] - center) * factor
    xyz = np.concatenate([inl, far])
    centers = np.array([center, [0.0, 10.0, 0.0], [0.0, -10.0, 0.0]])
    return make_model(centers, xyz, [[1, 2, 3]] * len(xyz))


@pytest.mark.parametrize(
    ("n_inliers", "outliers", "factor"),
    [(297, 5, 1e6), (294, 8, 10.0), (1000, 26, 10.0), (300, 3, 1e-3)],  # 1e-3: outliers near the camera
)
def test_far_outliers_do_not_widen_the_depth_range(n_inliers, outliers, factor, caplog):
    model = _scene(n_inliers, outliers, factor)
    with caplog.at_level("DEBUG", logger="colmap_pvs.views"):
        dmin, dmax = compute_depth_range(model, model.images[1])
    assert 4.0 * 0.75 * 0.98 <= dmin <= 4.2 * 0.75 and 6.8 * 1.25 <= dmax <= 7.0 * 1.25 * 1.02
    assert "outlier" in caplog.text and f"{outliers} of {n_inliers + outliers}" in caplog.text
    assert all(r.levelname == "DEBUG" for r in caplog.records)  # harmless: a detail (issue 41)
    # select_views uses the same rule, and says so once
    caplog.clear()
    with caplog.at_level("INFO"):
        sel = select_views(model)
    assert sel.references["img_001.jpg"].depth_range == pytest.approx((dmin, dmax))
    summary = [r for r in caplog.records if "outlier" in r.getMessage()]
    assert len(summary) == 1 and summary[0].levelname == "INFO"


def test_outlier_notes_are_one_short_summary_with_details_at_debug(caplog):
    """Issue 41 item 7: one short INFO line for all images whose depth range left out outliers, no
    WARNING, and the per-image counts only at DEBUG."""
    model = _scene(297, 5, 1e6)  # all three images see the far points
    with caplog.at_level("DEBUG", logger="colmap_pvs.views"):
        select_views(model)
    records = [r for r in caplog.records if "outlier" in r.getMessage()]
    above = [r for r in records if r.levelno > logging.DEBUG]
    assert len(above) == 1 and above[0].levelname == "INFO"
    assert len(above[0].getMessage()) < 150 and "3 of 3 image(s)" in above[0].getMessage()
    details = [r for r in records if r.levelno == logging.DEBUG]
    assert len(details) == 3 and "5 of 302 sparse points" in details[0].getMessage()
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_structure_is_not_an_outlier():
    # 30 % of the points 10x farther: a background, not outliers; the range must cover it
    model = _scene(200, 86, 10.0)
    dmin, dmax = compute_depth_range(model, model.images[1])
    assert dmax > 40.0 and dmin < 4.0


def test_wide_scenes_keep_their_range():
    # depths spread log-uniformly over 1..100: nothing is an outlier
    rng = np.random.default_rng(1)
    depth = np.exp(rng.uniform(0, np.log(100.0), 400))
    xyz = np.stack([10.0 - depth, np.zeros(400), np.zeros(400)], axis=1)
    model = make_model(np.array([[10.0, 0, 0], [0, 10.0, 0]]), xyz, [[1, 2]] * 400)
    lo, hi = np.percentile(depth, [1, 99])
    dmin, dmax = compute_depth_range(model, model.images[1])
    assert dmin == pytest.approx(0.75 * lo) and dmax == pytest.approx(1.25 * hi)


def test_outlier_rejection_can_be_switched_off():
    model = _scene(297, 5, 1e6)
    cfg = ViewSelectionConfig(depth_outlier_sigmas=0.0)
    _, dmax = compute_depth_range(model, model.images[1], cfg)
    assert dmax > 1e3


def test_only_outlier_hints_are_dropped():
    from colmap_pvs.stereo.context import HINT_OUTLIER_FACTOR, drop_outlier_hints

    assert HINT_OUTLIER_FACTOR == 2.0
    hints = np.array([[5.0, 3.5, 30.0, 1.0, 0.0, 9.0, 2.5]], dtype=np.float32)
    out = drop_outlier_hints(hints.copy(), (4.0, 8.0))
    # just outside the range (3.5, 9, 2.5): kept, a near wall is real; 2x outside (30, 1): dropped
    np.testing.assert_array_equal(out, [[5.0, 3.5, 0.0, 0.0, 0.0, 9.0, 2.5]])


def test_the_outlier_threshold_is_three_robust_sigmas_of_log_depth():
    """Log depths 0, +-0.5 (10 each) around log 4: median 0, MAD 0.5, sigma 1.4826 * 0.5, so a point
    2.1 from the median is kept and one 2.4 away (beyond 3 sigma = 2.22, and beyond factor 5) is not."""
    offsets = [0.0] * 10 + [0.5] * 10 + [-0.5] * 10
    cfg = ViewSelectionConfig(depth_percentiles=(0.0, 100.0), depth_margin=0.0)
    for last, dmax in [(2.1, 4.0 * np.exp(2.1)), (2.4, 4.0 * np.exp(0.5))]:
        model, image = depths_model(4.0 * np.exp(np.array([*offsets, last])))
        assert compute_depth_range(model, image, cfg) == pytest.approx((4.0 * np.exp(-0.5), dmax))


def test_a_point_exactly_min_factor_from_the_median_is_kept():
    """The doc's closed interval ``[median / f, median * f]``: depth 5 with the rest at 1 (sigma 0) stays."""
    cfg = ViewSelectionConfig(depth_percentiles=(0.0, 100.0), depth_margin=0.0, depth_outlier_min_factor=5.0)
    model, image = depths_model([1.0] * 19 + [5.0])
    assert compute_depth_range(model, image, cfg) == pytest.approx((1.0, 5.0))
    model, image = depths_model([1.0] * 19 + [5.001])
    assert compute_depth_range(model, image, cfg) == pytest.approx((0.99, 1.01))


def test_outliers_are_looked_for_from_four_points_on():
    cfg = ViewSelectionConfig(min_points=3, depth_percentiles=(0.0, 100.0), depth_margin=0.0,
                              depth_outlier_max_fraction=0.3)
    model, image = depths_model([2.0, 2.2, 2.4, 200.0])
    assert compute_depth_range(model, image, cfg) == pytest.approx((2.0, 2.4))
    model, image = depths_model([2.0, 2.4, 200.0])  # too few to tell an outlier from the scene
    assert compute_depth_range(model, image, cfg) == pytest.approx((2.0, 200.0))
