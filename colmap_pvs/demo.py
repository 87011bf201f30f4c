"""``colmap-pvs demo [OUT]``: the whole dense pipeline on a small built-in synthetic scene.

Needs no input. Renders a synthetic object scene with ground truth
(:func:`colmap_pvs.synthetic.workspace.make_synthetic_workspace`) as a COLMAP dense workspace in
``OUT``, runs ``stereo`` with the shipped checkpoint (``colmap_pvs/weights/pvsnet_default.pt``;
:class:`~colmap_pvs.errors.CheckpointError` if it is missing and no ``--checkpoint`` is given),
writes depth/normal/confidence previews (``OUT/stereo/previews``), fuses the maps
(``OUT/fused.ply``), meshes the cloud (``OUT/meshed-poisson.ply``) and reports depth accuracy
against the scene's GT depth (``OUT/gt/depth_maps``). About a minute on 2 CPU cores.

``OUT`` is replaced when it holds a previous demo (``OUT/gt/scene.json``); any other existing,
non-empty folder is refused.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

from .config import check_threads
from .errors import CheckpointError, ConfigError, WorkspaceError

logger = logging.getLogger(__name__)

__all__ = ["DemoConfig", "DemoResult", "run_demo"]


@dataclass(frozen=True)
class DemoConfig:
    """Settings of ``demo`` (the single source of its defaults and CLI flags)."""

    output_path: Path = field(
        default=Path("demo_output"), metadata={"help": "output folder (also accepted as the positional OUT)"}
    )
    checkpoint: Path | None = field(
        default=None,
        metadata={"help": "model checkpoint; default: the shipped colmap_pvs/weights/pvsnet_default.pt"},
    )
    seed: int = field(default=0, metadata={"help": "synthetic scene seed"})
    num_images: int = field(default=8, metadata={"help": "rendered views"})
    width: int = field(default=320, metadata={"help": "image width"})
    height: int = field(default=240, metadata={"help": "image height"})
    num_views: int = field(default=5, metadata={"help": "stereo: views per reference (reference + sources)"})
    mesh_depth: int = field(default=8, metadata={"help": "Poisson octree depth"})
    threads: int = field(default=0, metadata={"help": "torch CPU threads; 0 keeps torch's default"})

    def __post_init__(self) -> None:
        check_threads("threads", self.threads, auto=0)
        if self.num_images < 2:
            raise ConfigError(f"num_images must be >= 2, got {self.num_images}")
        if self.num_views < 2:
            raise ConfigError(f"num_views must be >= 2, got {self.num_views}")
        if self.width < 32 or self.height < 32:
            raise ConfigError(f"image size must be at least 32x32, got {self.width}x{self.height}")


@dataclass
class DemoResult:
    """What the demo produced.

    Attributes:
        workspace: the dense workspace (``OUT``); previews: ``OUT/stereo/previews``.
        fused_path, mesh_path: the cloud and the mesh (``mesh_path`` ``None`` if meshing failed).
        num_images, num_fused_points: counts.
        depth_absrel, depth_mae: pooled mean relative / absolute depth error over pixels valid in both.
        depth_under_1pct / depth_under_5pct: % of those pixels within 1 % / 5 % of the GT depth.
        depth_coverage_pct: % of valid GT pixels with a predicted depth.
        cloud_median_error: median distance (scene units) of fused points to the GT mesh (``nan`` if
            it could not be computed); scene_size: the GT mesh's bounding-box diagonal.
        stage_seconds: time per stage; seconds: total.
    """

    workspace: Path
    previews: Path
    fused_path: Path
    mesh_path: Path | None
    checkpoint: Path
    num_images: int = 0
    num_fused_points: int = 0
    depth_absrel: float = float("nan")
    depth_mae: float = float("nan")
    depth_under_1pct: float = float("nan")
    depth_under_5pct: float = float("nan")
    depth_coverage_pct: float = float("nan")
    cloud_median_error: float = float("nan")
    scene_size: float = float("nan")
    stage_seconds: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0


def _cloud_error(fused: Path, gt_mesh: Path) -> tuple[float, float]:
    """Median point-to-mesh distance of the fused cloud and the GT mesh's bounding-box diagonal."""
    import numpy as np
    import open3d as o3d

    from .io.ply import read_point_cloud

    mesh = o3d.io.read_triangle_mesh(str(gt_mesh))
    if len(mesh.triangles) == 0:
        return float("nan"), float("nan")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    pts = read_point_cloud(fused).xyz.astype(np.float32)
    v = np.asarray(mesh.vertices)
    size = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    if len(pts) == 0:
        return float("nan"), size
    dist = scene.compute_distance(o3d.core.Tensor(pts)).numpy()
    return float(np.median(dist)), size


