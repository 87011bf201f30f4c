"""Incremental structure from motion (pycolmap's ``incremental_mapping``) and sparse-model counts."""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import pycolmap

from ..errors import WorkspaceError
from .files import make_temp_dir

logger = logging.getLogger(__name__)

__all__ = ["ModelCounts", "incremental_mapping", "model_counts"]


def incremental_mapping(
    database: str | os.PathLike,
    image_dir: str | os.PathLike,
    output_path: str | os.PathLike,
    *,
    num_threads: int = -1,
    num_images: int,
    work_dir: str | os.PathLike,
) -> Path:
    """COLMAP's incremental mapper on ``database``; the largest model is written to ``output_path``.

    The models are made in a temporary folder inside ``work_dir``; ``output_path`` is replaced only
    when mapping succeeded. A progress bar counts the registered images (of ``num_images``).

    Raises:
        WorkspaceError: no image could be registered.
    """
    from tqdm import tqdm

    image_dir = Path(image_dir)
    sparse = Path(output_path)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = num_threads
    tmp = make_temp_dir(prefix=".sparse.", suffix=".tmp", parent=work_dir)
    bar = tqdm(total=num_images, desc="mapping", unit="image")

    def registered() -> None:
        if bar.n < bar.total:
            bar.update(1)

    try:
        try:
            models = pycolmap.incremental_mapping(
                str(database), str(image_dir), str(tmp), options=options, next_image_callback=registered
            )
            if not models and options.triangulation.ignore_two_view_tracks:
                # pycolmap's mapper ignores the points only two images see, even for its initial pair: two
                # photos (or an initial pair without a third view) then triangulate nothing, where
                # COLMAP 3.8's mapper registers them. Tried again with those points.
                logger.info("SfM: no model without the points only two images see; trying again with them")
                options.triangulation.ignore_two_view_tracks = False
                shutil.rmtree(tmp, ignore_errors=True)
                tmp.mkdir()
                bar.reset()
                models = pycolmap.incremental_mapping(
                    str(database), str(image_dir), str(tmp), options=options, next_image_callback=registered
                )
        finally:
            bar.close()
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
    return sparse


@dataclass(frozen=True)
class ModelCounts:
    """Sizes of a COLMAP sparse model."""

    num_reg_images: int
    num_cameras: int
    num_points3D: int


def model_counts(path: str | os.PathLike) -> ModelCounts:
    """Registered images, cameras and 3D points of the sparse model in ``path``."""
    rec = pycolmap.Reconstruction(str(path))
    return ModelCounts(rec.num_reg_images(), rec.num_cameras(), rec.num_points3D())
