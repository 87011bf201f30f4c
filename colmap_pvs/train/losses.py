"""Training losses and depth metrics for PVSNet.

The loss is the paper's (Xu & Tao 2020, eq. 6-7): a masked L1 depth loss on every
output of the network, i.e. the three coarse outputs at ``H/4`` (ResNet, U-Net 1,
U-Net 2) and every cascade stage up to full resolution, combined with the weights
``lambda_0 .. lambda_k`` (``PVSNetConfig.loss_weights``)::

    L = sum_k  lambda_k * mean_{valid p} |d_k(p) - d_gt,k(p)| / s

where ``s`` is ``1`` (``normalize="none"``, the paper's raw L1 in scene units) or the
per-sample depth range ``depth_max - depth_min`` (``normalize="range"``, our default: it
makes the loss scale-free, so synthetic scenes in metres and DTU in millimetres give
comparable numbers).

Ground truth at a coarser output resolution
-------------------------------------------
The full-resolution GT depth ``[B, H, W]`` is brought to each output's ``[h, w]`` by

- ``"min"`` (default): every output pixel takes the **minimum valid** GT depth of its
  ``f x f`` block (``f`` = the output's stride, 4 / 2; invalid pixels, depth ``0``, are
  ignored; a block with no valid pixel stays invalid). The block is centred exactly on
  the output pixel centre (pixel-centre convention of ``docs/CONVENTIONS.md``), every GT
  pixel is used once, and the minimum is the front-most surface, the one visible at a
  depth edge, so no depth between two surfaces is ever invented.
- ``"nearest"``: the GT pixel nearest to the output pixel centre (for even ``f`` the one
  just below-right of it), as the network's nearest-neighbour downsampling does.

Sizes that are not ``ceil(H / f)`` for an integer ``f`` fall back to nearest resampling.
Images whose size is not a multiple of the stride are handled like the network does:
the GT is zero-padded (invalid) bottom/right before the blocks are formed.

Validity
--------
A GT pixel is valid when its depth is ``> 0`` (and finite) and, with
``mask_depth_range=True``, inside ``[depth_min, depth_max]`` of its sample.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F

from ..errors import ShapeError

GTDownsample = Literal["min", "nearest"]
LossNormalize = Literal["range", "none"]

#: Relative-error thresholds of the ``pct_rel_*`` metrics.
REL_THRESHOLDS = (0.01, 0.02, 0.05)


def _check_depth(name: str, depth: torch.Tensor) -> None:
    if depth.dim() != 3:
        raise ShapeError(f"{name} must be [B, H, W], got shape {tuple(depth.shape)}")


def _block_factor(full: int, small: int, factor: int | None) -> int | None:
    """Integer ``f`` with ``ceil(full / f) == small`` (the network's padded stride), else ``None``."""
    f = factor if factor is not None else -(-full // small)
    return f if f >= 1 and -(-full // f) == small else None


def downsample_depth(
    depth: torch.Tensor, size: tuple[int, int], mode: GTDownsample = "min", factor: int | None = None
) -> torch.Tensor:
    """GT depth ``[B, H, W]`` brought to ``size = (h, w)``; ``0`` stays "invalid".

    When ``h = ceil(H / f)`` and ``w = ceil(W / g)`` for integers ``f, g`` (PVSNet's outputs,
    computed on the image padded bottom/right to a multiple of its stride), the GT is
    zero-padded the same way and reduced per ``f x g`` block: ``"min"`` takes the minimum
    valid depth, ``"nearest"`` the pixel ``(f*row + f//2, g*col + g//2)``, nearest to the
    block centre (the same pixel as the network's nearest-neighbour downsampling). Other sizes
    use ``F.interpolate(mode="nearest-exact")``. ``factor`` is the output's stride ``f = g``
    (``PVSNetConfig.output_scales``); without it ``f = ceil(H / h)``, ``g = ceil(W / w)``,
    exact when the image size is a multiple of the stride. Returns ``depth`` itself when
    the size already matches.
    """
    _check_depth("depth", depth)
    b, H, W = depth.shape
    h, w = int(size[0]), int(size[1])
    if (h, w) == (H, W):
        return depth
    if h <= 0 or w <= 0 or h > H or w > W:
        raise ShapeError(f"cannot downsample GT depth of size {(H, W)} to {(h, w)}")
    if mode not in ("min", "nearest"):
        raise ValueError(f"unknown GT downsampling mode {mode!r}; expected 'min' or 'nearest'")
    valid = torch.isfinite(depth) & (depth > 0)
    clean = torch.where(valid, depth, torch.zeros_like(depth))
    fy, fx = _block_factor(H, h, factor), _block_factor(W, w, factor)
    if fy is None or fx is None:
        if factor is not None:
            raise ShapeError(f"output size {(h, w)} is not ceil({(H, W)} / {factor})")
        return F.interpolate(clean[:, None], size=(h, w), mode="nearest-exact")[:, 0]
    padded = F.pad(clean, (0, w * fx - W, 0, h * fy - H))
    if mode == "nearest":
        return padded[:, fy // 2 :: fy, fx // 2 :: fx].contiguous()
    big = torch.finfo(depth.dtype).max
    filled = torch.where(padded > 0, padded, torch.full_like(padded, big))
    out = -F.max_pool2d(-filled[:, None], kernel_size=(fy, fx), stride=(fy, fx))[:, 0]
    return torch.where(out < big, out, torch.zeros_like(out))


def valid_mask(
    gt: torch.Tensor,
    depth_min: torch.Tensor | None = None,
    depth_max: torch.Tensor | None = None,
) -> torch.Tensor:
    """Boolean ``[B, h, w]``: GT finite, ``> 0`` and (when given) in ``[depth_min, depth_max]`` (``[B]``)."""
    _check_depth("gt", gt)
    mask = torch.isfinite(gt) & (gt > 0)
    if depth_min is not None:
        mask &= gt >= depth_min.reshape(-1, 1, 1).to(gt)
    if depth_max is not None:
        mask &= gt <= depth_max.reshape(-1, 1, 1).to(gt)
    return mask


@dataclass(frozen=True)
class DepthLoss:
    """The weighted loss and its parts.

    Attributes:
        total: scalar tensor (with graph), ``sum_k weights[k] * per_output[k]``.
        per_output: ``[K]`` detached tensor, the unweighted masked L1 of each output.
        valid_fraction: ``[K]`` detached tensor, fraction of valid GT pixels per output.
    """

    total: torch.Tensor
    per_output: torch.Tensor
    valid_fraction: torch.Tensor


def _prepare(
    depths: Sequence[torch.Tensor],
    gt: torch.Tensor,
    weights: Sequence[float] | None,
) -> None:
    _check_depth("gt", gt)
    if len(depths) == 0:
        raise ValueError("got no depth outputs")
    if weights is not None and len(weights) != len(depths):
        raise ValueError(
            f"got {len(depths)} depth outputs but {len(weights)} loss weights {tuple(weights)}; "
            "PVSNetConfig.loss_weights must have one weight per output"
        )
    for k, d in enumerate(depths):
        _check_depth(f"depths[{k}]", d)
        if d.shape[0] != gt.shape[0]:
            raise ShapeError(f"depths[{k}] has batch size {d.shape[0]}, GT has {gt.shape[0]}")


def depth_loss(
    depths: Sequence[torch.Tensor],
    gt: torch.Tensor,
    depth_min: torch.Tensor,
    depth_max: torch.Tensor,
    weights: Sequence[float],
    *,
    gt_downsample: GTDownsample = "min",
    normalize: LossNormalize = "range",
    mask_depth_range: bool = True,
    scales: Sequence[int] | None = None,
) -> DepthLoss:
    """Weighted masked L1 over all outputs (paper eq. 6-7).

    Args:
        depths: ``K`` predicted depth maps ``[B, h_k, w_k]`` (``PVSNetOutput.depths``).
        gt: ``[B, H, W]`` GT reference depth at full resolution, ``0`` = invalid.
        depth_min, depth_max: ``[B]`` depth range of each sample.
        weights: ``K`` loss weights ``lambda_k``.
        gt_downsample: ``"min"`` or ``"nearest"`` (module docstring).
        normalize: ``"range"`` divides the error by ``depth_max - depth_min``; ``"none"``
            keeps scene units.
        mask_depth_range: also mask GT outside ``[depth_min, depth_max]``.
        scales: stride of each output (``PVSNetConfig.output_scales``); inferred when ``None``.

    Returns:
        A :class:`DepthLoss`. An output with no valid pixel contributes ``0`` (with a graph).
    """
    _prepare(depths, gt, weights)
    depth_min = depth_min.reshape(-1).to(gt)
    depth_max = depth_max.reshape(-1).to(gt)
    if normalize == "range":
        scale = (depth_max - depth_min).clamp_min(torch.finfo(gt.dtype).eps)
    elif normalize == "none":
        scale = torch.ones_like(depth_min)
    else:
        raise ValueError(f"unknown loss normalisation {normalize!r}; expected 'range' or 'none'")
    total = depths[0].new_zeros(())
    parts, fractions = [], []
    scales = [None] * len(depths) if scales is None else list(scales)
    if len(scales) != len(depths):
        raise ValueError(f"got {len(depths)} depth outputs but {len(scales)} scales {tuple(scales)}")
    for d, w, f in zip(depths, weights, scales, strict=True):
        g = downsample_depth(gt, (d.shape[1], d.shape[2]), gt_downsample, f)
        m = valid_mask(g, depth_min if mask_depth_range else None, depth_max if mask_depth_range else None)
        err = (d - g).abs() / scale.reshape(-1, 1, 1)
        n = m.sum()
        part = torch.where(m, err, torch.zeros_like(err)).sum() / n.clamp_min(1)
        total = total + float(w) * part
        parts.append(part.detach())
        fractions.append(m.float().mean())
    return DepthLoss(total=total, per_output=torch.stack(parts), valid_fraction=torch.stack(fractions))


def depth_metrics(
    depth: torch.Tensor,
    gt: torch.Tensor,
    *,
    depth_min: torch.Tensor | None = None,
    depth_max: torch.Tensor | None = None,
    gt_downsample: GTDownsample = "min",
    factor: int | None = None,
) -> dict[str, float]:
    """Error metrics of one prediction ``[B, h, w]`` against full-resolution GT ``[B, H, W]``.

    Returns a dict of floats over all valid pixels of the batch (the GT is brought to the
    prediction's size as in :func:`depth_loss`):

    - ``mae``: mean absolute error in scene units;
    - ``absrel``: mean of ``|d - gt| / gt``;
    - ``pct_rel_1``, ``pct_rel_2``, ``pct_rel_5``: percentage (0-100) of pixels with relative
      error under 1, 2 and 5 %;
    - ``valid``: number of valid pixels (all metrics are ``nan`` when it is 0).
    """
    _check_depth("depth", depth)
    g = downsample_depth(gt, (depth.shape[1], depth.shape[2]), gt_downsample, factor)
    m = valid_mask(g, depth_min, depth_max)
    n = int(m.sum())
    out = {"valid": float(n)}
    names = ("mae", "absrel") + tuple(f"pct_rel_{round(t * 100)}" for t in REL_THRESHOLDS)
    if n == 0:
        out.update({k: float("nan") for k in names})
        return out
    d, gv = depth.detach()[m].double(), g[m].double()
    abs_err = (d - gv).abs()
    rel = abs_err / gv
    out["mae"] = float(abs_err.mean())
    out["absrel"] = float(rel.mean())
    for t in REL_THRESHOLDS:
        out[f"pct_rel_{round(t * 100)}"] = float((rel < t).double().mean() * 100.0)
    return out


def output_metrics(
    depths: Sequence[torch.Tensor],
    gt: torch.Tensor,
    depth_min: torch.Tensor | None = None,
    depth_max: torch.Tensor | None = None,
    *,
    gt_downsample: GTDownsample = "min",
    scales: Sequence[int] | None = None,
) -> dict[str, float]:
    """:func:`depth_metrics` of every output, flattened as ``"out{k}_{metric}"``."""
    _prepare(depths, gt, None)
    result: dict[str, float] = {}
    for k, d in enumerate(depths):
        f = None if scales is None else scales[k]
        for name, value in depth_metrics(
            d, gt, depth_min=depth_min, depth_max=depth_max, gt_downsample=gt_downsample, factor=f
        ).items():
            result[f"out{k}_{name}"] = value
    return result
