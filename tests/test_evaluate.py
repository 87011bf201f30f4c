"""Tests for colmap_pvs.evaluate: depth metrics and point-cloud metrics on inputs with known answers."""

from __future__ import annotations

import hashlib
import importlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from colmap_pvs import __version__
from colmap_pvs.errors import ConfigError, ShapeError, WorkspaceError
from colmap_pvs.evaluate import (
    STEREO_RECORD,
    EvaluateCloudConfig,
    EvaluateDepthConfig,
    cloud_metrics,
    compute_depth_metrics,
    evaluate_cloud,
    evaluate_depth,
    find_gt_depth,
    read_gt_depth,
    thin_structure_mask,
)

REL = (0.01, 0.02, 0.05)
ABS = (0.01, 0.02, 0.05, 0.1)


# --------------------------------------------------------------------------- depth metrics


def test_constant_offset_gives_known_errors():
    gt = np.full((20, 30), 2.0)
    pred = gt + 0.03  # relative error 1.5%
    s = compute_depth_metrics(pred, gt, REL, ABS)
    assert s.num_gt == s.num_valid == 600
    assert s.coverage_pct == pytest.approx(100.0)
    assert s.mae == pytest.approx(0.03)
    assert s.rmse == pytest.approx(0.03)
    assert s.absrel == pytest.approx(0.015)
    assert list(s.rel_under_pct.values()) == pytest.approx([0.0, 100.0, 100.0])
    assert list(s.abs_under_pct.values()) == pytest.approx([0.0, 0.0, 100.0, 100.0])


