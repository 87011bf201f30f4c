"""Differentiable plane-sweep warping of source features onto reference depth hypotheses.

Conventions (``docs/CONVENTIONS.md``):

- pixel ``(col, row)`` of a ``h x w`` map has its centre at continuous coordinate
  ``(col + 0.5, row + 0.5)``; ``K`` is given for that map (a map downsampled by ``s``
  from a padded image uses ``diag(1/s, 1/s, 1) K``, exactly);
- ``grid_sample`` uses ``align_corners=False``: continuous ``u in [0, w]`` maps to
  ``2 u / w - 1``;
- depth is the camera-frame z; ``cam_from_world`` is ``[4, 4]`` with ``x_cam = R x_world + t``.

Depth hypotheses are uniform in *inverse* depth. A set of hypotheses is described by
``inv_start`` (the inverse depth of plane 0, the nearest plane) and ``inv_step`` (the
positive inverse-depth spacing): plane ``i`` has inverse depth ``inv_start - i * inv_step``,
so depth increases with the plane index.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..errors import ShapeError
from .runtime import exporting

_Z_EPS = 1e-6


def scale_intrinsics(K: torch.Tensor, scale: float) -> torch.Tensor:
    """``K`` ``[..., 3, 3]`` of a map whose size is ``scale`` times the original's: ``diag(s, s, 1) @ K``."""
    S = torch.tensor([scale, scale, 1.0], dtype=K.dtype, device=K.device)
    return K * S.view(*([1] * (K.dim() - 2)), 3, 1)


def plane_range(
    depth_min: torch.Tensor, depth_max: torch.Tensor, num_planes: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Fronto-parallel planes uniform in inverse depth between ``depth_min`` and ``depth_max`` ``[B]``.

    Returns ``(inv_start, inv_step)``, each ``[B, 1, 1, 1]``: plane 0 is at ``depth_min``,
    plane ``num_planes - 1`` at ``depth_max``.
    """
    inv_start = 1.0 / depth_min
    inv_step = (1.0 / depth_min - 1.0 / depth_max) / (num_planes - 1)
    return inv_start.view(-1, 1, 1, 1), inv_step.view(-1, 1, 1, 1)


def hypothesis_depths(inv_start: torch.Tensor, inv_step: torch.Tensor, num_planes: int) -> torch.Tensor:
    """Depths of the planes, ``[B, D, h, w]`` (``inv_start``/``inv_step`` are ``[B, 1, h|1, w|1]``)."""
    idx = torch.arange(num_planes, dtype=inv_start.dtype, device=inv_start.device).view(1, -1, 1, 1)
    return 1.0 / (inv_start - idx * inv_step)


def homography_grid(
    K_ref: torch.Tensor,
    K_src: torch.Tensor,
    src_from_ref: torch.Tensor,
    depths: torch.Tensor,
    height: int,
    width: int,
) -> torch.Tensor:
    """Sampling grid that maps each reference pixel at each hypothesis depth into the source map.

    Args:
        K_ref, K_src: ``[B, 3, 3]`` intrinsics of the reference and source maps (size ``height x width``).
        src_from_ref: ``[B, 4, 4]`` rigid transform from reference to source camera coordinates.
        depths: ``[B, D]`` (fronto-parallel planes) or ``[B, D, height, width]`` (per-pixel hypotheses);
            the grid has their dtype (the camera matrices are composed in float64).

    Returns:
        ``[B, D * height, width, 2]`` normalised ``(x, y)`` for ``grid_sample(align_corners=False)``:
        reference pixel ``(col, row)`` at continuous ``(col + 0.5, row + 0.5)`` is back-projected
        to depth ``z``, moved into the source camera and projected to continuous ``(u, v)``,
        stored as ``(2u/width - 1, 2v/height - 1)``. Points behind the source camera get ``-2``
        (outside the map, so they sample zeros).
    """
    rays, b = homography_rays(K_ref, K_src, src_from_ref, height, width, depths.dtype)
    return grid_from_rays(rays, b, depths, height, width)


def homography_rays(
    K_ref: torch.Tensor,
    K_src: torch.Tensor,
    src_from_ref: torch.Tensor,
    height: int,
    width: int,
    dtype: torch.dtype,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The depth-independent part of :func:`homography_grid`: ``rays = A [u, v, 1]^T`` ``[B, 3, hw]`` and
    ``b`` ``[B, 3, 1]``, with ``p = depth * rays + b`` the source projection (``A = K_src R K_ref^-1``,
    ``b = K_src t``)."""
    device = K_ref.device
    # Compose the per-batch 3x3 / 3x1 maps in float64 for accuracy.
    K_ref64, K_src64, T64 = K_ref.double(), K_src.double(), src_from_ref.double()
    K_ref_inv = inverse3x3(K_ref64) if exporting() else torch.linalg.inv(K_ref64)
    A = (K_src64 @ T64[:, :3, :3] @ K_ref_inv).to(dtype)  # [B, 3, 3]
    b = (K_src64 @ T64[:, :3, 3:]).to(dtype)  # [B, 3, 1]
    v, u = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device) + 0.5,
        torch.arange(width, dtype=dtype, device=device) + 0.5,
        indexing="ij",
    )
    pix = torch.stack([u.reshape(-1), v.reshape(-1), torch.ones_like(u).reshape(-1)], 0)  # [3, hw]
    return A @ pix, b


