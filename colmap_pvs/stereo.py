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
  ``NAME.filled.bin`` depth and confidence maps that COLMAP's fusion never reads.

Every output group has a provenance file ``stereo/provenance/NAME.KIND.json`` (the resolved settings
that affect that pass, the checkpoint's sha256 and, for the geometric pass, the photometric
fingerprints it read). A pass of a reference is *done* when its depth map (written last) is readable
and its provenance matches the current run; anything else is recomputed. ``stereo/fusion.cfg`` lists
the references whose final maps exist, so COLMAP's ``stereo_fusion --input_type geometric`` (or
``photometric`` with ``geom_consistency`` off) runs unchanged.

As in COLMAP, the reference images are those listed in ``stereo/patch-match.cfg`` when it exists
(explicit source lists, ``__auto__, N`` and ``__all__`` are all understood), otherwise every
registered image with sparse points.

Python users (and the Ray backend) use :func:`prepare_stereo` once, then :func:`process_reference`
per reference and pass; :func:`run_stereo` is the local backend.
"""

from __future__ import annotations

import hashlib
import json
import logging
import threading
import time
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from tqdm import tqdm

from .completion import complete_depth, completed_confidence, plane_deviation, segment_planes, splat_depths
from .config import atomic_write_bytes, config_to_dict, replace_config, save_config
from .consistency import SourceMaps, check_consistency
from .errors import CheckpointError, ColmapPVSError, ConfigError, MapFormatError, ShapeError, WorkspaceError
from .evaluate import file_sha256, resize_nearest
from .geometry import sparse_depth_map, to_homogeneous
from .io.cleanup import remove_orphan_temps
from .io.images import load_image, resize_image
from .io.maps import (
    fusion_intrinsics,
    read_array,
    read_depth_map,
    read_normal_map,
    save_depth_preview,
    save_normal_preview,
    save_scalar_preview,
    write_array,
    write_depth_map,
    write_normal_map,
)
from .io.workspace import (
    Workspace,
    detect_workspace,
    load_workspace,
    read_patch_match_cfg,
    write_fusion_cfg,
)
from .model.runtime import check_memory_budget
from .normals import depth_to_normals, fit_normals
from .prior import blend_with_prior, prior_agreement, texture_weight, upsample_prior
from .types import Image, SparseModel
from .upsampling import guided_upsample_depth, resize_area, resize_bilinear, sample_depth_down
from .views import WIDE_SOURCES_HELP, ViewSelection, ViewSelectionConfig, reference_sources, select_views

logger = logging.getLogger(__name__)

DEFAULT_CHECKPOINT = Path(__file__).resolve().parent / "weights" / "pvsnet_default.pt"
CONFIG_FILENAME = "colmap_pvs_stereo.json"
#: Bumped when a pass's output changes for the same settings (part of its provenance fingerprint).
FORMAT_VERSIONS = {"photometric": 3, "geometric": 8, "filled": 3}
Stage = Literal["photometric", "geometric", "filled"]
#: Relative deviation from the local plane at which the geometric confidence falls by ``1 / e``.
GEOM_DEVIATION_SCALE = 0.02
#: Parallax (pixels per ``consistency.PARALLAX_STEP`` of depth) from which an agreeing source counts fully
#: in the geometric confidence; one with less counts in proportion.
GEOM_FULL_PARALLAX = 1.0
#: Confidence of a geometric pixel that the sources' seeds give (``geom_splat_min_sources``), times the
#: share of the checked sources that agree on it: below most checked pixels, which are more often right.
SPLAT_CONFIDENCE = 0.1

#: :class:`StereoConfig` fields that override the checkpoint's :class:`~colmap_pvs.model.PVSNetConfig`
#: field of the same name ("on" / "off"; "checkpoint" keeps it). Each must be one of
#: :data:`colmap_pvs.model.PARAMETER_FREE_FIELDS` (pinned by a test): flipping it keeps the weights valid.
MODEL_SWITCHES = ("sparse_guidance", "sparse_prior")

#: Settings that change the photometric maps (with the checkpoint's sha256 and the sources).
PHOTOMETRIC_SETTINGS = (
    "num_views", "max_image_size", "network_scale", "network_min_size", "min_confidence", "sparse_guidance",
    "sparse_prior", "prior_blend_texture", "prior_blend_window", "prior_agreement_scale",
)
#: Settings that change the geometric maps (with the photometric fingerprints they read).
GEOMETRIC_SETTINGS = (
    "geom_min_consistent",
    "geom_max_reproj_error",
    "geom_max_depth_error",
    "geom_max_normal_error",
    "geom_min_visibility",
    "geom_min_triangulation_angle",
    "geom_num_sources",
    "geom_average_depth",
    "geom_min_confidence",
    "geom_reestimate",
    "geom_seed_min_consistent",
    "geom_seed_depth_error",
    "geom_splat_min_sources",
)
#: Settings that change the geometric maps but not the seeds (their own fingerprint omits them).
GEOMETRIC_ONLY_SETTINGS = ("geom_splat_min_sources",)
#: Seed maps computed on demand (for other references' geometric passes) kept in memory per run.
SEED_CACHE_SIZE = 32

#: Largest ``network_scale``: the network on twice the map's size (about 4x its time and memory).
NETWORK_SCALE_MAX = 2.0
#: Settings that change the dense completion (with the geometric fingerprints it reads).
FILLED_SETTINGS = (
    "geom_fill_min_sources",
    "geom_fill_segments",
    "geom_fill_segment_min_pixels",
    "geom_fill_segment_inliers",
)


@dataclass(frozen=True)
class StereoConfig:
    """Settings of the ``stereo`` step (the single source of its defaults and CLI flags)."""

    workspace_path: Path = field(metadata={"help": "COLMAP dense workspace (images/, sparse/, stereo/)"})
    num_views: int = field(default=5, metadata={"help": "views per reference: reference + N-1 sources"})
    wide_sources: int = field(default=0, metadata={"help": WIDE_SOURCES_HELP})
    max_image_size: int = field(
        default=640, metadata={"help": "longest image side for inference; <= 0 keeps full size"}
    )
    network_scale: float = field(
        default=0.8,
        metadata={
            "help": "run the network at this multiple of the map size (0.25-2) and bring its depth "
            "back to the map size: image-guided upsampling below 1, nearest sampling above 1 (the "
            "image is read at that size from its original, so up to its full resolution with real "
            "detail: thin structures, at about scale^2 the time and memory); maps keep max_image_size"
        },
    )
    network_min_size: int = field(
        default=400,
        metadata={
            "help": "network_scale never takes the network's longest side below this (px), nor below "
            "the map's: small images keep their detail"
        },
    )
    checkpoint: Path | None = field(
        default=None, metadata={"help": "model checkpoint (.pt); default: the shipped checkpoint"}
    )
    device: Literal["auto", "cpu", "cuda"] = field(default="auto", metadata={"help": "torch device"})
    overwrite: bool = field(default=False, metadata={"help": "recompute images whose maps already exist"})
    min_confidence: float = field(
        default=0.0,
        metadata={
            "help": "photometric pass: pixels with confidence (the network's probability mass times its "
            "agreement with the sparse prior, see prior_agreement_scale) below this are set invalid; "
            "0 keeps the maps dense and leaves the filtering to the geometric pass"
        },
    )
    sparse_guidance: Literal["checkpoint", "on", "off"] = field(
        default="checkpoint",
        metadata={"help": "modulate the cost volume around projected sparse points (Guided Stereo)"},
    )
    sparse_prior: Literal["checkpoint", "on", "off"] = field(
        default="checkpoint",
        metadata={
            "help": "centre the coarse depth hypotheses on the interpolated sparse points "
            "(off: the image's global depth range everywhere)"
        },
    )
    prior_blend_texture: float = field(
        default=0.01,
        metadata={
            "help": "photometric pass: where the image's grey-level standard deviation (0-1 scale, over "
            "prior_blend_window pixels) is below this, the depth moves towards the sparse prior in log "
            "depth, all the way where the image is flat (0 = off)"
        },
    )
    prior_blend_window: int = field(
        default=7, metadata={"help": "photometric pass: window (map pixels, odd) of prior_blend_texture"}
    )
    prior_agreement_scale: float = field(
        default=0.05,
        metadata={
            "help": "photometric pass: the confidence is multiplied by exp(-|log(d / prior)| / this), "
            "the network's agreement with the sparse prior (0 = the network's probability mass alone)"
        },
    )
    previews: bool = field(
        default=False, metadata={"help": "write PNG previews of depth, normals, confidence, visibility"}
    )
    threads: int = field(default=0, metadata={"help": "torch CPU threads; 0 keeps torch's default"})
    min_sources: int = field(default=1, metadata={"help": "skip references with fewer sources"})
    adapt_steps: int = field(
        default=0,
        metadata={
            "help": "test-time adaptation: fine-tune a copy of the network for this many steps on the "
            "workspace's own images (self-supervised) before inference; 0 = off"
        },
    )
    adapt_max_seconds: float = field(
        default=0.0, metadata={"help": "test-time adaptation: time limit in seconds (0 = none)"}
    )
    adapt_lr: float = field(default=1e-4, metadata={"help": "test-time adaptation: learning rate"})
    adapt_seed: int = field(default=0, metadata={"help": "test-time adaptation: seed"})
    adapt_pseudo_labels: Literal["none", "geometric", "filled"] = field(
        default="none",
        metadata={
            "help": "test-time adaptation: also fit the workspace's own maps of this kind as dense "
            "pseudo-labels (self-training): stereo first runs with the base checkpoint, adapts on its "
            "'geometric' or 'filled' maps, then runs again with the adapted weights; 'none': off"
        },
    )
    # Scale-out (colmap_pvs.distributed; README "Scale out on Ray").
    backend: Literal["local", "ray"] = field(
        default="local", metadata={"help": "local: this process; ray: one task per image on a Ray cluster"}
    )
    ray_address: str = field(
        default="", metadata={"help": "ray: empty starts a local Ray; 'auto' or HOST:PORT joins a cluster"}
    )
    ray_workers: int = field(default=0, metadata={"help": "ray: worker actors; 0: fill the CPUs"})
    ray_worker_threads: int = field(default=1, metadata={"help": "ray: torch threads (and CPUs) per worker"})
    ray_worker_memory: float = field(
        default=0.0, metadata={"help": "ray: GiB of memory Ray reserves per worker when placing it; 0: none"}
    )
    ray_max_retries: int = field(
        default=3, metadata={"help": "ray: times a reference is retried after its worker died"}
    )
    ray_task_timeout: float = field(
        default=0.0, metadata={"help": "ray: seconds after which a reference's worker is killed and the "
                               "reference retried; 0: no limit"}
    )
    geom_consistency: bool = field(
        default=True,
        metadata={"help": "run the geometric pass (writes *.geometric.bin); off: photometric maps only "
                  "(COLMAP's PatchMatchStereo.geom_consistency)"},
    )
    geom_min_consistent: int = field(
        default=2, metadata={"help": "geometric pass: a pixel must agree with at least this many sources"}
    )
    geom_max_reproj_error: float = field(
        default=2.0, metadata={"help": "geometric pass: max forward-backward reprojection error (px)"}
    )
    geom_max_depth_error: float = field(
        default=0.03, metadata={"help": "geometric pass: max relative depth error |z'-d|/d"}
    )
    geom_max_normal_error: float = field(
        default=180.0, metadata={"help": "geometric pass: max normal angle (degrees; >= 180 disables)"}
    )
    geom_min_visibility: float = field(
        default=0.2,
        metadata={"help": "geometric pass: consult a source only where its learned visibility >= this"},
    )
    geom_min_triangulation_angle: float = field(
        default=3.0,
        metadata={
            "help": "geometric pass: a source confirms a pixel only where the rays from its centre and "
            "the reference's meet at the pixel's point at this angle (degrees) or more (COLMAP's "
            "filter_min_triangulation_angle; 0: any)"
        },
    )
    geom_num_sources: int = field(
        default=10,
        metadata={
            "help": "geometric pass: check against up to this many sources with photometric maps: the "
            "network's sources, then the next best by view score (0: the network's sources only; a "
            "network source that is not a candidate view of the reference takes no slot)"
        },
    )
    geom_average_depth: bool = field(
        default=True,
        metadata={"help": "geometric pass: average the depth with the agreeing sources' reprojected depths"},
    )
    geom_min_confidence: float = field(
        default=0.0,
        metadata={"help": "geometric pass: pixels with geometric confidence below this are invalid"},
    )
    geom_reestimate: bool = field(
        default=False,
        metadata={
            "help": "geometric pass: run the network again on each reference with the depth its sources' "
            "photometric maps agree on as dense hints, then check that re-estimate (more pixels kept, "
            "one more network run per image)"
        },
    )
    geom_seed_min_consistent: int = field(
        default=3,
        metadata={
            "help": "geometric pass: a pixel seeds the dense completion (stereo/seed_maps/NAME.bin) where "
            "at least this many sources agree with it within geom_seed_depth_error (at any angle) and "
            "enough of its neighbours do for a normal; the completion keeps only the seeds as they are"
        },
    )
    geom_seed_depth_error: float = field(
        default=0.025,
        metadata={"help": "geometric pass: max relative depth error of the sources that make a seed "
                  "(see geom_seed_min_consistent)"},
    )
    geom_splat_min_sources: int = field(
        default=3,
        metadata={
            "help": "geometric pass: a pixel the check drops is kept with its sources' confirmed depth "
            "where at least this many of the checked sources' seed maps, projected into it, agree "
            "within 3 % (their median; 0: off)"
        },
    )
    geom_fill: bool = field(
        default=True,
        metadata={
            "help": "third pass, after the geometric one: a dense completion of each geometric map, "
            "NAME.filled.bin in stereo/depth_maps and stereo/confidence_maps: dropped pixels from the "
            "sources' kept pixels, then a local plane fit (COLMAP's fusion never reads it)"
        },
    )
    geom_fill_min_sources: int = field(
        default=2,
        metadata={"help": "dense completion: sources whose kept depths must agree to give a dropped pixel"},
    )
    geom_fill_segments: bool = field(
        default=True,
        metadata={
            "help": "dense completion: a dropped pixel takes the robust plane of the known pixels of its "
            "image segment (the region between image edges) where that plane fits them"
        },
    )
    geom_fill_segment_min_pixels: int = field(
        default=30, metadata={"help": "dense completion: known pixels a segment needs to give its plane"}
    )
    geom_fill_segment_inliers: float = field(
        default=0.6,
        metadata={"help": "dense completion: least fraction of a segment's known pixels within 3 % of its "
                  "plane for the segment to give it"},
    )

    def __post_init__(self) -> None:  # bad values are refused where they enter (issue 11)
        from .config import check_int_fields, check_range

        check_int_fields(self)
        check_range("num_views", self.num_views, low=2)
        check_range("geom_fill_min_sources", self.geom_fill_min_sources, low=1)
        check_range("geom_fill_segment_min_pixels", self.geom_fill_segment_min_pixels, low=3)
        check_range("geom_fill_segment_inliers", self.geom_fill_segment_inliers, low=0.0, high=1.0)
        check_range("geom_seed_min_consistent", self.geom_seed_min_consistent, low=1)
        check_range("geom_splat_min_sources", self.geom_splat_min_sources, low=0)
        check_range("min_confidence", self.min_confidence, low=0.0, high=1.0)
        check_range("prior_blend_texture", self.prior_blend_texture, low=0.0, high=1.0)
        check_range("prior_agreement_scale", self.prior_agreement_scale, low=0.0)
        if self.prior_blend_window < 1 or self.prior_blend_window % 2 == 0:
            raise ConfigError(f"prior_blend_window must be an odd number >= 1, got {self.prior_blend_window}")
        check_range("network_scale", self.network_scale, low=0.25, high=NETWORK_SCALE_MAX)
        check_range("network_min_size", self.network_min_size, low=16)
        check_range("threads", self.threads, low=0)
        check_range("min_sources", self.min_sources, low=1)
        check_range("adapt_steps", self.adapt_steps, low=0)
        check_range("adapt_max_seconds", self.adapt_max_seconds, low=0.0)
        if self.adapt_pseudo_labels != "none":
            if self.adapt_steps == 0:
                raise ConfigError(
                    f"adapt_pseudo_labels={self.adapt_pseudo_labels!r} needs adapt_steps > 0 (got 0)"
                )
            if not self.geom_consistency or (self.adapt_pseudo_labels == "filled" and not self.geom_fill):
                raise ConfigError(
                    f"adapt_pseudo_labels={self.adapt_pseudo_labels!r} needs the pass that writes those "
                    f"maps: geom_consistency={self.geom_consistency}, geom_fill={self.geom_fill}"
                )
        check_range("geom_min_visibility", self.geom_min_visibility, low=0.0, high=1.0)
        check_range("geom_min_triangulation_angle", self.geom_min_triangulation_angle, low=0.0, high=90.0)
        check_range("geom_num_sources", self.geom_num_sources, low=0)
        for name, low in (("ray_workers", 0), ("ray_worker_threads", 1), ("ray_worker_memory", 0.0),
                          ("ray_max_retries", 0), ("ray_task_timeout", 0.0)):
            check_range(name, getattr(self, name), low=low)
        if 0 < self.max_image_size < 16:
            raise ConfigError(f"max_image_size must be <= 0 (full size) or >= 16, got {self.max_image_size}")
        if self.geom_min_consistent < 1:
            raise ConfigError(f"geom_min_consistent must be >= 1, got {self.geom_min_consistent}")
        for name in ("geom_max_reproj_error", "geom_max_depth_error", "geom_max_normal_error",
                     "geom_seed_depth_error"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)}")


@dataclass
class RefOutcome:
    """What :func:`process_reference` did for one reference and pass."""

    name: str
    stage: Stage
    status: Literal["computed", "done", "skipped"]
    reason: str = ""
    seconds: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class StereoResult:
    """What :func:`run_stereo` did: processed, skipped (with reasons) and timing.

    ``processed`` / ``already_done`` are the photometric pass's, ``geometric_processed`` /
    ``geometric_done`` the geometric pass's, ``filled_processed`` / ``filled_done`` / ``filled_skipped``
    the dense completion's (``geom_fill``); ``timings`` sums seconds per stage over the passes;
    ``pass_seconds`` is the wall time of each pass; ``seconds_per_image`` is the whole run's wall time
    per computed reference. ``auxiliary`` lists the sources that are no reference (``patch-match.cfg``
    lists a subset) and got photometric maps for the geometric pass.
    """

    workspace: Workspace
    processed: list[str] = field(default_factory=list)
    already_done: list[str] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)
    sources: dict[str, list[str]] = field(default_factory=dict)
    seconds_per_image: float = 0.0
    geometric_processed: list[str] = field(default_factory=list)
    geometric_done: list[str] = field(default_factory=list)
    geometric_skipped: dict[str, str] = field(default_factory=dict)
    filled_processed: list[str] = field(default_factory=list)
    filled_done: list[str] = field(default_factory=list)
    filled_skipped: dict[str, str] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    pass_seconds: dict[str, float] = field(default_factory=dict)
    auxiliary: list[str] = field(default_factory=list)
    adapt_seconds: float = 0.0
    adapt_seconds_per_image: float = 0.0


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA when available."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ColmapPVSError("--device cuda was requested but torch.cuda.is_available() is False")
    return torch.device(name)


def base_checkpoint_path(config: StereoConfig) -> Path:
    """The checkpoint a run starts from (``config.checkpoint``, else the shipped default)."""
    return Path(config.checkpoint) if config.checkpoint is not None else DEFAULT_CHECKPOINT


def load_stereo_model(config: StereoConfig, device: torch.device):
    """Load the checkpoint (``weights_only=True``) and apply the config's overrides."""
    from .model import PVSNet, load_checkpoint

    path = base_checkpoint_path(config)
    if config.checkpoint is None and not path.exists():
        raise CheckpointError(
            f"no trained default checkpoint is shipped at {str(path)!r}; pass --checkpoint PATH "
            "(random weights never produce maps)"
        )
    model, meta = load_checkpoint(path, map_location="cpu")
    # Switches that add no parameters can be flipped on a trained model.
    requested = {name: getattr(config, name) for name in MODEL_SWITCHES}
    changes = {
        name: value == "on"
        for name, value in requested.items()
        if value != "checkpoint" and getattr(model.config, name) != (value == "on")
    }
    if changes:
        state = model.state_dict()
        model = PVSNet(replace_config(model.config, **changes))
        model.load_state_dict(state)
    model.eval().to(device)
    return model, path, meta


