"""``colmap-pvs demo`` end to end (small), and its refusals with a tiny random test checkpoint."""

from __future__ import annotations

import os

import pytest

import colmap_pvs.stereo.config as stereo_module
from colmap_pvs.cli.main import main
from colmap_pvs.demo import DemoConfig, run_demo
from colmap_pvs.errors import CheckpointError, WorkspaceError
from colmap_pvs.io.ply import read_mesh, read_point_cloud

SMALL = [
    "--num_images",
    "4",
    "--width",
    "128",
    "--height",
    "96",
    "--num_views",
    "3",
    "--mesh_depth",
    "6",
    "--threads",
    "2",
]


def _cpu_seconds() -> float:
    """CPU time of this process (all its threads) and of its children that finished."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def test_demo_end_to_end_via_cli(tmp_path, capsys):
    """With the shipped weights (a random checkpoint may fuse no point, which is an error)."""
    out = tmp_path / "demo"
    start = _cpu_seconds()
    assert main(["demo", str(out), *SMALL]) == 0
    # quick: CPU seconds, which other jobs on a shared machine do not add to (wall-clock time they do)
    assert _cpu_seconds() - start < 45
    report = capsys.readouterr().out
    assert "depth vs GT: AbsRel" in report and "fused cloud" in report
    assert (out / "stereo" / "fusion.cfg").is_file()
    depth_maps = sorted((out / "stereo" / "depth_maps").glob("*.geometric.bin"))
    assert len(depth_maps) == 4
    assert list((out / "stereo" / "previews").glob("*.depth.png"))
    assert (out / "stereo" / "metrics.json").is_file()
    assert (out / "fused.ply.vis").is_file()
    assert len(read_point_cloud(out / "fused.ply")) > 100
    # Re-running into a previous demo output replaces it.
    result = run_demo(
        DemoConfig(output_path=out, num_images=5, width=128, height=96, num_views=3, mesh_depth=6)
    )
    assert result.num_images == 5 and result.depth_coverage_pct >= 0
    assert result.mesh_path is None or len(read_mesh(result.mesh_path)[1]) > 0


def test_demo_needs_a_checkpoint(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(stereo_module, "DEFAULT_CHECKPOINT", tmp_path / "missing.pt")
    with pytest.raises(CheckpointError, match="missing.pt"):
        run_demo(DemoConfig(output_path=tmp_path / "out"))
    assert not (tmp_path / "out").exists()  # fails before rendering anything
    assert main(["demo", str(tmp_path / "out")]) == 1
    assert "missing.pt" in capsys.readouterr().err


def test_demo_refuses_a_foreign_folder(tmp_path, monkeypatch, tiny_checkpoint):
    monkeypatch.setattr(stereo_module, "DEFAULT_CHECKPOINT", tiny_checkpoint)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("keep me")
    with pytest.raises(WorkspaceError, match="not a previous demo"):
        run_demo(DemoConfig(output_path=tmp_path / "mine"))
    assert (tmp_path / "mine" / "thesis.tex").read_text() == "keep me"
