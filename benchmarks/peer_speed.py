"""The whole default ``colmap-pvs stereo`` command against IterMVS's whole process, alternated (issue 57).

    python benchmarks/peer_speed.py --itermvs /path/IterMVS --repeats 3
    python benchmarks/peer_speed.py --itermvs /path/IterMVS --ours old=/venv-old/bin/python \\
        --ours new=/venv-new/bin/python          # old and new code in the same alternation

The frames are ``profile_stereo.py``'s: ``--count`` consecutive frames from ``--first`` of
``hololens-dev`` (the COLMAP model ``real_depth.build_model`` caches in ``--work_dir``), 540 px, N = 5.
Both sides get the same sources and depth ranges, and our run's view selection decides them: the
workspace's ``stereo/patch-match.cfg`` lists each reference with ``__auto__, N-1`` (as
``profile_stereo.py`` does), the stereo step's own :func:`~colmap_pvs.stereo.context.prepare_stereo`
resolves it (:func:`plan_views`), the result is written to ``WORK/ws/peer_speed/sources.json``, IterMVS
is given exactly those sources and ranges, and after each of our runs its photometric provenance is
checked against them (:func:`plan_mismatches`; a difference is printed as a warning).

Each side is one fresh subprocess, timed from this process: wall time, CPU time (user + sys) and peak
RSS of the child (``os.wait4``); the 1-minute load average is read before each run. The order is
ours (each ``--ours`` in turn), IterMVS (then IterMVS with its filtering), repeated ``--repeats``
times. What each side includes:

- ours: ``colmap-pvs stereo --workspace_path W --max_image_size 540 --num_views 5 --threads 2`` (the
  ``colmap-pvs`` script next to each ``--ours`` python, else ``python -m colmap_pvs.cli``) on a fresh
  workspace (``images/`` and ``sparse/`` linked, only ``patch-match.cfg`` in ``stereo/``, no maps):
  Python start-up and imports, the model's load, view selection, the photometric maps of the
  references and of their auxiliary sources (the sources that are no reference, which the geometric
  pass needs), the geometric pass, the dense completion and its confirmation, every default output
  written (depth, normal, confidence, visibility, seed maps, provenance, ``fusion.cfg``).
- IterMVS (``--child itermvs``, this script in a child process): Python start-up, the imports of torch,
  of IterMVS (its clone's ``models.net``, through ``tools/teacher_labels.py``'s :class:`Teacher`, which
  also prepares its inputs as its ``datasets/custom.py`` does) and of ``colmap_pvs``'s readers and
  writers, the weights' load (``--teacher``, default the BlendedMVS weights), the plan's cameras and
  depth ranges (read from ``sources.json``, as IterMVS reads its cams and pair files), the reading of
  the references' and sources' images (each once), one forward per reference at IterMVS's own
  multiple-of-32 size with ``--threads`` torch threads, and its depth and its own confidence at the map
  size written per reference as COLMAP ``.bin`` files. No filtering, no geometric check, no fusion.
- IterMVS with its own filtering (``--filter``, side ``itermvs+filter``): the same, plus the maps of the
  auxiliary sources (each with the sources and depth range our view selection gives it), then
  ``eval.py``'s filtering and fusion as its ``eval_custom.sh`` runs it (:func:`itermvs_filter`): what
  IterMVS's own whole process does to make its cloud, and the closest to our command's work.

The table lists every run; the summary gives each side's medians and, per ``--ours``, the median over
the repeats of the paired ratio ours / IterMVS (the IterMVS run right after it). ``--json`` writes it
all. On a shared machine the numbers are noisy: read the load column.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tools"))

import real_depth  # noqa: E402  (the model builder and workspace helpers)
import teacher_labels as tl  # noqa: E402  (IterMVS with our cameras: Teacher)

#: The ``colmap-pvs stereo`` flags of our side, as ``--flag value`` pairs (besides ``--workspace_path``).
CLI_FLAGS = ("max_image_size", "num_views", "threads")
#: The 1-minute load average from which the summary says the machine was not quiet.
QUIET_LOAD = 0.5
#: ``eval_custom.sh``'s IterMVS filter: confidence above this, and this many sources agreeing.
ITERMVS_PHOTO_THRES = 0.3
ITERMVS_GEO_MASK_THRES = 3
#: Depth ranges are recorded to 9 significant digits in the provenance.
RANGE_RTOL = 1e-8


# --------------------------------------------------------------------------- the plan (pure logic)


def plan_views(fields: dict) -> dict[str, dict]:
    """``{"references": {name: {"sources", "depth_range"}}, "auxiliary": {...}, "views": {name: {"size", "K",
    "pose"}}}``: each reference's (and auxiliary source's) sources and depth range as our stereo step decides
    them for the
    :class:`~colmap_pvs.stereo.StereoConfig` ``fields`` (the flags of our run; its own
    :func:`~colmap_pvs.stereo.context.prepare_stereo`: ``patch-match.cfg``, view selection, depth
    ranges), and each reference's and source's map size ``[W, H]``, map intrinsics and
    ``cam_from_world`` ``[4, 4]``."""
    from colmap_pvs.config import config_from_dict
    from colmap_pvs.geometry import to_homogeneous
    from colmap_pvs.stereo import StereoConfig
    from colmap_pvs.stereo.context import prepare_stereo
    from colmap_pvs.stereo.local import auxiliary_references

    ctx = prepare_stereo(config_from_dict(StereoConfig, {**fields, "device": "cpu"}))
    try:
        planned: dict[str, dict] = {"references": {}, "auxiliary": {}}
        views = {}
        for kind, names in (("references", list(ctx.references)), ("auxiliary", auxiliary_references(ctx))):
            for name in names:
                sources, reason = ctx.sources_of(name)
                if sources is None:
                    raise SystemExit(f"{name}: our stereo step skips it ({reason})")
                dmin, dmax = ctx.selection.references[name].depth_range
                planned[kind][name] = {"sources": list(sources), "depth_range": [float(dmin), float(dmax)]}
                for n in [name, *sources]:
                    size = ctx.map_size(n)
                    views[n] = {"size": list(size), "K": ctx.map_K(n, size).tolist(),
                                "pose": to_homogeneous(ctx.sparse.image_by_name(n).cam_from_world).tolist()}
    finally:
        ctx.close()
    return {**planned, "views": views}


def recorded_views(ws: Path, refs) -> dict[str, dict]:
    """``{reference: {"sources", "depth_range"}}`` as our run's photometric provenance records them
    (``None`` for a reference without a readable record)."""
    from colmap_pvs.io.workspace import Workspace
    from colmap_pvs.stereo.reference import provenance_path

    out = {}
    for name in refs:
        try:
            rec = json.loads(provenance_path(Workspace(Path(ws)), name, "photometric").read_text())
            out[name] = {"sources": list(rec.get("sources", rec["settings"]["sources"])),
                         "depth_range": [float(v) for v in rec["settings"]["depth_range"]]}
        except (OSError, ValueError, KeyError, TypeError):
            out[name] = None
    return out


def plan_mismatches(plan: dict, ws: Path) -> list[str]:
    """The references whose sources or depth range in our run's provenance differ from ``plan``, in words."""
    found = []
    refs = plan["references"]
    for name, rec in recorded_views(ws, refs).items():
        want = refs[name]
        if rec is None:
            found.append(f"{name}: no photometric provenance")
        elif rec["sources"] != want["sources"]:
            found.append(f"{name}: sources {rec['sources']}, planned {want['sources']}")
        elif any(abs(a - b) > RANGE_RTOL * abs(b) for a, b in zip(rec["depth_range"], want["depth_range"],
                                                                     strict=True)):
            found.append(f"{name}: depth range {rec['depth_range']}, planned {want['depth_range']}")
    return found


