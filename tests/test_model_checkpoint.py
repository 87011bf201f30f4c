"""Checkpoint round trip and every failure mode (CheckpointError naming the path and the problem)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from tiny_models import TINY_PVSNET

from colmap_pvs.config import config_to_dict, replace_config
from colmap_pvs.errors import CheckpointError
from colmap_pvs.model import (
    CHECKPOINT_FORMAT,
    PVSNet,
    PVSNetConfig,
    load_checkpoint,
    save_checkpoint,
    stored_config,
)
from colmap_pvs.model.checkpoint import read_stored_config

pytestmark = pytest.mark.usefixtures("one_torch_thread")


TINY = TINY_PVSNET
WEIGHTS = Path(__file__).resolve().parents[1] / "colmap_pvs" / "weights"


def _inputs():
    g = torch.Generator().manual_seed(1)
    images = torch.rand(1, 2, 3, 20, 24, generator=g)
    K = torch.tensor([[20.0, 0, 12], [0, 20.0, 10], [0, 0, 1]]).expand(1, 2, 3, 3).clone()
    T = torch.eye(4).expand(1, 2, 4, 4).clone()
    T[0, 1, 0, 3] = 0.2
    return images, K, T, torch.tensor([1.0]), torch.tensor([5.0])


def _trained_model() -> PVSNet:
    torch.manual_seed(0)
    model = PVSNet(TINY).train()
    model(*_inputs())  # updates BN running statistics: they must round-trip too
    return model.eval()


def test_round_trip_gives_identical_outputs(tmp_path):
    model = _trained_model()
    path = save_checkpoint(tmp_path / "sub" / "ckpt.pt", model, step=7, extra={"note": "hi", "lr": 0.1})
    assert path == tmp_path / "sub" / "ckpt.pt" and path.is_file()
    assert not [p for p in path.parent.iterdir() if p.name != "ckpt.pt"]  # no temporary left behind
    loaded, meta = load_checkpoint(path)
    assert isinstance(loaded, PVSNet) and not loaded.training
    assert loaded.config == model.config
    assert meta["step"] == 7 and meta["note"] == "hi" and meta["lr"] == 0.1
    assert meta["format"] == CHECKPOINT_FORMAT and meta["model_config"] == stored_config(TINY)
    with torch.inference_mode():
        a, b = model(*_inputs()), loaded(*_inputs())
    assert torch.equal(a.depth, b.depth) and torch.equal(a.visibility, b.visibility)
    raw = torch.load(path, weights_only=True)
    assert set(raw) >= {"format", "model_config", "state_dict", "step", "note"}


def test_missing_file(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "nope.pt")


def test_corrupt_file(tmp_path):
    path = save_checkpoint(tmp_path / "c.pt", _trained_model())
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="corrupt") as exc:
        load_checkpoint(path)
    assert str(path) in str(exc.value)
    (tmp_path / "text.pt").write_text("not a checkpoint")
    with pytest.raises(CheckpointError, match="corrupt"):
        load_checkpoint(tmp_path / "text.pt")


class _Evil:
    def __reduce__(self):
        return (print, ("unsafe code ran",))


def test_weights_only_refuses_pickled_code(tmp_path):
    path = tmp_path / "evil.pt"
    torch.save({"format": CHECKPOINT_FORMAT, "x": _Evil()}, path)
    with pytest.raises(CheckpointError, match="corrupt"):
        load_checkpoint(path)


def test_wrong_format(tmp_path):
    path = tmp_path / "w.pt"
    torch.save({"format": "something-else/3", "state_dict": {}}, path)
    with pytest.raises(CheckpointError, match="format"):
        load_checkpoint(path)
    torch.save([1, 2, 3], path)
    with pytest.raises(CheckpointError, match="format"):
        load_checkpoint(path)


def test_mismatched_state_dict(tmp_path):
    path = save_checkpoint(tmp_path / "m.pt", _trained_model())
    raw = torch.load(path, weights_only=True)
    # The config says wider U-Nets than the stored weights.
    raw["model_config"] = config_to_dict(replace_config(TINY, regularization_channels=8))
    torch.save(raw, path)
    with pytest.raises(CheckpointError, match="state_dict does not match") as exc:
        load_checkpoint(path)
    assert str(path) in str(exc.value)
    raw = torch.load(tmp_path / "m.pt", weights_only=True)
    raw["model_config"] = config_to_dict(TINY)
    del raw["state_dict"]["coarse.head0.bias"]
    torch.save(raw, path)
    with pytest.raises(CheckpointError, match="state_dict does not match"):
        load_checkpoint(path)


def test_invalid_or_unknown_config(tmp_path):
    path = save_checkpoint(tmp_path / "u.pt", _trained_model())
    raw = torch.load(path, weights_only=True)
    raw["model_config"]["mystery_switch"] = True
    torch.save(raw, path)
    with pytest.raises(CheckpointError, match="mystery_switch"):
        load_checkpoint(path)


def test_reserved_extra_keys_rejected(tmp_path):
    with pytest.raises(ValueError, match="reserved"):
        save_checkpoint(tmp_path / "r.pt", _trained_model(), extra={"state_dict": 1})


def test_default_config_is_the_shipped_checkpoints():
    """``PVSNet()`` is the network ``stereo`` runs: the defaults are the shipped checkpoint's config, and
    their stored form is its ``model_config`` key for key, in order (what stereo's provenance records)."""
    stored = torch.load(WEIGHTS / "pvsnet_default.pt", weights_only=True)["model_config"]
    assert list(stored_config(PVSNetConfig()).items()) == list(stored.items())
    assert load_checkpoint(WEIGHTS / "pvsnet_default.pt")[0].config == PVSNetConfig()


def test_retired_options_load_at_their_one_value_and_are_refused_at_another(tmp_path):
    path = save_checkpoint(tmp_path / "c.pt", _trained_model())
    data = torch.load(path, weights_only=True)
    assert (data["model_config"]["guidance_mode"], data["model_config"]["normalized_channels"]) == ("cost", 0)
    assert load_checkpoint(path)[0].config == TINY
    for key, value in (("guidance_mode", "probability"), ("normalized_channels", 2)):
        torch.save({**data, "model_config": {**data["model_config"], key: value}}, path)
        with pytest.raises(CheckpointError, match=f"c.pt.*{key}.* was removed"):
            load_checkpoint(path)


def test_a_config_stored_before_a_field_existed_means_it_off():
    """``pvsnet_v2.pt`` was saved before ``frustum_weights`` and ``stage_neighbourhood`` existed: they are
    off for it, whatever ``PVSNetConfig``'s defaults."""
    stored = torch.load(WEIGHTS / "pvsnet_v2.pt", weights_only=True)["model_config"]
    assert "frustum_weights" not in stored and "stage_neighbourhood" not in stored
    config = load_checkpoint(WEIGHTS / "pvsnet_v2.pt")[0].config
    assert (config.frustum_weights, config.stage_neighbourhood) == (False, 0)
    # a checkpoint saved before the sparse prior existed ran without it (the default is now on)
    older = {k: v for k, v in stored.items() if k not in ("sparse_prior", "prior_halfwidth")}
    assert read_stored_config(older).sparse_prior is False
