"""The fused cloud against a GT cloud on ``hololens-dev``, ETH3D-style (issue 39, item 4).

The protocol of issue 39: every 3rd frame a reference (60 references at ``--offset 0``), 540 px, N = 5
(the reference and its 4 best-scored sources, an explicit ``stereo/patch-match.cfg``), the default
stereo settings, in the workspace ``WORK/quick/TAG_clean`` of ``benchmarks/hololens_quick.py`` (the same
model, references and sources; a ``hololens_quick.py --stride 3 --tag TAG`` workspace is reused with
``--resume``)::

    python benchmarks/cloud_benchmark.py --tag cloud                      # stereo, fusions, scores
    python benchmarks/cloud_benchmark.py --tag cloud --resume --picture benchmarks/cloud_benchmark.jpg
    python benchmarks/cloud_benchmark.py --tag T --resume --stereo geom_fill_segments=false

1. The GT cloud: every valid GT depth pixel of the references back-projected with the data's ``K.txt``
   and the model's poses (the known poses, metres), voxel-downsampled (``--gt_voxel``, 1 cm: one point
   per voxel, the centroid).
2. The clouds scored: ``pvs`` (``colmap_pvs.fusion.fuse`` with its defaults: what ``colmap-pvs fuse``
   writes), ``colmap`` (Debian COLMAP's ``colmap stereo_fusion --input_type geometric`` with its
   defaults; multi-threaded, so its point count varies by a few hundred points from run to run),
   ``pvs_geometric`` and ``pvs_photometric`` (``fuse`` of the geometric or the network maps);
   ``--fusions`` picks.
3. The score, ETH3D-style (:func:`frustum_cloud_score`, on :func:`colmap_pvs.evaluate.cloud_metrics`,
   voxel-normalised at 1 cm as ETH3D's program): completeness = share of GT points within t of the
   cloud; accuracy = share of the cloud's points within t of the GT, counted only over the points
   some reference observes (:func:`observed_mask`: the point projects inside that reference onto a
   valid GT pixel and is not more than ``--behind`` (10 cm) behind that GT surface; points in space
   no GT depth observes, like ETH3D's unobserved points, are left out); F1 their harmonic mean; at
   t = 2, 5, 10 cm.
4. How each map kind's confidence ranks its errors (:func:`ranking`: ``evaluate depth``'s relative
   AUSE, the AbsRel of the most confident pixels, the calibration error), and with
   ``--min_confidence_curve 0 0.5 0.7 0.9`` the ``pvs`` cloud's accuracy / completeness / F1 at each
   ``fuse --min_confidence`` (:func:`confidence_curve`): the curve that one number moves along.
5. The per-frame check: each reference's % of GT pixels within 5 % relative error for the network map
   (``photometric``) and the completion (``filled``) (``colmap_pvs.evaluate.evaluate_depth``); a frame
   is flagged where the completion is more than ``--flag_points`` (5) points below the network map.
   ``--picture OUT.jpg``: the ``--picture_count`` worst frames, one row each: image | GT depth |
   relative error of the network map | of the completion (black 0 to yellow >= 10 %, black without GT)
   | the completion's confidence (black 0 to yellow 1: where the error is bright, a confidence that
   ranks well is dark).

Prints one table and the flags, and writes every number to ``--json`` (default
``WORK/quick/TAG_clean/cloud_benchmark.json``).
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import real_depth as rd
from far_sources_split import picture_row

from colmap_pvs.config import config_from_dict
from colmap_pvs.evaluate import cloud_metrics, read_gt_depth
from colmap_pvs.geometry import backproject_depth
from colmap_pvs.io.maps import read_array, read_depth_map
from colmap_pvs.io.sparse import read_sparse_model
from colmap_pvs.io.workspace import write_patch_match_cfg
from colmap_pvs.upsampling import resize_nearest
from colmap_pvs.views import ViewSelectionConfig, select_views

THRESHOLDS = (0.02, 0.05, 0.10)
FUSIONS = ("pvs", "colmap", "pvs_geometric", "pvs_photometric")


# --------------------------------------------------------------------------- scoring


@dataclass
class GTView:
    """One frame with GT depth: ``K`` ``[3, 3]`` and ``cam_from_world`` ``[3, 4]`` of the depth grid
    (COLMAP's pixel convention: pixel ``(col, row)`` covers ``[col, col + 1) x [row, row + 1)``),
    ``depth`` ``[H, W]`` in scene units (0 = invalid)."""

    name: str
    K: np.ndarray
    cam_from_world: np.ndarray
    depth: np.ndarray


def gt_cloud(views: list[GTView], voxel: float) -> np.ndarray:
    """``[G, 3]`` world points of every valid GT pixel of ``views``, one per ``voxel`` cube (open3d's
    voxel downsampling: the mean of the points in it; ``voxel <= 0``: every pixel)."""
    chunks = []
    for v in views:
        valid = v.depth > 0
        cam = backproject_depth(v.depth.astype(np.float64), v.K)[valid]  # [P, 3]
        R, t = v.cam_from_world[:, :3], v.cam_from_world[:, 3]
        chunks.append((cam - t) @ R)  # R^T (x - t)
    points = np.concatenate(chunks) if chunks else np.zeros((0, 3))
    if voxel <= 0 or len(points) == 0:
        return points
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel)
    return np.asarray(pcd.points, dtype=np.float64)


def project(points: np.ndarray, view: GTView, size: tuple[int, int] | None = None,
            shift: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel ``(col, row)`` and depth ``z`` of ``points`` ``[P, 3]`` in ``view`` on a grid of ``size``
    ``(w, h)`` (default: the GT's own); the pixel is ``-1`` outside the image or behind the camera.
    ``shift``: 0 for a grid whose pixel ``(c, r)`` covers ``[c, c + 1)`` (the GT), 0.5 for a ``stereo/``
    map (pixel ``(c, r)`` holds the ray of ``(c, r)``: the nearest pixel is the rounded coordinate)."""
    H, W = view.depth.shape
    w, h = (W, H) if size is None else size
    K = np.diag([w / W, h / H, 1.0]) @ view.K
    cam = np.asarray(points, dtype=np.float64).reshape(-1, 3) @ view.cam_from_world[:, :3].T
    cam += view.cam_from_world[:, 3]
    z = cam[:, 2]
    uvw = cam @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.floor(uvw[:, 0] / uvw[:, 2] + shift)
        r = np.floor(uvw[:, 1] / uvw[:, 2] + shift)
    ok = (z > 1e-9) & (u >= 0) & (u < w) & (r >= 0) & (r < h)
    return np.where(ok, u, -1).astype(np.int64), np.where(ok, r, -1).astype(np.int64), z


def observed_mask(points: np.ndarray, views: list[GTView], behind: float) -> np.ndarray:
    """``[P]`` bool: the points some view's GT depth observes, ETH3D's idea with depth maps instead of
    laser beams. A point is observed by a view when it lies in front of its camera, projects inside its
    image onto a pixel with valid GT depth ``d``, and its depth ``z <= d + behind``: in the free space
    the GT ray crossed (an error the score must count) or near the GT surface. Points behind the GT
    surface of every view that sees them, or in no view's GT, are unobserved (not counted)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    seen = np.zeros(len(points), bool)
    for v in views:
        u, r, z = project(points, v)
        idx = np.flatnonzero(u >= 0)
        d = v.depth[r[idx], u[idx]]
        ok = (d > 0) & (z[idx] <= d + behind)
        seen[idx[ok]] = True
    return seen


def frustum_cloud_score(
    points: np.ndarray,
    gt_points: np.ndarray,
    views: list[GTView],
    thresholds: tuple[float, ...] = THRESHOLDS,
    voxel_size: float = 0.01,
    behind: float | None = None,
) -> dict:
    """ETH3D-style accuracy / completeness / F1 (%) of the cloud ``points`` against ``gt_points``,
    accuracy over the points :func:`observed_mask` keeps (``behind``: default the largest tolerance),
    completeness over every GT point against the whole cloud. Both from
    :func:`colmap_pvs.evaluate.cloud_metrics` (voxel-normalised as ETH3D; ``*_points_pct``: plain
    point fractions; ``accuracy_unmasked_pct``: every point counted, as ``cloud_metrics`` alone)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    thresholds = tuple(sorted(thresholds))
    behind = max(thresholds) if behind is None else behind
    observed = observed_mask(points, views, behind)
    acc = cloud_metrics(points[observed], gt_points, thresholds, voxel_size)
    comp = cloud_metrics(points, gt_points, thresholds, voxel_size)
    a, c = np.asarray(acc.accuracy_pct), np.asarray(comp.completeness_pct)
    f1 = np.where(a + c > 0, 2 * a * c / np.maximum(a + c, 1e-300), 0.0)
    return {
        "thresholds": list(thresholds),
        "num_points": len(points),
        "num_observed": int(observed.sum()),
        "observed_pct": 100.0 * float(observed.mean()) if len(points) else 0.0,
        "num_gt_points": len(gt_points),
        "accuracy_pct": [float(x) for x in a],
        "completeness_pct": [float(x) for x in c],
        "f1_pct": [float(x) for x in f1],
        "accuracy_points_pct": list(acc.accuracy_points_pct),
        "completeness_points_pct": list(comp.completeness_points_pct),
        "accuracy_unmasked_pct": list(comp.accuracy_pct),  # every point counted, as cloud_metrics alone
    }


# --------------------------------------------------------------------------- steps


def gt_views(model, refs: list[str], gt_dir: Path) -> list[GTView]:
    """The references' GT depth (uint16 mm) on the GT's own grid, with the dataset's own calibration
    (``K.txt`` beside ``gt_dir``, for the images' size) and the model's poses (the known ones): not the
    model's cameras, whose focal lengths ``import-poses`` refines, so that the GT cloud does not move
    with our calibration."""
    K_data = np.loadtxt(gt_dir.parent / "K.txt").reshape(3, 3)
    out = []
    for name in refs:
        depth = read_gt_depth(gt_dir / name, 0.001)
        img = model.image_by_name(name)
        cam = model.cameras[img.camera_id]
        h, w = depth.shape
        K = np.diag([w / cam.width, h / cam.height, 1.0]) @ K_data
        out.append(GTView(name, K, np.asarray(img.cam_from_world, dtype=np.float64)[:3], depth))
    return out


def run_fusion(kind: str, ws: Path, colmap: str, fuse_overrides: dict | None = None,
               out: Path | None = None) -> tuple[Path, float]:
    """Fuse ``ws`` the ``kind`` way into ``out`` (default ``ws/cloud_KIND.ply``); ``(path, seconds)``."""
    out = out or ws / f"cloud_{kind}.ply"
    start = time.perf_counter()
    if kind == "colmap":
        cmd = [colmap, "stereo_fusion", "--workspace_path", str(ws), "--workspace_format", "COLMAP",
               "--input_type", "geometric", "--output_path", str(out)]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=3600)
        if proc.returncode != 0 or not out.is_file():
            tail = proc.stderr.strip()[-500:]
            raise RuntimeError(f"colmap stereo_fusion failed ({proc.returncode}): {tail}")
    else:
        from colmap_pvs.fusion import FuseConfig, fuse

        input_type = {"pvs_geometric": "geometric", "pvs_photometric": "photometric"}.get(kind, "auto")
        settings = {"workspace_path": ws, "output_path": out, "input_type": input_type,
                    **(fuse_overrides or {})}
        fuse(config_from_dict(FuseConfig, settings))
    return out, time.perf_counter() - start


