"""Inference-time execution settings of PVSNet: chunking of the large temporaries.

These change how the forward pass is *executed*, never what it computes (the results match the
straightforward path up to float rounding; ``tests/test_model_runtime.py``) and never the
checkpoint: nothing here is a config field or a parameter.

Why chunk on the CPU: glibc serves every allocation above 32 MiB with a fresh ``mmap``, so each
full-resolution temporary (a ``[1, 8, 8, 480, 640]`` float volume is 79 MB) is page-faulted in
on first touch, which costs about three times the arithmetic of an element-wise pass over it.
Temporaries of at most :data:`CHUNK_BYTES` are recycled from the heap instead, and bound the
memory of the cost volumes whatever the image size.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

import torch

from ..errors import ConfigError, MemoryBudgetError

if TYPE_CHECKING:
    from .config import PVSNetConfig

#: Target size of one chunk of a temporary (warped features, sampling grid, upsampled rows).
CHUNK_BYTES = 16 * 1024 * 1024


def resolve_device(name: str) -> torch.device:
    """The torch device of a ``device`` setting (``stereo``'s and ``train``'s): ``cpu``, ``cuda``, or
    ``auto`` (CUDA when available, else the CPU)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda was requested but torch.cuda.is_available() is False")
    return torch.device(name)


def exporting() -> bool:
    """Whether the forward pass is being traced for export (``torch.export``, ``torch.onnx.export``,
    ``torch.jit.trace``): the model then skips its checks of input values and its branches on tensor
    values, which a traced graph cannot hold, and computes the same results with ops that export."""
    return bool(torch.compiler.is_exporting() or torch.jit.is_tracing() or torch.onnx.is_in_onnx_export())


def chunk_bytes() -> int:
    """The current :data:`CHUNK_BYTES` (read at call time, so tests can lower it)."""
    return CHUNK_BYTES


