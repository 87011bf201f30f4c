"""PVSNet model: ``PVSNet``, its config, outputs, checkpoints and the training loss."""

from __future__ import annotations

from .checkpoint import CHECKPOINT_FORMAT, load_checkpoint, save_checkpoint, stored_config
from .config import NETWORK_STRIDE, PARAMETER_FREE_FIELDS, PVSNetConfig
from .pvsnet import PVSNet, PVSNetOutput

__all__ = [
    "CHECKPOINT_FORMAT",
    "NETWORK_STRIDE",
    "PARAMETER_FREE_FIELDS",
    "PVSNet",
    "PVSNetConfig",
    "PVSNetOutput",
    "load_checkpoint",
    "save_checkpoint",
    "stored_config",
]
