"""Albedo textures for synthetic scenes: shipped CC0 photographs and procedural patterns.

All textures are square ``[S, S, 3]`` float32 arrays in ``[0, 1]`` (``S`` =
:data:`TEXTURE_SIZE`, a power of two), so that a scene's textures stack into one
``[T, S, S, 3]`` array and share one mip-map pyramid (:func:`build_mipmaps`).
Lookups (:func:`sample_textures`) use *mirrored repeat* addressing, so photographs tile
without seams, and trilinear filtering between mip levels, so that minified textures do
not alias (aliasing would make the same surface look different in different views).

Texture coordinates ``uv`` are in *tiles*: ``u`` runs along columns, ``v`` along rows,
and ``uv = (1, 1)`` is the far corner of the first tile. Texel ``(col, row)`` has its
centre at ``((col + 0.5) / S, (row + 0.5) / S)``.

The photographs live in ``colmap_pvs/synthetic/textures/`` (see ``LICENSES.md`` there);
scikit-image is not needed at run time.
"""

from __future__ import annotations

import functools
import importlib.resources
import logging

import cv2
import numpy as np

from ..errors import ShapeError

logger = logging.getLogger(__name__)

TEXTURE_SIZE = 256
"""Edge length in texels of every texture (power of two)."""

PHOTO_NAMES = ("astronaut", "coffee", "chelsea", "rocket", "brick", "grass", "gravel", "camera")
"""Photographs shipped in ``textures/`` (all public domain or CC0, see ``LICENSES.md``)."""

PROCEDURAL_KINDS = ("noise", "stripes", "checker", "bricks", "blobs")
"""Procedural, well-textured pattern kinds."""

TEXTURE_KINDS = ("photo", *PROCEDURAL_KINDS, "low")
"""Every kind :func:`make_texture` accepts; ``"low"`` is a deliberately low-texture surface."""


@functools.lru_cache(maxsize=1)
def photo_textures() -> tuple[np.ndarray, ...]:
    """The shipped photographs, in :data:`PHOTO_NAMES` order, each ``[S, S, 3]`` float32 in ``[0, 1]``.

    Grey-level photographs are replicated to three channels. The arrays are cached and
    read-only.
    """
    root = importlib.resources.files("colmap_pvs.synthetic") / "textures"
    out = []
    for name in PHOTO_NAMES:
        resource = root / f"{name}.jpg"
        try:
            data = np.frombuffer(resource.read_bytes(), dtype=np.uint8)
        except FileNotFoundError:
            raise FileNotFoundError(f"texture file {str(resource)!r} is missing from the package") from None
        img = cv2.imdecode(data, cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"texture file {str(resource)!r} could not be decoded")
        img = img[..., ::-1]
        if img.shape[:2] != (TEXTURE_SIZE, TEXTURE_SIZE):
            img = cv2.resize(img, (TEXTURE_SIZE, TEXTURE_SIZE), interpolation=cv2.INTER_AREA)
        arr = np.ascontiguousarray(img, dtype=np.float32) / 255.0
        arr.setflags(write=False)
        out.append(arr)
    return tuple(out)


# --------------------------------------------------------------------------- procedural


def value_noise(
    rng: np.random.Generator, size: int, octaves: int = 5, base_cells: int = 4, persistence: float = 0.55
) -> np.ndarray:
    """Multi-octave value noise (interpolated random lattices): ``[size, size]`` float32 in [0, 1]."""
    out = np.zeros((size, size), np.float32)
    amp, total = 1.0, 0.0
    cells = base_cells
    for _ in range(octaves):
        grid = rng.random((cells + 1, cells + 1)).astype(np.float32)
        layer = cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC)
        out += amp * layer
        total += amp
        amp *= persistence
        cells = min(cells * 2, size)
    out /= total
    lo, hi = np.percentile(out, [1, 99])
    return np.clip((out - lo) / max(hi - lo, 1e-6), 0.0, 1.0).astype(np.float32)


