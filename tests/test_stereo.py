"""The ``stereo`` step end to end: COLMAP maps written, resumable, skips, patch-match.cfg, real data."""

from __future__ import annotations

import dataclasses
import json
import shutil
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from scenes import stereo_config

import colmap_pvs.stereo as stereo_module
import colmap_pvs.stereo.config as stereo_config_module
from colmap_pvs.cli.main import main
from colmap_pvs.config import replace_config
from colmap_pvs.errors import CheckpointError, ConfigError
from colmap_pvs.fusion import FuseConfig, fuse
from colmap_pvs.geometry import backproject_depth
from colmap_pvs.io.maps import (
    colorize_depth,
    fusion_intrinsics,
    read_array,
    read_depth_map,
    read_normal_map,
    write_depth_map,
)
from colmap_pvs.io.ply import read_point_cloud
from colmap_pvs.io.sparse import read_sparse_model, write_sparse_model
from colmap_pvs.io.workspace import load_workspace, read_fusion_cfg, write_patch_match_cfg
from colmap_pvs.normals import plane_residual
from colmap_pvs.stereo import context as stereo_context
from colmap_pvs.stereo import filled as stereo_filled
from colmap_pvs.stereo import geometric as stereo_geometric
from colmap_pvs.stereo import network as stereo_network
from colmap_pvs.stereo import outputs as stereo_outputs
from colmap_pvs.stereo import photometric as stereo_photometric
from colmap_pvs.stereo import run_stereo
from colmap_pvs.stereo.config import COMPLETION_RESIDUAL_SCALE, COMPLETION_RESIDUAL_WINDOW
from colmap_pvs.stereo.reference import PassMaps, PassRecord, Reference, preview_path
from colmap_pvs.stereo.timing import Timer
from colmap_pvs.synthetic.workspace import SyntheticWorkspaceConfig, make_synthetic_workspace


@pytest.fixture(scope="module")
def synthetic_ws(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("stereo") / "ws"
    make_synthetic_workspace(root, SyntheticWorkspaceConfig(seed=3, width=96, height=72, num_views=4))
    return root


def _copy(ws: Path, tmp_path: Path) -> Path:
    out = tmp_path / "ws"
    shutil.copytree(ws, out)
    return out


def test_stereo_refuses_to_run_without_weights(synthetic_ws, tmp_path, monkeypatch, capsys):
    ws = _copy(synthetic_ws, tmp_path)
    monkeypatch.setattr(stereo_config_module, "DEFAULT_CHECKPOINT", tmp_path / "none.pt")
    with pytest.raises(CheckpointError, match="--checkpoint"):
        run_stereo(stereo_config(workspace_path=ws))
    assert main(["stereo", "--workspace_path", str(ws)]) == 1
    assert "none.pt" in capsys.readouterr().err
    with pytest.raises(CheckpointError, match="missing.pt"):
        run_stereo(stereo_config(workspace_path=ws, checkpoint=tmp_path / "missing.pt"))
    assert not list((ws / "stereo" / "depth_maps").glob("*.bin"))


def test_stereo_cli_writes_colmap_maps_and_resumes(synthetic_ws, tmp_path, tiny_checkpoint, capsys):
    ws = _copy(synthetic_ws, tmp_path)
    args = ["stereo", "--workspace_path", str(ws), "--checkpoint", str(tiny_checkpoint), "--num_views", "3",
            "--min_confidence", "0", "--previews", "true", "--max_image_size", "64"]
    assert main(args) == 0
    assert "computed: 4" in capsys.readouterr().out
    _, model = load_workspace(ws)
    names = sorted(im.name for im in model.images.values())
    assert read_fusion_cfg(ws / "stereo" / "fusion.cfg") == names
    for name in names:
        im = model.image_by_name(name)
        cam = model.camera_of(im)
        geometric = read_depth_map(ws / "stereo" / "depth_maps" / f"{name}.geometric.bin")
        depth = read_depth_map(ws / "stereo" / "depth_maps" / f"{name}.photometric.bin")
        assert depth.shape == geometric.shape == (48, 64)  # 96x72 -> longest side 64
        # The geometric pass only removes (and averages) pixels; random weights agree nowhere much.
        assert np.all(depth[geometric > 0] > 0) and (geometric > 0).sum() < (depth > 0).sum()
        normals = read_normal_map(ws / "stereo" / "normal_maps" / f"{name}.photometric.bin")
        valid = depth > 0
        assert valid.mean() > 0.5
        np.testing.assert_allclose(np.linalg.norm(normals[valid], axis=-1), 1.0, atol=1e-4)
        assert np.all(normals[~valid] == 0)
        K = fusion_intrinsics(cam.K, (cam.width, cam.height), (64, 48))
        pts = backproject_depth(depth, K)
        assert np.all(np.sum(normals * pts, -1)[valid] < 0)  # camera-facing
        for kind in ("photometric", "geometric"):
            conf = read_array(ws / "stereo" / "confidence_maps" / f"{name}.{kind}.bin")
            assert conf.shape == depth.shape and np.all((conf >= 0) & (conf <= 1))
            assert (ws / "stereo" / "provenance" / f"{name}.{kind}.json").is_file()
        assert (ws / "stereo" / "previews" / f"{name}.depth.png").is_file()
        assert (ws / "stereo" / "previews" / f"{name}.photometric.depth.png").is_file()
        assert len(list((ws / "stereo" / "previews").glob(f"{name}.visibility.*.png"))) == 2
    assert (ws / "stereo" / stereo_module.CONFIG_FILENAME).is_file()
    # A rerun resumes: nothing is recomputed unless --overwrite.
    first = (ws / "stereo" / "depth_maps" / f"{names[0]}.geometric.bin").stat().st_mtime_ns
    cfg = stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3, max_image_size=64,
                       min_confidence=0.0)
    res = run_stereo(cfg)
    assert res.processed == [] and sorted(res.already_done) == names
    assert res.geometric_processed == [] and sorted(res.geometric_done) == names
    res = run_stereo(stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3,
                                  max_image_size=64, overwrite=True))
    assert sorted(res.processed) == names
    assert (ws / "stereo" / "depth_maps" / f"{names[0]}.geometric.bin").stat().st_mtime_ns != first
    assert not list(ws.rglob("*.tmp"))


def test_patch_match_cfg_explicit_sources_are_used(synthetic_ws, tmp_path, tiny_checkpoint):
    ws = _copy(synthetic_ws, tmp_path)
    _, model = load_workspace(ws)
    names = sorted(im.name for im in model.images.values())
    write_patch_match_cfg(ws / "stereo" / "patch-match.cfg", {names[0]: [names[3], names[1]]})
    res = run_stereo(stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, max_image_size=48))
    assert res.processed == [names[0]]
    assert res.sources[names[0]] == [names[3], names[1]]
    (ws / "stereo" / "patch-match.cfg").write_text(f"{names[1]}\n__all__\n{names[2]}\n__auto__, 1\n")
    res = run_stereo(stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, max_image_size=48,
                                  num_views=3))
    assert sorted(res.processed) == [names[1], names[2]]
    assert len(res.sources[names[1]]) == 2  # __all__ capped at num_views - 1
    assert len(res.sources[names[2]]) == 1


def test_geometric_check_slots_skip_unrelated_network_sources(synthetic_ws, tmp_path, tiny_checkpoint):
    """A network source that is not one of the reference's candidate views (no shared sparse points,
    as an unrelated frame in patch-match.cfg) is still checked but takes none of the
    ``geom_num_sources`` slots: the next best view by score is checked too."""
    ws = _copy(synthetic_ws, tmp_path)
    _, model = load_workspace(ws)
    names = sorted(im.name for im in model.images.values())
    ref = names[0]
    sources = {n: [m for m in names if m != n][:2] for n in names}
    write_patch_match_cfg(ws / "stereo" / "patch-match.cfg", sources)
    cfg = stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, max_image_size=48, num_views=3,
                       geom_num_sources=2, geom_fill=False)
    run_stereo(cfg)
    provenance = ws / "stereo" / "provenance"
    network_sources = json.loads((provenance / f"{ref}.photometric.json").read_text())["sources"]
    geo_prov = provenance / f"{ref}.geometric.json"
    assert json.loads(geo_prov.read_text())["sources"] == network_sources  # both related: slots full
    ctx = stereo_module.prepare_stereo(cfg)
    entry = ctx.selection.references[ref]
    unrelated = network_sources[1]
    keep = [i for i, s in enumerate(entry.ranked_names) if s != unrelated]
    ranked = tuple(entry.ranked_names[i] for i in keep)
    ctx.selection.references[ref] = dataclasses.replace(entry, ranked_names=ranked,
                                                        ranked_scores=entry.ranked_scores[keep])
    next_best = next(s for s in ctx.selection.references[ref].ranked_names if s not in network_sources)
    assert stereo_module.process_reference(ctx, ref, "geometric").status == "computed"
    ctx.close()
    assert json.loads(geo_prov.read_text())["sources"] == [*network_sources, next_best]
    # One network source and three slots: the next two best views fill them.
    ctx = stereo_module.prepare_stereo(replace_config(cfg, geom_num_sources=3))
    photo_prov = provenance / f"{ref}.photometric.json"
    record = photo_prov.read_text()
    photo_prov.write_text(json.dumps(dict(json.loads(record), sources=network_sources[:1])))
    extra = [s for s in ctx.selection.references[ref].ranked_names if s != network_sources[0]]
    assert len(extra) == 2 and stereo_geometric._check_setup(ctx, ref).sources == [network_sources[0], *extra]
    photo_prov.write_text(record)
    # Photometric maps without their provenance (COLMAP's), or a provenance without its depth map (a pass
    # cut short): no check.
    paths = ctx.reference(ref).paths["photometric"]
    for moved in (paths.provenance, paths.depth):
        moved.rename(tmp_path / "aside")
        assert stereo_geometric._check_setup(ctx, ref) == "its photometric maps do not exist", moved
        (tmp_path / "aside").rename(moved)
    ctx.close()


def test_image_without_points_is_skipped_not_fatal(synthetic_ws, tmp_path, tiny_checkpoint, caplog):
    ws = _copy(synthetic_ws, tmp_path)
    model = read_sparse_model(ws / "sparse")
    victim = sorted(model.images.values(), key=lambda im: im.name)[1]
    images = dict(model.images)
    images[victim.image_id] = dataclasses.replace(victim, point3D_ids=np.zeros(0, np.int64))
    pts = model.points
    keep = pts.track_image_ids != victim.image_id
    counts = np.add.reduceat(keep.astype(np.int64), pts.track_offsets[:-1]) if len(pts) else []
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    points = dataclasses.replace(pts, track_offsets=offsets, track_image_ids=pts.track_image_ids[keep])
    shutil.rmtree(ws / "sparse")
    write_sparse_model(dataclasses.replace(model, images=images, points=points), ws / "sparse")
    (ws / "stereo" / "patch-match.cfg").unlink()
    with caplog.at_level("WARNING"):
        res = run_stereo(stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, max_image_size=48))
    assert victim.name in res.skipped and victim.name not in res.processed
    assert len(res.processed) == 3
    assert victim.name in caplog.text
    assert not (ws / "stereo" / "depth_maps" / f"{victim.name}.geometric.bin").exists()


def test_statue_runs_end_to_end(statue_workspace, tmp_path, tiny_checkpoint):
    """The real COLMAP workspace (mixed image heights) with a tiny checkpoint: no crash, 23 maps."""
    ws = tmp_path / "statue"
    shutil.copytree(statue_workspace, ws)
    for p in ws.rglob("*"):
        p.chmod(0o755 if p.is_dir() else 0o644)
    ws.chmod(0o755)
    res = run_stereo(stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3,
                                  max_image_size=96, min_confidence=0.0))
    assert len(res.processed) == 23 and not res.skipped
    _, model = load_workspace(ws)
    for im in model.images.values():
        cam = model.camera_of(im)
        depth = read_depth_map(ws / "stereo" / "depth_maps" / f"{im.name}.geometric.bin")
        # Each map keeps its own image's aspect ratio (heights 656..662 differ slightly).
        assert depth.shape[1] == 96
        assert abs(depth.shape[0] - round(cam.height * 96 / cam.width)) <= 1
    # COLMAP's own fusion reads every map (random weights fuse few points; no crash is the check).
    fused = fuse(FuseConfig(workspace_path=ws, output_path=tmp_path / "fused.ply", method="colmap"))
    assert fused.output_path.is_file()


