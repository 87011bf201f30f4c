"""Depth accuracy of a checkpoint on held-out synthetic scenes (never used in training).

    python benchmarks/synthetic_val.py --checkpoint colmap_pvs/weights/pvsnet_default.pt

Held-out scenes come from a seed far from the training seeds (``--seed``). Prints one row per
variant: the checkpoint as trained, sparse guidance off/on, sparse prior off/on and visibility off
(mean aggregation), with MAE (scene units), AbsRel, % of pixels under 1/2/5 % relative error (all
valid GT pixels, final full-resolution depth), the same AbsRel and % under 5 % on the pixels of thin
structures (``evaluate.thin_structure_mask``) and coverage / AbsRel after the stereo step's confidence
filter. ``--families plant`` draws the held-out scenes from other families (stop 31: the plant's fronds)::

    python benchmarks/synthetic_val.py --checkpoint runs/x/model.pt --families plant --as_trained_only

``--classes`` adds, per variant, the % within 5 % of the classes of ``blind_spots.py`` (issue 56: outside
the sample's own depth range, slanted, low texture, thin; the same masks and thresholds as on
``hololens-dev``) and each class's share of the pixels, to compare the renders with the real frames.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from blind_spots import CLASSES, class_masks, counts

from colmap_pvs.config import replace_config
from colmap_pvs.evaluate import thin_structure_mask
from colmap_pvs.model import PVSNet, load_checkpoint
from colmap_pvs.synthetic import SyntheticDatasetConfig, SyntheticMVSDataset
from colmap_pvs.synthetic.scenes import FAMILIES, SceneConfig


def sample_class_masks(sample: dict) -> dict[str, np.ndarray]:
    """The classes of ``blind_spots.class_masks`` ``[H, W]`` of one sample's reference (view 0), with the
    sample's own depth range."""
    gt = sample["depth"].numpy()
    rgb = sample["images"][0].numpy()
    grey = 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]
    K = sample["intrinsics"][0].numpy().astype(np.float64)
    return class_masks(gt, grey, K, (float(sample["depth_min"]), float(sample["depth_max"])))


def class_counts(depth: np.ndarray, sample: dict,
                 masks: dict[str, np.ndarray] | None = None) -> dict[str, tuple[int, int]]:
    """``{class: (pixels within 5 %, pixels)}`` of one sample's ``depth`` ``[H, W]`` (its reference:
    view 0), over its ``masks`` (default: :func:`sample_class_masks`), counted by ``blind_spots.counts``."""
    masks = sample_class_masks(sample) if masks is None else masks
    gt = sample["depth"].numpy()
    out = {}
    for c, m in masks.items():
        n, _, within = counts(depth, gt, m)
        out[c] = (within, n)
    return out


