"""Two-view matching volumes (group-wise correlation) and sparse-depth guidance."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..errors import ShapeError
from .runtime import exporting
from .warping import adjugate3x3


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


def _gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of ``[B, C, h, w]``, zero padding, kernel peak 1 (a weighted sum)."""
    r = max(1, int(math.ceil(3.0 * sigma)))
    t = torch.arange(-r, r + 1, dtype=x.dtype, device=x.device)
    k = torch.exp(-(t * t) / (2.0 * sigma * sigma))
    c = x.shape[1]
    x = F.conv2d(F.pad(x, (r, r, 0, 0)), k.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return F.conv2d(F.pad(x, (0, 0, r, r)), k.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def _pool_factor(sigma: float) -> int:
    """The largest power of 2 not above ``sigma / 2``: the grid step at which scale ``sigma`` is computed."""
    f = 1
    while 2 * f <= sigma / 2.0:
        f *= 2
    return f


def _blurred_sums(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """:func:`_gaussian_blur` of sums ``[B, C, h, w]``, computed on a grid pooled by ``f ~ sigma / 2``.

    Pooled cells hold exact sums; the kernel in cell units is ``sigma / f``, so the result keeps the
    scale of a full-resolution blur (bilinear back to ``h x w``) at a fraction of the cost.
    """
    f = _pool_factor(sigma)
    if f == 1:
        return _gaussian_blur(x, sigma)
    h, w = x.shape[-2:]
    hp, wp = -(-h // f) * f, -(-w // f) * f
    pooled = F.avg_pool2d(F.pad(x, (0, wp - w, 0, hp - h)), f) * float(f * f)
    blurred = _gaussian_blur(pooled, sigma / f)
    return F.interpolate(blurred, size=(hp, wp), mode="bilinear", align_corners=False)[..., :h, :w]


def _box_max(x: torch.Tensor, r: int, f: int = 1) -> torch.Tensor:
    """Maximum over the ``(2r+1)^2`` box around each pixel of ``[B, C, h, w]`` (separable).

    With ``f > 1`` it is taken on ``f x f`` cells (the box grows by up to ``f - 1`` pixels a side).
    """
    h, w = x.shape[-2:]
    if f > 1:
        hp, wp = -(-h // f) * f, -(-w // f) * f
        x = F.max_pool2d(F.pad(x, (0, wp - w, 0, hp - h), value=float("-inf")), f)
        r = -(-r // f)
    x = F.max_pool2d(x, (1, 2 * r + 1), stride=1, padding=(0, r))
    x = F.max_pool2d(x, (2 * r + 1, 1), stride=1, padding=(r, 0))
    if f > 1:
        x = x.repeat_interleave(f, -2).repeat_interleave(f, -1)[..., :h, :w]
    return x


def _solve3x3(A: torch.Tensor, rhs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``torch.linalg.solve_ex(A, rhs)`` for ``[..., 3, 3]`` systems; when exporting, Cramer's rule (no ONNX
    op solves a linear system): the same solution up to rounding, ``info`` nonzero where ``det(A) == 0``."""
    if not exporting():
        return torch.linalg.solve_ex(A, rhs)
    batch = A.shape[:-2]
    adj, det = adjugate3x3(A.reshape(-1, 3, 3))
    sol = (adj @ rhs.reshape(-1, 3, 1)) / det.view(-1, 1, 1)
    return sol.view(*batch, 3, 1), (det == 0).to(torch.int32).view(batch)


def affine_fill_inverse_depth(
    hint: torch.Tensor,
    sigmas: tuple[float, ...] = (2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0),
    min_weight: float = 3.0,
    slope_damping: float = 0.01,
) -> torch.Tensor:
    """Dense inverse-depth prior from sparse hints by a local affine fit (moving least squares).

    Each pixel fits ``a + b x + c y`` to the hints' inverse depths with Gaussian weights around it,
    at the smallest scale of ``sigmas`` whose summed weight reaches ``min_weight`` (about that many
    hints within one sigma); between ``min_weight / 2`` and ``min_weight`` a scale's fit is blended
    with the coarser scales' result, so the prior has no steps where the scale changes. Inverse
    depth is affine in the image on a plane, so a wall between hints is filled exactly, where an
    average of the hints (push-pull) is off by its slope. The slopes are damped by
    ``slope_damping * weight * sigma**2`` so that one or two hints give a near-constant fit. The
    fit is clipped to the range ``[lo, hi]`` of the hints within about ``3 sigma``, widened by a
    quarter of ``hi - lo`` on each side, so that an extrapolation (to the image border, or across
    a depth edge) stays near the depths its hints span (the quarter is measured in
    ``benchmarks/RESULTS.md``). Pixels that no scale reaches (and fits that are not
    positive) take :func:`densify_inverse_depth` (where the image has hints at all). The hints
    themselves are smoothed like every other pixel (SfM points are noisy). Scales of 4 pixels and
    more are computed on a grid pooled by about ``sigma / 2`` (:func:`_blurred_sums`).

    Args:
        hint: ``[B, 1, h, w]`` sparse depth (0 = no hint).

    Returns:
        ``[B, 1, h, w]`` inverse depth; all 0 for an image without hints.
    """
    if hint.dim() != 4 or hint.shape[1] != 1:
        raise ShapeError(f"hint must be [B, 1, h, w], got {tuple(hint.shape)}")
    fallback = densify_inverse_depth(hint)
    B, _, h, w = hint.shape
    m = (hint > 0).to(hint.dtype)
    z = torch.where(hint > 0, 1.0 / hint.clamp_min(1e-12), torch.zeros_like(hint))
    # Coordinates centred on the image and scaled to ~[-1, 1] keep the moments well conditioned.
    scale = float(max(h, w)) / 2.0
    ys = (torch.arange(h, dtype=hint.dtype, device=hint.device) - (h - 1) / 2.0) / scale
    xs = (torch.arange(w, dtype=hint.dtype, device=hint.device) - (w - 1) / 2.0) / scale
    Y, X = torch.meshgrid(ys, xs, indexing="ij")
    X, Y = X.expand(B, 1, h, w), Y.expand(B, 1, h, w)
    big = torch.finfo(hint.dtype).max
    eye = torch.eye(3, dtype=hint.dtype, device=hint.device)
    moments = [m, m * X, m * Y, m * X * X, m * X * Y, m * Y * Y, m * z, m * X * z, m * Y * z]
    moments = torch.cat(moments, 1)
    x0, y0 = X[:, 0], Y[:, 0]
    fits, alphas = [], []
    for sigma in sigmas:
        mom = _blurred_sums(moments, sigma)
        S, Sx, Sy, Sxx, Sxy, Syy, Sz, Sxz, Syz = mom.unbind(1)
        # Moments about the pixel itself: the fit's constant term is then its value there.
        a12, a13 = Sx - x0 * S, Sy - y0 * S
        a22 = Sxx - 2 * x0 * Sx + x0 * x0 * S
        a23 = Sxy - x0 * Sy - y0 * Sx + x0 * y0 * S
        a33 = Syy - 2 * y0 * Sy + y0 * y0 * S
        lam = (slope_damping * S + 1e-6) * (sigma / scale) ** 2
        A = torch.stack([S, a12, a13, a12, a22 + lam, a23, a13, a23, a33 + lam], -1).view(B, h, w, 3, 3)
        rhs = torch.stack([Sz, Sxz - x0 * Sz, Syz - y0 * Sz], -1).unsqueeze(-1)
        sol, info = _solve3x3(A + 1e-12 * eye, rhs)
        fit = sol[..., 0, 0].unsqueeze(1)
        r = max(1, int(math.ceil(3.0 * sigma)))
        f = _pool_factor(sigma)
        hi = _box_max(torch.where(m > 0, z, torch.zeros_like(z)), r, f)
        lo = -_box_max(torch.where(m > 0, -z, torch.full_like(z, -big)), r, f)
        span = 0.25 * (hi - lo).clamp_min(0.0)
        fit = torch.minimum(torch.maximum(fit, lo - span), hi + span)
        # The weight ramps from 0 at min_weight / 2 to 1 at min_weight: scales hand over smoothly.
        alpha = ((S.unsqueeze(1) - 0.5 * min_weight) / (0.5 * min_weight)).clamp(0.0, 1.0)
        ok = (info.view(B, 1, h, w) == 0) & (fit > 0)
        fits.append(torch.where(ok, fit, torch.zeros_like(fit)))
        alphas.append(torch.where(ok, alpha, torch.zeros_like(alpha)))
    # From the coarsest scale to the finest, each finer fit takes over where it has enough hints.
    out = fallback
    for fit, alpha in zip(reversed(fits), reversed(alphas), strict=True):
        out = alpha * fit + (1.0 - alpha) * out
    return out


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
        ``[B, D, h, w]`` factors ``1 - v + v * k * exp(-(x - x*)^2 / (2 c^2))``, ``x`` the plane index
        and ``x*`` the hint's (continuous) plane index, both in units of this stage's inverse-depth
        spacing. ``v = 1`` at pixels with a hint whose ``x*`` lies within ``3c`` of the stage's
        hypothesis range, 0 elsewhere (factor 1): a hint the stage cannot represent is ignored
        rather than wiping out the matching volume. Computed as the exponential of the factor's
        logarithm (as PVSNet has always multiplied its cost by them).
    """
    inv_hint = torch.where(hint > 0, 1.0 / hint.clamp_min(1e-12), torch.zeros_like(hint))
    x_star = (inv_start - inv_hint) / inv_step  # [B, 1, h, w]
    on = (hint > 0) & (x_star >= -3.0 * c) & (x_star <= num_planes - 1 + 3.0 * c)
    x = torch.arange(num_planes, dtype=hint.dtype, device=hint.device).view(1, -1, 1, 1)
    sq = -((x - x_star) ** 2) / (2.0 * c * c)
    return torch.where(on, math.log(k) + sq, torch.zeros_like(sq)).exp()
