"""The GPU training recipe (``benchmarks/configs/gpu_wide.train_config.json``) runs: its real file, on the
CPU, for two steps at tiny sizes, checkpointed with its wide model, and resumed."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from colmap_pvs.config import load_config, replace_config
from colmap_pvs.errors import ConfigError
from colmap_pvs.model import PVSNetConfig
from colmap_pvs.model.runtime import resolve_device
from colmap_pvs.train import TrainConfig, Trainer

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "benchmarks" / "configs" / "gpu_wide.train_config.json"
WIDTHS = ("feature_channels", "planes_per_stage", "regularization_channels", "visibility_channels",
          "stage_channels")


def _widths(model: PVSNetConfig | dict) -> dict:
    get = model.get if isinstance(model, dict) else lambda k: getattr(model, k)
    return {k: tuple(v) if isinstance(v := get(k), list | tuple) else v for k in WIDTHS}


def test_the_recipe_is_a_wider_model_on_renders_and_real_train():
    cfg = load_config(TrainConfig, RECIPE)
    shipped = PVSNetConfig()
    assert cfg.device == "auto" and cfg.num_workers > 0 and cfg.checkpoint_every_steps > 0
    assert cfg.model.feature_channels == tuple(2 * c for c in shipped.feature_channels)
    assert cfg.model.stage_channels == tuple(2 * c for c in shipped.stage_channels)
    assert cfg.model.regularization_channels == 2 * shipped.regularization_channels
    assert cfg.model.planes_per_stage[0] > shipped.planes_per_stage[0]
    # the rest of the model is the shipped one
    assert replace_config(cfg.model, **{k: getattr(shipped, k) for k in WIDTHS}) == shipped
    assert 0 < cfg.real_fraction < 1 and cfg.dataset == "synthetic" and cfg.real.pseudo_labels == "none"
    assert [r.parent.name for r in cfg.real.roots] == ["real-train"] * 9  # no teacher labels needed
    assert (ROOT / cfg.init_weights).is_file()


def test_the_recipe_trains_two_steps_on_the_cpu_and_resumes(analytic_scene, tmp_path: Path):
    recipe = load_config(TrainConfig, RECIPE)
    cfg = replace_config(
        recipe,
        output_dir=tmp_path / "run",
        init_weights=ROOT / recipe.init_weights,
        data=replace_config(recipe.data, width=64, height=48, num_samples=2, samples_per_scene=2,
                            cache_dir=tmp_path / "scenes"),
        real=replace_config(recipe.real, roots=(analytic_scene["root"],), width=64, height=48,
                            max_image_size=96),
        steps=1,
        num_workers=0,
        torch_threads=1,
        val_every=0,
        progress=False,
    )
    first = Trainer(cfg)
    assert first.device.type == ("cuda" if torch.cuda.is_available() else "cpu")
    first.train()
    last = torch.load(tmp_path / "run" / "last.pt", map_location="cpu", weights_only=True)
    assert last["step"] == 1 and _widths(last["model_config"]) == _widths(recipe.model)
    resumed = Trainer(replace_config(cfg, steps=2, device="cpu"))  # another device resumes the run
    assert resumed.resumed_from == tmp_path / "run" / "last.pt" and resumed.step == 1
    resumed.train()
    model = torch.load(tmp_path / "run" / "model.pt", map_location="cpu", weights_only=True)
    assert model["step"] == 2 and _widths(model["model_config"]) == _widths(recipe.model)


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_device_cuda_without_cuda_is_a_config_error():
    assert resolve_device("auto") == torch.device("cpu")
    with pytest.raises(ConfigError, match="--device cuda was requested"):
        resolve_device("cuda")