def stereo_command(python: str, ws: Path, fields: dict) -> list[str]:
    """Our side's command line: the ``colmap-pvs`` script next to ``python`` (``python -m colmap_pvs.cli``
    without one) with ``stereo --workspace_path ws`` and the :data:`CLI_FLAGS` of ``fields``."""
    script = Path(python).parent / "colmap-pvs"
    head = [str(script)] if script.is_file() else [python, "-m", "colmap_pvs.cli"]
    flags = [item for key in CLI_FLAGS for item in (f"--{key}", str(fields[key]))]
    return [*head, "stereo", "--workspace_path", str(ws), *flags]


def parse_ours(items: list[str]) -> list[tuple[str, str]]:
    """``["LABEL=PYTHON", ...]`` as ``[(label, python)]`` (default: ``ours`` = this interpreter)."""
    if not items:
        return [("ours", sys.executable)]
    out = []
    for item in items:
        label, sep, python = item.partition("=")
        if not sep or not label or not python:
            raise SystemExit(f"--ours {item!r}: expected LABEL=PYTHON")
        if label == "itermvs" or label in dict(out):
            raise SystemExit(f"--ours {item!r}: the label {label!r} is taken")
        if not Path(python).is_file():
            raise SystemExit(f"--ours {item!r}: no python at {python}")
        out.append((label, python))
    return out


