"""The geometric pass: each reference's photometric depth checked against its sources' maps.

Forward-backward consistency (:mod:`colmap_pvs.consistency`), consulting only the sources the network
found visible; pixels that fewer than ``geom_min_consistent`` sources confirm (agree with, seen at a
triangulation angle of at least ``geom_min_triangulation_angle``) are dropped, the rest averaged with
the confirming sources' depths. A dropped pixel is kept where ``geom_splat_min_sources`` of the
sources' seeds, projected into it, agree. Writes ``NAME.geometric.bin`` depth, normal and confidence
maps and ``stereo/seed_maps/NAME.bin``, the pixels that ``geom_seed_min_consistent`` sources agree
with within ``geom_seed_depth_error`` (the dense completion's seeds). With ``geom_reestimate`` the
depth that passes the check first becomes dense hints of a second network run on the reference, and
that re-estimate is what is checked (COLMAP's geometric PatchMatch re-estimates each reference with
its sources' photometric maps, too).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..completion import plane_deviation, splat_depths
from ..consistency import SourceMaps, check_consistency
from ..errors import MapFormatError, ShapeError
from ..geometry import to_homogeneous
from ..io.maps import read_array, read_depth_map, read_normal_map
from ..normals import fit_normals
from ..upsampling import resize_bilinear
from .config import Stage, StereoConfig, pass_settings
from .context import RefOutcome, StereoContext
from .outputs import (
    fingerprint,
    geometric_files_exist,
    read_confidence,
    read_visibility,
    stage_settings,
    stale_reason,
    write_missing_previews,
    write_pass,
    write_seeds,
)
from .photometric import network_maps
from .reference import PassMaps, PassRecord, Reference
from .timing import Timer

logger = logging.getLogger(__name__)

#: Relative deviation from the local plane at which the geometric confidence falls by ``1 / e``.
GEOM_DEVIATION_SCALE = 0.02
#: Parallax (pixels per ``consistency.PARALLAX_STEP`` of depth) from which an agreeing source counts fully
#: in the geometric confidence; one with less counts in proportion.
GEOM_FULL_PARALLAX = 1.0
#: Confidence of a geometric pixel that the sources' seeds give (``geom_splat_min_sources``), times the
#: share of the checked sources that agree on it and the network's probability at the pixel: below most
#: checked pixels, which are more often right.
SPLAT_CONFIDENCE = 0.1
#: Seed maps computed on demand (for other references' geometric passes) kept in memory per run.
SEED_CACHE_SIZE = 32


def geometric_confidence(agree: np.ndarray, visibility: np.ndarray | None,
                         deviation: np.ndarray | None = None,
                         parallax: np.ndarray | None = None,
                         network: np.ndarray | None = None) -> np.ndarray:
    """``[H, W]`` confidence of a geometric map in ``[0, 1]`` (definition: ``docs/CONVENTIONS.md``).

    ``c = q * exp(-e / GEOM_DEVIATION_SCALE) * sum_s v_s * min(1, p_s / GEOM_FULL_PARALLAX) * agree_s / S``:
    the fraction of the ``S`` sources that confirm the pixel, each weighted by the network's learned
    visibility ``v_s`` of that source at the pixel (``agree`` ``[S, H, W]``, ``visibility``
    ``[S, H, W]`` or ``None`` for all ones) and by its parallax ``p_s`` (``[S, H, W]`` pixels,
    :attr:`~colmap_pvs.consistency.ConsistencyResult.parallax`; ``None``: full), times a factor for
    how far the pixel stands off the local plane of the kept pixels around it (``deviation`` ``e``
    ``[H, W]``, :func:`~colmap_pvs.completion.plane_deviation`; ``None``: 0), times the network's own
    probability ``q`` of its depth (``network`` ``[H, W]``, the photometric confidence; ``None``: 1).
    A source with little parallax agrees with almost any depth, so its agreement says less. Chosen by
    measurement (``benchmarks/RESULTS.md``, "Geometric confidence with the plane deviation", the
    entries before it, and "The network's confidence in the completion's"): the weighted fraction
    ranks errors better than the network's probability mass alone, the agreement count alone, or the
    reprojection and depth errors; the deviation factor, the parallax weight and the network's
    probability rank them better still (views that agree on a wrong depth are most often views the
    network was unsure in).
    """
    S = max(agree.shape[0], 1)
    weighted = agree if visibility is None else np.where(agree, visibility, 0.0)
    if parallax is not None:
        if parallax.shape != agree.shape:
            raise ShapeError(f"parallax must be {agree.shape}, got {parallax.shape}")
        weighted = weighted * np.clip(np.nan_to_num(parallax) / GEOM_FULL_PARALLAX, 0.0, 1.0)
    conf = weighted.sum(0) / S
    if network is not None:
        if network.shape != conf.shape:
            raise ShapeError(f"network must be {conf.shape}, got {network.shape}")
        conf = conf * np.clip(np.nan_to_num(network), 0.0, 1.0)
    if deviation is not None:
        if deviation.shape != conf.shape:
            raise ShapeError(f"deviation must be {conf.shape}, got {deviation.shape}")
        conf = conf * np.exp(-np.nan_to_num(deviation, nan=np.inf) / GEOM_DEVIATION_SCALE)
    return np.clip(conf, 0.0, 1.0).astype(np.float32)


def load_maps(ctx: StereoContext, ref: Reference, kind: Stage = "photometric",
              normals: bool = True, depth_path: Path | None = None) -> SourceMaps:
    """``ref``'s ``kind`` depth map (or the depth map at ``depth_path``; and its ``kind`` normal map,
    with ``normals``), intrinsics and pose."""
    name, out = ref.name, ref.paths[kind]
    depth = read_depth_map(out.depth if depth_path is None else depth_path)
    normal_map = read_normal_map(out.normals) if normals else None
    if normal_map is not None and normal_map.shape[:2] != depth.shape:
        raise MapFormatError(
            f"normal map of {name!r} is {normal_map.shape[:2]} but its depth map is {depth.shape}"
        )
    h, w = depth.shape
    T = to_homogeneous(ctx.sparse.image_by_name(name).cam_from_world)
    return SourceMaps(depth, normal_map, ctx.map_K(name, (w, h)), T)


def _check_visibility(coarse: np.ndarray, network_sources: list[str], sources: list[str],
                      size: tuple[int, int]) -> np.ndarray | None:
    """``[S, H, W]`` learned visibility of each of ``sources`` for the check, from the network's
    ``coarse`` ``[len(network_sources), h, w]`` maps upsampled to ``size`` ``(H, W)``; a source the
    network did not see counts as visible. ``None`` when ``coarse`` does not match the network's sources."""
    if coarse.shape[0] != len(network_sources):
        return None
    h, w = size
    up = resize_bilinear(np.ascontiguousarray(coarse, dtype=np.float32), h, w)
    ones = np.ones((h, w), np.float32)
    return np.stack([up[network_sources.index(s)] if s in network_sources else ones for s in sources])


