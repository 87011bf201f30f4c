"""The ``evaluate depth`` step: the depth maps of a workspace against GT depth maps.

Every ``stereo/depth_maps/NAME.{geometric|photometric}.bin`` of a workspace is compared with
a GT depth map found in a folder by a configurable name pattern (``{stem}`` by default: the
image name without its extension, so ``frame.jpg`` -> ``GT/frame.npy`` or ``GT/frame.png``).
GT maps are ``.npy`` arrays, 16-bit / float PNG or TIFF; integer GT needs an explicit
``gt_scale`` (e.g. ``0.001`` for millimetres), float GT defaults to scale 1 (scene units).
GT of a different size is resized to the prediction's size with nearest-neighbour sampling at
pixel centres (prediction pixel ``(c, r)`` reads GT pixel
``(floor((c + 0.5) W_gt / W), floor((r + 0.5) H_gt / H))``); depths are never interpolated.

Validity: a GT pixel is valid when finite and ``> 0`` (and ``<= max_gt_depth`` if set); a
prediction pixel when finite and ``> 0``. **Error metrics (MAE, RMSE, AbsRel, % under
thresholds) are computed over the pixels valid in both**; ``coverage`` is the percentage of
valid GT pixels that have a valid prediction. Report both: a method can trade coverage for error.

- MAE ``= mean |p - g|``, RMSE ``= sqrt(mean (p - g)^2)``, AbsRel ``= mean |p - g| / g``;
- ``rel_under_pct[t]`` = % of pixels with ``|p - g| / g < t``;
- ``abs_under_pct[t]`` = % of pixels with ``|p - g| < t`` (``t`` in scene units).

"Pooled" statistics sum over all pixels of all evaluated images (images with more valid
pixels weigh more). Images listed in ``images`` without a prediction count as coverage 0.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from tqdm import tqdm

from .. import __version__
from ..confidence import reliability
from ..config import config_json_bytes
from ..errors import ConfigError, MapFormatError, ShapeError, WorkspaceError
from ..io.files import atomic_write_bytes, file_sha256
from ..upsampling import resize_nearest

logger = logging.getLogger(__name__)

__all__ = [
    "DepthErrorStats",
    "DepthMetrics",
    "EvaluateDepthConfig",
    "compute_depth_metrics",
    "evaluate_depth",
    "find_gt_depth",
    "read_gt_depth",
    "relative_ause",
    "sparsification_curve",
    "thin_structure_mask",
]

GT_EXTENSIONS = (".npy", ".png", ".tif", ".tiff")
# colmap_pvs.stereo.CONFIG_FILENAME (not imported: that would pull in torch and the model).
STEREO_RECORD = "colmap_pvs_stereo.json"
METRICS_NOTE = (
    "MAE, RMSE, AbsRel and the % under thresholds are computed over pixels valid in both the "
    "prediction and the GT; coverage_pct = % of valid GT pixels with a valid prediction"
)


def check_thresholds(name: str, values: tuple[float, ...]) -> None:
    """Raise :class:`ConfigError` naming ``name`` unless every tolerance is a positive number."""
    bad = [v for v in values if not (math.isfinite(v) and v > 0)]
    if bad:
        raise ConfigError(f"{name} must be positive numbers, got {values!r} (bad: {bad})")


@dataclass(frozen=True)
class EvaluateDepthConfig:
    """Settings of ``evaluate depth`` (the single source of its defaults and CLI flags)."""

    workspace_path: Path = field(metadata={"help": "COLMAP dense workspace with stereo/depth_maps"})
    gt: Path = field(metadata={"help": "folder of GT depth maps (.npy in scene units, or 16-bit PNG)"})
    kind: Literal["geometric", "photometric", "filled"] = field(
        default="geometric",
        metadata={"help": "which predicted depth maps to evaluate (filled: the geometric maps, completed)"},
    )
    gt_pattern: str = field(
        default="{stem}",
        metadata={
            "help": "GT file name (relative to --gt) of an image; {name}: image name, {stem}: image name "
            "without extension (then, where none is found, with it: the demo's NAME.EXT.npy). Without a "
            "known extension, .npy/.png/.tif/.tiff are tried in turn"
        },
    )
    gt_scale: float | None = field(
        default=None,
        metadata={
            "help": "GT depth = stored value * gt_scale (e.g. 0.001 for uint16 millimetres); "
            "default: 1 for float GT, required for integer GT"
        },
    )
    images: tuple[str, ...] = field(
        default=(),
        metadata={
            "help": "evaluate only these image names; listed images without a prediction count as "
            "coverage 0 (default: every predicted map)"
        },
    )
    rel_thresholds: tuple[float, ...] = field(
        default=(0.01, 0.02, 0.05), metadata={"help": "relative-error thresholds for '% under' (0.01 = 1%)"}
    )
    abs_thresholds: tuple[float, ...] = field(
        default=(0.01, 0.02, 0.05, 0.1),
        metadata={"help": "absolute-error thresholds for '% under', in scene units"},
    )
    max_gt_depth: float = field(
        default=0.0, metadata={"help": "ignore GT pixels deeper than this (scene units); 0: no limit"}
    )
    scale_alignment: Literal["none", "median"] = field(
        default="none",
        metadata={
            "help": "'median': scale each prediction by median(gt / pred) first (for models whose scale "
            "is arbitrary, e.g. plain SfM); 'none': compare as is"
        },
    )
    output_path: Path | None = field(
        default=None, metadata={"help": "metrics JSON; default: WORKSPACE/stereo/metrics.json"}
    )

    def __post_init__(self) -> None:
        check_thresholds("rel_thresholds", self.rel_thresholds)
        check_thresholds("abs_thresholds", self.abs_thresholds)
        if self.gt_scale is not None and not (math.isfinite(self.gt_scale) and self.gt_scale > 0):
            raise ConfigError(f"gt_scale must be a positive number, got {self.gt_scale}")
        if not (math.isfinite(self.max_gt_depth) and self.max_gt_depth >= 0):
            raise ConfigError(f"max_gt_depth must be >= 0 (0: no limit), got {self.max_gt_depth}")
        if "{name}" not in self.gt_pattern and "{stem}" not in self.gt_pattern:
            raise ConfigError(f"gt_pattern must contain {{name}} or {{stem}}, got {self.gt_pattern!r}")


@dataclass(frozen=True)
class DepthErrorStats:
    """Depth errors of one image (or pooled over images).

    Attributes:
        num_gt: valid GT pixels.
        num_valid: pixels valid in both prediction and GT (the error metrics use these).
        coverage_pct: ``100 * num_valid / num_gt`` (``nan`` without valid GT).
        mae, rmse, absrel: mean absolute error, root mean square error (scene units), mean
            absolute relative error (``nan`` when ``num_valid == 0``).
        rel_under_pct: relative threshold -> % of the ``num_valid`` pixels with ``|p-g|/g < t``.
        abs_under_pct: absolute threshold -> % of the ``num_valid`` pixels with ``|p-g| < t``.
        scale: the scale applied to the prediction (1 unless ``scale_alignment="median"``).
    """

    num_gt: int
    num_valid: int
    coverage_pct: float
    mae: float
    rmse: float
    absrel: float
    rel_under_pct: dict[float, float]
    abs_under_pct: dict[float, float]
    scale: float = 1.0

    def to_json(self) -> dict:
        """JSON-compatible dict (``nan`` becomes ``None``; threshold keys become strings)."""

        def num(v: float) -> float | None:
            return None if not math.isfinite(v) else float(v)

        return {
            "num_gt": self.num_gt,
            "num_valid": self.num_valid,
            "coverage_pct": num(self.coverage_pct),
            "mae": num(self.mae),
            "rmse": num(self.rmse),
            "absrel": num(self.absrel),
            "rel_under_pct": {f"{k:g}": num(v) for k, v in self.rel_under_pct.items()},
            "abs_under_pct": {f"{k:g}": num(v) for k, v in self.abs_under_pct.items()},
            "scale": num(self.scale),
        }


@dataclass
class _DepthSums:
    """Additive sums from which :class:`DepthErrorStats` follow exactly (so pooling is exact)."""

    rel_thresholds: tuple[float, ...]
    abs_thresholds: tuple[float, ...]
    num_gt: int = 0
    num_valid: int = 0
    sum_abs: float = 0.0
    sum_sq: float = 0.0
    sum_rel: float = 0.0
    rel_counts: np.ndarray = field(default=None)  # type: ignore[assignment]
    abs_counts: np.ndarray = field(default=None)  # type: ignore[assignment]
    scale: float = 1.0

    def __post_init__(self) -> None:
        if self.rel_counts is None:
            self.rel_counts = np.zeros(len(self.rel_thresholds), dtype=np.int64)
        if self.abs_counts is None:
            self.abs_counts = np.zeros(len(self.abs_thresholds), dtype=np.int64)

    def add(self, other: _DepthSums) -> None:
        self.num_gt += other.num_gt
        self.num_valid += other.num_valid
        self.sum_abs += other.sum_abs
        self.sum_sq += other.sum_sq
        self.sum_rel += other.sum_rel
        self.rel_counts += other.rel_counts
        self.abs_counts += other.abs_counts

    def stats(self) -> DepthErrorStats:
        n = self.num_valid
        nan = float("nan")

        def pct(count: int) -> float:
            return 100.0 * float(count) / n if n else nan

        return DepthErrorStats(
            num_gt=int(self.num_gt),
            num_valid=int(n),
            coverage_pct=100.0 * n / self.num_gt if self.num_gt else nan,
            mae=self.sum_abs / n if n else nan,
            rmse=math.sqrt(self.sum_sq / n) if n else nan,
            absrel=self.sum_rel / n if n else nan,
            rel_under_pct={t: pct(c) for t, c in zip(self.rel_thresholds, self.rel_counts, strict=True)},
            abs_under_pct={t: pct(c) for t, c in zip(self.abs_thresholds, self.abs_counts, strict=True)},
            scale=self.scale,
        )


def thin_structure_mask(depth: np.ndarray, width: int = 4, gap: float = 0.8) -> np.ndarray:
    """``[H, W]`` bool: the pixels of structures at most ``width`` pixels across, along a row or a
    column, whose depth is below ``gap`` times the depth on both sides of them (fronds, poles, a
    crown's prongs in front of what is behind them). ``depth`` is ``[H, W]``, 0 = no surface (treated
    as infinitely far); the ``width`` pixels along the image border are never in the mask.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ShapeError(f"thin_structure_mask expects an [H, W] depth map, got shape {depth.shape}")
    integer = isinstance(width, (int, np.integer)) and not isinstance(width, bool)
    if not integer or width < 1 or not 0 < gap < 1:
        raise ConfigError(
            f"thin_structure_mask needs an integer width >= 1 and 0 < gap < 1, got {width!r}, {gap!r}"
        )
    d = np.where(depth > 0, depth, np.inf)
    thin = np.zeros(depth.shape, bool)
    for axis in (0, 1):
        for before in range(1, width + 1):  # the structure spans before + after - 1 <= width pixels
            for after in range(1, width + 2 - before):
                thin |= (d < gap * np.roll(d, before, axis)) & (d < gap * np.roll(d, -after, axis))
    thin &= depth > 0
    thin[:width] = thin[-width:] = thin[:, :width] = thin[:, -width:] = False
    return thin


