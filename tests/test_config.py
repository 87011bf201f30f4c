"""Configs: strict keys, typed coercion, CLI flag generation and saved configs."""

from __future__ import annotations

import argparse
import json
from dataclasses import FrozenInstanceError, dataclass, field
from pathlib import Path
from typing import Literal

import pytest
from scenes import stereo_config

from colmap_pvs.config import (
    add_config_arguments,
    config_from_args,
    config_from_dict,
    config_json_bytes,
    config_to_dict,
    load_config,
    replace_config,
)
from colmap_pvs.errors import ConfigError
from colmap_pvs.io.files import atomic_write_bytes


@dataclass(frozen=True)
class Inner:
    width: int = 8


@dataclass(frozen=True)
class Demo:
    path: Path
    count: int = 3
    ratio: float = 0.5
    flag: bool = False
    mode: Literal["a", "b"] = "a"
    sizes: tuple[int, ...] = (1, 2)
    maybe: float | None = None
    inner: Inner = field(default_factory=Inner)


def test_unknown_key_is_an_error_naming_it():
    with pytest.raises(ConfigError, match="colour"):
        config_from_dict(Demo, {"path": "x", "colour": 1})
    with pytest.raises(ConfigError, match="depth"):
        config_from_dict(Demo, {"path": "x", "inner": {"depth": 1}})


@pytest.mark.parametrize(
    "key,value",
    [("count", "three"), ("count", 2.5), ("flag", "maybe"), ("mode", "c"), ("ratio", True), ("sizes", 3)],
)
def test_bad_values_are_rejected(key, value):
    with pytest.raises(ConfigError, match=key):
        config_from_dict(Demo, {"path": "x", key: value})


def test_round_trip_and_frozen(tmp_path):
    cfg = config_from_dict(Demo, {"path": "a/b", "count": "4", "flag": "true", "sizes": [3, 4], "maybe": 1})
    assert cfg.path == Path("a/b") and cfg.count == 4 and cfg.flag is True and cfg.sizes == (3, 4)
    assert cfg.maybe == 1.0
    with pytest.raises(FrozenInstanceError):
        cfg.count = 5  # type: ignore[misc]
    assert config_from_dict(Demo, config_to_dict(cfg)) == cfg
    atomic_write_bytes(tmp_path / "c.json", config_json_bytes(cfg, note="x"))
    assert json.loads((tmp_path / "c.json").read_text())["note"] == "x"
    assert load_config(Demo, tmp_path / "c.json") == cfg
    assert not [p for p in tmp_path.iterdir() if p.suffix == ".tmp"]
    assert replace_config(cfg, count=9).count == 9
    with pytest.raises(ConfigError):
        replace_config(cfg, nope=1)


def test_cli_flags_come_from_the_dataclass():
    parser = argparse.ArgumentParser()
    add_config_arguments(parser, Demo, required=("path",))
    args = parser.parse_args(["--path", "p", "--flag", "1", "--sizes", "5", "6", "--mode", "b"])
    cfg = config_from_args(Demo, args)
    assert cfg == Demo(path=Path("p"), flag=True, sizes=(5, 6), mode="b")
    # Flags that are not given keep the dataclass default (no second copy of defaults).
    assert config_from_args(Demo, parser.parse_args(["--path", "p"])) == Demo(path=Path("p"))
    with pytest.raises(SystemExit):
        parser.parse_args(["--path", "p", "--mode", "z"])
    with pytest.raises(SystemExit):
        parser.parse_args([])


def test_stereo_config_built_in_python_refuses_a_float_for_an_int_field():
    from colmap_pvs.stereo import CompletionConfig, PhotometricConfig

    cfg = stereo_config(workspace_path=Path("w"), geom_fill_min_sources=4)
    assert cfg.completion.min_sources == 4
    bad = ((CompletionConfig, "min_sources", 2.0, "geom_fill_min_sources"),
           (PhotometricConfig, "num_views", True, "num_views"))
    for cls, name, value, flag in bad:  # the message names the flag
        with pytest.raises(ConfigError, match=f"{flag} must be an integer"):
            cls(**{name: value})


@dataclass(frozen=True)
class Pair:
    lim: tuple[float, int] = (1.0, 2)


def test_fixed_length_tuples():
    assert config_from_dict(Pair, {"lim": ["0.5", "3"]}).lim == (0.5, 3)
    with pytest.raises(ConfigError, match="lim"):
        config_from_dict(Pair, {"lim": [1.0]})


def test_atomic_outputs_are_not_private(tmp_path):
    import os
    import stat

    from colmap_pvs.io.files import atomic_write_bytes, make_temp_dir

    mask = os.umask(0o022)
    try:
        f = atomic_write_bytes(tmp_path / "a.bin", b"x")
        d = make_temp_dir(tmp_path, ".x.")
    finally:
        os.umask(mask)
    assert stat.S_IMODE(f.stat().st_mode) == 0o644
    assert stat.S_IMODE(d.stat().st_mode) == 0o755


def test_load_config_reads_a_variant_over_its_base(tmp_path):
    base = Demo(path=Path("p"), count=5, inner=Inner(width=4))
    atomic_write_bytes(tmp_path / "base.json", config_json_bytes(base))
    (tmp_path / "variant.json").write_text(json.dumps(
        {"base": "base.json", "config_class": "Demo", "config": {"count": 6}}))
    assert load_config(Demo, tmp_path / "variant.json") == Demo(path=Path("p"), count=6, inner=Inner(width=4))
    (tmp_path / "base.json").write_text(json.dumps(
        {"base": "variant.json", "config_class": "Demo", "config": {}}))
    with pytest.raises(ConfigError, match="comes back"):
        load_config(Demo, tmp_path / "variant.json")
