"""Real training samples from COLMAP models (colmap_pvs.train.real_dataset) and mixed training."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from scenes import render_view
from tiny_models import TINY_PVSNET

from colmap_pvs.config import replace_config
from colmap_pvs.errors import ConfigError, MapFormatError, WorkspaceError
from colmap_pvs.train import TrainConfig, Trainer
from colmap_pvs.train.real_dataset import (
    REAL_SAMPLE_KEYS,
    MixedDataset,
    RealDatasetConfig,
    RealMVSDataset,
    crop_label_map,
    open_scene,
)
from colmap_pvs.train.selfsup import photometric_error

SMALL = dict(width=128, height=96, max_image_size=160, crop_scale=(0.6, 0.9), num_best=2, num_worst=1)


def _dataset(gt: dict, tmp_path: Path, **kw) -> RealMVSDataset:
    return RealMVSDataset(RealDatasetConfig(roots=(gt["root"],), **{**SMALL, **kw}), cache_dir=tmp_path)


def test_sample_layout_and_disjoint_hints_and_labels(analytic_scene, tmp_path):
    ds = _dataset(analytic_scene, tmp_path)
    assert len(ds) == len(analytic_scene["names"])
    s = ds[1]
    assert tuple(s) == REAL_SAMPLE_KEYS
    assert s["images"].shape == s["photo_images"].shape == (4, 3, 96, 128)
    assert s["intrinsics"].shape == (4, 3, 3) and s["cam_from_world"].shape == (4, 4, 4)
    assert s["sparse_depth"].shape == (1, 96, 128) and s["label_depth"].shape == (96, 128)
    assert float(s["is_real"]) == 1.0 and float(s["depth"].abs().sum()) == 0.0
    hints, labels = s["sparse_depth"][0] > 0, s["label_depth"] > 0
    assert int(hints.sum()) > 5 and int(labels.sum()) > 5
    assert not bool((hints & labels).any())
    # jitter changes the network input, never the photometric-loss images
    assert not torch.equal(s["images"], s["photo_images"])
    assert float(s["depth_min"]) < float(s["depth_max"])
    # deterministic in the index
    t = ds[1]
    assert all(torch.equal(s[k], t[k]) for k in REAL_SAMPLE_KEYS)


def test_hint_fraction_extremes(analytic_scene, tmp_path):
    none = _dataset(analytic_scene, tmp_path, hint_fraction=0.0)[0]
    every = _dataset(analytic_scene, tmp_path, hint_fraction=1.0)[0]
    assert float(none["sparse_depth"].sum()) == 0.0 and float(none["label_depth"].sum()) > 0
    assert float(every["label_depth"].sum()) == 0.0 and float(every["sparse_depth"].sum()) > 0


def test_sources_follow_the_anti_noise_strategy(analytic_scene, tmp_path):
    ds = _dataset(analytic_scene, tmp_path, num_best=1, num_worst=1, shuffle_sources=False)
    scene = ds.scenes[0]
    ref = ds.index[2][1]
    row = scene.selection.score_row(ref)
    order = np.argsort(-row)
    cands = [i for i in order if np.isfinite(row[i]) and row[i] > 0]
    s = ds[2]
    model = scene.model
    poses = s["cam_from_world"].numpy()
    expected = [cands[0], cands[-1]]
    for k, idx in enumerate(expected, start=1):
        im = model.image_by_name(scene.selection.names[idx])
        np.testing.assert_allclose(poses[k, :3], im.cam_from_world, atol=1e-5)


def test_crops_keep_the_geometry_exact(analytic_scene, tmp_path):
    """The true depth rendered with the sample's own K and pose explains the cropped images."""
    ds = _dataset(analytic_scene, tmp_path)
    s = ds[3]
    K0 = s["intrinsics"][0].double().numpy()
    pose0 = s["cam_from_world"][0].double().numpy()[:3]
    depth = render_view(analytic_scene["scene"], K0, pose0, 128, 96)["depth"]
    d = torch.as_tensor(depth, dtype=torch.float32)[None]
    args = (s["photo_images"][None], s["intrinsics"][None], s["cam_from_world"][None])
    err, mask = photometric_error(*args, d)
    mask &= d > 0
    wrong, _ = photometric_error(*args, d * 1.15)
    assert float(mask.float().mean()) > 0.3
    assert float(err[mask].mean()) < 0.6 * float(wrong[mask].mean())
    # the hints sit on the true surface
    hints = s["sparse_depth"][0].numpy()
    m = hints > 0
    rel = np.abs(hints[m] - depth[m]) / depth[m]
    assert np.median(rel) < 0.03


