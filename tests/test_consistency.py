"""The geometric pass's forward-backward consistency check (``colmap_pvs.consistency``) on exact maps."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_pvs.consistency import SourceMaps, backproject_pixels, check_consistency, match_points


@pytest.fixture(scope="module")
def exact(analytic_scene):
    gt = analytic_scene
    model = gt["model"]
    views = []
    for name in gt["names"]:
        im = model.image_by_name(name)
        K = model.camera_of(im).K
        views.append(SourceMaps(gt["depth"][name].astype(np.float32), gt["normals"][name].astype(np.float32),
                                K, im.cam_from_world))
    return views


def _check(ref, srcs, **kw):
    return check_consistency(ref.depth, ref.normals, ref.K, ref.cam_from_world, srcs, **kw)


def test_exact_maps_agree_and_wrong_depths_do_not(exact):
    ref, srcs = exact[0], exact[1:]
    res = _check(ref, srcs)
    valid = ref.depth > 0
    # Pixels seen by a source agree with it (nearest-pixel back-projection: < 1 px, < 1 %); the rest
    # are occluded by the box or on depth edges.
    assert res.agree[res.checked].mean() > 0.85
    seen_twice = res.checked.sum(0) >= 2
    assert seen_twice.mean() > 0.3 and (res.count[seen_twice] >= 2).mean() > 0.85
    np.testing.assert_allclose(res.mean_depth(ref.depth)[valid], ref.depth[valid], rtol=0.01)
    # 5 % too deep in one block: that block agrees with nobody, the rest is unaffected.
    bad = ref.depth.copy()
    bad[30:60, 40:90] *= 1.05
    res_bad = check_consistency(bad, ref.normals, ref.K, ref.cam_from_world, srcs)
    block = np.zeros_like(valid)
    block[30:60, 40:90] = True
    assert (res_bad.count[block & valid] > 0).mean() < 0.02  # (a few land on another surface)
    np.testing.assert_array_equal(res_bad.count[~block], res.count[~block])


def test_parallax_is_how_far_a_depth_step_moves_the_projection(exact):
    """``parallax`` is the source-image distance between the projections of the pixel at depth ``d``
    and ``(1 + PARALLAX_STEP) d`` (computed here independently); a source at the reference's own
    centre has none."""
    from colmap_pvs.consistency import PARALLAX_STEP

    ref, src = exact[0], exact[1]
    same_centre = SourceMaps(ref.depth, ref.normals, ref.K, ref.cam_from_world)
    res = _check(ref, [src, same_centre])
    rows, cols = np.nonzero(ref.depth > 0)
    rows, cols = rows[::97], cols[::97]
    T_ref, T_src = np.eye(4), np.eye(4)
    T_ref[:3], T_src[:3] = ref.cam_from_world[:3], src.cam_from_world[:3]
    M = T_src @ np.linalg.inv(T_ref)

    def project(scale):
        d = ref.depth[rows, cols].astype(np.float64) * scale
        X = np.linalg.inv(ref.K) @ np.stack([(cols + 0.5) * d, (rows + 0.5) * d, d])
        x = src.K @ (M[:3, :3] @ X + M[:3, 3:])
        return x[:2] / x[2]

    expected = np.linalg.norm(project(1.0 + PARALLAX_STEP) - project(1.0), axis=0)
    np.testing.assert_allclose(res.parallax[0][rows, cols], expected, rtol=1e-4, atol=1e-4)
    assert expected.min() > 0.5  # the scene's sources see real parallax
    assert np.abs(res.parallax[1]).max() < 1e-6
    assert not res.parallax[:, ref.depth <= 0].any()


def test_a_source_confirms_only_from_a_wide_enough_triangulation_angle(exact):
    """``angle`` is the angle between the rays from the two centres to the pixel's point (computed here
    independently). A source at the reference's own centre agrees with every depth but confirms none;
    a real source confirms where its angle is enough, and the mean depth can use just those."""
    ref, src = exact[0], exact[1]
    same_centre = SourceMaps(ref.depth, ref.normals, ref.K, ref.cam_from_world)
    res = _check(ref, [src, same_centre])
    rows, cols = np.nonzero(ref.depth > 0)
    rows, cols = rows[::97], cols[::97]
    d = ref.depth[rows, cols].astype(np.float64)
    X_cam = np.linalg.inv(ref.K) @ np.stack([(cols + 0.5) * d, (rows + 0.5) * d, d])
    R, t = ref.cam_from_world[:3, :3], ref.cam_from_world[:3, 3:]
    X = R.T @ (X_cam - t)  # world
    centres = [-(m[:3, :3].T @ m[:3, 3:]) for m in (ref.cam_from_world, src.cam_from_world)]
    a, b = X - centres[0], X - centres[1]
    expected = np.degrees(np.arccos(np.sum(a * b, 0) / np.linalg.norm(a, axis=0) / np.linalg.norm(b, axis=0)))
    np.testing.assert_allclose(res.angle[0][rows, cols], expected, atol=1e-3)
    assert expected.min() > 1.0 and np.abs(res.angle[1]).max() < 1e-3
    assert res.agree[1][ref.depth > 0].mean() > 0.99  # it agrees with anything at all
    angle = float(np.median(res.angle[0][res.agree[0]]))
    confirm = res.confirming(angle)
    assert not confirm[1].any()
    np.testing.assert_array_equal(confirm[0], res.agree[0] & (res.angle[0] >= angle))
    assert 0.3 < confirm[0].sum() / res.agree[0].sum() < 0.7
    np.testing.assert_array_equal(res.confirming(0.0), res.agree)
    both = confirm[0] & res.agree[1]
    expected = (ref.depth + res.reprojected_depth[0]) / 2
    np.testing.assert_allclose(res.mean_depth(ref.depth, confirm)[both], expected[both], rtol=1e-6)
    np.testing.assert_allclose(res.mean_depth(ref.depth)[both],
                               (ref.depth + res.reprojected_depth[0] + res.reprojected_depth[1])[both] / 3,
                               rtol=1e-6)


def test_learned_visibility_chooses_the_views_checked(exact):
    ref, srcs = exact[0], exact[1:]
    H, W = ref.depth.shape
    vis = np.ones((len(srcs), H, W), np.float32)
    vis[0] = 0.0  # the network says source 0 sees nothing
    res = _check(ref, srcs, visibility=vis, min_visibility=0.5)
    assert not res.checked[0].any() and not res.agree[0].any()
    full = _check(ref, srcs)
    np.testing.assert_array_equal(res.agree[1:], full.agree[1:])
    with pytest.raises(Exception, match="visibility"):
        _check(ref, srcs, visibility=vis[:1], min_visibility=0.5)


def test_normal_angle_test_rejects_flipped_source_normals(exact):
    ref, srcs = exact[0], exact[1:]
    tilted = [SourceMaps(s.depth, -s.normals, s.K, s.cam_from_world) for s in srcs]
    assert _check(ref, tilted, max_normal_error=180.0).count.sum() == _check(ref, srcs).count.sum()
    assert _check(ref, tilted, max_normal_error=30.0).count.sum() == 0
    assert _check(ref, srcs, max_normal_error=30.0).count.sum() > 0.9 * _check(ref, srcs).count.sum()


def test_affine_row_is_one_row_of_the_affine_map():
    from colmap_pvs.geometry import affine_row

    rng = np.random.default_rng(0)
    M, b, X = rng.normal(size=(3, 3)), rng.normal(size=3), rng.normal(size=(3, 50))
    rows = np.stack([affine_row(M[i], b[i], tuple(X)) for i in range(3)])
    np.testing.assert_allclose(rows, M @ X + b[:, None], rtol=1e-12, atol=1e-12)


def test_sources_checked_in_threads_give_the_same_result(exact):
    """``workers``: the sources are checked in threads, each writing its own slice; nothing changes."""
    ref, srcs = exact[0], exact[1:]
    bad = ref.depth.copy()
    bad[30:60, 40:90] *= 1.05  # some pixels agree, some do not
    kw = dict(max_normal_error=30.0, max_depth_error=0.02)
    one = check_consistency(bad, ref.normals, ref.K, ref.cam_from_world, srcs, **kw)
    many = check_consistency(bad, ref.normals, ref.K, ref.cam_from_world, srcs, workers=3, **kw)
    none = check_consistency(bad, ref.normals, ref.K, ref.cam_from_world, srcs, workers=0, **kw)  # no threads
    np.testing.assert_array_equal(none.agree, one.agree)
    assert one.agree.any() and not one.agree.all()
    for field in ("agree", "checked", "reproj_error", "depth_error", "reprojected_depth", "parallax"):
        np.testing.assert_array_equal(getattr(many, field), getattr(one, field), err_msg=field)


def _facing_source(scale):
    """A 16 x 16 reference at the origin looking at a plane at depth 2 (its top 4 rows at 3.9), and a
    source at depth 4 on its axis looking back at it (turned 180 degrees about y); lengths times ``scale``."""
    K = np.array([[16.0, 0.0, 8.0], [0.0, 16.0, 8.0], [0.0, 0.0, 1.0]])
    depth = np.full((16, 16), 2.0 * scale, np.float32)
    depth[:4] = 3.9 * scale
    src = np.array([[-1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 4.0 * scale]])
    return depth, K, np.eye(4)[:3], src


@pytest.mark.parametrize("scale", [1.0, 0.1])
def test_parallax_and_angle_of_a_source_facing_the_reference_in_any_unit(scale):
    """Triangulation angles beyond 90 degrees are measured as they are (a source facing the reference sees
    the points at about 180); a pixel whose deeper point passes behind the source has no parallax (0); both
    are the same whatever the scene's unit."""
    from colmap_pvs.consistency import PARALLAX_STEP

    depth, K, ref_T, src_T = _facing_source(scale)
    res = check_consistency(depth, None, K, ref_T, [SourceMaps(depth, None, K, src_T)])
    rows, cols = np.mgrid[:16, :16]
    X = np.linalg.inv(K) @ np.stack([(cols + 0.5) * depth, (rows + 0.5) * depth, depth]).reshape(3, -1)
    to_src = X - np.array([[0.0], [0.0], [4.0 * scale]])
    expected_angle = np.degrees(np.arccos(np.sum(X * to_src, 0) / np.linalg.norm(X, axis=0)
                                          / np.linalg.norm(to_src, axis=0)))
    np.testing.assert_allclose(res.angle[0].ravel(), expected_angle, atol=1e-3)
    assert res.angle[0].max() > 150 and (res.angle[0] > 90).mean() > 0.5

    def project(Y):
        x = K @ (src_T[:, :3] @ Y + src_T[:, 3:])
        return x[:2] / x[2], x[2]

    (p0, z0), (p1, z1) = project(X), project((1 + PARALLAX_STEP) * X)
    expected = np.where((z0 > 0) & (z1 > 0), np.linalg.norm(p1 - p0, axis=0), 0.0).reshape(16, 16)
    assert (expected[:4] == 0).all() and (expected[4:] > 1e-3).all()
    np.testing.assert_allclose(res.parallax[0], expected, rtol=1e-4, atol=1e-6)


