"""Sparse model reading/writing: round trips, real data and clear errors."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_pvs.errors import UnsupportedCameraError, WorkspaceError
from colmap_pvs.io import read_sparse_model, write_sparse_model
from colmap_pvs.io.sparse import image_indices, images_bin_order
from colmap_pvs.types import Camera, Image, Points3D, SparseModel


def _assert_models_equal(a: SparseModel, b: SparseModel) -> None:
    assert sorted(a.cameras) == sorted(b.cameras)
    for cid, cam in a.cameras.items():
        other = b.cameras[cid]
        assert (cam.model, cam.width, cam.height) == (other.model, other.width, other.height)
        np.testing.assert_allclose(cam.K, other.K, rtol=0, atol=1e-12)
        np.testing.assert_allclose(cam.params, other.params, rtol=0, atol=1e-12)
    assert sorted(a.images) == sorted(b.images)
    for iid, image in a.images.items():
        other = b.images[iid]
        assert (image.name, image.camera_id) == (other.name, other.camera_id)
        np.testing.assert_allclose(image.cam_from_world, other.cam_from_world, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(np.unique(image.point3D_ids), other.point3D_ids)
    np.testing.assert_array_equal(a.points.ids, b.points.ids)
    np.testing.assert_allclose(a.points.xyz, b.points.xyz, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(a.points.rgb, b.points.rgb)
    np.testing.assert_allclose(a.points.error, b.points.error)
    for i in range(len(a.points)):
        assert sorted(a.points.track(i)) == sorted(b.points.track(i))
    assert a.image_ids_by_name == b.image_ids_by_name


@pytest.mark.parametrize("binary", [True, False])
def test_write_read_round_trip(analytic_scene: dict, tmp_path: Path, binary: bool) -> None:
    model = analytic_scene["model"]
    out = write_sparse_model(model, tmp_path / "model", binary=binary)
    suffix = ".bin" if binary else ".txt"
    assert {"cameras", "images", "points3D"} <= {p.stem for p in out.iterdir() if p.suffix == suffix}
    _assert_models_equal(model, read_sparse_model(out))
    assert [p.name for p in tmp_path.iterdir()] == ["model"]  # no temp folders left


def test_written_observations_are_exact_projections(analytic_scene: dict, tmp_path: Path) -> None:
    out = write_sparse_model(analytic_scene["model"], tmp_path / "model")
    rec = pycolmap.Reconstruction(str(out))
    assert rec.compute_num_observations() == analytic_scene["model"].points.track_image_ids.size
    rec.update_point_3d_errors()
    assert rec.compute_mean_reprojection_error() < 1e-9


def test_image_point_ids_match_tracks(analytic_scene: dict) -> None:
    model = read_sparse_model(analytic_scene["root"] / "sparse")
    for image in model.images.values():
        expected = [
            model.points.ids[i] for i in range(len(model.points)) if image.image_id in model.points.track(i)
        ]
        np.testing.assert_array_equal(image.point3D_ids, sorted(expected))
        assert image.point3D_ids.dtype == np.int64
    assert model.points.track_offsets[-1] == model.points.track_image_ids.size
    assert model.points.xyz.dtype == np.float64 and model.points.rgb.dtype == np.uint8


def test_overwrite_existing_model_but_not_foreign_folder(analytic_scene: dict, tmp_path: Path) -> None:
    model = analytic_scene["model"]
    out = write_sparse_model(model, tmp_path / "model", binary=False)
    write_sparse_model(model, out, binary=True)  # replaces the text model
    assert {p.suffix for p in out.iterdir()} == {".bin"}
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.md").write_text("keep me")
    with pytest.raises(WorkspaceError, match="notes.md"):
        write_sparse_model(model, foreign)
    assert [p.name for p in foreign.iterdir()] == ["notes.md"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["foreign", "model"]


def test_failed_write_leaves_nothing(analytic_scene: dict, tmp_path: Path) -> None:
    model = analytic_scene["model"]
    image = next(iter(model.images.values()))
    flipped = Image(image.image_id, image.name, image.camera_id, -image.cam_from_world, image.point3D_ids)
    bad = SparseModel(
        model.cameras, {**model.images, image.image_id: flipped}, model.points, model.image_ids_by_name
    )
    with pytest.raises(WorkspaceError, match="behind its camera"):
        write_sparse_model(bad, tmp_path / "model")
    assert list(tmp_path.iterdir()) == []


def test_statue_model(statue_workspace: Path) -> None:
    model = read_sparse_model(statue_workspace / "sparse")
    assert len(model.images) == 23
    assert len(model.points) == 1443
    assert all(cam.model == "PINHOLE" for cam in model.cameras.values())
    heights = {model.camera_of(im).height for im in model.images.values()}
    assert min(heights) == 656 and max(heights) == 662
    for image in model.images.values():
        R = image.R
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
        cam = model.camera_of(image)
        assert cam.K[0, 0] == cam.params[0] and cam.K[1, 1] == cam.params[1]
        assert (cam.K[0, 2], cam.K[1, 2]) == (cam.params[2], cam.params[3])
        assert np.isin(image.point3D_ids, model.points.ids).all()
    # points seen in front of every camera of their track
    for i in range(0, len(model.points), 50):
        for image_id in model.points.track(i):
            image = model.images[int(image_id)]
            assert (image.R @ model.points.xyz[i] + image.t)[2] > 0


# --------------------------------------------------------------------------- errors


def test_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(WorkspaceError, match="does not exist") as info:
        read_sparse_model(tmp_path / "nothing")
    assert "nothing" in str(info.value)


def test_missing_files_are_named(analytic_scene: dict, tmp_path: Path) -> None:
    model_dir = shutil.copytree(analytic_scene["root"] / "sparse", tmp_path / "sparse")
    (model_dir / "points3D.bin").unlink()
    with pytest.raises(WorkspaceError, match=r"missing points3D\.bin") as info:
        read_sparse_model(model_dir)
    assert str(model_dir) in str(info.value)


def test_empty_model(tmp_path: Path) -> None:
    empty = SparseModel(
        cameras={},
        images={},
        points=Points3D(
            ids=np.zeros(0, np.int64),
            xyz=np.zeros((0, 3)),
            rgb=np.zeros((0, 3), np.uint8),
            error=np.zeros(0),
            track_offsets=np.zeros(1, np.int64),
            track_image_ids=np.zeros(0, np.int64),
        ),
    )
    out = write_sparse_model(empty, tmp_path / "empty")
    with pytest.raises(WorkspaceError, match="is empty") as info:
        read_sparse_model(out)
    assert str(out) in str(info.value)


@pytest.mark.parametrize("victim", ["images.bin", "cameras.bin", "points3D.bin"])
def test_corrupt_model(analytic_scene: dict, tmp_path: Path, victim: str) -> None:
    model_dir = shutil.copytree(analytic_scene["root"] / "sparse", tmp_path / "sparse")
    data = (model_dir / victim).read_bytes()
    (model_dir / victim).write_bytes(data[: len(data) // 2])
    with pytest.raises(WorkspaceError, match="could not read") as info:
        read_sparse_model(model_dir)
    assert str(model_dir) in str(info.value)


def _distorted_model(model: SparseModel) -> SparseModel:
    cam = model.cameras[1]
    radial = Camera(
        1, "SIMPLE_RADIAL", cam.width, cam.height, cam.K, np.array([cam.K[0, 0], *cam.K[:2, 2], 0.05])
    )
    return SparseModel({1: radial}, model.images, model.points, model.image_ids_by_name)


def test_distorted_camera_is_refused(analytic_scene: dict, tmp_path: Path) -> None:
    out = write_sparse_model(_distorted_model(analytic_scene["model"]), tmp_path / "radial")
    with pytest.raises(UnsupportedCameraError, match="camera 1 .*SIMPLE_RADIAL") as info:
        read_sparse_model(out)
    assert "colmap-pvs undistort" in str(info.value) and "image_undistorter" in str(info.value)
    model = read_sparse_model(out, require_pinhole=False)
    assert model.cameras[1].model == "SIMPLE_RADIAL"
    np.testing.assert_allclose(model.cameras[1].params[-1], 0.05)  # distortion kept, not dropped


def test_distorted_cameras_are_one_warning(
    analytic_scene: dict, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 41 item 7: one camera per image (COLMAP without single_camera) gives one summary
    WARNING for all distorted cameras, each camera only at DEBUG."""
    import dataclasses

    model = _distorted_model(analytic_scene["model"])
    radial = model.cameras[1]
    cameras = {i: dataclasses.replace(radial, camera_id=i) for i in model.images}
    images = {i: dataclasses.replace(im, camera_id=i) for i, im in model.images.items()}
    out = write_sparse_model(
        SparseModel(cameras, images, model.points, model.image_ids_by_name), tmp_path / "radial"
    )
    with caplog.at_level("DEBUG", logger="colmap_pvs.io.sparse"):
        read_sparse_model(out, require_pinhole=False)
    warnings = [r for r in caplog.records if r.levelname == "WARNING"]
    n = len(images)
    assert len(warnings) == 1 and f"{n} of {n} camera(s)" in warnings[0].getMessage()
    assert len([r for r in caplog.records if r.levelname == "DEBUG" and "distortion" in r.getMessage()]) == n


