"""Per-stage profile of one ``colmap-pvs stereo`` run (every pass) on ``hololens-dev``.

    python benchmarks/profile_stereo.py --count 10 --max_image_size 540 --num_views 5 --threads 2

Builds (or reuses) the COLMAP model of ``benchmarks/real_depth.py`` in ``--work_dir``, makes a fresh
workspace whose ``patch-match.cfg`` lists ``--count`` consecutive frames from ``--first`` (every
reference's sources are automatic, so their photometric maps are computed too: the geometric pass
needs them), runs :func:`colmap_pvs.stereo.run_stereo` once in this process and prints: seconds per
image of each pass (wall time of the pass / maps it wrote), the per-stage sums of
``StereoResult.timings`` (load, prior, network, confidence, normals, writes, previews, and the
geometric pass's load, consistency, confidence, normals, writes; the dense completion's load, splat,
fit, writes) and the peak RSS. ``--record``
appends the table to ``benchmarks/RESULTS.md``. Timings on a shared machine are upper bounds.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import resource
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import real_depth  # noqa: E402  (the model builder and workspace helpers)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=real_depth.DEFAULT_DATA)
    p.add_argument("--work_dir", type=Path, default=real_depth.DEFAULT_WORK)
    p.add_argument("--first", type=int, default=60, help="index of the first reference frame")
    p.add_argument("--count", type=int, default=10, help="consecutive reference frames")
    p.add_argument("--max_image_size", type=int, default=540)
    p.add_argument("--num_views", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--previews", action="store_true")
    p.add_argument("--no_geom", action="store_true", help="photometric pass only")
    p.add_argument("--record", action="store_true", help="append the table to benchmarks/RESULTS.md")
    p.add_argument("--stereo", nargs="*", default=[], metavar="KEY=VALUE", help="more StereoConfig fields")
    args = p.parse_args(argv)
    if not (args.data / "poses.txt").is_file():
        print(f"hololens-dev data not found at {args.data}", file=sys.stderr)
        return 2

    from colmap_pvs.config import config_from_dict
    from colmap_pvs.stereo import StereoConfig, run_stereo

    work = args.work_dir.resolve()
    sparse, refs = real_depth.consecutive_references(args.data, work, args.threads, args.first, args.count)
    ws = work / "ws" / "profile"
    if ws.exists():
        shutil.rmtree(ws)
    real_depth.auto_sources_workspace(ws, args.data / "images", sparse, refs, args.num_views)
    start = time.perf_counter()
    fields = {
        "workspace_path": str(ws),
        "num_views": args.num_views,
        "max_image_size": args.max_image_size,
        "threads": args.threads,
        "device": "cpu",
        "previews": args.previews,
        "geom_consistency": not args.no_geom,
    }
    res = run_stereo(config_from_dict(StereoConfig, {**fields, **real_depth.parse_overrides(args.stereo)}))
    wall = time.perf_counter() - start
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    n_photo = len(res.processed) + len(res.auxiliary)
    n_geo = len(res.geometric_processed)
    n_fill = len(res.filled_processed)
    n_confirm = len(res.confirm_processed)
    lines = [
        f"{len(refs)} references + {len(res.auxiliary)} auxiliary sources, {args.max_image_size} px, "
        f"N={args.num_views}, {args.threads} threads; wall {wall:.1f} s, peak RSS {rss:.0f} MB",
        "",
        "| pass / stage | total s | s per map |",
        "|---|---|---|",
    ]
    per = {"photometric": max(n_photo, 1), "geometric": max(n_geo, 1), "filled": max(n_fill, 1),
           "confirm": max(n_confirm, 1)}
    lines.append(f"| prepare (workspace, model, view selection) | {res.timings.get('prepare', 0):.2f} | |")
    for pass_name in ("photometric", "geometric", "filled", "confirm"):
        if pass_name not in res.pass_seconds:
            continue
        sec = res.pass_seconds[pass_name]
        lines.append(f"| **{pass_name} pass** ({per[pass_name]} maps) | {sec:.1f} | "
                     f"**{sec / per[pass_name]:.2f}** |")
        for key, value in res.timings.items():
            later = key.startswith(("geometric.", "filled.", "confirm."))
            stage_pass = key.split(".")[0] if later else "photometric"
            if key == "prepare" or stage_pass != pass_name:
                continue
            lines.append(f"| &nbsp; {key} | {value:.2f} | {value / per[pass_name]:.3f} |")
    if n_photo and n_geo:
        total = res.pass_seconds["photometric"] / n_photo + res.pass_seconds["geometric"] / n_geo
        total += res.pass_seconds["filled"] / n_fill if n_fill else 0.0
        total += res.pass_seconds["confirm"] / n_confirm if n_confirm else 0.0
        lines.append(f"| **every default pass, per image** (sum of per-map times) | | **{total:.2f}** |")
    table = "\n".join(lines)
    print(table)
    if args.record:
        date = _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
        with real_depth.RESULTS.open("a") as f:
            f.write(f"\n## stereo profile, {date}, commit `{real_depth.git_commit()}`\n\n{table}\n")
        print(f"appended to {real_depth.RESULTS}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
