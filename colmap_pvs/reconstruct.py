"""The ``reconstruct`` step: a folder of photos -> sparse model -> depth maps -> point cloud -> mesh.

Stages (all on the CPU), each skipped when its finished output already exists, so a stopped
run resumes where it stopped::

    features   SIFT (pycolmap.extract_features)      WORKSPACE/database.db  (+ .done marker)
    matching   exhaustive (<= exhaustive_max_images) or sequential           (+ .done marker)
    mapping    incremental SfM (pycolmap.incremental_mapping)  WORKSPACE/sparse/0
    undistort  colmap_pvs.io.workspace.undistort                WORKSPACE/dense
    stereo     colmap_pvs.stereo.run_stereo (per-image resumable)  WORKSPACE/dense/stereo
    fusion     colmap_pvs.fusion.fuse                           WORKSPACE/dense/fused.ply(.vis)
    mesh       colmap_pvs.mesh.mesh                             WORKSPACE/dense/meshed-poisson.ply

With ``input_path`` (an existing sparse model of ``image_path``) the first three stages are
skipped. Markers live in ``WORKSPACE/.colmap_pvs/``; outputs are written atomically by each step.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from .config import atomic_write_bytes, make_temp_dir, save_config
from .errors import ConfigError, WorkspaceError

logger = logging.getLogger(__name__)

__all__ = ["ReconstructConfig", "ReconstructResult", "reconstruct", "STAGES"]

STAGES = ("features", "matching", "mapping", "undistort", "stereo", "fusion", "mesh")
_IMAGE_EXTENSIONS = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".ppm", ".pgm"}


@dataclass(frozen=True)
class ReconstructConfig:
    """Settings of ``reconstruct`` (the single source of its defaults and CLI flags)."""

    image_path: Path = field(metadata={"help": "folder with the photos"})
    workspace_path: Path = field(metadata={"help": "output folder (database.db, sparse/0, dense/)"})
    input_path: Path | None = field(
        default=None,
        metadata={"help": "existing sparse model of these images: skip feature/matching/mapping"},
    )
    camera_model: str = field(default="SIMPLE_RADIAL", metadata={"help": "COLMAP camera model for SfM"})
    single_camera: bool = field(default=False, metadata={"help": "all images share one camera"})
    max_num_features: int = field(default=4096, metadata={"help": "SIFT features per image"})
    sift_max_image_size: int = field(
        default=1600, metadata={"help": "SIFT runs on images downscaled to this longest side"}
    )
    matcher: Literal["auto", "exhaustive", "sequential"] = field(
        default="auto",
        metadata={"help": "auto: exhaustive up to exhaustive_max_images images, else sequential"},
    )
    exhaustive_max_images: int = field(default=50, metadata={"help": "auto matcher threshold"})
    undistort_max_image_size: int = field(
        default=-1, metadata={"help": "longest side of the undistorted images; -1 keeps the size"}
    )
    max_image_size: int = field(default=640, metadata={"help": "stereo: longest image side for inference"})
    num_views: int = field(default=5, metadata={"help": "stereo: views per reference (reference + sources)"})
    checkpoint: Path | None = field(
        default=None, metadata={"help": "stereo: model checkpoint; default: the shipped checkpoint"}
    )
    backend: Literal["local", "ray"] = field(
        default="local", metadata={"help": "stereo: local, or ray (one task per image on a Ray cluster)"}
    )
    ray_address: str = field(default="", metadata={"help": "stereo: Ray address; empty starts a local Ray"})
    ray_workers: int = field(default=0, metadata={"help": "stereo: Ray workers; 0: fill the CPUs"})
    ray_worker_threads: int = field(default=1, metadata={"help": "stereo: torch threads per Ray worker"})
    fusion_method: Literal["pvs", "colmap"] = field(default="pvs", metadata={"help": "fusion method"})
    mesh: bool = field(default=True, metadata={"help": "build a Poisson mesh of the fused cloud"})
    mesh_depth: int = field(default=9, metadata={"help": "Poisson octree depth"})
    num_threads: int = field(default=-1, metadata={"help": "CPU threads for SfM and meshing; -1 = all"})
    stop_after: Literal["features", "matching", "mapping", "undistort", "stereo", "fusion", "mesh"] | None = (
        field(
            default=None,
            metadata={"help": "stop after this stage (run the rest later: finished stages are reused)"},
        )
    )

    def __post_init__(self) -> None:
        if self.max_num_features < 16:
            raise ConfigError(f"max_num_features must be >= 16, got {self.max_num_features}")
        if self.num_views < 2:
            raise ConfigError(f"num_views must be >= 2, got {self.num_views}")
        if self.exhaustive_max_images < 2:
            raise ConfigError(f"exhaustive_max_images must be >= 2, got {self.exhaustive_max_images}")


@dataclass
class ReconstructResult:
    """Summary of a :func:`reconstruct` run.

    Attributes:
        num_images: photos in ``image_path``; num_registered: images in the sparse model.
        num_points3D: sparse points; num_fused_points: points of the fused cloud.
        stage_seconds: wall time of each stage run now (``0`` for a stage that was already done).
        resumed: stages whose finished output was found and reused.
        sparse_path, dense_path, fused_path, mesh_path: outputs (``mesh_path`` ``None`` without mesh).
        stereo_skipped: images stereo skipped, with the reason.
    """

    workspace_path: Path
    sparse_path: Path | None = None
    dense_path: Path | None = None
    fused_path: Path | None = None
    mesh_path: Path | None = None
    num_images: int = 0
    num_registered: int = 0
    num_points3D: int = 0
    num_fused_points: int = 0
    stage_seconds: dict[str, float] = field(default_factory=dict)
    resumed: list[str] = field(default_factory=list)
    stereo_skipped: dict[str, str] = field(default_factory=dict)


def _list_images(folder: Path) -> list[str]:
    return sorted(
        str(p.relative_to(folder))
        for p in folder.rglob("*")
        if p.is_file() and p.suffix.lower() in _IMAGE_EXTENSIONS and not p.name.startswith(".")
    )


class _Progress:
    """Per-stage timing, logging and done-markers."""

    def __init__(self, root: Path, result: ReconstructResult) -> None:
        self.markers = root / ".colmap_pvs"
        self.result = result
        self._t = 0.0
        self._stage = ""

    def done(self, stage: str) -> bool:
        return (self.markers / f"{stage}.done").is_file()

    def mark(self, stage: str) -> None:
        atomic_write_bytes(self.markers / f"{stage}.done", b"done\n")

    def start(self, stage: str) -> None:
        self._stage, self._t = stage, time.perf_counter()
        logger.info("reconstruct [%d/%d] %s ...", STAGES.index(stage) + 1, len(STAGES), stage)

    def stop(self) -> None:
        seconds = time.perf_counter() - self._t
        self.result.stage_seconds[self._stage] = seconds
        logger.info("reconstruct: %s done in %.1f s", self._stage, seconds)

    def skip(self, stage: str, why: str) -> None:
        self.result.stage_seconds[stage] = 0.0
        self.result.resumed.append(stage)
        logger.info("reconstruct [%d/%d] %s: %s", STAGES.index(stage) + 1, len(STAGES), stage, why)


def _model_dir_ok(path: Path) -> bool:
    return all(
        (path / f"{n}.bin").is_file() or (path / f"{n}.txt").is_file()
        for n in ("cameras", "images", "points3D")
    )


def _run_sfm(
    config: ReconstructConfig, root: Path, names: list[str], prog: _Progress, stop_after: str | None
) -> Path | None:
    """Features, matching and mapping; ``None`` when ``stop_after`` stopped it before a model exists."""
    import pycolmap

    image_dir = Path(config.image_path)
    db = root / "database.db"
    sparse = root / "sparse" / "0"
    if _model_dir_ok(sparse):
        for stage in ("features", "matching", "mapping"):
            prog.skip(stage, f"model found in {sparse}")
        return sparse

    if prog.done("features") and db.is_file():
        prog.skip("features", "already extracted")
    else:
        prog.start("features")
        for p in (db, Path(str(db) + "-wal"), Path(str(db) + "-shm")):
            p.unlink(missing_ok=True)
        (prog.markers / "matching.done").unlink(missing_ok=True)
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = config.num_threads
        extraction.max_image_size = config.sift_max_image_size
        extraction.sift.max_num_features = config.max_num_features
        reader = pycolmap.ImageReaderOptions(camera_model=config.camera_model)
        mode = pycolmap.CameraMode.SINGLE if config.single_camera else pycolmap.CameraMode.AUTO
        pycolmap.extract_features(
            str(db),
            str(image_dir),
            image_names=names,
            camera_mode=mode,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
        prog.mark("features")
        prog.stop()
    if stop_after == "features":
        return None

    if prog.done("matching"):
        prog.skip("matching", "already matched")
    else:
        prog.start("matching")
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = config.num_threads
        use = config.matcher
        if use == "auto":
            use = "exhaustive" if len(names) <= config.exhaustive_max_images else "sequential"
        logger.info("reconstruct: %s matching of %d images", use, len(names))
        if use == "exhaustive":
            pycolmap.match_exhaustive(str(db), matching_options=matching, device=pycolmap.Device.cpu)
        else:
            pycolmap.match_sequential(str(db), matching_options=matching, device=pycolmap.Device.cpu)
        prog.mark("matching")
        prog.stop()
    if stop_after == "matching":
        return None

    prog.start("mapping")
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = config.num_threads
    tmp = make_temp_dir(prefix=".sparse.", suffix=".tmp", parent=root)
    try:
        models = pycolmap.incremental_mapping(str(db), str(image_dir), str(tmp), options=options)
        if not models:
            raise WorkspaceError(
                f"SfM registered no images of {str(image_dir)!r}: too few matches "
                "(check the overlap, or raise "
                "--max_num_features)"
            )
        best_idx, best = max(models.items(), key=lambda kv: kv[1].num_reg_images())
        if len(models) > 1:
            logger.warning(
                "SfM produced %d separate models; keeping the largest (%d images)",
                len(models),
                best.num_reg_images(),
            )
        out = tmp / "best"
        out.mkdir()
        best.write(str(out))
        sparse.parent.mkdir(parents=True, exist_ok=True)
        if sparse.exists():
            shutil.rmtree(sparse)
        os.replace(out, sparse)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    prog.stop()
    return sparse


def reconstruct(config: ReconstructConfig) -> ReconstructResult:
    """Run the whole pipeline (see the module docstring); resumable.

    Raises:
        WorkspaceError: no images, SfM failure, or a failure of a later step (named by that step).
        CheckpointError: no checkpoint given and none shipped.
    """
    import pycolmap

    from .fusion import FuseConfig, fuse
    from .io.ply import read_point_cloud
    from .io.workspace import UndistortConfig, detect_workspace, undistort
    from .mesh import DEFAULT_MESH_NAME, MeshConfig, mesh
    from .stereo import DEFAULT_CHECKPOINT, StereoConfig, run_stereo

    image_dir = Path(config.image_path)
    root = Path(config.workspace_path)
    if not image_dir.is_dir():
        raise WorkspaceError(f"image folder {str(image_dir)!r} does not exist")
    names = _list_images(image_dir)
    if len(names) < 2:
        raise WorkspaceError(
            f"image folder {str(image_dir)!r} has {len(names)} image(s); at least 2 are needed"
        )
    needs_stereo = config.stop_after not in ("features", "matching", "mapping", "undistort")
    if needs_stereo and config.checkpoint is None and not Path(DEFAULT_CHECKPOINT).is_file():
        from .errors import CheckpointError

        raise CheckpointError(
            f"no trained default checkpoint is shipped at {str(DEFAULT_CHECKPOINT)!r}; pass --checkpoint PATH"
        )
    root.mkdir(parents=True, exist_ok=True)
    save_config(config, root / "colmap_pvs_reconstruct.json")
    result = ReconstructResult(workspace_path=root, num_images=len(names))
    prog = _Progress(root, result)
    total = time.perf_counter()

    if config.input_path is not None:
        sparse = Path(config.input_path)
        if not _model_dir_ok(sparse):
            raise WorkspaceError(
                f"--input_path {str(sparse)!r} holds no COLMAP model (cameras/images/points3D)"
            )
        for stage in ("features", "matching", "mapping"):
            prog.skip(stage, f"using the existing model {sparse}")
    else:
        sparse = _run_sfm(config, root, names, prog, config.stop_after)
        if sparse is None:
            return result
        if "mapping" not in result.resumed and (root / "dense").exists():
            logger.info("reconstruct: new sparse model; removing the stale dense workspace")
            shutil.rmtree(root / "dense")
    rec = pycolmap.Reconstruction(str(sparse))
    result.sparse_path = sparse
    result.num_registered = rec.num_reg_images()
    result.num_points3D = rec.num_points3D()
    logger.info(
        "reconstruct: sparse model: %d/%d images registered, %d points",
        result.num_registered,
        len(names),
        result.num_points3D,
    )
    if result.num_registered < len(names):
        logger.warning("reconstruct: %d image(s) were not registered", len(names) - result.num_registered)
    if config.stop_after == "mapping":
        return result

    dense = root / "dense"
    fused = dense / "fused.ply"
    meshed = dense / DEFAULT_MESH_NAME
    result.dense_path = dense
    try:
        detect_workspace(dense, create_stereo_dirs=False)
        prog.skip("undistort", f"dense workspace found in {dense}")
    except WorkspaceError:
        prog.start("undistort")
        if dense.exists():
            shutil.rmtree(dense)
        (prog.markers / "stereo.done").unlink(missing_ok=True)
        undistort(
            UndistortConfig(
                image_path=image_dir,
                input_path=sparse,
                output_path=dense,
                max_image_size=config.undistort_max_image_size,
            )
        )
        prog.stop()
    if config.stop_after == "undistort":
        return result

    if prog.done("stereo"):
        prog.skip("stereo", "depth maps already computed")
    else:
        prog.start("stereo")
        for stale in (fused, Path(str(fused) + ".vis"), meshed):
            stale.unlink(missing_ok=True)
        st = run_stereo(
            StereoConfig(
                workspace_path=dense,
                num_views=config.num_views,
                max_image_size=config.max_image_size,
                checkpoint=config.checkpoint,
                backend=config.backend,
                ray_address=config.ray_address,
                ray_workers=config.ray_workers,
                ray_worker_threads=config.ray_worker_threads,
            )
        )
        result.stereo_skipped = dict(st.skipped)
        prog.mark("stereo")
        prog.stop()
    if config.stop_after == "stereo":
        return result

    if fused.is_file() and Path(str(fused) + ".vis").is_file():
        prog.skip("fusion", f"{fused} exists")
    else:
        prog.start("fusion")
        meshed.unlink(missing_ok=True)
        fuse(FuseConfig(workspace_path=dense, output_path=fused, method=config.fusion_method))
        prog.stop()
    result.fused_path = fused
    result.num_fused_points = len(read_point_cloud(fused))
    if config.stop_after == "fusion":
        return result

    if config.mesh:
        if meshed.is_file():
            prog.skip("mesh", f"{meshed} exists")
        elif result.num_fused_points < 4:
            logger.warning("reconstruct: the fused cloud has %d points; no mesh", result.num_fused_points)
        else:
            prog.start("mesh")
            mesh(
                MeshConfig(
                    input_path=fused,
                    output_path=meshed,
                    depth=config.mesh_depth,
                    num_threads=config.num_threads,
                )
            )
            prog.stop()
        result.mesh_path = meshed if meshed.is_file() else None
    logger.info(
        "reconstruct: finished in %.1f s: %d/%d images registered, %d sparse points, %d fused points",
        time.perf_counter() - total,
        result.num_registered,
        len(names),
        result.num_points3D,
        result.num_fused_points,
    )
    return result
