"""The PVSNet training loop: seeded, resumable, checkpointed, logged.

Run folder (``TrainConfig.output_dir``):

- ``config.json``: the resolved :class:`TrainConfig` (:func:`colmap_pvs.config.config_json_bytes`);
- ``last.pt``: the full training state, written atomically every
  ``checkpoint_every_seconds`` / ``checkpoint_every_steps``, at the end and on
  SIGINT/SIGTERM. A :func:`colmap_pvs.model.save_checkpoint` file whose ``extra`` holds
  ``train_config``, ``optimizer``, ``scheduler``, ``rng`` (torch/numpy/python states as
  tensors and lists), ``log_accum``, ``best_val_loss`` and ``elapsed_s``; everything
  loads with ``torch.load(weights_only=True)``;
- ``best.pt``: weights (+ ``train_config``, ``val``) of the lowest validation loss;
- ``model.pt``: the final weights without optimizer state (the file to ship);
- ``log.csv``: ``step, time_s, loss, loss_out0.., lr, sec_per_step``, one row per
  ``log_every`` steps (means over those steps);
- ``val.csv``: ``step, val_loss, val_loss_out0.., out{k}_{metric}..`` per validation;
- ``loss.png``: loss curves (drawn with OpenCV: matplotlib is not a dependency).

Determinism and resuming
------------------------
A step is one optimizer update; ``step`` counts completed updates. The samples of step
``s`` are a pure function of ``(seed, s)``: the sample stream is the concatenation of
per-epoch permutations ``numpy.random.default_rng([seed, epoch]).permutation(len(data))``
and step ``s`` takes stream positions ``s * batch_size ... (s + 1) * batch_size - 1``
(:class:`StepSampler`). Datasets should be deterministic functions of the index (both
of ours are); with ``num_workers=0`` a dataset may also draw from the global RNGs, since
their states are checkpointed (with workers, their seeds come from a generator seeded by
``seed + step`` at the (re)start, so such a dataset is only reproducible per start).
Validation saves and restores the RNG states, so it never changes the training run. On
start, ``last.pt`` (if ``resume``) restores the weights, optimizer, scheduler, the
torch/numpy/python RNG states and the log accumulators, so a resumed run is identical to
an uninterrupted one (same thread count assumed: CPU reductions may depend on it; on CUDA
(``device``), whose convolution kernels are not deterministic, close to it, not identical). Only
the fields in :data:`~colmap_pvs.train.config.RESUMABLE_CHANGES` may differ from the
checkpoint's config.
"""

from __future__ import annotations

import contextlib
import csv
import logging
import math
import os
import random
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset
from tqdm import tqdm

from ..config import config_from_dict, config_json_bytes, config_to_dict
from ..errors import CheckpointError, ColmapPVSError, ConfigError
from ..io.files import atomic_write_bytes
from ..model import PVSNet, load_checkpoint, save_checkpoint
from ..model.runtime import resolve_device
from .config import RESUMABLE_CHANGES, TrainConfig
from .data import StepSampler, build_datasets
from .logs import _fmt, _read_csv, _write_csv, plot_curves
from .losses import depth_loss, output_metrics
from .rng import _rng_state, _set_rng_state
from .selfsup import selfsup_loss

logger = logging.getLogger(__name__)

__all__ = [
    "StepSampler",
    "Trainer",
    "TrainingDivergedError",
    "TrainingInterrupted",
    "build_datasets",
    "plot_curves",
    "train",
]

#: Size limit of the shipped weights file (``model.pt``); a warning is logged above it.
SHIP_LIMIT_BYTES = 20 * 1024 * 1024


class TrainingDivergedError(ColmapPVSError):
    """The loss became NaN or infinite; ``last.pt`` keeps the last finite state."""


class TrainingInterrupted(KeyboardInterrupt):
    """Training stopped on SIGINT/SIGTERM after writing ``checkpoint``.

    Attributes:
        checkpoint: path of the ``last.pt`` just written.
        signal_name: ``"SIGINT"`` or ``"SIGTERM"``.
        step: completed steps saved in the checkpoint.
    """

    def __init__(self, checkpoint: Path, signal_name: str, step: int) -> None:
        super().__init__(f"training interrupted by {signal_name} at step {step}; state saved to {checkpoint}")
        self.checkpoint = checkpoint
        self.signal_name = signal_name
        self.step = step



