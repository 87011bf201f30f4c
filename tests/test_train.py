"""Trainer: identical resumption, loss decrease, run files, signals, sampler, schedules.

Uses a tiny PVSNet and an in-test dataset of textured planes rendered exactly (ray-plane
intersection, analytic texture), so it does not depend on the synthetic renderer.
"""

from __future__ import annotations

import csv
import math
import os
import signal
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from tiny_models import TINY_PVSNET
from torch.utils.data import Dataset

from colmap_pvs.config import load_config, replace_config
from colmap_pvs.errors import CheckpointError, ConfigError
from colmap_pvs.model import load_checkpoint
from colmap_pvs.train import StepSampler, TrainConfig, Trainer, TrainingInterrupted

H, W, N = 48, 64, 3

# oneDNN's channels-last 3D kernels cost seconds of warm-up per shape: off for these tiny runs.
TINY = replace_config(TINY_PVSNET, confidence_planes=2, channels_last=False)


def _rot_y(a: float) -> np.ndarray:
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


class PlaneDataset(Dataset):
    """Textured planes ``z = z0 + p x + q y`` (reference camera frame = world), exact renders.

    Adds noise from the global torch RNG, so that resuming is only identical when the RNG
    state is restored too.
    """

    def __init__(self, length: int = 3, seed: int = 0, trigger: tuple[int, int] | None = None) -> None:
        self.length, self.seed = length, seed
        self.trigger = trigger  # (fetch number, signal) sent to this process at that fetch
        self.fetches = 0

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        self.fetches += 1
        if self.trigger is not None and self.fetches == self.trigger[0]:
            os.kill(os.getpid(), self.trigger[1])
        rng = np.random.default_rng([self.seed, index])
        z0, p, q = rng.uniform(2.0, 3.0), rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3)
        freq = rng.uniform(3.0, 9.0, size=(3, 2))
        K = np.array([[55.0, 0, W / 2], [0, 55.0, H / 2], [0, 0, 1]])
        n = np.array([-p, -q, 1.0])  # plane: n . X = z0
        v, u = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
        pix = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
        images, poses, depth = [], [], None
        for i in range(N):
            T = np.eye(4)
            if i:
                T[:3, :3] = _rot_y(rng.uniform(-0.05, 0.05))
                T[:3, 3] = [rng.choice([-1, 1]) * rng.uniform(0.15, 0.3), rng.uniform(-0.05, 0.05), 0.0]
            R, t = T[:3, :3], T[:3, 3]
            C, d = -R.T @ t, pix @ R  # rays in world: R^T K^-1 x
            s = (z0 - n @ C) / (d @ n)
            X = C + s[..., None] * d
            img = 0.5 + 0.22 * np.sin(X[..., :1] * freq[:, 0] * 3) * np.cos(X[..., 1:2] * freq[:, 1] * 3)
            img += 0.2 * np.sin(7 * X[..., :1] + 5 * X[..., 1:2])
            images.append(np.clip(img, 0, 1).transpose(2, 0, 1))
            poses.append(T)
            if i == 0:
                depth = X[..., 2]
        noise = 0.01 * torch.randn(N, 3, H, W)  # global-RNG "augmentation": resuming must restore the RNG
        sparse = np.zeros((1, H, W))
        sparse[0, ::9, ::11] = depth[::9, ::11]
        return {
            "images": torch.tensor(np.stack(images), dtype=torch.float32) + noise,
            "intrinsics": torch.tensor(np.stack([K] * N), dtype=torch.float32),
            "cam_from_world": torch.tensor(np.stack(poses), dtype=torch.float32),
            "depth": torch.tensor(depth, dtype=torch.float32),
            "depth_min": torch.tensor(1.5, dtype=torch.float32),
            "depth_max": torch.tensor(4.5, dtype=torch.float32),
            "sparse_depth": torch.tensor(sparse, dtype=torch.float32),
        }


def _config(tmp: Path, **kw) -> TrainConfig:
    base = dict(
        output_dir=tmp,
        model=TINY,
        steps=4,
        batch_size=2,
        log_every=1,
        val_every=2,
        val_samples=2,
        checkpoint_every_seconds=0.0,
        progress=False,
        torch_threads=1,  # 2 threads on 2 cores shared with other jobs can be 50x slower for tiny ops
        seed=7,
    )
    base.update(kw)
    return TrainConfig(**base)


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return [
            {k: v for k, v in r.items() if k not in ("time_s", "sec_per_step")} for r in csv.DictReader(f)
        ]


def _raw(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)


