"""``run_stereo``: the ``stereo`` step, on the local or the Ray backend."""

from __future__ import annotations

import logging
import time

from ..config import replace_config
from ..io.workspace import detect_workspace
from .adaptation import adapted_exists
from .config import StereoConfig
from .context import StereoResult
from .local import run_local
from .ray import run_stereo_ray

logger = logging.getLogger(__name__)


def run_stereo(config: StereoConfig) -> StereoResult:
    """Compute depth and normal maps for every reference image of the workspace (both passes).

    Resumable per pass: maps that exist with matching provenance are kept unless ``config.overwrite``.
    Images without usable sources or sparse points are skipped with a warning.
    ``config.backend == "ray"`` runs the same passes on a Ray cluster (:mod:`colmap_pvs.stereo.ray`).
    With ``adapt_pseudo_labels`` (self-training) a first run with the base checkpoint writes the maps
    that the adaptation fits; its time is part of ``adapt_seconds``.
    """
    first_round = _pseudo_label_round(config) if config.adapt.pseudo_labels != "none" else 0.0
    if config.backend == "ray":
        result = run_stereo_ray(config)
    else:
        result = run_local(config)
    if first_round > 0:  # the run that made the pseudo-labels is part of the adaptation's cost
        result.adapt_seconds += first_round
        count = len(result.processed) + len(result.already_done) + len(result.skipped)
        result.adapt_seconds_per_image = result.adapt_seconds / max(1, count)
    return result


def _pseudo_label_round(config: StereoConfig) -> float:
    """Self-training's first round: every pass with the base checkpoint, whose maps become the
    adaptation's pseudo-labels. Skipped (0 s) when the adapted weights for them already exist."""
    ws = detect_workspace(config.workspace_path)  # the paths only: the run itself reads the model
    if adapted_exists(config, ws):
        return 0.0
    logger.info("test-time adaptation on %s pseudo-labels: a first run with the base checkpoint",
                config.adapt.pseudo_labels)
    start = time.perf_counter()
    run_stereo(replace_config(config, adapt_steps=0, adapt_pseudo_labels="none"))
    return time.perf_counter() - start
