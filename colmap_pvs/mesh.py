"""The ``mesh`` step: a screened Poisson surface from a fused, oriented point cloud.

``method="open3d"`` (default) runs Kazhdan & Hoppe's screened Poisson reconstruction through
open3d, then trims the surface where the input samples are sparse: every vertex whose
Poisson density (the octree depth of the samples that support it) lies below the
``density_quantile`` quantile is removed, with the faces that use it, and the mesh is cropped
to the cloud's bounding box (enlarged by ``bbox_margin``). Poisson always produces a closed
surface, so without trimming it bulges over unobserved regions.

``method="colmap"`` runs COLMAP's own mesher (``pycolmap.poisson_meshing``, the same code as
``colmap poisson_mesher``) with ``depth`` and ``colmap_trim``.

The mesh is written as binary PLY (vertex positions, normals, colours; triangle faces)
through a temporary file and a rename.
"""

from __future__ import annotations

import logging
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from .config import check_threads
from .errors import ConfigError, MapFormatError
from .io.files import current_umask
from .io.ply import read_point_cloud, write_mesh
from .io.workspace import record_written_output, set_aside_foreign_output

logger = logging.getLogger(__name__)

__all__ = ["MeshConfig", "mesh", "poisson_mesh"]

DEFAULT_MESH_NAME = "meshed-poisson.ply"


@dataclass(frozen=True)
class MeshConfig:
    """Settings of the ``mesh`` step (the single source of its defaults and CLI flags)."""

    input_path: Path = field(metadata={"help": "fused point cloud (.ply with normals), e.g. dense/fused.ply"})
    output_path: Path | None = field(
        default=None, metadata={"help": f"output mesh .ply; default: {DEFAULT_MESH_NAME} next to the input"}
    )
    method: Literal["open3d", "colmap"] = field(
        default="open3d", metadata={"help": "open3d screened Poisson + density trimming, or COLMAP's mesher"}
    )
    depth: int = field(
        default=9,
        metadata={"help": "Poisson octree depth: the finest grid is at most 2^depth cells per side"},
    )
    density_quantile: float = field(
        default=0.05,
        metadata={
            "help": "open3d: remove vertices whose Poisson density is below this quantile (0 keeps all)"
        },
    )
    bbox_margin: float = field(
        default=0.05,
        metadata={
            "help": "open3d: crop to the cloud's bounding box enlarged by this fraction of its size "
            "(negative disables)"
        },
    )
    point_weight: float = field(
        default=2.0, metadata={"help": "screening weight of the points (interpolation vs smoothness)"}
    )
    colmap_trim: float | None = field(
        default=None,
        metadata={
            "help": "colmap: PoissonRecon trim value (vertices with a lower density value are removed); "
            "default depth - 3, COLMAP's own 13/10 ratio (a trim >= depth removes everything)"
        },
    )
    normal_neighbors: int = field(
        default=30, metadata={"help": "open3d: neighbours for estimating normals when the cloud has none"}
    )
    num_threads: int = field(default=-1, metadata={"help": "threads; -1 = all"})

    def __post_init__(self) -> None:
        check_threads("num_threads", self.num_threads, auto=-1)
        if not 1 <= self.depth <= 16:
            raise ConfigError(f"depth must be in [1, 16], got {self.depth}")
        if not 0.0 <= self.density_quantile < 1.0:
            raise ConfigError(f"density_quantile must be in [0, 1), got {self.density_quantile}")
        if self.point_weight < 0:
            raise ConfigError(f"point_weight must be >= 0, got {self.point_weight}")
        if self.normal_neighbors < 3:
            raise ConfigError(f"normal_neighbors must be >= 3, got {self.normal_neighbors}")


