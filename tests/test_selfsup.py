"""Self-supervised losses (colmap_pvs.train.selfsup) on the exact analytic scene."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from colmap_pvs.errors import ShapeError
from colmap_pvs.train.selfsup import (
    SelfSupConfig,
    photometric_error,
    selfsup_loss,
    smoothness,
    warp_to_reference,
)


def _views(gt: dict, order: list[int]):
    """``images [1, N, 3, H, W]``, ``K [1, N, 3, 3]``, ``poses [1, N, 4, 4]`` and the reference GT depth."""
    names = [gt["names"][i] for i in order]
    model = gt["model"]
    ims, Ks, poses = [], [], []
    for name in names:
        im = model.image_by_name(name)
        ims.append(gt["rgb"][name].astype(np.float32).transpose(2, 0, 1) / 255.0)
        Ks.append(model.camera_of(im).K)
        T = np.eye(4)
        T[:3] = im.cam_from_world
        poses.append(T)
    f = lambda a: torch.as_tensor(np.stack(a), dtype=torch.float32)[None]  # noqa: E731
    depth = torch.as_tensor(gt["depth"][names[0]], dtype=torch.float32)[None]
    return f(ims), f(Ks), f(poses), depth


def _mean_error(images, K, poses, depth, mask=None):
    err, m = photometric_error(images, K, poses, depth)
    m = m & (depth > 0) if mask is None else mask
    return float(err[m].mean()), m


def test_photometric_loss_is_minimal_at_the_true_depth(analytic_scene):
    images, K, poses, depth = _views(analytic_scene, [0, 1, 2, 3])
    _, mask = _mean_error(images, K, poses, depth)
    factors = [0.8, 0.9, 0.95, 1.0, 1.05, 1.1, 1.25]
    errors = [_mean_error(images, K, poses, depth * f, mask)[0] for f in factors]
    best = int(np.argmin(errors))
    assert factors[best] == 1.0, errors
    # it rises on both sides, monotonically
    assert all(np.diff(errors[: best + 1]) < 0) and all(np.diff(errors[best:]) > 0), errors
    assert errors[best] < 0.5 * min(errors[0], errors[-1])


def test_warp_reproduces_the_reference_where_visible(analytic_scene):
    images, K, poses, depth = _views(analytic_scene, [0, 1])
    warped, valid = warp_to_reference(images, K, poses, depth)
    assert warped.shape == (1, 1, 3, *depth.shape[1:]) and valid.dtype == torch.bool
    m = valid[0, 0] & (depth[0] > 0)
    assert m.float().mean() > 0.5
    diff = (warped[0, 0] - images[0, 0]).abs().mean(0)[m]
    assert float(diff.median()) < 0.05


def test_minimum_over_sources_ignores_an_unrelated_view(analytic_scene):
    images, K, poses, depth = _views(analytic_scene, [0, 1, 2])
    _, valid = warp_to_reference(images, K, poses, depth)
    mask = valid.all(dim=1) & (depth > 0)  # pixels that both sources see
    single, _ = _mean_error(images[:, :2], K[:, :2], poses[:, :2], depth, mask)  # source 1 alone
    noisy = images.clone()
    noisy[:, 2] = torch.rand_like(noisy[:, 2])  # a "view" that shows something else entirely
    disturbed, _ = _mean_error(noisy, K, poses, depth, mask)
    only_noise = _mean_error(noisy[:, [0, 2]], K[:, [0, 2]], poses[:, [0, 2]], depth, mask)[0]
    # the unrelated view never makes a pixel worse than source 1 alone (a mean over sources would)
    assert disturbed <= single + 1e-6
    assert only_noise > 3 * single


def test_pixels_outside_every_source_frustum_are_masked(analytic_scene):
    images, K, poses, depth = _views(analytic_scene, [0, 1])
    away = poses.clone()
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))  # the source looks the other way
    away[:, 1] = flip @ poses[:, 1]
    _, mask = photometric_error(images, K, away, depth.clamp_min(0.1))
    assert not bool(mask.any())


def test_smoothness_is_zero_for_a_constant_depth_and_edge_aware():
    img = torch.rand(1, 3, 16, 20)
    flat = torch.full((1, 16, 20), 2.0)
    assert float(smoothness(flat, img)) == pytest.approx(0.0, abs=1e-7)
    step = flat.clone()
    step[:, :, 10:] = 4.0
    edge_img = torch.zeros(1, 3, 16, 20)
    edge_img[:, :, :, 10:] = 1.0
    flat_img = torch.zeros(1, 3, 16, 20)
    # a depth edge costs less where the image has an edge too
    assert float(smoothness(step, edge_img)) < float(smoothness(step, flat_img))
    noisy = flat * (1 + 0.2 * torch.rand(1, 16, 20))
    assert float(smoothness(noisy, flat_img)) > float(smoothness(flat, flat_img))


def test_selfsup_loss_sparse_term_pins_the_labels(analytic_scene):
    images, K, poses, depth = _views(analytic_scene, [0, 1, 2])
    labels = torch.zeros_like(depth)
    rows = torch.randint(0, depth.shape[1], (50,))
    cols = torch.randint(0, depth.shape[2], (50,))
    labels[0, rows, cols] = depth[0, rows, cols]
    dmin, dmax = torch.tensor([0.5]), torch.tensor([10.0])
    cfg = SelfSupConfig(photometric_weight=0.0, smooth_weight=0.0)
    exact = selfsup_loss([depth], images, K, poses, labels, dmin, dmax, [1.0], [1], cfg)
    wrong = selfsup_loss([depth * 1.2], images, K, poses, labels, dmin, dmax, [1.0], [1], cfg)
    assert float(exact.total) == pytest.approx(0.0, abs=1e-6)
    assert float(wrong.total) > 0.01


def test_selfsup_loss_on_coarse_outputs_and_gradient(analytic_scene):
    images, K, poses, depth = _views(analytic_scene, [0, 1, 2])
    h, w = depth.shape[1:]
    coarse = torch.nn.functional.interpolate(depth[:, None], size=(-(-h // 4), -(-w // 4)))[:, 0]
    coarse = (coarse.clamp_min(0.5) * 1.1).requires_grad_(True)
    loss = selfsup_loss(
        [coarse, depth.clamp_min(0.5)], images, K, poses, torch.zeros_like(depth),
        torch.tensor([0.5]), torch.tensor([10.0]), [1.0, 1.0], [4, 1],
    )
    loss.total.backward()
    assert torch.isfinite(loss.total) and coarse.grad is not None and float(coarse.grad.abs().sum()) > 0
    assert loss.per_output.shape == (2,)


def test_bad_shapes_are_refused():
    with pytest.raises(ShapeError):
        warp_to_reference(torch.rand(2, 3, 8, 8), torch.eye(3)[None], torch.eye(4)[None], torch.ones(1, 8, 8))


def test_selfsup_loss_pseudo_term_pins_the_dense_labels(analytic_scene):
    """The pseudo-label term is zero at the labelled depth, grows away from it, and is off without labels."""
    images, K, poses, depth = _views(analytic_scene, [0, 1, 2])
    dmin, dmax = torch.tensor([0.5]), torch.tensor([10.0])
    no_sparse = torch.zeros_like(depth)
    cfg = SelfSupConfig(photometric_weight=0.0, smooth_weight=0.0, sparse_weight=0.0, pseudo_weight=2.0)
    args = (images, K, poses, no_sparse, dmin, dmax, [1.0], [1], cfg)
    exact = selfsup_loss([depth], *args, pseudo_depth=depth)
    near = selfsup_loss([depth * 1.05], *args, pseudo_depth=depth)
    far = selfsup_loss([depth * 1.2], *args, pseudo_depth=depth)
    assert float(exact.total) == pytest.approx(0.0, abs=1e-6)
    assert 0.0 < float(near.total) < float(far.total)
    assert float(far.total) == pytest.approx(2.0 * float(far.pseudo), rel=1e-5)
    without = selfsup_loss([depth * 1.2], *args)
    assert without.pseudo is None and float(without.total) == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(ShapeError, match="pseudo_depth"):
        selfsup_loss([depth], *args, pseudo_depth=depth[:, :-1])
