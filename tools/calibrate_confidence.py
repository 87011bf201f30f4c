"""Fit or check the confidence calibration: confidence score -> P(depth within a tolerance).

``colmap-pvs stereo`` writes calibrated confidence maps (:mod:`colmap_pvs.confidence`). This tool makes
the calibration from workspaces with known depth, and checks any calibration against known depth.

Fit (on maps of uncalibrated scores: stereo run with a copy of the checkpoint that has no
``NAME.calibration.json`` beside it; GT per workspace is found as ``evaluate depth`` finds it)::

    mkdir raw && cp colmap_pvs/weights/pvsnet_default.pt raw/
    colmap-pvs stereo --workspace_path W --checkpoint raw/pvsnet_default.pt
    python tools/calibrate_confidence.py fit --workspaces W1 W2 ... --gt gt/depth_maps \\
        --gt_pattern {name} --kinds photometric --out cal1.json

The geometric scores are made from the photometric probabilities on disk, and the ``filled`` scores
from the photometric and geometric ones (``READS``), so each is fitted after those it reads: copy
``cal1.json`` beside the raw checkpoint as ``raw/pvsnet_default.calibration.json``, rerun stereo (the
photometric maps are made again with the curve, the later ones hold scores) and ``fit --kinds
geometric --start cal1.json --out cal2.json``; then the same with ``cal2.json`` and ``fit --kinds
filled --start cal2.json --out ...``. The result goes beside the checkpoint it was fitted for.
``fit`` reads each map's provenance: it refuses calibrated maps, maps whose score reads maps made with
other curves than ``--start``'s, and a kind asked for together with one it reads; refitting a kind
drops ``--start``'s curves of the kinds that read it. It records the checkpoint's sha256 (from the
workspaces' stereo run), which ``stereo`` compares with the weights it loads.

Check (calibrated maps against GT, at the tolerance their provenance names: per kind the reliability
table and the expected calibration error; ``--apply cal.json`` calibrates the scores of raw maps first)::

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
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from colmap_pvs.confidence import (
    KINDS,
    calibration_from_dict,
    fit_curve,
    load_calibration,
    reliability,
)
from colmap_pvs.errors import ShapeError
from colmap_pvs.evaluate.depth import find_gt_depth, read_gt_depth
from colmap_pvs.io.maps import read_array, read_depth_map
from colmap_pvs.io.workspace import detect_workspace
from colmap_pvs.stereo.config import CONFIG_FILENAME
from colmap_pvs.stereo.outputs import read_provenance
from colmap_pvs.stereo.reference import confirm_map_path
from colmap_pvs.upsampling import resize_nearest

logger = logging.getLogger("calibrate_confidence")
#: The kinds whose probabilities (confidence maps) a kind's score reads.
READS = {"photometric": (), "geometric": ("photometric",), "filled": ("photometric", "geometric")}


@dataclass
class Pixels:
    """The pooled pixels of one kind of map with GT: ``conf`` and relative error ``err`` ``[P]``, and
    what the maps say they were made with: the calibration ``curves`` of each kind in their provenance
    (``None``: raw scores) and the ``checkpoints`` (sha256) of their stereo runs."""

    conf: np.ndarray
    err: np.ndarray
    curves: dict[str, set]
    checkpoints: set


def _provenance_curve(ws, name: str, kind: str) -> str:
    """The calibration of ``name``'s ``kind`` map from its provenance, as JSON (``"null"``: raw)."""
    prov = read_provenance(ws, name, kind)
    if prov is None or "settings" not in prov:
        raise SystemExit(f"{ws.root}: no readable provenance for {name!r} {kind}")
    return json.dumps(prov["settings"].get("confidence_calibration"), sort_keys=True)


