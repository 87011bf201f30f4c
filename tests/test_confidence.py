"""Calibrated confidence (:mod:`colmap_pvs.confidence`): the curves, their fit and the reliability check."""

from __future__ import annotations

import json

import numpy as np
import pytest

from colmap_pvs.confidence import (
    DEFAULT_CALIBRATION,
    KINDS,
    RAW,
    Curve,
    calibration_from_dict,
    calibration_path,
    checkpoint_calibration,
    fit_curve,
    load_calibration,
    reliability,
)
from colmap_pvs.errors import ConfigError, ShapeError
from colmap_pvs.io.files import file_sha256


def test_reliability_is_zero_for_honest_probabilities_and_the_gap_for_overconfident_ones():
    rng = np.random.default_rng(0)
    prob = np.repeat([0.15, 0.55, 0.95], 20000)
    honest = rng.random(prob.size) < prob
    assert reliability(prob, honest).ece < 0.01
    # always 0.9, right half the time: the gap is 0.4 in the one bin used
    rel = reliability(np.full(1000, 0.9), np.arange(1000) % 2 == 0)
    assert rel.ece == pytest.approx(0.4)
    assert rel.count[9] == 1000 and sum(rel.count) == 1000


def test_fitted_curve_calibrates_a_monotone_score_and_keeps_its_order():
    rng = np.random.default_rng(1)
    score = rng.random(300000)
    correct = rng.random(score.size) < score**3  # P(correct | score) = score^3: the raw score is far off
    curve = fit_curve(score, correct)
    assert reliability(score, correct).ece > 0.15
    assert reliability(curve(score), correct).ece < 0.01
    np.testing.assert_allclose(curve(np.array([0.2, 0.5, 0.9])), [0.008, 0.125, 0.729], atol=0.03)
    assert np.all(np.diff(curve.prob) > 0)  # strictly: pooled levels keep the scores' order


def test_fitted_curve_pools_a_score_that_does_not_rank():
    rng = np.random.default_rng(2)
    score = rng.random(100000)
    correct = rng.random(score.size) < 0.3  # the score says nothing: one level, the base rate
    curve = fit_curve(score, correct)
    assert max(curve.prob) - min(curve.prob) < 0.02
    assert np.mean(curve.prob) == pytest.approx(0.3, abs=0.02)


def test_fit_curve_leaves_out_non_finite_scores_and_needs_enough_pixels():
    rng = np.random.default_rng(3)
    score = rng.random(5000)
    correct = rng.random(score.size) < score
    score[:100] = np.nan
    curve = fit_curve(score, correct)
    assert np.isfinite(curve.score).all() and np.isfinite(curve.prob).all()
    with pytest.raises(ShapeError, match="at least 96 pixels with a finite score"):
        fit_curve(np.full(200, np.nan), np.ones(200, bool))
    one = fit_curve(np.full(1000, 0.3), np.arange(1000) % 4 == 0)  # one score value: the base rate
    assert len(one.score) == 1 and one.prob[0] == pytest.approx(0.25, abs=1e-3)
    assert np.isnan(reliability(np.zeros(0), np.zeros(0, bool)).ece)  # nothing to check: not "perfect"


def test_apply_maps_valid_pixels_and_keeps_kinds_without_a_curve_as_they_are():
    cal = calibration_from_dict({"tolerance": 0.05,
                                 "curves": {"geometric": {"score": [0.0, 1.0], "prob": [0.5, 0.9]}}})
    score = np.array([[0.0, 0.5], [1.0, 2.0]], np.float32)
    valid = np.array([[True, True], [True, False]])
    np.testing.assert_allclose(cal.apply("geometric", score, valid), [[0.5, 0.7], [0.9, 0.0]])
    np.testing.assert_allclose(cal.apply("geometric", score), [[0.0, 0.7], [0.9, 0.9]])  # valid: score > 0
    nan = np.array([[np.nan, 0.5]], np.float32)  # a non-finite score is no probability
    np.testing.assert_allclose(cal.apply("geometric", nan, np.ones((1, 2), bool)), [[0.0, 0.7]])
    np.testing.assert_array_equal(cal.apply("photometric", score), score)
    np.testing.assert_array_equal(RAW.apply("filled", score), score)
    with pytest.raises(ConfigError, match="unknown kind"):
        cal.apply("teacher", score)


