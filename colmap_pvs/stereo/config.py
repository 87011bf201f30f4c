"""The ``stereo`` step's settings: one frozen config per pass, nested in :class:`StereoConfig`.

Each nested config is one argparse group of ``colmap-pvs stereo --help``; its fields are flags named
``PREFIX + field`` (``StereoConfig.geometric.min_consistent`` is ``--geom_min_consistent``). A pass's
provenance is every field of its own config under its flag name (:func:`pass_settings`), so a new
setting is one field and nothing else: it is a flag, it is checked, it is in the provenance.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import ClassVar, Literal

from ..completion import SEGMENT_MIN_INLIERS, SEGMENT_MIN_PIXELS
from ..config import check_int_fields, check_range, check_threads, config_flags, config_to_flags
from ..errors import ConfigError

DEFAULT_CHECKPOINT = Path(__file__).resolve().parents[1] / "weights" / "pvsnet_default.pt"
#: The resolved config of the last run, in ``stereo/``.
CONFIG_FILENAME = "colmap_pvs_stereo.json"
#: Bumped when a pass's output changes for the same settings (part of its provenance fingerprint).
FORMAT_VERSIONS = {"photometric": 6, "geometric": 9, "filled": 8, "confirm": 1}
Stage = Literal["photometric", "geometric", "filled", "confirm"]
#: Largest ``network_scale``: the network on twice the map's size (about 4x its time and memory).
NETWORK_SCALE_MAX = 2.0
#: :class:`PhotometricConfig` fields that override the checkpoint's
#: :class:`~colmap_pvs.model.PVSNetConfig` field of the same name ("on" / "off"; "checkpoint" keeps
#: it). Each must be one of :data:`colmap_pvs.model.PARAMETER_FREE_FIELDS` (pinned by a test):
#: flipping it keeps the weights valid.
MODEL_SWITCHES = ("sparse_guidance", "sparse_prior")

_OFF = {"provenance": False}  # a pass's on/off switch: not one of the settings its maps depend on
#: Where and how the step runs, or what else it writes: a setting no map depends on.
_RUN = {"run_only": True}

#: Window (map pixels, odd) over which ``prior_blend_texture`` measures the image's texture.
PRIOR_BLEND_WINDOW = 7
#: Window (map pixels, odd) of the local plane whose residual lowers the photometric score
#: (:func:`~colmap_pvs.normals.plane_residual`), and the relative residual at which it falls by ``1 / e``
#: (``benchmarks/RESULTS.md``, "Depth edges in the network's confidence").
PLANE_RESIDUAL_WINDOW = 15
PLANE_RESIDUAL_SCALE = 0.02
#: The same for the completion's score, on the completed depth (``benchmarks/RESULTS.md``, "Depth edges in
#: the completion's confidence").
COMPLETION_RESIDUAL_WINDOW = 21
COMPLETION_RESIDUAL_SCALE = 0.05
#: Settings that are no longer options but that a pass's maps still depend on, with their value: each
#: stays in its pass's provenance under its old flag name, before the flag named second (``None``: at
#: the end), so that the maps made while they were options stay current. Back-compat (dropped in 0.3):
#: the provenance of the maps in a user's workspace holds them (after 0.3 those passes rerun once).
FIXED_SETTINGS: dict[str, list[tuple[str, str | None, object]]] = {
    "photometric": [("prior_blend_window", "prior_agreement_scale", PRIOR_BLEND_WINDOW)],
    "geometric": [("geom_max_normal_error", "geom_min_visibility", 180.0)],  # the normal check: off
    "completion": [("geom_fill_segment_min_pixels", None, SEGMENT_MIN_PIXELS),
                   ("geom_fill_segment_inliers", None, SEGMENT_MIN_INLIERS)],
}


@dataclass(frozen=True)
class PhotometricConfig:
    """The photometric pass: the network on each reference (flags without prefix)."""

    num_views: int = field(default=5, metadata={"help": "views per reference: reference + N-1 sources"})
    max_image_size: int = field(
        default=640, metadata={"help": "longest image side for inference; <= 0 keeps full size"}
    )
    depth_range: tuple[float, ...] = field(
        default=(),
        metadata={  # the maps' provenance holds the range used, so the flag itself is not in it
            "provenance": False,
            "help": "MIN MAX: one depth range for every reference (default: each from its sparse points)",
        },
    )
    depth_near_factor: float = field(
        default=1.0,
        metadata={"provenance": False,  # the maps' provenance holds the range it gives
                  "help": "in (0, 1]: each reference's depth range's near end times this (1: COLMAP's)"},
    )
    network_scale: float = field(
        default=0.8,
        metadata={
            "help": "network size as a multiple of the map's (0.25-2); 1.5 for thin structures, slower"
        },
    )
    network_min_size: int = field(
        default=400,
        metadata={"help": "network_scale never takes the network's longest side below this (px)"},
    )
    min_confidence: float = field(
        default=0.0,
        metadata={
            "help": "drop network pixels whose confidence (P(within 5 %)) is below this (0: keep all)"
        },
    )
    sparse_guidance: Literal["checkpoint", "on", "off"] = field(
        default="checkpoint",
        metadata={"help": "modulate the cost volume around projected sparse points (Guided Stereo)"},
    )
    sparse_prior: Literal["checkpoint", "on", "off"] = field(
        default="checkpoint",
        metadata={
            "help": "centre the coarse depth hypotheses on the sparse points (off: global depth range)"
        },
    )
    prior_blend_texture: float = field(
        default=0.01,
        metadata={
            "help": "in flat image regions (grey std below this) move the depth to the sparse prior (0: off)"
        },
    )
    prior_agreement_scale: float = field(
        default=0.05,
        metadata={
            "help": "confidence times exp(-|log(d / prior)| / this): agreement with the prior (0: off)"
        },
    )

    def __post_init__(self) -> None:
        check_int_fields(self)
        check_range("num_views", self.num_views, low=2)
        check_range("min_confidence", self.min_confidence, low=0.0, high=1.0)
        check_range("prior_blend_texture", self.prior_blend_texture, low=0.0, high=1.0)
        check_range("prior_agreement_scale", self.prior_agreement_scale, low=0.0)
        check_range("network_scale", self.network_scale, low=0.25, high=NETWORK_SCALE_MAX)
        check_range("network_min_size", self.network_min_size, low=16)
        if not 0.0 < self.depth_near_factor <= 1.0:
            raise ConfigError(f"depth_near_factor must be in (0, 1], got {self.depth_near_factor}")
        try:
            object.__setattr__(self, "depth_range", tuple(float(v) for v in self.depth_range))
        except (TypeError, ValueError):
            raise ConfigError(f"depth_range must be two numbers MIN MAX, got {self.depth_range!r}") from None
        lo_hi = self.depth_range
        if lo_hi and not (len(lo_hi) == 2 and 0 < lo_hi[0] < lo_hi[1] < float("inf")):
            raise ConfigError(f"depth_range must be two numbers 0 < MIN < MAX, got {list(self.depth_range)}")
        if 0 < self.max_image_size < 16:
            raise ConfigError(f"max_image_size must be <= 0 (full size) or >= 16, got {self.max_image_size}")


@dataclass(frozen=True)
class GeometricConfig:
    """The geometric pass: forward-backward consistency against the sources (flags ``--geom_*``)."""

    enabled: bool = field(
        default=True,
        metadata={"flag": "geom_consistency", **_OFF,
                  "help": "run the geometric pass (*.geometric.bin; COLMAP's geom_consistency)"},
    )
    min_consistent: int = field(
        default=2, metadata={"help": "a pixel must agree with at least this many sources"}
    )
    max_reproj_error: float = field(
        default=2.0, metadata={"help": "max forward-backward reprojection error (px)"}
    )
    max_depth_error: float = field(default=0.03, metadata={"help": "max relative depth error |z'-d|/d"})
    min_visibility: float = field(
        default=0.2, metadata={"help": "consult a source only where its learned visibility >= this"},
    )
    min_triangulation_angle: float = field(
        default=3.0,
        metadata={"help": "a source confirms a pixel only from this angle (degrees) or more"},
    )
    num_sources: int = field(
        default=10,
        metadata={"help": "check against up to this many views with maps: the sources, then the next best"},
    )
    average_depth: bool = field(
        default=True, metadata={"help": "average the depth with the agreeing sources' reprojected depths"},
    )
    min_confidence: float = field(
        default=0.0,
        metadata={"help": "pixels whose geometric confidence (P(within 5 %)) is below this are invalid"},
    )
    reestimate: bool = field(
        default=False,
        metadata={"help": "run the network again with the agreed depth as hints and check that (slower)"},
    )
    seed_min_consistent: int = field(
        default=3,
        metadata={"help": "sources that must agree with a pixel for it to seed the completion"},
    )
    seed_depth_error: float = field(
        default=0.025,
        metadata={"help": "max relative depth error of the sources that make a seed"},
    )
    splat_min_sources: int = field(
        default=3,
        metadata={
            "seeds": False,  # changes the geometric maps, not the seeds
            "help": "keep a dropped pixel where this many sources' seeds agree on it (0: off)",
        },
    )

    def __post_init__(self) -> None:
        check_int_fields(self, "geom_")
        check_range("geom_seed_min_consistent", self.seed_min_consistent, low=1)
        check_range("geom_splat_min_sources", self.splat_min_sources, low=0)
        check_range("geom_min_visibility", self.min_visibility, low=0.0, high=1.0)
        check_range("geom_min_triangulation_angle", self.min_triangulation_angle, low=0.0, high=90.0)
        check_range("geom_num_sources", self.num_sources, low=0)
        if self.min_consistent < 1:
            raise ConfigError(f"geom_min_consistent must be >= 1, got {self.min_consistent}")
        for name in ("max_reproj_error", "max_depth_error", "seed_depth_error"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"geom_{name} must be > 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class CompletionConfig:
    """The dense completion of each geometric map (flags ``--geom_fill*``)."""

    enabled: bool = field(
        default=True,
        metadata={
            "flag": "geom_fill", **_OFF,
            "help": "dense completion of each geometric map (*.filled.bin; COLMAP's fusion never reads it)",
        },
    )
    min_sources: int = field(
        default=2, metadata={"help": "sources whose kept depths must agree to give a dropped pixel"},
    )
    segments: bool = field(
        default=True,
        metadata={"help": "fill a dropped pixel from the robust plane of its image segment where it fits"},
    )

    def __post_init__(self) -> None:
        check_int_fields(self, "geom_fill_")
        check_range("geom_fill_min_sources", self.min_sources, low=1)


@dataclass(frozen=True)
class AdaptationConfig:
    """Test-time adaptation of the network on the workspace's own images (flags ``--adapt_*``): the
    step above this one, :func:`colmap_pvs.adapt.run_adapted_stereo`, which the ``stereo`` command runs.
    This step checks them and records them with the run; it runs the weights that step gives it."""

    steps: int = field(
        default=0,
        metadata={
            "help": "test-time adaptation: fine-tune on the workspace's own images for N steps (0: off)"
        },
    )
    max_seconds: float = field(default=0.0, metadata={"help": "time limit in seconds (0 = none)"})
    lr: float = field(default=1e-4, metadata={"help": "learning rate"})
    pseudo_labels: Literal["none", "geometric", "filled"] = field(
        default="none",
        metadata={
            "help": "also fit the workspace's maps of this kind (self-training: stereo runs twice)"
        },
    )

    def __post_init__(self) -> None:
        check_int_fields(self, "adapt_")
        check_range("adapt_steps", self.steps, low=0)
        check_range("adapt_max_seconds", self.max_seconds, low=0.0)
        if self.pseudo_labels != "none" and self.steps == 0:
            raise ConfigError(f"adapt_pseudo_labels={self.pseudo_labels!r} needs adapt_steps > 0 (got 0)")


@dataclass(frozen=True)
class RayConfig:
    """The Ray backend (``--backend ray``; :mod:`colmap_pvs.stereo.ray`, flags ``--ray_*``)."""

    address: str = field(
        default="", metadata={"help": "empty starts a local Ray; 'auto' or HOST:PORT joins a cluster"}
    )
    workers: int = field(default=0, metadata={"help": "worker actors; 0: fill the CPUs"})
    worker_threads: int = field(default=1, metadata={"help": "torch threads (and CPUs) per worker"})
    worker_memory: float = field(
        default=0.0, metadata={"help": "GiB of memory Ray reserves per worker when placing it; 0: none"}
    )
    max_retries: int = field(
        default=3, metadata={"help": "times a reference is retried after its worker died"}
    )
    task_timeout: float = field(
        default=0.0,
        metadata={"help": "seconds after which a reference's worker is killed and it is retried (0: none)"},
    )

    def __post_init__(self) -> None:
        check_int_fields(self, "ray_")
        check_threads("ray_worker_threads", self.worker_threads, auto=None)
        for name, low in (("workers", 0), ("worker_memory", 0.0),
                          ("max_retries", 0), ("task_timeout", 0.0)):
            check_range(f"ray_{name}", getattr(self, name), low=low)


def _section(cls: type, prefix: str, title: str, run_only: bool = False):
    return field(default_factory=cls,
                 metadata={"flag_prefix": prefix, "title": title, **(_RUN if run_only else {})})


@dataclass(frozen=True)
class StereoConfig:
    """Settings of the ``stereo`` step (the single source of its defaults and CLI flags)."""

    workspace_path: Path = field(
        metadata={"help": "COLMAP dense workspace (images/, sparse/, stereo/)", **_RUN}
    )
    checkpoint: Path | None = field(  # the maps depend on its content (in the provenance), not its path
        default=None, metadata={"help": "model checkpoint (.pt); default: the shipped checkpoint", **_RUN}
    )
    device: Literal["auto", "cpu", "cuda"] = field(default="auto", metadata={"help": "torch device", **_RUN})
    threads: int = field(default=0, metadata={"help": "torch CPU threads; 0 keeps torch's default", **_RUN})
    overwrite: bool = field(
        default=False, metadata={"help": "recompute images whose maps already exist", **_RUN}
    )
    previews: bool = field(
        default=False,
        metadata={"help": "write PNG previews of depth, normals, confidence, visibility", **_RUN},
    )
    min_sources: int = field(default=1, metadata={"help": "skip references with fewer sources"})
    backend: Literal["local", "ray"] = field(
        default="local",
        metadata={"help": "local: this process; ray: one task per image on a Ray cluster", **_RUN},
    )
    photometric: PhotometricConfig = _section(PhotometricConfig, "", "photometric pass (the network)")
    geometric: GeometricConfig = _section(GeometricConfig, "geom_", "geometric pass")
    completion: CompletionConfig = _section(CompletionConfig, "geom_fill_", "dense completion")
    adapt: AdaptationConfig = _section(AdaptationConfig, "adapt_", "test-time adaptation")
    ray: RayConfig = _section(RayConfig, "ray_", "Ray backend (--backend ray)", run_only=True)

    #: Options that are gone, with the value they now always have (accepted with a warning).
    #: Back-compat (dropped in 0.3): a config file a user wrote or a saved stereo config may set them.
    REMOVED_OPTIONS: ClassVar[dict[str, object]] = {
        "wide_sources": 0, "adapt_seed": 0,
        **{name: value for fixed in FIXED_SETTINGS.values() for name, _, value in fixed},
    }

    def __post_init__(self) -> None:  # bad values are refused where they enter
        check_int_fields(self)
        check_threads("threads", self.threads, auto=0)
        check_range("min_sources", self.min_sources, low=1)
        kind = self.adapt.pseudo_labels
        needs_fill = kind == "filled" and not self.completion.enabled
        if kind != "none" and (not self.geometric.enabled or needs_fill):
            raise ConfigError(
                f"adapt_pseudo_labels={kind!r} needs the pass that writes those maps: "
                f"geom_consistency={self.geometric.enabled}, geom_fill={self.completion.enabled}"
            )


#: :class:`StereoConfig`'s flags (:func:`~colmap_pvs.config.config_flags`), computed once.
FLAGS = config_flags(StereoConfig)


def map_settings(config: StereoConfig) -> dict:
    """Flag name -> value of every setting some map depends on (all but the run-only ones; the
    checkpoint is in each pass's provenance by its content)."""
    sections = {f.name: f for f in fields(StereoConfig)}
    return {flag: value for flag, value in config_to_flags(config).items()
            if not (FLAGS[flag].field.metadata.get("run_only")
                    or sections[FLAGS[flag].path[0]].metadata.get("run_only"))}


def pass_settings(config: StereoConfig, section: str, *, seeds: bool = False) -> dict:
    """The settings of ``config.<section>`` that the pass's maps depend on, by flag name, in field
    order (every field but the pass's on/off switch, and its :data:`FIXED_SETTINGS`; with ``seeds``,
    only those the geometric pass's seed maps depend on)."""
    entries = FIXED_SETTINGS.get(section, [])
    fixed = {before: (name, value) for name, before, value in entries if before is not None}
    out = {}
    for flag, spec in FLAGS.items():
        meta = spec.field.metadata
        if spec.path[0] != section or meta.get("provenance", True) is False:
            continue
        if seeds and meta.get("seeds", True) is False:
            continue
        if flag in fixed:
            out[fixed[flag][0]] = fixed[flag][1]
        out[flag] = getattr(getattr(config, section), spec.path[1])
    out.update({name: value for name, before, value in entries if before is None})
    return out
