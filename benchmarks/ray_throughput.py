"""Stereo throughput, local against Ray: images per minute on this machine (issue 12).

    python benchmarks/ray_throughput.py                               # 23 statue images, 320 px
    python benchmarks/ray_throughput.py --references 8 --max_image_size 640

Copies ``../shared/data/colmap-statue`` (read-only) to a temporary folder and runs the stereo step with
the shipped checkpoint, each setting in its own subprocess on a fresh copy:

- ``local, T threads`` (``--backend local --threads T``, default T=2);
- ``ray, W workers x 1 thread`` (``--backend ray --ray_workers W --ray_worker_threads 1``, a local
  Ray started by the run, default W=2).

For each it prints the wall time of the whole command and the images per minute that makes, and the
steady-state rate with the start-up cost (torch import, Ray start, model and sparse model loading)
removed: the same command rerun on the finished workspace (every reference comes back ``done``)
measures that start-up, and ``steady = images / (wall - wall of the rerun)``. Both walls include the
driver's import of torch and colmap-pvs (timed once, as every command pays it). Peak RSS is the
process's own for local runs and the largest Ray worker's (``VmHWM`` of ``ray::StereoWorker``
processes, sampled) for Ray runs. Timings on a shared machine are upper bounds.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
STATUE = REPO.parent / "shared" / "data" / "colmap-statue"


def _copy_workspace(src: Path, dst: Path, references: int) -> int:
    """Copy images/ + sparse/ (+ a patch-match.cfg limited to the first ``references`` entries)."""
    shutil.copytree(src / "images", dst / "images")
    shutil.copytree(src / "sparse", dst / "sparse")
    (dst / "stereo").mkdir()
    cfg = src / "stereo" / "patch-match.cfg"
    lines = [ln for ln in cfg.read_text().splitlines() if ln.strip()] if cfg.is_file() else []
    pairs = [lines[i : i + 2] for i in range(0, len(lines), 2)]
    if references > 0:
        pairs = pairs[:references]
    (dst / "stereo" / "patch-match.cfg").write_text("".join(f"{a}\n{b}\n" for a, b in pairs))
    return len(pairs)


def _worker_peak_rss_mb(stop: threading.Event, peak: list[float]) -> None:
    """Largest VmHWM (peak RSS) of any ``ray::StereoWorker`` process seen while ``stop`` is unset."""
    while not stop.is_set():
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                if not (entry / "cmdline").read_bytes().startswith(b"ray::StereoWorker"):
                    continue
                for line in (entry / "status").read_text().splitlines():
                    if line.startswith("VmHWM:"):
                        peak[0] = max(peak[0], int(line.split()[1]) / 1024)
            except OSError:
                continue
        stop.wait(0.5)


def _child(args: argparse.Namespace) -> None:
    """One setting: run the stereo step twice (compute, then the resume that finds all done)."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the CLI does
    start = time.perf_counter()
    from colmap_pvs.config import config_from_dict
    from colmap_pvs.stereo import StereoConfig, run_stereo

    imported = time.perf_counter() - start  # paid by every command (the driver's own torch import)

    kw = dict(workspace_path=Path(args.workspace), max_image_size=args.max_image_size,
              num_views=args.num_views)
    if args.backend == "local":
        config = config_from_dict(StereoConfig, dict(kw, threads=args.threads))
    else:
        config = config_from_dict(StereoConfig, dict(kw, backend="ray", ray_workers=args.workers,
                                                     ray_worker_threads=1))
    peak = [0.0]
    stop = threading.Event()
    sampler = threading.Thread(target=_worker_peak_rss_mb, args=(stop, peak), daemon=True)
    sampler.start()
    out = {}
    for run in ("compute", "resume"):
        start = time.perf_counter()
        result = run_stereo(config)
        out[run] = {"wall": time.perf_counter() - start + imported, "computed": len(result.processed),
                    "done": len(result.already_done), "skipped": len(result.skipped),
                    # compute time of one image in one process (Ray: per task on one worker)
                    "s_per_image": getattr(result, "seconds_per_task", result.seconds_per_image)}
    stop.set()
    sampler.join()
    out["peak_rss_mb"] = (peak[0] if args.backend == "ray"
                          else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    print("RESULT " + json.dumps(out), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", type=Path, default=STATUE, help="dense workspace to copy (read-only)")
    parser.add_argument("--references", type=int, default=0,
                        help="first N references of patch-match.cfg; 0: all")
    parser.add_argument("--max_image_size", type=int, default=320)
    parser.add_argument("--num_views", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2, help="local: torch threads")
    parser.add_argument("--workers", type=int, default=2, help="ray: workers of 1 thread each")
    parser.add_argument("--timeout", type=float, default=1800, help="seconds per setting")
    parser.add_argument("--_child", choices=["local", "ray"], dest="backend", help=argparse.SUPPRESS)
    parser.add_argument("--_workspace", dest="workspace", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.backend:
        _child(args)
        return
    if not (args.source / "sparse").is_dir():
        sys.exit(f"no dense workspace at {args.source}")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    settings = [("local", f"local, {args.threads} threads"),
                ("ray", f"ray, {args.workers} workers x 1 thread")]
    rows = []
    with tempfile.TemporaryDirectory(prefix="ray_throughput_") as tmp:
        for backend, label in settings:
            ws = Path(tmp) / backend
            n = _copy_workspace(args.source, ws, args.references)
            cmd = [sys.executable, __file__, "--_child", backend, "--_workspace", str(ws),
                   "--max_image_size", str(args.max_image_size), "--num_views", str(args.num_views),
                   "--threads", str(args.threads), "--workers", str(args.workers)]
            proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=args.timeout)
            line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")), None)
            if proc.returncode != 0 or line is None:
                sys.exit(f"{label} failed (rc {proc.returncode}):\n{proc.stderr[-3000:]}")
            res = json.loads(line[len("RESULT "):])
            comp, resume = res["compute"], res["resume"]
            if comp["computed"] != n:
                sys.exit(f"{label}: computed {comp['computed']} of {n} references ({comp})")
            steady = comp["wall"] - resume["wall"]
            rows.append((label, n, comp["wall"], 60 * n / comp["wall"], resume["wall"],
                         60 * n / steady if steady > 0 else float("nan"), comp["s_per_image"],
                         res["peak_rss_mb"]))
    print(f"colmap-statue copy, {args.max_image_size} px, N={args.num_views}, shipped checkpoint, "
          f"{os.cpu_count()} CPUs (shared machine: upper bounds)")
    print("| setting | images | wall (s) | images/min | start-up (s) | steady images/min | "
          "s/image (per worker) | peak RSS (MB) |")
    print("|---|---|---|---|---|---|---|---|")
    for label, n, wall, ipm, startup, steady, spi, rss in rows:
        print(f"| {label} | {n} | {wall:.1f} | {ipm:.1f} | {startup:.1f} | {steady:.1f} | {spi:.2f} "
              f"| {rss:.0f} |")


if __name__ == "__main__":
    main()
