"""The ``stereo`` step: PVSNet depth and normal maps for every image of a COLMAP workspace.

A drop-in replacement for COLMAP's ``patch_match_stereo``: it writes
``stereo/depth_maps/NAME.{geometric,photometric}.bin`` and
``stereo/normal_maps/NAME.{geometric,photometric}.bin`` plus ``stereo/fusion.cfg``, so
COLMAP's own ``stereo_fusion`` runs on the result unchanged.

As in COLMAP, the reference images are those listed in ``stereo/patch-match.cfg``
when it exists (explicit source lists, ``__auto__, N`` and ``__all__`` are all
understood), otherwise every registered image with sparse points.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from tqdm import tqdm

from .config import replace_config, save_config
from .errors import CheckpointError, ColmapPVSError, ConfigError, WorkspaceError
from .geometry import sparse_depth_map, to_homogeneous
from .io.cleanup import remove_orphan_temps
from .io.images import load_image, resize_image
from .io.maps import (
    fusion_intrinsics,
    save_depth_preview,
    save_normal_preview,
    save_scalar_preview,
    write_array,
    write_depth_map,
    write_normal_map,
)
from .io.workspace import Workspace, load_workspace, read_patch_match_cfg, write_fusion_cfg
from .model.runtime import check_memory_budget
from .normals import depth_to_normals
from .types import Image, SparseModel
from .views import ViewSelection, ViewSelectionConfig, reference_sources, select_views

logger = logging.getLogger(__name__)

DEFAULT_CHECKPOINT = Path(__file__).resolve().parent / "weights" / "pvsnet_default.pt"
CONFIG_FILENAME = "colmap_pvs_stereo.json"


@dataclass(frozen=True)
class StereoConfig:
    """Settings of the ``stereo`` step (the single source of its defaults and CLI flags)."""

    workspace_path: Path = field(metadata={"help": "COLMAP dense workspace (images/, sparse/, stereo/)"})
    num_views: int = field(default=5, metadata={"help": "views per reference: reference + N-1 sources"})
    max_image_size: int = field(
        default=640, metadata={"help": "longest image side for inference; <= 0 keeps full size"}
    )
    checkpoint: Path | None = field(
        default=None, metadata={"help": "model checkpoint (.pt); default: the shipped checkpoint"}
    )
    device: Literal["auto", "cpu", "cuda"] = field(default="auto", metadata={"help": "torch device"})
    overwrite: bool = field(default=False, metadata={"help": "recompute images whose maps already exist"})
    min_confidence: float = field(
        default=0.3, metadata={"help": "pixels with confidence below this are set invalid (depth 0)"}
    )
    sparse_guidance: Literal["checkpoint", "on", "off"] = field(
        default="checkpoint",
        metadata={"help": "modulate the cost volume around projected sparse points (Guided Stereo)"},
    )
    sparse_prior: Literal["checkpoint", "on", "off"] = field(
        default="checkpoint",
        metadata={
            "help": "centre the coarse depth hypotheses on the interpolated sparse points "
            "(off: the image's global depth range everywhere)"
        },
    )
    previews: bool = field(
        default=False, metadata={"help": "write PNG previews of depth, normals, confidence, visibility"}
    )
    threads: int = field(default=0, metadata={"help": "torch CPU threads; 0 keeps torch's default"})
    min_sources: int = field(default=1, metadata={"help": "skip references with fewer sources"})
    adapt_steps: int = field(
        default=0,
        metadata={
            "help": "test-time adaptation: fine-tune a copy of the network for this many steps on the "
            "workspace's own images (self-supervised) before inference; 0 = off"
        },
    )
    adapt_max_seconds: float = field(
        default=0.0, metadata={"help": "test-time adaptation: time limit in seconds (0 = none)"}
    )
    adapt_lr: float = field(default=1e-4, metadata={"help": "test-time adaptation: learning rate"})
    adapt_seed: int = field(default=0, metadata={"help": "test-time adaptation: seed"})
    # Scale-out (colmap_pvs.distributed; README "Scale out on Ray").
    backend: Literal["local", "ray"] = field(
        default="local", metadata={"help": "local: this process; ray: one task per image on a Ray cluster"}
    )
    ray_address: str = field(
        default="", metadata={"help": "ray: empty starts a local Ray; 'auto' or HOST:PORT joins a cluster"}
    )
    ray_workers: int = field(default=0, metadata={"help": "ray: worker actors; 0: fill the CPUs"})
    ray_worker_threads: int = field(default=1, metadata={"help": "ray: torch threads (and CPUs) per worker"})
    ray_worker_memory: float = field(
        default=0.0, metadata={"help": "ray: GiB of memory Ray reserves per worker when placing it; 0: none"}
    )
    ray_max_retries: int = field(
        default=3, metadata={"help": "ray: times a reference is retried after its worker died"}
    )
    ray_task_timeout: float = field(
        default=0.0, metadata={"help": "ray: seconds after which a reference's worker is killed and the "
                               "reference retried; 0: no limit"}
    )
    # issue 11: the field COLMAP's --PatchMatchStereo.geom_consistency maps to (its pass: issue 13).
    geom_consistency: bool = field(
        default=True,
        metadata={"help": "geometric-consistency pass (COLMAP's PatchMatchStereo.geom_consistency)"},
    )

    def __post_init__(self) -> None:  # issue 11: bad values are refused where they enter
        from .config import check_range

        check_range("num_views", self.num_views, low=2)
        check_range("min_confidence", self.min_confidence, low=0.0, high=1.0)
        check_range("threads", self.threads, low=0)
        check_range("min_sources", self.min_sources, low=1)
        check_range("adapt_steps", self.adapt_steps, low=0)
        check_range("adapt_max_seconds", self.adapt_max_seconds, low=0.0)
        for name, low in (("ray_workers", 0), ("ray_worker_threads", 1), ("ray_worker_memory", 0.0),
                          ("ray_max_retries", 0), ("ray_task_timeout", 0.0)):
            check_range(name, getattr(self, name), low=low)
        if 0 < self.max_image_size < 16:
            raise ConfigError(f"max_image_size must be <= 0 (full size) or >= 16, got {self.max_image_size}")


@dataclass
class StereoResult:
    """What :func:`run_stereo` did: processed, skipped (with reasons) and timing."""

    workspace: Workspace
    processed: list[str] = field(default_factory=list)
    already_done: list[str] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)
    sources: dict[str, list[str]] = field(default_factory=dict)
    seconds_per_image: float = 0.0
    adapt_seconds: float = 0.0
    adapt_seconds_per_image: float = 0.0


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA when available."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ColmapPVSError("--device cuda was requested but torch.cuda.is_available() is False")
    return torch.device(name)


def load_stereo_model(config: StereoConfig, device: torch.device):
    """Load the checkpoint (``weights_only=True``) and apply the config's overrides."""
    from .model import PVSNet, load_checkpoint

    path = Path(config.checkpoint) if config.checkpoint is not None else DEFAULT_CHECKPOINT
    if config.checkpoint is None and not path.exists():
        raise CheckpointError(
            f"no trained default checkpoint is shipped at {str(path)!r}; pass --checkpoint PATH "
            "(random weights never produce maps)"
        )
    model, meta = load_checkpoint(path, map_location="cpu")
    # Switches that add no parameters can be flipped on a trained model.
    requested = {"sparse_guidance": config.sparse_guidance, "sparse_prior": config.sparse_prior}
    changes = {
        name: value == "on"
        for name, value in requested.items()
        if value != "checkpoint" and getattr(model.config, name) != (value == "on")
    }
    if changes:
        state = model.state_dict()
        model = PVSNet(replace_config(model.config, **changes))
        model.load_state_dict(state)
    model.eval().to(device)
    return model, path, meta


