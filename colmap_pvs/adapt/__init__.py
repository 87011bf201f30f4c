"""Test-time adaptation: the ``stereo`` command's ``--adapt_*`` step, above :mod:`colmap_pvs.stereo`.

``colmap-pvs stereo --adapt_steps K`` runs :func:`run_adapted_stereo` (:mod:`.stereo`): it fine-tunes a
copy of the checkpoint on the workspace's own images (:func:`adapt_checkpoint`, :mod:`.checkpoint`,
through the trainer of :mod:`colmap_pvs.train`), then runs :func:`colmap_pvs.stereo.run_stereo` with
those weights. With ``--adapt_pseudo_labels`` (self-training) a first stereo run with the base checkpoint
writes the maps the adaptation also fits. The stereo package itself never imports this package or the
trainer: it only runs the weights it is given.
"""

from .checkpoint import ADAPT_DIRNAME, AdaptConfig, AdaptResult, adapt_checkpoint, adapted_is_current
from .stereo import adapt_config, pseudo_label_key, run_adapted_stereo

__all__ = [
    "ADAPT_DIRNAME",
    "AdaptConfig",
    "AdaptResult",
    "adapt_checkpoint",
    "adapt_config",
    "adapted_is_current",
    "pseudo_label_key",
    "run_adapted_stereo",
]
