"""Training loss and metrics: GT downsampling, masking, weighting, metric values."""

from __future__ import annotations

import pytest
import torch

from colmap_pvs.errors import ShapeError
from colmap_pvs.train.losses import depth_loss, depth_metrics, downsample_depth, output_metrics, valid_mask


def test_min_pooling_ignores_invalid_and_keeps_empty_blocks_invalid() -> None:
    gt = torch.tensor(
        [
            [
                [0.0, 5.0, 0.0, 0.0],
                [3.0, 4.0, 0.0, 0.0],
                [2.0, 2.0, 9.0, 1.0],
                [2.0, 2.0, float("nan"), 8.0],
            ]
        ]
    )
    out = downsample_depth(gt, (2, 2), "min")
    assert out.tolist() == [[[3.0, 0.0], [2.0, 1.0]]]
    near = downsample_depth(gt, (2, 2), "nearest")  # pixel just below-right of each block centre
    assert near.tolist() == [[[4.0, 0.0], [2.0, 8.0]]]
    assert downsample_depth(gt, (4, 4)) is gt
    # non-integer factor falls back to nearest
    assert downsample_depth(torch.ones(1, 6, 6), (4, 4)).shape == (1, 4, 4)
    with pytest.raises(ShapeError):
        downsample_depth(gt[0], (2, 2))


def test_loss_is_weighted_masked_l1_per_output() -> None:
    gt = torch.full((2, 8, 8), 4.0)
    gt[0, :4] = 0.0  # invalid top half in sample 0
    gt[1, 0, 0] = 20.0  # outside [depth_min, depth_max]: masked
    dmin, dmax = torch.tensor([1.0, 1.0]), torch.tensor([9.0, 11.0])
    full = torch.full((2, 8, 8), 5.0, requires_grad=True)  # error 1 everywhere
    coarse = torch.full((2, 2, 2), 6.0, requires_grad=True)  # error 2 where valid
    loss = depth_loss([coarse, full], gt, dmin, dmax, (0.5, 0.7), normalize="none")
    # full res: valid = 32 (sample 0) + 63 (sample 1), error 1
    assert loss.per_output.tolist() == pytest.approx([2.0, 1.0])
    assert float(loss.total.detach()) == pytest.approx(0.5 * 2.0 + 0.7 * 1.0)
    assert loss.valid_fraction.tolist() == pytest.approx([6 / 8, 95 / 128])
    loss.total.backward()
    assert full.grad[0, 0, 0] == 0 and full.grad[1, 0, 0] == 0 and full.grad[1, 5, 5] > 0
    # range normalisation divides each sample by its depth range
    norm = depth_loss([full], gt, dmin, dmax, (1.0,), normalize="range")
    expected = (32 * 1 / 8 + 63 * 1 / 10) / 95
    assert float(norm.total.detach()) == pytest.approx(expected)
    # without range masking the out-of-range pixel counts (error 15)
    nomask = depth_loss([full.detach()], gt, dmin, dmax, (1.0,), normalize="none", mask_depth_range=False)
    assert float(nomask.total) == pytest.approx((95 + 15) / 96)


def test_loss_without_valid_pixels_is_zero_with_graph_and_checks_weights() -> None:
    gt = torch.zeros(1, 4, 4)
    pred = torch.ones(1, 4, 4, requires_grad=True)
    loss = depth_loss([pred], gt, torch.tensor([1.0]), torch.tensor([2.0]), (1.0,))
    assert float(loss.total.detach()) == 0.0
    loss.total.backward()
    assert float(pred.grad.abs().sum()) == 0.0
    with pytest.raises(ValueError, match="2 loss weights"):
        depth_loss([pred], gt, torch.tensor([1.0]), torch.tensor([2.0]), (1.0, 1.0))


def test_metrics() -> None:
    gt = torch.tensor([[[100.0, 100.0, 100.0, 0.0]]])
    pred = torch.tensor([[[100.5, 101.5, 110.0, 7.0]]])
    m = depth_metrics(pred, gt)
    assert m["valid"] == 3
    assert m["mae"] == pytest.approx(4.0)
    assert m["absrel"] == pytest.approx(0.04)
    assert m["pct_rel_1"] == pytest.approx(100 / 3)
    assert m["pct_rel_2"] == pytest.approx(200 / 3)
    assert m["pct_rel_5"] == pytest.approx(200 / 3)
    all_m = output_metrics([pred, pred[:, :, :2]], gt)  # out1: GT min-pooled to width 2
    assert all_m["out0_valid"] == 3 and all_m["out0_mae"] == pytest.approx(4.0)
    assert all_m["out1_valid"] == 2 and all_m["out1_mae"] == pytest.approx(1.0)
    assert valid_mask(gt, torch.tensor([100.0]), torch.tensor([100.0])).sum() == 3
    empty = depth_metrics(pred, torch.zeros_like(gt))
    assert empty["valid"] == 0 and empty["mae"] != empty["mae"]


def test_padded_sizes_match_the_network() -> None:
    gt = torch.arange(1.0, 31.0).reshape(1, 6, 5)  # outputs of a stride-4 net: ceil(6/4) x ceil(5/4)
    out = downsample_depth(gt, (2, 2), "min", factor=4)
    assert out.tolist() == [[[1.0, 5.0], [21.0, 25.0]]]  # padded zeros are invalid, not minima
    near = downsample_depth(gt, (2, 2), "nearest", factor=4)
    assert near.tolist() == [[[13.0, 0.0], [0.0, 0.0]]]  # centre pixels (2, 2), (2, 6), ... padded = invalid
    gt16 = torch.arange(1.0, 16 * 12 + 1).reshape(1, 12, 16)
    # nearest: the pixel just below-right of each 4x4 block centre
    assert torch.equal(downsample_depth(gt16, (3, 4), "nearest"), gt16[:, 2::4, 2::4])
    with pytest.raises(ShapeError, match="not ceil"):
        downsample_depth(gt, (2, 2), factor=2)