def test_images_bin_order_is_the_files_order(analytic_scene: dict, tmp_path: Path, caplog) -> None:
    """``images.bin`` records stored out of id order (as COLMAP <= 3.9 numbered them in ``.vis`` files)
    are read in the file's order and warned about; a cut-short file reads as unknown, silently."""
    model = read_sparse_model(analytic_scene["root"] / "sparse")
    write_sparse_model(model, tmp_path / "sparse")
    path = tmp_path / "sparse" / "images.bin"
    data = path.read_bytes()
    records, offset = [], 8
    while offset < len(data):  # id, qvec, tvec, camera id (64 bytes), name, 2D points
        end = data.index(b"\0", offset + 64) + 1
        size = end + 8 + 24 * int(np.frombuffer(data, "<u8", 1, end)[0]) - offset
        records.append(data[offset : offset + size])
        offset += size
    ids = sorted(model.images)
    expected = {model.images[i].name: k for k, i in enumerate(ids)}
    assert images_bin_order(path) == ids
    with caplog.at_level("WARNING", logger="colmap_pvs"):
        assert image_indices(tmp_path / "sparse", model) == expected
    assert not caplog.records
    path.write_bytes(data[:8] + b"".join(reversed(records)))
    assert images_bin_order(path) == ids[::-1]
    with caplog.at_level("WARNING", logger="colmap_pvs"):
        assert image_indices(tmp_path / "sparse", model) == expected  # the index stays by id
    assert "out of id order" in caplog.text
    path.write_bytes(data[:-3])
    assert images_bin_order(path) is None
