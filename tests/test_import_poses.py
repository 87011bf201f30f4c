"""Known poses -> COLMAP model (``colmap_pvs.io.import_poses``): readers, conventions, triangulation."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from conftest import disk_full_after_writing_half

from colmap_pvs.errors import ConfigError, WorkspaceError
from colmap_pvs.io.import_poses import (
    MIN_IMAGES_TO_REFINE_FOCAL,
    ImportPosesConfig,
    import_poses,
    read_known_cameras,
    reprojection_errors,
)


def _rotation(seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q if np.linalg.det(q) > 0 else -q


def _project(K: np.ndarray, cam_from_world: np.ndarray, X: np.ndarray) -> np.ndarray:
    x = K @ (cam_from_world[:, :3] @ X + cam_from_world[:, 3])
    return x[:2] / x[2]


# --------------------------------------------------------------------------- readers


def test_strecha_reader_convention(tmp_path):
    K = np.array([[689.87, 0, 379.7975], [0, 691.04, 251.3275], [0, 0, 1]])
    R = _rotation(0)  # camera-to-world rotation (columns = camera axes in world)
    C = np.array([-7.28, -7.58, 0.20])

    def fmt_row(row) -> str:
        return " ".join(repr(float(v)) for v in row)

    lines = [*(fmt_row(r) for r in K), "0 0 0", *(fmt_row(r) for r in R), fmt_row(C), "768 512"]
    (tmp_path / "cameras").mkdir()
    (tmp_path / "cameras" / "0000.jpg.camera").write_text("\n".join(lines) + "\n")
    fmt, cams = read_known_cameras(tmp_path)
    assert fmt == "strecha" and len(cams) == 1
    cam = cams[0]
    assert cam.name == "0000.jpg" and cam.size == (768, 512)
    X = C + R @ np.array([0.3, -0.2, 5.0])  # in front of the camera
    strecha = K @ R.T @ (X - C)
    expected = strecha[:2] / strecha[2] + 0.5  # centre-at-0 -> COLMAP's centre-at-0.5 convention
    np.testing.assert_allclose(_project(cam.K, cam.cam_from_world, X), expected, atol=1e-9)
    _, cams0 = read_known_cameras(tmp_path, principal_point_offset=0.0)
    np.testing.assert_allclose(_project(cams0[0].K, cams0[0].cam_from_world, X), expected - 0.5, atol=1e-9)


def test_hololens_reader_convention_and_errors(tmp_path):
    K = np.array([[495.6, 0, 269.5], [0, 495.5, 169.2], [0, 0, 1]])
    poses = []
    for i in range(3):
        T = np.eye(4)
        T[:3, :3] = _rotation(i)
        T[:3, 3] = [i, 2.0 * i, -1.0]
        poses.append(T)  # camera-to-world
    np.savetxt(tmp_path / "K.txt", K)
    np.savetxt(tmp_path / "poses.txt", np.stack([p.ravel() for p in poses]))
    (tmp_path / "frames.txt").write_text("a.png\nb.png\nc.png\n")
    fmt, cams = read_known_cameras(tmp_path)
    assert fmt == "hololens" and [c.name for c in cams] == ["a.png", "b.png", "c.png"]
    for cam, T in zip(cams, poses, strict=True):
        X = T[:3, :3] @ np.array([0.1, 0.2, 3.0]) + T[:3, 3]  # camera point (0.1, 0.2, 3) in world
        np.testing.assert_allclose(
            cam.cam_from_world[:, :3] @ X + cam.cam_from_world[:, 3], [0.1, 0.2, 3.0], atol=1e-9
        )
        np.testing.assert_allclose(cam.K, K)
    (tmp_path / "frames.txt").write_text("a.png\nb.png\n")
    with pytest.raises(WorkspaceError, match="2 frames but .* 3 poses"):
        read_known_cameras(tmp_path)


def test_readers_accept_a_utf8_byte_order_mark(tmp_path):
    """Files saved by Windows editors start with a BOM: read as if it were not there (not as part of the
    first name or number)."""
    bom = "\ufeff"
    K = np.array([[100.0, 0, 50], [0, 110.0, 40], [0, 0, 1]])
    pose = np.concatenate([_rotation(5), [[1.0], [2.0], [3.0]]], axis=1)
    (tmp_path / "p.json").write_text(bom + json.dumps([{"name": "x.png", "K": K.tolist(),
                                                         "cam_from_world": pose.tolist()}]), encoding="utf-8")
    row = ",".join(["x.png", "100", "110", "50", "40", *(repr(float(v)) for v in pose.ravel())])
    (tmp_path / "p.csv").write_text(bom + row + "\n", encoding="utf-8")
    holo = tmp_path / "holo"
    holo.mkdir()
    world_from_cam = np.vstack([np.concatenate([pose[:, :3].T, (-pose[:, :3].T @ pose[:, 3])[:, None]], 1),
                                [0, 0, 0, 1]])
    np.savetxt(holo / "K.txt", K, header=bom, comments="")
    np.savetxt(holo / "poses.txt", world_from_cam.reshape(1, 16), header=bom, comments="")
    (holo / "frames.txt").write_text(bom + "x.png\n", encoding="utf-8")
    for path in (tmp_path / "p.json", tmp_path / "p.csv", holo):
        _, cams = read_known_cameras(path)
        assert [c.name for c in cams] == ["x.png"], path
        np.testing.assert_allclose(cams[0].cam_from_world, pose, atol=1e-9)
        np.testing.assert_allclose(cams[0].K, K)


def test_json_and_csv_readers(tmp_path):
    K = [[100.0, 0, 50], [0, 110.0, 40], [0, 0, 1]]
    R = _rotation(3)
    pose = np.concatenate([R, [[1.0], [2.0], [3.0]]], axis=1)
    (tmp_path / "p.json").write_text(json.dumps([{"name": "x.png", "K": K, "cam_from_world": pose.tolist()}]))
    fmt, cams = read_known_cameras(tmp_path / "p.json")
    assert fmt == "json"
    np.testing.assert_allclose(cams[0].cam_from_world, pose, atol=1e-12)
    row = ",".join(["x.png", "100", "110", "50", "40", *(repr(float(v)) for v in pose.ravel())])
    (tmp_path / "p.csv").write_text(
        "name,fx,fy,cx,cy," + ",".join(f"p{i}" for i in range(12)) + "\n" + row + "\n"
    )
    fmt, cams = read_known_cameras(tmp_path / "p.csv")
    assert fmt == "csv"
    np.testing.assert_allclose(cams[0].cam_from_world, pose, atol=1e-12)
    np.testing.assert_allclose(cams[0].K, K)
    bad = pose.copy()
    bad[:, :3] *= 2  # not a rotation
    (tmp_path / "bad.json").write_text(
        json.dumps([{"name": "x.png", "K": K, "cam_from_world": bad.tolist()}])
    )
    with pytest.raises(WorkspaceError, match="not orthonormal"):
        read_known_cameras(tmp_path / "bad.json")
    with pytest.raises(WorkspaceError, match="cannot tell the format"):
        read_known_cameras(tmp_path)
    with pytest.raises(ConfigError, match="frame_step"):
        ImportPosesConfig(image_path=Path("i"), poses_path=Path("p"), output_path=Path("o"), frame_step=0)


# --------------------------------------------------------------------------- triangulation


def _analytic_scene_with_poses(tmp_path, n_views: int = 5) -> dict:
    """The analytic scene's workspace in ``tmp_path/ws`` and its exact cameras in ``tmp_path/poses.json``."""
    from scenes import make_analytic_workspace

    gt = make_analytic_workspace(tmp_path / "ws", n_views=n_views, width=320, height=240, focal=300.0,
                                 write_maps=False)
    model = gt["model"]
    entries = [
        {"name": im.name, "K": model.camera_of(im).K.tolist(), "cam_from_world": im.cam_from_world.tolist()}
        for im in model.images.values()
    ]
    (tmp_path / "poses.json").write_text(json.dumps({"images": entries}))
    return gt