def adapt_config(config: StereoConfig):
    """The :class:`~colmap_pvs.adapt.AdaptConfig` of a stereo run's ``adapt_*`` settings."""
    from .adapt import AdaptConfig

    return AdaptConfig(
        steps=config.adapt_steps,
        max_seconds=config.adapt_max_seconds,
        lr=config.adapt_lr,
        seed=config.adapt_seed,
        num_views=config.num_views,
        threads=config.threads,
    )


def _adapt(config: StereoConfig, ws: Workspace, base: Path, device: torch.device):
    """Test-time adaptation of ``base`` on the workspace; returns ``(net, adapted path, seconds)``."""
    from .adapt import adapt_checkpoint

    done = adapt_checkpoint(ws.root, ws.stereo_dir, base, adapt_config(config))
    net, path, _ = load_stereo_model(replace_config(config, checkpoint=done.checkpoint), device)
    logger.info(
        "test-time adaptation: %d steps, %.1f s (%s)", done.steps, done.seconds,
        "reused" if done.reused else "computed",
    )
    return net, path, done.seconds


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


def _sparse_depth_map(
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


def drop_outlier_hints(sparse: np.ndarray, depth_range: tuple[float, float], config) -> np.ndarray:
    """Zero the hints of ``sparse`` ``[H, W]`` (in place) that are depth outliers.

    A hint is an outlier when it lies more than ``config.depth_outlier_min_factor`` (3) outside the
    image's depth range: ``z < dmin / f`` or ``z > dmax * f``. Hints just outside the range are real
    surfaces more often than not (the range is the 1st-99th percentile, and near walls in indoor
    video lie below it): dropping every hint outside it raised hololens-dev MAE from 212 to 219 mm.
    """
    f = config.depth_outlier_min_factor
    sparse[(sparse < depth_range[0] / f) | (sparse > depth_range[1] * f)] = 0.0
    return sparse


def _prepare_views(ws: Workspace, model: SparseModel, names: list[str], max_image_size: int):
    """Load the reference and sources, resized to the reference's inference size.

    Returns images ``[N, 3, H, W]`` float32, intrinsics ``[N, 3, 3]`` and poses ``[N, 4, 4]``.
    Each source is resized to the reference's ``(H, W)`` with its own exact scale, so
    sources of slightly different size are fine. Intrinsics follow COLMAP's MVS
    convention (:func:`colmap_pvs.io.maps.fusion_intrinsics`), as COLMAP's patch-match does.
    """
    ref_img = load_image(ws.images_dir / names[0])
    ref_small, _, _ = resize_image(ref_img, max_image_size)
    height, width = ref_small.shape[:2]
    images, Ks, poses = [], [], []
    for i, name in enumerate(names):
        im = model.image_by_name(name)
        cam = model.camera_of(im)
        pix = ref_img if i == 0 else load_image(ws.images_dir / name)
        if pix.shape[0] != cam.height or pix.shape[1] != cam.width:
            raise WorkspaceError(
                f"image {name!r} is {pix.shape[1]}x{pix.shape[0]} but its camera {cam.camera_id} says "
                f"{cam.width}x{cam.height}"
            )
        if i == 0:
            small = ref_small
        else:
            import cv2

            small = cv2.resize(pix, (width, height), interpolation=cv2.INTER_AREA)
        images.append(small.astype(np.float32).transpose(2, 0, 1) / 255.0)
        # COLMAP's fusion reads map pixel (col, row) along K_s^-1 [col, row, 1]; see CONVENTIONS.md.
        Ks.append(fusion_intrinsics(cam.K, (cam.width, cam.height), (width, height)))
        poses.append(to_homogeneous(im.cam_from_world))
    return np.stack(images), np.stack(Ks), np.stack(poses)


def _is_done(ws: Workspace, name: str) -> bool:
    return ws.depth_map_path(name, "geometric").exists() and ws.normal_map_path(name, "geometric").exists()


def _write_outputs(
    ws: Workspace, name: str, depth: np.ndarray, normals: np.ndarray, confidence: np.ndarray
) -> None:
    # Confidence and normals first, the geometric depth map last: it marks the image as done.
    write_array(ws.confidence_map_path(name), confidence.astype(np.float32))
    for kind in ("photometric", "geometric"):
        write_normal_map(ws.normal_map_path(name, kind), normals)
    write_depth_map(ws.depth_map_path(name, "photometric"), depth)
    write_depth_map(ws.depth_map_path(name, "geometric"), depth)


def _write_previews(ws: Workspace, name: str, depth, normals, confidence, visibility, sources, dr) -> None:
    out = ws.stereo_dir / "previews"
    save_depth_preview(out / f"{name}.depth.png", depth, vmin=dr[0], vmax=dr[1])
    save_normal_preview(out / f"{name}.normal.png", normals)
    save_scalar_preview(out / f"{name}.confidence.png", confidence)
    for k, src in enumerate(sources):
        save_scalar_preview(out / f"{name}.visibility.{k:02d}.{Path(src).stem}.png", visibility[k])


def estimate_depth(model, images, intrinsics, poses, depth_range, sparse_depth, device):
    """Run the network on one reference.

    Args:
        images: ``[N, 3, H, W]`` float32 in ``[0, 1]``, reference at index 0.
        intrinsics: ``[N, 3, 3]``; poses: ``[N, 4, 4]`` cam_from_world.
        depth_range: ``(d_min, d_max)``; sparse_depth: ``[H, W]`` (0 = no point).

    Returns:
        depth ``[H, W]``, confidence ``[H, W]`` and visibility ``[N-1, H, W]`` (upsampled), numpy.
    """
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32), device=device)[None]  # noqa: E731
    with torch.inference_mode():
        out = model(
            t(images),
            t(intrinsics),
            t(poses),
            t(depth_range[0]),
            t(depth_range[1]),
            sparse_depth=t(sparse_depth)[:, None],
        )
        h, w = images.shape[-2:]
        vis = torch.nn.functional.interpolate(out.visibility.float(), size=(h, w), mode="bilinear",
                                              align_corners=False)
    return out.depth[0].cpu().numpy(), out.confidence[0].cpu().numpy(), vis[0].cpu().numpy()


