"""Fine-tune a copy of a checkpoint on a workspace's own images (:func:`adapt_checkpoint`).

The copy is trained for ``steps`` steps (or ``max_seconds``, whichever ends first) on samples of the
workspace itself, with the self-supervised losses of :mod:`colmap_pvs.train.selfsup` (multi-view
photometric consistency, the reference's SfM points as sparse labels disjoint from the hints,
edge-aware smoothness), and with ``pseudo_labels`` also on the workspace's own maps of that kind
(read as in :mod:`colmap_pvs.train.real_dataset`). No ground truth is used. It runs through the
ordinary :class:`~colmap_pvs.train.Trainer` with ``real_fraction=1``, so it is seeded, shows a
progress bar and resumes after an interruption.

Files, all inside ``WORKSPACE/stereo/adapt/``: the run folder of the trainer (``last.pt``,
``log.csv``, ``config.json``), ``adapted.pt`` (the weights inference uses) and
``adapted.json`` (provenance: the base checkpoint's sha256, the settings, what the pseudo-labels
were made with, steps and seconds). A rerun with the same base checkpoint and settings reuses
``adapted.pt``; any other base or setting starts the adaptation again from scratch.
"""

from __future__ import annotations

import json
import logging
import shutil
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from ..config import check_threads, config_to_dict
from ..errors import ConfigError
from ..io.files import atomic_write_bytes, file_sha256

logger = logging.getLogger(__name__)

ADAPT_DIRNAME = "adapt"


@dataclass(frozen=True)
class AdaptConfig:
    """Settings of :func:`adapt_checkpoint` (:func:`~colmap_pvs.adapt.stereo.adapt_config` makes them from
    ``StereoConfig.adapt``)."""

    steps: int = field(default=0, metadata={"help": "optimizer steps (0 = no adaptation)"})
    max_seconds: float = field(default=0.0, metadata={"help": "stop after this many seconds (0 = no limit)"})
    lr: float = field(default=1e-4, metadata={"help": "learning rate (Adam)"})
    seed: int = field(default=0, metadata={"help": "seed of sampling and crops"})
    width: int = field(default=256, metadata={"help": "crop width of the adaptation samples"})
    height: int = field(default=192, metadata={"help": "crop height of the adaptation samples"})
    max_image_size: int = field(default=352, metadata={"help": "images are downscaled to this first"})
    num_views: int = field(default=5, metadata={"help": "views per sample (reference + best sources)"})
    threads: int = field(default=0, metadata={"help": "torch threads (0 = torch's default)"})
    pseudo_labels: str = field(
        default="none",
        metadata={
            "help": "also fit the workspace's own maps of this kind ('geometric' or 'filled', made by "
            "the base checkpoint) as dense pseudo-labels; 'none': self-supervised losses only"
        },
    )

    def __post_init__(self) -> None:
        from ..train.real_dataset import STEREO_PSEUDO_LABEL_KINDS

        check_threads("threads", self.threads, auto=0)
        if self.pseudo_labels not in STEREO_PSEUDO_LABEL_KINDS:
            raise ConfigError(
                f"AdaptConfig: pseudo_labels must be one of {STEREO_PSEUDO_LABEL_KINDS}, "
                f"got {self.pseudo_labels!r}"
            )
        if self.steps < 0 or not self.max_seconds >= 0:
            raise ConfigError(
                f"AdaptConfig: steps and max_seconds must be >= 0, got {self.steps}, {self.max_seconds}"
            )
        if not self.lr > 0:
            raise ConfigError(f"AdaptConfig: lr must be > 0, got {self.lr}")
        if self.num_views < 2:
            raise ConfigError(f"AdaptConfig: num_views must be >= 2, got {self.num_views}")


@dataclass
class AdaptResult:
    """What :func:`adapt_checkpoint` did."""

    checkpoint: Path
    steps: int
    seconds: float
    reused: bool


def _fingerprint(base_checkpoint: Path, config: AdaptConfig, labels: Mapping | None) -> dict:
    out = {
        "base_checkpoint_sha256": file_sha256(Path(base_checkpoint)),
        "settings": {k: v for k, v in config_to_dict(config).items() if k != "threads"},
    }
    if config.pseudo_labels != "none":
        out["labels"] = dict(labels or {})
    return out


def _reusable(stereo_dir: Path, fingerprint: dict) -> dict | None:
    """The metadata of ``stereo/adapt/adapted.pt`` if it was made with ``fingerprint``, else ``None``."""
    out = Path(stereo_dir) / ADAPT_DIRNAME
    if not ((out / "adapted.pt").is_file() and (out / "adapted.json").is_file()):
        return None
    try:
        meta = json.loads((out / "adapted.json").read_text())
    except (OSError, ValueError):
        return None
    return meta if meta.get("fingerprint") == fingerprint else None


