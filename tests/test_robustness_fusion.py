"""Issue 11, fusion: fused.ply and its .vis become visible together or not at all; --method colmap
checks the maps first (0-byte, truncated, mis-sized maps are skipped with a warning, as with pvs)."""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

import pytest

from colmap_pvs.errors import OutputError, WorkspaceError
from colmap_pvs.fusion import FuseConfig, fuse
from colmap_pvs.io.maps import write_array
from colmap_pvs.io.ply import cloud_pair_is_complete, read_point_cloud, read_visibility


@pytest.fixture()
def workspace(analytic_scene, tmp_path) -> Path:
    root = tmp_path / "ws"
    shutil.copytree(analytic_scene["root"], root)
    return root


def _pair(ws: Path) -> tuple[Path, Path]:
    return ws / "fused.ply", ws / "fused.ply.vis"


def _consistent(ws: Path) -> bool:
    ply, vis = _pair(ws)
    if not ply.exists():
        return True  # no cloud: no result, nothing mismatched
    offsets, _ = read_visibility(vis)
    return len(offsets) - 1 == len(read_point_cloud(ply))


@pytest.mark.parametrize("method", ["pvs", "colmap"])
@pytest.mark.parametrize("killed_at", ["fused.ply", "fused.ply.vis"])
def test_kill_between_the_renames_never_leaves_a_mismatched_pair(workspace, method, killed_at, monkeypatch):
    # The old pair is made stricter than the new one, so the two differ in size.
    strict = {"min_consistent_views": 4} if method == "pvs" else {"colmap_options": ("min_num_pixels=5",)}
    fuse(FuseConfig(workspace_path=workspace, method=method, **strict))  # the old pair
    old_points = len(read_point_cloud(_pair(workspace)[0]))
    real_replace = os.replace

    def killed(src, dst):
        if str(dst).endswith(killed_at):
            raise KeyboardInterrupt  # stands for kill -9 at this rename
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        fuse(FuseConfig(workspace_path=workspace, method=method))
    monkeypatch.undo()
    assert _consistent(workspace)  # the old pair, or no cloud at all; never a mixed pair
    assert not list(workspace.glob(".fused.ply*"))
    result = fuse(FuseConfig(workspace_path=workspace, method=method))
    assert result.num_points > 1.2 * old_points and _consistent(workspace)
    assert cloud_pair_is_complete(workspace / "fused.ply")


def test_disk_full_while_writing_the_vis_keeps_the_old_pair(workspace, monkeypatch):
    import colmap_pvs.io.files as files_module

    fuse(FuseConfig(workspace_path=workspace))
    ply, vis = _pair(workspace)
    before = (ply.read_bytes(), vis.read_bytes())
    real = files_module.tempfile.mkstemp

    def full(*args, **kwargs):
        if kwargs.get("prefix", "").startswith(".fused.ply.vis."):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(*args, **kwargs)

    monkeypatch.setattr(files_module.tempfile, "mkstemp", full)
    with pytest.raises(OutputError, match="fused.ply.vis.*No space left"):
        fuse(FuseConfig(workspace_path=workspace, min_consistent_views=1))
    assert (ply.read_bytes(), vis.read_bytes()) == before
    assert sorted(p.name for p in workspace.glob("*fused.ply*")) == ["fused.ply", "fused.ply.vis"]


@pytest.mark.parametrize("damage", ["empty normal", "truncated depth", "mis-sized normal"])
def test_colmap_method_checks_maps_first(workspace, analytic_scene, damage, caplog):
    name = analytic_scene["names"][1]
    depth = workspace / "stereo" / "depth_maps" / f"{name}.geometric.bin"
    normal = workspace / "stereo" / "normal_maps" / f"{name}.geometric.bin"
    if damage == "empty normal":
        normal.write_bytes(b"")
    elif damage == "truncated depth":
        data = depth.read_bytes()
        depth.write_bytes(data[: len(data) // 2])
    else:
        import numpy as np

        write_array(normal, np.tile(np.array([0, 0, -1.0], np.float32), (60, 80, 1)))
    with caplog.at_level("WARNING"):
        result = fuse(FuseConfig(workspace_path=workspace, method="colmap"))
    assert name in result.skipped and result.num_images == 4 and result.num_points > 0
    assert name in caplog.text
    assert cloud_pair_is_complete(result.output_path)
    assert (workspace / "stereo" / "fusion.cfg").read_text().count(name) == 1  # the user's file untouched


@pytest.mark.parametrize("method", ["pvs", "colmap"])
def test_an_empty_cloud_is_an_error_and_the_old_cloud_stays(workspace, analytic_scene, method, capsys):
    """`fuse --input_type geometric` on maps that agree nowhere wrote "0 points from 3 images" and exited 0:
    now one line naming the maps, a non-zero exit, and the cloud already there untouched."""
    from colmap_pvs.cli.main import main
    from colmap_pvs.io.maps import read_depth_map, write_depth_map

    fuse(FuseConfig(workspace_path=workspace, method=method))
    ply, vis = _pair(workspace)
    before = (ply.read_bytes(), vis.read_bytes())
    for i, name in enumerate(analytic_scene["names"]):  # every map at another scale: no two agree
        path = workspace / "stereo" / "depth_maps" / f"{name}.geometric.bin"
        write_depth_map(path, read_depth_map(path) * (1.5 ** i))
    code = main(["fuse", "--workspace_path", str(workspace), "--input_type", "geometric", "--method", method])
    err = capsys.readouterr().err.strip().splitlines()[-1]  # after the progress bar
    assert code == 1 and err.startswith("colmap-pvs fuse: error: fusion made no points"), err
    assert "no points from the geometric maps of 5 image(s)" in err and analytic_scene["names"][0] in err
    assert (ply.read_bytes(), vis.read_bytes()) == before
    assert sorted(p.name for p in workspace.glob("*fused.ply*")) == ["fused.ply", "fused.ply.vis"]


def test_colmap_method_with_every_map_broken_is_an_error(workspace, analytic_scene):
    for path in (workspace / "stereo" / "normal_maps").glob("*.bin"):
        path.write_bytes(b"")
    with pytest.raises(WorkspaceError, match="no usable"):
        fuse(FuseConfig(workspace_path=workspace, method="colmap"))
    assert not (workspace / "fused.ply").exists()
