"""The ``average-weights`` step: a weighted average of PVSNet checkpoints (a "model soup").

Averaging the weights of a network and of its fine-tune ("WiSE-FT", Wortsman et al., CVPR 2022)
often keeps what the fine-tune learned and loses less of what the starting weights did well on
other data. The shipped default weights are made this way (see the model card): the average of
the v2 release and of its fine-tune on real images (``stage_neighbourhood`` 2, ``frustum_weights``).

Every floating-point tensor of the state dicts (weights, biases, BatchNorm running statistics)
is averaged with ``weights``; integer buffers (BatchNorm's ``num_batches_tracked``), the model
config and the ``step`` are taken from checkpoint ``config_from``. All checkpoints must hold the
same tensors (names and shapes); configs that differ only in parameter-free switches
(:data:`colmap_pvs.model.PARAMETER_FREE_FIELDS`: the sparse prior and guidance, ``stage_neighbourhood``, ...)
average fine, other differences are warned about.

The output is a normal checkpoint (:func:`colmap_pvs.model.save_checkpoint`, atomic) that also
records its recipe: ``averaged_from`` (path, sha256, weight and step of each input) and the
resolved ``average_config`` (weights and ``config_from`` resolved), also written next to it as
``STEM.average_config.json`` (an old one is removed first).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import torch

from .config import config_json_bytes, config_to_dict
from .errors import CheckpointError, ConfigError
from .io.files import atomic_write_bytes, file_sha256
from .model import PARAMETER_FREE_FIELDS, PVSNet, load_checkpoint, save_checkpoint

logger = logging.getLogger(__name__)

__all__ = ["AverageWeightsConfig", "average_weights", "config_path"]


@dataclass(frozen=True)
class AverageWeightsConfig:
    """Settings of the ``average-weights`` step (the single source of its defaults and CLI flags)."""

    checkpoints: tuple[Path, ...] = field(
        metadata={
            "help": "two or more PVSNet checkpoints with the same tensors (e.g. weights and their fine-tune)"
        }
    )
    output_path: Path = field(metadata={"help": "the averaged checkpoint (.pt) to write"})
    weights: tuple[float, ...] = field(
        default=(),
        metadata={"help": "one weight per checkpoint, each >= 0, summing to 1; default: equal weights"},
    )
    config_from: int = field(
        default=-1,
        metadata={
            "help": "index into checkpoints (negative counts from the end) of the checkpoint whose model "
            "config and integer buffers the output takes; default: the last one"
        },
    )

    def __post_init__(self) -> None:
        object.__setattr__(self, "checkpoints", tuple(Path(p) for p in self.checkpoints))
        object.__setattr__(self, "output_path", Path(self.output_path))
        object.__setattr__(self, "weights", tuple(float(w) for w in self.weights))
        n = len(self.checkpoints)
        if n < 2:
            raise ConfigError(f"checkpoints: averaging needs at least 2 checkpoints, got {n}")
        if self.weights:
            if len(self.weights) != n:
                raise ConfigError(
                    f"weights: {len(self.weights)} weight(s) {self.weights} for {n} checkpoints"
                )
            bad = [w for w in self.weights if not (math.isfinite(w) and w >= 0)]
            if bad:
                raise ConfigError(f"weights must be finite and >= 0, got {self.weights}")
            if abs(sum(self.weights) - 1.0) > 1e-6:
                raise ConfigError(f"weights must sum to 1, got {self.weights} (sum {sum(self.weights):.6g})")
        if not -n <= self.config_from < n:
            raise ConfigError(f"config_from {self.config_from} is not an index into the {n} checkpoints")
        out = self.output_path.resolve()
        clash = [str(p) for p in self.checkpoints if p.resolve() == out]
        if clash:
            raise ConfigError(
                f"output_path {str(self.output_path)!r} is also an input checkpoint: {clash[0]!r}"
            )

    def resolved_weights(self) -> tuple[float, ...]:
        """The weight of each checkpoint (equal weights when none were given)."""
        n = len(self.checkpoints)
        return self.weights if self.weights else tuple(1.0 / n for _ in range(n))


def config_path(output_path: Path) -> Path:
    """Where :func:`average_weights` writes the resolved config of ``output_path``."""
    return output_path.with_name(f"{output_path.stem}.average_config.json")


def average_weights(config: AverageWeightsConfig) -> Path:
    """Write the weighted average of ``config.checkpoints`` to ``config.output_path``.

    Returns:
        The written checkpoint's path.

    Raises:
        CheckpointError: an input is missing or corrupt, or the inputs hold different tensors
            (the message names the file and the first differing tensor).
    """
    weights = config.resolved_weights()
    paths = list(config.checkpoints)
    base_index = config.config_from % len(paths)
    models: list[PVSNet] = []
    metas: list[dict] = []
    for path in paths:
        model, meta = load_checkpoint(path)
        models.append(model)
        metas.append(meta)
    base_model = models[base_index]
    base_state = base_model.state_dict()
    states = [m.state_dict() for m in models]
    for path, state in zip(paths, states, strict=True):
        missing = sorted(set(base_state) ^ set(state))
        if missing:
            raise CheckpointError(
                f"checkpoint {str(path)!r} holds different tensors than {str(paths[base_index])!r} "
                f"(e.g. {missing[0]!r}): it cannot be averaged with it"
            )
        for key, value in base_state.items():
            if state[key].shape != value.shape:
                raise CheckpointError(
                    f"checkpoint {str(path)!r}: tensor {key!r} has shape {tuple(state[key].shape)}, "
                    f"{str(paths[base_index])!r} has {tuple(value.shape)}: they cannot be averaged"
                )
    base_cfg = config_to_dict(base_model.config)
    for path, model in zip(paths, models, strict=True):
        differs = sorted(k for k, v in config_to_dict(model.config).items() if base_cfg.get(k) != v)
        switches = [k for k in differs if k in PARAMETER_FREE_FIELDS]
        others = [k for k in differs if k not in PARAMETER_FREE_FIELDS]
        if switches:
            logger.info("%s: parameter-free switches differ from the output's: %s", path, switches)
        if others:
            logger.warning(
                "%s: model config differs from the output's (taken from %s) in %s: its tensors were "
                "trained for another network; check the average before using it",
                path, paths[base_index], others,
            )
    averaged = {}
    for key, value in base_state.items():
        if value.is_floating_point():
            total = torch.zeros_like(value, dtype=torch.float64)
            for w, state in zip(weights, states, strict=True):
                total += w * state[key].to(torch.float64)
            averaged[key] = total.to(value.dtype)
        else:
            averaged[key] = value.clone()
    out_model = PVSNet(base_model.config)
    out_model.load_state_dict(averaged, strict=True)
    recipe = [
        {"path": str(p), "sha256": file_sha256(p), "weight": w, "step": int(meta.get("step", 0))}
        for p, w, meta in zip(paths, weights, metas, strict=True)
    ]
    resolved = dataclasses.replace(config, weights=weights, config_from=base_index)
    stale = config_path(config.output_path)
    stale.unlink(missing_ok=True)  # never an old recipe beside a new checkpoint
    out = save_checkpoint(
        config.output_path,
        out_model,
        step=int(metas[base_index].get("step", 0)),
        extra={"averaged_from": recipe, "average_config": config_to_dict(resolved)},
    )
    atomic_write_bytes(config_path(out), config_json_bytes(resolved, averaged_from=recipe))
    logger.info(
        "averaged %d checkpoints (weights %s) into %s",
        len(paths),
        ", ".join(f"{w:.3g}" for w in weights),
        out,
    )
    return out
