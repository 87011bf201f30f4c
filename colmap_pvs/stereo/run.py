"""``run_stereo``: the ``stereo`` step, on the local or the Ray backend."""

from __future__ import annotations

from pathlib import Path

from .config import StereoConfig
from .context import StereoResult, check_weights
from .local import run_local
from .ray import run_stereo_ray


def run_stereo(config: StereoConfig, *, weights: Path | None = None) -> StereoResult:
    """Compute depth and normal maps for every reference image of the workspace (both passes).

    Resumable per pass: maps that exist with matching provenance are kept unless ``config.overwrite``.
    Images without usable sources or sparse points are skipped with a warning.
    ``config.backend == "ray"`` runs the same passes on a Ray cluster (:mod:`colmap_pvs.stereo.ray`).

    ``weights``: a checkpoint to run in place of ``config.checkpoint`` (a fine-tuned copy of it): its
    sha256 is in every pass's provenance, the confidence calibration stays ``config.checkpoint``'s.
    ``config.adapt`` (``adapt_steps > 0``) needs them: :func:`colmap_pvs.adapt.run_adapted_stereo` (the
    ``stereo`` command) makes them and calls this function; without them it raises
    :class:`~colmap_pvs.errors.ConfigError`.
    """
    check_weights(config, weights)
    if config.backend == "ray":
        return run_stereo_ray(config, weights)
    return run_local(config, weights)
