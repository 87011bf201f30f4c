"""Per-class accuracy on ``hololens-dev`` (issue 56): where the network's maps miss, by kind of pixel.

Scores the maps of ``hololens_quick.py`` workspaces (``WORK/quick/TAG_clean``) against the GT depth::

    python benchmarks/hololens_quick.py --stride 3 --offset 0 --tag base        # the maps
    python benchmarks/blind_spots.py --stride 3 --offset 0 --tags base [NEW ...] --picture OUT.jpg

For each kind of map (``--kinds``: the network's ``photometric`` maps, the ``filled`` completion, the
``geometric`` maps) and each tag, the % of a class's GT pixels within 5 % of the GT (a pixel without
a depth counts as wrong; for ``geometric``: of the pixels the map keeps, and its coverage) and the
class's pixel count. The classes (on the GT grid, GT-valid pixels only; :func:`class_masks`):

- ``all``: every GT pixel;
- ``outside range`` / ``inside range``: GT depth outside / inside the depth range COLMAP's rule gives
  the reference (the default ``ViewSelectionConfig``: the sparse points' 1st / 99th percentiles with
  a 25 % margin), whatever range the maps were made with;
- ``slanted``: the angle between the GT normal (``colmap_pvs.normals.fit_normals`` of the GT depth,
  7x7 plane fit) and the viewing ray above :data:`SLANT_DEG`;
- ``low texture``: the grey image's (0-1) standard deviation in a 7x7 window below
  :data:`TEXTURE_STD` (about 1.3 of 255 grey levels: white walls, doors, the carpet; a quarter of
  the pixels);
- ``thin``: GT pixels nearer than :data:`THIN_GAP` times the farthest GT depth within
  ``2 * THIN_WIDTH`` px (a foreground band along a depth edge) that a ``THIN_WIDTH`` x ``THIN_WIDTH``
  morphological opening of that band removes: foreground narrower than ``THIN_WIDTH`` px (stems,
  fronds, chair legs, a door's edge seen end-on). Invalid GT is no edge.

``--picture OUT.jpg`` draws, for each class but ``all`` and ``inside range``, its worst frame of the
first tag's network maps (the lowest % within 5 % among frames where the class has at least
:data:`PICTURE_MIN_PIXELS` pixels): image | GT depth | relative error of the network map (black 0 to
yellow >= 10 %), the class outlined in cyan on the first and the last. Every number goes to
``WORK/quick/TAG_clean/blind_spots_oOFFSET_sSTRIDE.json``.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import cv2
import numpy as np
import real_depth as rd

SLANT_DEG = 60.0
TEXTURE_STD = 0.005
TEXTURE_WINDOW = 7
THIN_WIDTH = 5
THIN_GAP = 0.8
PICTURE_MIN_PIXELS = 500
PICTURE_ERROR = 0.10
WITHIN = 0.05
CLASSES = ("all", "outside range", "inside range", "slanted", "low texture", "thin")


def outside_range_mask(gt: np.ndarray, depth_range: tuple[float, float]) -> np.ndarray:
    """``[H, W]`` bool: valid GT pixels (``> 0``) outside ``[depth_range[0], depth_range[1]]``."""
    return (gt > 0) & ((gt < depth_range[0]) | (gt > depth_range[1]))


def slanted_mask(gt: np.ndarray, K: np.ndarray, angle_deg: float = SLANT_DEG) -> np.ndarray:
    """``[H, W]`` bool: GT pixels whose normal (a 7x7 plane fit of the GT depth) is more than
    ``angle_deg`` away from the viewing ray (pixels without a normal are not in it)."""
    from colmap_pvs.normals import fit_normals

    n = fit_normals(gt, K, window=7)
    h, w = gt.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    cos = np.abs(np.sum(n * rays, axis=-1))
    has = np.linalg.norm(n, axis=-1) > 0.5
    return (gt > 0) & has & (cos < np.cos(np.radians(angle_deg)))


def low_texture_mask(grey: np.ndarray, gt: np.ndarray, threshold: float = TEXTURE_STD,
                     window: int = TEXTURE_WINDOW) -> np.ndarray:
    """``[H, W]`` bool: GT pixels where the grey image (``[H, W]``, 0-1) has a standard deviation
    below ``threshold`` in the ``window`` x ``window`` box around them."""
    g = np.asarray(grey, dtype=np.float64)
    mean = cv2.blur(g, (window, window), borderType=cv2.BORDER_REFLECT)
    sq = cv2.blur(g * g, (window, window), borderType=cv2.BORDER_REFLECT)
    std = np.sqrt(np.maximum(sq - mean * mean, 0.0))
    return (gt > 0) & (std < threshold)


def thin_mask(gt: np.ndarray, width: int = THIN_WIDTH, gap: float = THIN_GAP) -> np.ndarray:
    """``[H, W]`` bool: GT foreground narrower than ``width`` px (see the module docstring): pixels
    below ``gap`` times the farthest valid GT depth within ``2 * width`` px, less what a
    ``width`` x ``width`` opening of those pixels keeps. ``gt`` ``[H, W]``, 0 = invalid (no edge)."""
    d = np.asarray(gt, dtype=np.float32)
    radius = 2 * width
    far = cv2.dilate(d, np.ones((2 * radius + 1, 2 * radius + 1), np.uint8))  # invalid (0) never wins
    band = ((d > 0) & (d < gap * far)).astype(np.uint8)
    opened = cv2.morphologyEx(band, cv2.MORPH_OPEN, np.ones((width, width), np.uint8))
    return (band > 0) & (opened == 0)


def class_masks(gt: np.ndarray, grey: np.ndarray, K: np.ndarray,
                depth_range: tuple[float, float]) -> dict[str, np.ndarray]:
    """Every class of :data:`CLASSES` for one frame: ``gt`` ``[H, W]`` metres (0 invalid), ``grey``
    ``[H, W]`` 0-1, ``K`` ``[3, 3]`` of that grid, ``depth_range`` the COLMAP-rule range."""
    valid = gt > 0
    outside = outside_range_mask(gt, depth_range)
    return {
        "all": valid,
        "outside range": outside,
        "inside range": valid & ~outside,
        "slanted": slanted_mask(gt, K),
        "low texture": low_texture_mask(grey, gt),
        "thin": thin_mask(gt),
    }


def counts(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> tuple[int, int, int]:
    """``(pixels, predicted, within)`` of ``mask``: its pixels, those with a depth, those within 5 %."""
    p, g = pred[mask], gt[mask]
    has = p > 0
    within = has & (np.abs(p - g) <= WITHIN * g)
    return int(mask.sum()), int(has.sum()), int(within.sum())


def error_tile(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    valid = gt > 0
    rel = np.where(valid & (pred > 0), np.abs(pred - gt) / np.maximum(gt, 1e-6), PICTURE_ERROR)
    err = cv2.applyColorMap((np.clip(rel / PICTURE_ERROR, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
    err[~valid] = 0
    return err


def outline(tile: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``tile`` with ``mask`` outlined in cyan (closed over the GT's small holes first, for legibility)."""
    out = tile.copy()
    closed = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((7, 7), np.uint8))
    contours, _ = cv2.findContours(closed, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, [c for c in contours if cv2.contourArea(c) >= 20], -1, (255, 255, 0), 2)
    return out