@dataclass(frozen=True)
class RefOutcome:
    """What :func:`process_reference` did for one reference and one pass."""

    name: str
    stage: Literal["photometric", "geometric"]
    status: Literal["computed", "done", "skipped"]
    reason: str = ""
    seconds: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class StereoContext:
    """Everything loaded once per run (or once per Ray worker): workspace, sparse model, network."""

    config: StereoConfig
    workspace: Workspace
    sparse: SparseModel
    net: torch.nn.Module
    checkpoint_path: Path
    device: torch.device
    selection: ViewSelection
    references: dict[str, object]
    id_order: np.ndarray
    adapt_seconds: float = 0.0  # test-time adaptation (0: none, or reused)


def prepare_stereo(config: StereoConfig) -> StereoContext:
    """Load the workspace, the sparse model, the view selection and the checkpoint (once)."""
    ws, model_sparse = load_workspace(config.workspace_path)
    remove_orphan_temps(ws.stereo_dir, recursive=True)  # issue 11: what a killed run left behind
    device = resolve_device(config.device)
    if config.threads > 0:
        torch.set_num_threads(config.threads)
    net, ckpt_path, _meta = load_stereo_model(config, device)
    adapt_seconds = 0.0
    if config.adapt_steps > 0:
        net, ckpt_path, adapt_seconds = _adapt(config, ws, ckpt_path, device)
    selection: ViewSelection = select_views(model_sparse, ViewSelectionConfig(num_views=config.num_views))
    return StereoContext(
        config=config,
        workspace=ws,
        sparse=model_sparse,
        net=net,
        checkpoint_path=ckpt_path,
        device=device,
        selection=selection,
        references=choose_references(ws, model_sparse),
        id_order=np.argsort(model_sparse.points.ids, kind="stable"),
        adapt_seconds=adapt_seconds,
    )


