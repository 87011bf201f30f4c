"""What a ``stereo`` run loads once: the workspace, the network, the view selection and an image
cache (:func:`prepare_stereo`), and what each pass reports (:class:`RefOutcome`, :class:`StereoResult`)."""

from __future__ import annotations

import hashlib
import logging
import threading
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from ..confidence import Calibration, checkpoint_calibration
from ..config import replace_config
from ..errors import ConfigError, WorkspaceError
from ..geometry import sparse_depth_map
from ..io.files import file_sha256
from ..io.images import load_image, resize_image
from ..io.maps import fusion_intrinsics
from ..io.workspace import Workspace, load_workspace, read_patch_match_cfg
from ..model.runtime import resolve_device
from ..types import Image, SparseModel
from ..views import ViewSelection, ViewSelectionConfig, reference_sources, select_views
from .config import Stage, StereoConfig
from .network import base_checkpoint_path, load_stereo_model
from .reference import Reference

logger = logging.getLogger(__name__)


@dataclass
class RefOutcome:
    """What :func:`process_reference` did for one reference and pass."""

    name: str
    stage: Stage
    status: Literal["computed", "done", "skipped"]
    reason: str = ""
    seconds: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class StereoResult:
    """What :func:`run_stereo` did: processed, skipped (with reasons) and timing.

    ``processed`` / ``already_done`` are the photometric pass's, ``geometric_processed`` /
    ``geometric_done`` the geometric pass's, ``filled_processed`` / ``filled_done`` / ``filled_skipped``
    the dense completion's (``geom_fill``), ``confirm_*`` its confirmation's; ``timings`` sums seconds per
    stage over the passes; ``pass_seconds`` is the wall time of each pass; ``seconds_per_image`` is this
    run's wall time per computed reference. ``auxiliary`` lists the sources that are no reference
    (``patch-match.cfg`` lists a subset) and got photometric maps for the geometric pass.
    ``adapt_seconds`` (in all and per reference; also ``timings["adapt"]``) is the time the step above
    that made the run's ``weights`` took (0 without one), which this run's other times leave out.
    """

    workspace: Workspace
    processed: list[str] = field(default_factory=list)
    already_done: list[str] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)
    sources: dict[str, list[str]] = field(default_factory=dict)
    seconds_per_image: float = 0.0
    geometric_processed: list[str] = field(default_factory=list)
    geometric_done: list[str] = field(default_factory=list)
    geometric_skipped: dict[str, str] = field(default_factory=dict)
    filled_processed: list[str] = field(default_factory=list)
    filled_done: list[str] = field(default_factory=list)
    filled_skipped: dict[str, str] = field(default_factory=dict)
    confirm_processed: list[str] = field(default_factory=list)
    confirm_done: list[str] = field(default_factory=list)
    confirm_skipped: dict[str, str] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    pass_seconds: dict[str, float] = field(default_factory=dict)
    auxiliary: list[str] = field(default_factory=list)
    adapt_seconds: float = 0.0
    adapt_seconds_per_image: float = 0.0


def choose_references(ws: Workspace, model: SparseModel) -> dict[str, object]:
    """Reference names mapped to their source spec (``None``: automatic selection)."""
    if ws.patch_match_cfg.exists():
        specs = read_patch_match_cfg(ws.patch_match_cfg)
        for name in specs:
            if name not in model.image_ids_by_name:
                raise WorkspaceError(
                    f"{ws.patch_match_cfg}: reference image {name!r} is not in the sparse model"
                )
        return dict(specs)
    return {img.name: None for img in sorted(model.images.values(), key=lambda im: im.name)}


def patch_match_note(ws: Workspace, references: dict[str, object], num_views: int) -> str | None:
    """The warning to give once per run when ``stereo/patch-match.cfg`` decides how many sources some
    references get, not ``num_views`` (an explicit list of another length, or ``__auto__, N`` with
    ``N < num_views - 1``); ``None`` when ``num_views`` applies to every reference."""
    wanted = num_views - 1
    counts = [spec.num for spec in references.values() if spec is not None and (
        (spec.mode == "explicit" and spec.num != wanted) or (spec.mode == "auto" and spec.num < wanted))]
    if not counts:
        return None
    each = f"{counts[0]} each" if min(counts) == max(counts) else f"{min(counts)}-{max(counts)} each"
    return (f"{ws.patch_match_cfg} decides the sources of {len(counts)} of {len(references)} reference(s) "
            f"({each}), not --num_views {num_views}; to use {num_views} views rerun `colmap-pvs select-views "
            f"--workspace_path {ws.root} --num_views {num_views}`, or edit or remove that file")