def _depth_sums(
    pred: np.ndarray,
    gt: np.ndarray,
    rel_thresholds: tuple[float, ...],
    abs_thresholds: tuple[float, ...],
    max_gt_depth: float = 0.0,
    scale_alignment: str = "none",
) -> _DepthSums:
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.ndim != 2 or gt.ndim != 2:
        raise ShapeError(f"expected [H, W] prediction and GT, got shapes {pred.shape} and {gt.shape}")
    if gt.shape != pred.shape:
        gt = resize_nearest(gt, *pred.shape)
    gt_valid = np.isfinite(gt) & (gt > 0)
    if max_gt_depth > 0:
        gt_valid &= gt <= max_gt_depth
    both = gt_valid & np.isfinite(pred) & (pred > 0)
    p, g = pred[both], gt[both]
    scale = 1.0
    if scale_alignment == "median" and p.size:
        scale = float(np.median(g / p))
        p = p * scale
    err = np.abs(p - g)
    rel = err / g
    sums = _DepthSums(tuple(rel_thresholds), tuple(abs_thresholds), scale=scale)
    sums.num_gt = int(gt_valid.sum())
    sums.num_valid = int(both.sum())
    sums.sum_abs = float(err.sum())
    sums.sum_sq = float(np.square(err).sum())
    sums.sum_rel = float(rel.sum())
    sums.rel_counts = np.array([(rel < t).sum() for t in rel_thresholds], dtype=np.int64)
    sums.abs_counts = np.array([(err < t).sum() for t in abs_thresholds], dtype=np.int64)
    return sums