def test_shipped_checkpoint_end_to_end_through_colmap_fusion(tmp_path):
    """The default checkpoint on an unseen synthetic scene: accurate maps that COLMAP's fusion fuses."""
    import open3d as o3d

    from colmap_pvs.evaluate import EvaluateDepthConfig, evaluate_depth

    if not stereo_config_module.DEFAULT_CHECKPOINT.exists():
        pytest.fail(f"the shipped checkpoint {stereo_config_module.DEFAULT_CHECKPOINT} is missing")
    ws = tmp_path / "ws"
    make_synthetic_workspace(ws, SyntheticWorkspaceConfig(seed=11, width=160, height=120, num_views=5))
    res = run_stereo(stereo_config(workspace_path=ws, num_views=4, max_image_size=160, threads=2))
    assert len(res.processed) == 5
    metrics = evaluate_depth(EvaluateDepthConfig(workspace_path=ws, gt=ws / "gt" / "depth_maps",
                                                 gt_pattern="{name}.npy", kind="photometric"))
    assert metrics.pooled.coverage_pct > 80
    assert metrics.pooled.rel_under_pct[0.05] > 70  # measured ~85 % at step 1500 of training
    geo = evaluate_depth(
        EvaluateDepthConfig(workspace_path=ws, gt=ws / "gt" / "depth_maps", gt_pattern="{name}.npy")
    )
    # v2 weights: 34.7 % at 96.3 % within 5 %; the v3 average (stage_neighbourhood 2): 29.1 % at 97.2 %
    assert geo.pooled.coverage_pct > 25
    assert geo.pooled.rel_under_pct[0.05] > 90
    assert geo.pooled.absrel < 0.7 * metrics.pooled.absrel
    fused = fuse(FuseConfig(workspace_path=ws, output_path=tmp_path / "fused.ply", method="colmap"))
    assert fused.num_points > 2000
    mesh = o3d.io.read_triangle_mesh(str(ws / "gt" / "mesh.ply"))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    points = read_point_cloud(tmp_path / "fused.ply").xyz.astype(np.float32)
    dist = scene.compute_distance(o3d.core.Tensor(points)).numpy()
    extent = np.linalg.norm(points.max(0) - points.min(0))
    assert np.median(dist) < 0.01 * extent


def test_sparse_hints_follow_point_ids_in_any_order():
    from colmap_pvs.types import Camera, Image, Points3D, SparseModel

    K = np.array([[50.0, 0, 20], [0, 50.0, 15], [0, 0, 1]])
    xyz = np.array([[0.0, 0.0, 2.0], [0.2, 0.1, 3.0], [-0.1, 0.05, 4.0]])
    ids = np.array([30, 10, 20])  # not sorted
    cam = Camera(1, "PINHOLE", 40, 30, K, np.array([50.0, 50.0, 20, 15]))
    img = Image(1, "a.png", 1, np.hstack([np.eye(3), np.zeros((3, 1))]), np.array([10, 20, 30]))
    pts = Points3D(ids, xyz, np.zeros((3, 3), np.uint8), np.zeros(3), np.arange(4), np.ones(3, np.int64))
    model = SparseModel({1: cam}, {1: img}, pts, {"a.png": 1})
    hints = stereo_context.image_sparse_depth(model, img, K, 30, 40)
    for p in xyz:
        u, v = (K @ p)[:2] / p[2]
        assert hints[int(v), int(u)] == pytest.approx(p[2])
    assert (hints > 0).sum() == 3


def test_parameter_free_switches_can_be_flipped_at_inference(tmp_path, tiny_checkpoint):
    from colmap_pvs.model import PARAMETER_FREE_FIELDS, load_checkpoint

    # flipping keeps the weights valid
    assert set(stereo_config_module.MODEL_SWITCHES) <= PARAMETER_FREE_FIELDS
    base, _ = load_checkpoint(tiny_checkpoint, map_location="cpu")
    assert not base.config.sparse_prior and not base.config.sparse_guidance
    cfg = stereo_config(workspace_path=tmp_path, checkpoint=tiny_checkpoint, device="cpu")
    for prior, guidance in (("on", "checkpoint"), ("on", "on"), ("off", "checkpoint")):
        changed = replace_config(cfg, sparse_prior=prior, sparse_guidance=guidance)
        model, path, _ = stereo_network.load_stereo_model(changed, "cpu")
        assert path == tiny_checkpoint
        assert model.config.sparse_prior == (prior == "on")
        assert model.config.sparse_guidance == (guidance == "on")
        for k, v in model.state_dict().items():  # the same weights
            assert np.array_equal(v.numpy(), base.state_dict()[k].numpy()), k


def test_passes_resume_independently_and_recompute_what_a_setting_affects(synthetic_ws, tmp_path,
                                                                        tiny_checkpoint):
    ws = _copy(synthetic_ws, tmp_path)
    cfg = stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3, max_image_size=48,
                       min_confidence=0.0)
    first = run_stereo(cfg)
    names = sorted(first.processed)
    assert sorted(first.geometric_processed) == names and len(names) == 4
    assert set(first.timings) >= {"load", "prior", "network", "normals", "writes", "geometric.consistency"}
    assert set(first.pass_seconds) == {"photometric", "geometric", "filled", "confirm", "total"}
    assert sorted(first.filled_processed) == names and "filled.splat" in first.timings
    assert sorted(first.confirm_processed) == names
    assert "filled.segments" in first.timings
    # A setting of the dense completion: only that pass is recomputed.
    res = run_stereo(replace_config(cfg, geom_fill_min_sources=1))
    assert res.processed == [] and res.geometric_processed == [] and sorted(res.filled_processed) == names
    assert sorted(res.confirm_processed) == names  # it reads the completions
    res = run_stereo(replace_config(cfg, geom_fill_min_sources=1, geom_fill_segments=False))
    assert res.processed == [] and res.geometric_processed == [] and sorted(res.filled_processed) == names
    assert "filled.segments" not in res.timings
    # A geometric setting: the geometric pass and the completion that reads it.
    res = run_stereo(replace_config(cfg, geom_max_depth_error=0.05))
    assert res.processed == [] and sorted(res.already_done) == names
    assert sorted(res.geometric_processed) == names and sorted(res.filled_processed) == names
    assert run_stereo(replace_config(cfg, geom_max_depth_error=0.05)).filled_processed == []
    # A photometric setting: both passes.
    res = run_stereo(replace_config(cfg, geom_max_depth_error=0.05, min_confidence=0.01))
    assert sorted(res.processed) == names and sorted(res.geometric_processed) == names
    # A truncated map or a missing provenance file recomputes that reference's pass only.
    cfg = replace_config(cfg, geom_max_depth_error=0.05, min_confidence=0.01)
    path = ws / "stereo" / "depth_maps" / f"{names[1]}.geometric.bin"
    path.write_bytes(path.read_bytes()[:100])
    (ws / "stereo" / "provenance" / f"{names[2]}.photometric.json").unlink()
    res = run_stereo(cfg)
    assert res.processed == [names[2]]
    # names[2]'s new photometric maps change nothing in its fingerprint: only names[1] is redone.
    assert res.geometric_processed == [names[1]]
    read_depth_map(path)
    # A different checkpoint recomputes everything.
    from conftest import make_tiny_checkpoint

    other = make_tiny_checkpoint(tmp_path / "other.pt", visibility_channels=6)
    res = run_stereo(replace_config(cfg, checkpoint=other))
    assert sorted(res.processed) == names


def test_geometric_pass_removes_inconsistent_pixels(analytic_scene, tmp_path, tiny_checkpoint, monkeypatch):
    """Exact photometric maps with one corrupted block: the geometric pass keeps the rest and drops it
    (without the sources' seeds, which would give it their depth: the next test)."""
    from colmap_pvs.io.maps import write_depth_map, write_normal_map

    ws = tmp_path / "ws"
    shutil.copytree(analytic_scene["root"], ws)
    cfg = stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=4, max_image_size=0,
                       min_confidence=0.0, geom_consistency=False, geom_splat_min_sources=0)
    run_stereo(cfg)
    from scenes import render_view

    for name in analytic_scene["names"]:  # replace the network's maps by the exact ones
        K = analytic_scene["map_K"][name]
        im = analytic_scene["model"].image_by_name(name)
        view = render_view(analytic_scene["scene"], K, im.cam_from_world, 160, 120)
        depth = view["depth"].astype(np.float32)
        if name == analytic_scene["names"][0]:
            depth[40:70, 60:100] *= 1.1
        write_depth_map(ws / "stereo" / "depth_maps" / f"{name}.photometric.bin", depth)
        write_normal_map(ws / "stereo" / "normal_maps" / f"{name}.photometric.bin", view["normals"])
    ctx = stereo_module.prepare_stereo(replace_config(cfg, geom_consistency=True))
    ref = analytic_scene["names"][0]
    out = stereo_module.process_reference(ctx, ref, "geometric")
    assert out.status == "computed" and out.timings["consistency"] >= 0
    geo = read_depth_map(ws / "stereo" / "depth_maps" / f"{ref}.geometric.bin")
    photo = read_depth_map(ws / "stereo" / "depth_maps" / f"{ref}.photometric.bin")
    assert (geo[40:70, 60:100] > 0).mean() < 0.02
    outside = np.ones_like(geo, bool)
    outside[40:70, 60:100] = False
    assert (geo[outside] > 0).mean() > 0.4
    ok = geo > 0
    np.testing.assert_allclose(geo[ok], photo[ok], rtol=0.03)  # averaged within geom_max_depth_error
    conf = read_array(ws / "stereo" / "confidence_maps" / f"{ref}.geometric.bin")
    assert np.all(conf[~ok] == 0) and conf[ok].min() > 0
    assert stereo_module.process_reference(ctx, ref, "geometric").status == "done"
    # The confidence weighs each agreeing source by its parallax: asking for far more parallax than
    # any source has scales it down (same kept pixels); then the shipped value again.
    strict = stereo_module.prepare_stereo(replace_config(cfg, geom_consistency=True, overwrite=True))
    monkeypatch.setattr(stereo_geometric, "GEOM_FULL_PARALLAX", 1e4)
    assert stereo_module.process_reference(strict, ref, "geometric").status == "computed"
    strict.flush()
    weak = read_array(ws / "stereo" / "confidence_maps" / f"{ref}.geometric.bin")
    assert np.array_equal(weak > 0, ok) and weak[ok].max() < 0.01 * conf[ok].max()
    monkeypatch.undo()
    assert stereo_module.process_reference(strict, ref, "geometric").status == "computed"
    strict.close()
    again = read_array(ws / "stereo" / "confidence_maps" / f"{ref}.geometric.bin")
    np.testing.assert_array_equal(again, conf)
    # The dense completion, from the reference's own kept pixels only (no other geometric map yet):
    # the kept pixels as they are, the dropped block filled by the plane fit from around it (the
    # block spans the box's edge, so the fit is not exact there), closer to the truth than the
    # corrupted photometric depth (10 % off), and ranked below the kept pixels.
    maps = ws / "stereo" / "depth_maps"
    assert stereo_module.process_reference(ctx, ref, "filled").status == "computed"
    ctx.flush()
    filled = read_depth_map(maps / f"{ref}.filled.bin")
    filled_conf = read_array(ws / "stereo" / "confidence_maps" / f"{ref}.filled.bin")
    assert np.all(filled > 0)
    # Its seeds: the pixels with at least 3 sources within geom_seed_depth_error (most of the kept ones,
    # none of the wrong block), their depth averaged with those sources'.
    seed_map = read_array(ws / "stereo" / "seed_maps" / f"{ref}.bin")
    seeds = seed_map > 0
    assert (seeds & ok).sum() > 0.5 * ok.sum() and seeds[40:70, 60:100].mean() < 0.02
    np.testing.assert_allclose(seed_map[seeds], photo[seeds], rtol=0.025)
    np.testing.assert_array_equal(filled[seeds], seed_map[seeds])
    truth = photo[40:70, 60:100] / 1.1
    fitted_error = np.median(np.abs(filled[40:70, 60:100] / truth - 1))
    assert fitted_error < 0.07
    # the tiers rank the seeds first; the local plane's factor then lowers the box's depth edges
    factor = np.exp(-plane_residual(filled, COMPLETION_RESIDUAL_WINDOW) / COMPLETION_RESIDUAL_SCALE)
    tiers = filled_conf / factor
    assert tiers[seeds].min() > tiers[~seeds].max()
    assert filled_conf[seeds & (factor > 0.99)].min() > filled_conf[~seeds].max()
    # With the other views' geometric maps, the block takes their kept depths (exact maps).
    for name in analytic_scene["names"][1:]:
        assert stereo_module.process_reference(ctx, name, "geometric").status == "computed"
    ctx.flush()
    assert stereo_module.process_reference(ctx, ref, "filled").status == "computed"  # sources changed
    ctx.flush()
    filled = read_depth_map(maps / f"{ref}.filled.bin")
    splat_error = np.median(np.abs(filled[40:70, 60:100] / truth - 1))
    assert splat_error < 0.005 and splat_error < fitted_error / 5
    np.testing.assert_array_equal(filled[seeds], seed_map[seeds])
    assert stereo_module.process_reference(ctx, ref, "filled").status == "done"
    # A source's geometric maps from other settings (another run) are not read.
    other = analytic_scene["names"][1]
    assert stereo_filled.current_geometric_provenance(ctx, other) is not None
    prov_path = ws / "stereo" / "provenance" / f"{other}.geometric.json"
    prov = json.loads(prov_path.read_text())
    prov["settings"]["geom_max_depth_error"] = 0.5
    prov_path.write_text(json.dumps(prov))
    assert stereo_filled.current_geometric_provenance(ctx, other) is None
    assert stereo_module.process_reference(ctx, ref, "filled").status == "computed"  # its sources changed
    ctx.close()
    # Switching the completion off removes it; the geometric maps stay as they are.
    res = run_stereo(replace_config(cfg, geom_consistency=True, geom_fill=False))
    assert res.geometric_processed == [] and res.filled_processed == []
    assert not list(maps.glob("*.filled.bin"))
    assert not list((ws / "stereo" / "confidence_maps").glob("*.filled.bin"))
    np.testing.assert_array_equal(read_depth_map(maps / f"{ref}.geometric.bin"), geo)