def adapt_config(config: StereoConfig):
    """The :class:`~colmap_pvs.adapt.AdaptConfig` of a stereo run's ``adapt_*`` settings."""
    from .adapt import AdaptConfig

    return AdaptConfig(
        steps=config.adapt_steps,
        max_seconds=config.adapt_max_seconds,
        lr=config.adapt_lr,
        seed=config.adapt_seed,
        num_views=config.num_views,
        threads=config.threads,
        pseudo_labels=config.adapt_pseudo_labels,
    )


def pseudo_label_key(config: StereoConfig, ws: Workspace) -> dict | None:
    """What the pseudo-labels of self-training are made with (``None`` without them).

    The settings of the passes up to ``adapt_pseudo_labels``, their format versions and the
    ``patch-match.cfg`` content, hashed: any change among them makes :func:`run_stereo` adapt again.
    """
    kind = config.adapt_pseudo_labels
    if kind == "none":
        return None
    keys = PHOTOMETRIC_SETTINGS + ("wide_sources",) + GEOMETRIC_SETTINGS
    keys += FILLED_SETTINGS if kind == "filled" else ()
    cfg = config_to_dict(config)
    settings = {k: cfg[k] for k in keys}
    settings["format_versions"] = {k: FORMAT_VERSIONS[k] for k in ("photometric", "geometric", kind)}
    if ws.patch_match_cfg.is_file():
        settings["patch_match_cfg_sha256"] = file_sha256(ws.patch_match_cfg)
    text = json.dumps(settings, sort_keys=True, default=str).encode()
    return {"kind": kind, "settings_sha256": hashlib.sha256(text).hexdigest()}


