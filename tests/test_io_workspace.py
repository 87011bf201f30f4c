"""Dense workspace detection/loading, stereo .cfg files, undistortion and image helpers."""

from __future__ import annotations

import logging
import shutil
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pytest

from colmap_pvs.errors import ConfigError, ShapeError, UnsupportedCameraError, WorkspaceError
from colmap_pvs.geometry import scale_intrinsics
from colmap_pvs.io import (
    SourceSpec,
    UndistortConfig,
    Workspace,
    detect_workspace,
    load_image,
    load_workspace,
    read_fusion_cfg,
    read_image_size,
    read_patch_match_cfg,
    read_sparse_model,
    resize_image,
    undistort,
    write_fusion_cfg,
    write_patch_match_cfg,
    write_sparse_model,
)
from colmap_pvs.io.workspace import WRITTEN_RECORD
from colmap_pvs.types import Camera, SparseModel


@pytest.fixture
def workspace_copy(analytic_scene: dict, tmp_path: Path) -> Path:
    """A private, modifiable copy of the analytic workspace (images, sparse, cfgs; no maps)."""
    root = tmp_path / "ws"
    shutil.copytree(analytic_scene["root"], root, ignore=shutil.ignore_patterns("*.bin", "fused*"))
    shutil.copytree(analytic_scene["root"] / "sparse", root / "sparse", dirs_exist_ok=True)
    return root


# --------------------------------------------------------------------------- layout


def test_workspace_paths() -> None:
    ws = Workspace(Path("/data/ws"))
    assert ws.images_dir == Path("/data/ws/images")
    assert ws.sparse_dir == Path("/data/ws/sparse")
    assert ws.patch_match_cfg == Path("/data/ws/stereo/patch-match.cfg")
    assert ws.fusion_cfg == Path("/data/ws/stereo/fusion.cfg")
    assert ws.depth_map_path("a/b.jpg") == Path("/data/ws/stereo/depth_maps/a/b.jpg.geometric.bin")
    assert ws.normal_map_path("x.png", "photometric") == Path(
        "/data/ws/stereo/normal_maps/x.png.photometric.bin"
    )
    with pytest.raises(ConfigError, match="'fancy'"):
        ws.depth_map_path("x.png", "fancy")
    with pytest.raises(ConfigError, match=r"\.\./x\.png"):
        ws.depth_map_path("../x.png")


def test_detect_workspace_creates_stereo_dirs(workspace_copy: Path) -> None:
    shutil.rmtree(workspace_copy / "stereo")
    ws = detect_workspace(workspace_copy)
    assert ws.root == workspace_copy
    assert ws.depth_maps_dir.is_dir() and ws.normal_maps_dir.is_dir()


@pytest.mark.parametrize(
    ("remove", "match"),
    [("images", "images/"), ("sparse", "sparse/"), ("sparse/images.bin", r"images\.bin")],
)
def test_detect_workspace_names_what_is_missing(workspace_copy: Path, remove: str, match: str) -> None:
    target = workspace_copy / remove
    shutil.rmtree(target) if target.is_dir() else target.unlink()
    with pytest.raises(WorkspaceError, match=match) as info:
        detect_workspace(workspace_copy)
    assert str(workspace_copy) in str(info.value)


def test_detect_workspace_missing_root(tmp_path: Path) -> None:
    with pytest.raises(WorkspaceError, match="does not exist"):
        detect_workspace(tmp_path / "nowhere")


def test_model_in_sparse_0_is_accepted(workspace_copy: Path) -> None:
    sparse = workspace_copy / "sparse"
    (sparse / "0").mkdir()
    for f in list(sparse.glob("*.bin")):
        f.rename(sparse / "0" / f.name)
    ws, model = load_workspace(workspace_copy)
    assert ws.sparse_dir == sparse / "0"
    assert len(model.images) == 5


