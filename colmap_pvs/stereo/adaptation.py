"""Test-time adaptation hooks of the ``stereo`` step (``--adapt_*``): the adapted network a run uses.

The adaptation itself is :mod:`colmap_pvs.adapt`, imported only when ``adapt_steps > 0``.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import torch

from ..config import replace_config
from ..io.files import file_sha256
from ..io.workspace import Workspace
from .config import FORMAT_VERSIONS, StereoConfig, pass_settings
from .network import base_checkpoint_path, load_stereo_model

logger = logging.getLogger(__name__)


def adapt_config(config: StereoConfig):
    """The :class:`~colmap_pvs.adapt.AdaptConfig` of a stereo run's ``adapt_*`` settings."""
    from ..adapt import AdaptConfig

    return AdaptConfig(
        steps=config.adapt.steps,
        max_seconds=config.adapt.max_seconds,
        lr=config.adapt.lr,
        num_views=config.photometric.num_views,
        threads=config.threads,
        pseudo_labels=config.adapt.pseudo_labels,
    )


def pseudo_label_key(config: StereoConfig, ws: Workspace) -> dict | None:
    """What the pseudo-labels of self-training are made with (``None`` without them).

    The settings of the passes up to ``adapt_pseudo_labels``, their format versions and the
    ``patch-match.cfg`` content, hashed: any change among them makes :func:`run_stereo` adapt again.
    """
    kind = config.adapt.pseudo_labels
    if kind == "none":
        return None
    settings = {**pass_settings(config, "photometric"), "wide_sources": 0,  # once an option
                **pass_settings(config, "geometric")}
    if kind == "filled" or config.completion.enabled:  # the geometric maps hold the confirmed completion
        settings.update(pass_settings(config, "completion"), geom_fill=config.completion.enabled)
    kinds = ("photometric", "geometric", kind) + (("filled", "confirm") if config.completion.enabled else ())
    settings["format_versions"] = {k: FORMAT_VERSIONS[k] for k in kinds}
    if ws.patch_match_cfg.is_file():
        settings["patch_match_cfg_sha256"] = file_sha256(ws.patch_match_cfg)
    text = json.dumps(settings, sort_keys=True, default=str).encode()
    return {"kind": kind, "settings_sha256": hashlib.sha256(text).hexdigest()}


def adapted_exists(config: StereoConfig, ws: Workspace) -> bool:
    """Whether the adapted weights that ``config`` asks for exist already (so the pseudo-labels'
    first round is not needed)."""
    from ..adapt import adapted_is_current

    base = base_checkpoint_path(config)
    return base.is_file() and adapted_is_current(ws.stereo_dir, base, adapt_config(config),
                                                 pseudo_label_key(config, ws))


def adapt_network(config: StereoConfig, ws: Workspace, base: Path, device: torch.device):
    """Test-time adaptation of ``base`` on the workspace; returns ``(net, adapted path, seconds)``."""
    from ..adapt import adapt_checkpoint

    done = adapt_checkpoint(ws.root, ws.stereo_dir, base, adapt_config(config),
                            labels=pseudo_label_key(config, ws))
    net, path, _ = load_stereo_model(replace_config(config, checkpoint=done.checkpoint), device)
    logger.info(
        "test-time adaptation: %d steps, %.1f s (%s)", done.steps, done.seconds,
        "reused" if done.reused else "computed",
    )
    return net, path, done.seconds
