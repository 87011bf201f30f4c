"""Tiny PVSNet configs shared by the tests (plumbing and gradients, not accuracy).

Each states every switch it relies on (``PVSNetConfig()`` is the shipped model): no sparse guidance or
prior and no frustum weights unless a test turns them on.
"""

from __future__ import annotations

from colmap_pvs.model import PVSNetConfig

#: The switches the tiny models leave off.
TINY_SWITCHES = dict(sparse_guidance=False, sparse_prior=False, frustum_weights=False, stage_neighbourhood=0)

#: Three stages (coarse + two cascade stages), a few channels each.
TINY_PVSNET = PVSNetConfig(
    feature_channels=(8, 8, 8),
    planes_per_stage=(8, 8, 4),
    groups_per_stage=(4, 4, 4),
    visibility_channels=4,
    regularization_channels=4,
    stage_channels=(4, 4),
    **TINY_SWITCHES,
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
    **TINY_SWITCHES,
)