def test_pseudo_labels_are_cropped_at_the_ray_of_each_pixel_centre():
    """A map pixel ``(col, row)`` holds the ray of continuous ``(col, row)`` (COLMAP's map convention):
    a ramp map that stores its own column reads back within half a map pixel of each crop pixel's ray."""
    Wm, Hm = 200, 150
    ramp = np.tile(np.arange(Wm, dtype=np.float32), (Hm, 1))
    rows = np.tile(np.arange(Hm, dtype=np.float32)[:, None], (1, Wm))
    window = (13.3, 7.9, 60.0, 45.0)  # in a 100 x 75 image: the map has twice its resolution
    out_u = crop_label_map(ramp, (100, 75), window, 64, 48)
    out_v = crop_label_map(rows, (100, 75), window, 64, 48)
    u = (window[0] + (np.arange(64) + 0.5) * window[2] / 64) * 2.0
    v = (window[1] + (np.arange(48) + 0.5) * window[3] / 48) * 2.0
    assert out_u.shape == (48, 64)
    assert np.abs(out_u - u[None, :]).max() <= 0.5 + 1e-4
    assert np.abs(out_v - v[:, None]).max() <= 0.5 + 1e-4
    # outside the map: the border pixel, never a wrap-around
    edge = crop_label_map(ramp, (100, 75), (90.0, 0.0, 20.0, 15.0), 16, 12)
    assert edge.max() == Wm - 1 and edge.min() >= 179


def test_pseudo_labels_follow_the_crop_geometry(analytic_scene, tmp_path):
    """The workspace's geometric maps (here the true depth) come back as the sample's true depth."""
    ds = _dataset(analytic_scene, tmp_path, pseudo_labels="geometric")
    assert set(ds.scenes[0].pseudo) == set(ds.scenes[0].references)
    for i in (0, 3):
        s = ds[i]
        K0 = s["intrinsics"][0].double().numpy()
        pose0 = s["cam_from_world"][0].double().numpy()[:3]
        truth = render_view(analytic_scene["scene"], K0, pose0, 128, 96)["depth"]
        pseudo = s["pseudo_depth"].numpy()
        m = (pseudo > 0) & (truth > 0)
        assert m.mean() > 0.9
        assert np.median(np.abs(pseudo[m] - truth[m]) / truth[m]) < 0.005
    assert float(_dataset(analytic_scene, tmp_path)[0]["pseudo_depth"].abs().sum()) == 0.0


def test_pseudo_labels_need_the_maps(analytic_scene, tmp_path):
    import shutil

    root = tmp_path / "ws"
    shutil.copytree(analytic_scene["root"], root)
    for f in (root / "stereo" / "depth_maps").glob("*.geometric.bin"):
        f.unlink()
    with pytest.raises(WorkspaceError, match="no geometric depth map"):
        cfg = RealDatasetConfig(roots=(root,), pseudo_labels="geometric", **SMALL)
        RealMVSDataset(cfg, cache_dir=tmp_path)
    with pytest.raises(ConfigError, match="pseudo_labels"):
        RealDatasetConfig(roots=(root,), pseudo_labels="photometric")
    with pytest.raises(WorkspaceError, match="no teacher depth map.*tools/teacher_labels.py"):
        RealMVSDataset(RealDatasetConfig(roots=(root,), pseudo_labels="teacher", **SMALL), cache_dir=tmp_path)


def test_teacher_labels_are_read_like_the_other_pseudo_labels(analytic_scene, tmp_path):
    """``pseudo_labels="teacher"`` reads ``NAME.teacher.bin``; a reference without one gets no label."""
    import shutil

    root = tmp_path / "ws"
    shutil.copytree(analytic_scene["root"], root)
    maps = root / "stereo" / "depth_maps"
    geometric = sorted(maps.glob("*.geometric.bin"))
    for f in geometric[1:]:
        f.rename(f.with_name(f.name.replace(".geometric.bin", ".teacher.bin")))
    cfg = RealDatasetConfig(roots=(root,), pseudo_labels="teacher", **SMALL)
    ds = RealMVSDataset(cfg, cache_dir=tmp_path)
    labelled = {f.name.replace(".geometric.bin", "") for f in geometric[1:]}
    assert set(ds.scenes[0].pseudo) == labelled & set(ds.scenes[0].references)
    assert all(p.name.endswith(".teacher.bin") for p in ds.scenes[0].pseudo.values())


