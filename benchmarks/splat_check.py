"""What the geometric maps would gain from their sources' seeds projected into them (issue 13, stop 29).

The geometric pass keeps a pixel when enough sources confirm the reference's own photometric depth.
Where that depth is wrong, the pixel is dropped even when several *other* views have a confirmed
depth for the same surface (their seeds, ``stereo/seed_maps``). The dense completion already uses
them (:func:`colmap_pvs.completion.splat_depths`: each source's map projected into the reference,
nearest surface first, the median where ``k`` sources agree within 3 %), but COLMAP's fusion reads
the geometric maps. This script measures, on a workspace after ``colmap-pvs stereo``, the pixels the
geometric map lacks and ``k`` sources' maps (``--kind seeds``, ``geometric`` or ``photometric``) agree
on:

- with ``--gt``: coverage and % within 5 % of the geometric maps, of the added pixels and of both;
- with ``--fuse OUT``: a copy of the workspace at ``OUT`` whose geometric maps hold both (normals
  re-fitted), then stock ``colmap stereo_fusion`` with its default options, and the share of fused
  points within 0.05 of the plane of their 8 nearest SfM points (as ``statue_fusion.py``).

::

    python benchmarks/hololens_quick.py --tag all --all_references --stride 9
    python benchmarks/splat_check.py --workspace outputs/benchmarks/hololens/quick/all_clean \\
        --gt ../shared/data/hololens-dev/depth --gt_scale 0.001 --k 3
    python benchmarks/statue_fusion.py --tag base --mesh 0
    python benchmarks/splat_check.py --workspace outputs/benchmarks/statue/base --k 2 \\
        --fuse outputs/benchmarks/statue/base_splat

Not part of ``stereo``: the geometric pass of a reference would need its sources' seeds, which the
same pass writes (see ``benchmarks/RESULTS.md``, stop 29).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
from sweep_check import read_gt

from colmap_pvs.completion import splat_depths
from colmap_pvs.consistency import SourceMaps
from colmap_pvs.geometry import to_homogeneous
from colmap_pvs.io.maps import read_array, write_depth_map, write_normal_map
from colmap_pvs.io.sparse import read_sparse_model
from colmap_pvs.normals import fit_normals


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--workspace", type=Path, required=True)
    p.add_argument("--kind", choices=("seeds", "geometric", "photometric"), default="seeds")
    p.add_argument("--k", type=int, default=3, help="sources that must agree (geom_fill_min_sources)")
    p.add_argument("--num_sources", type=int, default=10, help="sources of the geometric pass used")
    p.add_argument("--gt", type=Path, default=None, help="GT depth folder (NAME png or NAME.npy)")
    p.add_argument("--gt_scale", type=float, default=1.0)
    p.add_argument("--fuse", type=Path, default=None, help="write the augmented copy here and fuse it")
    p.add_argument("--colmap", default="colmap")
    a = p.parse_args()
    ws = a.workspace
    if a.fuse is not None:
        if a.fuse.exists():
            shutil.rmtree(a.fuse)
        shutil.copytree(ws, a.fuse, symlinks=True)
    model = read_sparse_model(ws / "sparse")

    def camera(name: str, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        im = model.image_by_name(name)
        cam = model.camera_of(im)
        K = cam.K.copy()
        K[0] *= shape[1] / cam.width
        K[1] *= shape[0] / cam.height
        return K, to_homogeneous(im.cam_from_world)

    def source_map(name: str) -> np.ndarray | None:
        path = (ws / "stereo" / "seed_maps" / f"{name}.bin" if a.kind == "seeds"
                else ws / "stereo" / "depth_maps" / f"{name}.{a.kind}.bin")
        return read_array(path) if path.is_file() else None

    def gt_of(name: str) -> np.ndarray | None:
        return read_gt(a.gt, name, a.gt_scale)

    counts = dict.fromkeys(("px", "kept", "added", "gt", "g", "g_ok", "a", "a_ok"), 0)
    suffix = ".geometric.json"
    for prov_path in sorted((ws / "stereo" / "provenance").glob(f"*{suffix}")):
        name = prov_path.name[: -len(suffix)]
        gt = gt_of(name)
        if a.gt is not None and gt is None and a.fuse is None:
            continue
        sources = json.loads(prov_path.read_text())["sources"][: a.num_sources]
        geo = read_array(ws / "stereo" / "depth_maps" / f"{name}.geometric.bin")
        K, T = camera(name, geo.shape)
        maps = []
        for s in sources:
            d = source_map(s)
            if d is not None:
                maps.append(SourceMaps(d, None, *camera(s, d.shape)))
        splat, _ = splat_depths(K, T, (geo.shape[1], geo.shape[0]), maps, a.k)
        added = (geo <= 0) & (splat > 0)
        counts["px"] += geo.size
        counts["kept"] += int((geo > 0).sum())
        counts["added"] += int(added.sum())
        if gt is not None and gt.shape == geo.shape:
            m = gt > 0
            rel_geo = np.abs(geo - gt) / np.maximum(gt, 1e-9)
            rel_add = np.abs(splat - gt) / np.maximum(gt, 1e-9)
            counts["gt"] += int(m.sum())
            counts["g"] += int((m & (geo > 0)).sum())
            counts["g_ok"] += int((m & (geo > 0) & (rel_geo < 0.05)).sum())
            counts["a"] += int((m & added).sum())
            counts["a_ok"] += int((m & added & (rel_add < 0.05)).sum())
        if a.fuse is not None:
            depth = np.where(geo > 0, geo, splat).astype(np.float32)
            normals = fit_normals(depth, K)
            depth[~np.any(normals != 0, axis=-1)] = 0.0
            write_normal_map(a.fuse / "stereo" / "normal_maps" / f"{name}.geometric.bin", normals)
            write_depth_map(a.fuse / "stereo" / "depth_maps" / f"{name}.geometric.bin", depth)
    c = counts
    print(f"{ws} ({a.kind}, k = {a.k}): geometric maps keep {100 * c['kept'] / c['px']:.1f} % of the pixels, "
          f"the splats add {100 * c['added'] / c['px']:.1f} %")
    if c["gt"]:
        both = c["g"] + c["a"]
        def pct(n: int, d: int) -> str:
            return f"{100 * n / max(d, 1):.1f} %"

        print(f"GT pixels: geometric {pct(c['g'], c['gt'])} at {pct(c['g_ok'], c['g'])} within 5 %; "
              f"added {pct(c['a'], c['gt'])} at {pct(c['a_ok'], c['a'])}; "
              f"both {pct(both, c['gt'])} at {pct(c['g_ok'] + c['a_ok'], both)}")
    if a.fuse is not None:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from statue_fusion import plane_distances

        from colmap_pvs.io.ply import read_point_cloud

        out = a.fuse / "fused_colmap.ply"
        subprocess.run([a.colmap, "stereo_fusion", "--workspace_path", str(a.fuse), "--workspace_format",
                        "COLMAP", "--input_type", "geometric", "--output_path", str(out)],
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        xyz = read_point_cloud(out).xyz
        d = plane_distances(np.asarray(xyz, np.float64), model.points.xyz)
        print(f"colmap stereo_fusion: {len(xyz)} points, {100 * np.mean(d < 0.05):.1f} % within 0.05 of the "
              f"SfM surface (median {np.median(d):.4f}); {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
