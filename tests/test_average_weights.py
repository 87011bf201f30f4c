"""The ``average-weights`` step: weighted means of checkpoints, their recipe, and bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from conftest import make_tiny_checkpoint

from colmap_pvs.average_weights import AverageWeightsConfig, average_weights, config_path
from colmap_pvs.errors import CheckpointError, ConfigError
from colmap_pvs.io.files import file_sha256
from colmap_pvs.model import load_checkpoint


def _checkpoint(path: Path, seed: int, step: int = 0, **overrides) -> Path:
    """A tiny random checkpoint whose every tensor (BatchNorm's too) depends on ``seed``."""
    return make_tiny_checkpoint(path, seed=seed, step=step, perturb=True, **overrides)


def test_weighted_mean_of_every_float_tensor(tmp_path: Path) -> None:
    a = _checkpoint(tmp_path / "a.pt", seed=1, step=3000)
    b = _checkpoint(tmp_path / "b.pt", seed=2, step=1500, stage_neighbourhood=2)
    out = average_weights(AverageWeightsConfig(checkpoints=(a, b), output_path=tmp_path / "avg.pt",
                                               weights=(0.25, 0.75)))
    model, meta = load_checkpoint(out)
    sa, sb, so = (load_checkpoint(p)[0].state_dict() for p in (a, b, out))
    floats = [k for k, v in so.items() if v.is_floating_point()]
    assert any("running_var" in k for k in floats)  # BatchNorm statistics are averaged too
    for key in floats:
        assert not torch.equal(sa[key], sb[key])
        torch.testing.assert_close(so[key], 0.25 * sa[key] + 0.75 * sb[key], rtol=1e-6, atol=1e-6)
    # integer buffers, the model config and the step come from config_from (the last by default)
    counters = [k for k, v in so.items() if not v.is_floating_point()]
    assert counters and all(torch.equal(so[k], sb[k]) and not torch.equal(so[k], sa[k]) for k in counters)
    assert model.config.stage_neighbourhood == 2
    assert meta["step"] == 1500
    recipe = meta["averaged_from"]
    assert [r["weight"] for r in recipe] == [0.25, 0.75]
    assert [r["sha256"] for r in recipe] == [file_sha256(a), file_sha256(b)]
    assert meta["average_config"]["weights"] == [0.25, 0.75]
    saved = json.loads(config_path(out).read_text())
    assert saved["config"]["checkpoints"] == [str(a), str(b)]
    assert saved["config"]["weights"] == [0.25, 0.75] and saved["config"]["config_from"] == 1
    assert saved["averaged_from"] == recipe


def test_equal_weights_and_config_from_the_first(tmp_path: Path) -> None:
    paths = [_checkpoint(tmp_path / f"{i}.pt", seed=i) for i in range(3)]
    config_path(tmp_path / "o.pt").write_text("an older run's recipe")
    out = average_weights(AverageWeightsConfig(checkpoints=tuple(paths), output_path=tmp_path / "o.pt",
                                               config_from=-3))
    # the recipe next to it is this run's, resolved: equal weights, the first checkpoint's config
    saved = json.loads(config_path(out).read_text())["config"]
    assert saved["weights"] == pytest.approx([1 / 3] * 3) and saved["config_from"] == 0
    states = [load_checkpoint(p)[0].state_dict() for p in paths]
    so = load_checkpoint(out)[0].state_dict()
    key = next(k for k, v in so.items() if v.is_floating_point() and v.numel() > 1)
    torch.testing.assert_close(so[key], sum(s[key] for s in states) / 3, rtol=1e-6, atol=1e-6)
    counter = next(k for k, v in so.items() if not v.is_floating_point())
    assert torch.equal(so[counter], states[0][counter])


def test_checkpoints_with_different_tensors_are_refused(tmp_path: Path) -> None:
    a = _checkpoint(tmp_path / "a.pt", seed=1)
    wide = _checkpoint(tmp_path / "wide.pt", seed=2, feature_channels=(16, 8, 8))
    with pytest.raises(CheckpointError, match="wide.pt"):
        average_weights(AverageWeightsConfig(checkpoints=(a, wide), output_path=tmp_path / "o.pt"))
    with pytest.raises(CheckpointError, match="missing.pt' does not exist"):
        average_weights(AverageWeightsConfig(checkpoints=(a, tmp_path / "missing.pt"),
                                             output_path=tmp_path / "o.pt"))
    assert not (tmp_path / "o.pt").exists() and not config_path(tmp_path / "o.pt").exists()


def test_other_config_differences_are_warned_about(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    a = _checkpoint(tmp_path / "a.pt", seed=1, sparse_prior=True)
    b = _checkpoint(tmp_path / "b.pt", seed=2, planes_per_stage=(16,))  # same tensors, other network
    with caplog.at_level("INFO", logger="colmap_pvs.average_weights"):
        average_weights(AverageWeightsConfig(checkpoints=(a, b), output_path=tmp_path / "o.pt"))
    warned = [r for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1 and "planes_per_stage" in warned[0].getMessage()
    assert "sparse_prior" not in warned[0].getMessage()
    assert any("sparse_prior" in r.getMessage() for r in caplog.records if r.levelname == "INFO")


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"checkpoints": ("a.pt",)}, "at least 2"),
        ({"weights": (0.5, 0.4)}, "sum to 1"),
        ({"weights": (1.0,)}, "1 weight"),
        ({"weights": (1.5, -0.5)}, ">= 0"),
        ({"config_from": 2}, "config_from 2"),
        ({"output_path": "a.pt"}, "also an input"),
    ],
)
def test_bad_settings_are_named(tmp_path: Path, fields: dict, message: str) -> None:
    base = {"checkpoints": ("a.pt", "b.pt"), "output_path": "o.pt"}
    with pytest.raises(ConfigError, match=message):
        AverageWeightsConfig(**{**base, **fields})


def test_cli_writes_the_average(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from colmap_pvs.cli.main import main

    a = _checkpoint(tmp_path / "a.pt", seed=1)
    b = _checkpoint(tmp_path / "b.pt", seed=2)
    out = tmp_path / "soup.pt"
    assert main(["average-weights", "--checkpoints", str(a), str(b), "--output_path", str(out)]) == 0
    assert str(out) in capsys.readouterr().out
    assert load_checkpoint(out)[1]["average_config"]["weights"] == [0.5, 0.5]
    assert main(["average-weights", "--checkpoints", str(a), str(b), "--weights", "0.7", "0.2",
                 "--output_path", str(tmp_path / "bad.pt")]) == 1
    assert "sum to 1" in capsys.readouterr().err
    assert not (tmp_path / "bad.pt").exists()
