"""The sparse prior after the network: texture weight, blend, agreement, upsampling (colmap_pvs.prior)."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_pvs.errors import ShapeError
from colmap_pvs.prior import blend_with_prior, prior_agreement, texture_weight, upsample_prior


def test_texture_weight_is_zero_on_flat_and_one_on_textured_image():
    rng = np.random.default_rng(0)
    gray = np.full((40, 60), 0.5, np.float32)
    gray[:, 30:] += rng.uniform(-0.2, 0.2, (40, 30)).astype(np.float32)
    w = texture_weight(gray, 7, 0.01)
    assert w.shape == gray.shape and w.dtype == np.float32
    # flat, away from the textured half's window (3 px) and the smoothing (sigma 3, 12 px reach)
    assert np.all(w[:, :14] < 1e-4)
    assert np.all(w[:, 46:] > 1.0 - 1e-4)
    assert np.all(np.diff(w[20]) >= -1e-6)  # a ramp across the border, no thin line
    # A faint texture gets a partial weight: its std over the threshold.
    faint = 0.5 + 0.004 * (np.indices((40, 60)).sum(0) % 2).astype(np.float32)
    mid = texture_weight(faint, 7, 0.01)[20, 30]
    assert 0.1 < mid < 0.4  # std of a 0/0.004 checker is 0.002
    np.testing.assert_array_equal(texture_weight(gray, 7, 0.0), np.ones_like(gray))
    with pytest.raises(ShapeError):
        texture_weight(np.zeros((4, 4, 3), np.float32), 7, 0.01)


def test_blend_with_prior_weights_in_log_depth():
    depth = np.array([[2.0, 2.0, 2.0, 0.0, 3.0]], np.float32)
    prior = np.array([[8.0, 8.0, 8.0, 5.0, 0.0]], np.float32)
    weight = np.array([[1.0, 0.0, 0.5, 0.0, 0.0]], np.float32)
    out = blend_with_prior(depth, prior, weight)
    # keep / take the prior / geometric mean; no depth stays none; no prior keeps the depth
    np.testing.assert_allclose(out, [[2.0, 8.0, 4.0, 0.0, 3.0]], rtol=1e-6)
    with pytest.raises(ShapeError):
        blend_with_prior(depth, prior[:, :3], weight)


def test_prior_agreement_falls_with_the_relative_difference():
    depth = np.array([[2.0, 2.1, 4.0, 2.0, 0.0]], np.float32)
    prior = np.array([[2.0, 2.0, 2.0, 0.0, 2.0]], np.float32)
    a = prior_agreement(depth, prior, 0.05)
    assert a[0, 0] == pytest.approx(1.0)
    assert a[0, 1] == pytest.approx(np.exp(-np.log(2.1 / 2.0) / 0.05), rel=1e-5)
    assert a[0, 2] < 1e-5 < a[0, 1] < 1.0  # a factor 2 apart: no confidence left
    assert a[0, 3] == 1.0 and a[0, 4] == 1.0  # without a prior (or a depth) nothing changes
    # symmetric in log depth: 2 vs 4 as 4 vs 2
    assert prior_agreement(prior[:, :1] * 2, depth[:, :1], 0.05)[0, 0] == pytest.approx(a[0, 2], rel=1e-4)
    np.testing.assert_array_equal(prior_agreement(depth, prior, 0.0), np.ones_like(depth))


def test_upsample_prior_keeps_a_constant_and_aligns_coarse_pixels():
    # network 30x18 -> coarse 8x5 (ceil); map 45x27
    prior = np.full((5, 8), 2.0, np.float32)
    out = upsample_prior(prior, (30, 18), (45, 27))
    assert out.shape == (27, 45)
    np.testing.assert_allclose(out, 2.0, rtol=1e-6)
    # A missing coarse pixel leaves a hole (never an average of a depth with "none").
    prior[2, 3] = 0.0
    out = upsample_prior(prior, (30, 18), (30, 18))
    assert np.all(out[8:12, 12:16] == 0) and np.all(out[:, 24:] == 2.0)
    # Bilinear in inverse depth: halfway between 1 and 1/3 in inverse depth is depth 1.5.
    two = np.array([[1.0, 3.0]], np.float32)
    mid = upsample_prior(two, (8, 4), (8, 4))[0]
    assert mid[0] == pytest.approx(1.0) and mid[-1] == pytest.approx(3.0)
    assert 1.0 < mid[4] < 2.0  # inverse-depth interpolation lies nearer the near value
    with pytest.raises(ShapeError):
        upsample_prior(prior, (64, 48), (64, 48))