def test_resume_continues_the_identical_run(tmp_path: Path) -> None:
    straight, split = tmp_path / "straight", tmp_path / "split"
    # log rows at steps 3 (mean of steps 1-3: the accumulators must survive the resume) and 4
    # 4 steps of batch 1 over 3 samples also cross an epoch boundary of the sample order
    cfg_a, cfg_b = _config(straight, log_every=3, batch_size=1), _config(split, log_every=3, batch_size=1)
    a = Trainer(cfg_a, train_dataset=PlaneDataset(), val_dataset=PlaneDataset(seed=99))
    a.train()
    b = Trainer(cfg_b, train_dataset=PlaneDataset(), val_dataset=PlaneDataset(seed=99))
    b.train(max_steps=2)
    assert _raw(split / "last.pt")["step"] == 2 and not (split / "model.pt").exists()
    b2 = Trainer(cfg_b, train_dataset=PlaneDataset(), val_dataset=PlaneDataset(seed=99))
    assert b2.step == 2 and b2.resumed_from == split / "last.pt"
    b2.train()

    ca, cb = _raw(straight / "last.pt"), _raw(split / "last.pt")
    assert ca["step"] == cb["step"] == 4
    assert ca["state_dict"].keys() == cb["state_dict"].keys()
    for k, v in ca["state_dict"].items():
        assert torch.equal(v, cb["state_dict"][k]), k
    for k, st in ca["optimizer"]["state"].items():
        assert torch.equal(st["square_avg"], cb["optimizer"]["state"][k]["square_avg"])
    assert torch.equal(ca["rng"]["torch"], cb["rng"]["torch"])
    assert ca["rng"]["numpy"] == cb["rng"]["numpy"] and ca["rng"]["python"] == cb["rng"]["python"]
    assert ca["scheduler"]["last_epoch"] == cb["scheduler"]["last_epoch"] == 4
    rows_a, rows_b = _rows(straight / "log.csv"), _rows(split / "log.csv")
    assert [r["step"] for r in rows_a] == ["3", "4"] and rows_a == rows_b
    assert _rows(straight / "val.csv") == _rows(split / "val.csv")
    assert ca["best_val_loss"] == cb["best_val_loss"] < math.inf

    # the run actually trained: the weights moved away from the initial ones
    init = Trainer(
        _config(tmp_path / "init"), train_dataset=PlaneDataset(), val_dataset=None
    ).model.state_dict()
    assert any(not torch.equal(init[k], v) for k, v in ca["state_dict"].items())

    # run files
    header = (straight / "log.csv").read_text().splitlines()[0].split(",")
    assert header == ["step", "time_s", "loss"] + [f"loss_out{k}" for k in range(5)] + ["lr", "sec_per_step"]
    assert load_config(TrainConfig, straight / "config.json") == cfg_a
    png = cv2.imread(str(straight / "loss.png"))
    assert png is not None and png.shape[2] == 3 and png.std() > 0
    for name in ("last.pt", "best.pt", "model.pt"):
        raw = _raw(straight / name)  # weights_only=True loads everything we store
        assert raw["train_config"]["model"]["feature_channels"] == [8, 8, 8]
        model, meta = load_checkpoint(straight / name)
        assert meta["step"] in (2, 4)
    assert "optimizer" not in _raw(straight / "model.pt")
    assert (straight / "model.pt").stat().st_size < (straight / "last.pt").stat().st_size

    # finished run: resuming is a no-op; a changed training field is refused
    assert Trainer(cfg_a, train_dataset=PlaneDataset(), val_dataset=None).step == 4
    with pytest.raises(ConfigError, match="lr"):
        Trainer(replace_config(cfg_a, lr=5e-4), train_dataset=PlaneDataset(), val_dataset=None)
    longer = Trainer(replace_config(cfg_a, steps=5, val_every=0), train_dataset=PlaneDataset())
    assert longer.step == 4  # steps may grow on resume


def test_a_few_steps_reduce_the_loss_on_a_fixed_batch(tmp_path: Path) -> None:
    trainer = Trainer(
        _config(tmp_path, val_every=0, batch_size=1, lr_schedule="constant"), train_dataset=PlaneDataset(1)
    )
    batch = {k: v[None] for k, v in PlaneDataset(1)[0].items()}
    with trainer.torch_threads():
        losses = [trainer.train_step(batch)[0] for _ in range(10)]
    assert trainer.step == 10
    assert np.mean(losses[-3:]) < 0.7 * losses[0], losses