@dataclass
class CheckSetup:
    """What a reference's geometric check reads: its photometric provenance ``prov``, the ``sources``
    checked (with photometric maps), the network sources without maps (``missing``), its
    view-selection ``entry`` and the ``settings`` (fingerprinted) that fix the check and the seeds."""

    prov: dict
    sources: list[str]
    missing: list[str]
    entry: object
    settings: dict


def _check_setup(ctx: StereoContext, name: str) -> CheckSetup | str:
    """:class:`CheckSetup` of ``name``, or why its geometric pass cannot run."""
    cfg, ref = ctx.config, ctx.reference(name)
    prov = ref.provenance("photometric")
    if prov is None or not ref.has_maps("photometric"):
        return "its photometric maps do not exist"
    source_prov: dict[str, dict] = {}  # each source's provenance, read once

    def has_maps(s: str) -> bool:
        if s not in source_prov and ctx.reference(s).has_maps("photometric"):
            found = ctx.reference(s).provenance("photometric")
            if found is not None:
                source_prov[s] = found
        return s in source_prov

    sources = [s for s in prov.get("sources", []) if has_maps(s)]
    missing = [s for s in prov.get("sources", []) if s not in sources]
    entry = ctx.selection.references.get(name)
    if cfg.geometric.num_sources > 0 and entry is not None:  # the next best views with maps
        # A network source that is not a candidate view of the reference (score 0 or fewer than
        # min_shared_points shared sparse points: an unrelated frame in patch-match.cfg) is still
        # checked but takes none of the slots.
        candidates = set(entry.ranked_names)
        counted = sum(s in candidates for s in sources)
        for s in entry.ranked_names:
            if counted >= cfg.geometric.num_sources:
                break
            if s not in sources and s != name and has_maps(s):
                sources.append(s)
                counted += 1
    settings = stage_settings(ctx, "geometric", "geometric", seeds=True)
    settings.update(
        reference=prov["fingerprint"],
        sources={s: source_prov[s]["fingerprint"] for s in sources},
    )
    if len(sources) < min(cfg.geometric.min_consistent, len(prov.get("sources", []))) or not sources:
        return f"{len(sources)} of its sources have photometric maps (missing: {missing})"
    return CheckSetup(prov, sources, missing, entry, settings)


