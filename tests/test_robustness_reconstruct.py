"""Issue 11, ``reconstruct``: provenance (a changed setting recomputes with --overwrite or is refused,
naming it), quiet pycolmap log in the workspace, a progress bar per SfM stage, a closing summary that
names where to look, and bad photos refused before SfM."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import disk_full_after_writing_half, make_tiny_checkpoint
from scenes import reconstruct_config, stereo_config

from colmap_pvs.cli.main import main
from colmap_pvs.errors import ConfigError, WorkspaceError
from colmap_pvs.fusion.config import FUSION_RULES
from colmap_pvs.io.maps import read_depth_map
from colmap_pvs.reconstruct import reconstruct
from colmap_pvs.stereo.config import FORMAT_VERSIONS

GLOG_LINE = re.compile(r"^[IWEF]\d{8} \d\d:\d\d:\d\d", re.MULTILINE)


def test_changed_settings_are_refused_or_recomputed(analytic_scene, tmp_path, capfd):
    ws = analytic_scene["root"]
    ckpt = make_tiny_checkpoint(tmp_path / "tiny.pt")
    out = tmp_path / "out"
    argv = ["reconstruct", "--image_path", str(ws / "images"), "--workspace_path", str(out),
            "--input_path", str(ws / "sparse"), "--checkpoint", str(ckpt), "--num_views", "3",
            "--mesh_depth", "5", "--num_threads", "1", "--network_scale", "0.5", "--max_image_size", "64"]
    assert main(argv) == 0
    captured = capfd.readouterr()
    assert not GLOG_LINE.search(captured.err), "pycolmap's log must go to the workspace, not the terminal"
    logs = list((out / "logs").glob("pycolmap*"))
    assert logs and any(GLOG_LINE.search(p.read_text()) for p in logs)
    for where in ("previews:", "fused cloud:", "mesh:", "pycolmap log:"):
        assert where in captured.out
    assert list((out / "dense" / "stereo" / "previews").glob("*.depth.png"))
    depth = out / "dense" / "stereo" / "depth_maps" / "view_000.png.geometric.bin"
    assert max(read_depth_map(depth).shape) == 64

    # Another --max_image_size: refused, naming the setting, both values and --overwrite.
    assert main([*argv[:-1], "48"]) == 1
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "max_image_size" in err[0] and "64" in err[0] and "48" in err[0]
    assert "--overwrite" in err[0] and "stereo" in err[0]
    assert max(read_depth_map(depth).shape) == 64  # nothing was touched
    # the network's scale reaches stereo and is one of its settings
    saved = json.loads((out / "dense" / "stereo" / "colmap_pvs_stereo.json").read_text())["config"]
    assert saved["photometric"]["network_scale"] == 0.5
    assert main([*argv, "--network_scale", "1.5"]) == 1
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "network_scale" in err[0] and "1.5" in err[0] and "stereo" in err[0]

    # With --overwrite only stereo and what follows it are recomputed.
    config = reconstruct_config(image_path=ws / "images", workspace_path=out, input_path=ws / "sparse",
                               checkpoint=ckpt, num_views=3, mesh_depth=5, num_threads=1, max_image_size=48,
                               overwrite=True)
    result = reconstruct(config)
    assert "undistort" in result.resumed and "stereo" not in result.resumed and "fusion" not in result.resumed
    assert max(read_depth_map(depth).shape) == 48
    # ... and then the new settings are the workspace's: a plain rerun resumes everything.
    result = reconstruct(reconstruct_config(**{**config.__dict__, "overwrite": False}))
    assert {"undistort", "stereo", "fusion", "mesh"} <= set(result.resumed)

    # The same checkpoint path with other weights is a changed checkpoint.
    make_tiny_checkpoint(ckpt, regularization_channels=8)
    with pytest.raises(ConfigError, match="checkpoint.*content"):
        reconstruct(reconstruct_config(**{**config.__dict__, "overwrite": False}))

    # Another fusion method only recomputes fusion and mesh.
    make_tiny_checkpoint(ckpt)
    with pytest.raises(ConfigError, match="fusion_method"):
        reconstruct(reconstruct_config(**{**config.__dict__, "overwrite": False, "fusion_method": "colmap"}))
    result = reconstruct(reconstruct_config(**{**config.__dict__, "fusion_method": "colmap"}))
    assert "stereo" in result.resumed and "fusion" not in result.resumed

    # --overwrite with nothing changed recomputes every stage.
    result = reconstruct(reconstruct_config(**{**config.__dict__, "fusion_method": "colmap"}))
    assert result.resumed == ["features", "matching", "mapping"]  # given by --input_path


def test_bad_photos_are_refused_before_sfm(analytic_scene, tmp_path):
    images = tmp_path / "photos"
    shutil.copytree(analytic_scene["root"] / "images", images)
    (images / "view_001.png").write_bytes(b"")
    data = (images / "view_002.png").read_bytes()
    (images / "view_002.png").write_bytes(data[: len(data) // 3])
    pattern = r"2 of 5 photos.*view_001\.png.*empty.*view_002\.png.*truncated"
    with pytest.raises(WorkspaceError, match=pattern):
        reconstruct(reconstruct_config(image_path=images, workspace_path=tmp_path / "out"))
    assert not (tmp_path / "out").exists()


def test_sfm_stages_have_progress_bars_and_a_quiet_log(tmp_path, capfd):
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur((rng.random((600, 800)) * 255).astype(np.uint8), (0, 0), 2)
    images = tmp_path / "photos"
    images.mkdir()
    for i in range(4):
        cv2.imwrite(str(images / f"{i}.png"), texture[50:450, 60 * i : 60 * i + 500])
    result = reconstruct(reconstruct_config(image_path=images, workspace_path=tmp_path / "out",
                                           max_num_features=256, num_threads=1, stop_after="matching"))
    assert result.stage_seconds.keys() >= {"features", "matching"}
    err = capfd.readouterr().err
    assert not GLOG_LINE.search(err)
    assert re.search(r"features: 100%.*4/4", err) and re.search(r"matching: 100%.*6/6", err)


def test_pycolmap_log_goes_to_the_file_unless_disabled(tmp_path, capfd):
    import pycolmap

    from colmap_pvs.io.pycolmap_output import pycolmap_log_to_file

    with pycolmap_log_to_file(tmp_path / "logs") as folder:
        pycolmap.logging.info("quiet message")
    assert folder == tmp_path / "logs"
    assert "quiet message" not in capfd.readouterr().err
    assert "quiet message" in "".join(p.read_text() for p in folder.glob("pycolmap.log.*"))
    with pycolmap_log_to_file(tmp_path / "logs2", enabled=False) as folder:  # --log_level DEBUG
        pycolmap.logging.info("loud message")
    assert folder is None and "loud message" in capfd.readouterr().err


def test_reconstruct_holds_a_stereo_config_with_stereos_defaults_and_checks(tmp_path):
    """``reconstruct`` takes every stereo setting as the stereo step's own config (one source of
    defaults and ranges), except its workspace and ``overwrite``; previews are on by default."""
    from colmap_pvs.config import config_flags
    from colmap_pvs.reconstruct import ReconstructConfig
    from colmap_pvs.stereo import StereoConfig
    from colmap_pvs.stereo.config import NETWORK_SCALE_MAX

    rec = reconstruct_config(image_path=tmp_path, workspace_path=tmp_path / "w")
    assert rec.stereo.photometric == stereo_config(workspace_path=tmp_path).photometric
    assert rec.stereo.previews is True
    flags = config_flags(ReconstructConfig)
    own = {"workspace_path", "overwrite"}  # reconstruct's own; stereo's are set by reconstruct
    assert all(flags[f].path[0] == "stereo" for f in config_flags(StereoConfig) if f not in own)
    assert all(flags[f].path == (f,) for f in own)
    for ok in (0.25, NETWORK_SCALE_MAX):
        rec = reconstruct_config(image_path=tmp_path, workspace_path=tmp_path / "w", network_scale=ok,
                                 geom_min_consistent=3)
        assert rec.stereo.photometric.network_scale == ok and rec.stereo.geometric.min_consistent == 3
    for bad in (0.2, NETWORK_SCALE_MAX + 0.1):
        with pytest.raises(ConfigError, match="network_scale"):
            reconstruct_config(image_path=tmp_path, workspace_path=tmp_path / "w", network_scale=bad)


def _two_overlapping_photos(images):
    """Two crops of one random texture, 40 px apart: enough SIFT for the features stage."""
    rng = np.random.default_rng(1)
    texture = cv2.GaussianBlur((rng.random((400, 500)) * 255).astype(np.uint8), (0, 0), 3)
    images.mkdir()
    for i in range(2):
        cv2.imwrite(str(images / f"{i}.png"), texture[:, 40 * i : 40 * i + 420])
    return images


def test_sift_peak_threshold_reaches_extraction_and_is_a_features_setting(tmp_path):
    """A lower SIFT peak threshold finds more keypoints; changing it is refused (naming it and the
    features stage), and ``overwrite`` extracts again."""
    import sqlite3

    images = _two_overlapping_photos(tmp_path / "photos")

    def keypoints(peak: float, overwrite: bool = False) -> list[int]:
        reconstruct(reconstruct_config(image_path=images, workspace_path=tmp_path / "out", num_threads=1,
                                      sift_peak_threshold=peak, stop_after="features", overwrite=overwrite))
        with sqlite3.connect(tmp_path / "out" / "database.db") as db:
            return [r[0] for r in db.execute("SELECT rows FROM keypoints ORDER BY image_id")]

    high = keypoints(0.0067)
    with pytest.raises(ConfigError, match=r"sift_peak_threshold 0\.0067 -> 0\.002 \(features\)"):
        keypoints(0.002)
    low = keypoints(0.002, overwrite=True)
    assert len(low) == len(high) == 2
    assert all(lo > hi for lo, hi in zip(low, high, strict=True)), (low, high)
    with pytest.raises(ConfigError, match="sift_peak_threshold"):
        reconstruct_config(image_path=images, workspace_path=tmp_path / "x", sift_peak_threshold=0.0)


def test_unreadable_photo_is_skipped_by_name_before_sfm(tmp_path, caplog):
    """Issue 41 item 3: a text file named like a photo is named in a WARNING and skipped before SfM,
    not left to COLMAP (which failed to read it and reported it as "not registered")."""
    images = _two_overlapping_photos(tmp_path / "photos")
    (images / "IMG_0001.jpg").write_text("not a photo, just some notes\n")
    with caplog.at_level("INFO", logger="colmap_pvs"):
        result = reconstruct(reconstruct_config(image_path=images, workspace_path=tmp_path / "out",
                                               num_threads=1, stop_after="features"))
    assert result.num_images == 2
    assert list(result.skipped_photos) == ["IMG_0001.jpg"]
    assert "not a readable image" in result.skipped_photos["IMG_0001.jpg"]
    messages = [(r.levelname, r.getMessage()) for r in caplog.records]
    warning = next(i for i, (level, msg) in enumerate(messages)
                   if level == "WARNING" and "no readable image: IMG_0001.jpg" in msg)
    features = next(i for i, (_, msg) in enumerate(messages) if "features ..." in msg)
    assert warning < features  # reported before SfM starts
    import sqlite3

    with sqlite3.connect(tmp_path / "out" / "database.db") as db:
        assert sorted(r[0] for r in db.execute("SELECT name FROM images")) == ["0.png", "1.png"]


def test_summary_names_the_real_dense_workspace_and_previews_folder(tmp_path):
    """Issue 41 item 3: the closing summary names the dense workspace and the previews folder (on by
    default) instead of ``None`` / "run with --previews true", also when the run stopped before them."""
    from colmap_pvs.cli.reports_pipeline import report_reconstruct
    from colmap_pvs.reconstruct import ReconstructResult

    dense = tmp_path / "ws" / "dense"
    previews = dense / "stereo" / "previews"
    stopped = ReconstructResult(workspace_path=tmp_path / "ws", dense_path=dense, previews_path=previews,
                                num_images=21, num_registered=20, stopped_after="mapping",
                                skipped_photos={"IMG_0001.jpg": "not a readable image"})
    text = report_reconstruct(stopped)
    assert f"dense workspace: {dense}  (not made yet; the run stopped after mapping)" in text
    assert f"previews:        {previews}  (none yet: stereo has not run" in text
    assert "skipped photo IMG_0001.jpg: not a readable image" in text
    assert "None" not in text.split("where to look:")[1].split("fused cloud")[0]
    previews.mkdir(parents=True)
    (previews / "a.png.geometric.depth.png").write_bytes(b"")
    done = ReconstructResult(workspace_path=tmp_path / "ws", dense_path=dense, previews_path=previews)
    text = report_reconstruct(done)
    assert f"dense workspace: {dense}\n" in text and f"previews:        {previews}  (1 depth maps" in text
    (previews / "cam0").mkdir()  # image names with folders (cam0/x.jpg) keep them in the previews
    (previews / "cam0" / "x.jpg.geometric.depth.png").write_bytes(b"")
    assert f"previews:        {previews}  (2 depth maps" in report_reconstruct(done)
    assert "(off; run with --previews true)" in report_reconstruct(
        ReconstructResult(workspace_path=tmp_path / "ws", dense_path=dense))


def test_reconstruct_result_paths_are_set_before_the_stages(tmp_path, analytic_scene):
    """The dense workspace and previews folder of the summary come from the run's layout (previews are
    on by default), even for a run stopped before stereo."""
    images = tmp_path / "photos"
    shutil.copytree(analytic_scene["root"] / "images", images)
    config = reconstruct_config(image_path=images, workspace_path=tmp_path / "out",
                               input_path=analytic_scene["root"] / "sparse", stop_after="mapping")
    result = reconstruct(config)
    assert result.dense_path == tmp_path / "out" / "dense"
    assert result.previews_path == tmp_path / "out" / "dense" / "stereo" / "previews"
    assert result.stopped_after == "mapping"


def _tiny_run(analytic_scene, tmp_path) -> tuple[Path, Path, Path, dict]:
    """The analytic workspace, a tiny checkpoint, ``tmp_path/out`` and the flags of a small whole run on
    them (from its sparse model)."""
    ws = analytic_scene["root"]
    ckpt = make_tiny_checkpoint(tmp_path / "tiny.pt")
    out = tmp_path / "out"
    flags = dict(image_path=ws / "images", workspace_path=out, input_path=ws / "sparse", checkpoint=ckpt,
                 num_views=3, mesh_depth=5, num_threads=1, max_image_size=64)
    return ws, ckpt, out, flags


def test_previews_asked_for_on_a_finished_reconstruction_are_written_without_recomputing(analytic_scene,
                                                                                        tmp_path):
    """``--previews`` is output-only: a finished run without previews, rerun with them, writes the
    previews of the finished maps and recomputes no stage (maps, cloud and mesh stay as they were)."""
    ws, ckpt, out, flags = _tiny_run(analytic_scene, tmp_path)
    reconstruct(reconstruct_config(**flags, previews=False))
    previews = out / "dense" / "stereo" / "previews"
    assert not previews.exists()
    # every output but the record of the last run's resolved settings
    before = {p: p.read_bytes() for p in (out / "dense").rglob("*")
              if p.is_file() and p.name != "colmap_pvs_stereo.json"}
    result = reconstruct(reconstruct_config(**flags, previews=True))
    assert {"undistort", "stereo", "fusion", "mesh"} <= set(result.resumed)
    assert result.previews_path == previews and len(list(previews.glob("*.depth.png"))) >= 5
    changed = sorted(str(p.relative_to(out)) for p, data in before.items() if p.read_bytes() != data)
    assert not changed, changed


def _record_older(marker: Path, key: str, current, older) -> None:
    """Make a stage marker that records ``current`` under ``key`` look written by an older colmap-pvs:
    ``older`` in its place, or (``None``) no such record."""
    payload = json.loads(marker.read_text())
    assert payload["settings"][key] == current
    if older is None:
        del payload["settings"][key]
    else:
        payload["settings"][key] = older
    marker.write_text(json.dumps(payload))


def test_run_only_stereo_flags_resume_and_an_older_stereo_record_is_still_checked(analytic_scene, tmp_path):
    """Flags that change no map (threads, device, backend, the Ray settings, previews) resume a finished
    run; a marker of an older colmap-pvs (flat stereo settings) is still compared with the new ones."""
    ws, ckpt, out, flags = _tiny_run(analytic_scene, tmp_path)
    reconstruct(reconstruct_config(**flags))
    rerun = reconstruct(reconstruct_config(**flags, threads=1, device="cpu", ray_workers=3, previews=False))
    assert {"undistort", "stereo", "fusion", "mesh"} <= set(rerun.resumed)
    marker = out / ".colmap_pvs" / "stereo.done"
    payload = json.loads(marker.read_text())
    payload["settings"] = {"max_image_size": 64, "num_views": 3, "network_scale": 0.8,
                           "checkpoint_sha256": payload["settings"]["checkpoint_sha256"]}
    marker.write_text(json.dumps(payload))
    with pytest.raises(ConfigError, match=r"--num_views 3 -> 4"):
        reconstruct(reconstruct_config(**{**flags, "num_views": 4}))
    # the same settings: not refused; an older marker records no map formats, so stereo resumes
    again = reconstruct(reconstruct_config(**flags))
    assert "undistort" in again.resumed and "stereo" not in again.resumed
    assert "stereo" in reconstruct(reconstruct_config(**flags)).resumed  # now recorded
    with pytest.raises(ConfigError, match=r"--num_views 3 -> 4"):
        reconstruct(reconstruct_config(**{**flags, "num_views": 4}))
    # a calibration beside the checkpoint changes the confidence maps: stereo's record names it
    reconstruct(reconstruct_config(**flags, overwrite=True))  # a marker of this version
    # maps of an older colmap-pvs (another format of a pass, or none recorded): stereo resumes, redoing
    # what changed, then fusion and mesh; nothing is refused
    stereo = out / ".colmap_pvs" / "stereo.done"
    for formats in ({**FORMAT_VERSIONS, "filled": FORMAT_VERSIONS["filled"] - 1}, None):
        _record_older(stereo, "stereo_formats", FORMAT_VERSIONS, formats)
        again = reconstruct(reconstruct_config(**flags))
        assert "undistort" in again.resumed and not {"stereo", "fusion", "mesh"} & set(again.resumed)
    assert {"stereo", "fusion", "mesh"} <= set(reconstruct(reconstruct_config(**flags)).resumed)
    # a cloud fused under older rules of fuse (or none recorded): fusion and mesh again, stereo resumes
    fusion = out / ".colmap_pvs" / "fusion.done"
    for rules in (FUSION_RULES - 1, None):
        _record_older(fusion, "fusion_rules", FUSION_RULES, rules)
        again = reconstruct(reconstruct_config(**flags))
        assert "stereo" in again.resumed and not {"fusion", "mesh"} & set(again.resumed)
    assert {"stereo", "fusion", "mesh"} <= set(reconstruct(reconstruct_config(**flags)).resumed)
    (tmp_path / "tiny.calibration.json").write_text(json.dumps(
        {"tolerance": 0.05, "curves": {"photometric": {"score": [0, 1], "prob": [0.2, 0.6]}}}))
    with pytest.raises(ConfigError, match=r"confidence calibration \(sha256 None -> "):
        reconstruct(reconstruct_config(**flags))


def test_fusion_and_mesh_follow_the_maps_they_read(analytic_scene, tmp_path, caplog):
    """Maps made again since the cloud was fused (a `colmap-pvs stereo` on the dense workspace) are
    fused and meshed again, and the log says why; with nothing changed both resume."""
    from colmap_pvs.stereo import run_stereo

    ws, ckpt, out, flags = _tiny_run(analytic_scene, tmp_path)
    reconstruct(reconstruct_config(**flags))
    fused = out / "dense" / "fused.ply"
    assert {"stereo", "fusion", "mesh"} <= set(reconstruct(reconstruct_config(**flags)).resumed)
    before = fused.stat().st_mtime_ns
    st = run_stereo(stereo_config(workspace_path=out / "dense", checkpoint=ckpt, num_views=3,
                                  max_image_size=64, geom_max_depth_error=0.05))
    assert st.geometric_processed
    caplog.set_level("INFO", logger="colmap_pvs")
    result = reconstruct(reconstruct_config(**flags))
    assert "stereo" in result.resumed and not {"fusion", "mesh"} & set(result.resumed)
    assert fused.stat().st_mtime_ns != before
    assert any("changed since" in r.getMessage() and "fusing again" in r.getMessage() for r in caplog.records)
    assert {"stereo", "fusion", "mesh"} <= set(reconstruct(reconstruct_config(**flags)).resumed)


def test_a_failed_undistort_of_an_overwrite_keeps_the_old_dense_workspace(analytic_scene, tmp_path,
                                                                          monkeypatch):
    """`reconstruct --overwrite` removed the old dense workspace (its depth maps: hours) before the new
    one was made: a failing undistort (disk full) now leaves it as it was."""
    import errno
    import os

    import colmap_pvs.io.workspace as workspace_module
    from colmap_pvs.errors import OutputError
    from colmap_pvs.reconstruct import reconstruct

    ws = analytic_scene["root"]
    out = tmp_path / "out"
    flags = dict(image_path=ws / "images", workspace_path=out, input_path=ws / "sparse", num_threads=1,
                 stop_after="undistort")
    reconstruct(reconstruct_config(**flags))
    before = {p: p.read_bytes() for p in (out / "dense").rglob("*") if p.is_file()}

    def full(config):
        raise OutputError(f"cannot write {str(config.output_path)!r}: {os.strerror(errno.ENOSPC)}")

    monkeypatch.setattr(workspace_module, "undistort", full)
    with pytest.raises(OutputError, match="No space left"):
        reconstruct(reconstruct_config(**flags, undistort_max_image_size=64, overwrite=True))
    assert {p: p.read_bytes() for p in (out / "dense").rglob("*") if p.is_file()} == before
    monkeypatch.undo()
    reconstruct(reconstruct_config(**flags, undistort_max_image_size=64, overwrite=True))
    assert before.keys() != {p for p in (out / "dense").rglob("*") if p.is_file()} or any(
        p.read_bytes() != data for p, data in before.items())
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".dense")) == []


def test_two_overlapping_photos_reconstruct(shared_data_dir, tmp_path):
    """Two neighbouring frames (500+ verified matches) said "too few matches": pycolmap's mapper ignores
    the points only two images see, even for its initial pair; COLMAP 3.8's mapper registers both."""
    frames = [shared_data_dir / "fern-images" / f"image{i:03d}.png" for i in (0, 1)]
    if not all(f.is_file() for f in frames):
        pytest.skip("fern-images are missing")
    images = tmp_path / "photos"
    images.mkdir()
    for i, frame in enumerate(frames):
        cv2.imwrite(str(images / f"{i}.png"), cv2.imread(str(frame)))
    result = reconstruct(reconstruct_config(image_path=images, workspace_path=tmp_path / "out", num_threads=1,
                                           stop_after="mapping"))
    assert result.num_registered == 2 and result.num_points3D > 100


