"""``reconstruct``: the fast variant starts from an existing sparse model of the analytic scene; the
slow one runs SfM on ``../shared/data/fern-images`` (stopping after mapping)."""

from __future__ import annotations

import pytest
from conftest import make_tiny_checkpoint
from scenes import reconstruct_config

from colmap_pvs.cli.main import main
from colmap_pvs.errors import CheckpointError, WorkspaceError
from colmap_pvs.io.ply import read_point_cloud
from colmap_pvs.reconstruct import reconstruct


def test_reconstruct_from_existing_model_and_resume(analytic_scene, tmp_path, capsys):
    ws = analytic_scene["root"]
    ckpt = make_tiny_checkpoint(tmp_path / "tiny.pt")
    out = tmp_path / "out"
    argv = [
        "reconstruct",
        "--image_path",
        str(ws / "images"),
        "--workspace_path",
        str(out),
        "--input_path",
        str(ws / "sparse"),
        "--checkpoint",
        str(ckpt),
        "--num_views",
        "3",
        "--mesh_depth",
        "6",
        "--num_threads",
        "1",
    ]
    assert main(argv) == 0
    report = capsys.readouterr().out
    assert "images registered: 5/5" in report and "time per stage" in report
    for stage in ("undistort", "stereo", "fusion"):
        assert stage in report
    dense = out / "dense"
    assert len(list((dense / "stereo" / "depth_maps").glob("*.geometric.bin"))) == 5
    assert (dense / "fused.ply").is_file() and (dense / "fused.ply.vis").is_file()
    read_point_cloud(dense / "fused.ply")

    # A second run finds every finished output and recomputes nothing.
    mtime = (dense / "fused.ply").stat().st_mtime_ns
    rerun = reconstruct_config(
        image_path=ws / "images",
        workspace_path=out,
        input_path=ws / "sparse",
        checkpoint=ckpt,
        num_views=3,
        mesh_depth=6,
    )
    result = reconstruct(rerun)
    assert {"undistort", "stereo", "fusion"} <= set(result.resumed)
    assert (dense / "fused.ply").stat().st_mtime_ns == mtime
    assert result.num_registered == 5 and result.num_fused_points == len(
        read_point_cloud(dense / "fused.ply")
    )

    # With the fused cloud gone (a run stopped during fusion), only fusion runs again.
    (dense / "fused.ply").unlink()
    result = reconstruct(rerun)
    assert "stereo" in result.resumed and "fusion" not in result.resumed
    assert (dense / "fused.ply").is_file()


def test_reconstruct_errors(tmp_path, monkeypatch):
    import colmap_pvs.stereo.config as stereo_module

    with pytest.raises(WorkspaceError, match="does not exist"):
        reconstruct(reconstruct_config(image_path=tmp_path / "nope", workspace_path=tmp_path / "o"))
    (tmp_path / "imgs").mkdir()
    with pytest.raises(WorkspaceError, match="0 image"):
        reconstruct(reconstruct_config(image_path=tmp_path / "imgs", workspace_path=tmp_path / "o"))
    for i in range(2):
        (tmp_path / "imgs" / f"{i}.png").write_bytes(b"")
    monkeypatch.setattr(stereo_module, "DEFAULT_CHECKPOINT", tmp_path / "missing.pt")
    with pytest.raises(CheckpointError, match="missing.pt"):
        reconstruct(reconstruct_config(image_path=tmp_path / "imgs", workspace_path=tmp_path / "o"))


@pytest.mark.slow
def test_fern_sfm_registers_every_image(shared_data_dir, tmp_path):
    images = shared_data_dir / "fern-images"
    if not images.is_dir():
        pytest.skip(f"{images} is missing")
    result = reconstruct(
        reconstruct_config(
            image_path=images,
            workspace_path=tmp_path / "fern",
            single_camera=True,
            max_num_features=1024,
            num_threads=2,
            stop_after="mapping",
        )
    )
    assert result.num_images == 20
    assert result.num_registered == 20
    assert result.num_points3D > 500
