"""Our fusion (``fuse --method pvs``, described in :mod:`colmap_pvs.fusion`), top to bottom: the views
(maps loaded as fusion checks them, an LRU of them, each reference's sources), one reference checked
against its sources (:func:`colmap_pvs.consistency.match_points`) and averaged into points, the cloud
those points are added to; :func:`fuse_pvs` runs them in that order."""

from __future__ import annotations

import functools
import logging
from collections import Counter, OrderedDict
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ..consistency import SourceMaps, backproject_pixels, match_points
from ..errors import MapFormatError, WorkspaceError
from ..geometry import rowmul
from ..io.images import load_image
from ..io.maps import fusion_intrinsics, read_array, read_depth_map, read_normal_map
from ..io.ply import CloudPairStream
from ..io.sparse import image_indices
from ..io.workspace import Workspace, read_patch_match_cfg
from ..normals import fit_normals
from ..types import SparseModel
from .config import FuseConfig, FuseResult

logger = logging.getLogger(__name__)

__all__ = ["PointCloud", "fuse_pvs"]

# Threads that check one reference's sources (both cores; a third, the prefetch, mostly waits on reads).
MATCH_THREADS = 2
#: A completed pixel is fused only where its calibrated confidence is at least this: where it is more
#: likely right than wrong (``benchmarks/RESULTS.md``, "One confirming view for a confident completed
#: pixel"). An uncalibrated score (a checkpoint without a calibration) is no probability: there only the
#: unsupported pixels (0) are left out.
FILLED_MIN_PROBABILITY = 0.5

# --------------------------------------------------------------------------- pvs fusion: the views


@dataclass
class _View(SourceMaps):
    """One image at map resolution: the maps checked (depth ``[h, w]`` float32, 0 = not fused; camera
    normals ``[h, w, 3]`` float32; ``K``; ``cam_from_world`` ``[3, 4]``) and the colours ``[h, w, 3]``."""

    rgb: np.ndarray
    checked: np.ndarray | None = None  # [h, w] bool: pixels the geometric pass already kept (completion)

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth.shape  # type: ignore[return-value]

    @property
    def R(self) -> np.ndarray:
        return self.cam_from_world[:, :3]

    @property
    def t(self) -> np.ndarray:
        return self.cam_from_world[:, 3]


def _calibrated(ws: Workspace, name: str) -> bool:
    """Whether ``name``'s completion holds calibrated probabilities (its provenance names a
    calibration); ``False`` without a readable provenance."""
    from ..stereo.outputs import read_provenance  # imported where used, as by fuse's input choice

    record = read_provenance(ws, name, "filled")
    settings = record.get("settings") if isinstance(record, dict) else None
    return isinstance(settings, dict) and bool(settings.get("confidence_calibration"))


def _load_view(config: FuseConfig, ws: Workspace, model: SparseModel, name: str) -> _View:
    """The maps of ``name`` as fusion checks them: the depth of the pixels that may become points (finite,
    with a normal, confident enough; on the completion, supported), its normals, its image resized to
    the map, and on the completion the pixels that hold the depth the geometric pass checked.

    Raises:
        MapFormatError: a map unreadable or of another size than the depth map.
    """
    image = model.image_by_name(name)
    cam = model.camera_of(image)
    depth = read_depth_map(ws.depth_map_path(name, config.input_type))
    h, w = depth.shape
    K = fusion_intrinsics(cam.K, (cam.width, cam.height), (w, h))
    if config.input_type == "filled":  # the completion has no normal map: the local plane fit's
        normals = fit_normals(np.where(np.isfinite(depth), depth, 0.0).astype(np.float32), K)
    else:
        normals = read_normal_map(ws.normal_map_path(name, config.input_type))
    if normals.shape[:2] != (h, w):
        raise MapFormatError(
            f"normal map of {name!r} is {normals.shape[1]}x{normals.shape[0]} "
            f"but its depth map is {w}x{h}"
        )
    depth = np.where(np.isfinite(depth) & (np.abs(normals).sum(axis=2) > 0), depth, 0.0).astype(
        np.float32
    )
    conf_path = ws.confidence_map_path(name, config.input_type)
    if not conf_path.is_file() and config.input_type != "filled":
        # Back-compat (dropped in 0.3): a workspace whose maps were made before per-kind confidence files
        conf_path = ws.confidence_map_path(name)
    filled = config.input_type == "filled"  # its confidence 0 marks the unsupported pixels
    if filled and not conf_path.is_file():
        raise MapFormatError(f"the completion of {name!r} has no confidence map {str(conf_path)!r}")
    if (config.min_confidence > 0 or filled) and conf_path.is_file():
        conf = read_array(conf_path)
        if conf.shape[:2] != (h, w):
            raise MapFormatError(f"confidence map {str(conf_path)!r} is not {w}x{h}")
        conf = conf.reshape(h, w)
        floor = FILLED_MIN_PROBABILITY if filled and _calibrated(ws, name) else 0.0
        least = max(config.min_confidence, floor)
        depth[~(conf >= least) | (filled & ~(conf > 0))] = 0.0
    checked = None  # completed pixels that hold the depth the geometric map checked
    geometric_path = ws.depth_map_path(name, "geometric")
    if filled and geometric_path.is_file():
        try:
            geometric = read_depth_map(geometric_path)
        except MapFormatError as exc:
            geometric = None
            logger.warning("fusion: %s; every completed pixel of %r needs %d agreeing views", exc, name,
                           config.min_consistent_views)
        if geometric is not None and geometric.shape == (h, w):
            checked = (geometric > 0) & (np.abs(depth - geometric) <= config.max_depth_error * geometric)
        elif geometric is not None:
            logger.warning("fusion: the geometric map of %r is not %dx%d: every completed pixel needs "
                           "%d agreeing views", name, w, h, config.min_consistent_views)
    rgb = load_image(ws.image_path(name))
    if rgb.shape[:2] != (h, w):
        rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
    return _View(depth, normals.astype(np.float32), K, image.cam_from_world, rgb, checked)


