"""The confirmed completion (the last step of ``geom_fill``), once every completion exists.

A completed pixel (:mod:`colmap_pvs.stereo.filled`) that other references' completions agree with, as
``fuse`` checks them (:data:`CONFIRM_MIN_VIEWS` views within :data:`CONFIRM_MAX_REPROJ_ERROR` px
forward-backward and :data:`CONFIRM_MAX_DEPTH_ERROR` in depth; one view for a pixel whose confidence
is at least :data:`CONFIRM_ONE_VIEW_CONFIDENCE`), joins the geometric maps, which is
what COLMAP's own ``stereo_fusion`` reads, so its cloud and mesh gain the surfaces only the completion
covers (``benchmarks/RESULTS.md``, "The confirmed completion joins the geometric maps"). Such a pixel takes
the completion's depth, a normal fitted to it and the completion's confidence.

The pixels a run added are kept in ``stereo/confirm_maps/NAME.bin`` (their depth, 0 elsewhere) with the
geometric maps' fingerprint in ``stereo/provenance/NAME.confirm.json``, so that a later run that
changes the completions takes them out of the geometric maps again before it adds its own
(:func:`remove_confirmed`; also when the completion is switched off).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..consistency import SourceMaps, check_consistency
from ..io.files import file_sha256
from ..io.maps import read_array, read_depth_map, write_depth_map
from ..normals import fit_normals
from .config import FORMAT_VERSIONS
from .context import RefOutcome, StereoContext
from .filled import current_geometric_provenance
from .geometric import load_maps
from .outputs import change_reason, fingerprint, pure_geometric, remove_confirmed, write_geometric, write_json
from .reference import Reference, read_json
from .timing import Timer

#: Other references whose completions must agree with a completed pixel (``fuse``'s default) ...
CONFIRM_MIN_VIEWS = 2
#: ... or one, where the pixel's confidence is at least this (``benchmarks/RESULTS.md``, "One confirming
#: view for a confident completed pixel").
CONFIRM_ONE_VIEW_CONFIDENCE = 0.7
#: Forward-backward reprojection error (map pixels) and relative depth error of that agreement.
CONFIRM_MAX_REPROJ_ERROR = 1.0
CONFIRM_MAX_DEPTH_ERROR = 0.01


def confirmed(agreeing: np.ndarray, confidence: np.ndarray) -> np.ndarray:
    """``[H, W]`` bool: the completed pixels that the confirmation adds, given how many other
    references' completions agree with each (``agreeing`` ``[H, W]`` int) and its confidence
    ``[H, W]``: :data:`CONFIRM_MIN_VIEWS` agreeing views, or one where the confidence is at least
    :data:`CONFIRM_ONE_VIEW_CONFIDENCE`."""
    return (agreeing >= CONFIRM_MIN_VIEWS) | ((agreeing >= 1) & (confidence >= CONFIRM_ONE_VIEW_CONFIDENCE))


def _supported_completion(ctx: StereoContext, ref: Reference) -> tuple[SourceMaps, np.ndarray]:
    """``ref``'s completion with its supported pixels only (confidence above 0; 0 elsewhere), and its
    confidence ``[H, W]``."""
    maps = load_maps(ctx, ref, "filled", normals=False)
    conf = read_array(ref.paths["filled"].confidence).reshape(maps.depth.shape)
    return replace(maps, depth=np.where(conf > 0, maps.depth, 0.0).astype(np.float32)), conf


def confirm_pass(ctx: StereoContext, name: str) -> RefOutcome:
    """Add to ``name``'s geometric maps the completed pixels that the completions of its best views by
    score among this run's references (up to ``geom_num_sources``) confirm."""
    cfg, this = ctx.config, ctx.reference(name)
    timer = Timer()
    geo, filled = this.provenance("geometric"), this.provenance("filled")
    if geo is None or filled is None or not this.has_maps("filled"):
        remove_confirmed(this)
        return RefOutcome(name, "confirm", "skipped", "it has no completion")
    if not this.has_maps("geometric"):
        remove_confirmed(this)
        return RefOutcome(name, "confirm", "skipped", "it has no geometric maps")
    entry = ctx.selection.references.get(name)
    refs = set(ctx.references)
    sources: dict[str, str] = {}
    for s in entry.ranked_names if entry is not None else ():
        if len(sources) >= max(1, cfg.geometric.num_sources):
            break
        prov = ctx.reference(s).provenance("filled") if s in refs and s != name else None
        geometric = current_geometric_provenance(ctx, s) if prov is not None else None
        if (geometric is not None and ctx.reference(s).has_maps("filled")  # made from its current maps
                and prov.get("settings", {}).get("reference") == geometric.get("fingerprint")):
            sources[s] = prov["fingerprint"]
    settings = {"format_version": FORMAT_VERSIONS["confirm"], "min_views": CONFIRM_MIN_VIEWS,
                "one_view_confidence": CONFIRM_ONE_VIEW_CONFIDENCE,
                "max_reproj_error": CONFIRM_MAX_REPROJ_ERROR, "max_depth_error": CONFIRM_MAX_DEPTH_ERROR,
                "geometric": geo["fingerprint"], "filled": filled["fingerprint"], "sources": sources}
    paths = this.paths
    record = read_json(paths.confirm_provenance)
    geometric_path = paths["geometric"].depth
    geometric_sha256 = file_sha256(geometric_path)
    same = record is not None and record.get("fingerprint") == fingerprint(settings)
    if (same and paths.confirm_map.is_file()
            and record.get("geometric_depth_sha256") == geometric_sha256):  # not rewritten since
        if not cfg.overwrite:
            return RefOutcome(name, "confirm", "done", seconds=timer.elapsed())
        why = "--overwrite"
    elif same:
        why = ("its geometric maps were rewritten" if paths.confirm_map.is_file()
               else "its confirmed pixels are missing")
    elif record is None:  # a first run, or new geometric maps (their pass removes the record)
        why = "its geometric maps are new"
    else:
        why = change_reason(record, settings, "confirm")
    with timer.step("load"):
        depth, normals, conf = pure_geometric(this, geometric_sha256)
        ref, fconf = _supported_completion(ctx, this)
        supported = ref.depth
        srcs = [_supported_completion(ctx, ctx.reference(s))[0] for s in sources]
    with timer.step("check"):
        candidates = np.where(depth > 0, 0.0, supported).astype(np.float32)
        added = np.zeros(depth.shape, bool)
        if srcs and (candidates > 0).any():
            res = check_consistency(candidates, None, ref.K, ref.cam_from_world, srcs,
                                    max_reproj_error=CONFIRM_MAX_REPROJ_ERROR,
                                    max_depth_error=CONFIRM_MAX_DEPTH_ERROR, workers=2)
            added = (candidates > 0) & confirmed(res.agree.sum(0), fconf)
        fitted = fit_normals(supported, ref.K)
        added &= np.any(fitted != 0, axis=-1)
    with timer.step("writes"):
        # Crash-safe order: first a record that covers the old and the new pixels (on these geometric
        # maps), then the maps, then the exact record.
        old_path = paths.confirm_map
        # The interim record below has no geometric_depth_sha256 (None): a run killed between its
        # writes left maps that still hold its pixels.
        applies = record is not None and record.get("geometric") == geo["fingerprint"] and record.get(
            "geometric_depth_sha256") in (None, geometric_sha256)
        old = read_depth_map(old_path) if old_path.is_file() and applies else np.zeros_like(depth)
        old = old if old.shape == depth.shape else np.zeros_like(depth)
        old_path.parent.mkdir(parents=True, exist_ok=True)
        write_depth_map(old_path, np.where(added, supported, old).astype(np.float32))
        write_json(paths.confirm_provenance, {"fingerprint": None, "geometric": geo["fingerprint"]})
        write_geometric(this, np.where(added, supported, depth),
                        np.where(added[..., None], fitted, normals), np.where(added, fconf, conf))
        write_depth_map(old_path, np.where(added, supported, 0.0).astype(np.float32))
        write_json(paths.confirm_provenance, {
            "fingerprint": fingerprint(settings), "geometric": geo["fingerprint"], "settings": settings,
            "geometric_depth_sha256": file_sha256(geometric_path), "added_fraction": float(added.mean())})
    return RefOutcome(name, "confirm", "computed", why, seconds=timer.elapsed(), timings=timer.steps)