def _adapt(config: StereoConfig, ws: Workspace, base: Path, device: torch.device):
    """Test-time adaptation of ``base`` on the workspace; returns ``(net, adapted path, seconds)``."""
    from .adapt import adapt_checkpoint

    done = adapt_checkpoint(ws.root, ws.stereo_dir, base, adapt_config(config),
                            labels=pseudo_label_key(config, ws))
    net, path, _ = load_stereo_model(replace_config(config, checkpoint=done.checkpoint), device)
    logger.info(
        "test-time adaptation: %d steps, %.1f s (%s)", done.steps, done.seconds,
        "reused" if done.reused else "computed",
    )
    return net, path, done.seconds


def choose_references(ws: Workspace, model: SparseModel) -> dict[str, object]:
    """Reference names mapped to their source spec (``None``: automatic selection)."""
    if ws.patch_match_cfg.exists():
        specs = read_patch_match_cfg(ws.patch_match_cfg)
        for name in specs:
            if name not in model.image_ids_by_name:
                raise WorkspaceError(
                    f"{ws.patch_match_cfg}: reference image {name!r} is not in the sparse model"
                )
        return dict(specs)
    return {img.name: None for img in sorted(model.images.values(), key=lambda im: im.name)}


def _sparse_depth_map(
    model: SparseModel,
    image: Image,
    K: np.ndarray,
    height: int,
    width: int,
    id_order: np.ndarray | None = None,
) -> np.ndarray:
    """``[H, W]`` depth of the image's own sparse points projected with ``K`` (0 elsewhere).

    ``id_order`` is ``np.argsort(model.points.ids)``; pass it to avoid re-sorting per image.
    """
    if image.point3D_ids.size == 0:
        return np.zeros((height, width), dtype=np.float32)
    ids = model.points.ids
    order = np.argsort(ids, kind="stable") if id_order is None else id_order
    pos = np.searchsorted(ids, image.point3D_ids, sorter=order).clip(max=len(ids) - 1)
    rows = order[pos]
    rows = rows[ids[rows] == image.point3D_ids]
    return sparse_depth_map(model.points.xyz[rows], K, image.cam_from_world, height, width)


#: Sparse hints farther than this factor outside the image's depth range are outliers.
HINT_OUTLIER_FACTOR = 2.0


def drop_outlier_hints(sparse: np.ndarray, depth_range: tuple[float, float]) -> np.ndarray:
    """Zero the hints of ``sparse`` ``[H, W]`` (in place) that are depth outliers.

    A hint is an outlier when ``z < dmin / f`` or ``z > dmax * f`` with ``f`` =
    :data:`HINT_OUTLIER_FACTOR` (the range already carries COLMAP's 25 % stretch). Hints just outside
    the range are real surfaces more often than not (the range is the 1st-99th percentile, and near
    walls in indoor video lie below it): dropping every hint outside it raised hololens-dev MAE from
    212 to 219 mm.
    """
    f = HINT_OUTLIER_FACTOR
    sparse[(sparse < depth_range[0] / f) | (sparse > depth_range[1] * f)] = 0.0
    return sparse


# --------------------------------------------------------------------------- image cache


class ImageCache:
    """Decoded, resized ``[3, H, W]`` float32 images shared across references (thread-safe LRU).

    Each image is a source of several references; it is decoded and resized once per size. Entries
    are futures, so a prefetch in a background thread and a later request share one load.
    """

    def __init__(self, ws: Workspace, model: SparseModel, capacity: int = 16) -> None:
        self.ws, self.model, self.capacity = ws, model, capacity
        self._items: OrderedDict[tuple, Future] = OrderedDict()
        self._lock = threading.Lock()

    def _load(self, name: str, max_image_size: int, size: tuple[int, int] | None) -> np.ndarray:
        im = self.model.image_by_name(name)
        cam = self.model.camera_of(im)
        pix = load_image(self.ws.images_dir / name)
        if pix.shape[0] != cam.height or pix.shape[1] != cam.width:
            raise WorkspaceError(
                f"image {name!r} is {pix.shape[1]}x{pix.shape[0]} but its camera {cam.camera_id} says "
                f"{cam.width}x{cam.height}"
            )
        if size is None:
            small, _, _ = resize_image(pix, max_image_size)
        else:
            import cv2

            shrink = size[0] <= pix.shape[1] and size[1] <= pix.shape[0]
            small = pix if (pix.shape[1], pix.shape[0]) == size else cv2.resize(
                pix, size, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
            )
        return np.ascontiguousarray(small.transpose(2, 0, 1), dtype=np.float32) * np.float32(1.0 / 255.0)

    def future(self, name: str, max_image_size: int, size: tuple[int, int] | None = None,
               executor: ThreadPoolExecutor | None = None) -> Future:
        """The image at its own inference size (``size=None``) or resized to ``size = (W, H)``."""
        key = (name, max_image_size, size)
        with self._lock:
            fut = self._items.get(key)
            if fut is not None:
                self._items.move_to_end(key)
                return fut
            fut = Future()
            self._items[key] = fut
            while len(self._items) > self.capacity:
                self._items.popitem(last=False)

        def work() -> None:
            try:
                fut.set_result(self._load(name, max_image_size, size))
            except BaseException as exc:  # re-raised by .result() in the caller
                fut.set_exception(exc)
                with self._lock:
                    self._items.pop(key, None)

        if executor is None:
            work()
        else:
            executor.submit(work)
        return fut

    def get(self, name: str, max_image_size: int, size: tuple[int, int] | None = None) -> np.ndarray:
        return self.future(name, max_image_size, size).result()


# --------------------------------------------------------------------------- context


@dataclass
class StereoContext:
    """Everything loaded once per run (or once per Ray worker): see :func:`prepare_stereo`."""

    config: StereoConfig
    workspace: Workspace
    sparse: SparseModel
    net: torch.nn.Module
    checkpoint_path: Path
    checkpoint_sha256: str
    device: torch.device
    selection: ViewSelection
    references: dict[str, object]
    id_order: np.ndarray
    images: ImageCache
    adapt_seconds: float = 0.0
    loader: ThreadPoolExecutor | None = None
    writer: ThreadPoolExecutor | None = None
    pending_writes: list[Future] = field(default_factory=list)
    seed_cache: OrderedDict = field(default_factory=OrderedDict)  # name -> (fingerprint, Checked)

    def sources_of(self, name: str) -> tuple[list[str] | None, str]:
        """The sources of reference ``name``, or ``(None, reason)`` when it must be skipped."""
        entry = self.selection.references.get(name)
        if entry is None:
            reason = next((sk.reason for sk in self.selection.skipped if sk.name == name), "not selectable")
            return None, reason
        sources = list(reference_sources(self.selection, name, self.references.get(name),
                                         self.config.num_views - 1))
        if len(sources) < self.config.min_sources:
            return None, (f"only {len(sources)} source view(s) share points with it "
                          f"(need {self.config.min_sources})")
        return sources, ""

    def map_size(self, name: str) -> tuple[int, int]:
        """``(W, H)`` of ``name``'s maps at this run's ``max_image_size``."""
        cam = self.sparse.camera_of(self.sparse.image_by_name(name))
        longest = max(cam.width, cam.height)
        m = self.config.max_image_size
        if m <= 0 or longest <= m:
            return cam.width, cam.height
        s = m / longest
        return (max(1, min(m, int(np.floor(cam.width * s + 0.5)))),
                max(1, min(m, int(np.floor(cam.height * s + 0.5)))))

    def network_size(self, name: str) -> tuple[int, int]:
        """``(W, H)`` the network runs at for ``name``: ``network_scale`` times its map size, its
        longest side not below ``min(network_min_size, the map's)``."""
        w, h = self.map_size(name)
        s = max(self.config.network_scale, min(1.0, self.config.network_min_size / max(w, h)))
        if s == 1.0:
            return w, h
        return max(16, int(np.floor(w * s + 0.5))), max(16, int(np.floor(h * s + 0.5)))

    def map_K(self, name: str, size: tuple[int, int]) -> np.ndarray:
        cam = self.sparse.camera_of(self.sparse.image_by_name(name))
        return fusion_intrinsics(cam.K, (cam.width, cam.height), size)

    def prefetch(self, name: str) -> None:
        """Start decoding ``name``'s reference and source images in the loader thread."""
        if self.loader is None:
            return
        sources, _ = self.sources_of(name)
        if sources is None:
            return
        size = self.network_size(name)
        for n in [name, *sources]:
            self.images.future(n, self.config.max_image_size, size, executor=self.loader)
        if size != self.map_size(name):  # the upsampling's guide
            self.images.future(name, self.config.max_image_size, self.map_size(name), executor=self.loader)

    def submit_write(self, fn, *args) -> None:
        """Run a write job in the writer thread (synchronously when there is none)."""
        if self.writer is None:
            fn(*args)
        else:
            self.pending_writes.append(self.writer.submit(fn, *args))

    def flush(self) -> None:
        """Wait for every pending write; re-raises the first failure."""
        pending, self.pending_writes = self.pending_writes, []
        for fut in pending:
            fut.result()

    def close(self) -> None:
        try:
            self.flush()
        finally:
            for ex in (self.loader, self.writer):
                if ex is not None:
                    ex.shutdown(wait=True)
            self.loader = self.writer = None


