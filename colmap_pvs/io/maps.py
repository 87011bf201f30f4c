"""Reading and writing COLMAP dense ``.bin`` arrays (depth, normal, confidence maps) and PNG previews.

File format (COLMAP ``src/colmap/mvs/mat.cc``, ``Mat<float>::Read/Write``): an ASCII header
``W&H&C&`` followed by ``W*H*C`` little-endian float32 values stored **channel by channel**
(planar), row-major inside a channel: value ``(row, col, channel)`` sits at flat index
``channel*W*H + row*W + col`` (``mat.h``, ``Mat::Get``). We never use pycolmap's
``NormalMap.from_array/to_array`` (they scramble channels in pycolmap 4.2.1).

Pixel convention of the maps that COLMAP's ``stereo_fusion`` reads (pinned by
``tests/test_colmap_fusion_roundtrip.py``): fusion back-projects map pixel ``(col, row)`` with
depth ``d`` to ``d * K_s^-1 [col, row, 1]`` -- integer pixel coordinates, **no +0.5** -- where
``K_s = diag(w/W, h/H, 1) K`` for a map of size ``(w, h)`` and an image of size ``(W, H)``
(``src/colmap/mvs/fusion.cc``). In our pixel-centre convention (centre of pixel ``(col, row)`` at
``(col + 0.5, row + 0.5)``) that is the camera :func:`fusion_intrinsics` returns: its principal
point is shifted by +0.5 px. Depth/normal maps meant for ``stereo/`` must therefore be computed
for ``fusion_intrinsics(K, ...)``, not for ``K`` itself (see ``docs/CONVENTIONS.md``).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import cv2
import numpy as np

from ..errors import ConfigError, MapFormatError, ShapeError
from .files import atomic_write_bytes

logger = logging.getLogger(__name__)

_MAX_HEADER_BYTES = 64
_UNIT_TOLERANCE = 1e-3

__all__ = [
    "read_array",
    "write_array",
    "read_depth_map",
    "write_depth_map",
    "read_normal_map",
    "write_normal_map",
    "fusion_intrinsics",
    "save_depth_preview",
    "save_normal_preview",
    "save_scalar_preview",
    "save_confidence_preview",
    "colour_bar",
]


# --------------------------------------------------------------------------- raw arrays


def _parse_header(data: bytes, path: Path) -> tuple[int, int, int, int]:
    """Return ``(width, height, channels, header_length)`` of a COLMAP array file."""
    end = 0
    for _ in range(3):
        end = data.find(b"&", end, _MAX_HEADER_BYTES) + 1
        if end == 0:
            raise MapFormatError(
                f"{str(path)!r} is not a COLMAP array: no 'W&H&C&' header in its first "
                f"{_MAX_HEADER_BYTES} bytes (starts with {data[:24]!r})"
            )
    fields = data[: end - 1].split(b"&")
    try:
        width, height, channels = (int(f.decode("ascii").strip()) for f in fields)
    except (UnicodeDecodeError, ValueError):
        raise MapFormatError(f"{str(path)!r} has a malformed header {data[:end]!r}") from None
    if min(width, height, channels) <= 0:
        raise MapFormatError(f"{str(path)!r} has a header with a non-positive size {data[:end]!r}")
    return width, height, channels, end


def read_array(path: str | os.PathLike) -> np.ndarray:
    """Read a COLMAP ``.bin`` array.

    Returns:
        float32 array, ``[H, W]`` when the file has one channel, ``[H, W, C]`` otherwise.

    Raises:
        MapFormatError: missing file, bad header, or a payload that is not exactly ``W*H*C*4`` bytes.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise MapFormatError(f"map file {str(path)!r} does not exist") from None
    except OSError as exc:
        raise MapFormatError(f"cannot read map file {str(path)!r}: {exc}") from None
    width, height, channels, offset = _parse_header(data, path)
    expected = width * height * channels * 4
    actual = len(data) - offset
    if actual != expected:
        kind = "truncated" if actual < expected else "has trailing data"
        raise MapFormatError(
            f"{str(path)!r} is {kind}: header {width}x{height}x{channels} needs {expected} payload bytes, "
            f"found {actual}"
        )
    planar = np.frombuffer(data, dtype="<f4", offset=offset).reshape(channels, height, width)
    array = np.ascontiguousarray(planar.transpose(1, 2, 0), dtype=np.float32)
    return array[:, :, 0] if channels == 1 else array


def write_array(path: str | os.PathLike, array: np.ndarray) -> Path:
    """Write ``array`` (``[H, W]`` or ``[H, W, C]``, real numbers) as a COLMAP ``.bin`` file, atomically."""
    return atomic_write_bytes(path, encode_array(path, array))