def _check_kwargs(ctx: StereoContext) -> dict:
    cfg = ctx.config.geometric
    return {"max_reproj_error": cfg.max_reproj_error, "max_depth_error": cfg.max_depth_error,
            "min_visibility": cfg.min_visibility,
            # the sources in threads, as many as torch's: with two references at once (REFERENCE_THREADS)
            # twice the cores, on purpose (a thread waiting for memory leaves its core to another)
            "workers": max(1, torch.get_num_threads())}


def _load_check(ctx: StereoContext, name: str, setup: CheckSetup):
    """``(ref, srcs, vis)``: the photometric maps of ``name`` and of its checked sources, and the
    learned visibility of those sources (``None`` without a visibility map)."""
    ref = load_maps(ctx, ctx.reference(name))
    srcs = [load_maps(ctx, ctx.reference(s)) for s in setup.sources]
    coarse = read_visibility(ctx.reference(name))
    vis = None if coarse is None else _check_visibility(coarse, list(setup.prov.get("sources", [])),
                                                       setup.sources, ref.depth.shape)
    return ref, srcs, vis


def _seeds(cfg: StereoConfig, ref: SourceMaps, res) -> np.ndarray:
    """``[H, W]`` the completion's seeds of ``ref``'s photometric depth from its check ``res``:
    pixels that ``geom_seed_min_consistent`` sources confirm within ``geom_seed_depth_error`` (at any
    angle: the completion is better off with the narrow-baseline agreement of a video than without
    it), not isolated (the map of the seeds alone still gives them a normal); 0 elsewhere."""
    strict = (res.agree & (res.depth_error <= cfg.geometric.seed_depth_error)).sum(0)
    seed_depth = res.mean_depth(ref.depth) if cfg.geometric.average_depth else ref.depth
    seeds = np.where((ref.depth > 0) & (strict >= cfg.geometric.seed_min_consistent), seed_depth, 0.0)
    return np.where(np.any(fit_normals(seeds, ref.K) != 0, axis=-1), seeds, 0.0).astype(np.float32)


@dataclass
class Checked:
    """A reference's check: its seeds ``[H, W]`` (from its photometric maps) and its checked depth and
    confidence ``[H, W]`` (0 where dropped) before the sources' seeds are added, ``reestimated`` when
    they are the check of a re-estimate. Cached in ``ctx.seed_cache`` for other references' passes,
    with the depth and confidence when another reference's geometric pass made it in this run, for its
    own pass to reuse (``None`` for seeds read from disk, once its own pass has checked it, for an image
    that is no reference of the run, and for one whose pass re-estimates it)."""

    seeds: np.ndarray
    depth: np.ndarray | None = None
    conf: np.ndarray | None = None
    reestimated: bool = False


def _warn_if_every_source_is_too_close(ctx: StereoContext, name: str, sources: list[str], ref: SourceMaps,
                                       res) -> None:
    """One WARNING for a reference that every source sees from less than ``geom_min_triangulation_angle``
    (the median over its pixels): no source can confirm a pixel, so its geometric map is (nearly) empty."""
    min_angle = ctx.config.geometric.min_triangulation_angle
    valid = ref.depth > 0
    if min_angle <= 0 or not sources or not valid.any():
        return
    seen = [valid & res.checked[s] for s in range(len(sources))]
    angles = [float(np.median(res.angle[s][m])) if m.any() else 0.0 for s, m in enumerate(seen)]
    if max(angles) >= min_angle:
        return
    listed = ", ".join(f"{src} {a:.2g}" for src, a in zip(sources, angles, strict=True))
    logger.warning("geometric pass: every source of %r sees it from less than geom_min_triangulation_angle "
                   "%g degrees (median angles: %s), so its geometric map is empty: lower "
                   "--geom_min_triangulation_angle or give it sources farther away (patch-match.cfg)",
                   name, min_angle, listed)