def test_load_workspace(analytic_scene: dict) -> None:
    ws, model = load_workspace(analytic_scene["root"], check_image_sizes=True)
    assert sorted(model.image_ids_by_name) == sorted(analytic_scene["names"])
    assert all(ws.image_path(n).is_file() for n in analytic_scene["names"])


def test_missing_image_file_is_named(workspace_copy: Path) -> None:
    (workspace_copy / "images" / "view_003.png").unlink()
    with pytest.raises(WorkspaceError, match="view_003.png"):
        load_workspace(workspace_copy)


def test_image_size_mismatch_is_detected(workspace_copy: Path) -> None:
    path = workspace_copy / "images" / "view_001.png"
    cv2.imwrite(str(path), np.zeros((100, 160, 3), np.uint8))
    load_workspace(workspace_copy)  # sizes are only checked on request
    with pytest.raises(WorkspaceError, match=r"view_001\.png.*160x100.*160x120"):
        load_workspace(workspace_copy, check_image_sizes=True)


def _make_distorted_workspace(analytic_scene: dict, root: Path) -> Path:
    """The analytic workspace, but its camera declared SIMPLE_RADIAL (a user forgot to undistort)."""
    model = analytic_scene["model"]
    cam = model.cameras[1]
    radial = Camera(
        1, "SIMPLE_RADIAL", cam.width, cam.height, cam.K, np.array([cam.K[0, 0], *cam.K[:2, 2], -0.04])
    )
    shutil.copytree(analytic_scene["root"] / "images", root / "images")
    write_sparse_model(
        SparseModel({1: radial}, model.images, model.points, model.image_ids_by_name), root / "sparse"
    )
    return root


def test_distorted_workspace_is_refused(analytic_scene: dict, tmp_path: Path) -> None:
    root = _make_distorted_workspace(analytic_scene, tmp_path / "distorted")
    with pytest.raises(UnsupportedCameraError, match="SIMPLE_RADIAL.*undistort"):
        load_workspace(root)


# --------------------------------------------------------------------------- undistortion


def test_undistort_yields_pinhole_workspace(analytic_scene: dict, tmp_path: Path) -> None:
    src = _make_distorted_workspace(analytic_scene, tmp_path / "distorted")
    out = tmp_path / "dense"
    ws = undistort(UndistortConfig(image_path=src / "images", input_path=src / "sparse", output_path=out))
    assert ws.root == out
    ws, model = load_workspace(out, check_image_sizes=True)
    assert {c.model for c in model.cameras.values()} == {"PINHOLE"}
    assert sorted(model.image_ids_by_name) == sorted(analytic_scene["names"])
    assert len(model.points) == len(analytic_scene["model"].points)
    assert len(read_patch_match_cfg(ws.patch_match_cfg)) == 5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dense", "distorted"]  # no temp folders left


def test_undistort_max_image_size(analytic_scene: dict, tmp_path: Path) -> None:
    src = analytic_scene["root"]
    cfg = UndistortConfig(
        image_path=src / "images",
        input_path=src / "sparse",
        output_path=tmp_path / "small",
        max_image_size=80,
    )
    _, model = load_workspace(undistort(cfg).root, check_image_sizes=True)
    assert all(max(c.width, c.height) <= 80 for c in model.cameras.values())


def test_undistort_missing_image_leaves_nothing(analytic_scene: dict, tmp_path: Path) -> None:
    src = _make_distorted_workspace(analytic_scene, tmp_path / "distorted")
    (src / "images" / "view_002.png").unlink()
    out = tmp_path / "dense"
    with pytest.raises(WorkspaceError, match="view_002.png"):
        undistort(UndistortConfig(image_path=src / "images", input_path=src / "sparse", output_path=out))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["distorted"]


