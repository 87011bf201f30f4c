"""COLMAP ``.bin`` map reader/writer: layout, bit-exact round trips, corruption, atomicity, previews."""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

import colmap_pvs.io.files
from colmap_pvs.errors import ConfigError, MapFormatError, ShapeError
from colmap_pvs.io import (
    colorize_depth,
    fusion_intrinsics,
    read_array,
    read_depth_map,
    read_normal_map,
    save_depth_preview,
    save_normal_preview,
    save_scalar_preview,
    write_array,
    write_depth_map,
    write_normal_map,
)
from colmap_pvs.io.maps import BAR_HEIGHT, save_confidence_preview


def _colmap_mat_bytes(values: np.ndarray) -> bytes:
    """Bytes as COLMAP's ``Mat<float>::Write`` produces them, element by element (mat.h indexing)."""
    height, width, depth = values.shape
    flat = np.zeros(width * height * depth, dtype="<f4")
    for row in range(height):
        for col in range(width):
            for slice_ in range(depth):
                flat[slice_ * width * height + row * width + col] = values[row, col, slice_]
    return f"{width}&{height}&{depth}&".encode() + flat.tobytes()


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def test_layout_matches_colmap_mat(tmp_path: Path) -> None:
    values = np.arange(4 * 5 * 3, dtype=np.float32).reshape(4, 5, 3) * 0.25 - 3.0
    path = write_array(tmp_path / "a.bin", values)
    assert path.read_bytes() == _colmap_mat_bytes(values)
    (tmp_path / "b.bin").write_bytes(_colmap_mat_bytes(values))
    np.testing.assert_array_equal(read_array(tmp_path / "b.bin"), values)


def test_single_channel_is_2d_and_header_is_ascii(tmp_path: Path) -> None:
    depth = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], dtype=np.float32)
    write_array(tmp_path / "d.bin", depth)
    data = (tmp_path / "d.bin").read_bytes()
    assert data.startswith(b"3&2&1&")
    assert np.frombuffer(data[6:], dtype="<f4").tolist() == [1, 2, 3, 4, 5, 6]
    out = read_array(tmp_path / "d.bin")
    assert out.shape == (2, 3) and out.dtype == np.float32


@pytest.mark.parametrize("shape", [(7, 9), (6, 4, 3), (3, 5, 2)])
def test_round_trip_is_bit_exact(tmp_path: Path, shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(sum(shape))
    bits = rng.integers(0, 2**32, size=shape, dtype=np.uint64).astype(np.uint32)
    values = bits.view(np.float32)  # every bit pattern, NaN payloads and infinities included
    values.flat[:3] = [-0.0, np.inf, np.float32(1e-45)]
    write_array(tmp_path / "x.bin", values)
    back = read_array(tmp_path / "x.bin")
    assert back.shape == values.shape and back.dtype == np.float32
    np.testing.assert_array_equal(back.view(np.uint32), values.view(np.uint32))


def test_typed_maps_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 9.0, (12, 16)).astype(np.float32)
    depth[3:5, 2:9] = 0.0
    normals = rng.normal(size=(12, 16, 3))
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    normals[0, 0] = 0.0
    write_depth_map(tmp_path / "d.bin", depth)
    write_normal_map(tmp_path / "n.bin", normals)
    np.testing.assert_array_equal(read_depth_map(tmp_path / "d.bin"), depth)
    np.testing.assert_array_equal(read_normal_map(tmp_path / "n.bin"), normals.astype(np.float32))
    with pytest.raises(MapFormatError, match="it has 3 channels, expected 1"):
        read_depth_map(tmp_path / "n.bin")
    with pytest.raises(MapFormatError, match="it has 1 channels, expected 3"):
        read_normal_map(tmp_path / "d.bin")
    write_array(tmp_path / "four.bin", np.zeros((2, 3, 4), dtype=np.float32))
    with pytest.raises(MapFormatError, match="it has 4 channels, expected 3"):
        read_normal_map(tmp_path / "four.bin")