def test_a_completions_unsupported_pixels_are_no_pseudo_labels(tmp_path):
    """``pseudo_labels="filled"``: a pixel of confidence 0 holds the network's own depth, so no label."""
    from colmap_pvs.io.maps import write_array, write_depth_map
    from colmap_pvs.train.real_dataset import read_pseudo_label

    maps = tmp_path / "stereo" / "depth_maps"
    confs = tmp_path / "stereo" / "confidence_maps"
    maps.mkdir(parents=True)
    confs.mkdir()
    depth = np.full((6, 8), 2.0, np.float32)
    conf = np.full((6, 8), 0.7, np.float32)
    conf[:, :3] = 0.0
    write_depth_map(maps / "a.png.filled.bin", depth)
    write_array(confs / "a.png.filled.bin", conf)
    label = read_pseudo_label(maps / "a.png.filled.bin", "filled")
    assert np.all(label[:, :3] == 0) and np.all(label[:, 3:] == 2.0)
    write_depth_map(maps / "a.png.geometric.bin", depth)
    write_array(confs / "a.png.geometric.bin", conf)
    assert np.all(read_pseudo_label(maps / "a.png.geometric.bin", "geometric") == 2.0)  # its own meaning
    write_array(confs / "a.png.filled.bin", conf[:, :4])
    with pytest.raises(MapFormatError, match="a.png.filled.bin"):
        read_pseudo_label(maps / "a.png.filled.bin", "filled")


def test_mixed_dataset_ratio_and_keys(analytic_scene, tmp_path):
    real = _dataset(analytic_scene, tmp_path)

    class Synth(torch.utils.data.Dataset):
        def __len__(self):
            return 50

        def __getitem__(self, i):
            return {"images": torch.zeros(3, 3, 8, 8), "depth": torch.ones(8, 8)}

    mixed = MixedDataset(Synth(), real, 0.3, seed=1)
    kinds = [mixed.is_real(i) for i in range(len(mixed))]
    assert 0.1 < np.mean(kinds) < 0.5
    syn = mixed[kinds.index(False)]
    assert float(syn["is_real"]) == 0.0 and syn["label_depth"].shape == (8, 8)
    assert syn["pseudo_depth"].shape == (8, 8) and float(syn["pseudo_depth"].abs().sum()) == 0.0
    assert float(mixed[kinds.index(True)]["is_real"]) == 1.0
    with pytest.raises(ConfigError):
        MixedDataset(None, real, 0.5)


def test_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="multiple of 16"):
        RealDatasetConfig(roots=(tmp_path,), width=100)
    with pytest.raises(ConfigError, match="roots"):
        RealMVSDataset(RealDatasetConfig(), cache_dir=tmp_path)
    with pytest.raises(WorkspaceError, match="no COLMAP model"):
        open_scene(tmp_path, tmp_path / "cache")
    with pytest.raises(ConfigError, match="batch_size 1"):
        TrainConfig(real_fraction=0.5, real=RealDatasetConfig(roots=(tmp_path,)), batch_size=2)
    with pytest.raises(ConfigError, match="real.roots"):
        TrainConfig(real_fraction=0.5)


def test_distorted_scene_is_undistorted_once(shared_data_dir, tmp_path):
    root = shared_data_dir / "real-train" / "strecha-entry-P10"
    if not root.is_dir():
        pytest.skip(f"{root} is missing")
    images, model = open_scene(root, tmp_path)
    assert images.parent.parent == tmp_path
    assert all(cam.is_pinhole for cam in model.cameras.values())
    stamp = (images.parent / "sparse").stat().st_mtime
    images2, _ = open_scene(root, tmp_path)  # cached: not undistorted again
    assert images2 == images and (images.parent / "sparse").stat().st_mtime == stamp


def test_trainer_runs_self_supervised_steps_and_resumes(analytic_scene, tmp_path):
    tiny = replace_config(TINY_PVSNET, confidence_planes=2, channels_last=False)
    cfg = TrainConfig(
        output_dir=tmp_path / "run",
        model=tiny,
        real=RealDatasetConfig(roots=(analytic_scene["root"],), **SMALL),
        real_fraction=1.0,
        steps=2,
        val_every=0,
        torch_threads=1,
        progress=False,
        checkpoint_every_seconds=0,
    )
    trainer = Trainer(cfg)
    assert isinstance(trainer.train_dataset, MixedDataset)
    before = [p.detach().clone() for p in trainer.model.parameters()]
    trainer.train()
    assert trainer.step == 2 and (tmp_path / "run" / "last.pt").is_file()
    changed = any(not torch.equal(a, b) for a, b in zip(before, trainer.model.parameters(), strict=True))
    assert changed
    resumed = Trainer(replace_config(cfg, steps=3))
    assert resumed.step == 2
    resumed.train()
    assert resumed.step == 3
