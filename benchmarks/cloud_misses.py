"""Where the fused cloud of ``cloud_benchmark.py`` misses the GT and where it is wrong (issue 39).

Reads a ``cloud_benchmark.py`` workspace (``WORK/quick/TAG_clean`` with its ``cloud_pvs.ply`` and
``.vis``; run that first) and prints two tables at the 5 cm tolerance::

    python benchmarks/cloud_misses.py --tag cloud
    python benchmarks/cloud_misses.py --tag cloud_o1 --offset 1

1. **Misses**: each GT point (the benchmark's GT cloud) with no cloud point within 5 cm, by the best
   thing any reference that sees it (its GT depth there within 5 cm of the point) holds at its pixel:
   a geometric-map depth within 5 cm ("geometric right"), else a completed depth within 5 cm
   ("completion right"), else a completed depth that is farther off ("completion wrong"), else no
   completed depth (confidence 0); or no reference sees it. Also how many of the wrong ones a
   network map (``photometric``) holds right. The first two are what fusion's rules threw away; the
   third is what only better depth can bring.
2. **Wrong points**: the observed cloud points (the benchmark's accuracy mask) by their number of
   agreeing views (the ``.vis`` entries minus the reference) and by their triangulation angle (the
   largest angle at the point between the rays to the cameras of its ``.vis`` images), with the
   share within 5 cm of the GT. Point fractions, not voxel-normalised like the benchmark's accuracy.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import real_depth as rd
from cloud_benchmark import gt_cloud, gt_views, observed_mask, project, read_points
from scipy.spatial import cKDTree

from colmap_pvs.io.maps import read_array, read_depth_map
from colmap_pvs.io.ply import read_visibility, vis_path_of
from colmap_pvs.io.sparse import image_indices, read_sparse_model

TOLERANCE = 0.05
MISS_KINDS = ("seen by no reference", "no completed depth", "completion wrong", "completion right",
              "geometric right")


def classify_misses(ws: Path, views, missed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``[M]`` index into :data:`MISS_KINDS` of each missed GT point, and ``[M]`` bool: some network map
    holds it within the tolerance."""
    best = np.zeros(len(missed), np.int64)
    network_right = np.zeros(len(missed), bool)
    maps = ws / "stereo" / "depth_maps"
    for v in views:
        filled = read_depth_map(maps / f"{v.name}.filled.bin")
        h, w = filled.shape
        conf = read_array(ws / "stereo" / "confidence_maps" / f"{v.name}.filled.bin").reshape(h, w)
        geometric = read_depth_map(maps / f"{v.name}.geometric.bin")
        network = read_depth_map(maps / f"{v.name}.photometric.bin")
        u, r, z = project(missed, v, (w, h), 0.5)
        ug, rg = project(missed, v)[:2]
        seen = (u >= 0) & (ug >= 0)
        seen[seen] = np.abs(v.depth[rg[seen], ug[seen]] - z[seen]) < TOLERANCE
        idx = np.flatnonzero(seen)
        uu, rr, zz = u[idx], r[idx], z[idx]

        right = {k: (m[rr, uu] > 0) & (np.abs(m[rr, uu] - zz) < TOLERANCE)
                 for k, m in (("filled", filled), ("geometric", geometric), ("network", network))}
        kind = np.where((filled[rr, uu] > 0) & (conf[rr, uu] > 0), np.where(right["filled"], 3, 2), 1)
        kind = np.where(right["geometric"], 4, kind)
        np.maximum.at(best, idx, kind)
        network_right[idx[right["network"]]] = True
    return best, network_right


