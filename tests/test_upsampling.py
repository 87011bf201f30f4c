"""Image-guided depth upsampling (``colmap_pvs.upsampling``) and the network_scale path of stereo."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_pvs.errors import ShapeError
from colmap_pvs.upsampling import guided_upsample_depth, resize_bilinear, resize_nearest


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


def test_sample_depth_down_takes_the_network_pixel_on_the_same_ray():
    """A map ``W`` wide from a network ``w`` wide: map pixel ``c`` takes network pixel nearest to
    ``c * w / W`` (COLMAP's fusion scales about the image origin), never a blend."""
    from colmap_pvs.upsampling import sample_depth_down

    net = np.arange(12 * 18, dtype=np.float32).reshape(12, 18) + 1.0
    np.testing.assert_array_equal(sample_depth_down(net, 6, 9), net[::2, ::2])
    out = sample_depth_down(net, 8, 12)  # scale 1.5: columns 0, 1.5, 3, 4.5, ... -> 0, 2, 3, 5, ...
    cols = np.minimum(np.floor(np.arange(12) * 1.5 + 0.5).astype(int), 17)
    rows = np.minimum(np.floor(np.arange(8) * 1.5 + 0.5).astype(int), 11)
    np.testing.assert_array_equal(out, net[rows][:, cols])
    assert set(np.unique(out)) <= set(np.unique(net))
    with pytest.raises(ShapeError):
        sample_depth_down(net[None], 6, 9)


def test_resize_nearest_uses_pixel_centres():
    a = np.arange(3)[None, :].repeat(2, 0)  # columns 0 1 2
    out = resize_nearest(a, 2, 2)
    # output centres 0.5, 1.5 -> input coordinates 0.75, 2.25 -> columns 0 and 2
    assert out[0].tolist() == [0, 2]
    # 2x downsampling picks the lower-right pixel of each 2x2 block (centre 1.0 -> index 1)
    big = np.arange(16).reshape(4, 4)
    assert resize_nearest(big, 2, 2).tolist() == [[5, 7], [13, 15]]
    # upsampling repeats each pixel, never blends
    assert resize_nearest(np.array([[1.0, 2.0]]), 1, 4).tolist() == [[1.0, 1.0, 2.0, 2.0]]
    with pytest.raises(ShapeError, match=r"\(2, 2, 3\)"):
        resize_nearest(np.zeros((2, 2, 3)), 1, 1)
