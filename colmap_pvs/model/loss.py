"""Multi-output masked L1 depth loss (paper eq. 6-7) and ground-truth downsampling."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..errors import ShapeError
from .pvsnet import PVSNetOutput


def downsample_depth(depth: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Ground-truth depth ``[B, H, W]`` (0 = invalid) -> ``[B, *size]`` with ``size = ceil(H/s), ceil(W/s)``.

    Takes the pixel ``(s*row + s//2, s*col + s//2)`` of each ``s x s`` block (nearest to the coarse pixel
    centre, no mixing across depth edges). ``s`` is ``H // size[0]`` rounded.
    """
    B, H, W = depth.shape
    if (H, W) == tuple(size):
        return depth
    s = max(1, round(H / size[0]))
    Hp, Wp = size[0] * s, size[1] * s
    padded = F.pad(depth, (0, max(0, Wp - W), 0, max(0, Hp - H)))
    return padded[:, s // 2 :: s, s // 2 :: s][:, : size[0], : size[1]]


def masked_l1(
    pred: torch.Tensor, gt: torch.Tensor, depth_min: torch.Tensor, depth_max: torch.Tensor
) -> torch.Tensor:
    """Mean ``|pred - gt| / (depth_max - depth_min)`` over pixels with ``gt > 0`` (``[B, h, w]`` each).

    Returns 0 (with a graph) when no pixel is valid.
    """
    if pred.shape != gt.shape:
        raise ShapeError(f"masked_l1: pred {list(pred.shape)} and gt {list(gt.shape)} differ")
    mask = gt > 0
    scale = (depth_max - depth_min).view(-1, 1, 1)
    err = (pred - gt).abs() / scale
    n = mask.sum()
    return torch.where(mask, err, torch.zeros_like(err)).sum() / n.clamp_min(1)


def pvsnet_loss(
    out: PVSNetOutput,
    depth_gt: torch.Tensor,
    depth_min: torch.Tensor,
    depth_max: torch.Tensor,
    loss_weights: tuple[float, ...],
) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """``sum_k lambda_k * masked_l1(depths[k], gt downsampled to that size)``.

    ``depth_gt`` ``[B, H, W]`` full resolution (0 = invalid). Returns ``(total, per_output)``.
    """
    if len(loss_weights) != len(out.depths):
        raise ShapeError(f"pvsnet_loss: {len(loss_weights)} loss weights for {len(out.depths)} outputs")
    terms = []
    for pred in out.depths:
        gt = downsample_depth(depth_gt, tuple(pred.shape[-2:]))
        terms.append(masked_l1(pred, gt, depth_min, depth_max))
    total = sum(w * t for w, t in zip(loss_weights, terms, strict=True))
    return total, terms