def triangulation_angles(points: np.ndarray, offsets: np.ndarray, images: np.ndarray,
                         centres: np.ndarray) -> np.ndarray:
    """``[P]`` largest angle (degrees) at each point between the rays to the centres of its images."""
    counts = np.diff(offsets)
    owner = np.repeat(np.arange(len(points)), counts)
    rays = centres[images] - points[owner]
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
    first = rays[offsets[:-1][counts > 0]]  # the reference's ray, the first .vis entry
    cos = np.ones(len(points))
    has = np.flatnonzero(counts > 0)
    ref_of = np.zeros(len(points), np.int64)
    ref_of[has] = np.arange(len(has))
    dots = np.einsum("ij,ij->i", rays, first[ref_of[owner]])
    np.minimum.at(cos, owner, dots)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def share_table(title: str, values: np.ndarray, good: np.ndarray, edges: list[float],
                integer: bool = False) -> None:
    print(f"\n| {title} | share of points | within {100 * TOLERANCE:.0f} cm |\n|---|---|---|")
    bins = np.digitize(values, edges)
    for k in range(len(edges) + 1):
        m = bins == k
        if not m.any():
            continue
        lo = f"{edges[k - 1]:g}" if k else ""
        hi = f"{edges[k]:g}" if k < len(edges) else ""
        label = f"< {hi}" if not lo else (f">= {lo}" if not hi else f"{lo} - {hi}")
        if integer and lo and hi and edges[k] - edges[k - 1] == 1:
            label = lo
        print(f"| {label} | {100 * m.mean():.1f} % | {100 * good[m].mean():.1f} % |")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    rd.add_quick_args(p, "cloud", "the workspace WORK/quick/TAG_clean (cloud_benchmark's)", stride=3)
    p.add_argument("--gt_voxel", type=float, default=0.01, help="GT cloud voxel (metres), as the benchmark")
    p.add_argument("--behind", type=float, default=0.10, help="as the benchmark's --behind")
    a = p.parse_args()
    ws = (a.work_dir / "quick" / f"{a.tag}_clean").resolve()
    cloud = ws / "cloud_pvs.ply"
    if not cloud.is_file():
        print(f"{cloud} not found: run benchmarks/cloud_benchmark.py --tag {a.tag} first")
        return 2
    model = read_sparse_model(ws / "sparse")
    names = sorted(model.image_ids_by_name)
    refs = [n for n in names[a.offset :: a.stride]
            if (ws / "stereo" / "depth_maps" / f"{n}.filled.bin").is_file()]
    if not refs:
        print(f"no completion of the frames --offset {a.offset} --stride {a.stride} picks in {ws}")
        return 2
    views = gt_views(model, refs, a.data / "depth")
    gt = gt_cloud(views, a.gt_voxel)
    points = read_points(cloud)
    dist, _ = cKDTree(points).query(gt, workers=-1)
    missed = gt[dist > TOLERANCE]
    kinds, network_right = classify_misses(ws, views, missed)
    print(f"{a.tag}: {len(refs)} references, {len(gt)} GT points, {len(points)} cloud points; "
          f"{100 * (1 - len(missed) / len(gt)):.1f} % of the GT points have a cloud point within "
          f"{100 * TOLERANCE:.0f} cm (point fractions)")
    print("\n| GT points missed, by the best any reference holds there | share of all GT points |\n|---|---|")
    for k, label in enumerate(MISS_KINDS):
        print(f"| {label} | {100 * (kinds == k).sum() / len(gt):.2f} % |")
    both = ((kinds == 2) & network_right).sum() / len(gt)
    print(f"| (completion wrong, a network map right) | {100 * both:.2f} % |")

    offsets, images = read_visibility(vis_path_of(cloud))
    order = image_indices(ws / "sparse", model)
    centres = np.zeros((max(order.values()) + 1, 3))
    for name, i in order.items():
        centres[i] = model.image_by_name(name).center
    observed = observed_mask(points, views, a.behind)
    good = cKDTree(gt).query(points[observed], workers=-1)[0] < TOLERANCE
    agreeing = (np.diff(offsets) - 1)[observed]
    angles = triangulation_angles(points, offsets, images, centres)[observed]
    print(f"\n{100 * observed.mean():.1f} % of the cloud points observed, {100 * good.mean():.1f} % of "
          "them within the tolerance")
    share_table("agreeing views", agreeing, good, [1, 2, 3, 4], integer=True)
    share_table("triangulation angle (degrees)", angles, good, [2, 3, 5, 8, 12, 20])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