def compute_depth_metrics(
    pred: np.ndarray,
    gt: np.ndarray,
    rel_thresholds: tuple[float, ...] = (0.01, 0.02, 0.05),
    abs_thresholds: tuple[float, ...] = (0.01, 0.02, 0.05, 0.1),
    max_gt_depth: float = 0.0,
    scale_alignment: Literal["none", "median"] = "none",
) -> DepthErrorStats:
    """Depth errors of one predicted map against GT.

    Args:
        pred: ``[H, W]`` predicted depth (``0`` / non-finite = no prediction).
        gt: ``[H', W']`` GT depth in the same units (``0`` / non-finite = invalid); resized to
            ``[H, W]`` with :func:`resize_nearest` when the sizes differ.

    Returns:
        :class:`DepthErrorStats`; errors over pixels valid in both, plus coverage.
    """
    return _depth_sums(pred, gt, rel_thresholds, abs_thresholds, max_gt_depth, scale_alignment).stats()


def find_gt_depth(gt_dir: Path, name: str, pattern: str = "{stem}") -> Path | None:
    """GT file of image ``name`` in ``gt_dir`` following ``pattern`` (see :class:`EvaluateDepthConfig`):
    a ``{stem}`` pattern that finds nothing is tried again with the whole name (``000.png`` ->
    ``000.png.npy``, the demo's own layout)."""
    stem = str(Path(name).with_suffix("")) if Path(name).suffix else name
    try:
        rels = [pattern.format(name=name, stem=stem)]
        if "{stem}" in pattern and stem != name:
            rels.append(pattern.format(name=name, stem=name))
    except (KeyError, IndexError, ValueError) as exc:
        raise ConfigError(
            f"gt_pattern {pattern!r} is not a valid pattern ({exc!r}); use {{name}}/{{stem}}"
        ) from None
    for rel in rels:
        base = Path(gt_dir) / rel
        if base.suffix.lower() in GT_EXTENSIONS and base.is_file():
            return base
        for ext in GT_EXTENSIONS:  # also NAME.png.npy, as the demo writes its GT
            candidate = base.with_name(base.name + ext)
            if candidate.is_file():
                return candidate
    return None