def test_analytic_scene_points_land_on_the_surface(tmp_path):
    """Exact cameras of the analytic scene: triangulated points lie on its surface, poses stay fixed."""
    import pycolmap

    gt = _analytic_scene_with_poses(tmp_path)
    model = gt["model"]
    out = import_poses(
        ImportPosesConfig(
            image_path=tmp_path / "ws" / "images",
            poses_path=tmp_path / "poses.json",
            output_path=tmp_path / "out",
            max_num_features=1024,
            num_threads=1,
        )
    )
    assert out == tmp_path / "out" / "sparse"
    rec = pycolmap.Reconstruction(str(out))
    assert rec.num_reg_images() == 5 and rec.num_points3D() >= 20
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    assert np.median(gt["scene"].distance(xyz)) < 0.015 * gt["scene"].size
    assert np.median(reprojection_errors(out)) < 1.0
    by_name = {im.name: im for im in model.images.values()}
    for image in rec.images.values():
        np.testing.assert_allclose(
            image.cam_from_world().matrix(), by_name[image.name].cam_from_world, atol=1e-6
        )
        assert image.camera.model_name == "PINHOLE"
        # 5 images: too few to refine the focal lengths (MIN_IMAGES_TO_REFINE_FOCAL), kept exactly
        np.testing.assert_allclose(image.camera.calibration_matrix(), model.camera_of(by_name[image.name]).K)
    # Resumable: a second call with the same settings returns the existing model without recomputing.
    mtime = (out / "points3D.bin").stat().st_mtime_ns
    import_poses(
        ImportPosesConfig(
            image_path=tmp_path / "ws" / "images",
            poses_path=tmp_path / "poses.json",
            output_path=tmp_path / "out",
            max_num_features=1024,
            num_threads=2,  # threads do not change the model
        )
    )
    assert (out / "points3D.bin").stat().st_mtime_ns == mtime