def test_geometric_pass_keeps_dropped_pixels_that_its_sources_seeds_confirm(analytic_scene, tmp_path,
                                                                          tiny_checkpoint):
    """A block of the reference 10 % too far fails the check; with ``geom_splat_min_sources`` the
    sources' seeds (made on demand from their photometric maps, the same as their own geometric pass
    makes them) give it their depth, ranked below the checked pixels."""
    ws, cfg, exact = _exact_photometric_maps(analytic_scene, tmp_path, tiny_checkpoint, 1.1)
    names = analytic_scene["names"]
    ref, truth = names[0], exact[names[0]]
    maps, seeds_dir = ws / "stereo" / "depth_maps", ws / "stereo" / "seed_maps"
    block = np.zeros_like(truth, bool)
    block[40:70, 60:100] = True
    off = replace_config(cfg, geom_consistency=True, geom_splat_min_sources=0)
    ctx = stereo_module.prepare_stereo(off)
    assert stereo_module.process_reference(ctx, ref, "geometric").status == "computed"
    ctx.close()
    dropped = read_depth_map(maps / f"{ref}.geometric.bin")
    assert (dropped[block] > 0).mean() < 0.02 and not (seeds_dir / f"{names[1]}.bin").exists()
    on = replace_config(off, geom_splat_min_sources=3)
    ctx = stereo_module.prepare_stereo(on)
    assert stereo_module.process_reference(ctx, ref, "geometric").status == "computed"
    ctx.close()
    geo = read_depth_map(maps / f"{ref}.geometric.bin")
    added = block & (geo > 0)
    assert added.sum() > 0.5 * block.sum()
    assert np.median(np.abs(geo[added] / truth[added] - 1)) < 0.005  # the sources' exact depth
    np.testing.assert_array_equal(geo[dropped > 0], dropped[dropped > 0])  # the checked pixels as they were
    conf = read_array(ws / "stereo" / "confidence_maps" / f"{ref}.geometric.bin")
    assert conf[added].min() > 0 and conf[added].max() <= stereo_geometric.SPLAT_CONFIDENCE
    assert conf[added].max() < np.median(conf[dropped > 0])  # ranked below the checked pixels
    prov = json.loads((ws / "stereo" / "provenance" / f"{ref}.geometric.json").read_text())
    assert prov["settings"]["geom_splat_min_sources"] == 3
    assert set(prov["settings"]["splat_seeds"]) <= set(names)
    newly = ((geo > 0) & ~(dropped > 0)).mean()  # splatted, less those the normal fit dropped
    assert newly > 0 and newly <= prov["splatted_fraction"] <= 1.25 * newly  # a share of the pixels
    # The sources' seeds were made on demand, and their fingerprints are part of the reference's; their
    # own geometric pass makes the same ones.
    on_demand = {n: read_array(seeds_dir / f"{n}.bin") for n in prov["settings"]["splat_seeds"]}
    assert on_demand
    for n in on_demand:
        stamp = json.loads((seeds_dir / f"{n}.json").read_text())["fingerprint"]
        assert prov["settings"]["splat_seeds"][n] == stamp
    res = run_stereo(replace_config(on, geom_fill=False))
    assert ref in res.geometric_done and sorted(res.geometric_processed) == sorted(set(names) - {ref})
    for n, seeds in on_demand.items():
        np.testing.assert_array_equal(read_array(seeds_dir / f"{n}.bin"), seeds)
    # A seed setting changes the sources' seeds and so the reference's pass; the splat setting is a
    # geometric one that leaves the seeds as they are: switching it off recomputes that pass only.
    res = run_stereo(replace_config(on, geom_fill=False, geom_seed_depth_error=0.02))
    assert sorted(res.geometric_processed) == sorted(names) and res.processed == []
    stamps = {n: json.loads((seeds_dir / f"{n}.json").read_text())["fingerprint"] for n in names}
    assert all(stamps[n] != prov["settings"]["splat_seeds"][n] for n in on_demand)
    res = run_stereo(replace_config(off, geom_fill=False, geom_seed_depth_error=0.02))
    assert sorted(res.geometric_processed) == sorted(names) and res.processed == []
    assert stamps == {n: json.loads((seeds_dir / f"{n}.json").read_text())["fingerprint"] for n in names}
    np.testing.assert_array_equal(read_depth_map(maps / f"{ref}.geometric.bin"), dropped)


def test_geometric_pass_of_a_scene_nearer_than_one_unit(analytic_scene, tmp_path, tiny_checkpoint):
    """Scene units are arbitrary: the analytic scene at a tenth of its size (depths 0.2-0.6). The
    sources' seeds splatted into the reference's dropped block keep a confidence, and the depth previews
    of a reference without a view-selection entry span its own depths."""
    ws, cfg, exact = _exact_photometric_maps(analytic_scene, tmp_path, tiny_checkpoint, 1.1, scale=0.1)
    ref = analytic_scene["names"][0]
    assert exact[ref].max() < 1
    on = replace_config(cfg, geom_consistency=True, geom_splat_min_sources=3, previews=True)
    ctx = stereo_module.prepare_stereo(on)
    ctx.selection = dataclasses.replace(ctx.selection, references={
        n: e for n, e in ctx.selection.references.items() if n != ref})
    assert stereo_module.process_reference(ctx, ref, "geometric").status == "computed"
    ctx.close()
    geo = read_depth_map(ws / "stereo" / "depth_maps" / f"{ref}.geometric.bin")
    conf = read_array(ws / "stereo" / "confidence_maps" / f"{ref}.geometric.bin")
    added = np.zeros_like(geo, bool)
    added[40:70, 60:100] = True
    added &= geo > 0
    assert added.sum() > 0.5 * 30 * 40 and np.median(np.abs(geo[added] / exact[ref][added] - 1)) < 0.005
    assert conf[added].min() > 0
    preview = cv2.imread(str(preview_path(load_workspace(ws)[0], ref, "geometric")))[: geo.shape[0]]  # no bar
    colours = np.unique(preview[geo > 0].reshape(-1, 3), axis=0)
    assert len(colours) > 50  # not one colour clipped at an end of the scale
    nearest = np.unravel_index(np.argmin(np.where(geo > 0, geo, np.inf)), geo.shape)
    lowest = colorize_depth(geo, geo[nearest], 2 * geo[nearest])[nearest]
    np.testing.assert_array_equal(preview[nearest], lowest)  # the scale starts at the nearest depth
    farthest = np.unravel_index(np.argmax(geo), geo.shape)
    highest = colorize_depth(geo, 0.5 * geo[farthest], geo[farthest])[farthest]
    np.testing.assert_array_equal(preview[farthest], highest)  # and ends at the farthest, not at 2
    prov = json.loads((ws / "stereo" / "provenance" / f"{ref}.geometric.json").read_text())
    assert prov["kept_fraction"] == pytest.approx(float((geo > 0).mean()))
    normals = read_normal_map(ws / "stereo" / "normal_maps" / f"{ref}.geometric.bin")
    np.testing.assert_array_equal(geo > 0, np.any(normals != 0, axis=-1))  # a depth only with a normal
    # geom_min_confidence is inclusive for splatted pixels too.
    least = float(conf[added].min())
    ctx = stereo_module.prepare_stereo(replace_config(on, geom_min_confidence=least))
    assert stereo_module.process_reference(ctx, ref, "geometric").status == "computed"
    ctx.close()
    geo = read_depth_map(ws / "stereo" / "depth_maps" / f"{ref}.geometric.bin")
    assert (geo[added & (conf == least)] > 0).all()


def test_geometric_check_refuses_a_normal_map_of_another_size(analytic_scene, tmp_path, tiny_checkpoint):
    """A photometric normal map whose size differs from its depth map's: an error naming both sizes."""
    from colmap_pvs.errors import MapFormatError
    from colmap_pvs.io.maps import write_normal_map

    ws, cfg, _ = _exact_photometric_maps(analytic_scene, tmp_path, tiny_checkpoint, 1.0)
    ref = analytic_scene["names"][0]
    small = np.zeros((60, 80, 3), np.float32)
    small[..., 2] = -1.0
    write_normal_map(ws / "stereo" / "normal_maps" / f"{ref}.photometric.bin", small)
    ctx = stereo_module.prepare_stereo(replace_config(cfg, geom_consistency=True))
    try:
        with pytest.raises(MapFormatError, match=r"is \(60, 80\) but its depth map is \(120, 160\)"):
            stereo_geometric.load_maps(ctx, ctx.reference(ref))
    finally:
        ctx.close()


def test_geometric_check_visibility_follows_the_network_sources():
    """The learned visibility of each checked source is the network's map of that source (upsampled to the
    depth map); a checked source the network did not see counts as visible; maps that do not match the
    network's sources are not used."""
    coarse = np.stack([np.full((3, 4), 0.25, np.float32), np.full((3, 4), 0.75, np.float32)])
    vis = stereo_geometric._check_visibility(coarse, ["a", "b"], ["b", "c", "a"], (6, 8))
    assert vis.shape == (3, 6, 8)
    np.testing.assert_allclose(vis[0], 0.75)
    np.testing.assert_allclose(vis[1], 1.0)
    np.testing.assert_allclose(vis[2], 0.25)
    assert stereo_geometric._check_visibility(coarse, ["a"], ["a"], (6, 8)) is None
    assert stereo_geometric._check_visibility(coarse, ["a", "b", "c"], ["a"], (6, 8)) is None


def test_geometric_pass_averages_agreeing_depths_and_drops_unconfident_pixels(analytic_scene, tmp_path,
                                                                              tiny_checkpoint):
    """A block of the reference 2 % too far passes the check (3 %): with ``geom_average_depth`` it takes
    the mean of its depth and the confirming sources' (exact) ones, without it its own depth;
    ``geom_min_confidence`` drops the pixels below it, the rest as they were; too few sources with
    photometric maps skip the pass."""
    ws, cfg, exact = _exact_photometric_maps(analytic_scene, tmp_path, tiny_checkpoint, 1.02)
    names = analytic_scene["names"]
    ref, truth = names[0], exact[names[0]]
    maps, confs = ws / "stereo" / "depth_maps", ws / "stereo" / "confidence_maps"
    photo = read_depth_map(maps / f"{ref}.photometric.bin")
    block = np.zeros_like(truth, bool)
    block[40:70, 60:100] = True
    on = replace_config(cfg, geom_consistency=True, geom_splat_min_sources=0, overwrite=True)

    def geometric(**changes):
        ctx = stereo_module.prepare_stereo(replace_config(on, **changes))
        out = stereo_module.process_reference(ctx, ref, "geometric")
        ctx.close()
        if out.status != "computed":
            return out
        return read_depth_map(maps / f"{ref}.geometric.bin"), read_array(confs / f"{ref}.geometric.bin")

    geo, conf = geometric()
    kept = block & (geo > 0)
    assert kept.sum() > 0.5 * block.sum()
    assert np.median(np.abs(geo[kept] / truth[kept] - 1)) < 0.01  # 2 % off, averaged with exact sources
    prov = json.loads((ws / "stereo" / "provenance" / f"{ref}.geometric.json").read_text())
    assert prov["kept_fraction"] == pytest.approx(float((geo > 0).mean()))
    assert prov["reestimated"] is False  # the photometric maps checked, not re-estimated
    assert prov["splatted_fraction"] == 0 and "splat_seeds" not in prov["settings"]  # no splat asked
    seed_map = read_array(ws / "stereo" / "seed_maps" / f"{ref}.bin")  # within 2.5 %: the block seeds too
    seeded = block & (seed_map > 0)
    assert seeded.sum() > 0.3 * block.sum()
    assert np.median(np.abs(seed_map[seeded] / truth[seeded] - 1)) < 0.01  # averaged, as the kept depth
    own, _ = geometric(geom_average_depth=False)
    np.testing.assert_array_equal(own[own > 0], photo[own > 0])
    own_seeds = read_array(ws / "stereo" / "seed_maps" / f"{ref}.bin")
    assert (own_seeds > 0).any()
    np.testing.assert_array_equal(own_seeds[own_seeds > 0], photo[own_seeds > 0])
    threshold = float(np.median(conf[geo > 0]))
    strict, strict_conf = geometric(geom_min_confidence=threshold)
    assert 0.2 * (geo > 0).sum() < (strict > 0).sum() < 0.8 * (geo > 0).sum()
    assert strict_conf[strict > 0].min() >= threshold
    np.testing.assert_array_equal(strict_conf[strict > 0], conf[strict > 0])
    # One source with photometric maps, where geom_min_consistent (2) must agree: skipped, not computed.
    source = prov["sources"][0]
    for name in names:
        if name not in (ref, source):
            (maps / f"{name}.photometric.bin").unlink()
    out = geometric()
    assert out.status == "skipped" and out.reason.startswith("1 of its sources have photometric maps")


