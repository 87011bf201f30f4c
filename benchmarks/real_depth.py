"""Depth accuracy on real video with GT depth (``../shared/data/hololens-dev``): PVSNet with N views,
with disturbing views, without visibility (mean aggregation), and a sparse-interpolation baseline.

    python benchmarks/real_depth.py --checkpoint colmap_pvs/weights/pvsnet_default.pt

Steps (everything is cached or rebuilt under ``--work_dir``):

1. A COLMAP model from the known poses (``colmap_pvs.io.import_poses``: SIFT + matching +
   triangulation with the poses fixed), cached in ``WORK/model/sparse``.
2. Reference frames: every ``--stride``-th frame. One dense workspace per setting
   (``WORK/ws/SETTING``: ``images`` and ``sparse`` are links, ``stereo/`` is the setting's own), each
   with an explicit ``stereo/patch-match.cfg``:
   - ``N=k``: the ``k-1`` best-scored sources (MVSNet view score of ``colmap_pvs.views``);
   - ``disturbed``: N=``--disturb_n`` where ``--disturb_count`` of the best sources are replaced
     by unrelated frames far away in the sequence (index distance >= 1/3 of the sequence, lowest
     view score first; on video they see other parts of the room);
   - ``sparse guidance off`` / ``sparse prior off``: N=``--disturb_n`` with that parameter-free
     switch of the checkpoint turned off (only when the checkpoint has it on), and with both off
     (``no sparse input``) when it has both on;
   - ``mean-agg`` (ablation): the same sources as ``N=--disturb_n`` (and as ``disturbed``) with
     pixelwise visibility off: the same checkpoint with ``PVSNetConfig.visibility`` flipped
     (written to ``WORK/checkpoints``), or ``--ablation_checkpoint`` (a separately trained one).
3. ``run_stereo`` for every setting, each in its own subprocess (peak RSS per setting).
4. Baselines: linear interpolation of the depths of the reference's own sparse points over
   their Delaunay triangulation in the image (``cv2.Subdiv2D``; no prediction outside the hull),
   and the push-pull fill of the same points over the whole image (the network's sparse prior).
   Every setting is also scored on the Delaunay baseline's pixels (``AbsRel (hull)``,
   ``% <5% (hull)``), the fair comparison with it.
5. ``colmap_pvs.evaluate.evaluate_depth`` against the GT (uint16 millimetres, ``gt_scale=0.001``),
   at the prediction's resolution (GT resized with nearest). Prints ONE table and appends it to
   ``benchmarks/RESULTS.md`` with the git commit, the date and the checkpoint's sha256
   (``--no_record``: print only).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import logging
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "hololens-dev"
DEFAULT_WORK = ROOT / "outputs" / "benchmarks" / "hololens"
RESULTS = ROOT / "benchmarks" / "RESULTS.md"
DEFAULT_CHECKPOINT = ROOT / "colmap_pvs" / "weights" / "pvsnet_default.pt"

logger = logging.getLogger("real_depth")


# --------------------------------------------------------------------------- helpers


def _link(target: Path, link: Path) -> None:
    if link.is_symlink() or link.exists():
        if link.is_symlink() and link.resolve() == target.resolve():
            return
        if link.is_symlink() or link.is_file():
            link.unlink()
        else:
            shutil.rmtree(link)
    link.parent.mkdir(parents=True, exist_ok=True)
    try:
        link.symlink_to(target.resolve(), target_is_directory=target.is_dir())
    except OSError:  # no symlinks (some file systems): copy
        shutil.copytree(target, link)


def git_commit() -> str:
    def run(*cmd: str) -> str:
        try:
            return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=20).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""

    commit = run("git", "rev-parse", "--short", "HEAD") or "no-commit"
    dirty = bool(run("git", "status", "--porcelain", "--untracked-files=no"))
    return commit + ("-dirty" if dirty else "")


def quick_model(args: argparse.Namespace) -> tuple[Path, Path] | None:
    """``(work, sparse)`` of a quick benchmark (``args.data``, ``args.work_dir``, ``args.threads``): the
    work folder and the cached COLMAP model, or ``None`` (after saying so) without the hololens-dev data."""
    if not (args.data / "poses.txt").is_file():
        print(f"hololens-dev data not found at {args.data}; nothing to do")
        return None
    work = args.work_dir.resolve()
    work.mkdir(parents=True, exist_ok=True)
    return work, build_model(args.data, work, args.threads)


def quick_sources(names: list[str], selection, args: argparse.Namespace) -> dict[str, list[str]]:
    """The evaluated references of ``names`` (every ``args.stride``-th from ``args.offset``, if the
    :class:`~colmap_pvs.views.ViewSelection` ``selection`` made them references) and the first
    ``args.num_views - 1`` of each one's ranked sources (the view selection's own choice)."""
    refs = [n for n in frame_names(names, args) if n in selection.references]
    return top_sources(selection, refs, args.num_views)


def frame_names(names: list[str], args: argparse.Namespace) -> list[str]:
    """The frames of ``names`` a quick benchmark evaluates: every ``args.stride``-th from ``args.offset``,
    and of those only the ``args.frames`` when given (``--frames``)."""
    picked = sorted(names)[args.offset :: args.stride]
    frames = getattr(args, "frames", None)
    return [n for n in picked if n in set(frames)] if frames else picked


def top_sources(selection, refs, num_views: int) -> dict[str, list[str]]:
    """Each of ``refs`` with the first ``num_views - 1`` of its ranked sources in ``selection``."""
    return {r: list(selection.references[r].ranked_names)[: num_views - 1] for r in refs}


def build_model(data: Path, work: Path, threads: int) -> Path:
    """The cached COLMAP model of the sequence built from its known poses."""
    import pycolmap

    from colmap_pvs.errors import ConfigError
    from colmap_pvs.io.import_poses import ImportPosesConfig, import_poses

    pycolmap.logging.minloglevel = 2  # COLMAP's INFO lines would bury the table (errors still show)
    start = time.perf_counter()
    config = ImportPosesConfig(
        image_path=data / "images",
        poses_path=data,
        output_path=work / "model",
        format="hololens",
        num_threads=threads if threads > 0 else -1,
    )
    try:
        model_dir = import_poses(config)
    except ConfigError as exc:  # the cached model was made with other settings: it is only a cache
        print(f"[model] rebuilding: {exc}", flush=True)
        model_dir = import_poses(replace(config, overwrite=True))
    print(f"[model] {model_dir} ready in {time.perf_counter() - start:.0f} s", flush=True)
    return model_dir


def consecutive_references(data: Path, work: Path, threads: int, first: int,
                           count: int) -> tuple[Path, list[str]]:
    """The cached model of :func:`build_model` and ``count`` consecutive image names from index ``first``
    (the frames of ``profile_stereo.py`` and ``peer_speed.py``)."""
    from colmap_pvs.io.sparse import read_sparse_model

    sparse = build_model(data, work, threads)
    names = sorted(read_sparse_model(sparse).image_ids_by_name)
    return sparse, names[first : first + count]


def auto_sources_workspace(ws: Path, images: Path, sparse: Path, refs: list[str], num_views: int) -> Path:
    """A fresh workspace (:func:`make_workspace`) whose ``stereo/`` holds only a ``patch-match.cfg`` listing
    ``refs``, each with ``__auto__, num_views - 1`` sources (the stereo step's view selection picks them)."""
    make_workspace(ws, images, sparse)
    (ws / "stereo" / "patch-match.cfg").write_text("".join(f"{r}\n__auto__, {num_views - 1}\n" for r in refs))
    return ws


def add_frame_args(p: argparse.ArgumentParser, stride: int) -> None:
    """The data, work folder, frames (``--stride``, ``--offset``, ``--frames``), ``--num_views`` and
    ``--threads`` arguments that :func:`quick_model` and :func:`quick_sources` read."""
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--work_dir", type=Path, default=DEFAULT_WORK)
    p.add_argument("--stride", type=int, default=stride)
    p.add_argument("--offset", type=int, default=0)
    p.add_argument("--num_views", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--frames", nargs="*", default=[], metavar="NAME",
                   help="only these of the --stride/--offset frames (a subset while developing)")


def add_quick_args(p: argparse.ArgumentParser, tag: str, tag_help: str, stride: int) -> None:
    """The arguments of a ``WORK/quick/TAG_clean`` workspace (``hololens_quick.py`` and
    ``cloud_benchmark.py``): checkpoint, :func:`add_frame_args`, map size, resume and stereo overrides."""
    p.add_argument("--checkpoint", type=Path, default=DEFAULT_CHECKPOINT)
    p.add_argument("--tag", default=tag, help=tag_help)
    add_frame_args(p, stride)
    p.add_argument("--max_image_size", type=int, default=540)
    p.add_argument("--resume", action="store_true", help="keep the tag's maps (the stereo step's resume)")
    p.add_argument("--stereo", nargs="*", default=[], metavar="KEY=VALUE", help="more StereoConfig fields")


def parse_overrides(items: list[str]) -> dict:
    """``["key=value", ...]`` from a ``--stereo`` / ``--views`` flag as a dict; values parsed as JSON
    where they are (``true``, ``0.8``, ``[8, 16]``), else kept as strings."""
    out = {}
    for item in items:
        key, _, text = item.partition("=")
        try:
            out[key] = json.loads(text)
        except ValueError:
            out[key] = text
    return out


def stereo_config(ws: Path, args: argparse.Namespace, extra: dict):
    """The ``StereoConfig`` of a benchmark run on the CPU in ``ws`` from its ``args`` (``num_views``,
    ``max_image_size``, ``checkpoint``, ``threads``, ``resume``) and ``extra`` fields."""
    from colmap_pvs.config import config_from_dict
    from colmap_pvs.stereo import StereoConfig

    fields = {
        "workspace_path": str(ws),
        "num_views": args.num_views,
        "max_image_size": args.max_image_size,
        "checkpoint": str(args.checkpoint.resolve()),
        "threads": args.threads,
        "overwrite": not args.resume,
        "device": "cpu",
        **extra,
    }
    return config_from_dict(StereoConfig, fields)


def make_workspace(root: Path, images: Path, sparse: Path, keep_stereo: bool = False) -> Path:
    """A dense workspace with linked images/ and sparse/ and an empty stereo/ (kept as it is with
    ``keep_stereo``, for a resumed run)."""
    root.mkdir(parents=True, exist_ok=True)
    _link(images, root / "images")
    _link(sparse, root / "sparse")
    if (root / "stereo").exists() and not keep_stereo:
        shutil.rmtree(root / "stereo")
    (root / "stereo").mkdir(exist_ok=True)
    return root


def far_sources(ref_index: int, names: list[str], row: dict[str, float], count: int) -> list[str]:
    """``count`` unrelated frames far away in the sequence: index distance >= len/3, lowest view score
    first (0 = no shared sparse point), then the farthest."""
    n = len(names)
    cands = [j for j in range(n) if abs(j - ref_index) >= n / 3]
    cands.sort(key=lambda j: (row.get(names[j], 0.0), -abs(j - ref_index), j))
    return [names[j] for j in cands[:count]]


def make_ablation_checkpoint(checkpoint: Path, out: Path) -> Path:
    """The same weights with ``visibility`` off (mean aggregation); the visibility net is dropped."""
    from colmap_pvs.config import replace_config
    from colmap_pvs.io.files import file_sha256
    from colmap_pvs.model import PVSNet, load_checkpoint, save_checkpoint

    model, meta = load_checkpoint(checkpoint, map_location="cpu")
    if not model.config.visibility:
        raise SystemExit(f"{checkpoint} already has visibility off: pass --ablation_checkpoint instead")
    ablated = PVSNet(replace_config(model.config, visibility=False))
    wanted = ablated.state_dict()
    state = {k: v for k, v in model.state_dict().items() if k in wanted}
    missing = sorted(set(wanted) - set(state))
    if missing:
        raise SystemExit(f"cannot flip visibility off in {checkpoint}: the ablated model needs {missing[:5]}")
    ablated.load_state_dict(state, strict=True)
    return save_checkpoint(
        out,
        ablated,
        step=int(meta.get("step", 0)),
        extra={
            "derived_from": str(checkpoint),
            "derived_from_sha256": file_sha256(checkpoint),
            "note": "visibility switched off (mean aggregation) for the ablation",
        },
    )


def make_switch_off_checkpoint(checkpoint: Path, out: Path, switch: str) -> Path | None:
    """The same weights with the boolean ``PVSNetConfig`` field ``switch`` off (``None`` if it is off
    already): e.g. ``sparse_guidance`` or ``sparse_prior``, which add no parameters."""
    from colmap_pvs.config import replace_config
    from colmap_pvs.io.files import file_sha256
    from colmap_pvs.model import PVSNet, load_checkpoint, save_checkpoint

    model, meta = load_checkpoint(checkpoint, map_location="cpu")
    if not getattr(model.config, switch):
        return None
    off = PVSNet(replace_config(model.config, **{switch: False}))
    off.load_state_dict(model.state_dict(), strict=True)
    return save_checkpoint(
        out,
        off,
        step=int(meta.get("step", 0)),
        extra={"derived_from": str(checkpoint), "derived_from_sha256": file_sha256(checkpoint),
               "note": f"{switch} switched off"},
    )


# --------------------------------------------------------------------------- sparse-interpolation baseline


def interpolate_sparse_depth(uv: np.ndarray, depth: np.ndarray, height: int, width: int) -> np.ndarray:
    """Linear interpolation of sparse depths over their Delaunay triangulation in the image.

    Args:
        uv: ``[P, 2]`` continuous pixel coordinates (pixel ``(c, r)`` has its centre at ``(c+0.5, r+0.5)``).
        depth: ``[P]`` depths. Returns ``[height, width]`` float32, 0 outside the convex hull.
    """
    import cv2

    out = np.zeros((height, width), np.float32)
    keep = (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height) & (depth > 0)
    uv, depth = uv[keep].astype(np.float32), depth[keep]
    if len(uv) < 3:
        return out
    subdiv = cv2.Subdiv2D((-1, -1, width + 2, height + 2))
    lookup: dict[tuple[float, float], float] = {}
    for (u, v), d in zip(uv, depth, strict=True):
        key = (float(u), float(v))
        if key in lookup:  # duplicate position: keep the nearest point
            lookup[key] = min(lookup[key], float(d))
            continue
        lookup[key] = float(d)
        subdiv.insert(key)
    tris = subdiv.getTriangleList().reshape(-1, 3, 2)
    inside = np.all(
        (tris[:, :, 0] >= 0) & (tris[:, :, 0] < width) & (tris[:, :, 1] >= 0) & (tris[:, :, 1] < height),
        axis=1,
    )
    tris = tris[inside]
    if len(tris) == 0:
        return out
    zs = np.array([[lookup[(float(u), float(v))] for u, v in t] for t in tris], np.float64)
    # Exact point-in-triangle test at pixel centres, triangle by triangle over its bounding box.
    for t, z in zip(tris.astype(np.float64), zs, strict=True):
        (x0, y0), (x1, y1), (x2, y2) = t
        det = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
        if abs(det) < 1e-12:
            continue
        c0, c1 = int(np.floor(t[:, 0].min() - 0.5)), int(np.ceil(t[:, 0].max() - 0.5))
        r0, r1 = int(np.floor(t[:, 1].min() - 0.5)), int(np.ceil(t[:, 1].max() - 0.5))
        c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, width - 1), min(r1, height - 1)
        if c1 < c0 or r1 < r0:
            continue
        px, py = np.meshgrid(np.arange(c0, c1 + 1) + 0.5, np.arange(r0, r1 + 1) + 0.5)
        w0 = ((y1 - y2) * (px - x2) + (x2 - x1) * (py - y2)) / det
        w1 = ((y2 - y0) * (px - x2) + (x0 - x2) * (py - y2)) / det
        w2 = 1.0 - w0 - w1
        inside = (w0 >= -1e-9) & (w1 >= -1e-9) & (w2 >= -1e-9)
        block = out[r0 : r1 + 1, c0 : c1 + 1]
        block[inside] = (w0 * z[0] + w1 * z[1] + w2 * z[2])[inside]
    return out