def encode_array(path: str | os.PathLike, array: np.ndarray) -> bytes:
    """The bytes of :func:`write_array` (``path`` names the file in errors)."""
    array = np.asarray(array)
    if array.ndim not in (2, 3) or array.size == 0:
        raise ShapeError(
            f"cannot write {str(path)!r}: expected a non-empty [H, W] or [H, W, C] array, "
            f"got shape {array.shape}"
        )
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise ShapeError(f"cannot write {str(path)!r}: expected a real-valued array, got dtype {array.dtype}")
    if array.ndim == 2:
        array = array[:, :, None]
    height, width, channels = array.shape
    header = f"{width}&{height}&{channels}&".encode("ascii")
    payload = np.ascontiguousarray(array.transpose(2, 0, 1), dtype="<f4").tobytes()
    return header + payload


# --------------------------------------------------------------------------- typed maps


def _require_finite(array: np.ndarray, path: str | os.PathLike, what: str) -> None:
    bad = ~np.isfinite(array)
    if bad.any():
        raise MapFormatError(f"refusing to write {what} {str(path)!r}: {int(bad.sum())} non-finite values")


def read_depth_map(path: str | os.PathLike) -> np.ndarray:
    """Read a depth map: ``[H, W]`` float32 camera-frame z, ``0`` = invalid."""
    depth = read_array(path)
    if depth.ndim != 2:
        raise MapFormatError(
            f"{str(path)!r} is not a depth map: it has {depth.shape[2]} channels, expected 1"
        )
    return depth


def write_depth_map(path: str | os.PathLike, depth: np.ndarray) -> Path:
    """Write a ``[H, W]`` depth map (finite, ``>= 0``, ``0`` = invalid), atomically."""
    return atomic_write_bytes(path, encode_depth_map(path, depth))


def encode_depth_map(path: str | os.PathLike, depth: np.ndarray) -> bytes:
    """The bytes of :func:`write_depth_map`, checked the same way."""
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ShapeError(f"cannot write depth map {str(path)!r}: expected [H, W], got shape {depth.shape}")
    _require_finite(depth, path, "depth map")
    if (depth < 0).any():
        raise MapFormatError(
            f"refusing to write depth map {str(path)!r}: {int((depth < 0).sum())} negative depths "
            f"(min {float(depth.min())}); use 0 for invalid pixels"
        )
    return encode_array(path, depth)


def read_normal_map(path: str | os.PathLike) -> np.ndarray:
    """Read a normal map: ``[H, W, 3]`` float32 camera-frame normals (unit, or zero = invalid)."""
    normals = read_array(path)
    if normals.ndim != 3 or normals.shape[2] != 3:
        channels = 1 if normals.ndim == 2 else normals.shape[2]
        raise MapFormatError(f"{str(path)!r} is not a normal map: it has {channels} channels, expected 3")
    return normals


def write_normal_map(path: str | os.PathLike, normals: np.ndarray) -> Path:
    """Write ``[H, W, 3]`` camera-frame normals (unit vectors, or zero vectors = invalid), atomically.

    COLMAP's fusion expects unit normals that face the camera (``dot(n, x_cam) < 0``).
    """
    return atomic_write_bytes(path, encode_normal_map(path, normals))


def encode_normal_map(path: str | os.PathLike, normals: np.ndarray) -> bytes:
    """The bytes of :func:`write_normal_map`, checked the same way."""
    normals = np.asarray(normals, dtype=np.float32)
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise ShapeError(
            f"cannot write normal map {str(path)!r}: expected [H, W, 3], got shape {normals.shape}"
        )
    _require_finite(normals, path, "normal map")
    norm = np.linalg.norm(normals.astype(np.float64), axis=2)
    bad = (norm > 0) & (np.abs(norm - 1.0) > _UNIT_TOLERANCE)
    if bad.any():
        raise MapFormatError(
            f"refusing to write normal map {str(path)!r}: {int(bad.sum())} normals are neither unit nor zero "
            f"(norms range {float(norm[bad].min()):.4g}..{float(norm[bad].max()):.4g})"
        )
    return encode_array(path, normals)


def fusion_intrinsics(
    K: np.ndarray, image_size: tuple[int, int], map_size: tuple[int, int] | None = None
) -> np.ndarray:
    """Intrinsics, in our pixel-centre convention, of the camera COLMAP's fusion assumes for a map.

    COLMAP's ``stereo_fusion`` back-projects map pixel ``(col, row)`` along ``K_s^-1 [col, row, 1]``
    with ``K_s = diag(w/W, h/H, 1) K``. Rendering (or predicting) a map at our pixel centres
    ``(col + 0.5, row + 0.5)`` with the returned ``[3, 3]`` matrix gives exactly those rays.

    Args:
        K: ``[3, 3]`` intrinsics of the image (COLMAP SfM convention).
        image_size: ``(W, H)`` of the image ``K`` belongs to.
        map_size: ``(w, h)`` of the map; defaults to ``image_size``.
    """
    width, height = image_size
    map_w, map_h = map_size if map_size is not None else image_size
    K_map = np.diag([map_w / width, map_h / height, 1.0]) @ np.asarray(K, dtype=np.float64)
    K_map[0, 2] += 0.5
    K_map[1, 2] += 0.5
    return K_map


