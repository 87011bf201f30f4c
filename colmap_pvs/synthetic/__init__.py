"""Synthetic multi-view scenes for training and testing (CPU only, deterministic from a seed).

- :mod:`.textures`: shipped CC0 / public-domain photographs and procedural textures.
- :mod:`.mesh`, :mod:`.scenes`: textured primitives and the ``object`` / ``room`` / ``facade`` / ``plant``
  families (:mod:`.scene_types`, :mod:`.builder`, :mod:`.families`).
- :mod:`.cameras`: video-like, unstructured and "disturbing" camera rigs.
- :mod:`.render`: open3d ray casting (GT depth and normals) and per-view photometric changes.
- :mod:`.sfm`: simulated sparse points with tracks, as a :class:`~colmap_pvs.types.SparseModel`.
- :mod:`.dataset`: the cached training :class:`SyntheticMVSDataset` (anti-noise source selection).
- :mod:`.workspace`: :func:`make_synthetic_workspace`, a complete COLMAP dense workspace plus GT.

Submodules import open3d / torch lazily through this package: ``import colmap_pvs.synthetic``
alone is cheap.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .cameras import CameraConfig, CameraRig, generate_cameras, look_at
    from .dataset import SceneViews, SyntheticDatasetConfig, SyntheticMVSDataset, render_scene
    from .render import RenderConfig, Renderer
    from .scenes import Scene, SceneConfig, build_scene
    from .workspace import SyntheticWorkspaceConfig, make_synthetic_workspace

_EXPORTS = {
    "CameraConfig": "cameras",
    "CameraRig": "cameras",
    "generate_cameras": "cameras",
    "look_at": "cameras",
    "SceneViews": "dataset",
    "SyntheticDatasetConfig": "dataset",
    "SyntheticMVSDataset": "dataset",
    "render_scene": "dataset",
    "RenderConfig": "render",
    "Renderer": "render",
    "Scene": "scenes",
    "SceneConfig": "scenes",
    "build_scene": "scenes",
    "SyntheticWorkspaceConfig": "workspace",
    "make_synthetic_workspace": "workspace",
}

__all__ = [
    "CameraConfig",
    "CameraRig",
    "RenderConfig",
    "Renderer",
    "Scene",
    "SceneConfig",
    "SceneViews",
    "SyntheticDatasetConfig",
    "SyntheticMVSDataset",
    "SyntheticWorkspaceConfig",
    "build_scene",
    "generate_cameras",
    "look_at",
    "make_synthetic_workspace",
    "render_scene",
]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value
