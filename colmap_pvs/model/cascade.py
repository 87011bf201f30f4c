"""Depth regression, confidence and cascade hypothesis ranges (paper eq. 5 and sec. 3.4).

Hypotheses are described as in :mod:`.warping`: plane ``i`` has inverse depth
``inv_start - i * inv_step`` (``inv_start``/``inv_step`` broadcastable to ``[B, 1, h, w]``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F


@dataclass
class Regression:
    """Result of :func:`regress_inverse_depth` (all ``[B, h, w]`` except the ``[B, 1, h, w]`` moments)."""

    depth: torch.Tensor
    inv_mean: torch.Tensor
    inv_sigma: torch.Tensor
    index: torch.Tensor


def regress_inverse_depth(prob: torch.Tensor, inv_start: torch.Tensor, inv_step: torch.Tensor) -> Regression:
    """Inverse-depth regression (paper eq. 5): ``depth = 1 / sum_d P(d) / d_d``.

    Args:
        prob: ``[B, D, h, w]`` probability volume (softmax over ``D``).
        inv_start, inv_step: the hypotheses, broadcastable to ``[B, 1, h, w]``.

    Returns:
        :class:`Regression` with the depth ``[B, h, w]``, the mean and standard deviation of
        the inverse depth under ``prob`` (``[B, 1, h, w]``, used for the next stage's range)
        and the expected plane index ``[B, h, w]``.
    """
    D = prob.shape[1]
    idx = torch.arange(D, dtype=prob.dtype, device=prob.device).view(1, -1, 1, 1)
    e_idx = (prob * idx).sum(1, keepdim=True)
    e_idx2 = (prob * idx * idx).sum(1, keepdim=True)
    var_idx = (e_idx2 - e_idx * e_idx).clamp_min(0.0)
    inv_mean = inv_start - e_idx * inv_step
    inv_sigma = torch.sqrt(var_idx + 1e-12) * inv_step
    depth = 1.0 / inv_mean.clamp_min(1e-12)
    return Regression(depth=depth.squeeze(1), inv_mean=inv_mean, inv_sigma=inv_sigma, index=e_idx.squeeze(1))


def probability_confidence(prob: torch.Tensor, index: torch.Tensor, planes: int = 4) -> torch.Tensor:
    """Probability mass of the ``planes`` hypotheses nearest the expected index (MVSNet-style).

    ``prob`` ``[B, D, h, w]``, ``index`` ``[B, h, w]`` -> ``[B, h, w]`` in ``[0, 1]``. For
    ``planes=4`` the window is ``floor(index) - 1 ... floor(index) + 2``.
    """
    D = prob.shape[1]
    planes = min(planes, D)
    cs = F.pad(torch.cumsum(prob, 1), (0, 0, 0, 0, 1, 0))  # [B, D+1, h, w]
    start = torch.round(index.detach() - (planes - 1) / 2.0).long().clamp(0, D - planes).unsqueeze(1)
    mass = cs.gather(1, start + planes) - cs.gather(1, start)
    return mass.squeeze(1).clamp(0.0, 1.0)


def next_stage_range(
    inv_mean: torch.Tensor,
    inv_sigma: torch.Tensor,
    inv_step: torch.Tensor,
    size: tuple[int, int],
    num_planes: int,
    *,
    k: float,
    min_halfwidth_planes: float,
    inv_lo: torch.Tensor,
    inv_hi: torch.Tensor,
    neighbourhood: int = 0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel hypothesis range of the next (finer) stage (UCSNet-style uncertainty awareness).

    The range is ``mean +- max(k * sigma, min_halfwidth_planes * inv_step)`` in inverse depth,
    computed at the current resolution, bilinearly upsampled to ``size`` and moved (then
    clipped) inside ``[inv_lo, inv_hi] = [1/depth_max, 1/depth_min]`` (``[B]``). Gradients do
    not flow through the range.

    With ``neighbourhood = r > 0`` the range is widened (before upsampling) to also span the
    minimum and maximum of ``inv_mean`` within ``r`` pixels (Chebyshev), so that next to a depth
    edge the finer stage can still choose either side: a thin structure that the coarser stage
    merged with its background keeps both depths among its hypotheses. Away from edges the range
    is the same as with ``r = 0``.

    Returns ``(inv_start, inv_step)``, each ``[B, 1, *size]``.
    """
    inv_mean, inv_sigma = inv_mean.detach(), inv_sigma.detach()
    half = torch.maximum(k * inv_sigma, min_halfwidth_planes * inv_step.detach().expand_as(inv_sigma))
    if neighbourhood > 0:
        window, r = 2 * neighbourhood + 1, neighbourhood
        high = torch.maximum(F.max_pool2d(inv_mean, window, stride=1, padding=r), inv_mean + half)
        low = torch.minimum(-F.max_pool2d(-inv_mean, window, stride=1, padding=r), inv_mean - half)
        inv_mean, half = (high + low) / 2, (high - low) / 2
    center = F.interpolate(inv_mean, size=size, mode="bilinear", align_corners=False)
    half = F.interpolate(half, size=size, mode="bilinear", align_corners=False)
    lo_b, hi_b = inv_lo.view(-1, 1, 1, 1), inv_hi.view(-1, 1, 1, 1)
    half = torch.minimum(half, (hi_b - lo_b) / 2)
    center = torch.maximum(torch.minimum(center, hi_b - half), lo_b + half)
    inv_start = center + half
    step = (2.0 * half / (num_planes - 1)).clamp_min(1e-12)
    return inv_start, step


def prior_halfwidth_map(
    hint: torch.Tensor, halfwidth: float, growth: float, radii: tuple[int, ...]
) -> torch.Tensor:
    """Per-pixel relative half-width of the sparse prior's window, wider far from every hint.

    The push-pull prior is an average of distant hints where no hint is near, and there it is
    often wrong (a near object at the image border between far points): the window widens.

    Args:
        hint: ``[B, 1, h, w]`` sparse depth at the coarse resolution (0 = no hint).
        halfwidth: ``r0``, the half-width near hints.
        growth: ``g``; a pixel with no hint within ``k`` of the ``radii`` (pixels, Chebyshev
            distance) gets ``r0 * g**k``, with ``k`` box-blurred over ``2 min(radii) + 1`` pixels
            (so the window widens gradually; far inside a region ``k`` is exact).

    Returns ``[B, 1, h, w]``; all ``r0`` when ``g == 1``.
    """
    has = (hint > 0).to(hint.dtype)
    misses = torch.zeros_like(has)
    if growth != 1.0 and radii:
        for radius in radii:
            misses = misses + (F.max_pool2d(has, 2 * radius + 1, stride=1, padding=radius) <= 0).to(has.dtype)
        # A box blur over the smallest radius turns the square steps of the count into ramps: a
        # step in the window shows as a step in the depth.
        r = min(radii)
        misses = F.avg_pool2d(misses, 2 * r + 1, stride=1, padding=r, count_include_pad=False)
    return halfwidth * growth**misses


def prior_plane_range(
    prior_inv: torch.Tensor,
    halfwidth: float | torch.Tensor,
    num_planes: int,
    *,
    inv_lo: torch.Tensor,
    inv_hi: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel coarse hypotheses around a dense inverse-depth prior.

    Args:
        prior_inv: ``[B, 1, h, w]`` prior inverse depth (0 = none: that pixel gets the global range).
        halfwidth: relative half-width ``r`` (a number, or per pixel ``[B, 1, h, w]``, see
            :func:`prior_halfwidth_map`): planes span ``prior_inv * (1 +- r)``, moved (then
            clipped) inside ``[inv_lo, inv_hi]`` (``[B]``).

    Returns ``(inv_start, inv_step)``, each ``[B, 1, h, w]``.
    """
    lo_b, hi_b = inv_lo.view(-1, 1, 1, 1), inv_hi.view(-1, 1, 1, 1)
    full = (hi_b - lo_b) / 2
    has = prior_inv > 0
    half = torch.where(has, torch.minimum(halfwidth * prior_inv, full), full.expand_as(prior_inv))
    center = torch.where(has, prior_inv, (hi_b + lo_b).expand_as(prior_inv) / 2)
    center = torch.maximum(torch.minimum(center, hi_b - half), lo_b + half)
    inv_start = center + half
    step = (2.0 * half / (num_planes - 1)).clamp_min(1e-12)
    return inv_start, step
