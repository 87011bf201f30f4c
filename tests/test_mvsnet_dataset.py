"""MVSNet-format loader: PFM / cam / pair parsing, both layouts, source selection."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from colmap_pvs.config import config_from_dict, config_to_dict
from colmap_pvs.errors import ConfigError
from colmap_pvs.train.mvsnet_dataset import (
    MVSNetDataset,
    MVSNetDatasetConfig,
    MVSNetFormatError,
    read_mvsnet_cam,
    read_pair_file,
    read_pfm,
    select_sources,
    write_pfm,
)

W, H = 64, 48


def _pfm_bytes(arr: np.ndarray, little: bool) -> bytes:
    """Independent PFM writer: header, then rows bottom to top."""
    h, w = arr.shape[:2]
    magic = "PF" if arr.ndim == 3 else "Pf"
    fmt = "<" if little else ">"
    body = b"".join(struct.pack(f"{fmt}{arr[r].size}f", *arr[r].reshape(-1)) for r in range(h - 1, -1, -1))
    return f"{magic}\n{w} {h}\n{-1.0 if little else 1.0}\n".encode() + body


def _cam_text(T: np.ndarray, K: np.ndarray, depth_line: str) -> str:
    rows = ["extrinsic", *(" ".join(repr(float(v)) for v in r) for r in T), "", "intrinsic"]
    rows += [*(" ".join(repr(float(v)) for v in r) for r in K), "", depth_line]
    return "\n".join(rows) + "\n"


def _pose(i: int) -> np.ndarray:
    a = 0.05 * i
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = [0.1 * i, -0.02 * i, 0.3]
    return T


# Source scores of view 0 (pair.txt order is deliberately not sorted).
SCORES0 = [(3, 5.0), (1, 9.0), (5, 0.5), (2, 7.0), (4, 1.0), (6, 3.0)]


def _pair_text(n: int) -> str:
    lines = [str(n)]
    for ref in range(n):
        listed = SCORES0 if ref == 0 else [(j, 10.0 - abs(j - ref)) for j in range(n) if j != ref]
        lines += [str(ref), f"{len(listed)} " + " ".join(f"{j} {s}" for j, s in listed)]
    return "\n".join(lines) + "\n"


def _colour(i: int) -> np.ndarray:
    """A distinct RGB uint8 image per view: R = 10 i, G = column, B = 200."""
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0] = 10 * i
    img[..., 1] = np.arange(W, dtype=np.uint8)[None, :]
    img[..., 2] = 200
    return img


K_FILE = np.array([[50.0, 0, 31.5], [0, 52.0, 23.5], [0, 0, 1]])


def _write_blendedmvs(root: Path, scan: str, n: int = 7) -> None:
    d = root / scan
    for sub in ("blended_images", "rendered_depth_maps", "cams"):
        (d / sub).mkdir(parents=True, exist_ok=True)
    for i in range(n):
        cv2.imwrite(
            str(d / "blended_images" / f"{i:08d}.jpg"), _colour(i)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 100]
        )
        depth = np.full((H, W), 2.0 + i, np.float32)
        depth[:5, :7] = 0.0
        depth[10, 20] = 1.25
        (d / "rendered_depth_maps" / f"{i:08d}.pfm").write_bytes(_pfm_bytes(depth, little=i % 2 == 0))
        (d / "cams" / f"{i:08d}_cam.txt").write_text(_cam_text(_pose(i), K_FILE, "1.0 0.05 128 8.5"))
    (d / "cams" / "pair.txt").write_text(_pair_text(n))


def test_pfm_roundtrip_both_endians_and_row_order(tmp_path: Path) -> None:
    arr = np.arange(12, dtype=np.float32).reshape(3, 4) * 0.5 - 1.0
    rgb = np.random.default_rng(0).random((2, 3, 3)).astype(np.float32)
    for little in (True, False):
        p = tmp_path / f"a{little}.pfm"
        p.write_bytes(_pfm_bytes(arr, little))
        np.testing.assert_array_equal(read_pfm(p), arr)  # top row first after reading
        q = tmp_path / f"c{little}.pfm"
        q.write_bytes(_pfm_bytes(rgb, little))
        np.testing.assert_array_equal(read_pfm(q), rgb)
        r = write_pfm(tmp_path / f"w{little}.pfm", arr, little_endian=little)
        assert r.read_bytes() == _pfm_bytes(arr, little)
    (tmp_path / "bad.pfm").write_bytes(b"P6\n4 3\n255\n")
    with pytest.raises(MVSNetFormatError, match="not a PFM"):
        read_pfm(tmp_path / "bad.pfm")
    (tmp_path / "short.pfm").write_bytes(_pfm_bytes(arr, True)[:-4])
    with pytest.raises(MVSNetFormatError, match="truncated"):
        read_pfm(tmp_path / "short.pfm")


def test_cam_and_pair_parsing(tmp_path: Path) -> None:
    T = _pose(3)
    for line, expected in [
        ("425.0 2.5", (425.0, 425.0 + 2.5 * 191)),
        ("425.0 2.5 100", (425.0, 425.0 + 2.5 * 99)),
        ("1.0 0.05 128 8.5", (1.0, 8.5)),
    ]:
        p = tmp_path / "c.txt"
        p.write_text(_cam_text(T, K_FILE, line))
        cam = read_mvsnet_cam(p)
        np.testing.assert_array_equal(cam.cam_from_world, T)
        np.testing.assert_array_equal(cam.K, K_FILE)
        assert cam.depth_range() == pytest.approx(expected)
    p.write_text(_cam_text(T, K_FILE, "425.0"))
    with pytest.raises(MVSNetFormatError, match="only depth_min"):
        read_mvsnet_cam(p)
    p.write_text("extrinsic\n1 0 0\n")
    with pytest.raises(MVSNetFormatError):
        read_mvsnet_cam(p)
    pair = tmp_path / "pair.txt"
    pair.write_text(_pair_text(7))
    pairs = read_pair_file(pair)
    assert sorted(pairs) == list(range(7)) and pairs[0] == SCORES0
    pair.write_text("2\n0\n1 1 3.0\n")
    with pytest.raises(MVSNetFormatError, match="truncated"):
        read_pair_file(pair)


def test_source_selection() -> None:
    # by score: 1 (9), 2 (7), 3 (5), 6 (3), 4 (1), 5 (0.5)
    assert select_sources(SCORES0, 4, "anti_noise") == [1, 2, 5, 4]
    assert select_sources(SCORES0, 4, "best") == [1, 2, 3, 6]
    assert select_sources(SCORES0, 2, "anti_noise") == [1, 5]
    assert select_sources([(7, 2.0), (8, 1.0)], 4, "anti_noise") == [7, 8, 7, 8]  # cyclic padding
    assert select_sources([(7, 0.0)], 4) == []  # score 0 is not a candidate
    assert select_sources(SCORES0, 4, "best", exclude=1) == [2, 3, 6, 4]


def test_blendedmvs_layout_sample_values(tmp_path: Path) -> None:
    _write_blendedmvs(tmp_path, "sceneA")
    _write_blendedmvs(tmp_path, "sceneB", n=5)
    (tmp_path / "not_a_scene").mkdir()
    cfg = MVSNetDatasetConfig(root=tmp_path, layout="blendedmvs")
    assert config_from_dict(MVSNetDatasetConfig, config_to_dict(cfg)) == cfg
    ds = MVSNetDataset(cfg)
    assert ds.scans == ("sceneA", "sceneB") and len(ds) == 7 + 5
    s = ds[0]
    assert set(s) == {
        "images",
        "intrinsics",
        "cam_from_world",
        "depth",
        "depth_min",
        "depth_max",
        "sparse_depth",
    }
    assert s["images"].shape == (5, 3, H, W) and s["images"].dtype == torch.float32
    assert ds.sample_info(0)["sources"] == (1, 2, 5, 4)
    views = [0, 1, 2, 5, 4]
    # RGB order and [0, 1] range: red channel is 10 * view id.
    red = s["images"][:, 0].mean(dim=(1, 2)) * 255
    np.testing.assert_allclose(red.numpy(), [10 * v for v in views], atol=2.0)
    assert s["images"][:, 2].mean() == pytest.approx(200 / 255, abs=0.01)
    K = K_FILE.copy()
    K[:2, 2] += 0.5  # integer-centre -> +0.5 convention, intrinsics_scale 1
    for j, v in enumerate(views):
        np.testing.assert_allclose(s["intrinsics"][j].numpy(), K, rtol=1e-6)
        np.testing.assert_allclose(s["cam_from_world"][j].numpy(), _pose(v), atol=1e-6)
    assert s["depth"].shape == (H, W) and s["sparse_depth"].shape == (1, H, W)
    assert s["depth"][0, 0] == 0 and s["depth"][10, 20] == pytest.approx(1.25) and s["depth"][30, 30] == 2.0
    assert float(s["depth_min"]) == 1.0 and float(s["depth_max"]) == 8.5
    assert float(s["sparse_depth"].abs().sum()) == 0.0
    # odd views were written big-endian
    assert float(ds[1]["depth"][30, 30]) == 3.0
    best = MVSNetDataset(MVSNetDatasetConfig(root=tmp_path, layout="blendedmvs", source_strategy="best"))
    assert best.sample_info(0)["sources"] == (1, 2, 3, 6)
    only_b = MVSNetDataset(
        MVSNetDatasetConfig(root=tmp_path, layout="blendedmvs", scans=("sceneB",), num_views=3)
    )
    assert len(only_b) == 5 and only_b[2]["images"].shape == (3, 3, H, W)
    # A corrupt or missing image is a format error naming the file.
    (tmp_path / "sceneB" / "blended_images" / "00000002.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(MVSNetFormatError, match="00000002.jpg"):
        only_b[2]
    (tmp_path / "sceneB" / "blended_images" / "00000002.jpg").unlink()
    with pytest.raises(MVSNetFormatError, match="does not exist"):
        only_b[2]


def test_dtu_layout_scaling_lights_and_sparse(tmp_path: Path) -> None:
    n = 4
    k_cam = np.array([[12.5, 0, 7.5], [0, 13.0, 5.5], [0, 0, 1]])  # written for the 16x12 depth maps
    (tmp_path / "Cameras" / "train").mkdir(parents=True)
    for scan in ("scan1", "scan4"):
        (tmp_path / "Rectified" / f"{scan}_train").mkdir(parents=True)
        (tmp_path / "Depths" / f"{scan}_train").mkdir(parents=True)
        for i in range(n):
            for light in range(2):
                img = _colour(i)
                img[..., 2] = 100 + light
                path = tmp_path / "Rectified" / f"{scan}_train" / f"rect_{i + 1:03d}_{light}_r5000.png"
                cv2.imwrite(str(path), img[..., ::-1])
            depth = np.full((12, 16), 500.0 + i, np.float32)
            depth[0, 0] = 0.0
            (tmp_path / "Depths" / f"{scan}_train" / f"depth_map_{i:04d}.pfm").write_bytes(
                _pfm_bytes(depth, True)
            )
    for i in range(n):
        (tmp_path / "Cameras" / "train" / f"{i:08d}_cam.txt").write_text(
            _cam_text(_pose(i), k_cam, "425 2.5")
        )
    (tmp_path / "Cameras" / "pair.txt").write_text(
        "4\n"
        + "".join(f"{r}\n3 " + " ".join(f"{j} {10 - j}" for j in range(n) if j != r) + "\n" for r in range(n))
    )
    cfg = MVSNetDatasetConfig(
        root=tmp_path, lights=(0, 1), num_views=3, image_size=(32, 24), sparse_points=20, seed=3
    )
    ds = MVSNetDataset(cfg)
    assert ds.scans == ("scan1", "scan4") and len(ds) == 2 * n * 2
    info = ds.sample_info(1)
    assert (info["scan"], info["light"], info["ref"], info["sources"]) == ("scan1", 1, 0, (1, 3))
    s = ds[1]
    assert s["images"].shape == (3, 3, 24, 32)
    assert s["images"][:, 2].mean() * 255 == pytest.approx(101, abs=1)
    # K: +0.5 at the 16x12 cam resolution, x4 to the 64x48 files, x0.5 to 32x24
    K = k_cam.copy()
    K[:2, 2] += 0.5
    K = np.diag([2.0, 2.0, 1.0]) @ K
    np.testing.assert_allclose(s["intrinsics"][0].numpy(), K, rtol=1e-6)
    assert s["depth"].shape == (24, 32)
    # depth upsampled 2x by nearest: the invalid corner pixel covers a 2x2 block
    assert (
        (s["depth"][:2, :2] == 0).all()
        and s["depth"][2, 2] == 500.0
        and (s["depth"] > 0).sum() == 24 * 32 - 4
    )
    assert float(s["depth_min"]) == 425.0 and float(s["depth_max"]) == pytest.approx(425 + 2.5 * 191)
    sp = s["sparse_depth"][0]
    assert int((sp > 0).sum()) == 20 and torch.equal(sp[sp > 0], s["depth"][sp > 0])
    assert torch.equal(ds[1]["sparse_depth"], sp[None])  # deterministic per index


def test_config_validation(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="unknown field"):
        MVSNetDatasetConfig(image_template="{scene}/{view}.png")
    with pytest.raises(ConfigError, match="num_views"):
        MVSNetDatasetConfig(num_views=1)
    with pytest.raises(ConfigError, match="root"):
        MVSNetDataset(MVSNetDatasetConfig())
    with pytest.raises(MVSNetFormatError, match="no scans"):
        MVSNetDataset(MVSNetDatasetConfig(root=tmp_path, layout="blendedmvs"))
