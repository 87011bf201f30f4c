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

    Memory: one reference plus an LRU of ``cache_size`` source maps at their stored
    resolution; per image only a packed bit mask of used pixels is kept.

``colmap``
    ``pycolmap.stereo_fusion`` (COLMAP's own fusion) with defaults adapted to learned maps
    (:data:`COLMAP_DEFAULTS`); any ``StereoFusionOptions`` attribute can be overridden
    with ``colmap_options`` ``key=value`` strings (validated at config time).

Input (``input_type``): ``geometric`` or ``photometric`` maps (depth, normals, confidence), or for
``pvs`` the dense completion ``filled`` (no normal map: the normals are fitted to its depth,
:func:`colmap_pvs.normals.fit_normals`; its pixels of confidence 0, where nothing supported a
completed depth, are never fused; a pixel that holds its geometric map's depth, within
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
"""

from __future__ import annotations

import functools
import logging
import shutil
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from tqdm import tqdm

from .config import save_config
from .consistency import SourceMaps, backproject_pixels, match_points
from .errors import ConfigError, MapFormatError, WorkspaceError
from .geometry import rowmul
from .io.cleanup import remove_orphan_temps
from .io.colmap_tools import COLMAP_DEFAULTS, parse_colmap_options
from .io.files import make_temp_dir
from .io.images import load_image
from .io.maps import fusion_intrinsics, read_array, read_depth_map, read_normal_map
from .io.ply import commit_cloud_pair, read_point_cloud, vis_path_of, write_cloud_pair
from .io.sparse import image_indices
from .io.workspace import (
    Workspace,
    fusion_inputs_sha256,
    load_workspace,
    read_fusion_cfg,
    read_patch_match_cfg,
    record_written_output,
    set_aside_foreign_output,
    write_fusion_cfg,
)
from .normals import fit_normals
from .types import SparseModel

logger = logging.getLogger(__name__)

__all__ = ["COLMAP_DEFAULTS", "FuseConfig", "FuseResult", "fuse", "parse_colmap_options"]

DEFAULT_OUTPUT_NAME = "fused.ply"
CONFIG_SUFFIX = ".fuse_config.json"

@dataclass(frozen=True)
class FuseConfig:
    """Settings of the ``fuse`` step (the single source of its defaults and CLI flags)."""

    workspace_path: Path = field(
        metadata={"help": "COLMAP dense workspace with stereo/depth_maps and normal_maps"}
    )
    output_path: Path | None = field(
        default=None,
        metadata={"help": f"output .ply (plus .ply.vis); default: WORKSPACE/{DEFAULT_OUTPUT_NAME}"},
    )
    method: Literal["pvs", "colmap"] = field(
        default="pvs",
        metadata={"help": "pvs: our geometric-consistency fusion; colmap: pycolmap.stereo_fusion"},
    )
    input_type: Literal["auto", "geometric", "photometric", "filled"] = field(
        default="auto",
        metadata={"help": "which maps to fuse (stereo/*_maps/NAME.INPUT_TYPE.bin); filled: the dense "
                          "completion (pvs only); auto: filled for pvs where every image has a current "
                          "one, else geometric"},
    )
    num_sources: int = field(
        default=8, metadata={"help": "pvs: source views checked per reference (best first)"}
    )
    max_reproj_error: float = field(
        default=1.0, metadata={"help": "pvs: max forward-backward reprojection error, in map pixels"}
    )
    max_depth_error: float = field(
        default=0.01, metadata={"help": "pvs: max relative depth difference |d_src_in_ref - d| / d"}
    )
    min_consistent_views: int = field(
        default=2,
        metadata={"help": "pvs: minimum number of agreeing source views for a point (one fewer for "
                          "completed pixels that hold their geometric map's checked depth)"},
    )
    min_confidence: float = field(
        default=0.0,
        metadata={
            "help": "pvs: drop pixels whose confidence (P(within 5 %)) is below this, where confidence "
                    "maps exist"
        },
    )
    deduplicate: bool = field(
        default=True, metadata={"help": "pvs: source pixels that agreed are not fused again as references"}
    )
    cache_size: int = field(
        default=16, metadata={"help": "pvs: views (depth, normals, colours) kept in memory (LRU)"}
    )
    colmap_options: tuple[str, ...] = field(
        default=(),
        metadata={
            "help": "colmap: StereoFusionOptions overrides as key=value (e.g. min_num_pixels=5 "
            f"max_reproj_error=2); our defaults: {COLMAP_DEFAULTS}"
        },
    )

    def __post_init__(self) -> None:
        if self.num_sources < 1:
            raise ConfigError(f"num_sources must be >= 1, got {self.num_sources}")
        if not self.max_reproj_error > 0:
            raise ConfigError(f"max_reproj_error must be > 0, got {self.max_reproj_error}")
        if not self.max_depth_error > 0:
            raise ConfigError(f"max_depth_error must be > 0, got {self.max_depth_error}")
        if self.min_consistent_views < 0:
            raise ConfigError(f"min_consistent_views must be >= 0, got {self.min_consistent_views}")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ConfigError(f"min_confidence must be in [0, 1], got {self.min_confidence}")
        if self.cache_size < 1:
            raise ConfigError(f"cache_size must be >= 1, got {self.cache_size}")
        if self.input_type == "auto" and self.method == "colmap":  # for pvs: by the maps (fuse)
            object.__setattr__(self, "input_type", "geometric")
        if self.method == "colmap" and self.input_type == "filled":
            raise ConfigError("input_type 'filled' needs method 'pvs': COLMAP's fusion reads geometric or "
                              "photometric maps")
        object.__setattr__(self, "colmap_options", tuple(str(o) for o in self.colmap_options))
        parse_colmap_options(self.colmap_options)
        if self.colmap_options and self.method != "colmap":
            logger.warning("colmap_options are ignored with method=%r", self.method)


@dataclass
class FuseResult:
    """What :func:`fuse` wrote.

    Attributes:
        output_path / vis_path: the PLY and its ``.vis``.
        num_points: fused points.
        num_images: images whose maps were fused.
        points_per_image: ``{reference name: points it contributed}`` (``pvs`` only).
        skipped: ``{name: reason}`` for listed images without maps.
        seconds: wall time.
    """

    output_path: Path
    vis_path: Path
    method: str
    num_points: int = 0
    num_images: int = 0
    points_per_image: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0


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
    if not conf_path.is_file() and config.input_type != "filled":  # maps from before per-kind files
        conf_path = ws.confidence_map_path(name)
    filled = config.input_type == "filled"  # its confidence 0 marks the unsupported pixels
    if filled and not conf_path.is_file():
        raise MapFormatError(f"the completion of {name!r} has no confidence map {str(conf_path)!r}")
    if (config.min_confidence > 0 or filled) and conf_path.is_file():
        conf = read_array(conf_path)
        if conf.shape[:2] != (h, w):
            raise MapFormatError(f"confidence map {str(conf_path)!r} is not {w}x{h}")
        conf = conf.reshape(h, w)
        depth[~(conf >= config.min_confidence) | (filled & ~(conf > 0))] = 0.0
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
    large scenes)."""

    def __init__(self, loader: Callable[[str], _View], size: int) -> None:
        self._loader = loader
        self._size = size
        self._items: OrderedDict[str, _View] = OrderedDict()

    def get(self, name: str) -> _View:
        if name in self._items:
            self._items.move_to_end(name)
            return self._items[name]
        view = self._loader(name)
        self._items[name] = view
        while len(self._items) > self._size:
            self._items.popitem(last=False)
        return view


def _sources_for(ws: Workspace, model: SparseModel, names: list[str], num: int) -> dict[str, list[str]]:
    """The views each reference's points are checked against, at most ``num``: those of the fused
    ``names`` that ``stereo`` chose as its sources (``patch-match.cfg`` if present, else view
    selection), then the next fused views by view score. Only fused views have maps to check against:
    where the sources are no references themselves (every 3rd frame of a video a reference, its
    nearest frames its sources), the sources alone would leave a reference one view or none."""
    from .views import ViewSelectionConfig, reference_sources, select_views

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
    config: FuseConfig, ref: _View, valid: np.ndarray, srcs: list[tuple[str, _View]]
) -> _ReferencePoints:
    """The pixels of ``ref`` (those ``valid`` ``[h, w]``) that enough of its sources ``srcs`` (``(name,
    view)``) agree with (:func:`colmap_pvs.consistency.match_points`), as points averaged over the
    reference pixel and the agreeing source pixels."""
    rows, cols = np.nonzero(valid)
    d = ref.depth[rows, cols].astype(np.float64)
    x_ref = backproject_pixels(rows, cols, d, ref.K)  # reference camera frame
    sum_x = x_ref.copy()
    sum_n = ref.normals[rows, cols].astype(np.float64)
    sum_rgb = ref.rgb[rows, cols].astype(np.float64)
    count = np.zeros(len(d), dtype=np.int64)
    per_source = []
    for src_name, src in srcs:
        match = match_points(x_ref, rows, cols, ref.K, ref.cam_from_world, src,
                             max_reproj_error=config.max_reproj_error, max_depth_error=config.max_depth_error)
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
    they are not fused again when that view is the reference."""

    def __init__(self) -> None:
        self._masks: dict[str, np.ndarray] = {}

    def unused(self, name: str, valid: np.ndarray) -> np.ndarray:
        """``valid`` ``[h, w]`` less the used pixels of ``name``."""
        if name in self._masks:
            h, w = valid.shape
            valid &= ~np.unpackbits(self._masks[name], count=h * w).reshape(h, w).astype(bool)
        return valid

    def mark(self, name: str, shape: tuple[int, int], flat: np.ndarray) -> None:
        """Mark the pixels ``flat`` (row-major indices) of ``name`` (a map of ``shape``) used."""
        sh, sw = shape
        mask = (
            np.unpackbits(self._masks[name], count=sh * sw).astype(bool)
            if name in self._masks
            else np.zeros(sh * sw, dtype=bool)
        )
        mask[flat] = True
        self._masks[name] = np.packbits(mask)


class _Cloud:
    """The fused points in chunks, one per reference, with their visibility as COLMAP's ``.vis``
    numbers the images (``index_of``)."""

    def __init__(self, index_of: dict[str, int]) -> None:
        self._index_of = index_of
        self._xyz: list[np.ndarray] = []
        self._normals: list[np.ndarray] = []
        self._rgb: list[np.ndarray] = []
        self._counts: list[np.ndarray] = []
        self._vis: list[np.ndarray] = []

    def add(self, name: str, points: _ReferencePoints) -> None:
        """The points of reference ``name``, seen by it and by the sources that agreed with each."""
        self._xyz.append(points.xyz.astype(np.float32))
        self._normals.append(points.normals.astype(np.float32))
        self._rgb.append(points.rgb)
        # Visibility as a dense [P, 1 + n_sources] table of image indices (-1 = not visible).
        vis = np.full((len(points), 1 + len(points.per_source)), -1, dtype=np.int64)
        vis[:, 0] = self._index_of[name]
        for k, (src_name, point_idx, _) in enumerate(points.per_source):
            vis[point_idx, k + 1] = self._index_of[src_name]
        self._counts.append((vis >= 0).sum(axis=1))
        self._vis.append(vis[vis >= 0])

    def __len__(self) -> int:
        return sum(len(x) for x in self._xyz)

    def write(self, path: Path) -> None:
        """The PLY and its ``.vis``, together or not at all."""
        counts = np.concatenate(self._counts)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        write_cloud_pair(path, np.concatenate(self._xyz), np.concatenate(self._normals),
                         np.concatenate(self._rgb), offsets, np.concatenate(self._vis))


def _fuse_pvs(config: FuseConfig, ws: Workspace, model: SparseModel, names: list[str], result: FuseResult):
    """Our fusion: per reference, its views loaded (LRU), its unused valid pixels checked against its
    sources, the agreeing ones added to the cloud and their source pixels marked used; then the PLY and
    ``.vis`` written. A reference or source whose maps are unusable is skipped with a warning."""
    sources = _sources_for(ws, model, names, config.num_sources)
    views = _ViewCache(functools.partial(_load_view, config, ws, model), config.cache_size)
    used = _UsedPixels()
    cloud = _Cloud(image_indices(ws.sparse_dir, model))
    for name in tqdm(names, desc="fuse", unit="image"):
        try:
            ref = views.get(name)
        except (MapFormatError, WorkspaceError) as exc:
            logger.warning("fusion: skipping %s: %s", name, exc)
            result.skipped[name] = str(exc)
            continue
        srcs = []
        for src_name in sources.get(name, []):
            if src_name in result.skipped:
                continue
            try:
                srcs.append((src_name, views.get(src_name)))
            except (MapFormatError, WorkspaceError) as exc:
                logger.warning("fusion: source %s unusable: %s", src_name, exc)
        points = _fuse_reference(config, ref, used.unused(name, ref.depth > 0), srcs)
        result.points_per_image[name] = len(points)
        if not len(points):
            continue
        cloud.add(name, points)
        if config.deduplicate:
            shapes = {src_name: src.shape for src_name, src in srcs}
            for src_name, _, flat in points.per_source:
                if flat.size:
                    used.mark(src_name, shapes[src_name], flat)
    if not len(cloud):  # before anything is written or set aside: an existing cloud stays as it was
        raise _no_points_error(config, ws, names, result)
    _set_aside_foreign_cloud(result.output_path)
    cloud.write(result.output_path)
    result.num_points = len(cloud)


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
    from .io.colmap_tools import stereo_fusion

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
    from .stereo.outputs import outdated_completions

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
        _fuse_pvs(config, ws, model, names, result)
    record_written_output(out, vis_path_of(out))
    result.num_images = len(names)
    result.seconds = time.perf_counter() - start
    save_config(config, out.with_name(out.stem + CONFIG_SUFFIX), num_points=result.num_points,
                inputs_sha256=inputs_sha256)
    logger.info(
        "fusion: %d points from %d images in %.1f s -> %s", result.num_points, len(names), result.seconds, out
    )
    return result
