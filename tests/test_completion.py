"""Dense completion of geometric maps (``colmap_pvs.completion``)."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_pvs.completion import (
    NETWORK_FACTOR_FLOOR,
    complete_depth,
    completed_confidence,
    plane_deviation,
    segment_planes,
    splat_depths,
)
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


def test_complete_depth_treats_non_finite_kept_pixels_as_dropped():
    truth = _slanted_plane_depth(40, 52)
    kept = truth.copy()
    kept[10, 10], kept[20, 30] = np.inf, np.nan
    out = complete_depth(kept, np.ones_like(truth))
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(out[[10, 20], [10, 30]], truth[[10, 20], [10, 30]], rtol=0.01)


def test_complete_depth_without_kept_pixels_returns_the_fallback():
    fallback = _slanted_plane_depth(40, 50)
    out = complete_depth(np.zeros_like(fallback), fallback)
    np.testing.assert_array_equal(out, fallback)


def test_complete_depth_refuses_mismatched_shapes():
    with pytest.raises(ShapeError, match="same"):
        complete_depth(np.ones((4, 5), np.float32), np.ones((5, 4), np.float32))
    with pytest.raises(ValueError, match="factor"):
        complete_depth(np.ones((4, 5), np.float32), np.ones((4, 5), np.float32), factor=0)


def test_completed_confidence_is_the_tier_times_the_networks_probability():
    rng = np.random.default_rng(0)
    r = rng.random((30, 40))
    kept, splatted = r < 0.5, (r >= 0.5) & (r < 0.7)
    fitted = ~kept & ~splatted
    geometric = np.where(kept, rng.random((30, 40)), 0.0).astype(np.float32)
    support = rng.random((30, 40)).astype(np.float32)
    # Where the network is sure, the tiers alone: kept above splatted above fitted, each ranked by its own.
    sure = np.ones((30, 40), np.float32)
    conf = completed_confidence(kept, splatted, geometric, sure, support)
    assert conf.dtype == np.float32 and np.all((conf >= 0) & (conf <= 1))
    assert conf[kept].min() >= conf[splatted].max() and conf[splatted].min() >= conf[fitted].max()
    np.testing.assert_allclose(conf[kept], 0.5 + 0.5 * geometric[kept], rtol=1e-6)
    np.testing.assert_allclose(conf[splatted], 0.25 + 0.25 * support[splatted], rtol=1e-6)
    np.testing.assert_allclose(conf[fitted], 0.25, rtol=1e-6)
    # Every tier times the network's probability; where it has none (0, NaN) the floor keeps it positive.
    photometric = rng.random((30, 40)).astype(np.float32)
    photometric[fitted.nonzero()[0][0], fitted.nonzero()[1][0]] = np.nan
    photometric[kept.nonzero()[0][0], kept.nonzero()[1][0]] = 0.0
    doubted = completed_confidence(kept, splatted, geometric, photometric, support)
    factor = np.maximum(np.nan_to_num(photometric), NETWORK_FACTOR_FLOOR)
    np.testing.assert_allclose(doubted, conf * factor, rtol=1e-6)
    assert doubted.min() > 0
    # So a kept pixel the network doubts ranks below a splatted one it trusts.
    k, s = tuple(np.argwhere(kept)[1]), tuple(np.argwhere(splatted)[0])
    photometric[k], photometric[s] = 0.1, 1.0
    mixed = completed_confidence(kept, splatted, geometric, photometric, support)
    assert mixed[k] < mixed[s]
    with pytest.raises(ShapeError):
        completed_confidence(kept, splatted, geometric[:, :5], photometric, support)
    # Segment planes rank with the pixels the sources gave, by their inlier fraction, and win over
    # splatting where both gave a pixel (the completion replaces those pixels by the plane).
    segmented = (fitted & (r > 0.9)) | (splatted & (r < 0.6))
    assert (segmented & splatted).any() and (segmented & fitted).any()
    inliers = rng.random((30, 40)).astype(np.float32)
    conf = completed_confidence(kept, splatted, geometric, sure, support, segmented, inliers)
    np.testing.assert_allclose(conf[segmented], 0.25 + 0.25 * inliers[segmented], rtol=1e-6)
    np.testing.assert_allclose(conf[splatted & ~segmented], 0.25 + 0.25 * support[splatted & ~segmented],
                               rtol=1e-6)
    rest = fitted & ~segmented
    assert conf[kept].min() >= conf[segmented].max() and conf[segmented].min() >= conf[rest].max()


def _two_walls(H: int = 96, W: int = 128):
    """A left and a right wall of different grey and different slanted planes, split at column 64.

    Returns the true depth ``[H, W]`` and the image ``[3, H, W]`` (flat grey per wall, a few textured
    specks, a dark line at the split)."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    left = 1.0 / (0.40 + 0.0020 * xs + 0.0010 * ys)
    right = 1.0 / (0.25 - 0.0005 * xs + 0.0015 * ys)
    depth = np.where(xs < 64, left, right).astype(np.float32)
    grey = np.where(xs < 64, 0.7, 0.4).astype(np.float32)
    grey[:, 63:65] = 0.1
    return depth, np.stack([grey] * 3)


