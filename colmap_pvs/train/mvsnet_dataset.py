"""Training data in the MVSNet folder format (DTU training set, BlendedMVS).

Files
-----
``*_cam.txt`` (one per view)::

    extrinsic
    r11 r12 r13 t1          # 4 rows: the 4x4 world-to-camera matrix = our cam_from_world
    r21 r22 r23 t2
    r31 r32 r33 t3
    0 0 0 1

    intrinsic
    fx 0 cx                 # 3 rows: K
    0 fy cy
    0 0 1

    depth_min depth_interval [num_depth [depth_max]]

The depth range of a sample is ``[depth_min, depth_max]``; a missing ``depth_max`` is
``depth_min + depth_interval * depth_interval_scale * (num_depth - 1)`` with
``num_depth`` from the file or ``default_num_depth`` (MVSNet's 192).

``pair.txt``: the number of views, then per view a line with the reference id and a line
``num_src id score id score ...`` (sources listed best first).

``*.pfm`` depth maps: ``Pf`` (1 channel) or ``PF`` (3 channels), ``width height``, a
scale whose sign gives the byte order (negative = little endian), then float32 rows
stored **bottom to top**. ``0`` (or non-finite) = no depth.

Folder layouts
--------------
Paths are Python format templates relative to ``root``, with the fields ``{scan}``
(scene folder / scan name), ``{view}`` (int view id, 0-based, e.g. ``{view:08d}``),
``{view1}`` (``view + 1``, DTU's 1-based image numbers) and ``{light}`` (DTU lighting
index). The presets (``layout``); any template can be overridden in the config:

``dtu_train`` (MVSNet's ``dtu_training`` folder; cams written for the 160x128 depth
maps, so ``intrinsics_scale=4``)::

    image  Rectified/{scan}_train/rect_{view1:03d}_{light}_r5000.png
    depth  Depths/{scan}_train/depth_map_{view:04d}.pfm
    cam    Cameras/train/{view:08d}_cam.txt
    pair   Cameras/pair.txt

``blendedmvs`` (BlendedMVS low-res set, ``intrinsics_scale=1``)::

    image  {scan}/blended_images/{view:08d}.jpg
    depth  {scan}/rendered_depth_maps/{view:08d}.pfm
    cam    {scan}/cams/{view:08d}_cam.txt
    pair   {scan}/cams/pair.txt

With ``scans=()`` the scans are discovered: the folder named by the image template's
components before the first one containing ``{scan}`` is listed and the entries matching
that component (``{scan}`` as a wildcard) whose pair file exists are used.

Intrinsics convention (assumption, documented)
----------------------------------------------
MVSNet's homography warping builds its pixel grid with ``meshgrid(arange(W))``, i.e. it
treats the centre of pixel ``(col, row)`` as the integer coordinate ``(col, row)``. We
therefore assume a cam file's ``K`` follows that *integer-centre* convention at the
resolution it was written for (``image size / intrinsics_scale``) and convert it to ours
(``docs/CONVENTIONS.md``: centre at ``col + 0.5``) **at that resolution** by adding
``pixel_center_offset`` (0.5) to ``cx`` and ``cy``; the resulting ``K`` is then scaled
exactly, ``diag(s, s, 1) K``, first by ``intrinsics_scale`` to the image file and then by
the resize to ``image_size``. Set ``pixel_center_offset=0`` for cam files that already use
the ``+0.5`` convention. (The difference is half a pixel at the cam resolution.)

Depth maps are assumed to cover the same field of view as the image (true for both
presets); they are resized to the output size with the same valid-aware rules as the
loss (:func:`colmap_pvs.train.losses.downsample_depth`: min of valid pixels for integer
factors, else nearest; nearest for upsampling).

Sources
-------
``source_strategy="anti_noise"`` (PVSNet's training strategy): among the sources listed
in ``pair.txt`` for the reference, the ``ceil((num_views-1)/2)`` best and
``floor((num_views-1)/2)`` worst by score (2 + 2 for ``num_views=5``), via
:func:`colmap_pvs.views.best_and_worst`; ``"best"``: the ``num_views - 1`` best. Only
sources with a score ``> 0`` are candidates. With too few candidates the chosen ones
are repeated cyclically (best first); a reference without any candidate is dropped
with a warning.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import string
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import Dataset

from ..errors import ColmapPVSError, ConfigError, WorkspaceError
from ..geometry import scale_intrinsics
from ..io.files import atomic_write_bytes
from ..io.images import load_image
from ..views import best_and_worst
from .losses import downsample_depth

logger = logging.getLogger(__name__)

__all__ = [
    "LAYOUTS",
    "MVSNetCamera",
    "MVSNetDataset",
    "MVSNetDatasetConfig",
    "MVSNetFormatError",
    "read_mvsnet_cam",
    "read_pair_file",
    "read_pfm",
    "select_sources",
    "write_mvsnet_cam",
    "write_pfm",
]


class MVSNetFormatError(ColmapPVSError):
    """A missing or malformed file of an MVSNet-format dataset (cam, pair, pfm, image)."""


#: Path templates and intrinsics scale of each preset layout (see the module docstring).
LAYOUTS: dict[str, dict[str, Any]] = {
    "dtu_train": {
        "image_template": "Rectified/{scan}_train/rect_{view1:03d}_{light}_r5000.png",
        "depth_template": "Depths/{scan}_train/depth_map_{view:04d}.pfm",
        "cam_template": "Cameras/train/{view:08d}_cam.txt",
        "pair_template": "Cameras/pair.txt",
        "intrinsics_scale": 4.0,
    },
    "blendedmvs": {
        "image_template": "{scan}/blended_images/{view:08d}.jpg",
        "depth_template": "{scan}/rendered_depth_maps/{view:08d}.pfm",
        "cam_template": "{scan}/cams/{view:08d}_cam.txt",
        "pair_template": "{scan}/cams/pair.txt",
        "intrinsics_scale": 1.0,
    },
}

_TEMPLATE_FIELDS = {"scan", "view", "view1", "light"}


@dataclass(frozen=True)
class MVSNetDatasetConfig:
    """Where an MVSNet-format training set lies and how samples are built from it."""

    root: Path | None = field(
        default=None, metadata={"help": "dataset root folder (required when dataset=mvsnet)"}
    )
    layout: Literal["dtu_train", "blendedmvs"] = field(
        default="dtu_train",
        metadata={"help": "preset path templates and intrinsics scale; any template can be overridden"},
    )
    scans: tuple[str, ...] = field(
        default=(), metadata={"help": "training scans / scene folders; empty = discover all under root"}
    )
    val_scans: tuple[str, ...] = field(
        default=(), metadata={"help": "validation scans (used by the trainer's validation when non-empty)"}
    )
    image_template: str | None = field(
        default=None, metadata={"help": "image path template relative to root (None = layout preset)"}
    )
    depth_template: str | None = field(
        default=None, metadata={"help": "depth .pfm path template relative to root (None = layout preset)"}
    )
    cam_template: str | None = field(
        default=None, metadata={"help": "cam file path template relative to root (None = layout preset)"}
    )
    pair_template: str | None = field(
        default=None, metadata={"help": "pair.txt path template relative to root (None = layout preset)"}
    )
    intrinsics_scale: float | None = field(
        default=None,
        metadata={
            "help": "image size / resolution the cam K was written for (None = layout preset: 4 DTU, 1 BMVS)"
        },
    )
    pixel_center_offset: float = field(
        default=0.5,
        metadata={"help": "added to cx, cy of the cam files (integer-centre convention) to get ours (+0.5)"},
    )
    lights: tuple[int, ...] = field(
        default=(0, 1, 2, 3, 4, 5, 6),
        metadata={
            "help": "DTU lighting indices, one sample per light (only if the image template has {light})"
        },
    )
    num_views: int = field(default=5, metadata={"help": "views per sample, the reference included"})
    source_strategy: Literal["anti_noise", "best"] = field(
        default="anti_noise",
        metadata={"help": "anti_noise: half best + half worst listed sources (PVSNet); best: the best ones"},
    )
    image_size: tuple[int, int] | None = field(
        default=None,
        metadata={"help": "output (width, height); None = the image files' size. K is scaled exactly"},
    )
    default_num_depth: int = field(
        default=192, metadata={"help": "num_depth for cam files that give only depth_min and depth_interval"}
    )
    depth_interval_scale: float = field(
        default=1.0, metadata={"help": "multiplies depth_interval when depth_max is derived from it"}
    )
    sparse_points: int = field(
        default=0,
        metadata={"help": "valid GT pixels sampled into sparse_depth per sample (0 = all-zero sparse depth)"},
    )
    seed: int = field(default=0, metadata={"help": "seed of the per-sample sparse-point sampling"})

    def __post_init__(self) -> None:
        if self.num_views < 2:
            raise ConfigError(f"num_views must be >= 2, got {self.num_views}")
        if self.intrinsics_scale is not None and not self.intrinsics_scale > 0:
            raise ConfigError(f"intrinsics_scale must be > 0, got {self.intrinsics_scale}")
        if self.image_size is not None and (len(self.image_size) != 2 or min(self.image_size) < 1):
            raise ConfigError(f"image_size must be (width, height) >= 1, got {self.image_size!r}")
        if self.default_num_depth < 2:
            raise ConfigError(f"default_num_depth must be >= 2, got {self.default_num_depth}")
        if not self.depth_interval_scale > 0:
            raise ConfigError(f"depth_interval_scale must be > 0, got {self.depth_interval_scale}")
        if self.sparse_points < 0:
            raise ConfigError(f"sparse_points must be >= 0, got {self.sparse_points}")
        if not self.lights:
            raise ConfigError("lights must not be empty")
        for name in ("image_template", "depth_template", "cam_template", "pair_template"):
            tpl = getattr(self, name)
            if tpl is not None:
                _check_template(name, tpl)

    def resolved(self, name: str) -> Any:
        """The value of a template / ``intrinsics_scale`` field, the layout preset when ``None``."""
        value = getattr(self, name)
        return LAYOUTS[self.layout][name] if value is None else value


def _check_template(name: str, template: str) -> None:
    try:
        fields = {f for _, f, _, _ in string.Formatter().parse(template) if f is not None}
    except ValueError as exc:
        raise ConfigError(f"{name} {template!r} is not a valid format template: {exc}") from None
    unknown = fields - _TEMPLATE_FIELDS
    if unknown:
        raise ConfigError(
            f"{name} {template!r} uses unknown field(s) {sorted(unknown)}; "
            f"allowed: {sorted(_TEMPLATE_FIELDS)}"
        )


# --------------------------------------------------------------------------- PFM


def read_pfm(path: str | Path) -> np.ndarray:
    """Read a PFM file: ``[H, W]`` (``Pf``) or ``[H, W, 3]`` (``PF``) float32, top row first."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise MVSNetFormatError(f"PFM file {str(path)!r} does not exist") from None
    header: list[bytes] = []
    pos = 0
    # Header: three whitespace-separated "lines" (magic, "W H", scale); tolerate comments.
    while len(header) < 4 and pos < len(data):
        end = data.find(b"\n", pos)
        if end < 0:
            raise MVSNetFormatError(f"{str(path)!r}: truncated PFM header")
        line = data[pos:end].strip()
        pos = end + 1
        if not line or line.startswith(b"#"):
            continue
        header.extend(line.split())
    if len(header) != 4 or header[0] not in (b"PF", b"Pf"):
        raise MVSNetFormatError(f"{str(path)!r}: not a PFM file (header {header!r})")
    channels = 3 if header[0] == b"PF" else 1
    try:
        width, height, scale = int(header[1]), int(header[2]), float(header[3])
    except ValueError:
        raise MVSNetFormatError(f"{str(path)!r}: malformed PFM header {header!r}") from None
    if width <= 0 or height <= 0 or scale == 0:
        raise MVSNetFormatError(f"{str(path)!r}: bad PFM size/scale {width}x{height}, scale {scale}")
    dtype = np.dtype("<f4" if scale < 0 else ">f4")
    count = width * height * channels
    if len(data) - pos < count * 4:
        raise MVSNetFormatError(
            f"{str(path)!r}: PFM data truncated: {len(data) - pos} bytes "
            f"for {width}x{height}x{channels} floats"
        )
    arr = np.frombuffer(data, dtype=dtype, count=count, offset=pos).astype(np.float32)
    arr = arr.reshape(height, width, channels)[::-1]
    return np.ascontiguousarray(arr[..., 0] if channels == 1 else arr)


