"""Thin structures with ground truth: fronds of synthetic potted plants, against the network's scale.

Real scenes with thin structures (the fern's fronds, the statue's crown) have no ground truth, so this
renders the ``plant`` family (``colmap_pvs.synthetic.scenes``: fronds a few pixels wide, 1-4 m in
front of a wall) as COLMAP workspaces with GT depth, runs ``colmap-pvs stereo`` (both passes) at each
``--scales`` value of ``network_scale`` and scores the maps on two pixel sets of the GT:

- **thin**: pixels of a structure at most 4 map pixels across (along a row or a column) that is at
  least 20 % nearer than the surface on both sides of it (the fronds, a cane);
- **all**: every GT pixel.

For each, the photometric maps' AbsRel and % within 5 %, and the geometric maps' coverage and % within
5 %. The images are rendered at twice the map size, so a scale above 1 gives the network real detail
(as for photos larger than ``--max_image_size``)::

    python benchmarks/thin_structures.py                                  # 4 scenes, scales 0.8 1 1.25 1.5 2
    python benchmarks/thin_structures.py --scenes 2 --scales 0.8 1.5 --checkpoint runs/x/model.pt

Workspaces are cached in ``outputs/benchmarks/thin/``. About 5 minutes on 2 cores.
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
from colmap_pvs.evaluate import resize_nearest, thin_structure_mask
from colmap_pvs.io.maps import read_array
from colmap_pvs.stereo import StereoConfig, run_stereo
from colmap_pvs.synthetic.workspace import SyntheticWorkspaceConfig, make_synthetic_workspace

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


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", type=int, default=4, help="plant scenes (seeds 0, 1, ...)")
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--max_image_size", type=int, default=320, help="map size; images are rendered at 2x")
    p.add_argument("--scales", type=float, nargs="+", default=[0.8, 1.0, 1.25, 1.5, 2.0])
    p.add_argument("--checkpoint", type=Path, default=None, help="default: the shipped weights")
    p.add_argument("--stereo", nargs="*", default=[], metavar="KEY=VALUE", help="more StereoConfig fields")
    p.add_argument("--tag", default="default", help="names the run folders")
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

        def stats(x: np.ndarray) -> tuple[float, float, float]:
            valid = np.isfinite(x)
            return 100 * valid.mean(), float(x[valid].mean()), 100 * float((x[valid] < 0.05).mean())

        row = {"scale": scale, "s_per_image": float(np.mean(secs)), "thin_pixels": int(e["thin_photo"].size),
               "all_pixels": int(e["all_photo"].size)}
        for k in e:
            cov, absrel, under5 = stats(e[k])
            row[k] = {"coverage_pct": cov, "absrel": absrel, "pct_under_5": under5}
        rows.append(row)
    print(f"{a.scenes} plant scenes x {a.views} views, maps {size[0] // 2}x{size[1] // 2}, images rendered "
          f"at {size[0]}x{size[1]}; thin pixels {rows[0]['thin_pixels']} of {rows[0]['all_pixels']}")
    print("| network_scale | s / image | thin: photometric AbsRel / <5 % | thin: geometric coverage / <5 % "
          "| all: photometric AbsRel / <5 % | all: geometric coverage / <5 % |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scale']:g} | {r['s_per_image']:.2f} "
              f"| {r['thin_photo']['absrel']:.3f} / {r['thin_photo']['pct_under_5']:.1f} "
              f"| {r['thin_geo']['coverage_pct']:.1f} % / {r['thin_geo']['pct_under_5']:.1f} "
              f"| {r['all_photo']['absrel']:.3f} / {r['all_photo']['pct_under_5']:.1f} "
              f"| {r['all_geo']['coverage_pct']:.1f} % / {r['all_geo']['pct_under_5']:.1f} |")
    (WORK / "last.json").write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
