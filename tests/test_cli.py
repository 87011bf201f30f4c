"""The CLI: every subcommand is listed, flags come from configs, --config_file merges nested values."""

from __future__ import annotations

import dataclasses
import inspect
import json
from pathlib import Path

import pytest

from colmap_pvs.cli.colmap_flags import translate_colmap_flags
from colmap_pvs.cli.main import COMMANDS, _build_config, _load, build_parser, main
from colmap_pvs.config import config_to_dict
from colmap_pvs.errors import ConfigError
from colmap_pvs.train import TrainConfig


def test_help_lists_every_subcommand(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    for cmd in COMMANDS:
        assert cmd.name.split()[0] in out


def test_every_built_command_has_a_config_and_function():
    """Every ``module:attr`` of the table names what it should: a frozen config dataclass, a function
    whose one required argument is that config, a report function."""
    for cmd in COMMANDS:
        if cmd.planned is not None:
            continue
        assert cmd.config and cmd.function, cmd.name
        config_cls = _load(cmd.config)
        assert dataclasses.is_dataclass(config_cls) and config_cls.__dataclass_params__.frozen, cmd.config
        params = list(inspect.signature(_load(cmd.function)).parameters.values())
        annotation = params[0].annotation if params else None
        assert getattr(annotation, "__name__", annotation) == config_cls.__name__, cmd.function
        assert all(p.default is not inspect.Parameter.empty for p in params[1:]), cmd.function
        if cmd.report is not None:
            report = _load(cmd.report)
            assert callable(report) and len(inspect.signature(report).parameters) >= 1, cmd.report


def test_unknown_flag_is_rejected(capsys):
    assert main(["stereo", "--workspace_path", "w", "--no_such_flag", "1"]) == 2
    assert "unrecognized argument '--no_such_flag'" in capsys.readouterr().err


@pytest.mark.parametrize(("typed", "meant"), [("--num-views", "--num_views"),
                                              ("--max_imagesize", "--max_image_size"),
                                              ("--geom-fill", "--geom_fill")])
def test_mistyped_flag_gets_one_line_with_did_you_mean(capsys, typed, meant):
    assert main(["stereo", "--workspace_path", "w", typed, "5"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"did you mean {meant}?" in err and "usage:" not in err


def test_bad_flag_value_is_one_line_naming_the_flag(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["stereo", "--workspace_path", "w", "--max_image_size", "big"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--max_image_size" in err and "'big'" in err and "usage:" not in err


def test_stereo_help_groups_flags_by_pass_and_lists_colmap_flags_only_under_colmaps_name(capsys):
    for command in ("stereo", "patch_match_stereo"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        out = capsys.readouterr().out
        flags = {line.split()[0].split("=")[0] for line in out.splitlines() if line.startswith("  --")}
        assert "--geom_min_consistent" in flags and "geometric pass:" in out and "dense completion:" in out
        if command == "stereo":
            wrapped = [line for line in out.splitlines() if line.startswith(" " * 20)]
            assert not wrapped, wrapped  # one line a flag, with its default
            assert not any(f.startswith("--PatchMatchStereo.") for f in flags)
        else:
            assert "--PatchMatchStereo.max_image_size" in flags
    # accepted by both names
    args = build_parser().parse_args(["stereo", "--workspace_path", "w",
                                      "--PatchMatchStereo.max_image_size", "320"])
    assert translate_colmap_flags(args) == {"max_image_size": 320}


def test_config_file_with_nested_values_and_flag_override(tmp_path):
    path = tmp_path / "train.json"
    data = {"output_dir": str(tmp_path / "run"), "steps": 7, "model": {"visibility": False}}
    path.write_text(json.dumps(data))
    args = build_parser().parse_args(["train", "--config_file", str(path), "--steps", "9"])
    cfg = _build_config(TrainConfig, args)
    assert cfg.steps == 9 and cfg.model.visibility is False and cfg.output_dir == tmp_path / "run"
    path.write_text(json.dumps({"model": {"no_such_key": 1}}))
    with pytest.raises(ConfigError, match="no_such_key"):
        _build_config(TrainConfig, build_parser().parse_args(["train", "--config_file", str(path)]))


def test_library_errors_become_exit_code_1(tmp_path, capsys):
    assert main(["select-views", "--workspace_path", str(tmp_path / "nowhere")]) == 1
    assert "nowhere" in capsys.readouterr().err


def test_removed_flags_are_accepted_with_their_value_and_abbreviations_are_not(capsys, tmp_path):
    ws = str(tmp_path / "missing_ws")
    # the removed option with its fixed value: accepted (a warning), the run then fails on the workspace
    assert main(["stereo", "--workspace_path", ws, "--prior_blend_window", "7"]) == 1
    assert "workspace folder" in capsys.readouterr().err
    assert main(["stereo", "--workspace_path", ws, "--prior_blend_window", "5"]) == 1
    assert "'prior_blend_window' was removed; it is now always 7" in capsys.readouterr().err
    assert main(["reconstruct", "--image_path", ws, "--workspace_path", ws,
                 "--geom_max_normal_error", "90"]) == 1
    assert "geom_max_normal_error" in capsys.readouterr().err
    assert main(["stereo", "--workspace_path", ws, "--num_view", "3"]) == 2  # no silent abbreviation
    assert "did you mean --num_views?" in capsys.readouterr().err


def test_config_file_errors_name_the_file(tmp_path, capsys):
    path = tmp_path / "stereo.json"
    path.write_text(json.dumps({"geometric": {"min_consistent": "abc"}}))
    assert main(["stereo", "--workspace_path", str(tmp_path), "--config_file", str(path)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(path) in err and "min_consistent" in err


def test_a_config_file_changes_its_base_and_flags_change_both(tmp_path):
    base = tmp_path / "base.json"
    base.write_text(json.dumps({"config_class": "TrainConfig",
                                "config": {"steps": 7, "lr": 0.5, "model": {"visibility": False}}}))
    (tmp_path / "sub").mkdir()
    variant = tmp_path / "sub" / "variant.json"  # "base" is relative to the file that names it
    variant.write_text(json.dumps({"base": "../base.json", "config_class": "TrainConfig",
                                   "config": {"steps": 8, "model": {"truncation": False}}}))
    cfg = _build_config(TrainConfig, build_parser().parse_args(["train", "--config_file", str(variant),
                                                                 "--lr", "0.25"]))
    assert (cfg.steps, cfg.lr, cfg.model.visibility, cfg.model.truncation) == (8, 0.25, False, False)
    base.write_text(json.dumps({"base": "sub/variant.json", "config_class": "TrainConfig", "config": {}}))
    with pytest.raises(ConfigError, match="comes back"):
        _build_config(TrainConfig, build_parser().parse_args(["train", "--config_file", str(variant)]))


_ROOT = Path(__file__).parents[1]
RECORDED_CONFIGS = sorted([*(_ROOT / "benchmarks" / "configs").glob("*.json"),
                           *(_ROOT / "colmap_pvs" / "weights").glob("*.train_config.json")])


@pytest.mark.parametrize("path", RECORDED_CONFIGS, ids=lambda p: str(p.relative_to(_ROOT)))
def test_every_recorded_training_config_still_loads(path):
    def resolved(p):
        args = build_parser().parse_args(["train", "--config_file", str(p)])
        return config_to_dict(_build_config(TrainConfig, args))

    cfg = resolved(path)
    saved = json.loads(path.read_text())
    if "base" in saved:  # a variant: what it does not set is its base's
        base = resolved(path.parent / saved["base"])
        assert [k for k in base if k not in saved["config"] and cfg[k] != base[k]] == []
        assert cfg != base
    # a recorded fine-tune starts from weights kept in the repository under a release name (paths
    # relative to its root), not from the default checkpoint, which the next release replaces
    init = cfg["init_weights"]
    assert init is None or ((_ROOT / init).is_file() and Path(init).name != "pvsnet_default.pt"), init


@pytest.mark.parametrize("preset, expected", [
    ({}, {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": "1000"}),
    ({"OMP_WAIT_POLICY": "ACTIVE"}, {"OMP_WAIT_POLICY": "ACTIVE", "GOMP_SPINCOUNT": None}),
    ({"GOMP_SPINCOUNT": "5"}, {"OMP_WAIT_POLICY": None, "GOMP_SPINCOUNT": "5"}),
])
def test_the_command_line_sets_how_openmp_waits_unless_the_user_did(preset, expected):
    """Importing the command line (before it imports torch) sets OpenMP's short spin, then sleep
    (``colmap_pvs.openmp.WAIT_ENV``), and keeps a user's own setting of either variable."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    code = ("import json, os, sys; import colmap_pvs.openmp as o; real, torch_before = o.set_wait_env, []; "
            "o.set_wait_env = lambda e: (torch_before.append('torch' in sys.modules), real(e)); "
            "import colmap_pvs.cli.main; "
            "print(json.dumps({k: os.environ.get(k) for k in ('OMP_WAIT_POLICY', 'GOMP_SPINCOUNT')})); "
            "print(json.dumps(torch_before))")
    out = subprocess.run([sys.executable, "-c", code], env={**env, **preset}, capture_output=True, text=True,
                         check=True).stdout.splitlines()
    assert json.loads(out[-2]) == expected
    assert json.loads(out[-1]) == [False]  # set once, before torch was imported


def test_ray_workers_wait_as_the_command_line_or_as_the_user_said():
    """Ray's workers get :func:`colmap_pvs.openmp.wait_env`: the user's own setting where there is one."""
    from colmap_pvs.openmp import WAIT_ENV, wait_env

    assert wait_env({"HOME": "/h"}) == WAIT_ENV and wait_env({}) is not WAIT_ENV
    assert wait_env({"OMP_WAIT_POLICY": "ACTIVE", "HOME": "/h"}) == {"OMP_WAIT_POLICY": "ACTIVE"}
    assert wait_env({"GOMP_SPINCOUNT": "5"}) == {"GOMP_SPINCOUNT": "5"}