def write_pfm(path: str | Path, array: np.ndarray, *, little_endian: bool = True) -> Path:
    """Write ``[H, W]`` or ``[H, W, 3]`` float data as PFM (top row first in ``array``), atomically."""
    arr = np.asarray(array, dtype=np.float32)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] != 3):
        raise MVSNetFormatError(f"PFM data must be [H, W] or [H, W, 3], got shape {arr.shape}")
    magic = b"Pf" if arr.ndim == 2 else b"PF"
    h, w = arr.shape[:2]
    header = magic + f"\n{w} {h}\n{-1.0 if little_endian else 1.0}\n".encode()
    body = np.ascontiguousarray(arr[::-1]).astype("<f4" if little_endian else ">f4").tobytes()
    return atomic_write_bytes(path, header + body)


# --------------------------------------------------------------------------- cam / pair files


@dataclass(frozen=True, eq=False)
class MVSNetCamera:
    """One parsed cam file, as written (no convention conversion).

    Attributes:
        cam_from_world: ``[4, 4]`` float64 world-to-camera matrix.
        K: ``[3, 3]`` float64 intrinsics as in the file.
        depth_min: nearest depth of the range.
        depth_interval: depth step (``nan`` when absent).
        num_depth: number of depth planes (``None`` when absent).
        depth_max: farthest depth (``None`` when absent).
    """

    cam_from_world: np.ndarray
    K: np.ndarray
    depth_min: float
    depth_interval: float
    num_depth: int | None
    depth_max: float | None

    def depth_range(self, default_num_depth: int = 192, interval_scale: float = 1.0) -> tuple[float, float]:
        """``(depth_min, depth_max)``; see the module docstring for a missing ``depth_max``."""
        if self.depth_max is not None:
            return self.depth_min, self.depth_max
        if not math.isfinite(self.depth_interval):
            raise MVSNetFormatError("cam file gives neither depth_interval nor depth_max")
        n = self.num_depth if self.num_depth is not None else default_num_depth
        return self.depth_min, self.depth_min + self.depth_interval * interval_scale * (n - 1)


