"""Quick depth check on ``hololens-dev``: one N, the best sources (and optionally 2 far-away ones).

The N part of ``benchmarks/real_depth.py`` (same COLMAP model cache, same references, same
evaluation), for comparing checkpoints and stereo settings in a few minutes::

    python benchmarks/hololens_quick.py --checkpoint colmap_pvs/weights/pvsnet_default.pt --tag base
    python benchmarks/hololens_quick.py --tag tta30 --stereo adapt_steps=30
    python benchmarks/hololens_quick.py --stride 3 --offset 0 --disturbed --tag full   # the 60 refs
    python benchmarks/hololens_quick.py --tag base --resume --stereo geom_fill_segments=false
    python benchmarks/hololens_quick.py --tag base --resume --stereo geom_reestimate=true   # photometric kept
    python benchmarks/hololens_quick.py --tag all --all_references --stereo adapt_steps=60 \
        adapt_pseudo_labels=filled   # every frame a reference; then --offset 1 --resume: the check

``--resume`` keeps the tag's maps and recomputes only the passes whose settings changed (the
stereo step's own resume), for trying a later pass's settings without rerunning the network.

``--stereo key=value`` sets any ``StereoConfig`` field. Prints coverage, MAE, AbsRel and the % of
pixels within 1 / 2 / 5 % for the photometric, geometric and filled maps (those written).
"""

from __future__ import annotations

import argparse
import logging
import time

import real_depth as rd

from colmap_pvs.adapt import run_adapted_stereo  # run_stereo, adapting first with --stereo adapt_steps=N
from colmap_pvs.config import config_from_dict
from colmap_pvs.evaluate import EvaluateDepthConfig, evaluate_depth
from colmap_pvs.io.sparse import read_sparse_model
from colmap_pvs.io.workspace import write_patch_match_cfg
from colmap_pvs.views import ViewSelectionConfig, select_views


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    rd.add_quick_args(p, "quick", "names the workspaces under WORK/quick", stride=9)
    p.add_argument("--disturbed", action="store_true", help="also: 2 of the sources replaced by far frames")
    p.add_argument("--all_references", action="store_true",
                   help="every frame is a reference (as in a user's workspace); --stride/--offset pick the "
                   "frames evaluated")
    p.add_argument("--views", nargs="*", default=[], metavar="KEY=VALUE", help="ViewSelectionConfig fields")
    a = p.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    prepared = rd.quick_model(a)
    if prepared is None:
        return 2
    work, sparse = prepared
    model = read_sparse_model(sparse)
    names = sorted(model.image_ids_by_name)
    view_fields = {"num_views": a.num_views, **rd.parse_overrides(a.views)}
    view_cfg = config_from_dict(ViewSelectionConfig, view_fields)
    sel = select_views(model, view_cfg)
    clean = rd.quick_sources(names, sel, a)
    refs = list(clean)
    if a.all_references:  # every frame a reference; the evaluated ones keep their sources
        clean = rd.top_sources(sel, sel.references, a.num_views)
    settings = [("clean", clean)]
    if a.disturbed:
        far = {}
        for r in refs:
            ref = sel.references[r]
            row = dict(zip(ref.ranked_names, ref.ranked_scores, strict=True))
            far[r] = list(ref.ranked_names)[: a.num_views - 3] + rd.far_sources(names.index(r), names, row, 2)
        settings.append(("disturbed", far))
    extra = rd.parse_overrides(a.stereo)
    for label, sources in settings:
        ws = rd.make_workspace(work / "quick" / f"{a.tag}_{label}", a.data / "images", sparse, a.resume)
        write_patch_match_cfg(ws / "stereo" / "patch-match.cfg", sources)
        start = time.perf_counter()
        result = run_adapted_stereo(rd.stereo_config(ws, a, extra))
        wall = time.perf_counter() - start
        done = {  # per pass, the references computed now or kept as they were (--resume)
            "photometric": result.processed + result.already_done,
            "geometric": result.geometric_processed + result.geometric_done,
            "filled": result.filled_processed + result.filled_done,
        }
        for kind in ("photometric", "geometric", "filled"):
            if not any((ws / "stereo" / "depth_maps").glob(f"*.{kind}.bin")):
                continue
            m = evaluate_depth(
                EvaluateDepthConfig(workspace_path=ws, gt=a.data / "depth", gt_scale=0.001, kind=kind,
                                    images=tuple(refs), output_path=ws / f"metrics.{kind}.json")
            )
            s = m.pooled
            under = " / ".join(f"{s.rel_under_pct[t]:.1f}" for t in sorted(s.rel_under_pct))
            sp = ""
            curve = m.sparsification
            if curve and 0.5 in curve["fractions"]:
                best_half = curve["error"][curve["fractions"].index(0.5)]
                sp = f", AbsRel of the 50 % most confident {best_half:.4f}"
            print(
                f"{a.tag} {label} {kind}: {len(set(done[kind]) & set(refs))}/{len(refs)} refs, coverage "
                f"{s.coverage_pct:.1f} %, MAE {s.mae * 1000:.0f} mm, AbsRel {s.absrel:.4f}, % under "
                f"{sorted(s.rel_under_pct)}: {under}{sp}; {wall:.0f} s wall "
                f"(adaptation {result.adapt_seconds:.0f} s)",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