def test_known_fraction_of_bad_pixels():
    rng = np.random.default_rng(0)
    gt = rng.uniform(1.0, 4.0, size=(40, 50))
    pred = gt.copy()
    bad = np.zeros(gt.size, bool)
    bad[rng.permutation(gt.size)[: gt.size // 4]] = True  # exactly 25 %
    bad = bad.reshape(gt.shape)
    pred[bad] = gt[bad] * 1.5  # relative error 50 %
    s = compute_depth_metrics(pred, gt, REL, ABS)
    assert list(s.rel_under_pct.values()) == pytest.approx([75.0, 75.0, 75.0])
    assert s.absrel == pytest.approx(0.25 * 0.5)
    assert s.mae == pytest.approx(0.5 * gt[bad].sum() / gt.size)
    assert s.rmse == pytest.approx(np.sqrt(np.square(0.5 * gt[bad]).sum() / gt.size))


def test_coverage_with_holes_and_metrics_over_pixels_valid_in_both():
    gt = np.full((10, 10), 3.0)
    gt[:2] = 0.0  # 80 valid GT pixels
    gt[2, 0] = np.nan  # 79
    pred = gt.copy()
    pred = np.nan_to_num(pred)
    pred[5:] = 0.0  # predictions missing on 50 of the valid GT pixels
    pred[0, :] = 7.0  # predictions where GT is invalid are ignored
    pred[3, 3] = 3.3  # the only wrong pixel among those valid in both
    s = compute_depth_metrics(pred, gt, REL, ABS)
    assert s.num_gt == 79
    assert s.num_valid == 29
    assert s.coverage_pct == pytest.approx(100 * 29 / 79)
    assert s.mae == pytest.approx(0.3 / 29)
    assert s.rel_under_pct[0.05] == pytest.approx(100 * 28 / 29)


def test_empty_overlap_gives_nan_errors_and_zero_coverage():
    s = compute_depth_metrics(np.zeros((4, 4)), np.ones((4, 4)), REL, ABS)
    assert s.coverage_pct == 0.0 and s.num_valid == 0
    assert np.isnan(s.mae) and np.isnan(s.absrel)


def test_max_gt_depth_and_median_scale_alignment():
    gt = np.array([[1.0, 2.0], [3.0, 10.0]])
    s = compute_depth_metrics(gt * 0.5, gt, REL, ABS, max_gt_depth=5.0, scale_alignment="median")
    assert s.num_gt == 3 and s.scale == pytest.approx(2.0)
    assert s.mae == pytest.approx(0.0, abs=1e-12)


def test_gt_of_another_size_is_resized_with_nearest():
    pred = np.array([[1.0, 2.0], [3.0, 4.0]])
    gt = np.kron(pred, np.ones((3, 3)))  # 6x6, each value a 3x3 block
    gt[0, 0] = 100.0  # a corner pixel that nearest sampling never reads (block centre is read)
    s = compute_depth_metrics(pred, gt, REL, ABS)
    assert s.num_gt == 4 and s.mae == pytest.approx(0.0)
    # bilinear interpolation would blend depth edges; nearest keeps GT values exact
    gt2 = np.kron(pred, np.ones((2, 2)))
    assert compute_depth_metrics(np.kron(pred, np.ones((1, 1))), gt2).mae == pytest.approx(0.0)


def test_png_gt_with_scale(tmp_path):
    mm = np.array([[1000, 2500], [0, 65535]], dtype=np.uint16)
    path = tmp_path / "frame.png"
    assert cv2.imwrite(str(path), mm)
    depth = read_gt_depth(path, scale=0.001)
    assert depth.dtype == np.float32
    np.testing.assert_allclose(depth, [[1.0, 2.5], [0.0, 65.535]], rtol=1e-6)
    with pytest.raises(ConfigError, match="gt_scale"):
        read_gt_depth(path)
    np.save(tmp_path / "m.npy", np.array([[1.5]], dtype=np.float32))
    assert read_gt_depth(tmp_path / "m.npy").tolist() == [[1.5]]


def test_find_gt_depth_patterns(tmp_path):
    np.save(tmp_path / "frame1.npy", np.ones((2, 2)))
    (tmp_path / "sub").mkdir()
    cv2.imwrite(str(tmp_path / "sub" / "a.jpg.png"), np.ones((2, 2), np.uint16))
    assert find_gt_depth(tmp_path, "frame1.jpg") == tmp_path / "frame1.npy"
    assert find_gt_depth(tmp_path, "sub/a.jpg", "{name}") == tmp_path / "sub" / "a.jpg.png"
    assert find_gt_depth(tmp_path, "frame2.jpg") is None
    assert find_gt_depth(tmp_path, "x.jpg", "frame1.npy".replace("frame1", "{stem}")) is None
    # a name with a GT-like extension: the demo's NAME.png.npy is found with {name}
    np.save(tmp_path / "000.png.npy", np.ones((2, 2)))
    assert find_gt_depth(tmp_path, "000.png", "{name}") == tmp_path / "000.png.npy"
    cv2.imwrite(str(tmp_path / "001.png"), np.ones((2, 2), np.uint16))
    assert find_gt_depth(tmp_path, "001.png", "{name}") == tmp_path / "001.png"  # the file itself first
    # the default pattern ({stem}) finds the demo's own GT (000.png -> 000.png.npy) where 000.* is missing
    assert find_gt_depth(tmp_path, "000.png") == tmp_path / "000.png.npy"
    np.save(tmp_path / "000.npy", np.ones((2, 2)))
    assert find_gt_depth(tmp_path, "000.png") == tmp_path / "000.npy"  # the stem first
    with pytest.raises(ConfigError, match="gt_pattern"):
        find_gt_depth(tmp_path, "x.jpg", "{bad}")


def test_depth_config_validation():
    with pytest.raises(ConfigError, match="rel_thresholds"):
        EvaluateDepthConfig(Path("w"), Path("g"), rel_thresholds=(0.01, -1.0))
    with pytest.raises(ConfigError, match="gt_scale"):
        EvaluateDepthConfig(Path("w"), Path("g"), gt_scale=0.0)
    with pytest.raises(ConfigError, match="gt_pattern"):
        EvaluateDepthConfig(Path("w"), Path("g"), gt_pattern="depth.png")


# --------------------------------------------------------------------------- workspace + CLI


def make_workspace(root: Path, preds: dict[str, np.ndarray]) -> Path:
    """A minimal dense workspace: images/, an (empty) text sparse model, predicted depth maps."""
    from colmap_pvs.io.maps import write_depth_map

    (root / "images").mkdir(parents=True)
    (root / "sparse").mkdir()
    for stem in ("cameras", "images", "points3D"):
        (root / "sparse" / f"{stem}.txt").write_text("# empty\n")
    for name, depth in preds.items():
        for kind in ("geometric", "photometric"):
            write_depth_map(root / "stereo" / "depth_maps" / f"{name}.{kind}.bin", depth)
    return root


@pytest.fixture
def depth_case(tmp_path):
    """Two predicted images (one 0.02 too deep, one exact with a hole) and uint16-mm PNG GT at 2x size."""
    gt_m = {"a.jpg": np.full((6, 8), 2.0), "b.jpg": np.linspace(1.0, 3.0, 48).reshape(6, 8)}
    preds = {
        "a.jpg": np.full((3, 4), 2.02, np.float32),
        "b.jpg": gt_m["b.jpg"][1::2, 1::2].astype(np.float32),
    }
    preds["b.jpg"][0, 0] = 0.0
    ws = make_workspace(tmp_path / "ws", preds)
    gt_dir = tmp_path / "gt"
    gt_dir.mkdir()
    for name, depth in gt_m.items():
        cv2.imwrite(str(gt_dir / f"{Path(name).stem}.png"), np.round(depth * 1000).astype(np.uint16))
    return ws, gt_dir


def test_evaluate_depth_per_image_and_pooled(depth_case):
    ws, gt_dir = depth_case
    m = evaluate_depth(EvaluateDepthConfig(ws, gt_dir, gt_scale=0.001))
    assert list(m.per_image) == ["a.jpg", "b.jpg"]
    a, b = m.per_image["a.jpg"], m.per_image["b.jpg"]
    assert a.mae == pytest.approx(0.02, abs=1e-6) and a.coverage_pct == pytest.approx(100.0)
    assert b.mae == pytest.approx(0.0, abs=1e-3) and b.coverage_pct == pytest.approx(100 * 11 / 12)
    assert m.pooled.num_valid == 23 and m.pooled.num_gt == 24
    assert m.pooled.mae == pytest.approx((12 * 0.02 + 11 * b.mae) / 23, abs=1e-6)
    assert m.pooled.abs_under_pct[0.01] == pytest.approx(100 * 11 / 23)


def test_evaluate_depth_reads_the_kind_it_is_asked_for(depth_case):
    """``kind="filled"`` (the dense completion) reads ``NAME.filled.bin`` and its confidence map."""
    from colmap_pvs.io.maps import write_array, write_depth_map

    ws, gt_dir = depth_case
    with pytest.raises(WorkspaceError, match="filled"):
        evaluate_depth(EvaluateDepthConfig(ws, gt_dir, gt_scale=0.001, kind="filled"))
    exact = np.linspace(1.0, 3.0, 48).reshape(6, 8)[1::2, 1::2].astype(np.float32)
    for name, depth in (("a.jpg", np.full((3, 4), 2.2, np.float32)), ("b.jpg", exact)):
        write_depth_map(ws / "stereo" / "depth_maps" / f"{name}.filled.bin", depth)
        write_array(ws / "stereo" / "confidence_maps" / f"{name}.filled.bin",
                    np.full((3, 4), 0.1 if name == "a.jpg" else 0.9, np.float32))
    m = evaluate_depth(EvaluateDepthConfig(ws, gt_dir, gt_scale=0.001, kind="filled"))
    assert m.per_image["a.jpg"].mae == pytest.approx(0.2, abs=1e-5)  # not the geometric map's 0.02
    assert m.per_image["b.jpg"].coverage_pct == pytest.approx(100.0)  # the geometric map has a hole
    # The confident half is b's exact pixels: the sparsification curve reads the filled confidence.
    assert m.sparsification["error"][m.sparsification["fractions"].index(0.5)] == pytest.approx(0.0, abs=1e-3)
    assert m.sparsification["relative_ause"] < 0.01  # the oracle's ranking up to b's mm rounding


def test_evaluate_depth_reports_how_well_calibrated_confidences_predict(depth_case, capsys):
    """Confidences whose provenance names a calibration tolerance are checked as probabilities:
    a (2.02 for 2.0: 1 % off) is right within 5 % but said 0.2; b is exact and said 0.95."""
    from colmap_pvs.cli.reports_eval import report_depth
    from colmap_pvs.io.maps import write_array

    ws, gt_dir = depth_case
    for name, value in (("a.jpg", 0.2), ("b.jpg", 0.95)):
        path = ws / "stereo" / "confidence_maps" / f"{name}.geometric.bin"
        write_array(path, np.full((3, 4), value, np.float32))
    assert evaluate_depth(EvaluateDepthConfig(ws, gt_dir, gt_scale=0.001)).calibration is None  # raw scores
    prov = ws / "stereo" / "provenance"
    prov.mkdir(parents=True)
    for name in ("a.jpg", "b.jpg"):
        (prov / f"{name}.geometric.json").write_text(json.dumps(
            {"settings": {"confidence_calibration": {"tolerance": 0.05, "score": [0, 1], "prob": [0, 1]}}}))
    m = evaluate_depth(EvaluateDepthConfig(ws, gt_dir, gt_scale=0.001))
    cal = m.calibration
    assert cal["tolerance"] == 0.05 and cal["count"][2] == 12 and cal["count"][9] == 11
    assert cal["observed"][2] == 1.0 and cal["observed"][9] == 1.0
    assert cal["ece"] == pytest.approx((12 * 0.8 + 11 * 0.05) / 23)
    assert json.loads(m.output_path.read_text())["metrics"]["calibration"]["ece"] == pytest.approx(cal["ece"])
    assert "expected calibration error 0.441" in report_depth(m)


def test_listed_images_without_prediction_count_as_zero_coverage(depth_case):
    ws, gt_dir = depth_case
    cv2.imwrite(str(gt_dir / "c.png"), np.full((6, 8), 1000, np.uint16))
    m = evaluate_depth(EvaluateDepthConfig(ws, gt_dir, gt_scale=0.001, images=("a.jpg", "c.jpg")))
    assert m.missing_prediction == ["c.jpg"]
    assert m.per_image["c.jpg"].coverage_pct == 0.0
    assert m.pooled.coverage_pct == pytest.approx(50.0)  # counted at the 3x4 prediction size


def test_evaluate_depth_errors_name_values(depth_case, tmp_path):
    ws, gt_dir = depth_case
    with pytest.raises(ConfigError, match="nope"):
        evaluate_depth(EvaluateDepthConfig(ws, tmp_path / "nope", gt_scale=0.001))
    with pytest.raises(ConfigError, match="no GT depth found"):
        evaluate_depth(EvaluateDepthConfig(ws, gt_dir, gt_scale=0.001, gt_pattern="x_{stem}"))
    with pytest.raises(ConfigError, match="uint16"):
        evaluate_depth(EvaluateDepthConfig(ws, gt_dir))
    empty = make_workspace(tmp_path / "empty", {})
    with pytest.raises(WorkspaceError, match="geometric"):
        evaluate_depth(EvaluateDepthConfig(empty, gt_dir, gt_scale=0.001))


def test_metrics_json_is_written_atomically_with_config_version_and_checkpoint_hash(
    depth_case, tmp_path, monkeypatch
):
    ws, gt_dir = depth_case
    ckpt = tmp_path / "model.pt"
    ckpt.write_bytes(b"weights")
    (ws / "stereo" / STEREO_RECORD).write_text(json.dumps({"checkpoint_used": str(ckpt), "config": {}}))
    written = []
    step = importlib.import_module("colmap_pvs.evaluate.depth")
    real = step.atomic_write_bytes
    monkeypatch.setattr(step, "atomic_write_bytes", lambda p, d: written.append(Path(p)) or real(p, d))
    m = evaluate_depth(EvaluateDepthConfig(ws, gt_dir, gt_scale=0.001))
    out = ws / "stereo" / "metrics.json"
    assert m.output_path == out and written == [out]
    assert not [p for p in out.parent.iterdir() if p.name.endswith(".tmp")]
    data = json.loads(out.read_text())
    assert data["config"]["gt_scale"] == 0.001 and data["config"]["workspace_path"] == str(ws)
    assert data["colmap_pvs_version"] == __version__
    assert data["checkpoint_sha256"] == hashlib.sha256(b"weights").hexdigest()
    assert data["metrics"]["pooled"]["num_valid"] == 23
    assert "valid in both" in data["metrics"]["note"]


def test_stereo_record_name_matches_stereo_module():
    import colmap_pvs.stereo as stereo

    assert stereo.CONFIG_FILENAME == STEREO_RECORD


def test_cli_evaluate_depth_end_to_end(depth_case, capsys):
    from colmap_pvs.cli.main import main

    ws, gt_dir = depth_case
    out = ws / "m.json"
    rc = main(
        [
            "evaluate",
            "depth",
            "--workspace_path",
            str(ws),
            "--gt",
            str(gt_dir),
            "--gt_scale",
            "0.001",
            "--abs_thresholds",
            "0.01",
            "0.05",
            "--output_path",
            str(out),
        ]
    )
    text = capsys.readouterr().out
    assert rc == 0
    assert "POOLED (2 images)" in text and "valid in both" in text and "<5%rel" in text
    assert json.loads(out.read_text())["config"]["abs_thresholds"] == [0.01, 0.05]
    rc = main(["evaluate", "depth", "--workspace_path", str(ws), "--gt", str(gt_dir / "missing")])
    assert rc == 1
    assert "missing" in capsys.readouterr().err


# --------------------------------------------------------------------------- point clouds


def plane(n: int = 51, spacing: float = 0.01) -> np.ndarray:
    """``[n*n, 3]`` grid on z = 0 with the given spacing."""
    u, v = np.meshgrid(np.arange(n) * spacing, np.arange(n) * spacing)
    return np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], axis=1)