def push_pull_depth(cam_points: np.ndarray, K: np.ndarray, height: int, width: int) -> np.ndarray:
    """Every pixel filled from the camera-frame points ``[P, 3]`` by the push-pull interpolation
    (inverse depth) of ``colmap_pvs.model.cost.densify_inverse_depth``: the network's sparse prior."""
    import torch

    from colmap_pvs.geometry import sparse_depth_map
    from colmap_pvs.model.cost import densify_inverse_depth

    hints = sparse_depth_map(cam_points, K, np.eye(4), height, width)
    inv = densify_inverse_depth(torch.from_numpy(hints)[None, None])[0, 0].numpy()
    return np.where(inv > 0, 1.0 / np.maximum(inv, 1e-12), 0.0).astype(np.float32)


def baseline_worker(spec: dict) -> dict:
    """Write sparse-interpolation depth maps for ``spec['refs']`` into the workspace."""
    from colmap_pvs.geometry import scale_intrinsics
    from colmap_pvs.io.maps import write_depth_map
    from colmap_pvs.io.workspace import load_workspace

    ws, model = load_workspace(spec["workspace"])
    order = np.argsort(model.points.ids)
    times = []
    for name in spec["refs"]:
        start = time.perf_counter()
        im = model.image_by_name(name)
        cam = model.camera_of(im)
        scale = (
            min(1.0, spec["max_image_size"] / max(cam.width, cam.height)) if spec["max_image_size"] > 0 else 1
        )
        w = max(1, int(np.floor(cam.width * scale + 0.5)))
        h = max(1, int(np.floor(cam.height * scale + 0.5)))
        K = scale_intrinsics(cam.K, w / cam.width, h / cam.height)
        rows = order[np.searchsorted(model.points.ids[order], im.point3D_ids)]
        x = model.points.xyz[rows] @ im.R.T + im.t
        x = x[x[:, 2] > 0]
        uvw = x @ K.T
        if spec.get("method", "delaunay") == "delaunay":
            depth = interpolate_sparse_depth(uvw[:, :2] / uvw[:, 2:], x[:, 2], h, w)
        else:  # push-pull fill of the hints (the network's sparse prior, at full resolution)
            depth = push_pull_depth(x, K, h, w)
        write_depth_map(ws.depth_map_path(name, "geometric"), depth)
        times.append(time.perf_counter() - start)
    return {
        "seconds_per_image": float(np.mean(times)) if times else 0.0,
        "processed": list(spec["refs"]),
        "skipped": {},
    }


