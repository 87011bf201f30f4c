"""Input/output: COLMAP sparse models, dense workspaces, ``.bin`` maps and images.

pycolmap is only used inside this package; everything it returns is a plain numpy dataclass
from :mod:`colmap_pvs.types`.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .images import load_image, read_image_size, resize_image
    from .maps import (
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
    from .sparse import read_sparse_model, write_sparse_model
    from .workspace import (
        MAP_KINDS,
        SourceSpec,
        UndistortConfig,
        Workspace,
        detect_workspace,
        load_workspace,
        read_fusion_cfg,
        read_patch_match_cfg,
        undistort,
        write_fusion_cfg,
        write_patch_match_cfg,
    )

# The public names are loaded on first use (PEP 562), so that importing one light submodule
# (``colmap_pvs.io.files``, used by ``colmap_pvs.config`` and the model package) does not load
# pycolmap, OpenCV and the workspace readers.
_SUBMODULE = {
    **dict.fromkeys(("load_image", "read_image_size", "resize_image"), "images"),
    **dict.fromkeys(
        (
            "colorize_depth",
            "fusion_intrinsics",
            "read_array",
            "read_depth_map",
            "read_normal_map",
            "save_depth_preview",
            "save_normal_preview",
            "save_scalar_preview",
            "write_array",
            "write_depth_map",
            "write_normal_map",
        ),
        "maps",
    ),
    **dict.fromkeys(("read_sparse_model", "write_sparse_model"), "sparse"),
    **dict.fromkeys(
        (
            "MAP_KINDS",
            "SourceSpec",
            "UndistortConfig",
            "Workspace",
            "detect_workspace",
            "load_workspace",
            "read_fusion_cfg",
            "read_patch_match_cfg",
            "undistort",
            "write_fusion_cfg",
            "write_patch_match_cfg",
        ),
        "workspace",
    ),
}


def __getattr__(name: str):
    module = _SUBMODULE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


__all__ = [
    "MAP_KINDS",
    "SourceSpec",
    "UndistortConfig",
    "Workspace",
    "detect_workspace",
    "fusion_intrinsics",
    "load_image",
    "load_workspace",
    "read_array",
    "read_depth_map",
    "read_fusion_cfg",
    "read_image_size",
    "read_normal_map",
    "read_patch_match_cfg",
    "read_sparse_model",
    "resize_image",
    "colorize_depth",
    "save_depth_preview",
    "save_normal_preview",
    "save_scalar_preview",
    "undistort",
    "write_array",
    "write_depth_map",
    "write_fusion_cfg",
    "write_normal_map",
    "write_patch_match_cfg",
    "write_sparse_model",
]