def gather(ws_path: Path, kind: str, args) -> Pixels:
    """:class:`Pixels` of every valid pixel of ``kind`` maps with GT in ``ws_path``."""
    ws = detect_workspace(ws_path, create_stereo_dirs=False)
    suffix = f".{kind}.bin"
    conf_all, err_all, curves = [], [], {k: set() for k in KINDS}
    for path in sorted(ws.depth_maps_dir.rglob(f"*{suffix}")):
        name = path.relative_to(ws.depth_maps_dir).as_posix()[: -len(suffix)]
        if args.gt == "teacher":
            gt_path = ws.depth_maps_dir / f"{name}.teacher.bin"
            if not gt_path.is_file():
                continue
            g = read_depth_map(gt_path)
        else:
            gt_dir = Path(args.gt) if Path(args.gt).is_absolute() else ws_path / args.gt
            gt_path = find_gt_depth(gt_dir, name, args.gt_pattern)
            if gt_path is None:
                continue
            g = read_gt_depth(gt_path, args.gt_scale)
        conf_path = ws.confidence_map_path(name, kind)
        if not conf_path.is_file():
            continue
        for k in (kind, *READS[kind]):  # this kind's and those its score reads
            if ws.depth_map_path(name, k).is_file():
                curves[k].add(_provenance_curve(ws, name, k))
        d = read_depth_map(path)
        g = resize_nearest(g, *d.shape) if g.shape != d.shape else g
        c = read_array(conf_path).reshape(d.shape)
        ok = (d > 0) & (g > 0) & np.isfinite(g)
        added = confirm_map_path(ws, name)  # the confirmed completion: the filled kind's scores
        if kind == "geometric" and added.is_file():
            ok &= ~(read_depth_map(added) > 0)
        conf_all.append(c[ok])
        err_all.append(np.abs(d[ok] - g[ok]) / g[ok])
    try:
        run = json.loads((ws.stereo_dir / CONFIG_FILENAME).read_text())
        checkpoints = {run.get("checkpoint_sha256")}
    except (OSError, ValueError):
        checkpoints = {None}
    if not conf_all:
        return Pixels(np.zeros(0, np.float32), np.zeros(0, np.float32), curves, checkpoints)
    return Pixels(np.concatenate(conf_all), np.concatenate(err_all), curves, checkpoints)


def collect(args, kind: str) -> Pixels:
    """Pooled :class:`Pixels` of every workspace, each workspace weighted alike (subsampled to its share)."""
    parts = []
    for w in args.workspaces:
        px = gather(Path(w), kind, args)
        logger.info("%s %s: %d pixels with GT", w, kind, px.conf.size)
        if px.conf.size > args.pixels_per_workspace:  # every workspace counts alike
            pick = np.random.default_rng(0).choice(px.conf.size, args.pixels_per_workspace, replace=False)
            px.conf, px.err = px.conf[pick], px.err[pick]
        parts.append(px)
    return Pixels(np.concatenate([p.conf for p in parts]), np.concatenate([p.err for p in parts]),
                  {k: set().union(*(p.curves[k] for p in parts)) for k in KINDS},
                  set().union(*(p.checkpoints for p in parts)))


def git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              check=True, cwd=Path(__file__).parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _curve_json(calibration: dict, kind: str) -> str:
    """A curve of ``calibration`` (its JSON form) as the provenance records it."""
    return json.dumps(calibration_from_dict(calibration).settings(kind), sort_keys=True)


