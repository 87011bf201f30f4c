"""The ``evaluate cloud`` step: a point cloud against a GT point cloud (:func:`evaluate_cloud`).

ETH3D-style accuracy / completeness / F1 at each tolerance, following the official program
(github.com/ETH3D/multi-view-evaluation, ``src/accuracy.cc``, ``src/completeness.cc``):

- completeness: a GT point is *complete* at tolerance ``t`` when its nearest reconstruction point
  is within ``t``; accuracy: a reconstruction point is *accurate* when its nearest GT point is
  within ``t``.
- Density normalisation, exactly as the official program: points are binned into cubic voxels of
  ``voxel_size`` in two grids (shifted by 0 and by half a voxel); the per-voxel fraction of
  complete (accurate) points is averaged over all occupied voxels of both grids.
- F1 ``= 2 P R / (P + R)`` (0 when both are 0), with P = accuracy and R = completeness.

Approximation (documented): the official accuracy uses the laser scanner's beams to mark a
reconstruction point *unobserved* (ignored) when no scan ray passes near it, or *inaccurate*
only when it lies in observed free space. A plain GT ``.ply`` has no scanner origins, so here
**every reconstruction point counts as observed**: points where the GT has no coverage count as
inaccurate. This makes our accuracy a lower bound of ETH3D's on partial GT.
The plain point fractions (no voxel normalisation) are reported too.

DTU-style metrics (Jensen et al. 2014; the MATLAB/Python evaluation): mean distance from the
reconstruction to the GT (accuracy) and from the GT to the reconstruction (completeness) and
their mean ("overall"), with distances ``>= dtu_max_dist`` discarded as outliers (DTU's
convention; ``dtu_outliers="clamp"`` clamps them instead). DTU's observability mask and plane
are not modelled; the optional voxel downsampling of the reconstruction (``dtu_downsample``)
uses open3d's voxel-centroid downsampling instead of DTU's minimum-distance thinning.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from .. import __version__
from ..config import config_json_bytes
from ..errors import ConfigError, ShapeError, WorkspaceError
from ..io.files import atomic_write_bytes
from .depth import check_thresholds

logger = logging.getLogger(__name__)

__all__ = ["CloudMetrics", "EvaluateCloudConfig", "cloud_metrics", "evaluate_cloud"]


@dataclass(frozen=True)
class EvaluateCloudConfig:
    """Settings of ``evaluate cloud`` (the single source of its defaults and CLI flags)."""

    cloud: Path = field(metadata={"help": "reconstructed point cloud (.ply), e.g. fused.ply"})
    gt: Path = field(metadata={"help": "GT point cloud (.ply), same coordinate frame and units"})
    thresholds: tuple[float, ...] = field(
        default=(0.01, 0.02, 0.05, 0.1, 0.2, 0.5),
        metadata={"help": "tolerances (scene units) for accuracy / completeness / F1 (ETH3D's defaults)"},
    )
    voxel_size: float = field(
        default=0.01,
        metadata={
            "help": "voxel size (scene units) of ETH3D's per-volume normalisation (its default 0.01 m)"
        },
    )
    dtu_max_dist: float = field(
        default=0.5,
        metadata={"help": "DTU-style mean distances: distances >= this are outliers (DTU: 20 mm)"},
    )
    dtu_outliers: Literal["discard", "clamp"] = field(
        default="discard", metadata={"help": "DTU outliers are discarded (DTU's convention) or clamped"}
    )
    dtu_downsample: float = field(
        default=0.0,
        metadata={
            "help": "voxel-downsample the reconstruction to this size before the DTU distances; 0: off"
        },
    )
    output_path: Path | None = field(
        default=None, metadata={"help": "metrics JSON; default: CLOUD with suffix .metrics.json"}
    )

    def __post_init__(self) -> None:
        if not self.thresholds:
            raise ConfigError("thresholds must list at least one tolerance")
        check_thresholds("thresholds", self.thresholds)
        object.__setattr__(self, "thresholds", tuple(sorted(float(t) for t in self.thresholds)))
        if not (math.isfinite(self.voxel_size) and self.voxel_size > 0):
            raise ConfigError(f"voxel_size must be a positive number, got {self.voxel_size}")
        if not (math.isfinite(self.dtu_max_dist) and self.dtu_max_dist > 0):
            raise ConfigError(f"dtu_max_dist must be a positive number, got {self.dtu_max_dist}")
        if not (math.isfinite(self.dtu_downsample) and self.dtu_downsample >= 0):
            raise ConfigError(f"dtu_downsample must be >= 0 (0: off), got {self.dtu_downsample}")


@dataclass
class CloudMetrics:
    """Result of :func:`evaluate_cloud` / :func:`cloud_metrics` (percentages in ``[0, 100]``).

    Attributes:
        thresholds: ``[T]`` sorted tolerances.
        accuracy_pct, completeness_pct, f1_pct: ``[T]`` ETH3D-style, voxel-normalised.
        accuracy_points_pct, completeness_points_pct: ``[T]`` plain fractions of points.
        dtu_accuracy, dtu_completeness, dtu_overall: DTU-style mean distances (scene units;
            ``nan`` when every distance is an outlier).
        dtu_accuracy_outlier_pct, dtu_completeness_outlier_pct: % of distances ``>= dtu_max_dist``.
        num_points, num_gt_points: sizes of the two clouds.
    """

    thresholds: tuple[float, ...]
    accuracy_pct: tuple[float, ...]
    completeness_pct: tuple[float, ...]
    f1_pct: tuple[float, ...]
    accuracy_points_pct: tuple[float, ...]
    completeness_points_pct: tuple[float, ...]
    dtu_accuracy: float
    dtu_completeness: float
    dtu_overall: float
    dtu_accuracy_outlier_pct: float
    dtu_completeness_outlier_pct: float
    num_points: int
    num_gt_points: int
    config: EvaluateCloudConfig | None = None
    output_path: Path | None = None

    def to_json(self) -> dict:
        def num(v: float) -> float | None:
            return None if not math.isfinite(v) else float(v)

        out = {k: getattr(self, k) for k in ("num_points", "num_gt_points")}
        for key in (
            "thresholds",
            "accuracy_pct",
            "completeness_pct",
            "f1_pct",
            "accuracy_points_pct",
            "completeness_points_pct",
        ):
            out[key] = [num(v) for v in getattr(self, key)]
        for key in (
            "dtu_accuracy",
            "dtu_completeness",
            "dtu_overall",
            "dtu_accuracy_outlier_pct",
            "dtu_completeness_outlier_pct",
        ):
            out[key] = num(getattr(self, key))
        return out


def _cell_keys(points: np.ndarray, voxel_size: float, shift: float) -> np.ndarray:
    """``[P]`` int64 index of the voxel of each point (ETH3D's ``CalcCellCoordinates``: floor)."""
    cells = np.floor(points / voxel_size + shift).astype(np.int64)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    if float(dims[0]) * float(dims[1]) * float(dims[2]) < 2**62:
        return (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    return np.unique(cells, axis=0, return_inverse=True)[1].reshape(-1)


def _voxel_normalised_pct(points: np.ndarray, good: np.ndarray, voxel_size: float) -> np.ndarray:
    """ETH3D's per-volume average: mean over occupied voxels of two grids (shifts 0 and 1/2) of
    the fraction of ``good`` points in the voxel.

    Args:
        points: ``[P, 3]``; good: ``[T, P]`` bool. Returns ``[T]`` percentages.
    """
    ratios = []
    for shift in (0.0, 0.5):
        _, inverse, counts = np.unique(
            _cell_keys(points, voxel_size, shift), return_inverse=True, return_counts=True
        )
        inverse = inverse.reshape(-1)
        per_t = np.stack(
            [np.bincount(inverse, weights=g, minlength=counts.size) for g in good.astype(np.float64)]
        )
        ratios.append(per_t / counts[None, :])
    return 100.0 * np.concatenate(ratios, axis=1).mean(axis=1)


def _dtu_mean(dist: np.ndarray, max_dist: float, mode: str) -> tuple[float, float]:
    """``(mean distance, % outliers)`` with DTU's outlier rule."""
    if dist.size == 0:
        return float("nan"), float("nan")
    outlier = dist >= max_dist
    pct = 100.0 * float(outlier.mean())
    if mode == "clamp":
        return float(np.minimum(dist, max_dist).mean()), pct
    kept = dist[~outlier]
    return (float(kept.mean()) if kept.size else float("nan")), pct


def _nn_distances(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``[len(source)]`` distance of each source point to its nearest target point (open3d KD-tree)."""
    import open3d as o3d

    if len(source) == 0:
        return np.zeros(0)
    if len(target) == 0:
        return np.full(len(source), np.inf)
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(source, dtype=np.float64)))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(target, dtype=np.float64)))
    return np.asarray(src.compute_point_cloud_distance(tgt), dtype=np.float64)


def cloud_metrics(
    points: np.ndarray,
    gt_points: np.ndarray,
    thresholds: tuple[float, ...] = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5),
    voxel_size: float = 0.01,
    dtu_max_dist: float = 0.5,
    dtu_outliers: Literal["discard", "clamp"] = "discard",
    dtu_downsample: float = 0.0,
) -> CloudMetrics:
    """ETH3D-style and DTU-style metrics of a reconstruction against a GT cloud (see the module doc).

    Args:
        points: ``[P, 3]`` reconstruction; gt_points: ``[G, 3]`` GT (``G >= 1``), same frame and units.
        thresholds: tolerances in scene units (sorted internally).

    An empty reconstruction scores 0 accuracy and completeness (as ETH3D) and ``nan`` DTU distances.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    gt_points = np.asarray(gt_points, dtype=np.float64).reshape(-1, 3)
    if len(gt_points) == 0:
        raise ShapeError("the GT cloud has no points")
    thresholds = tuple(sorted(float(t) for t in thresholds))
    check_thresholds("thresholds", thresholds)
    t = np.asarray(thresholds)[:, None]
    d_gt = _nn_distances(gt_points, points)  # completeness: GT -> reconstruction
    complete = d_gt[None, :] <= t
    comp = _voxel_normalised_pct(gt_points, complete, voxel_size)
    comp_points = 100.0 * complete.mean(axis=1)
    if len(points):
        d_rec = _nn_distances(points, gt_points)  # accuracy: reconstruction -> GT
        accurate = d_rec[None, :] <= t
        acc = _voxel_normalised_pct(points, accurate, voxel_size)
        acc_points = 100.0 * accurate.mean(axis=1)
    else:
        d_rec = np.zeros(0)
        acc = acc_points = np.zeros(len(thresholds))
    f1 = np.where(acc + comp > 0, 2 * acc * comp / np.maximum(acc + comp, 1e-300), 0.0)
    if dtu_downsample > 0 and len(points):
        import open3d as o3d

        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(dtu_downsample)
        d_rec_dtu = _nn_distances(np.asarray(pcd.points), gt_points)
    else:
        d_rec_dtu = d_rec
    dtu_acc, acc_out = _dtu_mean(d_rec_dtu, dtu_max_dist, dtu_outliers)
    dtu_comp, comp_out = _dtu_mean(d_gt if len(points) else np.zeros(0), dtu_max_dist, dtu_outliers)
    return CloudMetrics(
        thresholds=thresholds,
        accuracy_pct=tuple(float(v) for v in acc),
        completeness_pct=tuple(float(v) for v in comp),
        f1_pct=tuple(float(v) for v in f1),
        accuracy_points_pct=tuple(float(v) for v in acc_points),
        completeness_points_pct=tuple(float(v) for v in comp_points),
        dtu_accuracy=dtu_acc,
        dtu_completeness=dtu_comp,
        dtu_overall=0.5 * (dtu_acc + dtu_comp),
        dtu_accuracy_outlier_pct=acc_out,
        dtu_completeness_outlier_pct=comp_out,
        num_points=len(points),
        num_gt_points=len(gt_points),
    )


def _read_cloud(path: Path, what: str) -> np.ndarray:
    """``[P, 3]`` float64 points of a PLY (or any format open3d reads)."""
    import open3d as o3d

    if not path.is_file():
        raise ConfigError(f"{what} {str(path)!r} does not exist")
    pcd = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(pcd.points, dtype=np.float64)
    if not np.isfinite(pts).all():
        n_bad = int((~np.isfinite(pts).all(axis=1)).sum())
        logger.warning("%s %s: dropping %d non-finite point(s)", what, path, n_bad)
        pts = pts[np.isfinite(pts).all(axis=1)]
    return pts


def evaluate_cloud(config: EvaluateCloudConfig) -> CloudMetrics:
    """Evaluate ``config.cloud`` against ``config.gt``; write the metrics JSON atomically.

    Raises:
        ConfigError: a missing file.
        WorkspaceError: an empty or unreadable GT cloud.
    """
    points = _read_cloud(Path(config.cloud), "reconstruction")
    gt_points = _read_cloud(Path(config.gt), "GT cloud")
    if len(gt_points) == 0:
        raise WorkspaceError(f"GT cloud {str(config.gt)!r} has no points")
    if len(points) == 0:
        logger.warning("reconstruction %s has no points: accuracy and completeness are 0", config.cloud)
    logger.info("evaluating %d points against %d GT points", len(points), len(gt_points))
    metrics = cloud_metrics(
        points,
        gt_points,
        thresholds=config.thresholds,
        voxel_size=config.voxel_size,
        dtu_max_dist=config.dtu_max_dist,
        dtu_outliers=config.dtu_outliers,
        dtu_downsample=config.dtu_downsample,
    )
    out = (
        Path(config.output_path)
        if config.output_path is not None
        else Path(config.cloud).with_suffix(".metrics.json")
    )
    metrics.config = config
    metrics.output_path = out
    atomic_write_bytes(out, config_json_bytes(
        config,
        colmap_pvs_version=__version__,
        metrics=metrics.to_json(),
        definition="ETH3D-style (all reconstruction points treated as observed) and DTU-style; "
        "see colmap_pvs.evaluate",
    ))
    return metrics
