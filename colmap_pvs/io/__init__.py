"""Input/output: COLMAP sparse models, dense workspaces, ``.bin`` maps and images.

pycolmap is only used inside this package; everything it returns is a plain numpy dataclass
from :mod:`colmap_pvs.types`.
"""

from __future__ import annotations

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