def test_bad_calibration_files_are_refused_naming_the_file(tmp_path):
    path = tmp_path / "cal.json"
    path.write_text(json.dumps({"tolerance": 0.05, "curves": {"fused": {"score": [0, 1], "prob": [0, 1]}}}))
    with pytest.raises(ConfigError, match=r"cal\.json.*unknown kinds \['fused'\]"):
        load_calibration(path)
    path.write_text(json.dumps({"tolerance": 0.05, "curves": {"filled": {"score": [1, 0], "prob": [0, 1]}}}))
    with pytest.raises(ConfigError, match="cal.json: bad tolerance or curve"):
        load_calibration(path)
    for bad in ({"tolerance": "five", "curves": {}}, {"tolerance": 0.05, "curves": [1]},
                {"tolerance": 0.05, "curves": {"filled": {"score": [0, float("nan")], "prob": [0, 1]}}}):
        path.write_text(json.dumps(bad))
        with pytest.raises(ConfigError, match="cal.json"):
            load_calibration(path)
    path.write_text("{")
    with pytest.raises(ConfigError, match="cannot read the confidence calibration"):
        load_calibration(path)
    with pytest.raises(ConfigError, match="rise within"):
        Curve((0.0, 1.0), (0.6, 0.4))


def test_shipped_calibration_has_a_rising_curve_for_every_kind():
    from colmap_pvs.stereo.config import DEFAULT_CHECKPOINT

    assert calibration_path(DEFAULT_CHECKPOINT) == DEFAULT_CALIBRATION
    cal = load_calibration(DEFAULT_CALIBRATION)
    assert 0 < cal.tolerance < 1 and set(cal.curves) == set(KINDS)
    for kind in KINDS:
        curve = cal.curves[kind]
        assert np.all(np.diff(curve.prob) > 0) and 0 <= curve.prob[0] and curve.prob[-1] <= 1
        assert kind in cal.fit  # where each curve comes from
        assert cal.fit[kind]["checkpoint_sha256"] == file_sha256(DEFAULT_CHECKPOINT)  # new weights: refit


def test_a_calibration_fitted_for_other_weights_is_used_with_a_warning(tmp_path, caplog):
    checkpoint = tmp_path / "w.pt"
    checkpoint.write_bytes(b"weights")
    assert checkpoint_calibration(checkpoint) is RAW and "no confidence calibration" in caplog.text
    calibration_path(checkpoint).write_text(json.dumps({
        "tolerance": 0.05, "curves": {"geometric": {"score": [0, 1], "prob": [0.5, 0.9]}},
        "fit": {"geometric": {"checkpoint_sha256": "0" * 64}}}))
    caplog.clear()
    cal = checkpoint_calibration(checkpoint, file_sha256(checkpoint))
    assert set(cal.curves) == {"geometric"} and "fitted for other weights" in caplog.text
    caplog.clear()
    checkpoint_calibration(checkpoint, "0" * 64)
    assert "fitted for other weights" not in caplog.text