def fit(args) -> int:
    start = {} if args.start is None else json.loads(Path(args.start).read_text())
    if start and abs(float(start.get("tolerance", args.tolerance)) - args.tolerance) > 1e-12:
        raise SystemExit(f"--start {args.start} was fitted at another tolerance ({start['tolerance']})")
    out = {"tolerance": args.tolerance, "curves": dict(start.get("curves", {})),
           "fit": dict(start.get("fit", {}))}
    for kind in args.kinds:
        together = sorted(set(READS[kind]) & set(args.kinds))
        if together:  # its scores were made from raw probabilities of those, not their new curves
            raise SystemExit(f"fit {kind} after {', '.join(together)}: rerun stereo with the new curve(s) "
                             f"beside the checkpoint, then fit {kind} with --start")
    for stale in [k for k in KINDS if k in out["curves"] and set(READS[k]) & set(args.kinds)]:
        # its score reads a probability refitted here: its curve is stale with that one's
        print(f"dropping the {stale} curve of --start: refit it after these")
        out["curves"].pop(stale)
        out["fit"].pop(stale, None)
    for kind in args.kinds:
        px = collect(args, kind)
        if px.conf.size == 0:
            raise SystemExit(f"no {kind} pixels with GT in {args.workspaces}")
        if px.curves[kind] != {"null"}:
            raise SystemExit(f"the {kind} maps hold calibrated confidences; fit needs their raw scores "
                             "(stereo with a checkpoint that has no calibration beside it)")
        for upstream in READS[kind]:  # the probabilities the score reads must be --start's
            wanted = _curve_json(out, upstream) if upstream in out["curves"] else "null"
            if px.curves[upstream] - {wanted}:
                raise SystemExit(f"the {kind} scores were made from {upstream} maps of another calibration "
                                 f"than --start's; rerun stereo with it beside the checkpoint")
        if len(px.checkpoints) != 1:
            found = sorted(map(str, px.checkpoints))
            raise SystemExit(f"the workspaces were made with different checkpoints: {found}")
        correct = px.err <= args.tolerance
        try:
            curve = fit_curve(px.conf, correct)
        except ShapeError as exc:
            raise SystemExit(f"{kind}: {exc}") from None
        out["curves"][kind] = {"score": list(curve.score), "prob": list(curve.prob)}
        before, after = reliability(np.clip(px.conf, 0, 1), correct), reliability(curve(px.conf), correct)
        out["fit"][kind] = {"data": args.data, "workspaces": [Path(w).name for w in args.workspaces],
                            "gt": args.gt, "checkpoint_sha256": next(iter(px.checkpoints)),
                            "pixels": int(px.conf.size), "correct_pct": float(correct.mean() * 100),
                            "ece_raw": before.ece, "ece_fitted": after.ece, "commit": git_commit()}
        print(f"{kind}: {px.conf.size} pixels, {correct.mean() * 100:.1f} % within {args.tolerance:g}; "
              f"ECE of the raw score {before.ece:.3f}, fitted {after.ece:.3f}")
    calibration_from_dict(out, args.out)  # refuse to write what would not load
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


def check(args) -> int:
    apply = None if args.apply is None else load_calibration(args.apply)
    for kind in args.kinds:
        px = collect(args, kind)
        if px.conf.size == 0:
            print(f"{kind}: no pixels with GT")
            continue
        recorded = [json.loads(c) for c in px.curves[kind]]  # the calibrations the maps were made with
        raw = all(r is None for r in recorded)
        if apply is not None:  # raw maps, calibrated here
            if not raw:
                raise SystemExit(f"the {kind} maps are calibrated already: check them without --apply")
            conf, tolerance = apply.apply(kind, px.conf, np.ones(px.conf.shape, bool)), apply.tolerance
        else:
            tolerances = {r["tolerance"] for r in recorded if r is not None}
            if raw or len(tolerances) != 1:
                raise SystemExit(f"the {kind} maps hold raw scores (or several calibrations): pass --apply")
            conf, tolerance = px.conf, tolerances.pop()
        tolerance = args.tolerance or tolerance
        rel = reliability(conf, px.err <= tolerance, bins=args.bins)
        print(f"{kind}: {conf.size} pixels, {np.mean(px.err <= tolerance) * 100:.1f} % within {tolerance:g}, "
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
        # fit: one kind per round by default (each reads the probabilities of the kinds before it)
        kinds = ["photometric"] if name == "fit" else list(KINDS)
        q.add_argument("--kinds", nargs="+", choices=KINDS, default=kinds)
        q.add_argument("--pixels_per_workspace", type=int, default=2_000_000)
    f = sub.choices["fit"]
    f.add_argument("--tolerance", type=float, default=0.05, help="relative depth error counted as right")
    f.add_argument("--start", default=None, help="a calibration whose other curves are kept")
    f.add_argument("--data", default="", help="what the workspaces are (recorded in the file)")
    f.add_argument("--out", required=True)
    c = sub.choices["check"]
    c.add_argument("--tolerance", type=float, default=None, help="instead of the calibration's")
    c.add_argument("--bins", type=int, default=10)
    c.add_argument("--apply", default=None, help="calibrate raw maps' scores with this calibration first")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    return fit(args) if args.command == "fit" else check(args)


if __name__ == "__main__":
    sys.exit(main())
