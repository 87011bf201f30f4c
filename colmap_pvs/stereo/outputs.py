"""What the ``stereo`` passes write and read back: provenance (what made each pass's maps, so that a
rerun keeps exactly the passes whose settings did not change), the map writers and the readers of a
:class:`~colmap_pvs.stereo.reference.Reference`'s files (the files themselves:
:mod:`colmap_pvs.stereo.reference`).

Every writer removes the pass's old depth map first and writes the new one last: a depth map with
matching provenance marks a pass done, also after a crash.
"""

from __future__ import annotations

import hashlib
import json
import logging
import threading
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import MapFormatError
from ..io.files import atomic_write_bytes, file_sha256, write_files_together
from ..io.maps import (
    encode_array,
    encode_depth_map,
    encode_normal_map,
    read_array,
    read_depth_map,
    read_normal_map,
    save_confidence_preview,
    save_depth_preview,
    save_normal_preview,
    save_scalar_preview,
    write_array,
    write_depth_map,
    write_normal_map,
)
from ..io.workspace import Workspace, move_aside
from ..model import stored_config
from .config import FORMAT_VERSIONS, Stage, pass_settings
from .reference import PassMaps, PassPaths, PassRecord, Reference, ReferencePaths, provenance_path, read_json
from .timing import Timer

if TYPE_CHECKING:
    from .context import StereoContext

logger = logging.getLogger(__name__)


def read_visibility(ref: Reference) -> np.ndarray | None:
    """``[S, h/4, w/4]`` learned visibility of ``ref``'s network sources (``None`` without a map)."""
    path = ref.paths.visibility
    if not path.is_file():
        return None
    coarse = read_array(path)
    return (coarse[..., None] if coarse.ndim == 2 else coarse).transpose(2, 0, 1)


def geometric_files_exist(ref: Reference) -> bool:
    """The geometric pass of ``ref`` left its depth map and its seed map (the completion reads both)."""
    return ref.has_maps("geometric") and ref.paths.seeds.is_file()


def fingerprint(settings: dict) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()


def stage_settings(ctx: StereoContext, stage: Stage, section: str, *, seeds: bool = False) -> dict:
    """The settings of ``stage`` that its maps depend on (:func:`~colmap_pvs.stereo.config.pass_settings`
    of ``ctx.config.<section>``), its name, its format version and (but for the seeds, which have no
    confidence) its confidence calibration curve."""
    out = pass_settings(ctx.config, section, seeds=seeds)
    out.update(stage=stage, format_version=FORMAT_VERSIONS[stage])
    if not seeds:
        out["confidence_calibration"] = ctx.calibration.settings(stage)
    return out


def photometric_settings(ctx: StereoContext, name: str, sources: list[str]) -> dict:
    """The resolved settings and inputs that determine ``name``'s photometric maps: the pass's settings
    (but ``num_views``: the ``sources`` it picked are recorded, and ``patch-match.cfg`` may pick them
    instead), the checkpoint, the depth range, the sha256 of the reference's and each source's image
    file, their cameras (model, size, parameters) and poses, and the reference's sparse points (its
    hints)."""
    s = stage_settings(ctx, "photometric", "photometric")
    s.pop("num_views", None)
    entry = ctx.selection.references[name]
    s.update(checkpoint_sha256=ctx.checkpoint_sha256, sources=list(sources),
             depth_range=[float(f"{entry.depth_range[0]:.9g}"), float(f"{entry.depth_range[1]:.9g}")],
             model_config=stored_config(ctx.net.config),
             image_sha256=ctx.image_sha256(name), camera=ctx.camera_record(name), pose=ctx.pose_record(name),
             sparse_points=ctx.sparse_points_sha256(name),
             source_image_sha256={s: ctx.image_sha256(s) for s in sources},
             source_cameras={s: ctx.camera_record(s) for s in sources},
             source_poses={s: ctx.pose_record(s) for s in sources})
    return s