def test_init_weights_starts_from_a_checkpoint_but_never_overrides_a_resume(tmp_path: Path) -> None:
    first = Trainer(_config(tmp_path / "a", val_every=0, steps=2), train_dataset=PlaneDataset())
    first.train()
    source = first.model.state_dict()
    # A model with one more switch (sparse prior) takes every matching tensor.
    model_cfg = replace_config(TINY, sparse_prior=True)
    cfg = _config(tmp_path / "b", val_every=0, steps=2, model=model_cfg, init_weights=first.model_path)
    second = Trainer(cfg, train_dataset=PlaneDataset())
    for k, v in second.model.state_dict().items():
        assert torch.equal(v, source[k]), k
    second.train()
    trained = {k: v.clone() for k, v in second.model.state_dict().items()}
    resumed = Trainer(replace_config(cfg, steps=3), train_dataset=PlaneDataset())
    assert resumed.step == 2
    for k, v in resumed.model.state_dict().items():
        assert torch.equal(v, trained[k]), k
    with pytest.raises(CheckpointError, match="missing.pt"):
        Trainer(_config(tmp_path / "c", init_weights=tmp_path / "missing.pt"), train_dataset=PlaneDataset())


def test_sigterm_checkpoints_and_the_run_resumes(tmp_path: Path) -> None:
    cfg = _config(tmp_path, val_every=0, batch_size=1, steps=3)
    # the 2nd sample fetch (step 2) raises SIGTERM: step 2 completes, then the loop stops
    trainer = Trainer(cfg, train_dataset=PlaneDataset(trigger=(2, signal.SIGTERM)))
    with pytest.raises(TrainingInterrupted) as info:
        trainer.train()
    assert info.value.signal_name == "SIGTERM" and info.value.step == 2
    assert _raw(tmp_path / "last.pt")["step"] == 2
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # handlers restored
    Trainer(cfg, train_dataset=PlaneDataset()).train()
    assert _raw(tmp_path / "last.pt")["step"] == 3 and (tmp_path / "model.pt").is_file()