def test_geometric_pass_checks_each_reference_once_and_reuses_current_seeds(analytic_scene, tmp_path,
                                                                           tiny_checkpoint, monkeypatch):
    """In a run, a reference checked for another reference's seeds is not checked again for its own pass;
    a later pass reads its sources' current seed maps instead of checking them again, unless
    ``overwrite``."""
    ws, cfg, _ = _exact_photometric_maps(analytic_scene, tmp_path, tiny_checkpoint, 1.1)
    names, ref = analytic_scene["names"], analytic_scene["names"][0]
    calls = []
    real = stereo_geometric.check_consistency

    def counted(*args, **kwargs):
        calls.append(args[5] if len(args) > 5 else kwargs.get("visibility"))  # the learned visibility
        return real(*args, **kwargs)

    monkeypatch.setattr(stereo_geometric, "check_consistency", counted)
    on = replace_config(cfg, geom_consistency=True, geom_fill=False, geom_splat_min_sources=3)
    res = run_stereo(on)
    assert sorted(res.geometric_processed) == sorted(names) and len(calls) == len(names)
    assert all(vis is not None and vis.any() for vis in calls)  # each check weighs the network's visibility
    sources = json.loads((ws / "stereo" / "provenance" / f"{ref}.geometric.json").read_text())["sources"]
    for changes, expected in (({"geom_splat_min_sources": 2}, 1), ({"overwrite": True}, 1 + len(sources))):
        calls.clear()
        ctx = stereo_module.prepare_stereo(replace_config(on, **changes))
        assert stereo_module.process_reference(ctx, ref, "geometric").status == "computed"
        ctx.close()
        assert len(calls) == expected, changes
    # A current pass whose seed map is missing is recomputed, its seed map written again.
    ctx = stereo_module.prepare_stereo(on)
    assert stereo_module.process_reference(ctx, ref, "geometric").status == "done"
    assert not preview_path(ctx.workspace, ref, "geometric").exists()  # no previews asked
    (ws / "stereo" / "seed_maps" / f"{ref}.bin").unlink()
    assert stereo_module.process_reference(ctx, ref, "geometric").status == "computed"
    ctx.flush()
    assert (ws / "stereo" / "seed_maps" / f"{ref}.bin").is_file()
    # Seeds held in memory under another fingerprint (other settings) are never reused.
    setup = stereo_geometric._check_setup(ctx, sources[0])
    stale = np.full((120, 160), 7.0, np.float32)
    ctx.seed_cache[sources[0]] = ("~" * 64, stereo_geometric.Checked(stale))  # "~" sorts after hex digits
    assert not np.array_equal(stereo_geometric._source_seeds(ctx, sources[0], setup), stale)
    # On disk too: only a seed map under the wanted fingerprint is read; a broken one is made again.
    name = sources[0]
    fresh = stereo_geometric._source_seeds(ctx, name, setup)
    paths = ctx.reference(name).paths
    seed_file, stamp = paths.seeds, paths.seed_provenance
    wanted = json.loads(stamp.read_text())["fingerprint"]
    for broken in ("sorts_after", "map", "json", "no_json"):
        ctx.seed_cache.clear()
        stereo_outputs.write_seeds(paths, stale, "~" * 64 if broken == "sorts_after" else wanted)
        if broken == "map":
            seed_file.write_bytes(seed_file.read_bytes()[:20])
        elif broken == "json":
            stamp.write_text("{")
        elif broken == "no_json":
            stamp.unlink()
        np.testing.assert_array_equal(stereo_geometric._source_seeds(ctx, name, setup), fresh, err_msg=broken)
        assert json.loads(stamp.read_text())["fingerprint"] == wanted  # and written again
        np.testing.assert_array_equal(read_array(seed_file), fresh)
    ctx.close()


def _pure_geometric(ws: Path, name: str) -> np.ndarray:
    """The geometric pass's own depth of ``name``: its geometric map without the completed pixels the
    confirmation added (``stereo/confirm_maps``)."""
    geo = read_depth_map(ws / "stereo" / "depth_maps" / f"{name}.geometric.bin")
    added = ws / "stereo" / "confirm_maps" / f"{name}.bin"
    return np.where(read_depth_map(added) > 0, 0.0, geo).astype(np.float32) if added.is_file() else geo


def _exact_photometric_maps(analytic_scene, tmp_path, checkpoint, factor, scale=1.0):
    """A copy of the analytic scene (its sparse model and depths ``scale`` times the original's) after a
    photometric-only run, its photometric maps replaced by the exact ones, but a block of the first view's
    depth ``factor`` times too far. Returns the workspace, that run's config and the exact depths by name."""
    from scenes import render_view

    from colmap_pvs.io.maps import write_depth_map, write_normal_map

    ws = tmp_path / "ws"
    shutil.copytree(analytic_scene["root"], ws)
    if scale != 1.0:  # the same images of a scene `scale` times the size
        model = analytic_scene["model"]
        images = {i: dataclasses.replace(im, cam_from_world=np.hstack([im.cam_from_world[:, :3],
                                                                       scale * im.cam_from_world[:, 3:]]))
                  for i, im in model.images.items()}
        points = dataclasses.replace(model.points, xyz=scale * model.points.xyz)
        write_sparse_model(dataclasses.replace(model, images=images, points=points), ws / "sparse")
    cfg = stereo_config(workspace_path=ws, checkpoint=checkpoint, num_views=4, max_image_size=0,
                       min_confidence=0.0, geom_consistency=False)
    run_stereo(cfg)
    names, model = analytic_scene["names"], analytic_scene["model"]
    exact = {}
    for name in names:
        view = render_view(analytic_scene["scene"], analytic_scene["map_K"][name],
                           model.image_by_name(name).cam_from_world, 160, 120)
        exact[name] = scale * view["depth"].astype(np.float32)
        depth = exact[name].copy()
        if name == names[0]:
            depth[40:70, 60:100] *= factor
        write_depth_map(ws / "stereo" / "depth_maps" / f"{name}.photometric.bin", depth)
        write_normal_map(ws / "stereo" / "normal_maps" / f"{name}.photometric.bin", view["normals"])
    return ws, cfg, exact


def test_completion_keeps_only_strictly_agreeing_pixels_and_fills_the_rest(analytic_scene, tmp_path,
                                                                           tiny_checkpoint):
    """A block of the reference 2.8 % too far passes the geometric check (3 %) but not the seeds' 2.5 %:
    the completion fills it from the sources' exact maps, unless every kept pixel seeds it."""
    ws, cfg, exact = _exact_photometric_maps(analytic_scene, tmp_path, tiny_checkpoint, 1.028)
    names = analytic_scene["names"]
    ref, truth = names[0], exact[names[0]]
    geo_cfg = replace_config(cfg, geom_consistency=True, geom_average_depth=False,
                                  geom_splat_min_sources=0)  # the kept pixels: the checked ones only
    run_stereo(geo_cfg)
    maps = ws / "stereo" / "depth_maps"
    geo = _pure_geometric(ws, ref)
    block = np.zeros_like(geo, bool)
    block[40:70, 60:100] = True
    assert (geo[block] > 0).mean() > 0.3  # much of the block is kept by the geometric check ...
    seed_map = read_array(ws / "stereo" / "seed_maps" / f"{ref}.bin")
    inner = block & (geo > 0)
    assert (seed_map[inner] > 0).mean() < 0.3  # ... but few of its pixels are seeds (within 2.5 %)
    assert (seed_map[~block & (geo > 0)] > 0).mean() > 0.6
    filled = read_depth_map(maps / f"{ref}.filled.bin")
    assert np.median(np.abs(filled[inner] / truth[inner] - 1)) < 0.005  # from the sources' exact maps
    # Seeds at the check's own tolerance: (nearly) every kept pixel is one, the block stays as it is.
    # The seed settings belong to the geometric pass: it is recomputed, then the completion.
    res = run_stereo(replace_config(geo_cfg, geom_seed_min_consistent=1, geom_seed_depth_error=0.03))
    assert sorted(res.geometric_processed) == sorted(names) and sorted(res.filled_processed) == sorted(names)
    every = read_depth_map(maps / f"{ref}.filled.bin")
    seed_map = read_array(ws / "stereo" / "seed_maps" / f"{ref}.bin")
    seeds = seed_map > 0
    assert (seeds & (geo > 0)).sum() > 0.99 * (geo > 0).sum()
    np.testing.assert_array_equal(every[seeds], seed_map[seeds])
    np.testing.assert_array_equal(seed_map[geo > 0], geo[geo > 0])  # the depth as it is (no averaging)
    assert np.median(np.abs(every[inner] / truth[inner] - 1)) > 0.025


def test_geometric_reestimate_runs_the_network_on_the_agreed_depth(analytic_scene, tmp_path, tiny_checkpoint,
                                                                    monkeypatch):
    """``geom_reestimate``: the depth the sources' photometric maps agree on reaches a second network run
    as dense hints, and that run's depth (not the photometric map) is what the check keeps."""
    # exact photometric maps, but a block of the reference 10 % too far (and no seeds of the sources,
    # which would fill it without the re-estimate)
    ws, cfg, exact = _exact_photometric_maps(analytic_scene, tmp_path, tiny_checkpoint, 1.1)
    cfg = replace_config(cfg, geom_splat_min_sources=0)
    names, model = analytic_scene["names"], analytic_scene["model"]
    calls = []
    real = stereo_photometric.estimate_depth

    def network(net, images, intrinsics, poses, depth_range, sparse_depth, device):
        """The tiny network's outputs, but the exact depth of the view (a network that gets it right)."""
        depth, conf, vis, prior = real(net, images, intrinsics, poses, depth_range, sparse_depth, device)
        name = next(n for n in names if np.allclose(poses[0][:3], model.image_by_name(n).cam_from_world))
        calls.append((name, sparse_depth.copy()))
        assert depth.shape == exact[name].shape
        return exact[name].copy(), np.full_like(conf, 0.25), vis, prior  # a network a quarter sure

    monkeypatch.setattr(stereo_photometric, "estimate_depth", network)
    ref = names[0]
    block = np.zeros((120, 160), bool)
    block[40:70, 60:100] = True
    plain = stereo_module.prepare_stereo(replace_config(cfg, geom_consistency=True))
    assert stereo_module.process_reference(plain, ref, "geometric").status == "computed"
    plain.close()
    assert calls == []  # off by default: no second network run
    geo = read_depth_map(ws / "stereo" / "depth_maps" / f"{ref}.geometric.bin")
    assert (geo[block] > 0).mean() < 0.02
    re_cfg = replace_config(cfg, geom_consistency=True, geom_reestimate=True)
    ctx = stereo_module.prepare_stereo(re_cfg)
    out = stereo_module.process_reference(ctx, ref, "geometric")
    ctx.close()
    assert out.status == "computed" and {"reestimate_hints", "reestimate_network"} <= set(out.timings)
    assert [c[0] for c in calls] == [ref]
    hints = calls[0][1]
    # Outside the block the hints are the agreed (averaged) depth, dense; inside only SfM points remain.
    outside = ~block & (exact[ref] > 0)
    assert (hints[outside] > 0).mean() > 0.4 and (hints[block] > 0).mean() < 0.1
    has = outside & (hints > 0)
    np.testing.assert_allclose(hints[has], exact[ref][has], rtol=0.03)
    geo = read_depth_map(ws / "stereo" / "depth_maps" / f"{ref}.geometric.bin")
    assert (geo[block] > 0).mean() > 0.5  # the re-estimate is right there, and its sources agree
    np.testing.assert_allclose(geo[geo > 0], exact[ref][geo > 0], rtol=0.03)
    # its confidence is the re-estimate's: times the network's probability (0.25; no calibration here)
    conf = read_array(ws / "stereo" / "confidence_maps" / f"{ref}.geometric.bin").reshape(geo.shape)
    assert 0.1 < conf[geo > 0].max() <= 0.25 + 1e-6
    prov = json.loads((ws / "stereo" / "provenance" / f"{ref}.geometric.json").read_text())
    assert prov["reestimated"] is True and prov["settings"]["geom_reestimate"] is True
    # A rerun keeps it; the setting is a geometric one: switching it back recomputes that pass only.
    res = run_stereo(re_cfg)
    assert res.processed == [] and ref in res.geometric_done
    res = run_stereo(replace_config(re_cfg, geom_reestimate=False))
    assert res.processed == [] and sorted(res.geometric_processed) == sorted(names)
    assert (_pure_geometric(ws, ref)[block] > 0).mean() < 0.02
    # Pixels agreed on by exactly geom_min_consistent sources are hints too (here: all of its sources).
    calls.clear()
    ctx = stereo_module.prepare_stereo(replace_config(re_cfg, geom_min_consistent=len(prov["sources"])))
    assert stereo_module.process_reference(ctx, ref, "geometric").status == "computed"
    ctx.close()
    assert (calls[0][1][outside] > 0).mean() > 0.2


