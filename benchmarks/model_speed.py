"""Speed, peak memory and FLOPs of one PVSNet forward pass (CPU inference by default).

Examples::

    python benchmarks/model_speed.py                          # 640x480, N=5, default config
    python benchmarks/model_speed.py --height 128 --width 160 --train   # one training step
    python benchmarks/model_speed.py --planes_per_stage 32 16 8 --profile

Prints seconds per forward (or per forward+backward+optimizer step with ``--train``), the
peak resident set size of the process (``resource.getrusage``) and the FLOP count of one
forward pass (``torch.utils.flop_counter.FlopCounterMode``; convolutions and matmuls only).
Any ``PVSNetConfig`` field can be overridden with ``--<field> value``.

On a machine shared with other busy processes, OpenMP's default spin-waiting makes
multi-threaded runs several times slower (threads spin while a sibling is descheduled);
``--omp_passive`` sets ``OMP_WAIT_POLICY=PASSIVE`` before torch is imported (measured
1.8-3.4x faster at load ~8 on 2 cores).
"""

from __future__ import annotations

import argparse
import logging
import os
import resource
import sys
import time

if "--omp_passive" in sys.argv:  # must happen before the OpenMP runtime starts (torch import)
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

import torch  # noqa: E402

from colmap_pvs.config import add_config_arguments, config_from_args, replace_config  # noqa: E402
from colmap_pvs.model import PVSNet, PVSNetConfig  # noqa: E402
from colmap_pvs.model.runtime import estimate_peak_memory  # noqa: E402
from colmap_pvs.train.losses import depth_loss  # noqa: E402


