"""How the pipeline scales with the number of views: ``stereo``, ``fuse`` and COLMAP's ``stereo_fusion``
on a synthetic street of up to 1,000 views (and more), time and peak memory per view count.

    python benchmarks/scale.py                                  # 100, 300, 1000 views, every step
    python benchmarks/scale.py --views 100 300 --steps select fuse colmap
    python benchmarks/scale.py --views 100 300 1000 --record    # append the table to benchmarks/RESULTS.md
    OLD_VENV/bin/python benchmarks/scale.py --steps fuse --label=-before   # that venv's colmap-pvs beside

The scene (:func:`_street`): a 2.5 m high facade with recesses and protruding boxes along a
straight street, a pavement in front, pillars between the facade and the path; the cameras walk
along the street at 1.6 m, looking at the facade (yaw, pitch and height jittered), ``--step`` m
apart: each view overlaps only its ~20 neighbours, like a video or a street capture, so the work per
view should not grow with the scene. Rendered once at ``--width x --height`` for the largest count
with simulated sparse points and tracks (:func:`colmap_pvs.synthetic.sfm.simulate_sparse_points`),
cached in ``OUT/scene`` (``--out``, default ``outputs/benchmarks/scale``). The workspace of ``N``
views (``OUT/views-N``) holds the first ``N`` cameras, the points they see at least twice and a
link to the shared images; its maps and clouds are cached there too: a rerun only runs what is
missing (``--force STEP`` reruns a step).

Steps (``--steps``), each in its own subprocess (peak RSS = ``ru_maxrss`` of that child, wall time of
the whole command: Python start-up and imports included):

- ``select``: :func:`colmap_pvs.views.select_views` alone (what ``stereo`` and ``fuse`` run first).
- ``stereo``: ``colmap-pvs stereo --max_image_size S --threads T`` (every default pass).
- ``fuse``: ``colmap-pvs fuse`` (``pvs``, the default input: the completion) and ``fuse_geometric``:
  ``colmap-pvs fuse --input_type geometric`` (the maps COLMAP fuses).
- ``colmap``: ``/usr/bin/colmap stereo_fusion --input_type geometric`` on the same maps, COLMAP's
  defaults.

The table (every record under ``OUT``; ``--steps`` with nothing new to run just prints it) gives per
step the wall time, seconds per view, CPU seconds (user + system; above the wall time: both cores
busy), peak RSS and the machine's load average when it finished, and extrapolates to 10,000
views "on paper" from the two largest measured counts (time and memory linear in the views between
them: ``a + b N``); the extrapolation is a trend, not a measurement.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
STEPS = ("select", "stereo", "fuse", "fuse_geometric", "colmap")
COLMAP = "/usr/bin/colmap"


# --------------------------------------------------------------------------- the scene


def _street(num_views: int, step: float, seed: int):
    """The scene (a :class:`colmap_pvs.synthetic.scene_types.Scene`) and the cameras' ``[V, 3, 4]``
    poses: a facade along +x at ``y = 3``, the cameras at ``y = 0`` looking at it."""
    from colmap_pvs.synthetic.cameras import look_at
    from colmap_pvs.synthetic.scene_types import ViewSpace
    from colmap_pvs.synthetic.scenes import scene_from_primitives

    rng = np.random.default_rng(seed)
    length = num_views * step + 8.0
    x0 = -4.0

    def build(mesh, material):
        pool = [material(scale=0.12) for _ in range(24)]
        pick = lambda: pool[int(rng.integers(len(pool)))]  # noqa: E731
        # The facade in bays of 2-4 m, each at its own depth (recesses), with a textured pavement.
        x = x0
        while x < x0 + length:
            w = float(rng.uniform(2.0, 4.0))
            depth = float(rng.uniform(-0.3, 0.3))
            mesh.add_quad([x, 3.0 + depth, 0.0], [w, 0.0, 0.0], [0.0, 0.0, 3.0], pick())
            if rng.random() < 0.7:  # a box (balcony, shop window) sticking out of the bay
                bw, bh = float(rng.uniform(0.4, 1.2)), float(rng.uniform(0.3, 1.0))
                bd = float(rng.uniform(0.15, 0.5))
                mesh.add_box([x + w / 2, 3.0 + depth - bd / 2, float(rng.uniform(0.5, 2.0))],
                             [bw, bd, bh], 0.0, pick())
            x += w
        mesh.add_quad([x0, -1.0, 0.0], [0.0, 4.5, 0.0], [length, 0.0, 0.0], pick())
        # Pillars between the path and the facade: occlusions that move with the camera.
        for px in np.arange(x0 + 1.0, x0 + length, 3.7):
            mesh.add_box([px, 2.0, 1.25], [0.15, 0.15, 2.5], 0.0, pick())

    view_space = ViewSpace(90.0, 10.0, (-5.0, 5.0), (2.0, 4.0), np.array([[-1e4] * 3, [1e4] * 3]), 0.0)
    scene = scene_from_primitives(build, seed=seed, roi_center=(length / 2, 3.0, 1.2), roi_radius=length,
                                  view_space=view_space, nominal_distance=3.0)
    poses = []
    for v in range(num_views):
        eye = np.array([v * step, 0.0, 1.6 + rng.uniform(-0.1, 0.1)])
        yaw = np.radians(rng.uniform(-12.0, 12.0))
        target = eye + np.array([np.sin(yaw), np.cos(yaw), rng.uniform(-0.12, 0.05)])
        poses.append(look_at(eye, target))
    return scene, np.stack(poses)


def build_scene(out: Path, num_views: int, width: int, height: int, step: float, seed: int,
                points_per_view: int) -> dict:
    """Render the street into ``out/scene`` (images, ``cameras.npz``), unless it is there already."""
    scene_dir = out / "scene"
    meta_path = scene_dir / "scene.json"
    want = dict(num_views=num_views, width=width, height=height, step=step, seed=seed,
                points_per_view=points_per_view)
    if meta_path.is_file():  # a scene of more views serves too: the workspaces take its first views
        meta = json.loads(meta_path.read_text())
        same = all(meta.get(k) == v for k, v in want.items() if k != "num_views")
        if same and meta["num_views"] >= num_views:
            return meta
        sys.exit(f"{scene_dir} holds another scene ({meta}); remove it or pass another --out")
    from colmap_pvs.synthetic.cameras import CameraRig, intrinsics
    from colmap_pvs.synthetic.render import RenderConfig, Renderer, apply_photometric
    from colmap_pvs.synthetic.sfm import simulate_sparse_points

    t0 = time.perf_counter()
    scene, poses = _street(num_views, step, seed)
    renderer = Renderer(scene)
    K = np.broadcast_to(intrinsics(width, height, 60.0), (num_views, 3, 3)).copy()
    rig = CameraRig(K=K, cam_from_world=poses, roles=("regular",) * num_views, width=width, height=height)
    tmp = out / "scene.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "images").mkdir(parents=True)
    images = np.zeros((num_views, height, width, 3), np.uint8)
    depths = np.zeros((num_views, height, width), np.float32)
    normals = np.zeros((num_views, height, width, 3), np.float32)
    cfg = RenderConfig()
    import cv2

    for v in range(num_views):
        view = renderer.render(K[v], poses[v], height, width, 1, cfg.shadows)
        images[v] = apply_photometric(view.image, np.random.default_rng([seed, 2, v]), cfg)
        depths[v], normals[v] = view.depth, view.normals
        cv2.imwrite(str(tmp / "images" / f"{v:05d}.png"), images[v][..., ::-1])
    points = simulate_sparse_points(renderer, rig, images, depths, normals, np.random.default_rng([seed, 3]),
                                    points_per_view * num_views)
    np.savez(tmp / "cameras.npz", K=K, cam_from_world=poses, xyz=points.xyz, rgb=points.rgb,
             visibility=np.packbits(points.visibility, axis=1))
    meta = {**want, "num_points": points_per_view * num_views, "points": int(len(points.xyz)),
            "seconds": round(time.perf_counter() - t0, 1)}
    (tmp / "scene.json").write_text(json.dumps(meta, indent=1) + "\n")
    os.replace(tmp, scene_dir)
    return meta


def build_workspace(out: Path, n: int) -> Path:
    """``out/views-N``: the first ``n`` cameras of the scene as a COLMAP dense workspace."""
    from colmap_pvs.io.sparse import write_sparse_model
    from colmap_pvs.io.workspace import write_fusion_cfg
    from colmap_pvs.synthetic.sfm import build_sparse_model

    ws = out / f"views-{n}"
    if (ws / "sparse" / "images.bin").is_file():
        return ws
    meta = json.loads((out / "scene" / "scene.json").read_text())
    if n > meta["num_views"]:
        sys.exit(f"the scene has {meta['num_views']} views, fewer than {n}: pass a larger --scene_views")
    with np.load(out / "scene" / "cameras.npz") as z:
        vis = np.unpackbits(z["visibility"], axis=1, count=meta["num_views"]).astype(bool)[:, :n]
        keep = vis.sum(axis=1) >= 2
        names = [f"{v:05d}.png" for v in range(n)]
        model = build_sparse_model(z["K"][:n], z["cam_from_world"][:n], meta["width"], meta["height"], names,
                                   z["xyz"][keep], z["rgb"][keep], vis[keep])
    (ws / "stereo").mkdir(parents=True, exist_ok=True)
    images = ws / "images"
    if not images.exists():
        images.symlink_to(Path("..") / "scene" / "images", target_is_directory=True)
    (ws / "stereo" / "patch-match.cfg").write_text("".join(f"{m}\n__auto__, 20\n" for m in names))
    write_fusion_cfg(ws / "stereo" / "fusion.cfg", names)
    write_sparse_model(model, ws / "sparse")
    return ws


# --------------------------------------------------------------------------- measuring a step


# The child's peak RSS must not include this (large) process: Linux keeps ``ru_maxrss`` across exec, so a
# child forked from here would start at our size. A small Python in between forks the command.
_WAIT = ("import json, os, subprocess, sys, time; t = time.perf_counter(); "
         "p = subprocess.Popen(sys.argv[1:]); _, s, u = os.wait4(p.pid, 0); "
         "print(json.dumps({'rc': os.waitstatus_to_exitcode(s), "
         "'peak_rss_mb': round(u.ru_maxrss / 1024, 1), 'cpu_seconds': round(u.ru_utime + u.ru_stime, 1), "
         "'seconds': round(time.perf_counter() - t, 2)}), file=sys.stderr)")


def run_measured(cmd: list[str], log: Path, env: dict | None = None) -> dict:
    """Run ``cmd`` as a child of a small Python; its wall time, peak RSS (MB, ``ru_maxrss``), CPU seconds
    and exit status."""
    with open(log, "w") as f:
        proc = subprocess.run([sys.executable, "-c", _WAIT, *cmd], stdout=f, stderr=subprocess.PIPE, cwd=REPO,
                              env=env, text=True)
    f_err = proc.stderr.strip().splitlines()
    with open(log, "a") as f:
        f.write("\n".join(f_err[:-1]) + "\n")
    if proc.returncode != 0 or not f_err:
        return {"rc": proc.returncode or 1, "seconds": 0.0, "peak_rss_mb": 0.0, "cpu_seconds": 0.0}
    return json.loads(f_err[-1])


def _cli() -> list[str]:
    return [str(Path(sys.executable).parent / "colmap-pvs")]


def step_command(step: str, ws: Path, args) -> list[str]:
    if step == "select":
        code = ("import sys; from colmap_pvs.io.workspace import load_workspace; "
                "from colmap_pvs.views import select_views, ViewSelectionConfig; "
                "ws, model = load_workspace(sys.argv[1]); import time; t = time.perf_counter(); "
                "s = select_views(model, ViewSelectionConfig()); "
                "print('select_views', round(time.perf_counter() - t, 2), 's', len(s.references), "
                "'references')")
        return [sys.executable, "-c", code, str(ws)]
    if step == "stereo":
        return [*_cli(), "stereo", "--workspace_path", str(ws), "--max_image_size", str(args.max_image_size),
                "--threads", str(args.threads)]
    if step == "fuse":
        return [*_cli(), "fuse", "--workspace_path", str(ws),
                "--output_path", str(ws / f"fused-pvs{args.label}.ply")]
    if step == "fuse_geometric":
        return [*_cli(), "fuse", "--workspace_path", str(ws), "--input_type", "geometric",
                "--output_path", str(ws / f"fused-pvs-geometric{args.label}.ply")]
    if step == "colmap":
        return [COLMAP, "stereo_fusion", "--workspace_path", str(ws), "--input_type", "geometric",
                "--output_path", str(ws / f"fused-colmap{args.label}.ply")]
    raise ValueError(step)


def _points(ply: Path) -> int | None:
    import re

    if not ply.is_file():
        return None
    m = re.search(rb"element vertex (\d+)", ply.read_bytes()[:512])
    return int(m.group(1)) if m else None


OUTPUT_OF = {"fuse": "fused-pvs", "fuse_geometric": "fused-pvs-geometric", "colmap": "fused-colmap"}


def run_step(step: str, ws: Path, n: int, args) -> dict:
    record = ws / f"{step}{args.label}.json"
    if record.is_file() and step not in args.force:
        return json.loads(record.read_text())
    maps = ws / "stereo" / "depth_maps"
    if step in ("fuse", "fuse_geometric", "colmap") and not list(maps.glob("*.geometric.bin")):
        sys.exit(f"{ws} has no maps: run the stereo step first")
    result = run_measured(step_command(step, ws, args), ws / f"{step}{args.label}.log")
    if result["rc"] != 0:
        sys.exit(f"{step} on {n} views failed (rc {result['rc']}); see {ws / (step + '.log')}")
    now = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    result.update(views=n, step=step, date=now, load=os.getloadavg()[0])
    if step in OUTPUT_OF:
        result["points"] = _points(ws / f"{OUTPUT_OF[step]}{args.label}.ply")
    record.write_text(json.dumps(result, indent=1) + "\n")
    print(f"{step + args.label:15s} {n:6d} views: {result['seconds']:8.1f} s  "
          f"{result['peak_rss_mb']:7.0f} MB  (load {result['load']:.1f})", flush=True)
    return result


# --------------------------------------------------------------------------- the table


def extrapolate(rows: list[dict], key: str, target: int) -> float | None:
    """``a + b * target`` through the two largest view counts measured."""
    pts = sorted((r["views"], r[key]) for r in rows)
    if len(pts) < 2:
        return None
    (n1, y1), (n2, y2) = pts[-2], pts[-1]
    b = (y2 - y1) / (n2 - n1)
    return y2 + b * (target - n2)


def table(out: Path, target: int) -> str:
    """Every step record under ``out`` (``views-N/STEP[LABEL].json``), by step, label and view count."""
    rows: dict[str, list[dict]] = {}
    for record in sorted(out.glob("views-*/*.json")):
        r = json.loads(record.read_text())
        if "step" in r:
            rows.setdefault(record.stem, []).append(r)
    order = sorted(rows, key=lambda k: (next(i for i, s in enumerate(STEPS) if k.startswith(s)), k))
    lines = ["| step | views | wall (s) | s/view | CPU (s) | peak RSS (MB) | points | load |",
             "|---|---|---|---|---|---|---|---|"]
    for key in order:
        measured = sorted(rows[key], key=lambda r: r["views"])
        for r in measured:
            pts = "" if r.get("points") is None else r["points"]
            lines.append(f"| {key} | {r['views']} | {r['seconds']:.1f} | {r['seconds'] / r['views']:.3f} | "
                         f"{r['cpu_seconds']:.0f} | {r['peak_rss_mb']:.0f} | {pts} | {r['load']:.0f} |")
        t, m = extrapolate(measured, "seconds", target), extrapolate(measured, "peak_rss_mb", target)
        if t is not None:
            lines.append(f"| {key} | *{target} (on paper)* | *{t:.0f}* | *{t / target:.3f}* | | *{m:.0f}* "
                         "| | |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=REPO / "outputs" / "benchmarks" / "scale")
    p.add_argument("--views", type=int, nargs="+", default=[100, 300, 1000])
    p.add_argument("--scene_views", type=int, default=None, help="views rendered (default: max of --views)")
    p.add_argument("--steps", nargs="+", choices=STEPS, default=list(STEPS))
    p.add_argument("--force", nargs="*", choices=STEPS, default=[], help="rerun these steps")
    p.add_argument("--width", type=int, default=192)
    p.add_argument("--height", type=int, default=144)
    p.add_argument("--step", type=float, default=0.25, help="metres between consecutive cameras")
    p.add_argument("--points_per_view", type=int, default=60, help="sparse points sampled per view")
    p.add_argument("--max_image_size", type=int, default=192)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--extrapolate", type=int, default=10000)
    p.add_argument("--label", default="", help="suffix of the step records and clouds (e.g. -before: "
                   "another code version on PYTHONPATH measured beside this one)")
    p.add_argument("--record", action="store_true", help="append the table to benchmarks/RESULTS.md")
    args = p.parse_args()
    if any(s == "colmap" for s in args.steps) and not Path(COLMAP).is_file():
        sys.exit(f"{COLMAP} not found: drop the colmap step")
    scene_views = args.scene_views or max(args.views)
    meta = build_scene(args.out, scene_views, args.width, args.height, args.step, args.seed,
                       args.points_per_view)
    print(f"scene: {meta}", flush=True)
    for n in sorted(args.views):
        ws = build_workspace(args.out, n)
        for step in STEPS:
            if step in args.steps:
                run_step(step, ws, n, args)
    text = table(args.out, args.extrapolate)
    print(text)
    if args.record:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True,
                                text=True).stdout.strip()
        with open(REPO / "benchmarks" / "RESULTS.md", "a") as f:
            f.write(f"\n`benchmarks/scale.py` at {commit}, {datetime.date.today()}:\n\n{text}\n")


if __name__ == "__main__":
    main()
