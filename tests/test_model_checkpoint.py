"""Checkpoint round trip and every failure mode (CheckpointError naming the path and the problem)."""

from __future__ import annotations

import pytest
import torch
from tiny_models import TINY_PVSNET

from colmap_pvs.config import config_to_dict, replace_config
from colmap_pvs.errors import CheckpointError
from colmap_pvs.model import CHECKPOINT_FORMAT, PVSNet, load_checkpoint, save_checkpoint

pytestmark = pytest.mark.usefixtures("one_torch_thread")


TINY = TINY_PVSNET


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
    assert meta["format"] == CHECKPOINT_FORMAT and meta["model_config"] == config_to_dict(TINY)
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
