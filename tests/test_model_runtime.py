"""The optimised inference path of PVSNet against the straightforward one, and the memory estimate.

The inference path (``torch.no_grad``/``inference_mode``: plane-chunked warping and correlation,
row-chunked upsampling added in place, one image at a time through the feature network, in-place
residual additions) must compute the same depths as the straightforward path that training runs
(autograd enabled), whatever the chunk size.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from test_model_pvsnet import make_inputs as pvsnet_inputs
from tiny_models import TINY_PVSNET

from colmap_pvs.config import replace_config
from colmap_pvs.errors import MemoryBudgetError
from colmap_pvs.model import PVSNet, PVSNetConfig, load_checkpoint, runtime
from colmap_pvs.model.layers import upsample2_add_
from colmap_pvs.model.runtime import check_memory_budget, estimate_peak_memory, largest_size_within

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SHIPPED_CHECKPOINT = Path(__file__).resolve().parents[1] / "colmap_pvs" / "weights" / "pvsnet_default.pt"

#: The shipped checkpoint's architecture (colmap_pvs/weights/pvsnet_default.pt: the defaults), random weights.
SHIPPED_LIKE = PVSNetConfig()


def make_inputs(B: int, N: int, H: int, W: int, seed: int = 0):
    """``test_model_pvsnet``'s rig (depths 1..6) plus sparse hints on 2 % of the pixels."""
    images, intrinsics, poses, dmin, dmax = pvsnet_inputs(B, N, H, W, seed)
    g = torch.Generator().manual_seed(seed + 1)
    sparse = torch.zeros(B, 1, H, W)
    hit = torch.rand(B, 1, H, W, generator=g) < 0.02
    sparse[hit] = 1.0 + 5.0 * torch.rand(int(hit.sum()), generator=g)
    return images, intrinsics, poses, dmin, dmax, sparse


def _randomize_batch_norms(model: torch.nn.Module, seed: int = 1) -> None:
    """Non-trivial running statistics, so the folded batch norms are exercised."""
    g = torch.Generator().manual_seed(seed)
    for m in model.modules():
        if isinstance(m, (torch.nn.BatchNorm2d, torch.nn.BatchNorm3d)):
            m.running_mean.copy_(0.1 * torch.randn(m.running_mean.shape, generator=g))
            m.running_var.copy_(0.5 + torch.rand(m.running_var.shape, generator=g))
            m.weight.data.copy_(0.5 + torch.rand(m.weight.shape, generator=g))
            m.bias.data.copy_(0.1 * torch.randn(m.bias.shape, generator=g))


@pytest.mark.parametrize(
    "config, B, N, H, W, chunk",
    [
        (SHIPPED_LIKE, 1, 4, 64, 80, 4096),  # tiny chunks: one plane / a few rows at a time
        (SHIPPED_LIKE, 2, 3, 48, 64, None),  # batch of 2, default chunk size
        (TINY_PVSNET, 1, 3, 45, 70, 2048),
    ],
    ids=["shipped-like-small-chunks", "shipped-like-batch2", "tiny"],
)
def test_inference_path_matches_reference_path(monkeypatch, config, B, N, H, W, chunk):
    torch.manual_seed(0)
    model = PVSNet(config).eval()
    _randomize_batch_norms(model)
    inputs = make_inputs(B, N, H, W)
    if chunk is not None:
        monkeypatch.setattr(runtime, "CHUNK_BYTES", chunk)
    with torch.inference_mode():
        fast = model(*inputs[:5], sparse_depth=inputs[5])
    with torch.enable_grad():  # the straightforward path (the one training runs)
        ref = model(*inputs[:5], sparse_depth=inputs[5])
    # Random weights make the depths depend only weakly on the cost volumes (a plane shifted by one
    # chunk moves them by ~1e-4 of the range): the tolerance sits between that and float rounding (~3e-7).
    depth_range = 6.0 - 1.0
    for a, b in zip(fast.depths, ref.depths, strict=True):
        assert a.shape == b.shape
        assert float((a - b.detach()).abs().max()) / depth_range < 2e-5
    torch.testing.assert_close(fast.visibility, ref.visibility.detach(), atol=1e-5, rtol=0)
    torch.testing.assert_close(fast.confidence, ref.confidence.detach(), atol=1e-4, rtol=0)


