"""The network of the ``stereo`` step: checkpoint loading and one forward pass."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..config import replace_config
from ..errors import CheckpointError
from . import config as settings
from .config import MODEL_SWITCHES, StereoConfig


def base_checkpoint_path(config: StereoConfig) -> Path:
    """The checkpoint a run starts from (``config.checkpoint``, else the shipped default)."""
    return Path(config.checkpoint) if config.checkpoint is not None else settings.DEFAULT_CHECKPOINT


def load_stereo_model(config: StereoConfig, device: torch.device):
    """Load the checkpoint (``weights_only=True``) and apply the config's overrides."""
    from ..model import PVSNet, load_checkpoint

    path = base_checkpoint_path(config)
    if config.checkpoint is None and not path.exists():
        raise CheckpointError(
            f"no trained default checkpoint is shipped at {str(path)!r}; pass --checkpoint PATH "
            "(random weights never produce maps)"
        )
    model, meta = load_checkpoint(path, map_location="cpu")
    # Switches that add no parameters can be flipped on a trained model.
    requested = {name: getattr(config.photometric, name) for name in MODEL_SWITCHES}
    changes = {
        name: value == "on"
        for name, value in requested.items()
        if value != "checkpoint" and getattr(model.config, name) != (value == "on")
    }
    if changes:
        state = model.state_dict()
        model = PVSNet(replace_config(model.config, **changes))
        model.load_state_dict(state)
    model.eval().to(device)
    return model, path, meta


#: Relative difference between the final depth and the previous cascade stage's at which the photometric
#: score falls by ``1 / e`` (:func:`cascade_confidence`).
STAGE_AGREEMENT_SCALE = 0.05


def cascade_confidence(out, output_scales: tuple[int, ...]) -> torch.Tensor:
    """``[B, H, W]`` the photometric score of a network output before the prior: the final stage's
    probability mass around its estimate, times the coarse stage's (the last output at the coarsest
    scale), times ``exp(-|log(d / d_prev)| / STAGE_AGREEMENT_SCALE)`` with ``d_prev`` the previous
    cascade stage's depth (both bilinearly upsampled; a network without a cascade: its mass alone).
    The stages see the cost at different resolutions, so where they disagree the depth is often
    wrong (chosen on one frame set and checked on another: ``benchmarks/RESULTS.md``, "A photometric
    score from the whole cascade")."""
    conf = out.confidence
    staged = out.confidences is not None and len(output_scales) == len(out.depths) == len(out.confidences)
    if not staged or len(out.depths) < 2 or output_scales[-1] == max(output_scales):
        return conf
    size = conf.shape[-2:]

    def up(t):
        return F.interpolate(t[:, None].float(), size=size, mode="bilinear", align_corners=False)[:, 0]

    coarse = max(i for i, s in enumerate(output_scales) if s == max(output_scales))
    ratio = out.depth.clamp_min(1e-12) / up(out.depths[-2]).clamp_min(1e-12)
    return conf * up(out.confidences[coarse]) * torch.exp(-ratio.log().abs() / STAGE_AGREEMENT_SCALE)


def estimate_depth(model, images, intrinsics, poses, depth_range, sparse_depth, device):
    """Run the network on one reference.

    Args:
        images: ``[N, 3, H, W]`` float32 in ``[0, 1]``, reference at index 0.
        intrinsics: ``[N, 3, 3]``; poses: ``[N, 4, 4]`` cam_from_world.
        depth_range: ``(d_min, d_max)``; sparse_depth: ``[H, W]`` (0 = no point).

    Every input goes to the network as float32, the cameras too: the network composes them in float64
    from these rounded values (:class:`~colmap_pvs.model.PVSNet`), as every map so far was made.

    Returns:
        depth ``[H, W]``, score ``[H, W]`` (:func:`cascade_confidence`), coarse visibility
        ``[N-1, ceil(H/4), ceil(W/4)]`` and
        the sparse prior's coarse depth ``[ceil(H/4), ceil(W/4)]`` (``None`` without one), numpy.
    """
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32), device=device)[None]  # noqa: E731
    with torch.inference_mode():
        out = model(
            t(images),
            t(intrinsics),
            t(poses),
            t(depth_range[0]),
            t(depth_range[1]),
            sparse_depth=t(sparse_depth)[:, None],
        )
    vis = out.visibility[0].float().cpu().numpy()
    prior = None if out.prior_depth is None else out.prior_depth[0].float().cpu().numpy()
    conf = cascade_confidence(out, model.config.output_scales)
    return out.depth[0].cpu().numpy(), conf[0].float().cpu().numpy(), vis, prior
