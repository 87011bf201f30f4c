"""The photometric pass: the network's depth, normal, confidence and visibility maps of a reference.

Writes ``stereo/{depth,normal,confidence}_maps/NAME.photometric.bin`` (flat image regions moved
towards the sparse prior, :mod:`colmap_pvs.prior`; the confidence is the network's score,
:func:`~colmap_pvs.stereo.network.cascade_confidence`, times its agreement with that prior and a factor
that falls where the depth departs from a local plane, :func:`~colmap_pvs.normals.plane_residual`,
calibrated by :mod:`colmap_pvs.confidence`) and
``stereo/visibility_maps/NAME.bin`` (the learned per-source visibility, ``[h/4, w/4, S]`` at the
network size, sources in the provenance file).
"""

from __future__ import annotations

import logging

import numpy as np

from ..errors import ShapeError
from ..geometry import to_homogeneous
from ..model.runtime import check_memory_budget
from ..normals import depth_to_normals, plane_residual
from ..prior import blend_with_prior, prior_agreement, texture_weight, upsample_prior
from ..upsampling import (
    guided_upsample_depth,
    resize_area,
    resize_bilinear,
    resize_nearest,
    sample_depth_down,
)
from .config import PLANE_RESIDUAL_SCALE, PLANE_RESIDUAL_WINDOW, PRIOR_BLEND_WINDOW
from .context import RefOutcome, StereoContext, drop_outlier_hints, image_sparse_depth
from .network import estimate_depth
from .outputs import photometric_settings, stale_reason, write_missing_previews, write_pass
from .reference import PassMaps, PassRecord
from .timing import Timer

logger = logging.getLogger(__name__)


