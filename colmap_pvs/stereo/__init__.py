"""The ``stereo`` step: PVSNet depth and normal maps for every image of a COLMAP workspace.

A drop-in replacement for COLMAP's ``patch_match_stereo``, with COLMAP's two passes:

- **photometric** (network): ``stereo/depth_maps/NAME.photometric.bin`` (flat image regions moved
  towards the sparse prior, :mod:`colmap_pvs.prior`), ``stereo/normal_maps/NAME.photometric.bin``,
  ``stereo/confidence_maps/NAME.photometric.bin`` (probability mass of the network times its
  agreement with the sparse prior) and ``stereo/visibility_maps/NAME.bin`` (the network's learned
  per-source visibility, ``[h/4, w/4, S]`` at the network size, sources in the provenance file);
- **geometric** (``geom_consistency``, on by default), once every photometric map exists: each
  reference's photometric depth is checked forward-backward against its sources' photometric maps
  (:mod:`colmap_pvs.consistency`), consulting only the sources the network found visible; pixels that
  fewer than ``geom_min_consistent`` sources confirm (agree with, seen at a triangulation angle of at
  least ``geom_min_triangulation_angle``) are set invalid, the rest are averaged with the confirming
  sources' depths. Writes ``NAME.geometric.bin`` depth, normal and confidence maps, and
  ``stereo/seed_maps/NAME.bin``, the pixels that ``geom_seed_min_consistent`` sources agree with within
  ``geom_seed_depth_error`` (the dense completion's seeds). With ``geom_reestimate`` the depth that
  passes this check first becomes dense hints of a second network run on the reference, and that
  re-estimate is what is checked (COLMAP's geometric PatchMatch re-estimates each reference with its
  sources' photometric maps, too);
- **filled** (``geom_fill``, on by default), once every geometric map exists: a dense completion
  from the seeds of the reference and of its sources (:mod:`colmap_pvs.completion`),
  ``NAME.filled.bin`` depth and confidence maps that COLMAP's fusion never reads;
- **confirm** (with ``geom_fill``), once every completion exists: the completed pixels that other
  references' completions agree with join the geometric maps, so COLMAP's fusion gains them too
  (:mod:`.confirm`; ``stereo/confirm_maps/NAME.bin`` records them).

Every output group has a provenance file ``stereo/provenance/NAME.KIND.json`` (the resolved settings
that affect that pass, the checkpoint's sha256 and, for the geometric pass, the photometric
fingerprints it read). A pass of a reference is *done* when its depth map (written last) is readable
and its provenance matches the current run; anything else is recomputed. ``stereo/fusion.cfg`` lists
the references whose final maps exist, so COLMAP's ``stereo_fusion --input_type geometric`` (or
``photometric`` with ``geom_consistency`` off) runs unchanged.

As in COLMAP, the reference images are those listed in ``stereo/patch-match.cfg`` when it exists
(explicit source lists, ``__auto__, N`` and ``__all__`` are all understood), otherwise every
registered image with sparse points.

One module per pass: :mod:`.photometric`, :mod:`.geometric`, :mod:`.filled` (the completion),
:mod:`.confirm`; their
settings in :mod:`.config` (one nested config per pass), what they share in :mod:`.context` (workspace,
network, image cache), :mod:`.outputs` (provenance, writers) and :mod:`.network`; the backends
in :mod:`.local` and :mod:`.ray`; :func:`run_stereo` (:mod:`.run`) picks one. Each image has one
:class:`~.reference.Reference` per run (:mod:`.reference`, ``StereoContext.reference``: its paths),
through which a pass reads its inputs; it adds its maps and the record that made them
(``Reference.with_pass``) and hands it to its writer (:func:`~.outputs.write_pass`); it times its steps with a
:class:`~.timing.Timer` (:mod:`.timing`), which ``StereoResult.timings`` sums. Python users call
:func:`run_stereo`, or :func:`prepare_stereo` once and then :func:`process_reference` per reference
and pass. The network is the checkpoint's, or other ``weights`` the caller gives: the ``stereo``
command's test-time adaptation (``--adapt_*``) is a step above this package,
:func:`colmap_pvs.adapt.run_adapted_stereo`, and nothing here imports it or the trainer.
"""

from .config import (
    CONFIG_FILENAME,
    DEFAULT_CHECKPOINT,
    AdaptationConfig,
    CompletionConfig,
    GeometricConfig,
    PhotometricConfig,
    RayConfig,
    StereoConfig,
)
from .context import RefOutcome, StereoContext, StereoResult, prepare_stereo
from .local import process_reference
from .run import run_stereo

__all__ = [
    "CONFIG_FILENAME",
    "DEFAULT_CHECKPOINT",
    "AdaptationConfig",
    "CompletionConfig",
    "GeometricConfig",
    "PhotometricConfig",
    "RayConfig",
    "RefOutcome",
    "StereoConfig",
    "StereoContext",
    "StereoResult",
    "prepare_stereo",
    "process_reference",
    "run_stereo",
]