def test_shifted_cloud_accuracy_completeness_f1_and_dtu_distances():
    gt = plane()
    rec = gt + np.array([0.0, 0.0, 0.03])
    m = cloud_metrics(rec, gt, thresholds=(0.05, 0.02), voxel_size=0.05, dtu_max_dist=0.5)
    assert m.thresholds == (0.02, 0.05)
    assert m.accuracy_pct == pytest.approx((0.0, 100.0))
    assert m.completeness_pct == pytest.approx((0.0, 100.0))
    assert m.f1_pct == pytest.approx((0.0, 100.0))
    assert m.dtu_accuracy == pytest.approx(0.03)
    assert m.dtu_completeness == pytest.approx(0.03)
    assert m.dtu_overall == pytest.approx(0.03)
    assert m.dtu_accuracy_outlier_pct == 0.0


def test_known_fraction_of_bad_points():
    gt = plane()
    rng = np.random.default_rng(1)
    rec = gt.copy()
    bad = rng.permutation(len(rec))[: len(rec) // 5]
    rec[bad, 2] += 1.0  # 20 % of the points 1 unit off the surface
    # one voxel per grid: the voxel normalisation reduces to the plain point fraction
    m = cloud_metrics(rec, gt, thresholds=(0.05,), voxel_size=10.0, dtu_max_dist=0.5)
    frac_good = 1 - len(bad) / len(rec)
    assert m.accuracy_pct[0] == pytest.approx(100 * frac_good)
    assert m.accuracy_points_pct[0] == pytest.approx(100 * frac_good)
    assert m.completeness_pct[0] == pytest.approx(100.0)  # neighbours 0.01 away still cover the GT
    p, r = 100 * frac_good, 100.0
    assert m.f1_pct[0] == pytest.approx(2 * p * r / (p + r))
    assert m.dtu_accuracy == pytest.approx(0.0)  # the 1.0 distances are discarded as outliers
    assert m.dtu_accuracy_outlier_pct == pytest.approx(100 * len(bad) / len(rec))
    clamped = cloud_metrics(
        rec, gt, thresholds=(0.05,), voxel_size=10.0, dtu_max_dist=0.5, dtu_outliers="clamp"
    )
    assert clamped.dtu_accuracy == pytest.approx(0.5 * len(bad) / len(rec))


def test_voxel_normalisation_weights_regions_equally():
    gt = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.3, 0.3, 0.3], [1.2, 1.2, 1.2]])
    # three accurate points in one voxel, one inaccurate point alone in another
    rec = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.3, 0.3, 0.3], [1.2, 1.2, 1.5]])
    m = cloud_metrics(rec, gt, thresholds=(0.1,), voxel_size=1.0, dtu_max_dist=1.0)
    assert m.accuracy_points_pct[0] == pytest.approx(75.0)
    assert m.accuracy_pct[0] == pytest.approx(50.0)  # ETH3D: the mean over voxels, not over points
    assert m.completeness_points_pct[0] == pytest.approx(75.0)
    assert m.completeness_pct[0] == pytest.approx(50.0)