def run_demo(config: DemoConfig) -> DemoResult:
    """Run the demo (see the module docstring).

    Raises:
        CheckpointError: no ``checkpoint`` given and the default one is not shipped.
        WorkspaceError: ``output_path`` is an existing non-empty folder that is not a previous demo.
    """
    from . import stereo as stereo_module
    from .evaluate import EvaluateDepthConfig, evaluate_depth
    from .fusion import FuseConfig, fuse
    from .mesh import DEFAULT_MESH_NAME, MeshConfig, mesh
    from .synthetic.workspace import SyntheticWorkspaceConfig, make_synthetic_workspace

    start = time.perf_counter()
    checkpoint = Path(config.checkpoint or stereo_module.config.DEFAULT_CHECKPOINT)
    if not checkpoint.is_file():
        raise CheckpointError(
            f"the demo needs a trained checkpoint, but {str(checkpoint)!r} does not exist"
            + (
                ""
                if config.checkpoint is not None
                else " (no default checkpoint is shipped yet); pass --checkpoint PATH"
            )
        )
    out = Path(config.output_path)
    if out.exists() and (
        not out.is_dir() or (any(out.iterdir()) and not (out / "gt" / "scene.json").is_file())
    ):
        raise WorkspaceError(
            f"output folder {str(out)!r} exists and is not a previous demo output; choose another OUT"
        )
    stages: dict[str, float] = {}

    t = time.perf_counter()
    logger.info(
        "demo [1/5] rendering a synthetic scene (%d views %dx%d) into %s",
        config.num_images,
        config.width,
        config.height,
        out,
    )
    summary = make_synthetic_workspace(
        out,
        SyntheticWorkspaceConfig(
            seed=config.seed,
            family="object",
            width=config.width,
            height=config.height,
            num_views=config.num_images,
            overwrite=True,
        ),
    )
    stages["render"] = time.perf_counter() - t

    t = time.perf_counter()
    logger.info("demo [2/5] stereo with %s", checkpoint)
    stereo_module.run_stereo(
        stereo_module.StereoConfig(
            workspace_path=out,
            checkpoint=checkpoint,
            previews=True,
            threads=config.threads,
            photometric=stereo_module.PhotometricConfig(
                num_views=config.num_views, max_image_size=max(config.width, config.height)
            ),
        )
    )
    stages["stereo"] = time.perf_counter() - t

    t = time.perf_counter()
    logger.info("demo [3/5] depth accuracy against the GT")
    metrics = evaluate_depth(
        EvaluateDepthConfig(workspace_path=out, gt=out / "gt" / "depth_maps", gt_pattern="{name}.npy")
    )
    stages["evaluate"] = time.perf_counter() - t

    t = time.perf_counter()
    logger.info("demo [4/5] fusion")
    fused = fuse(FuseConfig(workspace_path=out))
    stages["fusion"] = time.perf_counter() - t

    t = time.perf_counter()
    logger.info("demo [5/5] mesh")
    mesh_path: Path | None = None
    if fused.num_points >= 4:
        try:
            mesh_path = mesh(
                MeshConfig(
                    input_path=fused.output_path, output_path=out / DEFAULT_MESH_NAME, depth=config.mesh_depth
                )
            )
        except Exception as exc:  # noqa: BLE001 - a failed mesh must not hide the other results
            logger.warning("demo: meshing failed: %s", exc)
    else:
        logger.warning("demo: the fused cloud has %d points; no mesh", fused.num_points)
    stages["mesh"] = time.perf_counter() - t

    pooled = metrics.pooled
    cloud_err, size = (float("nan"), float("nan"))
    gt_mesh = out / "gt" / "mesh.ply"
    if gt_mesh.is_file() and fused.num_points:
        try:
            cloud_err, size = _cloud_error(fused.output_path, gt_mesh)
        except Exception as exc:  # noqa: BLE001 - optional statistic
            logger.warning("demo: could not compare the cloud with the GT mesh: %s", exc)
    result = DemoResult(
        workspace=out,
        previews=out / "stereo" / "previews",
        fused_path=fused.output_path,
        mesh_path=mesh_path,
        checkpoint=checkpoint,
        num_images=len(summary["image_names"]),
        num_fused_points=fused.num_points,
        depth_absrel=pooled.absrel,
        depth_mae=pooled.mae,
        depth_under_1pct=pooled.rel_under_pct.get(0.01, float("nan")),
        depth_under_5pct=pooled.rel_under_pct.get(0.05, float("nan")),
        depth_coverage_pct=pooled.coverage_pct,
        cloud_median_error=cloud_err,
        scene_size=size,
        stage_seconds=stages,
        seconds=time.perf_counter() - start,
    )
    logger.info(
        "demo: depth AbsRel %.4f, %.1f %% within 1 %%, coverage %.1f %%; %d fused points; %.1f s",
        result.depth_absrel,
        result.depth_under_1pct,
        result.depth_coverage_pct,
        result.num_fused_points,
        result.seconds,
    )
    return result