def _random_colors(rng: np.random.Generator, n: int) -> np.ndarray:
    """``[n, 3]`` random colours with varied saturation and brightness."""
    hsv = np.stack([rng.random(n) * 180, rng.uniform(40, 220, n), rng.uniform(50, 245, n)], -1)
    rgb = cv2.cvtColor(hsv.astype(np.uint8)[None], cv2.COLOR_HSV2RGB)[0]
    return rgb.astype(np.float32) / 255.0


def colorize(gray: np.ndarray, rng: np.random.Generator, n_colors: int = 3) -> np.ndarray:
    """Map a ``[S, S]`` scalar field in [0, 1] through a random colour ramp -> ``[S, S, 3]``."""
    colors = _random_colors(rng, n_colors)
    pos = np.linspace(0.0, 1.0, n_colors)
    return np.stack([np.interp(gray, pos, colors[:, c]) for c in range(3)], -1).astype(np.float32)


def _coords(size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Randomly rotated texel coordinates in tiles, each ``[S, S]``."""
    v, u = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size, indexing="ij")
    a = rng.uniform(0, np.pi)
    return (np.cos(a) * u + np.sin(a) * v).astype(np.float32), (-np.sin(a) * u + np.cos(a) * v).astype(
        np.float32
    )


def stripes(rng: np.random.Generator, size: int) -> np.ndarray:
    """Noisy sinusoidal stripes of random orientation and frequency, ``[S, S, 3]``."""
    x, _ = _coords(size, rng)
    freq = rng.uniform(3, 14)
    warp = value_noise(rng, size, octaves=3) - 0.5
    g = 0.5 + 0.5 * np.sin(2 * np.pi * (freq * x + rng.uniform(0.2, 1.0) * warp))
    g = 0.75 * g + 0.25 * value_noise(rng, size, octaves=6, base_cells=16)
    return colorize(g, rng, 2)


def checker(rng: np.random.Generator, size: int) -> np.ndarray:
    """A checkerboard with random cell size and per-cell noise, ``[S, S, 3]``."""
    x, y = _coords(size, rng)
    n = rng.integers(3, 12)
    g = ((np.floor(x * n) + np.floor(y * n)) % 2).astype(np.float32)
    g = 0.7 * g + 0.3 * value_noise(rng, size, octaves=5, base_cells=8)
    return colorize(g, rng, 2)


def bricks(rng: np.random.Generator, size: int) -> np.ndarray:
    """Bricks in running bond with mortar lines and per-brick colour variation, ``[S, S, 3]``."""
    rows = int(rng.integers(4, 12))
    cols = max(2, int(rows * rng.uniform(0.4, 0.8)))
    v, u = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size, indexing="ij")
    r = np.floor(v * rows)
    uu = u * cols + 0.5 * (r % 2)
    c = np.floor(uu)
    fu, fv = uu - c, v * rows - r
    mortar = rng.uniform(0.04, 0.1)
    is_mortar = (fu < mortar) | (fv < mortar * cols / rows * 1.5)
    brick_id = (r * 131 + c * 17).astype(np.int64) % 997
    shade = rng.uniform(0.6, 1.0, 997).astype(np.float32)[brick_id]
    base, mortar_col = _random_colors(rng, 2)
    img = base[None, None] * shade[..., None] * (0.8 + 0.4 * value_noise(rng, size, 6, 16)[..., None])
    img[is_mortar] = mortar_col * 0.9
    return np.clip(img, 0, 1).astype(np.float32)


def color_blobs(rng: np.random.Generator, size: int) -> np.ndarray:
    """Random coloured discs and ellipses on a noisy background, ``[S, S, 3]``."""
    img = colorize(value_noise(rng, size, 4), rng, 2)
    img8 = (img * 255).astype(np.uint8)
    for _ in range(int(rng.integers(15, 50))):
        col = tuple(int(x) for x in (_random_colors(rng, 1)[0] * 255))
        centre = (int(rng.integers(0, size)), int(rng.integers(0, size)))
        axes = (int(rng.integers(3, size // 6)), int(rng.integers(3, size // 6)))
        cv2.ellipse(img8, centre, axes, float(rng.uniform(0, 180)), 0, 360, col, -1, cv2.LINE_AA)
    return img8.astype(np.float32) / 255.0


def low_texture(rng: np.random.Generator, size: int) -> np.ndarray:
    """A deliberately low-texture surface: a near-uniform colour, a slight gradient and faint noise."""
    base = _random_colors(rng, 1)[0]
    x, _ = _coords(size, rng)
    grad = 1.0 + rng.uniform(-0.08, 0.08) * (x - 0.5)
    noise = 1.0 + rng.uniform(0.0, 0.02) * (value_noise(rng, size, 4, 4) - 0.5)
    return np.clip(base[None, None] * (grad * noise)[..., None], 0, 1).astype(np.float32)


def _photo(rng: np.random.Generator, size: int) -> np.ndarray:
    photos = photo_textures()
    img = photos[int(rng.integers(len(photos)))]
    img = np.rot90(img, int(rng.integers(4)))
    if rng.random() < 0.5:
        img = img[:, ::-1]
    if size != img.shape[0]:
        img = cv2.resize(np.ascontiguousarray(img), (size, size), interpolation=cv2.INTER_AREA)
    gray = bool(np.allclose(img[..., 0], img[..., 1]) and np.allclose(img[..., 1], img[..., 2]))
    tint = _random_colors(rng, 1)[0] * 0.6 + 0.4 if gray else rng.uniform(0.85, 1.15, 3).astype(np.float32)
    contrast = rng.uniform(0.7, 1.2)
    out = (img - 0.5) * contrast + 0.5
    return np.clip(out * tint[None, None], 0, 1).astype(np.float32)


_MAKERS = {
    "photo": _photo,
    "noise": lambda rng, size: colorize(
        value_noise(rng, size, int(rng.integers(4, 8)), int(rng.integers(2, 12))),
        rng,
        int(rng.integers(2, 5)),
    ),
    "stripes": stripes,
    "checker": checker,
    "bricks": bricks,
    "blobs": color_blobs,
    "low": low_texture,
}


def make_texture(rng: np.random.Generator, kind: str, size: int = TEXTURE_SIZE) -> np.ndarray:
    """One texture of ``kind`` (one of :data:`TEXTURE_KINDS`): ``[size, size, 3]`` float32 in [0, 1]."""
    try:
        maker = _MAKERS[kind]
    except KeyError:
        raise ValueError(f"unknown texture kind {kind!r}; expected one of {list(TEXTURE_KINDS)}") from None
    tex = maker(rng, size)
    if tex.shape != (size, size, 3):
        raise ShapeError(f"texture kind {kind!r} produced shape {tex.shape}, expected {(size, size, 3)}")
    return np.ascontiguousarray(tex, dtype=np.float32)


def random_texture_kind(rng: np.random.Generator, photo_fraction: float, low_texture_fraction: float) -> str:
    """A random kind: ``"low"`` with probability ``low_texture_fraction``, ``"photo"`` with
    ``photo_fraction``, else a procedural one."""
    r = rng.random()
    if r < low_texture_fraction:
        return "low"
    if r < low_texture_fraction + photo_fraction:
        return "photo"
    return PROCEDURAL_KINDS[int(rng.integers(len(PROCEDURAL_KINDS)))]


# --------------------------------------------------------------------------- sampling


def build_mipmaps(textures: np.ndarray) -> list[np.ndarray]:
    """Box-filtered mip pyramid of ``[T, S, S, 3]`` textures.

    Level ``l`` is ``[T, S / 2^l, S / 2^l, 3]``, down to 1x1.
    """
    if textures.ndim != 4 or textures.shape[1] != textures.shape[2] or textures.shape[3] != 3:
        raise ShapeError(f"textures must be [T, S, S, 3], got shape {textures.shape}")
    size = textures.shape[1]
    if size & (size - 1):
        raise ShapeError(f"texture size must be a power of two, got {size}")
    levels = [np.ascontiguousarray(textures, dtype=np.float32)]
    while levels[-1].shape[1] > 1:
        t = levels[-1]
        levels.append(0.25 * (t[:, 0::2, 0::2] + t[:, 1::2, 0::2] + t[:, 0::2, 1::2] + t[:, 1::2, 1::2]))
    return levels


def _mirror(idx: np.ndarray, n: int) -> np.ndarray:
    """Mirrored-repeat addressing of integer texel indices into ``[0, n)``."""
    m = np.mod(idx, 2 * n)
    return np.minimum(m, 2 * n - 1 - m)


def _bilinear(flat: np.ndarray, size: int, tex: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup in one mip level stored flat as ``[T * size * size, 3]``."""
    x = uv[:, 0] * np.float32(size) - np.float32(0.5)
    y = uv[:, 1] * np.float32(size) - np.float32(0.5)
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0).astype(np.float32)[:, None]
    fy = (y - y0).astype(np.float32)[:, None]
    x0 = x0.astype(np.int64)
    y0 = y0.astype(np.int64)
    base = tex * (size * size)
    ra = base + _mirror(y0, size) * size
    rb = base + _mirror(y0 + 1, size) * size
    xa, xb = _mirror(x0, size), _mirror(x0 + 1, size)
    top = np.take(flat, ra + xa, axis=0)
    top += (np.take(flat, ra + xb, axis=0) - top) * fx
    bot = np.take(flat, rb + xa, axis=0)
    bot += (np.take(flat, rb + xb, axis=0) - bot) * fx
    return top + (bot - top) * fy