def poisson_mesh(
    xyz: np.ndarray,
    normals: np.ndarray,
    colors: np.ndarray | None,
    config: MeshConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Screened Poisson + trimming on arrays.

    Args:
        xyz: ``[N, 3]`` points; normals: ``[N, 3]`` (rows of zeros are estimated);
        colors: ``[N, 3]`` uint8 or ``None``.

    Returns:
        ``(vertices [V, 3] float64, faces [F, 3] int64, vertex_normals [V, 3],
        vertex_colors [V, 3] uint8 or None)``.
    """
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(xyz, dtype=np.float64)))
    normals = np.asarray(normals, dtype=np.float64)
    have = np.linalg.norm(normals, axis=1) > 0.5
    if not have.all():
        logger.info("mesh: estimating normals for %d of %d points", int((~have).sum()), len(have))
        est = o3d.geometry.PointCloud(pcd)
        est.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(config.normal_neighbors))
        if have.any():
            # Orient estimated normals like the nearest point with a known normal.
            tree = o3d.geometry.KDTreeFlann(
                o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(xyz, dtype=np.float64)[have]))
            )
            known = normals[have]
            est_n = np.asarray(est.normals)
            for i in np.nonzero(~have)[0]:
                _, idx, _ = tree.search_knn_vector_3d(np.asarray(xyz[i], dtype=np.float64), 1)
                if np.dot(est_n[i], known[idx[0]]) < 0:
                    est_n[i] = -est_n[i]
            normals = np.where(have[:, None], normals, est_n)
        else:
            est.orient_normals_consistent_tangent_plane(min(config.normal_neighbors, max(3, len(xyz) - 1)))
            normals = np.asarray(est.normals)
    pcd.normals = o3d.utility.Vector3dVector(normals / np.linalg.norm(normals, axis=1, keepdims=True))
    if colors is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.asarray(colors, dtype=np.float64) / 255.0)
    logger.info("meshing: Poisson reconstruction at depth %d of %s points ...", config.depth, f"{len(xyz):,}")
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh_o3d, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            pcd, depth=config.depth, n_threads=config.num_threads, point_weight=config.point_weight
        )
    densities = np.asarray(densities)
    logger.info(
        "meshing: trimming the %s-vertex surface (density below the %g quantile, %s) ...",
        f"{len(densities):,}",
        config.density_quantile,
        f"outside the bounding box + {config.bbox_margin:g}" if config.bbox_margin >= 0 else "no crop",
    )
    remove = np.zeros(len(densities), dtype=bool)
    if config.density_quantile > 0 and densities.size:
        remove |= densities < np.quantile(densities, config.density_quantile)
    if config.bbox_margin >= 0 and len(xyz):
        lo, hi = np.min(xyz, axis=0), np.max(xyz, axis=0)
        pad = (hi - lo) * config.bbox_margin
        v = np.asarray(mesh_o3d.vertices)
        remove |= np.any((v < lo - pad) | (v > hi + pad), axis=1)
    if remove.any():
        mesh_o3d.remove_vertices_by_mask(remove)
    mesh_o3d.remove_unreferenced_vertices()
    mesh_o3d.compute_vertex_normals()
    vertices = np.asarray(mesh_o3d.vertices)
    faces = np.asarray(mesh_o3d.triangles, dtype=np.int64)
    vnormals = np.asarray(mesh_o3d.vertex_normals)
    vcolors = None
    if mesh_o3d.has_vertex_colors():
        vcolors = (np.clip(np.asarray(mesh_o3d.vertex_colors), 0, 1) * 255).round().astype(np.uint8)
    return vertices, faces, vnormals, vcolors


def mesh(config: MeshConfig) -> Path:
    """Mesh ``config.input_path`` and write the mesh; returns the output path.

    Raises:
        MapFormatError: missing/unreadable input, or an empty cloud / mesh.
    """
    src = Path(config.input_path)
    out = Path(config.output_path) if config.output_path is not None else src.parent / DEFAULT_MESH_NAME
    start = time.perf_counter()
    cloud = read_point_cloud(src)
    if len(cloud) < 4:
        raise MapFormatError(
            f"point cloud {str(src)!r} has {len(cloud)} points; at least 4 are needed to mesh"
        )
    if config.method == "colmap":
        from .io.colmap_tools import poisson_meshing

        out.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".ply", dir=out.parent)
        os.close(fd)
        try:
            trim = config.colmap_trim if config.colmap_trim is not None else max(0.0, config.depth - 3.0)
            logger.info(
                "meshing: COLMAP's Poisson reconstruction at depth %d (trim %g) of %s points ...",
                config.depth,
                trim,
                f"{len(cloud):,}",
            )
            poisson_meshing(
                src,
                tmp,
                depth=config.depth,
                trim=trim,
                point_weight=config.point_weight,
                num_threads=config.num_threads,
            )
            if os.path.getsize(tmp) == 0:
                raise MapFormatError(f"COLMAP's Poisson mesher wrote nothing for {str(src)!r}")
            os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp made it private
            set_aside_foreign_output(out)
            os.replace(tmp, out)
        finally:
            Path(tmp).unlink(missing_ok=True)
    else:
        vertices, faces, vnormals, vcolors = poisson_mesh(cloud.xyz, cloud.normals, cloud.colors, config)
        if len(faces) == 0:
            raise MapFormatError(
                f"the Poisson mesh of {str(src)!r} is empty after trimming; lower --density_quantile"
            )
        logger.info("meshing: writing %s ...", out)
        set_aside_foreign_output(out)  # COLMAP's poisson_mesher writes the same default name
        write_mesh(out, vertices, faces, normals=vnormals, colors=vcolors)
        logger.info("mesh: %d vertices, %d faces", len(vertices), len(faces))
    record_written_output(out)
    logger.info("mesh: wrote %s in %.1f s", out, time.perf_counter() - start)
    return out
