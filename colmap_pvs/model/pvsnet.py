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
from .features import FeatureNet
from .layers import set_compute_dtype, to_volume_format
from .regularization import CoarseRegularizer, StageRegularizer
from .runtime import exporting, plane_chunk
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
    warp_features_parts,
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


@dataclass
class _Inputs:
    """The inputs as :meth:`PVSNet._prepare` hands them to the stages."""

    intrinsics: torch.Tensor  # [B, N, 3, 3] float64, for the unpadded H, W (valid for the padded image)
    cam_from_world: torch.Tensor  # [B, N, 4, 4] float64
    depth_min: torch.Tensor  # [B], the model's dtype
    depth_max: torch.Tensor  # [B]
    inv_lo: torch.Tensor  # [B] 1 / depth_max
    inv_hi: torch.Tensor  # [B] 1 / depth_min
    hints: torch.Tensor | None  # [B, 1, Hp, Wp] sparse depth (0 = none) when guidance or prior use it
    guidance: bool  # config.sparse_guidance and hints given
    prior: bool  # config.sparse_prior and hints given
    B: int
    N: int
    size: tuple[int, int]  # (H, W) of the input images
    padded: tuple[int, int]  # (Hp, Wp): multiples of NETWORK_STRIDE


@dataclass
class _Stage:
    """What one stage hands on: its outputs (cropped to the input's size at its scale), its last
    regression and plane spacing (for the next stage's range); the coarse stage also its visibility
    maps and the prior."""

    inv_step: torch.Tensor
    depths: list[torch.Tensor] = field(default_factory=list)  # [B, ceil(H/s), ceil(W/s)] each
    confidences: list[torch.Tensor] = field(default_factory=list)
    regression: Regression | None = None  # uncropped [B, Hp/s, Wp/s]
    visibility: list[torch.Tensor] = field(default_factory=list)  # [B, 1, Hp/4, Wp/4] per source
    prior_inv: torch.Tensor | None = None  # [B, 1, Hp/4, Wp/4], 0 = none


def _shape(t: torch.Tensor) -> str:
    return str(list(t.shape))


def _check_tensor(name: str, t: object, expected: str, ok: bool) -> None:
    if not isinstance(t, torch.Tensor):
        raise ShapeError(f"PVSNet: {name} must be a torch.Tensor, got {type(t).__name__}")
    if not ok:
        raise ShapeError(f"PVSNet: {name} has shape {_shape(t)}, expected {expected}")


