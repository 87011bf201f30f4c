"""PVSNet speed on the CPU: seconds per image and peak RSS against resolution and N, FLOPs per forward,
achieved GFLOP/s against the machine's nominal peak.

Every configuration runs in its own subprocess, so the peak RSS (``ru_maxrss``) is that
configuration's alone (it includes the Python + torch baseline, also printed separately).
Inputs are random images with a plausible stereo rig (cameras side by side, depth 1..10):
PVSNet's cost does not depend on the image content.

    python benchmarks/speed.py                      # quick subset (a few minutes on 2 cores)
    python benchmarks/speed.py --full               # 320x240 ... 1600x1200 and N = 2 ... 11 (long)
    python benchmarks/speed.py --resolutions 640x480 --num_views 3 5 --threads 2 --json out.json

FLOPs are counted by ``torch.utils.flop_counter.FlopCounterMode`` on one forward pass: it counts
convolutions (including ``aten.mkldnn_convolution``, which the model calls directly without
autograd: a formula is registered for it here) and matrix products (2 FLOPs per multiply-add), not
element-wise ops, softmax, interpolation or ``grid_sample``, so achieved GFLOP/s is a lower bound of
the real arithmetic rate.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

QUICK_RESOLUTIONS = ("320x240", "640x480")
QUICK_NUM_VIEWS = (3, 5)
FULL_RESOLUTIONS = ("320x240", "640x480", "960x720", "1280x960", "1600x1200")
FULL_NUM_VIEWS = (2, 3, 5, 7, 11)


# --------------------------------------------------------------------------- machine peak


def _cpuinfo() -> dict[str, str]:
    info: dict[str, str] = {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            key = key.strip()
            if key and key not in info:
                info[key] = value.strip()
    except OSError:
        pass
    return info


def _lscpu() -> dict[str, str]:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.SubprocessError):
        return {}
    return {k.strip(): v.strip() for k, _, v in (line.partition(":") for line in out.splitlines()) if v}


def machine_peak(threads: int, fma_units: int | None = None, clock_ghz: float | None = None) -> dict:
    """Nominal fp32 peak = cores x SIMD lanes x 2 (FMA) x FMA units per core x clock, with its assumptions."""
    cpu, ls = _cpuinfo(), _lscpu()
    flags = set((ls.get("Flags") or cpu.get("flags", "")).split())
    if "avx512f" in flags:
        isa, lanes = "AVX-512", 16
    elif "avx2" in flags or "avx" in flags:
        isa, lanes = "AVX2" if "avx2" in flags else "AVX", 8
    else:
        isa, lanes = "SSE", 4
    has_fma = "fma" in flags or "avx512f" in flags
    # AMD Zen 4 (family 25 with AVX-512) executes a 512-bit FMA as two halves on its two 256-bit FMA
    # pipes: 16 fp32 FMAs per cycle, i.e. one 512-bit unit. Zen 5 (family 26) has full-width units.
    zen4 = cpu.get("vendor_id") == "AuthenticAMD" and cpu.get("cpu family") == "25" and lanes == 16
    units = fma_units if fma_units is not None else (1 if zen4 else 2)
    assumptions = []
    if fma_units is None and zen4:
        assumptions.append("AMD Zen 4: AVX-512 double-pumped on 2x256-bit FMA pipes = 1 512-bit unit")
    elif fma_units is None:
        assumptions.append("2 FMA units per core assumed (server Xeon/EPYC; some SKUs have 1: --fma_units)")
    if clock_ghz is None:
        mhz = ls.get("CPU max MHz") or cpu.get("cpu MHz")
        try:
            clock_ghz = float(mhz) / 1000.0
            src = "lscpu 'CPU max MHz'" if ls.get("CPU max MHz") else "/proc/cpuinfo 'cpu MHz' (nominal)"
        except (TypeError, ValueError):
            clock_ghz, src = 2.0, "unknown, 2.0 GHz assumed"
        assumptions.append(
            f"clock {clock_ghz:.2f} GHz from {src}; turbo/AVX-512 down-clocking ignored (a VM's 'cpu MHz' "
            "is the base clock: pass --clock_ghz with the boost clock for the stricter peak)"
        )
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    used = min(threads, cores) if threads > 0 else cores
    flop_per_cycle = lanes * (2 if has_fma else 1) * units
    peak = used * flop_per_cycle * clock_ghz
    assumptions.append(
        f"{used} core(s) used of {cores} available; fp32; {isa}: {lanes} lanes x "
        f"{'2 (FMA)' if has_fma else '1 (no FMA)'} x {units} unit(s) = {flop_per_cycle} FLOP/cycle/core"
    )
    if "amx_tile" in flags:
        assumptions.append("AMX present but unused by fp32 inference")
    return {
        "model_name": cpu.get("model name", platform.processor()),
        "isa": isa,
        "cores_used": used,
        "cores_available": cores,
        "clock_ghz": clock_ghz,
        "flop_per_cycle_per_core": flop_per_cycle,
        "peak_gflops": peak,
        "assumptions": assumptions,
    }


# --------------------------------------------------------------------------- one configuration (worker)


def _inputs(num_views: int, height: int, width: int):
    import numpy as np
    import torch

    rng = np.random.default_rng(0)
    images = torch.from_numpy(rng.random((1, num_views, 3, height, width), dtype=np.float32))
    f = 0.9 * width
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=torch.float32)
    poses = torch.eye(4).repeat(1, num_views, 1, 1)
    for i in range(num_views):  # cameras on a line, 0.1 apart, reference in the middle
        poses[0, i, 0, 3] = -0.1 * (i - (num_views - 1) / 2)
    intrinsics = K.repeat(1, num_views, 1, 1)
    return (
        images,
        intrinsics,
        poses,
        torch.tensor([1.0]),
        torch.tensor([10.0]),
        torch.zeros(1, 1, height, width),
    )


def _build_model(checkpoint: str | None, conv_dtype: str | None = None):
    from colmap_pvs.config import replace_config
    from colmap_pvs.model import PVSNet, PVSNetConfig, load_checkpoint

    if checkpoint:
        model, _meta = load_checkpoint(Path(checkpoint), map_location="cpu")
        what = f"checkpoint {checkpoint}"
    else:
        model, what = PVSNet(PVSNetConfig()), "random weights, default PVSNetConfig"
    if conv_dtype and conv_dtype != model.config.conv_dtype:  # a switch without parameters
        state = model.state_dict()
        model = PVSNet(replace_config(model.config, conv_dtype=conv_dtype))
        model.load_state_dict(state)
        what += f", conv_dtype={conv_dtype}"
    return model.eval(), what


def _register_onednn_conv_flops() -> None:
    """Count ``aten.mkldnn_convolution`` (called directly by ``colmap_pvs.model.layers`` without
    autograd) like any convolution: FlopCounterMode has no formula for it and would count 0."""
    import torch
    from torch.utils import flop_counter

    op = getattr(torch.ops.aten, "mkldnn_convolution", None)
    if op is None or op in flop_counter.flop_registry or op.default in flop_counter.flop_registry:
        return

    @flop_counter.register_flop_formula(op)
    def _flops(x_shape, w_shape, bias, padding, stride, dilation, groups, *, out_shape=None, **kwargs):
        return flop_counter.conv_flop_count(x_shape, w_shape, out_shape, transposed=False)


def worker(args: argparse.Namespace) -> dict:
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    _register_onednn_conv_flops()

    if args.threads > 0:
        torch.set_num_threads(args.threads)
    width, height = (int(v) for v in args.resolution.split("x"))
    rss_import = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    model, what = _build_model(args.checkpoint, args.conv_dtype)
    inputs = _inputs(args.num_views, height, width)
    images, K, poses, dmin, dmax, sparse = inputs
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    with torch.inference_mode():
        counter = FlopCounterMode(display=False)
        start = time.perf_counter()
        with counter:  # the warm-up pass counts FLOPs
            model(images, K, poses, dmin, dmax, sparse_depth=sparse)
        first = time.perf_counter() - start
        times, cpu_times = [], []
        for _ in range(args.repeats):
            start, cpu = time.perf_counter(), time.process_time()
            model(images, K, poses, dmin, dmax, sparse_depth=sparse)
            times.append(time.perf_counter() - start)
            cpu_times.append(time.process_time() - cpu)
    seconds = statistics.median(times) if times else first
    flops = int(counter.get_total_flops())
    return {
        "resolution": args.resolution,
        "num_views": args.num_views,
        "threads": torch.get_num_threads(),
        "seconds": seconds,
        "seconds_all": times,
        "seconds_min": min(times) if times else first,
        "seconds_first_with_counter": first,
        # CPU time of all threads: on a machine shared with other jobs, wall time is inflated by
        # waiting for a core, CPU time much less so (it still includes the other jobs' cache pressure).
        "cpu_seconds": statistics.median(cpu_times) if cpu_times else float("nan"),
        "load_average": os.getloadavg()[0],
        "flops": flops,
        "gflops_per_s": flops / seconds / 1e9,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "rss_before_forward_mb": rss_before,
        "rss_after_imports_mb": rss_import,
        "model": what,
    }


# --------------------------------------------------------------------------- sweep (parent)


def run_config(resolution: str, num_views: int, args: argparse.Namespace) -> dict:
    cmd = [
        sys.executable,
        __file__,
        "--_worker",
        "--resolution",
        resolution,
        "--num_views",
        str(num_views),
        "--repeats",
        str(args.repeats),
        "--threads",
        str(args.threads),
    ]
    if args.checkpoint:
        cmd += ["--checkpoint", str(args.checkpoint)]
    if args.conv_dtype:
        cmd += ["--conv_dtype", args.conv_dtype]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
    except subprocess.TimeoutExpired:
        return {
            "resolution": resolution,
            "num_views": num_views,
            "error": f"timed out after {args.timeout} s",
        }
    for line in proc.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT ") :])
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
    killed = " (killed: out of memory?)" if proc.returncode in (-9, 137) else ""
    return {
        "resolution": resolution,
        "num_views": num_views,
        "error": f"exit {proc.returncode}{killed}: {' | '.join(tail)}",
    }


def format_rows(results: list[dict], peak_gflops: float) -> str:
    header = ["resolution", "N", "s/image", "CPU s", "load", "peak RSS MB", "GFLOP/forward", "GFLOP/s"]
    header.append("% of peak")
    rows = []
    for r in results:
        if "error" in r:
            rows.append([r["resolution"], str(r["num_views"]), "-", "-", "-", "-", "-", "-", r["error"][:60]])
            continue
        rows.append(
            [
                r["resolution"],
                str(r["num_views"]),
                f"{r['seconds']:.2f}",
                f"{r.get('cpu_seconds', float('nan')):.2f}",
                f"{r.get('load_average', float('nan')):.1f}",
                f"{r['peak_rss_mb']:.0f}",
                f"{r['flops'] / 1e9:.1f}",
                f"{r['gflops_per_s']:.1f}",
                f"{100 * r['gflops_per_s'] / peak_gflops:.1f}",
            ]
        )
    widths = [max(len(x[c]) for x in [header, *rows]) for c in range(len(header))]
    fmt = lambda row: "  ".join(v.rjust(w) for v, w in zip(row, widths, strict=True))  # noqa: E731
    return "\n".join([fmt(header), "-" * len(fmt(header)), *(fmt(r) for r in rows)])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--full", action="store_true", help="full sweep: all resolutions at N=5, all N at 640x480")
    p.add_argument("--resolutions", nargs="+", default=None, help=f"WxH list (quick: {QUICK_RESOLUTIONS})")
    p.add_argument(
        "--num_views", nargs="+", type=int, default=None, help=f"N list (quick: {QUICK_NUM_VIEWS})"
    )
    p.add_argument("--sweep_n_at", default="320x240", help="resolution of the sweep over N (full: 640x480)")
    p.add_argument("--resolution_sweep_n", type=int, default=5, help="N of the sweep over resolutions")
    p.add_argument("--checkpoint", default=None, help="model checkpoint; default: random weights")
    p.add_argument("--threads", type=int, default=0, help="torch threads; 0 = torch's default")
    p.add_argument(
        "--conv_dtype", choices=["float32", "bfloat16"], default=None, help="override the model's conv_dtype"
    )
    p.add_argument("--repeats", type=int, default=2, help="timed forward passes after the warm-up")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds per configuration")
    p.add_argument("--fma_units", type=int, default=None, help="FMA units per core (default: 2, assumed)")
    p.add_argument("--clock_ghz", type=float, default=None, help="clock for the peak (default: from lscpu)")
    p.add_argument("--json", type=Path, default=None, help="also write all results to this JSON file")
    # worker mode (one configuration, in a subprocess)
    p.add_argument("--_worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--resolution", default="320x240", help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    if args._worker:
        args.num_views = args.num_views[0] if isinstance(args.num_views, list) else args.num_views or 5
        print("RESULT " + json.dumps(worker(args)), flush=True)
        return 0

    for res in [*(args.resolutions or []), args.sweep_n_at]:
        if not re.fullmatch(r"\d+x\d+", res):
            p.error(f"resolution {res!r} is not WxH")
    if args.full:
        resolutions = args.resolutions or list(FULL_RESOLUTIONS)
        num_views = args.num_views or list(FULL_NUM_VIEWS)
        sweep_n_at = "640x480" if args.sweep_n_at == "320x240" else args.sweep_n_at
    else:
        resolutions = args.resolutions or list(QUICK_RESOLUTIONS)
        num_views = args.num_views or list(QUICK_NUM_VIEWS)
        sweep_n_at = args.sweep_n_at
    configs = [(r, args.resolution_sweep_n) for r in resolutions]
    configs += [(sweep_n_at, n) for n in num_views if (sweep_n_at, n) not in configs]

    import torch

    threads = args.threads if args.threads > 0 else torch.get_num_threads()
    peak = machine_peak(threads, args.fma_units, args.clock_ghz)
    print(f"CPU: {peak['model_name']} ({peak['isa']}), torch {torch.__version__}, {threads} thread(s)")
    print(f"nominal peak: {peak['peak_gflops']:.0f} GFLOP/s fp32. Assumptions:")
    for a in peak["assumptions"]:
        print(f"  - {a}")
    print(
        "model: "
        + (f"checkpoint {args.checkpoint}" if args.checkpoint else "random weights (default config)")
    )
    print(
        f"{len(configs)} configuration(s), each in its own subprocess; "
        f"{args.repeats} timed pass(es) after a warm-up"
    )

    results = []
    for res, n in configs:
        start = time.perf_counter()
        r = run_config(res, n, args)
        results.append(r)
        status = r.get("error") or f"{r['seconds']:.2f} s, {r['peak_rss_mb']:.0f} MB"
        print(f"  {res} N={n}: {status}  [{time.perf_counter() - start:.0f} s wall]", flush=True)
    print()
    print(format_rows(results, peak["peak_gflops"]))
    ok = [r for r in results if "error" not in r]
    if ok:
        base = min(r["rss_after_imports_mb"] for r in ok)
        print(
            f"\npeak RSS includes ~{base:.0f} MB of Python + torch after imports. s/image = one forward "
            "(reference + N-1 sources), median of the timed passes."
        )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"machine": peak, "results": results}, indent=2))
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