@pytest.mark.parametrize("per_pixel", [False, True], ids=["planes", "per-pixel"])
@pytest.mark.parametrize("weighted", [False, True], ids=["plain", "weighted-accumulated"])
def test_chunked_two_view_cost_matches_reference(monkeypatch, per_pixel, weighted):
    """The cost volume itself (what the depths depend on only weakly with random weights)."""
    monkeypatch.setattr(runtime, "CHUNK_BYTES", 3000)  # 1 plane at a time
    model = PVSNet(SHIPPED_LIKE).eval()
    g = torch.Generator().manual_seed(0)
    B, N, C, h, w, D = 2, 3, 16, 12, 20, 8
    feats = torch.randn(B, N, C, h, w, generator=g)
    _, K, poses, dmin, dmax, _ = make_inputs(B, N, 4 * h, 4 * w)
    K = K.double() * torch.tensor([0.25, 0.25, 1.0], dtype=torch.float64).view(3, 1)
    poses = poses.double()
    if per_pixel:
        depths = 1.0 + 5.0 * torch.rand(B, D, h, w, generator=g)
    else:
        depths = torch.linspace(1.0, 6.0, D).expand(B, D).clone()
    weight = torch.rand(B, 1, h, w, generator=g) if weighted else None
    acc = torch.randn(B, 4, D, h, w, generator=g) if weighted else None
    def cost():
        start = None if acc is None else acc.clone()
        return model._two_view_cost(feats, K, poses, 2, depths, 0, weight, start)

    with torch.enable_grad():
        ref = cost()
    with torch.no_grad():
        fast = cost()
    assert fast.shape == ref.shape == (B, 4, D, h, w)
    torch.testing.assert_close(fast, ref.detach(), atol=1e-5, rtol=1e-5)


def test_shipped_checkpoint_inference_path_matches_reference_path():
    """Trained weights (sensitive to the matching cost) on a small random-texture rig."""
    model, _ = load_checkpoint(SHIPPED_CHECKPOINT)
    inputs = make_inputs(1, 3, 96, 128)
    with torch.inference_mode():
        fast = model(*inputs[:5], sparse_depth=inputs[5])
    with torch.enable_grad():
        ref = model(*inputs[:5], sparse_depth=inputs[5])
    diff = (fast.depth - ref.depth.detach()).abs() / (6.0 - 1.0)
    assert float(diff.max()) < 1e-3 and float(diff.median()) < 1e-5


@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize("rows", [1, 2, 3, 5, 1 << 20])  # input rows per band
@pytest.mark.parametrize("batch", [1, 2])
def test_upsample2_add_equals_interpolate_plus_add(monkeypatch, channels_last, rows, batch):
    row_bytes = batch * 3 * 4 * 2 * 5 * 4  # upsample2_add_'s budget of one input row of x below
    monkeypatch.setattr(runtime, "CHUNK_BYTES", row_bytes * (rows + 2))
    g = torch.Generator().manual_seed(0)
    for h in (1, 2, 3, 4, 7, 12):
        x = torch.randn(batch, 3, 2, h, 5, generator=g)
        skip = torch.randn(batch, 3, 4, 2 * h, 10, generator=g)
        if channels_last:
            x = x.contiguous(memory_format=torch.channels_last_3d)
            skip = skip.contiguous(memory_format=torch.channels_last_3d)
        expected = F.interpolate(x, scale_factor=2.0, mode="trilinear", align_corners=False) + skip
        out = upsample2_add_(x, skip.clone())
        assert torch.equal(out, expected), (h, float((out - expected).abs().max()))
    with pytest.raises(ValueError, match="not twice"):
        upsample2_add_(x, skip[:, :, :, :-1])