def prepare_stereo(config: StereoConfig, *, background_io: bool = False) -> StereoContext:
    """Load the workspace, the network and the view selection once.

    ``background_io``: decode the next references' images and write finished maps in two background
    threads (:meth:`StereoContext.prefetch`, :meth:`StereoContext.flush`); call
    :meth:`StereoContext.close` at the end.
    """
    ws, model_sparse = load_workspace(config.workspace_path)
    device = resolve_device(config.device)
    if config.threads > 0:
        torch.set_num_threads(config.threads)
    net, ckpt_path, _meta = load_stereo_model(config, device)
    adapt_seconds = 0.0
    if config.adapt_steps > 0:  # test-time adaptation: the adapted checkpoint's sha enters provenance
        net, ckpt_path, adapt_seconds = _adapt(config, ws, ckpt_path, device)
    selection: ViewSelection = select_views(
        model_sparse, ViewSelectionConfig(num_views=config.num_views, wide_sources=config.wide_sources)
    )
    refs = choose_references(ws, model_sparse)
    return StereoContext(
        config=config,
        workspace=ws,
        sparse=model_sparse,
        net=net,
        checkpoint_path=ckpt_path,
        checkpoint_sha256=file_sha256(ckpt_path),
        device=device,
        selection=selection,
        references=refs,
        id_order=np.argsort(model_sparse.points.ids, kind="stable"),
        images=ImageCache(ws, model_sparse, capacity=max(16, 3 * config.num_views)),
        adapt_seconds=adapt_seconds,
        loader=ThreadPoolExecutor(1, thread_name_prefix="stereo-load") if background_io else None,
        writer=ThreadPoolExecutor(1, thread_name_prefix="stereo-write") if background_io else None,
    )


# --------------------------------------------------------------------------- provenance


def provenance_path(ws: Workspace, name: str, stage: Stage) -> Path:
    """``stereo/provenance/NAME.STAGE.json``: what produced that pass's maps of ``name``."""
    ws.depth_map_path(name, stage)  # validates name and stage
    return ws.stereo_dir / "provenance" / f"{name}.{stage}.json"


def seed_map_path(ws: Workspace, name: str) -> Path:
    """``stereo/seed_maps/NAME.bin``: the depth of the pixels of ``name`` that seed its dense completion
    (at least ``geom_seed_min_consistent`` sources agree within ``geom_seed_depth_error``), 0 elsewhere."""
    ws.depth_map_path(name, "geometric")  # validates name
    return ws.stereo_dir / "seed_maps" / f"{name}.bin"


def _geometric_files_exist(ws: Workspace, name: str) -> bool:
    """The geometric pass of ``name`` left its depth map and its seed map (the completion reads both)."""
    return ws.depth_map_path(name, "geometric").is_file() and seed_map_path(ws, name).is_file()


def _fingerprint(settings: dict) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()


def _settings(ctx: StereoContext, stage: Stage, keys: tuple[str, ...]) -> dict:
    cfg = config_to_dict(ctx.config)
    out = {k: cfg[k] for k in keys}
    out.update(stage=stage, format_version=FORMAT_VERSIONS[stage])
    return out


def photometric_settings(ctx: StereoContext, name: str, sources: list[str]) -> dict:
    """The resolved settings that determine ``name``'s photometric maps."""
    s = _settings(ctx, "photometric", PHOTOMETRIC_SETTINGS)
    entry = ctx.selection.references[name]
    s.update(checkpoint_sha256=ctx.checkpoint_sha256, sources=list(sources),
             depth_range=[float(entry.depth_range[0]), float(entry.depth_range[1])],
             model_config=config_to_dict(ctx.net.config))
    return s


def read_provenance(ws: Workspace, name: str, stage: Stage) -> dict | None:
    path = provenance_path(ws, name, stage)
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _is_current(ws: Workspace, name: str, stage: Stage, fingerprint: str, size: tuple[int, int]) -> bool:
    """The pass's depth map is readable, has the expected size and its provenance matches."""
    prov = read_provenance(ws, name, stage)
    if prov is None or prov.get("fingerprint") != fingerprint:
        return False
    try:
        depth = read_depth_map(ws.depth_map_path(name, stage))
    except (OSError, MapFormatError):
        return False
    return depth.shape == (size[1], size[0])


def _write_provenance(ws: Workspace, name: str, stage: Stage, settings: dict, extra: dict) -> None:
    payload = {"fingerprint": _fingerprint(settings), "settings": settings, **extra}
    atomic_write_bytes(provenance_path(ws, name, stage), (json.dumps(payload, indent=1) + "\n").encode())


# --------------------------------------------------------------------------- photometric pass


def estimate_depth(model, images, intrinsics, poses, depth_range, sparse_depth, device):
    """Run the network on one reference.

    Args:
        images: ``[N, 3, H, W]`` float32 in ``[0, 1]``, reference at index 0.
        intrinsics: ``[N, 3, 3]``; poses: ``[N, 4, 4]`` cam_from_world.
        depth_range: ``(d_min, d_max)``; sparse_depth: ``[H, W]`` (0 = no point).

    Returns:
        depth ``[H, W]``, confidence ``[H, W]``, coarse visibility ``[N-1, ceil(H/4), ceil(W/4)]`` and
        the sparse prior's coarse depth ``[ceil(H/4), ceil(W/4)]`` (``None`` without one), numpy.
    """
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32), device=device)[None]  # noqa: E731
    with torch.inference_mode():
        out = model(
            t(images),
            t(intrinsics),
            t(poses),
            t(depth_range[0]),
            t(depth_range[1]),
            sparse_depth=t(sparse_depth)[:, None],
        )
    vis = out.visibility[0].float().cpu().numpy()
    prior = None if out.prior_depth is None else out.prior_depth[0].float().cpu().numpy()
    return out.depth[0].cpu().numpy(), out.confidence[0].cpu().numpy(), vis, prior


def _write_pass(ws: Workspace, name: str, stage: Stage, depth, normals, conf, settings, extra, previews,
                depth_range, timings, vis=None, sources=(), seeds=None, seed_fingerprint=None) -> None:
    """Write one pass's maps (an old depth removed first, the new one last: it marks the pass done),
    then its previews.

    ``vis`` ``[S, h, w]`` (photometric pass only) goes to ``stereo/visibility_maps/NAME.bin``,
    ``seeds`` ``[h, w]`` (geometric pass only) to :func:`seed_map_path`. Preview
    names: ``NAME.photometric.*.png`` for the first pass, ``NAME.*.png`` for the geometric one.
    """
    t0 = time.perf_counter()
    # The old depth goes first: new provenance beside an old depth would look done after a crash.
    ws.depth_map_path(name, stage).unlink(missing_ok=True)
    write_array(ws.confidence_map_path(name, stage), conf.astype(np.float32))
    if vis is not None:
        write_array(ws.stereo_dir / "visibility_maps" / f"{name}.bin",
                    np.ascontiguousarray(vis.transpose(1, 2, 0)) if vis.shape[0] else np.zeros((1, 1, 1)))
    if seeds is not None:
        _write_seeds(ws, name, seeds, seed_fingerprint)
    write_normal_map(ws.normal_map_path(name, stage), normals)
    _write_provenance(ws, name, stage, settings, extra)
    write_depth_map(ws.depth_map_path(name, stage), depth)  # last: marks the pass done
    timings["writes"] = time.perf_counter() - t0
    if previews:
        t0 = time.perf_counter()
        out = ws.stereo_dir / "previews"
        stem = out / (f"{name}.photometric" if stage == "photometric" else name)
        save_depth_preview(f"{stem}.depth.png", depth, vmin=depth_range[0], vmax=depth_range[1])
        save_normal_preview(f"{stem}.normal.png", normals)
        save_scalar_preview(f"{stem}.confidence.png", conf)
        for k, src in enumerate(sources):
            save_scalar_preview(out / f"{name}.visibility.{k:02d}.{Path(src).stem}.png", vis[k])
        timings["previews"] = time.perf_counter() - t0


@dataclass
class NetworkMaps:
    """One network run on a reference, at the map size ``[H, W]``: ``depth`` (0 = invalid),
    ``normals`` ``[H, W, 3]``, ``confidence`` and the coarse learned visibility ``[S, h/4, w/4]``."""

    depth: np.ndarray
    normals: np.ndarray
    confidence: np.ndarray
    visibility: np.ndarray


