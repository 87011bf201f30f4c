"""The training config (:class:`TrainConfig`).

Learning-rate schedules (``lr_schedule``), all a pure function of the step ``s`` (number
of optimizer steps already taken), multiplied by an optional linear warm-up
``min(1, (s + 1) / lr_warmup_steps)``:

- ``"constant"``: ``lr``;
- ``"step"`` (default, MVSNet/PVSNet style): ``lr * lr_decay_gamma ** floor(s / lr_decay_every)``;
- ``"cosine"``: ``lr * (f + (1 - f) * (1 + cos(pi * min(s, T) / T)) / 2)`` with
  ``f = lr_min_factor`` and ``T = lr_cosine_steps`` (``0`` = ``steps``). Note that with
  ``T = steps``, changing ``steps`` when resuming changes the schedule of the remaining
  steps; set ``lr_cosine_steps`` explicitly to extend a run without that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from ..config import check_threads
from ..errors import ConfigError
from ..model import PVSNetConfig
from ..synthetic import SyntheticDatasetConfig
from .mvsnet_dataset import MVSNetDatasetConfig
from .real_dataset import RealDatasetConfig
from .selfsup import SelfSupConfig

#: Fields that may differ between a run and the checkpoint it resumes from (they do not
#: change the optimisation trajectory).
RESUMABLE_CHANGES = frozenset(
    {
        "output_dir",
        "steps",
        "num_workers",
        "torch_threads",
        "checkpoint_every_seconds",
        "checkpoint_every_steps",
        "log_every",
        "val_every",
        "progress",
        "resume",
        "device",
    }
)


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run. Saved as ``output_dir/config.json`` and in checkpoints."""

    output_dir: Path = field(
        default=Path("runs/pvsnet"),
        metadata={"help": "run folder: last.pt, best.pt, model.pt, log.csv, val.csv, loss.png, config.json"},
    )
    dataset: Literal["synthetic", "mvsnet"] = field(
        default="synthetic",
        metadata={
            "help": "training data: procedural synthetic scenes, or an MVSNet-format folder (DTU/BlendedMVS)"
        },
    )
    model: PVSNetConfig = field(default_factory=PVSNetConfig, metadata={"help": "network architecture"})
    data: SyntheticDatasetConfig = field(
        default_factory=SyntheticDatasetConfig, metadata={"help": "synthetic dataset (dataset=synthetic)"}
    )
    mvsnet: MVSNetDatasetConfig = field(
        default_factory=MVSNetDatasetConfig, metadata={"help": "MVSNet-format dataset (dataset=mvsnet)"}
    )
    real: RealDatasetConfig = field(
        default_factory=RealDatasetConfig,
        metadata={"help": "real scenes without GT for self-supervised samples (used when real_fraction > 0)"},
    )
    real_fraction: float = field(
        default=0.0,
        metadata={
            "help": "fraction of training samples drawn from the real scenes (self-supervised); "
            "0 = none, 1 = real only (no synthetic/MVSNet training samples)"
        },
    )
    selfsup: SelfSupConfig = field(
        default_factory=SelfSupConfig, metadata={"help": "self-supervised loss of the real samples"}
    )
    steps: int = field(
        default=20000, metadata={"help": "total optimizer steps of the run (resuming continues)"}
    )
    batch_size: int = field(default=1, metadata={"help": "samples per optimizer step"})
    optimizer: Literal["rmsprop", "adam"] = field(
        default="rmsprop", metadata={"help": "optimizer: rmsprop (the paper's) or adam"}
    )
    lr: float = field(default=1e-3, metadata={"help": "initial learning rate (paper: 1e-3)"})
    rmsprop_alpha: float = field(
        default=0.9, metadata={"help": "RMSprop smoothing constant (TensorFlow/MVSNet decay 0.9)"}
    )
    weight_decay: float = field(default=0.0, metadata={"help": "L2 weight decay"})
    lr_schedule: Literal["constant", "step", "cosine"] = field(
        default="step", metadata={"help": "learning-rate schedule (see the module docstring)"}
    )
    lr_decay_every: int = field(default=2000, metadata={"help": "step schedule: decay every this many steps"})
    lr_decay_gamma: float = field(default=0.9, metadata={"help": "step schedule: multiplicative decay"})
    lr_cosine_steps: int = field(default=0, metadata={"help": "cosine schedule length (0 = steps)"})
    lr_min_factor: float = field(default=0.01, metadata={"help": "cosine schedule: final lr / lr"})
    lr_warmup_steps: int = field(default=0, metadata={"help": "linear warm-up steps (0 = none)"})
    grad_clip_norm: float = field(default=0.0, metadata={"help": "clip the gradient norm to this (0 = off)"})
    loss_normalize: Literal["range", "none"] = field(
        default="range",
        metadata={"help": "range: L1 / (depth_max - depth_min), scale-free; none: raw L1 (paper)"},
    )
    gt_downsample: Literal["min", "nearest"] = field(
        default="min",
        metadata={"help": "GT depth to coarse outputs: min of valid pixels per block, or nearest"},
    )
    mask_depth_range: bool = field(
        default=True, metadata={"help": "ignore GT depths outside [depth_min, depth_max] in the loss"}
    )
    use_sparse_depth: bool = field(
        default=True,
        metadata={
            "help": "pass the samples' sparse_depth to the model (used by model.sparse_guidance and "
            "model.sparse_prior)"
        },
    )
    init_weights: Path | None = field(
        default=None,
        metadata={
            "help": "start a fresh run from this checkpoint's weights (parameters whose name and shape "
            "match; the others keep their initialisation); ignored when resuming"
        },
    )
    seed: int = field(default=0, metadata={"help": "seed of weights init, sample order and all RNGs"})
    sample_grouping: int = field(
        default=1,
        metadata={
            "help": "sample order: shuffled blocks of this many consecutive indices (synthetic: "
            "data.samples_per_scene reuses each rendered scene); 1 = fully random"
        },
    )
    device: Literal["cpu", "cuda", "auto"] = field(
        default="cpu",
        metadata={
            "help": "torch device of the model and batches: cpu, cuda, or auto (cuda when "
            "torch.cuda.is_available(), else cpu)"
        },
    )
    num_workers: int = field(default=0, metadata={"help": "DataLoader worker processes (0 = main process)"})
    torch_threads: int = field(
        default=2,
        metadata={
            "help": "torch intra-op threads while training (0 = torch's default). On cores shared with "
            "other jobs set OMP_WAIT_POLICY=PASSIVE in the environment, or use 1: spinning OpenMP threads "
            "waiting on a descheduled peer made steps 10x slower there"
        },
    )
    checkpoint_every_seconds: float = field(
        default=300.0, metadata={"help": "write last.pt at least this often (seconds; 0 = off)"}
    )
    checkpoint_every_steps: int = field(
        default=0, metadata={"help": "also write last.pt every N steps (0 = off)"}
    )
    log_every: int = field(
        default=10, metadata={"help": "write a log.csv row every N steps (mean over them)"}
    )
    val_every: int = field(default=500, metadata={"help": "validate every N steps and at the end (0 = off)"})
    val_samples: int = field(default=16, metadata={"help": "validation samples (first N of the val set)"})
    val_seed_offset: int = field(
        default=1_000_000, metadata={"help": "synthetic validation scenes use data.seed + this offset"}
    )
    resume: bool = field(default=True, metadata={"help": "resume from output_dir/last.pt when it exists"})
    progress: bool = field(default=True, metadata={"help": "show a tqdm progress bar"})

    def __post_init__(self) -> None:
        def need(cond: bool, msg: str) -> None:
            if not cond:
                raise ConfigError(f"TrainConfig: {msg}")

        need(self.steps >= 0, f"steps must be >= 0, got {self.steps}")
        need(self.batch_size >= 1, f"batch_size must be >= 1, got {self.batch_size}")
        need(self.lr > 0 and math.isfinite(self.lr), f"lr must be a positive number, got {self.lr}")
        need(0.0 < self.rmsprop_alpha < 1.0, f"rmsprop_alpha must be in (0, 1), got {self.rmsprop_alpha}")
        need(self.weight_decay >= 0, f"weight_decay must be >= 0, got {self.weight_decay}")
        need(self.lr_decay_every >= 1, f"lr_decay_every must be >= 1, got {self.lr_decay_every}")
        need(0.0 < self.lr_decay_gamma <= 1.0, f"lr_decay_gamma must be in (0, 1], got {self.lr_decay_gamma}")
        need(self.lr_cosine_steps >= 0, f"lr_cosine_steps must be >= 0, got {self.lr_cosine_steps}")
        need(0.0 <= self.lr_min_factor <= 1.0, f"lr_min_factor must be in [0, 1], got {self.lr_min_factor}")
        need(self.lr_warmup_steps >= 0, f"lr_warmup_steps must be >= 0, got {self.lr_warmup_steps}")
        need(self.grad_clip_norm >= 0, f"grad_clip_norm must be >= 0, got {self.grad_clip_norm}")
        need(self.sample_grouping >= 1, f"sample_grouping must be >= 1, got {self.sample_grouping}")
        need(self.num_workers >= 0, f"num_workers must be >= 0, got {self.num_workers}")
        check_threads("torch_threads", self.torch_threads, auto=0)
        need(
            self.checkpoint_every_seconds >= 0,
            f"checkpoint_every_seconds must be >= 0, got {self.checkpoint_every_seconds}",
        )
        need(
            self.checkpoint_every_steps >= 0,
            f"checkpoint_every_steps must be >= 0, got {self.checkpoint_every_steps}",
        )
        need(self.log_every >= 1, f"log_every must be >= 1, got {self.log_every}")
        need(self.val_every >= 0, f"val_every must be >= 0, got {self.val_every}")
        need(self.val_samples >= 1, f"val_samples must be >= 1, got {self.val_samples}")
        need(0.0 <= self.real_fraction <= 1.0, f"real_fraction must be in [0, 1], got {self.real_fraction}")
        need(
            self.real_fraction == 0.0 or len(self.real.roots) > 0,
            "real_fraction > 0 needs real.roots (folders with images/ and a COLMAP model)",
        )
        need(
            self.real_fraction in (0.0, 1.0) or self.batch_size == 1,
            f"mixing real and synthetic samples (real_fraction={self.real_fraction}) needs batch_size 1, "
            f"got {self.batch_size}",
        )
        need(
            self.dataset != "mvsnet" or self.mvsnet.root is not None,
            "dataset=mvsnet needs mvsnet.root (the MVSNet-format dataset folder)",
        )

    def lr_factor(self, step: int) -> float:
        """Learning-rate multiplier for the optimizer step taken after ``step`` completed steps."""
        if self.lr_schedule == "constant":
            f = 1.0
        elif self.lr_schedule == "step":
            f = self.lr_decay_gamma ** (step // self.lr_decay_every)
        else:
            total = self.lr_cosine_steps or self.steps
            t = min(step, total) / max(total, 1)
            f = self.lr_min_factor + (1.0 - self.lr_min_factor) * 0.5 * (1.0 + math.cos(math.pi * t))
        if self.lr_warmup_steps:
            f *= min(1.0, (step + 1) / self.lr_warmup_steps)
        return f
