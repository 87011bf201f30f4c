"""The learned peers on ``hololens-dev`` with our cameras, references and sources: network maps only.

IterMVS (DTU and BlendedMVS weights) and PatchmatchNet, run by ``tools/teacher_labels.py``'s
:class:`Teacher` (their clones stay outside the repository; see that tool's docstring), on the
references and sources of ``hololens_quick.py`` (the same cached COLMAP model, the top ``N - 1``
sources by view score, the same depth ranges, 540 px), scored by the same
:func:`colmap_pvs.evaluate.evaluate_depth`. Each peer's depth is written as the photometric map of its
own workspace ``WORK/quick/peer_<teacher>_n<N>_o<offset>``, so its numbers read like ours::

    python benchmarks/peers.py --itermvs /path/IterMVS --patchmatchnet /path/PatchmatchNet \\
        --stride 3 --num_views 11
    python benchmarks/hololens_quick.py --stride 3 --num_views 11 --tag n11 \\
        --stereo geom_consistency=false geom_fill=false   # ours, the same references and sources

A rerun keeps the maps whose teacher, sources and depth range are unchanged.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import real_depth as rd
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import teacher_labels as tl  # noqa: E402

from colmap_pvs.config import config_from_dict  # noqa: E402
from colmap_pvs.evaluate import EvaluateDepthConfig, evaluate_depth  # noqa: E402
from colmap_pvs.io.maps import write_depth_map  # noqa: E402
from colmap_pvs.io.workspace import write_patch_match_cfg  # noqa: E402
from colmap_pvs.views import ViewSelectionConfig  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--itermvs", type=Path, required=True, help="a clone of IterMVS with its checkpoints/")
    p.add_argument("--patchmatchnet", type=Path, required=True, help="a clone of PatchmatchNet")
    p.add_argument("--teachers", nargs="*", default=sorted(tl.TEACHER_KINDS),
                   choices=sorted(tl.TEACHER_KINDS))
    p.add_argument("--data", type=Path, default=rd.DEFAULT_DATA)
    p.add_argument("--work_dir", type=Path, default=rd.DEFAULT_WORK)
    p.add_argument("--stride", type=int, default=9)
    p.add_argument("--offset", type=int, default=0)
    p.add_argument("--num_views", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    prepared = rd.quick_model(a)
    if prepared is None:
        return 2
    work, sparse = prepared
    torch.set_num_threads(a.threads)
    repos = {"itermvs": a.itermvs, "patchmatchnet": a.patchmatchnet}
    for key in a.teachers:
        teacher = tl.Teacher(key, repos[tl.TEACHER_KINDS[key].repo])
        ws = rd.make_workspace(work / "quick" / f"peer_{key}_n{a.num_views}_o{a.offset}", a.data / "images",
                               sparse, keep_stereo=True)
        sd = tl.load_scene(ws, 1, config_from_dict(ViewSelectionConfig, {"num_views": a.num_views}))
        sources = rd.quick_sources(list(sd.Ks), sd.selection, a)
        refs = list(sources)
        write_patch_match_cfg(ws / "stereo" / "patch-match.cfg", sources)
        images = tl.ImageCache(ws)
        seconds = []
        for r in tqdm(refs, desc=f"{key} N={a.num_views}", unit="image"):
            rng = sd.selection.references[r].depth_range
            meta = tl.estimate_meta(key, teacher, r, sources[r], rng)
            out = ws / "stereo" / "depth_maps" / f"{r}.photometric.bin"
            stamp = out.with_suffix(".json")
            if out.is_file() and stamp.is_file() and json.loads(stamp.read_text()).get("meta") == meta:
                continue
            views = [r, *sources[r]]
            t0 = time.perf_counter()
            depth, _ = teacher.run([images.get(n) for n in views], [sd.Ks[n] for n in views],
                                   [sd.poses[n] for n in views], *rng)
            seconds.append(time.perf_counter() - t0)
            write_depth_map(out, depth)
            stamp.write_text(json.dumps({"meta": meta}))
        m = evaluate_depth(EvaluateDepthConfig(workspace_path=ws, gt=a.data / "depth", gt_scale=0.001,
                                               kind="photometric", images=tuple(refs),
                                               output_path=ws / "metrics.photometric.json"))
        s = m.pooled
        under = " / ".join(f"{s.rel_under_pct[t]:.1f}" for t in sorted(s.rel_under_pct))
        speed = f", {np.mean(seconds):.2f} s per image" if seconds else ""
        print(f"{key} N={a.num_views} offset {a.offset}: {len(refs)} refs, coverage {s.coverage_pct:.1f} %, "
              f"MAE {s.mae * 1000:.0f} mm, AbsRel {s.absrel:.4f}, % under {sorted(s.rel_under_pct)}: "
              f"{under}{speed}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