#: A recorded key that changed, in words (:func:`change_reason`); a key not listed is a setting,
#: ``settings KEY``. ``reference`` and ``sources`` of the later passes: the maps they read.
CHANGE_WORDS = {
    "image_sha256": "image pixels", "source_image_sha256": "source pixels", "camera": "camera",
    "source_cameras": "source camera", "pose": "pose", "source_poses": "source pose",
    "sparse_points": "sparse points", "depth_range": "depth range", "sources": "sources",
    "checkpoint_sha256": "checkpoint", "model_config": "checkpoint", "format_version": "map format",
    "confidence_calibration": "confidence calibration", "splat_seeds": "source seeds",
}
#: What the ``reference`` / ``sources`` fingerprints of a later pass's provenance stand for.
_READS = {"geometric": "photometric maps", "filled": "geometric maps", "confirm": "completion"}


def change_reason(old: dict | None, new: dict, stage: Stage) -> str:
    """Why a pass is recomputed, in words, from its old provenance ``old`` (``None``: none) and the
    settings ``new`` it is made with now: ``"image pixels, camera changed"``, ``"new"``, ..."""
    if old is None:
        return "new"
    before = old.get("settings")
    if not isinstance(before, dict):
        return "no readable record"
    if stage == "photometric" and "image_sha256" not in before:  # before the inputs were recorded
        return "recorded by an older colmap-pvs (without the images' hashes)"
    words: list[str] = []
    older = False
    for key in sorted(set(new) | set(before)):
        if before.get(key) == new.get(key):
            continue
        if key not in before or key not in new:
            older = True
            continue
        if key == "reference" and stage in _READS:
            word = f"its {_READS[stage]}"
        elif key == "sources" and stage in _READS and isinstance(new[key], dict):
            same = isinstance(before[key], dict) and set(before[key]) == set(new[key])
            word = f"sources' {_READS[stage]}" if same else "sources"
        elif key in ("geometric", "filled") and stage == "confirm":
            word = f"its {'geometric maps' if key == 'geometric' else 'completion'}"
        else:
            word = CHANGE_WORDS.get(key, f"settings {key}")
        if word not in words:
            words.append(word)
    if "sources" in words:  # other sources: their pixels, cameras and poses differ too
        words = [w for w in words if w not in ("source pixels", "source camera", "source pose")]
    if stage in _READS:  # the maps it reads: the nearest change only (the others follow from it)
        chain = [f"its {_READS[stage]}", f"sources' {_READS[stage]}", "source seeds"]
        first = next((w for w in chain if w in words), None)
        words = [w for w in words if w not in chain or w == first]
    if words:
        return ", ".join(words) + " changed"
    return "recorded by an older colmap-pvs" if older else "maps missing or unreadable"


def stale_reason(ref: Reference, stage: Stage, settings: dict, size: tuple[int, int],
                 overwrite: bool = False) -> str | None:
    """``None`` when ``ref``'s ``stage`` maps are current (:func:`is_current`), else why not in
    words (:func:`change_reason`; ``"--overwrite"``)."""
    if is_current(ref.paths[stage], fingerprint(settings), size):
        return "--overwrite" if overwrite else None
    return change_reason(ref.provenance(stage), settings, stage)


def pass_summary(stage: str, outcomes, limit: int = 3) -> str:
    """One line on one pass of a run: ``photometric: 2 computed (image pixels changed: a.jpg; camera
    changed: b.jpg), 1 already done, 0 skipped``; the references of each reason (the ``reason`` of a
    computed :class:`~colmap_pvs.stereo.context.RefOutcome`) and the reasons themselves are cut at
    ``limit`` (``and N more``)."""
    outs = [o for o in outcomes if o.stage == stage]
    computed = [o for o in outs if o.status == "computed"]
    by_reason: dict[str, list[str]] = {}
    for o in computed:
        by_reason.setdefault(o.reason or "not recorded", []).append(o.name)

    def cut(items: list[str], sep: str) -> str:
        more = f" and {len(items) - limit} more" if len(items) > limit else ""
        return sep.join(items[:limit]) + more

    parts = [f"{why}: {cut(names, ', ')}" for why, names in by_reason.items()]
    detail = f" ({cut(parts, '; ')})" if parts else ""
    done = sum(o.status == "done" for o in outs)
    skipped = sum(o.status == "skipped" for o in outs)
    return f"{stage}: {len(computed)} computed{detail}, {done} already done, {skipped} skipped"


def json_bytes(payload: dict) -> bytes:
    return (json.dumps(payload, indent=1) + "\n").encode()


