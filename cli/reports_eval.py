"""Readable tables for ``evaluate depth`` and ``evaluate cloud`` (the library returns data)."""

from __future__ import annotations

import math


def _fmt(value: float, spec: str) -> str:
    return "-" if value is None or not math.isfinite(value) else format(value, spec)


def format_table(header: list[str], rows: list[list[str]], align_left: int = 1) -> str:
    """Plain-text table; the first ``align_left`` columns are left-aligned, the rest right-aligned."""
    widths = [max(len(r[c]) for r in [header, *rows]) for c in range(len(header))]

    def line(r: list[str]) -> str:
        cells = [f"{v:<{widths[c]}}" if c < align_left else f"{v:>{widths[c]}}" for c, v in enumerate(r)]
        return "  ".join(cells).rstrip()

    head = line(header)
    return "\n".join([head, "-" * len(head), *(line(r) for r in rows)])


def depth_stats_row(label: str, stats) -> list[str]:
    """One table row of a :class:`colmap_pvs.evaluate.DepthErrorStats`."""
    return [
        label,
        _fmt(stats.coverage_pct, ".1f"),
        _fmt(stats.mae, ".4f"),
        _fmt(stats.rmse, ".4f"),
        _fmt(stats.absrel, ".4f"),
        *(_fmt(v, ".1f") for v in stats.rel_under_pct.values()),
        *(_fmt(v, ".1f") for v in stats.abs_under_pct.values()),
    ]


def depth_stats_header(stats, first: str = "image") -> list[str]:
    return [
        first,
        "cover%",
        "MAE",
        "RMSE",
        "AbsRel",
        *(f"<{100 * t:g}%rel" for t in stats.rel_under_pct),
        *(f"<{t:g}abs" for t in stats.abs_under_pct),
    ]


def report_depth(metrics, per_image: bool = True) -> str:
    """Per-image and pooled depth metrics of :func:`colmap_pvs.evaluate.evaluate_depth`."""
    pooled = metrics.pooled
    rows = [depth_stats_row(name, s) for name, s in metrics.per_image.items()] if per_image else []
    rows.append(depth_stats_row(f"POOLED ({len(metrics.per_image)} images)", pooled))
    lines = [
        format_table(depth_stats_header(pooled), rows),
        "",
        "errors over pixels valid in both prediction and GT; cover% = % of valid GT pixels with a "
        "prediction; '%' columns = % of those pixels under the threshold (abs thresholds in scene units)",
    ]
    if metrics.config.scale_alignment == "median":
        lines.append("predictions were scaled per image by median(gt / pred) before comparison")
    if metrics.missing_prediction:
        lines.append(
            f"{len(metrics.missing_prediction)} listed image(s) had no prediction (coverage 0): "
            + ", ".join(metrics.missing_prediction[:10])
            + (" ..." if len(metrics.missing_prediction) > 10 else "")
        )
    if metrics.missing_gt:
        lines.append(
            f"{len(metrics.missing_gt)} predicted image(s) had no GT (not evaluated): "
            + ", ".join(metrics.missing_gt[:10])
            + (" ..." if len(metrics.missing_gt) > 10 else "")
        )
    if metrics.sparsification is not None:  # AbsRel of the most-confident fraction kept vs. the oracle
        sp = metrics.sparsification
        lines.append("sparsification (AbsRel of the most confident fraction kept / oracle):")
        lines.append("  " + "  ".join(
            f"{f:.0%}: {_fmt(e, '.4f')}/{_fmt(o, '.4f')}"
            for f, e, o in zip(sp["fractions"], sp["error"], sp["oracle"], strict=True)
        ))
        if "relative_ause" in sp:
            lines.append("relative AUSE (0 = the oracle's ranking, 1 = chance): "
                         + _fmt(sp["relative_ause"], ".3f"))
    if metrics.calibration is not None:  # the confidence as a probability: predicted vs observed
        cal = metrics.calibration
        lines.append(f"confidence calibration (P(relative error <= {cal['tolerance']:g}); expected "
                     f"calibration error {cal['ece']:.3f}), per bin of confidence: predicted/observed:")
        lines.append("  " + "  ".join(
            f"{lo:.1f}-{hi:.1f}: {p:.2f}/{o:.2f}"
            for lo, hi, n, p, o in zip(cal["edges"][:-1], cal["edges"][1:], cal["count"], cal["predicted"],
                                       cal["observed"], strict=True) if n
        ))
    if metrics.checkpoint_used is None:
        ckpt = "unknown (no stereo/colmap_pvs_stereo.json)"
    elif metrics.checkpoint_sha256 is None:
        ckpt = f"{metrics.checkpoint_used} (file gone: no sha256)"
    else:
        ckpt = f"{metrics.checkpoint_used} (sha256 {metrics.checkpoint_sha256[:16]}...)"
    lines.append(f"checkpoint: {ckpt}   metrics: {metrics.output_path}")
    return "\n".join(lines)


def report_cloud(metrics) -> str:
    """Accuracy / completeness / F1 per tolerance and DTU distances of ``evaluate cloud``."""
    header = ["tolerance", "accuracy%", "completeness%", "F1%", "acc% (points)", "comp% (points)"]
    rows = [
        [
            f"{t:g}",
            _fmt(a, ".2f"),
            _fmt(c, ".2f"),
            _fmt(f, ".2f"),
            _fmt(ap, ".2f"),
            _fmt(cp, ".2f"),
        ]
        for t, a, c, f, ap, cp in zip(
            metrics.thresholds,
            metrics.accuracy_pct,
            metrics.completeness_pct,
            metrics.f1_pct,
            metrics.accuracy_points_pct,
            metrics.completeness_points_pct,
            strict=True,
        )
    ]
    lines = [
        f"reconstruction: {metrics.num_points} points   GT: {metrics.num_gt_points} points",
        format_table(header, rows),
        "ETH3D-style (voxel-normalised; every reconstruction point treated as observed)",
        f"DTU-style mean distance: accuracy {_fmt(metrics.dtu_accuracy, '.4g')} "
        f"({_fmt(metrics.dtu_accuracy_outlier_pct, '.1f')}% outliers), completeness "
        f"{_fmt(metrics.dtu_completeness, '.4g')} ({_fmt(metrics.dtu_completeness_outlier_pct, '.1f')}% "
        f"outliers), overall {_fmt(metrics.dtu_overall, '.4g')}",
    ]
    if metrics.output_path is not None:
        lines.append(f"metrics: {metrics.output_path}")
    return "\n".join(lines)