def _skip(name: str, stage, reason: str) -> RefOutcome:
    logger.warning("skipping %s: %s", name, reason)
    return RefOutcome(name, stage, "skipped", reason)


def process_reference(
    ctx: StereoContext, name: str, stage: Literal["photometric", "geometric"] = "photometric"
) -> RefOutcome:
    """Compute (if not current) and atomically write one reference's maps for one pass.

    This single-pass version computes in the photometric pass and writes the geometric maps as its
    copies; its geometric pass only confirms they exist.
    """
    config, ws, model_sparse = ctx.config, ctx.workspace, ctx.sparse
    if stage == "geometric":
        if _is_done(ws, name):
            return RefOutcome(name, stage, "done")
        return RefOutcome(name, stage, "skipped", "no photometric maps")
    if stage != "photometric":
        raise ConfigError(f"stage must be 'photometric' or 'geometric', got {stage!r}")
    if not config.overwrite and _is_done(ws, name):
        return RefOutcome(name, stage, "done")
    entry = ctx.selection.references.get(name)
    if entry is None:
        reason = next((sk.reason for sk in ctx.selection.skipped if sk.name == name), "not selectable")
        return _skip(name, stage, reason)
    sources = list(reference_sources(ctx.selection, name, ctx.references.get(name), config.num_views - 1))
    if len(sources) < config.min_sources:
        reason = f"only {len(sources)} source view(s) share points with it (need {config.min_sources})"
        return _skip(name, stage, reason)
    start = time.perf_counter()
    images, Ks, poses = _prepare_views(ws, model_sparse, [name, *sources], config.max_image_size)
    h, w = images.shape[-2:]
    ref = model_sparse.image_by_name(name)
    sparse = _sparse_depth_map(model_sparse, ref, Ks[0], h, w, ctx.id_order)
    drop_outlier_hints(sparse, entry.depth_range, ctx.selection.config)
    loaded = time.perf_counter()
    try:
        if ctx.device.type == "cpu":  # issue 14: refuse up front what would not fit in memory
            check_memory_budget(h, w, len(sources) + 1, ctx.net.config)
        depth, conf, vis = estimate_depth(ctx.net, images, Ks, poses, entry.depth_range, sparse, ctx.device)
    except (RuntimeError, MemoryError) as exc:
        if "memory" not in str(exc).lower() and not isinstance(exc, MemoryError):
            raise
        reason = f"out of memory at {w}x{h} with {len(sources) + 1} views; lower --max_image_size"
        logger.error("skipping %s: %s (%s)", name, reason, exc)
        return RefOutcome(name, stage, "skipped", reason)
    inferred = time.perf_counter()
    depth = np.where((conf >= config.min_confidence) & np.isfinite(depth), depth, 0.0).astype(np.float32)
    normals = depth_to_normals(depth, Ks[0])
    depth[~np.any(normals != 0, axis=-1)] = 0.0
    _write_outputs(ws, name, depth, normals, conf)
    if config.previews:
        _write_previews(ws, name, depth, normals, conf, vis, sources, entry.depth_range)
    end = time.perf_counter()
    timings = {"load": loaded - start, "network": inferred - loaded, "write": end - inferred}
    return RefOutcome(name, stage, "computed", seconds=end - start, timings=timings)


