"""The shipped network's forward on ONNX Runtime and OpenVINO against torch (CPU, same inputs, one process).

Example::

    nice -n 5 python benchmarks/onnx_runtime.py            # 640x480, N = 5, 2 threads, 5 timed rounds

Exports ``PVSNet`` (the shipped checkpoint) with ``torch.onnx.export(dynamo=True)`` at the fixed input
shape into a temporary folder (never kept), then alternates torch (``inference_mode``, the stereo's path),
ONNX Runtime (``intra_op_num_threads``, inter-op 1) and OpenVINO (``INFERENCE_NUM_THREADS``, f32
precision) forwards on the same inputs: seconds per forward (median of ``--repeats`` after one warm-up each),
the peak RSS of a fresh process running only that runtime (two forwards), and the agreement of each
runtime's maps with torch's: the final depth's relative difference ``|d - d_torch| / d_torch`` (max, 99th
percentile, % of pixels within 0.1 % and 1 %) and the final confidence's absolute difference (max, 99th
percentile, % within 0.001 and 0.01).

Inputs: ``model_speed.make_inputs``' random images and rig with random hints (2 % of the pixels), and
``--real`` hololens-dev frames (``../shared/data/hololens-dev`` or ``--hololens``): each reference with
the frames 2 and 4 before and after it, resized to the export size (``K`` scaled per axis), poses from the
GT, the depth range from the GT depth's 1st/99th percentiles widened by 20 %, hints = GT depth at 0.5 % of
the valid pixels (standing in for the SfM points the stereo gives). onnxruntime, onnxscript and openvino
are not dependencies of the package: this script needs them installed by hand (a runtime that is missing
is skipped, and said so).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from colmap_pvs.model import load_checkpoint
from colmap_pvs.stereo.config import DEFAULT_CHECKPOINT

#: Names of the exported graph's inputs and outputs (final depth, confidence, coarse visibility).
INPUT_NAMES = ("images", "intrinsics", "cam_from_world", "depth_min", "depth_max", "sparse_depth")
OUTPUT_NAMES = ("depth", "confidence", "visibility")


class FinalMaps(torch.nn.Module):
    """``PVSNet`` with tensor outputs: ``(depth, confidence, visibility)`` of :class:`PVSNetOutput`."""

    def __init__(self, model: torch.nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, images, intrinsics, cam_from_world, depth_min, depth_max, sparse_depth):
        out = self.model(images, intrinsics, cam_from_world, depth_min, depth_max, sparse_depth=sparse_depth)
        return out.depth, out.confidence, out.visibility


def export_onnx(model: torch.nn.Module, inputs: tuple, path: Path) -> float:
    """Export ``model`` (eval mode) at the shapes of ``inputs`` to ``path``; returns the seconds it took.

    Traced with autograd on, so the graph holds the model's straightforward (training) path, not the
    torch-specific inference path (plane chunks, in-place writes); the runtime plans its own memory."""
    model.eval()
    t0 = time.perf_counter()
    with torch.enable_grad():
        torch.onnx.export(FinalMaps(model), tuple(inputs), str(path), input_names=list(INPUT_NAMES),
                          output_names=list(OUTPUT_NAMES), dynamo=True, opset_version=18, optimize=False,
                          verbose=False)
    return time.perf_counter() - t0


def torch_runner(model: torch.nn.Module):
    def run(inputs: tuple) -> list[np.ndarray]:
        with torch.inference_mode():
            out = model(*inputs[:5], sparse_depth=inputs[5])
        return [out.depth.numpy(), out.confidence.numpy(), out.visibility.numpy()]

    return run


def ort_runner(path: Path, threads: int):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]

    def run(inputs: tuple) -> list[np.ndarray]:
        return session.run(None, {n: t.numpy() for n, t in zip(names, inputs, strict=True)})

    return run


def openvino_runner(path: Path, threads: int):
    import openvino as ov

    core = ov.Core()
    compiled = core.compile_model(core.read_model(str(path)), "CPU", {
        "INFERENCE_NUM_THREADS": threads, "INFERENCE_PRECISION_HINT": "f32", "PERFORMANCE_HINT": "LATENCY",
    })
    request = compiled.create_infer_request()

    def run(inputs: tuple) -> list[np.ndarray]:
        result = request.infer([t.numpy() for t in inputs])
        return [np.array(result[compiled.output(i)]) for i in range(len(OUTPUT_NAMES))]

    return run


def random_inputs(height: int, width: int, views: int, seed: int = 0) -> tuple:
    """``model_speed.make_inputs`` (random images, depths 2..10) with random hints on 2 % of the pixels."""
    from model_speed import make_inputs

    images, intrinsics, poses, dmin, dmax = make_inputs(1, views, height, width, seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    keep = torch.rand(1, 1, height, width, generator=g) < 0.02
    sparse = torch.where(keep, 2.0 + 8.0 * torch.rand(1, 1, height, width, generator=g), 0.0)
    return images, intrinsics, poses, dmin, dmax, sparse


def hololens_inputs(root: Path, index: int, height: int, width: int, views: int, seed: int = 0) -> tuple:
    """Frame ``index`` of hololens-dev and its neighbours 2, 4, ... frames away as network inputs (module
    docstring)."""
    import cv2

    names = (root / "frames.txt").read_text().split()
    K = np.loadtxt(root / "K.txt")
    world_from_cam = np.loadtxt(root / "poses.txt").reshape(-1, 4, 4)
    offsets = [0] + [s * 2 * (k // 2 + 1) for k, s in zip(range(views - 1), [-1, 1] * views, strict=False)]
    frames = [min(max(index + o, 0), len(names) - 1) for o in offsets]
    images, Ks, poses = [], [], []
    for f in frames:
        img = cv2.imread(str(root / "images" / names[f]), cv2.IMREAD_COLOR)[:, :, ::-1]
        h0, w0 = img.shape[:2]
        img = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
        images.append(img.transpose(2, 0, 1) / 255.0)
        Ks.append(np.diag([width / w0, height / h0, 1.0]) @ K)
        poses.append(np.linalg.inv(world_from_cam[f]))
    gt = cv2.imread(str(root / "depth" / names[frames[0]]), cv2.IMREAD_UNCHANGED).astype(np.float64) / 1000.0
    gt = cv2.resize(gt, (width, height), interpolation=cv2.INTER_NEAREST)
    valid = gt > 0
    lo, hi = np.percentile(gt[valid], [1, 99])
    rng = np.random.default_rng(seed + index)
    sparse = np.where(valid & (rng.random(gt.shape) < 0.005), gt, 0.0)
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32))[None]  # noqa: E731
    return (t(np.stack(images)), t(np.stack(Ks)), t(np.stack(poses)), t(0.8 * lo), t(1.2 * hi),
            t(sparse)[:, None])


def agreement(ref: list[np.ndarray], got: list[np.ndarray]) -> dict[str, float]:
    """The final depth's relative and the confidence's absolute difference from torch's (module docstring)."""
    d_ref, c_ref = ref[0].astype(np.float64), ref[1].astype(np.float64)
    rel = np.abs(got[0].astype(np.float64) - d_ref) / np.maximum(d_ref, 1e-12)
    dc = np.abs(got[1].astype(np.float64) - c_ref)
    return {
        "depth_rel_max": float(rel.max()), "depth_rel_p99": float(np.percentile(rel, 99)),
        "depth_within_0.1%": 100.0 * float((rel <= 1e-3).mean()),
        "depth_within_1%": 100.0 * float((rel <= 1e-2).mean()),
        "conf_abs_max": float(dc.max()), "conf_abs_p99": float(np.percentile(dc, 99)),
        "conf_within_0.001": 100.0 * float((dc <= 1e-3).mean()),
        "conf_within_0.01": 100.0 * float((dc <= 1e-2).mean()),
    }


