"""The pixel classes of ``benchmarks/blind_spots.py`` (issue 56), on synthetic arrays."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
if str(BENCHMARKS) not in sys.path:
    sys.path.insert(0, str(BENCHMARKS))

import blind_spots as bs  # noqa: E402  (benchmarks/ is no package: on sys.path above)

W, H, F = 80, 60, 600.0  # a narrow view: a grazing plane changes depth by < 5 % a pixel
K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])


def _plane(tilt_deg: float, distance: float = 3.0) -> np.ndarray:
    """``[H, W]`` depth of a plane whose normal is ``tilt_deg`` away from the optical axis (about x)."""
    t = np.radians(tilt_deg)
    n = np.array([0.0, np.sin(t), -np.cos(t)])
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    rays = np.stack([(u - K[0, 2]) / F, (v - K[1, 2]) / F, np.ones((H, W))], axis=-1)
    return (-distance / (rays @ n)).astype(np.float32)


def test_outside_range_is_below_the_near_or_beyond_the_far_end_of_valid_gt():
    gt = np.array([[0.0, 0.5, 1.0, 2.0, 3.0, 4.5]])
    np.testing.assert_array_equal(bs.outside_range_mask(gt, (1.0, 3.0)), [[0, 1, 0, 0, 0, 1]])


def test_slanted_is_a_plane_seen_at_a_grazing_angle_not_one_facing_the_camera():
    assert bs.slanted_mask(_plane(0.0), K).sum() == 0
    assert bs.slanted_mask(_plane(45.0), K)[H // 2 - 5 : H // 2 + 5, W // 2 - 5 : W // 2 + 5].sum() == 0
    steep = bs.slanted_mask(_plane(72.0), K)
    assert steep[H // 2 - 5 : H // 2 + 5, W // 2 - 5 : W // 2 + 5].all()
    assert not bs.slanted_mask(np.zeros((H, W), np.float32), K).any()  # no GT, no normal


def test_low_texture_is_the_flat_half_of_the_image_only():
    rng = np.random.default_rng(0)
    grey = np.full((H, W), 0.8)
    grey[:, W // 2 :] = rng.uniform(0, 1, (H, W - W // 2))
    gt = np.full((H, W), 2.0)
    gt[:5, :5] = 0  # no GT: in no class
    low = bs.low_texture_mask(grey, gt)
    assert low[5:, : W // 2 - 4].all() and not low[:, W // 2 + 4 :].any()
    assert not low[:5, :5].any()
    grey[:, : W // 2] += rng.normal(0, 0.02, (H, W // 2))  # a textured wall is no low-texture pixel
    assert not bs.low_texture_mask(grey, gt)[:, : W // 2 - 4].any()


def test_thin_is_a_narrow_near_bar_not_a_wide_block_a_shallow_step_or_a_hole_edge():
    gt = np.full((H, W), 4.0, np.float32)
    gt[10:50, 20:23] = 1.0  # a pole 3 px wide, far in front of the wall
    gt[10:50, 40:70] = 1.0  # a block 30 px wide
    thin = bs.thin_mask(gt)
    assert thin[10:50, 20:23].all()
    assert not thin[:, 30:].any() and not thin[:, :19].any()
    shallow = np.full((H, W), 4.0, np.float32)
    shallow[10:50, 20:23] = 3.5  # only 12 % nearer than the wall: no foreground
    assert not bs.thin_mask(shallow).any()
    strip = np.zeros((H, W), np.float32)
    strip[:, 20:23] = 2.0  # a valid strip between invalid GT: no depth edge
    assert not bs.thin_mask(strip).any()


def test_class_masks_are_within_the_valid_gt_and_counts_score_a_missing_depth_as_wrong():
    gt = _plane(72.0)
    gt[:, :10] = 0
    masks = bs.class_masks(gt, np.full((H, W), 0.5), K, (2.0, 6.0))
    assert set(masks) == set(bs.CLASSES)
    for mask in masks.values():
        assert not mask[:, :10].any()
    assert (masks["outside range"] | masks["inside range"]).sum() == masks["all"].sum()
    pred = gt * 1.02
    pred[:, 10:20] = 0  # no depth
    pred[:, 20:30] *= 1.1  # 12 % off
    n, has, within = bs.counts(pred, gt, masks["all"])
    assert (n, has, within) == (H * (W - 10), H * (W - 20), H * (W - 30))


def test_frames_keeps_only_the_named_ones_of_the_stride_and_offset():
    import argparse

    import real_depth as rd

    names = [f"{i:05d}.png" for i in range(10)]
    args = argparse.Namespace(stride=3, offset=1, frames=[])
    assert rd.frame_names(names, args) == ["00001.png", "00004.png", "00007.png"]
    args.frames = ["00004.png", "00005.png"]  # 00005 is not one of the stride's frames
    assert rd.frame_names(names, args) == ["00004.png"]


def test_synthetic_val_scores_the_classes_of_a_sample_with_its_own_depth_range():
    import synthetic_val as sv
    import torch

    gt = _plane(72.0)
    gt[:, :10] = 0
    rgb = np.full((3, H, W), 0.5, np.float32)  # flat grey: every valid pixel is low texture
    lo, hi = float(gt[gt > 0].min()), float(np.percentile(gt[gt > 0], 90))
    sample = {"depth": torch.from_numpy(gt), "images": torch.from_numpy(rgb)[None],
              "intrinsics": torch.from_numpy(K)[None],
              "depth_min": torch.tensor(lo), "depth_max": torch.tensor(hi)}
    pred = gt * 1.02
    pred[:, 10:20] *= 1.1  # 12 % off
    got = sv.class_counts(pred, sample)
    valid = int((gt > 0).sum())
    assert got["all"] == (valid - H * 10, valid)
    assert got["low texture"] == got["all"]
    outside = (gt > hi).sum()
    assert 0 < outside < valid and got["outside range"][1] == outside
    assert got["outside range"][1] + got["inside range"][1] == valid
