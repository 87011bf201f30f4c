"""Calibrated confidence: every confidence map holds the probability that its depth is right.

Each pass first scores its pixels (the photometric pass by its cascade's probability masses and their
agreement, by its agreement with the sparse prior and by how well a local plane fits its depth; the
geometric pass by the visibility- and parallax-weighted share of confirming sources, the deviation from
the local plane and the network's probability; the completion by how a pixel was made, times the
network's probability and how well a local plane fits the completed depth; ``docs/CONVENTIONS.md``).
A score ranks the pixels of its own kind but means nothing across kinds. A :class:`Calibration`
turns the score of each kind into ``P(|d - d_true| <= tolerance * d_true)`` (``tolerance`` 5 %) by a
monotone piecewise-linear curve
fitted on pixels with known depth (``tools/calibrate_confidence.py``), so a threshold means the same in
every map and ``evaluate depth`` can check it (:func:`reliability`). The scores depend on the network,
so a calibration belongs to a checkpoint: ``NAME.calibration.json`` beside ``NAME.pt``
(:func:`checkpoint_calibration`); a checkpoint without one writes its scores as they are.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import ConfigError, ShapeError

logger = logging.getLogger(__name__)

#: The shipped checkpoint's calibration (fitted by ``tools/calibrate_confidence.py``; how, inside it).
DEFAULT_CALIBRATION = Path(__file__).resolve().parent / "weights" / "pvsnet_default.calibration.json"
#: The kinds of map a calibration has a curve for (a missing curve leaves that kind's score as it is).
KINDS = ("photometric", "geometric", "filled")
#: Most knots a fitted curve keeps.
MAX_KNOTS = 48
#: Weight of a ramp (0 at a fitted curve's first knot, 1 at its last) blended into it so that it rises
#: strictly (each level moves by at most this): pixels the isotonic fit pools into one level keep the
#: order of their scores.
TIE_BREAK = 1e-3


@dataclass(frozen=True)
class Curve:
    """A monotone map from a score to a probability: knots ``score`` (increasing) and ``prob``
    (non-decreasing, in ``[0, 1]``), linear between them and constant beyond the ends."""

    score: tuple[float, ...]
    prob: tuple[float, ...]

    def __post_init__(self) -> None:
        s, p = np.asarray(self.score, float), np.asarray(self.prob, float)
        if s.ndim != 1 or s.shape != p.shape or s.size < 1:
            raise ConfigError(f"a curve needs as many scores as probabilities, got {s.size} and {p.size}")
        if not (np.isfinite(s).all() and np.isfinite(p).all()):
            raise ConfigError("a curve's scores and probabilities must be finite numbers")
        if np.any(np.diff(s) <= 0) or np.any(np.diff(p) < 0) or p.min() < 0 or p.max() > 1:
            raise ConfigError("a curve's scores must increase and its probabilities rise within [0, 1]")

    def __call__(self, score: np.ndarray) -> np.ndarray:
        return np.interp(np.nan_to_num(score, nan=0.0), self.score, self.prob).astype(np.float32)


@dataclass(frozen=True)
class Calibration:
    """One :class:`Curve` per kind of map (:data:`KINDS`; a kind without one keeps its score),
    for the relative ``tolerance`` they were fitted at, with a free-form ``fit`` record."""

    tolerance: float
    curves: dict[str, Curve]
    fit: dict

    def apply(self, kind: str, score: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """``score`` ``[H, W]`` of a ``kind`` map as probabilities, 0 outside ``valid`` ``[H, W]``
        (default: where the score is positive) and where the score is not finite."""
        if kind not in KINDS:
            raise ConfigError(f"unknown kind of map {kind!r}; expected one of {KINDS}")
        score = np.asarray(score, np.float32)
        valid = score > 0 if valid is None else valid
        if valid.shape != score.shape:
            raise ShapeError(f"valid {valid.shape} must match score {score.shape}")
        valid = valid & np.isfinite(score)
        curve = self.curves.get(kind)
        return np.where(valid, score if curve is None else curve(score), 0.0).astype(np.float32)

    def settings(self, kind: str) -> dict | None:
        """What a ``kind`` map depends on (in its pass's provenance): the curve and the tolerance."""
        curve = self.curves.get(kind)
        if curve is None:
            return None
        return {"tolerance": self.tolerance, "score": list(curve.score), "prob": list(curve.prob)}

    def sha256(self) -> str | None:
        """Hash of what the maps depend on (the tolerance and the curves, not the ``fit`` notes);
        ``None`` without curves."""
        if not self.curves:
            return None
        payload = {kind: self.settings(kind) for kind in sorted(self.curves)}
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


#: Scores written as they are: no curve for any kind (what the calibration tool fits on).
RAW = Calibration(tolerance=0.0, curves={}, fit={"what": "uncalibrated scores"})


def calibration_from_dict(data: dict, where: str = "calibration") -> Calibration:
    """A :class:`Calibration` from its JSON form; unknown keys and kinds are errors naming ``where``."""
    if not isinstance(data, dict) or set(data) - {"tolerance", "curves", "fit"}:
        raise ConfigError(f"{where}: expected an object with the keys tolerance, curves, fit")
    curves, fit = data.get("curves", {}), data.get("fit", {})
    if not isinstance(curves, dict) or not isinstance(fit, dict):
        raise ConfigError(f"{where}: curves and fit must be objects")
    unknown = set(curves) - set(KINDS)
    if unknown:
        raise ConfigError(f"{where}: unknown kinds {sorted(unknown)}; expected some of {KINDS}")
    try:
        tolerance = float(data.get("tolerance", 0.0))
        parsed = {k: Curve(tuple(map(float, c["score"])), tuple(map(float, c["prob"])))
                  for k, c in curves.items()}
    except (KeyError, TypeError, ValueError, ConfigError) as exc:
        raise ConfigError(f"{where}: bad tolerance or curve ({exc})") from exc
    if curves and not 0 < tolerance < 1:
        raise ConfigError(f"{where}: tolerance must be in (0, 1), got {tolerance}")
    return Calibration(tolerance, parsed, dict(fit))


def load_calibration(path: str | Path) -> Calibration:
    """The calibration in the JSON file ``path``."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ConfigError(f"cannot read the confidence calibration {str(path)!r}: {exc}") from exc
    return calibration_from_dict(data, str(path))


def calibration_path(checkpoint: str | Path) -> Path:
    """``NAME.calibration.json`` beside the checkpoint ``NAME.pt``: where its calibration is."""
    checkpoint = Path(checkpoint)
    return checkpoint.with_name(checkpoint.stem + ".calibration.json")


def checkpoint_calibration(checkpoint: str | Path, checkpoint_sha256: str | None = None) -> Calibration:
    """The calibration of ``checkpoint`` (:func:`calibration_path`), or :data:`RAW` with a warning
    when it has none. A calibration fitted for other weights (its ``fit`` records their
    ``checkpoint_sha256``) is used with a warning: the scores of new weights need new curves."""
    path = calibration_path(checkpoint)
    if not path.is_file():
        logger.warning("no confidence calibration for %s (%s): the confidence maps hold uncalibrated "
                       "scores (tools/calibrate_confidence.py makes one)", checkpoint, path.name)
        return RAW
    calibration = load_calibration(path)
    fitted_for = {fit.get("checkpoint_sha256") for fit in calibration.fit.values() if isinstance(fit, dict)}
    if checkpoint_sha256 is not None and fitted_for - {None} and checkpoint_sha256 not in fitted_for:
        logger.warning("the confidence calibration %s was fitted for other weights than %s: its "
                       "probabilities may be off (refit it with tools/calibrate_confidence.py)",
                       path, checkpoint)
    return calibration


def fit_curve(score: np.ndarray, correct: np.ndarray, max_knots: int = MAX_KNOTS) -> Curve:
    """The isotonic (pool-adjacent-violators) fit of ``P(correct | score)`` over pixels ``score``,
    ``correct`` (same shape, bool; non-finite scores are left out), summarised by at most
    ``max_knots`` knots at score quantiles, blended with a ramp by :data:`TIE_BREAK` so that it rises
    strictly (each level moves by at most that much)."""
    score = np.asarray(score, np.float64).ravel()
    correct = np.asarray(correct, bool).ravel()
    if score.shape != correct.shape:
        raise ShapeError(f"need as many scores as labels, got {score.size} and {correct.size}")
    finite = np.isfinite(score)
    score, correct = score[finite], correct[finite]
    if score.size < 2 * max_knots:
        raise ShapeError(f"need at least {2 * max_knots} pixels with a finite score, got {score.size}")
    order = np.argsort(score, kind="stable")
    score, correct = score[order], correct[order].astype(np.float64)
    # blocks of equal size along the score (so that each level rests on many pixels), then PAV
    edges = np.unique(np.linspace(0, score.size, 4 * max_knots + 1).astype(int))
    means = np.add.reduceat(correct, edges[:-1]) / np.diff(edges)
    centres = np.array([np.median(score[a:b]) for a, b in zip(edges[:-1], edges[1:], strict=True)])
    level, weight, blocks = [], [], []  # pooled levels, their pixels and their blocks
    for m, w in zip(means, np.diff(edges), strict=True):
        level.append(float(m))
        weight.append(float(w))
        blocks.append(1)
        while len(level) > 1 and level[-2] > level[-1]:  # pool the violators
            w2 = weight[-2] + weight[-1]
            level[-2:] = [(level[-2] * weight[-2] + level[-1] * weight[-1]) / w2]
            weight[-2:] = [w2]
            blocks[-2:] = [blocks[-2] + blocks[-1]]
    fitted = np.repeat(level, blocks)
    # blocks of one score value (ties) are one level: their pixel-weighted mean
    xs, group = np.unique(centres, return_inverse=True)
    sizes = np.diff(edges).astype(np.float64)
    ps = np.bincount(group, fitted * sizes) / np.bincount(group, sizes)
    keep = np.unique(np.linspace(0, xs.size - 1, min(max_knots, xs.size)).round().astype(int))
    xs, ps = xs[keep], np.maximum.accumulate(ps[keep])
    ps = np.clip(ps * (1 - TIE_BREAK) + TIE_BREAK * np.linspace(0, 1, ps.size), 0.0, 1.0)
    return Curve(tuple(xs.tolist()), tuple(ps.tolist()))


@dataclass(frozen=True)
class Reliability:
    """How well probabilities ``p`` predicted ``correct``: per bin of ``p`` (``edges``) the pixel
    ``count``, the mean predicted and the observed rate of correct pixels; ``ece`` their
    count-weighted mean absolute gap (expected calibration error)."""

    edges: tuple[float, ...]
    count: tuple[int, ...]
    predicted: tuple[float, ...]
    observed: tuple[float, ...]
    ece: float

    def to_dict(self) -> dict:
        return {"edges": list(self.edges), "count": list(self.count), "predicted": list(self.predicted),
                "observed": list(self.observed), "ece": self.ece}


def reliability(prob: np.ndarray, correct: np.ndarray, bins: int = 10) -> Reliability:
    """:class:`Reliability` of probabilities ``prob`` against outcomes ``correct`` (same shape; pixels
    with a non-finite probability are left out; ``ece`` is NaN when none is left)."""
    prob = np.asarray(prob, np.float64).ravel()
    correct = np.asarray(correct, bool).ravel()
    if prob.shape != correct.shape:
        raise ShapeError(f"prob {prob.shape} and correct {correct.shape} must match")
    finite = np.isfinite(prob)
    prob, correct = np.clip(prob[finite], 0.0, 1.0), correct[finite]
    edges = np.linspace(0.0, 1.0, bins + 1)
    which = np.clip(np.digitize(prob, edges) - 1, 0, bins - 1)
    count = np.bincount(which, minlength=bins)
    pred = np.bincount(which, prob, bins) / np.maximum(count, 1)
    obs = np.bincount(which, correct.astype(np.float64), bins) / np.maximum(count, 1)
    ece = float((np.abs(pred - obs) * count).sum() / count.sum()) if count.sum() else float("nan")
    return Reliability(tuple(edges.tolist()), tuple(int(c) for c in count), tuple(pred.tolist()),
                       tuple(obs.tolist()), ece)
