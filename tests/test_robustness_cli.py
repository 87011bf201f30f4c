"""Issue 11, command line: every --help works, bare booleans, COLMAP's patch_match_stereo flags,
OS errors as one line."""

from __future__ import annotations

import errno
import re

import pytest

from colmap_pvs.cli.main import COMMANDS, build_parser, main, translate_colmap_flags
from colmap_pvs.errors import ConfigError


def _help_argvs() -> list[list[str]]:
    argvs = [["--help"]]
    groups = set()
    for cmd in COMMANDS:
        words = cmd.name.split()
        argvs.append([*words, "--help"])
        if len(words) > 1:
            groups.add(words[0])
    argvs += [[g, "--help"] for g in sorted(groups)]
    argvs.append(["patch_match_stereo", "--help"])
    return argvs


@pytest.mark.parametrize("argv", _help_argvs(), ids=lambda a: " ".join(a))
def test_help_of_every_command_and_subcommand(argv, capsys):
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert "usage: colmap-pvs" in out
    if argv[0] in {c.name.split()[0] for c in COMMANDS} and len(argv) == 2 and " " not in argv[0]:
        assert "--" in out  # flags are listed


def test_bare_boolean_flags_and_explicit_values():
    parser = build_parser()
    assert parser.parse_args(["stereo", "--workspace_path", "w", "--overwrite"]).overwrite is True
    args = parser.parse_args(["stereo", "--workspace_path", "w", "--overwrite", "false", "--previews"])
    assert args.overwrite is False and args.previews is True
    args = parser.parse_args(["stereo", "--previews", "--workspace_path", "w"])  # bare, then a flag
    assert args.previews is True and args.workspace_path == "w"
    assert parser.parse_args(["stereo", "--workspace_path", "w", "--previews=0"]).previews is False
    with pytest.raises(SystemExit):
        parser.parse_args(["stereo", "--workspace_path", "w", "--previews", "maybe"])


def test_colmap_patch_match_stereo_flags_translate(caplog):
    argv = ["--workspace_path", "dense", "--workspace_format", "COLMAP",
            "--PatchMatchStereo.max_image_size", "2000", "--PatchMatchStereo.geom_consistency", "false",
            "--PatchMatchStereo.num_threads=-1", "--PatchMatchStereo.gpu_index", "-1",
            "--PatchMatchStereo.window_radius", "7", "--PatchMatchStereo.filter", "1"]
    parser = build_parser()
    args = parser.parse_args(["patch_match_stereo", *argv])
    assert args.command == "stereo"
    with caplog.at_level("WARNING"):
        values = translate_colmap_flags(args)
    assert values == {"max_image_size": 2000, "geom_consistency": False, "threads": 0, "device": "auto"}
    assert "PatchMatchStereo.window_radius" in caplog.text and "PatchMatchStereo.filter" in caplog.text
    assert "max_image_size" not in caplog.text  # only flags without a meaning are named
    # The same flags work on `colmap-pvs stereo`, and a GPU index selects CUDA.
    args = parser.parse_args(["stereo", "--workspace_path", "d", "--PatchMatchStereo.gpu_index", "0"])
    assert translate_colmap_flags(args) == {"device": "cuda"}
    args = parser.parse_args(["stereo", "--workspace_path", "d", "--workspace_format", "PMVS"])
    with pytest.raises(ConfigError, match="PMVS"):
        translate_colmap_flags(args)
    # Our own flag and its COLMAP alias together must agree.
    args = parser.parse_args(["stereo", "--workspace_path", "d", "--max_image_size", "5",
                              "--PatchMatchStereo.max_image_size", "7"])
    with pytest.raises(ConfigError, match="max_image_size"):
        translate_colmap_flags(args)