def test_confirmation_adds_the_agreed_completion_to_the_geometric_maps_and_takes_it_back(
        analytic_scene, tmp_path, tiny_checkpoint):
    """A block of the reference 10 % too far fails the geometric check; the completion fills it from the
    sources' exact maps and the other references' completions agree, so those pixels join the geometric
    maps (which COLMAP's fusion reads), recorded in ``confirm_maps``; a rerun keeps them, and without
    the completion the geometric maps are the geometric pass's own again."""
    ws, cfg, exact = _exact_photometric_maps(analytic_scene, tmp_path, tiny_checkpoint, 1.1)
    fresh = {k: shutil.copytree(ws, tmp_path / k) for k in ("other_fill", "no_fill")}  # before any pass
    names = analytic_scene["names"]
    ref = names[0]
    block = np.zeros((120, 160), bool)
    block[40:70, 60:100] = True
    cfg = replace_config(cfg, geom_consistency=True, geom_splat_min_sources=0,  # no sources' seeds in it
                         geom_min_triangulation_angle=20)  # seeds outside the pass's own pixels
    res = run_stereo(cfg)
    assert sorted(res.confirm_processed) == sorted(names)
    maps = ws / "stereo" / "depth_maps"
    geo, pure = read_depth_map(maps / f"{ref}.geometric.bin"), _pure_geometric(ws, ref)
    added = read_depth_map(ws / "stereo" / "confirm_maps" / f"{ref}.bin") > 0
    assert (pure[block] > 0).mean() < 0.02 and (added[block]).mean() > 0.5
    assert not (added & (pure > 0)).any() and np.array_equal(geo[~added], pure[~added])
    assert np.median(np.abs(geo[added & block] / exact[ref][added & block] - 1)) < 0.01
    normals = read_normal_map(ws / "stereo" / "normal_maps" / f"{ref}.geometric.bin")
    assert np.all(np.linalg.norm(normals[added], axis=-1) > 0.99)
    record = json.loads((ws / "stereo" / "provenance" / f"{ref}.confirm.json").read_text())
    assert record["geometric"] == json.loads(
        (ws / "stereo" / "provenance" / f"{ref}.geometric.json").read_text())["fingerprint"]
    mtime = (maps / f"{ref}.geometric.bin").stat().st_mtime_ns
    again = run_stereo(cfg)
    assert ref in again.confirm_done and (maps / f"{ref}.geometric.bin").stat().st_mtime_ns == mtime

    def same_maps(a: Path, b: Path, kinds=("geometric", "filled")) -> None:
        for n in names:
            for kind in kinds:
                for sub in ("depth_maps", "normal_maps", "confidence_maps"):
                    f = f"stereo/{sub}/{n}.{kind}.bin"
                    if (a / f).is_file() or (b / f).is_file():
                        np.testing.assert_array_equal(read_array(a / f), read_array(b / f), err_msg=f)

    # Another completion: the confirmed pixels of the old one are taken out first, as in a fresh run.
    other = replace_config(cfg, geom_fill_min_sources=1)
    res = run_stereo(other)
    assert res.geometric_processed == [] and sorted(res.confirm_processed) == sorted(names)
    run_stereo(replace_config(other, workspace_path=fresh["other_fill"]))
    same_maps(ws, fresh["other_fill"])
    # Without the completion the geometric maps are the geometric pass's own, as in a fresh run.
    run_stereo(replace_config(cfg, geom_fill=False))
    run_stereo(replace_config(cfg, geom_fill=False, workspace_path=fresh["no_fill"]))
    same_maps(ws, fresh["no_fill"], ("geometric",))
    np.testing.assert_array_equal(read_depth_map(maps / f"{ref}.geometric.bin"), pure)
    assert not (ws / "stereo" / "confirm_maps" / f"{ref}.bin").exists()
    assert not (ws / "stereo" / "provenance" / f"{ref}.confirm.json").exists()
    # A geometric depth file that another tool rewrote: the record no longer applies, nothing is taken out.
    assert sorted(run_stereo(cfg).confirm_processed) == sorted(names)
    outside = maps / f"{ref}.geometric.bin"
    other = read_depth_map(outside).copy()
    other[0, 0] += 1.0
    write_depth_map(outside, other)
    run_stereo(replace_config(cfg, geom_fill=False))
    np.testing.assert_array_equal(read_depth_map(outside), other)
    assert not (ws / "stereo" / "provenance" / f"{ref}.confirm.json").exists()


def test_one_view_confirms_only_a_confident_completed_pixel():
    from colmap_pvs.stereo.confirm import CONFIRM_MIN_VIEWS, CONFIRM_ONE_VIEW_CONFIDENCE, confirmed

    agreeing = np.array([[0, 1, 1, 1], [2, 2, 3, 0]])
    c = CONFIRM_ONE_VIEW_CONFIDENCE
    below = np.nextafter(np.float32(c), np.float32(0))
    confidence = np.array([[1.0, c, below, 0.0], [0.0, 1.0, 0.2, 1.0]], np.float32)
    assert CONFIRM_MIN_VIEWS == 2 and c == 0.7  # docs/CONVENTIONS.md
    np.testing.assert_array_equal(confirmed(agreeing, confidence), [[False, True, False, False],
                                                                    [True, True, True, False]])


def test_confirmation_with_one_other_completion_adds_only_confident_pixels(analytic_scene, tmp_path,
                                                                          tiny_checkpoint, monkeypatch):
    """With one other completion to check against, the pass adds a pixel only through the one-view rule:
    nothing where no confidence reaches its threshold, and only pixels at or above it otherwise."""
    from colmap_pvs.stereo import confirm as stereo_confirm

    ws, cfg, _ = _exact_photometric_maps(analytic_scene, tmp_path, tiny_checkpoint, 1.1)
    fresh = shutil.copytree(ws, tmp_path / "fresh")
    cfg = replace_config(cfg, geom_consistency=True, geom_splat_min_sources=0,
                         geom_min_triangulation_angle=20, geom_num_sources=1)
    ref = analytic_scene["names"][0]

    def added(workspace: Path, threshold: float) -> tuple[np.ndarray, np.ndarray]:
        monkeypatch.setattr(stereo_confirm, "CONFIRM_ONE_VIEW_CONFIDENCE", threshold)
        run_stereo(replace_config(cfg, workspace_path=workspace))
        conf = read_array(workspace / "stereo" / "confidence_maps" / f"{ref}.filled.bin").reshape(120, 160)
        return read_depth_map(workspace / "stereo" / "confirm_maps" / f"{ref}.bin") > 0, conf

    none, conf = added(ws, 2.0)  # no confidence reaches 2: one view confirms nothing
    assert not none.any()
    level = float(np.median(conf[conf > 0]))  # (the completion is the same in both runs)
    some, conf = added(fresh, level)
    assert some.sum() > 100 and conf[some].min() >= level


def test_network_scale_runs_the_network_smaller_and_writes_map_size(synthetic_ws, tmp_path, tiny_checkpoint,
                                                                     monkeypatch):
    ws = _copy(synthetic_ws, tmp_path)
    seen = []
    real = stereo_photometric.estimate_depth

    def spy(model, images, intrinsics, poses, depth_range, sparse_depth, device):
        seen.append((images.shape[-2:], sparse_depth.shape, intrinsics[0].copy()))
        return real(model, images, intrinsics, poses, depth_range, sparse_depth, device)

    monkeypatch.setattr(stereo_photometric, "estimate_depth", spy)
    cfg = stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3, max_image_size=64,
                       min_confidence=0.0, network_scale=0.5, network_min_size=16, geom_consistency=False)
    res = run_stereo(cfg)
    names = sorted(res.processed)
    assert names and "upsample" in res.timings
    # the network saw 32x24 images with matching hints and intrinsics; the maps are 64x48
    assert all(tuple(s) == (24, 32) and tuple(h) == (24, 32) for s, h, _ in seen)
    ws_obj, model = load_workspace(ws)
    cam = model.camera_of(model.image_by_name(names[0]))
    np.testing.assert_allclose(seen[0][2], fusion_intrinsics(cam.K, (cam.width, cam.height), (32, 24)))
    for name in names:
        assert read_depth_map(ws_obj.depth_map_path(name, "photometric")).shape == (48, 64)
        assert read_normal_map(ws_obj.normal_map_path(name, "photometric")).shape == (48, 64, 3)
    # the scale is a photometric setting: changing it recomputes the maps
    seen.clear()
    again = run_stereo(replace_config(cfg, network_scale=1.0))
    assert sorted(again.processed) == names and all(tuple(s) == (48, 64) for s, _, _ in seen)
    assert "upsample" not in again.timings
    # network_min_size: the network's longest side stays >= 40 px (scale 0.625 here, not 0.5)
    seen.clear()
    run_stereo(replace_config(cfg, network_min_size=40))
    assert all(tuple(s) == (30, 40) for s, _, _ in seen)


def test_network_scale_above_one_reads_the_original_image_and_samples_the_depth_down(
        synthetic_ws, tmp_path, tiny_checkpoint, monkeypatch):
    """``network_scale`` 2 with 48 px maps: the network sees the 96x72 original (its real detail, not
    the 48 px image enlarged) with intrinsics and hints at 96x72, and each map pixel ``(c, r)`` takes
    the network's depth at pixel ``(2c, 2r)``, the one on its own ray (no average across an edge).
    With 64 px maps the network's 128x96 input is the original enlarged bilinearly."""
    ws = _copy(synthetic_ws, tmp_path)
    seen = []
    real = stereo_photometric.estimate_depth

    def spy(model, images, intrinsics, poses, depth_range, sparse_depth, device):
        depth, conf, vis, prior = real(model, images, intrinsics, poses, depth_range, sparse_depth, device)
        h, w = depth.shape  # a depth that tells every network pixel apart (the tiny net's is flat)
        rows, cols = np.mgrid[0:h, 0:w].astype(np.float32)
        pattern = (2.0 + 0.01 * rows + 0.0001 * cols).astype(np.float32)
        seen.append((images.copy(), sparse_depth.shape, intrinsics[0].copy(), pattern))
        return pattern, conf, vis, prior

    monkeypatch.setattr(stereo_photometric, "estimate_depth", spy)
    cfg = stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3, max_image_size=48,
                       min_confidence=0.0, network_scale=2.0, network_min_size=16, geom_consistency=False,
                       sparse_prior="off")
    res = run_stereo(cfg)
    names = sorted(res.processed)
    assert names and len(seen) == len(names)
    ws_obj, model = load_workspace(ws)
    for name, (images, hints, K, net_depth) in zip(names, seen, strict=True):
        assert images.shape[-2:] == (72, 96) and hints == (72, 96)
        cam = model.camera_of(model.image_by_name(name))
        assert (cam.width, cam.height) == (96, 72)  # the original: its pixels, unresampled
        original = cv2.cvtColor(cv2.imread(str(ws / "images" / name)), cv2.COLOR_BGR2RGB)
        np.testing.assert_allclose(images[0], original.transpose(2, 0, 1) / 255.0, atol=1e-6)
        np.testing.assert_allclose(K, fusion_intrinsics(cam.K, (cam.width, cam.height), (96, 72)))
        depth = read_depth_map(ws_obj.depth_map_path(name, "photometric"))
        assert depth.shape == (36, 48)
        valid = depth > 0
        assert valid.mean() > 0.5
        np.testing.assert_array_equal(depth[valid], net_depth[::2, ::2][valid])
    # the same ray: a map pixel's and its network pixel's rays through fusion_intrinsics coincide
    K_map = fusion_intrinsics(cam.K, (cam.width, cam.height), (48, 36))
    ray_map = np.linalg.solve(K_map, [5 + 0.5, 7 + 0.5, 1.0])
    ray_net = np.linalg.solve(fusion_intrinsics(cam.K, (96, 72), (96, 72)), [10 + 0.5, 14 + 0.5, 1.0])
    np.testing.assert_allclose(ray_map / ray_map[2], ray_net / ray_net[2], atol=1e-12)
    # beyond the original's size the network's input is the original enlarged bilinearly
    seen.clear()
    run_stereo(replace_config(cfg, max_image_size=64, overwrite=True))
    original = cv2.cvtColor(cv2.imread(str(ws / "images" / names[0])), cv2.COLOR_BGR2RGB)
    enlarged = cv2.resize(original, (128, 96), interpolation=cv2.INTER_LINEAR)
    np.testing.assert_allclose(seen[0][0][0], enlarged.transpose(2, 0, 1) / 255.0, atol=1e-6)
    with pytest.raises(ConfigError, match="network_scale"):
        stereo_config(workspace_path=ws, network_scale=2.5)