def read_gt_depth(path: str | Path, scale: float | None = None) -> np.ndarray:
    """Read a GT depth map as ``[H, W]`` float32 scene units (0 = invalid).

    ``.npy`` arrays, PNG (8/16-bit, or float via TIFF) are supported. Integer data needs ``scale``
    (stored value * scale = depth); float data defaults to scale 1.

    Raises:
        MapFormatError: unreadable file, not a single-channel map.
        ConfigError: integer GT without ``scale``.
    """
    path = Path(path)
    if path.suffix.lower() == ".npy":
        try:
            data = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise MapFormatError(f"cannot read GT depth {str(path)!r}: {exc}") from None
    else:
        import cv2

        data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if data is None:
            raise MapFormatError(f"cannot read GT depth {str(path)!r} (missing, or not an image)")
    data = np.asarray(data)
    if data.ndim == 3 and data.shape[2] == 1:
        data = data[:, :, 0]
    if data.ndim != 2:
        raise MapFormatError(
            f"GT depth {str(path)!r} must be a single-channel [H, W] map, got shape {data.shape}"
        )
    if np.issubdtype(data.dtype, np.integer) or data.dtype == np.bool_:
        if scale is None:
            raise ConfigError(
                f"GT depth {str(path)!r} stores integers ({data.dtype}); pass gt_scale "
                "(e.g. 0.001 for millimetres) to convert them to scene units"
            )
    elif not np.issubdtype(data.dtype, np.floating):
        raise MapFormatError(f"GT depth {str(path)!r} has unsupported dtype {data.dtype}")
    depth = data.astype(np.float64) * (1.0 if scale is None else float(scale))
    return depth.astype(np.float32)


