"""SIFT features and their matching in a COLMAP database (pycolmap, on the CPU).

The one place that extracts and matches features: ``reconstruct`` (before incremental SfM) and
``import-poses`` (before triangulation with known poses) both call :func:`extract_features` and
:func:`match_features`. They are two functions because ``reconstruct`` resumes between them.
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import pycolmap

__all__ = ["clear_matches", "extract_features", "match_features", "resolve_matcher", "sequential_pairs"]


def extract_features(
    database: str | os.PathLike,
    image_dir: str | os.PathLike,
    image_names: Sequence[str],
    *,
    camera_model: str,
    camera_params: Sequence[float] | None = None,
    single_camera: bool = True,
    num_threads: int = -1,
    max_image_size: int,
    max_num_features: int,
    peak_threshold: float,
    progress: bool = False,
) -> None:
    """SIFT keypoints and descriptors of ``image_names`` (relative to ``image_dir``) into ``database``.

    Args:
        camera_model: COLMAP camera model of the new cameras; camera_params: their parameters
            (e.g. ``fx, fy, cx, cy`` for ``PINHOLE``), ``None`` to let COLMAP guess them.
        single_camera: one camera shared by all images (else COLMAP's ``AUTO`` camera mode).
        max_image_size: SIFT runs on images downscaled to this longest side (``-1``: full size).
        progress: show a progress bar (images with keypoints).
    """
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    extraction.max_image_size = max_image_size
    extraction.sift.max_num_features = max_num_features
    extraction.sift.peak_threshold = peak_threshold
    if camera_params is None:
        reader = pycolmap.ImageReaderOptions(camera_model=camera_model)
    else:
        reader = pycolmap.ImageReaderOptions(
            camera_model=camera_model, camera_params=",".join(repr(float(v)) for v in camera_params)
        )
    mode = pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.AUTO
    with _progress(progress, database, "keypoints", len(image_names), "features", "image"):
        pycolmap.extract_features(
            str(database),
            str(image_dir),
            image_names=list(image_names),
            camera_mode=mode,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )


def resolve_matcher(
    matcher: Literal["auto", "exhaustive", "sequential"], num_images: int, exhaustive_max_images: int
) -> Literal["exhaustive", "sequential"]:
    """``auto``: exhaustive matching up to ``exhaustive_max_images`` images, sequential above."""
    if matcher != "auto":
        return matcher
    return "exhaustive" if num_images <= exhaustive_max_images else "sequential"


def match_features(
    database: str | os.PathLike,
    matcher: Literal["exhaustive", "sequential"],
    *,
    num_images: int,
    num_threads: int = -1,
    sequential_overlap: int | None = None,
    progress: bool = False,
) -> None:
    """Match the features of ``database`` (all pairs, or each image with its followers in name order).

    Args:
        num_images: images in the database (the progress bar's total).
        sequential_overlap: the sequential matcher's overlap (``None``: COLMAP's default pairing).
        progress: show a progress bar (matched pairs).
    """
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    if matcher == "exhaustive":
        total = num_images * (num_images - 1) // 2
    else:
        total = sequential_pairs(num_images, 10 if sequential_overlap is None else sequential_overlap)
    with _progress(progress, database, "matches", total, "matching", "pair"):
        if matcher == "exhaustive":
            pycolmap.match_exhaustive(str(database), matching_options=matching, device=pycolmap.Device.cpu)
        elif sequential_overlap is None:
            pycolmap.match_sequential(str(database), matching_options=matching, device=pycolmap.Device.cpu)
        else:
            pairing = pycolmap.SequentialPairingOptions(overlap=sequential_overlap)
            pycolmap.match_sequential(
                str(database), matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu
            )


def sequential_pairs(n: int, overlap: int = 10, quadratic: bool = True) -> int:
    """Number of image pairs COLMAP's sequential matcher matches (no loop detection)."""
    pairs = set()
    for i in range(n):
        for k in range(1, overlap + 1):
            if i + k < n:
                pairs.add((i, i + k))
        if quadratic:
            for k in range(overlap):
                if i + (1 << k) < n:
                    pairs.add((i, i + (1 << k)))
    return len(pairs)


def clear_matches(database: str | os.PathLike) -> None:
    """Forget the matches of a database (COLMAP's matchers skip pairs that are already matched)."""
    with contextlib.closing(sqlite3.connect(str(database))) as con:
        con.execute("DELETE FROM matches")
        con.execute("DELETE FROM two_view_geometries")
        con.commit()


def _progress(enabled: bool, database: str | os.PathLike, table: str, total: int, desc: str, unit: str):
    if not enabled:
        return contextlib.nullcontext()
    from .pycolmap_output import DatabaseProgress

    return DatabaseProgress(Path(database), table, total, desc, unit)
