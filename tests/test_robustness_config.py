"""Issue 11: bad config values are refused where they enter, naming the setting and the value."""

from __future__ import annotations

from pathlib import Path

import pytest

from colmap_pvs.cli.main import main
from colmap_pvs.config import config_from_dict
from colmap_pvs.errors import ConfigError
from colmap_pvs.fusion import FuseConfig
from colmap_pvs.stereo import StereoConfig


@pytest.mark.parametrize(
    ("key", "value"),
    [("min_confidence", 2), ("min_confidence", "nan"), ("min_confidence", -0.1), ("threads", -3),
     ("num_views", 1), ("min_sources", 0), ("max_image_size", 8), ("prior_blend_texture", 2),
     ("prior_blend_texture", -0.01), ("prior_agreement_scale", -1), ("geom_min_consistent", 0),
     ("geom_fill_min_sources", 0), ("adapt_steps", -1), ("ray_worker_threads", 0)],
)
def test_stereo_config_refuses_bad_values(key, value):
    with pytest.raises(ConfigError, match=key):
        config_from_dict(StereoConfig, {"workspace_path": "w", key: value})


def test_removed_stereo_options_are_accepted_only_with_their_fixed_value(caplog):
    """An old saved config or script may name an option that is gone: its fixed value is accepted
    with a warning naming it, any other value is refused naming it."""
    for key, fixed in StereoConfig.REMOVED_OPTIONS.items():
        caplog.clear()
        cfg = config_from_dict(StereoConfig, {"workspace_path": "w", key: fixed})
        assert cfg == StereoConfig(workspace_path=Path("w"))
        assert any(key in r.getMessage() and r.levelname == "WARNING" for r in caplog.records)
        with pytest.raises(ConfigError, match=key):
            config_from_dict(StereoConfig, {"workspace_path": "w", key: fixed + 1})


def test_old_flat_stereo_config_file_is_read_as_the_nested_config(tmp_path):
    """A resolved config saved before the configs were nested (flat flag names) still loads."""
    flat = {"workspace_path": "w", "num_views": 3, "geom_consistency": False, "geom_fill_min_sources": 1,
            "adapt_steps": 0, "ray_workers": 2, "wide_sources": 0, "geom_max_normal_error": 180.0}
    cfg = config_from_dict(StereoConfig, flat)
    assert cfg.photometric.num_views == 3 and cfg.geometric.enabled is False
    assert cfg.completion.min_sources == 1 and cfg.ray.workers == 2


def test_stereo_cli_refuses_bad_values(tmp_path, capsys):
    for flag, value in (("--min_confidence", "2"), ("--min_confidence", "nan"), ("--threads", "-3")):
        assert main(["stereo", "--workspace_path", str(tmp_path), flag, value]) == 1
        err = capsys.readouterr().err
        assert flag[2:] in err and value in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize(
    "argv",
    [["stereo", "--workspace_path", "w", "--threads"],
     ["stereo", "--workspace_path", "w", "--ray_worker_threads"],
     ["patch_match_stereo", "--workspace_path", "w", "--PatchMatchStereo.num_threads"],
     ["mesh", "--input_path", "c.ply", "--num_threads"],
     ["reconstruct", "--image_path", "i", "--workspace_path", "w", "--num_threads"],
     ["import-poses", "--image_path", "i", "--poses_path", "p.txt", "--output_path", "o", "--num_threads"],
     ["demo", "--output_path", "o", "--threads"], ["train", "--output_dir", "o", "--torch_threads"]],
    ids=lambda argv: argv[0] + " " + argv[-1],
)
def test_every_thread_count_is_bounded_with_a_one_line_error(argv, tmp_path, monkeypatch, capsys):
    """`stereo --threads 100000` crashed (SIGSEGV), `mesh --num_threads 100000` aborted: every threads
    option of every command refuses a count far above the machine's CPUs, naming the value and the bound."""
    monkeypatch.chdir(tmp_path)
    assert main([*argv, "100000"]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "100000" in err and "256" in err, err
    assert argv[-1].rsplit(".", 1)[-1].lstrip("-").replace("num_", "") in err
    assert not (tmp_path / "o").exists()


def test_the_test_time_adaptation_thread_count_is_bounded():
    from colmap_pvs.adapt import AdaptConfig

    with pytest.raises(ConfigError, match="threads must be 0 .* 1 to 256 .*got 100000"):
        AdaptConfig(threads=100000)


def test_nan_is_never_a_number():
    with pytest.raises(ConfigError, match="nan"):
        config_from_dict(FuseConfig, {"workspace_path": "w", "max_depth_error": "nan"})


@pytest.mark.parametrize(("key", "value"), [("min_confidence", 1.5), ("min_confidence", -1)])
def test_fuse_config_refuses_bad_values(key, value):
    with pytest.raises(ConfigError, match=key):
        FuseConfig(workspace_path=Path("w"), **{key: value})


@pytest.mark.parametrize(("key", "value"), [("num_threads", -3), ("num_threads", 0), ("mesh_depth", 0),
                                            ("max_image_size", 4)])
def test_reconstruct_config_refuses_bad_values(key, value):
    from colmap_pvs.reconstruct import ReconstructConfig

    with pytest.raises(ConfigError, match=key):
        config_from_dict(ReconstructConfig, {"image_path": "i", "workspace_path": "w", key: value})
