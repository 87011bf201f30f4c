"""Two-view matching volumes (group-wise correlation) and sparse-depth guidance."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..errors import ShapeError


def group_correlation(ref: torch.Tensor, warped: torch.Tensor, groups: int) -> torch.Tensor:
    """Group-wise correlation (Guo et al. 2019; paper sec. 3.2).

    Args:
        ref: ``[B, C, h, w]`` reference features.
        warped: ``[B, C, D, h, w]`` source features warped onto the ``D`` hypotheses.
        groups: ``G``, must divide ``C``.

    Returns:
        ``[B, G, D, h, w]``: the mean over each group's ``C/G`` channels of ``ref * warped``.
        Under ``torch.no_grad``/``inference_mode`` ``warped`` is overwritten (saves memory).
    """
    B, C, D, h, w = warped.shape
    if C % groups:
        raise ShapeError(f"group_correlation: {groups} groups do not divide {C} channels")
    if ref.shape != (B, C, h, w):
        raise ShapeError(
            f"group_correlation: ref {tuple(ref.shape)} does not match warped {tuple(warped.shape)}"
        )
    r = ref.view(B, groups, C // groups, 1, h, w)
    if torch.is_grad_enabled():
        prod = warped.view(B, groups, C // groups, D, h, w) * r
    else:
        prod = warped.view(B, groups, C // groups, D, h, w).mul_(r)
    return prod.mean(2)


def downsample_sparse_depth(sparse_depth: torch.Tensor, scale: int) -> torch.Tensor:
    """Sparse depth hints ``[B, 1, H, W]`` (0 = none) -> ``[B, 1, H/scale, W/scale]``.

    Each ``scale x scale`` block keeps its *nearest* hint (max-pool of inverse depth), so
    occluders win over the background; blocks without a hint stay 0.
    """
    if scale == 1:
        return sparse_depth
    inv = torch.where(sparse_depth > 0, 1.0 / sparse_depth.clamp_min(1e-12), torch.zeros_like(sparse_depth))
    inv = F.max_pool2d(inv, scale)
    return torch.where(inv > 0, 1.0 / inv.clamp_min(1e-12), torch.zeros_like(inv))


def guidance_weights(
    hint: torch.Tensor,
    inv_start: torch.Tensor,
    inv_step: torch.Tensor,
    num_planes: int,
    k: float,
    c: float,
) -> torch.Tensor:
    """Guided-matching modulation (Poggi et al., "Guided Stereo Matching", CVPR 2019).

    Args:
        hint: ``[B, 1, h, w]`` sparse depth at this stage's resolution, 0 = no hint.
        inv_start, inv_step: the hypotheses (see :mod:`.warping`), broadcastable to ``[B, 1, h, w]``.

    Returns:
        ``[B, D, h, w]`` factors ``1 - v + v * k * exp(-(x - x*)^2 / (2 c^2))`` with ``v = 1`` at
        hinted pixels (0 elsewhere, giving factor 1), ``x`` the plane index and ``x*`` the hint's
        (continuous) plane index, both in units of this stage's inverse-depth spacing.
    """
    v = (hint > 0).to(hint.dtype)
    inv_hint = torch.where(hint > 0, 1.0 / hint.clamp_min(1e-12), torch.zeros_like(hint))
    x_star = (inv_start - inv_hint) / inv_step  # [B, 1, h, w]
    x = torch.arange(num_planes, dtype=hint.dtype, device=hint.device).view(1, -1, 1, 1)
    gauss = torch.exp(-((x - x_star) ** 2) / (2.0 * c * c))
    return 1.0 - v + v * k * gauss
