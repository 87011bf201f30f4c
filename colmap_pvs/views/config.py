"""The parameters of view selection and depth-range estimation."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError

WIDE_SOURCES_HELP = (
    "of the num_views-1 sources, this many (at most half, rounded down) are picked by the MVSNet score "
    "at wide_theta0_deg instead of theta0_deg: wider baselines make the geometric maps more accurate "
    "but sparser (e.g. 2 at N = 5; 0: off)"
)


@dataclass(frozen=True)
class ViewSelectionConfig:
    """Parameters of view selection and depth-range estimation."""

    num_views: int = field(
        default=5,
        metadata={
            "help": "views per reference, the reference included: each reference gets num_views-1 sources"
        },
    )
    theta0_deg: float = field(
        default=5.0,
        metadata={"help": "preferred triangulation angle theta0 (degrees) of the MVSNet view score"},
    )
    sigma1: float = field(
        default=1.0,
        metadata={"help": "width (degrees) of the view-score Gaussian for angles below theta0"},
    )
    sigma2: float = field(
        default=10.0,
        metadata={"help": "width (degrees) of the view-score Gaussian for angles above theta0"},
    )
    coverage_decay: float = field(
        default=0.1,
        metadata={
            "help": "coverage-aware source choice in [0, 1]: sources are picked one at a time by their "
            "MVSNet score over the reference's sparse points, a point already seen by k picked sources "
            "counting decay^k (1: the plain top-N by score; 0: only points no picked source sees)"
        },
    )
    wide_sources: int = field(default=0, metadata={"help": WIDE_SOURCES_HELP})
    wide_theta0_deg: float = field(
        default=15.0,
        metadata={"help": "preferred triangulation angle (degrees) of the wide_sources picks"},
    )
    min_shared_points: int = field(
        default=3,
        metadata={"help": "a source must share at least this many sparse points with the reference"},
    )
    min_points: int = field(
        default=10,
        metadata={
            "help": "an image observing fewer sparse points (in front of it) is skipped as a reference, "
            "with a warning"
        },
    )
    # ``tuple[float, ...]`` validated to two values: config._coerce mishandles fixed-length tuples
    # (``zip(args, value)`` is unpacked as ``(v, a)``), so ``tuple[float, float]`` fails to load.
    depth_percentiles: tuple[float, ...] = field(
        default=(1.0, 99.0),
        metadata={"help": "lower and upper percentiles (0-100) of the sparse points' depths, per image"},
    )
    depth_margin: float = field(
        default=0.25,
        metadata={
            "help": "relative margin m in [0, 1) applied to the percentile range [lo, hi]: "
            "depth range = [lo*(1-m), hi*(1+m)] (0.25 and the 1/99 percentiles are what COLMAP's "
            "own dense workspace uses)"
        },
    )
    depth_near_factor: float = field(
        default=1.0,
        metadata={
            "help": "in (0, 1]: the range's near end times this (0.5 doubles the nearest inverse depth "
            "swept; 1: COLMAP's range)"
        },
    )
    min_depth_ratio: float = field(
        default=1e-3,
        metadata={"help": "guard in (0, 1): the minimum depth is at least min_depth_ratio * maximum depth"},
    )
    depth_outlier_sigmas: float = field(
        default=3.0,
        metadata={
            "help": "points whose log depth is more than this many robust sigmas (1.4826 MAD) and more than "
            "depth_outlier_min_factor away from the median depth are outliers, ignored for the range; "
            "0 disables"
        },
    )
    depth_outlier_min_factor: float = field(
        default=5.0,
        metadata={"help": "points within [median / f, median * f] are never outliers (f > 1)"},
    )
    depth_outlier_max_fraction: float = field(
        default=0.1,
        metadata={
            "help": "if more than this fraction of the points would be outliers they are scene structure "
            "(a background), and all points are kept"
        },
    )

    def __post_init__(self) -> None:
        if self.num_views < 2:
            raise ConfigError(
                f"num_views must be >= 2 (reference + at least one source), got {self.num_views}"
            )
        if not 0.0 <= self.theta0_deg <= 180.0:
            raise ConfigError(f"theta0_deg must be in [0, 180], got {self.theta0_deg}")
        for name in ("sigma1", "sigma2"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a positive number, got {value}")
        if not 0.0 <= self.wide_theta0_deg <= 180.0:
            raise ConfigError(f"wide_theta0_deg must be in [0, 180], got {self.wide_theta0_deg}")
        if self.wide_sources < 0:
            raise ConfigError(f"wide_sources must be >= 0, got {self.wide_sources}")
        if not 0.0 <= self.coverage_decay <= 1.0:
            raise ConfigError(f"coverage_decay must be in [0, 1], got {self.coverage_decay}")
        if self.min_shared_points < 1:
            raise ConfigError(f"min_shared_points must be >= 1, got {self.min_shared_points}")
        if self.min_points < 1:
            raise ConfigError(f"min_points must be >= 1, got {self.min_points}")
        try:
            percentiles = tuple(float(v) for v in self.depth_percentiles)
        except (TypeError, ValueError):
            raise ConfigError(
                f"depth_percentiles must be two numbers, got {self.depth_percentiles!r}"
            ) from None
        object.__setattr__(self, "depth_percentiles", percentiles)
        if len(self.depth_percentiles) != 2:
            raise ConfigError(
                f"depth_percentiles must be two numbers (lo, hi), got {self.depth_percentiles!r}"
            )
        lo, hi = self.depth_percentiles
        if not 0.0 <= lo < hi <= 100.0:
            raise ConfigError(
                f"depth_percentiles must satisfy 0 <= lo < hi <= 100, got {self.depth_percentiles!r}"
            )
        if not 0.0 <= self.depth_margin < 1.0:
            raise ConfigError(f"depth_margin must be in [0, 1), got {self.depth_margin}")
        if not (np.isfinite(self.depth_near_factor) and 0.0 < self.depth_near_factor <= 1.0):
            raise ConfigError(f"depth_near_factor must be in (0, 1], got {self.depth_near_factor}")
        if not 0.0 < self.min_depth_ratio < 1.0:
            raise ConfigError(f"min_depth_ratio must be in (0, 1), got {self.min_depth_ratio}")
        if not (np.isfinite(self.depth_outlier_sigmas) and self.depth_outlier_sigmas >= 0):
            raise ConfigError(f"depth_outlier_sigmas must be >= 0, got {self.depth_outlier_sigmas}")
        if not (np.isfinite(self.depth_outlier_min_factor) and self.depth_outlier_min_factor > 1):
            raise ConfigError(f"depth_outlier_min_factor must be > 1, got {self.depth_outlier_min_factor}")
        if not 0.0 <= self.depth_outlier_max_fraction < 0.5:
            raise ConfigError(
                f"depth_outlier_max_fraction must be in [0, 0.5), got {self.depth_outlier_max_fraction}"
            )