def write_json(path: Path, payload: dict) -> None:
    atomic_write_bytes(path, json_bytes(payload))


def read_provenance(ws: Workspace, name: str, stage: Stage) -> dict | None:
    """The provenance of ``name``'s ``stage`` maps, for callers without a run's
    :class:`~colmap_pvs.stereo.reference.Reference` (fusion, tools); a pass uses
    :meth:`Reference.provenance <colmap_pvs.stereo.reference.Reference.provenance>`."""
    return read_json(provenance_path(ws, name, stage))


def outdated_completions(ws: Workspace, names: list[str]) -> tuple[list[str], list[str]]:
    """Of ``names``, those without a filled depth map and those whose completion is of another format
    version (``FORMAT_VERSIONS["filled"]``, read from its provenance)."""
    missing = [n for n in names if not ws.depth_map_path(n, "filled").is_file()]
    old = [n for n in names if n not in missing and ((read_provenance(ws, n, "filled") or {}).get(
        "settings") or {}).get("format_version") != FORMAT_VERSIONS["filled"]]
    return missing, old


def is_current(out: PassPaths, fingerprint: str, size: tuple[int, int]) -> bool:
    """The pass's depth map (at ``out``) is readable, has the expected size and its provenance matches."""
    prov = read_json(out.provenance)
    if prov is None or prov.get("fingerprint") != fingerprint:
        return False
    try:
        depth = read_depth_map(out.depth)
    except (OSError, MapFormatError):
        return False
    return depth.shape == (size[1], size[0])


def provenance_record(settings: dict, extra: dict) -> dict:
    return {"fingerprint": fingerprint(settings), "settings": settings, **extra}


def write_pass(ref: Reference, *, previews: bool, timer: Timer) -> None:
    """Write ``ref``'s maps and record of its pass (``ref.stage``, ``ref.maps``, ``ref.record``), then
    with ``previews`` its previews: every file is written beside its place first (a full disk leaves
    the old maps as they were), then the old depth is removed and the new files renamed into place,
    the depth last (it marks the pass done). Times ``writes`` and ``previews`` in ``timer``.

    The maps' ``visibility`` (photometric pass) goes to ``stereo/visibility_maps/NAME.bin``, their
    ``seeds`` (geometric pass) to ``stereo/seed_maps/NAME.bin`` with the record's ``seed_fingerprint``.
    Preview names: ``NAME.photometric.*.png`` for the first pass, ``NAME.*.png`` for the geometric one.
    """
    stage, maps, record, paths = ref.stage, ref.maps, ref.record, ref.paths
    out = paths[stage]
    with timer.step("writes"):
        files = [(out.confidence, encode_array(out.confidence, maps.confidence.astype(np.float32)))]
        if maps.visibility is not None:
            vis = maps.visibility
            files.append((paths.visibility, encode_array(paths.visibility, np.ascontiguousarray(
                vis.transpose(1, 2, 0)) if vis.shape[0] else np.zeros((1, 1, 1)))))
        if maps.seeds is not None:  # the seed map, then its fingerprint (which marks it current)
            files.append((paths.seeds, encode_array(paths.seeds, maps.seeds.astype(np.float32))))
            files.append((paths.seed_provenance, json_bytes({"fingerprint": record.seed_fingerprint})))
        files.append((out.normals, encode_normal_map(out.normals, maps.normals)))
        files.append((out.provenance, json_bytes(provenance_record(record.settings, record.extra))))
        files.append((out.depth, encode_depth_map(out.depth, maps.depth)))  # last: marks the pass done

        def drop_old() -> None:  # once every new file is on disk
            _set_aside_colmaps_maps(out, paths.stereo_dir)
            # The old depth goes first: new provenance beside an old depth would look done after a crash.
            out.depth.unlink(missing_ok=True)
            if maps.seeds is not None:
                paths.seed_provenance.unlink(missing_ok=True)
            if stage == "geometric":  # new maps of the pass itself: nothing confirmed was added to them
                paths.confirm_provenance.unlink(missing_ok=True)
                paths.confirm_map.unlink(missing_ok=True)

        write_files_together(files, before_commit=drop_old)
    if previews:
        with timer.step("previews"):
            write_previews(ref)