def read_points(path: Path) -> np.ndarray:
    import open3d as o3d

    pts = np.asarray(o3d.io.read_point_cloud(str(path)).points, dtype=np.float64)
    return pts[np.isfinite(pts).all(axis=1)]


def ranking(ws: Path, data: Path, refs: list[str]) -> dict:
    """Per map kind with maps: how well its confidence ranks its errors (``evaluate depth``'s relative
    AUSE, the AbsRel of the 30 % and 50 % most confident pixels and of all) and its calibration (ECE)."""
    out = {}
    for kind in ("photometric", "geometric", "filled"):
        if not any((ws / "stereo" / "depth_maps").glob(f"*.{kind}.bin")):
            continue
        m = rd.evaluate_against_gt(ws, data, refs, kind)
        sp = m.sparsification or {}
        if not sp:
            continue
        at = dict(zip(sp["fractions"], sp["error"], strict=True))
        out[kind] = {"relative_ause": sp.get("relative_ause"), "absrel_top30": at.get(0.3),
                     "absrel_top50": at.get(0.5), "absrel": at.get(1.0),
                     "ece": (m.calibration or {}).get("ece")}
    return out


def confidence_curve(ws: Path, colmap: str, levels: list[float], fuse_overrides: dict, gt_points: np.ndarray,
                     views: list[GTView], behind: float) -> list[dict]:
    """The accuracy / completeness curve of ``fuse`` along ``--min_confidence``: one cloud per level."""
    rows = []
    path = ws / "cloud_pvs_min_confidence.ply"  # one level's cloud at a time, beside the default's
    for level in levels:
        path, fuse_s = run_fusion("pvs", ws, colmap, {**fuse_overrides, "min_confidence": level}, path)
        score = frustum_cloud_score(read_points(path), gt_points, views, THRESHOLDS, 0.01, behind)
        score.update(min_confidence=level, fusion_seconds=fuse_s)
        rows.append(score)
        print(f"[min_confidence {level:g}] {score['num_points']} points, accuracy "
              f"{fmt(score['accuracy_pct'])}, completeness {fmt(score['completeness_pct'])}, "
              f"F1 {fmt(score['f1_pct'])}", flush=True)
    for leftover in (path, path.with_suffix(".ply.vis"), path.with_suffix(".fuse_config.json")):
        leftover.unlink(missing_ok=True)
    return rows


