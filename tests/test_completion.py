"""Dense completion of geometric maps (``colmap_pvs.completion``)."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_pvs.completion import complete_depth, completed_confidence
from colmap_pvs.errors import ShapeError


def _slanted_plane_depth(H: int = 90, W: int = 122) -> np.ndarray:
    """``[H, W]`` depth of a slanted plane: inverse depth affine in the pixel coordinates."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    return (1.0 / (0.4 + 0.002 * xs + 0.001 * ys)).astype(np.float32)


def test_complete_depth_fills_a_plane_from_its_border_where_the_fallback_is_wrong():
    """A wall whose middle was dropped: the plane fit of the border restores it (the photometric
    fallback is 10 % off there), and the kept pixels are returned unchanged."""
    truth = _slanted_plane_depth()  # 122 x 90: not a multiple of the pooling factor
    kept = truth.copy()
    kept[20:70, 30:95] = 0.0
    kept[::7, ::5] = 0.0  # scattered drops
    fallback = truth * 1.1
    out = complete_depth(kept, fallback)
    assert out.shape == truth.shape and out.dtype == np.float32
    np.testing.assert_array_equal(out[kept > 0], kept[kept > 0])
    err = np.abs(out / truth - 1)
    assert err[20:70, 30:95].max() < 0.01 and err.max() < 0.02  # the image's corner extrapolates
    # Filling with the fallback (or a constant from the border) would fail this.
    assert np.abs(fallback[20:70, 30:95] / truth[20:70, 30:95] - 1).min() > 0.05


def test_complete_depth_does_not_fill_across_the_whole_image_with_one_side():
    """Two planes at different depths: each hole takes its own side's depth, not an average."""
    truth = np.full((64, 96), 2.0, np.float32)
    truth[:, 48:] = 4.0
    kept = truth.copy()
    kept[20:44, 10:30] = 0.0
    kept[20:44, 66:86] = 0.0
    out = complete_depth(kept, np.ones_like(truth))
    np.testing.assert_allclose(out[20:44, 10:30], 2.0, rtol=0.01)
    np.testing.assert_allclose(out[20:44, 66:86], 4.0, rtol=0.01)


def test_complete_depth_without_kept_pixels_returns_the_fallback():
    fallback = _slanted_plane_depth(40, 50)
    out = complete_depth(np.zeros_like(fallback), fallback)
    np.testing.assert_array_equal(out, fallback)


def test_complete_depth_refuses_mismatched_shapes():
    with pytest.raises(ShapeError, match="same"):
        complete_depth(np.ones((4, 5), np.float32), np.ones((5, 4), np.float32))
    with pytest.raises(ValueError, match="factor"):
        complete_depth(np.ones((4, 5), np.float32), np.ones((4, 5), np.float32), factor=0)


def test_completed_confidence_ranks_every_kept_pixel_above_every_filled_one():
    rng = np.random.default_rng(0)
    kept = rng.random((30, 40)) < 0.6
    geometric = np.where(kept, rng.random((30, 40)), 0.0).astype(np.float32)
    photometric = rng.random((30, 40)).astype(np.float32)
    photometric[0, 0] = np.nan
    photometric[kept] = 1.0  # a kept pixel's photometric confidence does not matter
    conf = completed_confidence(kept, geometric, photometric)
    assert conf.dtype == np.float32 and np.all((conf >= 0) & (conf <= 1))
    assert conf[kept].min() >= conf[~kept].max()
    # Within each group the pass's own confidence orders the pixels.
    np.testing.assert_allclose(conf[kept], 0.5 + 0.5 * geometric[kept], rtol=1e-6)
    np.testing.assert_allclose(conf[~kept], 0.5 * np.nan_to_num(photometric[~kept]), rtol=1e-6)
    with pytest.raises(ShapeError):
        completed_confidence(kept, geometric[:, :5], photometric)
