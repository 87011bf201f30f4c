"""How far outlier sparse points spoil depth maps, with and without the robust depth-range rule.

Copies the real ``colmap-statue`` workspace (images linked), moves a fraction of the sparse points
observed by each evaluated reference ``FACTOR`` times farther along that reference's rays (patched
in ``points3D.bin``: the 2D observations stay), and runs ``stereo`` with the shipped checkpoint on
the clean model, then on the corrupted one with the old rule (plain 1-99th percentiles:
``depth_outlier_sigmas=0``) and with the robust rule (the default). Prints each reference's depth
range and the share of the clean map's valid pixels whose depth moved by more than 5 %.

    PYTHONPATH=. python benchmarks/depth_range_outliers.py --fraction 0.026 --factor 10
"""

from __future__ import annotations

import argparse
import functools
import logging
import shutil
import struct
import tempfile
from pathlib import Path

import numpy as np

import colmap_pvs.stereo.context as stereo_module
from colmap_pvs.io.maps import read_depth_map, save_depth_preview
from colmap_pvs.io.sparse import read_sparse_model
from colmap_pvs.io.workspace import write_patch_match_cfg
from colmap_pvs.stereo import PhotometricConfig, StereoConfig, run_stereo
from colmap_pvs.views import ViewSelectionConfig, select_views

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "colmap-statue"


def _point_offsets(data: bytes) -> dict[int, int]:
    """point id -> byte offset of its xyz in points3D.bin."""
    (count,) = struct.unpack_from("<Q", data, 0)
    offset, out = 8, {}
    for _ in range(count):
        (pid,) = struct.unpack_from("<Q", data, offset)
        out[pid] = offset + 8
        (track_len,) = struct.unpack_from("<Q", data, offset + 43)
        offset += 51 + 8 * track_len
    return out


def corrupt(sparse: Path, refs: list[str], fraction: float, factor: float, seed: int = 0) -> int:
    model = read_sparse_model(sparse)
    data = bytearray((sparse / "points3D.bin").read_bytes())
    where = _point_offsets(bytes(data))
    rows = {int(pid): k for k, pid in enumerate(model.points.ids)}
    rng = np.random.default_rng(seed)
    moved = 0
    for name in refs:
        image = model.image_by_name(name)
        ids = rng.choice(image.point3D_ids, int(round(fraction * image.point3D_ids.size)), replace=False)
        for pid in ids:
            xyz = model.points.xyz[rows[int(pid)]]
            struct.pack_into("<ddd", data, where[int(pid)], *(image.center + factor * (xyz - image.center)))
            moved += 1
    (sparse / "points3D.bin").write_bytes(bytes(data))
    return moved


def run(ws: Path, ckpt: Path | None, size: int, robust: bool) -> dict[str, np.ndarray]:
    sigmas = ViewSelectionConfig().depth_outlier_sigmas if robust else 0.0
    original = stereo_module.ViewSelectionConfig
    stereo_module.ViewSelectionConfig = functools.partial(original, depth_outlier_sigmas=sigmas)
    try:
        run_stereo(StereoConfig(workspace_path=ws, checkpoint=ckpt, overwrite=True,
                                photometric=PhotometricConfig(max_image_size=size)))
    finally:
        stereo_module.ViewSelectionConfig = original
    maps = (ws / "stereo" / "depth_maps").glob("*.geometric.bin")
    return {p.name.split(".geometric")[0]: read_depth_map(p) for p in maps}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--fraction", type=float, default=0.026)
    parser.add_argument("--factor", type=float, default=10.0)
    parser.add_argument("--refs", type=int, default=3)
    parser.add_argument("--max_image_size", type=int, default=320)
    parser.add_argument("--checkpoint", type=Path, default=None)
    parser.add_argument("--previews", type=Path, default=None,
                        help="also write REF.{clean,1-99,robust}.png depth previews (the clean colours)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    with tempfile.TemporaryDirectory() as tmp:
        ws = Path(tmp) / "ws"
        (ws / "stereo").mkdir(parents=True)
        (ws / "images").symlink_to(DATA / "images")
        shutil.copytree(DATA / "sparse", ws / "sparse")
        model = read_sparse_model(ws / "sparse")
        sel = select_views(model)
        refs = sorted(sel.references)[:: max(1, len(sel.references) // args.refs)][: args.refs]
        sources = {r: sel.references[r].source_names for r in refs}
        write_patch_match_cfg(ws / "stereo" / "patch-match.cfg", sources)
        clean = run(ws, args.checkpoint, args.max_image_size, robust=True)
        scale = {n: (float(d[d > 0].min()), float(d[d > 0].max())) for n, d in clean.items()}
        if args.previews is not None:
            for name in refs:
                save_depth_preview(args.previews / f"{name}.clean.png", clean[name], *scale[name])
        moved = corrupt(ws / "sparse", refs, args.fraction, args.factor)
        bad = read_sparse_model(ws / "sparse")
        print(f"{moved} points moved {args.factor:g}x farther "
              f"({args.fraction:.1%} of each reference's points)")
        print(f"{'reference':<14} {'rule':<12} {'depth range':>18} {'pixels off by >5 %':>20}")
        for robust in (False, True):
            maps = run(ws, args.checkpoint, args.max_image_size, robust=robust)
            sigmas = ViewSelectionConfig().depth_outlier_sigmas if robust else 0.0
            ranges = select_views(bad, ViewSelectionConfig(depth_outlier_sigmas=sigmas)).references
            for name in refs:
                if args.previews is not None:
                    tag = "robust" if robust else "1-99"
                    save_depth_preview(args.previews / f"{name}.{tag}.png", maps[name], *scale[name])
                ok = clean[name] > 0
                rel = np.abs(maps[name][ok] - clean[name][ok]) / clean[name][ok]
                lo, hi = ranges[name].depth_range
                print(f"{name:<14} {'robust' if robust else '1-99 pct':<12} {lo:8.3g} .. {hi:<8.3g} "
                      f"{100 * np.mean(rel > 0.05):19.1f} %")
        for name in refs:
            lo, hi = select_views(model).references[name].depth_range
            print(f"{name:<14} {'clean':<12} {lo:8.3g} .. {hi:<8.3g}")


if __name__ == "__main__":
    main()
