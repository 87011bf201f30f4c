"""The dense completion (``geom_fill``), once every geometric map exists.

From the seeds of the reference and of its sources (:mod:`colmap_pvs.completion`): the seeds as they
are, other pixels from the sources' seeds projected in, then segment planes and a local plane fit.
Writes ``NAME.filled.bin`` depth and confidence maps, which COLMAP's fusion never reads.
"""

from __future__ import annotations

import numpy as np

from ..completion import (
    FIT_MIN_SUPPORT,
    complete_depth,
    completed_confidence,
    fit_support,
    segment_planes,
    splat_depths,
)
from ..errors import MapFormatError
from ..io.maps import read_depth_map
from ..normals import plane_residual
from .config import COMPLETION_RESIDUAL_SCALE, COMPLETION_RESIDUAL_WINDOW
from .context import RefOutcome, StereoContext
from .geometric import load_maps
from .outputs import (
    fingerprint,
    geometric_files_exist,
    photometric_settings,
    pure_geometric,
    read_confidence,
    remove_filled,
    stage_settings,
    stale_reason,
    write_filled,
    write_missing_previews,
)
from .reference import PassMaps, PassRecord
from .timing import Timer


def current_geometric_provenance(ctx: StereoContext, name: str) -> dict | None:
    """``name``'s geometric provenance if its geometric maps exist and match this run: it is one of
    the run's references, its geometric settings are the run's, and they were made from its current
    photometric maps (whose fingerprint matches this run's settings and sources). ``None`` otherwise:
    maps left by another run, or by a pass this run skipped."""
    if name not in ctx.references or name not in ctx.selection.references:
        return None
    ref = ctx.reference(name)
    prov = ref.provenance("geometric")
    photo = ref.provenance("photometric")
    if prov is None or photo is None or not geometric_files_exist(ref):
        return None
    settings = prov.get("settings", {})
    wanted = stage_settings(ctx, "geometric", "geometric")
    if any(settings.get(k) != v for k, v in wanted.items()) or settings.get("reference") != photo.get(
            "fingerprint"):
        return None
    sources, _ = ctx.sources_of(name)
    if sources is None or photo.get("fingerprint") != fingerprint(photometric_settings(ctx, name, sources)):
        return None
    return prov


def filled_pass(ctx: StereoContext, name: str) -> RefOutcome:
    """The dense completion of ``name``'s geometric map (:mod:`colmap_pvs.completion`).

    Reads the geometric maps of ``name`` and of its best views by score whose geometric maps are
    current (:func:`current_geometric_provenance`, up to ``geom_num_sources``), so it runs once every
    geometric map exists.
    """
    cfg, ref = ctx.config, ctx.reference(name)
    timer = Timer()
    prov = ref.provenance("geometric")
    if prov is None or not geometric_files_exist(ref):
        remove_filled(ref)
        return RefOutcome(name, "filled", "skipped", "its geometric maps do not exist")
    entry = ctx.selection.references.get(name)
    source_prov: dict[str, dict] = {}  # the best views by score whose geometric maps are current
    for s in entry.ranked_names if entry is not None else ():
        if len(source_prov) >= max(1, cfg.geometric.num_sources):
            break
        found = current_geometric_provenance(ctx, s) if s != name else None
        if found is not None:
            source_prov[s] = found
    settings = stage_settings(ctx, "filled", "completion")
    settings.update(reference=prov["fingerprint"],
                    sources={s: p["fingerprint"] for s, p in source_prov.items()})
    size = tuple(prov.get("image_size", ctx.map_size(name)))
    why = stale_reason(ref, "filled", settings, size, cfg.overwrite)
    if why is None:
        if cfg.previews:  # an output-only option: its files from the maps on disk, nothing recomputed
            write_missing_previews(ref, "filled")  # over ref.depth_range: the entry's, if any
        return RefOutcome(name, "filled", "done", seconds=timer.elapsed())
    with timer.step("load"):
        # The seeds of the reference and of its sources are what is known.
        seeds = load_maps(ctx, ref, "geometric", normals=False, depth_path=ref.paths.seeds)
        srcs = [load_maps(ctx, src, "geometric", normals=False, depth_path=src.paths.seeds)
                for src in map(ctx.reference, source_prov)]
        h, w = seeds.depth.shape
        # the geometric pass's own maps: not the confirmed completion a previous run added to them
        geometric_depth, _, geo_conf = pure_geometric(ref)
        geometric_kept = geometric_depth > 0
        if geometric_kept.shape != (h, w):
            raise MapFormatError(
                f"geometric depth map of {name!r} is {geometric_kept.shape}, its seed map is {(h, w)}"
            )
        photo = read_depth_map(ref.paths["photometric"].depth)
        if photo.shape != (h, w):
            raise MapFormatError(
                f"photometric depth map of {name!r} is {photo.shape}, its geometric one is {(h, w)}"
            )
        photo_conf = read_confidence(ref.paths["photometric"].confidence, (h, w))
    with timer.step("splat"):
        kept = seeds.depth > 0
        splat, support = splat_depths(seeds.K, seeds.cam_from_world, (w, h), srcs, cfg.completion.min_sources)
        splatted = ~kept & (splat > 0)
        known = np.where(kept, seeds.depth, splat).astype(np.float32)
    segmented, refused, inliers = np.zeros_like(kept), np.zeros_like(kept), None
    if cfg.completion.segments:
        with timer.step("segments"):
            image = ctx.images.get(name, cfg.photometric.max_image_size, (w, h))
            plane, inliers, refused = segment_planes(known, image, ~kept)
            segmented = ~kept & (plane > 0)
            refused &= ~splatted
    with timer.step("fit"):
        depth = complete_depth(known, photo)
        if cfg.completion.segments:
            depth = np.where(segmented, plane, depth).astype(np.float32)
        # Nothing supports a depth where a segment's plane was refused or the local fit has too few known
        # pixels around it: those pixels keep the network's depth, with confidence 0 (docs/CONVENTIONS.md).
        fitted = ~kept & ~splatted & ~segmented
        unsupported = refused | (fitted & (fit_support(known) < FIT_MIN_SUPPORT))
        depth = np.where(unsupported, photo, depth).astype(np.float32)
        score = completed_confidence(
            kept, splatted, geo_conf, photo_conf, support / max(1, len(srcs)), segmented, inliers)
        # a completed depth that leaves its local plane (a depth edge, a broken surface) is more often
        # wrong; the floor keeps a supported pixel's score positive (0 marks the unsupported ones)
        score = np.maximum(score * np.exp(-plane_residual(depth, COMPLETION_RESIDUAL_WINDOW)
                                          / COMPLETION_RESIDUAL_SCALE), np.float32(1e-6))
        conf = ctx.calibration.apply("filled", score, depth > 0)
        conf = np.where(unsupported, 0.0, conf).astype(np.float32)
    extra = {"image_size": [w, h], "sources": list(source_prov), "kept_fraction": float(kept.mean()),
             "geometric_fraction": float(geometric_kept.mean()),
             "splatted_fraction": float((splatted & ~segmented).mean()),
             "segmented_fraction": float(segmented.mean()),
             "unsupported_fraction": float(unsupported.mean())}
    dr = entry.depth_range if entry is not None else tuple(np.percentile(depth, [1, 99]))
    ref = ref.with_pass("filled", PassMaps(depth, conf), PassRecord(settings, extra), depth_range=dr,
                        sources=source_prov)
    ctx.submit_write(write_filled, ref, previews=cfg.previews, timer=timer)
    return RefOutcome(name, "filled", "computed", why, seconds=timer.elapsed(), timings=timer.steps)