# --------------------------------------------------------------------------- trainer


def _to(batch: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    return {k: (v.to(device) if torch.is_tensor(v) else v) for k, v in batch.items()}


class Trainer:
    """Trains a :class:`~colmap_pvs.model.PVSNet` as configured by a :class:`TrainConfig`.

    Args:
        config: the run config.
        train_dataset, val_dataset: optional datasets replacing the ones selected by
            ``config.dataset`` (for tests and custom data); items must be the sample dicts
            of :class:`~colmap_pvs.synthetic.SyntheticMVSDataset`.

    Construction seeds every RNG, builds the model/optimizer/scheduler and, when
    ``config.resume`` and ``output_dir/last.pt`` exists, restores the saved state.
    """

    def __init__(
        self,
        config: TrainConfig,
        *,
        train_dataset: Dataset | None = None,
        val_dataset: Dataset | None = None,
    ) -> None:
        self.config = config
        self.output_dir = Path(config.output_dir)
        self.device = resolve_device(config.device)
        random.seed(config.seed)
        np.random.seed(config.seed % 2**32)
        torch.manual_seed(config.seed)
        if train_dataset is None:
            train_dataset, built_val = build_datasets(config)
            val_dataset = built_val if val_dataset is None else val_dataset
        self.train_dataset = train_dataset
        self.val_dataset = val_dataset if config.val_every > 0 else None
        self.model = PVSNet(config.model).to(self.device)
        self.optimizer = self._make_optimizer()
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, config.lr_factor)
        self.step = 0
        self.best_val_loss = math.inf
        self.elapsed_s = 0.0
        self._log_accum: dict[str, Any] = {"n": 0, "loss": [], "seconds": 0.0}
        self._stop_signal: str | None = None
        self.last_lr = float(self.optimizer.param_groups[0]["lr"])  # lr of the latest step
        self.num_outputs = len(config.model.loss_weights)
        self.last_path = self.output_dir / "last.pt"
        self.best_path = self.output_dir / "best.pt"
        self.model_path = self.output_dir / "model.pt"
        self.log_path = self.output_dir / "log.csv"
        self.val_log_path = self.output_dir / "val.csv"
        self.plot_path = self.output_dir / "loss.png"
        self.resumed_from: Path | None = None
        if config.resume and self.last_path.is_file():
            self._resume(self.last_path)
        elif config.init_weights is not None:
            self._init_weights(Path(config.init_weights))

    # ----------------------------------------------------------------- setup

    @contextlib.contextmanager
    def torch_threads(self) -> Iterator[None]:
        """Run the body with ``config.torch_threads`` intra-op threads, then restore the previous count.

        :meth:`train` uses it; wrap direct :meth:`train_step` / :meth:`validate` calls in it too.
        """
        previous = torch.get_num_threads()
        if self.config.torch_threads > 0:
            torch.set_num_threads(self.config.torch_threads)
        try:
            yield
        finally:
            torch.set_num_threads(previous)

    def _make_optimizer(self) -> torch.optim.Optimizer:
        cfg = self.config
        params = [p for p in self.model.parameters() if p.requires_grad]
        if cfg.optimizer == "rmsprop":
            return torch.optim.RMSprop(
                params, lr=cfg.lr, alpha=cfg.rmsprop_alpha, weight_decay=cfg.weight_decay
            )
        return torch.optim.Adam(params, lr=cfg.lr, weight_decay=cfg.weight_decay)

    def _resume(self, path: Path) -> None:
        saved_model, ckpt = load_checkpoint(path, map_location="cpu")
        try:
            saved_cfg = ckpt["train_config"]
            state = (saved_model.state_dict(), ckpt["optimizer"], ckpt["scheduler"], ckpt["rng"])
        except KeyError as exc:
            raise CheckpointError(
                f"{str(path)!r} is not a training checkpoint: no {exc.args[0]!r} entry"
            ) from None
        current = config_to_dict(self.config)
        try:  # fields added since the checkpoint was written take their defaults
            saved_cfg = config_to_dict(config_from_dict(TrainConfig, saved_cfg))
        except ConfigError as exc:
            raise ConfigError(
                f"cannot resume from {str(path)!r}: its training config no longer loads: {exc}"
            ) from None
        differing = sorted(
            k
            for k in set(current) | set(saved_cfg)
            if k not in RESUMABLE_CHANGES and current.get(k) != saved_cfg.get(k)
        )
        if differing:
            raise ConfigError(
                f"cannot resume from {str(path)!r}: config field(s) {differing} differ from the checkpoint's "
                f"(saved { {k: saved_cfg.get(k) for k in differing} }, "
                f"now { {k: current.get(k) for k in differing} }); "
                "use another output_dir or resume=false"
            )
        self.model.load_state_dict(state[0])
        self.optimizer.load_state_dict(state[1])
        self.scheduler.load_state_dict(state[2])
        _set_rng_state(state[3])
        self.step = int(ckpt["step"])
        self.best_val_loss = float(ckpt.get("best_val_loss", math.inf))
        self.elapsed_s = float(ckpt.get("elapsed_s", 0.0))
        accum = ckpt.get("log_accum")
        if accum is not None:
            self._log_accum = {
                "n": int(accum["n"]),
                "loss": list(accum["loss"]),
                "seconds": float(accum["seconds"]),
            }
        self.resumed_from = path
        logger.info("resumed from %s at step %d", path, self.step)

    def _init_weights(self, path: Path) -> None:
        """Copy the parameters of ``path`` whose name and shape match (fresh runs only)."""
        source, _ = load_checkpoint(path, map_location="cpu")
        own = self.model.state_dict()
        taken = {k: v for k, v in source.state_dict().items() if k in own and own[k].shape == v.shape}
        if not taken:
            raise CheckpointError(f"init_weights {str(path)!r} shares no parameter with this model")
        own.update(taken)
        self.model.load_state_dict(own)
        logger.info(
            "initialised %d of %d tensors from %s (%d left at their initialisation)",
            len(taken), len(own), path, len(own) - len(taken),
        )

    # ----------------------------------------------------------------- checkpoints

    def _training_state(self) -> dict[str, Any]:
        return {
            "train_config": config_to_dict(self.config),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "rng": _rng_state(),
            "log_accum": {
                "n": self._log_accum["n"],
                "loss": [float(v) for v in self._log_accum["loss"]],
                "seconds": float(self._log_accum["seconds"]),
            },
            "best_val_loss": float(self.best_val_loss),
            "elapsed_s": float(self.elapsed_s),
        }

    def save(self, path: Path | None = None) -> Path:
        """Write the full training state (``last.pt`` by default), atomically."""
        path = self.last_path if path is None else Path(path)
        save_checkpoint(path, self.model, step=self.step, extra=self._training_state())
        logger.debug("checkpoint %s at step %d", path, self.step)
        return path

    def export(self, path: Path | None = None) -> Path:
        """Write the weights without optimizer state (``model.pt``): the file to ship."""
        path = self.model_path if path is None else Path(path)
        save_checkpoint(path, self.model, step=self.step, extra={"train_config": config_to_dict(self.config)})
        size = path.stat().st_size
        if size > SHIP_LIMIT_BYTES:
            logger.warning(
                "%s is %.1f MB, over the %.0f MB limit for shipped weights", path, size / 2**20, 20
            )
        return path

    # ----------------------------------------------------------------- one step

    def _forward(self, batch: dict[str, torch.Tensor]):
        sparse = batch.get("sparse_depth") if self.config.use_sparse_depth else None
        return self.model(
            batch["images"],
            batch["intrinsics"],
            batch["cam_from_world"],
            batch["depth_min"],
            batch["depth_max"],
            sparse_depth=sparse,
        )

    def _scales(self) -> tuple[int, ...] | None:
        """Stride of each output (``PVSNetConfig.output_scales``) for GT downsampling."""
        scales = getattr(self.config.model, "output_scales", None)
        return tuple(scales) if scales is not None else None

    def _loss(self, out, batch: dict[str, torch.Tensor]):
        cfg = self.config
        is_real = batch.get("is_real")
        if is_real is not None and bool(is_real.any()):
            if not bool(is_real.all()):
                raise ColmapPVSError("a batch mixes real and synthetic samples; use batch_size 1")
            return selfsup_loss(
                out.depths,
                batch["photo_images"],
                batch["intrinsics"],
                batch["cam_from_world"],
                batch["label_depth"],
                batch["depth_min"],
                batch["depth_max"],
                cfg.model.loss_weights,
                self._scales() or cfg.model.output_scales,
                cfg.selfsup,
                pseudo_depth=batch.get("pseudo_depth"),
            )
        return depth_loss(
            out.depths,
            batch["depth"],
            batch["depth_min"],
            batch["depth_max"],
            cfg.model.loss_weights,
            gt_downsample=cfg.gt_downsample,
            normalize=cfg.loss_normalize,
            mask_depth_range=cfg.mask_depth_range,
            scales=self._scales(),
        )

    def train_step(self, batch: dict[str, torch.Tensor]) -> tuple[float, list[float]]:
        """One optimizer update on a collated ``batch``; returns ``(loss, per-output losses)``."""
        self.model.train()
        batch = _to(batch, self.device)
        self.optimizer.zero_grad(set_to_none=True)
        out = self._forward(batch)
        loss = self._loss(out, batch)
        total = float(loss.total.detach())
        if not math.isfinite(total):
            raise TrainingDivergedError(
                f"loss is {total} at step {self.step + 1} (per output {loss.per_output.tolist()}); "
                f"{self.last_path} holds the last saved finite state"
            )
        loss.total.backward()
        if self.config.grad_clip_norm > 0:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.config.grad_clip_norm)
        self.last_lr = float(self.optimizer.param_groups[0]["lr"])
        self.optimizer.step()
        self.scheduler.step()
        self.step += 1
        return total, [float(v) for v in loss.per_output]

    # ----------------------------------------------------------------- validation

    @torch.no_grad()
    def validate(self) -> dict[str, float] | None:
        """Loss and metrics over the first ``val_samples`` validation samples (``None`` without a val set)."""
        if self.val_dataset is None:
            return None
        cfg = self.config
        n = min(cfg.val_samples, len(self.val_dataset))
        loader = DataLoader(
            torch.utils.data.Subset(self.val_dataset, range(n)),
            batch_size=cfg.batch_size,
            shuffle=False,
            num_workers=cfg.num_workers,
            generator=torch.Generator().manual_seed(cfg.seed),  # never touch the global torch RNG
        )
        self.model.eval()
        loss_sum, parts_sum, count = 0.0, np.zeros(self.num_outputs), 0
        metric_sums: dict[str, float] = {}
        valid_sums: dict[str, float] = {}
        for batch in loader:
            batch = _to(batch, self.device)
            out = self._forward(batch)
            loss = self._loss(out, batch)
            b = batch["images"].shape[0]
            loss_sum += float(loss.total) * b
            parts_sum += loss.per_output.detach().double().cpu().numpy() * b
            count += b
            metrics = output_metrics(
                out.depths,
                batch["depth"],
                batch["depth_min"] if cfg.mask_depth_range else None,
                batch["depth_max"] if cfg.mask_depth_range else None,
                gt_downsample=cfg.gt_downsample,
                scales=self._scales(),
            )
            # pixel-weighted means over the whole validation set
            for name, value in metrics.items():
                if name.endswith("_valid"):
                    continue
                v = metrics[name.split("_", 1)[0] + "_valid"]
                metric_sums.setdefault(name, 0.0)
                valid_sums.setdefault(name, 0.0)
                if v > 0:
                    metric_sums[name] += value * v
                    valid_sums[name] += v
        self.model.train()
        result = {"val_loss": loss_sum / count}
        result.update({f"val_loss_out{k}": float(parts_sum[k] / count) for k in range(self.num_outputs)})
        result.update(
            {
                n: (metric_sums[n] / valid_sums[n] if valid_sums[n] > 0 else math.nan)
                for n in sorted(metric_sums)
            }
        )
        return result

    # ----------------------------------------------------------------- logs

    def _log_columns(self) -> list[str]:
        return (
            ["step", "time_s", "loss"]
            + [f"loss_out{k}" for k in range(self.num_outputs)]
            + ["lr", "sec_per_step"]
        )

    def _prepare_logs(self) -> None:
        """Drop log rows past the current step (written after the checkpoint we resume from)."""
        for path in (self.log_path, self.val_log_path):
            columns, rows = _read_csv(path)
            if not columns:
                continue
            kept = [r for r in rows if int(r["step"]) <= self.step]
            if len(kept) != len(rows):
                _write_csv(path, columns, kept)

    def _append_row(self, path: Path, columns: list[str], row: dict[str, Any]) -> None:
        new = not path.is_file()
        with path.open("a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
            if new:
                writer.writeheader()
            writer.writerow({k: _fmt(v) for k, v in row.items()})

    def _flush_train_log(self) -> None:
        acc = self._log_accum
        if acc["n"] == 0:
            return
        sums = np.asarray(acc["loss"], dtype=np.float64) / acc["n"]
        row = {
            "step": self.step,
            "time_s": round(self.elapsed_s, 3),
            "loss": float(sums[0]),
            "lr": self.last_lr,
            "sec_per_step": acc["seconds"] / acc["n"],
        }
        row.update({f"loss_out{k}": float(sums[k + 1]) for k in range(self.num_outputs)})
        self._append_row(self.log_path, self._log_columns(), row)
        self._log_accum = {"n": 0, "loss": [], "seconds": 0.0}

    def _accumulate(self, total: float, parts: list[float], seconds: float) -> None:
        acc = self._log_accum
        values = [total, *parts]
        acc["loss"] = values if acc["n"] == 0 else [a + b for a, b in zip(acc["loss"], values, strict=True)]
        acc["n"] += 1
        acc["seconds"] += seconds

    def _log_validation(self, result: dict[str, float]) -> None:
        columns = ["step", *result]
        old_columns, _ = _read_csv(self.val_log_path)
        if old_columns and old_columns != columns:
            raise CheckpointError(f"{self.val_log_path} has columns {old_columns}, expected {columns}")
        self._append_row(self.val_log_path, columns, {"step": self.step, **result})

    def plot(self) -> Path | None:
        """Redraw ``loss.png`` from ``log.csv`` and ``val.csv``."""
        series: dict[str, tuple[list[float], list[float]]] = {}
        _, rows = _read_csv(self.log_path)
        if rows:
            steps = [float(r["step"]) for r in rows]
            series["loss"] = (steps, [float(r["loss"]) for r in rows])
            for k in range(self.num_outputs):
                series[f"out{k}"] = (steps, [float(r[f"loss_out{k}"]) for r in rows])
        _, vrows = _read_csv(self.val_log_path)
        if vrows:
            series["val_loss"] = ([float(r["step"]) for r in vrows], [float(r["val_loss"]) for r in vrows])
        try:
            return plot_curves(self.plot_path, series, title=f"PVSNet training: {self.output_dir.name}")
        except (OSError, cv2.error) as exc:  # a plot must never stop training
            logger.warning("could not draw %s: %s", self.plot_path, exc)
            return None

    # ----------------------------------------------------------------- loop

    def _handle_signal(self, signum: int, _frame: Any) -> None:
        name = signal.Signals(signum).name
        if self._stop_signal is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt  # second Ctrl-C: stop at once
        self._stop_signal = name
        logger.warning("%s received: stopping after the current step and saving %s", name, self.last_path)

    def request_stop(self, reason: str = "SIGTERM") -> None:
        """Ask the loop to checkpoint and stop after the current step (what the signal handlers do)."""
        self._stop_signal = reason

    def _validate_and_keep_best(self) -> None:
        rng = _rng_state()  # validation must not perturb the training RNG streams
        try:
            result = self.validate()
        finally:
            _set_rng_state(rng)
        if result is None:
            return
        self._log_validation(result)
        logger.info(
            "step %d: val_loss %.5g (final output AbsRel %.4g)",
            self.step,
            result["val_loss"],
            result.get(f"out{self.num_outputs - 1}_absrel", float("nan")),
        )
        if result["val_loss"] < self.best_val_loss:
            self.best_val_loss = result["val_loss"]
            extra = {
                "train_config": config_to_dict(self.config),
                "val": {k: float(v) for k, v in result.items()},
            }
            save_checkpoint(self.best_path, self.model, step=self.step, extra=extra)

    def train(self, max_steps: int | None = None) -> Path:
        """Train until ``config.steps`` (or ``max_steps`` more steps in this call); returns ``last.pt``.

        Raises:
            TrainingInterrupted: after checkpointing, on SIGINT/SIGTERM (or :meth:`request_stop`).
            TrainingDivergedError: on a non-finite loss (the previous checkpoint is kept).
        """
        cfg = self.config
        self.output_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(self.output_dir / "config.json", config_json_bytes(cfg))
        self._prepare_logs()
        end = cfg.steps if max_steps is None else min(cfg.steps, self.step + max_steps)
        handlers = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                handlers[sig] = signal.signal(sig, self._handle_signal)
        try:
            with self.torch_threads():
                self._loop(end)
        finally:
            for sig, old in handlers.items():
                signal.signal(sig, old)
        return self.last_path

    def _loop(self, end: int) -> None:
        cfg = self.config
        if self.step >= end:
            logger.info("nothing to do: step %d >= %d", self.step, end)
            if not self.last_path.is_file():
                self.save()
            return
        loader = DataLoader(
            self.train_dataset,
            batch_size=cfg.batch_size,
            sampler=StepSampler(
                len(self.train_dataset), cfg.seed, self.step * cfg.batch_size, cfg.sample_grouping
            ),
            num_workers=cfg.num_workers,
            generator=torch.Generator().manual_seed(cfg.seed + self.step),
        )
        n_params = sum(p.numel() for p in self.model.parameters())
        logger.info(
            "training %s parameters on %d samples: step %d -> %d, batch %d, %d threads, device %s",
            f"{n_params:,}",
            len(self.train_dataset),
            self.step,
            end,
            cfg.batch_size,
            torch.get_num_threads(),
            self.device,
        )
        if torch.get_num_threads() > 1 and "OMP_WAIT_POLICY" not in os.environ:
            logger.info(
                "tip: on a machine whose cores are shared with other jobs, start with "
                "OMP_WAIT_POLICY=PASSIVE "
                "(or use torch_threads=1): spinning OpenMP threads can make steps 10x slower there"
            )
        last_ckpt = time.monotonic()
        batches = iter(loader)
        bar = tqdm(total=cfg.steps, initial=self.step, disable=not cfg.progress, desc="train", unit="step")
        try:
            while self.step < end and self._stop_signal is None:
                t0 = time.perf_counter()
                try:
                    batch = next(batches)
                except Exception:
                    if self._stop_signal is not None:  # workers interrupted by the same signal
                        break
                    raise
                total, parts = self.train_step(batch)
                dt = time.perf_counter() - t0
                self.elapsed_s += dt
                self._accumulate(total, parts, dt)
                bar.update(1)
                bar.set_postfix(loss=f"{total:.4g}", s_per_step=f"{dt:.2f}")
                done = self.step >= end
                if self.step % cfg.log_every == 0 or self.step == cfg.steps:
                    self._flush_train_log()
                if self.val_dataset is not None and (
                    self.step % cfg.val_every == 0 or self.step == cfg.steps
                ):
                    self._validate_and_keep_best()
                due_time = (
                    cfg.checkpoint_every_seconds > 0
                    and time.monotonic() - last_ckpt >= cfg.checkpoint_every_seconds
                )
                due_step = cfg.checkpoint_every_steps > 0 and self.step % cfg.checkpoint_every_steps == 0
                if (due_time or due_step) and not done:
                    self.save()
                    self.plot()
                    last_ckpt = time.monotonic()
        finally:
            bar.close()
        self.save()
        self.plot()
        if self._stop_signal is not None:
            raise TrainingInterrupted(self.last_path, self._stop_signal, self.step)
        if self.step >= self.config.steps:
            self.export()
        logger.info("step %d: saved %s", self.step, self.last_path)


def train(config: TrainConfig) -> Path:
    """Build a :class:`Trainer` and train to ``config.steps``; returns the ``last.pt`` path.

    The shipped weights (no optimizer state) are ``output_dir/model.pt``; with validation
    on, the best ones are ``output_dir/best.pt``.
    """
    return Trainer(config).train()