def test_geometric_reestimate_with_a_smaller_network_gives_hints_at_the_network_size(
        synthetic_ws, tmp_path, tiny_checkpoint, monkeypatch):
    """With ``network_scale`` the re-estimate's dense hints are resized to the network input, and add
    to the SfM hints; the geometric maps stay at the map size."""
    ws = _copy(synthetic_ws, tmp_path)
    seen: dict[str, list[np.ndarray]] = {"photometric": [], "geometric": []}
    stage = ["photometric"]
    real = stereo_photometric.estimate_depth

    def spy(model, images, intrinsics, poses, depth_range, sparse_depth, device):
        seen[stage[0]].append((poses[0].tobytes(), sparse_depth.copy()))
        return real(model, images, intrinsics, poses, depth_range, sparse_depth, device)

    monkeypatch.setattr(stereo_photometric, "estimate_depth", spy)
    cfg = stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3, max_image_size=64,
                       min_confidence=0.0, network_scale=0.5, network_min_size=16, geom_max_depth_error=0.5,
                       geom_max_reproj_error=50.0, geom_min_visibility=0.0, geom_fill=False)
    run_stereo(cfg)
    assert seen["geometric"] == []
    stage[0] = "geometric"
    res = run_stereo(replace_config(cfg, geom_reestimate=True))
    names = sorted(res.geometric_processed)
    assert res.processed == [] and len(names) == 4 and len(seen["geometric"]) == 4  # one run per reference
    assert "geometric.reestimate_network" in res.timings
    sfm_only = dict(seen["photometric"])
    for pose, hints in seen["geometric"]:
        assert hints.shape == sfm_only[pose].shape == (24, 32)
        # the loose check keeps most pixels: dense hints where the SfM points left gaps, SfM hints kept
        assert (hints > 0).mean() > (sfm_only[pose] > 0).mean() + 0.05
        assert np.all(hints[sfm_only[pose] > 0] > 0)
    ws_obj, _ = load_workspace(ws)
    for name in names:
        assert read_depth_map(ws_obj.depth_map_path(name, "geometric")).shape == (48, 64)


def test_prior_blend_and_agreement_in_the_photometric_pass(synthetic_ws, tmp_path, tiny_checkpoint,
                                                           monkeypatch):
    """A flat image takes the sparse prior's depth; a network far from the prior loses its confidence, and
    every score is times the local plane's factor."""
    from colmap_pvs.prior import upsample_prior
    from colmap_pvs.stereo.config import PLANE_RESIDUAL_SCALE, PLANE_RESIDUAL_WINDOW

    ws = _copy(synthetic_ws, tmp_path)
    real = stereo_photometric.estimate_depth

    def flat_and_off(model, images, intrinsics, poses, depth_range, sparse_depth, device):
        depth, conf, vis, prior = real(model, images, intrinsics, poses, depth_range, sparse_depth, device)
        assert prior is not None
        images[0][...] = 0.5  # the texture weight is read from these pixels after the network
        h, w = images.shape[-2:]
        off = 2.0 * upsample_prior(prior, (w, h), (w, h))  # the "network": twice the prior's depth
        return off.astype(np.float32), np.ones_like(conf), vis, prior

    monkeypatch.setattr(stereo_photometric, "estimate_depth", flat_and_off)
    cfg = stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3, max_image_size=64,
                       min_confidence=0.0, sparse_prior="on", geom_consistency=False)
    res = run_stereo(cfg)
    names = sorted(res.processed)
    assert names and "prior_blend" in res.timings
    ws_obj, _ = load_workspace(ws)

    def maps():
        return {n: (read_depth_map(ws_obj.depth_map_path(n, "photometric")),
                    read_array(ws_obj.confidence_map_path(n, "photometric"))) for n in names}

    on = maps()
    # both are photometric settings: turned off, the maps are recomputed from the network alone
    again = run_stereo(replace_config(cfg, prior_blend_texture=0.0, prior_agreement_scale=0.0))
    assert sorted(again.processed) == names and "prior_blend" not in again.timings
    for name, (depth_off, conf_off) in maps().items():
        depth_on, conf_on = on[name]
        has = (depth_on > 0) & (depth_off > 0)
        assert has.mean() > 0.9
        # flat image: the prior's depth, half the network's
        np.testing.assert_allclose(depth_off[has], 2.0 * depth_on[has], rtol=1e-4)
        # a factor 2 from the prior: exp(-ln 2 / 0.05) ~ 1e-6 of the network's confidence (1)
        assert conf_on[has].max() < 1e-5
        # without the prior: the network's confidence times the local plane's factor (docs/CONVENTIONS.md)
        # (where the whole window is valid: the pass drops pixels without a normal after the factor)
        k = PLANE_RESIDUAL_WINDOW
        padded = np.pad(depth_off > 0, k // 2)
        full = np.lib.stride_tricks.sliding_window_view(padded, (k, k)).all(axis=(-1, -2)) & has
        assert full.mean() > 0.5
        plane = np.exp(-plane_residual(depth_off, k) / PLANE_RESIDUAL_SCALE)
        np.testing.assert_allclose(conf_off[full], plane[full], rtol=1e-5)
        assert plane[full].min() < 0.99  # (the factor is not all ones here)


def test_completion_score_falls_where_its_depth_leaves_a_local_plane(synthetic_ws, tmp_path, tiny_checkpoint,
                                                                     monkeypatch):
    """The completion's score is its tiers' times the local plane's factor of the completed depth."""
    assert (COMPLETION_RESIDUAL_WINDOW, COMPLETION_RESIDUAL_SCALE) == (21, 0.05)  # docs/CONVENTIONS.md

    def completions(factor: bool) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        ws = _copy(synthetic_ws, tmp_path / ("on" if factor else "off"))
        if not factor:
            monkeypatch.setattr(stereo_filled, "COMPLETION_RESIDUAL_SCALE", float("inf"))
        cfg = stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3, max_image_size=64,
                           min_confidence=0.0)
        names = sorted(run_stereo(cfg).filled_processed)
        ws_obj, _ = load_workspace(ws)
        return {n: (read_depth_map(ws_obj.depth_map_path(n, "filled")),
                    read_array(ws_obj.confidence_map_path(n, "filled"))) for n in names}

    on, off = completions(True), completions(False)
    assert sorted(on) == sorted(off) and len(on) >= 3
    lowered = supported = 0
    for name, (depth, conf) in on.items():
        depth_off, conf_off = off[name]
        np.testing.assert_array_equal(depth, depth_off)  # the depth is the same: only the score changes
        factor = np.exp(-plane_residual(depth, COMPLETION_RESIDUAL_WINDOW) / COMPLETION_RESIDUAL_SCALE)
        has = conf_off > 0  # the supported pixels (0 marks the others in both)
        np.testing.assert_array_equal(conf > 0, has)
        np.testing.assert_allclose(conf[has], (conf_off * factor)[has], rtol=1e-5, atol=1e-9)
        supported += int(has.sum())
        lowered += int((factor[has] < 0.99).sum())
    assert supported > 200 and lowered > 0, (supported, lowered)  # (the factor is not all ones here)


@pytest.mark.parametrize("stage", ["photometric", "geometric"])
def test_rewritten_pass_interrupted_before_its_depth_is_not_done(tmp_path, monkeypatch, stage):
    """An overwrite that dies after the new provenance but before the new depth must not look done
    (the old depth beside the new provenance would)."""
    from colmap_pvs.io.workspace import Workspace

    ws = Workspace(tmp_path)
    for sub in ("depth_maps", "normal_maps", "confidence_maps", "provenance", "visibility_maps"):
        (ws.stereo_dir / sub).mkdir(parents=True)
    depth = np.full((6, 8), 2.0, np.float32)
    normals = np.tile(np.array([0.0, 0.0, -1.0], np.float32), (6, 8, 1))
    conf = np.full((6, 8), 0.5, np.float32)

    def write(settings):
        maps = PassMaps(depth, conf, normals)
        ref = Reference.of(ws, "a.png", depth_range=(1.0, 3.0))
        ref = ref.with_pass(stage, maps, PassRecord(settings, {}))
        stereo_outputs.write_pass(ref, previews=False, timer=Timer())

    old, new = {"v": 1}, {"v": 2}
    write(old)
    out = Reference.of(ws, "a.png").paths[stage]
    assert stereo_outputs.is_current(out, stereo_outputs.fingerprint(old), (8, 6))

    import os

    real_replace = os.replace

    def dies(src, dst):  # every new file is written; the run dies as the new depth is renamed into place
        if Path(dst) == ws.depth_map_path("a.png", stage):
            raise OSError("killed")
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", dies)
    with pytest.raises(OSError):
        write(new)
    assert stereo_outputs.read_provenance(ws, "a.png", stage)["settings"] == new  # renamed before it
    assert not stereo_outputs.is_current(out, stereo_outputs.fingerprint(new), (8, 6))
    assert not stereo_outputs.is_current(out, stereo_outputs.fingerprint(old), (8, 6))


def test_select_views_wide_sources_reach_stereo_through_patch_match_cfg(analytic_scene, tmp_path,
                                                                       tiny_checkpoint):
    # select-views --wide_sources picks the same sources as the view selection with that setting, which
    # differ from the default's on this scene (N = 3: 1 of the 2 sources wide); stereo reads them from
    # the patch-match.cfg it wrote
    from colmap_pvs.io.workspace import read_patch_match_cfg
    from colmap_pvs.views import ViewSelectionConfig, select_views

    ws = _copy(analytic_scene["root"], tmp_path)
    _, model = load_workspace(ws)
    expected = {
        wide: {name: ref.source_names for name, ref in select_views(
            model, ViewSelectionConfig(num_views=3, wide_sources=wide)).references.items()}
        for wide in (0, 1)
    }
    assert expected[0] != expected[1]
    cfg_path = ws / "stereo" / "patch-match.cfg"
    for wide in (0, 1):
        assert main(["select-views", "--workspace_path", str(ws), "--num_views", "3",
                     "--wide_sources", str(wide)]) == 0
        written = {name: spec.names for name, spec in read_patch_match_cfg(cfg_path).items()}
        assert written == expected[wide]
        ctx = stereo_module.prepare_stereo(stereo_config(
            workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3))
        try:
            chosen = {name: tuple(ctx.sources_of(name)[0]) for name in ctx.references}
        finally:
            ctx.close()
        assert chosen == expected[wide]


def test_previews_on_a_finished_workspace_are_written_without_recomputing(synthetic_ws, tmp_path,
                                                                          tiny_checkpoint):
    """``--previews`` is an output-only option: a rerun that only adds it writes the previews of every
    pass from the maps on disk and recomputes nothing (maps and provenance stay as they were). With a
    calibrated checkpoint, each confidence preview is on the calibration's scale ("P(depth within
    10 %)", the tolerance read from the provenance), and every depth and confidence preview has the
    map's size plus the colour bar below it."""
    from colmap_pvs.io.maps import BAR_HEIGHT, save_confidence_preview

    ws = _copy(synthetic_ws, tmp_path)
    checkpoint = tmp_path / "model" / "tiny.pt"
    checkpoint.parent.mkdir()
    shutil.copy(tiny_checkpoint, checkpoint)
    curve = {"score": [0.0, 1.0], "prob": [0.0, 1.0]}
    (checkpoint.parent / "tiny.calibration.json").write_text(json.dumps(
        {"tolerance": 0.1, "curves": {"photometric": curve, "geometric": curve}, "fit": {}}))
    cfg = stereo_config(workspace_path=ws, checkpoint=checkpoint, num_views=3, max_image_size=48,
                        geom_min_consistent=1)
    first = run_stereo(cfg)
    assert first.processed and not (ws / "stereo" / "previews").exists()
    stereo = ws / "stereo"
    before = {p: p.read_bytes() for d in ("depth_maps", "provenance") for p in (stereo / d).rglob("*")}
    res = run_stereo(replace_config(cfg, previews=True))
    assert not res.processed and not res.geometric_processed and not res.filled_processed
    assert sorted(res.already_done) == sorted(first.processed)
    assert {p: p.read_bytes() for p in before} == before
    for name in first.processed:
        for stage in ("photometric", "geometric", "filled"):
            assert preview_path(load_workspace(ws)[0], name, stage).is_file()
        assert (stereo / "previews" / f"{name}.normal.png").is_file()
        assert list((stereo / "previews").glob(f"{name}.visibility.*.png"))
    # They are the previews a run with --previews from the start writes: the same depth range (the
    # view selection's) and colours.
    ws_at_once = _copy(synthetic_ws, tmp_path / "at_once")
    run_stereo(replace_config(cfg, workspace_path=ws_at_once, previews=True))
    for name in first.processed:
        for stage in ("photometric", "geometric"):
            late = preview_path(load_workspace(ws)[0], name, stage)
            at_once = preview_path(load_workspace(ws_at_once)[0], name, stage)
            assert at_once.is_file()
            np.testing.assert_array_equal(cv2.imread(str(late)), cv2.imread(str(at_once)), err_msg=str(late))
            conf = read_array(ws / "stereo" / "confidence_maps" / f"{name}.{stage}.bin")
            assert cv2.imread(str(late)).shape == (conf.shape[0] + BAR_HEIGHT, conf.shape[1], 3)
            expected = save_confidence_preview(tmp_path / "expected.png", conf, 0.1).read_bytes()
            assert expected != save_confidence_preview(tmp_path / "raw.png", conf, None).read_bytes()
            for folder in (ws, ws_at_once):
                conf_preview = preview_path(load_workspace(folder)[0], name, stage)
                conf_preview = conf_preview.with_name(conf_preview.name.replace(".depth.", ".confidence."))
                assert conf_preview.read_bytes() == expected, conf_preview