def _numbers(tokens: list[str], start: int, count: int, path: Path, what: str) -> np.ndarray:
    chunk = tokens[start : start + count]
    if len(chunk) != count:
        raise MVSNetFormatError(f"{str(path)!r}: expected {count} numbers after {what!r}, got {len(chunk)}")
    try:
        return np.array([float(t) for t in chunk], dtype=np.float64)
    except ValueError:
        raise MVSNetFormatError(f"{str(path)!r}: non-numeric value after {what!r}: {chunk}") from None


def read_mvsnet_cam(path: str | Path) -> MVSNetCamera:
    """Parse an MVSNet ``*_cam.txt`` file (layout in the module docstring)."""
    path = Path(path)
    try:
        tokens = path.read_text(encoding="utf-8-sig").split()
    except FileNotFoundError:
        raise MVSNetFormatError(f"cam file {str(path)!r} does not exist") from None
    try:
        i_ext, i_int = tokens.index("extrinsic"), tokens.index("intrinsic")
    except ValueError:
        raise MVSNetFormatError(f"{str(path)!r}: missing 'extrinsic' or 'intrinsic' section") from None
    ext = _numbers(tokens, i_ext + 1, 16, path, "extrinsic").reshape(4, 4)
    K = _numbers(tokens, i_int + 1, 9, path, "intrinsic").reshape(3, 3)
    rest = tokens[max(i_ext + 17, i_int + 10) :]
    if not 1 <= len(rest) <= 4:
        raise MVSNetFormatError(
            f"{str(path)!r}: expected 'depth_min depth_interval [num_depth [depth_max]]', got {rest}"
        )
    vals = _numbers(rest, 0, len(rest), path, "depth line")
    if len(vals) == 1:
        raise MVSNetFormatError(f"{str(path)!r}: depth line has only depth_min {vals[0]}, no depth_interval")
    if not np.allclose(ext[3], [0, 0, 0, 1]):
        raise MVSNetFormatError(
            f"{str(path)!r}: last extrinsic row is {ext[3].tolist()}, expected [0, 0, 0, 1]"
        )
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
        raise MVSNetFormatError(f"{str(path)!r}: invalid intrinsics {K.tolist()}")
    cam = MVSNetCamera(
        cam_from_world=ext,
        K=K,
        depth_min=float(vals[0]),
        depth_interval=float(vals[1]),
        num_depth=int(round(vals[2])) if len(vals) > 2 else None,
        depth_max=float(vals[3]) if len(vals) > 3 else None,
    )
    return cam