def image_sparse_depth(
    model: SparseModel,
    image: Image,
    K: np.ndarray,
    height: int,
    width: int,
    id_order: np.ndarray | None = None,
) -> np.ndarray:
    """``[H, W]`` depth of the image's own sparse points projected with ``K`` (0 elsewhere).

    ``id_order`` is ``np.argsort(model.points.ids)``; pass it to avoid re-sorting per image.
    """
    if image.point3D_ids.size == 0:
        return np.zeros((height, width), dtype=np.float32)
    ids = model.points.ids
    order = np.argsort(ids, kind="stable") if id_order is None else id_order
    pos = np.searchsorted(ids, image.point3D_ids, sorter=order).clip(max=len(ids) - 1)
    rows = order[pos]
    rows = rows[ids[rows] == image.point3D_ids]
    return sparse_depth_map(model.points.xyz[rows], K, image.cam_from_world, height, width)


#: Decimals of the camera parameters and poses in the provenance: what a model written again (its
#: rotations through quaternions) changes in the last bits is no change.
RECORD_DECIMALS = 9


#: Sparse hints farther than this factor outside the image's depth range are outliers.
HINT_OUTLIER_FACTOR = 2.0


def drop_outlier_hints(sparse: np.ndarray, depth_range: tuple[float, float]) -> np.ndarray:
    """Zero the hints of ``sparse`` ``[H, W]`` (in place) that are depth outliers.

    A hint is an outlier when ``z < dmin / f`` or ``z > dmax * f`` with ``f`` =
    :data:`HINT_OUTLIER_FACTOR` (the range already carries COLMAP's 25 % stretch). Hints just outside
    the range are real surfaces more often than not (the range is the 1st-99th percentile, and near
    walls in indoor video lie below it): dropping every hint outside it made the maps less accurate
    (``benchmarks/RESULTS.md``, "Numbers moved out of the code").
    """
    f = HINT_OUTLIER_FACTOR
    sparse[(sparse < depth_range[0] / f) | (sparse > depth_range[1] * f)] = 0.0
    return sparse


# --------------------------------------------------------------------------- image cache


class ImageCache:
    """Decoded, resized ``[3, H, W]`` float32 images shared across references (thread-safe LRU).

    Each image is a source of several references; it is decoded and resized once per size. Entries
    are futures, so a prefetch in a background thread and a later request share one load.
    """

    def __init__(self, ws: Workspace, model: SparseModel, capacity: int = 16) -> None:
        self.ws, self.model, self.capacity = ws, model, capacity
        self._items: OrderedDict[tuple, Future] = OrderedDict()
        self._lock = threading.Lock()

    def _load(self, name: str, max_image_size: int, size: tuple[int, int] | None) -> np.ndarray:
        im = self.model.image_by_name(name)
        cam = self.model.camera_of(im)
        pix = load_image(self.ws.images_dir / name)
        if pix.shape[0] != cam.height or pix.shape[1] != cam.width:
            raise WorkspaceError(
                f"image {name!r} is {pix.shape[1]}x{pix.shape[0]} but its camera {cam.camera_id} says "
                f"{cam.width}x{cam.height}"
            )
        if size is None:
            small, _, _ = resize_image(pix, max_image_size)
        else:
            import cv2

            shrink = size[0] <= pix.shape[1] and size[1] <= pix.shape[0]
            small = pix if (pix.shape[1], pix.shape[0]) == size else cv2.resize(
                pix, size, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
            )
        return np.ascontiguousarray(small.transpose(2, 0, 1), dtype=np.float32) * np.float32(1.0 / 255.0)

    def future(self, name: str, max_image_size: int, size: tuple[int, int] | None = None,
               executor: ThreadPoolExecutor | None = None) -> Future:
        """The image at its own inference size (``size=None``) or resized to ``size = (W, H)``."""
        key = (name, max_image_size, size)
        with self._lock:
            fut = self._items.get(key)
            if fut is not None:
                self._items.move_to_end(key)
                return fut
            fut = Future()
            self._items[key] = fut
            while len(self._items) > self.capacity:
                self._items.popitem(last=False)

        def work() -> None:
            try:
                fut.set_result(self._load(name, max_image_size, size))
            except BaseException as exc:  # re-raised by .result() in the caller
                fut.set_exception(exc)
                with self._lock:
                    self._items.pop(key, None)

        if executor is None:
            work()
        else:
            executor.submit(work)
        return fut

    def get(self, name: str, max_image_size: int, size: tuple[int, int] | None = None) -> np.ndarray:
        return self.future(name, max_image_size, size).result()