def summary(runs: list[dict], labels: list[str], peers: tuple[str, ...] = ("itermvs",)) -> list[str]:
    """Each side's medians and, per label and peer side, the median paired ratio ours / peer (same repeat)."""
    lines = ["", "| side | runs | median wall s | median CPU s | median peak RSS MB |",
             "|---|---|---|---|---|"]
    for side in [*labels, *peers]:
        mine = [r for r in runs if r["side"] == side]
        if mine:
            lines.append(f"| {side} | {len(mine)} | {statistics.median(r['wall_s'] for r in mine):.1f} | "
                         f"{statistics.median(r['cpu_s'] for r in mine):.1f} | "
                         f"{statistics.median(r['peak_rss_mb'] for r in mine):.0f} |")
    lines.append("")
    for side in peers:
        peer = {r["repeat"]: r for r in runs if r["side"] == side}
        for label in labels:
            pairs = [(r, peer[r["repeat"]]) for r in runs if r["side"] == label and r["repeat"] in peer]
            if not pairs:
                continue
            ratio = {k: statistics.median(a[k] / b[k] for a, b in pairs)
                     for k in ("wall_s", "cpu_s", "peak_rss_mb")}
            name = "IterMVS" if side == "itermvs" else side
            lines.append(f"{label} / {name}, median of {len(pairs)} paired ratio(s): "
                         f"wall {ratio['wall_s']:.2f}x, CPU {ratio['cpu_s']:.2f}x, "
                         f"peak RSS {ratio['peak_rss_mb']:.2f}x")
    return lines


# --------------------------------------------------------------------------- the IterMVS child


def itermvs_child(args: argparse.Namespace) -> int:
    """IterMVS's whole process on the plan ``args.plan``: depth and confidence per reference in
    ``args.out`` (with ``--filter`` also per auxiliary source, then :func:`itermvs_filter`'s cloud)."""
    import cv2
    import numpy as np
    import torch

    from colmap_pvs.io.maps import write_depth_map

    torch.set_num_threads(args.threads)
    teacher = tl.Teacher(args.teacher, args.itermvs)
    plan = json.loads(Path(args.plan).read_text())
    views = plan["views"]
    images = tl.ImageCache(Path(plan["workspace"]))

    def image(name: str) -> np.ndarray:  # at our map size (its file's own size on hololens-dev)
        pix = images.get(name)
        w, h = views[name]["size"]
        return pix if pix.shape[:2] == (h, w) else cv2.resize(pix, (w, h), interpolation=cv2.INTER_AREA)

    out = Path(args.out)
    forward = 0.0
    todo = {**plan["references"], **(plan["auxiliary"] if args.filter else {})}
    maps = {}
    for name, ref in todo.items():
        names = [name, *ref["sources"]]
        pixels = [image(n) for n in names]
        start = time.perf_counter()
        depth, conf = teacher.run(pixels, [np.asarray(views[n]["K"]) for n in names],
                                  [np.asarray(views[n]["pose"]) for n in names], *ref["depth_range"])
        forward += time.perf_counter() - start
        write_depth_map(out / "depth_maps" / f"{name}.itermvs.bin", depth)
        write_depth_map(out / "confidence_maps" / f"{name}.itermvs.bin", conf)
        maps[name] = (depth, conf)
    print(f"itermvs: {len(todo)} maps, forward {forward:.1f} s in all", flush=True)
    if args.filter:
        itermvs_filter(args.itermvs, plan, maps, image, out / "fused.ply")
    return 0


