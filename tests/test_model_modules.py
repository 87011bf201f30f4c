"""Unit tests of the PVSNet building blocks: shapes, aggregation, regression, guidance, conv dispatch."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from colmap_pvs.errors import ConfigError, ShapeError
from colmap_pvs.model import PVSNetConfig
from colmap_pvs.model.cascade import (
    next_stage_range,
    prior_halfwidth_map,
    prior_plane_range,
    probability_confidence,
    regress_inverse_depth,
)
from colmap_pvs.model.cost import (
    affine_fill_inverse_depth,
    densify_inverse_depth,
    downsample_sparse_depth,
    group_correlation,
    guidance_weights,
)
from colmap_pvs.model.features import FeatureNet
from colmap_pvs.model.layers import ConvBnReLU, Up3d, conv_nd
from colmap_pvs.model.regularization import CoarseRegularizer, ResNet3D, StageRegularizer, UNet3D
from colmap_pvs.model.visibility import (
    CostAccumulator,
    VisibilityNet,
    aggregate,
    normalized_weights,
    truncate_visibility,
)
from colmap_pvs.model.warping import plane_range

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


# ----------------------------------------------------------------------------- shapes


def test_feature_net_shapes():
    net = FeatureNet((16, 8, 4))
    outs = net(torch.rand(2, 3, 32, 48))
    assert [tuple(o.shape) for o in outs] == [(2, 16, 8, 12), (2, 8, 16, 24), (2, 4, 32, 48)]
    assert len(net(torch.rand(1, 3, 32, 48), levels=1)) == 1


@pytest.mark.parametrize("train", [True, False])
def test_volume_network_shapes(train):
    x = torch.rand(1, 4, 8, 12, 16)
    for net, cout in [(UNet3D(4, 8), 8), (ResNet3D(4, 8, 2), 8)]:
        net.train(train)
        assert net(x).shape == (1, cout, 8, 12, 16)
    reg = CoarseRegularizer(4, 8, 1).train(train)
    logits = reg(x)
    assert len(logits) == 3 and all(lg.shape == (1, 8, 12, 16) for lg in logits)
    assert StageRegularizer(4, 8).train(train)(x).shape == (1, 8, 12, 16)
    vis = VisibilityNet(4, 8).train(train)
    v = vis(x)
    assert v.shape == (1, 1, 12, 16) and torch.all((v > 0) & (v < 1))
    pv = vis.probability(x)
    assert pv.shape == (1, 8, 12, 16)
    torch.testing.assert_close(pv.amax(1, keepdim=True), v)  # V = max_d P_v


def test_up3d_doubles_every_axis():
    assert Up3d(8, 4)(torch.rand(1, 8, 2, 3, 4)).shape == (1, 4, 4, 6, 8)


def test_group_correlation():
    ref = torch.rand(2, 8, 5, 6)
    warped = torch.rand(2, 8, 3, 5, 6)
    out = group_correlation(ref, warped.clone(), 4)
    expected = (warped.view(2, 4, 2, 3, 5, 6) * ref.view(2, 4, 2, 1, 5, 6)).mean(2)
    assert out.shape == (2, 4, 3, 5, 6)
    torch.testing.assert_close(out, expected)
    with torch.no_grad():  # in-place path, and one channel per group
        torch.testing.assert_close(group_correlation(ref, warped.clone(), 8), warped * ref[:, :, None])
        torch.testing.assert_close(group_correlation(ref, warped.clone(), 4), expected)
    with pytest.raises(ShapeError):
        group_correlation(ref, warped, 3)
    # Weighted accumulation (used by the cascade stages) == sum of weighted volumes.
    wt = [torch.rand(2, 1, 5, 6) for _ in range(2)]
    warps = [torch.rand(2, 8, 3, 5, 6) for _ in range(2)]
    for groups in (4, 8):
        expected = sum(
            group_correlation(ref, x.clone(), groups) * v[:, None] for x, v in zip(warps, wt, strict=True)
        )
        for grad in (True, False):
            with torch.set_grad_enabled(grad):
                acc = None
                for x, v in zip(warps, wt, strict=True):
                    acc = group_correlation(ref, x.clone(), groups, pixel_weight=v, accumulate=acc)
            torch.testing.assert_close(acc, expected)


# ----------------------------------------------------------------------------- conv dispatch


@pytest.mark.parametrize(
    "shape, cout, stride", [((1, 8, 4, 6, 8), 8, 1), ((1, 4, 4, 6, 8), 3, 2), ((2, 4, 4, 6, 8), 6, 1)]
)
def test_conv_dispatch_matches_plain_conv(shape, cout, stride):
    """The oneDNN group trick / direct call compute exactly the dense convolution, with gradients."""
    x = torch.rand(*shape, requires_grad=True)
    w = torch.rand(cout, shape[1], 3, 3, 3, requires_grad=True)
    b = torch.rand(cout, requires_grad=True)
    y = conv_nd(x, w, b, stride, 1)
    ref = F.conv3d(x, w, b, stride, 1)
    torch.testing.assert_close(y, ref, atol=1e-4, rtol=1e-4)
    g = torch.rand_like(ref)
    grads = torch.autograd.grad(y, (x, w, b), g)
    grads_ref = torch.autograd.grad(ref, (x, w, b), g)
    for a, r in zip(grads, grads_ref, strict=True):
        torch.testing.assert_close(a, r, atol=1e-3, rtol=1e-4)
    with torch.inference_mode():
        torch.testing.assert_close(conv_nd(x, w, b, stride, 1), ref.detach(), atol=1e-4, rtol=1e-4)


def test_bn_folding_in_eval_matches_unfolded():
    layer = ConvBnReLU(4, 8)
    layer.train()
    for _ in range(3):
        layer(torch.randn(2, 4, 4, 6, 8))  # populate running statistics
    layer.eval()
    x = torch.randn(1, 4, 4, 6, 8)
    expected = F.relu(layer.bn(F.conv3d(x, layer.weight, None, 1, 1)))
    with torch.no_grad():
        torch.testing.assert_close(layer(x), expected, atol=1e-4, rtol=1e-4)


# ----------------------------------------------------------------------------- aggregation


def test_visibility_off_aggregation_is_plain_mean():
    costs = [torch.rand(1, 4, 3, 5, 6) for _ in range(3)]
    torch.testing.assert_close(aggregate(costs, None), sum(costs) / 3)
    with torch.no_grad():  # in-place accumulation path
        torch.testing.assert_close(aggregate([c.clone() for c in costs], None), sum(costs) / 3)
    # Equal visibility weights also give the plain mean.
    w = [torch.full((1, 1, 5, 6), 0.7)] * 3
    torch.testing.assert_close(aggregate(costs, w), sum(costs) / 3)


def test_weighted_aggregation():
    costs = [torch.rand(1, 4, 3, 5, 6) for _ in range(2)]
    w = [torch.rand(1, 1, 5, 6) + 0.1 for _ in range(2)]
    expected = (costs[0] * w[0][:, None] + costs[1] * w[1][:, None]) / (w[0] + w[1])[:, None]
    torch.testing.assert_close(aggregate(costs, w), expected)


def test_truncation_zeroes_views_below_tau():
    v = torch.tensor([[[[0.01, 0.049, 0.05, 0.051, 0.9]]]])
    t = truncate_visibility(v, 0.05)
    torch.testing.assert_close(t, torch.tensor([[[[0.0, 0.0, 0.0, 0.051, 0.9]]]]))
    # A truncated view does not contribute to the aggregation at all.
    costs = [torch.rand(1, 2, 3, 1, 5), torch.full((1, 2, 3, 1, 5), 100.0)]
    weights = [torch.ones(1, 1, 1, 5), truncate_visibility(torch.full((1, 1, 1, 5), 0.04), 0.05)]
    torch.testing.assert_close(aggregate(costs, weights), costs[0])


def test_all_truncated_guard_is_finite_plain_mean():
    costs = [torch.rand(1, 2, 3, 4, 5) for _ in range(3)]
    zeros = [torch.zeros(1, 1, 4, 5)] * 3
    out = aggregate(costs, zeros)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, sum(costs) / 3)
    # Mixed: some pixels all-truncated, others not.
    w = [torch.zeros(1, 1, 4, 5) for _ in range(3)]
    w[1][..., 0, :] = 0.5
    out = aggregate(costs, w)
    torch.testing.assert_close(out[..., 0, :], costs[1][..., 0, :])
    torch.testing.assert_close(out[..., 1:, :], (sum(costs) / 3)[..., 1:, :])
    # Gradients stay finite too.
    c = [x.clone().requires_grad_() for x in costs]
    aggregate(c, zeros).sum().backward()
    assert all(torch.isfinite(x.grad).all() for x in c)


def test_normalized_weights():
    w = [torch.tensor([[[[0.2, 0.0]]]]), torch.tensor([[[[0.6, 0.0]]]])]
    n = normalized_weights(w)
    torch.testing.assert_close(torch.cat(n, 1), torch.tensor([[[[0.25, 0.5]], [[0.75, 0.5]]]]))


def test_accumulator_requires_a_volume():
    with pytest.raises(ValueError):
        CostAccumulator().result()


# ----------------------------------------------------------------------------- regression


def test_inverse_depth_regression_and_confidence():
    inv_start, inv_step = plane_range(torch.tensor([1.0]), torch.tensor([5.0]), 8)
    prob = torch.zeros(1, 8, 2, 3)
    prob[:, 3] = 1.0
    reg = regress_inverse_depth(prob, inv_start, inv_step)
    expected = 1.0 / (inv_start - 3 * inv_step)
    torch.testing.assert_close(reg.depth, expected.view(1, 1, 1).expand(1, 2, 3))
    torch.testing.assert_close(reg.index, torch.full((1, 2, 3), 3.0))
    assert torch.all(reg.inv_sigma < 1e-5)
    # Two equal peaks: the mean is taken in inverse depth (eq. 5), not in depth.
    prob = torch.zeros(1, 8, 1, 1)
    prob[:, 0] = prob[:, 7] = 0.5
    reg = regress_inverse_depth(prob, inv_start, inv_step)
    torch.testing.assert_close(reg.depth.view(()), torch.tensor(1.0 / (0.5 * (1.0 + 0.2))))
    conf = probability_confidence(prob, reg.index, 4)
    torch.testing.assert_close(conf.view(()), torch.tensor(0.0))
    uniform = torch.full((1, 8, 1, 1), 1 / 8)
    r = regress_inverse_depth(uniform, inv_start, inv_step)
    torch.testing.assert_close(probability_confidence(uniform, r.index, 4).view(()), torch.tensor(0.5))


def test_next_stage_range_is_clamped_and_has_min_width():
    dmin, dmax = torch.tensor([1.0]), torch.tensor([5.0])
    inv_start, inv_step = plane_range(dmin, dmax, 8)
    inv_mean = torch.tensor([0.21, 0.6, 0.99]).view(1, 1, 1, 3)
    sigma = torch.tensor([0.0, 0.0, 0.5]).view(1, 1, 1, 3)
    start, step = next_stage_range(
        inv_mean,
        sigma,
        inv_step,
        (2, 6),
        4,
        k=1.5,
        min_halfwidth_planes=1.0,
        inv_lo=1 / dmax,
        inv_hi=1 / dmin,
    )
    assert start.shape == step.shape == (1, 1, 2, 6)
    end = start - 3 * step
    assert torch.all(start <= 1.0 + 1e-6) and torch.all(end >= 0.2 - 1e-6)
    # Minimum half-width of one coarse plane spacing in the middle.
    torch.testing.assert_close(step[0, 0, 0, 2], 2 * inv_step.view(()) / 3, atol=1e-3, rtol=1e-3)
    # A huge sigma is limited to the full range.
    assert torch.all(2 * 1.5 * 0.5 >= start[..., -1] - end[..., -1])


def test_next_stage_range_spans_both_sides_of_an_edge_within_the_neighbourhood():
    """``neighbourhood = r``: a pixel within ``r`` of a depth edge gets hypotheses on both sides of it
    (a thin structure merged with its background keeps both depths); farther away the range is the
    same as without the neighbourhood."""
    dmin, dmax = torch.tensor([1.0]), torch.tensor([5.0])
    _, inv_step = plane_range(dmin, dmax, 32)
    inv_mean = torch.full((1, 1, 1, 12), 0.3)
    inv_mean[..., 6:] = 0.9  # near (inverse depth 0.9) right of column 6, far (0.3) left of it
    sigma = torch.full_like(inv_mean, 0.01)
    common = dict(k=1.5, min_halfwidth_planes=1.0, inv_lo=1 / dmax, inv_hi=1 / dmin)
    plain = next_stage_range(inv_mean, sigma, inv_step, (1, 12), 8, **common)
    wide = next_stage_range(inv_mean, sigma, inv_step, (1, 12), 8, neighbourhood=2, **common)
    zero = next_stage_range(inv_mean, sigma, inv_step, (1, 12), 8, neighbourhood=0, **common)
    for a, b in zip(plain, zero, strict=True):
        torch.testing.assert_close(a, b)  # 0 is off: the range of before
    start, step = wide
    end = start - 7 * step
    for col in (4, 5, 6, 7):  # within 2 pixels of the edge: both 0.3 and 0.9 among the hypotheses
        assert end[0, 0, 0, col] <= 0.3 + 1e-6 and start[0, 0, 0, col] >= 0.9 - 1e-6, col
    for col in (0, 1, 2, 9, 10, 11):  # farther away: unchanged
        torch.testing.assert_close(start[..., col], plain[0][..., col])
        torch.testing.assert_close(step[..., col], plain[1][..., col])
    assert torch.all(start <= 1.0 + 1e-6) and torch.all(end >= 0.2 - 1e-6)  # still inside the depth range
    with pytest.raises(ConfigError, match="stage_neighbourhood must be >= 0, got -1"):
        PVSNetConfig(stage_neighbourhood=-1)


# ----------------------------------------------------------------------------- guidance


def test_guidance_weights_and_sparse_downsampling():
    sparse = torch.zeros(1, 1, 8, 8)
    sparse[0, 0, 1, 2] = 3.0
    sparse[0, 0, 2, 3] = 2.0  # nearer hint in the same 4x4 block wins
    small = downsample_sparse_depth(sparse, 4)
    assert small.shape == (1, 1, 2, 2)
    torch.testing.assert_close(small[0, 0], torch.tensor([[2.0, 0.0], [0.0, 0.0]]))
    inv_start, inv_step = plane_range(torch.tensor([1.0]), torch.tensor([5.0]), 8)
    hint_depth = 1.0 / (inv_start.view(()) - 5 * inv_step.view(()))
    small[0, 0, 0, 0] = hint_depth
    gw = guidance_weights(small, inv_start, inv_step, 8, k=10.0, c=1.0)
    assert gw.shape == (1, 8, 2, 2)
    assert int(gw[0, :, 0, 0].argmax()) == 5
    torch.testing.assert_close(gw[0, 5, 0, 0], torch.tensor(10.0))
    torch.testing.assert_close(gw[0, :, 1, 1], torch.ones(8))  # no hint: factor 1
    # A hint far outside the hypothesis range is ignored (factor 1), not allowed to zero the volume.
    small[0, 0, 1, 0] = 0.3  # nearer than depth_min = 1
    torch.testing.assert_close(
        guidance_weights(small, inv_start, inv_step, 8, k=10.0, c=1.0)[0, :, 1, 0], torch.ones(8)
    )


def test_densify_inverse_depth_keeps_hints_and_fills_between():
    hint = torch.zeros(2, 1, 9, 13)
    hint[0, 0, 1, 1] = 2.0
    hint[0, 0, 7, 11] = 4.0
    dense = densify_inverse_depth(hint)
    assert dense.shape == hint.shape and torch.isfinite(dense).all()
    # Hint pixels keep their exact inverse depth; everything else lies between the two hints.
    torch.testing.assert_close(dense[0, 0, 1, 1], torch.tensor(0.5))
    torch.testing.assert_close(dense[0, 0, 7, 11], torch.tensor(0.25))
    assert torch.all((dense[0] >= 0.25 - 1e-6) & (dense[0] <= 0.5 + 1e-6))
    # Nearer the first hint means nearer its value.
    assert dense[0, 0, 2, 2] > dense[0, 0, 6, 10]
    # An image without hints gets no prior.
    assert torch.all(dense[1] == 0)
    # One hint: a constant prior over the whole image.
    one = torch.zeros(1, 1, 6, 6)
    one[0, 0, 4, 2] = 5.0
    torch.testing.assert_close(densify_inverse_depth(one), torch.full((1, 1, 6, 6), 0.2))


def _slanted_plane_inverse_depth(h: int, w: int) -> torch.Tensor:
    """``[h, w]`` inverse depth of a slanted plane: affine in the image, 0.004 per column, 0.002 per row."""
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32),
                            indexing="ij")
    return 0.3 + 0.004 * xs + 0.002 * ys


def test_affine_fill_is_exact_on_a_plane_where_push_pull_is_not():
    # A slanted plane: inverse depth affine in the image; hints at scattered pixels of it.
    h, w = 40, 56
    inv = _slanted_plane_inverse_depth(h, w)
    gen = torch.Generator().manual_seed(0)
    picks = torch.randperm(h * w, generator=gen)[:60]
    hint = torch.zeros(1, 1, h, w)
    hint.view(-1)[picks] = 1.0 / inv.view(-1)[picks]
    affine = affine_fill_inverse_depth(hint)
    assert affine.shape == hint.shape and torch.isfinite(affine).all()
    affine_err = ((affine[0, 0] - inv).abs() / inv).max()
    push_pull_err = ((densify_inverse_depth(hint)[0, 0] - inv).abs() / inv).max()
    assert affine_err < 0.01 < push_pull_err  # push-pull averages hints: off by the slope


def test_affine_fill_degenerate_inputs():
    # No hints: no prior (zeros), per image of the batch.
    hint = torch.zeros(2, 1, 12, 16)
    hint[1, 0, 5, 7] = 4.0  # one hint: a constant fill (the slopes are damped, not undetermined)
    out = affine_fill_inverse_depth(hint)
    assert torch.all(out[0] == 0)
    torch.testing.assert_close(out[1], torch.full((1, 12, 16), 0.25), rtol=1e-4, atol=1e-6)
    # Two hints: the steepest slope there is, yet the fit stays within the hints' range widened by a
    # quarter of it on each side.
    two = torch.zeros(1, 1, 30, 30)
    two[0, 0, 14, 14], two[0, 0, 15, 15] = 1.0, 2.0  # inverse depths 1 and 0.5
    out = affine_fill_inverse_depth(two)
    assert torch.isfinite(out).all() and torch.all(out >= 0.375 - 1e-6) and torch.all(out <= 1.125 + 1e-6)
    assert out[0, 0, 14, 14] > out[0, 0, 15, 15] and out[0, 0, 0, 0] >= out[0, 0, -1, -1]  # along the slope
    with pytest.raises(ShapeError):
        affine_fill_inverse_depth(torch.zeros(1, 2, 4, 4))


def test_affine_fill_has_no_steps_where_the_scale_changes():
    # Hints on a slanted plane in two clusters (as SfM points gather on textured objects); between
    # and around them the fill changes scale. A hard scale switch drew steps (rings) into the prior:
    # 0.033 here, against 0.019 with the blended hand-over (the rest is the clipping of the fill).
    h, w = 48, 64
    inv = _slanted_plane_inverse_depth(h, w)
    gen = torch.Generator().manual_seed(1)
    hint = torch.zeros(1, 1, h, w)
    for cy, cx in ((14, 16), (34, 46)):
        for _ in range(25):
            y = int(cy + torch.randint(-4, 5, (1,), generator=gen))
            x = int(cx + torch.randint(-4, 5, (1,), generator=gen))
            hint[0, 0, y, x] = 1.0 / inv[y, x]
    out = affine_fill_inverse_depth(hint)[0, 0]
    steps = torch.cat([(out[:, 1:] - out[:, :-1]).abs().flatten(), (out[1:] - out[:-1]).abs().flatten()])
    # The plane changes by at most 0.004 per pixel; where the fill hands over between scales and
    # clips its extrapolation it changes faster, but not by a step.
    assert steps.max() < 0.025, steps.max()


def test_prior_plane_range_windows_and_fallback():
    prior = torch.tensor([[[[0.5, 0.0], [0.9, 0.21]]]])  # inverse depths; 0 = no prior
    inv_lo, inv_hi = torch.tensor([0.2]), torch.tensor([1.0])  # depth range [1, 5]
    start, step = prior_plane_range(prior, 0.2, 9, inv_lo=inv_lo, inv_hi=inv_hi)
    assert start.shape == step.shape == (1, 1, 2, 2)
    end = start - 8 * step
    # Inside the range: +-20 % of the prior.
    torch.testing.assert_close(start[0, 0, 0, 0], torch.tensor(0.6))
    torch.testing.assert_close(end[0, 0, 0, 0], torch.tensor(0.4))
    # No prior: the global range.
    torch.testing.assert_close(start[0, 0, 0, 1], torch.tensor(1.0))
    torch.testing.assert_close(end[0, 0, 0, 1], torch.tensor(0.2))
    # Near the range's ends the window keeps its width and is moved inside.
    torch.testing.assert_close(start[0, 0, 1, 0], torch.tensor(1.0))
    torch.testing.assert_close(end[0, 0, 1, 0], torch.tensor(1.0 - 0.36))
    torch.testing.assert_close(end[0, 0, 1, 1], torch.tensor(0.2))
    assert torch.all(start <= 1.0 + 1e-6) and torch.all(end >= 0.2 - 1e-6) and torch.all(step > 0)


def test_config_validation():
    with pytest.raises(ConfigError, match="planes_per_stage"):
        PVSNetConfig(planes_per_stage=(48, 16))
    with pytest.raises(ConfigError, match="multiples"):
        PVSNetConfig(planes_per_stage=(48, 18, 8))
    with pytest.raises(ConfigError, match="loss_weights"):
        PVSNetConfig(loss_weights=(1.0, 1.0))
    with pytest.raises(ConfigError, match="prior_halfwidth"):
        PVSNetConfig(prior_halfwidth=1.0)
    with pytest.raises(ConfigError, match="groups_per_stage"):
        PVSNetConfig(groups_per_stage=(8, 8, 3))
    cfg = PVSNetConfig(
        num_stages=1,
        planes_per_stage=(32,),
        groups_per_stage=(8,),
        stage_channels=(),
        loss_weights=(0.5, 0.5, 1.0),
    )
    assert cfg.output_scales == (4, 4, 4)
    assert PVSNetConfig().output_scales == (4, 4, 4, 2, 1)


def test_prior_halfwidth_grows_away_from_hints():
    hint = torch.zeros(1, 1, 80, 80)
    hint[0, 0, 5, 5] = 2.0
    r = prior_halfwidth_map(hint, 0.3, 2.0, (8, 16))
    assert r.shape == hint.shape
    torch.testing.assert_close(r[0, 0, 5, 5], torch.tensor(0.3))  # every pixel within 8 of it is near
    torch.testing.assert_close(r[0, 0, 60, 60], torch.tensor(1.2))  # beyond both radii, all around
    torch.testing.assert_close(r[0, 0, 5, 30], torch.tensor(1.2))  # 25 away: beyond both radii
    assert 0.3 < float(r[0, 0, 5, 17]) < 1.2  # 12 away: between, on a ramp
    diagonal = r[0, 0, torch.arange(80), torch.arange(80)]
    assert torch.all(diagonal[1:] >= diagonal[:-1] - 1e-6)  # widens with the distance, without steps
    assert torch.all(diagonal[1:] / diagonal[:-1] < 1.2)
    torch.testing.assert_close(prior_halfwidth_map(hint, 0.3, 1.0, (8, 16)), torch.full_like(hint, 0.3))
    # a per-pixel half-width widens only those pixels' windows (clipped to the global range)
    prior = torch.full((1, 1, 1, 2), 0.5)
    inv_lo, inv_hi = torch.tensor([0.2]), torch.tensor([1.0])
    start, step = prior_plane_range(prior, torch.tensor([[[[0.2, 1.2]]]]), 9, inv_lo=inv_lo, inv_hi=inv_hi)
    torch.testing.assert_close(start[0, 0, 0], torch.tensor([0.6, 1.0]))
    torch.testing.assert_close((start - 8 * step)[0, 0, 0], torch.tensor([0.4, 0.2]))
