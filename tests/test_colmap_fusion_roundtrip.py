"""Our depth/normal maps fused by COLMAP itself (pycolmap and Debian's `colmap` binary).

Also pins the pixel convention of COLMAP's fusion: it back-projects map pixel ``(col, row)``
along ``K^-1 [col, row, 1]`` (integer coordinates), not through our pixel centre
``(col + 0.5, row + 0.5)``. Maps rendered for ``fusion_intrinsics(K)`` (principal point +0.5)
fuse onto the true surface to float precision; maps rendered at our pixel centres with ``K``
land half a pixel off.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from scenes import make_analytic_workspace, read_ply_vertices

from colmap_pvs.geometry import backproject_depth
from colmap_pvs.io import load_workspace, read_depth_map, read_normal_map

COLMAP = shutil.which("colmap")
FUSERS = ["pycolmap", pytest.param("colmap-binary", marks=pytest.mark.colmap_binary)]
SINGLE_PIXEL = {"min_num_pixels": 1, "max_num_pixels": 1}  # every fused point = one back-projected pixel


@pytest.fixture(scope="module")
def workspaces(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict]:
    """The analytic scene with maps written in COLMAP's convention and half a pixel shifted."""
    base = tmp_path_factory.mktemp("fusion")
    return {conv: make_analytic_workspace(base / conv, map_convention=conv) for conv in ("colmap", "centre")}


def _fuse(fuser: str, workspace: Path, out: Path, options: dict) -> tuple[np.ndarray, np.ndarray]:
    """Run COLMAP's stereo_fusion; returns fused points ``[N, 3]`` and normals ``[N, 3]`` (float64)."""
    ply = out / f"fused-{fuser}.ply"
    if fuser == "pycolmap":
        opts = pycolmap.StereoFusionOptions()
        opts.num_threads = 2
        for key, value in options.items():
            setattr(opts, key, value)
        pycolmap.stereo_fusion(
            str(ply),
            str(workspace),
            workspace_format="COLMAP",
            input_type="geometric",
            options=opts,
            output_type="PLY",
        )
    else:
        if COLMAP is None:
            pytest.skip("Debian's `colmap` binary is not on PATH (apt install colmap)")
        cmd = [
            COLMAP,
            "stereo_fusion",
            "--workspace_path",
            str(workspace),
            "--workspace_format",
            "COLMAP",
            "--input_type",
            "geometric",
            "--output_path",
            str(ply),
            "--StereoFusion.num_threads",
            "2",
        ]
        for key, value in options.items():
            cmd += [f"--StereoFusion.{key}", str(value)]
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
        assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    vertices = read_ply_vertices(ply)
    xyz = np.stack([vertices[k] for k in ("x", "y", "z")], axis=1).astype(np.float64)
    normals = np.stack([vertices[k] for k in ("nx", "ny", "nz")], axis=1).astype(np.float64)
    return xyz, normals


def test_written_maps_meet_fusion_requirements(workspaces: dict[str, dict]) -> None:
    gt = workspaces["colmap"]
    ws, model = load_workspace(gt["root"])
    for name in gt["names"]:
        image = model.image_by_name(name)
        depth = read_depth_map(ws.depth_map_path(name))
        normals = read_normal_map(ws.normal_map_path(name)).astype(np.float64)
        cam = model.camera_of(image)
        assert depth.shape == (cam.height, cam.width) and normals.shape == (cam.height, cam.width, 3)
        assert (depth > 0).all() and np.isfinite(depth).all()
        np.testing.assert_allclose(np.linalg.norm(normals, axis=2), 1.0, atol=1e-6)  # unit
        points = backproject_depth(depth.astype(np.float64), gt["map_K"][name])
        assert ((points * normals).sum(axis=2) < 0).all()  # facing the camera
        world = (points.reshape(-1, 3) - image.t) @ image.R
        assert np.abs(gt["scene"].distance(world)).max() < 1e-5 * gt["scene"].size  # float32 depth


@pytest.mark.parametrize("fuser", FUSERS)
def test_fused_cloud_lies_on_true_surface(workspaces: dict[str, dict], tmp_path: Path, fuser: str) -> None:
    gt = workspaces["colmap"]
    scene = gt["scene"]
    xyz, normals = _fuse(fuser, gt["root"], tmp_path, {})
    assert len(xyz) > 2000, f"only {len(xyz)} fused points"
    dist = scene.distance(xyz)
    assert np.median(dist) < 1e-5 * scene.size and np.percentile(dist, 95) < 1e-4 * scene.size
    cos = (normals * scene.nearest_normal(xyz)).sum(axis=1)
    assert np.median(cos) > np.cos(np.radians(0.5))
    on_box = np.abs(scene.nearest_normal(xyz)[:, 2]) < 0.5  # box side faces are part of the cloud
    assert on_box.sum() > 100


@pytest.mark.parametrize("fuser", FUSERS)
@pytest.mark.parametrize("options", [SINGLE_PIXEL, {}], ids=["single-pixel", "default"])
def test_fusion_pixel_convention_is_integer_centres(
    workspaces: dict[str, dict], tmp_path: Path, fuser: str, options: dict
) -> None:
    scene = workspaces["colmap"]["scene"]
    errors = {}
    for conv, gt in workspaces.items():
        out = tmp_path / conv
        out.mkdir()
        xyz, _ = _fuse(fuser, gt["root"], out, options)
        errors[conv] = float(np.median(scene.distance(xyz)))
    # half a pixel at depth ~3..8 with f = 150 px on surfaces seen at 30..60 degrees: ~0.005..0.02
    assert errors["colmap"] < 1e-5 * scene.size, errors
    assert errors["centre"] > 1e-3 * scene.size, errors
    assert errors["centre"] > 100 * max(errors["colmap"], 1e-7), errors