def write_mvsnet_cam(
    path: str | Path,
    cam_from_world: np.ndarray,
    K: np.ndarray,
    depth_min: float,
    depth_interval: float,
    num_depth: int | None = None,
    depth_max: float | None = None,
) -> Path:
    """Write an MVSNet cam file (values as given, no convention conversion)."""
    T = np.eye(4)
    T[:3, :] = np.asarray(cam_from_world, dtype=np.float64)[:3, :]
    lines = ["extrinsic"] + [" ".join(f"{v:.17g}" for v in row) for row in T] + ["", "intrinsic"]
    lines += [" ".join(f"{v:.17g}" for v in row) for row in np.asarray(K, dtype=np.float64)] + [""]
    depth = [f"{depth_min:.17g}", f"{depth_interval:.17g}"]
    if num_depth is not None:
        depth.append(str(int(num_depth)))
        if depth_max is not None:
            depth.append(f"{depth_max:.17g}")
    elif depth_max is not None:
        raise ValueError("depth_max needs num_depth in the MVSNet cam format")
    lines.append(" ".join(depth))
    return atomic_write_bytes(path, ("\n".join(lines) + "\n").encode())


def read_pair_file(path: str | Path) -> dict[int, list[tuple[int, float]]]:
    """Parse ``pair.txt``: ``{ref_id: [(src_id, score), ...]}`` in file order."""
    path = Path(path)
    try:
        tokens = path.read_text(encoding="utf-8-sig").split()
    except FileNotFoundError:
        raise MVSNetFormatError(f"pair file {str(path)!r} does not exist") from None
    try:
        pos = 0
        n = int(tokens[pos])
        pos += 1
        pairs: dict[int, list[tuple[int, float]]] = {}
        for _ in range(n):
            ref = int(tokens[pos])
            m = int(tokens[pos + 1])
            pos += 2
            if m < 0:
                raise MVSNetFormatError(f"{str(path)!r}: view {ref} lists {m} sources")
            srcs = [(int(tokens[pos + 2 * j]), float(tokens[pos + 2 * j + 1])) for j in range(m)]
            pos += 2 * m
            if ref in pairs:
                raise MVSNetFormatError(f"{str(path)!r}: reference view {ref} is listed twice")
            pairs[ref] = srcs
    except IndexError:
        raise MVSNetFormatError(
            f"{str(path)!r}: truncated pair file (ran out of values at token {pos})"
        ) from None
    except ValueError as exc:
        raise MVSNetFormatError(f"{str(path)!r}: malformed pair file: {exc}") from None
    if pos != len(tokens):
        raise MVSNetFormatError(f"{str(path)!r}: {len(tokens) - pos} unexpected trailing value(s)")
    return pairs


