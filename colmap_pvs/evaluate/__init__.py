"""The ``evaluate`` steps: depth maps against GT depth (:mod:`.depth`), point clouds against a GT
cloud (:mod:`.cloud`).

The public names of both modules are importable from here (the CLI table names
``colmap_pvs.evaluate:EvaluateDepthConfig`` and friends).
"""

from __future__ import annotations

from .cloud import CloudMetrics, EvaluateCloudConfig, cloud_metrics, evaluate_cloud
from .depth import (
    GT_EXTENSIONS,
    METRICS_NOTE,
    SPARSIFICATION_FRACTIONS,
    STEREO_RECORD,
    DepthErrorStats,
    DepthMetrics,
    EvaluateDepthConfig,
    compute_depth_metrics,
    evaluate_depth,
    find_gt_depth,
    read_gt_depth,
    relative_ause,
    sparsification_curve,
    thin_structure_mask,
)

__all__ = [
    "GT_EXTENSIONS",
    "METRICS_NOTE",
    "SPARSIFICATION_FRACTIONS",
    "STEREO_RECORD",
    "CloudMetrics",
    "DepthErrorStats",
    "DepthMetrics",
    "EvaluateCloudConfig",
    "EvaluateDepthConfig",
    "cloud_metrics",
    "compute_depth_metrics",
    "evaluate_cloud",
    "evaluate_depth",
    "find_gt_depth",
    "read_gt_depth",
    "relative_ause",
    "sparsification_curve",
    "thin_structure_mask",
]
