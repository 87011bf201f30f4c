"""Two-view matching volumes (group-wise correlation) and sparse-depth guidance."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..errors import ShapeError


def group_correlation(
    ref: torch.Tensor,
    warped: torch.Tensor,
    groups: int,
    *,
    pixel_weight: torch.Tensor | float | None = None,
    accumulate: torch.Tensor | None = None,
) -> torch.Tensor:
    """Group-wise correlation (Guo et al. 2019; paper sec. 3.2).

    Args:
        ref: ``[B, C, h, w]`` reference features.
        warped: ``[B, C, D, h, w]`` source features warped onto the ``D`` hypotheses.
        groups: ``G``, must divide ``C``.
        pixel_weight: optional ``[B, 1, h, w]`` (or scalar) factor applied to the result (folded into ``ref``,
            which is cheaper than weighting the volume).
        accumulate: optional ``[B, G, D, h, w]`` contiguous volume the result is added to (in place).

    Returns:
        ``[B, G, D, h, w]`` (contiguous): the mean over each group's ``C/G`` channels of
        ``ref * warped`` (times ``pixel_weight``, plus ``accumulate``). Under
        ``torch.no_grad``/``inference_mode`` ``warped`` may be overwritten.
    """
    B, C, D, h, w = warped.shape
    if C % groups:
        raise ShapeError(f"group_correlation: {groups} groups do not divide {C} channels")
    if ref.shape != (B, C, h, w):
        raise ShapeError(
            f"group_correlation: ref {tuple(ref.shape)} does not match warped {tuple(warped.shape)}"
        )
    r = correlation_reference(ref, groups, pixel_weight)
    wv = warped.contiguous().view(B, groups, C // groups, D, h, w)
    if accumulate is None and C == groups and not torch.is_grad_enabled():
        return wv[:, :, 0].mul_(r[:, :, 0]).contiguous()
    if accumulate is None:
        accumulate = wv[:, :, 0] * r[:, :, 0]
        return _correlate(r, wv, accumulate, start=1)
    return _correlate(r, wv, accumulate, start=0)


def correlation_reference(
    ref: torch.Tensor, groups: int, pixel_weight: torch.Tensor | float | None = None
) -> torch.Tensor:
    """The reference side of :func:`group_correlation`: ``[B, C, h, w] -> [B, G, C/G, 1, h, w]``
    (contiguous), ``ref * pixel_weight / (C/G)``."""
    B, C, h, w = ref.shape
    if C % groups:
        raise ShapeError(f"group_correlation: {groups} groups do not divide {C} channels")
    per = C // groups
    scale = ref * (1.0 / per) if pixel_weight is None else ref * (pixel_weight * (1.0 / per))
    # Contiguous operands: the broadcast then runs over outer dimensions only (fast on CPU).
    return scale.contiguous().view(B, groups, per, 1, h, w)


def correlate_into(
    r: torch.Tensor, warped: torch.Tensor, out: torch.Tensor, *, accumulate: bool
) -> torch.Tensor:
    """Write (or, with ``accumulate``, add) the group-wise correlation into ``out`` ``[B, G, D, h, w]``
    (any strides, e.g. a slice of planes of a larger volume) and return it.

    ``r`` ``[B, G, P, 1, h, w]`` from :func:`correlation_reference`, ``warped`` ``[B, G * P, D, h, w]``.
    """
    B, G, P, _, h, w = r.shape
    D = warped.shape[2]
    if warped.shape != (B, G * P, D, h, w) or out.shape != (B, G, D, h, w):
        raise ShapeError(
            f"correlate_into: reference {tuple(r.shape)}, warped {tuple(warped.shape)}, "
            f"out {tuple(out.shape)}"
        )
    wv = warped.contiguous().view(B, G, P, D, h, w)
    if accumulate:
        return _correlate(r, wv, out, start=0)
    torch.mul(wv[:, :, 0], r[:, :, 0], out=out)
    return _correlate(r, wv, out, start=1)


def _correlate(r: torch.Tensor, wv: torch.Tensor, out: torch.Tensor, start: int) -> torch.Tensor:
    """``out += sum_{j >= start} wv[:, :, j] * r[:, :, j]`` in place (``wv`` ``[B, G, P, D, h, w]``)."""
    for j in range(start, wv.shape[2]):
        out.addcmul_(wv[:, :, j], r[:, :, j])
    return out


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


def densify_inverse_depth(hint: torch.Tensor) -> torch.Tensor:
    """Dense inverse-depth prior from sparse depth hints by push-pull interpolation.

    Args:
        hint: ``[B, 1, h, w]`` sparse depth (0 = no hint).

    Returns:
        ``[B, 1, h, w]`` inverse depth: the hint's where there is one, elsewhere a smooth fill
        from a pyramid of hint averages (each level averages the hints of 2x2 blocks of the
        level below; a pixel takes its own level's average where that level has a hint and the
        bilinearly upsampled coarser estimate elsewhere). All 0 for an image without hints.
    """
    inv = torch.where(hint > 0, 1.0 / hint.clamp_min(1e-12), torch.zeros_like(hint))
    sums, counts = [inv], [(hint > 0).to(inv.dtype)]
    while max(sums[-1].shape[-2:]) > 1:
        sums.append(F.avg_pool2d(sums[-1], 2, ceil_mode=True) * 4.0)
        counts.append(F.avg_pool2d(counts[-1], 2, ceil_mode=True) * 4.0)
    est = sums[-1] / counts[-1].clamp_min(1e-12)
    for s, n in zip(reversed(sums[:-1]), reversed(counts[:-1]), strict=True):
        up = F.interpolate(est, size=s.shape[-2:], mode="bilinear", align_corners=False)
        own = s / n.clamp_min(1e-12)
        c = n.clamp(0.0, 1.0)
        est = c * own + (1.0 - c) * up
    return est


def guidance_weights(
    hint: torch.Tensor,
    inv_start: torch.Tensor,
    inv_step: torch.Tensor,
    num_planes: int,
    k: float,
    c: float,
    *,
    log: bool = False,
) -> torch.Tensor:
    """Guided-matching modulation (Poggi et al., "Guided Stereo Matching", CVPR 2019).

    Args:
        hint: ``[B, 1, h, w]`` sparse depth at this stage's resolution, 0 = no hint.
        inv_start, inv_step: the hypotheses (see :mod:`.warping`), broadcastable to ``[B, 1, h, w]``.
        log: return the natural log of the factors instead (exact, no underflow far from the hint).

    Returns:
        ``[B, D, h, w]`` factors ``1 - v + v * k * exp(-(x - x*)^2 / (2 c^2))``, ``x`` the plane index
        and ``x*`` the hint's (continuous) plane index, both in units of this stage's inverse-depth
        spacing. ``v = 1`` at pixels with a hint whose ``x*`` lies within ``3c`` of the stage's
        hypothesis range, 0 elsewhere (factor 1): a hint the stage cannot represent is ignored
        rather than wiping out the matching volume.
    """
    inv_hint = torch.where(hint > 0, 1.0 / hint.clamp_min(1e-12), torch.zeros_like(hint))
    x_star = (inv_start - inv_hint) / inv_step  # [B, 1, h, w]
    on = (hint > 0) & (x_star >= -3.0 * c) & (x_star <= num_planes - 1 + 3.0 * c)
    x = torch.arange(num_planes, dtype=hint.dtype, device=hint.device).view(1, -1, 1, 1)
    sq = -((x - x_star) ** 2) / (2.0 * c * c)
    if log:
        return torch.where(on, math.log(k) + sq, torch.zeros_like(sq))
    return torch.where(on, k * torch.exp(sq), torch.ones_like(sq))