class _ViewCache:
    """The views by name, loaded on first use and kept in an LRU of ``size`` (memory stays bounded on
    large scenes). :meth:`prefetch` loads the next reference's views in a background thread while the
    current one is checked (reading and decoding release the GIL): at most ``size`` views in the LRU
    plus those of one reference in flight. A view that failed to load raises in :meth:`get`, in the
    caller's thread, as without the prefetch."""

    def __init__(self, loader: Callable[[str], _View], size: int) -> None:
        self._loader = loader
        self._size = size
        self._items: OrderedDict[str, _View] = OrderedDict()
        self._pending: dict[str, Future] = {}
        self._pool: ThreadPoolExecutor | None = None

    def __len__(self) -> int:
        return len(self._items)

    def get(self, name: str) -> _View:
        if name in self._items:
            self._items.move_to_end(name)
            return self._items[name]
        pending = self._pending.pop(name, None)
        view = pending.result() if pending is not None else self._loader(name)
        self._items[name] = view
        while len(self._items) > self._size:
            self._items.popitem(last=False)
        return view

    def prefetch(self, names: list[str]) -> None:
        """Start loading those of ``names`` not held (in order); loads pending for other names are dropped."""
        wanted = set(names)
        for name in [n for n in self._pending if n not in wanted]:
            self._pending.pop(name).cancel()
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fuse-prefetch")
        for name in names:
            if name not in self._items and name not in self._pending:
                self._pending[name] = self._pool.submit(self._loader, name)

    def close(self) -> None:
        for future in self._pending.values():
            future.cancel()
        self._pending.clear()
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None


def _sources_for(ws: Workspace, model: SparseModel, names: list[str], num: int) -> dict[str, list[str]]:
    """The views each reference's points are checked against, at most ``num``: those of the fused
    ``names`` that ``stereo`` chose as its sources (``patch-match.cfg`` if present, else view
    selection), then the next fused views by view score. Only fused views have maps to check against:
    where the sources are no references themselves (every 3rd frame of a video a reference, its
    nearest frames its sources), the sources alone would leave a reference one view or none."""
    from ..views import ViewSelectionConfig, reference_sources, select_views

    selection = select_views(model, ViewSelectionConfig(num_views=num + 1))
    specs = read_patch_match_cfg(ws.patch_match_cfg) if ws.patch_match_cfg.is_file() else {}
    fused = set(names)
    out: dict[str, list[str]] = {}
    for name in names:
        entry = selection.references.get(name)
        if entry is None and specs.get(name) is None:
            out[name] = []  # not selectable (e.g. no sparse points): stereo skipped it too
            continue
        chosen = list(reference_sources(selection, name, specs.get(name), num))
        ranked = list(entry.ranked_names) if entry is not None else []
        out[name] = [s for s in dict.fromkeys(chosen + ranked) if s in fused and s != name][:num]
    return out


# --------------------------------------------------------------------------- pvs fusion: one reference