def test_a_focal_length_off_by_two_percent_is_refined_with_the_poses_fixed(tmp_path, caplog):
    """10 images rendered at focal 300 px but declared at 306 px: the default ``refine_focal_length``
    brings the focal length back to within 1 % of the true one (the poses and principal point stay as
    given), and the triangulated points nearer the surface; with it off, or with fewer images than
    ``MIN_IMAGES_TO_REFINE_FOCAL``, the declared calibration is kept. A record from before the setting
    existed stands for a model made without the refinement."""
    import pycolmap

    gt = _analytic_scene_with_poses(tmp_path, n_views=MIN_IMAGES_TO_REFINE_FOCAL)
    entries = json.loads((tmp_path / "poses.json").read_text())["images"]
    for e in entries:
        e["K"][0][0] *= 1.02
        e["K"][1][1] *= 1.02
    (tmp_path / "poses.json").write_text(json.dumps({"images": entries}))

    def run(out: str, **kw) -> pycolmap.Reconstruction:
        model_dir = import_poses(ImportPosesConfig(image_path=tmp_path / "ws" / "images",
                                                   poses_path=tmp_path / "poses.json",
                                                   output_path=tmp_path / out, num_threads=1, **kw))
        return pycolmap.Reconstruction(str(model_dir))

    declared = {e["name"]: np.array(e["K"]) for e in entries}
    with caplog.at_level(logging.INFO, logger="colmap_pvs.io.import_poses"):
        refined = run("refined")
    assert "focal length refined from 306.00, 306.00 to" in caplog.text
    kept = run("kept", refine_focal_length=False)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="colmap_pvs.io.import_poses"):
        few = run("few", max_images=MIN_IMAGES_TO_REFINE_FOCAL - 1)
    assert f"has {MIN_IMAGES_TO_REFINE_FOCAL - 1} image(s)" in caplog.text
    from colmap_pvs.cli.reports_pipeline import report_import_poses  # says what was actually held

    assert "focal lengths refined" in report_import_poses(tmp_path / "refined" / "sparse")
    assert "poses and intrinsics held fixed" in report_import_poses(tmp_path / "few" / "sparse")
    poses = {e["name"]: np.array(e["cam_from_world"]) for e in entries}
    for rec, focal, rtol in ((refined, 300.0, 0.01), (kept, 306.0, 1e-9), (few, 306.0, 1e-9)):
        for image in rec.images.values():
            K = image.camera.calibration_matrix()
            np.testing.assert_allclose(K[[0, 1], [0, 1]], focal, rtol=rtol)
            np.testing.assert_allclose(K[:2, 2], declared[image.name][:2, 2])  # principal point as given
            np.testing.assert_allclose(image.cam_from_world().matrix(), poses[image.name][:3], atol=1e-6)
    near = np.median(gt["scene"].distance(np.array([p.xyz for p in refined.points3D.values()])))
    far = np.median(gt["scene"].distance(np.array([p.xyz for p in kept.points3D.values()])))
    assert near < far, (near, far)
    record = tmp_path / "kept" / "import_poses.json"
    old = json.loads(record.read_text())
    del old["model_settings"]["refine_focal_length"]
    record.write_text(json.dumps(old))
    mtime = (tmp_path / "kept" / "sparse" / "points3D.bin").stat().st_mtime_ns
    run("kept", refine_focal_length=False)  # the same model: reused
    assert (tmp_path / "kept" / "sparse" / "points3D.bin").stat().st_mtime_ns == mtime
    with pytest.raises(ConfigError, match="refine_focal_length False -> True"):
        run("kept")