def test_step_sampler_is_a_pure_function_of_seed_and_position() -> None:
    full = StepSampler(5, seed=3)
    it = iter(full)
    stream = [next(it) for _ in range(17)]
    assert sorted(stream[:5]) == list(range(5)) and sorted(stream[5:10]) == list(range(5))
    assert stream[:5] != stream[5:10] or stream[5:10] != stream[10:15]  # epochs are reshuffled
    for start in (0, 4, 5, 11):
        it = iter(StepSampler(5, seed=3, start=start))
        assert [next(it) for _ in range(17 - start)] == stream[start:]
    other = iter(StepSampler(5, seed=4))
    assert [next(other) for _ in range(17)] != stream
    grouped = StepSampler(10, seed=1, group=4).permutation(0)
    assert sorted(grouped) == list(range(10))
    blocks = [sorted(int(i) // 4 for i in grouped[j : j + n]) for j, n in _block_spans(grouped)]
    assert all(len(set(b)) == 1 for b in blocks) and len(blocks) == 3


def _block_spans(order: np.ndarray) -> list[tuple[int, int]]:
    spans, j = [], 0
    while j < len(order):
        n = 2 if order[j] >= 8 else 4  # blocks {0-3}, {4-7}, {8, 9}
        spans.append((j, n))
        j += n
    return spans


def test_lr_schedules(tmp_path: Path) -> None:
    cfg = _config(tmp_path, lr_schedule="step", lr_decay_every=10, lr_decay_gamma=0.5)
    assert [cfg.lr_factor(s) for s in (0, 9, 10, 25)] == [1.0, 1.0, 0.5, 0.25]
    cos = replace_config(cfg, lr_schedule="cosine", steps=100, lr_min_factor=0.1)
    assert cos.lr_factor(0) == 1.0 and cos.lr_factor(50) == pytest.approx(0.55) and cos.lr_factor(200) == 0.1
    warm = replace_config(cfg, lr_schedule="constant", lr_warmup_steps=4)
    assert [warm.lr_factor(s) for s in range(5)] == [0.25, 0.5, 0.75, 1.0, 1.0]
    with pytest.raises(ConfigError, match="batch_size"):
        replace_config(cfg, batch_size=0)
    with pytest.raises(ConfigError, match="mvsnet.root"):
        replace_config(cfg, dataset="mvsnet")


def test_trainer_takes_its_dataset_from_the_config(tmp_path: Path) -> None:
    from test_mvsnet_dataset import _write_blendedmvs

    from colmap_pvs.synthetic import SyntheticDatasetConfig
    from colmap_pvs.train import MVSNetDatasetConfig, build_datasets

    data = SyntheticDatasetConfig(num_samples=2, width=64, height=48, samples_per_scene=2)
    cfg = _config(tmp_path / "syn", data=data, steps=1, val_every=1, val_samples=1)
    train_ds, val_ds = build_datasets(cfg)
    assert len(train_ds) == 2 and val_ds.config.seed == data.seed + cfg.val_seed_offset
    assert train_ds.config.cache_dir == tmp_path / "syn" / "scene_cache"  # default scene cache
    Trainer(replace_config(cfg, val_every=0)).train()  # renders one scene
    assert (tmp_path / "syn" / "model.pt").is_file() and any(
        (tmp_path / "syn" / "scene_cache").rglob("*.npz")
    )

    _write_blendedmvs(tmp_path / "bmvs", "sceneA")
    _write_blendedmvs(tmp_path / "bmvs", "sceneB")
    mv = MVSNetDatasetConfig(root=tmp_path / "bmvs", layout="blendedmvs", num_views=3, scans=("sceneA",))
    mcfg = _config(
        tmp_path / "mv", dataset="mvsnet", mvsnet=replace_config(mv, val_scans=("sceneB",)), steps=1
    )
    train_ds, val_ds = build_datasets(mcfg)
    assert train_ds.scans == ("sceneA",) and val_ds.scans == ("sceneB",)
    Trainer(replace_config(mcfg, val_every=0)).train()
    assert _raw(tmp_path / "mv" / "last.pt")["train_config"]["dataset"] == "mvsnet"


def test_plot_curves_log_and_linear_axes(tmp_path: Path) -> None:
    from colmap_pvs.train import plot_curves

    series = {"first curve": ([3, 5, 7, 9], [0.30, 0.25, 0.22, 0.20]), "second": ([3, 5], [0.35, -1.0])}
    blue = np.array([180, 119, 31])  # the first curve's colour (BGR)
    for log_y in (True, False):
        path = plot_curves(tmp_path / f"{log_y}.png", series, xlabel="N", log_y=log_y)
        img = cv2.imread(str(path))
        assert img.shape == (540, 960, 3)
        assert (np.abs(img.astype(int) - blue).sum(-1) < 30).sum() > 200  # the curve is drawn
    assert plot_curves(tmp_path / "none.png", {"x": ([1], [float("nan")])}) is None


def test_resume_accepts_a_checkpoint_written_before_a_field_existed(tmp_path: Path) -> None:
    cfg = _config(tmp_path, val_every=0, steps=1, batch_size=1)
    Trainer(cfg, train_dataset=PlaneDataset()).train()
    last = tmp_path / "last.pt"
    raw = _raw(last)
    del raw["train_config"]["init_weights"]  # as written by an older version
    del raw["train_config"]["data"]["hint_noise"]
    torch.save(raw, last)
    resumed = Trainer(replace_config(cfg, steps=2), train_dataset=PlaneDataset())
    assert resumed.step == 1
    raw["train_config"]["data"]["no_such_field"] = 1  # a field that no longer exists: refused
    torch.save(raw, last)
    with pytest.raises(ConfigError, match="no longer loads"):
        Trainer(cfg, train_dataset=PlaneDataset())


def test_recorded_training_configs_keep_their_model() -> None:
    """``train`` builds the shipped model (``PVSNetConfig()``) where a config is silent, so a recorded
    config (``benchmarks/configs``, the weights' ``*.train_config.json``) states its whole model, or
    inherits it from its ``base``: its meaning never follows a changed default."""
    import dataclasses
    import json

    from colmap_pvs.model import PVSNetConfig

    assert TrainConfig().model == PVSNetConfig()
    root = Path(__file__).resolve().parents[1]
    fields = {f.name for f in dataclasses.fields(PVSNetConfig)}
    recorded = sorted([*(root / "benchmarks" / "configs").glob("*.json"),
                       *(root / "colmap_pvs" / "weights").glob("*.train_config.json")])
    assert len(recorded) >= 10
    for path in recorded:
        data = json.loads(path.read_text())
        model = data["config"].get("model")
        assert model is not None or "base" in data, path.name
        if model is not None:
            assert set(model) == fields, (path.name, fields ^ set(model))
    plant = root / "benchmarks" / "configs" / "plant_scratch.train_config.json"
    model = load_config(TrainConfig, plant).model
    assert (model.frustum_weights, model.stage_neighbourhood, model.sparse_prior) == (False, 0, False)
    assert model.feature_channels == (16, 8, 8)  # what the file says