def _stereo_run_info(stereo_dir: Path) -> tuple[dict | None, str | None, str | None]:
    """``(stereo config json, checkpoint path, checkpoint sha256)`` from the stereo step's record."""
    record = stereo_dir / STEREO_RECORD
    if not record.is_file():
        logger.warning("no %s: the checkpoint used for these maps is unknown", record)
        return None, None, None
    try:
        info = json.loads(record.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        logger.warning("cannot read %s (%s): the checkpoint used is unknown", record, exc)
        return None, None, None
    ckpt = info.get("checkpoint_used") if isinstance(info, dict) else None
    sha = None
    if ckpt:
        if Path(ckpt).is_file():
            sha = file_sha256(ckpt)
        else:
            logger.warning("checkpoint %r recorded in %s no longer exists: no hash", ckpt, record)
    return info, ckpt, sha


def _predicted_names(depth_dir: Path, kind: str) -> list[str]:
    suffix = f".{kind}.bin"
    if not depth_dir.is_dir():
        return []
    return sorted(
        p.relative_to(depth_dir).as_posix()[: -len(suffix)]
        for p in depth_dir.rglob(f"*{suffix}")
        if p.is_file()
    )


@dataclass
class DepthMetrics:
    """Result of :func:`evaluate_depth`.

    Attributes:
        per_image: image name -> its :class:`DepthErrorStats`, in name order.
        pooled: statistics pooled over every pixel of every evaluated image.
        missing_gt: predicted images without a GT file (not evaluated).
        missing_prediction: images listed in ``config.images`` without a predicted map (counted
            with coverage 0 in ``pooled``).
        config: the config used; output_path: where the metrics JSON was written.
        checkpoint_used, checkpoint_sha256: from ``stereo/colmap_pvs_stereo.json`` (``None`` if unknown).
    """

    per_image: dict[str, DepthErrorStats]
    pooled: DepthErrorStats
    missing_gt: list[str]
    missing_prediction: list[str]
    config: EvaluateDepthConfig
    output_path: Path
    checkpoint_used: str | None = None
    checkpoint_sha256: str | None = None
    sparsification: dict[str, list[float]] | None = None
    calibration: dict | None = None

    def to_json(self) -> dict:
        return {
            "note": METRICS_NOTE,
            "pooled": self.pooled.to_json(),
            "sparsification": self.sparsification,
            "calibration": self.calibration,
            "per_image": {k: v.to_json() for k, v in self.per_image.items()},
            "missing_gt": list(self.missing_gt),
            "missing_prediction": list(self.missing_prediction),
        }


SPARSIFICATION_FRACTIONS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)


def sparsification_curve(
    confidence: np.ndarray, error: np.ndarray, fractions: tuple[float, ...] = SPARSIFICATION_FRACTIONS
) -> dict[str, list[float]]:
    """Mean ``error`` of the most-confident ``fraction`` of pixels, and of the oracle ranking.

    Args:
        confidence, error: ``[P]`` per pixel (higher confidence = trusted; error e.g. AbsRel).

    Returns:
        ``{"fractions": [...], "error": [...], "oracle": [...]}``: ``error[i]`` is the mean error of
        the ``ceil(fractions[i] * P)`` pixels of highest confidence (ties broken by pixel order),
        ``oracle[i]`` that of the pixels of lowest true error; ``nan`` when ``P == 0``.
    """
    confidence = np.asarray(confidence, np.float64).ravel()
    error = np.asarray(error, np.float64).ravel()
    if confidence.shape != error.shape:
        raise ShapeError(f"confidence {confidence.shape} and error {error.shape} differ")
    P = error.size
    out: dict[str, list[float]] = {"fractions": [float(f) for f in fractions], "error": [], "oracle": []}
    by_conf = np.cumsum(error[np.argsort(-confidence, kind="stable")])
    by_err = np.cumsum(np.sort(error))
    for f in fractions:
        n = int(math.ceil(f * P))
        out["error"].append(float(by_conf[n - 1] / n) if n > 0 else float("nan"))
        out["oracle"].append(float(by_err[n - 1] / n) if n > 0 else float("nan"))
    return out


