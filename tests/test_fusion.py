"""Fusion (``colmap_pvs.fusion``), the PLY / ``.vis`` writers and COLMAP-option validation.

Most tests use the exact analytic workspace of ``tests/scenes.py`` (5 views of 160x120, maps in
COLMAP's integer-centre convention), so a correct fusion puts every point on the true surface.
"""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from colmap_pvs.errors import ConfigError, WorkspaceError
from colmap_pvs.fusion import FuseConfig, fuse, parse_colmap_options
from colmap_pvs.io import read_depth_map, read_sparse_model, write_depth_map, write_normal_map
from colmap_pvs.io.maps import fusion_intrinsics, read_array, write_array
from colmap_pvs.io.ply import (
    read_mesh,
    read_point_cloud,
    read_visibility,
    write_point_cloud,
    write_visibility,
)
from colmap_pvs.io.sparse import image_indices
from colmap_pvs.stereo.config import FORMAT_VERSIONS


@pytest.fixture()
def workspace(analytic_scene, tmp_path) -> Path:
    """A private copy of the session's analytic workspace (safe to modify)."""
    root = tmp_path / "ws"
    shutil.copytree(analytic_scene["root"], root)
    return root


def _surface_distance(gt, xyz: np.ndarray) -> np.ndarray:
    return gt["scene"].distance(np.asarray(xyz, dtype=np.float64))


# --------------------------------------------------------------------------- PLY / vis


def test_ply_and_vis_roundtrip_and_layout(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(7, 3)).astype(np.float32)
    nrm = rng.normal(size=(7, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (7, 3)).astype(np.uint8)
    path = write_point_cloud(tmp_path / "c.ply", xyz, nrm, rgb)
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    assert "format binary_little_endian 1.0" in header
    props = [ln.split()[-1] for ln in header.splitlines() if ln.startswith("property")]
    assert props == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"]
    cloud = read_point_cloud(path)
    np.testing.assert_array_equal(cloud.xyz, xyz)
    np.testing.assert_array_equal(cloud.normals, nrm)
    np.testing.assert_array_equal(cloud.colors, rgb)

    offsets = np.array([0, 2, 2, 5])
    idx = np.array([3, 1, 0, 4, 2])
    vis = write_visibility(tmp_path / "c.ply.vis", offsets, idx)
    # COLMAP's WritePointsVisibility: uint64 count, then per point uint32 n + n uint32 indices.
    expected = struct.pack("<Q", 3) + struct.pack("<7I", 2, 3, 1, 0, 3, 0, 4) + struct.pack("<I", 2)
    assert vis.read_bytes() == expected
    got_off, got_idx = read_visibility(vis)
    np.testing.assert_array_equal(got_off, offsets)
    np.testing.assert_array_equal(got_idx, idx)


def test_ply_read_by_open3d(tmp_path):
    o3d = pytest.importorskip("open3d")
    xyz = np.array([[0, 0, 1], [1, 2, 3], [-1, 0.5, 2]], dtype=np.float32)
    nrm = np.array([[0, 0, 1], [0, 1, 0], [1, 0, 0]], dtype=np.float32)
    rgb = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], dtype=np.uint8)
    path = write_point_cloud(tmp_path / "c.ply", xyz, nrm, rgb)
    pcd = o3d.io.read_point_cloud(str(path))
    np.testing.assert_allclose(np.asarray(pcd.points), xyz)
    np.testing.assert_allclose(np.asarray(pcd.normals), nrm)
    np.testing.assert_allclose(np.asarray(pcd.colors), rgb / 255.0)


# --------------------------------------------------------------------------- pvs fusion, exact maps