#: References whose geometric or completion pass runs at once, in threads: their numpy work releases the
#: GIL in its array loops, so two keep two cores busy. The confirmation stays one at a time (it rewrites
#: the geometric maps that the other references' confirmations read).
REFERENCE_THREADS = 2
#: Above this map size (``max_image_size`` squared, pixels) one reference at a time: a second one holds
#: its own checks' arrays (several times the map's size per source), which large maps cannot afford.
REFERENCE_THREADS_MAX_PIXELS = 1024 * 1024


def reference_threads(config: StereoConfig, stage: Stage) -> int:
    """How many references ``stage`` runs at once: :data:`REFERENCE_THREADS` for the geometric pass
    (unless it runs the network again, ``geom_reestimate``) and the completion, at most torch's thread
    count (``--threads``), for maps up to :data:`REFERENCE_THREADS_MAX_PIXELS`; 1 otherwise."""
    size = config.photometric.max_image_size
    if (stage not in ("geometric", "filled") or (stage == "geometric" and config.geometric.reestimate)
            or size <= 0 or size * size > REFERENCE_THREADS_MAX_PIXELS):
        return 1
    return max(1, min(REFERENCE_THREADS, torch.get_num_threads()))


# --------------------------------------------------------------------------- context


@dataclass
class StereoContext:
    """Everything loaded once per run (or once per Ray worker): see :func:`prepare_stereo`."""

    config: StereoConfig
    workspace: Workspace
    sparse: SparseModel
    net: torch.nn.Module
    checkpoint_path: Path
    checkpoint_sha256: str
    calibration: Calibration
    device: torch.device
    selection: ViewSelection
    references: dict[str, object]
    id_order: np.ndarray
    images: ImageCache
    loader: ThreadPoolExecutor | None = None
    writer: ThreadPoolExecutor | None = None
    pending_writes: list[Future] = field(default_factory=list)
    seed_cache: OrderedDict = field(default_factory=OrderedDict)  # name -> (fingerprint, Checked)
    image_hashes: dict[str, str] = field(default_factory=dict)  # name -> sha256 of its file, once a run
    reference_cache: dict[str, Reference] = field(default_factory=dict)  # name -> its Reference, once a run
    _hash_lock: threading.Lock = field(default_factory=threading.Lock)
    seed_lock: threading.Lock = field(default_factory=threading.Lock)  # guards seed_cache and _check_locks
    _check_locks: dict[str, threading.Lock] = field(default_factory=dict)

    def reference(self, name: str) -> Reference:
        """Image ``name``'s :class:`~colmap_pvs.stereo.reference.Reference` in this run (made once: its
        files and its view-selection depth range, ``None`` without an entry), from which every pass
        reads its files and that of its sources."""
        found = self.reference_cache.get(name)
        if found is None:
            entry = self.selection.references.get(name)
            found = self.reference_cache.setdefault(name, Reference.of(
                self.workspace, name, depth_range=None if entry is None else entry.depth_range))
        return found

    def check_lock(self, name: str) -> threading.Lock:
        """The lock held while image ``name``'s photometric maps are checked against its sources, so that
        references run in threads check each image once (the others then find it in ``seed_cache``)."""
        with self.seed_lock:
            return self._check_locks.setdefault(name, threading.Lock())

    def image_sha256(self, name: str) -> str:
        """sha256 of image ``name``'s file (hashed once per run; the photometric provenance records it)."""
        with self._hash_lock:
            found = self.image_hashes.get(name)
        if found is None:
            path = self.workspace.images_dir / name
            try:
                found = file_sha256(path)
            except OSError as exc:
                raise WorkspaceError(f"cannot read image {str(path)!r}: {exc}") from None
            with self._hash_lock:
                self.image_hashes[name] = found
        return found

    def camera_record(self, name: str) -> dict:
        """Image ``name``'s camera as the provenance records it: model, size and parameters (to
        :data:`RECORD_DECIMALS`: a model written again, with its poses through quaternions, is the same)."""
        cam = self.sparse.camera_of(self.sparse.image_by_name(name))
        return {"model": cam.model, "size": [int(cam.width), int(cam.height)],
                "params": [round(float(v), RECORD_DECIMALS) for v in np.asarray(cam.params).ravel()]}

    def pose_record(self, name: str) -> list[float]:
        """Image ``name``'s ``cam_from_world`` ``[R | t]``, row by row, to :data:`RECORD_DECIMALS`."""
        pose = np.asarray(self.sparse.image_by_name(name).cam_from_world).ravel()
        return [round(float(v), RECORD_DECIMALS) + 0.0 for v in pose]  # + 0.0: no -0.0

    def sparse_points_sha256(self, name: str) -> str:
        """sha256 of the ids and positions of the sparse points image ``name`` observes (its hints)."""
        image = self.sparse.image_by_name(name)
        ids = self.sparse.points.ids
        pos = np.searchsorted(ids, image.point3D_ids, sorter=self.id_order).clip(max=max(len(ids) - 1, 0))
        rows = self.id_order[pos] if len(ids) else pos
        rows = rows[ids[rows] == image.point3D_ids] if len(ids) else rows[:0]
        digest = hashlib.sha256(np.ascontiguousarray(ids[rows], dtype=np.int64).tobytes())
        digest.update(np.ascontiguousarray(self.sparse.points.xyz[rows], dtype=np.float64).tobytes())
        return digest.hexdigest()

    def sources_of(self, name: str) -> tuple[list[str] | None, str]:
        """The sources of reference ``name``, or ``(None, reason)`` when it must be skipped."""
        entry = self.selection.references.get(name)
        if entry is None:
            reason = next((sk.reason for sk in self.selection.skipped if sk.name == name), "not selectable")
            return None, reason
        sources = list(reference_sources(self.selection, name, self.references.get(name),
                                         self.config.photometric.num_views - 1))
        if len(sources) < self.config.min_sources:
            return None, (f"only {len(sources)} source view(s) share points with it "
                          f"(need {self.config.min_sources})")
        return sources, ""

    def sources_origin(self, name: str) -> str:
        """What decided the sources of ``name``: its ``patch-match.cfg`` entry or the view selection."""
        spec = self.references.get(name)
        if spec is None:
            return f"view selection (num_views {self.config.photometric.num_views})"
        entry = {"explicit": "its source list", "auto": f"__auto__, {spec.num}", "all": "__all__"}[spec.mode]
        return f"stereo/patch-match.cfg ({entry})"

    def map_size(self, name: str) -> tuple[int, int]:
        """``(W, H)`` of ``name``'s maps at this run's ``max_image_size``."""
        cam = self.sparse.camera_of(self.sparse.image_by_name(name))
        longest = max(cam.width, cam.height)
        m = self.config.photometric.max_image_size
        if m <= 0 or longest <= m:
            return cam.width, cam.height
        s = m / longest
        return (max(1, min(m, int(np.floor(cam.width * s + 0.5)))),
                max(1, min(m, int(np.floor(cam.height * s + 0.5)))))

    def network_size(self, name: str) -> tuple[int, int]:
        """``(W, H)`` the network runs at for ``name``: ``network_scale`` times its map size, its
        longest side not below ``min(network_min_size, the map's)``."""
        w, h = self.map_size(name)
        cfg = self.config.photometric
        s = max(cfg.network_scale, min(1.0, cfg.network_min_size / max(w, h)))
        if s == 1.0:
            return w, h
        return max(16, int(np.floor(w * s + 0.5))), max(16, int(np.floor(h * s + 0.5)))

    def map_K(self, name: str, size: tuple[int, int]) -> np.ndarray:
        cam = self.sparse.camera_of(self.sparse.image_by_name(name))
        return fusion_intrinsics(cam.K, (cam.width, cam.height), size)

    def prefetch(self, name: str) -> None:
        """Start decoding ``name``'s reference and source images in the loader thread."""
        if self.loader is None:
            return
        sources, _ = self.sources_of(name)
        if sources is None:
            return
        size = self.network_size(name)
        for n in [name, *sources]:
            self.images.future(n, self.config.photometric.max_image_size, size, executor=self.loader)
        if size != self.map_size(name):  # the upsampling's guide
            self.images.future(name, self.config.photometric.max_image_size, self.map_size(name),
                               executor=self.loader)

    def submit_write(self, fn, *args, **kwargs) -> None:
        """Run a write job in the writer thread (synchronously when there is none)."""
        if self.writer is None:
            fn(*args, **kwargs)
        else:
            self.pending_writes.append(self.writer.submit(fn, *args, **kwargs))

    def flush(self) -> None:
        """Wait for every pending write; re-raises the first failure."""
        pending, self.pending_writes = self.pending_writes, []
        for fut in pending:
            fut.result()

    def close(self) -> None:
        try:
            self.flush()
        finally:
            for ex in (self.loader, self.writer):
                if ex is not None:
                    ex.shutdown(wait=True)
            self.loader = self.writer = None