def _border_known(depth: np.ndarray, rng) -> np.ndarray:
    """The pixels a geometric pass keeps on untextured walls: their borders and a few specks."""
    known = np.zeros_like(depth)
    H, W = depth.shape
    band = np.zeros((H, W), bool)
    band[:6], band[-6:], band[:, :6], band[:, -6:], band[:, 56:72] = True, True, True, True, True
    band |= rng.random((H, W)) < 0.01
    known[band] = depth[band]
    return known


def test_segment_planes_fill_each_wall_with_its_own_plane_from_its_borders():
    """Each wall's middle, unknown, takes that wall's plane (not the other's, not a blend across the
    edge between them), and every pixel the planes give is within 0.5 % of the truth."""
    rng = np.random.default_rng(0)
    depth, image = _two_walls()
    known = _border_known(depth, rng)
    out, inliers, _ = segment_planes(known, image)
    assert out.shape == depth.shape and out.dtype == np.float32 and inliers.dtype == np.float32
    middle = np.zeros(depth.shape, bool)
    middle[12:-12, 12:52], middle[12:-12, 76:-12] = True, True
    assert (out[middle & (known == 0)] > 0).all() and not (out[known > 0] > 0).any()  # targets only
    assert np.abs(out[middle & (known == 0)] / depth[middle & (known == 0)] - 1).max() < 0.005
    given = out > 0
    assert np.abs(out[given] / depth[given] - 1).max() < 0.005
    assert np.all(inliers[given] > 0.95) and np.all(inliers[~given] == 0)
    # The local plane fit of the same pixels blends the two walls near the split (16 % off there).
    fit = complete_depth(known, np.ones_like(depth))
    near = np.zeros(depth.shape, bool)
    near[12:-12, 48:52], near[12:-12, 76:80] = True, True
    assert np.abs(fit[near] / depth[near] - 1).max() > 0.05
    assert np.abs(out[near & (known == 0)] / depth[near & (known == 0)] - 1).max() < 0.005
    # Explicit targets: known pixels too (the completion replaces projected ones), or none at all.
    every, _, _ = segment_planes(known, image, np.ones(depth.shape, bool))
    assert (every[middle] > 0).all() and np.abs(every[middle] / depth[middle] - 1).max() < 0.005
    assert not (segment_planes(known, image, np.zeros(depth.shape, bool))[0] > 0).any()


def test_segment_planes_are_robust_to_wrong_known_pixels():
    """A quarter of the known pixels 10-30 % off: the plane still comes from the right ones."""
    rng = np.random.default_rng(1)
    depth, image = _two_walls()
    known = _border_known(depth, rng)
    bad = (known > 0) & (rng.random(depth.shape) < 0.25)
    known[bad] *= rng.uniform(1.1, 1.3, size=bad.sum()).astype(np.float32)
    out, inliers, _ = segment_planes(known, image)
    given = out > 0
    unknown = known == 0
    middle = np.zeros(depth.shape, bool)
    middle[12:-12, 12:52], middle[12:-12, 76:-12] = True, True
    assert given[middle & unknown].all()
    assert np.abs(out[given] / depth[given] - 1).max() < 0.01
    assert 0.6 < inliers[given].min() and inliers[given].max() < 0.85  # about 3 in 4 are inliers