def itermvs_filter(clone: Path, plan: dict, maps: dict, image, path: Path) -> None:
    """IterMVS's own filtering and fusion of ``maps`` (``name -> (depth, confidence)``), as its ``eval.py``
    does for a custom scene (``eval_custom.sh``'s thresholds): per reference, its confidence above 0.3 and
    3 of its sources agreeing by its ``check_geometric_consistency`` (1 px, 1 % depth), the agreeing depths
    averaged, every kept pixel a world point; the cloud written to ``path`` (our PLY writer: faster than
    ``eval.py``'s, so IterMVS's side is if anything short). Its two functions are read from the clone's
    ``eval.py`` (which parses arguments and needs ``plyfile`` when imported)."""
    import ast

    import cv2
    import numpy as np

    from colmap_pvs.io.ply import write_point_cloud

    source = (clone / "eval.py").read_text()
    wanted = {"reproject_with_depth", "check_geometric_consistency"}
    body = [node for node in ast.parse(source).body
            if isinstance(node, ast.FunctionDef) and node.name in wanted]
    functions = {"np": np, "cv2": cv2}
    exec(compile(ast.Module(body, type_ignores=[]), str(clone / "eval.py"), "exec"), functions)  # noqa: S102
    check = functions["check_geometric_consistency"]
    views = plan["views"]
    points, colours = [], []
    for name, ref in plan["references"].items():
        depth, conf = maps[name]
        K, pose = np.asarray(views[name]["K"]), np.asarray(views[name]["pose"])
        agree = np.zeros(depth.shape, np.int32)
        reprojected = []
        for src in ref["sources"]:
            if src not in maps:
                continue
            mask, depth_src, _, _ = check(depth, K, pose, maps[src][0], np.asarray(views[src]["K"]),
                                          np.asarray(views[src]["pose"]), 1.0, 0.01)
            agree += mask.astype(np.int32)
            reprojected.append(depth_src)
        averaged = (sum(reprojected) + depth) / (agree + 1)
        keep = (conf > ITERMVS_PHOTO_THRES) & (agree >= ITERMVS_GEO_MASK_THRES)
        rows, cols = np.nonzero(keep)
        cam = np.linalg.inv(K) @ (np.stack([cols, rows, np.ones_like(cols)]) * averaged[keep])
        points.append((np.linalg.inv(pose) @ np.vstack([cam, np.ones_like(cols)]))[:3].T)
        colours.append(image(name)[keep])  # uint8 RGB (colmap_pvs.io.images.load_image)
    write_point_cloud(path, np.concatenate(points), colors=np.concatenate(colours))
    print(f"itermvs: filtered and fused {sum(len(c) for c in points)} points into {path}", flush=True)


# --------------------------------------------------------------------------- timing


def timed(cmd: list[str], log: Path, cwd: Path) -> dict:
    """Run ``cmd`` as one child (output to ``log``); its wall, CPU (user + sys) and peak RSS, the load
    average before it and its exit status."""
    load = os.getloadavg()
    with log.open("w") as f:
        start = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=cwd)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait again
    return {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_mb": usage.ru_maxrss / 1024,
            "load_before": list(load), "returncode": proc.returncode}