def test_exact_maps_fuse_onto_the_true_surface(workspace, analytic_scene):
    gt = analytic_scene
    result = fuse(FuseConfig(workspace_path=workspace))
    assert result.output_path == workspace / "fused.ply"
    assert result.num_images == 5 and result.num_points > 5000
    cloud = read_point_cloud(result.output_path)
    assert len(cloud) == result.num_points
    dist = _surface_distance(gt, cloud.xyz)
    size = gt["scene"].size
    assert np.median(dist) < 1e-5 * size
    assert np.percentile(dist, 99) < 1e-4 * size
    # Normals agree with the true surface normals, colours are not black.
    true_n = gt["scene"].nearest_normal(cloud.xyz.astype(np.float64))
    assert np.median(np.sum(cloud.normals * true_n, axis=1)) > 0.999
    assert cloud.colors.astype(int).sum(axis=1).mean() > 100
    # Visibility: the reference plus at least min_consistent_views sources, valid indices.
    offsets, idx = read_visibility(result.vis_path)
    assert len(offsets) - 1 == result.num_points
    assert np.diff(offsets).min() >= 1 + 2
    assert idx.min() >= 0 and idx.max() < 5


def test_deduplicate_reduces_points_not_accuracy(workspace, analytic_scene):
    dedup = fuse(FuseConfig(workspace_path=workspace, output_path=workspace / "a.ply"))
    full = fuse(FuseConfig(workspace_path=workspace, output_path=workspace / "b.ply", deduplicate=False))
    assert full.num_points > 2 * dedup.num_points
    dist = _surface_distance(analytic_scene, read_point_cloud(full.output_path).xyz)
    assert np.median(dist) < 1e-5 * analytic_scene["scene"].size


def test_cache_of_one_view_gives_the_same_cloud(workspace):
    a = fuse(FuseConfig(workspace_path=workspace, output_path=workspace / "a.ply"))
    b = fuse(FuseConfig(workspace_path=workspace, output_path=workspace / "b.ply", cache_size=1))
    np.testing.assert_array_equal(read_point_cloud(a.output_path).xyz, read_point_cloud(b.output_path).xyz)


def test_corrupted_region_is_rejected(workspace, analytic_scene):
    """+30 % depth in a block of one view: consistency rejects it; without the check it shows up."""
    gt = analytic_scene
    name = gt["names"][2]
    path = workspace / "stereo" / "depth_maps" / f"{name}.geometric.bin"
    depth = read_depth_map(path).copy()
    depth[30:90, 40:120] *= 1.3
    write_depth_map(path, depth)
    size = gt["scene"].size

    checked = fuse(FuseConfig(workspace_path=workspace, output_path=workspace / "checked.ply"))
    dist = _surface_distance(gt, read_point_cloud(checked.output_path).xyz)
    assert (dist > 0.01 * size).sum() == 0

    unchecked = fuse(
        FuseConfig(workspace_path=workspace, output_path=workspace / "unchecked.ply", min_consistent_views=0)
    )
    dist = _surface_distance(gt, read_point_cloud(unchecked.output_path).xyz)
    assert (dist > 0.01 * size).sum() > 1000  # the corrupted block (60 x 80 px) is there without the check
    # The corrupted view contributes far fewer points as a reference than the clean ones.
    counts = checked.points_per_image
    assert counts[name] < 0.5 * np.median([counts[n] for n in gt["names"] if n != name])


def test_maps_smaller_than_images_use_scaled_intrinsics(workspace, analytic_scene):
    """Maps at half resolution (inference at --max_image_size) still fuse onto the surface."""
    from scenes import render_view

    gt = analytic_scene
    model = gt["model"]
    for image in model.images.values():
        cam = model.camera_of(image)
        K_half = fusion_intrinsics(cam.K, (cam.width, cam.height), (80, 60))
        maps = render_view(gt["scene"], K_half, image.cam_from_world, 80, 60)
        write_depth_map(workspace / "stereo" / "depth_maps" / f"{image.name}.geometric.bin", maps["depth"])
        write_normal_map(
            workspace / "stereo" / "normal_maps" / f"{image.name}.geometric.bin", maps["normals"]
        )
    result = fuse(FuseConfig(workspace_path=workspace))
    assert result.num_points > 1000
    dist = _surface_distance(gt, read_point_cloud(result.output_path).xyz)
    assert np.median(dist) < 1e-5 * gt["scene"].size


def test_view_selection_when_no_patch_match_cfg(workspace, analytic_scene):
    (workspace / "stereo" / "patch-match.cfg").unlink()
    result = fuse(FuseConfig(workspace_path=workspace, num_sources=2))
    assert result.num_points > 1000
    offsets, _ = read_visibility(result.vis_path)
    assert np.diff(offsets).max() <= 3  # reference + at most 2 sources