def plane_chunk(bytes_per_plane: int, num_planes: int) -> int:
    """Number of depth planes processed at once so that one chunk stays within :data:`CHUNK_BYTES`
    (at least 1, at most ``num_planes``)."""
    return max(1, min(num_planes, chunk_bytes() // max(1, bytes_per_plane)))


# --------------------------------------------------------------------------- peak memory

#: Resident memory of the Python process with torch and colmap_pvs imported, before any forward pass.
BASELINE_BYTES = 400 * 1024 * 1024
#: Allocator slack (fragmentation, the chunk temporaries' free lists) on top of the live tensors.
_SLACK = 1.15


def estimate_peak_memory(
    height: int, width: int, num_views: int, config: PVSNetConfig, *, batch: int = 1, dtype_bytes: int = 4
) -> int:
    """Estimated peak resident memory (bytes) of one inference forward pass of PVSNet on the CPU.

    Args:
        height, width: the input image size (before the network's padding to a multiple of 16).
        num_views: ``N``, reference included (``>= 2``).
        config: the model's :class:`~colmap_pvs.model.PVSNetConfig`.
        batch: ``B``.

    Counts the tensors alive at the largest of the feature, coarse and cascade phases of the chunked
    inference path (input images, the kept features, the stage's cost volume and its channels-last copy,
    the 3D U-Net's activations, the probability volume and the regression temporaries), plus the process
    baseline :data:`BASELINE_BYTES` and allocator slack. Calibrated against ``ru_maxrss`` (printed next to
    it by ``benchmarks/model_speed.py``); an upper bound within ~15 % for the shipped architecture.
    """
    if num_views < 2:
        raise ValueError(f"estimate_peak_memory: num_views must be >= 2, got {num_views}")
    if height < 1 or width < 1:
        raise ValueError(f"estimate_peak_memory: image size must be positive, got {width}x{height}")
    from .config import NETWORK_STRIDE

    cfg = config
    Hp = -(-height // NETWORK_STRIDE) * NETWORK_STRIDE
    Wp = -(-width // NETWORK_STRIDE) * NETWORK_STRIDE
    P = float(Hp * Wp)
    N = num_views
    levels = cfg.num_stages
    per_pixel = cfg.feature_channels[0] / 16.0
    if levels >= 2:
        per_pixel += cfg.feature_channels[1] / 4.0
    if levels >= 3:
        per_pixel += cfg.feature_channels[2]
    feats = N * per_pixel * P
    images = 3.0 * N * P  # the caller's images (kept), in floats
    always = feats + images + 2.0 * P  # + the sparse hints
    # Feature phase: the padded copy of all images and one image's full-resolution activations.
    phases = [images + 3.0 * N * P + feats + 6.0 * 8.0 * P]
    # Coarse stage (H/4): per-source cost + weighted and plain accumulators + visibility net, then the
    # aggregated volume, its channels-last copy, the ResNet/U-Net activations and three logit volumes.
    P0, D0 = P / 16.0, cfg.planes_per_stage[0]
    G0 = cfg.groups_per_stage[0]
    cv, c = cfg.visibility_channels, cfg.regularization_channels
    phases.append(always + D0 * P0 * max(4.0 * G0 + 2.5 * cv, 2.0 * G0 + 6.0 * c + 3.0))
    # Cascade stages: hypotheses, per-source weights, the aggregated volume and its channels-last copy,
    # the U-Net's activations (full and quarter volume), then the probability and regression temporaries.
    for k in range(1, levels):
        s = cfg.stage_scale(k)
        Pk, Dk = P / (s * s), cfg.planes_per_stage[k]
        Gk, ck = cfg.groups_per_stage[k], cfg.stage_channels[k - 1]
        volume = Dk * Pk * max(2.0 * Gk + 1.5 * ck + 1.0, Gk + 6.0)
        phases.append(always + volume + Pk * (Dk + 2.0 * (N - 1) + 4.0))
    live = batch * dtype_bytes * max(phases) + 4 * CHUNK_BYTES
    return int(BASELINE_BYTES + _SLACK * live)


def largest_size_within(
    height: int, width: int, num_views: int, config: PVSNetConfig, budget_bytes: int, *, batch: int = 1
) -> tuple[int, int]:
    """The largest ``(height, width)`` with the aspect ratio of the given size whose
    :func:`estimate_peak_memory` fits ``budget_bytes`` (``(0, 0)`` if not even 16 px fits)."""
    def fits(scale: float) -> bool:
        h, w = max(1, round(height * scale)), max(1, round(width * scale))
        return estimate_peak_memory(h, w, num_views, config, batch=batch) <= budget_bytes

    lo, hi = 0.0, 1.0
    if fits(hi):
        return height, width
    for _ in range(40):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    h, w = round(height * lo), round(width * lo)
    return (h, w) if min(h, w) >= 16 else (0, 0)


def default_memory_budget() -> int:
    """80 % of the memory available now (``MemAvailable`` in ``/proc/meminfo``, else of physical memory)."""
    try:
        for line in open("/proc/meminfo", encoding="ascii"):  # noqa: SIM115 - tiny read-only file
            if line.startswith("MemAvailable:"):
                return int(0.8 * int(line.split()[1]) * 1024)
    except OSError:
        pass
    try:
        return int(0.8 * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 16 * 1024**3


def check_memory_budget(
    height: int,
    width: int,
    num_views: int,
    config: PVSNetConfig,
    budget_bytes: int | None = None,
    *,
    batch: int = 1,
) -> int:
    """Raise :class:`~colmap_pvs.errors.MemoryBudgetError` before running a forward pass whose
    :func:`estimate_peak_memory` exceeds ``budget_bytes`` (default :func:`default_memory_budget`);
    the message names the largest ``max_image_size`` that fits. Returns the estimate otherwise."""
    budget = default_memory_budget() if budget_bytes is None else int(budget_bytes)
    need = estimate_peak_memory(height, width, num_views, config, batch=batch)
    if need <= budget:
        return need
    h, w = largest_size_within(height, width, num_views, config, budget, batch=batch)
    gib = 1024**3
    fix = (
        f"use max_image_size <= {max(h, w)} ({w}x{h}) or fewer views"
        if h
        else "no image size fits; free memory or use fewer views"
    )
    raise MemoryBudgetError(
        f"PVSNet at {width}x{height} with N={num_views} views needs ~{need / gib:.1f} GiB, over the "
        f"{budget / gib:.1f} GiB budget: {fix}"
    )