def test_one_camera_with_too_few_images_keeps_every_focal_length_with_a_warning(caplog):
    """The focal lengths move only where every camera has ``MIN_IMAGES_TO_REFINE_FOCAL`` images; a camera
    short of them stops the refinement of all, with a warning naming it when others had enough."""
    from types import SimpleNamespace

    from colmap_pvs.io.import_poses import _enough_images_to_refine

    def images(counts: dict[int, int]) -> list:
        return [SimpleNamespace(camera_id=c) for c, n in counts.items() for _ in range(n)]

    enough = MIN_IMAGES_TO_REFINE_FOCAL
    assert _enough_images_to_refine(images({1: enough, 2: enough + 5}))
    with caplog.at_level(logging.INFO, logger="colmap_pvs.io.import_poses"):
        assert not _enough_images_to_refine(images({1: enough + 2, 2: 3}))
    assert [r.levelno for r in caplog.records] == [logging.WARNING]
    assert "camera 2 has 3 image(s)" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="colmap_pvs.io.import_poses"):
        assert not _enough_images_to_refine(images({1: enough - 1}))
    assert [r.levelno for r in caplog.records] == [logging.INFO]


def _keypoint_counts(db_path) -> list[int]:
    import sqlite3

    with sqlite3.connect(db_path) as db:
        return [row[0] for row in db.execute("SELECT rows FROM keypoints ORDER BY image_id")]