def test_colmaps_own_maps_are_kept_beside_ours(synthetic_ws, tmp_path, tiny_checkpoint, caplog):
    """Depth and normal maps in the workspace that colmap-pvs did not write (COLMAP's patch_match_stereo
    output: no provenance) are kept as ``NAME.KIND.bin.bak`` before ours replace them, with one WARNING
    for the workspace; our own maps are replaced silently on a rerun."""
    from colmap_pvs.io.maps import write_depth_map, write_normal_map

    ws = _copy(synthetic_ws, tmp_path)
    names = sorted(p.name for p in (ws / "images").iterdir())
    maps = ws / "stereo"
    for name in names:
        for kind in ("photometric", "geometric"):
            write_depth_map(maps / "depth_maps" / f"{name}.{kind}.bin", np.full((5, 7), 2.0, np.float32))
            write_normal_map(maps / "normal_maps" / f"{name}.{kind}.bin",
                             np.tile(np.array([0, 0, -1], np.float32), (5, 7, 1)))
    theirs = {p: p.read_bytes() for p in maps.rglob("*.bin")}
    cfg = stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3, max_image_size=48,
                        geom_min_consistent=1)
    with caplog.at_level("WARNING", logger="colmap_pvs"):
        res = run_stereo(cfg)
    assert sorted(res.processed) == names
    for path, data in theirs.items():
        assert path.with_name(path.name + ".bak").read_bytes() == data
        if "depth_maps" in path.parts:  # ours in their place
            assert read_depth_map(path).shape == (36, 48)
    assert sum("did not write" in r.getMessage() for r in caplog.records) == 1
    caplog.clear()
    run_stereo(replace_config(cfg, overwrite=True))
    assert not list(maps.rglob("*.bak.bak")) and not any("did not write" in r.getMessage()
                                                          for r in caplog.records)


def _edit_model(ws: Path, *, camera_of: str | None = None, pose_of: str | None = None) -> None:
    """Scale the focal length of ``camera_of``'s camera by 5 %; move ``pose_of``'s camera slightly."""
    model = read_sparse_model(ws / "sparse")
    cameras, images = dict(model.cameras), dict(model.images)
    if camera_of is not None:
        cam = model.camera_of(model.image_by_name(camera_of))
        params = cam.params.copy()
        params[:2] *= 1.05
        K = cam.K.copy()
        K[0, 0], K[1, 1] = params[0], params[1]
        cameras[cam.camera_id] = dataclasses.replace(cam, params=params, K=K)
    if pose_of is not None:
        im = model.image_by_name(pose_of)
        pose = im.cam_from_world.copy()
        pose[:, 3] += 0.01
        images[im.image_id] = dataclasses.replace(im, cam_from_world=pose)
    write_sparse_model(dataclasses.replace(model, cameras=cameras, images=images), ws / "sparse")


def test_maps_follow_image_pixels_cameras_and_poses_with_one_line_per_pass(synthetic_ws, tmp_path,
                                                                           tiny_checkpoint, caplog):
    ws = _copy(synthetic_ws, tmp_path)
    cfg = stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=2, max_image_size=32,
                        geom_fill=False)
    first = run_stereo(cfg)
    names = sorted(first.processed)
    assert len(names) == 4 and run_stereo(cfg).processed == []
    # a third of one photo painted over (same size, same name)
    path = ws / "images" / names[0]
    image = cv2.imread(str(path))
    image[:, : image.shape[1] // 3] = (0, 0, 255)
    cv2.imwrite(str(path), image)
    caplog.set_level("INFO", logger="colmap_pvs")
    caplog.clear()
    res = run_stereo(cfg)
    users = sorted(n for n in names if names[0] in res.sources[n])  # the references that read it
    assert sorted(res.processed) == sorted({names[0], *users})
    assert set(res.processed) <= set(res.geometric_processed)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("stereo photometric:")]
    assert len(lines) == 1, lines
    assert f"image pixels changed: {names[0]}" in lines[0]
    assert "source pixels changed" in lines[0] or not users
    assert lines[0].endswith(f"{4 - len(res.processed)} already done, 0 skipped")
    assert any(r.getMessage().startswith(f"stereo geometric: {len(res.geometric_processed)} computed (its "
                                         f"photometric maps changed: {names[0]}") for r in caplog.records)
    # a focal length 5 % longer, then a pose moved
    _edit_model(ws, camera_of=names[1])
    res = run_stereo(cfg)
    assert sorted(res.processed) == sorted({names[1], *(n for n in names if names[1] in res.sources[n])})
    prov = json.loads((ws / "stereo" / "provenance" / f"{names[1]}.photometric.json").read_text())
    assert prov["settings"]["camera"]["params"][0] == pytest.approx(
        read_sparse_model(ws / "sparse").camera_of(read_sparse_model(ws / "sparse").image_by_name(
            names[1])).params[0])
    assert run_stereo(cfg).processed == []
    _edit_model(ws, pose_of=names[2])
    caplog.clear()
    res = run_stereo(cfg)
    assert sorted(res.processed) == sorted({names[2], *(n for n in names if names[2] in res.sources[n])})
    assert names[2] in res.geometric_processed
    line = next(r.getMessage() for r in caplog.records if r.getMessage().startswith("stereo photometric:"))
    assert f"depth range, pose changed: {names[2]}" in line, line


def test_num_views_that_patch_match_cfg_overrides_is_said_once_and_recomputes_nothing(
        synthetic_ws, tmp_path, tiny_checkpoint, caplog):
    from colmap_pvs.views.step import SelectViewsConfig, run_select_views

    ws = _copy(synthetic_ws, tmp_path)
    run_select_views(SelectViewsConfig(workspace_path=ws, num_views=2))  # explicit lists of 1 source
    cfg = stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=2, max_image_size=32,
                        geom_consistency=False)
    caplog.set_level("WARNING", logger="colmap_pvs")
    first = run_stereo(cfg)
    names = sorted(first.processed)
    assert len(names) == 4 and not [r for r in caplog.records if "decides the sources" in r.getMessage()]
    caplog.clear()
    res = run_stereo(replace_config(cfg, num_views=3))
    assert res.processed == [] and sorted(res.already_done) == names  # the same sources: nothing to redo
    notes = [r.getMessage() for r in caplog.records if "decides the sources" in r.getMessage()]
    assert len(notes) == 1 and "patch-match.cfg decides the sources of 4 of 4 reference(s) (1 each), not " \
        "--num_views 3" in notes[0] and "colmap-pvs select-views" in notes[0] and "--num_views 3" in notes[0]
    prov = json.loads((ws / "stereo" / "provenance" / f"{names[0]}.photometric.json").read_text())
    assert "num_views" not in prov["settings"] and len(prov["sources"]) == 1
    assert prov["sources_from"] == "stereo/patch-match.cfg (its source list)"
    # __auto__: num_views applies (up to N), and more sources recompute
    (ws / "stereo" / "patch-match.cfg").write_text("".join(f"{n}\n__auto__, 3\n" for n in names))
    caplog.clear()
    res = run_stereo(replace_config(cfg, num_views=3))
    assert sorted(res.processed) == names and all(len(res.sources[n]) == 2 for n in names)
    assert not [r for r in caplog.records if "decides the sources" in r.getMessage()]


def test_a_fixed_depth_range_is_every_references_range(synthetic_ws, tiny_checkpoint):
    """``--depth_range`` (COLMAP's depth_min/depth_max) replaces each reference's range from its points."""
    ctx = stereo_context.prepare_stereo(stereo_config(workspace_path=synthetic_ws, checkpoint=tiny_checkpoint,
                                                      depth_range=[0.5, 9]))
    assert ctx.selection.references
    assert {entry.depth_range for entry in ctx.selection.references.values()} == {(0.5, 9.0)}


def test_depth_near_factor_moves_every_references_near_end(synthetic_ws, tiny_checkpoint):
    """``--depth_near_factor`` reaches the view selection: the near end moves, the far end stays."""
    flags = dict(workspace_path=synthetic_ws, checkpoint=tiny_checkpoint)
    base = stereo_context.prepare_stereo(stereo_config(**flags)).selection.references
    half = stereo_context.prepare_stereo(stereo_config(**flags, depth_near_factor=0.5)).selection.references
    assert base and set(half) == set(base)
    for name, entry in base.items():
        assert half[name].depth_range == pytest.approx((0.5 * entry.depth_range[0], entry.depth_range[1]))
    with pytest.raises(ConfigError, match="depth_near_factor"):
        stereo_config(**flags, depth_near_factor=0.0)


def test_a_failed_overwrite_keeps_the_old_maps(synthetic_ws, tmp_path, tiny_checkpoint, monkeypatch):
    """A disk that fills up during `stereo --overwrite` had already cost the old photometric maps: each
    pass's new files are now written beside the old ones first, and the old go only once all are written."""
    import errno

    import colmap_pvs.io.files as files_module
    from colmap_pvs.errors import OutputError

    ws = _copy(synthetic_ws, tmp_path)
    flags = dict(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3, max_image_size=64,
                 geom_fill=False)
    run_stereo(stereo_config(**flags))
    before = {p: p.read_bytes() for p in (ws / "stereo").rglob("*") if p.is_file()}
    real = files_module.tempfile.mkstemp

    def full(*args, **kwargs):
        if Path(kwargs["dir"]).name == "normal_maps":
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(*args, **kwargs)

    monkeypatch.setattr(files_module.tempfile, "mkstemp", full)
    with pytest.raises(OutputError, match="No space left on device"):
        run_stereo(stereo_config(**flags, overwrite=True, min_confidence=0.5))
    monkeypatch.undo()
    after = {p: p.read_bytes() for p in (ws / "stereo").rglob("*") if p.is_file()}
    run_record = ws / "stereo" / stereo_config_module.CONFIG_FILENAME  # the last run's settings
    assert after.keys() == before.keys()  # no temporary file left
    assert {p for p in after if after[p] != before[p]} == {run_record}  # every map and provenance kept
    assert run_stereo(stereo_config(**flags, overwrite=True, min_confidence=0.5)).processed


def test_the_geometric_too_close_warning_lists_a_source_that_sees_nothing_at_angle_0(caplog):
    """Each source's median triangulation angle over the reference's pixels it checks; 0 for a source
    that checks none of them."""
    from types import SimpleNamespace

    from colmap_pvs.consistency import SourceMaps

    ctx = SimpleNamespace(config=SimpleNamespace(geometric=SimpleNamespace(min_triangulation_angle=5.0)))
    ref = SourceMaps(np.ones((4, 4), np.float32), None, np.eye(3), np.eye(4)[:3])
    checked = np.zeros((2, 4, 4), bool)
    checked[0] = True
    res = SimpleNamespace(checked=checked, angle=np.full((2, 4, 4), 2.0, np.float32))
    with caplog.at_level("WARNING", logger="colmap_pvs.stereo"):
        stereo_geometric._warn_if_every_source_is_too_close(ctx, "r.png", ["a.png", "b.png"], ref, res)
    assert "(median angles: a.png 2, b.png 0)" in caplog.text


def test_the_geometric_too_close_warning_needs_a_reference_depth_and_sources(caplog):
    """No warning for a reference without any depth (nothing to confirm, whatever the angles) or
    without sources (nothing to list)."""
    from types import SimpleNamespace

    from colmap_pvs.consistency import SourceMaps

    ctx = SimpleNamespace(config=SimpleNamespace(geometric=SimpleNamespace(min_triangulation_angle=5.0)))
    empty = SourceMaps(np.zeros((4, 4), np.float32), None, np.eye(3), np.eye(4)[:3])
    res = SimpleNamespace(checked=np.ones((2, 4, 4), bool), angle=np.full((2, 4, 4), 2.0, np.float32))
    full = SourceMaps(np.ones((4, 4), np.float32), None, np.eye(3), np.eye(4)[:3])
    with caplog.at_level("WARNING", logger="colmap_pvs.stereo"):
        stereo_geometric._warn_if_every_source_is_too_close(ctx, "r.png", ["a.png", "b.png"], empty, res)
        stereo_geometric._warn_if_every_source_is_too_close(ctx, "r.png", [], full, res)
    assert caplog.text == ""
    # any positive limit warns (here 0.5 degrees, above every source's 0.2), 0 never
    low = SimpleNamespace(checked=res.checked, angle=np.full((2, 4, 4), 0.2, np.float32))
    for limit, warned in ((0.5, True), (0.0, False)):
        ctx.config.geometric.min_triangulation_angle = limit
        caplog.clear()
        with caplog.at_level("WARNING", logger="colmap_pvs.stereo"):
            stereo_geometric._warn_if_every_source_is_too_close(ctx, "r.png", ["a.png", "b.png"], full, low)
        assert ("(median angles: a.png 0.2, b.png 0.2)" in caplog.text) == warned, limit
    ctx.config.geometric.min_triangulation_angle = 0.1  # a source at 0.2 degrees is far enough
    caplog.clear()
    with caplog.at_level("WARNING", logger="colmap_pvs.stereo"):
        stereo_geometric._warn_if_every_source_is_too_close(ctx, "r.png", ["a.png", "b.png"], full, low)
    assert caplog.text == ""


