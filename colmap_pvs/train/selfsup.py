"""Self-supervised losses for real images without ground-truth depth.

Used for the real samples of :class:`~colmap_pvs.train.real_dataset.RealMVSDataset` while
training, and by test-time adaptation (:mod:`colmap_pvs.adapt`). Three terms, each
evaluated on every network output (``PVSNetOutput.depths``, weights
``PVSNetConfig.loss_weights``) at that output's resolution:

- **photometric**: every source image is warped into the reference with the predicted
  depth (:func:`warp_to_reference`); the per-pixel error is
  ``alpha * (1 - SSIM) / 2 + (1 - alpha) * |I_ref - I_src->ref|`` (channel mean, 3x3 SSIM,
  ``alpha = 0.85``, as in Monodepth). Occlusions and unrelated views are handled by the
  per-pixel **minimum over the sources** whose warp lands inside their frustum; pixels that
  no source sees are left out.
- **sparse**: the reference's SfM points that were *not* handed to the network as hints
  (``label_depth``) supervise the depth like the synthetic GT does (masked L1 divided by the
  depth range, coarse outputs take the front-most label of their block).
- **smoothness**: edge-aware first-order smoothness of the mean-normalised inverse depth,
  ``|d_x (1/z)| exp(-|d_x I|) + |d_y (1/z)| exp(-|d_y I|)``.
- **pseudo** (self-training, optional): dense ``pseudo_depth`` labels, an earlier model's
  geometric map (the depths that agree across views) or its dense completion, supervise the
  depth like the sparse labels do (masked L1 divided by the depth range).

Total: ``photometric_weight * photo + sparse_weight * sparse + smooth_weight * smooth
+ pseudo_weight * pseudo``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from ..errors import ConfigError, ShapeError
from ..model.warping import homography_grid, relative_pose
from .losses import depth_loss


@dataclass(frozen=True)
class SelfSupConfig:
    """Weights and options of the self-supervised loss (see the module docstring)."""

    photometric_weight: float = field(default=1.0, metadata={"help": "weight of the photometric term"})
    sparse_weight: float = field(default=1.0, metadata={"help": "weight of the sparse SfM-point term"})
    smooth_weight: float = field(default=0.002, metadata={"help": "weight of the edge-aware smoothness"})
    ssim_alpha: float = field(default=0.85, metadata={"help": "SSIM share of the photometric error"})
    min_sources: int = field(
        default=1, metadata={"help": "a pixel counts when at least this many sources see it"}
    )
    pseudo_weight: float = field(
        default=1.0, metadata={"help": "weight of the dense pseudo-label term (samples that have them)"}
    )

    def __post_init__(self) -> None:
        for name in ("photometric_weight", "sparse_weight", "smooth_weight", "pseudo_weight"):
            value = getattr(self, name)
            if not value >= 0:
                raise ConfigError(f"SelfSupConfig: {name} must be >= 0, got {value}")
        if not 0.0 <= self.ssim_alpha <= 1.0:
            raise ConfigError(f"SelfSupConfig: ssim_alpha must be in [0, 1], got {self.ssim_alpha}")
        if self.min_sources < 1:
            raise ConfigError(f"SelfSupConfig: min_sources must be >= 1, got {self.min_sources}")


@dataclass(frozen=True)
class SelfSupLoss:
    """The weighted self-supervised loss and its parts (detached, summed over outputs with the weights)."""

    total: torch.Tensor
    photometric: torch.Tensor
    sparse: torch.Tensor
    smooth: torch.Tensor
    per_output: torch.Tensor
    pseudo: torch.Tensor | None = None


def _pool_images(images: torch.Tensor, stride: int) -> torch.Tensor:
    """``[B, N, 3, H, W]`` averaged over ``stride x stride`` blocks (bottom/right padded by edge copies)."""
    if stride == 1:
        return images
    B, N, C, H, W = images.shape
    x = images.reshape(B * N, C, H, W)
    ph, pw = (-H) % stride, (-W) % stride
    if ph or pw:
        x = F.pad(x, (0, pw, 0, ph), mode="replicate")
    x = F.avg_pool2d(x, stride)
    return x.reshape(B, N, C, x.shape[-2], x.shape[-1])


def warp_to_reference(
    images: torch.Tensor,
    intrinsics: torch.Tensor,
    cam_from_world: torch.Tensor,
    depth: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp every source into the reference with the reference depth.

    Args:
        images: ``[B, N, 3, h, w]`` at the depth's resolution, reference at index 0.
        intrinsics: ``[B, N, 3, 3]`` for maps of size ``h x w`` (COLMAP's pixel-centre convention).
        cam_from_world: ``[B, N, 4, 4]``.
        depth: ``[B, h, w]`` reference depth (> 0).

    Returns:
        ``warped [B, N-1, 3, h, w]`` and ``valid [B, N-1, h, w]`` (bool: in front of the source
        and inside its image).
    """
    if images.dim() != 5 or depth.dim() != 3:
        raise ShapeError(
            f"images must be [B, N, 3, h, w] and depth [B, h, w], got {tuple(images.shape)}, "
            f"{tuple(depth.shape)}"
        )
    B, N, C, h, w = images.shape
    if depth.shape != (B, h, w):
        raise ShapeError(f"depth {tuple(depth.shape)} does not match images {tuple(images.shape)}")
    warped, valid = [], []
    d = depth.clamp_min(1e-6)[:, None]  # [B, 1, h, w]
    for i in range(1, N):
        grid = homography_grid(
            intrinsics[:, 0], intrinsics[:, i], relative_pose(cam_from_world, i), d, h, w
        )  # [B, h, w, 2]
        grid = grid.view(B, h, w, 2)
        warped.append(F.grid_sample(images[:, i], grid, mode="bilinear", padding_mode="border",
                                    align_corners=False))
        valid.append((grid.abs() <= 1.0).all(dim=-1))
    return torch.stack(warped, 1), torch.stack(valid, 1)