@pytest.mark.parametrize(
    ("writer", "array", "error", "match"),
    [
        (write_depth_map, -np.ones((4, 4)), MapFormatError, "negative"),
        (write_depth_map, np.full((4, 4), np.nan), MapFormatError, "non-finite"),
        (write_depth_map, np.ones((4, 4, 1)), ShapeError, r"\[H, W\]"),
        (write_normal_map, np.full((4, 4, 3), 0.5), MapFormatError, "neither unit nor zero"),
        (write_normal_map, np.ones((4, 4)), ShapeError, r"\[H, W, 3\]"),
        (write_normal_map, np.zeros((4, 4, 2)), ShapeError, r"\[H, W, 3\]"),
        (write_array, np.ones((2, 2, 2, 2)), ShapeError, "shape"),
        (write_array, np.array([["a"]]), ShapeError, "dtype"),
    ],
)
def test_writers_reject_bad_input_without_output(tmp_path, writer, array, error, match) -> None:
    with pytest.raises(error, match=match):
        writer(tmp_path / "bad.bin", array)
    assert list(tmp_path.iterdir()) == []


def _corrupt_cases() -> dict[str, tuple[bytes, str]]:
    good = b"4&3&1&" + np.ones(12, dtype="<f4").tobytes()
    return {
        "truncated": (good[:-5], "truncated.*48 payload bytes, found 43"),
        "trailing": (good + b"\0\0\0\0", "trailing data.*48 payload bytes, found 52"),
        "no_header": (b"\x00" * 80, re.escape(f"header in its first 64 bytes (starts with {bytes(24)!r})")),
        "header_past_64_bytes": (b"4&3&" + b"0" * 59 + b"1&" + good[6:], "no 'W&H&C&' header in its first"),
        "bad_number": (b"4&x&1&" + good[6:], "malformed header"),
        "zero_size": (b"0&3&1&", "non-positive"),
        "negative_size": (b"-4&3&1&" + good[6:], "non-positive"),
        "empty_width": (b"&3&1&" + good[6:], "malformed header"),
        "empty": (b"", "no 'W&H&C&' header"),
        "payload_only": (np.ones(12, dtype="<f4").tobytes(), "header"),
    }


@pytest.mark.parametrize("case", sorted(_corrupt_cases()))
def test_corrupt_files_raise_map_format_error(tmp_path: Path, case: str) -> None:
    data, match = _corrupt_cases()[case]
    path = tmp_path / f"{case}.bin"
    path.write_bytes(data)
    with pytest.raises(MapFormatError, match=match) as info:
        read_array(path)
    assert str(path) in str(info.value)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(MapFormatError, match="does not exist") as info:
        read_depth_map(tmp_path / "nope.bin")
    assert "nope.bin" in str(info.value)


def test_writes_are_atomic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "d.bin"
    old = np.full((5, 6), 2.0, dtype=np.float32)
    write_depth_map(path, old)
    write_depth_map(path, old * 2)  # overwrite works
    np.testing.assert_array_equal(read_depth_map(path), old * 2)
    assert _leftovers(tmp_path) == []

    def failing_replace(src, dst):
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(colmap_pvs.io.files.os, "replace", failing_replace)
    with pytest.raises(OSError, match="simulated"):
        write_depth_map(path, old * 3)
    monkeypatch.undo()
    np.testing.assert_array_equal(read_depth_map(path), old * 2)  # old file intact
    assert _leftovers(tmp_path) == []  # temp file removed
    with pytest.raises(MapFormatError):
        write_depth_map(path, -old)
    np.testing.assert_array_equal(read_depth_map(path), old * 2)