def test_colmap_flags_with_an_equivalent_are_translated_into_the_config(caplog):
    """COLMAP's geometric filter thresholds and its fixed depth range have equivalents: they change the
    config (good values, not only bad ones) and are not named as ignored."""
    from colmap_pvs.cli.main import _build_config
    from colmap_pvs.stereo import StereoConfig
    from colmap_pvs.stereo.config import PhotometricConfig

    argv = ["patch_match_stereo", "--workspace_path", "d",
            "--PatchMatchStereo.filter_min_num_consistent", "4",
            "--PatchMatchStereo.filter_min_triangulation_angle", "1.5",
            "--PatchMatchStereo.filter_geom_consistency_max_cost", "1",
            "--PatchMatchStereo.depth_min", "0.5", "--PatchMatchStereo.depth_max", "12",
            "--PatchMatchStereo.num_samples", "20"]
    args = build_parser().parse_args(argv)
    with caplog.at_level("WARNING"):
        for key, value in translate_colmap_flags(args).items():
            setattr(args, key, value)
    config = _build_config(StereoConfig, args)
    assert config.geometric.min_consistent == 4 and config.geometric.min_triangulation_angle == 1.5
    assert config.geometric.max_reproj_error == 1.0 and config.photometric.depth_range == (0.5, 12.0)
    assert "num_samples" in caplog.text
    assert not any(k in caplog.text for k in ("filter_min", "filter_geom", "depth_m"))
    # COLMAP's -1 (the ranges from the sparse points) is our default; one bound alone is refused
    args = build_parser().parse_args(["stereo", "--workspace_path", "d", "--PatchMatchStereo.depth_min", "-1",
                                      "--PatchMatchStereo.depth_max", "-1"])
    assert translate_colmap_flags(args) == {}
    args = build_parser().parse_args(["stereo", "--workspace_path", "d", "--PatchMatchStereo.depth_max", "3"])
    with pytest.raises(ConfigError, match="depth_max 3 needs --PatchMatchStereo.depth_min"):
        translate_colmap_flags(args)
    args = build_parser().parse_args(["stereo", "--workspace_path", "d", "--depth_range", "1", "2",
                                      "--PatchMatchStereo.depth_min", "1",
                                      "--PatchMatchStereo.depth_max", "3"])
    with pytest.raises(ConfigError, match="contradicts --depth_range"):
        translate_colmap_flags(args)
    with pytest.raises(ConfigError, match="depth_range"):
        PhotometricConfig(depth_range=(2.0, 1.0))


def test_colmap_flags_reach_the_config(tmp_path, capsys, monkeypatch):
    import colmap_pvs.adapt as adapt

    seen = []

    def run_stereo(config):  # the config the command built; stop there
        seen.append(config)
        raise ConfigError("stopped by the test")

    monkeypatch.setattr(adapt, "run_adapted_stereo", run_stereo)  # the stereo command's step
    ws = str(tmp_path / "ws")
    code = main(["patch_match_stereo", "--workspace_path", ws, "--workspace_format", "COLMAP",
                 "--PatchMatchStereo.max_image_size", "320", "--PatchMatchStereo.geom_consistency", "false",
                 "--PatchMatchStereo.num_threads", "3", "--PatchMatchStereo.gpu_index", "-1"])
    assert code == 1 and "stopped by the test" in capsys.readouterr().err
    config = seen[0]
    assert config.photometric.max_image_size == 320 and config.geometric.enabled is False
    assert config.threads == 3 and config.device == "auto"
    seen.clear()  # the same flags on `stereo`, and COLMAP's -1s
    assert main(["stereo", "--workspace_path", ws, "--PatchMatchStereo.max_image_size", "-1",
                 "--PatchMatchStereo.num_threads", "-1"]) == 1
    assert seen[0].photometric.max_image_size == -1 and seen[0].threads == 0
    # a bad value fails before the step runs, naming the flag
    code = main(["patch_match_stereo", "--workspace_path", str(tmp_path / "nowhere"),
                 "--PatchMatchStereo.max_image_size", "big"])
    assert code == 1 and "max_image_size" in capsys.readouterr().err and len(seen) == 1


def test_os_errors_are_one_line(tmp_path, monkeypatch, capsys):
    import colmap_pvs.views as views

    def boom(config):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "stereo" / "x.bin"))

    monkeypatch.setattr(views, "run_select_views", boom)
    assert main(["select-views", "--workspace_path", str(tmp_path)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "No space left on device" in err and "x.bin" in err


@pytest.mark.parametrize("flags, message", [
    (["--PatchMatchStereo.num_threads", "100000"],
     r"--PatchMatchStereo\.num_threads must be -1 \(all cores\)"),
    (["--PatchMatchStereo.depth_min", "0", "--PatchMatchStereo.depth_max", "10"],
     r"--PatchMatchStereo\.depth_min 0 --PatchMatchStereo\.depth_max 10: .*0 < depth_min < depth_max"),
])
def test_a_bad_colmap_value_is_named_as_the_user_typed_it(flags, message, tmp_path, capsys):
    """Not as the colmap-pvs flag it becomes (``threads``, ``depth_range``), with COLMAP's values."""
    assert main(["patch_match_stereo", "--workspace_path", str(tmp_path), *flags]) == 1
    assert re.search(message, capsys.readouterr().err)
