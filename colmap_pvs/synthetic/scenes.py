"""Procedural synthetic scenes, deterministic from a seed.

Four families (``SceneConfig.family``):

- ``"object"``: DTU-like. A few objects (boxes, spheres, cylinders, cones, bumpy blobs) on
  a table with thin legs, a floor and optional backdrop walls. Cameras live on a sphere
  cap around the objects.
- ``"room"``: indoor. Walls, floor and ceiling (often low-texture), furniture-like shapes
  (tables and chairs with thin legs, shelves, cabinets, sofas, lamps on thin poles, balls),
  posters. Cameras move inside the room.
- ``"facade"``: a building facade with relief (recessed windows, ledges), protruding
  boxes (balconies, pilasters), neighbouring facades, a street and street furniture
  (poles, bins, trees) that occludes it. Cameras stand in the street.
- ``"plant"`` (only when named, or listed in ``SceneConfig.families``): a potted plant whose
  fronds (2-11 cm wide, 0.3-1.4 m long) are thin curved strips, some with leaflets, fanned out in
  front of a wall about 1-5 m behind the pot:
  thin structures a few pixels wide with a large depth gap to what is behind them, the case
  (fern fronds, a statue's crown) that a coarse cost volume blurs. Cameras stand in front.

A :class:`Scene` is a single textured triangle mesh (plain numpy, see :mod:`.mesh`) plus
what camera generation needs: a region of interest that cameras look at, the space the
cameras may occupy and solid boxes they must stay out of, and occluder positions for the
"disturbing" views. World axes: +z is up; units are metres.

The types are in :mod:`.scene_types`, the building blocks in :mod:`.builder` and the families in
:mod:`.families`; this module builds a scene of a family (:func:`build_scene`) or of given
primitives (:func:`scene_from_primitives`).
"""

from __future__ import annotations

import logging

import numpy as np

from .builder import _Builder
from .families import _facade_scene, _object_scene, _plant_scene, _room_scene
from .scene_types import ALL_FAMILIES, FAMILIES, Light, Scene, SceneConfig, ViewSpace

logger = logging.getLogger(__name__)

__all__ = [
    "ALL_FAMILIES",
    "FAMILIES",
    "Light",
    "Scene",
    "SceneConfig",
    "ViewSpace",
    "build_scene",
    "scene_from_primitives",
]


_NOMINAL_DISTANCE = {"object": 0.9, "room": 2.2, "facade": 8.0, "plant": 2.0}


def build_scene(config: SceneConfig, seed: int) -> Scene:
    """Build a scene of ``config.family`` from ``seed`` (same inputs -> identical arrays)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5CE4E]))
    family = config.family
    if family == "any":
        family = config.families[int(rng.integers(len(config.families)))]
    nominal = _NOMINAL_DISTANCE[family] * float(rng.uniform(0.85, 1.2))
    builder = _Builder(rng, config, nominal)
    make = {"object": _object_scene, "room": _room_scene, "facade": _facade_scene, "plant": _plant_scene}[
        family
    ]
    scene = make(builder, int(seed))
    logger.debug(
        "built %s scene (seed %d): %d triangles, %d textures",
        family,
        seed,
        scene.num_triangles,
        scene.textures.shape[0],
    )
    return scene


def scene_from_primitives(
    builder_fn,
    *,
    seed: int = 0,
    roi_center=(0.0, 0.0, 0.0),
    roi_radius: float = 1.0,
    view_space: ViewSpace | None = None,
    light: Light | None = None,
    config: SceneConfig | None = None,
    nominal_distance: float = 1.0,
) -> Scene:
    """A custom scene: ``builder_fn(mesh: MeshBuilder, material: Callable[..., Material])`` adds primitives.

    ``material(kind=None, scale=1.0)`` returns a new random material; used by tests and examples
    that need simple analytic geometry (a plane, a sphere).
    """
    config = config or SceneConfig()
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xC057]))
    b = _Builder(rng, config, nominal_distance)
    builder_fn(b.mesh, lambda kind=None, scale=1.0: b.material(kind=kind, scale=scale))
    vs = view_space or ViewSpace(
        0.0, 180.0, (-80.0, 80.0), (1.0, 2.0), np.array([[-1e3] * 3, [1e3] * 3]), 0.0
    )
    light = light or Light("directional", (0.3, 0.4, -0.866), 0.7, 0.35)
    return b.finish("custom", int(seed), light, np.asarray(roi_center, float), roi_radius, vs)
