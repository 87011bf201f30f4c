"""The frustum-limited ETH3D-style cloud score of ``benchmarks/cloud_benchmark.py``, on a tiny scene."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
if str(BENCHMARKS) not in sys.path:
    sys.path.insert(0, str(BENCHMARKS))

import cloud_benchmark as cb  # noqa: E402  (benchmarks/ is no package: on sys.path above)

W, H, F = 40, 30, 40.0


def _wall_view(z: float = 2.0) -> cb.GTView:
    """A camera at the origin looking down +z at a wall at depth ``z`` (every pixel valid)."""
    K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
    return cb.GTView("a.png", K, np.eye(4)[:3], np.full((H, W), z, np.float32))


def test_gt_cloud_lies_on_the_wall_and_is_voxelised():
    view = _wall_view()
    every = cb.gt_cloud([view], 0.0)
    assert every.shape == (W * H, 3)
    np.testing.assert_allclose(every[:, 2], 2.0)
    thin = cb.gt_cloud([view], 0.2)
    assert 0 < len(thin) < len(every)
    np.testing.assert_allclose(thin[:, 2], 2.0)


def test_observed_mask_ignores_points_outside_or_behind_the_gt():
    view = _wall_view()
    pts = np.array([
        [0.0, 0.0, 2.0],    # on the wall: observed
        [0.1, 0.0, 1.0],    # in front of the wall (free space the GT saw): observed
        [0.0, 0.1, 2.05],   # just behind, within 10 cm: observed
        [0.0, 0.0, 3.0],    # 1 m behind the wall: unobserved
        [10.0, 0.0, 2.0],   # outside the image: unobserved
        [0.0, 0.0, -2.0],   # behind the camera: unobserved
    ])
    np.testing.assert_array_equal(cb.observed_mask(pts, [view], 0.1), [1, 1, 1, 0, 0, 0])
    invalid = cb.GTView("b.png", view.K, view.cam_from_world, np.zeros((H, W), np.float32))
    assert not cb.observed_mask(pts, [invalid], 0.1).any()  # no valid GT depth observes nothing


def test_frustum_score_counts_accuracy_only_where_observed():
    view = _wall_view()
    gt = cb.gt_cloud([view], 0.0)
    good = gt[::7] + np.array([0.0, 0.0, 0.01])         # 1 cm off the wall: accurate at 2 cm
    wrong = gt[3::50] * 0.75   # on their pixel's ray, 50 cm in front: observed, inaccurate
    hidden = gt[5::50] * 1.5   # on their ray, 1 m behind: not counted
    outside = np.array([[30.0, 0.0, 2.0], [0.0, 40.0, 2.0]])  # outside the frustum: not counted
    pts = np.concatenate([good, wrong, hidden, outside])
    s = cb.frustum_cloud_score(pts, gt, [view], thresholds=(0.02, 0.05, 0.1), voxel_size=0.01)
    assert s["num_points"] == len(pts)
    assert s["num_observed"] == len(good) + len(wrong)
    expected = 100.0 * len(good) / (len(good) + len(wrong))
    np.testing.assert_allclose(s["accuracy_points_pct"], expected)
    # every point counted (no frustum), the hidden and outside points would lower it
    assert s["accuracy_unmasked_pct"][0] < s["accuracy_pct"][0]
    a, c = np.array(s["accuracy_pct"]), np.array(s["completeness_pct"])
    np.testing.assert_allclose(s["f1_pct"], 2 * a * c / (a + c))
    assert 0 < c[0] < 100