def per_frame(ws: Path, data: Path, refs: list[str], flag_points: float) -> dict:
    """Per reference: % within 5 % of the network map and the completion; the flagged frames."""
    rows = {}
    for kind in ("photometric", "filled"):
        m = rd.evaluate_against_gt(ws, data, refs, kind)
        for name, s in m.per_image.items():
            rows.setdefault(name, {})[kind] = float(s.rel_under_pct[0.05])
        rows_pooled = rows.setdefault("__pooled__", {})
        rows_pooled[kind] = float(m.pooled.rel_under_pct[0.05])
        rows_pooled[kind + "_mae_mm"] = 1000 * float(m.pooled.mae)
    pooled = rows.pop("__pooled__")
    frames = {n: r for n, r in rows.items() if "photometric" in r and "filled" in r}
    for r in frames.values():
        r["difference"] = r["filled"] - r["photometric"]
    worst = sorted(frames, key=lambda n: frames[n]["difference"])
    flagged = [n for n in worst if frames[n]["difference"] < -flag_points]
    return {"pooled": pooled, "frames": frames, "worst": worst, "flagged": flagged}


def depth_tile(gt: np.ndarray) -> np.ndarray:
    """``[H, W, 3]`` BGR of the GT depth (viridis from the 2nd to the 98th percentile; black invalid)."""
    valid = gt > 0
    tile = np.zeros((*gt.shape, 3), np.uint8)
    if valid.any():
        lo, hi = np.percentile(gt[valid], (2, 98))
        scaled = (np.clip((gt - lo) / max(hi - lo, 1e-6), 0, 1) * 255).astype(np.uint8)
        tile = cv2.applyColorMap(scaled, cv2.COLORMAP_VIRIDIS)
        tile[~valid] = 0
    return tile