@dataclass
class _ReferencePoints:
    """The points one reference contributes (:func:`_fuse_reference`).

    Attributes:
        xyz: ``[P, 3]`` float64 world points; normals: ``[P, 3]`` unit world normals; rgb: ``[P, 3]`` uint8.
        per_source: per source ``(name, point_index [k], flat_source_pixel [k])`` for the ``k`` points it
            agreed with.
    """

    xyz: np.ndarray
    normals: np.ndarray
    rgb: np.ndarray
    per_source: list[tuple[str, np.ndarray, np.ndarray]]

    def __len__(self) -> int:
        return len(self.xyz)


def _fuse_reference(
    config: FuseConfig, ref: _View, valid: np.ndarray, srcs: list[tuple[str, _View]],
    pool: ThreadPoolExecutor | None = None,
) -> _ReferencePoints:
    """The pixels of ``ref`` (those ``valid`` ``[h, w]``) that enough of its sources ``srcs`` (``(name,
    view)``) agree with (:func:`colmap_pvs.consistency.match_points`), as points averaged over the
    reference pixel and the agreeing source pixels. With ``pool`` the sources are checked in its
    threads; their matches are summed in the sources' order all the same (the same bits)."""
    rows, cols = np.nonzero(valid)
    d = ref.depth[rows, cols].astype(np.float64)
    x_ref = backproject_pixels(rows, cols, d, ref.K)  # reference camera frame
    sum_x = x_ref.copy()
    sum_n = ref.normals[rows, cols].astype(np.float64)
    sum_rgb = ref.rgb[rows, cols].astype(np.float64)
    count = np.zeros(len(d), dtype=np.int64)
    per_source = []

    def check(src: _View):
        return match_points(x_ref, rows, cols, ref.K, ref.cam_from_world, src,
                            max_reproj_error=config.max_reproj_error, max_depth_error=config.max_depth_error)

    views = [src for _, src in srcs]
    matches = pool.map(check, views) if pool is not None and len(views) > 1 else map(check, views)
    for (src_name, src), match in zip(srcs, matches, strict=True):
        idx, rs, cs = match.index, match.rows, match.cols
        count[idx] += 1
        sum_x[idx] += match.points
        sum_n[idx] += rowmul(src.normals[rs, cs].astype(np.float64), match.rotation)
        sum_rgb[idx] += src.rgb[rs, cs]
        per_source.append((src_name, idx, rs * src.shape[1] + cs))
    need = np.full(len(d), config.min_consistent_views)
    if ref.checked is not None:  # the geometric pass's own check counts as one agreeing view
        need = np.maximum(need - ref.checked[rows, cols], 0)
    keep = count >= need
    denom = (count[keep] + 1).astype(np.float64)[:, None]
    xyz = rowmul(sum_x[keep] / denom - ref.t, ref.R)  # world
    nrm = rowmul(sum_n[keep], ref.R)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    rgb = np.clip(np.round(sum_rgb[keep] / denom), 0, 255).astype(np.uint8)
    # Re-index the per-source agreements to the kept points.
    new_index = np.cumsum(keep) - 1
    out_sources = []
    for src_name, idx, flat in per_source:
        sel = keep[idx]
        out_sources.append((src_name, new_index[idx[sel]], flat[sel]))
    return _ReferencePoints(xyz, nrm, rgb, out_sources)


# --------------------------------------------------------------------------- pvs fusion: the cloud


class _UsedPixels:
    """Per view a packed bit mask of the pixels already fused as agreeing source pixels (``deduplicate``):
    they are not fused again when that view is the reference. A view's mask is dropped once it was
    the reference for the last time (:meth:`retire`) and is not made again: only the views still to
    come as references hold one (on a path-like capture, the neighbours ahead)."""

    def __init__(self) -> None:
        self._masks: dict[str, np.ndarray] = {}
        self._retired: set[str] = set()

    def __len__(self) -> int:
        return len(self._masks)

    def unused(self, name: str, valid: np.ndarray) -> np.ndarray:
        """``valid`` ``[h, w]`` less the used pixels of ``name``."""
        if name in self._masks:
            h, w = valid.shape
            valid &= ~np.unpackbits(self._masks[name], count=h * w).reshape(h, w).astype(bool)
        return valid

    def retire(self, name: str) -> None:
        """``name`` will not be a reference again: its mask is not needed any more."""
        self._masks.pop(name, None)
        self._retired.add(name)

    def mark(self, name: str, shape: tuple[int, int], flat: np.ndarray) -> None:
        """Mark the pixels ``flat`` (row-major indices) of ``name`` (a map of ``shape``) used."""
        if name in self._retired:
            return
        sh, sw = shape
        mask = (
            np.unpackbits(self._masks[name], count=sh * sw).astype(bool)
            if name in self._masks
            else np.zeros(sh * sw, dtype=bool)
        )
        mask[flat] = True
        self._masks[name] = np.packbits(mask)