def _runner(name: str, model, path: Path, threads: int):
    if name == "torch":
        return torch_runner(model)
    return ort_runner(path, threads) if name == "onnxruntime" else openvino_runner(path, threads)


def peak_rss_child(args) -> None:
    """``--rss_of RUNTIME``: two forwards of one runtime in this fresh process, then print its peak RSS."""
    torch.set_num_threads(args.threads)
    model = _load(args.checkpoint)
    run = _runner(args.rss_of, model, Path(args.onnx), args.threads)
    if args.rss_of != "torch":
        del model
    inputs = random_inputs(args.height, args.width, args.views)
    for _ in range(2):
        run(inputs)
    print(json.dumps({"peak_rss_mb": _peak_rss_mb()}))


def _peak_rss_mb() -> float:
    """This process's peak resident set: ``VmHWM`` (``ru_maxrss`` survives the ``exec`` of a child, so a
    child of a big parent would report the parent's peak)."""
    status = Path("/proc/self/status")
    if status.exists():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _load(checkpoint: str):
    model, _ = load_checkpoint(checkpoint, map_location="cpu")
    return model.eval()


def _available(name: str) -> str | None:
    """Why runtime ``name`` cannot run here (not installed), or None."""
    import importlib.util

    module = {"onnxruntime": "onnxruntime", "openvino": "openvino"}.get(name)
    if module is None:
        return None
    if importlib.util.find_spec(module) is None:
        return f"{module} is not installed"
    return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--views", type=int, default=5, help="N, reference included")
    parser.add_argument("--threads", type=int, default=2, help="threads of every runtime")
    parser.add_argument("--repeats", type=int, default=5, help="timed rounds (after one warm-up each)")
    parser.add_argument("--checkpoint", default=str(DEFAULT_CHECKPOINT))
    parser.add_argument("--runtimes", nargs="+", default=["torch", "onnxruntime", "openvino"])
    parser.add_argument("--real", type=int, nargs="*", default=[20, 90, 160],
                        help="hololens-dev frame indices for the agreement on real frames (none: skip)")
    parser.add_argument("--hololens", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"
                                                  / "hololens-dev"))
    parser.add_argument("--rss_of", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--onnx", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.rss_of:
        peak_rss_child(args)
        return
    torch.set_num_threads(args.threads)
    runtimes = []
    for name in args.runtimes:
        why = _available(name)
        if why:
            print(f"skipping {name}: {why}")
        else:
            runtimes.append(name)
    model = _load(args.checkpoint)
    inputs = random_inputs(args.height, args.width, args.views)
    print(f"PVSNet {args.checkpoint}, {args.width}x{args.height}, N = {args.views}, {args.threads} threads; "
          f"torch {torch.__version__}; load before: {os.getloadavg()}")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "pvsnet.onnx"
        if any(r != "torch" for r in runtimes):
            seconds = export_onnx(model, inputs, path)
            print(f"exported in {seconds:.0f} s ({path.stat().st_size / 2**20:.1f} MB)")
        runners = {}
        for name in runtimes:
            t0 = time.perf_counter()
            try:
                runners[name] = _runner(name, model, path, args.threads)
                runners[name](inputs)  # warm-up
            except RuntimeError as exc:  # a runtime that cannot load or run the exported graph
                runners.pop(name, None)
                lines = [line for line in str(exc).splitlines() if line.strip()]
                print(f"{name}: FAILED on the exported graph: {' / '.join(lines[:3])[:600]}")
                continue
            print(f"{name}: ready and warmed up in {time.perf_counter() - t0:.1f} s")
        ref = runners["torch"](inputs) if "torch" in runners else None
        times: dict[str, list[float]] = {n: [] for n in runners}
        outputs = {}
        for _ in range(args.repeats):  # alternated: each round runs every runtime once
            for name, run in runners.items():
                t0 = time.perf_counter()
                outputs[name] = run(inputs)
                times[name].append(time.perf_counter() - t0)
        real = {n: [] for n in runners if n != "torch"}
        for index in args.real:
            frame = hololens_inputs(Path(args.hololens), index, args.height, args.width, args.views)
            frame_ref = runners["torch"](frame)
            for name in real:
                real[name].append(agreement(frame_ref, runners[name](frame)))
        rss = {}
        for name in runners:
            cmd = [sys.executable, __file__, "--rss_of", name, "--onnx", str(path),
                   "--height", str(args.height), "--width", str(args.width), "--views", str(args.views),
                   "--threads", str(args.threads), "--checkpoint", args.checkpoint]
            done = subprocess.run(cmd, capture_output=True, text=True, check=True)
            rss[name] = json.loads(done.stdout.strip().splitlines()[-1])["peak_rss_mb"]
    print(f"load after: {os.getloadavg()}")
    print("| runtime | s / forward (median) | all runs | peak RSS (MB, own process) |")
    print("|---|---|---|---|")
    for name, ts in times.items():
        runs = " ".join(f"{t:.2f}" for t in ts)
        print(f"| {name} | {statistics.median(ts):.3f} | {runs} | {rss[name]:.0f} |")
    if ref is None:
        return
    print("\nagreement with torch (final depth: relative difference; confidence: absolute difference)")
    print("| runtime | inputs | depth max | depth p99 | depth % <= 0.1 % | depth % <= 1 % | conf max | "
          "conf p99 | conf % <= 0.001 | conf % <= 0.01 |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    rows = [(n, "random", agreement(ref, outputs[n])) for n in outputs if n != "torch"]
    rows += [(n, f"hololens frame {i}", a) for n in real for i, a in zip(args.real, real[n], strict=True)]
    for name, what, a in rows:
        print(f"| {name} | {what} | {a['depth_rel_max']:.2e} | {a['depth_rel_p99']:.2e} | "
              f"{a['depth_within_0.1%']:.2f} | {a['depth_within_1%']:.2f} | {a['conf_abs_max']:.2e} | "
              f"{a['conf_abs_p99']:.2e} | {a['conf_within_0.001']:.2f} | {a['conf_within_0.01']:.2f} |")


if __name__ == "__main__":
    main()
