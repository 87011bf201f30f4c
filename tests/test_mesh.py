"""Meshing (``colmap_pvs.mesh``): screened Poisson of a sphere cloud, trimming, COLMAP's mesher."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from colmap_pvs.errors import ConfigError, MapFormatError
from colmap_pvs.io.ply import read_mesh, write_point_cloud
from colmap_pvs.mesh import MeshConfig, mesh

CENTER = np.array([1.0, -2.0, 0.5])
RADIUS = 2.0


def _sphere_cloud(path: Path, n: int = 6000, normals: bool = True, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    colors = np.full((n, 3), 180, np.uint8)
    return write_point_cloud(path, CENTER + RADIUS * d, d if normals else None, colors)


def _boundary_edges(faces: np.ndarray) -> int:
    """Edges not shared by exactly two faces (0 for a closed 2-manifold)."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int((counts != 2).sum())


def test_sphere_mesh_is_closed_and_on_the_sphere(tmp_path):
    cloud = _sphere_cloud(tmp_path / "sphere.ply")
    out = mesh(
        MeshConfig(
            input_path=cloud, output_path=tmp_path / "m.ply", depth=6, density_quantile=0.0, num_threads=1
        )
    )
    vertices, faces = read_mesh(out)
    assert len(faces) > 1000
    assert _boundary_edges(faces) == 0  # watertight (no trimming)
    r = np.linalg.norm(vertices - CENTER, axis=1)
    assert np.abs(r - RADIUS).max() < 0.03 * RADIUS
    assert np.abs(r - RADIUS).mean() < 0.005 * RADIUS


def test_default_output_name_and_trimming(tmp_path):
    o3d = pytest.importorskip("open3d")
    cloud = _sphere_cloud(tmp_path / "fused.ply")
    full = mesh(
        MeshConfig(
            input_path=cloud, output_path=tmp_path / "full.ply", depth=6, density_quantile=0.0, num_threads=1
        )
    )
    trimmed = mesh(MeshConfig(input_path=cloud, depth=6, density_quantile=0.2, num_threads=1))
    assert trimmed == tmp_path / "meshed-poisson.ply"
    v_full, _ = read_mesh(full)
    v_trim, f_trim = read_mesh(trimmed)
    assert 0.6 * len(v_full) < len(v_trim) < 0.95 * len(v_full)
    assert np.abs(np.linalg.norm(v_trim - CENTER, axis=1) - RADIUS).max() < 0.03 * RADIUS
    m = o3d.io.read_triangle_mesh(str(trimmed))  # open3d reads our PLY (with colours)
    assert len(m.triangles) == len(f_trim) and m.has_vertex_colors()


def test_half_sphere_is_cropped_to_the_cloud(tmp_path):
    """Poisson closes an open surface; density trimming + bbox crop remove most of that bulge."""
    rng = np.random.default_rng(1)
    d = rng.normal(size=(6000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[d[:, 2] > 0]
    cloud = write_point_cloud(tmp_path / "half.ply", RADIUS * d, d)
    v, _ = read_mesh(mesh(MeshConfig(input_path=cloud, depth=6, num_threads=1)))
    assert v[:, 2].min() > -0.05 * RADIUS * 2


def test_normals_are_estimated_when_missing(tmp_path):
    cloud = _sphere_cloud(tmp_path / "nonormals.ply", n=3000, normals=False)
    v, f = read_mesh(mesh(MeshConfig(input_path=cloud, depth=5, density_quantile=0.0, num_threads=1)))
    r = np.linalg.norm(v - CENTER, axis=1)
    assert len(f) > 500 and np.abs(r - RADIUS).mean() < 0.02 * RADIUS


def test_colmap_mesher(tmp_path):
    cloud = _sphere_cloud(tmp_path / "sphere.ply", n=3000)
    out = mesh(
        MeshConfig(input_path=cloud, output_path=tmp_path / "c.ply", method="colmap", depth=5, num_threads=1)
    )
    v, f = read_mesh(out)
    assert len(f) > 100
    assert np.abs(np.linalg.norm(v - CENTER, axis=1) - RADIUS).max() < 0.05 * RADIUS


def test_bad_input_and_config(tmp_path):
    with pytest.raises(MapFormatError, match="does not exist"):
        mesh(MeshConfig(input_path=tmp_path / "missing.ply"))
    with pytest.raises(ConfigError, match="density_quantile"):
        MeshConfig(input_path=Path("x.ply"), density_quantile=1.5)
    with pytest.raises(ConfigError, match="depth"):
        MeshConfig(input_path=Path("x.ply"), depth=0)
    tiny = write_point_cloud(tmp_path / "tiny.ply", np.zeros((2, 3)))
    with pytest.raises(MapFormatError, match="2 points"):
        mesh(MeshConfig(input_path=tiny))


@pytest.mark.parametrize("method", ["open3d", "colmap"])
def test_meshing_logs_each_long_step_before_it_runs(tmp_path, caplog, method):
    """Issue 41 item 7: meshing took ~49 s in silence; each long step now opens with an INFO line."""
    cloud = _sphere_cloud(tmp_path / "sphere.ply", n=2000)
    with caplog.at_level("INFO", logger="colmap_pvs"):
        mesh(MeshConfig(input_path=cloud, output_path=tmp_path / "m.ply", depth=5, num_threads=1,
                        method=method))
    messages = [r.getMessage() for r in caplog.records if r.levelname == "INFO"]
    poisson = next(i for i, m in enumerate(messages)
                   if re.search(r"meshing: .*Poisson reconstruction at depth 5 .*of 2,000 points \.\.\.", m))
    wrote = next(i for i, m in enumerate(messages) if m.startswith("mesh: wrote"))
    assert poisson < wrote
    if method == "open3d":
        trimming = next(i for i, m in enumerate(messages) if m.startswith("meshing: trimming"))
        assert poisson < trimming < wrote


def test_colmaps_mesh_under_the_default_name_is_kept_beside_ours(tmp_path, caplog):
    """``meshed-poisson.ply`` is also the name COLMAP's ``poisson_mesher`` writes in the README's chain:
    a mesh colmap-pvs did not write is moved to ``.bak`` (with a warning) before ours replaces it; our
    own mesh is replaced silently on a rerun."""
    cloud = _sphere_cloud(tmp_path / "fused.ply", n=3000)
    theirs = tmp_path / "meshed-poisson.ply"
    theirs.write_bytes(b"COLMAP's mesh")
    config = MeshConfig(input_path=cloud, depth=5, density_quantile=0.0, num_threads=1)
    with caplog.at_level("WARNING"):
        out = mesh(config)
    assert out == theirs and (tmp_path / "meshed-poisson.ply.bak").read_bytes() == b"COLMAP's mesh"
    assert any("meshed-poisson.ply.bak" in r.getMessage() for r in caplog.records)
    caplog.clear()
    mesh(config)
    assert not (tmp_path / "meshed-poisson.ply.bak.2").exists() and not caplog.records
    theirs.write_bytes(b"another of theirs")
    mesh(config)
    assert (tmp_path / "meshed-poisson.ply.bak.2").read_bytes() == b"another of theirs"