def test_settings_are_recorded_and_a_changed_peak_threshold_recomputes(tmp_path, caplog):
    """The SIFT peak threshold reaches pycolmap (a higher one finds fewer keypoints in every image), and
    a model made with other settings is refused, then recomputed with ``overwrite``."""
    _analytic_scene_with_poses(tmp_path)

    def config(**kw):
        return ImportPosesConfig(
            image_path=tmp_path / "ws" / "images",
            poses_path=tmp_path / "poses.json",
            output_path=tmp_path / "out",
            num_threads=1,
            **kw,
        )

    out = import_poses(config(sift_peak_threshold=0.002))
    recorded = json.loads((tmp_path / "out" / "import_poses.json").read_text())
    assert recorded["model_settings"]["sift_peak_threshold"] == 0.002
    low = _keypoint_counts(tmp_path / "out" / "database.db")
    mtime = (out / "points3D.bin").stat().st_mtime_ns
    with pytest.raises(ConfigError, match=r"sift_peak_threshold 0\.002 -> 0\.008"):
        import_poses(config(sift_peak_threshold=0.008))
    assert (out / "points3D.bin").stat().st_mtime_ns == mtime  # refused: nothing touched
    import_poses(config(sift_peak_threshold=0.008, overwrite=True))
    high = _keypoint_counts(tmp_path / "out" / "database.db")
    assert len(low) == len(high) == 5
    assert all(h < lo for h, lo in zip(high, low, strict=True)), (low, high)
    assert (
        json.loads((tmp_path / "out" / "import_poses.json").read_text())["model_settings"][
            "sift_peak_threshold"
        ]
        == 0.008
    )
    for bad in (0.0, -0.01, 1.5, float("nan")):
        with pytest.raises(ConfigError, match="sift_peak_threshold"):
            config(sift_peak_threshold=bad)
    # A damaged record is refused naming the file; a model without one (made before the record
    # existed) is reused as it is, with a warning.
    record = tmp_path / "out" / "import_poses.json"
    record.write_text("{not json")
    with pytest.raises(WorkspaceError, match="import_poses.json"):
        import_poses(config(sift_peak_threshold=0.008))
    record.unlink()
    mtime = (out / "points3D.bin").stat().st_mtime_ns
    with caplog.at_level(logging.WARNING, logger="colmap_pvs.io.import_poses"):
        assert import_poses(config(sift_peak_threshold=0.002)) == out
    assert "no record of its settings" in caplog.text
    assert (out / "points3D.bin").stat().st_mtime_ns == mtime


def test_missing_images_are_named(tmp_path):
    K = [[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]]
    pose = np.eye(3, 4).tolist()
    (tmp_path / "p.json").write_text(json.dumps([{"name": "nope.png", "K": K, "cam_from_world": pose}]))
    (tmp_path / "images").mkdir()
    with pytest.raises(WorkspaceError, match="nope.png"):
        import_poses(
            ImportPosesConfig(
                image_path=tmp_path / "images", poses_path=tmp_path / "p.json", output_path=tmp_path / "out"
            )
        )


@pytest.mark.slow
@pytest.mark.parametrize(
    "folder, marker, subset, max_median_px",
    [
        ("hololens-dev", "poses.txt", {"frame_step": 3, "max_images": 15}, 1.0),
        ("fountain-P11", "cameras", {"max_images": 6}, 0.5),
    ],
)
def test_real_subset_subpixel(shared_data_dir, tmp_path, folder, marker, subset, max_median_px):
    data = shared_data_dir / folder
    if not (data / marker).exists():
        pytest.skip(f"{data} is missing")
    out = import_poses(
        ImportPosesConfig(
            image_path=data / "images",
            poses_path=data,
            output_path=tmp_path / "out",
            max_num_features=1024,
            num_threads=2,
            **subset,
        )
    )
    errs = reprojection_errors(out)
    assert errs.size > 1000
    assert np.median(errs) < max_median_px


def test_a_failed_overwrite_keeps_the_old_model_record_and_database(tmp_path, monkeypatch):
    """`--overwrite` deleted the model, its record and the database before making new ones: a full disk
    during the new feature extraction left nothing. Now the new database is built beside the old one."""

    import colmap_pvs.io.import_poses as module

    _analytic_scene_with_poses(tmp_path)
    config = dict(image_path=tmp_path / "ws" / "images", poses_path=tmp_path / "poses.json",
                  output_path=tmp_path / "out", num_threads=1)
    import_poses(ImportPosesConfig(**config))
    out = tmp_path / "out"
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert {Path("database.db"), Path("import_poses.json"), Path("sparse/points3D.bin")} <= set(before)

    monkeypatch.setattr(module, "extract_features", disk_full_after_writing_half)
    with pytest.raises(OSError, match="No space left"):
        import_poses(ImportPosesConfig(**config, sift_peak_threshold=0.008, overwrite=True))
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