def select_sources(
    listed: list[tuple[int, float]],
    num_sources: int,
    strategy: Literal["anti_noise", "best"] = "anti_noise",
    *,
    exclude: int | None = None,
) -> list[int]:
    """Source ids for one reference from its ``pair.txt`` entries (module docstring, "Sources").

    Returns ``num_sources`` ids (repeated cyclically when too few candidates exist), or
    ``[]`` when there is no candidate (score ``> 0``, not ``exclude``) at all.
    """
    if num_sources < 1:
        raise ValueError(f"num_sources must be >= 1, got {num_sources}")
    ids = np.array([i for i, _ in listed], dtype=np.int64)
    scores = np.array([s for _, s in listed], dtype=np.float64)
    if exclude is not None:
        scores[ids == exclude] = -np.inf
    if strategy == "anti_noise":
        n_best = (num_sources + 1) // 2
        best, worst = best_and_worst(scores, n_best, num_sources - n_best)
        chosen = np.concatenate([best, worst])
    elif strategy == "best":
        best, _ = best_and_worst(scores, num_sources, 0)
        chosen = best
    else:
        raise ValueError(f"unknown source strategy {strategy!r}; expected 'anti_noise' or 'best'")
    if chosen.size == 0:
        return []
    return [int(ids[chosen[j % chosen.size]]) for j in range(num_sources)]


