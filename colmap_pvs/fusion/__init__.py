"""The ``fuse`` step: depth + normal maps of a dense workspace -> one coloured, oriented point cloud.

Two methods:

``pvs`` (default, ours; MVSNet/PVSNet-style geometric consistency, vectorised numpy)
    References are processed one at a time. For reference ``r`` every valid pixel ``p``
    (depth ``> 0``, non-zero normal, confidence ``>= min_confidence`` when a confidence map
    ``stereo/confidence_maps/NAME.bin`` exists) is back-projected to ``X``. ``X`` is projected
    into each of ``r``'s source views ``s`` (the ``patch-match.cfg`` sources, else view
    selection; the first ``num_sources``), the source depth at the pixel it lands in is
    back-projected and that point is reprojected into ``r``. Source ``s`` *agrees* with ``p``
    when the reprojection lands within ``max_reproj_error`` px of ``p`` and its depth in ``r``
    differs from ``p``'s by less than ``max_depth_error`` (relative). Pixels with at least
    ``min_consistent_views`` agreeing sources become points (on the completion, a pixel holding the
    depth its geometric map holds, which the geometric pass already checked against its sources,
    needs one fewer): the 3D position, world normal
    and colour are averaged over ``X`` and the agreeing sources' back-projected pixels, and the
    visibility is ``r`` plus those sources. With ``deduplicate`` the source pixels that
    agreed are marked as used and are not fused again when that source is the reference
    (COLMAP-like; otherwise every surface patch is emitted once per view that sees it).
    The check is :func:`colmap_pvs.consistency.match_points` (why it is not the geometric pass's
    :func:`~colmap_pvs.consistency.check_consistency`: :mod:`colmap_pvs.consistency`).

    Memory is bounded, by streaming: the points of each reference go to disk as soon as it is
    fused (temporary PLY body and ``.vis`` beside the output; the PLY header, which holds the count,
    is written last and the pair renamed into place together), so the cloud is never held; the maps
    held are an LRU of ``cache_size`` views at their stored resolution plus the next reference's
    views, which a background thread loads while the current reference is checked against its
    sources in two threads (both cores); a packed bit mask of used pixels is kept only for the
    views still to come as references. What grows with the number of views: the sparse model and
    the view selection's ``[n, n]`` score matrices (:mod:`colmap_pvs.views`).

``colmap``
    ``pycolmap.stereo_fusion`` (COLMAP's own fusion) with defaults adapted to learned maps
    (:data:`COLMAP_DEFAULTS`); any ``StereoFusionOptions`` attribute can be overridden
    with ``colmap_options`` ``key=value`` strings (validated at config time).

Input (``input_type``): ``geometric`` or ``photometric`` maps (depth, normals, confidence), or for
``pvs`` the dense completion ``filled`` (no normal map: the normals are fitted to its depth,
:func:`colmap_pvs.normals.fit_normals`; its pixels of confidence 0, where nothing supported a
completed depth, are never fused, nor, in a calibrated completion, those below
``pvs.FILLED_MIN_PROBABILITY`` (0.5); a pixel that holds its geometric map's depth, within
``max_depth_error``, counts that check as one agreeing view). ``auto`` (the default) is ``geometric``
for ``colmap``, and for
``pvs`` ``filled`` where every listed image with geometric maps has a completion (else ``geometric``,
e.g. maps from COLMAP's ``patch_match_stereo`` or a run without the completion); why the completion by
default: ``benchmarks/RESULTS.md``.

Pixel convention: maps in ``stereo/`` hold, at pixel ``(col, row)``, the depth along COLMAP's
integer-centre ray; ours is the same ray written with :func:`colmap_pvs.io.maps.fusion_intrinsics`
(``diag(w/W, h/H, 1) K`` with ``+0.5`` on the principal point) and pixel centres ``+0.5``, so
maps smaller than the images (inference at ``--max_image_size``) are handled exactly.
Colours come from the images resized to the map size.

Output: a binary little-endian PLY ``x y z nx ny nz red green blue`` and ``PLY.vis`` in
COLMAP's layout (:mod:`colmap_pvs.io.ply`), both written atomically; COLMAP's
``poisson_mesher`` and ``delaunay_mesher`` read them.

Code: :mod:`.config` (settings, result), :mod:`.pvs` (our fusion), this module (the entry point,
COLMAP's fusion).
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..config import config_json_bytes
from ..errors import MapFormatError, WorkspaceError
from ..io.cleanup import remove_orphan_temps
from ..io.colmap_tools import COLMAP_DEFAULTS, parse_colmap_options
from ..io.files import atomic_write_bytes, make_temp_dir
from ..io.maps import read_depth_map, read_normal_map
from ..io.ply import commit_cloud_pair, read_point_cloud, vis_path_of
from ..io.workspace import (
    Workspace,
    fusion_inputs_sha256,
    load_workspace,
    read_fusion_cfg,
    record_written_output,
    set_aside_foreign_output,
    write_fusion_cfg,
)
from .config import CONFIG_SUFFIX, DEFAULT_OUTPUT_NAME, FuseConfig, FuseResult
from .pvs import fuse_pvs

logger = logging.getLogger(__name__)

__all__ = ["COLMAP_DEFAULTS", "FuseConfig", "FuseResult", "fuse", "parse_colmap_options"]


# --------------------------------------------------------------------------- colmap fusion


def _map_problem(ws: Workspace, name: str, input_type: str) -> str | None:
    """Why the maps of ``name`` cannot be fused (COLMAP's fusion crashes on them or misreads them), or
    ``None``: 0-byte, truncated or non-finite maps, or a normal map of another size than the depth map."""
    try:
        depth = read_depth_map(ws.depth_map_path(name, input_type))
        normals = read_normal_map(ws.normal_map_path(name, input_type))
    except MapFormatError as exc:
        return str(exc)
    if normals.shape[:2] != depth.shape:
        return (
            f"normal map of {name!r} is {normals.shape[1]}x{normals.shape[0]} but its depth map is "
            f"{depth.shape[1]}x{depth.shape[0]}"
        )
    if not (np.isfinite(depth).all() and np.isfinite(normals).all()):
        return f"the {input_type} maps of {name!r} hold non-finite values"
    return None


def _fuse_colmap(config: FuseConfig, ws: Workspace, names: list[str], result: FuseResult) -> None:
    """COLMAP's fusion on a view of the workspace (symbolic links) whose ``fusion.cfg`` lists ``names``:
    only the maps that were checked are fused, and the user's ``stereo/fusion.cfg`` is never touched."""
    from ..io.colmap_tools import stereo_fusion

    options = {**COLMAP_DEFAULTS, **parse_colmap_options(config.colmap_options)}
    out = result.output_path
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = make_temp_dir(out.parent, prefix=f".{out.name}.")
    try:
        view = tmp / "workspace"
        (view / "stereo").mkdir(parents=True)
        (view / "images").symlink_to(ws.images_dir.resolve(), target_is_directory=True)
        (view / "sparse").symlink_to(ws.sparse_dir.resolve(), target_is_directory=True)
        for folder in (ws.depth_maps_dir, ws.normal_maps_dir):
            (view / "stereo" / folder.name).symlink_to(folder.resolve(), target_is_directory=True)
        write_fusion_cfg(view / "stereo" / "fusion.cfg", names)
        tmp_ply = tmp / out.name
        try:
            stereo_fusion(tmp_ply, view, input_type=config.input_type, options=options)
        except RuntimeError as exc:
            first = str(exc).strip().splitlines()
            raise WorkspaceError(
                f"COLMAP's stereo_fusion failed on {str(ws.root)!r}: {first[-1] if first else exc}"
            ) from None
        vis_tmp = vis_path_of(tmp_ply)
        if not tmp_ply.is_file() or not vis_tmp.is_file():
            raise WorkspaceError(f"COLMAP's stereo_fusion wrote no point cloud for {str(ws.root)!r}")
        result.num_points = len(read_point_cloud(tmp_ply))
        if not result.num_points:
            raise _no_points_error(config, ws, names, result)
        _set_aside_foreign_cloud(out)
        commit_cloud_pair(tmp_ply, vis_tmp, out)  # together or not at all
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# --------------------------------------------------------------------------- entry point


def _no_points_error(config: FuseConfig, ws: Workspace, names: list[str],
                     result: FuseResult) -> WorkspaceError:
    """The one-line error of a fusion that made no point: an empty cloud is never written."""
    fused = [n for n in names if n not in result.skipped]
    shown = ", ".join(repr(n) for n in fused[:3]) + (f" and {len(fused) - 3} more" if len(fused) > 3 else "")
    unusable = f"; {len(result.skipped)} listed image(s) skipped, named above" if result.skipped else ""
    if fused:
        what = (f" from the {config.input_type} maps of {len(fused)} image(s) in {str(ws.stereo_dir)!r} "
                f"({shown}){unusable}")
    else:
        what = (f": the {config.input_type} maps in {str(ws.stereo_dir)!r} of all {len(result.skipped)} "
                f"listed image(s) are unusable (named above)")
    advice = "check those maps or loosen the fusion thresholds"
    if config.method == "pvs" and len(names) - 1 < config.min_consistent_views:
        advice = (f"with {len(names)} image(s) a point has at most {len(names) - 1} agreeing view(s), fewer "
                  f"than min_consistent_views {config.min_consistent_views}: add photos or lower it")
    return WorkspaceError(
        f"fusion made no points{what}; {str(result.output_path)!r} was not written (a cloud already "
        f"there is kept): {advice}"
    )


def _set_aside_foreign_cloud(out: Path) -> None:
    """``out`` and its ``.vis`` if COLMAP or the user wrote them (``dense/fused.ply`` is the name of
    COLMAP's own fusion output): moved to ``.bak`` before ours replace them."""
    for path in (out, vis_path_of(out)):
        set_aside_foreign_output(path)


def _auto_input_type(ws: Workspace, listed: list[str]) -> str:
    """``filled`` when every listed image with a geometric map has a completion of this version's format
    (older ones hold no unsupported pixels), else ``geometric``."""
    from ..stereo.outputs import outdated_completions

    geometric = [n for n in listed if ws.depth_map_path(n, "geometric").is_file()]
    missing, old = outdated_completions(ws, geometric)
    if old:
        logger.warning("fusion: %d completion(s) (e.g. %r) are from an older colmap-pvs: fusing the "
                       "geometric maps; rerun `colmap-pvs stereo` to update them", len(old), old[0])
    chosen = "filled" if geometric and not missing and not old else "geometric"
    logger.info("fusion: input_type auto -> %s (%d of %d images without a current completion)",
                chosen, len(missing) + len(old), len(geometric))
    return chosen


def fuse(config: FuseConfig) -> FuseResult:
    """Fuse the workspace's depth maps into ``config.output_path`` (+ ``.vis``).

    The images fused are those in ``stereo/fusion.cfg`` if it exists, else every image of the
    model with both maps; listed images without maps are skipped with a warning.

    Raises:
        WorkspaceError: not a workspace, or no image has maps.
    """
    start = time.perf_counter()
    ws, model = load_workspace(config.workspace_path)
    inputs_sha256 = fusion_inputs_sha256(ws.root)  # before reading: a map rewritten meanwhile is a change
    out = Path(config.output_path) if config.output_path is not None else ws.root / DEFAULT_OUTPUT_NAME
    remove_orphan_temps(out.parent)  # what a killed run left behind
    result = FuseResult(output_path=out, vis_path=Path(str(out) + ".vis"), method=config.method)
    all_names = [model.images[i].name for i in sorted(model.images)]
    if ws.fusion_cfg.is_file():
        listed = read_fusion_cfg(ws.fusion_cfg)
        unknown = [n for n in listed if n not in model.image_ids_by_name]
        if unknown:
            raise WorkspaceError(
                f"{str(ws.fusion_cfg)!r} lists images not in the sparse model: {unknown[:5]}"
            )
    else:
        listed = all_names
    if config.input_type == "auto":
        config = replace(config, input_type=_auto_input_type(ws, listed))
    names = []
    for n in listed:
        have = ws.depth_map_path(n, config.input_type).is_file() and (
            config.input_type == "filled" or ws.normal_map_path(n, config.input_type).is_file()
        )
        if have:
            names.append(n)
        else:
            result.skipped[n] = f"no {config.input_type} depth/normal map"
            logger.debug("fusion: skipping %s: no %s depth/normal map", n, config.input_type)
    if result.skipped:  # one line, not one per image; each image at DEBUG
        missing = list(result.skipped)
        shown = ", ".join(repr(n) for n in missing[:3]) + (
            f" and {len(missing) - 3} more" if len(missing) > 3 else ""
        )
        logger.warning(
            "fusion: skipping %d of %d listed image(s) without %s depth/normal maps: %s",
            len(missing), len(listed), config.input_type, shown,
        )
    if not names:
        raise WorkspaceError(
            f"no {config.input_type} depth and normal maps to fuse in {str(ws.stereo_dir)!r}; "
            "run `colmap-pvs stereo`"
        )
    if config.method == "colmap":  # COLMAP's fusion crashes on, or silently misreads, broken maps
        for n in list(names):
            problem = _map_problem(ws, n, config.input_type)
            if problem is not None:
                names.remove(n)
                result.skipped[n] = problem
                logger.warning("fusion: skipping %s: %s", n, problem)
        if not names:
            raise WorkspaceError(f"no usable {config.input_type} maps to fuse in {str(ws.stereo_dir)!r}")
    logger.info("fusion (%s): %d images from %s", config.method, len(names), ws.root)
    if config.method == "colmap":
        _fuse_colmap(config, ws, names, result)
    else:
        cloud = fuse_pvs(config, ws, model, names, result)  # streamed to temporaries beside `out`
        try:
            if not len(cloud):  # before anything is written or set aside: an existing cloud stays as it was
                raise _no_points_error(config, ws, names, result)
            _set_aside_foreign_cloud(out)
            cloud.write()  # the PLY and its .vis together or not at all
        finally:
            cloud.discard()
        result.num_points = len(cloud)
    record_written_output(out, vis_path_of(out))
    result.num_images = len(names)
    result.seconds = time.perf_counter() - start
    atomic_write_bytes(out.with_name(out.stem + CONFIG_SUFFIX),
                       config_json_bytes(config, num_points=result.num_points, inputs_sha256=inputs_sha256))
    logger.info(
        "fusion: %d points from %d images in %.1f s -> %s", result.num_points, len(names), result.seconds, out
    )
    return result
