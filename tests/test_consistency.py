"""The geometric pass's forward-backward consistency check (``colmap_pvs.consistency``) on exact maps."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_pvs.consistency import SourceMaps, check_consistency


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
    assert one.agree.any() and not one.agree.all()
    for field in ("agree", "checked", "reproj_error", "depth_error", "reprojected_depth", "parallax"):
        np.testing.assert_array_equal(getattr(many, field), getattr(one, field), err_msg=field)
