"""Where do far sources cost accuracy? Errors split by whether a far frame sees the pixel (hololens-dev).

The ``disturbed`` setting of ``hololens_quick.py`` replaces 2 of the 4 best sources by far-away
frames. This script reads three of its workspaces, run on the same references:

- ``--clean``: the 4 best sources (``T_clean`` of ``hololens_quick.py --tag T --disturbed``);
- ``--disturbed``: the 2 best + 2 far frames (``T_disturbed``);
- ``--control``: the same 2 best sources alone, N = 3 (``T3_clean`` of ``--num_views 3 --tag T3``),

and splits every reference's GT pixels in two: those that at least one of its far frames truly sees
(the GT point projects inside that frame and its own GT depth agrees within 5 %, as in
``visibility_check.py``) and the rest. For each map kind it prints MAE, AbsRel and the % within 5 %
of each setting on each part, over the pixels that all three settings estimate::

    python benchmarks/hololens_quick.py --stride 3 --offset 0 --disturbed --tag T
    python benchmarks/hololens_quick.py --stride 3 --offset 0 --num_views 3 --tag T3
    python benchmarks/far_sources_split.py --clean T_clean --disturbed T_disturbed --control T3_clean

On the pixels no far frame sees, the disturbed setting has the information of the control (N = 3) and
no more; only on the others can the far frames make up for the two good views they replace.

``--picture OUT.jpg --picture_refs A B``: one row per named reference: the image with the pixels a far
frame sees tinted green | the relative error of the photometric map with the 4 best sources | with
2 best + 2 far | with the 2 best alone (0 black to 10 % and more yellow; no GT black).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import real_depth as rd
from visibility_check import true_visibility

from colmap_pvs.evaluate import compute_depth_metrics, read_gt_depth
from colmap_pvs.io.maps import read_depth_map
from colmap_pvs.io.sparse import read_sparse_model
from colmap_pvs.upsampling import resize_nearest

KINDS = ("photometric", "geometric", "filled")
#: Relative error shown at full brightness in the picture.
PICTURE_ERROR = 0.10


def stats(rows: list[tuple[np.ndarray, np.ndarray]]) -> tuple[float, float, float]:
    """MAE (metres), AbsRel and % within 5 % of the ``(pred, gt)`` pairs in ``rows`` (1-D, > 0), by
    :func:`~colmap_pvs.evaluate.compute_depth_metrics` (as every other depth number of the project)."""
    pred, gt = np.concatenate([r[0] for r in rows]), np.concatenate([r[1] for r in rows])
    m = compute_depth_metrics(pred[None], gt[None], rel_thresholds=(0.05,), abs_thresholds=())
    return m.mae, m.absrel, m.rel_under_pct[0.05]


def picture_row(image_path: Path, gt: np.ndarray, seen: np.ndarray, maps: list[np.ndarray]) -> np.ndarray:
    """``[H, (1 + len(maps)) W, 3]`` BGR: the image with ``seen`` tinted green, then each map's relative
    error against ``gt`` (inferno, 0 to :data:`PICTURE_ERROR`; black without GT)."""
    image = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
    h, w = gt.shape
    image = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
    tint = image.copy()
    tint[seen] = (0.5 * tint[seen] + 0.5 * np.array([0, 255, 0])).astype(np.uint8)
    tiles = [tint]
    valid = gt > 0
    for d in maps:
        rel = np.where(valid & (d > 0), np.abs(d - gt) / np.maximum(gt, 1e-6), 0.0)
        scaled = (np.clip(rel / PICTURE_ERROR, 0, 1) * 255).astype(np.uint8)
        err = cv2.applyColorMap(scaled, cv2.COLORMAP_INFERNO)
        err[~valid] = 0
        tiles.append(err)
    return np.concatenate(tiles, axis=1)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--clean", required=True, help="workspace under WORK/quick with the 4 best sources")
    p.add_argument("--disturbed", required=True, help="workspace with 2 best + 2 far sources")
    p.add_argument("--control", required=True, help="workspace with the 2 best sources alone (N = 3)")
    p.add_argument("--data", type=Path, default=rd.DEFAULT_DATA)
    p.add_argument("--work_dir", type=Path, default=rd.DEFAULT_WORK)
    p.add_argument("--far", type=int, default=2, help="the disturbed setting's far frames (its last sources)")
    p.add_argument("--picture", type=Path, help="write the error picture (JPEG) of --picture_refs here")
    p.add_argument("--picture_refs", nargs="*", default=[], help="references drawn in --picture")
    a = p.parse_args()
    if not (a.data / "depth").is_dir():
        print(f"hololens-dev data not found at {a.data}; nothing to do")
        return 2
    spaces = {k: a.work_dir / "quick" / t for k, t in
              (("clean", a.clean), ("disturbed", a.disturbed), ("control", a.control))}
    for label, ws in spaces.items():
        if not (ws / "stereo" / "provenance").is_dir():
            print(f"{label} workspace {ws} has no stereo maps: run benchmarks/hololens_quick.py first")
            return 2
    metrics = spaces["disturbed"] / "metrics.photometric.json"
    if not metrics.is_file():
        print(f"{metrics} is missing: run benchmarks/hololens_quick.py --disturbed first")
        return 2
    refs = sorted(json.loads(metrics.read_text())["config"]["images"])
    model = read_sparse_model(spaces["disturbed"] / "sparse")
    picture_rows = []
    # per kind and setting: the (pred, gt) of the pixels seen by a far frame, and of the rest
    pooled: dict[tuple[str, str, bool], list[tuple[np.ndarray, np.ndarray]]] = {}
    seen_share = []
    for name in refs:
        prov = spaces["disturbed"] / "stereo" / "provenance" / f"{name}.photometric.json"
        far = json.loads(prov.read_text())["settings"]["sources"][-a.far :]
        gt = read_gt_depth(a.data / "depth" / name, 0.001)
        h, w = gt.shape
        seen = np.zeros((h, w), bool)
        for src in far:
            seen |= true_visibility(model, name, src, a.data / "depth", (w, h))[1]
        for kind in KINDS:
            maps = {}
            for label, ws in spaces.items():
                path = ws / "stereo" / "depth_maps" / f"{name}.{kind}.bin"
                if path.is_file():
                    d = read_depth_map(path)
                    maps[label] = d if d.shape == (h, w) else resize_nearest(d, h, w)
            if len(maps) < len(spaces):
                continue
            common = (gt > 0) & np.logical_and.reduce([d > 0 for d in maps.values()])
            if kind == "photometric":
                seen_share.append((seen[gt > 0].sum(), (gt > 0).sum()))
                if name in a.picture_refs:
                    picture_rows.append(picture_row(a.data / "images" / name, gt, seen, list(maps.values())))
            for label, d in maps.items():
                for part in (True, False):
                    m = common & (seen == part)
                    pooled.setdefault((kind, label, part), []).append((d[m], gt[m]))
    if not pooled:
        print("no reference has maps in all three workspaces")
        return 2
    s, n = np.sum(seen_share, axis=0)
    print(f"{len(refs)} references; a far frame sees {100 * s / n:.1f} % of the GT pixels")
    print("| maps | pixels | share | 4 best | 2 best + 2 far | 2 best (N = 3) |")
    print("|---|---|---|---|---|---|")
    for kind in KINDS:
        if (kind, "clean", True) not in pooled:
            continue
        sizes = {part: sum(r[0].size for r in pooled[(kind, "clean", part)]) for part in (True, False)}
        for part in (True, False):
            cells = []
            for label in spaces:
                mae, absrel, under = stats(pooled[(kind, label, part)])
                cells.append(f"{1000 * mae:.0f} mm / {absrel:.4f} / {under:.1f}")
            share = 100 * sizes[part] / max(1, sum(sizes.values()))
            part_name = "seen by a far frame" if part else "seen by no far frame"
            print(f"| {kind} | {part_name} | {share:.1f} % | " + " | ".join(cells) + " |")
    if a.picture is not None and picture_rows:
        cv2.imwrite(str(a.picture), np.concatenate(picture_rows, axis=0), [cv2.IMWRITE_JPEG_QUALITY, 85])
        print(f"picture: {a.picture} ({len(picture_rows)} references)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
