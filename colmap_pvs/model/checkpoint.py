"""Atomic, self-describing model checkpoints (loaded with ``torch.load(weights_only=True)``)."""

from __future__ import annotations

import io
import logging
import os
from pathlib import Path
from typing import Any

import torch

from ..config import config_from_dict, config_to_dict
from ..errors import CheckpointError, ConfigError
from ..io.files import atomic_write_bytes
from .config import PVSNetConfig
from .pvsnet import PVSNet

logger = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "colmap-pvs-checkpoint/1"
_RESERVED = ("format", "model_config", "state_dict", "step")

#: :class:`PVSNetConfig` fields removed in colmap-pvs 0.2, each with the field it followed and the one
#: value every recorded config gives it. Checkpoints and stereo provenance written by 0.1 hold them:
#: :func:`stored_config` writes them back, so the provenance of maps made by 0.1 still matches (they are
#: not recomputed) and a checkpoint is still read by 0.1; a stored config's are dropped when read.
#: Back-compat (dropped in 0.3): a user's checkpoints and maps' provenance hold them (after 0.3 a
#: workspace made before then recomputes its photometric maps once).
RETIRED_FIELDS: dict[str, tuple[str, Any]] = {
    "guidance_mode": ("guidance_c", "cost"),
    "normalized_channels": ("prior_growth_radii", 0),
}
#: What a stored config written before these fields existed means (``pvsnet_v2.pt`` lacks the first two):
#: off, not :class:`PVSNetConfig`'s default. The rule: every field added after the first checkpoint
#: whose default is not what its absence meant. Back-compat (dropped in 0.3): a user's checkpoints
#: trained before the fields existed, and the shipped ``pvsnet_v2.pt`` (to be saved again with them by then).
ABSENT_FIELDS: dict[str, Any] = {"frustum_weights": False, "stage_neighbourhood": 0, "sparse_prior": False}


def stored_config(config: PVSNetConfig) -> dict[str, Any]:
    """The mapping a checkpoint (``model_config``) and stereo's provenance record for ``config``: its
    fields, with :data:`RETIRED_FIELDS` at their value in their old place."""
    after = {prev: (name, value) for name, (prev, value) in RETIRED_FIELDS.items()}
    out: dict[str, Any] = {}
    for key, value in config_to_dict(config).items():
        out[key] = value
        if key in after:
            out[after[key][0]] = after[key][1]
    return out


def read_stored_config(stored: dict[str, Any]) -> PVSNetConfig:
    """The config a stored mapping (:func:`stored_config`, or one written before a field existed:
    :data:`ABSENT_FIELDS`) describes. Raises :class:`ConfigError` for unknown keys, bad values and a
    retired field at another value."""
    stored = dict(stored)
    for name, (_, value) in RETIRED_FIELDS.items():
        if name in stored and stored[name] == value:
            del stored[name]
    return config_from_dict(PVSNetConfig, {**ABSENT_FIELDS, **stored})


def save_checkpoint(
    path: str | os.PathLike, model: PVSNet, *, step: int = 0, extra: dict[str, Any] | None = None
) -> Path:
    """Save ``model`` to ``path`` atomically (temporary file + rename).

    The file holds ``{"format": "colmap-pvs-checkpoint/1", "model_config": stored_config(model.config),
    "state_dict": ..., "step": step, **extra}``. ``extra`` values must be loadable with
    ``weights_only=True`` (tensors, numbers, strings, lists, dicts) and may not use the reserved keys.
    """
    extra = dict(extra or {})
    clash = sorted(set(extra) & set(_RESERVED))
    if clash:
        raise ValueError(f"save_checkpoint: extra uses reserved key(s) {clash}")
    payload: dict[str, Any] = {
        "format": CHECKPOINT_FORMAT,
        "model_config": stored_config(model.config),
        "state_dict": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
        "step": int(step),
    }
    payload.update(extra)
    buf = io.BytesIO()
    torch.save(payload, buf)
    out = atomic_write_bytes(path, buf.getvalue())
    logger.info("saved checkpoint %s (step %d)", out, step)
    return out


def load_checkpoint(
    path: str | os.PathLike, map_location: str | torch.device = "cpu"
) -> tuple[PVSNet, dict[str, Any]]:
    """Load a checkpoint written by :func:`save_checkpoint`.

    Returns ``(model, meta)``: the model built from the stored config with the stored weights
    (in eval mode), and every other key of the file (``format``, ``model_config``, ``step``,
    the ``extra`` keys). Raises :class:`CheckpointError` naming the path and the problem for a
    missing, corrupt, wrong-format or mismatched file.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist")
    try:
        data = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means a corrupt/unsafe file
        raise CheckpointError(f"checkpoint {str(path)!r} is corrupt or not a torch file: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
        fmt = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise CheckpointError(f"checkpoint {str(path)!r} has format {fmt!r}, expected {CHECKPOINT_FORMAT!r}")
    for key in ("model_config", "state_dict"):
        if not isinstance(data.get(key), dict):
            raise CheckpointError(f"checkpoint {str(path)!r} has no valid {key!r} entry")
    try:
        config = read_stored_config(data["model_config"])
    except ConfigError as exc:
        raise CheckpointError(f"checkpoint {str(path)!r} has an invalid model_config: {exc}") from None
    model = PVSNet(config)
    try:
        model.load_state_dict(data["state_dict"], strict=True)
    except (RuntimeError, KeyError, TypeError) as exc:
        raise CheckpointError(
            f"checkpoint {str(path)!r}: state_dict does not match its model_config: {exc}"
        ) from None
    model.to(map_location).eval()
    meta = {k: v for k, v in data.items() if k != "state_dict"}
    logger.info("loaded checkpoint %s (step %s)", path, meta.get("step"))
    return model, meta
