"""Synthetic training data: sparse simulation, anti-noise source selection, sample dicts, cache, workspace."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import torch

from colmap_pvs.errors import ConfigError, WorkspaceError
from colmap_pvs.geometry import sparse_depth_map
from colmap_pvs.synthetic.cameras import CameraConfig, CameraRig, intrinsics, look_at
from colmap_pvs.synthetic.dataset import (
    SAMPLE_KEYS,
    SyntheticDatasetConfig,
    SyntheticMVSDataset,
    render_views,
    select_sources,
)
from colmap_pvs.synthetic.render import RenderConfig, Renderer
from colmap_pvs.synthetic.scenes import scene_from_primitives
from colmap_pvs.synthetic.sfm import project
from colmap_pvs.synthetic.workspace import SyntheticWorkspaceConfig, make_synthetic_workspace
from colmap_pvs.views import compute_view_scores

W, H = 64, 48


# --------------------------------------------------------------------------- anti-noise selection


@pytest.fixture(scope="module")
def known_overlap_views():
    """A textured ground plane; a reference looking straight down and six sources with known overlap.

    - A, B: ~5 degree triangulation angle, full overlap (best MVSNet score);
    - E, F: ~20 degrees, full overlap (middle);
    - C, D: ~5 degrees but turned away, sharing only a thin strip with the reference (worst).
    """
    scene = scene_from_primitives(
        lambda mesh, material: mesh.add_quad(
            [-30, -30, 0], [60, 0, 0], [0, 60, 0], material(kind="noise", scale=0.3)
        )
    )
    down = [0.0, 1.0, 0.0]  # "up" vector for cameras looking straight down
    poses = {
        "ref": look_at([0, 0, 4], [0, 0, 0], up=down),
        "A": look_at([0.35, 0, 4], [0, 0, 0], up=down),
        "B": look_at([0, 0.35, 4], [0, 0, 0], up=down),
        "E": look_at([1.37, 0, 3.76], [0, 0, 0], up=down),
        "F": look_at([-1.37, 0, 3.76], [0, 0, 0], up=down),
        "C": look_at([-0.35, 0, 4], [4.4, 0, 0], up=down),
        "D": look_at([0, -0.35, 4], [0, -3.4, 0], up=down),
    }
    order = ["ref", "E", "C", "A", "D", "F", "B"]  # not sorted by quality
    K = intrinsics(W, H, 60.0)
    rig = CameraRig(
        K=np.stack([K] * len(order)),
        cam_from_world=np.stack([poses[n] for n in order]),
        roles=("unstructured",) * len(order),
        width=W,
        height=H,
    )
    views = render_views(Renderer(scene), rig, seed=0, render=RenderConfig(supersample=1), num_points=1500)
    return views, order


def test_anti_noise_picks_the_known_best_and_worst_views(known_overlap_views):
    views, order = known_overlap_views
    model = views.sparse_model()
    assert len(model.points) > 300
    ids, scores = compute_view_scores(model)
    assert list(ids) == list(range(1, len(order) + 1))
    row = scores[0].copy()
    row[0] = -np.inf
    best, worst = select_sources(row, "anti_noise", 2, 2)
    assert {order[i] for i in best} == {"A", "B"}
    assert {order[i] for i in worst} == {"C", "D"}
    best4, none = select_sources(row, "best", 2, 2)
    assert {order[i] for i in best4} == {"A", "B", "E", "F"} and none.size == 0
    with pytest.raises(ConfigError, match="'random'"):
        select_sources(row, "random", 2, 2)


def test_select_sources_fills_missing_slots_with_non_overlapping_views():
    row = np.array([-np.inf, 5.0, 0.0, 0.0, 1.0])  # views 2, 3 share nothing with the reference
    best, worst = select_sources(row, "anti_noise", 2, 2)
    assert best.tolist() == [1, 4] and sorted(worst.tolist()) == [2, 3]


def test_sparse_points_tracks_are_visible_and_consistent_with_gt_depth(known_overlap_views):
    views, _ = known_overlap_views
    pts = views.points
    assert np.all(pts.visibility.sum(1) >= 2)
    for v in range(views.num_views):
        uv, z = project(pts.xyz[pts.visibility[:, v]], views.K[v], views.cam_from_world[v])
        assert np.all(z > 0) and np.all((uv >= 0) & (uv < [W, H]))
        sparse = sparse_depth_map(pts.xyz[pts.visibility[:, v]], views.K[v], views.cam_from_world[v], H, W)
        hit = sparse > 0
        rel = np.abs(sparse[hit] - views.depths[v][hit]) / views.depths[v][hit]
        assert np.median(rel) < 0.01  # plane: nearest-pixel GT depth is within the noise and slope


# --------------------------------------------------------------------------- dataset


def _dataset_config(tmp_path, **changes) -> SyntheticDatasetConfig:
    base = dict(
        num_samples=4,
        samples_per_scene=2,
        width=W,
        height=H,
        num_points=500,
        seed=3,
        camera=CameraConfig(num_views=(6, 6), check_width=16, max_attempts=15),
        render=RenderConfig(supersample=1),
        cache_dir=tmp_path / "cache",
    )
    base.update(changes)
    return SyntheticDatasetConfig(**base)


def test_sample_dict_keys_shapes_dtypes_and_depth_range(tmp_path):
    ds = SyntheticMVSDataset(_dataset_config(tmp_path))
    assert len(ds) == 4
    sample = ds[1]
    assert tuple(sample) == SAMPLE_KEYS
    assert sample["images"].shape == (5, 3, H, W) and sample["images"].dtype == torch.float32
    assert 0 <= sample["images"].min() and sample["images"].max() <= 1
    assert sample["intrinsics"].shape == (5, 3, 3) and sample["intrinsics"].dtype == torch.float32
    assert sample["cam_from_world"].shape == (5, 4, 4) and sample["cam_from_world"].dtype == torch.float32
    assert torch.all(sample["cam_from_world"][:, 3] == torch.tensor([0, 0, 0, 1.0]))
    assert sample["depth"].shape == (H, W) and sample["depth"].dtype == torch.float32
    assert sample["sparse_depth"].shape == (1, H, W) and sample["sparse_depth"].dtype == torch.float32
    for key in ("depth_min", "depth_max"):
        assert sample[key].shape == () and sample[key].dtype == torch.float32
    dmin, dmax = float(sample["depth_min"]), float(sample["depth_max"])
    gt = sample["depth"][sample["depth"] > 0]
    assert 0 < dmin < dmax and ((gt >= dmin) & (gt <= dmax)).float().mean() >= 0.85
    info = ds.sample_info(1)
    views = ds.scene_views(info.scene_index)
    assert info.roles[info.reference] in ("video", "unstructured")
    assert len(set(info.sources)) == 4 and info.reference not in info.sources
    torch.testing.assert_close(
        sample["images"][0], torch.from_numpy(views.images[info.reference]).permute(2, 0, 1) / 255.0
    )
    torch.testing.assert_close(sample["depth"], torch.from_numpy(views.depths[info.reference]))
    sparse = sample["sparse_depth"][0]
    hit = sparse > 0
    assert hit.sum() > 10
    rel = (sparse[hit] - sample["depth"][hit]).abs() / sample["depth"][hit].clamp_min(1e-6)
    assert rel.median() < 0.02  # sparse points lie on the GT surfaces (up to noise / pixel quantisation)
    with pytest.raises(IndexError):
        ds[4]


def test_cache_hit_returns_identical_samples_and_survives_corruption(tmp_path, caplog):
    cfg = _dataset_config(tmp_path)
    first = SyntheticMVSDataset(cfg)
    a = first[2]
    assert first.stats["generated"] == 1
    path = first.cache_path(1)
    assert path is not None and path.is_file()
    second = SyntheticMVSDataset(cfg)
    b = second[2]
    assert second.stats == {"generated": 0, "loaded": 1, "generate_s": 0.0}
    for key in SAMPLE_KEYS:
        assert torch.equal(a[key], b[key]), key
    assert first.sample_info(3) == second.sample_info(3)
    path.write_bytes(b"not an npz")
    third = SyntheticMVSDataset(cfg)
    with caplog.at_level(logging.WARNING):
        c = third[2]
    assert "regenerating" in caplog.text and third.stats["generated"] == 1
    assert torch.equal(a["images"], c["images"])
    # a different generation config uses a different cache folder
    assert SyntheticMVSDataset(_dataset_config(tmp_path, width=48)).cache_path(1) != path


def test_best_strategy_and_config_validation(tmp_path):
    ds = SyntheticMVSDataset(
        _dataset_config(
            tmp_path, source_strategy="best", cache_dir=None, num_samples=2, shuffle_sources=False
        )
    )
    info = ds.sample_info(0)
    assert info.worst == () and len(info.best) == 4 and info.sources == info.best
    with pytest.raises(ConfigError, match="fewer than"):
        _dataset_config(tmp_path, num_best=4, num_worst=2)
    with pytest.raises(ConfigError, match="depth_percentiles"):
        _dataset_config(tmp_path, depth_percentiles=(1.0,))


def test_hint_corruption_drops_perturbs_and_is_deterministic(tmp_path):
    clean_ds = SyntheticMVSDataset(_dataset_config(tmp_path))
    cfg = _dataset_config(tmp_path, hint_keep=(0.5, 0.5), hint_noise=0.02, hint_outliers=0.2)
    noisy_ds = SyntheticMVSDataset(cfg)
    assert noisy_ds.cache_path(0) == clean_ds.cache_path(0)  # sampling options keep the scene cache
    clean, noisy = clean_ds[1]["sparse_depth"], noisy_ds[1]["sparse_depth"]
    assert torch.equal(noisy, SyntheticMVSDataset(cfg)[1]["sparse_depth"])  # seeded
    n_clean, kept = int((clean > 0).sum()), noisy > 0
    assert 0.35 * n_clean < int(kept.sum()) < 0.65 * n_clean
    assert torch.all(clean[kept] > 0)  # hints are only dropped, never moved
    ratio = torch.log(noisy[kept] / clean[kept]).abs()
    assert 0.005 < float(ratio.median()) < 0.05  # the 2 % noise
    outliers = float((ratio > 0.1).float().mean())
    assert 0.08 < outliers < 0.3 and float(ratio.max()) <= np.log(1.5) + 0.15
    # Everything else of the sample is unchanged.
    assert torch.equal(clean_ds[1]["images"], noisy_ds[1]["images"])
    with pytest.raises(ConfigError, match="hint_keep"):
        _dataset_config(tmp_path, hint_keep=(0.8, 0.2))


# --------------------------------------------------------------------------- workspace


def test_make_synthetic_workspace_loads_and_sparse_points_lie_on_gt_surfaces(tmp_path):
    out = tmp_path / "ws"
    cfg = SyntheticWorkspaceConfig(width=96, height=72, num_views=4, num_points=600, seed=2)
    summary = make_synthetic_workspace(out, cfg)
    names = summary["image_names"]
    assert len(names) == 4 and summary["path"] == str(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ws"]  # no temporary folders left
    for sub in ("stereo/depth_maps", "stereo/normal_maps", "stereo/consistency_graphs"):
        assert (out / sub).is_dir()
    assert (out / "stereo" / "patch-match.cfg").read_text().splitlines()[:2] == [names[0], "__auto__, 20"]
    assert (out / "stereo" / "fusion.cfg").read_text().split() == names
    meta = json.loads((out / "gt" / "scene.json").read_text())
    assert meta["image_names"] == names and meta["width"] == 96

    from colmap_pvs.io.sparse import read_sparse_model

    model = read_sparse_model(out / "sparse")
    assert sorted(model.image_ids_by_name) == names
    assert len(model.points) == summary["num_points"] > 50
    checked = 0
    for name in names:
        image = model.image_by_name(name)
        cam = model.camera_of(image)
        assert cam.model == "PINHOLE" and (cam.width, cam.height) == (96, 72)
        gt = np.load(out / "gt" / "depth_maps" / f"{name}.npy")
        assert gt.shape == (72, 96) and gt.dtype == np.float32
        rows = np.isin(model.points.ids, image.point3D_ids)
        uv, z = project(model.points.xyz[rows], cam.K, image.cam_from_world)
        col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        g = gt[row, col]
        assert np.all(g > 0)
        rel = np.abs(z - g) / g
        assert np.median(rel) < 0.01
        checked += 1
    assert checked == 4
    with pytest.raises(WorkspaceError, match="already exists"):
        make_synthetic_workspace(out, cfg)
    again = make_synthetic_workspace(
        out,
        SyntheticWorkspaceConfig(width=96, height=72, num_views=4, num_points=600, seed=2, overwrite=True),
    )
    assert again["image_names"] == names
