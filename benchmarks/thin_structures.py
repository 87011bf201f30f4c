"""Thin structures with ground truth: fronds of synthetic potted plants, against the network's scale.

Real scenes with thin structures (the fern's fronds, the statue's crown) have no ground truth, so this
renders the ``plant`` family (``colmap_pvs.synthetic.scenes``: fronds a few pixels wide in front of a
wall) as COLMAP workspaces with GT depth, runs ``colmap-pvs stereo`` (both passes) at each
``--scales`` value of ``network_scale`` and scores the maps on two pixel sets of the GT:

- **thin**: pixels of a structure at most 4 map pixels across (along a row or a column) that is at
  least 20 % nearer than the surface on both sides of it (the fronds, a cane);
- **all**: every GT pixel.

For each: the photometric maps' coverage, AbsRel (over the pixels they cover) and % within 5 % (of
*all* the set's pixels: a pixel without depth counts as wrong), and the geometric maps' coverage and
% within 5 % of the pixels they keep. The images are rendered at twice the map size, so a scale above 1
gives the network real detail (as for photos larger than ``--max_image_size``)::

    python benchmarks/thin_structures.py                                  # 4 scenes, scales 0.8 1 1.25 1.5 2
    python benchmarks/thin_structures.py --scenes 2 --scales 0.8 1.5 --checkpoint runs/x/model.pt
    python benchmarks/thin_structures.py --scales 0.8 1.5 2 --picture thin.jpg   # image | GT | each scale

Workspaces are cached in ``outputs/benchmarks/thin/`` by seed, size and view count: delete the folder
after changing the plant generator. About 5 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import real_depth as rd

from colmap_pvs.config import config_from_dict
from colmap_pvs.evaluate import thin_structure_mask
from colmap_pvs.io.maps import colorize_depth, read_array
from colmap_pvs.stereo import StereoConfig, run_stereo
from colmap_pvs.synthetic.workspace import SyntheticWorkspaceConfig, make_synthetic_workspace
from colmap_pvs.upsampling import resize_nearest

WORK = Path(__file__).resolve().parents[1] / "outputs" / "benchmarks" / "thin"


def scene_workspace(seed: int, size: tuple[int, int], views: int) -> Path:
    """The rendered plant scene ``seed`` at ``size`` (cached)."""
    path = WORK / f"plant_{seed}_{size[0]}x{size[1]}_{views}"
    if not (path / "gt" / "scene.json").is_file():
        cfg = SyntheticWorkspaceConfig(
            seed=seed, family="plant", width=size[0], height=size[1], num_views=views,
            trajectory="unstructured", write_mesh=False, overwrite=True,
        )
        make_synthetic_workspace(path, cfg)
    return path


def run_scale(scene: Path, scale: float, max_image_size: int, checkpoint: Path | None,
              extra: dict[str, object], tag: str) -> tuple[Path, float]:
    """``colmap-pvs stereo`` at ``network_scale = scale`` on a fresh copy of ``scene``; seconds per image."""
    tag = f"{scene.name}_s{scale:g}_{tag}"
    ws = WORK / "runs" / tag
    if ws.exists():
        shutil.rmtree(ws)
    (ws / "stereo").mkdir(parents=True)
    (ws / "images").symlink_to(scene / "images")
    shutil.copytree(scene / "sparse", ws / "sparse")
    shutil.copy(scene / "stereo" / "patch-match.cfg", ws / "stereo" / "patch-match.cfg")
    cfg = config_from_dict(StereoConfig, {
        "workspace_path": ws, "max_image_size": max_image_size, "network_scale": scale,
        "checkpoint": checkpoint, "threads": 2, "network_min_size": 16, **extra,
    })
    t0 = time.perf_counter()
    run_stereo(cfg)
    n = len(list((scene / "images").iterdir()))
    return ws, (time.perf_counter() - t0) / n


def score(ws: Path, scene: Path) -> dict[str, list[np.ndarray]]:
    """Relative errors of the photometric / geometric maps on the thin and all pixels of every image."""
    out: dict[str, list] = {k: [] for k in ("thin_photo", "all_photo", "thin_geo", "all_geo")}
    for gt_path in sorted((scene / "gt" / "depth_maps").glob("*.npy")):
        name = gt_path.name[: -len(".npy")]
        photo = read_array(ws / "stereo" / "depth_maps" / f"{name}.photometric.bin")
        geo = read_array(ws / "stereo" / "depth_maps" / f"{name}.geometric.bin")
        gt = resize_nearest(np.load(gt_path), *photo.shape)
        masks = {"thin": thin_structure_mask(gt), "all": gt > 0}
        for kind, pred in (("photo", photo), ("geo", geo)):
            err = np.where(pred > 0, np.abs(pred - gt) / np.maximum(gt, 1e-9), np.inf)
            for m, mask in masks.items():
                out[f"{m}_{kind}"].append(err[mask])
    return out


def write_picture(out: Path, scenes: list[Path], scales: list[float], tag: str) -> None:
    """One row per scene (its first view): image | GT | photometric map at each scale, inverse depth on
    one colour scale per row (black: no depth)."""
    import cv2

    rows = []
    for scene in scenes:
        name = sorted((scene / "images").iterdir())[0].name
        maps = [read_array(WORK / "runs" / f"{scene.name}_s{s:g}_{tag}" / "stereo" / "depth_maps"
                           / f"{name}.photometric.bin") for s in scales]
        h, w = maps[0].shape
        gt = resize_nearest(np.load(scene / "gt" / "depth_maps" / f"{name}.npy"), h, w)
        inv = [np.where(m > 0, 1.0 / np.maximum(m, 1e-9), 0.0) for m in [gt, *maps]]
        lo, hi = np.percentile(inv[0][inv[0] > 0], [2, 98])
        tiles = [cv2.resize(cv2.imread(str(scene / "images" / name)), (w, h), interpolation=cv2.INTER_AREA)]
        for label, x in zip(["GT", *[f"scale {s:g}" for s in scales]], inv, strict=True):
            c = colorize_depth(x, lo, hi)
            cv2.putText(c, label, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
            tiles.append(c)
        rows.append(np.concatenate(tiles, axis=1))
    cv2.imwrite(str(out), np.concatenate(rows, axis=0), [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(f"picture: {out}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", type=int, default=4, help="plant scenes (seeds 0, 1, ...)")
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--max_image_size", type=int, default=320, help="map size; images are rendered at 2x")
    p.add_argument("--scales", type=float, nargs="+", default=[0.8, 1.0, 1.25, 1.5, 2.0])
    p.add_argument("--checkpoint", type=Path, default=None, help="default: the shipped weights")
    p.add_argument("--stereo", nargs="*", default=[], metavar="KEY=VALUE", help="more StereoConfig fields")
    p.add_argument("--tag", default="default", help="names the run folders")
    p.add_argument("--picture", type=Path, default=None,
                   help="write image | GT | photometric map per scale (first view of each scene) here")
    a = p.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    extra = rd.parse_overrides(a.stereo)
    size = (2 * a.max_image_size, 2 * a.max_image_size * 3 // 4)
    scenes = [scene_workspace(s, size, a.views) for s in range(a.scenes)]
    rows = []
    for scale in a.scales:
        errs: dict[str, list] = {}
        secs = []
        for scene in scenes:
            ws, s = run_scale(scene, scale, a.max_image_size, a.checkpoint, extra, a.tag)
            secs.append(s)
            for k, v in score(ws, scene).items():
                errs.setdefault(k, []).extend(v)
        e = {k: np.concatenate(v) for k, v in errs.items()}

        def stats(x: np.ndarray) -> dict[str, float]:
            valid = np.isfinite(x)  # pixels with a depth
            return {"coverage_pct": 100 * float(valid.mean()), "absrel": float(x[valid].mean()),
                    "pct_under_5_of_all": 100 * float((x < 0.05).mean()),
                    "pct_under_5_of_kept": 100 * float((x[valid] < 0.05).mean())}

        row = {"scale": scale, "s_per_image": float(np.mean(secs)), "thin_pixels": int(e["thin_photo"].size),
               "all_pixels": int(e["all_photo"].size)}
        row.update({k: stats(v) for k, v in e.items()})
        rows.append(row)
    print(f"{a.scenes} plant scenes x {a.views} views, maps {size[0] // 2}x{size[1] // 2}, images rendered "
          f"at {size[0]}x{size[1]}; thin pixels {rows[0]['thin_pixels']} of {rows[0]['all_pixels']}")
    print("| network_scale | s / image | thin: photometric coverage / AbsRel / <5 % of all "
          "| thin: geometric coverage / <5 % of kept | all: photometric coverage / AbsRel / <5 % of all "
          "| all: geometric coverage / <5 % of kept |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        cells = [f"{r['scale']:g}", f"{r['s_per_image']:.2f}"]
        for part in ("thin", "all"):
            ph, ge = r[f"{part}_photo"], r[f"{part}_geo"]
            cells.append(f"{ph['coverage_pct']:.1f} % / {ph['absrel']:.3f} / {ph['pct_under_5_of_all']:.1f}")
            cells.append(f"{ge['coverage_pct']:.1f} % / {ge['pct_under_5_of_kept']:.1f}")
        print("| " + " | ".join(cells) + " |")
    if a.picture:
        write_picture(a.picture, scenes, a.scales, a.tag)
    (WORK / "last.json").write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
