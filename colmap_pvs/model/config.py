"""The PVSNet model config: every architectural switch of :class:`~colmap_pvs.model.PVSNet`.

Stages: stage 0 is the coarse stage at ``H/4 x W/4`` (two-view cost volumes, pixelwise
visibility network, 3D ResNet and two stacked 3D U-Nets); stage ``k >= 1`` is a cascade
stage at ``H/4 * 2**k`` with per-pixel depth hypotheses. ``num_stages=3`` ends at full
resolution.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Literal

from ..errors import ConfigError

#: Total downsampling of the network: 4 (features) x 4 (three-scale 3D U-Net at H/4).
NETWORK_STRIDE = 16
#: Plane counts must be divisible by this (three-scale 3D U-Nets halve the depth axis twice).
PLANE_MULTIPLE = 4
#: :class:`PVSNetConfig` fields that add no parameters: checkpoints differing only in them hold the
#: same tensors, so they can be averaged and the fields flipped on trained weights (whether a flip
#: helps is measured: ``frustum_weights`` needs weights trained with it).
PARAMETER_FREE_FIELDS = frozenset({
    "sparse_prior", "sparse_guidance", "guidance_k", "guidance_c", "prior_fill",
    "prior_halfwidth", "prior_growth", "prior_growth_radii", "stage_neighbourhood", "min_halfwidth_planes",
    "uncertainty_k", "confidence_planes", "loss_weights", "channels_last", "conv_dtype", "frustum_weights",
})


@dataclass(frozen=True)
class PVSNetConfig:
    """Architecture of PVSNet. Saved inside every checkpoint; unknown keys are errors.

    The defaults are the shipped model's (``colmap_pvs/weights/pvsnet_default.pt``), so ``PVSNet()``
    is the network ``stereo`` runs, with random weights [``tests/test_model_checkpoint.py::
    test_default_config_is_the_shipped_checkpoints``].
    """

    #: Options that are gone, with the one value every recorded config gives them (accepted with a
    #: warning in a mapping, refused with another value; a checkpoint's are dropped silently:
    #: :data:`RETIRED_FIELDS`). Back-compat (dropped in 0.3): a model or training config file a user
    #: wrote may set them.
    REMOVED_OPTIONS: ClassVar[dict[str, object]] = {"guidance_mode": "cost", "normalized_channels": 0}

    feature_channels: tuple[int, ...] = field(
        default=(16, 8, 8),
        metadata={"help": "learned feature channels at H/4, H/2 and H (FPN outputs)"},
    )
    num_stages: int = field(
        default=3,
        metadata={"help": "1 = coarse stage only (H/4), 2 = up to H/2, 3 = up to full resolution"},
    )
    planes_per_stage: tuple[int, ...] = field(
        default=(32, 8, 8),
        metadata={"help": "depth hypotheses per stage (one value per stage, multiples of 4)"},
    )
    groups_per_stage: tuple[int, ...] = field(
        default=(4, 4, 4),
        metadata={"help": "group-wise correlation groups per stage (must divide that stage's features)"},
    )
    visibility: bool = field(
        default=True,
        metadata={
            "help": "pixelwise visibility-weighted aggregation (false = plain mean, the CIDER baseline)"
        },
    )
    truncation: bool = field(
        default=True,
        metadata={"help": "zero visibility maps below truncation_threshold before aggregation"},
    )
    frustum_weights: bool = field(
        default=True,
        metadata={
            "help": "aggregation: weight each source's cost, per pixel and depth plane, by whether the "
            "plane's point projects inside that source image (the cascade stages: by the share of their "
            "planes that do), so a source that cannot see a pixel adds no zero cost to its mean; adds no "
            "parameters, but a network must be trained with it (measured: see benchmarks/RESULTS.md)"
        },
    )
    truncation_threshold: float = field(
        default=0.05, metadata={"help": "visibility truncation threshold tau"}
    )
    visibility_channels: int = field(
        default=4, metadata={"help": "base width of the visibility 3D U-Net (x1, x2, x4 per scale)"}
    )
    regularization_channels: int = field(
        default=8, metadata={"help": "base width of the coarse 3D ResNet and the two stacked 3D U-Nets"}
    )
    resnet_blocks: int = field(default=1, metadata={"help": "residual blocks of the coarse 3D ResNet"})
    stage_channels: tuple[int, ...] = field(
        default=(8, 8),
        metadata={"help": "base width of each cascade stage's 3D U-Net (one value per cascade stage)"},
    )
    uncertainty_k: float = field(
        default=1.5,
        metadata={"help": "next-stage range = mean +- k * sigma of the inverse-depth distribution"},
    )
    min_halfwidth_planes: float = field(
        default=1.0,
        metadata={"help": "minimum half-width of a next-stage range, in previous-stage plane spacings"},
    )
    stage_neighbourhood: int = field(
        default=2,
        metadata={
            "help": "next-stage range also spans the min..max of the previous estimate within this many "
            "previous-stage pixels (0: off), so a structure merged at a coarser stage can still separate"
        },
    )
    confidence_planes: int = field(
        default=4, metadata={"help": "confidence = probability mass of this many planes around the estimate"}
    )
    sparse_guidance: bool = field(
        default=True,
        metadata={"help": "Gaussian modulation around sparse depth hints (Poggi et al., CVPR 2019)"},
    )
    guidance_k: float = field(default=10.0, metadata={"help": "guided matching: peak height k"})
    guidance_c: float = field(
        default=1.0, metadata={"help": "guided matching: Gaussian width c, in plane-index units"}
    )
    sparse_prior: bool = field(
        default=True,
        metadata={
            "help": "centre the coarse stage's hypotheses per pixel on a dense prior interpolated "
            "(see prior_fill) from the sparse depth hints, +- prior_halfwidth; pixels of an "
            "image without hints use the global range"
        },
    )
    prior_fill: Literal["affine", "push_pull"] = field(
        default="affine",
        metadata={
            "help": "how the sparse prior is interpolated between hints, in inverse depth: a local "
            "affine fit (exact on planes) or push-pull (a pyramid of hint averages)"
        },
    )
    prior_halfwidth: float = field(
        default=0.3,
        metadata={
            "help": "coarse search half-width around the sparse prior, relative to its inverse depth, "
            "near sparse hints (see prior_growth)"
        },
    )
    prior_growth: float = field(
        default=2.0,
        metadata={
            "help": "the prior's half-width is multiplied by this factor for each radius of "
            "prior_growth_radii within which a pixel has no hint, so pixels far from every SfM point "
            "search a wider window (up to the global range); 1 = a fixed half-width"
        },
    )
    prior_growth_radii: tuple[int, ...] = field(
        default=(8, 16),
        metadata={"help": "radii (coarse pixels, Chebyshev) of prior_growth, each >= 1"},
    )
    channels_last: bool = field(
        default=True, metadata={"help": "use torch.channels_last_3d memory format for the 3D convolutions"}
    )
    conv_dtype: Literal["float32", "bfloat16"] = field(
        default="float32",
        metadata={
            "help": "inference only (training is float32): dtype of the convolutions' inputs, weights and "
            "hidden activations; bfloat16 is faster on CPUs with AVX512-BF16 or AMX and moves the "
            "depths slightly (measured: see benchmarks/RESULTS.md); adds no parameters"
        },
    )
    loss_weights: tuple[float, ...] = field(
        default=(0.5, 0.5, 0.7, 0.7, 0.7),
        metadata={
            "help": "loss weight of each output in PVSNetOutput.depths: coarse ResNet, coarse U-Net 1, "
            "coarse U-Net 2, then one per cascade stage"
        },
    )

    def __post_init__(self) -> None:
        def need(cond: bool, msg: str) -> None:
            if not cond:
                raise ConfigError(f"PVSNetConfig: {msg}")

        need(self.num_stages in (1, 2, 3), f"num_stages must be 1, 2 or 3, got {self.num_stages}")
        need(
            len(self.feature_channels) == 3 and all(c > 0 for c in self.feature_channels),
            f"feature_channels needs 3 positive values (H/4, H/2, H), got {self.feature_channels}",
        )
        need(
            len(self.planes_per_stage) == self.num_stages,
            f"planes_per_stage needs num_stages={self.num_stages} values, got {self.planes_per_stage}",
        )
        need(
            all(d >= PLANE_MULTIPLE and d % PLANE_MULTIPLE == 0 for d in self.planes_per_stage),
            f"planes_per_stage must be positive multiples of {PLANE_MULTIPLE}, got {self.planes_per_stage}",
        )
        need(
            len(self.groups_per_stage) == self.num_stages,
            f"groups_per_stage needs num_stages={self.num_stages} values, got {self.groups_per_stage}",
        )
        for k, g in enumerate(self.groups_per_stage):
            c = self.feature_channels[k]
            need(g > 0 and c % g == 0, f"groups_per_stage[{k}]={g} must divide feature_channels[{k}]={c}")
        need(
            len(self.stage_channels) == self.num_stages - 1 and all(c > 0 for c in self.stage_channels),
            f"stage_channels needs num_stages-1={self.num_stages - 1} positive values, "
            f"got {self.stage_channels}",
        )
        need(
            len(self.loss_weights) == self.num_stages + 2,
            f"loss_weights needs num_stages+2={self.num_stages + 2} values (3 coarse outputs + "
            f"{self.num_stages - 1} cascade stages), got {self.loss_weights}",
        )
        need(all(w >= 0 for w in self.loss_weights), f"loss_weights must be >= 0, got {self.loss_weights}")
        need(
            0.0 <= self.truncation_threshold < 1.0,
            f"truncation_threshold must be in [0, 1), got {self.truncation_threshold}",
        )
        need(self.visibility_channels > 0, f"visibility_channels must be > 0, got {self.visibility_channels}")
        need(
            self.regularization_channels > 0,
            f"regularization_channels must be > 0, got {self.regularization_channels}",
        )
        need(self.resnet_blocks >= 0, f"resnet_blocks must be >= 0, got {self.resnet_blocks}")
        need(self.uncertainty_k > 0, f"uncertainty_k must be > 0, got {self.uncertainty_k}")
        need(
            self.stage_neighbourhood >= 0,
            f"stage_neighbourhood must be >= 0, got {self.stage_neighbourhood}",
        )
        need(
            self.min_halfwidth_planes > 0,
            f"min_halfwidth_planes must be > 0, got {self.min_halfwidth_planes}",
        )
        need(
            1 <= self.confidence_planes <= min(self.planes_per_stage),
            f"confidence_planes must be in [1, {min(self.planes_per_stage)}], got {self.confidence_planes}",
        )
        need(self.guidance_k > 0, f"guidance_k must be > 0, got {self.guidance_k}")
        need(self.guidance_c > 0, f"guidance_c must be > 0, got {self.guidance_c}")
        need(
            self.conv_dtype in ("float32", "bfloat16"),
            f"conv_dtype must be 'float32' or 'bfloat16', got {self.conv_dtype!r}",
        )
        need(
            0.0 < self.prior_halfwidth < 1.0,
            f"prior_halfwidth must be in (0, 1), got {self.prior_halfwidth}",
        )
        need(
            1.0 <= self.prior_growth <= 4.0,
            f"prior_growth must be in [1, 4], got {self.prior_growth}",
        )
        need(
            all(int(r) == r and r >= 1 for r in self.prior_growth_radii),
            f"prior_growth_radii must be integers >= 1, got {self.prior_growth_radii!r}",
        )

    @property
    def num_outputs(self) -> int:
        """Length of :attr:`PVSNetOutput.depths` (3 coarse outputs + one per cascade stage)."""
        return self.num_stages + 2

    def stage_scale(self, stage: int) -> int:
        """Downsampling factor of ``stage`` relative to the input image (4, 2, 1)."""
        return 4 // (2**stage)

    @property
    def output_scales(self) -> tuple[int, ...]:
        """Downsampling factor of each entry of :attr:`PVSNetOutput.depths` (e.g. ``(4, 4, 4, 2, 1)``)."""
        return (4, 4, 4) + tuple(self.stage_scale(k) for k in range(1, self.num_stages))