def stereo_worker(spec: dict) -> dict:
    from colmap_pvs.stereo import PhotometricConfig, StereoConfig, run_stereo

    result = run_stereo(
        StereoConfig(
            workspace_path=Path(spec["workspace"]),
            photometric=PhotometricConfig(num_views=spec["num_views"], max_image_size=spec["max_image_size"]),
            checkpoint=Path(spec["checkpoint"]),
            threads=spec["threads"],
            overwrite=True,
            device="cpu",
        )
    )
    return {
        "seconds_per_image": result.seconds_per_image,
        "processed": result.processed,
        "skipped": result.skipped,
    }


def run_worker(kind: str, spec: dict, log: Path) -> dict:
    """Run ``stereo_worker``/``baseline_worker`` in a subprocess; adds its peak RSS and wall time."""
    log.parent.mkdir(parents=True, exist_ok=True)
    spec_path = log.with_suffix(".spec.json")
    out_path = log.with_suffix(".result.json")
    spec_path.write_text(json.dumps(spec))
    out_path.unlink(missing_ok=True)
    start = time.perf_counter()
    with log.open("w") as f:
        proc = subprocess.run(
            [sys.executable, __file__, f"--_{kind}_worker", str(spec_path), str(out_path)],
            stdout=f,
            stderr=subprocess.STDOUT,
        )
    wall = time.perf_counter() - start
    if proc.returncode != 0 or not out_path.is_file():
        tail = log.read_text().strip().splitlines()[-5:]
        raise SystemExit(f"{kind} worker failed (exit {proc.returncode}); log {log}:\n  " + "\n  ".join(tail))
    result = json.loads(out_path.read_text())
    result["wall_s"] = wall
    return result