def write_picture(path: Path, ws: Path, data: Path, names: list[str]) -> None:
    rows = []
    for name in names:
        gt = read_gt_depth(data / "depth" / name, 0.001)
        h, w = gt.shape
        maps = []
        for kind in ("photometric", "filled"):
            d = read_depth_map(ws / "stereo" / "depth_maps" / f"{name}.{kind}.bin")
            maps.append(d if d.shape == (h, w) else resize_nearest(d, h, w))
        row = picture_row(data / "images" / name, gt, np.zeros((h, w), bool), maps)
        conf = read_array(ws / "stereo" / "confidence_maps" / f"{name}.filled.bin")
        conf = conf if conf.shape == (h, w) else resize_nearest(conf, h, w)
        conf_tile = cv2.applyColorMap((np.clip(conf, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
        rows.append(np.concatenate([row[:, :w], depth_tile(gt), row[:, w:], conf_tile], axis=1))
    cv2.imwrite(str(path), np.concatenate(rows, axis=0), [cv2.IMWRITE_JPEG_QUALITY, 85])


def fmt(values: list[float]) -> str:
    return " / ".join(f"{v:.1f}" for v in values)


# --------------------------------------------------------------------------- main


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    rd.add_quick_args(p, "cloud", "the workspace WORK/quick/TAG_clean (hololens_quick's)", stride=3)
    p.add_argument("--fusions", nargs="*", default=list(FUSIONS), choices=FUSIONS)
    p.add_argument("--fuse", nargs="*", default=[], metavar="KEY=VALUE", help="FuseConfig fields (pvs)")
    p.add_argument("--reuse_clouds", action="store_true", help="score the clouds already in the workspace")
    p.add_argument("--colmap", default="colmap", help="the COLMAP executable")
    p.add_argument("--gt_voxel", type=float, default=0.01, help="GT cloud voxel (metres)")
    p.add_argument("--behind", type=float, default=0.10,
                   help="a point more than this (metres) behind the GT surface of every view is unobserved")
    p.add_argument("--flag_points", type=float, default=5.0)
    p.add_argument("--picture", type=Path, help="JPEG of the worst frames")
    p.add_argument("--picture_count", type=int, default=3)
    p.add_argument("--json", type=Path, help="default: the workspace's cloud_benchmark.json")
    p.add_argument("--min_confidence_curve", nargs="*", type=float, default=[], metavar="P",
                   help="also fuse (pvs) at each of these --min_confidence: the accuracy/completeness curve")
    a = p.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    wall_start = time.perf_counter()
    prepared = rd.quick_model(a)
    if prepared is None:
        return 2
    work, sparse = prepared
    model = read_sparse_model(sparse)
    names = sorted(model.image_ids_by_name)
    sel = select_views(model, config_from_dict(ViewSelectionConfig, {"num_views": a.num_views}))
    sources = rd.quick_sources(names, sel, a)
    refs = list(sources)
    ws = rd.make_workspace(work / "quick" / f"{a.tag}_clean", a.data / "images", sparse, a.resume)
    write_patch_match_cfg(ws / "stereo" / "patch-match.cfg", sources)
    start = time.perf_counter()
    from colmap_pvs.adapt import run_adapted_stereo  # run_stereo, adapting first with adapt_steps=N

    result = run_adapted_stereo(rd.stereo_config(ws, a, rd.parse_overrides(a.stereo)))
    stereo_s = time.perf_counter() - start
    print(f"[stereo] {len(result.processed)} references computed, {len(result.already_done)} kept, "
          f"{stereo_s:.0f} s", flush=True)

    start = time.perf_counter()
    views = gt_views(model, refs, a.data / "depth")
    gt_points = gt_cloud(views, a.gt_voxel)
    gt_s = time.perf_counter() - start
    print(f"[gt] {len(gt_points)} GT points from {len(views)} references ({a.gt_voxel * 100:.0f} cm voxels), "
          f"{gt_s:.0f} s", flush=True)

    clouds = {}
    for kind in a.fusions:
        if kind == "colmap" and shutil.which(a.colmap) is None:
            print(f"COLMAP executable {a.colmap!r} not found: no colmap cloud")
            continue
        path = ws / f"cloud_{kind}.ply"
        fuse_s = None
        if not (a.reuse_clouds and path.is_file()):
            path, fuse_s = run_fusion(kind, ws, a.colmap, rd.parse_overrides(a.fuse))
        start = time.perf_counter()
        score = frustum_cloud_score(read_points(path), gt_points, views, THRESHOLDS, 0.01, a.behind)
        score.update(fusion_seconds=fuse_s, score_seconds=time.perf_counter() - start, path=str(path))
        clouds[kind] = score
        print(f"[{kind}] {score['num_points']} points, F1 {fmt(score['f1_pct'])}, fusion "
              f"{fuse_s if fuse_s is None else round(fuse_s)} s, score {score['score_seconds']:.0f} s",
              flush=True)

    curve = confidence_curve(ws, a.colmap, a.min_confidence_curve, rd.parse_overrides(a.fuse), gt_points,
                             views, a.behind)
    frames = per_frame(ws, a.data, refs, a.flag_points)
    ranks = ranking(ws, a.data, refs)
    wall = time.perf_counter() - wall_start
    cm = " / ".join(f"{100 * t:.0f}" for t in THRESHOLDS)
    print(f"\n{a.tag}: {len(refs)} references, {a.max_image_size} px, N = {a.num_views}; GT cloud "
          f"{len(gt_points)} points; accuracy / completeness / F1 at {cm} cm (ETH3D-style, %)")
    print("| cloud | points | observed | accuracy | completeness | F1 |")
    print("|---|---|---|---|---|---|")
    for kind, s in clouds.items():
        print(f"| {kind} | {s['num_points']} | {s['observed_pct']:.1f} % | {fmt(s['accuracy_pct'])} | "
              f"{fmt(s['completeness_pct'])} | {fmt(s['f1_pct'])} |")
    if curve:
        print(f"\nfuse along --min_confidence (accuracy / completeness / F1 at {cm} cm, %)")
        print("| min_confidence | points | accuracy | completeness | F1 |")
        print("|---|---|---|---|---|")
        for s in curve:
            print(f"| {s['min_confidence']:g} | {s['num_points']} | {fmt(s['accuracy_pct'])} | "
                  f"{fmt(s['completeness_pct'])} | {fmt(s['f1_pct'])} |")
    print("\nconfidence per map kind: relative AUSE (0 = oracle, 1 = chance), AbsRel of the 30 % / 50 % most "
          "confident / all, ECE")
    print("| map | relative AUSE | AbsRel top 30 % / 50 % / all | ECE |")
    print("|---|---|---|---|")
    for kind, r in ranks.items():
        print(f"| {kind} | {r['relative_ause']:.3f} | {r['absrel_top30']:.4f} / {r['absrel_top50']:.4f} / "
              f"{r['absrel']:.4f} | {'-' if r['ece'] is None else format(r['ece'], '.3f')} |")
    pooled = frames["pooled"]
    print(f"\nper frame, % within 5 %: network pooled {pooled['photometric']:.1f} "
          f"(MAE {pooled['photometric_mae_mm']:.0f} mm), completion {pooled['filled']:.1f} "
          f"(MAE {pooled['filled_mae_mm']:.0f} mm); {len(frames['flagged'])} of {len(frames['frames'])} "
          f"frames with the completion more than {a.flag_points:g} points below the network: "
          f"{', '.join(frames['flagged']) or 'none'}")
    print("worst 5 (completion - network): " + "; ".join(
        f"{n} {frames['frames'][n]['photometric']:.1f} -> {frames['frames'][n]['filled']:.1f}"
        for n in frames["worst"][:5]))
    print(f"wall {wall:.0f} s (stereo {stereo_s:.0f} s)")
    if a.picture is not None and frames["worst"]:
        write_picture(a.picture, ws, a.data, frames["worst"][: a.picture_count])
        print(f"picture: {a.picture} ({', '.join(frames['worst'][: a.picture_count])})")
    out = a.json or ws / "cloud_benchmark.json"
    out.write_text(json.dumps({
        "commit": rd.git_commit(), "tag": a.tag, "references": refs, "max_image_size": a.max_image_size,
        "num_views": a.num_views, "stereo": rd.parse_overrides(a.stereo), "gt_voxel": a.gt_voxel,
        "behind": a.behind, "num_gt_points": len(gt_points), "clouds": clouds, "per_frame": frames,
        "confidence_curve": curve, "ranking": ranks,
        "seconds": {"wall": wall, "stereo": stereo_s, "gt": gt_s},
    }, indent=1))
    print(f"json: {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
