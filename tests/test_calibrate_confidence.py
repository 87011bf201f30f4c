"""tools/calibrate_confidence.py: fit curves on raw maps with known depth, then check them."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from conftest import load_tool

from colmap_pvs.confidence import load_calibration, reliability
from colmap_pvs.io.files import file_sha256
from colmap_pvs.io.maps import read_array, read_depth_map


@pytest.fixture(scope="module")
def tool():
    return load_tool("calibrate_confidence")


def test_fit_then_check_on_a_workspace_with_known_depth(tool, analytic_scene, tmp_path, tiny_checkpoint,
                                                        capsys, monkeypatch):
    """The documented procedure: raw maps from a checkpoint without a calibration, fit photometric,
    stereo again with it, fit geometric (whose score reads the photometric probability), stereo again,
    fit filled on top; every step refuses maps of the wrong kind."""
    from scenes import render_view, stereo_config

    from colmap_pvs.stereo import photometric, run_stereo

    # The untrained network's scores are one value; the local plane's factor (tested elsewhere) would
    # spread them by float rounding only, into near-ties that 48 knots cannot follow. Off here.
    monkeypatch.setattr(photometric, "PLANE_RESIDUAL_SCALE", float("inf"))

    ws = tmp_path / "ws"
    shutil.copytree(analytic_scene["root"], ws)
    checkpoint = tmp_path / "model" / "tiny.pt"
    checkpoint.parent.mkdir()
    shutil.copy(tiny_checkpoint, checkpoint)
    cfg = stereo_config(workspace_path=ws, checkpoint=checkpoint, num_views=4, max_image_size=0)
    run_stereo(cfg)
    gt = ws / "gt"
    gt.mkdir()
    for name in analytic_scene["names"]:
        im = analytic_scene["model"].image_by_name(name)
        K = analytic_scene["map_K"][name]
        view = render_view(analytic_scene["scene"], K, im.cam_from_world, 160, 120)
        np.save(gt / f"{name}.npy", view["depth"].astype(np.float32))
    out = checkpoint.with_name("tiny.calibration.json")
    common = ["--workspaces", str(ws), "--gt", "gt", "--gt_pattern", "{name}"]
    # geometric scores read the photometric probability: not fitted in one go from raw maps
    for kinds in (["photometric", "geometric"], ["geometric", "photometric"], ["filled", "geometric"]):
        with pytest.raises(SystemExit, match="fit .* after"):
            tool.main(["fit", *common, "--kinds", *kinds, "--tolerance", "0.1",
                       "--out", str(tmp_path / "both.json")])
    assert not (tmp_path / "both.json").exists()
    assert tool.main(["fit", *common, "--kinds", "photometric", "--tolerance", "0.1",
                      "--data", "analytic", "--out", str(out)]) == 0
    cal = load_calibration(out)
    assert set(cal.curves) == {"photometric"} and cal.tolerance == 0.1
    assert cal.fit["photometric"]["data"] == "analytic" and cal.fit["photometric"]["workspaces"] == ["ws"]
    # the fitted photometric curve predicts the share of right pixels of these maps (in-sample)
    conf, right = [], []
    for name in analytic_scene["names"]:
        d = read_depth_map(ws / "stereo" / "depth_maps" / f"{name}.photometric.bin")
        c = read_array(ws / "stereo" / "confidence_maps" / f"{name}.photometric.bin").reshape(d.shape)
        g = np.load(gt / f"{name}.npy")
        ok = (d > 0) & (g > 0)
        conf.append(c[ok])
        right.append(np.abs(d[ok] - g[ok]) <= 0.1 * g[ok])
    conf, right = np.concatenate(conf), np.concatenate(right)
    fitted = cal.apply("photometric", conf, np.ones(conf.shape, bool))
    assert abs(fitted.mean() - right.mean()) < 0.02
    assert reliability(fitted, right).ece < 0.05
    # raw maps are checked only through --apply; the filled maps still hold raw-made scores
    with pytest.raises(SystemExit, match="raw scores"):
        tool.main(["check", *common])
    for kind in ("geometric", "filled"):
        with pytest.raises(SystemExit, match="other curves than|another calibration"):
            tool.main(["fit", *common, "--kinds", kind, "--tolerance", "0.1", "--start", str(out),
                       "--out", str(out)])
    run_stereo(cfg)  # the curve beside the checkpoint: calibrated photometric maps
    with pytest.raises(SystemExit, match="calibrated confidences"):
        tool.main(["fit", *common, "--kinds", "photometric", "--out", str(tmp_path / "x")])
    assert tool.main(["fit", *common, "--kinds", "geometric", "--tolerance", "0.1", "--start", str(out),
                      "--out", str(out)]) == 0
    cal = load_calibration(out)
    assert set(cal.curves) == {"photometric", "geometric"}
    assert cal.fit["geometric"]["checkpoint_sha256"] == file_sha256(checkpoint)
    with pytest.raises(SystemExit, match="other curves than|another calibration"):
        tool.main(["fit", *common, "--kinds", "filled", "--tolerance", "0.1", "--start", str(out),
                   "--out", str(out)])
    run_stereo(cfg)  # calibrated photometric and geometric maps
    with pytest.raises(SystemExit, match="calibrated confidences"):
        tool.main(["fit", *common, "--kinds", "geometric", "--out", str(tmp_path / "x")])
    assert tool.main(["fit", *common, "--kinds", "filled", "--tolerance", "0.1", "--start", str(out),
                      "--out", str(out)]) == 0
    assert set(json.loads(out.read_text())["curves"]) == {"photometric", "geometric", "filled"}
    run_stereo(cfg)
    capsys.readouterr()
    assert tool.main(["check", *common]) == 0
    printed = capsys.readouterr().out
    assert printed.count("ECE") == 3 and "within 0.1" in printed
    with pytest.raises(SystemExit, match="calibrated already"):
        tool.main(["check", *common, "--apply", str(out)])
    with pytest.raises(SystemExit, match="another tolerance"):
        tool.main(["fit", *common, "--kinds", "filled", "--start", str(out), "--out", str(tmp_path / "o")])
