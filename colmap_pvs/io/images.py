"""Loading and resizing images with the exact intrinsics scale factors.

EXIF orientation is ignored on purpose: COLMAP reads pixels as stored, and the sparse model's
image sizes and poses refer to that pixel grid.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import cv2
import numpy as np

from ..errors import ShapeError, WorkspaceError

logger = logging.getLogger(__name__)

__all__ = ["check_image_file", "check_image_format", "load_image", "read_image_size", "resize_image"]

_READ_FLAGS = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"IEND\xaeB`\x82"
_JPEG_START, _JPEG_END = b"\xff\xd8", b"\xff\xd9"


def _check_image_bytes(data: bytes, path: Path) -> None:
    """Refuse empty files and PNG / JPEG files without their end marker (cut-off downloads, full disks).

    Decoders (libpng, libjpeg, COLMAP's FreeImage) may return a truncated image with its missing part
    grey or black instead of failing, so the end marker is checked explicitly.
    """
    if not data:
        raise WorkspaceError(f"image file {str(path)!r} is empty (0 bytes)")
    if data.startswith(_PNG_SIGNATURE) and _PNG_END not in data[-64:]:
        raise WorkspaceError(f"image file {str(path)!r} is truncated: its PNG end marker (IEND) is missing "
                             f"after {len(data)} bytes")
    if data.startswith(_JPEG_START) and _JPEG_END not in data[-4096:]:
        raise WorkspaceError(f"image file {str(path)!r} is truncated: its JPEG end marker (EOI) is missing "
                             f"after {len(data)} bytes")


def check_image_file(path: str | os.PathLike) -> None:
    """Cheap check (no decoding) that ``path`` is a non-empty image that is not cut off.

    Raises:
        WorkspaceError: missing, unreadable, empty, or a PNG / JPEG without its end marker.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(8)
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(size - 4096, len(head)))
            tail = f.read()
    except FileNotFoundError:
        raise WorkspaceError(f"image file {str(path)!r} does not exist") from None
    except OSError as exc:
        raise WorkspaceError(f"cannot read image file {str(path)!r}: {exc.strerror or exc}") from None
    # The head and the last 4 KiB are all that the end-marker check looks at.
    data = head + tail if size <= 4096 + len(head) else head + b"\0" + tail
    _check_image_bytes(data, path)


def check_image_format(path: str | os.PathLike) -> None:
    """Cheap check (the file's signature only, nothing is decoded) that ``path`` holds an image format
    a decoder recognises: a text file or a document named ``IMG_0001.jpg`` does not.

    Raises:
        WorkspaceError: no image decoder recognises the file's content.
    """
    if not cv2.haveImageReader(str(path)):
        raise WorkspaceError(
            f"image file {str(path)!r} is not a readable image (no image decoder recognises its content)"
        )


def load_image(path: str | os.PathLike) -> np.ndarray:
    """Load an image as ``[H, W, 3]`` uint8 RGB (greyscale is expanded, alpha dropped, 16 bit reduced).

    Raises:
        WorkspaceError: the file is missing, empty, truncated (PNG / JPEG end marker missing) or cannot
            be decoded.
    """
    path = Path(path)
    if not path.is_file():
        raise WorkspaceError(f"image file {str(path)!r} does not exist")
    data = np.fromfile(path, dtype=np.uint8)
    _check_image_bytes(data.tobytes(), path)
    image = cv2.imdecode(data, _READ_FLAGS)
    if image is None:
        raise WorkspaceError(f"image file {str(path)!r} could not be decoded (corrupt or unsupported "
                             "format); replace it with the original photo")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_image_size(path: str | os.PathLike) -> tuple[int, int]:
    """``(width, height)`` of the image at ``path`` as COLMAP sees it (decodes the file)."""
    height, width = load_image(path).shape[:2]
    return width, height


def resize_image(image: np.ndarray, max_image_size: int) -> tuple[np.ndarray, float, float]:
    """Shrink ``image`` (``[H, W]`` or ``[H, W, C]``) so that its longest side is ``<= max_image_size``.

    New sizes are rounded half up to an integer (at least 1). ``max_image_size <= 0`` or an image
    that already fits keeps the input unchanged.

    Returns:
        ``(resized, sx, sy)`` with ``sx = new_w / old_w`` and ``sy = new_h / old_h`` exactly, so the
        intrinsics of the resized image are ``diag(sx, sy, 1) @ K``
        (:func:`colmap_pvs.geometry.scale_intrinsics`).
    """
    image = np.asarray(image)
    if image.ndim not in (2, 3) or image.shape[0] == 0 or image.shape[1] == 0:
        raise ShapeError(f"expected a non-empty [H, W] or [H, W, C] image, got shape {image.shape}")
    height, width = image.shape[:2]
    longest = max(width, height)
    if max_image_size <= 0 or longest <= max_image_size:
        return image, 1.0, 1.0
    scale = max_image_size / longest
    new_w = max(1, min(max_image_size, math.floor(width * scale + 0.5)))
    new_h = max(1, min(max_image_size, math.floor(height * scale + 0.5)))
    resized = cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_AREA)
    if image.ndim == 3 and resized.ndim == 2:
        resized = resized[:, :, None]
    return resized, new_w / width, new_h / height
