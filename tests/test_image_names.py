"""Image names COLMAP allows: sub-folders (rigs write ``cam0/0001.jpg``), spaces and non-ASCII letters.

The whole chain works on them and writes where COLMAP does: ``stereo/depth_maps/cam0/0001.jpg.geometric.bin``.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
from scenes import ODD_NAMES as ODD
from scenes import make_odd_names_workspace, stereo_config

from colmap_pvs.cli.main import main
from colmap_pvs.fusion import FuseConfig, fuse
from colmap_pvs.io.maps import read_depth_map
from colmap_pvs.io.ply import read_point_cloud
from colmap_pvs.io.workspace import read_fusion_cfg
from colmap_pvs.stereo import run_stereo


@pytest.fixture(scope="module")
def odd_ws(tmp_path_factory) -> Path:
    return make_odd_names_workspace(tmp_path_factory.mktemp("names") / "ws")


def test_stereo_fuse_and_previews_work_on_sub_folder_names_with_spaces_and_non_ascii(odd_ws, tmp_path,
                                                                                      tiny_checkpoint):
    ws = tmp_path / "ws"
    shutil.copytree(odd_ws, ws)
    cfg = stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3, max_image_size=64,
                        geom_min_consistent=1, geom_splat_min_sources=0, previews=True)
    res = run_stereo(cfg)
    assert sorted(res.processed) == sorted(ODD) and sorted(res.geometric_processed) == sorted(ODD)
    assert sorted(res.filled_processed) == sorted(ODD)
    stereo = ws / "stereo"
    for name in ODD:  # where COLMAP writes them
        for kind in ("photometric", "geometric", "filled"):
            assert read_depth_map(stereo / "depth_maps" / f"{name}.{kind}.bin").shape == (48, 64)
            assert (stereo / "provenance" / f"{name}.{kind}.json").is_file()
        assert (stereo / "normal_maps" / f"{name}.geometric.bin").is_file()
        assert (stereo / "seed_maps" / f"{name}.bin").is_file()
        assert (stereo / "seed_maps" / f"{name}.json").is_file()
        assert (stereo / "previews" / f"{name}.depth.png").is_file()
    assert sorted(read_fusion_cfg(stereo / "fusion.cfg")) == sorted(ODD)
    # a rerun resumes every pass
    again = run_stereo(cfg)
    assert sorted(again.already_done) == sorted(ODD) and not again.processed and not again.filled_processed
    out = fuse(FuseConfig(workspace_path=ws, output_path=ws / "fused.ply"))
    assert out.num_points > 0
    assert main(["stereo", "--workspace_path", str(ws), "--checkpoint", str(tiny_checkpoint),
                 "--num_views", "3", "--max_image_size", "64", "--geom_min_consistent", "1",
                 "--geom_splat_min_sources", "0"]) == 0


@pytest.mark.colmap_binary
def test_colmaps_own_fusion_reads_our_maps_of_sub_folder_names(odd_ws, tmp_path, tiny_checkpoint):
    if shutil.which("colmap") is None:
        pytest.skip("Debian's colmap binary is not installed (apt-get install colmap)")
    ws = tmp_path / "ws"
    shutil.copytree(odd_ws, ws)
    run_stereo(stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3, max_image_size=64,
                             geom_min_consistent=1, geom_splat_min_sources=0, geom_fill=False))
    out = ws / "colmap_fused.ply"
    proc = subprocess.run(["colmap", "stereo_fusion", "--workspace_path", str(ws), "--workspace_format",
                           "COLMAP", "--input_type", "geometric", "--output_path", str(out),
                           "--StereoFusion.min_num_pixels", "2"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert read_point_cloud(out).xyz.shape[0] > 0