def test_fusion_intrinsics() -> None:
    K = np.array([[500.0, 0, 320.0], [0, 510.0, 240.0], [0, 0, 1]])
    np.testing.assert_allclose(fusion_intrinsics(K, (640, 480)), K + [[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
    half = fusion_intrinsics(K, (640, 480), (320, 240))
    np.testing.assert_allclose(half, [[250.0, 0, 160.5], [0, 255.0, 120.5], [0, 0, 1]])


def _read_png(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None, path
    return image


def test_previews(tmp_path: Path) -> None:
    depth = np.tile(np.linspace(1.0, 5.0, 20), (10, 1))
    depth[0, :5] = 0.0
    depth[1, 0] = np.nan
    preview = _read_png(save_depth_preview(tmp_path / "d.png", depth))
    assert preview.shape == (10 + BAR_HEIGHT, 20, 3)  # the colour bar below the picture
    assert (preview[0, :5] == 0).all() and (preview[1, 0] == 0).all()
    assert (preview[5].astype(int).sum(axis=1) > 0).all()
    assert not np.array_equal(preview[5, 1], preview[5, -2])  # colour varies with depth
    # the preview is colorize_depth's picture; a fixed range clips (benchmark pictures share one scale)
    assert np.array_equal(preview[:10], colorize_depth(depth))
    fixed = colorize_depth(depth, 2.0, 3.0)
    assert np.array_equal(fixed[5, 0], fixed[5, 4]) and not np.array_equal(fixed[5, 0], fixed[5, -1])
    assert (fixed[0, :5] == 0).all()
    narrow_range = colorize_depth(np.array([[0.2, 0.4, 0.6]]), 0.2, 0.6)  # a range under 1 unit
    assert np.array_equal(narrow_range[0], cv2.applyColorMap(np.array([[0, 128, 255]], np.uint8),
                                                             cv2.COLORMAP_TURBO)[0])
    with pytest.raises(ShapeError):
        colorize_depth(np.ones((2, 2, 1)))

    normals = np.zeros((4, 5, 3))
    normals[1:, :, 2] = -1.0
    n_png = _read_png(save_normal_preview(tmp_path / "n.png", normals))[:, :, ::-1]  # BGR -> RGB
    assert (n_png[0] == 0).all() and (n_png[1:] == [128, 128, 0]).all()

    values = np.array([[0.0, 0.5, 1.0, 2.0], [-1.0, np.nan, 0.25, 1.0]])
    s_png = _read_png(save_scalar_preview(tmp_path / "s.png", values))
    assert s_png.tolist() == [[0, 128, 255, 255], [0, 0, 64, 255]]
    with pytest.raises(ConfigError, match="vmax"):
        save_scalar_preview(tmp_path / "bad.png", values, vmin=1.0, vmax=1.0)
    assert not (tmp_path / "bad.png").exists()
    assert _leftovers(tmp_path) == []


def _lut(colormap: int, width: int) -> np.ndarray:
    """``[width, 3]``: the colour map from its low end to its high end."""
    return cv2.applyColorMap(np.round(np.linspace(0, 255, width)).astype(np.uint8)[None], colormap)[0]


def _has_row(strip: np.ndarray, row: np.ndarray) -> bool:
    return any(np.array_equal(r, row) for r in strip)


def test_depth_preview_has_a_colour_bar_with_near_and_far_values(tmp_path: Path) -> None:
    """Below the depth picture (its size unchanged): a strip with the turbo colour map from near (left)
    to far (right), and under it the values and units; the far value's label changes with the range."""
    depth = np.tile(np.linspace(2.0, 6.0, 200), (30, 1))
    preview = _read_png(save_depth_preview(tmp_path / "d.png", depth, vmin=2.0, vmax=6.0))
    assert preview.shape == (30 + BAR_HEIGHT, 200, 3)
    assert np.array_equal(preview[:30], colorize_depth(depth, 2.0, 6.0))
    strip = preview[30:]
    assert _has_row(strip, _lut(cv2.COLORMAP_TURBO, 200))  # the colour map, one end to the other
    gradient_rows = [i for i, r in enumerate(strip) if np.array_equal(r, _lut(cv2.COLORMAP_TURBO, 200))]
    labels = strip[gradient_rows[-1] + 1:]
    assert labels[:, :20].any() and labels[:, -20:].any() and labels[:, 80:120].any()  # near, far, title
    farther = _read_png(save_depth_preview(tmp_path / "f.png", depth, vmin=2.0, vmax=9.0))[30:]
    assert np.array_equal(farther[:, :20], strip[:, :20])  # the same near value
    assert not np.array_equal(farther[:, -20:], strip[:, -20:])  # another far value


def test_confidence_preview_is_dark_where_the_depth_is_likely_wrong(tmp_path: Path) -> None:
    """A calibrated confidence preview: inferno (black at P = 0) on the fixed probability scale (P = 0.9
    mid-way, 0.99 and above at the top), so that the probabilities near 1 of kept pixels are told
    apart; an uncalibrated one linearly over [0, 1]. Both have the colour bar and their title below."""
    conf = np.tile(np.linspace(0.0, 1.0, 201), (20, 1))
    conf[:, -1] = np.nan  # non-finite: black
    lut = _lut(cv2.COLORMAP_INFERNO, 256)
    cal = _read_png(save_confidence_preview(tmp_path / "c.png", conf, 0.05))
    raw = _read_png(save_confidence_preview(tmp_path / "r.png", conf, None))
    assert cal.shape == raw.shape == (20 + BAR_HEIGHT, 201, 3)
    at = {p: int(round(p * 200)) for p in (0.0, 0.5, 0.82, 0.9, 0.99)}
    assert np.array_equal(cal[5, at[0.0]], lut[0]) and cal[5, at[0.0]].astype(int).sum() < 30  # dark
    assert np.array_equal(cal[5, at[0.9]], lut[128]) and np.array_equal(cal[5, at[0.99]], lut[255])
    assert np.array_equal(cal[5, -1], lut[0])
    brightness = cal[5, :-1].astype(int).sum(axis=1)
    assert np.all(np.diff(brightness) >= -2)  # darker where less likely right
    # P 0.82 and 0.99 (a geometric map's span) are far apart on the colour map, not both white
    assert np.abs(cal[5, at[0.82]].astype(int) - lut[255]).sum() > 150
    assert np.array_equal(raw[5, at[0.5]], lut[128]) and np.array_equal(raw[5, at[0.9]], lut[230])
    for preview in (cal, raw):
        assert _has_row(preview[20:], _lut(cv2.COLORMAP_INFERNO, 201))
        assert preview[-12:, 60:140].any()  # the title
    assert not np.array_equal(cal[-12:], raw[-12:])  # "P(depth within 5 %)" / "confidence score"


def test_read_error_names_unreadable_path(tmp_path: Path) -> None:
    folder = tmp_path / "dir.bin"
    folder.mkdir()
    with pytest.raises(MapFormatError) as info:
        read_array(folder)
    assert os.fspath(folder) in str(info.value)


def test_a_header_within_64_bytes_is_read(tmp_path: Path) -> None:
    header = b"4&3&" + b"0" * 58 + b"1&"  # the third '&' is the 64th byte
    assert len(header) == 64
    (tmp_path / "a.bin").write_bytes(header + np.arange(12, dtype="<f4").tobytes())
    np.testing.assert_array_equal(read_array(tmp_path / "a.bin"), np.arange(12).reshape(3, 4))


def test_write_errors_count_the_offending_values(tmp_path: Path) -> None:
    depth = np.array([[0.0, 0.5, -1.0], [2.0, -0.25, 3.0]])  # 2 negative, 3 positive
    with pytest.raises(MapFormatError, match=r": 2 negative depths \(min -1.0\)"):
        write_depth_map(tmp_path / "d.bin", depth)
    normals = np.zeros((3, 4, 3))
    normals[..., 2] = -1.0
    normals[2, 1] = [0.0, 0.0, -2.0]
    with pytest.raises(MapFormatError, match=r": 1 normals are neither unit nor zero \(norms range 2..2\)"):
        write_normal_map(tmp_path / "n.bin", normals)
    assert list(tmp_path.iterdir()) == []


def test_depth_colours_follow_the_turbo_map_between_vmin_and_vmax() -> None:
    depth = np.array([[1.0, 2.0, 3.0, 4.0, 5.0, 9.0, -2.0]])  # 9 clips to vmax's colour; -2 is invalid
    index = np.array([[0, 64, 128, 191, 255, 255, 0]], dtype=np.uint8)
    expected = cv2.applyColorMap(index, cv2.COLORMAP_TURBO)
    expected[0, -1] = 0
    np.testing.assert_array_equal(colorize_depth(depth, 1.0, 5.0), expected)
    # by default vmin / vmax are the 2nd / 98th percentiles of the valid depths
    ramp = np.linspace(1.0, 101.0, 101)[None]
    np.testing.assert_array_equal(colorize_depth(ramp), colorize_depth(ramp, 3.0, 99.0))
    # a flat map has one colour, vmin's, without numpy warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        flat = colorize_depth(np.full((3, 4), 2.5))
    assert (flat == cv2.applyColorMap(np.zeros((1, 1), np.uint8), cv2.COLORMAP_TURBO)[0, 0]).all()


def test_normal_preview_colours_and_saturation(tmp_path: Path) -> None:
    # out-of-range components saturate, never wrap around
    normals = np.array([[[0.6, 0.0, -0.8], [1.5, -1.5, -1.0]]])
    rgb = _read_png(save_normal_preview(tmp_path / "n.png", normals))[:, :, ::-1]
    assert rgb.tolist() == [[[204, 128, 25], [255, 0, 0]]]  # 0.2 * 127.5 is just below 25.5


@pytest.mark.parametrize("shape", [(4, 5), (4, 5, 2), (4, 5, 4), (4, 5, 3, 1)])
def test_normal_preview_refuses_other_shapes(tmp_path: Path, shape: tuple[int, ...]) -> None:
    with pytest.raises(ShapeError, match=r"\[H, W, 3\]"):
        save_normal_preview(tmp_path / "n.png", np.zeros(shape))
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- the colour bar, in detail

_FONT = cv2.FONT_HERSHEY_SIMPLEX


def _label_box(label: str) -> tuple[int, int, int]:
    """``(width, first ink column, last ink column)`` of ``label`` in the bar's font, the ink columns
    relative to the left end of its text box (measured on a scratch canvas)."""
    (w, _), _ = cv2.getTextSize(label, _FONT, 0.4, 1)
    canvas = np.zeros((40, w + 40), np.uint8)
    cv2.putText(canvas, label, (20, 30), _FONT, 0.4, 255, 1, cv2.LINE_AA)
    cols = np.nonzero(canvas.any(axis=0))[0]
    return w, int(cols[0]) - 20, int(cols[-1]) - 20


def _runs(cols: np.ndarray) -> list[tuple[int, int]]:
    """Runs of ink columns (a label's characters touch; labels are 5 px or more apart)."""
    runs: list[list[int]] = []
    for c in cols.tolist():
        if runs and c - runs[-1][1] <= 2:
            runs[-1][1] = c
        else:
            runs.append([c, c])
    return [(a, b) for a, b in runs]


def _bar_parts(strip: np.ndarray, colormap: int) -> tuple[list[int], list[tuple[int, int]], np.ndarray]:
    """The tick columns, the label ink runs (left to right) and the title rows of a colour bar."""
    gradient = [i for i, r in enumerate(strip) if np.array_equal(r, _lut(colormap, strip.shape[1]))]
    tick_row = gradient[-1] + 1
    ticks = np.nonzero(strip[tick_row].any(axis=1))[0].tolist()
    labels = strip[tick_row + 3:tick_row + 13]
    return ticks, _runs(np.nonzero(labels.any(axis=(0, 2)))[0]), strip[tick_row + 13:]


def test_colour_bar_layout() -> None:
    """The strip's rows: 4 black rows between the picture and the gradient, 12 rows of gradient, 3 rows
    of tick marks, the labels (rows 19-28), 2 black rows, the title (rows 31-43, its descenders whole)."""
    from colmap_pvs.io.maps import colour_bar

    title = "P(depth within 5 %)"
    strip = colour_bar(200, cv2.COLORMAP_TURBO, [(0.0, "2"), (1.0, "6"), (0.5, "4")], title)
    assert strip.shape == (44, 200, 3) and BAR_HEIGHT == 44
    ink_rows = np.nonzero(strip.any(axis=(1, 2)))[0].tolist()
    assert ink_rows == list(range(4, 29)) + list(range(31, 44))
    assert all(np.array_equal(strip[r], _lut(cv2.COLORMAP_TURBO, 200)) for r in range(4, 16))
    assert not np.array_equal(strip[16], _lut(cv2.COLORMAP_TURBO, 200))
    ticks = np.zeros((3, 200), bool)
    ticks[:, [0, 100, 199]] = True
    assert np.array_equal(strip[16:19].any(axis=2), ticks)  # 3-row tick marks, nothing else
    label_rows = np.nonzero(strip[19:31].any(axis=(1, 2)))[0]
    assert (label_rows.min(), label_rows.max()) == (0, 9)  # digits: 10 rows, baseline at row 28
    canvas = np.zeros((60, 200), np.uint8)
    cv2.putText(canvas, title, (10, 40), _FONT, 0.4, 255, 1, cv2.LINE_AA)
    assert np.count_nonzero(canvas.any(axis=1)) == 13  # the title's full height: nothing clipped


def test_colour_bar_ticks_and_text_are_white() -> None:
    from colmap_pvs.io.maps import colour_bar

    strip = colour_bar(200, cv2.COLORMAP_TURBO, [(0.0, "2"), (1.0, "6"), (0.5, "4")], "depth (m)")
    below = strip[16:].astype(int)
    assert (below[:, :, 0] == below[:, :, 1]).all() and (below[:, :, 1] == below[:, :, 2]).all()  # grey
    assert (strip[16:19, [0, 100, 199]] == 255).all() and below.max() == 255


def test_colour_bar_labels_centred_on_their_ticks_and_inside_the_strip() -> None:
    """Each label's box is centred on its tick (+-1 px); the end labels' boxes lie exactly 2 px inside
    the strip; the title is centred (+-1 px), or starts at column 0 where it is wider than the strip."""
    from colmap_pvs.io.maps import colour_bar

    labels = ["2.5", "10.3", "0.25", "0.99", "6"]
    positions = [0.0, 1.0, 0.5, 0.25, 0.75]
    strip = colour_bar(401, cv2.COLORMAP_TURBO, list(zip(positions, labels, strict=True)), "depth (m)")
    ticks, runs, title = _bar_parts(strip, cv2.COLORMAP_TURBO)
    assert ticks == [0, 100, 200, 300, 400]
    assert len(runs) == 5
    by_x = dict(zip([0, 400, 200, 100, 300], labels, strict=True))
    for x, (first, last) in zip(ticks, runs, strict=True):
        w, off_first, off_last = _label_box(by_x[x])
        left = first - off_first
        assert last - off_last == left  # the run is one whole label
        if x == 0:
            assert left == 2
        elif x == 400:
            assert left + w == 401 - 2
        else:
            assert abs(left + w / 2 - x) <= 1
    w, off_first, _ = _label_box("depth (m)")
    first = int(np.nonzero(title.any(axis=(0, 2)))[0][0])
    assert abs(first - off_first + w / 2 - 401 / 2) <= 1
    narrow = colour_bar(40, cv2.COLORMAP_INFERNO, [], "P(depth within 5 %)")
    _, off_first, _ = _label_box("P(depth within 5 %)")
    assert off_first > 0  # so that a start left of column 0 shows
    assert int(np.nonzero(narrow[30:].any(axis=(0, 2)))[0][0]) == off_first
    w, _, _ = _label_box("8")
    for width in (w + 3, w + 4):  # a label that cannot be 2 px inside the strip on both sides is left out
        strip = colour_bar(width, cv2.COLORMAP_TURBO, [(0.5, "8")], "")
        ticks, runs, _ = _bar_parts(strip, cv2.COLORMAP_TURBO)
        assert len(ticks) == len(runs) == (width >= w + 4)


@pytest.mark.parametrize("side", ["left", "inner", "inner_overlapping_bits", "right"])
def test_colour_bar_drops_labels_closer_than_5_px_to_a_drawn_one(side: str) -> None:
    """A label (and its tick) is drawn only if its box is at least 5 px from every label drawn before it;
    the labels after a dropped one are still tried."""
    from colmap_pvs.io.maps import colour_bar

    width, (w_a, _, _), (w_b, _, _) = 201, _label_box("0"), _label_box("8")
    for gap in (-3, 3, 4, 5, 6):
        if side != "right":  # "0" at the left end (box 2 .. 2 + w_a) or 2 px in, "8" to its right
            left_a = {"left": 2, "inner": 4, "inner_overlapping_bits": 10}[side]
            left_b = left_a + w_a + gap
            ticks = [((left_a + w_a // 2) / (width - 1), "0")]
        else:  # "0" at the right end, "8" to its left
            left_b = width - 2 - w_a - gap - w_b
            ticks = [(1.0, "0")]
        x_b = left_b + w_b // 2
        far = 0.0 if side == "right" else 1.0
        strip = colour_bar(width, cv2.COLORMAP_TURBO, [*ticks, (x_b / (width - 1), "8"), (far, "9")], "t")
        drawn, runs, _ = _bar_parts(strip, cv2.COLORMAP_TURBO)
        assert (x_b in drawn) == (gap >= 5), (side, gap)
        assert len(drawn) == len(runs) == (3 if gap >= 5 else 2), (side, gap)


def test_preview_bars_mark_the_documented_values(tmp_path: Path) -> None:
    """The previews' bars are :func:`colour_bar` with the documented ticks and titles: a depth preview
    near, far and the quarter values of its range (0..1 for a map without valid depths); an uncalibrated
    confidence preview 0, 1 and 0.5; a calibrated one 0, 0.99, 0.9 and 0.5 on its scale."""
    from colmap_pvs.io.maps import CONFIDENCE_NINES, colour_bar

    depth = np.tile(np.linspace(2.0, 6.0, 400), (8, 1))
    bar = _read_png(save_depth_preview(tmp_path / "d.png", depth, 2.0, 6.0, units="m"))[8:]
    ticks = [(0.0, "2"), (1.0, "6"), (0.5, "4"), (0.25, "3"), (0.75, "5")]
    assert np.array_equal(bar, colour_bar(400, cv2.COLORMAP_TURBO, ticks, "depth (m)"))
    assert len(_bar_parts(bar, cv2.COLORMAP_TURBO)[0]) == 5  # wide enough for all five labels
    empty = _read_png(save_depth_preview(tmp_path / "e.png", np.zeros((8, 400))))
    assert not empty[:8].any()
    ticks = [(0.0, "0"), (1.0, "1"), (0.5, "0.5"), (0.25, "0.25"), (0.75, "0.75")]
    assert np.array_equal(empty[8:], colour_bar(400, cv2.COLORMAP_TURBO, ticks, "depth (scene units)"))

    conf = np.tile(np.linspace(0.0, 1.0, 400), (8, 1))
    raw = _read_png(save_confidence_preview(tmp_path / "r.png", conf, None))[8:]
    ticks = [(0.0, "0"), (1.0, "1"), (0.5, "0.5")]
    assert np.array_equal(raw, colour_bar(400, cv2.COLORMAP_INFERNO, ticks, "confidence score"))
    cal = _read_png(save_confidence_preview(tmp_path / "c.png", conf, 0.05))[8:]
    half = np.log10(2.0) / CONFIDENCE_NINES
    ticks = [(0.0, "0"), (1.0, "0.99"), (0.5, "0.9"), (half, "0.5")]
    assert np.array_equal(cal, colour_bar(400, cv2.COLORMAP_INFERNO, ticks, "P(depth within 5 %)"))


@pytest.mark.parametrize("tolerance", [None, 0.05])
def test_confidence_preview_out_of_range_values(tmp_path: Path, tolerance: float | None) -> None:
    """Non-finite confidences are black (0); values outside [0, 1] are clipped, never wrapped around."""
    conf = np.array([[np.inf, -np.inf, np.nan, -0.5, 0.0, 1.0, 1.5, 3.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # P = 1 without a division by zero
        image = _read_png(save_confidence_preview(tmp_path / "c.png", conf, tolerance))[:1]
    lut = _lut(cv2.COLORMAP_INFERNO, 256)
    assert np.array_equal(image[0], lut[[0, 0, 0, 0, 0, 255, 255, 255]])


def test_degenerate_shapes_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ShapeError, match="non-empty"):
        write_array(tmp_path / "e.bin", np.zeros((0, 4), np.float32))
    with pytest.raises(ShapeError, match=r"\[H, W\] map"):
        colorize_depth(np.ones(5))
    write_array(tmp_path / "two.bin", np.zeros((2, 3, 2), np.float32))
    with pytest.raises(MapFormatError, match="it has 2 channels, expected 3"):
        read_normal_map(tmp_path / "two.bin")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["two.bin"]


def test_depth_preview_without_valid_depths_keeps_the_given_range(tmp_path: Path) -> None:
    """An all-invalid depth map (every pixel filtered out) is black, and its bar still reads the range it
    was given (stereo passes the view's depth range), not a made-up 0..1."""
    from colmap_pvs.io.maps import colour_bar

    depth = np.zeros((8, 400))
    depth[0, 0] = np.nan
    preview = _read_png(save_depth_preview(tmp_path / "d.png", depth, 2.0, 6.0, units="m"))
    assert not preview[:8].any()
    ticks = [(0.0, "2"), (1.0, "6"), (0.5, "4"), (0.25, "3"), (0.75, "5")]
    assert np.array_equal(preview[8:], colour_bar(400, cv2.COLORMAP_TURBO, ticks, "depth (m)"))