# --------------------------------------------------------------------------- previews


def _write_png(path: str | os.PathLike, bgr: np.ndarray) -> Path:
    ok, buffer = cv2.imencode(".png", bgr)
    if not ok:
        raise MapFormatError(f"could not encode PNG preview {str(path)!r}")
    return atomic_write_bytes(path, buffer.tobytes())


def _check_2d(values: np.ndarray, path: str | os.PathLike) -> np.ndarray:
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2:
        raise ShapeError(f"cannot write preview {str(path)!r}: expected [H, W], got shape {values.shape}")
    return values


def _depth_scale(depth: np.ndarray, vmin: float | None, vmax: float | None,
                 ) -> tuple[np.ndarray, float, float]:
    """The valid pixels of ``depth`` and the range ``(lo, hi)`` a preview colours it over (``vmin`` /
    ``vmax``, by default the 2nd/98th percentiles of the valid values, or 0 / 1 where there are none)."""
    valid = np.isfinite(depth) & (depth > 0)
    lo, hi = np.percentile(depth[valid], [2.0, 98.0]) if valid.any() else (0.0, 1.0)
    lo = float(lo) if vmin is None else float(vmin)
    hi = float(hi) if vmax is None else float(vmax)
    return valid, lo, hi


def colorize_depth(depth: np.ndarray, vmin: float | None = None, vmax: float | None = None) -> np.ndarray:
    """``[H, W, 3]`` uint8 BGR (turbo colour map) of a ``[H, W]`` depth (or inverse depth) map, ``vmin``
    blue to ``vmax`` red; invalid (``<= 0`` or non-finite) pixels are black.

    ``vmin``/``vmax`` default to the 2nd/98th percentiles of the valid values.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ShapeError(f"colorize_depth expects an [H, W] map, got shape {depth.shape}")
    valid, lo, hi = _depth_scale(depth, vmin, vmax)
    scaled = np.clip((np.where(valid, depth, lo) - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    bgr = cv2.applyColorMap((scaled * 255).round().astype(np.uint8), cv2.COLORMAP_TURBO)
    bgr[~valid] = 0
    return bgr


#: Height in pixels of the colour bar strip below a depth or confidence preview.
BAR_HEIGHT = 44
_BAR_ROWS = (4, 16)  # the rows of the strip the colour gradient fills
_FONT, _FONT_SCALE = cv2.FONT_HERSHEY_SIMPLEX, 0.4


def colour_bar(width: int, colormap: int, ticks: list[tuple[float, str]], title: str) -> np.ndarray:
    """``[BAR_HEIGHT, width, 3]`` uint8 BGR legend strip: the colour map ``colormap`` from its low end
    (left) to its high end (right), ``ticks`` (position in ``[0, 1]`` along it, label; in order of
    priority: one whose label would overlap an earlier one's is left out) marked under it with their
    labels, and ``title`` below them, white on black."""
    strip = np.zeros((BAR_HEIGHT, width, 3), np.uint8)
    levels = np.round(np.linspace(0.0, 255.0, width)).astype(np.uint8)[None, :]
    top, bottom = _BAR_ROWS
    strip[top:bottom] = cv2.applyColorMap(levels, colormap)
    white, text_row, placed = (255, 255, 255), bottom + 12, []
    for pos, label in ticks:  # in order of priority: a label that would overlap a placed one is left out
        x = int(round(pos * (width - 1)))
        (w, _), _ = cv2.getTextSize(label, _FONT, _FONT_SCALE, 1)
        left = min(max(x - w // 2, 2), width - w - 2)  # the end labels stay inside the strip
        if left < 2 or any(left <= b + 4 and a <= left + w + 4 for a, b in placed):
            continue
        strip[bottom:bottom + 3, x] = white
        cv2.putText(strip, label, (left, text_row), _FONT, _FONT_SCALE, white, 1, cv2.LINE_AA)
        placed.append((left, left + w))
    (w, _), _ = cv2.getTextSize(title, _FONT, _FONT_SCALE, 1)
    cv2.putText(strip, title, (max((width - w) // 2, 0), BAR_HEIGHT - 3), _FONT, _FONT_SCALE, white, 1,
                cv2.LINE_AA)
    return strip


def _with_bar(image: np.ndarray, bar: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return np.concatenate([image, bar], axis=0)


def save_depth_preview(
    path: str | os.PathLike, depth: np.ndarray, vmin: float | None = None, vmax: float | None = None,
    units: str = "scene units",
) -> Path:
    """Colour-mapped PNG of a ``[H, W]`` depth map (:func:`colorize_depth`) with a colour bar strip of
    :data:`BAR_HEIGHT` rows below it (:func:`colour_bar`: near to far, five values in ``units``);
    invalid (``<= 0`` or non-finite) pixels are black. ``vmin``/``vmax`` default to the 2nd/98th
    percentiles of the valid depths.
    """
    depth = _check_2d(depth, path)
    _, lo, hi = _depth_scale(depth, vmin, vmax)
    ticks = [(f, f"{lo + f * (hi - lo):.3g}") for f in (0.0, 1.0, 0.5, 0.25, 0.75)]  # near and far first
    bar = colour_bar(depth.shape[1], cv2.COLORMAP_TURBO, ticks, f"depth ({units})")
    return _write_png(path, _with_bar(colorize_depth(depth, lo, hi), bar))


def save_normal_preview(path: str | os.PathLike, normals: np.ndarray) -> Path:
    """PNG of ``[H, W, 3]`` normals, RGB = ``(n + 1) / 2``; zero/non-finite normals are black."""
    normals = np.asarray(normals, dtype=np.float64)
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise ShapeError(f"cannot write preview {str(path)!r}: expected [H, W, 3], got shape {normals.shape}")
    valid = np.isfinite(normals).all(axis=2) & (np.abs(np.nan_to_num(normals)).sum(axis=2) > 0)
    rgb = np.clip((np.nan_to_num(normals) + 1.0) * 127.5, 0, 255).round().astype(np.uint8)
    rgb[~valid] = 0
    return _write_png(path, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def save_scalar_preview(
    path: str | os.PathLike, values: np.ndarray, vmin: float = 0.0, vmax: float = 1.0
) -> Path:
    """Greyscale PNG of a ``[H, W]`` scalar map (confidence, visibility): ``vmin`` black, ``vmax`` white.

    Non-finite values are black.
    """
    values = _check_2d(values, path)
    if not vmax > vmin:
        raise ConfigError(
            f"cannot write preview {str(path)!r}: vmax ({vmax}) must be greater than vmin ({vmin})"
        )
    scaled = np.clip((np.nan_to_num(values, nan=vmin, posinf=vmin, neginf=vmin) - vmin) / (vmax - vmin), 0, 1)
    return _write_png(path, (scaled * 255).round().astype(np.uint8))


#: The calibrated confidence previews' scale: ``P`` sits at ``log10(1 / (1 - P)) / CONFIDENCE_NINES``
#: along the colour map (0 at ``P = 0``, one step per nine, the top at ``P = 0.99``), so that the
#: probabilities near 1 that kept pixels have are told apart.
CONFIDENCE_NINES = 2.0


def _nines(p: np.ndarray) -> np.ndarray:
    return np.clip(np.log10(1.0 / np.maximum(1.0 - p, 10.0**-CONFIDENCE_NINES)) / CONFIDENCE_NINES, 0, 1)


def save_confidence_preview(path: str | os.PathLike, confidence: np.ndarray, tolerance: float | None) -> Path:
    """PNG of a ``[H, W]`` confidence map (inferno colour map: black where the depth is likely wrong or
    missing) with a colour bar strip of :data:`BAR_HEIGHT` rows below it. A calibrated map (``tolerance``:
    the calibration's, ``P(|d - d_true| <= tolerance * d_true)``) is coloured on the fixed scale of
    :data:`CONFIDENCE_NINES` and labelled "P(depth within X %)"; an uncalibrated one (``tolerance``
    ``None``) linearly over ``[0, 1]`` and labelled "confidence score". Non-finite values are 0."""
    values = np.clip(np.nan_to_num(_check_2d(confidence, path), nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)
    if tolerance is None:
        scaled, title = values, "confidence score"
        ticks = [(0.0, "0"), (1.0, "1"), (0.5, "0.5")]
    else:
        scaled, title = _nines(values), f"P(depth within {100 * tolerance:g} %)"
        ticks = [(float(_nines(np.float64(p))), f"{p:g}") for p in (0.0, 0.99, 0.9, 0.5)]
    image = cv2.applyColorMap((scaled * 255).round().astype(np.uint8), cv2.COLORMAP_INFERNO)
    return _write_png(path, _with_bar(image, colour_bar(values.shape[1], cv2.COLORMAP_INFERNO, ticks, title)))
