"""The network of the ``stereo`` step: device, checkpoint loading and one forward pass."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..config import replace_config
from ..errors import CheckpointError, ColmapPVSError
from . import config as settings
from .config import MODEL_SWITCHES, StereoConfig


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA when available."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ColmapPVSError("--device cuda was requested but torch.cuda.is_available() is False")
    return torch.device(name)


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


def estimate_depth(model, images, intrinsics, poses, depth_range, sparse_depth, device):
    """Run the network on one reference.

    Args:
        images: ``[N, 3, H, W]`` float32 in ``[0, 1]``, reference at index 0.
        intrinsics: ``[N, 3, 3]``; poses: ``[N, 4, 4]`` cam_from_world.
        depth_range: ``(d_min, d_max)``; sparse_depth: ``[H, W]`` (0 = no point).

    Returns:
        depth ``[H, W]``, confidence ``[H, W]``, coarse visibility ``[N-1, ceil(H/4), ceil(W/4)]`` and
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
    return out.depth[0].cpu().numpy(), out.confidence[0].cpu().numpy(), vis, prior