def test_undistort_bad_inputs(analytic_scene: dict, tmp_path: Path) -> None:
    src = analytic_scene["root"]
    with pytest.raises(WorkspaceError, match="does not exist"):
        undistort(
            UndistortConfig(
                image_path=src / "images", input_path=tmp_path / "none", output_path=tmp_path / "o"
            )
        )
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "keep.txt").write_text("x")
    with pytest.raises(WorkspaceError, match="not empty"):
        undistort(UndistortConfig(image_path=src / "images", input_path=src / "sparse", output_path=busy))
    assert [p.name for p in busy.iterdir()] == ["keep.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["busy"]


# --------------------------------------------------------------------------- cfg files


def test_patch_match_cfg_round_trip(tmp_path: Path) -> None:
    sources = {"a.jpg": ["b.jpg", "c.jpg"], "b.jpg": ["a.jpg"], "sub/c.jpg": ["a.jpg", "b.jpg"]}
    path = write_patch_match_cfg(tmp_path / "stereo" / "patch-match.cfg", sources)
    specs = read_patch_match_cfg(path)
    assert list(specs) == list(sources)
    for ref, names in sources.items():
        assert specs[ref] == SourceSpec("explicit", tuple(names), len(names))
    write_fusion_cfg(tmp_path / "fusion.cfg", ["a.jpg", "sub/c.jpg"])
    assert read_fusion_cfg(tmp_path / "fusion.cfg") == ["a.jpg", "sub/c.jpg"]
    assert (tmp_path / "fusion.cfg").read_text() == "a.jpg\nsub/c.jpg\n"


def test_cfg_files_and_config_files_with_a_utf8_byte_order_mark_are_read(tmp_path: Path) -> None:
    """A patch-match.cfg, fusion.cfg or --config_file saved with a BOM (Windows editors) reads as without."""
    from colmap_pvs.config import read_config_file
    from colmap_pvs.fusion import FuseConfig

    (tmp_path / "patch-match.cfg").write_bytes("\ufeffa.jpg\nb.jpg, c.jpg\n".encode())
    specs = read_patch_match_cfg(tmp_path / "patch-match.cfg")
    assert specs == {"a.jpg": SourceSpec("explicit", ("b.jpg", "c.jpg"), 2)}
    (tmp_path / "fusion.cfg").write_bytes("\ufeffa.jpg\nb.jpg\n".encode())
    assert read_fusion_cfg(tmp_path / "fusion.cfg") == ["a.jpg", "b.jpg"]
    (tmp_path / "fuse.json").write_bytes('\ufeff{"num_sources": 3}'.encode())
    assert read_config_file(FuseConfig, tmp_path / "fuse.json") == {"num_sources": 3}
    (tmp_path / "latin1.cfg").write_bytes("caf\xe9.jpg\n".encode("latin-1"))
    with pytest.raises(WorkspaceError, match="latin1.cfg"):
        read_fusion_cfg(tmp_path / "latin1.cfg")


def test_patch_match_cfg_colmap_variants(tmp_path: Path) -> None:
    text = "# made by hand\n\n  a.jpg \n__auto__, 20\nb.jpg\n__all__\nc.jpg\n a.jpg ;b.jpg,\n"
    (tmp_path / "pm.cfg").write_text(text)
    specs = read_patch_match_cfg(tmp_path / "pm.cfg")
    assert specs == {
        "a.jpg": SourceSpec("auto", (), 20),
        "b.jpg": SourceSpec("all", (), 0),
        "c.jpg": SourceSpec("explicit", ("a.jpg", "b.jpg"), 2),
    }
    names = ["a.jpg", "b.jpg", "c.jpg", "d.jpg"]
    assert specs["b.jpg"].resolve("b.jpg", names) == ["a.jpg", "c.jpg", "d.jpg"]
    assert specs["a.jpg"].resolve("a.jpg", names, auto=lambda ref, n: names[1:3]) == ["b.jpg", "c.jpg"]
    with pytest.raises(ConfigError, match="__auto__"):
        specs["a.jpg"].resolve("a.jpg", names)
    with pytest.raises(WorkspaceError, match="b.jpg"):
        specs["c.jpg"].resolve("c.jpg", ["a.jpg", "c.jpg"])


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("a.jpg\nb.jpg\nc.jpg\n", r":3: reference image 'c.jpg' has no source line"),
        ("a.jpg\n__auto__, x\n", r":2: '__auto__, x': expected '__auto__, N'"),
        ("a.jpg\n__auto__, 0\n", r":2: .*N > 0"),
        ("a.jpg\nb.jpg, a.jpg\n", r":2: .*'a.jpg' is listed as its own source"),
        (
            "a.jpg\nb.jpg\n\nb.jpg\na.jpg\na.jpg\nb.jpg\n",
            r":6: 'a.jpg': reference image listed twice \(first on line 1\)",
        ),
        ("__auto__, 20\na.jpg\n", r":1: '__auto__, 20': expected a reference image name"),
        ("a.jpg\nb.jpg, b.jpg\n", r":2: .*duplicate"),
    ],
)
def test_patch_match_cfg_errors(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "patch-match.cfg"
    path.write_text(text)
    with pytest.raises(WorkspaceError, match=match) as info:
        read_patch_match_cfg(path)
    assert str(path) in str(info.value)


def test_cfg_write_errors(tmp_path: Path) -> None:
    with pytest.raises(WorkspaceError, match="does not exist"):
        read_patch_match_cfg(tmp_path / "none.cfg")
    with pytest.raises(ConfigError, match="'b,c.jpg'"):
        write_patch_match_cfg(tmp_path / "p.cfg", {"a.jpg": ["b,c.jpg"]})
    with pytest.raises(ConfigError, match="no source images"):
        write_patch_match_cfg(tmp_path / "p.cfg", {"a.jpg": []})
    with pytest.raises(ConfigError, match="own source"):
        write_patch_match_cfg(tmp_path / "p.cfg", {"a.jpg": ["a.jpg"]})
    assert list(tmp_path.iterdir()) == []



@pytest.mark.parametrize(
    ("write", "user_text", "ours", "ours_text", "other"),
    [
        (write_fusion_cfg, "a.jpg\nb.jpg\nc.jpg\n", ["a.jpg", "b.jpg"], "a.jpg\nb.jpg\n", ["a.jpg"]),
        (
            write_patch_match_cfg,
            "a.jpg\n__auto__, 20\nb.jpg\n__auto__, 20\n",
            {"a.jpg": ["b.jpg"]},
            "a.jpg\nb.jpg\n",
            {"b.jpg": ["a.jpg"]},
        ),
    ],
)
def test_cfg_writers_keep_the_users_file(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, write, user_text, ours, ours_text, other
) -> None:
    """Issue 41 item 6: a .cfg COLMAP or the user wrote is kept beside it (``NAME.bak``) with a
    warning naming it; our own file is replaced silently; identical content is not rewritten."""
    name = "fusion.cfg" if write is write_fusion_cfg else "patch-match.cfg"
    stereo = tmp_path / "stereo"
    stereo.mkdir()
    path = stereo / name
    path.write_text(user_text)  # image_undistorter's (or a hand-made) file
    with caplog.at_level("INFO"):
        write(path, ours)
    assert path.read_text() == ours_text
    backup = stereo / f"{name}.bak"
    assert backup.read_text() == user_text
    warnings = [r for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and str(backup) in warnings[0].getMessage()
    # a rerun replaces our own file without a backup or a warning
    caplog.clear()
    with caplog.at_level("INFO"):
        write(path, other)
        inode = path.stat().st_ino
        write(path, other)  # identical content: a no-op
    assert path.stat().st_ino == inode
    assert not [r for r in caplog.records if r.levelname == "WARNING"]
    assert sorted(p.name for p in stereo.iterdir()) == sorted([name, f"{name}.bak", WRITTEN_RECORD])
    # the user edits it again: a second backup, the first one untouched
    path.write_text(user_text.replace("a.jpg", "z.jpg"))
    write(path, ours)
    assert backup.read_text() == user_text
    assert (stereo / f"{name}.bak.2").read_text() == user_text.replace("a.jpg", "z.jpg")
    # the user's original content again: its backup exists already, no third copy
    path.write_text(user_text)
    write(path, other)
    assert not (stereo / f"{name}.bak.3").exists()
    assert backup.read_text() == user_text


def test_select_views_keeps_image_undistorters_patch_match_cfg(
    workspace_copy: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """``select-views`` on a workspace whose patch-match.cfg image_undistorter wrote: kept as .bak."""
    from colmap_pvs.views import SelectViewsConfig, run_select_views

    ws = load_workspace(workspace_copy)[0]
    names = sorted(read_fusion_cfg(ws.fusion_cfg))
    original = "".join(f"{n}\n__auto__, 20\n" for n in names)
    ws.patch_match_cfg.write_text(original)
    (ws.stereo_dir / WRITTEN_RECORD).unlink(missing_ok=True)
    with caplog.at_level("WARNING"):
        run_select_views(SelectViewsConfig(workspace_path=workspace_copy, num_views=3))
    assert (ws.stereo_dir / "patch-match.cfg.bak").read_text() == original
    assert all(s.mode == "explicit" for s in read_patch_match_cfg(ws.patch_match_cfg).values())
    assert any("patch-match.cfg.bak" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level("WARNING"):
        run_select_views(SelectViewsConfig(workspace_path=workspace_copy, num_views=4))
    assert not any("patch-match.cfg" in r.getMessage() for r in caplog.records)
    assert not (ws.stereo_dir / "patch-match.cfg.bak.2").exists()


# --------------------------------------------------------------------------- real data


def test_statue_workspace(statue_workspace: Path) -> None:
    ws, model = load_workspace(statue_workspace, check_image_sizes=True)  # read-only folder: no writes
    assert len(model.images) == 23
    heights = Counter(model.camera_of(im).height for im in model.images.values())
    assert min(heights) == 656 and max(heights) == 662 and len(heights) > 1
    for name in model.image_ids_by_name:
        cam = model.camera_of(model.image_by_name(name))
        assert read_image_size(ws.image_path(name)) == (cam.width, cam.height)
    specs = read_patch_match_cfg(ws.patch_match_cfg)
    assert len(specs) == 23 and set(specs) == set(model.image_ids_by_name)
    assert read_fusion_cfg(ws.fusion_cfg) == list(specs)

    def shared_points(ref: str, num: int) -> list[str]:
        counts = Counter()
        ref_id = model.image_ids_by_name[ref]
        for i in range(len(model.points)):
            track = set(model.points.track(i).tolist())
            if ref_id in track:
                counts.update(track - {ref_id})
        return [model.images[i].name for i, _ in counts.most_common(num)]

    names = sorted(model.image_ids_by_name)
    for ref, spec in specs.items():
        assert spec == SourceSpec("auto", (), 20)
        sources = spec.resolve(ref, names, auto=shared_points)
        assert 1 <= len(sources) <= 20 and ref not in sources and set(sources) <= set(names)


# --------------------------------------------------------------------------- images


def test_load_image_variants(tmp_path: Path) -> None:
    gray = (np.arange(12 * 10) % 256).astype(np.uint8).reshape(10, 12)
    cv2.imwrite(str(tmp_path / "g.png"), gray)
    rgb = load_image(tmp_path / "g.png")
    assert rgb.shape == (10, 12, 3) and rgb.dtype == np.uint8
    assert (rgb == gray[:, :, None]).all()
    color = np.zeros((4, 5, 3), np.uint8)
    color[..., 0] = 200  # red in RGB
    cv2.imwrite(str(tmp_path / "c.png"), color[:, :, ::-1])
    assert (load_image(tmp_path / "c.png") == color).all()
    assert read_image_size(tmp_path / "c.png") == (5, 4)
    with pytest.raises(WorkspaceError, match="does not exist"):
        load_image(tmp_path / "missing.png")
    (tmp_path / "bad.jpg").write_bytes(b"not a jpeg at all")
    with pytest.raises(WorkspaceError, match=r"bad\.jpg.*could not be decoded"):
        load_image(tmp_path / "bad.jpg")


@pytest.mark.parametrize(
    ("size", "max_size", "expected"),
    [
        ((1000, 657), 500, (500, 329)),
        ((657, 1000), 500, (329, 500)),
        ((160, 120), 200, (160, 120)),
        ((160, 120), -1, (160, 120)),
        ((101, 33), 50, (50, 16)),
        ((640, 480), 640, (640, 480)),
    ],
)
def test_resize_image_exact_scales(size, max_size, expected) -> None:
    width, height = size
    image = np.zeros((height, width, 3), np.uint8)
    out, sx, sy = resize_image(image, max_size)
    assert (out.shape[1], out.shape[0]) == expected
    assert sx == expected[0] / width and sy == expected[1] / height
    assert out.shape[2] == 3


def test_resize_image_keeps_pixel_centre_geometry() -> None:
    # a bright pixel-centre grid point must land where diag(sx, sy, 1) K predicts
    image = np.zeros((120, 160), np.float32)
    image[59:61, 79:81] = 1.0  # 2x2 block centred on continuous coordinate (80, 60)
    out, sx, sy = resize_image(image, 80)
    v, u = np.unravel_index(np.argmax(out), out.shape)
    K = scale_intrinsics(np.array([[100, 0, 80.0], [0, 100, 60.0], [0, 0, 1]]), sx, sy)
    assert abs(u + 0.5 - K[0, 2]) <= 0.5 and abs(v + 0.5 - K[1, 2]) <= 0.5
    with pytest.raises(ShapeError):
        resize_image(np.zeros((0, 3)), 10)


def _tree(root: Path) -> dict[str, tuple[bool, int, int]]:
    """Every path under ``root``: (is a folder, size, mtime)."""
    return {str(p.relative_to(root)): (p.is_dir(), p.stat().st_size, p.stat().st_mtime_ns)
            for p in root.rglob("*")}


def test_statue_patch_match_is_read_only_safe(statue_workspace: Path, tmp_path, read_only, caplog) -> None:
    """COLMAP's own workspace, read-only (the tests refuse writes under the shared data, also as root):
    detected, its sparse model, patch-match.cfg and fusion.cfg read as COLMAP wrote them, nothing under it
    changed. The same workspace as a user has it before any stereo run (no map folders), read-only: the
    folders that cannot be made are named in a warning."""
    before = _tree(statue_workspace)
    with pytest.raises(PermissionError):  # the guard is on
        (statue_workspace / "stereo" / "probe").mkdir()
    fresh = tmp_path / "statue"
    (fresh / "stereo").mkdir(parents=True)
    for folder in ("images", "sparse"):
        (fresh / folder).symlink_to(statue_workspace / folder, target_is_directory=True)
    for name in ("patch-match.cfg", "fusion.cfg"):
        shutil.copy(statue_workspace / "stereo" / name, fresh / "stereo" / name)
    read_only(fresh)
    fresh_before = _tree(fresh)
    with caplog.at_level(logging.WARNING, logger="colmap_pvs"):
        detect_workspace(fresh)
    assert [r for r in caplog.records if "could not create the stereo folders" in r.getMessage()]
    assert _tree(fresh) == fresh_before
    ws = detect_workspace(statue_workspace)
    model = read_sparse_model(ws.sparse_dir)
    lines = [line.strip() for line in ws.patch_match_cfg.read_text().splitlines() if line.strip()]
    expected = {}
    for reference, sources in zip(lines[0::2], lines[1::2], strict=True):
        items = [item.strip() for item in sources.split(",")]
        expected[reference] = (SourceSpec("auto", (), int(items[1])) if items[0] == "__auto__" else
                               SourceSpec("explicit", tuple(items), len(items)))
    assert len(expected) >= 3 and read_patch_match_cfg(ws.patch_match_cfg) == expected
    assert set(expected) <= set(model.image_ids_by_name)
    assert set(read_fusion_cfg(ws.fusion_cfg)) <= set(model.image_ids_by_name)
    assert _tree(statue_workspace) == before