def adapted_is_current(stereo_dir: Path, base_checkpoint: Path, config: AdaptConfig,
                       labels: Mapping | None = None) -> bool:
    """Whether :func:`adapt_checkpoint` with these arguments would reuse ``stereo/adapt/adapted.pt``."""
    return _reusable(stereo_dir, _fingerprint(base_checkpoint, config, labels)) is not None


def adapt_checkpoint(workspace_root: Path, stereo_dir: Path, base_checkpoint: Path, config: AdaptConfig,
                     progress: bool = True, labels: Mapping | None = None) -> AdaptResult:
    """Fine-tune ``base_checkpoint`` on the workspace's own images; return the adapted checkpoint.

    Args:
        workspace_root: the dense workspace (``images/``, pinhole ``sparse/``).
        stereo_dir: its ``stereo/`` folder (the adaptation writes ``stereo/adapt/``).
        base_checkpoint: the checkpoint to adapt.
        config: :class:`AdaptConfig` with ``steps > 0``. With ``pseudo_labels`` set, the
            workspace's ``stereo/depth_maps/NAME.{pseudo_labels}.bin`` must exist.
        labels: with ``pseudo_labels``, what those maps were made with (e.g. the settings of the
            stereo run that wrote them): part of the fingerprint, so other labels adapt again.
    """
    from ..model import load_checkpoint
    from ..train import TrainConfig, Trainer, TrainingInterrupted
    from ..train.real_dataset import RealDatasetConfig

    if config.steps <= 0:
        raise ConfigError("adapt_checkpoint needs AdaptConfig.steps > 0")
    out = Path(stereo_dir) / ADAPT_DIRNAME
    adapted, meta_path = out / "adapted.pt", out / "adapted.json"
    fingerprint = _fingerprint(base_checkpoint, config, labels)
    meta = _reusable(stereo_dir, fingerprint)
    if meta is not None:
        logger.info("test-time adaptation: reusing %s (%s steps)", adapted, meta.get("steps"))
        return AdaptResult(adapted, int(meta.get("steps", 0)), float(meta.get("seconds", 0.0)), True)
    run = out / "run"
    run_meta = out / "run.json"
    if run.exists():
        try:
            same = json.loads(run_meta.read_text()) == fingerprint
        except (OSError, ValueError):
            same = False
        if not same:
            logger.info("test-time adaptation: settings or base checkpoint changed; starting again")
            shutil.rmtree(run)
    for stale in (adapted, meta_path):
        stale.unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(run_meta, json.dumps(fingerprint, indent=1).encode())
    base_model, _ = load_checkpoint(Path(base_checkpoint), map_location="cpu")
    train_cfg = TrainConfig(
        output_dir=run,
        model=base_model.config,
        real=RealDatasetConfig(
            roots=(Path(workspace_root),),
            width=config.width,
            height=config.height,
            max_image_size=config.max_image_size,
            num_best=config.num_views - 1,
            num_worst=0,
            seed=config.seed,
            min_points=5,
            pseudo_labels=config.pseudo_labels,
        ),
        real_fraction=1.0,
        steps=config.steps,
        optimizer="adam",
        lr=config.lr,
        lr_schedule="constant",
        init_weights=Path(base_checkpoint),
        use_sparse_depth=True,
        grad_clip_norm=5.0,
        seed=config.seed,
        val_every=0,
        torch_threads=config.threads,
        checkpoint_every_seconds=60.0,
        progress=progress,
    )
    trainer = Trainer(train_cfg)
    start, step0 = time.perf_counter(), trainer.step
    timer = None
    if config.max_seconds > 0:  # the trainer checkpoints and stops after the current step
        timer = threading.Timer(config.max_seconds, trainer.request_stop, args=("time limit",))
        timer.daemon = True
        timer.start()
    try:
        trainer.train()
    except TrainingInterrupted as exc:
        if exc.signal_name != "time limit":
            raise
        logger.info("test-time adaptation: time limit of %.0f s reached at step %d",
                    config.max_seconds, trainer.step)
    finally:
        if timer is not None:
            timer.cancel()
    seconds = time.perf_counter() - start
    trainer.export(adapted)
    meta = {"fingerprint": fingerprint, "steps": trainer.step, "seconds": round(seconds, 2),
            "steps_this_run": trainer.step - step0}
    atomic_write_bytes(meta_path, json.dumps(meta, indent=1).encode())
    logger.info("test-time adaptation: %d steps in %.1f s -> %s", trainer.step, seconds, adapted)
    return AdaptResult(adapted, trainer.step, seconds, False)


__all__ = ["ADAPT_DIRNAME", "AdaptConfig", "AdaptResult", "adapt_checkpoint", "adapted_is_current"]
