"""A complete COLMAP dense workspace rendered from one synthetic scene, with ground truth.

Layout written by :func:`make_synthetic_workspace` (what COLMAP's ``image_undistorter`` writes,
plus ``gt/``)::

    root/images/NNN.png                       rendered images (uint8 RGB)
    root/sparse/{cameras,images,points3D}.bin PINHOLE cameras, poses, simulated sparse points + tracks
    root/stereo/{depth_maps,normal_maps,consistency_graphs}/   empty
    root/stereo/patch-match.cfg               "NAME" / "__auto__, 20" per image, like image_undistorter
    root/stereo/fusion.cfg                    every image
    root/gt/depth_maps/NNN.png.npy            [H, W] float32 GT z-depth in scene units (0 = no surface)
    root/gt/normal_maps/NNN.png.npy           [H, W, 3] float32 camera-frame normals facing the camera
    root/gt/mesh.ply                          the scene mesh (world coordinates)
    root/gt/scene.json                        family, seed, sizes, names, roles, depth ranges, config

The workspace is built in a temporary folder beside ``output_path`` and renamed into place.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from ..config import config_to_dict, replace_config
from ..errors import ConfigError, WorkspaceError
from ..io.files import atomic_write_bytes, make_temp_dir
from .cameras import CameraConfig
from .dataset import render_scene
from .render import RenderConfig
from .scenes import SceneConfig

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SyntheticWorkspaceConfig:
    """One synthetic scene as a COLMAP dense workspace.

    The top-level ``family``, ``num_views``, ``trajectory``, ``disturbing_fraction`` and
    ``supersample`` override the matching fields of the nested ``scene``, ``camera`` and
    ``render`` configs.
    """

    seed: int = field(default=0, metadata={"help": "scene seed"})
    family: Literal["any", "object", "room", "facade", "plant"] = field(
        default="object", metadata={"help": "scene family (plant: thin fronds in front of a wall)"}
    )
    width: int = field(default=320, metadata={"help": "image width in pixels"})
    height: int = field(default=240, metadata={"help": "image height in pixels"})
    num_views: int = field(default=8, metadata={"help": "number of images"})
    trajectory: Literal["video", "unstructured", "mixed"] = field(
        default="unstructured", metadata={"help": "camera capture style"}
    )
    disturbing_fraction: float = field(
        default=0.0, metadata={"help": "fraction of occluded / barely overlapping views"}
    )
    num_points: int = field(
        default=3000, metadata={"help": "sparse points sampled (before the track filter)"}
    )
    supersample: int = field(default=2, metadata={"help": "colour rays per pixel along each axis"})
    auto_sources: int = field(default=20, metadata={"help": "N of '__auto__, N' in stereo/patch-match.cfg"})
    write_mesh: bool = field(default=True, metadata={"help": "write the scene mesh to gt/mesh.ply"})
    overwrite: bool = field(default=False, metadata={"help": "replace an existing output folder"})
    scene: SceneConfig = field(default_factory=SceneConfig)
    camera: CameraConfig = field(default_factory=lambda: CameraConfig(min_coverage=0.7))
    render: RenderConfig = field(default_factory=RenderConfig)

    def __post_init__(self) -> None:
        if self.num_views < 2:
            raise ConfigError(f"num_views must be >= 2, got {self.num_views}")
        if self.width < 8 or self.height < 8:
            raise ConfigError(f"image size must be at least 8x8, got {self.width}x{self.height}")
        if self.num_points < 1 or self.auto_sources < 1:
            raise ConfigError(
                f"num_points and auto_sources must be >= 1, got {self.num_points}, {self.auto_sources}"
            )

    def resolved(self) -> tuple[SceneConfig, CameraConfig, RenderConfig]:
        """The nested configs with the top-level overrides applied."""
        scene = replace_config(self.scene, family=self.family)
        camera = replace_config(
            self.camera,
            num_views=[self.num_views, self.num_views],
            trajectory=self.trajectory,
            disturbing_fraction=self.disturbing_fraction,
        )
        render = replace_config(self.render, supersample=self.supersample)
        return scene, camera, render


def _write_png(path: Path, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image[..., ::-1]))
    if not ok:
        raise WorkspaceError(f"could not encode {str(path)!r} as PNG")
    path.write_bytes(buf.tobytes())


def _write_npy(path: Path, array: np.ndarray) -> None:
    with open(path, "wb") as f:
        np.save(f, array)


def make_synthetic_workspace(
    output_path: str | os.PathLike, config: SyntheticWorkspaceConfig | None = None
) -> dict[str, Any]:
    """Render one synthetic scene into a COLMAP dense workspace at ``output_path`` (layout: module docstring).

    Returns:
        A summary dict: ``path``, ``image_names``, ``num_points``, ``family``, ``seed``, ``width``,
        ``height``, ``depth_ranges`` (``{name: [lo, hi]}`` of the valid GT depth), ``roles``, ``seconds``.

    Raises:
        WorkspaceError: ``output_path`` exists and ``overwrite`` is false, or writing fails.
    """
    from ..io.sparse import write_sparse_model
    from ..io.workspace import write_fusion_cfg

    config = config or SyntheticWorkspaceConfig()
    out = Path(output_path)
    if out.exists() and not config.overwrite:
        raise WorkspaceError(f"output folder {str(out)!r} already exists (set overwrite to replace it)")
    t0 = time.perf_counter()
    scene_cfg, cam_cfg, ren_cfg = config.resolved()
    views, scene = render_scene(
        config.seed,
        config.width,
        config.height,
        scene_cfg,
        cam_cfg,
        ren_cfg,
        config.num_points,
        keep_normals=True,
    )
    names = views.image_names()
    model = views.sparse_model(names)

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = make_temp_dir(prefix=f".{out.name}.", suffix=".tmp", parent=out.parent)
    try:
        for sub in (
            "images",
            "stereo/depth_maps",
            "stereo/normal_maps",
            "stereo/consistency_graphs",
            "gt/depth_maps",
            "gt/normal_maps",
        ):
            (tmp / sub).mkdir(parents=True, exist_ok=True)
        depth_ranges = {}
        for v, name in enumerate(names):
            _write_png(tmp / "images" / name, views.images[v])
            _write_npy(tmp / "gt" / "depth_maps" / f"{name}.npy", views.depths[v].astype(np.float32))
            _write_npy(tmp / "gt" / "normal_maps" / f"{name}.npy", views.normals[v].astype(np.float32))
            d = views.depths[v][views.depths[v] > 0]
            depth_ranges[name] = [float(d.min()), float(d.max())] if d.size else [0.0, 0.0]
        write_sparse_model(model, tmp / "sparse")
        atomic_write_bytes(
            tmp / "stereo" / "patch-match.cfg",
            "".join(f"{n}\n__auto__, {config.auto_sources}\n" for n in names).encode(),
        )
        write_fusion_cfg(tmp / "stereo" / "fusion.cfg", names)
        if config.write_mesh:
            import open3d as o3d

            mesh = o3d.geometry.TriangleMesh(
                o3d.utility.Vector3dVector(scene.vertices),
                o3d.utility.Vector3iVector(scene.triangles.astype(np.int32)),
            )
            if not o3d.io.write_triangle_mesh(str(tmp / "gt" / "mesh.ply"), mesh, write_ascii=False):
                raise WorkspaceError(f"could not write {str(tmp / 'gt' / 'mesh.ply')!r}")
        summary: dict[str, Any] = {
            "family": views.family,
            "seed": int(config.seed),
            "width": views.width,
            "height": views.height,
            "image_names": names,
            "roles": list(views.roles),
            "num_points": len(views.points),
            "depth_ranges": depth_ranges,
            "depth_units": "scene units (metres)",
            "depth_definition": "camera-frame z; 0 = no surface; pixel (col,row) centre at (col+0.5,row+0.5)",
            "config": config_to_dict(config),
        }
        atomic_write_bytes(tmp / "gt" / "scene.json", (json.dumps(summary, indent=2) + "\n").encode())
        if out.exists():
            old = make_temp_dir(prefix=f".{out.name}.old.", parent=out.parent)
            old.rmdir()
            os.replace(out, old)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    seconds = time.perf_counter() - t0
    logger.info(
        "wrote a synthetic %s workspace (%d images %dx%d, %d points) to %s in %.1f s",
        views.family,
        len(names),
        views.width,
        views.height,
        len(views.points),
        out,
        seconds,
    )
    summary = {k: v for k, v in summary.items() if k != "config"}
    summary["path"] = str(out)
    summary["seconds"] = seconds
    return summary