def grid_from_rays(
    rays: torch.Tensor, b: torch.Tensor, depths: torch.Tensor, height: int, width: int
) -> torch.Tensor:
    """:func:`homography_grid` from :func:`homography_rays` (reused across chunks of depths)."""
    B, D = depths.shape[:2]
    dtype, device = depths.dtype, depths.device
    if depths.dim() == 2:
        d = depths.view(B, D, 1)
    else:
        d = depths.reshape(B, D, height * width)
    # Projection of X = depth * K_ref^-1 [u, v, 1]: p = depth * A [u, v, 1] + b.
    z = torch.addcmul(b[:, 2:3], rays[:, 2:3], d)  # [B, D, hw]
    invalid = z <= _Z_EPS
    inv_z = torch.reciprocal(z.clamp_min_(_Z_EPS))
    if torch.is_grad_enabled():
        gx = torch.addcmul(b[:, 0:1], rays[:, 0:1], d)
        gy = torch.addcmul(b[:, 1:2], rays[:, 1:2], d)
    else:  # write straight into the interleaved grid (saves a copy)
        grid = torch.empty(*z.shape, 2, dtype=dtype, device=device)
        gx = torch.addcmul(b[:, 0:1], rays[:, 0:1], d, out=grid[..., 0])
        gy = torch.addcmul(b[:, 1:2], rays[:, 1:2], d, out=grid[..., 1])
    gx.mul_(inv_z).mul_(2.0 / width).sub_(1.0).clamp_(-2.0, 2.0)
    gy.mul_(inv_z).mul_(2.0 / height).sub_(1.0).clamp_(-2.0, 2.0)
    if torch.is_grad_enabled():
        grid = torch.stack([gx, gy], -1)
    if exporting() or bool(invalid.any()):  # the same values either way
        grid.masked_fill_(invalid.unsqueeze(-1), -2.0)
    return grid.view(B, D * height, width, 2)


def inside_source(rays: torch.Tensor, b: torch.Tensor, depths: torch.Tensor, height: int, width: int,
                  valid_size: tuple[float, float] | None = None, chunk: int = 8) -> torch.Tensor:
    """``[B, D, height, width]`` bool: where the reference pixel at each depth of ``depths`` (``[B, D]``
    or ``[B, D, height, width]``) projects in front of the source camera and inside the source map
    (:func:`homography_rays` gives ``rays``, ``b``). ``valid_size`` ``(w, h)``: where the source's
    image content ends (a map padded on the bottom and right); default the whole map. No gradient."""
    B, D = depths.shape[:2]
    vw, vh = valid_size if valid_size is not None else (width, height)
    out = torch.empty(B, D, height, width, dtype=torch.bool, device=depths.device)
    with torch.no_grad():
        for d0 in range(0, D, chunk):
            d1 = min(D, d0 + chunk)
            part = depths[:, d0:d1].detach()
            d = part.reshape(B, d1 - d0, 1 if part.dim() == 2 else height * width)
            # p = depth * rays + b (as in grid_from_rays); inside: z > 0, 0 <= p_x / z <= w, 0 <= p_y / z <= h
            z = torch.addcmul(b[:, 2:3], rays[:, 2:3], d)
            px = torch.addcmul(b[:, 0:1], rays[:, 0:1], d)
            py = torch.addcmul(b[:, 1:2], rays[:, 1:2], d)
            ok = (z > _Z_EPS) & (px >= 0) & (px <= vw * z) & (py >= 0) & (py <= vh * z)
            out[:, d0:d1] = ok.view(B, d1 - d0, height, width)
    return out