def make_inputs(batch: int, views: int, height: int, width: int, seed: int = 0):
    """Random images and a small forward-facing camera rig looking at depths 2..10."""
    g = torch.Generator().manual_seed(seed)
    images = torch.rand(batch, views, 3, height, width, generator=g)
    f = 0.8 * width
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    intrinsics = K.expand(batch, views, 3, 3).clone()
    poses = torch.eye(4).expand(batch, views, 4, 4).clone()
    for i in range(1, views):
        poses[:, i, 0, 3] = 0.15 * ((i + 1) // 2) * (-1) ** i
        poses[:, i, 1, 3] = 0.05 * (i % 3 - 1)
    depth_min = torch.full((batch,), 2.0)
    depth_max = torch.full((batch,), 10.0)
    return images, intrinsics, poses, depth_min, depth_max


def count_flops(model: PVSNet, inputs) -> int:
    """FLOPs of one inference forward pass (convolutions and matmuls; multiply-add = 2 FLOPs)."""
    from torch.utils.flop_counter import FlopCounterMode, conv_flop_count

    def mkldnn_conv_flop(x_shape, w_shape, *args, out_shape=None, **kwargs) -> int:
        # The model calls oneDNN's convolution directly at inference; count it like aten.convolution.
        return conv_flop_count(x_shape, w_shape, out_shape, transposed=False)

    mapping = {torch.ops.aten.mkldnn_convolution: mkldnn_conv_flop}
    model.eval()
    with torch.inference_mode(), FlopCounterMode(display=False, custom_mapping=mapping) as counter:
        model(*inputs)
    return counter.get_total_flops()


def cpu_time_profile(run, top: int = 15) -> str:
    """Per-operator CPU time of one call of ``run`` (``time.thread_time`` around every aten op).

    Unlike ``torch.profiler`` (wall time per op), this excludes the time spent waiting for a core, so
    it is meaningful on a machine shared with other jobs. With more than one torch thread the ops'
    work on the other threads is not counted.
    """
    import collections

    from torch.utils._python_dispatch import TorchDispatchMode

    class _Timer(TorchDispatchMode):
        def __init__(self) -> None:
            super().__init__()
            self.ms: collections.Counter = collections.Counter()
            self.calls: collections.Counter = collections.Counter()

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            start = time.thread_time()
            out = func(*args, **(kwargs or {}))
            name = str(func.overloadpacket)
            self.ms[name] += 1000.0 * (time.thread_time() - start)
            self.calls[name] += 1
            return out

    timer = _Timer()
    with timer:
        run()
    lines = [f"CPU time in aten ops (calling thread): {sum(timer.ms.values()):.0f} ms"]
    lines += [f"{ms:9.1f} ms {timer.calls[k]:6d}  {k}" for k, ms in timer.ms.most_common(top)]
    return "\n".join(lines)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--views", type=int, default=5, help="N, reference included")
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2, help="torch.set_num_threads")
    parser.add_argument(
        "--checkpoint", default=None, help="time this checkpoint's model (config overrides still apply)"
    )
    parser.add_argument("--repeats", type=int, default=2, help="timed runs (after one warm-up)")
    parser.add_argument("--train", action="store_true", help="time a training step (forward+backward+Adam)")
    parser.add_argument("--no_flops", action="store_true", help="skip the FLOP count")
    parser.add_argument("--profile", action="store_true", help="print the top operators (torch.profiler)")
    parser.add_argument(
        "--cpu_profile",
        action="store_true",
        help="print the top operators by the CPU time of the calling thread (robust on a loaded machine; "
        "use with --threads 1)",
    )
    parser.add_argument(
        "--omp_passive", action="store_true", help="OMP_WAIT_POLICY=PASSIVE (shared machines)"
    )
    add_config_arguments(parser, PVSNetConfig)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(args.threads)
    if args.checkpoint:
        from colmap_pvs.config import config_to_dict
        from colmap_pvs.model import load_checkpoint

        loaded, _ = load_checkpoint(args.checkpoint)
        defaults = config_to_dict(PVSNetConfig())
        overrides = config_to_dict(config_from_args(PVSNetConfig, args)).items()
        given = {k: v for k, v in overrides if v != defaults[k]}  # flags given on the command line
        config = replace_config(loaded.config, **given)
        model = PVSNet(config)
        model.load_state_dict(loaded.state_dict())
    else:
        config = config_from_args(PVSNetConfig, args)
        model = PVSNet(config)
    inputs = make_inputs(args.batch, args.views, args.height, args.width)
    print(f"config: {config}")
    print(
        f"input: B={args.batch} N={args.views} {args.width}x{args.height}, threads={args.threads}, "
        f"params={model.num_parameters() / 1e6:.3f} M, rss before={peak_rss_mb():.0f} MB, "
        f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', 'default')}, load={os.getloadavg()[0]:.1f}"
    )

    if args.train:
        model.train()
        opt = torch.optim.Adam(model.parameters(), lr=1e-4)
        gt = torch.full((args.batch, args.height, args.width), 4.0)

        def step() -> None:
            opt.zero_grad(set_to_none=True)
            out = model(*inputs)
            loss = depth_loss(out.depths, gt, inputs[3], inputs[4], config.loss_weights,
                              scales=config.output_scales).total
            loss.backward()
            opt.step()

        run = step
    else:
        model.eval()

        def run() -> None:
            with torch.inference_mode():
                model(*inputs)

    run()  # warm-up
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    what = "train step (fwd+bwd+Adam)" if args.train else "forward (inference_mode)"
    if times:
        print(f"{what}: {min(times):.3f} s best, {sum(times) / len(times):.3f} s mean over {len(times)} runs")
    print(f"peak RSS: {peak_rss_mb():.0f} MB")
    if not args.train:
        est = estimate_peak_memory(args.height, args.width, args.views, config, batch=args.batch)
        print(f"estimated peak (colmap_pvs.model.runtime.estimate_peak_memory): {est / 2**20:.0f} MB")

    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU]) as prof:
            run()
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))

    if args.cpu_profile:
        print(cpu_time_profile(run))

    if not args.no_flops:
        print(f"FLOPs of one forward pass: {count_flops(model, inputs) / 1e9:.1f} GFLOP")


if __name__ == "__main__":
    main()
