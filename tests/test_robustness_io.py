"""Issue 11, input validation where data enters: cameras, poses, points, images."""

from __future__ import annotations

import shutil
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from colmap_pvs.errors import WorkspaceError
from colmap_pvs.io.images import check_image_file, load_image
from colmap_pvs.io.sparse import read_sparse_model


def _model_copy(analytic_scene, tmp_path: Path) -> Path:
    """A copy in COLMAP <= 3.11's layout (no rigs.bin / frames.bin: images.bin holds the poses)."""
    out = tmp_path / "sparse"
    shutil.copytree(analytic_scene["root"] / "sparse", out)
    for extra in ("rigs.bin", "frames.bin"):
        (out / extra).unlink(missing_ok=True)
    return out


def _patch(path: Path, offset: int, fmt: str, *values) -> None:
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset, *values)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("focal", [0.0, -150.0, float("nan")])
def test_non_positive_focal_length_is_a_clear_error(analytic_scene, tmp_path, focal):
    sparse = _model_copy(analytic_scene, tmp_path)
    # cameras.bin: uint64 count, then camera_id int32, model int32, width uint64, height uint64, params
    _patch(sparse / "cameras.bin", 8 + 24, "<d", focal)
    with pytest.raises(WorkspaceError, match=r"cameras\.bin.*camera 1.*focal") as info:
        read_sparse_model(sparse)
    assert str(focal) in str(info.value) and "\n" not in str(info.value)


def test_nan_quaternion_is_a_clear_error(analytic_scene, tmp_path):
    sparse = _model_copy(analytic_scene, tmp_path)
    # images.bin: uint64 count, then image_id uint32, qw qx qy qz, tx ty tz (doubles), ...
    _patch(sparse / "images.bin", 8 + 4, "<d", float("nan"))
    with pytest.raises(WorkspaceError, match=r"images\.bin.*view_000\.png.*pose.*nan"):
        read_sparse_model(sparse)


def test_zero_quaternion_and_infinite_translation_are_errors(analytic_scene, tmp_path):
    sparse = _model_copy(analytic_scene, tmp_path)
    _patch(sparse / "images.bin", 8 + 4, "<dddd", 0.0, 0.0, 0.0, 0.0)
    with pytest.raises(WorkspaceError, match="view_000.png"):
        read_sparse_model(sparse)
    sparse = _model_copy(analytic_scene, tmp_path / "b")
    _patch(sparse / "images.bin", 8 + 4 + 32, "<d", float("inf"))
    with pytest.raises(WorkspaceError, match="view_000.png.*inf"):
        read_sparse_model(sparse)


def test_non_finite_points_are_dropped_with_a_warning(analytic_scene, tmp_path, caplog):
    sparse = _model_copy(analytic_scene, tmp_path)
    n_before = len(read_sparse_model(sparse).points)
    # points3D.bin: uint64 count, then point_id uint64, xyz doubles, ...
    _patch(sparse / "points3D.bin", 8 + 8, "<d", float("nan"))
    with caplog.at_level("WARNING"):
        model = read_sparse_model(sparse)
    assert len(model.points) == n_before - 1 and np.isfinite(model.points.xyz).all()
    assert "non-finite" in caplog.text and "1 " in caplog.text


def _photo(path: Path, ext: str) -> bytes:
    rng = np.random.default_rng(0)
    smooth = cv2.GaussianBlur((rng.random((240, 320, 3)) * 255).astype(np.uint8), (0, 0), 5)
    ok, buf = cv2.imencode(ext, smooth)
    assert ok
    return buf.tobytes()


@pytest.mark.parametrize("ext", [".png", ".jpg"])
@pytest.mark.parametrize("keep", [0.3, 0.9])
def test_truncated_images_are_refused(tmp_path, ext, keep):
    data = _photo(tmp_path, ext)
    path = tmp_path / f"cut{ext}"
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(WorkspaceError, match="truncated") as info:
        load_image(path)
    assert str(path) in str(info.value)
    with pytest.raises(WorkspaceError, match="truncated"):
        check_image_file(path)
    whole = tmp_path / f"whole{ext}"
    whole.write_bytes(data)
    check_image_file(whole)
    assert load_image(whole).shape == (240, 320, 3)


def test_empty_image_file_is_named_as_empty(tmp_path):
    path = tmp_path / "empty.png"
    path.write_bytes(b"")
    for fn in (load_image, check_image_file):
        with pytest.raises(WorkspaceError, match="empty.png.*empty \\(0 bytes\\)"):
            fn(path)


def test_undistort_does_not_claim_distortion_is_ignored(analytic_scene, tmp_path, caplog):
    from test_io_workspace import _make_distorted_workspace

    from colmap_pvs.io.workspace import UndistortConfig, undistort

    src = _make_distorted_workspace(analytic_scene, tmp_path / "distorted")
    with caplog.at_level("INFO"):
        undistort(UndistortConfig(image_path=src / "images", input_path=src / "sparse",
                                  output_path=tmp_path / "dense"))
    assert "undistorted 5 images" in caplog.text
    assert "distortion is ignored" not in caplog.text
    with caplog.at_level("WARNING"):  # reading it without undistorting still says so
        read_sparse_model(src / "sparse", require_pinhole=False)
    assert "distortion is ignored" in caplog.text


def test_undistort_refuses_a_truncated_photo(analytic_scene, tmp_path):
    from colmap_pvs.io.workspace import UndistortConfig, undistort

    images = tmp_path / "images"
    shutil.copytree(analytic_scene["root"] / "images", images)
    data = (images / "view_003.png").read_bytes()
    (images / "view_003.png").write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(WorkspaceError, match=r"view_003\.png.*truncated"):
        undistort(UndistortConfig(image_path=images, input_path=analytic_scene["root"] / "sparse",
                                  output_path=tmp_path / "dense"))
    assert not (tmp_path / "dense").exists()