def test_references_whose_sources_are_not_fused_are_checked_against_the_other_fused_views(
        workspace, analytic_scene):
    """Every 3rd frame of a video a reference, its nearest frames its sources: the sources have no
    maps to check against, so the fused references next by view score are checked instead (as COLMAP's
    fusion checks every fused image that sees the point). Here each reference's only source is a view
    without maps: before, no reference had 2 views to confirm its points, and the cloud was empty."""
    from colmap_pvs.io.workspace import write_fusion_cfg, write_patch_match_cfg

    names = analytic_scene["names"]
    refs, others = names[:3], names[3:]
    write_patch_match_cfg(workspace / "stereo" / "patch-match.cfg", {r: [others[0]] for r in refs})
    write_fusion_cfg(workspace / "stereo" / "fusion.cfg", refs)
    result = fuse(FuseConfig(workspace_path=workspace))
    assert result.num_images == 3 and result.num_points > 1000
    assert all(result.points_per_image[r] > 0 for r in refs)
    dist = _surface_distance(analytic_scene, read_point_cloud(result.output_path).xyz)
    assert np.median(dist) < 1e-5 * analytic_scene["scene"].size
    _, idx = read_visibility(result.vis_path)
    index = image_indices(workspace / "sparse", read_sparse_model(workspace / "sparse"))
    fused_ids = {index[r] for r in refs}
    assert set(np.unique(idx)) <= fused_ids  # only fused views confirm points