def ssim_error(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """``(1 - SSIM) / 2`` per pixel and channel, 3x3 windows, for ``[B, C, h, w]`` images in [0, 1]."""
    c1, c2 = 0.01**2, 0.03**2
    xp, yp = F.pad(x, (1, 1, 1, 1), mode="reflect"), F.pad(y, (1, 1, 1, 1), mode="reflect")
    mx, my = F.avg_pool2d(xp, 3, 1), F.avg_pool2d(yp, 3, 1)
    sx = F.avg_pool2d(xp * xp, 3, 1) - mx * mx
    sy = F.avg_pool2d(yp * yp, 3, 1) - my * my
    sxy = F.avg_pool2d(xp * yp, 3, 1) - mx * my
    ssim = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sx + sy + c2))
    return ((1 - ssim) / 2).clamp(0, 1)


def photometric_error(
    images: torch.Tensor,
    intrinsics: torch.Tensor,
    cam_from_world: torch.Tensor,
    depth: torch.Tensor,
    alpha: float = 0.85,
    min_sources: int = 1,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel photometric error of ``depth`` (minimum over the sources that see the pixel).

    Args: as :func:`warp_to_reference`.

    Returns:
        ``error [B, h, w]`` and ``mask [B, h, w]`` (pixels seen by at least ``min_sources`` sources).
    """
    warped, valid = warp_to_reference(images, intrinsics, cam_from_world, depth)
    B, S, C, h, w = warped.shape
    ref = images[:, 0:1].expand(B, S, C, h, w).reshape(B * S, C, h, w)
    src = warped.reshape(B * S, C, h, w)
    err = alpha * ssim_error(ref, src) + (1 - alpha) * (ref - src).abs()
    err = err.mean(1).reshape(B, S, h, w)
    big = torch.full_like(err, 1e3)
    per_pixel = torch.where(valid, err, big).min(dim=1).values
    mask = valid.sum(1) >= min_sources
    return per_pixel, mask


def smoothness(depth: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """Edge-aware smoothness of the mean-normalised inverse depth ``[B, h, w]`` guided by ``[B, 3, h, w]``."""
    disp = 1.0 / depth.clamp_min(1e-6)
    disp = disp / disp.mean(dim=(1, 2), keepdim=True).clamp_min(1e-12)
    dx = (disp[:, :, 1:] - disp[:, :, :-1]).abs()
    dy = (disp[:, 1:, :] - disp[:, :-1, :]).abs()
    ix = (image[:, :, :, 1:] - image[:, :, :, :-1]).abs().mean(1)
    iy = (image[:, :, 1:, :] - image[:, :, :-1, :]).abs().mean(1)
    return (dx * torch.exp(-ix)).mean() + (dy * torch.exp(-iy)).mean()


def selfsup_loss(
    depths: Sequence[torch.Tensor],
    images: torch.Tensor,
    intrinsics: torch.Tensor,
    cam_from_world: torch.Tensor,
    label_depth: torch.Tensor,
    depth_min: torch.Tensor,
    depth_max: torch.Tensor,
    weights: Sequence[float],
    scales: Sequence[int],
    config: SelfSupConfig | None = None,
    pseudo_depth: torch.Tensor | None = None,
) -> SelfSupLoss:
    """The self-supervised loss of one batch (module docstring).

    Args:
        depths: ``K`` predicted depths ``[B, ceil(H/s_k), ceil(W/s_k)]`` (``PVSNetOutput.depths``).
        images: ``[B, N, 3, H, W]`` clean images in [0, 1] (no photometric jitter), reference first.
        intrinsics: ``[B, N, 3, 3]`` for ``H x W``; cam_from_world: ``[B, N, 4, 4]``.
        label_depth: ``[B, H, W]`` sparse depth labels (0 = none), disjoint from the hints.
        depth_min, depth_max: ``[B]``.
        weights: one weight per output; scales: one stride per output (``PVSNetConfig.output_scales``).
        pseudo_depth: ``[B, H, W]`` dense pseudo-labels (0 = none), or ``None``.
    """
    cfg = config or SelfSupConfig()
    if images.dim() != 5:
        raise ShapeError(f"images must be [B, N, 3, H, W], got {tuple(images.shape)}")
    if len(depths) != len(weights) or len(depths) != len(scales):
        raise ValueError(f"got {len(depths)} outputs, {len(weights)} weights and {len(scales)} scales")
    total = depths[0].new_zeros(())
    photo_sum = smooth_sum = depths[0].new_zeros(())
    per_output = []
    pooled: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
    for d, w, s in zip(depths, weights, scales, strict=True):
        if s not in pooled:
            K = intrinsics.clone()
            K[..., :2, :] = K[..., :2, :] / s
            pooled[s] = (_pool_images(images, s), K)
        ims, K = pooled[s]
        ims = ims[..., : d.shape[1], : d.shape[2]]
        err, mask = photometric_error(ims, K, cam_from_world, d, cfg.ssim_alpha, cfg.min_sources)
        photo = torch.where(mask, err, torch.zeros_like(err)).sum() / mask.sum().clamp_min(1)
        smooth = smoothness(d, ims[:, 0])
        part = cfg.photometric_weight * photo + cfg.smooth_weight * smooth
        total = total + float(w) * part
        photo_sum = photo_sum + float(w) * photo.detach()
        smooth_sum = smooth_sum + float(w) * smooth.detach()
        per_output.append(part.detach())
    sparse = depth_loss(
        depths, label_depth, depth_min, depth_max, weights, gt_downsample="min", scales=scales
    )
    total = total + cfg.sparse_weight * sparse.total
    per = torch.stack(per_output) + cfg.sparse_weight * sparse.per_output
    pseudo = None
    if pseudo_depth is not None and cfg.pseudo_weight > 0:
        if pseudo_depth.shape != label_depth.shape:
            raise ShapeError(
                f"pseudo_depth {tuple(pseudo_depth.shape)} does not match label_depth "
                f"{tuple(label_depth.shape)}"
            )
        dense = depth_loss(
            depths, pseudo_depth, depth_min, depth_max, weights, gt_downsample="min", scales=scales
        )
        total = total + cfg.pseudo_weight * dense.total
        per = per + cfg.pseudo_weight * dense.per_output
        pseudo = dense.total.detach()
    return SelfSupLoss(
        total=total,
        photometric=photo_sum,
        sparse=sparse.total.detach(),
        smooth=smooth_sum,
        per_output=per,
        pseudo=pseudo,
    )


__all__ = [
    "SelfSupConfig",
    "SelfSupLoss",
    "photometric_error",
    "selfsup_loss",
    "smoothness",
    "ssim_error",
    "warp_to_reference",
]
