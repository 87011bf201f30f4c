"""Fit or check the confidence calibration: confidence score -> P(depth within a tolerance).

``colmap-pvs stereo`` writes calibrated confidence maps (:mod:`colmap_pvs.confidence`). This tool makes
the calibration from workspaces with known depth, and checks any calibration against known depth.

Fit (on maps of uncalibrated scores: stereo run with a copy of the checkpoint that has no
``NAME.calibration.json`` beside it; GT per workspace is found as ``evaluate depth`` finds it)::

    mkdir raw && cp colmap_pvs/weights/pvsnet_default.pt raw/
    colmap-pvs stereo --workspace_path W --checkpoint raw/pvsnet_default.pt
    python tools/calibrate_confidence.py fit --workspaces W1 W2 ... --gt gt/depth_maps \\
        --gt_pattern {name} --kinds photometric geometric --out raw/pvsnet_default.calibration.json

``filled`` scores are made from the photometric and geometric probabilities on disk, so fit it after
the others: rerun stereo with that calibration beside the copy (no ``filled`` curve yet, so the filled
maps hold scores) and ``fit --kinds filled --start raw/pvsnet_default.calibration.json --out ...``.
The result goes beside the checkpoint it was fitted for.

Check (calibrated maps against GT: per kind the reliability table and the expected calibration error;
``--apply cal.json`` calibrates the scores of raw maps first)::

    python tools/calibrate_confidence.py check --workspaces W --gt DIR --gt_scale 0.001

``--gt`` is relative to each workspace unless absolute. Teacher labels (``tools/teacher_labels.py``,
``stereo/depth_maps/NAME.teacher.bin``) serve as GT with ``--gt teacher``.
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np

from colmap_pvs.confidence import (
    DEFAULT_CALIBRATION,
    KINDS,
    calibration_from_dict,
    fit_curve,
    load_calibration,
    reliability,
)
from colmap_pvs.evaluate.depth import find_gt_depth, read_gt_depth
from colmap_pvs.io.maps import read_array, read_depth_map
from colmap_pvs.io.workspace import detect_workspace
from colmap_pvs.upsampling import resize_nearest

logger = logging.getLogger("calibrate_confidence")


def pairs(ws_path: Path, kind: str, gt: str, pattern: str,
          scale: float | None) -> tuple[np.ndarray, np.ndarray]:
    """``(confidence, relative error)`` of every valid pixel of ``kind`` maps with GT in ``ws_path``."""
    ws = detect_workspace(ws_path, create_stereo_dirs=False)
    suffix = f".{kind}.bin"
    conf_all, err_all = [], []
    for path in sorted(ws.depth_maps_dir.rglob(f"*{suffix}")):
        name = path.relative_to(ws.depth_maps_dir).as_posix()[: -len(suffix)]
        if gt == "teacher":
            gt_path = ws.depth_maps_dir / f"{name}.teacher.bin"
            if not gt_path.is_file():
                continue
            g = read_depth_map(gt_path)
        else:
            gt_dir = Path(gt) if Path(gt).is_absolute() else ws_path / gt
            gt_path = find_gt_depth(gt_dir, name, pattern)
            if gt_path is None:
                continue
            g = read_gt_depth(gt_path, scale)
        conf_path = ws.confidence_map_path(name, kind)
        if not conf_path.is_file():
            continue
        d = read_depth_map(path)
        g = resize_nearest(g, *d.shape) if g.shape != d.shape else g
        c = read_array(conf_path).reshape(d.shape)
        ok = (d > 0) & (g > 0) & np.isfinite(g)
        conf_all.append(c[ok])
        err_all.append(np.abs(d[ok] - g[ok]) / g[ok])
    if not conf_all:
        return np.zeros(0, np.float32), np.zeros(0, np.float32)
    return np.concatenate(conf_all), np.concatenate(err_all)


def collect(args, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """Pooled pairs of every workspace, each workspace weighted alike (subsampled to its share)."""
    confs, errs = [], []
    for w in args.workspaces:
        c, e = pairs(Path(w), kind, args.gt, args.gt_pattern, args.gt_scale)
        logger.info("%s %s: %d pixels with GT", w, kind, c.size)
        if c.size > args.pixels_per_workspace:  # every workspace counts alike
            pick = np.random.default_rng(0).choice(c.size, args.pixels_per_workspace, replace=False)
            c, e = c[pick], e[pick]
        confs.append(c)
        errs.append(e)
    return np.concatenate(confs), np.concatenate(errs)


def git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              check=True, cwd=Path(__file__).parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def fit(args) -> int:
    start = {} if args.start is None else json.loads(Path(args.start).read_text())
    out = {"tolerance": args.tolerance, "curves": dict(start.get("curves", {})),
           "fit": dict(start.get("fit", {}))}
    if start and abs(float(start.get("tolerance", args.tolerance)) - args.tolerance) > 1e-12:
        raise SystemExit(f"--start {args.start} was fitted at another tolerance ({start['tolerance']})")
    for kind in args.kinds:
        conf, err = collect(args, kind)
        if conf.size == 0:
            raise SystemExit(f"no {kind} pixels with GT in {args.workspaces}")
        correct = err <= args.tolerance
        curve = fit_curve(conf, correct)
        out["curves"][kind] = {"score": list(curve.score), "prob": list(curve.prob)}
        before, after = reliability(np.clip(conf, 0, 1), correct), reliability(curve(conf), correct)
        out["fit"][kind] = {"data": args.data, "workspaces": [Path(w).name for w in args.workspaces],
                            "gt": args.gt,
                            "pixels": int(conf.size), "correct_pct": float(correct.mean() * 100),
                            "ece_raw": before.ece, "ece_fitted": after.ece, "commit": git_commit()}
        print(f"{kind}: {conf.size} pixels, {correct.mean() * 100:.1f} % within {args.tolerance:g}; "
              f"ECE of the raw score {before.ece:.3f}, fitted {after.ece:.3f}")
    calibration_from_dict(out, args.out)  # refuse to write what would not load
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


def check(args) -> int:
    tolerance = args.tolerance or load_calibration(args.calibration or DEFAULT_CALIBRATION).tolerance
    apply = None if args.apply is None else load_calibration(args.apply)
    for kind in args.kinds:
        conf, err = collect(args, kind)
        if apply is not None:  # maps made with --confidence_calibration raw, calibrated here
            conf = apply.apply(kind, conf)
        if conf.size == 0:
            print(f"{kind}: no pixels with GT")
            continue
        rel = reliability(conf, err <= tolerance, bins=args.bins)
        print(f"{kind}: {conf.size} pixels, {np.mean(err <= tolerance) * 100:.1f} % within {tolerance:g}, "
              f"mean confidence {conf.mean():.3f}; ECE {rel.ece:.3f}")
        print("   bin         pixels  predicted  observed")
        for i, n in enumerate(rel.count):
            if n:
                print(f"   {rel.edges[i]:.1f}-{rel.edges[i + 1]:.1f}  {n:9d}  {rel.predicted[i]:9.3f}"
                      f"  {rel.observed[i]:8.3f}")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    for name in ("fit", "check"):
        q = sub.add_parser(name)
        q.add_argument("--workspaces", nargs="+", type=Path, required=True)
        q.add_argument("--gt", required=True, help="GT folder (relative to each workspace) or 'teacher'")
        q.add_argument("--gt_pattern", default="{stem}")
        q.add_argument("--gt_scale", type=float, default=None)
        q.add_argument("--kinds", nargs="+", choices=KINDS, default=list(KINDS))
        q.add_argument("--pixels_per_workspace", type=int, default=2_000_000)
    f = sub.choices["fit"]
    f.add_argument("--tolerance", type=float, default=0.05, help="relative depth error counted as right")
    f.add_argument("--start", default=None, help="a calibration whose other curves are kept")
    f.add_argument("--data", default="", help="what the workspaces are (recorded in the file)")
    f.add_argument("--out", required=True)
    c = sub.choices["check"]
    c.add_argument("--calibration", default=None, help="whose tolerance to check (default: the shipped)")
    c.add_argument("--tolerance", type=float, default=None, help="instead of the calibration's")
    c.add_argument("--bins", type=int, default=10)
    c.add_argument("--apply", default=None, help="calibrate raw maps' scores with this calibration first")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    return fit(args) if args.command == "fit" else check(args)


if __name__ == "__main__":
    sys.exit(main())