def evaluate(model: PVSNet, dataset, n: int, min_confidence: float,
             masks: list[dict[str, np.ndarray]] | None = None) -> dict[str, float]:
    """The metrics of ``model`` on the first ``n`` samples; per class too with ``masks`` (one
    :func:`sample_class_masks` per sample, made once for every variant)."""
    errs, rels, covered, rels_kept, total_valid, rels_thin = [], [], 0, [], 0, []
    seconds = []
    per_class = {c: [0, 0] for c in CLASSES}
    for i in range(n):
        s = dataset[i]
        t0 = time.perf_counter()
        with torch.inference_mode():
            out = model(
                s["images"][None], s["intrinsics"][None], s["cam_from_world"][None],
                s["depth_min"][None], s["depth_max"][None], sparse_depth=s["sparse_depth"][None],
            )
        seconds.append(time.perf_counter() - t0)
        d, c, gt = out.depth[0].numpy(), out.confidence[0].numpy(), s["depth"].numpy()
        v = gt > 0
        e = np.abs(d[v] - gt[v])
        errs.append(e)
        rels.append(e / gt[v])
        thin = thin_structure_mask(gt)
        rels_thin.append(np.abs(d[thin] - gt[thin]) / gt[thin])
        keep = c[v] >= min_confidence
        covered += int(keep.sum())
        total_valid += int(v.sum())
        rels_kept.append((e / gt[v])[keep])
        if masks is not None:
            for c, (k, m) in class_counts(d, s, masks[i]).items():
                per_class[c][0] += k
                per_class[c][1] += m
    e, r, rk, rt = (np.concatenate(x) for x in (errs, rels, rels_kept, rels_thin))
    return {
        "mae": float(e.mean()),
        "absrel": float(r.mean()),
        "pct1": float((r < 0.01).mean() * 100),
        "pct2": float((r < 0.02).mean() * 100),
        "pct5": float((r < 0.05).mean() * 100),
        "absrel_thin": float(rt.mean()) if rt.size else float("nan"),
        "pct5_thin": float((rt < 0.05).mean() * 100) if rt.size else float("nan"),
        "coverage": covered / max(total_valid, 1) * 100,
        "absrel_kept": float(rk.mean()) if rk.size else float("nan"),
        "s_per_sample": float(np.mean(seconds)),
        "classes": {c: (100 * k / max(m, 1), m) for c, (k, m) in per_class.items()},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--samples", type=int, default=48)
    ap.add_argument("--seed", type=int, default=5_000_000, help="held-out scene seed (training uses 0..)")
    ap.add_argument("--strategy", default="anti_noise", choices=["anti_noise", "best"])
    ap.add_argument("--min_confidence", type=float, default=0.3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--families", nargs="+", default=list(FAMILIES), help="scene families drawn")
    ap.add_argument("--as_trained_only", action="store_true", help="skip the switch variants")
    ap.add_argument("--classes", action="store_true",
                    help="also the %% within 5 %% of blind_spots.py's classes")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    model, meta = load_checkpoint(args.checkpoint)
    ds = SyntheticMVSDataset(
        SyntheticDatasetConfig(num_samples=args.samples, seed=args.seed, source_strategy=args.strategy,
                               samples_per_scene=4, scene=SceneConfig(families=tuple(args.families)))
    )
    state = model.state_dict()
    variants = {
        "as trained": model.config,
        "sparse guidance off": replace_config(model.config, sparse_guidance=False),
        "sparse guidance on": replace_config(model.config, sparse_guidance=True),
        "sparse prior off": replace_config(model.config, sparse_prior=False),
        "sparse prior on": replace_config(model.config, sparse_prior=True),
        "visibility off (mean)": replace_config(model.config, visibility=False),
    }
    if args.as_trained_only:
        variants = {"as trained": model.config}
    print(f"checkpoint {args.checkpoint} (step {meta.get('step')}), {args.samples} held-out samples, "
          f"seed {args.seed}, families {args.families}, sources: {args.strategy}, "
          f"{ds[0]['images'].shape[0]} views, "
          f"{tuple(ds[0]['depth'].shape[::-1])} px")
    header = (f"| variant | MAE | AbsRel | % <1% | % <2% | % <5% | thin: AbsRel / % <5% "
              f"| coverage @conf{args.min_confidence} | AbsRel kept | s/sample |")
    print(header)
    print("|" + "---|" * 10)
    masks = [sample_class_masks(ds[i]) for i in range(args.samples)] if args.classes else None
    results = {}
    for name, cfg in variants.items():
        m = PVSNet(cfg)
        wanted = m.state_dict()
        m.load_state_dict({k: v for k, v in state.items() if k in wanted})  # visibility off: no vis net
        m.eval()
        r = results[name] = evaluate(m, ds, args.samples, args.min_confidence, masks)
        print(f"| {name} | {r['mae']:.4f} | {r['absrel']:.4f} | {r['pct1']:.1f} | {r['pct2']:.1f} | "
              f"{r['pct5']:.1f} | {r['absrel_thin']:.3f} / {r['pct5_thin']:.1f} | {r['coverage']:.1f}% | "
              f"{r['absrel_kept']:.4f} | {r['s_per_sample']:.2f} |")
    if args.classes:
        first = next(iter(results.values()))["classes"]
        total = first["all"][1]
        print("\n% within 5 % by class (blind_spots.py's classes; the class's share of the GT pixels)")
        shares = [f"{c} ({100 * n / max(total, 1):.1f} %)" for c, (_, n) in first.items()]
        print("| variant | " + " | ".join(shares) + " |")
        print("|" + "---|" * (len(CLASSES) + 1))
        for name, r in results.items():
            print(f"| {name} | " + " | ".join(f"{p:.1f}" for p, _ in r["classes"].values()) + " |")


if __name__ == "__main__":
    main()
