"""What a synthetic scene is: :class:`SceneConfig`, its light, its camera space and the :class:`Scene`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from ..errors import ConfigError

FAMILIES = ("object", "room", "facade")

#: Every family :func:`build_scene` knows (``"plant"`` is drawn by ``"any"`` only when listed in
#: ``SceneConfig.families``).
ALL_FAMILIES = (*FAMILIES, "plant")


@dataclass(frozen=True)
class SceneConfig:
    """How synthetic scenes are built (the seed is passed separately)."""

    family: Literal["any", "object", "room", "facade", "plant"] = field(
        default="any", metadata={"help": "scene family; 'any' draws one of `families` uniformly per scene"}
    )
    families: tuple[str, ...] = field(
        default=FAMILIES, metadata={"help": "the families 'any' draws from; add 'plant' for thin fronds"}
    )
    min_objects: int = field(default=3, metadata={"help": "minimum number of objects / furniture items"})
    max_objects: int = field(default=6, metadata={"help": "maximum number of objects / furniture items"})
    photo_texture_fraction: float = field(
        default=0.35, metadata={"help": "probability that a surface gets a photographic texture"}
    )
    low_texture_fraction: float = field(
        default=0.15,
        metadata={
            "help": "probability that a surface gets a deliberately low-texture (near-uniform) material"
        },
    )
    texture_scale: tuple[float, ...] = field(
        default=(0.15, 1.0),
        metadata={
            "help": "range (lo, hi) of the size of one texture tile, relative to the nominal viewing "
            "distance (log-uniform)"
        },
    )
    bumpiness: float = field(default=1.0, metadata={"help": "scale of height-field / blob relief amplitudes"})
    segments: int = field(default=32, metadata={"help": "segments of spheres and cylinders"})
    thin_structures: bool = field(default=True, metadata={"help": "add thin legs, poles and railings"})

    def __post_init__(self) -> None:
        if not 0 <= self.min_objects <= self.max_objects:
            raise ConfigError(
                f"need 0 <= min_objects <= max_objects, got min_objects={self.min_objects}, "
                f"max_objects={self.max_objects}"
            )
        for name in ("photo_texture_fraction", "low_texture_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if self.photo_texture_fraction + self.low_texture_fraction > 1.0:
            raise ConfigError(
                f"photo_texture_fraction + low_texture_fraction must be <= 1, got "
                f"{self.photo_texture_fraction} + {self.low_texture_fraction}"
            )
        scale = tuple(float(v) for v in self.texture_scale)
        object.__setattr__(self, "texture_scale", scale)
        if len(scale) != 2 or not 0 < scale[0] <= scale[1]:
            raise ConfigError(f"texture_scale must be two numbers 0 < lo <= hi, got {self.texture_scale!r}")
        if self.bumpiness < 0:
            raise ConfigError(f"bumpiness must be >= 0, got {self.bumpiness}")
        if self.segments < 6:
            raise ConfigError(f"segments must be >= 6, got {self.segments}")
        if self.family != "any" and self.family not in ALL_FAMILIES:
            raise ConfigError(f"family must be 'any' or one of {ALL_FAMILIES}, got {self.family!r}")
        given = self.families
        families = () if isinstance(given, str) else tuple(str(f) for f in given)
        if not families or any(f not in ALL_FAMILIES for f in families):
            raise ConfigError(
                f"families must be a non-empty list of names from {ALL_FAMILIES} (a name given twice is "
                f"drawn twice as often), got {given!r}"
            )
        object.__setattr__(self, "families", families)


@dataclass(frozen=True)
class Light:
    """Scene lighting (view independent, so shading is multi-view consistent).

    Attributes:
        kind: ``"directional"`` (``vector`` = direction the light travels) or ``"point"``
            (``vector`` = light position).
        vector: ``[3]``.
        intensity: diffuse intensity.
        ambient: ambient term.
        falloff: point lights only: distance at which the intensity halves (``1 / (1 + (d/f)^2)``).
    """

    kind: Literal["directional", "point"]
    vector: tuple[float, float, float]
    intensity: float
    ambient: float
    falloff: float = 0.0


@dataclass(frozen=True)
class ViewSpace:
    """Where cameras may be, as spherical coordinates around the region of interest.

    Eye = ``roi_center + dist * (cos(el) cos(az), cos(el) sin(az), sin(el))``.

    Attributes:
        az_center_deg, az_range_deg: azimuth in ``az_center +- az_range``.
        el_range_deg: ``(lo, hi)`` elevation.
        dist_range: ``(lo, hi)`` distance to the region of interest.
        eye_box: ``[2, 3]`` bounds the eye must stay in.
        margin: minimum clearance between the eye and any solid box.
    """

    az_center_deg: float
    az_range_deg: float
    el_range_deg: tuple[float, float]
    dist_range: tuple[float, float]
    eye_box: np.ndarray
    margin: float


@dataclass(frozen=True, eq=False)
class Scene:
    """A textured triangle mesh plus camera-placement hints.

    Attributes:
        family: ``"object"``, ``"room"``, ``"facade"`` or ``"plant"``.
        seed: the seed it was built from.
        vertices: ``[V, 3]`` float64.
        triangles: ``[F, 3]`` int32.
        uvs: ``[V, 2]`` float32 texture coordinates in tiles.
        triangle_texture: ``[F]`` int32 index into ``textures``.
        triangle_density: ``[F]`` float32 texture tiles per scene unit (for mip selection).
        triangle_part: ``[F]`` int32 id of the surface patch (box face, sphere...) each triangle belongs to.
        textures: ``[T, S, S, 3]`` float32 albedo in [0, 1].
        texture_kinds: ``T`` kind names (see :data:`.textures.TEXTURE_KINDS`).
        background: ``[3]`` colour of pixels that hit nothing.
        light: the scene's :class:`Light`.
        roi_center: ``[3]`` region of interest the cameras look at.
        roi_radius: its radius.
        view_space: where cameras may stand.
        solids: ``[M, 2, 3]`` boxes (min, max) cameras must stay out of.
        occluders: ``[K, 3]`` centres of objects that can hide the region of interest.
    """

    family: str
    seed: int
    vertices: np.ndarray
    triangles: np.ndarray
    uvs: np.ndarray
    triangle_texture: np.ndarray
    triangle_density: np.ndarray
    triangle_part: np.ndarray
    textures: np.ndarray
    texture_kinds: tuple[str, ...]
    background: np.ndarray
    light: Light
    roi_center: np.ndarray
    roi_radius: float
    view_space: ViewSpace
    solids: np.ndarray
    occluders: np.ndarray

    @property
    def num_triangles(self) -> int:
        return int(self.triangles.shape[0])

    def to_open3d(self):
        """An ``open3d.t.geometry.TriangleMesh`` with ``vertex.positions``, ``vertex.texture_uvs``
        and ``triangle.indices``, ``triangle.texture_ids`` and ``triangle.texture_density``."""
        import open3d as o3d

        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor(self.vertices.astype(np.float32))
        mesh.vertex.texture_uvs = o3d.core.Tensor(self.uvs.astype(np.float32))
        mesh.triangle.indices = o3d.core.Tensor(self.triangles.astype(np.int32))
        mesh.triangle.texture_ids = o3d.core.Tensor(self.triangle_texture.astype(np.int32))
        mesh.triangle.texture_density = o3d.core.Tensor(self.triangle_density.astype(np.float32))
        return mesh