def test_stereo_writes_each_kind_calibrated_and_a_new_calibration_recomputes(analytic_scene, tmp_path,
                                                                              tiny_checkpoint, caplog,
                                                                              monkeypatch):
    """Every pass writes its score through its kind's curve, the checkpoint's calibration (without one,
    the score itself, with a warning); the geometric score reads the network's probability (calibrated
    when there is a curve); the curves are in each pass's provenance, so another calibration
    recomputes the passes it changes and the same one nothing."""
    import shutil

    from scenes import stereo_config

    from colmap_pvs.io.maps import read_array, read_depth_map
    from colmap_pvs.stereo import photometric, run_stereo

    # The untrained network's scores are one value; the local plane's factor (tested elsewhere) would
    # spread them by float rounding only, across the threshold below. Off here.
    monkeypatch.setattr(photometric, "PLANE_RESIDUAL_SCALE", float("inf"))
    ws = tmp_path / "ws"
    shutil.copytree(analytic_scene["root"], ws)
    names = analytic_scene["names"]
    checkpoint = tmp_path / "model" / "tiny.pt"
    checkpoint.parent.mkdir()
    shutil.copy(tiny_checkpoint, checkpoint)
    cfg = stereo_config(workspace_path=ws, checkpoint=checkpoint, num_views=4, max_image_size=0)
    run_stereo(cfg)
    assert "no confidence calibration for" in caplog.text and "tiny.calibration.json" in caplog.text

    def maps(kind):
        out = {}
        for n in names:
            d = read_depth_map(ws / "stereo" / "depth_maps" / f"{n}.{kind}.bin")
            out[n] = (d, read_array(ws / "stereo" / "confidence_maps" / f"{n}.{kind}.bin").reshape(d.shape))
        return out

    raw = {k: maps(k) for k in ("photometric", "geometric")}
    path = calibration_path(checkpoint)
    assert path == tmp_path / "model" / "tiny.calibration.json"
    curves = {"photometric": {"score": [0.0, 1.0], "prob": [0.1, 0.3]},
              "geometric": {"score": [0.0, 0.5, 1.0], "prob": [0.2, 0.8, 0.9]},
              "filled": {"score": [0.0, 1.0], "prob": [0.05, 0.15]}}
    path.write_text(json.dumps({"tolerance": 0.05, "curves": curves}))
    res = run_stereo(cfg)
    assert sorted(res.processed) == sorted(res.geometric_processed) == sorted(res.filled_processed)
    assert sorted(res.processed) == sorted(names)
    cal = load_calibration(path)
    filled = maps("filled")
    photometric = maps("photometric")
    for kind in ("photometric", "geometric"):
        for n, (d, c) in maps(kind).items():
            d_raw, c_raw = raw[kind][n]
            np.testing.assert_array_equal(d, d_raw)  # the same pixels (no threshold set)
            added = np.zeros(d.shape, bool)  # the confirmed completion: the filled maps' confidence
            score = c_raw
            if kind == "geometric":
                added = read_depth_map(ws / "stereo" / "confirm_maps" / f"{n}.bin") > 0
                np.testing.assert_array_equal(c[added], filled[n][1][added])
                # the network's factor: its raw score in the first run, its probability now
                q_raw, q = raw["photometric"][n][1], photometric[n][1]
                added |= q_raw < 1e-3
                score = c_raw / np.maximum(q_raw, 1e-3) * q
            valid = (d > 0) & ~added
            assert valid.mean() > 0.05
            np.testing.assert_allclose(c[valid], cal.curves[kind](score[valid]), atol=1e-5)
            assert np.all(c[d <= 0] == 0)
    for n, (d, c) in maps("filled").items():
        assert (d > 0).all()  # a depth everywhere, each supported one through the filled curve
        supported = c > 0  # the others: the network's depth, confidence exactly 0
        assert supported.any() and (~supported).any()  # (this untrained network leaves most unsupported)
        np.testing.assert_array_equal(d[~supported], photometric[n][0][~supported])
        assert np.all((c[supported] >= 0.05) & (c[supported] <= 0.15)) and c.max() > c[supported].min()
    prov = json.loads((ws / "stereo" / "provenance" / f"{names[0]}.geometric.json").read_text())
    assert prov["settings"]["confidence_calibration"]["prob"] == [0.2, 0.8, 0.9]
    again = run_stereo(cfg)
    assert again.processed == again.geometric_processed == again.filled_processed == []
    # a new geometric curve alone: the geometric maps and the completion (which reads them) again
    curves["geometric"]["prob"] = [0.3, 0.8, 0.9]
    path.write_text(json.dumps({"tolerance": 0.05, "curves": curves}))
    res = run_stereo(cfg)
    assert res.processed == [] and sorted(res.geometric_processed) == sorted(names)
    assert sorted(res.filled_processed) == sorted(names)
    # min_confidence is a probability: 0.2 on the curve 0.1 -> 0.3 keeps the raw scores >= 0.5
    from colmap_pvs.config import replace_config

    run_stereo(replace_config(cfg, min_confidence=0.2))
    for n, (d, c) in maps("photometric").items():
        d_raw, c_raw = raw["photometric"][n]
        np.testing.assert_array_equal(d > 0, (d_raw > 0) & (c_raw >= 0.5))
        assert np.all(c[d > 0] >= 0.2) and np.all(c[d == 0] == 0)


def test_cascade_confidence_is_the_masses_of_the_final_and_coarse_stages_and_their_agreement():
    import torch

    from colmap_pvs.model.pvsnet import PVSNetOutput
    from colmap_pvs.stereo.network import STAGE_AGREEMENT_SCALE, cascade_confidence

    H, W = 8, 8
    depth = torch.full((1, H, W), 2.0)
    prev = torch.full((1, H // 2, W // 2), 2.0)
    prev[:, :, 2:] = 2.0 / 1.05  # the right half: the previous stage 5 % nearer
    coarse = [torch.full((1, H // 4, W // 4), 0.5)] * 3
    vis = torch.ones(1, 4, 2, 2)
    out = PVSNetOutput(depth=depth, confidence=torch.full((1, H, W), 0.8), visibility=vis,
                       depths=[torch.full((1, 2, 2), 2.0)] * 3 + [prev, depth],
                       confidences=coarse + [torch.full((1, 4, 4), 0.9), torch.full((1, H, W), 0.8)])
    score = cascade_confidence(out, (4, 4, 4, 2, 1))[0].numpy()
    np.testing.assert_allclose(score[:, :3], 0.8 * 0.5, rtol=1e-5)
    disagree = 0.8 * 0.5 * np.exp(-np.log(1.05) / STAGE_AGREEMENT_SCALE)
    np.testing.assert_allclose(score[:, 5:], disagree, rtol=1e-4)
    single = PVSNetOutput(depth=depth, confidence=torch.full((1, H, W), 0.7), visibility=vis,
                          depths=[torch.full((1, 2, 2), 2.0)] * 3, confidences=coarse)
    np.testing.assert_allclose(cascade_confidence(single, (4, 4, 4))[0].numpy(), 0.7)  # no cascade: the mass