def _network_maps(ctx: StereoContext, name: str, sources: list[str], timings: dict[str, float],
                  dense_hints: np.ndarray | None = None) -> NetworkMaps | str:
    """The network's maps of ``name`` with ``sources`` (its photometric pass), or the reason it could
    not run (out of memory).

    ``dense_hints`` ``[H, W]`` (map size, 0 = none): depths that replace the SfM hints where they are
    set (the geometric pass's re-estimation, ``geom_reestimate``); SfM hints stay elsewhere.
    """
    cfg = ctx.config
    size = ctx.map_size(name)
    t0 = time.perf_counter()
    names = [name, *sources]
    net_size = ctx.network_size(name)
    futures = [ctx.images.future(n, cfg.max_image_size, net_size) for n in names]
    images = np.stack([f.result() for f in futures])
    guide = ctx.images.get(name, cfg.max_image_size, size) if net_size != size else None
    Ks = np.stack([ctx.map_K(n, net_size) for n in names])
    # COLMAP's fusion reads map pixel (col, row) along K_s^-1 [col, row, 1]; see CONVENTIONS.md.
    poses = np.stack([to_homogeneous(ctx.sparse.image_by_name(n).cam_from_world) for n in names])
    timings["load"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    w, h = net_size
    ref = ctx.sparse.image_by_name(name)
    sparse = _sparse_depth_map(ctx.sparse, ref, Ks[0], h, w, ctx.id_order)
    entry = ctx.selection.references[name]
    drop_outlier_hints(sparse, entry.depth_range)
    if dense_hints is not None:
        if dense_hints.shape != (size[1], size[0]):
            raise ShapeError(
                f"dense_hints of {name!r} must be [{size[1]}, {size[0]}], got {dense_hints.shape}"
            )
        if net_size != size:  # nearest: a hint is a depth, never an average across an edge
            dense_hints = resize_nearest(dense_hints, h, w)
        sparse = np.where(dense_hints > 0, dense_hints, sparse).astype(np.float32)
    timings["prior"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    try:
        if ctx.device.type == "cpu":  # issue 14: refuse up front what would not fit in memory
            check_memory_budget(h, w, len(sources) + 1, ctx.net.config)
        depth, conf, vis, prior = estimate_depth(ctx.net, images, Ks, poses, entry.depth_range, sparse,
                                                 ctx.device)
    except (RuntimeError, MemoryError) as exc:
        if "memory" not in str(exc).lower() and not isinstance(exc, MemoryError):
            raise
        lower = "--network_scale or --max_image_size" if cfg.network_scale > 1.0 else "--max_image_size"
        reason = f"out of memory at {w}x{h} with {len(sources) + 1} views; lower {lower}"
        logger.error("skipping %s: %s (%s)", name, reason, exc)
        return reason
    timings["network"] = time.perf_counter() - t0
    conf = np.nan_to_num(conf, nan=0.0).astype(np.float32)
    if guide is not None:
        t0 = time.perf_counter()
        w, h = size
        if net_size[0] * net_size[1] < w * h:  # up to the map size along the image's edges
            depth = guided_upsample_depth(depth, guide)
            conf = resize_bilinear(conf, h, w)
        else:  # down: each map pixel takes the depth on its own ray, never an average across an edge
            depth = sample_depth_down(depth, h, w)
            conf = resize_area(conf, h, w)
        timings["upsample"] = time.perf_counter() - t0
    if prior is not None and (cfg.prior_blend_texture > 0 or cfg.prior_agreement_scale > 0):
        t0 = time.perf_counter()
        prior = upsample_prior(prior, net_size, size)
        conf = conf * prior_agreement(depth, prior, cfg.prior_agreement_scale)
        if cfg.prior_blend_texture > 0:
            rgb = guide if guide is not None else images[0]
            weight = texture_weight(rgb, cfg.prior_blend_window, cfg.prior_blend_texture)
            depth = blend_with_prior(depth, prior, weight)
        timings["prior_blend"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    depth = np.where((conf >= cfg.min_confidence) & np.isfinite(depth), depth, 0.0).astype(np.float32)
    timings["confidence"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    normals = depth_to_normals(depth, ctx.map_K(name, size))
    depth[~np.any(normals != 0, axis=-1)] = 0.0
    timings["normals"] = time.perf_counter() - t0
    return NetworkMaps(depth, normals, conf, vis)


def _photometric(ctx: StereoContext, name: str) -> RefOutcome:
    cfg, ws = ctx.config, ctx.workspace
    start = time.perf_counter()
    timings: dict[str, float] = {}
    sources, reason = ctx.sources_of(name)
    if sources is None:
        return RefOutcome(name, "photometric", "skipped", reason)
    size = ctx.map_size(name)
    settings = photometric_settings(ctx, name, sources)
    if not cfg.overwrite and _is_current(ws, name, "photometric", _fingerprint(settings), size):
        return RefOutcome(name, "photometric", "done", seconds=time.perf_counter() - start)
    maps = _network_maps(ctx, name, sources, timings)
    if isinstance(maps, str):
        return RefOutcome(name, "photometric", "skipped", maps)
    entry = ctx.selection.references[name]
    extra = {"image_size": list(size), "sources": sources}
    ctx.submit_write(_write_pass, ws, name, "photometric", maps.depth, maps.normals, maps.confidence,
                     settings, extra, cfg.previews, entry.depth_range, timings, maps.visibility, sources)
    return RefOutcome(name, "photometric", "computed", seconds=time.perf_counter() - start, timings=timings)


# --------------------------------------------------------------------------- geometric pass


def geometric_confidence(agree: np.ndarray, visibility: np.ndarray | None,
                         deviation: np.ndarray | None = None,
                         parallax: np.ndarray | None = None) -> np.ndarray:
    """``[H, W]`` confidence of a geometric map in ``[0, 1]`` (definition: ``docs/CONVENTIONS.md``).

    ``c = exp(-e / GEOM_DEVIATION_SCALE) * sum_s v_s * min(1, p_s / GEOM_FULL_PARALLAX) * agree_s / S``:
    the fraction of the ``S`` sources that confirm the pixel, each weighted by the network's learned
    visibility ``v_s`` of that source at the pixel (``agree`` ``[S, H, W]``, ``visibility``
    ``[S, H, W]`` or ``None`` for all ones) and by its parallax ``p_s`` (``[S, H, W]`` pixels,
    :attr:`~colmap_pvs.consistency.ConsistencyResult.parallax`; ``None``: full), times a factor for
    how far the pixel stands off the local plane of the kept pixels around it (``deviation`` ``e``
    ``[H, W]``, :func:`~colmap_pvs.completion.plane_deviation`; ``None``: 0). A source with little
    parallax agrees with almost any depth, so its agreement says less. Chosen by measurement on
    hololens-dev (``benchmarks/RESULTS.md``): the weighted fraction ranks errors better than the
    network's probability mass (which does not rank the consistent pixels at all), the agreement
    count alone, or the reprojection and depth errors; the deviation factor and the parallax weight
    rank them better still.
    """
    S = max(agree.shape[0], 1)
    weighted = agree if visibility is None else np.where(agree, visibility, 0.0)
    if parallax is not None:
        if parallax.shape != agree.shape:
            raise ShapeError(f"parallax must be {agree.shape}, got {parallax.shape}")
        weighted = weighted * np.clip(np.nan_to_num(parallax) / GEOM_FULL_PARALLAX, 0.0, 1.0)
    conf = weighted.sum(0) / S
    if deviation is not None:
        if deviation.shape != conf.shape:
            raise ShapeError(f"deviation must be {conf.shape}, got {deviation.shape}")
        conf = conf * np.exp(-np.nan_to_num(deviation, nan=np.inf) / GEOM_DEVIATION_SCALE)
    return np.clip(conf, 0.0, 1.0).astype(np.float32)


def _load_maps(ctx: StereoContext, name: str, kind: Stage = "photometric",
               normals: bool = True, depth_path: Path | None = None) -> SourceMaps:
    """``name``'s ``kind`` depth map (or the depth map at ``depth_path``; and its ``kind`` normal map,
    with ``normals``), intrinsics and pose."""
    ws = ctx.workspace
    depth = read_depth_map(ws.depth_map_path(name, kind) if depth_path is None else depth_path)
    normal_map = read_normal_map(ws.normal_map_path(name, kind)) if normals else None
    if normal_map is not None and normal_map.shape[:2] != depth.shape:
        raise MapFormatError(
            f"normal map of {name!r} is {normal_map.shape[:2]} but its depth map is {depth.shape}"
        )
    h, w = depth.shape
    T = to_homogeneous(ctx.sparse.image_by_name(name).cam_from_world)
    return SourceMaps(depth, normal_map, ctx.map_K(name, (w, h)), T)


def _check_visibility(coarse: np.ndarray, network_sources: list[str], sources: list[str],
                      size: tuple[int, int]) -> np.ndarray | None:
    """``[S, H, W]`` learned visibility of each of ``sources`` for the check, from the network's
    ``coarse`` ``[len(network_sources), h, w]`` maps upsampled to ``size`` ``(H, W)``; a source the
    network did not see counts as visible. ``None`` when ``coarse`` does not match the network's sources."""
    if coarse.shape[0] != len(network_sources):
        return None
    h, w = size
    up = resize_bilinear(np.ascontiguousarray(coarse, dtype=np.float32), h, w)
    ones = np.ones((h, w), np.float32)
    return np.stack([up[network_sources.index(s)] if s in network_sources else ones for s in sources])


@dataclass
class CheckSetup:
    """What a reference's geometric check reads: its photometric provenance ``prov``, the ``sources``
    checked (with photometric maps), the network sources without maps (``missing``), its
    view-selection ``entry`` and the ``settings`` (fingerprinted) that fix the check and the seeds."""

    prov: dict
    sources: list[str]
    missing: list[str]
    entry: object
    settings: dict


def _check_setup(ctx: StereoContext, name: str) -> CheckSetup | str:
    """:class:`CheckSetup` of ``name``, or why its geometric pass cannot run."""
    cfg, ws = ctx.config, ctx.workspace
    prov = read_provenance(ws, name, "photometric")
    if prov is None or not ws.depth_map_path(name, "photometric").is_file():
        return "its photometric maps do not exist"
    source_prov: dict[str, dict] = {}  # each source's provenance, read once

    def has_maps(s: str) -> bool:
        if s not in source_prov and ws.depth_map_path(s, "photometric").is_file():
            found = read_provenance(ws, s, "photometric")
            if found is not None:
                source_prov[s] = found
        return s in source_prov

    sources = [s for s in prov.get("sources", []) if has_maps(s)]
    missing = [s for s in prov.get("sources", []) if s not in sources]
    entry = ctx.selection.references.get(name)
    if cfg.geom_num_sources > 0 and entry is not None:  # the next best views with maps
        # A network source that is not a candidate view of the reference (score 0 or fewer than
        # min_shared_points shared sparse points: an unrelated frame in patch-match.cfg) is still
        # checked but takes none of the slots.
        candidates = set(entry.ranked_names)
        counted = sum(s in candidates for s in sources)
        for s in entry.ranked_names:
            if counted >= cfg.geom_num_sources:
                break
            if s not in sources and s != name and has_maps(s):
                sources.append(s)
                counted += 1
    keys = tuple(k for k in GEOMETRIC_SETTINGS if k not in GEOMETRIC_ONLY_SETTINGS)
    settings = _settings(ctx, "geometric", keys)
    settings.update(
        reference=prov["fingerprint"],
        sources={s: source_prov[s]["fingerprint"] for s in sources},
    )
    if len(sources) < min(cfg.geom_min_consistent, len(prov.get("sources", []))) or not sources:
        return f"{len(sources)} of its sources have photometric maps (missing: {missing})"
    return CheckSetup(prov, sources, missing, entry, settings)


def _check_kwargs(ctx: StereoContext) -> dict:
    cfg = ctx.config
    return {"max_reproj_error": cfg.geom_max_reproj_error, "max_depth_error": cfg.geom_max_depth_error,
            "max_normal_error": cfg.geom_max_normal_error, "min_visibility": cfg.geom_min_visibility,
            "workers": max(1, torch.get_num_threads())}  # the sources in threads, as many as torch's


def _load_check(ctx: StereoContext, name: str, setup: CheckSetup):
    """``(ref, srcs, vis)``: the photometric maps of ``name`` and of its checked sources, and the
    learned visibility of those sources (``None`` without a visibility map)."""
    ws = ctx.workspace
    ref = _load_maps(ctx, name)
    srcs = [_load_maps(ctx, s) for s in setup.sources]
    h, w = ref.depth.shape
    vis_path = ws.stereo_dir / "visibility_maps" / f"{name}.bin"
    vis = None
    if vis_path.is_file():
        coarse = read_array(vis_path)
        coarse = coarse[..., None] if coarse.ndim == 2 else coarse
        vis = _check_visibility(coarse.transpose(2, 0, 1), list(setup.prov.get("sources", [])), setup.sources,
                                (h, w))
    return ref, srcs, vis


def _seeds(cfg: StereoConfig, ref: SourceMaps, res) -> np.ndarray:
    """``[H, W]`` the completion's seeds of ``ref``'s photometric depth from its check ``res``:
    pixels that ``geom_seed_min_consistent`` sources confirm within ``geom_seed_depth_error`` (at any
    angle: the completion is better off with the narrow-baseline agreement of a video than without
    it), not isolated (the map of the seeds alone still gives them a normal); 0 elsewhere."""
    strict = (res.agree & (res.depth_error <= cfg.geom_seed_depth_error)).sum(0)
    seed_depth = res.mean_depth(ref.depth) if cfg.geom_average_depth else ref.depth
    seeds = np.where((ref.depth > 0) & (strict >= cfg.geom_seed_min_consistent), seed_depth, 0.0)
    return np.where(np.any(fit_normals(seeds, ref.K) != 0, axis=-1), seeds, 0.0).astype(np.float32)


@dataclass
class Checked:
    """A reference's check of its photometric maps (no re-estimate): its seeds ``[H, W]`` and, when
    another reference's geometric pass made it in this run, its checked depth and confidence
    ``[H, W]`` (0 where dropped) before the sources' seeds are added, for its own pass to reuse
    (``None`` for seeds read from disk or after its own pass)."""

    seeds: np.ndarray
    depth: np.ndarray | None = None
    conf: np.ndarray | None = None


def _kept(cfg: StereoConfig, ref: SourceMaps, res, vis: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``(depth, conf)`` ``[H, W]`` of the pixels of ``ref`` that the check ``res`` keeps: confirmed by
    ``geom_min_consistent`` sources from ``geom_min_triangulation_angle`` or more, averaged over them
    (``geom_average_depth``), with their geometric confidence of at least ``geom_min_confidence``."""
    confirm = res.confirming(cfg.geom_min_triangulation_angle)  # agreeing, from far enough apart
    keep = (ref.depth > 0) & (confirm.sum(0) >= cfg.geom_min_consistent)
    depth = res.mean_depth(ref.depth, confirm) if cfg.geom_average_depth else ref.depth.copy()
    depth = np.where(keep, depth, 0.0).astype(np.float32)
    conf = geometric_confidence(confirm, vis, plane_deviation(depth), res.parallax)
    keep &= conf >= cfg.geom_min_confidence
    depth[~keep] = 0.0
    return depth, np.where(keep, conf, 0.0).astype(np.float32)


def _reestimates(ctx: StereoContext, setup: CheckSetup) -> bool:
    """Whether the reference of ``setup`` is re-estimated in its geometric pass (``geom_reestimate``,
    with network sources and a view-selection entry): its kept pixels then come from the re-estimate,
    not from the check of its photometric maps."""
    return bool(ctx.config.geom_reestimate and setup.prov.get("sources") and setup.entry is not None)


def _check_photometric(ctx: StereoContext, name: str, setup: CheckSetup, kept: bool = True) -> Checked:
    """:class:`Checked` of ``name`` from its photometric maps and its checked sources' (the seeds
    only, without ``kept``)."""
    ref, srcs, vis = _load_check(ctx, name, setup)
    check = _check_kwargs(ctx)
    res = check_consistency(ref.depth, ref.normals, ref.K, ref.cam_from_world, srcs, vis, **check)
    depth, conf = _kept(ctx.config, ref, res, vis) if kept else (None, None)
    return Checked(_seeds(ctx.config, ref, res), depth, conf)


def seed_provenance_path(ws: Workspace, name: str) -> Path:
    """``stereo/seed_maps/NAME.json``: the fingerprint of the check that made ``NAME.bin``."""
    return seed_map_path(ws, name).with_name(f"{name}.json")


def _write_seeds(ws: Workspace, name: str, seeds: np.ndarray, fingerprint: str) -> None:
    """The seed map, then its fingerprint (which marks it current)."""
    seed_provenance_path(ws, name).unlink(missing_ok=True)
    write_array(seed_map_path(ws, name), seeds.astype(np.float32))
    payload = json.dumps({"fingerprint": fingerprint}) + "\n"
    atomic_write_bytes(seed_provenance_path(ws, name), payload.encode())


def _remember_seeds(ctx: StereoContext, name: str, fingerprint: str, checked: Checked) -> None:
    ctx.seed_cache[name] = (fingerprint, checked)
    ctx.seed_cache.move_to_end(name)
    while len(ctx.seed_cache) > SEED_CACHE_SIZE:
        ctx.seed_cache.popitem(last=False)


def _source_seeds(ctx: StereoContext, name: str, setup: CheckSetup) -> np.ndarray:
    """The seeds of ``name`` (its check's ``setup``) for another reference's geometric pass: from this
    run's memory or a current seed map on disk, else computed from the photometric maps (the same
    check as ``name``'s own geometric pass, so the same seeds whoever makes them) and written."""
    ws = ctx.workspace
    fingerprint = _fingerprint(setup.settings)
    cached = ctx.seed_cache.get(name)
    if cached is not None and cached[0] == fingerprint:
        return cached[1].seeds
    if not ctx.config.overwrite:
        try:
            on_disk = json.loads(seed_provenance_path(ws, name).read_text()).get("fingerprint")
            if on_disk == fingerprint:
                seeds = read_array(seed_map_path(ws, name))
                seeds = seeds[..., 0] if seeds.ndim == 3 else seeds
                _remember_seeds(ctx, name, fingerprint, Checked(seeds))
                return seeds
        except (OSError, json.JSONDecodeError, MapFormatError):
            pass
    # the whole check, kept for this image's own geometric pass later in the run (unless that pass
    # re-estimates, which checks the re-estimate instead)
    checked = _check_photometric(ctx, name, setup, kept=not _reestimates(ctx, setup))
    _write_seeds(ws, name, checked.seeds, fingerprint)
    _remember_seeds(ctx, name, fingerprint, checked)
    return checked.seeds


def _geometric(ctx: StereoContext, name: str) -> RefOutcome:
    cfg, ws = ctx.config, ctx.workspace
    start = time.perf_counter()
    timings: dict[str, float] = {}
    setup = _check_setup(ctx, name)
    if isinstance(setup, str):
        return RefOutcome(name, "geometric", "skipped", setup)
    prov, sources, missing, entry = setup.prov, setup.sources, setup.missing, setup.entry
    seed_fingerprint = _fingerprint(setup.settings)
    settings = dict(setup.settings, **_settings(ctx, "geometric", GEOMETRIC_ONLY_SETTINGS))
    splat_sources: dict[str, CheckSetup] = {}  # the sources whose seeds are projected in: their checks
    if cfg.geom_splat_min_sources > 0:
        for s in sources:
            found = _check_setup(ctx, s)
            if not isinstance(found, str):
                splat_sources[s] = found
        settings["splat_seeds"] = {s: _fingerprint(found.settings) for s, found in splat_sources.items()}
    size = tuple(prov.get("image_size", ctx.map_size(name)))
    if (not cfg.overwrite and _is_current(ws, name, "geometric", _fingerprint(settings), size)
            and _geometric_files_exist(ws, name)):
        return RefOutcome(name, "geometric", "done", seconds=time.perf_counter() - start)
    t0 = time.perf_counter()
    all_sources = list(prov.get("sources", []))
    reestimate = _reestimates(ctx, setup)
    reestimated = False
    cached = ctx.seed_cache.get(name)
    if (not reestimate and cached is not None and cached[0] == seed_fingerprint
            and cached[1].depth is not None):  # checked earlier in this run, for another pass's seeds
        checked = cached[1]
        seeds, depth, conf = checked.seeds, checked.depth.copy(), checked.conf.copy()
        timings["reused_check"] = time.perf_counter() - t0
    elif not reestimate:
        checked = _check_photometric(ctx, name, setup)
        seeds, depth, conf = checked.seeds, checked.depth.copy(), checked.conf.copy()
        timings["consistency"] = time.perf_counter() - t0
    else:
        # COLMAP's geometric PatchMatch re-estimates each reference with its sources' photometric maps;
        # here the depth they agree on becomes dense hints of a second network run (the coarse planes
        # centred on it, the cost modulated around it), whose maps are then checked as below.
        ref, srcs, vis = _load_check(ctx, name, setup)
        h, w = ref.depth.shape
        check = _check_kwargs(ctx)
        first = check_consistency(ref.depth, ref.normals, ref.K, ref.cam_from_world, srcs, vis, **check)
        seeds = _seeds(cfg, ref, first)  # from the photometric maps, as :func:`_source_seeds` makes them
        agreed = (ref.depth > 0) & (first.count >= cfg.geom_min_consistent)
        hints = np.where(agreed, first.mean_depth(ref.depth), 0.0).astype(np.float32)
        del first
        timings["reestimate_hints"] = time.perf_counter() - t0
        network_timings: dict[str, float] = {}
        maps = _network_maps(ctx, name, all_sources, network_timings, dense_hints=hints)
        timings.update({f"reestimate_{k}": v for k, v in network_timings.items()})
        if isinstance(maps, str):
            return RefOutcome(name, "geometric", "skipped", maps)
        ref = SourceMaps(maps.depth, maps.normals, ref.K, ref.cam_from_world)
        vis = _check_visibility(maps.visibility, all_sources, sources, (h, w))
        reestimated = True
        t0 = time.perf_counter()
        res = check_consistency(ref.depth, ref.normals, ref.K, ref.cam_from_world, srcs, vis, **check)
        depth, conf = _kept(cfg, ref, res, vis)
        del res
        timings["consistency"] = time.perf_counter() - t0
    h, w = depth.shape
    K = ctx.map_K(name, (w, h))
    cam_from_world = to_homogeneous(ctx.sparse.image_by_name(name).cam_from_world)
    keep = depth > 0
    splatted = 0
    if splat_sources:
        # A dropped pixel whose surface other views confirmed: their seeds projected in (nearest
        # surface per source), the median where enough of them agree (docs/CONVENTIONS.md).
        t0 = time.perf_counter()
        seed_maps = []
        for s, found in splat_sources.items():
            seeds_s = _source_seeds(ctx, s, found)
            sh, sw = seeds_s.shape
            seed_maps.append(SourceMaps(seeds_s, None, ctx.map_K(s, (sw, sh)),
                                        to_homogeneous(ctx.sparse.image_by_name(s).cam_from_world)))
        timings["splat_seeds"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        splat, support = splat_depths(K, cam_from_world, (w, h), seed_maps, cfg.geom_splat_min_sources)
        splat_conf = (SPLAT_CONFIDENCE * support / max(1, len(sources))).astype(np.float32)
        added = ~keep & (splat > 0) & (splat_conf >= cfg.geom_min_confidence)
        depth = np.where(added, splat, depth).astype(np.float32)
        conf = np.where(added, splat_conf, conf).astype(np.float32)
        splatted = int(added.sum())
        timings["splat"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    normals = fit_normals(depth, K)
    depth[~np.any(normals != 0, axis=-1)] = 0.0
    conf[depth == 0] = 0.0
    timings["normals"] = time.perf_counter() - t0
    dr = entry.depth_range if entry is not None else (float(depth[depth > 0].min(initial=1.0)),
                                                      float(depth.max(initial=2.0)))
    extra = {"image_size": [w, h], "sources": sources, "missing_sources": missing,
             "kept_fraction": float((depth > 0).mean()), "splatted_fraction": splatted / depth.size,
             "reestimated": reestimated}
    _remember_seeds(ctx, name, seed_fingerprint, Checked(seeds))  # its own pass reruns its own check
    ctx.submit_write(_write_pass, ws, name, "geometric", depth, normals, conf, settings, extra, cfg.previews,
                     dr, timings, None, (), seeds, seed_fingerprint)
    return RefOutcome(name, "geometric", "computed", seconds=time.perf_counter() - start, timings=timings)


# --------------------------------------------------------------------------- dense completion


def _read_confidence(ws: Workspace, name: str, kind: Stage, shape: tuple[int, int]) -> np.ndarray:
    path = ws.confidence_map_path(name, kind)
    conf = read_array(path) if path.is_file() else np.zeros(shape, np.float32)
    if conf.shape != shape:
        raise MapFormatError(f"confidence map {str(path)!r} is {conf.shape}, its depth map is {shape}")
    return conf


def remove_filled(ws: Workspace, name: str) -> None:
    """Remove ``name``'s dense completion (its provenance first, so nothing half-removed looks done)."""
    for path in (provenance_path(ws, name, "filled"), ws.depth_map_path(name, "filled"),
                 ws.confidence_map_path(name, "filled")):
        path.unlink(missing_ok=True)


def _current_geometric_provenance(ctx: StereoContext, name: str) -> dict | None:
    """``name``'s geometric provenance if its geometric maps exist and match this run: it is one of
    the run's references, its geometric settings are the run's, and they were made from its current
    photometric maps (whose fingerprint matches this run's settings and sources). ``None`` otherwise:
    maps left by another run, or by a pass this run skipped."""
    ws = ctx.workspace
    if name not in ctx.references or name not in ctx.selection.references:
        return None
    prov = read_provenance(ws, name, "geometric")
    photo = read_provenance(ws, name, "photometric")
    if prov is None or photo is None or not _geometric_files_exist(ws, name):
        return None
    settings = prov.get("settings", {})
    wanted = _settings(ctx, "geometric", GEOMETRIC_SETTINGS)
    if any(settings.get(k) != v for k, v in wanted.items()) or settings.get("reference") != photo.get(
            "fingerprint"):
        return None
    sources, _ = ctx.sources_of(name)
    if sources is None or photo.get("fingerprint") != _fingerprint(photometric_settings(ctx, name, sources)):
        return None
    return prov


def _filled(ctx: StereoContext, name: str) -> RefOutcome:
    """The dense completion of ``name``'s geometric map (:mod:`colmap_pvs.completion`).

    Reads the geometric maps of ``name`` and of its best views by score whose geometric maps are
    current (:func:`_current_geometric_provenance`, up to ``geom_num_sources``), so it runs once every
    geometric map exists.
    """
    cfg, ws = ctx.config, ctx.workspace
    start = time.perf_counter()
    timings: dict[str, float] = {}
    prov = read_provenance(ws, name, "geometric")
    if prov is None or not _geometric_files_exist(ws, name):
        remove_filled(ws, name)
        return RefOutcome(name, "filled", "skipped", "its geometric maps do not exist")
    entry = ctx.selection.references.get(name)
    source_prov: dict[str, dict] = {}  # the best views by score whose geometric maps are current
    for s in entry.ranked_names if entry is not None else ():
        if len(source_prov) >= max(1, cfg.geom_num_sources):
            break
        found = _current_geometric_provenance(ctx, s) if s != name else None
        if found is not None:
            source_prov[s] = found
    settings = _settings(ctx, "filled", FILLED_SETTINGS)
    settings.update(reference=prov["fingerprint"],
                    sources={s: p["fingerprint"] for s, p in source_prov.items()})
    size = tuple(prov.get("image_size", ctx.map_size(name)))
    if not cfg.overwrite and _is_current(ws, name, "filled", _fingerprint(settings), size):
        return RefOutcome(name, "filled", "done", seconds=time.perf_counter() - start)
    t0 = time.perf_counter()
    # The seeds of the reference and of its sources are what is known.
    ref = _load_maps(ctx, name, "geometric", normals=False, depth_path=seed_map_path(ws, name))
    srcs = [_load_maps(ctx, s, "geometric", normals=False, depth_path=seed_map_path(ws, s))
            for s in source_prov]
    h, w = ref.depth.shape
    geometric_kept = read_depth_map(ws.depth_map_path(name, "geometric")) > 0
    if geometric_kept.shape != (h, w):
        raise MapFormatError(
            f"geometric depth map of {name!r} is {geometric_kept.shape}, its seed map is {(h, w)}"
        )
    photo = read_depth_map(ws.depth_map_path(name, "photometric"))
    if photo.shape != (h, w):
        raise MapFormatError(
            f"photometric depth map of {name!r} is {photo.shape}, its geometric one is {(h, w)}"
        )
    geo_conf = _read_confidence(ws, name, "geometric", (h, w))
    photo_conf = _read_confidence(ws, name, "photometric", (h, w))
    timings["load"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    kept = ref.depth > 0
    splat, support = splat_depths(ref.K, ref.cam_from_world, (w, h), srcs, cfg.geom_fill_min_sources)
    splatted = ~kept & (splat > 0)
    known = np.where(kept, ref.depth, splat).astype(np.float32)
    timings["splat"] = time.perf_counter() - t0
    segmented, inliers = np.zeros_like(kept), None
    if cfg.geom_fill_segments:
        t0 = time.perf_counter()
        image = ctx.images.get(name, cfg.max_image_size, (w, h))
        plane, inliers = segment_planes(known, image, ~kept, min_pixels=cfg.geom_fill_segment_min_pixels,
                                        min_inliers=cfg.geom_fill_segment_inliers)
        segmented = ~kept & (plane > 0)
        timings["segments"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    depth = complete_depth(known, photo)
    if cfg.geom_fill_segments:
        depth = np.where(segmented, plane, depth).astype(np.float32)
    conf = completed_confidence(kept, splatted, geo_conf, photo_conf, support / max(1, len(srcs)),
                                segmented, inliers)
    timings["fit"] = time.perf_counter() - t0
    extra = {"image_size": [w, h], "sources": list(source_prov), "kept_fraction": float(kept.mean()),
             "geometric_fraction": float(geometric_kept.mean()),
             "splatted_fraction": float((splatted & ~segmented).mean()),
             "segmented_fraction": float(segmented.mean())}
    dr = entry.depth_range if entry is not None else tuple(np.percentile(depth, [1, 99]))
    ctx.submit_write(_write_filled, ws, name, depth, conf, settings, extra, cfg.previews, dr, timings)
    return RefOutcome(name, "filled", "computed", seconds=time.perf_counter() - start, timings=timings)


def _write_filled(ws: Workspace, name: str, depth, conf, settings, extra, previews, depth_range,
                  timings) -> None:
    """Write the dense completion: confidence, provenance, then the depth (which marks it done)."""
    t0 = time.perf_counter()
    # The old depth goes first: new provenance beside an old depth would look done after a crash
    # (no other pass reads the completion, so nothing can miss it meanwhile).
    ws.depth_map_path(name, "filled").unlink(missing_ok=True)
    write_array(ws.confidence_map_path(name, "filled"), conf.astype(np.float32))
    _write_provenance(ws, name, "filled", settings, extra)
    write_depth_map(ws.depth_map_path(name, "filled"), depth)
    timings["writes"] = time.perf_counter() - t0
    if previews:
        save_depth_preview(ws.stereo_dir / "previews" / f"{name}.filled.depth.png", depth,
                           vmin=depth_range[0], vmax=depth_range[1])


def process_reference(ctx: StereoContext, name: str, stage: Stage) -> RefOutcome:
    """Compute (if not current) and atomically write one reference's maps for one pass.

    The pass's depth map is written last (after its provenance), so its existence with matching
    provenance marks the reference done. The geometric pass reads the photometric maps of ``name``
    and of its sources. With background writes (``prepare_stereo(background_io=True)``) the files
    appear after :meth:`StereoContext.flush`; ``timings`` then fills in ``writes`` at that point.
    """
    if stage == "photometric":
        return _photometric(ctx, name)
    if stage == "geometric":
        return _geometric(ctx, name)
    if stage == "filled":
        return _filled(ctx, name)
    raise ConfigError(f"stage must be 'photometric', 'geometric' or 'filled', got {stage!r}")


def auxiliary_references(ctx: StereoContext) -> list[str]:
    """Sources of the references that are not references themselves (``patch-match.cfg`` lists a
    subset): the geometric pass needs their photometric maps, so they get a photometric pass too
    (with automatic sources), but no geometric maps and no ``fusion.cfg`` entry."""
    refs = set(ctx.references)
    extra: dict[str, None] = {}
    for name in ctx.references:
        sources, _ = ctx.sources_of(name)
        for s in sources or ():
            if s not in refs:
                extra[s] = None
    return sorted(extra)


_PASS_LABELS = {"geometric": ("stereo (geometric)", "geometric pass"),
                "filled": ("stereo (dense completion)", "dense completion")}


def _run_later_pass(ctx: StereoContext, names: list[str], stage: Stage, result: StereoResult,
                    outcomes: list[RefOutcome], skip: set[str]) -> None:
    """Run the geometric or the completion pass over ``names`` (but ``skip``), filling
    ``result.{stage}_processed / _done / _skipped`` and ``result.pass_seconds[stage]``."""
    t_pass = time.perf_counter()
    desc, label = _PASS_LABELS[stage]
    processed, done, skipped = (getattr(result, f"{stage}_{k}") for k in ("processed", "done", "skipped"))
    for name in tqdm(names, desc=desc, unit="image"):
        if name in skip:
            if stage == "filled":  # never keep a completion of maps this run did not make
                remove_filled(ctx.workspace, name)
            continue
        out = process_reference(ctx, name, stage)
        outcomes.append(out)
        if out.status == "done":
            done.append(name)
        elif out.status == "skipped":
            logger.warning("%s: skipping %s: %s", label, name, out.reason)
            skipped[name] = out.reason
        else:
            processed.append(name)
    ctx.flush()
    result.pass_seconds[stage] = time.perf_counter() - t_pass


def _final_kind(config: StereoConfig) -> Stage:
    return "geometric" if config.geom_consistency else "photometric"


def run_stereo(config: StereoConfig) -> StereoResult:
    """Compute depth and normal maps for every reference image of the workspace (both passes).

    Resumable per pass: maps that exist with matching provenance are kept unless ``config.overwrite``.
    Images without usable sources or sparse points are skipped with a warning.
    ``config.backend == "ray"`` runs the same passes on a Ray cluster (:mod:`colmap_pvs.distributed`).
    With ``adapt_pseudo_labels`` (self-training) a first run with the base checkpoint writes the maps
    that the adaptation fits; its time is part of ``adapt_seconds``.
    """
    first_round = _pseudo_label_round(config) if config.adapt_pseudo_labels != "none" else 0.0
    if config.backend == "ray":
        from .distributed import run_stereo_ray

        result = run_stereo_ray(config)
    else:
        result = _run_stereo_here(config)
    if first_round > 0:  # the run that made the pseudo-labels is part of the adaptation's cost
        result.adapt_seconds += first_round
        count = len(result.processed) + len(result.already_done) + len(result.skipped)
        result.adapt_seconds_per_image = result.adapt_seconds / max(1, count)
    return result


def _pseudo_label_round(config: StereoConfig) -> float:
    """Self-training's first round: every pass with the base checkpoint, whose maps become the
    adaptation's pseudo-labels. Skipped (0 s) when the adapted weights for them already exist."""
    from .adapt import adapted_is_current

    ws = detect_workspace(config.workspace_path)  # the paths only: the run itself reads the model
    base = base_checkpoint_path(config)
    if base.is_file() and adapted_is_current(ws.stereo_dir, base, adapt_config(config),
                                             pseudo_label_key(config, ws)):
        return 0.0
    logger.info("test-time adaptation on %s pseudo-labels: a first run with the base checkpoint",
                config.adapt_pseudo_labels)
    start = time.perf_counter()
    run_stereo(replace_config(config, adapt_steps=0, adapt_pseudo_labels="none"))
    return time.perf_counter() - start


def _run_stereo_here(config: StereoConfig) -> StereoResult:
    """:func:`run_stereo` in this process."""
    wall = time.perf_counter()
    ctx = prepare_stereo(config, background_io=True)
    ws = ctx.workspace
    remove_orphan_temps(ws.stereo_dir, recursive=True)  # issue 11: what a killed run left behind
    t_prepare = time.perf_counter() - wall
    save_config(config, ws.stereo_dir / CONFIG_FILENAME, checkpoint_used=str(ctx.checkpoint_path),
                checkpoint_sha256=ctx.checkpoint_sha256, model_config=ctx.net.config)
    result = StereoResult(workspace=ws, adapt_seconds=ctx.adapt_seconds)
    result.adapt_seconds_per_image = ctx.adapt_seconds / max(1, len(ctx.references))
    result.timings["prepare"] = t_prepare
    outcomes: list[RefOutcome] = []
    names = list(ctx.references)
    result.auxiliary = auxiliary_references(ctx) if config.geom_consistency else []
    work = names + result.auxiliary
    try:
        t_pass = time.perf_counter()
        bar = tqdm(work, desc="stereo (photometric)", unit="image")
        for i, name in enumerate(bar):
            if i + 1 < len(work):
                ctx.prefetch(work[i + 1])
            out = process_reference(ctx, name, "photometric")
            outcomes.append(out)
            if i >= len(names):  # an auxiliary source: reported in result.auxiliary only
                if out.status == "skipped":
                    logger.warning("no photometric maps for source %s: %s", name, out.reason)
                continue
            if out.status == "done":
                result.already_done.append(name)
            elif out.status == "skipped":
                logger.warning("skipping %s: %s", name, out.reason)
                result.skipped[name] = out.reason
            else:
                result.processed.append(name)
                bar.set_postfix(s=f"{out.seconds:.2f}")
            sources, _ = ctx.sources_of(name)
            if sources is not None:
                result.sources[name] = sources
        ctx.flush()
        result.pass_seconds["photometric"] = time.perf_counter() - t_pass
        if config.geom_consistency:
            _run_later_pass(ctx, names, "geometric", result, outcomes, set(result.skipped))
        if config.geom_consistency and config.geom_fill:
            _run_later_pass(ctx, names, "filled", result, outcomes,
                            set(result.skipped) | set(result.geometric_skipped))
        else:  # never keep a completion that no longer matches the maps
            for name in names:
                remove_filled(ws, name)
    finally:
        ctx.close()
    for out in outcomes:
        for stage, sec in out.timings.items():
            key = stage if out.stage == "photometric" else f"{out.stage}.{stage}"
            result.timings[key] = result.timings.get(key, 0.0) + sec
    kind = _final_kind(config)
    done = [n for n in names
            if ws.depth_map_path(n, kind).is_file() and ws.normal_map_path(n, kind).is_file()]
    if not done:  # issue 11: an error, and the previous fusion.cfg is kept (not emptied)
        reasons = "; ".join(f"{n}: {r}" for n, r in list(result.skipped.items())[:3])
        raise WorkspaceError(
            f"no {kind} depth map in {str(ws.stereo_dir)!r}: all {len(names)} reference(s) were skipped "
            f"({reasons})"
        )
    write_fusion_cfg(ws.fusion_cfg, done)
    computed = len(set(result.processed) | set(result.geometric_processed) | set(result.filled_processed))
    total = time.perf_counter() - wall
    result.pass_seconds["total"] = total
    result.seconds_per_image = total / computed if computed else 0.0
    logger.info(
        "stereo: photometric %d computed, %d already done, %d skipped; geometric %d computed, %d done, "
        "%d skipped; %.2f s/image",
        len(result.processed), len(result.already_done), len(result.skipped),
        len(result.geometric_processed), len(result.geometric_done), len(result.geometric_skipped),
        result.seconds_per_image,
    )
    return result