def test_colmaps_fused_cloud_under_the_default_name_is_kept_beside_ours(workspace, caplog):
    """``dense/fused.ply`` is also where the README's COLMAP chain writes ``stereo_fusion``'s cloud: a
    cloud colmap-pvs did not write is moved to ``fused.ply.bak`` (and its ``.vis``) with a warning; our
    own cloud is replaced silently on a rerun."""
    (workspace / "fused.ply").write_bytes(b"COLMAP's cloud")
    (workspace / "fused.ply.vis").write_bytes(b"COLMAP's vis")
    with caplog.at_level("WARNING", logger="colmap_pvs"):
        result = fuse(FuseConfig(workspace_path=workspace))
    assert result.num_points > 1000
    assert (workspace / "fused.ply.bak").read_bytes() == b"COLMAP's cloud"
    assert (workspace / "fused.ply.vis.bak").read_bytes() == b"COLMAP's vis"
    assert any("fused.ply.bak" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level("WARNING", logger="colmap_pvs"):
        fuse(FuseConfig(workspace_path=workspace, method="colmap"))
    assert not list(workspace.glob("fused.ply.bak.*")) and not caplog.records


def test_confidence_maps_filter_pixels(workspace, analytic_scene):
    for name in analytic_scene["names"]:
        h, w = read_depth_map(workspace / "stereo" / "depth_maps" / f"{name}.geometric.bin").shape
        write_array(
            workspace / "stereo" / "confidence_maps" / f"{name}.bin", np.full((h, w), 0.2, np.float32)
        )
    assert fuse(FuseConfig(workspace_path=workspace)).num_points > 1000  # min_confidence 0: ignored
    with pytest.raises(WorkspaceError, match="fusion made no points"):  # an empty cloud is an error
        fuse(FuseConfig(workspace_path=workspace, min_confidence=0.5))


def _supported_everywhere(workspace: Path, names: list[str]) -> None:
    """A filled confidence of 0.6 for every pixel of each image's filled depth map."""
    for name in names:
        h, w = read_depth_map(workspace / "stereo" / "depth_maps" / f"{name}.filled.bin").shape
        write_array(workspace / "stereo" / "confidence_maps" / f"{name}.filled.bin",
                    np.full((h, w), 0.6, np.float32))


def test_completed_maps_fuse_without_normal_maps_onto_the_true_surface(workspace, analytic_scene):
    """``input_type filled``: the dense completion's depth (no normal map) with normals fitted to it
    fuses like the geometric maps; COLMAP's fusion cannot read it."""
    gt = analytic_scene
    maps = workspace / "stereo" / "depth_maps"
    for name in gt["names"]:
        (maps / f"{name}.geometric.bin").rename(maps / f"{name}.filled.bin")
    with pytest.raises(WorkspaceError, match="no geometric depth"):
        fuse(FuseConfig(workspace_path=workspace))
    # a completion needs its confidence (0 marks the unsupported pixels): without it, no image
    with pytest.raises(WorkspaceError, match="no points: the filled maps .* of all 5 listed image"):
        fuse(FuseConfig(workspace_path=workspace, input_type="filled"))
    _supported_everywhere(workspace, gt["names"])
    result = fuse(FuseConfig(workspace_path=workspace, input_type="filled"))
    assert result.num_images == 5 and result.num_points > 5000
    cloud = read_point_cloud(result.output_path)
    assert np.median(_surface_distance(gt, cloud.xyz)) < 1e-5 * gt["scene"].size
    true_n = gt["scene"].nearest_normal(cloud.xyz.astype(np.float64))
    assert np.median(np.sum(cloud.normals * true_n, axis=1)) > 0.99  # fitted, not read
    with pytest.raises(ConfigError, match="input_type 'filled' needs method 'pvs'"):
        FuseConfig(workspace_path=workspace, input_type="filled", method="colmap")
    # a legacy per-image confidence (NAME.bin, the geometric maps' of old runs) never filters them
    for name in gt["names"]:
        h, w = read_depth_map(maps / f"{name}.filled.bin").shape
        write_array(workspace / "stereo" / "confidence_maps" / f"{name}.bin", np.zeros((h, w), np.float32))
    kept = fuse(FuseConfig(workspace_path=workspace, input_type="filled", min_confidence=0.5))
    assert kept.num_points == result.num_points


def test_fuse_defaults_to_the_completion_and_never_fuses_its_unsupported_pixels(workspace, analytic_scene):
    """``input_type auto``: the completion where every image with geometric maps has one, never its
    pixels of confidence 0 (nothing supported them: the network's depth); the geometric maps when an
    image lacks one; always the geometric maps for COLMAP's fusion."""
    names = analytic_scene["names"]
    maps = workspace / "stereo" / "depth_maps"
    for name in names:
        shutil.copy(maps / f"{name}.geometric.bin", maps / f"{name}.filled.bin")
    _supported_everywhere(workspace, names)
    provenance = workspace / "stereo" / "provenance"
    provenance.mkdir(exist_ok=True)
    for version in (FORMAT_VERSIONS["filled"] - 1, FORMAT_VERSIONS["filled"]):
        for name in names:  # the completion's format version: older ones hold no unsupported pixels
            record = {"settings": {"format_version": version}}
            (provenance / f"{name}.filled.json").write_text(json.dumps(record))
        if version < FORMAT_VERSIONS["filled"]:
            assert fuse(FuseConfig(workspace_path=workspace)).num_points == fuse(
                FuseConfig(workspace_path=workspace, input_type="geometric")).num_points
    assert FuseConfig(workspace_path=workspace).input_type == "auto"
    assert FuseConfig(workspace_path=workspace, method="colmap").input_type == "geometric"
    filled = fuse(FuseConfig(workspace_path=workspace, input_type="filled"))
    auto = fuse(FuseConfig(workspace_path=workspace))
    saved = json.loads(auto.output_path.with_name(auto.output_path.stem + ".fuse_config.json").read_text())
    assert auto.num_points == filled.num_points and saved["config"]["input_type"] == "filled"
    for name in names:  # the left half unsupported
        h, w = read_depth_map(maps / f"{name}.filled.bin").shape
        conf = np.full((h, w), 0.6, np.float32)
        conf[:, : w // 2] = 0.0
        write_array(workspace / "stereo" / "confidence_maps" / f"{name}.filled.bin", conf)
    half = fuse(FuseConfig(workspace_path=workspace))
    assert 0.2 * filled.num_points < half.num_points < 0.8 * filled.num_points
    cloud = read_point_cloud(half.output_path)
    assert len(cloud.xyz) == half.num_points
    (maps / f"{names[0]}.filled.bin").unlink()
    geometric = fuse(FuseConfig(workspace_path=workspace, input_type="geometric"))
    fallback = fuse(FuseConfig(workspace_path=workspace))
    assert fallback.num_points == geometric.num_points and names[0] not in fallback.skipped


def test_fuse_leaves_out_completed_pixels_more_likely_wrong_than_right(workspace, analytic_scene, tmp_path):
    """A calibrated completion's pixels below ``FILLED_MIN_PROBABILITY`` are not fused; an uncalibrated
    completion's scores are no probabilities, so only its unsupported pixels (0) are left out."""
    from colmap_pvs.fusion.pvs import FILLED_MIN_PROBABILITY

    assert FILLED_MIN_PROBABILITY == 0.5  # docs/CONVENTIONS.md
    names = analytic_scene["names"]
    maps, provenance = workspace / "stereo" / "depth_maps", workspace / "stereo" / "provenance"
    provenance.mkdir(exist_ok=True)
    for name in names:
        shutil.copy(maps / f"{name}.geometric.bin", maps / f"{name}.filled.bin")
        h, w = read_depth_map(maps / f"{name}.filled.bin").shape
        conf = np.full((h, w), 0.6, np.float32)
        conf[:, : w // 2] = np.nextafter(np.float32(FILLED_MIN_PROBABILITY), np.float32(0))
        write_array(workspace / "stereo" / "confidence_maps" / f"{name}.filled.bin", conf)

    def fused(calibration: dict | None) -> int:
        for name in names:
            settings = {"format_version": FORMAT_VERSIONS["filled"], "confidence_calibration": calibration}
            (provenance / f"{name}.filled.json").write_text(json.dumps({"settings": settings}))
        out = tmp_path / f"{calibration is not None}.ply"
        return fuse(FuseConfig(workspace_path=workspace, output_path=out)).num_points

    raw, calibrated = fused(None), fused({"tolerance": 0.05})
    assert 0.2 * raw < calibrated < 0.8 * raw  # the left half, below the floor, is left out
    for name in names:  # at the floor itself: kept
        conf = read_array(workspace / "stereo" / "confidence_maps" / f"{name}.filled.bin").copy()
        conf[conf < FILLED_MIN_PROBABILITY] = FILLED_MIN_PROBABILITY
        write_array(workspace / "stereo" / "confidence_maps" / f"{name}.filled.bin", conf)
    assert fused({"tolerance": 0.05}) == raw
    with pytest.raises(WorkspaceError, match="made no points"):  # a min_confidence above it applies as before
        fuse(FuseConfig(workspace_path=workspace, output_path=tmp_path / "above.ply", min_confidence=0.7))


def test_fusing_the_completion_counts_the_geometric_check_as_one_agreeing_view(workspace, analytic_scene):
    """A completed pixel that holds the geometric map's depth needs ``min_consistent_views - 1`` agreeing
    sources, any other needs them all; a checked pixel no source agrees with is still dropped."""
    gt = analytic_scene
    names, maps = gt["names"], workspace / "stereo" / "depth_maps"
    for name in names:
        shutil.copy(maps / f"{name}.geometric.bin", maps / f"{name}.filled.bin")
    _supported_everywhere(workspace, names)
    # 5 agreeing views: more than the 4 sources, so only the geometric maps' pixels can pass (with 4)
    strict = FuseConfig(workspace_path=workspace, input_type="filled", min_consistent_views=5)
    checked = fuse(strict)
    assert checked.num_points > 2000
    left = maps / f"{names[1]}.geometric.bin"
    geometric = read_depth_map(left).copy()
    h, w = geometric.shape
    geometric[:, : w // 2] = 0.0  # the left half only completed
    write_depth_map(left, geometric)
    fewer = fuse(strict)
    assert 0.2 < fewer.points_per_image[names[1]] / checked.points_per_image[names[1]] < 0.9
    for name in names:
        (maps / f"{name}.geometric.bin").unlink()
    with pytest.raises(WorkspaceError, match="fusion made no points"):
        fuse(strict)
    # a wrong block: no source agrees with it
    for name in names:
        shutil.copy(maps / f"{name}.filled.bin", maps / f"{name}.geometric.bin")
    wrong = read_depth_map(maps / f"{names[2]}.filled.bin").copy()
    wrong[30:90, 40:120] *= 1.3
    write_depth_map(maps / f"{names[2]}.filled.bin", wrong)

    def off_surface(**kwargs) -> int:
        result = fuse(FuseConfig(workspace_path=workspace, input_type="filled", **kwargs))
        distance = _surface_distance(gt, read_point_cloud(result.output_path).xyz)
        return int((distance > 0.01 * gt["scene"].size).sum())

    # only in the completion: the geometric map checked another depth there, so no credit
    assert off_surface(min_consistent_views=1) < 10  # of the 60 x 80 block: at most a chance rim point
    # in the geometric map too (the check kept it): one agreeing view still rejects it, none does not
    write_depth_map(maps / f"{names[2]}.geometric.bin", wrong)
    assert off_surface() < 10
    assert off_surface(min_consistent_views=1) > 1000
    # a damaged geometric map costs its image the credit, not its place in the cloud
    (maps / f"{names[0]}.geometric.bin").write_bytes(b"not a map")
    damaged = fuse(FuseConfig(workspace_path=workspace, input_type="filled"))
    assert names[0] not in damaged.skipped and damaged.points_per_image[names[0]] > 0

def test_missing_maps(workspace, analytic_scene):
    name = analytic_scene["names"][0]
    (workspace / "stereo" / "depth_maps" / f"{name}.geometric.bin").unlink()
    result = fuse(FuseConfig(workspace_path=workspace))
    assert name in result.skipped and result.num_images == 4
    shutil.rmtree(workspace / "stereo" / "depth_maps")
    with pytest.raises(WorkspaceError, match="no geometric depth"):
        fuse(FuseConfig(workspace_path=workspace))


def test_missing_maps_are_one_warning(workspace, analytic_scene, caplog):
    """Issue 41 item 7: images listed without maps give one WARNING naming them, not one each."""
    names = analytic_scene["names"][:2]
    for name in names:
        (workspace / "stereo" / "depth_maps" / f"{name}.geometric.bin").unlink()
    with caplog.at_level("WARNING", logger="colmap_pvs.fusion"):
        result = fuse(FuseConfig(workspace_path=workspace))
    assert sorted(result.skipped) == sorted(names)
    assert len(caplog.records) == 1
    message = caplog.records[0].getMessage()
    assert "skipping 2 of 5 listed image(s)" in message and all(repr(n) in message for n in names)


# --------------------------------------------------------------------------- COLMAP method / options


def test_colmap_option_validation():
    assert parse_colmap_options(("min_num_pixels=4", "max_reproj_error=1.5", "use_cache=true")) == {
        "min_num_pixels": 4,
        "max_reproj_error": 1.5,
        "use_cache": True,
    }
    box = parse_colmap_options(("bounding_box=-1,-2,-3,1,2,3",))["bounding_box"]
    np.testing.assert_array_equal(box[0], [-1, -2, -3])
    with pytest.raises(ConfigError, match="'max_reproj_eror'"):
        FuseConfig(workspace_path=Path("w"), method="colmap", colmap_options=("max_reproj_eror=2",))
    with pytest.raises(ConfigError, match="min_num_pixels"):
        FuseConfig(workspace_path=Path("w"), method="colmap", colmap_options=("min_num_pixels=many",))
    with pytest.raises(ConfigError, match="key=value"):
        parse_colmap_options(("min_num_pixels",))
    with pytest.raises(ConfigError, match="bounding_box"):
        parse_colmap_options(("bounding_box=1,2,3",))
    with pytest.raises(ConfigError, match="rejects"):
        parse_colmap_options(("min_num_pixels=-1",))
    with pytest.raises(ConfigError, match="summary"):  # methods are not options
        parse_colmap_options(("summary=1",))


def test_colmap_method_and_options(workspace, analytic_scene):
    gt = analytic_scene
    loose = fuse(FuseConfig(workspace_path=workspace, method="colmap", output_path=workspace / "c3.ply"))
    strict = fuse(
        FuseConfig(
            workspace_path=workspace,
            method="colmap",
            output_path=workspace / "c5.ply",
            colmap_options=("min_num_pixels=5",),
        )
    )
    assert 0 < strict.num_points < loose.num_points
    assert loose.vis_path.is_file()
    dist = _surface_distance(gt, read_point_cloud(loose.output_path).xyz)
    assert np.median(dist) < 1e-5 * gt["scene"].size


def test_vis_indices_follow_colmaps_image_numbering(workspace, analytic_scene):
    """Our ``.vis`` and COLMAP's use the same image numbering (checked by projecting the points).

    The sparse model is rewritten with image ids in reverse name order so that id order, name order
    and the fusion.cfg order all differ.
    """
    from colmap_pvs.io import write_sparse_model
    from colmap_pvs.types import Image, SparseModel

    model = analytic_scene["model"]
    n = len(model.images)
    remap = {iid: n + 1 - iid for iid in model.images}
    images = {
        remap[i]: Image(remap[i], im.name, im.camera_id, im.cam_from_world, im.point3D_ids)
        for i, im in model.images.items()
    }
    points = model.points
    from dataclasses import replace

    points = replace(points, track_image_ids=np.array([remap[int(i)] for i in points.track_image_ids]))
    new = SparseModel(model.cameras, images, points, {im.name: iid for iid, im in images.items()})
    shutil.rmtree(workspace / "sparse")
    write_sparse_model(new, workspace / "sparse")
    reread = read_sparse_model(workspace / "sparse")
    index = image_indices(workspace / "sparse", reread)
    by_index = {k: reread.image_by_name(name) for name, k in index.items()}

    def check(result, min_fraction):
        xyz = read_point_cloud(result.output_path).xyz.astype(np.float64)
        offsets, idx = read_visibility(result.vis_path)
        sampled = range(0, len(xyz), max(1, len(xyz) // 300))
        assert len(xyz) > 100 and len(offsets) == len(xyz) + 1
        assert all(offsets[p + 1] > offsets[p] for p in sampled), "a fused point is seen by no image"
        good = total = 0
        for p in sampled:
            for k in idx[offsets[p] : offsets[p + 1]]:
                image = by_index[int(k)]
                cam = reread.camera_of(image)
                x = image.R @ xyz[p] + image.t
                depth = read_depth_map(workspace / "stereo" / "depth_maps" / f"{image.name}.geometric.bin")
                K = fusion_intrinsics(cam.K, (cam.width, cam.height))
                u, v = (K @ x)[:2] / x[2]
                total += 1
                if 0 <= u < cam.width and 0 <= v < cam.height:
                    d = depth[int(v), int(u)]
                    good += abs(d - x[2]) < 0.02 * x[2]
        assert good >= min_fraction * total

    check(fuse(FuseConfig(workspace_path=workspace, output_path=workspace / "ours.ply")), 0.95)
    check(
        fuse(FuseConfig(workspace_path=workspace, method="colmap", output_path=workspace / "colmap.ply")), 0.9
    )


@pytest.mark.colmap_binary
def test_colmap_poisson_mesher_reads_our_cloud(workspace):
    colmap = shutil.which("colmap")
    if colmap is None:
        pytest.skip("Debian's `colmap` executable is not installed")
    result = fuse(FuseConfig(workspace_path=workspace))
    out = workspace / "mesh.ply"
    proc = subprocess.run(
        [
            colmap,
            "poisson_mesher",
            "--input_path",
            str(result.output_path),
            "--output_path",
            str(out),
            "--PoissonMeshing.depth",
            "6",
            "--PoissonMeshing.trim",
            "3",
            "--PoissonMeshing.num_threads",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    vertices, faces = read_mesh(out)
    assert len(vertices) > 100 and len(faces) > 100


# --------------------------------------------------------------------------- bounded memory


def _spy_fuse(tmp_path: Path, monkeypatch, fail_at: int | None = None):
    """Fuse a 10-view analytic workspace (cache of 2 views, 2 sources) and record, before each reference
    is checked, the views alive, the PLY body bytes streamed to disk so far and the used-pixel masks."""
    import gc
    import weakref

    from scenes import make_analytic_workspace

    import colmap_pvs.fusion.pvs as pvs

    gt = make_analytic_workspace(tmp_path / "ws", n_views=10, width=80, height=60, focal=75.0)
    out = tmp_path / "out" / "fused.ply"
    live: list[weakref.ref] = []
    used: list = []
    seen: list[tuple[int, int, int]] = []
    load, check, init = pvs._load_view, pvs._fuse_reference, pvs._UsedPixels.__init__

    def counted_load(*args):
        view = load(*args)
        live.append(weakref.ref(view))
        return view

    def spied_check(config, ref, valid, srcs, *pool):
        if fail_at is not None and len(seen) == fail_at:
            raise KeyboardInterrupt
        gc.collect()
        streamed = sum(p.stat().st_size for p in out.parent.glob(f".{out.name}.pvs-*.tmp"))
        seen.append((sum(r() is not None for r in live), streamed, len(used[0]._masks)))
        return check(config, ref, valid, srcs, *pool)

    def spied_init(self):
        init(self)
        used.append(self)

    monkeypatch.setattr(pvs, "_load_view", counted_load)
    monkeypatch.setattr(pvs, "_fuse_reference", spied_check)
    monkeypatch.setattr(pvs._UsedPixels, "__init__", spied_init)
    config = FuseConfig(workspace_path=gt["root"], output_path=out, input_type="geometric", cache_size=2,
                        num_sources=2, min_consistent_views=1)
    return config, out, seen, used


def test_fuse_streams_the_points_to_disk_and_holds_a_bounded_number_of_views_and_masks(tmp_path, monkeypatch):
    config, out, seen, used = _spy_fuse(tmp_path, monkeypatch)
    result = fuse(config)
    names = list(result.points_per_image)
    assert len(names) == 10 and result.num_points > 1000
    before = np.cumsum([0] + [result.points_per_image[n] for n in names[:-1]])
    record = 27  # bytes per point: float x y z nx ny nz, uchar r g b
    # Each reference's points are on disk before the next one is checked: the cloud is never held.
    assert [s for _, s, _ in seen] == [record * int(b) for b in before]
    # Views alive: the LRU (2), the reference and its 2 sources, the next reference's 3 being prefetched.
    assert max(v for v, _, _ in seen) <= config.cache_size + 2 * (1 + config.num_sources)
    # A view's used-pixel mask is dropped once it was the reference: none is left at the end.
    assert len(used[0]._masks) == 0 and max(m for _, _, m in seen) <= config.num_sources * 2
    header = out.read_bytes()[:300]
    assert out.stat().st_size == header.index(b"end_header\n") + 11 + record * result.num_points
    assert not list(out.parent.glob("*.tmp"))


def test_fuse_interrupted_leaves_no_temporary_and_no_cloud(tmp_path, monkeypatch):
    config, out, seen, _ = _spy_fuse(tmp_path, monkeypatch, fail_at=4)
    with pytest.raises(KeyboardInterrupt):
        fuse(config)
    assert seen[-1][1] > 0  # points had been streamed
    assert sorted(p.name for p in out.parent.iterdir()) == []


def test_fuse_checks_a_references_sources_in_two_threads_with_the_same_bits(tmp_path, monkeypatch):
    import threading
    import time

    from scenes import make_analytic_workspace

    import colmap_pvs.fusion.pvs as pvs

    gt = make_analytic_workspace(tmp_path / "ws", n_views=6, width=80, height=60, focal=75.0)
    match, lock = pvs.match_points, threading.Lock()
    running, most = [0], [0]

    def slow_match(*args, **kwargs):  # how many checks run at once
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        time.sleep(0.01)
        try:
            return match(*args, **kwargs)
        finally:
            with lock:
                running[0] -= 1

    monkeypatch.setattr(pvs, "match_points", slow_match)
    clouds = []
    for threads in (1, 2):
        monkeypatch.setattr(pvs, "MATCH_THREADS", threads, raising=False)
        most[0] = 0
        out = tmp_path / f"fused-{threads}.ply"
        fuse(FuseConfig(workspace_path=gt["root"], output_path=out, input_type="geometric", num_sources=3))
        assert most[0] == threads
        clouds.append((out.read_bytes(), Path(str(out) + ".vis").read_bytes()))
    assert len(clouds[0][0]) > 10_000 and clouds[0] == clouds[1]
