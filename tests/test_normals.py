"""Normals from depth: unit length, camera-facing, exact on planes."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_pvs.errors import ShapeError
from colmap_pvs.geometry import backproject_depth, pixel_centers
from colmap_pvs.normals import depth_to_normals, plane_residual

K = np.array([[90.0, 0, 41.0], [0, 95.0, 29.0], [0, 0, 1]])


def plane_depth(n: np.ndarray, d: float, h: int = 60, w: int = 80) -> np.ndarray:
    """z-depth of the plane n.x = d (camera frame) at every pixel centre."""
    u, v = pixel_centers(h, w)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return d / (rays @ n)


def test_plane_normals_are_exact_and_face_the_camera():
    n_true = np.array([0.3, -0.2, -1.0])
    n_true /= np.linalg.norm(n_true)
    depth = plane_depth(n_true, -3.0)
    assert (depth > 0).all()
    normals = depth_to_normals(depth, K)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(normals.reshape(-1, 3), np.broadcast_to(n_true, (60 * 80, 3)), atol=1e-4)
    pts = backproject_depth(depth, K)
    assert (np.sum(normals * pts, -1) < 0).all()


def test_flipped_input_orientation_is_still_camera_facing():
    # The same plane written as -n . x = 3 has the same depth; normals must still face the camera.
    n = np.array([0.0, 0.0, 1.0])
    depth = plane_depth(n, 2.0)
    normals = depth_to_normals(depth, K)
    np.testing.assert_allclose(normals[..., 2], -1.0, atol=1e-6)


def test_invalid_pixels_and_discontinuities_get_no_normal_bleed():
    depth = np.full((40, 50), 2.0)
    depth[:, 25:] = 5.0  # a jump: both sides are fronto-parallel
    depth[10, 10] = 0.0
    normals = depth_to_normals(depth, K[:, :] * [[1], [1], [1]])
    assert np.all(normals[10, 10] == 0)
    np.testing.assert_allclose(normals[20, 24], [0, 0, -1], atol=1e-6)
    np.testing.assert_allclose(normals[20, 25], [0, 0, -1], atol=1e-6)
    isolated = np.zeros((5, 5))
    isolated[2, 2] = 1.0
    assert np.all(depth_to_normals(isolated, K) == 0)


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1, 1)))


def test_fitted_normals_beat_finite_differences_on_noisy_depth(analytic_scene):
    """Angular error vs. the exact normals of the analytic scene with 0.3 % depth noise."""
    from colmap_pvs.normals import fit_normals

    gt = analytic_scene
    name = gt["names"][0]
    K_img = gt["model"].camera_of(gt["model"].image_by_name(name)).K
    depth, n_true = gt["depth"][name], gt["normals"][name]
    rng = np.random.default_rng(0)
    noisy = depth * (1 + 0.003 * rng.standard_normal(depth.shape)) * (depth > 0)
    fd, fit = depth_to_normals(noisy, K_img), fit_normals(noisy, K_img)
    both = np.any(fd != 0, -1) & np.any(fit != 0, -1)
    assert both.mean() > 0.8
    err_fd, err_fit = _angles(fd, n_true)[both], _angles(fit, n_true)[both]
    assert np.median(err_fit) < 0.4 * np.median(err_fd)
    assert np.median(err_fit) < 5.0
    np.testing.assert_allclose(np.linalg.norm(fit[both], axis=-1), 1.0, atol=1e-5)
    pts = backproject_depth(noisy, K_img)
    assert (np.sum(fit * pts, -1)[both] < 0).all()
    # Exact on a plane too.
    n_plane = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    plane = fit_normals(plane_depth(n_plane, -3.0), K)
    inner = np.any(plane != 0, -1)
    assert inner.mean() > 0.8
    np.testing.assert_allclose(plane[inner], np.broadcast_to(n_plane, plane[inner].shape), atol=1e-4)


def test_plane_residual_is_zero_on_any_plane_and_large_at_depth_edges():
    """The RMS residual of the local least-squares plane in inverse depth, relative to the mean inverse
    depth (docs/CONVENTIONS.md, photometric confidence)."""
    h, w = 60, 80
    v, u = np.mgrid[:h, :w].astype(np.float64)
    slanted = 1.0 / (0.2 + 0.004 * u + 0.002 * v)  # a 3D plane seen at a grazing angle: 1/d linear in u, v
    assert plane_residual(slanted, 9).max() < 1e-5
    step = slanted.copy()
    step[:, 40:] *= 1.5  # a depth edge
    r = plane_residual(step, 9)
    assert r[30, 36:44].min() > 0.05 and r[30, :31].max() < 1e-5 and r[30, 49:].max() < 1e-5
    # one pixel off its plane: inverse depths z_i = z (1 + e) at one of n pixels -> RMS about e sqrt(1/n)
    bump = np.full((h, w), 2.0)
    bump[30, 40] = 2.0 / 1.1
    r = plane_residual(bump, 9)
    assert 0.1 / 9 * 0.8 < r[30, 40] < 0.1 / 9 * 1.2
    # invalid pixels: 0 there, ignored around them
    holes = slanted.copy()
    holes[::5, ::3] = 0.0
    r = plane_residual(holes, 9)
    assert np.all(r[holes == 0] == 0) and r.max() < 1e-5
    assert plane_residual(np.zeros((h, w)), 9).max() == 0
    with pytest.raises(ShapeError):
        plane_residual(np.ones((2, 3, 4)), 9)
    with pytest.raises(ValueError, match="odd"):
        plane_residual(slanted, 8)