def network_maps(ctx: StereoContext, name: str, sources: list[str], timer: Timer,
                  dense_hints: np.ndarray | None = None) -> PassMaps | str:
    """The network's maps of ``name`` with ``sources`` (its photometric pass: depth, normals,
    confidence and the coarse visibility of each source, :class:`~colmap_pvs.stereo.reference.PassMaps`),
    or the reason it could not run (out of memory); each step timed in ``timer``.

    ``dense_hints`` ``[H, W]`` (map size, 0 = none): depths that replace the SfM hints where they are
    set (the geometric pass's re-estimation, ``geom_reestimate``); SfM hints stay elsewhere.
    """
    cfg = ctx.config.photometric
    size = ctx.map_size(name)
    with timer.step("load"):
        names = [name, *sources]
        net_size = ctx.network_size(name)
        futures = [ctx.images.future(n, cfg.max_image_size, net_size) for n in names]
        images = np.stack([f.result() for f in futures])
        guide = ctx.images.get(name, cfg.max_image_size, size) if net_size != size else None
        Ks = np.stack([ctx.map_K(n, net_size) for n in names])
        # COLMAP's fusion reads map pixel (col, row) along K_s^-1 [col, row, 1]; see CONVENTIONS.md.
        poses = np.stack([to_homogeneous(ctx.sparse.image_by_name(n).cam_from_world) for n in names])
    with timer.step("prior"):
        w, h = net_size
        ref = ctx.sparse.image_by_name(name)
        sparse = image_sparse_depth(ctx.sparse, ref, Ks[0], h, w, ctx.id_order)
        entry = ctx.selection.references[name]
        drop_outlier_hints(sparse, entry.depth_range)
        if dense_hints is not None:
            if dense_hints.shape != (size[1], size[0]):
                raise ShapeError(
                    f"dense_hints of {name!r} must be [{size[1]}, {size[0]}], got {dense_hints.shape}"
                )
            if net_size != size:  # nearest: a hint is a depth, never an average across an edge
                dense_hints = resize_nearest(dense_hints, h, w)
            sparse = np.where(dense_hints > 0, dense_hints, sparse).astype(np.float32)
    try:
        with timer.step("network"):
            if ctx.device.type == "cpu":  # refuse up front what would not fit in memory
                check_memory_budget(h, w, len(sources) + 1, ctx.net.config)
            depth, conf, vis, prior = estimate_depth(ctx.net, images, Ks, poses, entry.depth_range, sparse,
                                                     ctx.device)
    except (RuntimeError, MemoryError) as exc:
        if "memory" not in str(exc).lower() and not isinstance(exc, MemoryError):
            raise
        lower = "--network_scale or --max_image_size" if cfg.network_scale > 1.0 else "--max_image_size"
        reason = f"out of memory at {w}x{h} with {len(sources) + 1} views; lower {lower}"
        logger.error("skipping %s: %s (%s)", name, reason, exc)
        return reason
    conf = np.nan_to_num(conf, nan=0.0).astype(np.float32)
    if guide is not None:
        with timer.step("upsample"):
            w, h = size
            if net_size[0] * net_size[1] < w * h:  # up to the map size along the image's edges
                depth = guided_upsample_depth(depth, guide)
                conf = resize_bilinear(conf, h, w)
            else:  # down: each map pixel takes the depth on its own ray, never an average across an edge
                depth = sample_depth_down(depth, h, w)
                conf = resize_area(conf, h, w)
    if prior is not None and (cfg.prior_blend_texture > 0 or cfg.prior_agreement_scale > 0):
        with timer.step("prior_blend"):
            prior = upsample_prior(prior, net_size, size)
            conf = conf * prior_agreement(depth, prior, cfg.prior_agreement_scale)
            if cfg.prior_blend_texture > 0:
                rgb = guide if guide is not None else images[0]
                weight = texture_weight(rgb, PRIOR_BLEND_WINDOW, cfg.prior_blend_texture)
                depth = blend_with_prior(depth, prior, weight)
    with timer.step("confidence"):
        # depth edges and broken surfaces are where the depth is most often wrong
        residual = plane_residual(np.where(np.isfinite(depth), depth, 0.0), PLANE_RESIDUAL_WINDOW)
        conf = conf * np.exp(-residual / PLANE_RESIDUAL_SCALE)
        # the score as P(depth within the tolerance)
        conf = ctx.calibration.apply("photometric", conf, np.isfinite(depth) & (depth > 0))
        depth = np.where((conf >= cfg.min_confidence) & np.isfinite(depth), depth, 0.0).astype(np.float32)
    with timer.step("normals"):
        normals = depth_to_normals(depth, ctx.map_K(name, size))
        depth[~np.any(normals != 0, axis=-1)] = 0.0
        conf = np.where(depth > 0, conf, 0.0).astype(np.float32)  # 0 on invalid pixels
    return PassMaps(depth, conf, normals, visibility=vis)


def photometric_pass(ctx: StereoContext, name: str) -> RefOutcome:
    """The photometric pass of reference ``name``: its network maps, unless current (module docstring)."""
    cfg = ctx.config
    timer = Timer()
    sources, reason = ctx.sources_of(name)
    if sources is None:
        return RefOutcome(name, "photometric", "skipped", reason)
    ref = ctx.reference(name)
    size = ctx.map_size(name)
    settings = photometric_settings(ctx, name, sources)
    why = stale_reason(ref, "photometric", settings, size, cfg.overwrite)
    if why is None:
        if cfg.previews:  # an output-only option: its files from the maps on disk, nothing recomputed
            write_missing_previews(ref, "photometric")
        return RefOutcome(name, "photometric", "done", seconds=timer.elapsed())
    maps = network_maps(ctx, name, sources, timer)
    if isinstance(maps, str):
        return RefOutcome(name, "photometric", "skipped", maps)
    record = PassRecord(settings, {"image_size": list(size), "sources": sources,
                                   "sources_from": ctx.sources_origin(name)})
    ref = ref.with_pass("photometric", maps, record, sources=sources)
    ctx.submit_write(write_pass, ref, previews=cfg.previews, timer=timer)
    return RefOutcome(name, "photometric", "computed", why, seconds=timer.elapsed(), timings=timer.steps)
