"""PVSNet's Fig. 3 on real data: depth error against the number of views, with unrelated views mixed in.

    python benchmarks/visibility_ablation.py \\
        --model "PVSNet=runs/noguide/model.pt" \\
        --model "CIDER mean, 2 best=runs/cider/model.pt" \\
        --model "PVSNet no truncation=runs/notrunc/model.pt"

On ``../shared/data/hololens-dev`` (the cached COLMAP model of ``benchmarks/real_depth.py``), every
``--stride``-th frame is a reference. For each checkpoint and each ``N`` in ``--views`` two source sets:

- ``mixed``: the 2 best-scored sources plus ``N-3`` unrelated frames far away in the sequence (index
  distance >= 1/3 of the sequence, lowest view score first; the selection of ``real_depth.far_sources``);
- ``best``: the ``N-1`` best-scored sources.

(``N=3`` is the same set for both.) Each run is ``colmap_pvs.stereo.run_stereo`` in a subprocess
with an explicit ``stereo/patch-match.cfg``; results are cached in ``OUT/results``, keyed by the
checkpoint's sha256, the sources and the image size, so adding a model reruns only its runs. Errors
are pooled over all valid GT pixels (``colmap_pvs.evaluate.evaluate_depth``). Prints one table and
writes ``OUT/ablation.md``, ``OUT/ablation.csv`` and ``OUT/ablation_mae.png`` (MAE against N, one
curve per model and source set).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
import time
from pathlib import Path

import real_depth as rd

ROOT = Path(__file__).resolve().parents[1]


def parse_model(text: str) -> tuple[str, Path]:
    label, sep, path = text.partition("=")
    if not sep or not label or not path:
        raise argparse.ArgumentTypeError(f"--model expects LABEL=PATH, got {text!r}")
    return label, Path(path)


def run_one(
    out: Path, slug: str, sparse: Path, chosen: dict, n: int, ckpt: Path, refs: list[str], args
) -> dict:
    """Stereo with the explicit ``chosen`` sources in a fresh workspace, then the pooled metrics."""
    from colmap_pvs.io.workspace import write_patch_match_cfg

    ws = rd.make_workspace(out / "ws" / slug, args.data / "images", sparse)
    write_patch_match_cfg(ws / "stereo" / "patch-match.cfg", chosen)
    spec = {
        "workspace": str(ws),
        "num_views": n,
        "max_image_size": args.max_image_size,
        "checkpoint": str(ckpt.resolve()),
        "threads": args.threads,
    }
    result = rd.run_worker("stereo", spec, out / "logs" / f"{slug}.log")
    m = rd.evaluate_against_gt(ws, args.data, refs).pooled
    return {
        "mae_m": m.mae,
        "absrel": m.absrel,
        "under5_pct": m.rel_under_pct[0.05],
        "coverage_pct": m.coverage_pct,
        "s_per_image": result["seconds_per_image"],
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--model", type=parse_model, action="append", required=True, help="LABEL=CHECKPOINT")
    p.add_argument("--data", type=Path, default=rd.DEFAULT_DATA, help="hololens-dev folder")
    p.add_argument("--work_dir", type=Path, default=rd.DEFAULT_WORK, help="cache (shared with real_depth.py)")
    p.add_argument("--output", type=Path, default=ROOT / "outputs" / "benchmarks" / "ablation")
    p.add_argument("--views", type=int, nargs="+", default=[3, 5, 7, 9, 11], help="N (reference included)")
    p.add_argument("--stride", type=int, default=16, help="every STRIDE-th frame is a reference")
    p.add_argument("--offset", type=int, default=None, help="first reference index (default STRIDE // 2)")
    p.add_argument("--max_image_size", type=int, default=320)
    p.add_argument("--threads", type=int, default=0, help="torch threads; 0 = torch's default")
    p.add_argument(
        "--plot", choices=["mixed", "best", "both"], default="both", help="source sets drawn in the plot"
    )
    args = p.parse_args(argv)
    if min(args.views) < 3:
        p.error(f"--views must be >= 3 (2 best sources + the reference), got {args.views}")
    if not (args.data / "poses.txt").is_file():
        print(f"hololens-dev data not found at {args.data} (pass --data); nothing to do", file=sys.stderr)
        return 2
    for label, path in args.model:
        if not path.is_file():
            print(f"checkpoint {path} of {label!r} does not exist", file=sys.stderr)
            return 2

    from colmap_pvs.io.files import file_sha256
    from colmap_pvs.io.sparse import read_sparse_model
    from colmap_pvs.train.trainer import plot_curves
    from colmap_pvs.views import ViewSelectionConfig, select_views

    start = time.perf_counter()
    work = args.work_dir.resolve()
    sparse = rd.build_model(args.data, work, args.threads)
    model = read_sparse_model(sparse)
    names = sorted(model.image_ids_by_name)
    selection = select_views(model, ViewSelectionConfig(num_views=max(args.views)))
    offset = args.stride // 2 if args.offset is None else args.offset
    refs = [n for n in names[offset :: args.stride] if n in selection.references]
    print(f"[refs] {len(refs)} reference frames: {', '.join(refs)}", flush=True)

    def sources(ref: str, n: int, mixed: bool) -> list[str]:
        sel = selection.references[ref]
        if not mixed:
            return list(sel.ranked_names[: n - 1])
        row = dict(zip(sel.ranked_names, sel.ranked_scores, strict=True))
        return list(sel.ranked_names[:2]) + rd.far_sources(names.index(ref), names, row, n - 3)

    out = args.output.resolve()
    out.mkdir(parents=True, exist_ok=True)
    shas = {label: file_sha256(path) for label, path in args.model}
    rows: list[dict] = []
    for label, ckpt in args.model:
        for n in sorted(set(args.views)):
            for kind in ("mixed", "best") if n > 3 else ("mixed",):
                slug = "".join(c if c.isalnum() else "_" for c in f"{label}_{kind}_N{n}")[:60]
                chosen = {r: sources(r, n, kind == "mixed") for r in refs}
                key = {"checkpoint_sha256": shas[label], "sources": chosen, "size": args.max_image_size}
                done = out / "results" / f"{slug}.json"
                cached = json.loads(done.read_text()) if done.is_file() else None
                if cached is not None and cached["key"] == key:
                    row = cached["row"]
                else:
                    row = run_one(out, slug, sparse, chosen, n, ckpt, refs, args)
                    done.parent.mkdir(parents=True, exist_ok=True)
                    done.write_text(json.dumps({"key": key, "row": row}))
                for k in ("mixed", "best") if n == 3 else (kind,):
                    rows.append({"model": label, "sources": k, "N": n, **row})
                print(
                    f"[{label} | {kind} | N={n}] MAE {row['mae_m']:.4f} m, AbsRel {row['absrel']:.4f}, "
                    f"<5% {row['under5_pct']:.1f}%, {row['s_per_image']:.2f} s/image"
                    + (" (cached)" if cached is not None and cached["key"] == key else ""),
                    flush=True,
                )

    views = sorted(set(args.views))
    header = "| model | sources | " + " | ".join(f"N={n}" for n in views) + " |"
    lines = [
        "MAE (m) / AbsRel pooled over every valid GT pixel of the references "
        f"({len(refs)} frames, every {args.stride}th of {len(names)}, {args.max_image_size} px).",
        "",
        header,
        "|" + "---|" * (2 + len(views)),
    ]
    for label, _ in args.model:
        for kind in ("mixed", "best"):
            cells = []
            for n in views:
                match = [r for r in rows if r["model"] == label and r["sources"] == kind and r["N"] == n]
                r = match[0] if match else None
                cells.append("-" if r is None else f"{r['mae_m']:.3f} / {r['absrel']:.3f}")
            lines.append(f"| {label} | {kind} | " + " | ".join(cells) + " |")
    table = "\n".join(lines)
    (out / "ablation.md").write_text(table + "\n")
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    (out / "ablation.csv").write_text(buf.getvalue())
    series = {}
    for label, _ in args.model:
        for kind in ("mixed", "best") if args.plot == "both" else (args.plot,):
            pts = sorted((r["N"], r["mae_m"]) for r in rows if (r["model"], r["sources"]) == (label, kind))
            name = label if args.plot != "both" else f"{label} ({kind})"
            series[name] = ([x for x, _ in pts], [y for _, y in pts])
    plot_curves(
        out / "ablation_mae.png",
        series,
        title=f"hololens-dev: depth MAE (m) vs views ({args.plot}; mixed = 2 best + far-away frames)",
        xlabel="N (views)",
        log_y=False,
    )
    print()
    print(table)
    print(f"\nwritten to {out} in {(time.perf_counter() - start) / 60:.1f} min")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
