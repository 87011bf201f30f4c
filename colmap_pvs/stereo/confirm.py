"""The confirmed completion (the last step of ``geom_fill``), once every completion exists.

A completed pixel (:mod:`colmap_pvs.stereo.filled`) that other references' completions agree with, as
``fuse`` checks them (:data:`CONFIRM_MIN_VIEWS` views within :data:`CONFIRM_MAX_REPROJ_ERROR` px
forward-backward and :data:`CONFIRM_MAX_DEPTH_ERROR` in depth), joins the geometric maps, which is
what COLMAP's own ``stereo_fusion`` reads: on hololens-dev its cloud went from F1 60.5 to 64.0 at 5 cm,
on colmap-statue its points and mesh grew by 2-3 % (``benchmarks/RESULTS.md``). Such a pixel takes
the completion's depth, a normal fitted to it and the completion's confidence.

The pixels a run added are kept in ``stereo/confirm_maps/NAME.bin`` (their depth, 0 elsewhere) with the
geometric maps' fingerprint in ``stereo/provenance/NAME.confirm.json``, so that a later run that
changes the completions takes them out of the geometric maps again before it adds its own
(:func:`remove_confirmed`; also when the completion is switched off).
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..consistency import check_consistency
from ..io.files import atomic_write_bytes, file_sha256
from ..io.maps import (
    read_array,
    read_depth_map,
    read_normal_map,
    write_array,
    write_depth_map,
    write_normal_map,
)
from ..io.workspace import Workspace
from ..normals import fit_normals
from .config import FORMAT_VERSIONS
from .context import RefOutcome, StereoContext
from .geometric import load_maps
from .outputs import fingerprint, read_provenance

#: Other references whose completions must agree with a completed pixel (``fuse``'s default).
CONFIRM_MIN_VIEWS = 2
#: Forward-backward reprojection error (map pixels) and relative depth error of that agreement.
CONFIRM_MAX_REPROJ_ERROR = 1.0
CONFIRM_MAX_DEPTH_ERROR = 0.01


def confirm_map_path(ws: Workspace, name: str) -> Path:
    """``stereo/confirm_maps/NAME.bin``: the depth of the pixels the confirmation added to ``name``'s
    geometric maps, 0 elsewhere."""
    ws.depth_map_path(name, "geometric")  # validates name
    return ws.stereo_dir / "confirm_maps" / f"{name}.bin"


def confirm_provenance_path(ws: Workspace, name: str) -> Path:
    ws.depth_map_path(name, "geometric")  # validates name
    return ws.stereo_dir / "provenance" / f"{name}.confirm.json"


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _write_json(path: Path, payload: dict) -> None:
    atomic_write_bytes(path, (json.dumps(payload, indent=1) + "\n").encode())


def _pure_geometric(ws: Workspace, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``name``'s geometric depth, normals and confidence without the pixels a confirmation added to
    these very maps (it recorded their fingerprint); ``None`` without geometric maps."""
    geo = read_provenance(ws, name, "geometric")
    depth_path = ws.depth_map_path(name, "geometric")
    if geo is None or not depth_path.is_file():
        return None
    depth = read_depth_map(depth_path)
    normals = read_normal_map(ws.normal_map_path(name, "geometric"))
    conf_path = ws.confidence_map_path(name, "geometric")
    conf = read_array(conf_path).reshape(depth.shape) if conf_path.is_file() else np.zeros_like(depth)
    record = _read_json(confirm_provenance_path(ws, name))
    added_path = confirm_map_path(ws, name)
    if record is not None and record.get("geometric") == geo.get("fingerprint") and added_path.is_file():
        added = read_depth_map(added_path) > 0
        if added.shape == depth.shape:
            depth, conf = np.where(added, 0.0, depth), np.where(added, 0.0, conf)
            normals = np.where(added[..., None], 0.0, normals)
    return depth.astype(np.float32), normals.astype(np.float32), conf.astype(np.float32)


def _write_geometric(ws: Workspace, name: str, depth, normals, conf) -> None:
    write_array(ws.confidence_map_path(name, "geometric"), conf.astype(np.float32))
    write_normal_map(ws.normal_map_path(name, "geometric"), normals.astype(np.float32))
    write_depth_map(ws.depth_map_path(name, "geometric"), depth.astype(np.float32))


def remove_confirmed(ws: Workspace, name: str) -> None:
    """Take the pixels a confirmation added back out of ``name``'s geometric maps (when they are the maps
    it added them to) and remove its record."""
    record_path, added_path = confirm_provenance_path(ws, name), confirm_map_path(ws, name)
    if not record_path.is_file() and not added_path.is_file():
        return
    pure = _pure_geometric(ws, name)
    if pure is not None and added_path.is_file():
        _write_geometric(ws, name, *pure)
    record_path.unlink(missing_ok=True)
    added_path.unlink(missing_ok=True)