def sample_textures(
    mipmaps: list[np.ndarray], texture_ids: np.ndarray, uv: np.ndarray, texels_per_pixel: np.ndarray
) -> np.ndarray:
    """Trilinear, mirrored-repeat texture lookup.

    Args:
        mipmaps: output of :func:`build_mipmaps`.
        texture_ids: ``[P]`` int texture index per sample.
        uv: ``[P, 2]`` texture coordinates in tiles.
        texels_per_pixel: ``[P]`` footprint of one pixel in level-0 texels (selects the mip level).

    Returns:
        ``[P, 3]`` float32 colours.
    """
    texture_ids = np.asarray(texture_ids, dtype=np.int64)
    uv = np.asarray(uv)
    if uv.ndim != 2 or uv.shape[1] != 2 or uv.shape[0] != texture_ids.shape[0]:
        raise ShapeError(f"uv must be [P, 2] with P = {texture_ids.shape[0]}, got shape {uv.shape}")
    n_levels = len(mipmaps)
    flats = [m.reshape(-1, 3) for m in mipmaps]
    level = np.clip(np.log2(np.maximum(np.asarray(texels_per_pixel, np.float32), 1e-6)), 0, n_levels - 1)
    l0 = np.minimum(np.floor(level).astype(np.int64), n_levels - 1)
    frac = (level - l0).astype(np.float32)[:, None]
    out = np.empty((texture_ids.shape[0], 3), np.float32)
    for lvl in np.nonzero(np.bincount(l0, minlength=n_levels))[0]:
        sel = np.nonzero(l0 == lvl)[0]
        t_sel, uv_sel = texture_ids[sel], uv[sel]
        col = _bilinear(flats[lvl], mipmaps[lvl].shape[1], t_sel, uv_sel)
        if lvl + 1 < n_levels:
            f = frac[sel]
            col += (_bilinear(flats[lvl + 1], mipmaps[lvl + 1].shape[1], t_sel, uv_sel) - col) * f
        out[sel] = col
    return out
