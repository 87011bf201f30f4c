"""Image-guided depth upsampling (``colmap_pvs.upsampling``) and the network_scale path of stereo."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_pvs.errors import ShapeError
from colmap_pvs.upsampling import guided_upsample_depth, resize_bilinear


def _step_guide(height: int, width: int, edge_col: int) -> np.ndarray:
    guide = np.zeros((height, width, 3), np.float32)
    guide[:, edge_col:] = 1.0
    return guide


def test_step_edge_follows_the_image_and_never_blends():
    low = np.full((4, 8), 2.0, np.float32)
    low[:, 4:] = 4.0  # low-res boundary at full-res column 16
    guide = _step_guide(16, 32, 15)  # the image's edge one full-res column earlier
    out = guided_upsample_depth(low, guide)
    assert out.shape == (16, 32)
    assert set(np.unique(np.round(out, 5))) == {2.0, 4.0}  # no flying pixels between the sides
    assert np.all(out[:, 15:] == pytest.approx(4.0)) and np.all(out[:, :15] == pytest.approx(2.0))
    bilinear = resize_bilinear(low, 16, 32)
    assert np.any((bilinear > 2.1) & (bilinear < 3.9))  # what the guide avoids


def test_smooth_ramp_is_interpolated_in_inverse_depth():
    ramp = 1.0 / (0.5 + 0.04 * np.arange(10, dtype=np.float32))[None].repeat(6, 0)  # depth, 1/z linear
    out = guided_upsample_depth(ramp, np.full((24, 40, 3), 0.5, np.float32))
    inv = 1.0 / out[:, 2:-2]
    cols = (np.arange(40, dtype=np.float32) + 0.5) / 4 - 0.5
    np.testing.assert_allclose(inv, np.broadcast_to(0.5 + 0.04 * cols[2:-2], inv.shape), rtol=1e-4)


def test_invalid_depth_never_contributes():
    low = np.full((4, 4), 3.0, np.float32)
    low[:, :2] = 0.0
    low[0, 3] = np.nan
    out = guided_upsample_depth(low, np.zeros((8, 8, 3), np.float32))
    assert np.all(np.isfinite(out))
    assert np.all(out[:, :2] == 0.0)  # two full-res columns from any valid pixel
    assert np.all(out[2:, 4:] == pytest.approx(3.0))
    assert out[0, 7] == 0.0  # the NaN pixel's own corner, where it is the only neighbour
    assert np.all(guided_upsample_depth(np.zeros((4, 4), np.float32), np.zeros((8, 8, 3))) == 0)
    # same size: a copy; a channels-first guide is accepted; bad shapes are refused
    same = guided_upsample_depth(low, np.zeros((3, 4, 4), np.float32))
    np.testing.assert_array_equal(same, low)
    with pytest.raises(ShapeError, match="guide"):
        guided_upsample_depth(low, np.zeros((8, 8), np.float32))
