"""Plane-sweep warping: pixel-centre convention, per-pixel depths, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from colmap_pvs.errors import ShapeError
from colmap_pvs.model.planes import render_plane
from colmap_pvs.model.warping import (
    homography_grid,
    hypothesis_depths,
    plane_range,
    relative_pose,
    scale_intrinsics,
    warp_features,
    warp_features_parts,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


H, W = 48, 64


def _pose(rvec, t) -> np.ndarray:
    import cv2

    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _scene(normal, offset):
    K = np.array([[52.0, 0.0, 31.0], [0.0, 50.0, 25.0], [0.0, 0.0, 1.0]])
    K_src = np.array([[47.0, 0.0, 33.5], [0.0, 49.0, 22.0], [0.0, 0.0, 1.0]])
    T_ref = _pose([0.02, -0.03, 0.01], [0.05, -0.02, 0.1])
    T_src = _pose([-0.04, 0.08, -0.02], [-0.35, 0.06, 0.05])
    kw = dict(normal=normal, offset=offset, period=1.2)
    ref_img, ref_depth = render_plane(K, T_ref, H, W, **kw)
    src_img, _ = render_plane(K_src, T_src, H, W, **kw)
    return K, K_src, T_ref, T_src, ref_img, ref_depth, src_img


def _warp_at_true_depth(K, K_src, T_ref, T_src, src_img, depth, shift=(0.0, 0.0)):
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)[None]  # noqa: E731
    poses = torch.stack([t(T_ref)[0], t(T_src)[0]])[None]
    src_from_ref = relative_pose(poses, 1)
    grid = homography_grid(t(K), t(K_src), src_from_ref, t(depth)[:, None], H, W)
    grid = grid + torch.tensor([2 * shift[0] / W, 2 * shift[1] / H], dtype=grid.dtype)
    warped = warp_features(t(src_img), grid, 1)[0, :, 0]  # [3, H, W]
    inside = (grid.abs() < 0.85).all(-1).view(H, W)  # well inside the source image
    return warped.numpy(), inside.numpy()


@pytest.mark.parametrize(
    "normal, offset",
    [
        ((0.0, 0.0, 1.0), 3.0),  # fronto-parallel (up to the small reference rotation)
        ((0.25, -0.3, 1.0), 3.2),  # slanted
    ],
    ids=["fronto_parallel", "slanted"],
)
def test_warp_at_true_depth_reproduces_reference(normal, offset):
    K, K_src, T_ref, T_src, ref_img, ref_depth, src_img = _scene(normal, offset)
    assert (ref_depth > 0).all()
    warped, inside = _warp_at_true_depth(K, K_src, T_ref, T_src, src_img, ref_depth)
    inside[:2], inside[-2:], inside[:, :2], inside[:, -2:] = False, False, False, False
    assert inside.sum() > 0.4 * H * W
    err = np.abs(warped - ref_img)[:, inside]
    # Only the bilinear interpolation error of a smooth texture remains.
    assert err.max() < 0.03, err.max()
    assert err.mean() < 0.006, err.mean()
    # Sensitivity: a half-pixel convention error (e.g. align_corners=True or a missing +0.5)
    # would be caught.
    for shift in [(0.5, 0.0), (0.0, 0.5), (0.5, 0.5)]:
        shifted, _ = _warp_at_true_depth(K, K_src, T_ref, T_src, src_img, ref_depth, shift)
        assert np.abs(shifted - ref_img)[:, inside].max() > 2 * err.max()


def test_warp_at_wrong_depth_does_not_reproduce_reference():
    K, K_src, T_ref, T_src, ref_img, ref_depth, src_img = _scene((0.0, 0.0, 1.0), 3.0)
    warped, inside = _warp_at_true_depth(K, K_src, T_ref, T_src, src_img, ref_depth * 1.15)
    assert np.abs(warped - ref_img)[:, inside].mean() > 0.02


def test_identity_pose_is_identity_warp():
    K = torch.tensor([[[20.0, 0.0, 8.0], [0.0, 20.0, 6.0], [0.0, 0.0, 1.0]]])
    src = torch.rand(1, 4, 12, 16)
    grid = homography_grid(K, K, torch.eye(4)[None], torch.tensor([[1.0, 2.0, 5.0]]), 12, 16)
    warped = warp_features(src, grid, 3)
    assert warped.shape == (1, 4, 3, 12, 16)
    for d in range(3):
        torch.testing.assert_close(warped[:, :, d], src, atol=1e-5, rtol=0)


def test_scaled_intrinsics_match_downsampled_image():
    """A map downsampled by 4 with diag(1/4, 1/4, 1) K sees the same geometry (COLMAP convention)."""
    K, K_src, T_ref, T_src, ref_img, ref_depth, src_img = _scene((0.0, 0.0, 1.0), 3.0)
    Ks = scale_intrinsics(torch.tensor(K)[None], 0.25)[0].numpy()
    small, small_depth = render_plane(Ks, T_ref, H // 4, W // 4, normal=(0, 0, 1), offset=3.0, period=1.2)
    pooled = F.avg_pool2d(torch.tensor(ref_img)[None], 4)[0].numpy()
    assert np.abs(small - pooled).max() < 0.03  # pixel centres line up; only blur differs
    pooled_depth = F.avg_pool2d(torch.tensor(ref_depth)[None, None], 4)[0, 0].numpy()
    assert np.abs(small_depth - pooled_depth).max() < 1e-3


def test_points_behind_source_camera_sample_zero():
    K = torch.tensor([[[20.0, 0.0, 8.0], [0.0, 20.0, 6.0], [0.0, 0.0, 1.0]]])
    T = torch.eye(4)[None].clone()
    T[0, 2, 3] = -10.0  # source camera 10 units in front of the reference: plane at z=2 is behind it
    grid = homography_grid(K, K, T, torch.tensor([[2.0]]), 12, 16)
    warped = warp_features(torch.ones(1, 2, 12, 16), grid, 1)
    assert torch.all(warped == 0)


def test_planes_uniform_in_inverse_depth():
    dmin, dmax = torch.tensor([1.0, 2.0]), torch.tensor([10.0, 4.0])
    inv_start, inv_step = plane_range(dmin, dmax, 8)
    depths = hypothesis_depths(inv_start, inv_step, 8)[:, :, 0, 0]
    torch.testing.assert_close(depths[:, 0], dmin)
    torch.testing.assert_close(depths[:, -1], dmax)
    inv = 1.0 / depths
    torch.testing.assert_close(inv[:, 1:] - inv[:, :-1], -inv_step.view(2, 1).expand(2, 7))
    assert torch.all(depths[:, 1:] > depths[:, :-1])


def test_warping_gradcheck():
    torch.manual_seed(0)
    K = torch.tensor([[[6.0, 0, 2.6], [0, 6.0, 2.1], [0, 0, 1]]], dtype=torch.float64)
    T = torch.eye(4, dtype=torch.float64)[None].clone()
    T[0, 0, 3], T[0, 1, 3] = 0.3, 0.1
    src = torch.rand(1, 2, 4, 5, dtype=torch.float64, requires_grad=True)
    planes = torch.tensor([[2.3, 3.1, 4.7]], dtype=torch.float64, requires_grad=True)
    per_pixel = (torch.rand(1, 3, 4, 5, dtype=torch.float64) * 3 + 2).requires_grad_()

    def f(s, d):
        return warp_features(s, homography_grid(K, K, T, d, 4, 5), 3)

    assert torch.autograd.gradcheck(f, (src, planes))
    assert torch.autograd.gradcheck(f, (src, per_pixel))


def test_inside_source_matches_projecting_each_pixel():
    """``inside_source`` is true exactly where the pixel centre's point projects in front of the source
    and within its image (and within ``valid_size`` when given)."""
    from colmap_pvs.model.warping import homography_rays, inside_source

    K = np.array([[52.0, 0.0, 31.0], [0.0, 50.0, 25.0], [0.0, 0.0, 1.0]])
    T_src = _pose([0.1, -0.5, 0.05], [-0.6, 0.1, 0.2])
    depths = torch.tensor([[0.7, 2.0, 9.0]], dtype=torch.float64)
    Kt = torch.from_numpy(K)[None]
    rays, b = homography_rays(Kt, Kt, torch.from_numpy(T_src)[None], H, W, torch.float64)
    cols, rows = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    pix = np.stack([cols.ravel(), rows.ravel(), np.ones(H * W)])
    for valid in (None, (40.0, 30.0)):
        got = inside_source(rays, b, depths, H, W, valid).numpy()[0]
        vw, vh = valid if valid is not None else (W, H)
        for k, d in enumerate(depths[0].tolist()):
            X = np.linalg.inv(K) @ pix * d
            p = K @ (T_src[:3, :3] @ X + T_src[:3, 3:])
            u, v = p[0] / p[2], p[1] / p[2]
            want = ((p[2] > 0) & (u >= 0) & (u <= vw) & (v >= 0) & (v <= vh)).reshape(H, W)
            assert 0 < want.sum() < H * W  # the case has both
            assert (got[k] != want).mean() < 0.002  # pixels exactly on the border may round either way
    behind = torch.from_numpy(np.diag([-1.0, 1.0, -1.0, 1.0]))[None]
    rays, b = homography_rays(Kt, Kt, behind, H, W, torch.float64)
    assert not inside_source(rays, b, depths, H, W).any()


def test_planes_sampled_in_parts_are_the_planes_sampled_at_once():
    """``warp_features_parts``: entry ``j`` holds planes ``j * D / parts ...``, each value the same bits as
    :func:`warp_features`'s (the rows a batch entry samples are the same rows)."""
    g = torch.Generator().manual_seed(0)
    src = torch.randn(1, 8, 12, 16, generator=g)
    grid = torch.rand(1, 6 * 12, 16, 2, generator=g) * 2.4 - 1.2  # some outside the map
    whole = warp_features(src, grid, 6)
    for parts in (1, 2, 3, 6):
        split = warp_features_parts(src, grid, 6, parts)
        assert split.shape == (parts, 8, 6 // parts, 12, 16)
        assert torch.equal(split.transpose(0, 1).reshape(1, 8, 6, 12, 16), whole), parts
    with pytest.raises(ShapeError, match="6 planes of batch 1 in 4 parts"):
        warp_features_parts(src, grid, 6, 4)