class PVSNet(nn.Module):
    """PVSNet multi-view depth estimation network. All switches are in :class:`PVSNetConfig`;
    ``PVSNet()`` is the shipped model's architecture (random weights).

    ``forward(images, intrinsics, cam_from_world, depth_min, depth_max, sparse_depth=None)``:

    - ``images`` ``[B, N, 3, H, W]`` float in ``[0, 1]``, reference view at index 0, ``N >= 2``, any ``H, W``;
      cast to the model's dtype;
    - ``intrinsics`` ``[B, N, 3, 3]`` ``K`` for these ``H, W`` (pixel centre of ``(col, row)`` at
      ``(col + 0.5, row + 0.5)``);
    - ``cam_from_world`` ``[B, N, 4, 4]`` (``x_cam = R x_world + t``);
    - ``depth_min``, ``depth_max`` ``[B]`` with ``0 < depth_min < depth_max``;
    - ``sparse_depth`` optional ``[B, 1, H, W]`` reference-view depth hints (0 = none), used only
      when ``config.sparse_guidance`` (Poggi modulation) or ``config.sparse_prior`` (coarse
      hypotheses centred on the hints' interpolation, ``config.prior_fill``) is on.

    The cameras may come in any floating dtype: they are cast to float64 (from the values given, so
    float32 cameras are composed as their float32 values) and the relative poses and plane
    homographies are composed in float64 [``tests/test_model_pvsnet.py::
    test_cameras_are_composed_in_float64_from_the_values_given``]. Images are padded bottom/right
    (replicate) to a multiple of 16 (``K`` unchanged) and the outputs are cropped back. Returns a
    :class:`PVSNetOutput`.

    ``forward`` reads as its stages: :meth:`_prepare` (cast, pad), the shared features,
    :meth:`_coarse_stage`, one :meth:`_cascade_stage` per further stage, :meth:`_output`.
    """

    def __init__(self, config: PVSNetConfig | None = None) -> None:
        super().__init__()
        self.config = config if config is not None else PVSNetConfig()
        cfg = self.config
        self.features = FeatureNet(cfg.feature_channels)
        G0 = cfg.groups_per_stage[0]
        self.visibility_net = VisibilityNet(G0, cfg.visibility_channels) if cfg.visibility else None
        self.coarse = CoarseRegularizer(G0, cfg.regularization_channels, cfg.resnet_blocks)
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
        if exporting():  # a traced graph holds no check of input values (shapes are checked above)
            return
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
        """Depth of the reference view (index 0): features, the coarse stage, the cascade stages.

        Args: see the class docstring. Returns a :class:`PVSNetOutput`.
        """
        self._check_inputs(images, intrinsics, cam_from_world, depth_min, depth_max, sparse_depth)
        x, flat = self._prepare(images, intrinsics, cam_from_world, depth_min, depth_max, sparse_depth)
        with record_function("pvsnet.features"):
            feats = self.features(flat, self.config.num_stages)
        del flat
        feats = [f.contiguous(memory_format=torch.channels_last).view(x.B, x.N, *f.shape[1:]) for f in feats]
        stages = [self._coarse_stage(x, feats[0])]
        for k in range(1, self.config.num_stages):
            stages.append(self._cascade_stage(k, x, feats[k], stages[-1], stages[0].visibility))
        return self._output(x, stages)

    def _prepare(
        self,
        images: torch.Tensor,
        intrinsics: torch.Tensor,
        cam_from_world: torch.Tensor,
        depth_min: torch.Tensor,
        depth_max: torch.Tensor,
        sparse_depth: torch.Tensor | None,
    ) -> tuple[_Inputs, torch.Tensor]:
        """The inputs on the model's device and dtype (the cameras in float64), and the images
        ``[B*N, 3, Hp, Wp]`` padded bottom/right (replicate) to a multiple of ``NETWORK_STRIDE``."""
        cfg = self.config
        param = next(self.parameters())
        dtype, device = param.dtype, param.device
        B, N, _, H, W = images.shape
        Hp = math.ceil(H / NETWORK_STRIDE) * NETWORK_STRIDE
        Wp = math.ceil(W / NETWORK_STRIDE) * NETWORK_STRIDE
        flat = images.to(device=device, dtype=dtype).reshape(B * N, 3, H, W)
        if (Hp, Wp) != (H, W):
            # Bottom/right padding keeps K valid for the padded image.
            flat = F.pad(flat, (0, Wp - W, 0, Hp - H), mode="replicate")
        guidance = cfg.sparse_guidance and sparse_depth is not None
        prior = cfg.sparse_prior and sparse_depth is not None
        hints = None
        if guidance or prior:
            hints = F.pad(sparse_depth.to(device=device, dtype=dtype), (0, Wp - W, 0, Hp - H))
            hints = torch.nan_to_num(hints, nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)
        depth_min = depth_min.to(device=device, dtype=dtype)
        depth_max = depth_max.to(device=device, dtype=dtype)
        x = _Inputs(
            intrinsics=intrinsics.to(device=device, dtype=torch.float64),
            cam_from_world=cam_from_world.to(device=device, dtype=torch.float64),
            depth_min=depth_min, depth_max=depth_max, inv_lo=1.0 / depth_max, inv_hi=1.0 / depth_min,
            hints=hints, guidance=guidance, prior=prior, B=B, N=N, size=(H, W), padded=(Hp, Wp),
        )
        return x, flat

    def _coarse_stage(self, x: _Inputs, feats: torch.Tensor) -> _Stage:
        """Stage 0 at ``H/4``: ``D0`` planes (global, or per pixel around the sparse prior), per-source
        cost volumes weighted by the visibility network (and the frustum), the 3D ResNet and two U-Nets.

        Args:
            feats: ``[B, N, C0, Hp/4, Wp/4]`` features.

        Returns:
            three outputs (ResNet, U-Net 1, U-Net 2), the visibility maps ``[B, 1, Hp/4, Wp/4]`` of each
            source and the prior's inverse depth ``[B, 1, Hp/4, Wp/4]`` (``None`` without it).
        """
        cfg = self.config
        Hp, Wp = x.padded
        h, w = Hp // 4, Wp // 4
        D = cfg.planes_per_stage[0]
        K = scale_intrinsics(x.intrinsics, 0.25)
        hint = downsample_sparse_depth(x.hints, 4) if x.hints is not None else None
        prior_inv = None
        if x.prior:
            fill = affine_fill_inverse_depth if cfg.prior_fill == "affine" else densify_inverse_depth
            prior_inv = fill(hint)
            halfwidth = prior_halfwidth_map(
                hint, cfg.prior_halfwidth, cfg.prior_growth, cfg.prior_growth_radii
            )
            inv_start, inv_step = prior_plane_range(prior_inv, halfwidth, D, inv_lo=x.inv_lo, inv_hi=x.inv_hi)
            planes = hypothesis_depths(inv_start, inv_step, D)  # [B, D, h, w]
        else:
            inv_start, inv_step = plane_range(x.depth_min, x.depth_max, D)
            planes = hypothesis_depths(inv_start, inv_step, D)[:, :, 0, 0]  # [B, D]
        H, W = x.size
        vis_maps: list[torch.Tensor] = []
        acc = CostAccumulator()
        for i in range(1, x.N):
            with record_function("pvsnet.coarse_cost"):
                cost = self._two_view_cost(feats, K, x.cam_from_world, i, planes, 0)
            weight = None
            if self.visibility_net is not None:
                with record_function("pvsnet.visibility"):
                    vis = self.visibility_net(to_volume_format(cost, cfg.channels_last))  # [B, 1, h, w]
                if cfg.truncation:
                    vis = truncate_visibility(vis, cfg.truncation_threshold)
                vis_maps.append(vis)
                weight = vis
            if cfg.frustum_weights:  # [B, D, h, w]: no weight where the plane's point misses the source
                inside = self._inside(K, x.cam_from_world, i, planes, (h, w), (W / 4, H / 4))
                weight = inside if weight is None else weight * inside
            acc.add(cost, weight)
            del cost
        agg = acc.result()
        del acc
        if x.guidance:
            agg = self._guide(agg, hint, inv_start, inv_step, D)
        with record_function("pvsnet.coarse_regularization"):
            logits = self.coarse(to_volume_format(agg, cfg.channels_last))
        del agg
        stage = _Stage(inv_step=inv_step, visibility=vis_maps, prior_inv=prior_inv)
        for lg in logits:
            self._regress(stage, lg, inv_start, inv_step, (math.ceil(H / 4), math.ceil(W / 4)))
        return stage

    def _cascade_stage(
        self, k: int, x: _Inputs, feats: torch.Tensor, previous: _Stage, vis_maps: list[torch.Tensor]
    ) -> _Stage:
        """Cascade stage ``k`` at ``H/s``, ``s = 4 / 2**k``: ``Dk`` hypotheses per pixel from the previous
        stage's inverse-depth uncertainty, the sources' costs weighted by the upsampled coarse visibility
        (and the share of planes in each source's frustum), one 3D U-Net.

        Args:
            feats: ``[B, N, Ck, Hp/s, Wp/s]`` features; ``vis_maps``: the coarse stage's.
        """
        cfg = self.config
        scale = cfg.stage_scale(k)
        Hp, Wp = x.padded
        H, W = x.size
        h, w = Hp // scale, Wp // scale
        D = cfg.planes_per_stage[k]
        reg = previous.regression
        inv_start, inv_step = next_stage_range(
            reg.inv_mean,
            reg.inv_sigma,
            previous.inv_step,
            (h, w),
            D,
            k=cfg.uncertainty_k,
            min_halfwidth_planes=cfg.min_halfwidth_planes,
            inv_lo=x.inv_lo,
            inv_hi=x.inv_hi,
            neighbourhood=cfg.stage_neighbourhood,
        )
        hyp = hypothesis_depths(inv_start, inv_step, D)  # [B, D, h, w]
        K = scale_intrinsics(x.intrinsics, 1.0 / scale)
        frustum = None
        if cfg.frustum_weights:  # the share of this stage's planes whose point each source sees
            valid = (W / scale, H / scale)
            frustum = [self._inside(K, x.cam_from_world, i, hyp, (h, w), valid).mean(1, True)
                       for i in range(1, x.N)]
        weights = self._stage_weights(vis_maps, (h, w), x.N - 1, frustum)
        agg = None
        for i in range(1, x.N):
            # Accumulates sum_i w_i C_i directly (w_i normalised beforehand): no per-view volume.
            with record_function(f"pvsnet.stage{k}_cost"):
                agg = self._two_view_cost(feats, K, x.cam_from_world, i, hyp, k, weights[i - 1], agg)
        del hyp
        if x.guidance:
            agg = self._guide(agg, downsample_sparse_depth(x.hints, scale), inv_start, inv_step, D)
        with record_function(f"pvsnet.stage{k}_regularization"):
            logits = self.stages[k - 1](to_volume_format(agg, cfg.channels_last))
        del agg
        stage = _Stage(inv_step=inv_step)
        self._regress(stage, logits, inv_start, inv_step, (math.ceil(H / scale), math.ceil(W / scale)))
        return stage

    def _guide(
        self, agg: torch.Tensor, hint: torch.Tensor, inv_start: torch.Tensor, inv_step: torch.Tensor, D: int
    ) -> torch.Tensor:
        """The aggregated cost ``[B, G, D, h, w]`` times the Poggi guidance factors of the hints
        ``[B, 1, h, w]`` (:func:`~colmap_pvs.model.cost.guidance_weights`)."""
        cfg = self.config
        factors = guidance_weights(hint, inv_start, inv_step, D, cfg.guidance_k, cfg.guidance_c)
        return agg * factors.unsqueeze(1)

    def _regress(
        self, stage: _Stage, logits: torch.Tensor, inv_start: torch.Tensor, inv_step: torch.Tensor,
        size: tuple[int, int],
    ) -> None:
        """Add to ``stage`` the depth and confidence of ``logits`` ``[B, D, h, w]`` (softmax over depth,
        inverse-depth regression), cropped to ``size`` (the unpadded image's at this scale)."""
        prob = torch.softmax(logits, 1)
        stage.regression = regress_inverse_depth(prob, inv_start, inv_step)
        conf = probability_confidence(prob, stage.regression.index, self.config.confidence_planes)
        stage.depths.append(stage.regression.depth[:, : size[0], : size[1]])
        stage.confidences.append(conf[:, : size[0], : size[1]])

    def _output(self, x: _Inputs, stages: list[_Stage]) -> PVSNetOutput:
        """The stages' outputs, the final one at the input's size, the visibility maps and the prior
        cropped to ``ceil(H/4) x ceil(W/4)``."""
        cfg = self.config
        H, W = x.size
        depths = [d for s in stages for d in s.depths]
        confidences = [c for s in stages for c in s.confidences]
        final_depth, final_conf = depths[-1], confidences[-1]
        if final_depth.shape[-2:] != (H, W):
            f = cfg.stage_scale(cfg.num_stages - 1)
            final_depth = _upsample_nearest(final_depth, f)[:, :H, :W]
            final_conf = _upsample_nearest(final_conf, f)[:, :H, :W]
        hc, wc = math.ceil(H / 4), math.ceil(W / 4)
        vis_maps = stages[0].visibility
        if vis_maps:
            visibility = torch.cat(vis_maps, 1)[:, :, :hc, :wc]
        else:
            visibility = torch.ones(x.B, x.N - 1, hc, wc, dtype=x.depth_min.dtype, device=x.depth_min.device)
        prior_depth = None
        if stages[0].prior_inv is not None:
            inv = stages[0].prior_inv[:, 0, :hc, :wc]
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
        """Contiguous two-view cost ``[B, G, D, h, w]`` of view ``src`` (features ``[B, N, C, h, w]``,
        ``depths`` ``[B, D]`` planes or ``[B, D, h, w]`` per pixel, ``K`` ``[B, N, 3, 3]`` at this scale).

        With ``pixel_weight`` ``[B, 1, h, w]`` the cost is weighted; with ``accumulate`` it is added to it.
        """
        if not torch.is_grad_enabled():
            return self._two_view_cost_chunked(
                feats, K, cam_from_world, src, depths, stage, pixel_weight, accumulate
            )
        _, _, _, h, w = feats.shape
        D = depths.shape[1]
        grid = homography_grid(K[:, 0], K[:, src], relative_pose(cam_from_world, src), depths, h, w)
        warped = warp_features(feats[:, src], grid, D)
        del grid
        G = self.config.groups_per_stage[stage]
        return group_correlation(feats[:, 0], warped, G, pixel_weight=pixel_weight, accumulate=accumulate)

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
        B, _, C, h, w = feats.shape
        D = depths.shape[1]
        G = self.config.groups_per_stage[stage]
        out = accumulate
        if out is None:
            out = torch.empty(B, G, D, h, w, dtype=feats.dtype, device=feats.device)
        rays, b = homography_rays(K[:, 0], K[:, src], relative_pose(cam_from_world, src), h, w, feats.dtype)
        # The reference side of the correlation, weighted and scaled once per source.
        ref = correlation_reference(feats[:, 0], G, pixel_weight)
        step = plane_chunk(B * C * h * w * feats.element_size(), D)
        threads = torch.get_num_threads() if feats.device.type == "cpu" and not exporting() else 1
        for d0 in range(0, D, step):
            d1 = min(D, d0 + step)
            grid = grid_from_rays(rays, b, depths[:, d0:d1], h, w)
            parts = _sampling_parts(B, d1 - d0, threads)
            if parts == 1:
                pieces = [(d0, warp_features(feats[:, src], grid, d1 - d0))]
            else:  # [parts, C, (d1 - d0) / parts, h, w]: entry j is the j-th run of planes
                warped = warp_features_parts(feats[:, src], grid, d1 - d0, parts)
                pieces = [(d0 + j * warped.shape[2], warped[j : j + 1]) for j in range(parts)]
                del warped
            del grid
            for lo, piece in pieces:
                correlate_into(ref, piece, out[:, :, lo : lo + piece.shape[2]],
                               accumulate=accumulate is not None)
            del pieces
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

    def num_parameters(self) -> int:
        """Number of trainable parameters."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad)


def _sampling_parts(batch: int, planes: int, threads: int) -> int:
    """In how many batch entries one view's ``planes`` are sampled (:func:`warp_features_parts`): up to
    ``threads`` equal parts for a single view on the CPU, else 1."""
    if batch != 1 or threads < 2:
        return 1
    return max(k for k in range(1, min(threads, planes) + 1) if planes % k == 0)


def _upsample_nearest(x: torch.Tensor, factor: int) -> torch.Tensor:
    """``[B, h, w] -> [B, h*f, w*f]`` nearest (fine pixel ``j`` takes coarse pixel ``j // f``)."""
    if factor == 1:
        return x
    return F.interpolate(x.unsqueeze(1), scale_factor=float(factor), mode="nearest").squeeze(1)
