"""The ``stereo`` command with test-time adaptation (``--adapt_*``): :func:`run_adapted_stereo`.

With ``adapt_steps > 0`` the step

1. with ``adapt_pseudo_labels`` (self-training) runs :func:`~colmap_pvs.stereo.run_stereo` with the
   base checkpoint, unless the adapted weights for its maps exist already: those maps are the labels;
2. adapts the base checkpoint on the workspace (:func:`~colmap_pvs.adapt.checkpoint.adapt_checkpoint`:
   ``stereo/adapt/adapted.pt``, reused when current, resumed when interrupted);
3. runs :func:`~colmap_pvs.stereo.run_stereo` with the adapted weights (``weights=``): their sha256 is
   in every pass's provenance, the confidence calibration stays the base checkpoint's.

``adapt_seconds`` of the result is the time of steps 1 and 2 (step 2's as recorded when it was reused).
"""

from __future__ import annotations

import hashlib
import json
import logging
import time

import torch

from ..config import replace_config
from ..io.files import file_sha256
from ..io.workspace import Workspace, load_workspace
from ..stereo import StereoConfig, StereoResult, run_stereo
from ..stereo.config import FORMAT_VERSIONS, pass_settings
from ..stereo.network import base_checkpoint_path, load_stereo_model
from .checkpoint import AdaptConfig, adapt_checkpoint, adapted_is_current

logger = logging.getLogger(__name__)


def adapt_config(config: StereoConfig) -> AdaptConfig:
    """The :class:`AdaptConfig` of a stereo run's ``adapt_*`` settings."""
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
    ``patch-match.cfg`` content, hashed: any change among them makes :func:`run_adapted_stereo` adapt again.
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


def _pseudo_label_round(config: StereoConfig, ws: Workspace) -> float:
    """Self-training's first round: every pass with the base checkpoint, whose maps become the
    adaptation's pseudo-labels. Skipped (0 s) when the adapted weights for them already exist."""
    base = base_checkpoint_path(config)
    if base.is_file() and adapted_is_current(ws.stereo_dir, base, adapt_config(config),
                                             pseudo_label_key(config, ws)):
        return 0.0
    logger.info("test-time adaptation on %s pseudo-labels: a first run with the base checkpoint",
                config.adapt.pseudo_labels)
    start = time.perf_counter()
    run_stereo(replace_config(config, adapt_steps=0, adapt_pseudo_labels="none"))
    return time.perf_counter() - start


def run_adapted_stereo(config: StereoConfig) -> StereoResult:
    """The ``stereo`` command: :func:`~colmap_pvs.stereo.run_stereo`, after test-time adaptation of
    the network when ``config.adapt.steps > 0`` (see the module docstring)."""
    if config.adapt.steps == 0:
        return run_stereo(config)
    # a bad workspace or checkpoint fails here with stereo's own message, before any training
    ws, _ = load_workspace(config.workspace_path)
    _, base, _ = load_stereo_model(config, torch.device("cpu"))
    first_round = _pseudo_label_round(config, ws) if config.adapt.pseudo_labels != "none" else 0.0
    done = adapt_checkpoint(ws.root, ws.stereo_dir, base, adapt_config(config),
                            labels=pseudo_label_key(config, ws))
    logger.info("test-time adaptation: %d steps, %.1f s (%s)", done.steps, done.seconds,
                "reused" if done.reused else "computed")
    result = run_stereo(config, weights=done.checkpoint)
    result.adapt_seconds = result.timings["adapt"] = done.seconds + first_round
    count = len(result.processed) + len(result.already_done) + len(result.skipped)
    result.adapt_seconds_per_image = result.adapt_seconds / max(1, count)
    return result