def test_segment_planes_are_not_extrapolated_far_beyond_their_support():
    """A steep plane known only in a corner of its segment gives its depth only while the plane stays
    within SEGMENT_MAX_EXTRAPOLATION of its known depths (the statue's paper drawn at twice the depth
    of everything else), and everywhere when the bar is lifted."""
    from colmap_pvs.completion import SEGMENT_MAX_EXTRAPOLATION

    H, W = 64, 96
    v, u = np.mgrid[0:H, 0:W] + 0.5
    depth = (1.0 / (1.0 - 0.0095 * u)).astype(np.float32)  # 1/d falls along the rows: 1 -> 11 m
    image = np.full((3, H, W), 0.5, np.float32)
    known = np.where(u < 24, depth, 0.0).astype(np.float32)  # the near quarter is known
    out, _, _ = segment_planes(known, image)
    given = out > 0
    assert np.abs(out[given] / depth[given] - 1).max() < 0.005  # where it is given, it is right
    limit = SEGMENT_MAX_EXTRAPOLATION * known[known > 0].max()
    assert given[(known == 0) & (depth < 0.95 * limit)].all()
    assert not given[depth > 1.05 * limit].any()
    assert not given[depth > 1.5 * known.max()].any()  # never twice as deep as anything it was fitted to
    monkey = pytest.MonkeyPatch()
    monkey.setattr("colmap_pvs.completion.SEGMENT_MAX_EXTRAPOLATION", 100.0)
    try:
        assert (segment_planes(known, image)[0][known == 0] > 0).all()
    finally:
        monkey.undo()


def test_segment_planes_reach_along_a_thin_strip_only_near_its_inliers():
    """fern's bar: a thin strip between two edges (a wall between shelf edges) known only at its left end,
    where another object's depth pins its plane, gives that plane only within SEGMENT_REACH radii of the
    inliers' hull, not along the whole strip; a compact region known along one side (a wall) takes its
    plane everywhere, as does the strip when the reach is lifted."""
    from colmap_pvs.completion import SEGMENT_HULL_MARGIN, SEGMENT_REACH

    H, W = 96, 160
    grey = np.full((H, W), 0.5, np.float32)
    grey[37:40], grey[53:56] = 0.1, 0.1  # the strip: rows 40-52, the whole width
    grey[60:, 100:] = 0.8  # a compact region below it: rows 60-95, columns 100-159
    depth = np.full((H, W), 6.0, np.float32)
    known = np.zeros((H, W), np.float32)
    known[40:53, :20] = 2.0  # the strip's left end: the near object's depth
    known[62:, 102:110] = 6.0  # the compact region's left side
    out, _, _ = segment_planes(known, grey)
    strip = (out[40:53] > 0).any(axis=0)
    assert strip[20:26].all() and np.allclose(out[44:49, 20:26], 2.0, rtol=1e-3)  # next to the inliers
    reach = max(SEGMENT_HULL_MARGIN * W, SEGMENT_REACH * 6.5)  # the strip's largest disc: radius < 6.5
    assert not strip[int(20 + reach) + 2:].any()  # not at the fronds' depth along the rest of the wall
    region = np.zeros((H, W), bool)
    region[64:-3, 112:-3] = True
    assert (out[region] > 0).all() and np.allclose(out[region], depth[region], rtol=1e-3)
    monkey = pytest.MonkeyPatch()
    monkey.setattr("colmap_pvs.completion.SEGMENT_REACH", 100.0)
    try:
        assert (segment_planes(known, grey)[0][44:49, 20:150] > 0).all()
    finally:
        monkey.undo()