_warned_foreign: set[Path] = set()  # the stereo folders whose COLMAP maps were reported this process
_warned_lock = threading.Lock()


def _set_aside_colmaps_maps(out: PassPaths, stereo_dir: Path) -> None:
    """Depth and normal maps at ``out`` that colmap-pvs did not write (no provenance: COLMAP's own
    ``patch_match_stereo`` output, hours of GPU time) are renamed to ``*.bin.bak`` (``.bak.2``, ... when
    taken) before ours replace them; one WARNING per workspace says so (each file at DEBUG)."""
    if not out.depth.is_file() or out.provenance.is_file():
        return
    for path in (out.depth, out.normals):
        if path.is_file():
            logger.debug("kept %s as %s", path, move_aside(path))
    with _warned_lock:
        first = stereo_dir not in _warned_foreign
        _warned_foreign.add(stereo_dir)
    if first:
        logger.warning("%s holds depth and normal maps colmap-pvs did not write (COLMAP's?), e.g. %s: each "
                       "is kept as NAME.bin.bak beside ours", stereo_dir, out.depth.name)


def confidence_tolerance(settings: dict) -> float | None:
    """The tolerance of the calibration a pass's confidence was made with, from its ``settings``
    (``None``: uncalibrated scores)."""
    calibration = settings.get("confidence_calibration")
    return float(calibration["tolerance"]) if isinstance(calibration, dict) else None


def write_previews(ref: Reference) -> None:
    """PNG previews of ``ref``'s maps (``ref.maps`` of ``ref.stage``): depth
    (:func:`~colmap_pvs.stereo.reference.preview_path`) coloured over ``ref.depth_range``, and but for
    the dense completion normals, confidence (on the scale of ``ref.record``'s calibration) and the
    learned visibility of each of ``ref.sources`` where the maps have it. The depth and confidence
    previews have a colour bar below them."""
    stage, maps, depth_path = ref.stage, ref.maps, ref.paths[ref.stage].preview
    stem = str(depth_path)[: -len(".depth.png")]
    save_depth_preview(depth_path, maps.depth, vmin=ref.depth_range[0], vmax=ref.depth_range[1])
    if stage == "filled":
        return
    if maps.normals is not None:
        save_normal_preview(f"{stem}.normal.png", maps.normals)
    tolerance = confidence_tolerance(ref.record.settings)
    save_confidence_preview(f"{stem}.confidence.png", maps.confidence, tolerance)
    for k, src in enumerate(ref.sources if maps.visibility is not None else ()):
        save_scalar_preview(ref.paths.visibility_preview(ref.name, k, src), maps.visibility[k])


def write_missing_previews(ref: Reference, stage: Stage) -> bool:
    """The previews of ``ref``'s finished ``stage`` pass when it has none (a rerun that only adds
    ``--previews``), from its maps on disk, coloured over ``ref.depth_range`` (``None``: the 1st-99th
    percentile of its depth). Returns whether it wrote them."""
    out = ref.paths[stage]
    if out.preview.is_file():
        return False
    depth = read_depth_map(out.depth)
    depth_range = ref.depth_range
    if depth_range is None:
        valid = depth[depth > 0]
        depth_range = tuple(np.percentile(valid, [1, 99])) if valid.size else (1.0, 2.0)
    if stage == "filled":
        maps = PassMaps(depth, np.zeros_like(depth))
    else:
        maps = PassMaps(depth, read_confidence(out.confidence, depth.shape), read_normal_map(out.normals))
    sources, provenance = (), ref.provenance(stage) or {}
    if stage == "photometric":
        recorded = provenance.get("sources", [])
        vis = read_visibility(ref)
        if vis is not None and vis.shape[0] == len(recorded):
            sources = recorded
            maps = replace(maps, visibility=vis)
    settings = provenance.get("settings") if isinstance(provenance.get("settings"), dict) else {}
    write_previews(ref.with_pass(stage, maps, PassRecord(settings, {}), depth_range=depth_range,
                                 sources=sources))
    return True