def test_voxel_normalisation_uses_two_grids_shifted_by_half_a_voxel():
    rec = np.array([[0.2, 0.2, 0.2], [0.9, 0.2, 0.2], [1.1, 0.2, 0.2]])
    gt = np.array([[0.2, 0.2, 0.2], [0.9, 0.2, 0.2], [1.1, 0.2, 0.5]])
    m = cloud_metrics(rec, gt, thresholds=(0.1,), voxel_size=1.0)
    # grid 0: {0.2, 0.9} -> 1, {1.1} -> 0; grid 1/2: {0.2} -> 1, {0.9, 1.1} -> 1/2; mean of 4 voxels
    assert m.accuracy_pct[0] == pytest.approx(100 * (1 + 0 + 1 + 0.5) / 4)


def test_empty_reconstruction_scores_zero():
    m = cloud_metrics(np.zeros((0, 3)), plane(5), thresholds=(0.1,))
    assert m.accuracy_pct == (0.0,) and m.completeness_pct == (0.0,) and m.f1_pct == (0.0,)
    assert np.isnan(m.dtu_accuracy)


def test_evaluate_cloud_reads_ply_and_writes_json(tmp_path, capsys):
    import open3d as o3d

    from colmap_pvs.cli.main import main

    gt = plane(21)
    for name, pts in (("gt.ply", gt), ("rec.ply", gt + [0, 0, 0.03])):
        o3d.io.write_point_cloud(
            str(tmp_path / name), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        )
    m = evaluate_cloud(
        EvaluateCloudConfig(tmp_path / "rec.ply", tmp_path / "gt.ply", thresholds=(0.02, 0.05))
    )
    assert m.f1_pct == pytest.approx((0.0, 100.0))
    data = json.loads((tmp_path / "rec.metrics.json").read_text())
    assert data["colmap_pvs_version"] == __version__ and data["config"]["thresholds"] == [0.02, 0.05]
    assert data["metrics"]["dtu_accuracy"] == pytest.approx(0.03)
    rc = main(
        [
            "evaluate",
            "cloud",
            "--cloud",
            str(tmp_path / "rec.ply"),
            "--gt",
            str(tmp_path / "gt.ply"),
            "--thresholds",
            "0.01",
            "0.1",
        ]
    )
    assert rc == 0 and "F1%" in capsys.readouterr().out
    with pytest.raises(ConfigError, match="nothere"):
        evaluate_cloud(EvaluateCloudConfig(tmp_path / "nothere.ply", tmp_path / "gt.ply"))
    with pytest.raises(ConfigError, match="thresholds"):
        EvaluateCloudConfig(tmp_path / "rec.ply", tmp_path / "gt.ply", thresholds=(0.0,))