def test_segment_planes_refuse_segments_that_do_not_pin_a_plane():
    """No depth where a segment's known pixels are too few, lie on one line, or are half on one
    plane and half on another (under ``min_inliers``)."""
    rng = np.random.default_rng(2)
    depth, image = _two_walls()
    line = np.zeros_like(depth)
    line[40, :60] = depth[40, :60]  # the left wall known along one row only
    line[:, 80] = depth[:, 80]  # the right wall known along one column only
    out, _, _ = segment_planes(line, image)
    assert not (out > 0).any()
    few = np.where(rng.random(depth.shape) < 0.002, depth, 0.0)
    assert (few[:, :64] > 0).sum() < 30 and (few[:, 64:] > 0).sum() < 30  # under min_pixels per wall
    assert not (segment_planes(few, image)[0] > 0).any()
    mixed = _border_known(depth, rng)
    swap = (mixed > 0) & (rng.random(depth.shape) < 0.5)
    mixed[swap] *= 1.5  # half the known pixels on a plane 50 % farther: no majority
    assert not (segment_planes(mixed, image)[0] > 0).any()
    mixed = _border_known(depth, rng)
    swap = (mixed > 0) & (rng.random(depth.shape) < 0.3)
    mixed[swap] *= 1.5  # 70 % on the true plane: given, exactly, unless the bar is above 70 %
    out, _, _ = segment_planes(mixed, image)
    assert (out[mixed == 0] > 0).mean() > 0.9 and np.abs(out[out > 0] / depth[out > 0] - 1).max() < 0.005
    assert not (segment_planes(mixed, image, min_inliers=0.8)[0] > 0).any()
    with pytest.raises(ShapeError):
        segment_planes(depth, image[:, :10])
    with pytest.raises(ValueError, match="min_pixels"):
        segment_planes(depth, image, min_pixels=2)


def test_segment_planes_refuse_a_large_region_with_a_few_specks():
    """The statue's background: a large untextured region whose known pixels, all on one plane, cover
    under SEGMENT_MIN_SUPPORT of it gives no plane, and its pixels come back ``refused``; the same
    region with its borders known (an indoor wall) is filled as before, nothing refused."""
    from colmap_pvs.completion import SEGMENT_MIN_SUPPORT

    rng = np.random.default_rng(4)
    depth, image = _two_walls()
    specks = np.where(rng.random(depth.shape) < 0.03, depth, 0.0).astype(np.float32)
    for wall in (slice(0, 63), slice(65, None)):
        share = (specks[:, wall] > 0).mean()
        assert 0.5 * SEGMENT_MIN_SUPPORT < share < SEGMENT_MIN_SUPPORT and (specks[:, wall] > 0).sum() > 30
    out, _, refused = segment_planes(specks, image)
    assert not (out > 0).any()
    assert refused.dtype == bool and refused[specks == 0].mean() > 0.9 and not refused[specks > 0].any()
    borders = _border_known(depth, rng)
    out, _, refused = segment_planes(borders, image)
    assert (out[borders == 0] > 0).mean() > 0.9 and not refused.any()


def test_a_refused_region_stays_refused_when_a_coarser_one_merges_it_with_a_supported_surface():
    """colmap-statue's background: a fully known object (a box) before a background whose few known
    specks lie in one corner (under SEGMENT_MIN_SUPPORT of it), split from the box by an edge only the
    finer segmentations see. The fine background region is refused; the coarse region that merges it
    with the box would give the background the box's plane, which is wrong by 25 %, unless the
    refusal carries over."""
    from colmap_pvs.completion import SEGMENT_EDGE_THRESHOLDS

    H, W = 96, 128
    ys, xs = np.mgrid[0:H, 0:W]
    box = (ys >= 24) & (ys < 72) & (xs >= 32) & (xs < 96)
    depth = np.where(box, 4.0, 5.0).astype(np.float32)  # both fronto-parallel
    grey = np.where(box, 0.5 + 60 / 255, 0.5).astype(np.float32)  # 60 grey levels: not a coarse edge
    corner = ~box & (ys >= H - 12) & (xs >= W - 12)
    known = np.where(box | (corner & ((ys + xs) % 2 == 0)), depth, 0.0).astype(np.float32)
    near_box = (ys >= 21) & (ys < 75) & (xs >= 29) & (xs < 99)  # the box's dilated edge: no region's
    background = ~near_box & ~corner
    out, _, refused = segment_planes(known, grey)
    assert refused[background].all() and not (out[background] > 0).any()
    # the coarse segmentation alone merges them: the box's plane for the background, 25 % off
    merged, _, merged_refused = segment_planes(known, grey, thresholds=SEGMENT_EDGE_THRESHOLDS[2:])
    assert (merged[background] > 0).mean() > 0.5 and not merged_refused.any()
    np.testing.assert_allclose(merged[background & (merged > 0)], 4.0, rtol=1e-3)