def _write_stored_png(path, image) -> None:
    """A PNG without compression: its size depends on the image size only, so edited pixels keep it."""
    assert cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 0])


def test_a_photo_edited_in_place_is_a_changed_input(analytic_scene, tmp_path, monkeypatch):
    """A photo painted over with its name and size unchanged was taken for the same photo; the models and
    maps made from the old one were kept. A resume reads only the photos whose size or time changed."""
    import colmap_pvs.io.files as files

    hashed = []
    real_sha256 = files.file_sha256
    monkeypatch.setattr(files, "file_sha256",
                        lambda path: hashed.append(Path(path).name) or real_sha256(path))
    ws = analytic_scene["root"]
    images = tmp_path / "photos"
    images.mkdir()
    for src in sorted((ws / "images").iterdir()):
        _write_stored_png(images / src.name, cv2.imread(str(src)))
    flags = dict(image_path=images, workspace_path=tmp_path / "out", input_path=ws / "sparse", num_threads=1,
                 stop_after="undistort")
    reconstruct(reconstruct_config(**flags))
    photo = sorted(images.iterdir())[1]
    assert len(hashed) == 5
    hashed.clear()
    reconstruct(reconstruct_config(**flags))
    assert hashed == []
    size = photo.stat().st_size
    image = cv2.imread(str(photo))
    image[:, : image.shape[1] // 3] = (0, 0, 255)
    _write_stored_png(photo, image)
    assert photo.stat().st_size == size
    with pytest.raises(ConfigError, match=r"the photos .*content changed.*--overwrite"):
        reconstruct(reconstruct_config(**flags))
    assert hashed == [photo.name]
    reconstruct(reconstruct_config(**flags, overwrite=True))
    assert "undistort" in reconstruct(reconstruct_config(**flags)).resumed


def test_stereo_follows_the_dense_workspaces_images(analytic_scene, tmp_path, caplog):
    """An undistorted image of `dense/` edited since its maps were made: the stereo step resumes (only the
    maps that read it are made again) instead of being skipped as done."""
    ws = analytic_scene["root"]
    ckpt = make_tiny_checkpoint(tmp_path / "tiny.pt")
    out = tmp_path / "out"
    flags = dict(image_path=ws / "images", workspace_path=out, input_path=ws / "sparse", checkpoint=ckpt,
                 num_views=3, num_threads=1, max_image_size=64, stop_after="stereo")
    reconstruct(reconstruct_config(**flags))
    assert "stereo" in reconstruct(reconstruct_config(**flags)).resumed
    edited = sorted((out / "dense" / "images").iterdir())[0]
    record = out / "dense" / "stereo" / "provenance" / f"{edited.name}.photometric.json"
    image = cv2.imread(str(edited))
    image[:, : image.shape[1] // 3] = (0, 0, 255)
    cv2.imwrite(str(edited), image)
    caplog.set_level("INFO", logger="colmap_pvs")
    result = reconstruct(reconstruct_config(**flags))
    assert "stereo" not in result.resumed
    assert any("resuming stereo" in r.getMessage() for r in caplog.records)
    assert any(r.getMessage().startswith("stereo photometric: ") and f"image pixels changed: {edited.name}"
               in r.getMessage() for r in caplog.records)
    recorded = json.loads(record.read_text())["settings"]["image_sha256"]
    assert recorded == hashlib.sha256(edited.read_bytes()).hexdigest()  # made from the edited image
    assert "stereo" in reconstruct(reconstruct_config(**flags)).resumed


def test_a_failed_feature_extraction_of_an_overwrite_keeps_the_old_database(analytic_scene, tmp_path,
                                                                           monkeypatch):
    """The database was deleted before the new extraction: a full disk left none."""

    import colmap_pvs.io.features as features

    flags = dict(image_path=analytic_scene["root"] / "images", workspace_path=tmp_path / "out", num_threads=1,
                 stop_after="features")
    reconstruct(reconstruct_config(**flags))
    db = tmp_path / "out" / "database.db"
    before = db.read_bytes()

    monkeypatch.setattr(features, "extract_features", disk_full_after_writing_half)
    with pytest.raises(OSError, match="No space left"):
        reconstruct(reconstruct_config(**flags, max_num_features=500, overwrite=True))
    assert db.read_bytes() == before
    assert sorted(p.name for p in db.parent.glob("database.db*")) == ["database.db"]


def test_the_state_of_a_folder_does_not_depend_on_where_it_is(tmp_path):
    """``reconstruct --workspace_path out`` and then ``$PWD/out`` (or a moved project) is the same workspace:
    its fusion and mesh are not made again."""
    from colmap_pvs.io.files import files_state_sha256

    a = tmp_path / "a" / "dense"
    (a / "images" / "cam0").mkdir(parents=True)
    (a / "images" / "cam0" / "x.png").write_bytes(b"x")
    (a / "sparse").mkdir()
    b = tmp_path / "b" / "dense"
    shutil.copytree(a, b)  # times kept
    state = files_state_sha256([a / "images", a / "sparse"])
    assert files_state_sha256([b / "images", b / "sparse"]) == state
    assert files_state_sha256([Path(os.path.relpath(a, Path.cwd())) / "images", a / "sparse"]) == state
    (b / "images" / "cam0" / "x.png").write_bytes(b"y")
    assert files_state_sha256([b / "images", b / "sparse"]) != state
    assert files_state_sha256([a / "sparse", a / "images"]) != state  # which folder a file is in counts
