"""The network exports (issue 57 item 1): ``torch.export`` traces it, the export-only branches compute the
same maps, and, where onnxruntime is installed by hand (it is no dependency), ONNX Runtime's maps match
torch's for the shipped model."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from test_model_runtime import SHIPPED_CHECKPOINT
from test_model_runtime import make_inputs as hinted_inputs
from tiny_models import TINY_PVSNET

from colmap_pvs.config import replace_config
from colmap_pvs.model import PVSNet, cost, layers, load_checkpoint, pvsnet, visibility, warping

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
if str(BENCHMARKS) not in sys.path:
    sys.path.insert(0, str(BENCHMARKS))

import onnx_runtime  # noqa: E402  (benchmarks/ is no package: on sys.path above)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: The tiny network with every switch of the shipped model that adds a branch: sparse guidance, the affine
#: sparse prior (a 3x3 solve per pixel), frustum weights (a per-plane mask), the stage neighbourhood.
TINY_SHIPPED_SWITCHES = replace_config(TINY_PVSNET, sparse_guidance=True, sparse_prior=True,
                                       prior_fill="affine", frustum_weights=True, stage_neighbourhood=2)


def _tiny_model() -> PVSNet:
    torch.manual_seed(0)
    return PVSNet(TINY_SHIPPED_SWITCHES).eval()


def _pretend_exporting(monkeypatch) -> None:
    for module in (pvsnet, warping, cost, visibility, layers):
        monkeypatch.setattr(module, "exporting", lambda: True)


def test_export_branches_compute_the_same_maps(monkeypatch):
    """What an exported graph computes (closed-form 3x3 solves and inverses, unconditional masks, plain
    convolutions, no value checks), run eagerly, gives torch's maps up to float rounding."""
    model = _tiny_model()
    inputs = hinted_inputs(1, 3, 64, 80)
    with torch.no_grad():
        ref = model(*inputs[:5], sparse_depth=inputs[5])
        _pretend_exporting(monkeypatch)
        got = model(*inputs[:5], sparse_depth=inputs[5])
    for a, b in [(ref.depth, got.depth), (ref.confidence, got.confidence), (ref.visibility, got.visibility),
                 (ref.prior_depth, got.prior_depth)]:
        torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-5)


def test_closed_form_3x3_inverse_and_solve_match_torch_linalg(monkeypatch):
    g = torch.Generator().manual_seed(0)
    A = torch.randn(50, 3, 3, dtype=torch.float64, generator=g) + 3 * torch.eye(3, dtype=torch.float64)
    torch.testing.assert_close(warping.inverse3x3(A), torch.linalg.inv(A))
    rhs = torch.randn(5, 10, 3, 1, dtype=torch.float64, generator=g)
    monkeypatch.setattr(cost, "exporting", lambda: True)
    sol, info = cost._solve3x3(A.view(5, 10, 3, 3), rhs)
    ref, ref_info = torch.linalg.solve_ex(A.view(5, 10, 3, 3), rhs)
    torch.testing.assert_close(sol, ref)
    assert torch.equal(info, ref_info.to(info.dtype))
    singular = torch.zeros(1, 3, 3, dtype=torch.float64)
    assert int(cost._solve3x3(singular, torch.ones(1, 3, 1, dtype=torch.float64))[1][0]) != 0


@pytest.mark.slow
def test_torch_export_traces_the_network_with_every_branch():
    """``torch.export`` (what ``torch.onnx.export(dynamo=True)`` runs) takes the whole forward: no branch on
    a tensor's value, no op without an export (the depth range check, the any() before a masked fill)."""
    model = _tiny_model()
    inputs = hinted_inputs(1, 3, 64, 80)
    with torch.enable_grad():
        program = torch.export.export(onnx_runtime.FinalMaps(model), tuple(inputs), strict=False)
    depth, confidence, _ = program.module()(*inputs)
    with torch.no_grad():
        ref = model(*inputs[:5], sparse_depth=inputs[5])
    torch.testing.assert_close(depth, ref.depth, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(confidence, ref.confidence, rtol=1e-4, atol=1e-5)


@pytest.mark.slow
def test_shipped_model_on_onnxruntime_matches_torch(tmp_path):
    """The shipped checkpoint exported at 80x64, N = 3 and run by ONNX Runtime: the final depth within
    0.1 % of torch's on 99 % of the pixels (1 % everywhere), the confidence within 0.01. Skipped without
    onnxruntime and onnxscript (no dependencies: the stereo runs torch)."""
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    model, _ = load_checkpoint(SHIPPED_CHECKPOINT, map_location="cpu")
    inputs = hinted_inputs(1, 3, 64, 80)
    onnx_runtime.export_onnx(model, inputs, tmp_path / "pvsnet.onnx")
    ref = onnx_runtime.torch_runner(model.eval())(inputs)
    got = onnx_runtime.ort_runner(tmp_path / "pvsnet.onnx", threads=1)(inputs)
    a = onnx_runtime.agreement(ref, got)
    assert a["depth_rel_p99"] <= 1e-3 and a["depth_rel_max"] <= 1e-2, a
    assert a["conf_abs_max"] <= 1e-2, a
    np.testing.assert_allclose(got[2], ref[2], atol=1e-4)
