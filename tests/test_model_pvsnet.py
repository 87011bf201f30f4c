"""Whole-model tests of PVSNet: shapes at odd sizes and N, input checks, padding, switches, guidance."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
import torch.nn.functional as F
from tiny_models import TINY_PVSNET

from colmap_pvs.config import replace_config
from colmap_pvs.errors import ShapeError
from colmap_pvs.model import PVSNet, PVSNetConfig, PVSNetOutput

pytestmark = pytest.mark.usefixtures("one_torch_thread")


TINY = TINY_PVSNET


def make_inputs(B: int, N: int, H: int, W: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    images = torch.rand(B, N, 3, H, W, generator=g)
    K = torch.tensor([[0.9 * W, 0.0, W / 2], [0.0, 0.9 * W, H / 2], [0.0, 0.0, 1.0]])
    intrinsics = K.expand(B, N, 3, 3).clone()
    poses = torch.eye(4).expand(B, N, 4, 4).clone()
    for i in range(1, N):
        poses[:, i, 0, 3] = 0.1 * i * (-1) ** i
        poses[:, i, 1, 3] = 0.03 * i
    return images, intrinsics, poses, torch.full((B,), 1.0), torch.full((B,), 6.0)


def check_output(out: PVSNetOutput, cfg: PVSNetConfig, B: int, N: int, H: int, W: int) -> None:
    h4, w4 = -(-H // 4), -(-W // 4)
    assert out.depth.shape == (B, H, W)
    assert out.confidence.shape == (B, H, W)
    assert out.visibility.shape == (B, N - 1, h4, w4)
    assert len(out.depths) == len(cfg.loss_weights) == len(out.confidences)
    for d, c, s in zip(out.depths, out.confidences, cfg.output_scales, strict=True):
        assert d.shape == c.shape == (B, -(-H // s), -(-W // s))
    for t in [out.depth, out.confidence, out.visibility, *out.depths]:
        assert torch.isfinite(t).all()
    assert torch.all((out.confidence >= 0) & (out.confidence <= 1))
    assert torch.all((out.visibility >= 0) & (out.visibility <= 1))
    assert torch.all(out.depth >= 1.0 - 1e-3) and torch.all(out.depth <= 6.0 + 1e-3)


@pytest.mark.parametrize(
    "B, N, H, W", [(1, 3, 48, 64), (1, 2, 45, 70), (2, 5, 45, 70), (1, 3, 17, 33)], ids=str
)
def test_shapes_inference(B, N, H, W):
    model = PVSNet(TINY).eval()
    with torch.inference_mode():
        out = model(*make_inputs(B, N, H, W))
    check_output(out, TINY, B, N, H, W)
    assert torch.equal(out.depth, out.depths[-1])


def test_training_forward_backward_at_odd_size():
    model = PVSNet(TINY).train()
    out = model(*make_inputs(1, 3, 45, 70))
    check_output(out, TINY, 1, 3, 45, 70)
    loss = sum(w * d.mean() for w, d in zip(TINY.loss_weights, out.depths, strict=True))
    loss.backward()
    grads = [p.grad for p in model.parameters() if p.requires_grad]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert (
        model.visibility_net.unet.conv0.weight.grad.abs().sum() > 0
    )  # visibility learns from the depth loss


def test_default_config_small_input():
    cfg = PVSNetConfig()
    assert cfg.loss_weights == (0.5, 0.5, 0.7, 0.7, 0.7) and len(cfg.output_scales) == 5
    model = PVSNet().eval()
    images, K, poses, dmin, dmax = make_inputs(1, 3, 40, 56)
    sparse = torch.zeros(1, 1, 40, 56)
    sparse[..., 3::8, 5::8] = 3.0
    with torch.inference_mode():
        out = model(images, K, poses, dmin, dmax)
        hinted = model(images, K, poses, dmin, dmax, sparse_depth=sparse)
    check_output(out, cfg, 1, 3, 40, 56)
    check_output(hinted, cfg, 1, 3, 40, 56)
    assert out.prior_depth is None and hinted.prior_depth is not None


def test_cameras_are_composed_in_float64_from_the_values_given():
    """float32 cameras (as ``stereo`` passes them) give exactly what their values in float64 give."""
    model = PVSNet(TINY).eval()
    images, K, poses, dmin, dmax = make_inputs(1, 3, 32, 48)
    K, poses = K.float(), poses.float()
    with torch.inference_mode():
        single = model(images, K, poses, dmin, dmax)
        double = model(images, K.double(), poses.double(), dmin, dmax)
    for a, b in zip(single.depths + single.confidences, double.depths + double.confidences, strict=True):
        assert torch.equal(a, b)


def test_padding_is_bottom_right_replicate_and_cropped_exactly():
    model = PVSNet(TINY).eval()
    images, K, poses, dmin, dmax = make_inputs(1, 3, 45, 70)
    padded = F.pad(images.view(3, 3, 45, 70), (0, 10, 0, 3), mode="replicate").view(1, 3, 3, 48, 80)
    with torch.inference_mode():
        out = model(images, K, poses, dmin, dmax)
        ref = model(padded, K, poses, dmin, dmax)
    torch.testing.assert_close(out.depth, ref.depth[:, :45, :70])
    torch.testing.assert_close(out.depths[0], ref.depths[0][:, :12, :18])
    torch.testing.assert_close(out.visibility, ref.visibility[:, :, :12, :18])


@pytest.mark.parametrize("num_stages", [1, 2])
def test_fewer_stages_still_give_full_resolution(num_stages):
    cfg = replace_config(
        TINY,
        num_stages=num_stages,
        planes_per_stage=TINY.planes_per_stage[:num_stages],
        groups_per_stage=TINY.groups_per_stage[:num_stages],
        stage_channels=TINY.stage_channels[: num_stages - 1],
        loss_weights=TINY.loss_weights[: num_stages + 2],
    )
    model = PVSNet(cfg).eval()
    with torch.inference_mode():
        out = model(*make_inputs(1, 2, 45, 70))
    check_output(out, cfg, 1, 2, 45, 70)


def test_visibility_off():
    cfg = replace_config(TINY, visibility=False)
    model = PVSNet(cfg).eval()
    assert model.visibility_net is None
    with torch.inference_mode():
        out = model(*make_inputs(1, 3, 32, 32))
    check_output(out, cfg, 1, 3, 32, 32)
    assert torch.all(out.visibility == 1)


def test_truncation_zeroes_low_visibility_in_output():
    """The output visibility is the visibility network's, zeroed at or below the threshold (a threshold
    between its values, so that both sides are seen)."""
    torch.manual_seed(0)
    inputs = make_inputs(1, 3, 32, 32)
    raw_model = PVSNet(replace_config(TINY, truncation=False)).eval()
    with torch.no_grad():  # a fresh visibility head gives 0.5 everywhere: spread it
        for p in raw_model.visibility_net.parameters():
            p.add_(0.3 * torch.randn_like(p))
    with torch.inference_mode():
        raw = raw_model(*inputs).visibility
    tau = float(raw.median())
    assert float(raw.min()) < tau < float(raw.max()) < 1, "the visibility network's maps are constant"
    model = PVSNet(replace_config(TINY, truncation_threshold=tau)).eval()
    model.load_state_dict(raw_model.state_dict())
    with torch.inference_mode():
        v = model(*inputs).visibility
    assert v.shape == raw.shape and bool((v == 0).any()) and bool((v > tau).any())
    assert torch.equal(v, torch.where(raw > tau, raw, torch.zeros_like(raw)))


@pytest.mark.parametrize(
    "args, match",
    [
        (lambda a: (a[0][0], *a[1:]), "images"),
        (lambda a: (a[0][:, :1], a[1][:, :1], a[2][:, :1], *a[3:]), "N >= 2"),
        (lambda a: (a[0], a[1][:, :, :2], *a[2:]), "intrinsics"),
        (lambda a: (a[0], a[1], a[2][:, :, :3], *a[3:]), "cam_from_world"),
        (lambda a: (*a[:3], a[3][None], a[4]), "depth_min"),
        (lambda a: (*a[:4], torch.ones(2)), "depth_max"),
        (lambda a: (*a, torch.zeros(1, 1, 16, 20)), "sparse_depth"),
        (lambda a: (a[0].to(torch.uint8), *a[1:]), "floating point"),
    ],
)
def test_shape_errors_name_the_shape(args, match):
    model = PVSNet(TINY).eval()
    inputs = make_inputs(1, 3, 16, 16)
    with pytest.raises(ShapeError, match=match):
        model(*args(inputs))


def test_depth_range_errors():
    model = PVSNet(TINY).eval()
    images, K, poses, _, _ = make_inputs(1, 2, 16, 16)
    with pytest.raises(ValueError, match="depth_min"):
        model(images, K, poses, torch.zeros(1), torch.ones(1))
    with pytest.raises(ValueError, match="depth_max"):
        model(images, K, poses, torch.ones(1), torch.ones(1))


def test_sparse_guidance_moves_depth_toward_hint():
    torch.manual_seed(0)
    inputs = make_inputs(1, 3, 32, 32)
    hint_depth = 4.5
    sparse = torch.zeros(1, 1, 32, 32)
    sparse[..., ::2, ::2] = hint_depth  # hints in every 2x2 block: every stage pixel is hinted
    base = PVSNet(TINY).eval()
    with torch.inference_mode():
        plain = base(*inputs, sparse_depth=sparse)
        guided_model = PVSNet(replace_config(TINY, sparse_guidance=True)).eval()
        guided_model.load_state_dict(base.state_dict())  # no retraining
        guided = guided_model(*inputs, sparse_depth=sparse)
        assert torch.isfinite(guided.depth).all()
        assert not torch.allclose(guided.depth, plain.depth)
        # Guidance off: the hints are ignored.
        torch.testing.assert_close(base(*inputs).depth, plain.depth)


def test_sparse_prior_confines_coarse_depth_to_the_hint_window():
    torch.manual_seed(0)
    inputs = make_inputs(1, 3, 32, 48)
    sparse = torch.zeros(1, 1, 32, 48)
    sparse[..., 2::8, 3::8] = 2.0  # a hint in every 8x8 block
    sparse[..., 18:, :] = torch.where(sparse[..., 18:, :] > 0, 3.0, 0.0)  # a farther lower half
    r = 0.1
    model = PVSNet(replace_config(TINY, sparse_prior=True, prior_halfwidth=r)).eval()
    with torch.inference_mode():
        out = model(*inputs, sparse_depth=sparse)
        plain = model(*inputs)  # no hints: the global range, as without the switch
        base = PVSNet(TINY).eval()
        base.load_state_dict(model.state_dict())
        torch.testing.assert_close(plain.depth, base(*inputs).depth)
    check_output(out, model.config, 1, 3, 32, 48)
    # Coarse depths regress over planes inside prior * (1 +- r) in inverse depth, the prior lying
    # between the two hints' inverse depths 1/3 and 1/2, widened by a quarter of their difference.
    lo, hi = 1 / 3 - 1 / 24, 1 / 2 + 1 / 24
    for d in out.depths[:3]:
        inv = 1.0 / d
        assert torch.all(inv <= (1 + r) * hi + 1e-5) and torch.all(inv >= (1 - r) * lo - 1e-5)
        assert d.max() - d.min() > 0.3  # the two halves stay apart
    # The prior the planes were centred on comes out at H/4: near the hints' depths, 0 nowhere.
    assert out.prior_depth is not None and out.prior_depth.shape == (1, 8, 12)
    assert torch.all(out.prior_depth > 1 / hi - 1e-3) and torch.all(out.prior_depth < 1 / lo + 1e-3)
    assert out.prior_depth[0, 0].mean() < 2.2 and out.prior_depth[0, -1].mean() > 2.8
    assert plain.prior_depth is None


def test_import_sets_no_global_torch_state():
    code = (
        "import torch\n"
        "s = lambda: (torch.get_num_threads(), torch.get_default_dtype(), torch.is_grad_enabled(),"
        " torch.backends.mkldnn.enabled, torch.are_deterministic_algorithms_enabled(),"
        " torch.get_float32_matmul_precision())\n"
        "a = s()\n"
        "import colmap_pvs.model\n"
        "assert s() == a, (a, s())\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_frustum_weights_ignore_a_source_that_sees_nothing():
    """With ``frustum_weights`` a source facing away (every plane's point behind it) changes nothing:
    the volumes the regularizers get and the depth with 3 views equal those with 2. Without them its
    zero cost dilutes the mean."""
    torch.manual_seed(0)
    cfg = replace_config(TINY, truncation=False, frustum_weights=True)
    model = PVSNet(cfg).eval()
    plain = PVSNet(replace_config(cfg, frustum_weights=False)).eval()
    plain.load_state_dict(model.state_dict())
    images, K, poses, dmin, dmax = make_inputs(1, 3, 48, 64, seed=3)
    poses[:, 1] = torch.eye(4)
    poses[:, 1, 2, 3] = 0.2  # behind the reference on its axis: sees all it sees, with parallax
    poses[:, 1, 0, 3] = 0.05
    poses[:, 2] = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0]))  # faces away: sees none of it

    def run(net, n):
        volumes = []
        hooks = [m.register_forward_pre_hook(lambda _m, args: volumes.append(args[0].clone()))
                 for m in (net.coarse, *net.stages)]
        with torch.inference_mode():
            out = net(images[:, :n], K[:, :n], poses[:, :n], dmin, dmax)
        for h in hooks:
            h.remove()
        return out.depth, volumes

    two, v_two = run(model, 2)
    three, v_three = run(model, 3)
    _, v_two_plain = run(plain, 2)
    _, v_diluted = run(plain, 3)
    assert len(v_two) == cfg.num_stages
    for a, b, c, d in zip(v_two, v_three, v_two_plain, v_diluted, strict=True):
        scale = a.abs().max()  # an untrained network's volumes are small: compare relative to them
        assert scale > 0
        assert (b - a).abs().max() <= 1e-4 * scale
        assert (c - a).abs().max() <= 1e-4 * scale  # it sees all the reference sees
        assert (d - a).abs().max() > 0.1 * scale  # diluted by the blind source's zeros
    torch.testing.assert_close(three, two, atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("grad", [False, True], ids=["inference", "autograd"])
def test_cost_accumulator_takes_per_plane_weights(grad):
    """``[B, D, h, w]`` weights give ``sum_i w_i C_i / sum_i w_i`` per plane, the plain mean where
    every weight is 0 (``frustum_weights`` at the coarse stage)."""
    from colmap_pvs.model.visibility import CostAccumulator

    g = torch.Generator().manual_seed(1)
    costs = [torch.rand(1, 3, 4, 5, 6, generator=g) for _ in range(3)]
    weights = [torch.rand(1, 4, 5, 6, generator=g) for _ in range(3)]
    for w in weights:
        w[:, 1] = 0.0  # plane 1: no source sees it
    weights[0][:, 2] = 0.0  # plane 2: source 0 does not
    expected = sum(c * w.unsqueeze(1) for c, w in zip(costs, weights, strict=True))
    expected = expected / sum(weights).unsqueeze(1)
    expected[:, :, 1] = sum(costs)[:, :, 1] / 3
    with torch.set_grad_enabled(grad):
        acc = CostAccumulator()
        for c, w in zip(costs, weights, strict=True):
            acc.add(c.clone(), w)
        got = acc.result()
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)
    assert not torch.allclose(got[:, :, 2], (sum(costs) / 3)[:, :, 2])  # a weighted plane differs


def test_frustum_weights_at_sizes_that_need_padding():
    model = PVSNet(replace_config(TINY, frustum_weights=True)).eval()
    with torch.inference_mode():
        out = model(*make_inputs(1, 3, 45, 70))
    check_output(out, model.config, 1, 3, 45, 70)


def test_frustum_weights_train_with_gradients():
    model = PVSNet(replace_config(TINY, frustum_weights=True)).train()
    out = model(*make_inputs(1, 3, 32, 48))
    sum(d.mean() for d in out.depths).backward()
    grads = [p.grad for p in model.parameters() if p.requires_grad]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)


def test_a_views_planes_are_sampled_in_parallel_parts_with_the_same_output(monkeypatch):
    """With two torch threads one view's planes are sampled as two batch entries (the CPU's ``grid_sample``
    runs batch entries in parallel, not the rows of one): the output is the same, bit for bit."""
    import colmap_pvs.model.pvsnet as pvsnet_module

    cases = ((1, 8, 2), (1, 7, 2), (2, 8, 2), (1, 8, 1), (1, 9, 3))  # (batch, planes, threads)
    assert [pvsnet_module._sampling_parts(*case) for case in cases] == [2, 1, 1, 1, 3]
    real, used = pvsnet_module._sampling_parts, []

    def two_threads(batch, planes, threads):
        used.append(real(batch, planes, 2))
        return used[-1]

    model = PVSNet().eval()
    inputs = make_inputs(1, 3, 40, 56)
    outs = []
    for parts in (two_threads, lambda batch, planes, threads: 1):
        monkeypatch.setattr(pvsnet_module, "_sampling_parts", parts)
        with torch.inference_mode():
            outs.append(model(*inputs))
    assert max(used) == 2
    for name in ("depth", "confidence", "visibility", "depths", "confidences"):
        split, whole = getattr(outs[0], name), getattr(outs[1], name)
        pairs = zip(split, whole, strict=True) if isinstance(split, list | tuple) else [(split, whole)]
        assert all(torch.equal(a, b) for a, b in pairs), name