def test_parallax_step_is_the_geometric_pass_depth_tolerance():
    """``parallax`` says how far an error as large as the pass tolerates moves a pixel in the source."""
    from colmap_pvs.consistency import PARALLAX_STEP
    from colmap_pvs.stereo.config import GeometricConfig

    assert PARALLAX_STEP == GeometricConfig().max_depth_error


def test_a_source_without_depth_where_the_pixel_lands_is_not_checked(exact):
    """Holes (0) in a source's map are no evidence either way: not checked, no agreement, no depth."""
    ref, src = exact[0], exact[1]
    holes = src.depth.copy()
    holes[:, : holes.shape[1] // 2] = 0.0
    full = _check(ref, [src])
    res = _check(ref, [SourceMaps(holes, src.normals, src.K, src.cam_from_world)])
    assert full.checked.sum() > res.checked.sum() > 0
    lost = full.checked & ~res.checked
    assert not res.agree[lost].any() and (res.reprojected_depth[lost] == 0).all()
    assert np.isinf(res.reproj_error[lost]).all() and np.isinf(res.depth_error[lost]).all()
    empty = _check(ref, [SourceMaps(np.zeros_like(src.depth), src.normals, src.K, src.cam_from_world)])
    assert not empty.checked.any() and not empty.agree.any()


def test_visibility_by_default_consults_every_source_and_its_threshold_is_inclusive(exact):
    ref, srcs = exact[0], exact[1:]
    half = np.full((len(srcs), *ref.depth.shape), 0.5, np.float32)
    full = _check(ref, srcs)
    for res in (_check(ref, srcs, visibility=half), _check(ref, srcs, visibility=half, min_visibility=0.5)):
        np.testing.assert_array_equal(res.checked, full.checked)
        np.testing.assert_array_equal(res.agree, full.agree)


def test_the_error_limits_are_inclusive():
    """``max_reproj_error`` and ``max_depth_error`` are "at most": a pixel exactly at both limits agrees.
    (A plane at depth 2 seen by a source shifted along x whose map says 2.125: binary fractions, so the
    errors, 0.25 px and 6.25 %, are exact.)"""
    K = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    src_T = np.hstack([np.eye(3), [[4.78125], [0.0], [0.0]]])
    src = SourceMaps(np.full((8, 16), 2.125, np.float32), None, K, src_T)
    ref = np.full((8, 8), 2.0, np.float32)
    res = check_consistency(ref, None, K, np.eye(4)[:3], [src], max_reproj_error=0.25, max_depth_error=0.0625)
    assert res.checked.all()
    assert (res.reproj_error == 0.25).all() and (res.depth_error == 0.0625).all()
    assert res.agree.all()
    assert not check_consistency(ref, None, K, np.eye(4)[:3], [src], max_reproj_error=0.2499,
                                 max_depth_error=0.0625).agree.any()


def test_a_reference_map_that_is_not_2d_is_refused(exact):
    from colmap_pvs.errors import ShapeError

    ref = exact[0]
    with pytest.raises(ShapeError, match=r"\(1, 120, 160\)"):
        check_consistency(ref.depth[None], None, ref.K, ref.cam_from_world, exact[1:])
    with pytest.raises(ShapeError, match=r"\(160,\)"):
        check_consistency(ref.depth[0], None, ref.K, ref.cam_from_world, exact[1:])


def test_only_pixels_that_land_inside_the_source_map_are_checked():
    """A source shifted by 2 pixels with a 6 x 6 map: reference columns and rows 2-7 land in its columns and
    rows 0-5 (edges included) and agree; the others land outside (negative or past the end) and are not
    checked."""
    K = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    shifted = np.hstack([np.eye(3), [[-4.0], [-4.0], [0.0]]])
    src = SourceMaps(np.full((6, 6), 2.0, np.float32), None, K, shifted)
    res = check_consistency(np.full((10, 10), 2.0, np.float32), None, K, np.eye(4)[:3], [src])
    inside = np.zeros((10, 10), bool)
    inside[2:8, 2:8] = True
    np.testing.assert_array_equal(res.checked[0], inside)
    np.testing.assert_array_equal(res.agree[0], inside)


def test_the_default_reprojection_limit_is_one_pixel(exact):
    """Without ``max_reproj_error`` a pixel agrees when its round trip lands within 1 px (COLMAP's
    ``filter_geom_consistency_max_cost``); depths 2 % too far give round trips of 0-3 px."""
    ref, srcs = exact[0], exact[1:]
    far = ref.depth * np.float32(1.02)
    res = check_consistency(far, None, ref.K, ref.cam_from_world, srcs, max_depth_error=1.0)
    err = res.reproj_error[res.checked]
    assert ((err > 1) & (err <= 2)).sum() > 100 and (err <= 1).sum() > 100
    np.testing.assert_array_equal(res.agree, res.checked & (res.reproj_error <= 1.0))


def test_cameras_as_4x4_matrices_give_the_same_result(exact):
    """``cam_from_world`` of the reference and of each source may be ``[3, 4]`` or ``[4, 4]``."""
    ref, srcs = exact[0], exact[1:]

    def square(T):
        return np.vstack([T, [0.0, 0.0, 0.0, 1.0]])

    res = _check(ref, srcs)
    squared = [SourceMaps(s.depth, s.normals, s.K, square(s.cam_from_world)) for s in srcs]
    res4 = check_consistency(ref.depth, ref.normals, ref.K, square(ref.cam_from_world), squared)
    assert res.agree.sum() > 0
    np.testing.assert_array_equal(res4.agree, res.agree)
    np.testing.assert_array_equal(res4.reproj_error, res.reproj_error)


def test_the_normal_test_skips_pixels_without_a_normal_on_either_side(exact):
    """A pixel whose source normal or reference normal is 0 (unknown) is judged by its depth alone."""
    ref, srcs = exact[0], exact[1:]
    no_source_normals = [SourceMaps(s.depth, np.zeros_like(s.normals), s.K, s.cam_from_world) for s in srcs]
    plain = _check(ref, srcs, max_normal_error=180.0)
    res = _check(ref, no_source_normals, max_normal_error=30.0)
    assert plain.agree.sum() > 0
    np.testing.assert_array_equal(res.agree, plain.agree)
    no_ref_normals = SourceMaps(ref.depth, np.zeros_like(ref.normals), ref.K, ref.cam_from_world)
    np.testing.assert_array_equal(_check(no_ref_normals, srcs, max_normal_error=30.0).agree, plain.agree)


def _plane_from_behind(depth):
    """A fronto-parallel plane at depth 2 in an 8 x 8 reference map ``depth`` (its holes 0), and a source
    with the same intrinsics 1 unit behind the reference, looking the same way (its map: 3 everywhere;
    nearest-pixel round trips of up to 1.07 px)."""
    K = np.array([[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]])
    behind = np.hstack([np.eye(3), [[0.0], [0.0], [1.0]]])
    return K, SourceMaps(np.full((8, 8), 3.0, np.float32), None, K, behind)


def test_holes_in_the_reference_map_are_not_checked():
    """Reference pixels without depth (0) are no point: not checked, whatever lands where the source sees
    the reference's centre."""
    depth = np.full((8, 8), 2.0, np.float32)
    depth[2:6, 2:6] = 0.0
    K, src = _plane_from_behind(depth)
    res = check_consistency(depth, None, K, np.eye(4)[:3], [src], max_reproj_error=2.0)
    np.testing.assert_array_equal(res.checked[0], depth > 0)
    np.testing.assert_array_equal(res.agree[0], depth > 0)


def test_points_behind_the_source_are_not_checked():
    """A point behind the source camera projects to a mirrored pixel inside its map: never checked."""
    depth, K, ref_T, src_T = _facing_source(1.0)
    behind = np.full_like(depth, 5.0)  # the source is at depth 4, looking back
    res = check_consistency(behind, None, K, ref_T, [SourceMaps(depth, None, K, src_T)])
    assert not res.checked.any() and not res.agree.any()
    assert check_consistency(depth, None, K, ref_T, [SourceMaps(depth, None, K, src_T)]).checked.any()


def test_the_normal_test_of_a_normal_along_the_camera_axis():
    """Normals facing the reference camera straight on ((0, 0, -1): the sum of their absolute values is 1)
    are compared too: flipped source normals are rejected."""
    depth = np.full((8, 8), 2.0, np.float32)
    K, src = _plane_from_behind(depth)
    facing = np.zeros((8, 8, 3), np.float32)
    facing[..., 2] = -1.0
    same = SourceMaps(src.depth, facing, K, src.cam_from_world)
    flipped = SourceMaps(src.depth, -facing, K, src.cam_from_world)
    assert check_consistency(depth, facing, K, np.eye(4)[:3], [same], max_normal_error=30.0,
                             max_reproj_error=2.0).agree.all()
    assert not check_consistency(depth, facing, K, np.eye(4)[:3], [flipped], max_normal_error=30.0,
                                 max_reproj_error=2.0).agree.any()


def test_a_source_map_one_pixel_wide():
    """The reference's first column lands in a one-pixel-wide source map (the same camera) and agrees; the
    other columns land outside it and are not checked."""
    K = np.array([[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]])
    src = SourceMaps(np.full((8, 1), 2.0, np.float32), None, K, np.eye(4)[:3])
    res = check_consistency(np.full((8, 8), 2.0, np.float32), None, K, np.eye(4)[:3], [src])
    first = np.zeros((8, 8), bool)
    first[:, 0] = True
    np.testing.assert_array_equal(res.checked[0], first)
    np.testing.assert_array_equal(res.agree[0], first)


def test_fusions_point_check_is_the_geometric_check_on_exact_maps(exact):
    """``match_points`` (fusion's form) and ``check_consistency`` (the geometric pass's) decide alike on
    exact maps: the same pixels agree (but for a few on the limits, where one form is strict and the
    other inclusive), the same source depths come home, and a block 5 % too deep agrees with neither."""
    ref, src = exact[0], exact[1]
    for depth in (ref.depth, np.where(np.arange(ref.depth.shape[1]) < 80, ref.depth * np.float32(1.05),
                                      ref.depth).astype(np.float32)):
        rows, cols = np.nonzero(depth > 0)
        points = backproject_pixels(rows, cols, depth[rows, cols].astype(np.float64), ref.K)
        match = match_points(points, rows, cols, ref.K, ref.cam_from_world, src,
                             max_reproj_error=1.0, max_depth_error=0.01)
        dense = check_consistency(depth, None, ref.K, ref.cam_from_world, [src])
        agree = np.zeros_like(dense.agree[0])
        agree[rows[match.index], cols[match.index]] = True
        assert agree.sum() > 1000 and (agree != dense.agree[0]).sum() <= 0.001 * agree.sum()
        both = dense.agree[0][rows[match.index], cols[match.index]]
        np.testing.assert_allclose(match.points[both, 2],
                                   dense.reprojected_depth[0][rows[match.index], cols[match.index]][both],
                                   rtol=1e-6)
        assert (src.depth[match.rows, match.cols] > 0).all()
    assert not agree[:, :80].any()


def test_fusions_point_check_limits_are_strict():
    """``match_points``'s limits are "less than" (COLMAP-like fusion): the plane of
    ``test_the_error_limits_are_inclusive``, whose errors are exactly 0.25 px and 6.25 %, agrees only
    with limits above both."""
    K = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    src_T = np.hstack([np.eye(3), [[4.78125], [0.0], [0.0]]])
    src = SourceMaps(np.full((8, 16), 2.125, np.float32), None, K, src_T)
    rows, cols = np.nonzero(np.ones((8, 8), bool))
    points = backproject_pixels(rows, cols, np.full(64, 2.0), K)

    def agreeing(reproj, depth):
        return len(match_points(points, rows, cols, K, np.eye(4)[:3], src, max_reproj_error=reproj,
                                max_depth_error=depth).index)

    assert agreeing(0.2501, 0.0626) == 64
    assert agreeing(0.25, 0.0626) == agreeing(0.2501, 0.0625) == 0