def _kept(ctx: StereoContext, name: str, sources: list[str], ref: SourceMaps, res,
          vis: np.ndarray | None, network: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(depth, conf)`` ``[H, W]`` of the pixels of ``ref`` (reference ``name``) that the check ``res``
    against ``sources`` keeps: confirmed by ``geom_min_consistent`` sources from
    ``geom_min_triangulation_angle`` or more, averaged over them (``geom_average_depth``), with their
    geometric confidence (calibrated; ``network`` ``[H, W]`` the network's probability of ``ref``'s
    depth) of at least ``geom_min_confidence``."""
    cfg = ctx.config
    _warn_if_every_source_is_too_close(ctx, name, sources, ref, res)
    confirm = res.confirming(cfg.geometric.min_triangulation_angle)  # agreeing, from far enough apart
    keep = (ref.depth > 0) & (confirm.sum(0) >= cfg.geometric.min_consistent)
    depth = res.mean_depth(ref.depth, confirm) if cfg.geometric.average_depth else ref.depth.copy()
    depth = np.where(keep, depth, 0.0).astype(np.float32)
    score = geometric_confidence(confirm, vis, plane_deviation(depth), res.parallax, network)
    conf = ctx.calibration.apply("geometric", score, keep)
    keep &= conf >= cfg.geometric.min_confidence
    depth[~keep] = 0.0
    return depth, np.where(keep, conf, 0.0).astype(np.float32)


def _reestimates(ctx: StereoContext, setup: CheckSetup) -> bool:
    """Whether the reference of ``setup`` is re-estimated in its geometric pass (``geom_reestimate``,
    with network sources and a view-selection entry): its kept pixels then come from the re-estimate,
    not from the check of its photometric maps."""
    return bool(ctx.config.geometric.reestimate and setup.prov.get("sources") and setup.entry is not None)


def _network_probability(ctx: StereoContext, name: str, shape: tuple[int, int]) -> np.ndarray:
    """``[H, W]`` the network's probability of ``name``'s photometric depth (its confidence map)."""
    return read_confidence(ctx.reference(name).paths["photometric"].confidence, shape)


def _check_photometric(ctx: StereoContext, name: str, setup: CheckSetup, kept: bool = True) -> Checked:
    """:class:`Checked` of ``name`` from its photometric maps and its checked sources' (the seeds
    only, without ``kept``)."""
    ref, srcs, vis = _load_check(ctx, name, setup)
    check = _check_kwargs(ctx)
    res = check_consistency(ref.depth, ref.normals, ref.K, ref.cam_from_world, srcs, vis, **check)
    depth = conf = None
    if kept:
        network = _network_probability(ctx, name, ref.depth.shape)
        depth, conf = _kept(ctx, name, setup.sources, ref, res, vis, network)
    return Checked(_seeds(ctx.config, ref, res), depth, conf)


def _remember_seeds(ctx: StereoContext, name: str, fingerprint: str, checked: Checked) -> None:
    with ctx.seed_lock:
        ctx.seed_cache[name] = (fingerprint, checked)
        ctx.seed_cache.move_to_end(name)
        while len(ctx.seed_cache) > SEED_CACHE_SIZE:
            ctx.seed_cache.popitem(last=False)


def _cached_check(ctx: StereoContext, name: str) -> tuple[str, Checked] | None:
    with ctx.seed_lock:
        return ctx.seed_cache.get(name)


def _source_seeds(ctx: StereoContext, name: str, setup: CheckSetup) -> np.ndarray:
    """The seeds of ``name`` (its check's ``setup``) for another reference's geometric pass: from this
    run's memory or a current seed map on disk, else computed from the photometric maps (the same
    check as ``name``'s own geometric pass, so the same seeds whoever makes them) and written."""
    with ctx.check_lock(name):
        return _source_seeds_locked(ctx, name, setup)


def _source_seeds_locked(ctx: StereoContext, name: str, setup: CheckSetup) -> np.ndarray:
    paths = ctx.reference(name).paths
    wanted = fingerprint(setup.settings)
    cached = _cached_check(ctx, name)
    if cached is not None and cached[0] == wanted:
        return cached[1].seeds
    if not ctx.config.overwrite:
        try:
            on_disk = json.loads(paths.seed_provenance.read_text()).get("fingerprint")
            if on_disk == wanted:
                seeds = read_array(paths.seeds)
                seeds = seeds[..., 0] if seeds.ndim == 3 else seeds
                _remember_seeds(ctx, name, wanted, Checked(seeds))
                return seeds
        except (OSError, json.JSONDecodeError, MapFormatError):
            pass
    # the whole check, kept for this image's own geometric pass later in the run (unless that pass
    # re-estimates, which checks the re-estimate instead); a source that is no reference of this run
    # has no geometric pass, so its seeds are all it needs
    own_pass = name in ctx.references and not _reestimates(ctx, setup)
    checked = _check_photometric(ctx, name, setup, kept=own_pass)
    write_seeds(paths, checked.seeds, wanted)
    _remember_seeds(ctx, name, wanted, checked)
    return checked.seeds


def _reused_check(ctx: StereoContext, name: str, seed_fingerprint: str, timer: Timer) -> Checked | None:
    """The check of ``name``'s photometric maps that another reference's pass made earlier in this run
    (for its seeds; :func:`_source_seeds`), or ``None``."""
    cached = _cached_check(ctx, name)
    if cached is None or cached[0] != seed_fingerprint or cached[1].depth is None:
        return None
    with timer.step("reused_check"):
        checked = cached[1]
        return Checked(checked.seeds, checked.depth.copy(), checked.conf.copy())


def _checked_photometric(ctx: StereoContext, name: str, setup: CheckSetup, timer: Timer) -> Checked:
    """The check of ``name``'s photometric maps (:func:`_check_photometric`)."""
    with timer.step("consistency"):
        return _check_photometric(ctx, name, setup)


def _reestimate(ctx: StereoContext, name: str, setup: CheckSetup, timer: Timer) -> Checked | str:
    """The check of a re-estimate of ``name`` (``geom_reestimate``), or why the network could not run.

    COLMAP's geometric PatchMatch re-estimates each reference with its sources' photometric maps; here
    the depth they agree on becomes dense hints of a second network run (the coarse planes centred on
    it, the cost modulated around it), whose maps are then checked as the photometric maps would be.
    """
    cfg = ctx.config
    all_sources = list(setup.prov.get("sources", []))
    with timer.step("reestimate_hints"):
        ref, srcs, vis = _load_check(ctx, name, setup)
        h, w = ref.depth.shape
        check = _check_kwargs(ctx)
        first = check_consistency(ref.depth, ref.normals, ref.K, ref.cam_from_world, srcs, vis, **check)
        seeds = _seeds(cfg, ref, first)  # from the photometric maps, as :func:`_source_seeds` makes them
        agreed = (ref.depth > 0) & (first.count >= cfg.geometric.min_consistent)
        hints = np.where(agreed, first.mean_depth(ref.depth), 0.0).astype(np.float32)
        del first
    network_timer = Timer()
    maps = network_maps(ctx, name, all_sources, network_timer, dense_hints=hints)
    timer.add(network_timer, "reestimate_")
    if isinstance(maps, str):
        return maps
    ref = SourceMaps(maps.depth, maps.normals, ref.K, ref.cam_from_world)
    vis = _check_visibility(maps.visibility, all_sources, setup.sources, (h, w))
    with timer.step("consistency"):
        res = check_consistency(ref.depth, ref.normals, ref.K, ref.cam_from_world, srcs, vis, **check)
        depth, conf = _kept(ctx, name, setup.sources, ref, res, vis, maps.confidence)
        del res
    return Checked(seeds, depth, conf, reestimated=True)


def _splat_sources(ctx: StereoContext, setup: CheckSetup) -> dict[str, CheckSetup]:
    """The checked sources whose seeds are projected into dropped pixels (``geom_splat_min_sources``):
    each with its own check's setup."""
    if ctx.config.geometric.splat_min_sources <= 0:
        return {}
    found = {s: _check_setup(ctx, s) for s in setup.sources}
    return {s: f for s, f in found.items() if not isinstance(f, str)}


def _add_splatted(ctx: StereoContext, name: str, setup: CheckSetup, splat_sources: dict[str, CheckSetup],
                  checked: Checked, timer: Timer) -> tuple[np.ndarray, np.ndarray, int]:
    """``(depth, conf, count)``: the checked maps with the dropped pixels whose surface other views
    confirmed: their seeds projected in (nearest surface per source), the median where enough of them
    agree (docs/CONVENTIONS.md), with the score :data:`SPLAT_CONFIDENCE` times the share of the
    sources that agree times the network's probability at the pixel, and how many pixels that added."""
    cfg = ctx.config
    depth, conf = checked.depth, checked.conf
    h, w = depth.shape
    with timer.step("splat_seeds"):
        seed_maps = []
        for s, found in splat_sources.items():
            seeds_s = _source_seeds(ctx, s, found)
            sh, sw = seeds_s.shape
            seed_maps.append(SourceMaps(seeds_s, None, ctx.map_K(s, (sw, sh)),
                                        to_homogeneous(ctx.sparse.image_by_name(s).cam_from_world)))
    with timer.step("splat"):
        K = ctx.map_K(name, (w, h))
        cam_from_world = to_homogeneous(ctx.sparse.image_by_name(name).cam_from_world)
        splat, support = splat_depths(K, cam_from_world, (w, h), seed_maps, cfg.geometric.splat_min_sources)
        network = _network_probability(ctx, name, (h, w))
        share = SPLAT_CONFIDENCE * support / max(1, len(setup.sources)) * network
        splat_conf = ctx.calibration.apply("geometric", share, splat > 0)
        added = ~(depth > 0) & (splat > 0) & (splat_conf >= cfg.geometric.min_confidence)
        depth = np.where(added, splat, depth).astype(np.float32)
        conf = np.where(added, splat_conf, conf).astype(np.float32)
    return depth, conf, int(added.sum())


def geometric_pass(ctx: StereoContext, name: str) -> RefOutcome:
    """The geometric pass of reference ``name``, once the photometric maps of it and of its sources
    exist: its checked maps and seeds, unless current (module docstring).

    Its check is one of three: reused from another reference's pass in this run (:func:`_reused_check`),
    of its photometric maps (:func:`_checked_photometric`) or of a re-estimate (:func:`_reestimate`);
    then the sources' seeds fill dropped pixels (:func:`_add_splatted`) and normals are fitted.
    """
    cfg, ref = ctx.config, ctx.reference(name)
    timer = Timer()
    setup = _check_setup(ctx, name)
    if isinstance(setup, str):
        return RefOutcome(name, "geometric", "skipped", setup)
    entry = setup.entry
    seed_fingerprint = fingerprint(setup.settings)
    settings = dict(setup.settings, **pass_settings(cfg, "geometric"),  # + those the seeds ignore
                    confidence_calibration=ctx.calibration.settings("geometric"))
    splat_sources = _splat_sources(ctx, setup)
    if cfg.geometric.splat_min_sources > 0:
        settings["splat_seeds"] = {s: fingerprint(found.settings) for s, found in splat_sources.items()}
    size = tuple(setup.prov.get("image_size", ctx.map_size(name)))
    why = stale_reason(ref, "geometric", settings, size, cfg.overwrite)
    if why is None and not geometric_files_exist(ref):
        why = "seed map missing"
    if why is None:
        if cfg.previews:  # an output-only option: its files from the maps on disk, nothing recomputed
            write_missing_previews(ref, "geometric")  # over ref.depth_range: the entry's, if any
        return RefOutcome(name, "geometric", "done", seconds=timer.elapsed())
    if _reestimates(ctx, setup):
        checked = _reestimate(ctx, name, setup, timer)
        if isinstance(checked, str):
            return RefOutcome(name, "geometric", "skipped", checked)
    else:
        with ctx.check_lock(name):  # not while another reference's pass checks it for its seeds
            checked = (_reused_check(ctx, name, seed_fingerprint, timer)
                       or _checked_photometric(ctx, name, setup, timer))
            _remember_seeds(ctx, name, seed_fingerprint, Checked(checked.seeds))  # its seeds only, from now
    depth, conf, splatted = checked.depth, checked.conf, 0
    if splat_sources:
        depth, conf, splatted = _add_splatted(ctx, name, setup, splat_sources, checked, timer)
    with timer.step("normals"):
        h, w = depth.shape
        normals = fit_normals(depth, ctx.map_K(name, (w, h)))
        depth[~np.any(normals != 0, axis=-1)] = 0.0
        conf[depth == 0] = 0.0
    kept = depth[depth > 0]  # the previews' scale without a view-selection entry: the kept depths'
    dr = entry.depth_range if entry is not None else (
        (float(kept.min()), float(kept.max())) if kept.size else (1.0, 2.0))
    extra = {"image_size": [w, h], "sources": setup.sources, "missing_sources": setup.missing,
             "kept_fraction": float((depth > 0).mean()), "splatted_fraction": splatted / depth.size,
             "reestimated": checked.reestimated}
    if checked.reestimated:
        _remember_seeds(ctx, name, seed_fingerprint, Checked(checked.seeds))
    maps = PassMaps(depth, conf, normals, seeds=checked.seeds)
    ref = ref.with_pass("geometric", maps, PassRecord(settings, extra, seed_fingerprint), depth_range=dr,
                        sources=setup.prov.get("sources", []))
    ctx.submit_write(write_pass, ref, previews=cfg.previews, timer=timer)
    return RefOutcome(name, "geometric", "computed", why, seconds=timer.elapsed(), timings=timer.steps)