# --------------------------------------------------------------------------- dataset


@dataclass(frozen=True)
class _Entry:
    scan: str
    light: int | None
    ref: int
    sources: tuple[int, ...]


def resize_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Depth ``[h, w]`` resized to ``[height, width]``: valid-aware down (module docstring), nearest up."""
    h, w = depth.shape
    if (h, w) == (height, width):
        return depth
    t = torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))[None]
    if height <= h and width <= w:
        out = downsample_depth(t, (height, width), "min")
    else:
        t = torch.where(torch.isfinite(t) & (t > 0), t, torch.zeros_like(t))
        out = F.interpolate(t[:, None], size=(height, width), mode="nearest-exact")[:, 0]
    return out[0].numpy()


class MVSNetDataset(Dataset):
    """An MVSNet-format training set as a map-style torch ``Dataset``.

    Every item is the same dict as :class:`colmap_pvs.synthetic.SyntheticMVSDataset`'s::

        images          [N, 3, H, W] float32 in [0, 1], reference at index 0
        intrinsics      [N, 3, 3] float32, our +0.5 pixel-centre convention, at [H, W]
        cam_from_world  [N, 4, 4] float32
        depth           [H, W] float32 GT reference depth, 0 = invalid
        depth_min       [] float32
        depth_max       [] float32
        sparse_depth    [1, H, W] float32, 0 = no point

    Items are deterministic functions of ``(config, index)``.

    Args:
        config: the dataset config; ``config.root`` must be set.
        scans: the scans to use; default ``config.scans`` (discovered when empty).
    """

    def __init__(self, config: MVSNetDatasetConfig, scans: tuple[str, ...] | None = None) -> None:
        if config.root is None:
            raise ConfigError("MVSNetDatasetConfig.root must be set to the dataset folder")
        self.config = config
        self.root = Path(config.root)
        if not self.root.is_dir():
            raise MVSNetFormatError(f"MVSNet dataset root {str(self.root)!r} is not a folder")
        self._templates = {
            k: config.resolved(k)
            for k in ("image_template", "depth_template", "cam_template", "pair_template")
        }
        self._uses_light = "{light" in self._templates["image_template"]
        scans = tuple(config.scans if scans is None else scans) or self.discover_scans()
        if not scans:
            raise MVSNetFormatError(f"no scans found under {str(self.root)!r} with layout {config.layout!r}")
        self.scans = scans
        self._entries = self._build_index()
        if not self._entries:
            raise MVSNetFormatError(
                f"no usable reference views in scans {list(scans)} under {str(self.root)!r}"
            )

    # ----------------------------------------------------------------- paths

    def path(self, kind: str, scan: str, view: int = 0, light: int | None = None) -> Path:
        """Path of a file: ``kind`` is ``"image"``, ``"depth"``, ``"cam"`` or ``"pair"``."""
        tpl = self._templates[f"{kind}_template"]
        return self.root / tpl.format(
            scan=scan, view=view, view1=view + 1, light=0 if light is None else light
        )

    def discover_scans(self) -> tuple[str, ...]:
        """Scans found under ``root`` (module docstring, "Folder layouts"), sorted."""
        parts = Path(self._templates["image_template"]).parts
        k = next((i for i, p in enumerate(parts) if "{scan" in p), None)
        if k is None:
            raise ConfigError(
                f"cannot discover scans: image template {self._templates['image_template']!r} "
                "has no {scan}; "
                "list them in MVSNetDatasetConfig.scans"
            )
        parent = self.root.joinpath(*parts[:k])
        pattern = re.escape(parts[k]).replace(re.escape("{scan}"), "(.+)")
        regex = re.compile(f"^{pattern}$")
        found = []
        for entry in sorted(parent.iterdir()) if parent.is_dir() else []:
            m = regex.match(entry.name)
            if m and self.path("pair", m.group(1)).is_file():
                found.append(m.group(1))
        return tuple(found)

    def _build_index(self) -> list[_Entry]:
        cfg = self.config
        lights = cfg.lights if self._uses_light else (None,)
        entries: list[_Entry] = []
        dropped = 0
        for scan in self.scans:
            pairs = read_pair_file(self.path("pair", scan))
            for ref, listed in pairs.items():
                srcs = select_sources(listed, cfg.num_views - 1, cfg.source_strategy, exclude=ref)
                if not srcs:
                    dropped += 1
                    continue
                for light in lights:
                    entries.append(_Entry(scan, light, ref, tuple(srcs)))
        if dropped:
            logger.warning("MVSNet dataset: dropped %d reference view(s) without any source", dropped)
        return entries

    # ----------------------------------------------------------------- items

    def __len__(self) -> int:
        return len(self._entries)

    def sample_info(self, index: int) -> dict[str, Any]:
        """``{"scan", "light", "ref", "sources"}`` of item ``index`` (not part of the sample)."""
        return dataclasses.asdict(self._entries[index])

    def _load_view(
        self, scan: str, view: int, light: int | None
    ) -> tuple[np.ndarray, np.ndarray, MVSNetCamera]:
        path = self.path("image", scan, view, light)
        try:
            rgb = load_image(path)
        except WorkspaceError as exc:
            raise MVSNetFormatError(str(exc)) from None
        cam = read_mvsnet_cam(self.path("cam", scan, view))
        K = cam.K.copy()
        K[0, 2] += self.config.pixel_center_offset
        K[1, 2] += self.config.pixel_center_offset
        s = float(self.config.resolved("intrinsics_scale"))
        K = scale_intrinsics(K, s, s)
        h, w = rgb.shape[:2]
        if self.config.image_size is not None:
            W, H = self.config.image_size
            if (W, H) != (w, h):
                interp = cv2.INTER_AREA if (W <= w and H <= h) else cv2.INTER_LINEAR
                rgb = cv2.resize(rgb, (W, H), interpolation=interp)
                K = np.diag([W / w, H / h, 1.0]) @ K
        return rgb, K, cam

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        if not 0 <= index < len(self._entries):
            raise IndexError(
                f"index {index} out of range for an MVSNet dataset of {len(self._entries)} items"
            )
        e = self._entries[index]
        images, Ks, poses = [], [], []
        ref_cam = None
        for view in (e.ref, *e.sources):
            rgb, K, cam = self._load_view(e.scan, view, e.light)
            if images and rgb.shape != images[0].shape:
                raise MVSNetFormatError(
                    f"scan {e.scan!r}: view {view} has image size {rgb.shape[1::-1]}, "
                    f"reference {e.ref} has {images[0].shape[1::-1]}"
                )
            if ref_cam is None:
                ref_cam = cam
            images.append(rgb)
            Ks.append(K)
            poses.append(cam.cam_from_world)
        H, W = images[0].shape[:2]
        depth = read_pfm(self.path("depth", e.scan, e.ref))
        if depth.ndim != 2:
            raise MVSNetFormatError(
                f"depth map of scan {e.scan!r} view {e.ref} has {depth.shape[2]} channels"
            )
        depth = resize_depth(np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32), W, H)
        dmin, dmax = ref_cam.depth_range(self.config.default_num_depth, self.config.depth_interval_scale)
        sparse = np.zeros((1, H, W), dtype=np.float32)
        if self.config.sparse_points > 0:
            rng = np.random.default_rng([self.config.seed, index])
            valid = np.flatnonzero(depth > 0)
            pick = rng.choice(valid, size=min(self.config.sparse_points, valid.size), replace=False)
            sparse.reshape(-1)[pick] = depth.reshape(-1)[pick]
        return {
            "images": torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).float().div_(255.0),
            "intrinsics": torch.from_numpy(np.stack(Ks)).float(),
            "cam_from_world": torch.from_numpy(np.stack(poses)).float(),
            "depth": torch.from_numpy(np.ascontiguousarray(depth)).float(),
            "depth_min": torch.tensor(dmin, dtype=torch.float32),
            "depth_max": torch.tensor(dmax, dtype=torch.float32),
            "sparse_depth": torch.from_numpy(sparse),
        }