def write_seeds(paths: ReferencePaths, seeds: np.ndarray, fingerprint: str) -> None:
    """The seed map, then its fingerprint (which marks it current)."""
    paths.seed_provenance.unlink(missing_ok=True)
    write_array(paths.seeds, seeds.astype(np.float32))
    payload = json.dumps({"fingerprint": fingerprint}) + "\n"
    atomic_write_bytes(paths.seed_provenance, payload.encode())


def read_confidence(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """The confidence map at ``path`` (all 0 without one), which must be ``shape``."""
    conf = read_array(path) if path.is_file() else np.zeros(shape, np.float32)
    if conf.shape != shape:
        raise MapFormatError(f"confidence map {str(path)!r} is {conf.shape}, its depth map is {shape}")
    return conf


def remove_filled(ref: Reference) -> None:
    """Remove ``ref``'s dense completion (its provenance first, so nothing half-removed looks done), and
    take what its confirmation added back out of the geometric maps."""
    remove_confirmed(ref)
    out = ref.paths["filled"]
    for path in (out.provenance, out.depth, out.confidence):
        path.unlink(missing_ok=True)


def write_filled(ref: Reference, *, previews: bool, timer: Timer) -> None:
    """Write ``ref``'s dense completion (``ref.maps`` and ``ref.record`` of its ``filled`` pass):
    confidence, provenance, then the depth (which marks it done), each beside its place first, so that a
    full disk leaves the old completion as it was; with ``previews`` its depth preview. Times ``writes``."""
    maps, record, out = ref.maps, ref.record, ref.paths["filled"]
    with timer.step("writes"):
        # The old depth goes once the new files are written, before they are renamed into place: new
        # provenance beside an old depth would look done after a crash.
        conf = encode_array(out.confidence, maps.confidence.astype(np.float32))
        write_files_together([(out.confidence, conf),
                              (out.provenance, json_bytes(provenance_record(record.settings, record.extra))),
                              (out.depth, encode_depth_map(out.depth, maps.depth))],
                             before_commit=lambda: out.depth.unlink(missing_ok=True))
    if previews:
        write_previews(ref)


# --------------------------------------------------------------------------- the confirmed completion


def pure_geometric(ref: Reference, depth_sha256: str | None = None,
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``ref``'s geometric depth, normals and confidence without the pixels a confirmation added to
    these very maps (it recorded their fingerprint and, once done, their depth file's sha256, which a
    caller that has it passes as ``depth_sha256``); ``None`` without geometric maps."""
    geo = ref.provenance("geometric")
    out = ref.paths["geometric"]
    depth_path = out.depth
    if geo is None or not depth_path.is_file():
        return None
    depth = read_depth_map(depth_path)
    normals = read_normal_map(out.normals)
    conf = read_confidence(out.confidence, depth.shape)
    record = read_json(ref.paths.confirm_provenance)
    added_path = ref.paths.confirm_map
    written = (record or {}).get("geometric_depth_sha256")  # absent while a confirmation is writing
    if (record is not None and record.get("geometric") == geo.get("fingerprint") and added_path.is_file()
            and (written is None or written == (depth_sha256 or file_sha256(depth_path)))):  # not rewritten
        added = read_depth_map(added_path) > 0
        if added.shape == depth.shape:
            depth, conf = np.where(added, 0.0, depth), np.where(added, 0.0, conf)
            normals = np.where(added[..., None], 0.0, normals)
    return depth.astype(np.float32), normals.astype(np.float32), conf.astype(np.float32)


def write_geometric(ref: Reference, depth, normals, conf) -> None:
    """``ref``'s geometric confidence, normals and depth (last), each written in place."""
    out = ref.paths["geometric"]
    write_array(out.confidence, conf.astype(np.float32))
    write_normal_map(out.normals, normals.astype(np.float32))
    write_depth_map(out.depth, depth.astype(np.float32))


def remove_confirmed(ref: Reference) -> None:
    """Take the pixels a confirmation added back out of ``ref``'s geometric maps (when they are the maps
    it added them to) and remove its record."""
    record_path, added_path = ref.paths.confirm_provenance, ref.paths.confirm_map
    if not record_path.is_file() and not added_path.is_file():
        return
    pure = pure_geometric(ref)
    if pure is not None and added_path.is_file():
        write_geometric(ref, *pure)
    record_path.unlink(missing_ok=True)
    added_path.unlink(missing_ok=True)
