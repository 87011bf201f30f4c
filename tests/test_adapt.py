"""Test-time adaptation (colmap_pvs.adapt): the adaptation itself and the step above ``stereo``."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
import torch
from conftest import make_tiny_checkpoint
from scenes import reconstruct_config, stereo_config

import colmap_pvs.adapt.checkpoint as adapt_module
from colmap_pvs.adapt import AdaptConfig, adapt_checkpoint, run_adapted_stereo
from colmap_pvs.cli.main import main
from colmap_pvs.config import replace_config
from colmap_pvs.errors import ConfigError
from colmap_pvs.io.files import file_sha256
from colmap_pvs.model import load_checkpoint
from colmap_pvs.stereo import run_stereo
from colmap_pvs.train import Trainer, TrainingInterrupted, real_dataset
from colmap_pvs.train.real_dataset import RealDatasetConfig, RealMVSDataset
from colmap_pvs.train.selfsup import selfsup_loss

FAST = dict(width=128, height=96, max_image_size=160, num_views=3, threads=1)


@pytest.fixture
def workspace(analytic_scene, tmp_path) -> Path:
    root = tmp_path / "ws"
    shutil.copytree(analytic_scene["root"], root)
    shutil.rmtree(root / "stereo" / "depth_maps")
    shutil.rmtree(root / "stereo" / "normal_maps")
    return root


@pytest.fixture
def base(tmp_path) -> Path:
    return make_tiny_checkpoint(tmp_path / "base.pt", channels_last=False)


def _weights(path: Path) -> list[torch.Tensor]:
    return [p.detach().clone() for p in load_checkpoint(path)[0].parameters()]


def test_adaptation_writes_weights_and_reuses_or_redoes_them(workspace, base):
    stereo_dir = workspace / "stereo"
    cfg = AdaptConfig(steps=2, lr=1e-3, **FAST)
    first = adapt_checkpoint(workspace, stereo_dir, base, cfg, progress=False)
    assert not first.reused and first.steps == 2 and first.checkpoint.is_file()
    assert any(not torch.equal(a, b) for a, b in zip(_weights(base), _weights(first.checkpoint), strict=True))
    meta = json.loads((stereo_dir / "adapt" / "adapted.json").read_text())
    assert meta["steps"] == 2 and meta["fingerprint"]["settings"]["lr"] == 1e-3
    again = adapt_checkpoint(workspace, stereo_dir, base, cfg, progress=False)
    assert again.reused and again.steps == 2
    changed = adapt_checkpoint(workspace, stereo_dir, base, AdaptConfig(steps=2, lr=5e-4, **FAST),
                               progress=False)
    assert not changed.reused
    meta = json.loads((stereo_dir / "adapt" / "adapted.json").read_text())
    assert meta["fingerprint"]["settings"]["lr"] == 5e-4


def _stop_after_step(monkeypatch, step: int, stop) -> None:
    """Call ``stop(trainer)`` once the trainer has finished optimizer step ``step`` (once)."""
    train_step = Trainer.train_step
    stopped = []

    def counting(self, batch):
        out = train_step(self, batch)
        if self.step == step and not stopped:
            stopped.append(step)
            stop(self)
        return out

    monkeypatch.setattr(Trainer, "train_step", counting)


def test_adaptation_resumes_an_interrupted_run(workspace, base, monkeypatch):
    stereo_dir = workspace / "stereo"
    cfg = AdaptConfig(steps=3, lr=1e-3, **FAST)
    # SIGTERM after step 2 of 3: the trainer checkpoints its run folder and stops; no adapted weights
    _stop_after_step(monkeypatch, 2, lambda trainer: trainer.request_stop("SIGTERM"))
    with pytest.raises(TrainingInterrupted):
        adapt_checkpoint(workspace, stereo_dir, base, cfg, progress=False)
    assert not (stereo_dir / "adapt" / "adapted.pt").exists()
    monkeypatch.undo()
    more = adapt_checkpoint(workspace, stereo_dir, base, cfg, progress=False)
    meta = json.loads((stereo_dir / "adapt" / "adapted.json").read_text())
    assert not more.reused and more.steps == meta["steps"] == 3
    assert meta["steps_this_run"] == 1  # resumed at step 2, not started again


def test_time_limit_stops_early(workspace, base, monkeypatch):
    """``max_seconds`` arms a timer that stops the trainer after its current step. The timer is replaced by
    one the test fires after step 2 (a wall-clock limit would depend on the machine's load)."""
    timers = []

    class Timer:
        def __init__(self, interval, function, args=()):
            self.interval, self.expire, self.cancelled = interval, lambda: function(*args), False
            timers.append(self)

        def start(self):
            pass

        def cancel(self):
            self.cancelled = True

    monkeypatch.setattr(adapt_module.threading, "Timer", Timer)
    _stop_after_step(monkeypatch, 2, lambda trainer: timers[0].expire())
    done = adapt_checkpoint(
        workspace, workspace / "stereo", base, AdaptConfig(steps=500, max_seconds=0.5, **FAST), progress=False
    )
    assert [t.interval for t in timers] == [0.5] and timers[0].cancelled
    assert done.steps == 2 and done.checkpoint.is_file() and not done.reused


def test_adaptation_lowers_the_self_supervised_loss(workspace, base):
    data = RealMVSDataset(
        RealDatasetConfig(roots=(workspace,), width=128, height=96, max_image_size=160, num_best=2,
                          num_worst=0, seed=123, min_points=5),
        cache_dir=workspace / "cache",
    )
    batches = [{k: v[None] for k, v in data[i].items()} for i in range(len(data))]

    def loss(path: Path) -> float:
        net, _ = load_checkpoint(path)
        net.eval()
        total = 0.0
        with torch.no_grad():
            for b in batches:
                out = net(b["images"], b["intrinsics"], b["cam_from_world"], b["depth_min"], b["depth_max"],
                          sparse_depth=b["sparse_depth"])
                total += float(selfsup_loss(out.depths, b["photo_images"], b["intrinsics"],
                                            b["cam_from_world"], b["label_depth"], b["depth_min"],
                                            b["depth_max"], net.config.loss_weights,
                                            net.config.output_scales).total)
        return total / len(batches)

    done = adapt_checkpoint(workspace, workspace / "stereo", base, AdaptConfig(steps=12, lr=3e-3, **FAST),
                            progress=False)
    assert loss(done.checkpoint) < 0.98 * loss(base)  # 12 steps of a tiny random net


def test_the_stereo_command_adapts_first_and_runs_the_adapted_weights(workspace, base, capsys):
    argv = ["stereo", "--workspace_path", str(workspace), "--checkpoint", str(base), "--num_views", "3",
            "--max_image_size", "160", "--threads", "1", "--adapt_steps", "2", "--min_confidence", "0"]
    assert main(argv) == 0
    report = capsys.readouterr().out
    assert re.search(r"test-time adaptation: [\d.]+ s \([\d.]+ s per reference image\)", report), report
    adapted = workspace / "stereo" / "adapt" / "adapted.pt"
    for prov in (workspace / "stereo" / "provenance").glob("*.photometric.json"):
        assert json.loads(prov.read_text())["settings"]["checkpoint_sha256"] == file_sha256(adapted)
    saved = json.loads((workspace / "stereo" / "colmap_pvs_stereo.json").read_text())
    assert saved["checkpoint_used"] == str(adapted) and saved["config"]["adapt"]["steps"] == 2


def test_run_stereo_adapts_nothing_and_says_what_does(workspace, base):
    cfg = stereo_config(workspace_path=workspace, checkpoint=base, adapt_steps=2)
    with pytest.raises(ConfigError, match=r"adapt_steps=2: .*colmap_pvs\.adapt\.run_adapted_stereo\("):
        run_stereo(cfg)
    assert not (workspace / "stereo" / "adapt").exists()


def test_reconstruct_adapts_before_its_stereo_stage(analytic_scene, base, tmp_path):
    from colmap_pvs.reconstruct import reconstruct

    ws, out = analytic_scene["root"], tmp_path / "out"
    reconstruct(reconstruct_config(image_path=ws / "images", workspace_path=out, input_path=ws / "sparse",
                                   checkpoint=base, num_views=3, num_threads=1, max_image_size=64,
                                   adapt_steps=1, stop_after="stereo"))
    adapted = out / "dense" / "stereo" / "adapt" / "adapted.pt"
    provs = list((out / "dense" / "stereo" / "provenance").glob("*.photometric.json"))
    assert provs and all(json.loads(p.read_text())["settings"]["checkpoint_sha256"] == file_sha256(adapted)
                         for p in provs)


def test_self_training_adapts_on_the_base_runs_maps_then_runs_again(workspace, base, monkeypatch):
    # adapt_pseudo_labels: a first run with the base checkpoint writes the maps, the adaptation
    # crops them as pseudo-labels before any adapted weights exist, and the final maps are the
    # adapted network's
    stereo_dir = workspace / "stereo"
    adapted = stereo_dir / "adapt" / "adapted.pt"
    crops: list[bool] = []  # per pseudo-label crop: did adapted weights already exist?
    crop = real_dataset.crop_label_map

    def spy(label, *args, **kwargs):
        crops.append(adapted.exists())
        return crop(label, *args, **kwargs)

    monkeypatch.setattr(real_dataset, "crop_label_map", spy)
    cfg = stereo_config(workspace_path=workspace, checkpoint=base, num_views=3, max_image_size=160, threads=1,
                       adapt_steps=2, min_confidence=0.0, adapt_pseudo_labels="filled")
    result = run_adapted_stereo(cfg)
    assert crops and not any(crops)
    meta = json.loads((stereo_dir / "adapt" / "adapted.json").read_text())
    assert meta["fingerprint"]["labels"]["kind"] == "filled"
    assert result.adapt_seconds > meta["seconds"]  # the first run counts as adaptation time
    sha = file_sha256(adapted)
    assert sha != file_sha256(base)
    names = sorted(result.processed)
    for name in names:
        prov = json.loads((stereo_dir / "provenance" / f"{name}.photometric.json").read_text())
        assert prov["settings"]["checkpoint_sha256"] == sha
        assert (stereo_dir / "depth_maps" / f"{name}.filled.bin").is_file()
    # a rerun keeps everything (no first run, no adaptation)
    crops.clear()
    again = run_adapted_stereo(cfg)
    assert not crops and not again.processed and sorted(again.already_done) == names
    assert again.adapt_seconds == again.timings["adapt"] == pytest.approx(meta["seconds"])
    # other label settings: adapted again, on the labels of a new base run
    redo = run_adapted_stereo(replace_config(cfg, geom_max_depth_error=0.05))
    assert crops and not any(crops) and sorted(redo.processed) == names
    new_meta = json.loads((stereo_dir / "adapt" / "adapted.json").read_text())
    assert new_meta["fingerprint"]["labels"] != meta["fingerprint"]["labels"]


def test_bad_adaptation_settings():
    with pytest.raises(ConfigError):
        AdaptConfig(steps=-1)
    with pytest.raises(ConfigError):
        AdaptConfig(steps=1, lr=0.0)
    with pytest.raises(ConfigError, match="pseudo_labels"):
        AdaptConfig(steps=1, pseudo_labels="dense")
    with pytest.raises(ConfigError, match="adapt_steps"):
        stereo_config(workspace_path=Path("ws"), adapt_pseudo_labels="geometric")
    with pytest.raises(ConfigError, match="geom_fill"):
        stereo_config(workspace_path=Path("ws"), adapt_steps=5, adapt_pseudo_labels="filled", geom_fill=False)