def test_sparsification_curve_matches_the_oracle_for_perfect_confidence():
    from colmap_pvs.evaluate import sparsification_curve

    rng = np.random.default_rng(0)
    err = rng.random(1000)
    perfect = sparsification_curve(-err, err)
    np.testing.assert_allclose(perfect["error"], perfect["oracle"])
    assert perfect["oracle"][-1] == pytest.approx(err.mean())
    assert perfect["oracle"][4] == pytest.approx(np.sort(err)[:500].mean())
    random_rank = sparsification_curve(rng.random(1000), err)
    assert random_rank["error"][4] > 1.5 * random_rank["oracle"][4]  # uniform errors: ~2x
    inverted = sparsification_curve(err, err)
    assert inverted["error"][0] > err.mean() > perfect["error"][0]


def test_relative_ause_by_hand_on_four_pixels():
    """Errors 1, 2, 3, 4 at fractions 1/4 ... 1: the oracle's curve 1, 1.5, 2, 2.5, chance 2.5 throughout
    (area 1.5 + 1 + 0.5 = 3 between them); reversed 4, 3.5, 3, 2.5 (area 6: 2.0); the best two swapped
    2, 1.5, 2, 2.5 (area 1: 1/3)."""
    from colmap_pvs.evaluate import relative_ause

    err = np.array([3.0, 1.0, 4.0, 2.0])
    assert relative_ause(-err, err, steps=4) == pytest.approx(0.0)
    assert relative_ause(err, err, steps=4) == pytest.approx(2.0)
    assert relative_ause(np.array([2.0, 3.0, 0.0, 4.0]), err, steps=4) == pytest.approx(1 / 3)