#: Fractions at which :func:`relative_ause` samples the sparsification curve (1 %, 2 %, ..., 100 %).
AUSE_STEPS = 100


def relative_ause(confidence: np.ndarray, error: np.ndarray, steps: int = AUSE_STEPS) -> float:
    """Relative area under the sparsification error: the area between the sparsification curve of
    ``error`` ranked by ``confidence`` and the oracle's (ranked by ``error`` itself), over the area
    between a random ranking's (the mean error at every fraction) and the oracle's; both curves sampled
    at fractions ``1 / steps, ..., 1`` (ties in pixel order). 0: the oracle's ranking; 1: chance;
    above 1: worse than chance. ``nan`` without pixels or when every error is the same."""
    confidence = np.asarray(confidence, np.float64).ravel()
    error = np.asarray(error, np.float64).ravel()
    if confidence.shape != error.shape:
        raise ShapeError(f"confidence {confidence.shape} and error {error.shape} differ")
    if error.size == 0:
        return float("nan")
    curve = sparsification_curve(confidence, error, tuple((i + 1) / steps for i in range(steps)))
    ours, oracle = np.asarray(curve["error"]), np.asarray(curve["oracle"])
    chance = float(np.sum(error.mean() - oracle))
    return float(np.sum(ours - oracle) / chance) if chance > 0 else float("nan")