def test_fit_support_is_the_share_of_known_pixels_around_each_pixel():
    from colmap_pvs.completion import FIT_SUPPORT_WINDOW, fit_support

    known = np.zeros((60, 200), np.float32)
    known[:, :20] = 2.0
    known[0, 199] = np.nan  # not finite: not known
    support = fit_support(known)
    win = int(FIT_SUPPORT_WINDOW * 200) | 1
    assert support.shape == known.shape and support.dtype == np.float32
    np.testing.assert_allclose(support[:, 20 + win // 2:], 0.0)
    np.testing.assert_allclose(support[:, : 20 - win // 2], 1.0)
    assert 0.0 < support[30, 20] < 1.0
    with pytest.raises(ShapeError):
        fit_support(np.zeros((2, 3, 4)))


def _camera(x: float) -> np.ndarray:
    """``[4, 4]`` cam_from_world of a camera at ``(x, 0, 0)`` looking down +z."""
    T = np.eye(4)
    T[0, 3] = -x
    return T


def test_splat_depths_reprojects_the_sources_and_needs_agreement():
    """A fronto-parallel wall at z = 4 seen by three sources shifted sideways: splatted into the
    reference it is exact where enough sources reach, a disagreeing source is outvoted, and one
    source is not enough for ``min_sources = 2``."""
    from colmap_pvs.consistency import SourceMaps

    H, W = 48, 64
    K = np.array([[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]])
    wall = np.full((H, W), 4.0, np.float32)
    sources = [SourceMaps(wall, None, K, _camera(x)) for x in (-0.2, 0.2, 0.4)]
    depth, agree = splat_depths(K, _camera(0.0), (W, H), sources, min_sources=2)
    assert depth.shape == (H, W) and depth.dtype == np.float32 and agree.dtype == np.int32
    inner = depth[:, 10:-10]
    np.testing.assert_allclose(inner[inner > 0], 4.0, rtol=1e-6)
    assert (inner > 0).mean() > 0.9 and agree[:, 10:-10].max() == 3
    # One source sees a nearer surface: the two that agree win.
    near = np.full((H, W), 2.0, np.float32)
    wrong = [SourceMaps(wall, None, K, _camera(-0.2)), SourceMaps(wall, None, K, _camera(0.2)),
             SourceMaps(near, None, K, _camera(0.4))]
    depth, agree = splat_depths(K, _camera(0.0), (W, H), wrong, min_sources=2)
    centre = depth[:, 24:40]
    np.testing.assert_allclose(centre[centre > 0], 4.0, rtol=1e-6)  # the 2 agreeing sources win
    # Only one source: nothing at min_sources 2, the wall at min_sources 1.
    depth, _ = splat_depths(K, _camera(0.0), (W, H), sources[:1], min_sources=2)
    assert not depth.any()
    depth, _ = splat_depths(K, _camera(0.0), (W, H), sources[:1], min_sources=1)
    assert (depth[:, 20:] > 0).mean() > 0.9
    empty, count = splat_depths(K, _camera(0.0), (W, H), [], min_sources=1)
    assert not empty.any() and not count.any()


def _plane_depth(K: np.ndarray, centre_x: float, size: tuple[int, int]) -> np.ndarray:
    """``[H, W]`` depth, at pixel centres, of the slanted plane ``z = 4 + 0.5 x`` (world) seen by a
    camera at ``(centre_x, 0, 0)`` looking down +z (see :func:`_camera`)."""
    W, H = size
    v, u = np.mgrid[0:H, 0:W] + 0.5
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T  # z component 1
    return ((4.0 + 0.5 * centre_x) / (rays[..., 2] - 0.5 * rays[..., 0])).astype(np.float32)


def test_splat_depths_on_a_slanted_plane_with_a_half_size_source():
    """Pixel centres and each source's own intrinsics: a source map at half the reference's size,
    splatted, gives the reference's exact depth (to well under the depth change of half a pixel)."""
    from colmap_pvs.consistency import SourceMaps

    W, H = 96, 64
    K = np.array([[80.0, 0, W / 2], [0, 80.0, H / 2], [0, 0, 1]])
    K_half = np.diag([0.5, 0.5, 1.0]) @ K
    truth = _plane_depth(K, 0.0, (W, H))
    sources = [SourceMaps(_plane_depth(K_half, x, (W // 2, H // 2)), None, K_half, _camera(x))
               for x in (-0.1, 0.1)]
    sources.append(SourceMaps(_plane_depth(K, 0.2, (W, H)), None, K, _camera(0.2)))
    depth, agree = splat_depths(K, _camera(0.0), (W, H), sources, min_sources=1)
    ok = depth > 0
    assert ok[:, 10:-10].mean() > 0.9
    half_pixel = np.abs(np.diff(truth, axis=1)).max() / 2
    err = np.abs(depth[ok] - truth[ok])
    assert np.median(err) < 0.25 * half_pixel


def test_plane_deviation_is_small_on_a_plane_and_large_off_it():
    """A slanted plane (affine in inverse depth) deviates < 0.5 % from its own fit away from the
    borders of what is kept (< 2 % at them); a pixel 10 % off it stands out by several %; the empty
    pixels read 0."""
    H, W = 60, 80
    yy, xx = np.mgrid[0:H, 0:W]
    depth = (1.0 / (0.4 + 0.003 * xx + 0.002 * yy)).astype(np.float32)
    depth[:, :10] = 0.0  # nothing kept there
    dev = plane_deviation(depth)
    assert dev.shape == (H, W) and dev.dtype == np.float32
    assert np.all(dev[:, :10] == 0)
    assert dev[4:-4, 14:-4].max() < 0.005  # away from the borders of the kept region
    assert dev[:, 10:].max() < 0.02  # border cells hold part of their pixels (documented bias)
    bumped = depth.copy()
    bumped[30, 40] *= 1.10
    dev = plane_deviation(bumped)
    assert dev[30, 40] > 0.05
    assert np.median(dev[:, 10:]) < 0.005
    assert not plane_deviation(np.zeros((8, 8), np.float32)).any()
    with pytest.raises(ShapeError):
        plane_deviation(np.zeros((2, 8, 8), np.float32))


def test_geometric_confidence_ranks_off_plane_and_low_parallax_pixels_lower():
    """Same agreement, more deviation from the local plane: lower confidence; no deviation: the
    visibility-weighted fraction of agreeing sources."""
    from colmap_pvs.stereo.geometric import GEOM_DEVIATION_SCALE, geometric_confidence

    agree = np.ones((4, 2, 3), bool)
    agree[3] = False
    vis = np.full((4, 2, 3), 0.8, np.float32)
    base = geometric_confidence(agree, vis)
    np.testing.assert_allclose(base, 0.6, rtol=1e-6)
    dev = np.zeros((2, 3), np.float32)
    dev[0, 1] = GEOM_DEVIATION_SCALE
    dev[1, 2] = np.nan  # unmeasurable: no confidence
    conf = geometric_confidence(agree, vis, dev)
    np.testing.assert_allclose(conf[0, 1], 0.6 / np.e, rtol=1e-5)
    assert conf[1, 2] == 0.0
    np.testing.assert_allclose(conf[0, 0], 0.6, rtol=1e-6)
    with pytest.raises(ShapeError):
        geometric_confidence(agree, vis, np.zeros((3, 3), np.float32))
    # An agreeing source with less parallax than GEOM_FULL_PARALLAX counts in proportion.
    from colmap_pvs.stereo.geometric import GEOM_FULL_PARALLAX

    parallax = np.full((4, 2, 3), 5.0 * GEOM_FULL_PARALLAX, np.float32)
    np.testing.assert_allclose(geometric_confidence(agree, vis, None, parallax), base, rtol=1e-6)
    parallax[0, 0, 0] = 0.5 * GEOM_FULL_PARALLAX
    parallax[1, 0, 0] = 0.0
    weaker = geometric_confidence(agree, vis, None, parallax)
    np.testing.assert_allclose(weaker[0, 0], 0.8 * 1.5 / 4, rtol=1e-5)
    for wrong in (parallax[:2], np.concatenate([parallax, parallax[:1]])):  # fewer or more sources
        with pytest.raises(ShapeError):
            geometric_confidence(agree, vis, None, wrong)
    # Full weight from a parallax of one pixel on (per PARALLAX_STEP of depth), half at half a pixel.
    one = np.ones((1, 1, 2), bool)
    np.testing.assert_allclose(geometric_confidence(one, None, None, np.array([[[1.0, 0.5]]], np.float32)),
                               [[1.0, 0.5]], rtol=1e-6)
    # One agreeing source without visibility: full confidence; no sources: none (not 0 / 0).
    np.testing.assert_array_equal(geometric_confidence(np.ones((1, 2, 3), bool), None), 1.0)
    np.testing.assert_array_equal(geometric_confidence(np.zeros((0, 2, 3), bool), None), 0.0)
    # Times the network's probability of the depth (NaN: none).
    network = np.array([[1.0, 0.5, 0.0], [0.25, np.nan, 2.0]], np.float32)
    np.testing.assert_allclose(geometric_confidence(agree, vis, None, None, network),
                               0.6 * np.array([[1.0, 0.5, 0.0], [0.25, 0.0, 1.0]]), rtol=1e-6)
    with pytest.raises(ShapeError):
        geometric_confidence(agree, vis, None, None, network[:1])


def test_segment_planes_coarsest_segments_need_local_support(monkeypatch):
    """A box 20 % nearer than the wall behind it, with an edge only the finer segmentations see and
    too few known pixels of its own for a plane: the coarse segment that merges box and wall has the
    wall's plane, and without the local check (a 1-pixel window) it would give it to the box."""
    import colmap_pvs.completion as completion

    H, W = 96, 128
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    wall = 1.0 / (0.30 + 0.0008 * xs + 0.0004 * ys)
    box = np.zeros((H, W), bool)
    box[24:72, 32:96] = True
    depth = np.where(box, wall / 1.2, wall).astype(np.float32)
    grey = np.where(box, 0.5 + 60 / 255, 0.5).astype(np.float32)  # 60 grey levels: not a coarse edge
    rng = np.random.default_rng(3)
    known = np.zeros_like(depth)
    band = ~box & ((ys < 8) | (ys >= H - 8) | (xs < 8) | (xs >= W - 8) | (rng.random((H, W)) < 0.05))
    known[band] = depth[band]
    inside = np.argwhere(box)[rng.choice(box.sum(), 25, replace=False)]  # 25 < min_pixels
    known[inside[:, 0], inside[:, 1]] = depth[inside[:, 0], inside[:, 1]]
    interior = np.zeros((H, W), bool)
    interior[40:56, 48:80] = True  # more than 15 pixels inside the box
    out, _, _ = segment_planes(known, grey)
    assert not (out[interior] > 0).any()
    given = out > 0
    assert given[~box & (known == 0)].mean() > 0.9
    assert np.abs(out[given & ~box] / depth[given & ~box] - 1).max() < 0.005
    monkeypatch.setattr(completion, "SEGMENT_LOCAL_WINDOW", 1)
    unguarded, _, _ = segment_planes(known, grey)
    unknown = interior & (known == 0)
    assert (unguarded[unknown] > 0).all()
    np.testing.assert_allclose(unguarded[unknown], wall[unknown], rtol=0.005)  # the wall's plane: wrong
