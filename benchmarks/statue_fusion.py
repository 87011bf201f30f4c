"""The drop-in check of issue 13 on ``colmap-statue``: our maps through COLMAP's own ``stereo_fusion``.

Copies the real COLMAP workspace ``../shared/data/colmap-statue`` (images linked, ``sparse`` and
``stereo/*.cfg`` copied, so COLMAP's own view selection is used), runs ``colmap-pvs stereo`` in it,
then the stock ``colmap stereo_fusion --input_type geometric`` with its default options and
``colmap poisson_mesher`` as the README runs it (``--PoissonMeshing.trim 5``). Prints the fused point
count, the mesh's size and how far the points lie from the SfM surface: for each fused point, the
distance to the least-squares plane of its 8 nearest SfM points (in the model's units; the statue is
about 1.5 units tall). No GT exists for this scene, so this measures agreement with the sparse model,
which is pessimistic where the SfM points are sparse (the table, the paper)::

    python benchmarks/statue_fusion.py                       # 640 px, N = 5, shipped weights
    python benchmarks/statue_fusion.py --tag tta --stereo adapt_steps=60 adapt_pseudo_labels=filled
    python benchmarks/statue_fusion.py --resume --fusion StereoFusion.min_num_pixels=3

``--resume`` keeps the tag's maps (the stereo step's own resume). ``--fusion KEY=VALUE`` passes
``--KEY VALUE`` to ``colmap stereo_fusion``.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import real_depth as rd

from colmap_pvs.adapt import run_adapted_stereo  # run_stereo, adapting first with --stereo adapt_steps=N
from colmap_pvs.io.sparse import read_sparse_model

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "colmap-statue"
WORK = Path(__file__).resolve().parents[1] / "outputs" / "benchmarks" / "statue"


def make_workspace(root: Path, data: Path, resume: bool) -> Path:
    """A COLMAP dense workspace at ``root``: images linked, sparse model and stereo configs copied."""
    if root.exists() and not resume:
        shutil.rmtree(root)
    (root / "stereo").mkdir(parents=True, exist_ok=True)
    if not (root / "images").exists():
        (root / "images").symlink_to((data / "images").resolve())
    if not (root / "sparse").exists():
        shutil.copytree(data / "sparse", root / "sparse")
    for cfg in ("patch-match.cfg", "fusion.cfg"):
        if (data / "stereo" / cfg).is_file():
            shutil.copy2(data / "stereo" / cfg, root / "stereo" / cfg)
    return root


def plane_distances(points: np.ndarray, sfm: np.ndarray, k: int = 8) -> np.ndarray:
    """``[P]`` distance of each of ``points`` ``[P, 3]`` to the LSQ plane of its ``k`` nearest ``sfm``."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sfm))
    tree = o3d.geometry.KDTreeFlann(cloud)
    out = np.empty(len(points))
    for i, p in enumerate(points):
        _, idx, _ = tree.search_knn_vector_3d(p, k)
        nb = sfm[np.asarray(idx)]
        centre = nb.mean(axis=0)
        normal = np.linalg.svd(nb - centre)[2][-1]
        out[i] = abs(float((p - centre) @ normal))
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DATA)
    p.add_argument("--work_dir", type=Path, default=WORK)
    p.add_argument("--tag", default="base", help="names the workspace under WORK")
    p.add_argument("--checkpoint", type=Path, default=rd.DEFAULT_CHECKPOINT)
    p.add_argument("--max_image_size", type=int, default=640)
    p.add_argument("--num_views", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--resume", action="store_true", help="keep the tag's current maps")
    p.add_argument("--stereo", nargs="*", default=[], metavar="KEY=VALUE", help="more StereoConfig fields")
    p.add_argument("--fusion", nargs="*", default=[], metavar="KEY=VALUE",
                   help="options of colmap stereo_fusion, e.g. StereoFusion.min_num_pixels=3")
    p.add_argument("--mesh", type=int, default=1, help="1: also colmap poisson_mesher on the cloud")
    p.add_argument("--mesher", nargs="*", default=["PoissonMeshing.trim=5"], metavar="KEY=VALUE",
                   help="options of colmap poisson_mesher (default: the README's trim 5; the default trim "
                   "10 leaves an empty mesh of this cloud)")
    p.add_argument("--colmap", default="colmap", help="the COLMAP executable")
    a = p.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if not (a.data / "sparse").is_dir():
        print(f"colmap-statue not found at {a.data}; nothing to do")
        return 2
    if shutil.which(a.colmap) is None:
        print(f"COLMAP executable {a.colmap!r} not found; nothing to do")
        return 2
    ws = make_workspace(a.work_dir.resolve() / a.tag, a.data, a.resume)
    start = time.perf_counter()
    result = run_adapted_stereo(rd.stereo_config(ws, a, rd.parse_overrides(a.stereo)))
    stereo_s = time.perf_counter() - start
    count = len(result.processed) + len(result.already_done)

    fused = ws / "fused_colmap.ply"
    cmd = [a.colmap, "stereo_fusion", "--workspace_path", str(ws), "--workspace_format", "COLMAP",
           "--input_type", "geometric", "--output_path", str(fused)]
    for item in a.fusion:
        key, _, value = item.partition("=")
        cmd += [f"--{key}", value]
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    fusion_s = time.perf_counter() - start
    if proc.returncode != 0:
        print(f"colmap stereo_fusion failed ({proc.returncode}): {proc.stderr.strip()[-500:]}")
        return 1
    import open3d as o3d

    mesh_text = ""
    if a.mesh:
        meshed = ws / "meshed_colmap.ply"
        cmd = [a.colmap, "poisson_mesher", "--input_path", str(fused), "--output_path", str(meshed)]
        for item in a.mesher:
            key, _, value = item.partition("=")
            cmd += [f"--{key}", value]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
        if proc.returncode != 0 or not meshed.is_file():
            print(f"colmap poisson_mesher failed ({proc.returncode}): {proc.stderr.strip()[-500:]}")
            return 1
        mesh = o3d.io.read_triangle_mesh(str(meshed))
        mesh_text = (f"; colmap poisson_mesher {' '.join(a.mesher)}: {len(mesh.vertices)} vertices, "
                     f"{len(mesh.triangles)} triangles")
    pts = np.asarray(o3d.io.read_point_cloud(str(fused)).points)
    sfm = read_sparse_model(ws / "sparse").points.xyz
    d = plane_distances(pts, sfm) if len(pts) else np.zeros(0)
    within = 100 * float(np.mean(d < 0.05)) if d.size else 0.0
    median = float(np.median(d)) if d.size else float("nan")
    print(
        f"{a.tag}: {count} images, stereo {stereo_s:.0f} s ({stereo_s / max(1, count):.2f} s per image, "
        f"adaptation {result.adapt_seconds:.0f} s); colmap stereo_fusion {fusion_s:.0f} s: "
        f"{len(pts)} points, {within:.1f} % within 0.05 of the SfM surface (median {median:.4f}){mesh_text}; "
        f"{fused}",
        flush=True,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
