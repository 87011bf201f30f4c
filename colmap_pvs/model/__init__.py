"""PVSNet model: ``PVSNet``, its config, outputs, checkpoints and the training loss."""

from __future__ import annotations

from .checkpoint import CHECKPOINT_FORMAT, load_checkpoint, save_checkpoint
from .config import NETWORK_STRIDE, PVSNetConfig
from .loss import downsample_depth, masked_l1, pvsnet_loss
from .pvsnet import PVSNet, PVSNetOutput

__all__ = [
    "CHECKPOINT_FORMAT",
    "NETWORK_STRIDE",
    "PVSNet",
    "PVSNetConfig",
    "PVSNetOutput",
    "downsample_depth",
    "load_checkpoint",
    "masked_l1",
    "pvsnet_loss",
    "save_checkpoint",
]