def confirm_pass(ctx: StereoContext, name: str) -> RefOutcome:
    """Add to ``name``'s geometric maps the completed pixels that the completions of its best views by
    score among this run's references (up to ``geom_num_sources``) confirm."""
    cfg, ws = ctx.config, ctx.workspace
    start = time.perf_counter()
    geo, filled = read_provenance(ws, name, "geometric"), read_provenance(ws, name, "filled")
    if geo is None or filled is None or not ws.depth_map_path(name, "filled").is_file():
        remove_confirmed(ws, name)
        return RefOutcome(name, "confirm", "skipped", "it has no completion")
    entry = ctx.selection.references.get(name)
    refs = set(ctx.references)
    sources: dict[str, str] = {}
    for s in entry.ranked_names if entry is not None else ():
        if len(sources) >= max(1, cfg.geometric.num_sources):
            break
        prov = read_provenance(ws, s, "filled") if s in refs and s != name else None
        if prov is not None and ws.depth_map_path(s, "filled").is_file():
            sources[s] = prov["fingerprint"]
    settings = {"format_version": FORMAT_VERSIONS["confirm"], "min_views": CONFIRM_MIN_VIEWS,
                "max_reproj_error": CONFIRM_MAX_REPROJ_ERROR, "max_depth_error": CONFIRM_MAX_DEPTH_ERROR,
                "geometric": geo["fingerprint"], "filled": filled["fingerprint"], "sources": sources}
    record = _read_json(confirm_provenance_path(ws, name))
    geometric_path = ws.depth_map_path(name, "geometric")
    if (not cfg.overwrite and record is not None and record.get("fingerprint") == fingerprint(settings)
            and confirm_map_path(ws, name).is_file() and geometric_path.is_file()
            and record.get("geometric_depth_sha256") == file_sha256(geometric_path)):  # not rewritten since
        return RefOutcome(name, "confirm", "done", seconds=time.perf_counter() - start)
    t0 = time.perf_counter()
    depth, normals, conf = _pure_geometric(ws, name)
    ref = load_maps(ctx, name, "filled", normals=False)
    fconf = read_array(ws.confidence_map_path(name, "filled")).reshape(ref.depth.shape)
    supported = np.where(fconf > 0, ref.depth, 0.0).astype(np.float32)
    srcs = []
    for s in sources:  # their supported pixels only
        src = load_maps(ctx, s, "filled", normals=False)
        sconf = read_array(ws.confidence_map_path(s, "filled")).reshape(src.depth.shape)
        srcs.append(replace(src, depth=np.where(sconf > 0, src.depth, 0.0).astype(np.float32)))
    timings = {"load": time.perf_counter() - t0}
    t0 = time.perf_counter()
    candidates = np.where(depth > 0, 0.0, supported).astype(np.float32)
    added = np.zeros(depth.shape, bool)
    if srcs and (candidates > 0).any():
        res = check_consistency(candidates, None, ref.K, ref.cam_from_world, srcs,
                                max_reproj_error=CONFIRM_MAX_REPROJ_ERROR,
                                max_depth_error=CONFIRM_MAX_DEPTH_ERROR, workers=2)
        added = (candidates > 0) & (res.agree.sum(0) >= CONFIRM_MIN_VIEWS)
    fitted = fit_normals(supported, ref.K)
    added &= np.any(fitted != 0, axis=-1)
    timings["check"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    # Crash-safe order: first a record that covers the old and the new pixels (on these geometric
    # maps), then the maps, then the exact record.
    old_path = confirm_map_path(ws, name)
    old = read_depth_map(old_path) if old_path.is_file() and record is not None and record.get(
        "geometric") == geo["fingerprint"] else np.zeros_like(depth)
    old = old if old.shape == depth.shape else np.zeros_like(depth)
    old_path.parent.mkdir(parents=True, exist_ok=True)
    write_depth_map(old_path, np.where(added, supported, old).astype(np.float32))
    _write_json(confirm_provenance_path(ws, name), {"fingerprint": None, "geometric": geo["fingerprint"]})
    _write_geometric(ws, name, np.where(added, supported, depth), np.where(added[..., None], fitted, normals),
                     np.where(added, fconf, conf))
    write_depth_map(old_path, np.where(added, supported, 0.0).astype(np.float32))
    _write_json(confirm_provenance_path(ws, name), {
        "fingerprint": fingerprint(settings), "geometric": geo["fingerprint"], "settings": settings,
        "geometric_depth_sha256": file_sha256(geometric_path), "added_fraction": float(added.mean())})
    timings["writes"] = time.perf_counter() - t0
    return RefOutcome(name, "confirm", "computed", seconds=time.perf_counter() - start, timings=timings)
