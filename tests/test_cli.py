"""The CLI: every subcommand is listed, flags come from configs, --config_file merges nested values."""

from __future__ import annotations

import json

import pytest

from colmap_pvs.cli.main import COMMANDS, _build_config, build_parser, main
from colmap_pvs.errors import ConfigError
from colmap_pvs.train import TrainConfig


def test_help_lists_every_subcommand(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    for cmd in COMMANDS:
        assert cmd.name.split()[0] in out


def test_every_built_command_has_a_config_and_function():
    for cmd in COMMANDS:
        assert cmd.planned is not None or (cmd.config and cmd.function)


def test_unknown_flag_is_rejected():
    with pytest.raises(SystemExit):
        main(["stereo", "--workspace_path", "w", "--no_such_flag", "1"])


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
