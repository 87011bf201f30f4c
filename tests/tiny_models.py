"""Tiny PVSNet configs shared by the tests (plumbing and gradients, not accuracy)."""

from __future__ import annotations

from colmap_pvs.model import PVSNetConfig

#: Three stages (coarse + two cascade stages), a few channels each.
TINY_PVSNET = PVSNetConfig(
    feature_channels=(8, 8, 8),
    planes_per_stage=(8, 8, 4),
    groups_per_stage=(4, 4, 4),
    visibility_channels=4,
    regularization_channels=4,
    stage_channels=(4, 4),
)

#: The coarse stage only: the cheapest checkpoint for end-to-end stereo / CLI tests.
TINY_COARSE_KWARGS = dict(
    feature_channels=(8, 8, 8),
    num_stages=1,
    planes_per_stage=(8,),
    groups_per_stage=(4,),
    stage_channels=(),
    visibility_channels=4,
    regularization_channels=4,
    loss_weights=(0.5, 0.5, 0.7),
)