def test_relative_ause_is_zero_for_the_oracle_one_for_chance_and_more_for_an_inverted_ranking():
    from colmap_pvs.evaluate import relative_ause

    rng = np.random.default_rng(4)
    err = rng.exponential(0.05, 20000)
    assert relative_ause(-err, err) == pytest.approx(0.0, abs=1e-9)
    assert relative_ause(rng.random(err.size), err) == pytest.approx(1.0, abs=0.05)
    assert relative_ause(err, err) > 1.5
    noisy = relative_ause(-err * np.exp(rng.normal(0, 1.0, err.size)), err)
    assert 0.1 < noisy < 0.6  # a confidence that knows the error roughly ranks in between
    assert np.isnan(relative_ause(np.ones(5), np.full(5, 0.1)))  # nothing to rank
    with pytest.raises(ShapeError):
        relative_ause(np.ones(3), np.ones(4))


def test_thin_structure_mask_keeps_narrow_near_structures_only():
    depth = np.full((40, 50), 10.0)
    depth[:, 44] = 9.0  # 10 % nearer only: not a separate structure
    depth[30:34, :] = 7.0  # a horizontal bar 4 px high, 30 % nearer than the wall
    depth[:, 20:23] = 5.0  # a vertical pole 3 px wide in front of both
    depth[5:15, 35:41] = 5.0  # a box 6 px wide: not thin
    mask = thin_structure_mask(depth)
    expected = np.zeros_like(mask)
    expected[4:-4, 20:23] = True  # the width-4 border is never in the mask
    expected[30:34, 4:-4] = True
    assert np.array_equal(mask, expected)
    assert not thin_structure_mask(depth, width=2)[:, 20:23].any()  # 3 px is wider than 2
    # no surface (0) counts as far: a pole against the sky is thin
    sky = np.zeros((20, 20))
    sky[:, 9] = 3.0
    assert thin_structure_mask(sky)[4:-4, 9].all() and thin_structure_mask(sky).sum() == 12
    with pytest.raises(ShapeError):
        thin_structure_mask(np.ones((4, 4, 1)))
    for width, gap in ((2.5, 0.8), (True, 0.8), (0, 0.8), (4, 1.0)):
        with pytest.raises(ConfigError, match="thin_structure_mask"):
            thin_structure_mask(depth, width=width, gap=gap)
