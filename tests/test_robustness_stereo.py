"""Issue 11, the parts of ``stereo`` owned by the robustness work: orphaned temporaries removed, an
empty ``patch-match.cfg`` or a run that skips every image is an error that keeps ``fusion.cfg``."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import test_stereo
from scenes import stereo_config

from colmap_pvs.cli.main import main
from colmap_pvs.errors import OutputError, WorkspaceError
from colmap_pvs.io.cleanup import remove_orphan_temps
from colmap_pvs.io.files import atomic_write_bytes, host_tag
from colmap_pvs.io.workspace import read_patch_match_cfg
from colmap_pvs.stereo import run_stereo

synthetic_ws = test_stereo.synthetic_ws  # the same small synthetic workspace (a module fixture)
_copy = test_stereo._copy


def _dead_pid() -> int:
    proc = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True)
    return int(proc.stdout)


def test_orphaned_temporaries_are_removed_but_live_ones_kept(tmp_path):
    dead = _dead_pid()
    maps = tmp_path / "stereo" / "depth_maps"
    maps.mkdir(parents=True)
    orphan = maps / f".a.png.geometric.bin.pvs-{host_tag()}-{dead}.k2j4h5g6.tmp"
    orphan_dir = tmp_path / f".sparse.pvs-{host_tag()}-{dead}.abcd1234.tmp"
    live = maps / f".b.png.geometric.bin.pvs-{host_tag()}-{os.getppid()}.zz11yy22.tmp"
    other_host = maps / f".c.png.geometric.bin.pvs-00000000-{dead}.zz11yy22.tmp"
    old_untagged = maps / ".d.png.geometric.bin.q1w2e3r4.tmp"
    user_file = maps / "notes.tmp"
    for path in (orphan, live, other_host, old_untagged, user_file):
        path.write_bytes(b"x")
    orphan_dir.mkdir()
    (orphan_dir / "cameras.bin").write_bytes(b"x")
    os.utime(old_untagged, (0, 0))
    removed = remove_orphan_temps(tmp_path, recursive=True)
    assert sorted(removed) == sorted([orphan, orphan_dir, old_untagged])
    assert live.exists() and other_host.exists() and user_file.exists()
    os.utime(other_host, (0, 0))  # another host's file is removed once it is old
    assert remove_orphan_temps(tmp_path, recursive=True) == [other_host]


def test_stereo_removes_orphans_of_a_killed_run(synthetic_ws, tmp_path, tiny_checkpoint):
    ws = _copy(synthetic_ws, tmp_path)
    name = f".x.png.geometric.bin.pvs-{host_tag()}-{_dead_pid()}.aaaa1111.tmp"
    orphan = ws / "stereo" / "depth_maps" / name
    orphan.parent.mkdir(parents=True, exist_ok=True)
    orphan.write_bytes(b"half a map")
    run_stereo(stereo_config(workspace_path=ws, checkpoint=tiny_checkpoint, max_image_size=32, num_views=2))
    assert not orphan.exists()
    assert not list(ws.rglob("*.tmp"))


def test_empty_patch_match_cfg_is_an_error(synthetic_ws, tmp_path, tiny_checkpoint, capsys):
    ws = _copy(synthetic_ws, tmp_path)
    cfg = ws / "stereo" / "patch-match.cfg"
    for text in ("", "# only a comment\n\n"):
        cfg.write_text(text)
        with pytest.raises(WorkspaceError, match="patch-match.cfg.*no reference"):
            read_patch_match_cfg(cfg)
    assert main(["stereo", "--workspace_path", str(ws), "--checkpoint", str(tiny_checkpoint)]) == 1
    assert "patch-match.cfg" in capsys.readouterr().err


def test_all_skipped_is_an_error_and_keeps_fusion_cfg(synthetic_ws, tmp_path, tiny_checkpoint, capsys):
    ws = _copy(synthetic_ws, tmp_path)
    fusion_cfg = ws / "stereo" / "fusion.cfg"
    fusion_cfg.write_text("keep.png\n")
    args = ["stereo", "--workspace_path", str(ws), "--checkpoint", str(tiny_checkpoint), "--min_sources", "9",
            "--max_image_size", "32"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "skipped" in err and "need 9" in err
    assert fusion_cfg.read_text() == "keep.png\n"


def test_write_errors_are_one_line_and_leave_nothing(tmp_path, monkeypatch):
    import errno

    import colmap_pvs.io.files as files_module

    real_fdopen = os.fdopen

    class Full:
        def __init__(self, fd, mode):
            self.f = real_fdopen(fd, mode)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(files_module.os, "fdopen", Full)
    target = tmp_path / "out" / "x.bin"
    with pytest.raises(OutputError, match=r"x\.bin.*No space left on device"):
        atomic_write_bytes(target, b"data")
    assert list((tmp_path / "out").iterdir()) == []
    monkeypatch.undo()

    def refuse(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "ro"))

    monkeypatch.setattr(files_module.tempfile, "mkstemp", refuse)
    with pytest.raises(OutputError, match=r"ro.*Permission denied"):
        atomic_write_bytes(tmp_path / "ro" / "y.bin", b"data")


def test_disk_full_during_stereo_is_one_line_and_no_map_is_done(synthetic_ws, tmp_path, tiny_checkpoint,
                                                                 monkeypatch, capsys):
    import errno

    import colmap_pvs.io.files as files_module

    ws = _copy(synthetic_ws, tmp_path)
    real = files_module.tempfile.mkstemp

    def full(*args, **kwargs):
        if ".photometric.bin." in kwargs.get("prefix", ""):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(*args, **kwargs)

    monkeypatch.setattr(files_module.tempfile, "mkstemp", full)
    args = ["stereo", "--workspace_path", str(ws), "--checkpoint", str(tiny_checkpoint),
            "--max_image_size", "32"]
    assert main(args) == 1
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if "error" in line.lower()]
    assert "Traceback" not in err and len(errors) == 1
    assert "No space left on device" in errors[0] and ".photometric.bin" in errors[0]
    assert not list((ws / "stereo" / "depth_maps").glob("*.geometric.bin"))  # nothing marked done
    assert not list(ws.rglob("*.tmp"))