def test_upsample2_add_splits_a_single_band_into_a_batch_of_two_halves(monkeypatch):
    """With one batch entry the band is interpolated as two stacked halves (both cores), and every row of
    ``out`` is added to exactly once."""
    calls = []
    interpolate = F.interpolate

    def spy(t, **kw):
        calls.append(tuple(t.shape))
        return interpolate(t, **kw)

    monkeypatch.setattr(F, "interpolate", spy)
    x = torch.randn(1, 2, 3, 9, 4).contiguous(memory_format=torch.channels_last_3d)
    out = upsample2_add_(x, torch.zeros(1, 2, 6, 18, 8).contiguous(memory_format=torch.channels_last_3d))
    assert calls == [(2, 2, 3, 6, 4)]
    monkeypatch.setattr(F, "interpolate", interpolate)
    torch.testing.assert_close(out, F.interpolate(x, scale_factor=2.0, mode="trilinear", align_corners=False),
                               atol=0, rtol=0)


def test_memory_estimate_grows_with_size_and_views():
    cfg = SHIPPED_LIKE
    small = estimate_peak_memory(480, 640, 5, cfg)
    assert estimate_peak_memory(960, 1280, 5, cfg) > 3.5 * small - 4 * runtime.BASELINE_BYTES
    assert estimate_peak_memory(480, 640, 11, cfg) > small
    assert estimate_peak_memory(480, 640, 5, replace_config(cfg, num_stages=1, planes_per_stage=(32,),
                                groups_per_stage=(4,), stage_channels=(),
                                loss_weights=(0.5, 0.5, 0.7))) < small
    with pytest.raises(ValueError, match="num_views"):
        estimate_peak_memory(480, 640, 1, cfg)


def test_memory_budget_refuses_up_front_and_names_a_size():
    cfg = SHIPPED_LIKE
    need = estimate_peak_memory(2000, 3000, 5, cfg)
    check_memory_budget(2000, 3000, 5, cfg, budget_bytes=need + 1)  # fits: no error
    budget = need // 3
    with pytest.raises(MemoryBudgetError, match=r"3000x2000.*N=5.*max_image_size") as info:
        check_memory_budget(2000, 3000, 5, cfg, budget_bytes=budget)
    # The size it names fits the budget, and is the largest such (within 1 %).
    h, w = largest_size_within(2000, 3000, 5, cfg, budget)
    assert str(max(h, w)) in str(info.value)
    assert estimate_peak_memory(h, w, 5, cfg) <= budget
    assert estimate_peak_memory(int(h * 1.02) + 16, int(w * 1.02) + 16, 5, cfg) > budget
    assert abs(w / h - 1.5) < 0.05  # the aspect ratio is kept


def test_bfloat16_convolutions_are_inference_only():
    """``conv_dtype="bfloat16"``: same parameters, float32 outputs, close depths; training stays float32."""
    torch.manual_seed(0)
    fp32 = PVSNet(SHIPPED_LIKE).eval()
    _randomize_batch_norms(fp32)
    bf16 = PVSNet(replace_config(SHIPPED_LIKE, conv_dtype="bfloat16")).eval()
    bf16.load_state_dict(fp32.state_dict(), strict=True)
    assert fp32.state_dict().keys() == bf16.state_dict().keys()
    inputs = make_inputs(1, 3, 48, 64)
    with torch.inference_mode():
        a = fp32(*inputs[:5], sparse_depth=inputs[5])
        b = bf16(*inputs[:5], sparse_depth=inputs[5])
    assert b.depth.dtype == b.confidence.dtype == b.visibility.dtype == torch.float32
    diff = (a.depth - b.depth).abs() / (6.0 - 1.0)
    assert 0 < float(diff.max()) < 0.05 and float(diff.median()) < 5e-3
    with torch.enable_grad():
        ga = fp32(*inputs[:5], sparse_depth=inputs[5])
        gb = bf16(*inputs[:5], sparse_depth=inputs[5])
    torch.testing.assert_close(ga.depth, gb.depth, atol=0, rtol=0)
