"""PVSNet: pixelwise visibility-aware multi-view stereo (Xu & Tao, 2020), CPU-first.

Pipeline (paper sections 3.1-3.4):

1. A shared 2D CNN extracts features of every view at ``H/4`` (and ``H/2``, ``H`` for the cascade).
2. Coarse stage (``H/4``): each source's features are warped onto ``D0`` fronto-parallel planes
   uniform in inverse depth (over the global depth range, or with ``sparse_prior`` per pixel around
   the interpolated sparse points) and correlated group-wise with the reference (``C_i``
   ``[B, G, D, h, w]``);
   the visibility network turns each ``C_i`` into a visibility map ``V_i``; truncated maps weight
   the aggregation ``C = sum V_i' C_i / sum V_i'``. Sources are processed one at a time, so
   inference memory grows linearly with ``N`` only through the features.
3. A 3D ResNet and two stacked 3D U-Nets filter ``C`` into three probability volumes and three
   coarse depths (inverse-depth regression, eq. 5).
4. Each cascade stage doubles the resolution: per-pixel hypotheses from the previous stage's
   inverse-depth uncertainty, visibility-weighted (upsampled ``V_i'``) thin cost volumes, a 3D U-Net.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn
from torch.profiler import record_function

from ..errors import ShapeError
from .cascade import (
    Regression,
    next_stage_range,
    prior_halfwidth_map,
    prior_plane_range,
    probability_confidence,
    regress_inverse_depth,
)
from .config import NETWORK_STRIDE, PVSNetConfig
from .cost import (
    affine_fill_inverse_depth,
    correlate_into,
    correlation_reference,
    densify_inverse_depth,
    downsample_sparse_depth,
    group_correlation,
    guidance_weights,
)
from .features import FeatureNet, normalized_intensity_channels
from .layers import set_compute_dtype, to_volume_format
from .regularization import CoarseRegularizer, StageRegularizer
from .runtime import plane_chunk
from .visibility import CostAccumulator, VisibilityNet, normalized_weights, truncate_visibility
from .warping import (
    grid_from_rays,
    homography_grid,
    homography_rays,
    hypothesis_depths,
    inside_source,
    plane_range,
    relative_pose,
    scale_intrinsics,
    warp_features,
)

logger = logging.getLogger(__name__)


@dataclass
class PVSNetOutput:
    """Outputs of :class:`PVSNet` for input images ``[B, N, 3, H, W]``.

    Attributes:
        depth: ``[B, H, W]`` final full-resolution depth (camera z).
        confidence: ``[B, H, W]`` in ``[0, 1]``: probability mass of the ``confidence_planes``
            hypotheses around the estimate, final stage (nearest-upsampled when that stage is coarser).
        visibility: ``[B, N-1, ceil(H/4), ceil(W/4)]`` truncated per-source visibility maps ``V_i'``
            in ``[0, 1]`` (all ones when ``config.visibility`` is off).
        depths: one ``[B, ceil(H/s), ceil(W/s)]`` per output, ``s`` from ``config.output_scales``:
            coarse ResNet, coarse U-Net 1, coarse U-Net 2 (``s = 4``), then each cascade stage
            (``s = 2, 1``). Same order as ``config.loss_weights``.
        confidences: the matching per-output confidence maps.
        prior_depth: ``[B, ceil(H/4), ceil(W/4)]`` the sparse prior's dense depth the coarse planes
            were centred on (0 where it has none), or ``None`` without ``config.sparse_prior`` or hints.
    """

    depth: torch.Tensor
    confidence: torch.Tensor
    visibility: torch.Tensor
    depths: list[torch.Tensor] = field(default_factory=list)
    confidences: list[torch.Tensor] | None = None
    prior_depth: torch.Tensor | None = None


def _shape(t: torch.Tensor) -> str:
    return str(list(t.shape))


def _check_tensor(name: str, t: object, expected: str, ok: bool) -> None:
    if not isinstance(t, torch.Tensor):
        raise ShapeError(f"PVSNet: {name} must be a torch.Tensor, got {type(t).__name__}")
    if not ok:
        raise ShapeError(f"PVSNet: {name} has shape {_shape(t)}, expected {expected}")


class PVSNet(nn.Module):
    """PVSNet multi-view depth estimation network. All switches are in :class:`PVSNetConfig`.

    ``forward(images, intrinsics, cam_from_world, depth_min, depth_max, sparse_depth=None)``:

    - ``images`` ``[B, N, 3, H, W]`` float in ``[0, 1]``, reference view at index 0, ``N >= 2``, any ``H, W``;
    - ``intrinsics`` ``[B, N, 3, 3]`` ``K`` for these ``H, W`` (pixel centre of ``(col, row)`` at
      ``(col + 0.5, row + 0.5)``);
    - ``cam_from_world`` ``[B, N, 4, 4]`` (``x_cam = R x_world + t``);
    - ``depth_min``, ``depth_max`` ``[B]`` with ``0 < depth_min < depth_max``;
    - ``sparse_depth`` optional ``[B, 1, H, W]`` reference-view depth hints (0 = none), used only
      when ``config.sparse_guidance`` (Poggi modulation) or ``config.sparse_prior`` (coarse
      hypotheses centred on the hints' push-pull interpolation) is on.

    Images are padded bottom/right (replicate) to a multiple of 16 (``K`` unchanged) and the
    outputs are cropped back. Returns a :class:`PVSNetOutput`.
    """

    def __init__(self, config: PVSNetConfig | None = None) -> None:
        super().__init__()
        self.config = config if config is not None else PVSNetConfig()
        cfg = self.config
        self.features = FeatureNet(cfg.feature_channels)
        coarse_in = cfg.groups_per_stage[0] + (1 if cfg.normalized_channels > 0 else 0)
        self.visibility_net = VisibilityNet(coarse_in, cfg.visibility_channels) if cfg.visibility else None
        self.coarse = CoarseRegularizer(coarse_in, cfg.regularization_channels, cfg.resnet_blocks)
        self.stages = nn.ModuleList(
            StageRegularizer(cfg.groups_per_stage[k], cfg.stage_channels[k - 1])
            for k in range(1, cfg.num_stages)
        )
        set_compute_dtype(self, torch.bfloat16 if cfg.conv_dtype == "bfloat16" else None)

    # ------------------------------------------------------------------ checks

    def _check_inputs(
        self,
        images: torch.Tensor,
        intrinsics: torch.Tensor,
        cam_from_world: torch.Tensor,
        depth_min: torch.Tensor,
        depth_max: torch.Tensor,
        sparse_depth: torch.Tensor | None,
    ) -> None:
        _check_tensor(
            "images",
            images,
            "[B, N, 3, H, W] with N >= 2",
            isinstance(images, torch.Tensor)
            and images.dim() == 5
            and images.shape[1] >= 2
            and images.shape[2] == 3
            and images.shape[0] >= 1
            and images.shape[3] >= 1
            and images.shape[4] >= 1,
        )
        if not images.is_floating_point():
            raise ShapeError(f"PVSNet: images must be floating point in [0, 1], got dtype {images.dtype}")
        B, N, _, H, W = images.shape
        _check_tensor(
            "intrinsics",
            intrinsics,
            f"[{B}, {N}, 3, 3]",
            isinstance(intrinsics, torch.Tensor) and tuple(intrinsics.shape) == (B, N, 3, 3),
        )
        _check_tensor(
            "cam_from_world",
            cam_from_world,
            f"[{B}, {N}, 4, 4]",
            isinstance(cam_from_world, torch.Tensor) and tuple(cam_from_world.shape) == (B, N, 4, 4),
        )
        _check_tensor(
            "depth_min",
            depth_min,
            f"[{B}]",
            isinstance(depth_min, torch.Tensor) and tuple(depth_min.shape) == (B,),
        )
        _check_tensor(
            "depth_max",
            depth_max,
            f"[{B}]",
            isinstance(depth_max, torch.Tensor) and tuple(depth_max.shape) == (B,),
        )
        if sparse_depth is not None:
            _check_tensor(
                "sparse_depth",
                sparse_depth,
                f"[{B}, 1, {H}, {W}]",
                isinstance(sparse_depth, torch.Tensor) and tuple(sparse_depth.shape) == (B, 1, H, W),
            )
        if not bool(torch.all(depth_min > 0)):
            raise ValueError(f"PVSNet: depth_min must be > 0, got {depth_min.tolist()}")
        if not bool(torch.all(depth_max > depth_min)):
            raise ValueError(
                f"PVSNet: depth_max must be > depth_min, got depth_min={depth_min.tolist()} "
                f"depth_max={depth_max.tolist()}"
            )

    # ------------------------------------------------------------------ forward

    def forward(
        self,
        images: torch.Tensor,
        intrinsics: torch.Tensor,
        cam_from_world: torch.Tensor,
        depth_min: torch.Tensor,
        depth_max: torch.Tensor,
        sparse_depth: torch.Tensor | None = None,
    ) -> PVSNetOutput:
        self._check_inputs(images, intrinsics, cam_from_world, depth_min, depth_max, sparse_depth)
        cfg = self.config
        param = next(self.parameters())
        dtype, device = param.dtype, param.device
        images = images.to(device=device, dtype=dtype)
        # Cameras stay in float64: relative poses and homographies are composed in double precision.
        intrinsics = intrinsics.to(device=device, dtype=torch.float64)
        cam_from_world = cam_from_world.to(device=device, dtype=torch.float64)
        depth_min = depth_min.to(device=device, dtype=dtype)
        depth_max = depth_max.to(device=device, dtype=dtype)
        B, N, _, H, W = images.shape
        Hp = math.ceil(H / NETWORK_STRIDE) * NETWORK_STRIDE
        Wp = math.ceil(W / NETWORK_STRIDE) * NETWORK_STRIDE
        flat = images.reshape(B * N, 3, H, W)
        if (Hp, Wp) != (H, W):
            # Bottom/right padding keeps K valid for the padded image.
            flat = F.pad(flat, (0, Wp - W, 0, Hp - H), mode="replicate")
        guidance = cfg.sparse_guidance and sparse_depth is not None
        use_prior = cfg.sparse_prior and sparse_depth is not None
        if guidance or use_prior:
            hints_full = F.pad(sparse_depth.to(device=device, dtype=dtype), (0, Wp - W, 0, Hp - H))
            hints_full = torch.nan_to_num(hints_full, nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)

        with record_function("pvsnet.features"):
            feats = self.features(flat, cfg.num_stages)
        if cfg.normalized_channels > 0:
            feats[0] = torch.cat([feats[0], normalized_intensity_channels(flat, cfg.normalized_channels)], 1)
        del flat
        feats = [f.contiguous(memory_format=torch.channels_last).view(B, N, *f.shape[1:]) for f in feats]
        inv_lo, inv_hi = 1.0 / depth_max, 1.0 / depth_min

        depths: list[torch.Tensor] = []
        confidences: list[torch.Tensor] = []
        sizes: list[tuple[int, int]] = []

        # ---------------------------------------------------------- coarse stage
        h, w = Hp // 4, Wp // 4
        D = cfg.planes_per_stage[0]
        K = scale_intrinsics(intrinsics, 0.25)
        if use_prior:
            hint_coarse = downsample_sparse_depth(hints_full, 4)
            if cfg.prior_fill == "affine":
                prior_inv = affine_fill_inverse_depth(hint_coarse)
            else:
                prior_inv = densify_inverse_depth(hint_coarse)
            halfwidth = prior_halfwidth_map(
                hint_coarse, cfg.prior_halfwidth, cfg.prior_growth, cfg.prior_growth_radii
            )
            inv_start, inv_step = prior_plane_range(prior_inv, halfwidth, D, inv_lo=inv_lo, inv_hi=inv_hi)
            plane_depths = hypothesis_depths(inv_start, inv_step, D)  # [B, D, h, w]
        else:
            inv_start, inv_step = plane_range(depth_min, depth_max, D)
            plane_depths = hypothesis_depths(inv_start, inv_step, D)[:, :, 0, 0]  # [B, D]
        vis_maps: list[torch.Tensor] = []
        acc = CostAccumulator()
        for i in range(1, N):
            with record_function("pvsnet.coarse_cost"):
                cost = self._two_view_cost(feats[0], K, cam_from_world, i, plane_depths, 0)
            weight = None
            if self.visibility_net is not None:
                with record_function("pvsnet.visibility"):
                    vis = self.visibility_net(to_volume_format(cost, cfg.channels_last))  # [B, 1, h, w]
                if cfg.truncation:
                    vis = truncate_visibility(vis, cfg.truncation_threshold)
                vis_maps.append(vis)
                weight = vis
            if cfg.frustum_weights:  # [B, D, h, w]: no weight where the plane's point misses the source
                inside = self._inside(K, cam_from_world, i, plane_depths, (h, w), (W / 4, H / 4))
                weight = inside if weight is None else weight * inside
            acc.add(cost, weight)
            del cost
        agg = acc.result()
        del acc
        glog = None
        if guidance:
            hint = downsample_sparse_depth(hints_full, 4)
            glog = guidance_weights(hint, inv_start, inv_step, D, cfg.guidance_k, cfg.guidance_c, log=True)
            if cfg.guidance_mode in ("cost", "both"):
                agg = agg * glog.exp().unsqueeze(1)
        with record_function("pvsnet.coarse_regularization"):
            logits = self.coarse(to_volume_format(agg, cfg.channels_last))
        del agg
        reg: Regression | None = None
        for lg in logits:
            prob = self._probability(lg, glog)
            reg = regress_inverse_depth(prob, inv_start, inv_step)
            depths.append(reg.depth)
            confidences.append(probability_confidence(prob, reg.index, cfg.confidence_planes))
            sizes.append((math.ceil(H / 4), math.ceil(W / 4)))
        del logits

        # ---------------------------------------------------------- cascade stages
        for k in range(1, cfg.num_stages):
            scale = 4 // (2**k)
            h, w = Hp // scale, Wp // scale
            D = cfg.planes_per_stage[k]
            inv_start, inv_step = next_stage_range(
                reg.inv_mean,
                reg.inv_sigma,
                inv_step,
                (h, w),
                D,
                k=cfg.uncertainty_k,
                min_halfwidth_planes=cfg.min_halfwidth_planes,
                inv_lo=inv_lo,
                inv_hi=inv_hi,
                neighbourhood=cfg.stage_neighbourhood,
            )
            hyp = hypothesis_depths(inv_start, inv_step, D)  # [B, D, h, w]
            Kk = scale_intrinsics(intrinsics, 1.0 / scale)
            frustum = None
            if cfg.frustum_weights:  # the share of this stage's planes whose point each source sees
                valid = (W / scale, H / scale)
                frustum = [self._inside(Kk, cam_from_world, i, hyp, (h, w), valid).mean(1, True)
                           for i in range(1, N)]
            weights = self._stage_weights(vis_maps, (h, w), N - 1, frustum)
            agg = None
            for i in range(1, N):
                # Accumulates sum_i w_i C_i directly (w_i normalised beforehand): no per-view volume.
                with record_function(f"pvsnet.stage{k}_cost"):
                    agg = self._two_view_cost(feats[k], Kk, cam_from_world, i, hyp, k, weights[i - 1], agg)
            del hyp
            glog = None
            if guidance:
                hint = downsample_sparse_depth(hints_full, scale)
                glog = guidance_weights(
                    hint, inv_start, inv_step, D, cfg.guidance_k, cfg.guidance_c, log=True
                )
                if cfg.guidance_mode in ("cost", "both"):
                    agg = agg * glog.exp().unsqueeze(1)
            with record_function(f"pvsnet.stage{k}_regularization"):
                lg = self.stages[k - 1](to_volume_format(agg, cfg.channels_last))
            del agg
            prob = self._probability(lg, glog)
            reg = regress_inverse_depth(prob, inv_start, inv_step)
            depths.append(reg.depth)
            confidences.append(probability_confidence(prob, reg.index, cfg.confidence_planes))
            sizes.append((math.ceil(H / scale), math.ceil(W / scale)))

        depths = [d[:, : s[0], : s[1]] for d, s in zip(depths, sizes, strict=True)]
        confidences = [c[:, : s[0], : s[1]] for c, s in zip(confidences, sizes, strict=True)]
        final_depth, final_conf = depths[-1], confidences[-1]
        if final_depth.shape[-2:] != (H, W):
            f = cfg.stage_scale(cfg.num_stages - 1)
            final_depth = _upsample_nearest(final_depth, f)[:, :H, :W]
            final_conf = _upsample_nearest(final_conf, f)[:, :H, :W]
        hc, wc = math.ceil(H / 4), math.ceil(W / 4)
        if vis_maps:
            visibility = torch.cat(vis_maps, 1)[:, :, :hc, :wc]
        else:
            visibility = torch.ones(B, N - 1, hc, wc, dtype=dtype, device=device)
        prior_depth = None
        if use_prior:
            inv = prior_inv[:, 0, :hc, :wc]
            prior_depth = torch.where(inv > 0, 1.0 / inv.clamp_min(1e-12), torch.zeros_like(inv))
        return PVSNetOutput(
            depth=final_depth,
            confidence=final_conf,
            visibility=visibility,
            depths=depths,
            confidences=confidences,
            prior_depth=prior_depth,
        )

    # ------------------------------------------------------------------ helpers

    def _two_view_cost(
        self,
        feats: torch.Tensor,
        K: torch.Tensor,
        cam_from_world: torch.Tensor,
        src: int,
        depths: torch.Tensor,
        stage: int,
        pixel_weight: torch.Tensor | float | None = None,
        accumulate: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Contiguous two-view cost ``[B, G(+1), D, h, w]`` of view ``src`` (features ``[B, N, C, h, w]``).

        With ``pixel_weight`` ``[B, 1, h, w]`` the cost is weighted; with ``accumulate`` it is added to it.
        """
        if not torch.is_grad_enabled():
            return self._two_view_cost_chunked(
                feats, K, cam_from_world, src, depths, stage, pixel_weight, accumulate
            )
        cfg = self.config
        _, _, C, h, w = feats.shape
        D = depths.shape[1]
        grid = homography_grid(K[:, 0], K[:, src], relative_pose(cam_from_world, src), depths, h, w)
        warped = warp_features(feats[:, src], grid, D)
        del grid
        ref = feats[:, 0]
        G = cfg.groups_per_stage[stage]
        n = cfg.normalized_channels if stage == 0 else 0
        if n > 0:
            learned = C - n
            cost = group_correlation(ref[:, :learned], warped[:, :learned], G, pixel_weight=pixel_weight)
            extra = group_correlation(ref[:, learned:], warped[:, learned:], 1, pixel_weight=pixel_weight)
            cost = torch.cat([cost, extra], 1)
            return cost if accumulate is None else accumulate + cost
        return group_correlation(ref, warped, G, pixel_weight=pixel_weight, accumulate=accumulate)

    def _two_view_cost_chunked(
        self,
        feats: torch.Tensor,
        K: torch.Tensor,
        cam_from_world: torch.Tensor,
        src: int,
        depths: torch.Tensor,
        stage: int,
        pixel_weight: torch.Tensor | float | None,
        accumulate: torch.Tensor | None,
    ) -> torch.Tensor:
        """Inference form of :meth:`_two_view_cost`: the same volume, warped and correlated a few planes
        at a time (``runtime.plane_chunk``), written straight into the output (or ``accumulate``).

        Bounds the temporaries (grid, warped features) to ``runtime.CHUNK_BYTES`` whatever the image
        size, and keeps them small enough to be recycled by the allocator instead of page-faulted in.
        """
        cfg = self.config
        B, _, C, h, w = feats.shape
        D = depths.shape[1]
        G = cfg.groups_per_stage[stage]
        n = cfg.normalized_channels if stage == 0 else 0
        learned = C - n
        out = accumulate
        if out is None:
            out = torch.empty(B, G + (1 if n > 0 else 0), D, h, w, dtype=feats.dtype, device=feats.device)
        rays, b = homography_rays(K[:, 0], K[:, src], relative_pose(cam_from_world, src), h, w, feats.dtype)
        ref, source = feats[:, 0], feats[:, src]
        # The reference side of the correlation, weighted and scaled once per source.
        r_learned = correlation_reference(ref[:, :learned], G, pixel_weight)
        r_extra = correlation_reference(ref[:, learned:], 1, pixel_weight) if n > 0 else None
        step = plane_chunk(B * C * h * w * feats.element_size(), D)
        add = accumulate is not None
        for d0 in range(0, D, step):
            d1 = min(D, d0 + step)
            grid = grid_from_rays(rays, b, depths[:, d0:d1], h, w)
            warped = warp_features(source, grid, d1 - d0)
            del grid
            correlate_into(r_learned, warped[:, :learned], out[:, :G, d0:d1], accumulate=add)
            if r_extra is not None:
                correlate_into(r_extra, warped[:, learned:], out[:, G:, d0:d1], accumulate=add)
            del warped
        return out

    def _stage_weights(
        self, vis_maps: list[torch.Tensor], size: tuple[int, int], num_sources: int,
        frustum: list[torch.Tensor] | None = None,
    ) -> list[torch.Tensor] | list[float]:
        """Normalised per-source weights ``[B, 1, *size]`` from the upsampled coarse visibility maps,
        times ``frustum`` ``[B, 1, *size]`` per source where given (:attr:`PVSNetConfig.frustum_weights`)."""
        if not vis_maps and frustum is None:
            return [1.0 / num_sources] * num_sources  # plain mean
        up = [F.interpolate(v, size=size, mode="bilinear", align_corners=False) for v in vis_maps]
        if frustum is not None:
            up = [u * f for u, f in zip(up, frustum, strict=True)] if up else frustum
        return normalized_weights(up)

    def _inside(self, K: torch.Tensor, cam_from_world: torch.Tensor, src: int, depths: torch.Tensor,
                size: tuple[int, int], valid_size: tuple[float, float]) -> torch.Tensor:
        """``[B, D, h, w]`` 1 where the reference pixel at each of ``depths`` projects inside source
        ``src``'s image (``valid_size``: its content's size at this stage), else 0."""
        h, w = size
        rays, b = homography_rays(K[:, 0], K[:, src], relative_pose(cam_from_world, src), h, w, depths.dtype)
        return inside_source(rays, b, depths, h, w, valid_size).to(depths.dtype)

    def _probability(self, logits: torch.Tensor, glog: torch.Tensor | None) -> torch.Tensor:
        """Softmax over depth of ``[B, D, h, w]`` logits; in probability-guidance mode times the
        guidance factors, renormalised (done in log space: ``softmax(logits + log factor)``)."""
        if glog is not None and self.config.guidance_mode in ("probability", "both"):
            logits = logits + glog
        return torch.softmax(logits, 1)

    def num_parameters(self) -> int:
        """Number of trainable parameters."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad)


def _upsample_nearest(x: torch.Tensor, factor: int) -> torch.Tensor:
    """``[B, h, w] -> [B, h*f, w*f]`` nearest (fine pixel ``j`` takes coarse pixel ``j // f``)."""
    if factor == 1:
        return x
    return F.interpolate(x.unsqueeze(1), scale_factor=float(factor), mode="nearest").squeeze(1)
