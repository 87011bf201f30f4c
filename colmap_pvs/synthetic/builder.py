"""The building blocks of the scene families: a mesh with its texture bank and bookkeeping, discs, lights."""

from __future__ import annotations

import numpy as np

from .mesh import Material, MeshBuilder
from .scene_types import Light, Scene, SceneConfig, ViewSpace
from .textures import TEXTURE_SIZE, make_texture, random_texture_kind


class _Builder:
    """Mesh + texture bank + bookkeeping while a scene is built."""

    def __init__(self, rng: np.random.Generator, config: SceneConfig, nominal_distance: float) -> None:
        self.rng = rng
        self.config = config
        self.nominal_distance = nominal_distance
        self.mesh = MeshBuilder()
        self.textures: list[np.ndarray] = []
        self.kinds: list[str] = []
        self.solids: list[np.ndarray] = []
        self.occluders: list[np.ndarray] = []

    def texture(self, kind: str | None = None) -> int:
        """Add a new texture (random kind unless given) and return its index."""
        c = self.config
        kind = kind or random_texture_kind(self.rng, c.photo_texture_fraction, c.low_texture_fraction)
        self.textures.append(make_texture(self.rng, kind, TEXTURE_SIZE))
        self.kinds.append(kind)
        return len(self.textures) - 1

    def material(self, kind: str | None = None, texture: int | None = None, scale: float = 1.0) -> Material:
        """A material with a new (or the given) texture and a random tile size."""
        lo, hi = self.config.texture_scale
        tile = self.nominal_distance * scale * float(np.exp(self.rng.uniform(np.log(lo), np.log(hi))))
        tex = self.texture(kind) if texture is None else texture
        return Material(
            texture=tex,
            density=1.0 / tile,
            angle=float(self.rng.uniform(0, 2 * np.pi)),
            offset=(float(self.rng.random()), float(self.rng.random())),
        )

    def solid(self, lo: np.ndarray, hi: np.ndarray) -> None:
        self.solids.append(np.stack([np.asarray(lo, float), np.asarray(hi, float)]))

    def last_aabb(self, n: int = 1) -> np.ndarray:
        """Union of the bounds of the last ``n`` primitives."""
        boxes = np.stack(self.mesh.aabbs[-n:])
        return np.stack([boxes[:, 0].min(0), boxes[:, 1].max(0)])

    def bumps(self, amplitude: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = int(self.rng.integers(3, 9))
        dirs = self.rng.normal(size=(n, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        amps = self.rng.uniform(-1, 1, n) * amplitude * self.config.bumpiness
        widths = self.rng.uniform(0.3, 0.8, n)
        return dirs, amps, widths

    def smooth_heights(self, nu: int, nv: int, amplitude: float, cells: int = 4) -> np.ndarray:
        """``[nu, nv]`` smooth random relief with the given peak amplitude."""
        import cv2

        grid = self.rng.uniform(-1, 1, (cells + 1, cells + 1)).astype(np.float32)
        h = cv2.resize(grid, (nv, nu), interpolation=cv2.INTER_CUBIC).astype(np.float64)
        return h * amplitude * self.config.bumpiness

    def finish(
        self,
        family: str,
        seed: int,
        light: Light,
        roi_center: np.ndarray,
        roi_radius: float,
        view_space: ViewSpace,
    ) -> Scene:
        arrays = self.mesh.arrays()
        bg = np.clip(self.rng.uniform(0.05, 0.6) * np.ones(3) + self.rng.normal(0, 0.05, 3), 0, 1)
        return Scene(
            family=family,
            seed=seed,
            vertices=arrays["vertices"],
            triangles=arrays["triangles"],
            uvs=arrays["uvs"],
            triangle_texture=arrays["triangle_texture"],
            triangle_density=arrays["triangle_density"],
            triangle_part=arrays["triangle_part"],
            textures=np.stack(self.textures).astype(np.float32),
            texture_kinds=tuple(self.kinds),
            background=bg.astype(np.float32),
            light=light,
            roi_center=np.asarray(roi_center, np.float64),
            roi_radius=float(roi_radius),
            view_space=view_space,
            solids=np.stack(self.solids) if self.solids else np.zeros((0, 2, 3)),
            occluders=np.stack(self.occluders) if self.occluders else np.zeros((0, 3)),
        )


def _place_discs(
    rng: np.random.Generator, radii: np.ndarray, bounds: np.ndarray, tries: int = 200
) -> list[tuple[int, np.ndarray]]:
    """Non-overlapping disc centres inside ``bounds`` ``[2, 2]`` (xy min/max); discs that don't fit are
    dropped."""
    placed: list[tuple[int, np.ndarray]] = []
    for i, r in enumerate(radii):
        lo, hi = bounds[0] + r, bounds[1] - r
        if np.any(lo > hi):
            continue
        for _ in range(tries):
            p = rng.uniform(lo, hi)
            if all(np.linalg.norm(p - q) >= r + radii[j] + 0.01 for j, q in placed):
                placed.append((i, p))
                break
    return placed


def _directional_light(rng: np.random.Generator, az_deg: float | None = None) -> Light:
    az = np.radians(rng.uniform(0, 360) if az_deg is None else az_deg)
    el = np.radians(rng.uniform(30, 75))
    to_light = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return Light(
        "directional",
        tuple(float(x) for x in -to_light),
        float(rng.uniform(0.55, 0.9)),
        float(rng.uniform(0.25, 0.45)),
    )