def _calibration_tolerance(stereo_dir: Path, name: str, kind: str) -> float | None:
    """The relative tolerance that ``name``'s ``kind`` confidence is a probability for (from its
    provenance: ``colmap_pvs.confidence``); ``None`` for raw scores or without provenance."""
    try:
        settings = json.loads((stereo_dir / "provenance" / f"{name}.{kind}.json").read_text())["settings"]
        return float(settings["confidence_calibration"]["tolerance"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def evaluate_depth(config: EvaluateDepthConfig) -> DepthMetrics:
    """Compare a workspace's predicted depth maps with GT depth; write the metrics JSON atomically.

    Raises:
        WorkspaceError: not a workspace, or no predicted depth map to evaluate.
        ConfigError: missing GT folder, no GT for any predicted image, integer GT without scale.
        MapFormatError: unreadable prediction or GT file.
    """
    from ..io.maps import read_array, read_depth_map
    from ..io.workspace import detect_workspace

    ws = detect_workspace(config.workspace_path, create_stereo_dirs=False)
    gt_dir = Path(config.gt)
    if not gt_dir.is_dir():
        raise ConfigError(f"GT folder {str(gt_dir)!r} does not exist or is not a folder")
    depth_dir = ws.depth_maps_dir
    predicted = _predicted_names(depth_dir, config.kind)
    names = list(config.images) if config.images else predicted
    if not predicted and not config.images:
        raise WorkspaceError(f"no {config.kind} depth maps (*.{config.kind}.bin) under {str(depth_dir)!r}")
    predicted_set = set(predicted)
    rel_t, abs_t = tuple(config.rel_thresholds), tuple(config.abs_thresholds)
    pooled = _DepthSums(rel_t, abs_t)
    per_image: dict[str, DepthErrorStats] = {}
    missing_gt: list[str] = []
    missing_pred: list[str] = []
    warned_aspect = False
    missing_shape: tuple[int, ...] | None = None
    conf_err: list[tuple[np.ndarray, np.ndarray]] = []
    tolerances: set[float | None] = set()  # of the confidence maps evaluated (one, when calibrated)
    for name in tqdm(names, desc="evaluate depth", unit="image", disable=len(names) < 20):
        gt_path = find_gt_depth(gt_dir, name, config.gt_pattern)
        if gt_path is None:
            logger.warning(
                "no GT depth for %r in %s (pattern %r): not evaluated", name, gt_dir, config.gt_pattern
            )
            missing_gt.append(name)
            continue
        gt = read_gt_depth(gt_path, config.gt_scale)
        if name in predicted_set:
            pred = read_depth_map(ws.depth_map_path(name, config.kind))
        else:
            logger.warning("no %s depth map for listed image %r: counted as coverage 0", config.kind, name)
            missing_pred.append(name)
            # Counted at the size of the other predictions (pixels weigh the same in the pool).
            if missing_shape is None:
                missing_shape = (
                    read_depth_map(ws.depth_map_path(predicted[0], config.kind)).shape
                    if predicted
                    else gt.shape
                )
            pred = np.zeros(missing_shape, dtype=np.float32)
        if not warned_aspect and gt.shape != pred.shape:
            sy, sx = gt.shape[0] / pred.shape[0], gt.shape[1] / pred.shape[1]
            if abs(sx / sy - 1.0) > 0.01:
                logger.warning(
                    "GT %s is %dx%d but the prediction is %dx%d: aspect ratios differ by %.1f%% "
                    "(different crops?); resizing anyway",
                    gt_path.name,
                    gt.shape[1],
                    gt.shape[0],
                    pred.shape[1],
                    pred.shape[0],
                    100 * abs(sx / sy - 1),
                )
                warned_aspect = True
        sums = _depth_sums(pred, gt, rel_t, abs_t, config.max_gt_depth, config.scale_alignment)
        conf_path = ws.confidence_map_path(name, config.kind)
        if name in predicted_set and conf_path.is_file() and config.scale_alignment == "none":
            conf = read_array(conf_path).reshape(-1)
            if conf.size == pred.size:  # sparsification: pooled (confidence, AbsRel) of valid pixels
                g = resize_nearest(gt, *pred.shape) if gt.shape != pred.shape else gt
                ok = (pred > 0) & (g > 0) & np.isfinite(g)
                if config.max_gt_depth > 0:
                    ok &= g <= config.max_gt_depth
                conf_err.append((conf[ok.ravel()], np.abs(pred[ok] - g[ok]) / g[ok]))
                tolerances.add(_calibration_tolerance(ws.stereo_dir, name, config.kind))
        if sums.num_gt == 0:
            logger.warning("GT depth %s has no valid pixel", gt_path)
        per_image[name] = sums.stats()
        pooled.add(sums)
    if not per_image:
        raise ConfigError(
            f"no GT depth found in {str(gt_dir)!r} for any of the {len(names)} image(s) "
            f"(pattern {config.gt_pattern!r}, e.g. {names[0]!r} -> "
            f"{config.gt_pattern.format(name=names[0], stem=Path(names[0]).with_suffix(''))!r}.*)"
        )
    pooled_stats = pooled.stats()
    if config.scale_alignment == "median":
        pooled_stats = dataclasses.replace(pooled_stats, scale=float("nan"))  # per-image scales differ
    stereo_info, ckpt, sha = _stereo_run_info(ws.stereo_dir)
    out = Path(config.output_path) if config.output_path is not None else ws.stereo_dir / "metrics.json"
    sparsification = calibration = None
    if conf_err:
        conf, err = np.concatenate([c for c, _ in conf_err]), np.concatenate([e for _, e in conf_err])
        sparsification = {**sparsification_curve(conf, err), "relative_ause": relative_ause(conf, err)}
        if len(tolerances) == 1 and None not in tolerances:  # probabilities: how well they predict
            tolerance = tolerances.pop()
            calibration = {"tolerance": tolerance, **reliability(conf, err <= tolerance).to_dict()}
    metrics = DepthMetrics(
        per_image=per_image,
        pooled=pooled_stats,
        missing_gt=missing_gt,
        missing_prediction=missing_pred,
        config=config,
        output_path=out,
        checkpoint_used=ckpt,
        checkpoint_sha256=sha,
        sparsification=sparsification,
        calibration=calibration,
    )
    atomic_write_bytes(out, config_json_bytes(
        config,
        colmap_pvs_version=__version__,
        checkpoint_used=ckpt,
        checkpoint_sha256=sha,
        stereo_run=stereo_info,
        metrics=metrics.to_json(),
    ))
    logger.info(
        "evaluated %d image(s): coverage %.1f%%, MAE %.4g, AbsRel %.4g -> %s",
        len(per_image),
        pooled_stats.coverage_pct,
        pooled_stats.mae,
        pooled_stats.absrel,
        out,
    )
    return metrics