def check_weights(config: StereoConfig, weights: Path | None) -> None:
    """Refuse ``adapt_steps > 0`` without the adapted ``weights``: this step runs a network, adapts none."""
    if config.adapt.steps > 0 and weights is None:
        raise ConfigError(
            f"adapt_steps={config.adapt.steps}: run_stereo adapts no network; call "
            "colmap_pvs.adapt.run_adapted_stereo(config) (what `colmap-pvs stereo` runs), which adapts "
            "the checkpoint and then calls run_stereo with its weights"
        )


def prepare_stereo(config: StereoConfig, *, background_io: bool = False,
                   weights: Path | None = None) -> StereoContext:
    """Load the workspace, the network and the view selection once.

    ``background_io``: decode the next references' images and write finished maps in two background
    threads (:meth:`StereoContext.prefetch`, :meth:`StereoContext.flush`); call
    :meth:`StereoContext.close` at the end. ``weights``: see :func:`~colmap_pvs.stereo.run_stereo`.
    """
    check_weights(config, weights)
    ws, model_sparse = load_workspace(config.workspace_path)
    device = resolve_device(config.device)
    if config.threads > 0:
        torch.set_num_threads(config.threads)
    run_config = config if weights is None else replace_config(config, checkpoint=weights)
    net, ckpt_path, _meta = load_stereo_model(run_config, device)
    ckpt_sha256 = file_sha256(ckpt_path)  # in every pass's provenance
    base = base_checkpoint_path(config)  # its calibration, also for other weights (not refitted)
    calibration = checkpoint_calibration(base, ckpt_sha256 if weights is None else file_sha256(base))
    selection: ViewSelection = select_views(
        model_sparse,
        ViewSelectionConfig(num_views=config.photometric.num_views,
                            depth_near_factor=config.photometric.depth_near_factor),
    )
    if config.photometric.depth_range:  # one range for all (COLMAP's depth_min/depth_max)
        fixed = tuple(config.photometric.depth_range)
        selection = replace(selection, references={
            name: replace(entry, depth_range=fixed) for name, entry in selection.references.items()
        })
    refs = choose_references(ws, model_sparse)
    return StereoContext(
        config=config,
        workspace=ws,
        sparse=model_sparse,
        net=net,
        checkpoint_path=ckpt_path,
        checkpoint_sha256=ckpt_sha256,
        calibration=calibration,
        device=device,
        selection=selection,
        references=refs,
        id_order=np.argsort(model_sparse.points.ids, kind="stable"),
        images=ImageCache(ws, model_sparse, capacity=max(16, 3 * config.photometric.num_views)),
        loader=ThreadPoolExecutor(1, thread_name_prefix="stereo-load") if background_io else None,
        writer=ThreadPoolExecutor(1, thread_name_prefix="stereo-write") if background_io else None,
    )
