"""The ``fuse`` step's settings and result (:func:`colmap_pvs.fusion.fuse`)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from ..errors import ConfigError
from ..io.colmap_tools import COLMAP_DEFAULTS, parse_colmap_options

logger = logging.getLogger(__name__)

__all__ = ["CONFIG_SUFFIX", "DEFAULT_OUTPUT_NAME", "FuseConfig", "FuseResult"]

DEFAULT_OUTPUT_NAME = "fused.ply"
#: Version of ``fuse``'s rules for which pixels a cloud holds, raised when one changes: ``reconstruct``
#: fuses a cloud made under other rules again.
FUSION_RULES = 2
CONFIG_SUFFIX = ".fuse_config.json"

@dataclass(frozen=True)
class FuseConfig:
    """Settings of the ``fuse`` step (the single source of its defaults and CLI flags)."""

    workspace_path: Path = field(
        metadata={"help": "COLMAP dense workspace with stereo/depth_maps and normal_maps"}
    )
    output_path: Path | None = field(
        default=None,
        metadata={"help": f"output .ply (plus .ply.vis); default: WORKSPACE/{DEFAULT_OUTPUT_NAME}"},
    )
    method: Literal["pvs", "colmap"] = field(
        default="pvs",
        metadata={"help": "pvs: our geometric-consistency fusion; colmap: pycolmap.stereo_fusion"},
    )
    input_type: Literal["auto", "geometric", "photometric", "filled"] = field(
        default="auto",
        metadata={"help": "which maps to fuse (stereo/*_maps/NAME.INPUT_TYPE.bin); filled: the dense "
                          "completion (pvs only); auto: filled for pvs where every image has a current "
                          "one, else geometric"},
    )
    num_sources: int = field(
        default=8, metadata={"help": "pvs: source views checked per reference (best first)"}
    )
    max_reproj_error: float = field(
        default=1.0, metadata={"help": "pvs: max forward-backward reprojection error, in map pixels"}
    )
    max_depth_error: float = field(
        default=0.01, metadata={"help": "pvs: max relative depth difference |d_src_in_ref - d| / d"}
    )
    min_consistent_views: int = field(
        default=2,
        metadata={"help": "pvs: minimum number of agreeing source views for a point (one fewer for "
                          "completed pixels that hold their geometric map's checked depth)"},
    )
    min_confidence: float = field(
        default=0.0,
        metadata={
            "help": "pvs: drop pixels whose confidence (P(within 5 %)) is below this, where confidence "
                    "maps exist (a calibrated completion's pixels below 0.5 are always dropped)"
        },
    )
    deduplicate: bool = field(
        default=True, metadata={"help": "pvs: source pixels that agreed are not fused again as references"}
    )
    cache_size: int = field(
        default=16, metadata={"help": "pvs: views (depth, normals, colours) kept in memory (LRU)"}
    )
    colmap_options: tuple[str, ...] = field(
        default=(),
        metadata={
            "help": "colmap: StereoFusionOptions overrides as key=value (e.g. min_num_pixels=5 "
            f"max_reproj_error=2); our defaults: {COLMAP_DEFAULTS}"
        },
    )

    def __post_init__(self) -> None:
        if self.num_sources < 1:
            raise ConfigError(f"num_sources must be >= 1, got {self.num_sources}")
        if not self.max_reproj_error > 0:
            raise ConfigError(f"max_reproj_error must be > 0, got {self.max_reproj_error}")
        if not self.max_depth_error > 0:
            raise ConfigError(f"max_depth_error must be > 0, got {self.max_depth_error}")
        if self.min_consistent_views < 0:
            raise ConfigError(f"min_consistent_views must be >= 0, got {self.min_consistent_views}")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ConfigError(f"min_confidence must be in [0, 1], got {self.min_confidence}")
        if self.cache_size < 1:
            raise ConfigError(f"cache_size must be >= 1, got {self.cache_size}")
        if self.input_type == "auto" and self.method == "colmap":  # for pvs: by the maps (fuse)
            object.__setattr__(self, "input_type", "geometric")
        if self.method == "colmap" and self.input_type == "filled":
            raise ConfigError("input_type 'filled' needs method 'pvs': COLMAP's fusion reads geometric or "
                              "photometric maps")
        object.__setattr__(self, "colmap_options", tuple(str(o) for o in self.colmap_options))
        parse_colmap_options(self.colmap_options)
        if self.colmap_options and self.method != "colmap":
            logger.warning("colmap_options are ignored with method=%r", self.method)


@dataclass
class FuseResult:
    """What :func:`fuse` wrote.

    Attributes:
        output_path / vis_path: the PLY and its ``.vis``.
        num_points: fused points.
        num_images: images whose maps were fused.
        points_per_image: ``{reference name: points it contributed}`` (``pvs`` only).
        skipped: ``{name: reason}`` for listed images without maps.
        seconds: wall time.
    """

    output_path: Path
    vis_path: Path
    method: str
    num_points: int = 0
    num_images: int = 0
    points_per_image: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0