class PointCloud:
    """The fused points, streamed to disk one reference at a time (:class:`colmap_pvs.io.ply.CloudPairStream`
    beside ``path``), with their visibility as COLMAP's ``.vis`` numbers the images (``index_of``)."""

    def __init__(self, index_of: dict[str, int], path: Path) -> None:
        self._index_of = index_of
        self._stream = CloudPairStream(path)

    def add(self, name: str, points: _ReferencePoints) -> None:
        """The points of reference ``name``, seen by it and by the sources that agreed with each."""
        # Visibility as a dense [P, 1 + n_sources] table of image indices (-1 = not visible).
        vis = np.full((len(points), 1 + len(points.per_source)), -1, dtype=np.int64)
        vis[:, 0] = self._index_of[name]
        for k, (src_name, point_idx, _) in enumerate(points.per_source):
            vis[point_idx, k + 1] = self._index_of[src_name]
        counts = (vis >= 0).sum(axis=1)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self._stream.append(points.xyz.astype(np.float32), points.normals.astype(np.float32), points.rgb,
                            offsets, vis[vis >= 0])

    def __len__(self) -> int:
        return len(self._stream)

    def write(self) -> None:
        """The PLY and its ``.vis`` in place, together or not at all."""
        self._stream.commit()

    def discard(self) -> None:
        """Remove what was streamed (nothing after :meth:`write`)."""
        self._stream.discard()


def fuse_pvs(
    config: FuseConfig, ws: Workspace, model: SparseModel, names: list[str], result: FuseResult
) -> PointCloud:
    """The cloud of ``names`` (streamed to temporaries beside ``result.output_path``; :meth:`PointCloud.write`
    puts it in place): per reference, its views loaded (LRU, the next reference's prefetched), its
    unused valid pixels checked against its sources (in ``MATCH_THREADS`` threads), the agreeing ones
    added to the cloud and their source pixels marked used. A reference or source whose maps are
    unusable is skipped with a warning (in ``result.skipped``); ``result.points_per_image`` counts each
    reference's points."""
    sources = _sources_for(ws, model, names, config.num_sources)
    views = _ViewCache(functools.partial(_load_view, config, ws, model), config.cache_size)
    used = _UsedPixels()
    cloud = PointCloud(image_indices(ws.sparse_dir, model), result.output_path)
    to_come = Counter(names)  # references still to be fused, by name
    pool = ThreadPoolExecutor(MATCH_THREADS, thread_name_prefix="fuse-match") if MATCH_THREADS > 1 else None
    try:
        for i, name in enumerate(tqdm(names, desc="fuse", unit="image")):
            to_come[name] -= 1
            try:
                ref = views.get(name)
            except (MapFormatError, WorkspaceError) as exc:
                logger.warning("fusion: skipping %s: %s", name, exc)
                result.skipped[name] = str(exc)
                if not to_come[name]:
                    used.retire(name)
                continue
            srcs = []
            for src_name in sources.get(name, []):
                if src_name in result.skipped:
                    continue
                try:
                    srcs.append((src_name, views.get(src_name)))
                except (MapFormatError, WorkspaceError) as exc:
                    logger.warning("fusion: source %s unusable: %s", src_name, exc)
            if i + 1 < len(names):
                following = [names[i + 1], *sources.get(names[i + 1], [])]
                views.prefetch([n for n in following if n not in result.skipped])
            valid = used.unused(name, ref.depth > 0)
            if not to_come[name]:
                used.retire(name)
            points = _fuse_reference(config, ref, valid, srcs, pool)
            result.points_per_image[name] = len(points)
            if not len(points):
                continue
            cloud.add(name, points)
            if config.deduplicate:
                shapes = {src_name: src.shape for src_name, src in srcs}
                for src_name, _, flat in points.per_source:
                    if flat.size:
                        used.mark(src_name, shapes[src_name], flat)
    except BaseException:
        cloud.discard()
        raise
    finally:
        views.close()
        if pool is not None:
            pool.shutdown(wait=True)
    return cloud