def _worker_main(kind: str, spec_path: str, out_path: str) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    spec = json.loads(Path(spec_path).read_text())
    result = stereo_worker(spec) if kind == "stereo" else baseline_worker(spec)
    result["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    Path(out_path).write_text(json.dumps(result))
    return 0


# --------------------------------------------------------------------------- main

BASELINES = {
    "delaunay": "sparse interpolation (baseline)",
    "pushpull": "sparse push-pull fill (baseline)",
}


def evaluate_against_gt(ws: Path, data: Path, refs: list[str], kind: str = "geometric"):
    """``colmap_pvs.evaluate.evaluate_depth`` of ``ws``'s ``kind`` maps of ``refs`` against the
    uint16-mm GT of ``data/depth`` (``metrics.json``, or ``metrics.KIND.json`` for another kind, written
    into ``ws``)."""
    from colmap_pvs.evaluate import EvaluateDepthConfig, evaluate_depth

    return evaluate_depth(
        EvaluateDepthConfig(
            workspace_path=ws,
            gt=data / "depth",
            gt_scale=0.001,
            gt_pattern="{stem}",
            kind=kind,
            images=tuple(refs),
            output_path=ws / ("metrics.json" if kind == "geometric" else f"metrics.{kind}.json"),
        )
    )


def errors_on_mask(ws: Path, mask_ws: Path, gt_dir: Path, refs: list[str],
                   kind: str = "geometric") -> tuple[float, float]:
    """Pooled AbsRel and % under 5 % of ``ws``'s ``kind`` depth maps over the pixels where ``mask_ws``
    (the Delaunay baseline) also has a geometric map and the GT is valid; NaN when there are none."""
    import cv2

    from colmap_pvs.io.maps import read_depth_map

    errs = []
    for name in refs:
        pred_path = ws / "stereo" / "depth_maps" / f"{name}.{kind}.bin"
        mask_path = mask_ws / "stereo" / "depth_maps" / f"{name}.geometric.bin"
        gt_path = gt_dir / f"{Path(name).stem}.png"
        if not (pred_path.is_file() and mask_path.is_file() and gt_path.is_file()):
            continue
        pred, mask = read_depth_map(pred_path), read_depth_map(mask_path)
        gt = cv2.imread(str(gt_path), cv2.IMREAD_UNCHANGED).astype(np.float32) * 0.001
        gt = cv2.resize(gt, pred.shape[::-1], interpolation=cv2.INTER_NEAREST)
        ok = (gt > 0) & (pred > 0) & (mask > 0)
        errs.append(np.abs(pred[ok] - gt[ok]) / gt[ok])
    e = np.concatenate(errs) if errs else np.zeros(0)
    if e.size == 0:
        return float("nan"), float("nan")
    return float(e.mean()), float(100.0 * np.mean(e < 0.05))



def markdown_table(rows: list[dict]) -> str:
    header = [
        "setting",
        "refs",
        "coverage %",
        "MAE (m)",
        "AbsRel",
        "% <1% rel",
        "% <2% rel",
        "% <5% rel",
        "AbsRel (hull)",
        "% <5% (hull)",
        "s / image",
        "peak RSS (MB)",
    ]

    def f(v: float, spec: str) -> str:
        return "-" if v is None or not np.isfinite(v) else format(v, spec)

    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for r in rows:
        p = r["pooled"]
        lines.append(
            "| "
            + " | ".join(
                [
                    r["setting"],
                    f"{r['evaluated']}/{r['refs']}",
                    f(p.coverage_pct, ".1f"),
                    f(p.mae, ".4f"),
                    f(p.absrel, ".4f"),
                    f(p.rel_under_pct[0.01], ".1f"),
                    f(p.rel_under_pct[0.02], ".1f"),
                    f(p.rel_under_pct[0.05], ".1f"),
                    f(r["hull"][0], ".4f"),
                    f(r["hull"][1], ".1f"),
                    f(r["seconds_per_image"], ".2f"),
                    f(r["peak_rss_mb"], ".0f"),
                ]
            )
            + " |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    for kind in ("stereo", "baseline"):
        if argv and argv[0] == f"--_{kind}_worker":
            return _worker_main(kind, argv[1], argv[2])

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", type=Path, default=DEFAULT_CHECKPOINT, help="PVSNet checkpoint")
    p.add_argument(
        "--ablation_checkpoint",
        type=Path,
        default=None,
        help="mean-aggregation checkpoint for the ablation (default: --checkpoint with visibility off)",
    )
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="hololens-dev folder")
    p.add_argument("--work_dir", type=Path, default=DEFAULT_WORK, help="cache and outputs")
    p.add_argument("--stride", type=int, default=16, help="every STRIDE-th frame is a reference")
    p.add_argument(
        "--offset",
        type=int,
        default=None,
        help="index of the first reference frame (default STRIDE // 2); --stride 3 --offset 0 gives "
        "frames 3, 6, ..., 180, the references of the PatchmatchNet numbers in issue #6",
    )
    p.add_argument("--max_image_size", type=int, default=320, help="inference (and evaluation) size")
    p.add_argument(
        "--views", type=int, nargs="+", default=[3, 5, 7, 11], help="N values (reference included)"
    )
    p.add_argument("--disturb_n", type=int, default=5, help="N of the disturbed and ablation settings")
    p.add_argument("--disturb_count", type=int, default=2, help="best sources replaced by far-away frames")
    p.add_argument("--threads", type=int, default=0, help="torch / SIFT threads; 0 = default (all cores)")
    p.add_argument(
        "--no_record", action="store_true", help="print the table only, do not append to RESULTS.md"
    )
    p.add_argument("--note", default="", help="a note stored with the results")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    # The baseline has no stereo record (checkpoint unknown) and missing outputs show in the table.
    logging.getLogger("colmap_pvs.evaluate").setLevel(logging.ERROR)

    from colmap_pvs.io.files import file_sha256
    from colmap_pvs.io.sparse import read_sparse_model
    from colmap_pvs.io.workspace import write_patch_match_cfg
    from colmap_pvs.views import ViewSelectionConfig, select_views

    if not (args.data / "poses.txt").is_file():
        print(f"hololens-dev data not found at {args.data} (pass --data); nothing to do", file=sys.stderr)
        return 2
    if not args.checkpoint.is_file():
        print(f"checkpoint {args.checkpoint} does not exist (pass --checkpoint PATH)", file=sys.stderr)
        return 2
    if not 1 <= args.disturb_count <= args.disturb_n - 1:
        p.error(f"--disturb_count must be in 1..{args.disturb_n - 1}, got {args.disturb_count}")
    t_start = time.perf_counter()
    work = args.work_dir.resolve()
    work.mkdir(parents=True, exist_ok=True)
    sparse = build_model(args.data, work, args.threads)
    model = read_sparse_model(sparse)
    names = sorted(model.image_ids_by_name)
    selection = select_views(model, ViewSelectionConfig(num_views=max([*args.views, args.disturb_n])))
    offset = args.stride // 2 if args.offset is None else args.offset
    refs = [n for n in names[offset :: args.stride] if n in selection.references]
    print(f"[refs] {len(refs)} reference frames (every {args.stride}th): {', '.join(refs)}", flush=True)

    ckpt = args.checkpoint.resolve()
    ckpt_sha = file_sha256(ckpt)
    if args.ablation_checkpoint is not None:
        ablation_ckpt = args.ablation_checkpoint.resolve()
    else:
        ablation_ckpt = make_ablation_checkpoint(
            ckpt, work / "checkpoints" / f"{ckpt.stem}.visibility_off.pt"
        )

    def ranked(ref: str) -> list[str]:
        return list(selection.references[ref].ranked_names)

    n_d = args.disturb_n
    settings: list[tuple[str, int, Path | None, dict[str, list[str]]]] = []
    for n in args.views:
        settings.append((f"PVSNet N={n}", n, ckpt, {r: ranked(r)[: n - 1] for r in refs}))
    disturbed: dict[str, list[str]] = {}
    for r in refs:
        row = dict(
            zip(selection.references[r].ranked_names, selection.references[r].ranked_scores, strict=True)
        )
        keep = ranked(r)[: n_d - 1 - args.disturb_count]
        disturbed[r] = keep + far_sources(names.index(r), names, row, args.disturb_count)
    clean = {r: ranked(r)[: n_d - 1] for r in refs}
    settings.append((f"PVSNet N={n_d}, {args.disturb_count} disturbing", n_d, ckpt, disturbed))
    offs = []
    for switch, what in (("sparse_guidance", "sparse guidance"), ("sparse_prior", "sparse prior")):
        off = make_switch_off_checkpoint(ckpt, work / "checkpoints" / f"{ckpt.stem}.{switch}_off.pt", switch)
        if off is not None:
            settings.append((f"PVSNet N={n_d}, {what} off", n_d, off, clean))
            offs.append(off)
    if len(offs) == 2:  # both on in the checkpoint: also without any sparse input
        both = work / "checkpoints" / f"{ckpt.stem}.sparse_off.pt"
        none = make_switch_off_checkpoint(offs[0], both, "sparse_prior")
        settings.append((f"PVSNet N={n_d}, no sparse input", n_d, none, clean))
    settings.append((f"mean-agg N={n_d} (visibility off)", n_d, ablation_ckpt, clean))
    settings.append((f"mean-agg N={n_d}, {args.disturb_count} disturbing", n_d, ablation_ckpt, disturbed))
    no_sources = {r: [] for r in refs}
    settings.append((BASELINES["delaunay"], 0, None, no_sources))
    settings.append((BASELINES["pushpull"], 0, None, no_sources))

    rows = []
    for i, (label, n, checkpoint, sources) in enumerate(settings):
        slug = f"{i:02d}_" + "".join(c if c.isalnum() else "_" for c in label).strip("_")[:40]
        ws = make_workspace(work / "ws" / slug, args.data / "images", sparse)
        if checkpoint is not None:
            write_patch_match_cfg(ws / "stereo" / "patch-match.cfg", sources)
            spec = {
                "workspace": str(ws),
                "num_views": n,
                "max_image_size": args.max_image_size,
                "checkpoint": str(checkpoint),
                "threads": args.threads,
            }
            result = run_worker("stereo", spec, work / "logs" / f"{slug}.log")
        else:
            method = next(k for k, v in BASELINES.items() if v == label)
            spec = {
                "workspace": str(ws),
                "refs": refs,
                "max_image_size": args.max_image_size,
                "method": method,
            }
            result = run_worker("baseline", spec, work / "logs" / f"{slug}.log")
        metrics = evaluate_against_gt(ws, args.data, refs)
        if checkpoint is None and label == BASELINES["delaunay"]:
            hull_ws = ws
        rows.append(
            {
                "workspace": ws,
                "setting": label,
                "refs": len(refs),
                "evaluated": len(result["processed"]),
                "pooled": metrics.pooled,
                "seconds_per_image": result["seconds_per_image"],
                "peak_rss_mb": result["peak_rss_mb"],
                "skipped": result["skipped"],
            }
        )
        print(
            f"[{label}] {len(result['processed'])}/{len(refs)} refs, "
            f"{result['seconds_per_image']:.2f} s/image, "
            f"coverage {metrics.pooled.coverage_pct:.1f}%, AbsRel {metrics.pooled.absrel:.4f} "
            f"[{result['wall_s']:.0f} s wall]",
            flush=True,
        )
        if checkpoint is not None and any((ws / "stereo" / "depth_maps").glob("*.filled.bin")):
            filled = evaluate_against_gt(ws, args.data, refs, kind="filled")  # every pixel, completed
            rows.append({**rows[-1], "setting": f"{label}, filled", "pooled": filled.pooled,
                         "kind": "filled"})
            print(f"[{label}, filled] coverage {filled.pooled.coverage_pct:.1f}%, AbsRel "
                  f"{filled.pooled.absrel:.4f}", flush=True)
        (work / "sources").mkdir(exist_ok=True)
        (work / "sources" / f"{slug}.json").write_text(json.dumps(sources, indent=1))

    for r in rows:  # errors on the pixels that the Delaunay baseline covers (its convex hull)
        kind = r.get("kind", "geometric")
        r["hull"] = errors_on_mask(r["workspace"], hull_ws, args.data / "depth", refs, kind)
    total = time.perf_counter() - t_start
    table = markdown_table(rows)
    import torch

    threads = args.threads if args.threads > 0 else torch.get_num_threads()
    commit = git_commit()
    date = _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    ablation_note = (
        f"`{args.ablation_checkpoint}`"
        if args.ablation_checkpoint is not None
        else "the same checkpoint with `visibility` off"
    )
    block = "\n".join(
        [
            f"## {date}, commit `{commit}`",
            "",
            f"- checkpoint: `{ckpt.name}` (sha256 `{ckpt_sha[:16]}`), ablation: {ablation_note}",
            f"- {len(refs)} reference frames (every {args.stride}th of {len(names)}), "
            "inference and evaluation at "
            f"max_image_size {args.max_image_size}, {threads} torch thread(s) on {os.cpu_count()} CPU(s) "
            f"({platform.processor() or platform.machine()}), total {total / 60:.1f} min",
            f"- disturbing: {args.disturb_count} of the {n_d - 1} best sources replaced by far-away frames",
            *([f"- note: {args.note}"] if args.note else []),
            "",
            table,
            "",
        ]
    )
    print()
    print(table)
    print(
        "\nerrors over pixels valid in both (GT resized with nearest to the prediction); "
        "coverage = % of valid "
        f"GT pixels with a prediction; references without output count as coverage 0. "
        f"Total {total / 60:.1f} min. Checkpoint {ckpt} (sha256 {ckpt_sha[:16]}), commit {commit}."
    )
    for r in rows:
        for name, why in r["skipped"].items():
            print(f"  {r['setting']}: skipped {name}: {why}")
    if args.no_record:
        print("(--no_record: not appended to benchmarks/RESULTS.md)")
    else:
        with RESULTS.open("a") as f:
            f.write("\n" + block)
        print(f"appended to {RESULTS}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