def picture_row(image: np.ndarray, gt: np.ndarray, pred: np.ndarray, mask: np.ndarray,
                label: str) -> np.ndarray:
    from cloud_benchmark import depth_tile

    row = np.concatenate([outline(image, mask), depth_tile(gt), outline(error_tile(pred, gt), mask)], axis=1)
    cv2.putText(row, label, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 2, cv2.LINE_AA)
    cv2.putText(row, label, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    return row


def frame_refs(work: Path, tag: str, names: list[str], args: argparse.Namespace) -> list[str]:
    depth_dir = work / "quick" / f"{tag}_clean" / "stereo" / "depth_maps"
    return [n for n in rd.frame_names(names, args) if (depth_dir / f"{n}.photometric.bin").is_file()]


def main() -> int:
    from colmap_pvs.evaluate import read_gt_depth
    from colmap_pvs.io.maps import read_depth_map
    from colmap_pvs.io.sparse import read_sparse_model
    from colmap_pvs.upsampling import resize_nearest
    from colmap_pvs.views import ViewSelectionConfig, select_views

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    rd.add_frame_args(p, stride=3)
    p.add_argument("--tags", nargs="+", default=["base"],
                   help="hololens_quick.py tags (WORK/quick/TAG_clean); the first is the reference")
    p.add_argument("--kinds", nargs="+", default=["photometric", "filled", "geometric"])
    p.add_argument("--picture", type=Path, default=None, help="the worst frame of each class (first tag)")
    a = p.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if not (a.data / "poses.txt").is_file():
        print(f"hololens-dev data not found at {a.data}; nothing to do")
        return 2
    work = a.work_dir.resolve()
    model = read_sparse_model(work / "model" / "sparse")
    names = sorted(model.image_ids_by_name)
    sel = select_views(model, ViewSelectionConfig(num_views=a.num_views))
    refs = frame_refs(work, a.tags[0], names, a)
    for tag in a.tags[1:]:
        refs = [r for r in refs if r in set(frame_refs(work, tag, names, a))]
    if not refs:
        print(f"no photometric maps of the frames --stride {a.stride} --offset {a.offset} in every tag")
        return 2
    K_data = np.loadtxt(a.data / "K.txt").reshape(3, 3)

    def frame(name: str) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Frame ``name``'s GT depth, image at the GT's size and class masks."""
        gt = read_gt_depth(a.data / "depth" / name, 0.001)
        h, w = gt.shape
        image = cv2.resize(cv2.imread(str(a.data / "images" / name), cv2.IMREAD_COLOR), (w, h),
                           interpolation=cv2.INTER_AREA)
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.float64) / 255.0
        cam = model.cameras[model.image_by_name(name).camera_id]
        K = np.diag([w / cam.width, h / cam.height, 1.0]) @ K_data
        return gt, image, class_masks(gt, grey, K, sel.references[name].depth_range)

    # totals[tag][kind][class] = [pixels, predicted, within]; frames[class] = [(pct, name, pixels)]
    totals = {t: {k: {c: [0, 0, 0] for c in CLASSES} for k in a.kinds} for t in a.tags}
    frames: dict[str, list[tuple[float, str, int]]] = {c: [] for c in CLASSES}
    per_frame: dict[str, dict] = {}
    for name in refs:
        gt, _, masks = frame(name)
        h, w = gt.shape
        per_frame[name] = {"pixels": {c: int(m.sum()) for c, m in masks.items()}}
        for tag in a.tags:
            for kind in a.kinds:
                path = work / "quick" / f"{tag}_clean" / "stereo" / "depth_maps" / f"{name}.{kind}.bin"
                if not path.is_file():
                    continue
                pred = read_depth_map(path)
                pred = pred if pred.shape == (h, w) else resize_nearest(pred, h, w)
                for c, m in masks.items():
                    n, has, within = counts(pred, gt, m)
                    acc = totals[tag][kind][c]
                    acc[0] += n
                    acc[1] += has
                    acc[2] += within
                    per_frame[name].setdefault(tag, {}).setdefault(kind, {})[c] = [has, within]
                    if tag == a.tags[0] and kind == "photometric" and n >= PICTURE_MIN_PIXELS:
                        frames[c].append((100.0 * within / n, name, n))
    print(f"{len(refs)} references (--stride {a.stride} --offset {a.offset}), % of the class's GT pixels "
          f"within {WITHIN:.0%} (geometric: of the pixels kept, and coverage); pixels (share of all)")
    header = "| class | pixels | " + " | ".join(f"{t} {k}" for k in a.kinds for t in a.tags) + " |"
    print(header)
    print("|" + "---|" * (2 + len(a.kinds) * len(a.tags)))
    for c in CLASSES:
        n_all = totals[a.tags[0]][a.kinds[0]]["all"][0]
        n = totals[a.tags[0]][a.kinds[0]][c][0]
        cells = []
        for kind in a.kinds:
            for tag in a.tags:
                px, has, within = totals[tag][kind][c]
                if kind == "geometric":
                    cells.append(f"{100 * within / max(has, 1):.1f} ({100 * has / max(px, 1):.0f} % cov.)")
                else:
                    cells.append(f"{100 * within / max(px, 1):.1f}")
        print(f"| {c} | {n:,} ({100 * n / max(n_all, 1):.1f} %) | " + " | ".join(cells) + " |")
    worst = {c: sorted(f)[0] for c, f in frames.items() if f}
    print("worst frame per class (network map of " + a.tags[0] + "): "
          + "; ".join(f"{c} {nm} {pct:.1f} % of {n:,} px" for c, (pct, nm, n) in worst.items()))
    for tag in a.tags:
        out = work / "quick" / f"{tag}_clean" / f"blind_spots_o{a.offset}_s{a.stride}.json"
        out.write_text(json.dumps({"refs": refs, "totals": totals[tag], "worst": worst,
                                   "per_frame": {n: {"pixels": f["pixels"], **f.get(tag, {})}
                                                 for n, f in per_frame.items()}}, indent=1))
    if a.picture is not None:
        rows = []
        for c, (pct, name, _) in worst.items():
            if c in ("all", "inside range"):
                continue
            gt, image, masks = frame(name)
            h, w = gt.shape
            mask = masks[c]
            pred = read_depth_map(work / "quick" / f"{a.tags[0]}_clean" / "stereo" / "depth_maps"
                                  / f"{name}.photometric.bin")
            pred = pred if pred.shape == (h, w) else resize_nearest(pred, h, w)
            row = picture_row(image, gt, pred, mask, f"{c}: {name} {pct:.1f} %")
            rows.append(cv2.resize(row, (row.shape[1] // 2, row.shape[0] // 2), interpolation=cv2.INTER_AREA))
        cv2.imwrite(str(a.picture), np.concatenate(rows, axis=0), [cv2.IMWRITE_JPEG_QUALITY, 80])
        print(f"picture: {a.picture}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