def warp_features(src: torch.Tensor, grid: torch.Tensor, num_planes: int) -> torch.Tensor:
    """Bilinearly sample ``src`` ``[B, C, h, w]`` at ``grid`` ``[B, D*h, w, 2]`` -> ``[B, C, D, h, w]``.

    Zero outside the source map (``padding_mode="zeros"``, ``align_corners=False``).
    """
    B, C, h, w = src.shape
    out = F.grid_sample(src, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return out.view(B, C, num_planes, h, w)


def warp_features_parts(src: torch.Tensor, grid: torch.Tensor, num_planes: int, parts: int) -> torch.Tensor:
    """:func:`warp_features` of one view (``B = 1``) with its ``num_planes`` planes sampled as ``parts``
    batch entries of ``num_planes / parts`` consecutive planes each: ``[1, C, h, w]``, ``[1, D*h, w, 2]`` ->
    ``[parts, C, D / parts, h, w]``, entry ``j`` holding planes ``j * D / parts ...``; the same values as
    :func:`warp_features`. The CPU's ``grid_sample`` runs its batch entries in parallel, not the rows of one.
    """
    _, C, h, w = src.shape
    per = num_planes // parts
    if src.shape[0] != 1 or per * parts != num_planes:
        raise ShapeError(f"warp_features_parts: {num_planes} planes of batch {src.shape[0]} "
                         f"in {parts} parts")
    out = F.grid_sample(src.expand(parts, C, h, w), grid.view(parts, per * h, w, 2), mode="bilinear",
                        padding_mode="zeros", align_corners=False)
    return out.view(parts, C, per, h, w)


def adjugate3x3(A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(adj(A), det(A))`` of ``[M, 3, 3]`` matrices (``[M, 3, 3]``, ``[M]``) in closed form: what an
    exported graph computes in place of ``torch.linalg`` (which no ONNX op implements)."""
    a, b, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 0], A[:, 1, 1], A[:, 1, 2]
    g, h, i = A[:, 2, 0], A[:, 2, 1], A[:, 2, 2]
    entries = [
        e * i - f * h, c * h - b * i, b * f - c * e,
        f * g - d * i, a * i - c * g, c * d - a * f,
        d * h - e * g, b * g - a * h, a * e - b * d,
    ]
    adj = torch.stack(entries, 1).view(A.shape[0], 3, 3)
    det = a * entries[0] + b * entries[3] + c * entries[6]
    return adj, det


def inverse3x3(A: torch.Tensor) -> torch.Tensor:
    """``A^-1`` of ``[M, 3, 3]`` matrices by :func:`adjugate3x3` (``torch.linalg.inv`` up to rounding)."""
    adj, det = adjugate3x3(A)
    return adj / det.view(-1, 1, 1)


def relative_pose(cam_from_world: torch.Tensor, src: int, ref: int = 0) -> torch.Tensor:
    """``src_from_ref`` ``[B, 4, 4]`` from ``cam_from_world`` ``[B, N, 4, 4]`` (computed in float64).

    Uses the closed-form rigid inverse ``[R^T | -R^T t]`` of the reference pose.
    """
    T = cam_from_world.double()
    R, t = T[:, ref, :3, :3], T[:, ref, :3, 3:]
    inv = torch.zeros_like(T[:, ref])
    inv[:, :3, :3] = R.transpose(1, 2)
    inv[:, :3, 3:] = -R.transpose(1, 2) @ t
    inv[:, 3, 3] = 1.0
    return (T[:, src] @ inv).to(cam_from_world.dtype)