def auxiliary_references(ctx: StereoContext) -> list[str]:
    """Sources of the references that are not references themselves (a geometric pass reads their
    photometric maps, so they get a photometric pass too)."""
    refs = set(ctx.references)
    extra: dict[str, None] = {}
    for name, spec in ctx.references.items():
        if name in ctx.selection.references:
            for src in reference_sources(ctx.selection, name, spec, ctx.config.num_views - 1):
                if src not in refs:
                    extra[src] = None
    return sorted(extra)


def run_stereo(config: StereoConfig) -> StereoResult:
    """Compute depth and normal maps for every reference image of the workspace.

    Resumable: images whose maps exist are skipped unless ``config.overwrite``.
    Images without usable sources or sparse points are skipped with a warning.
    ``config.backend == "ray"`` spreads the references over a Ray cluster
    (:func:`colmap_pvs.distributed.run_stereo_ray`).
    """
    if config.backend == "ray":
        from .distributed import run_stereo_ray

        return run_stereo_ray(config)
    ctx = prepare_stereo(config)
    ws, refs = ctx.workspace, ctx.references
    save_config(config, ws.stereo_dir / CONFIG_FILENAME, checkpoint_used=str(ctx.checkpoint_path),
                model_config=ctx.net.config)
    result = StereoResult(workspace=ws, adapt_seconds=ctx.adapt_seconds)
    result.adapt_seconds_per_image = ctx.adapt_seconds / max(1, len(refs))
    times: list[float] = []
    bar = tqdm(refs, desc="stereo", unit="image")
    for name in bar:
        outcome = process_reference(ctx, name, "photometric")
        if outcome.status == "done":
            result.already_done.append(name)
        elif outcome.status == "skipped":
            result.skipped[name] = outcome.reason
        else:
            result.processed.append(name)
            result.sources[name] = list(
                reference_sources(ctx.selection, name, refs[name], config.num_views - 1)
            )
            times.append(outcome.seconds)
            bar.set_postfix(s_per_image=f"{np.mean(times):.2f}")
    done = [n for n in refs if _is_done(ws, n)]
    if not done:  # issue 11: an error, and the previous fusion.cfg is kept (not emptied)
        reasons = "; ".join(f"{n}: {r}" for n, r in list(result.skipped.items())[:3])
        raise WorkspaceError(
            f"no depth map in {str(ws.stereo_dir)!r}: all {len(refs)} reference(s) were skipped ({reasons})"
        )
    write_fusion_cfg(ws.fusion_cfg, done)
    result.seconds_per_image = float(np.mean(times)) if times else 0.0
    logger.info(
        "stereo: %d computed, %d already done, %d skipped, %.2f s/image",
        len(result.processed), len(result.already_done), len(result.skipped), result.seconds_per_image,
    )
    return result