def test_geometric_seeds_need_enough_strictly_agreeing_sources_and_a_normal():
    """The completion's seeds: pixels that ``geom_seed_min_consistent`` sources confirm within
    ``geom_seed_depth_error``, at their own or the averaged depth; isolated ones (no normal) and the rest
    0."""
    from types import SimpleNamespace

    from colmap_pvs.consistency import SourceMaps

    h = w = 24
    K = np.array([[20.0, 0, 12], [0, 20.0, 12], [0, 0, 1]])
    ref = SourceMaps(np.full((h, w), 2.0, np.float32), None, K, np.eye(4)[:3])
    agree = np.zeros((3, h, w), bool)
    error = np.full((3, h, w), 0.01, np.float32)
    agree[:, 2:12, 2:12] = True  # three sources within 1 %: seeds (where the block gives a normal)
    agree[:2, 14:22, 2:12] = True  # two sources: not enough
    agree[:, 14:22, 14:22] = True
    error[:, 14:22, 14:22] = 0.03  # three sources, but beyond 2.5 %
    agree[:, 4, 18] = True  # one isolated pixel: no normal
    res = SimpleNamespace(agree=agree, depth_error=error, mean_depth=lambda d: np.full_like(d, 2.02))
    for average, depth in ((False, 2.0), (True, 2.02)):
        cfg = SimpleNamespace(geometric=SimpleNamespace(seed_depth_error=0.025, seed_min_consistent=3,
                                                        average_depth=average))
        seeds = stereo_geometric._seeds(cfg, ref, res)
        assert seeds.dtype == np.float32 and seeds[6, 6] == np.float32(depth)
        assert set(np.unique(seeds)) == {0.0, np.float32(depth)}
        outside = np.ones((h, w), bool)
        outside[2:12, 2:12] = False
        assert not seeds[outside].any()  # the isolated pixel included


def test_a_geometric_check_is_reused_only_under_its_own_fingerprint():
    """The check another reference's pass made is reused (a copy) only under the same seed fingerprint:
    one that sorts before or after it (other settings) or seeds alone (read from disk) are not."""
    from types import SimpleNamespace

    seeds, depth, conf = (np.full((2, 3), v, np.float32) for v in (1.0, 2.0, 0.5))
    ctx = SimpleNamespace(seed_cache={"a.png": ("5" * 64, stereo_geometric.Checked(seeds, depth, conf))},
                          seed_lock=threading.Lock())
    for other in ("4" * 64, "6" * 64):
        assert stereo_geometric._reused_check(ctx, "a.png", other, Timer()) is None
    reused = stereo_geometric._reused_check(ctx, "a.png", "5" * 64, Timer())
    np.testing.assert_array_equal(reused.depth, depth)
    np.testing.assert_array_equal(reused.conf, conf)
    assert reused.depth is not depth and reused.conf is not conf
    ctx.seed_cache["a.png"] = ("5" * 64, stereo_geometric.Checked(seeds))
    assert stereo_geometric._reused_check(ctx, "a.png", "5" * 64, Timer()) is None


def test_the_seed_cache_keeps_the_most_recently_used(monkeypatch):
    """At most ``SEED_CACHE_SIZE`` seed maps are kept: the least recently stored one goes first."""
    from collections import OrderedDict
    from types import SimpleNamespace

    monkeypatch.setattr(stereo_geometric, "SEED_CACHE_SIZE", 2)
    ctx = SimpleNamespace(seed_cache=OrderedDict(), seed_lock=threading.Lock())
    checked = stereo_geometric.Checked(np.zeros((2, 3), np.float32))
    for name, kept in (("a", "a"), ("b", "ab"), ("c", "bc"), ("b", "cb"), ("d", "bd")):
        stereo_geometric._remember_seeds(ctx, name, "f", checked)
        assert "".join(ctx.seed_cache) == kept, name


def test_a_reference_whose_sources_are_all_too_close_is_named_in_a_warning(synthetic_ws, tmp_path,
                                                                             tiny_checkpoint, caplog):
    """Sources all below geom_min_triangulation_angle give an empty geometric map: a WARNING names the
    image, the angles and what to do (no warning at the default angle)."""
    ws = _copy(synthetic_ws, tmp_path)
    flags = dict(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3, max_image_size=64,
                 geom_fill=False)
    with caplog.at_level("WARNING", logger="colmap_pvs.stereo"):
        run_stereo(stereo_config(**flags, geom_min_triangulation_angle=89))
    warned = [r.getMessage() for r in caplog.records if "geom_min_triangulation_angle" in r.getMessage()]
    _, model = load_workspace(ws)
    names = sorted(im.name for im in model.images.values())
    assert len(warned) == len(names) and all(any(repr(n) in m for m in warned) for n in names)
    assert "median angles:" in warned[0] and "lower --geom_min_triangulation_angle" in warned[0]
    for name in names:
        assert not read_depth_map(ws / "stereo" / "depth_maps" / f"{name}.geometric.bin").any()
    caplog.clear()
    with caplog.at_level("WARNING", logger="colmap_pvs.stereo"):
        run_stereo(stereo_config(**flags, overwrite=True))
    assert "geom_min_triangulation_angle" not in caplog.text


def test_a_record_of_an_older_colmap_pvs_is_named_as_such(synthetic_ws, tmp_path, tiny_checkpoint, caplog):
    """A record without the images' hashes recomputes once, saying why (not "depth range changed")."""
    ws = _copy(synthetic_ws, tmp_path)
    cfg = stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=2, max_image_size=32,
                        geom_consistency=False)
    names = sorted(run_stereo(cfg).processed)
    record = ws / "stereo" / "provenance" / f"{names[0]}.photometric.json"
    old = json.loads(record.read_text())
    for key in ("image_sha256", "source_image_sha256", "camera", "source_cameras", "pose", "source_poses"):
        del old["settings"][key]
    old["settings"]["depth_range"] = [v * (1 + 1e-12) for v in old["settings"]["depth_range"]]  # unrounded
    old["fingerprint"] = stereo_outputs.fingerprint(old["settings"])
    record.write_text(json.dumps(old))
    caplog.set_level("INFO", logger="colmap_pvs")
    assert run_stereo(cfg).processed == [names[0]]
    line = next(r.getMessage() for r in caplog.records if r.getMessage().startswith("stereo photometric:"))
    assert f"recorded by an older colmap-pvs (without the images' hashes): {names[0]}" in line, line


def test_references_in_threads_write_the_same_maps_and_check_each_image_once(synthetic_ws, tmp_path,
                                                                             tiny_checkpoint, monkeypatch):
    """The geometric and completion passes run two references at once (``REFERENCE_THREADS``, in the pass's
    own threads): every map is the same bytes as one reference at a time, and each image's photometric maps
    are still checked once (its own pass and the other references' seeds share the check)."""
    import collections

    import torch


    real, written = stereo_geometric._check_photometric, {}
    threads_before = torch.get_num_threads()
    try:
        for workers in (1, 2):
            ws = _copy(synthetic_ws, tmp_path / f"workers{workers}")
            checks, threads = collections.Counter(), set()

            def counting(ctx, name, setup, kept=True, checks=checks, threads=threads):
                checks[name] += 1
                threads.add(threading.current_thread().name.rsplit("_", 1)[0])
                return real(ctx, name, setup, kept)

            monkeypatch.setattr(stereo_context, "REFERENCE_THREADS", workers)
            monkeypatch.setattr(stereo_geometric, "_check_photometric", counting)
            run_stereo(stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3,
                                     max_image_size=64, min_confidence=0, threads=2, previews=True))
            # (whether two checks of one image would overlap without the lock is a race: it did in 3 of 3
            # runs here with the lock removed)
            assert len(checks) == 4 and set(checks.values()) == {1}, (workers, checks)
            assert threads == ({"MainThread"} if workers == 1 else {"stereo-geometric"}), threads
            written[workers] = {p.relative_to(ws): p.read_bytes() for p in (ws / "stereo").rglob("*")
                                if p.is_file()}
    finally:
        torch.set_num_threads(threads_before)
    assert written[1].keys() == written[2].keys() and len(written[1]) >= 4 * 7
    # every file: maps, previews, provenance, fusion.cfg; but the run's config, which names the workspace
    differ = [p for p in written[1] if written[1][p] != written[2][p]]
    assert differ == [Path("stereo/colmap_pvs_stereo.json")]


def test_an_auxiliary_sources_check_makes_only_its_seeds(synthetic_ws, tmp_path, tiny_checkpoint,
                                                         monkeypatch):
    """A source that is no reference of the run has no geometric pass: the check that makes its seeds
    (for the references' splatted pixels) skips the kept pixels and their confidence, which only a
    reference's own pass reads; a reference's check made for another's seeds keeps them for reuse."""
    ws = _copy(synthetic_ws, tmp_path)
    _, model = load_workspace(ws)
    names = sorted(im.name for im in model.images.values())
    refs = names[:2]
    write_patch_match_cfg(ws / "stereo" / "patch-match.cfg", {r: [n for n in names if n != r] for r in refs})
    real, calls = stereo_geometric._check_photometric, []

    def recording(ctx, name, setup, kept=True):
        calls.append((name, kept))
        return real(ctx, name, setup, kept)

    monkeypatch.setattr(stereo_geometric, "_check_photometric", recording)
    res = run_stereo(stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=4,
                                   max_image_size=64, min_confidence=0))
    assert sorted(res.processed) == refs and sorted(res.auxiliary) == names[2:]
    assert sorted(res.geometric_processed) == refs
    checked = dict(calls)
    assert len(calls) == len(checked) == len(names), calls  # every image checked once
    assert {n for n, kept in checked.items() if not kept} == set(names[2:]), calls


def test_references_run_at_once_only_in_the_passes_and_sizes_that_allow_it(monkeypatch):
    """Two references at once in the geometric pass and the completion, never in the photometric pass
    or the confirmation, never with a network inside the geometric pass, never beyond torch's threads
    or above ``REFERENCE_THREADS_MAX_PIXELS`` (or at full image size)."""
    import torch

    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    ref_threads = stereo_context.reference_threads
    config = stereo_config_module.StereoConfig(workspace_path="w")
    assert [ref_threads(config, s) for s in ("photometric", "geometric", "filled", "confirm")] == [1, 2, 2, 1]
    reestimate = dataclasses.replace(config, geometric=dataclasses.replace(config.geometric, reestimate=True))
    assert [ref_threads(reestimate, s) for s in ("geometric", "filled")] == [1, 2]
    for size, expected in ((1024, 2), (1025, 1), (0, 1), (-1, 1)):
        sized = dataclasses.replace(config, photometric=dataclasses.replace(config.photometric,
                                                                             max_image_size=size))
        assert ref_threads(sized, "geometric") == expected, size
    monkeypatch.setattr(torch, "get_num_threads", lambda: 1)
    assert ref_threads(config, "geometric") == 1


def test_a_failing_reference_stops_the_pass_and_the_queued_ones_never_start(synthetic_ws, tmp_path,
                                                                             tiny_checkpoint, monkeypatch):
    """An error in one reference of a pass run in threads is raised, and the references still queued are
    cancelled, not run."""
    import time

    import colmap_pvs.stereo.local as local_module

    ws = _copy(synthetic_ws, tmp_path)
    run_stereo(stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, num_views=3, max_image_size=48,
                             geom_consistency=False))
    ctx = stereo_context.prepare_stereo(stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint,
                                                      num_views=3, max_image_size=48, threads=2))
    names, started, never = list(ctx.references), [], threading.Event()

    def fake(ctx, name, stage):
        started.append(name)
        if name == names[0]:
            time.sleep(0.2)
            raise RuntimeError(f"broken {name}")
        never.wait(1.0)  # busy while the first one fails
        return stereo_context.RefOutcome(name, stage, "computed")

    monkeypatch.setattr(local_module, "process_reference", fake)
    result = stereo_context.StereoResult(workspace=ctx.workspace)
    try:
        with pytest.raises(RuntimeError, match=f"broken {names[0]}"):
            local_module._run_later_pass(ctx, names, "geometric", result, [], set())
    finally:
        ctx.close()
    # the first two start at once; the failed one's thread may take the third before the pass cancels
    # the queue, never the fourth
    assert len(names) == 4 and set(names[:2]) <= set(started) and names[3] not in started
