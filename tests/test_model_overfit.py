"""Overfitting one synthetic sample: the whole model (warping, visibility, cascade, loss) trains."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tiny_models import TINY_PVSNET

from colmap_pvs.config import replace_config
from colmap_pvs.model import PVSNet
from colmap_pvs.model.planes import render_plane
from colmap_pvs.train.losses import depth_loss

H, W = 48, 64


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def plane_sample():
    """A slanted textured plane seen by 3 cameras (exact renderings), with ground-truth depth."""
    K = np.array([[56.0, 0.0, 32.0], [0.0, 56.0, 24.0], [0.0, 0.0, 1.0]])
    poses = []
    for tx, ty in [(0.0, 0.0), (0.25, 0.02), (-0.2, -0.05)]:
        T = np.eye(4)
        T[:3, 3] = [-tx, -ty, 0.0]
        poses.append(T)
    kw = dict(normal=(0.2, -0.1, 1.0), offset=3.0, period=0.35)
    renders = [render_plane(K, T, H, W, **kw) for T in poses]
    images = torch.tensor(np.stack([r[0] for r in renders]), dtype=torch.float32)[None]
    depth = torch.tensor(renders[0][1], dtype=torch.float32)[None]
    intrinsics = torch.tensor(K, dtype=torch.float32).expand(1, 3, 3, 3).clone()
    cam_from_world = torch.tensor(np.stack(poses), dtype=torch.float32)[None]
    return images, intrinsics, cam_from_world, torch.tensor([1.5]), torch.tensor([8.0]), depth


def test_overfit_single_sample():
    torch.manual_seed(0)
    cfg = replace_config(TINY_PVSNET, planes_per_stage=(16, 8, 4), regularization_channels=8)
    model = PVSNet(cfg).train()
    *inputs, depth = plane_sample()
    assert (depth > 2.0).all() and (depth < 5.0).all()
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(25):
        opt.zero_grad(set_to_none=True)
        out = model(*inputs)
        loss = depth_loss(out.depths, depth, inputs[3], inputs[4], cfg.loss_weights,
                          scales=cfg.output_scales).total
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.isfinite(losses).all()
    final = float(np.mean(losses[-3:]))
    assert final < 0.5 * losses[0], losses

    # Guided matching (Poggi et al.) on the trained weights, no retraining: hints at a wrong depth
    # pull the prediction at hinted pixels toward them.
    model.eval()
    guided = PVSNet(replace_config(cfg, sparse_guidance=True)).eval()
    guided.load_state_dict(model.state_dict())
    before, after = [], []
    with torch.inference_mode():
        plain = model(*inputs).depth
        for factor in (0.8, 1.25):
            hint = torch.zeros(1, 1, H, W)
            hint[..., ::4, ::4] = depth[:, None, ::4, ::4] * factor
            mask = hint[:, 0] > 0
            pred = guided(*inputs, sparse_depth=hint).depth
            before.append((plain[mask] - hint[:, 0][mask]).abs().mean())
            after.append((pred[mask] - hint[:, 0][mask]).abs().mean())
    assert sum(after) < 0.9 * sum(before), (after, before)
