"""Training PVSNet on the CPU: config, losses, MVSNet-format data and the resumable trainer.

Entry point: :func:`train` (``Trainer(config).train()``), used by the CLI::

    from colmap_pvs.train import TrainConfig, train

    last = train(TrainConfig(output_dir=Path("runs/pvsnet"), steps=20000))
    # runs/pvsnet/model.pt: the weights to ship; rerunning the same call resumes from last.pt

- :mod:`.config`: :class:`TrainConfig` (optimizer, schedules, checkpoint/log/validation cadence);
- :mod:`.losses`: the multi-output masked L1 loss (paper eq. 6-7) and depth metrics;
- :mod:`.mvsnet_dataset`: DTU-training / BlendedMVS folders as the same sample dicts as
  :class:`colmap_pvs.synthetic.SyntheticMVSDataset`;
- :mod:`.trainer`: :class:`Trainer` (seeded, resumable, SIGINT/SIGTERM-safe).
- :mod:`.data`: the datasets a config selects and :class:`StepSampler`; :mod:`.rng`: the RNG states
  a checkpoint keeps; :mod:`.logs`: ``log.csv``, ``val.csv`` and the loss curves.
"""

from __future__ import annotations

from .config import RESUMABLE_CHANGES, TrainConfig
from .losses import DepthLoss, depth_loss, depth_metrics, downsample_depth, output_metrics, valid_mask
from .mvsnet_dataset import MVSNetDataset, MVSNetDatasetConfig, MVSNetFormatError, read_pfm, write_pfm
from .trainer import (
    StepSampler,
    Trainer,
    TrainingDivergedError,
    TrainingInterrupted,
    build_datasets,
    plot_curves,
    train,
)

__all__ = [
    "RESUMABLE_CHANGES",
    "DepthLoss",
    "MVSNetDataset",
    "MVSNetDatasetConfig",
    "MVSNetFormatError",
    "StepSampler",
    "TrainConfig",
    "Trainer",
    "TrainingDivergedError",
    "TrainingInterrupted",
    "build_datasets",
    "depth_loss",
    "depth_metrics",
    "downsample_depth",
    "output_metrics",
    "plot_curves",
    "read_pfm",
    "train",
    "valid_mask",
    "write_pfm",
]