def failed(run: dict, log: Path) -> bool:
    if run["returncode"] == 0:
        return False
    tail = log.read_text(errors="replace").strip().splitlines()[-5:]
    print(f"{run['side']} failed (exit {run['returncode']}), the end of {log}:", *tail, sep="\n  ",
          file=sys.stderr)
    return True


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--itermvs", type=Path,
                   help="clone of github.com/FangjinhuaWang/IterMVS with its checkpoints/")
    p.add_argument("--teacher", default="itermvs_blended",
                   choices=sorted(k for k, v in tl.TEACHER_KINDS.items() if v.repo == "itermvs"),
                   help="IterMVS weights (tools/teacher_labels.py's TEACHER_KINDS)")
    p.add_argument("--ours", nargs="+", action="extend", default=[], metavar="LABEL=PYTHON",
                   help="our side(s): a label and the python of a venv with colmap-pvs "
                        "(default: ours=this one)")
    p.add_argument("--repeats", type=int, default=3, help="alternations of every side")
    p.add_argument("--data", type=Path, default=real_depth.DEFAULT_DATA)
    p.add_argument("--work_dir", type=Path, default=real_depth.DEFAULT_WORK)
    p.add_argument("--first", type=int, default=60, help="index of the first reference frame")
    p.add_argument("--count", type=int, default=10, help="consecutive reference frames")
    p.add_argument("--max_image_size", type=int, default=540)
    p.add_argument("--num_views", type=int, default=5)
    p.add_argument("--threads", type=int, default=2, help="torch threads of both sides")
    p.add_argument("--filter", action="store_true",
                   help="also IterMVS with its own filtering and fusion (itermvs+filter): the maps of the "
                        "auxiliary sources too, then eval.py's geometric check, and a cloud")
    p.add_argument("--json", type=Path, default=None, help="also write the plan and every run here")
    p.add_argument("--child", choices=["itermvs"], help=argparse.SUPPRESS)
    p.add_argument("--plan", help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        return itermvs_child(args)
    if args.repeats < 1:
        p.error(f"--repeats must be at least 1, got {args.repeats}")
    if args.itermvs is None or not (args.itermvs / tl.TEACHER_KINDS[args.teacher].weights).is_file():
        weights = tl.TEACHER_KINDS[args.teacher].weights
        p.error(f"--itermvs: no clone of IterMVS with {weights} at {args.itermvs}")
    ours = parse_ours(args.ours)
    if not (args.data / "poses.txt").is_file():
        print(f"hololens-dev data not found at {args.data}", file=sys.stderr)
        return 2

    work = args.work_dir.resolve()
    sparse, refs = real_depth.consecutive_references(args.data, work, args.threads, args.first, args.count)
    base = work / "ws" / "peer_speed"

    def fresh(ws: Path) -> Path:  # images/ and sparse/ linked, stereo/ holding only patch-match.cfg
        return real_depth.auto_sources_workspace(ws, args.data / "images", sparse, refs, args.num_views)

    fields = {"workspace_path": str(fresh(base / "plan")), "max_image_size": args.max_image_size,
              "num_views": args.num_views, "threads": args.threads}
    plan = {"workspace": str(base / "plan"), **plan_views(fields)}
    (base / "sources.json").write_text(json.dumps(plan, indent=1) + "\n")
    print(f"{len(refs)} references {refs[0]} .. {refs[-1]}, {args.max_image_size} px, "
          f"N={args.num_views}, {args.threads} threads; sources and depth ranges (our view selection) "
          f"in {base / 'sources.json'}:")
    for name, ref in plan["references"].items():
        lo, hi = ref["depth_range"]
        print(f"  {name}: {' '.join(ref['sources'])}  [{lo:.3f}, {hi:.3f}] m")
    print("ours: " + " ".join(stereo_command(ours[0][1], Path("W"), fields)))
    print(f"itermvs: {sys.executable} {Path(__file__).name} --child itermvs ({args.teacher}, "
          f"{tl.clone_provenance(args.itermvs)['commit'][:7]})", flush=True)

    runs: list[dict] = []
    print("", "| # | side | wall s | CPU s | peak RSS MB | load before (1 min) |",
          "|---|---|---|---|---|---|", sep="\n", flush=True)
    for repeat in range(args.repeats):
        peers = [("itermvs", sys.executable)] + ([("itermvs+filter", sys.executable)] if args.filter else [])
        for label, python in [*ours, *peers]:
            run_dir = base / label
            if run_dir.exists():
                shutil.rmtree(run_dir)
            run_dir.mkdir(parents=True)
            log = base / f"{label}.log"
            if label.startswith("itermvs"):
                cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "itermvs",
                       "--plan", str(base / "sources.json"), "--out", str(run_dir),
                       "--itermvs", str(args.itermvs.resolve()), "--teacher", args.teacher,
                       "--threads", str(args.threads), *(["--filter"] if label == "itermvs+filter" else [])]
            else:
                ws = fresh(run_dir / "ws")
                cmd = stereo_command(python, ws, {**fields, "workspace_path": str(ws)})
            run = {"repeat": repeat, "side": label, **timed(cmd, log, run_dir)}
            runs.append(run)
            if failed(run, log):
                return 1
            if not label.startswith("itermvs"):
                for line in plan_mismatches(plan, run_dir / "ws"):
                    print(f"WARNING {label}: {line}", file=sys.stderr)
            row = (f"| {len(runs)} | {label} | {run['wall_s']:.1f} | {run['cpu_s']:.1f} | "
                   f"{run['peak_rss_mb']:.0f} | {run['load_before'][0]:.2f} |")
            print(row, flush=True)
    lines = summary(runs, [label for label, _ in ours], tuple(label for label, _ in peers))
    busiest = max(r["load_before"][0] for r in runs)
    if busiest >= QUIET_LOAD:
        lines.append(f"not a quiet machine: a 1-minute load average of {busiest:.2f} before a run "
                     f"({os.cpu_count()} cores): every time above is an upper bound, and the ratio is "
                     "unreliable (torch threads that wait for a busy core slow each side differently)")
    print("\n".join(lines))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"plan": plan, "ours": dict(ours), "runs": runs,
                                         "commit": real_depth.git_commit()}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
