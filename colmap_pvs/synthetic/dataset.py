"""Synthetic multi-view training data: scene generation, disk cache and a torch ``Dataset``.

Sample ``i`` belongs to scene ``i // samples_per_scene``; the scene's seed is derived from
``(config.seed, scene_index)``, so every sample is reproducible on its own (any worker,
any order). A scene (images, GT depths, cameras, simulated sparse points) is rendered once
and cached as one compressed ``.npz`` (uint8 images, float32 depths) under
``cache_dir/<hash of the generation config>/``; later requests load it instead. Without a
``cache_dir`` only the last ``memory_cache`` scenes are kept, so a shuffled sample order
(every sample of a scene requested at a different time) renders scenes repeatedly: training
should set ``cache_dir``.

Each sample takes one reference view (never a "disturbing" one) and ``num_best + num_worst``
source views chosen from the MVSNet view-selection scores of the simulated sparse model
(:func:`colmap_pvs.views.compute_view_scores`):

- ``source_strategy="anti_noise"`` (PVSNet's anti-noise training): the ``num_best`` best
  and the ``num_worst`` worst candidates (:func:`colmap_pvs.views.best_and_worst`);
- ``source_strategy="best"``: the ``num_best + num_worst`` best candidates.

The depth range comes from the sparse points the reference observes (robust percentiles
plus a margin, :func:`colmap_pvs.views.compute_depth_range`), as a COLMAP user would get it.
A reference whose GT depth falls mostly outside that range is skipped for the next candidate.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch.utils.data import Dataset

from ..config import config_to_dict
from ..errors import ConfigError
from ..geometry import sparse_depth_map
from ..io.files import atomic_write_bytes
from ..types import SparseModel
from ..views import (
    ViewSelectionConfig,
    best_and_worst,
    compute_depth_range,
    compute_view_scores,
    rank_sources,
)
from .cameras import REFERENCE_ROLES, CameraConfig, CameraRig, generate_cameras
from .render import RenderConfig, Renderer, _pair, apply_photometric
from .scenes import FAMILIES, Scene, SceneConfig, build_scene
from .sfm import SimulatedPoints, build_sparse_model, simulate_sparse_points

logger = logging.getLogger(__name__)

CACHE_FORMAT_VERSION = 2
"""Bumped whenever generation changes in a way that invalidates cached scenes."""

SAMPLE_KEYS = ("images", "intrinsics", "cam_from_world", "depth", "depth_min", "depth_max", "sparse_depth")


def _seed(*parts: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(p) & 0xFFFFFFFF for p in parts]))


# --------------------------------------------------------------------------- one scene


@dataclass(frozen=True, eq=False)
class SceneViews:
    """Everything rendered for one scene.

    Attributes:
        family: scene family.
        seed: scene seed.
        images: ``[V, H, W, 3]`` uint8 (after per-view photometric changes).
        depths: ``[V, H, W]`` float32 GT z-depth, 0 invalid.
        normals: ``[V, H, W, 3]`` float32 camera-frame normals, or ``None`` when not kept.
        K: ``[V, 3, 3]`` float64.
        cam_from_world: ``[V, 3, 4]`` float64.
        roles: ``V`` view roles (see :data:`.cameras.ROLES`).
        points: the simulated sparse points.
    """

    family: str
    seed: int
    images: np.ndarray
    depths: np.ndarray
    normals: np.ndarray | None
    K: np.ndarray
    cam_from_world: np.ndarray
    roles: tuple[str, ...]
    points: SimulatedPoints

    @property
    def num_views(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    def image_names(self) -> list[str]:
        return [f"{v:03d}.png" for v in range(self.num_views)]

    def sparse_model(self, names: list[str] | None = None) -> SparseModel:
        """The simulated sparse model (PINHOLE cameras, ids ``1..V`` in view order)."""
        p = self.points
        return build_sparse_model(
            self.K,
            self.cam_from_world,
            self.width,
            self.height,
            names or self.image_names(),
            p.xyz,
            p.rgb,
            p.visibility,
        )

    def to_npz_bytes(self) -> bytes:
        buf = io.BytesIO()
        arrays = dict(
            version=np.int64(CACHE_FORMAT_VERSION),
            family=np.str_(self.family),
            seed=np.int64(self.seed),
            images=self.images,
            depths=self.depths.astype(np.float32),
            K=self.K,
            cam_from_world=self.cam_from_world,
            roles=np.array(self.roles),
            xyz=self.points.xyz,
            rgb=self.points.rgb,
            visibility=np.packbits(self.points.visibility, axis=1),
            num_views=np.int64(self.num_views),
        )
        if self.normals is not None:
            arrays["normals"] = self.normals.astype(np.float16)
        np.savez_compressed(buf, **arrays)
        return buf.getvalue()

    @classmethod
    def from_npz(cls, path: str | os.PathLike) -> SceneViews:
        with np.load(path, allow_pickle=False) as z:
            if int(z["version"]) != CACHE_FORMAT_VERSION:
                raise ValueError(
                    f"cache file {str(path)!r} has format {int(z['version'])}, "
                    f"expected {CACHE_FORMAT_VERSION}"
                )
            V = int(z["num_views"])
            vis = np.unpackbits(z["visibility"], axis=1, count=V).astype(bool)
            return cls(
                family=str(z["family"]),
                seed=int(z["seed"]),
                images=z["images"],
                depths=z["depths"],
                normals=z["normals"].astype(np.float32) if "normals" in z.files else None,
                K=z["K"],
                cam_from_world=z["cam_from_world"],
                roles=tuple(str(r) for r in z["roles"]),
                points=SimulatedPoints(xyz=z["xyz"], rgb=z["rgb"], visibility=vis),
            )


def render_scene(
    seed: int,
    width: int,
    height: int,
    scene: SceneConfig | None = None,
    camera: CameraConfig | None = None,
    render: RenderConfig | None = None,
    num_points: int = 1500,
    keep_normals: bool = False,
) -> tuple[SceneViews, Scene]:
    """Build scene ``seed``, place cameras, render every view and simulate the sparse points.

    Returns the views and the :class:`~.scenes.Scene` itself. Deterministic: the same arguments
    give identical arrays.
    """
    scene_cfg, cam_cfg, ren_cfg = scene or SceneConfig(), camera or CameraConfig(), render or RenderConfig()
    sc = build_scene(scene_cfg, seed)
    renderer = Renderer(sc)
    rig = generate_cameras(sc, renderer, cam_cfg, width, height, _seed(seed, 1))
    return render_views(renderer, rig, seed, ren_cfg, num_points, keep_normals), sc


def render_views(
    renderer: Renderer,
    rig: CameraRig,
    seed: int,
    render: RenderConfig | None = None,
    num_points: int = 1500,
    keep_normals: bool = False,
) -> SceneViews:
    """Render every camera of ``rig`` (with per-view photometric changes) and simulate the sparse points.

    ``seed`` seeds the photometric changes (per view) and the sparse-point sampling.
    """
    ren_cfg = render or RenderConfig()
    h, w = rig.height, rig.width
    images, depths, normals = [], [], []
    for v in range(len(rig)):
        view = renderer.render(rig.K[v], rig.cam_from_world[v], h, w, ren_cfg.supersample, ren_cfg.shadows)
        images.append(apply_photometric(view.image, _seed(seed, 2, v), ren_cfg))
        depths.append(view.depth)
        normals.append(view.normals)
    images_a, depths_a, normals_a = np.stack(images), np.stack(depths), np.stack(normals)
    points = simulate_sparse_points(renderer, rig, images_a, depths_a, normals_a, _seed(seed, 3), num_points)
    return SceneViews(
        family=renderer.scene.family,
        seed=int(seed),
        images=images_a,
        depths=depths_a,
        normals=normals_a if keep_normals else None,
        K=rig.K,
        cam_from_world=rig.cam_from_world,
        roles=rig.roles,
        points=points,
    )


def select_sources(
    score_row: np.ndarray, strategy: str, num_best: int, num_worst: int
) -> tuple[np.ndarray, np.ndarray]:
    """Source views of one reference from its ``[V]`` score row (the reference itself ``-inf``).

    ``"anti_noise"``: :func:`colmap_pvs.views.best_and_worst`; ``"best"``: the ``num_best + num_worst``
    best candidates (all returned as "best"). When there are too few candidates (views sharing
    sparse points), the remaining slots are filled, as "worst", with non-candidate views in index
    order, so that every sample has ``num_best + num_worst`` sources when the scene has enough views.

    Returns:
        ``(best [b] int64, worst [w] int64)`` view indices, ``b + w = min(num_best + num_worst, V - 1)``.
    """
    row = np.asarray(score_row, np.float64)
    n_src = num_best + num_worst
    if strategy == "anti_noise":
        best, worst = best_and_worst(row, num_best, num_worst)
    elif strategy == "best":
        best, worst = rank_sources(row)[:n_src], np.zeros(0, np.int64)
    else:
        raise ConfigError(f"unknown source_strategy {strategy!r}; expected 'anti_noise' or 'best'")
    taken = set(best.tolist()) | set(worst.tolist())
    if len(taken) < n_src:
        others = [v for v in range(row.size) if v not in taken and np.isfinite(row[v])]
        worst = np.concatenate([worst, np.array(others[: n_src - len(taken)], np.int64)])
    return best.astype(np.int64), worst.astype(np.int64)


def rig_of(views: SceneViews) -> CameraRig:
    """The :class:`~.cameras.CameraRig` of rendered views."""
    return CameraRig(
        K=views.K,
        cam_from_world=views.cam_from_world,
        roles=views.roles,
        width=views.width,
        height=views.height,
    )


# --------------------------------------------------------------------------- dataset


@dataclass(frozen=True)
class SyntheticDatasetConfig:
    """Synthetic training data (see the module docstring)."""

    num_samples: int = field(default=10000, metadata={"help": "number of samples (dataset length)"})
    seed: int = field(default=0, metadata={"help": "base seed; sample i is reproducible from (seed, i)"})
    width: int = field(default=160, metadata={"help": "image width in pixels"})
    height: int = field(default=128, metadata={"help": "image height in pixels"})
    samples_per_scene: int = field(
        default=8, metadata={"help": "consecutive samples that share one scene (different references)"}
    )
    source_strategy: Literal["anti_noise", "best"] = field(
        default="anti_noise",
        metadata={
            "help": "anti_noise: num_best best + num_worst worst sources; best: num_best+num_worst best"
        },
    )
    num_best: int = field(default=2, metadata={"help": "best-scoring source views per sample"})
    num_worst: int = field(default=2, metadata={"help": "worst-scoring source views per sample (anti_noise)"})
    shuffle_sources: bool = field(default=True, metadata={"help": "shuffle the order of the source views"})
    num_points: int = field(
        default=1500, metadata={"help": "sparse points sampled per scene (before filtering)"}
    )
    hint_keep: tuple[float, ...] = field(
        default=(1.0, 1.0),
        metadata={"help": "each sample keeps a random fraction in [lo, hi] of its sparse depth hints"},
    )
    hint_noise: float = field(
        default=0.0,
        metadata={"help": "relative (log-normal) noise std of the sparse depth hints, per hint"},
    )
    hint_outliers: float = field(
        default=0.0,
        metadata={"help": "fraction of hints whose depth is scaled by a random factor in [2/3, 3/2]"},
    )
    depth_percentiles: tuple[float, ...] = field(
        default=(1.0, 99.0),
        metadata={"help": "percentiles of the reference's sparse depths giving the range"},
    )
    depth_margin: float = field(default=0.1, metadata={"help": "relative margin added to the depth range"})
    min_depth_inside: float = field(
        default=0.85, metadata={"help": "minimum fraction of valid GT depth inside [depth_min, depth_max]"}
    )
    cache_dir: Path | None = field(
        default=None, metadata={"help": "scene cache folder (None: no disk cache)"}
    )
    memory_cache: int = field(
        default=32,
        metadata={"help": "scenes kept in memory per dataset instance (about 2 MB each at 160x128)"},
    )
    scene: SceneConfig = field(default_factory=SceneConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    render: RenderConfig = field(default_factory=RenderConfig)

    def __post_init__(self) -> None:
        if self.num_samples < 1 or self.samples_per_scene < 1:
            raise ConfigError(
                "num_samples and samples_per_scene must be >= 1, got "
                f"{self.num_samples}, {self.samples_per_scene}"
            )
        if self.width < 8 or self.height < 8:
            raise ConfigError(f"image size must be at least 8x8, got {self.width}x{self.height}")
        if self.num_best < 0 or self.num_worst < 0 or self.num_best + self.num_worst < 1:
            raise ConfigError(
                "need num_best, num_worst >= 0 and at least one source, got "
                f"{self.num_best}, {self.num_worst}"
            )
        if self.camera.num_views[0] < 1 + self.num_sources:
            raise ConfigError(
                f"scenes may have only {self.camera.num_views[0]} views (camera.num_views), fewer than "
                f"1 + num_best + num_worst = {1 + self.num_sources}"
            )
        object.__setattr__(self, "depth_percentiles", _pair("depth_percentiles", self.depth_percentiles))
        object.__setattr__(self, "hint_keep", _pair("hint_keep", self.hint_keep))
        if not 0.0 <= self.hint_keep[0] <= self.hint_keep[1] <= 1.0:
            raise ConfigError(f"hint_keep must satisfy 0 <= lo <= hi <= 1, got {self.hint_keep}")
        if not (self.hint_noise >= 0 and 0 <= self.hint_outliers <= 1):
            raise ConfigError(
                f"hint_noise must be >= 0 and hint_outliers in [0, 1], got {self.hint_noise}, "
                f"{self.hint_outliers}"
            )
        if not 0 <= self.depth_margin < 1 or not 0 <= self.min_depth_inside <= 1:
            raise ConfigError(
                f"depth_margin must be in [0, 1) and min_depth_inside in [0, 1], got {self.depth_margin}, "
                f"{self.min_depth_inside}"
            )
        if self.num_points < 1 or self.memory_cache < 0:
            raise ConfigError(
                f"num_points must be >= 1, memory_cache >= 0; got {self.num_points}, {self.memory_cache}"
            )

    @property
    def num_sources(self) -> int:
        return self.num_best + self.num_worst

    @property
    def num_scenes(self) -> int:
        return -(-self.num_samples // self.samples_per_scene)

    def generation_key(self) -> str:
        """Hash of everything that changes a rendered scene (names the cache folder)."""
        d = config_to_dict(self)
        payload = {k: d[k] for k in ("seed", "width", "height", "num_points", "scene", "camera", "render")}
        if tuple(payload["scene"]["families"]) == FAMILIES:  # keys (and caches) from before the field
            payload["scene"] = {k: v for k, v in payload["scene"].items() if k != "families"}
        payload["version"] = CACHE_FORMAT_VERSION
        return hashlib.sha1(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class SampleInfo:
    """Which views a sample uses (indices into its scene's views)."""

    scene_index: int
    scene_seed: int
    family: str
    reference: int
    sources: tuple[int, ...]
    best: tuple[int, ...]
    worst: tuple[int, ...]
    roles: tuple[str, ...]


class SyntheticMVSDataset(Dataset):
    """Synthetic MVS samples for training (see the module docstring for the sample dict)."""

    def __init__(self, config: SyntheticDatasetConfig | None = None) -> None:
        self.config = config or SyntheticDatasetConfig()
        self._scenes: OrderedDict[int, tuple[SceneViews, SparseModel, np.ndarray]] = OrderedDict()
        self._cache_dir = (
            Path(self.config.cache_dir) / self.config.generation_key() if self.config.cache_dir else None
        )
        self.stats = {"generated": 0, "loaded": 0, "generate_s": 0.0}
        self._generated: set[int] = set()
        self._warned_regeneration = False

    def __len__(self) -> int:
        return self.config.num_samples

    # ------------------------------------------------------------------ scenes

    def scene_seed(self, scene_index: int) -> int:
        """Seed of scene ``scene_index`` (derived from ``config.seed``)."""
        ss = np.random.SeedSequence([int(self.config.seed) & 0xFFFFFFFF, int(scene_index), 0x5EED])
        return int(ss.generate_state(1)[0])

    def cache_path(self, scene_index: int) -> Path | None:
        if self._cache_dir is None:
            return None
        return self._cache_dir / f"scene_{scene_index:07d}.npz"

    def scene_views(self, scene_index: int) -> SceneViews:
        """Rendered views of scene ``scene_index`` (from memory, the disk cache, or generated)."""
        return self._scene(scene_index)[0]

    def _scene(self, scene_index: int) -> tuple[SceneViews, SparseModel, np.ndarray]:
        if not 0 <= scene_index < self.config.num_scenes:
            raise IndexError(f"scene index {scene_index} out of range [0, {self.config.num_scenes})")
        hit = self._scenes.get(scene_index)
        if hit is not None:
            self._scenes.move_to_end(scene_index)
            return hit
        views = None
        path = self.cache_path(scene_index)
        if path is not None and path.is_file():
            try:
                views = SceneViews.from_npz(path)
                self.stats["loaded"] += 1
            except (OSError, ValueError, KeyError) as exc:
                logger.warning("ignoring unreadable cache file %s (%s); regenerating", path, exc)
        if views is None:
            c = self.config
            t0 = time.perf_counter()
            views, _ = render_scene(
                self.scene_seed(scene_index), c.width, c.height, c.scene, c.camera, c.render, c.num_points
            )
            self.stats["generated"] += 1
            if scene_index in self._generated and path is None and not self._warned_regeneration:
                logger.warning(
                    "synthetic scene %d was rendered again because it fell out of the memory cache "
                    "(memory_cache=%d) and there is no disk cache: set cache_dir to render each scene once",
                    scene_index,
                    self.config.memory_cache,
                )
                self._warned_regeneration = True
            self._generated.add(scene_index)
            self.stats["generate_s"] += time.perf_counter() - t0
            if path is not None:
                atomic_write_bytes(path, views.to_npz_bytes())
        model = views.sparse_model()
        _, scores = compute_view_scores(model, self._view_config())
        entry = (views, model, scores)
        if self.config.memory_cache:
            self._scenes[scene_index] = entry
            while len(self._scenes) > self.config.memory_cache:
                self._scenes.popitem(last=False)
        return entry

    def _view_config(self) -> ViewSelectionConfig:
        c = self.config
        return ViewSelectionConfig(
            num_views=1 + c.num_sources,
            depth_percentiles=c.depth_percentiles,
            depth_margin=c.depth_margin,
            min_points=5,
        )

    def prepare(self, scene_indices: list[int] | None = None, progress: bool = True) -> None:
        """Generate (and cache) scenes ahead of training; with no indices, all of them."""
        from tqdm import tqdm

        indices = range(self.config.num_scenes) if scene_indices is None else scene_indices
        for i in tqdm(indices, desc="synthetic scenes", disable=not progress, leave=False):
            self._scene(int(i))

    # ------------------------------------------------------------------ samples

    def sample_info(self, index: int) -> SampleInfo:
        """Reference and source views of sample ``index`` (without building tensors)."""
        return self._select(index)[0]

    def _select(self, index: int) -> tuple[SampleInfo, SceneViews, tuple[float, float]]:
        c = self.config
        if not 0 <= index < len(self):
            raise IndexError(f"sample index {index} out of range [0, {len(self)})")
        scene_index, k = divmod(index, c.samples_per_scene)
        views, model, scores = self._scene(scene_index)
        cand = np.array([v for v, r in enumerate(views.roles) if r in REFERENCE_ROLES], np.int64)
        seed = self.scene_seed(scene_index)
        order = _seed(seed, 7).permutation(cand)
        vcfg = self._view_config()
        chosen = None
        fallback = None
        for j in range(order.size):
            ref = int(order[(k + j) % order.size])
            rng = compute_depth_range(model, model.images[ref + 1], vcfg)
            if rng is None:
                continue
            gt = views.depths[ref]
            valid = gt > 0
            inside = float(np.mean((gt[valid] >= rng[0]) & (gt[valid] <= rng[1]))) if valid.any() else 0.0
            if fallback is None or inside > fallback[2]:
                fallback = (ref, rng, inside)
            if inside >= c.min_depth_inside:
                chosen = (ref, rng)
                break
        if chosen is None:
            if fallback is None:
                raise RuntimeError(
                    f"scene {scene_index} (seed {seed}) has no reference view with sparse points"
                )
            ref, _, _ = fallback
            gt = views.depths[ref]
            lo, hi = np.percentile(gt[gt > 0], [1, 99])
            chosen = (ref, (float(lo) * (1 - c.depth_margin), float(hi) * (1 + c.depth_margin)))
            logger.debug(
                "scene %d: no reference with >= %.0f%% GT depth inside the sparse range; widened it",
                scene_index,
                100 * c.min_depth_inside,
            )
        ref, depth_range = chosen
        row = scores[ref].copy()
        row[ref] = -np.inf
        best, worst = select_sources(row, c.source_strategy, c.num_best, c.num_worst)
        chosen_src = [int(x) for x in np.concatenate([best, worst])]
        sources = np.array(chosen_src, np.int64)
        if c.shuffle_sources:
            sources = _seed(seed, 8, index).permutation(sources)
        info = SampleInfo(
            scene_index=scene_index,
            scene_seed=seed,
            family=views.family,
            reference=ref,
            sources=tuple(int(s) for s in sources),
            best=tuple(int(b) for b in best),
            worst=tuple(int(w) for w in worst),
            roles=views.roles,
        )
        return info, views, depth_range

    def _corrupt_hints(self, sparse: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Drop, perturb and corrupt the hints ``[H, W]`` (0 = none) as ``hint_*`` asks (like real SfM)."""
        c = self.config
        if c.hint_keep == (1.0, 1.0) and c.hint_noise == 0 and c.hint_outliers == 0:
            return sparse
        rows, cols = np.nonzero(sparse)
        keep = rng.random(rows.size) < rng.uniform(*c.hint_keep)
        z = sparse[rows, cols].astype(np.float64)
        z *= np.exp(rng.normal(0.0, c.hint_noise, z.size))
        bad = rng.random(z.size) < c.hint_outliers
        z[bad] *= np.exp(rng.uniform(np.log(2 / 3), np.log(3 / 2), int(bad.sum())))
        out = np.zeros_like(sparse)
        out[rows[keep], cols[keep]] = z[keep]
        return out

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        """Sample ``index``: a dict with exactly the keys of :data:`SAMPLE_KEYS`.

        - ``images``: ``[N, 3, H, W]`` float32 in [0, 1], reference first (``N = 1 + num_best + num_worst``);
        - ``intrinsics``: ``[N, 3, 3]`` float32; ``cam_from_world``: ``[N, 4, 4]`` float32;
        - ``depth``: ``[H, W]`` float32 GT reference depth (0 invalid);
        - ``depth_min``, ``depth_max``: float32 scalars (sparse-point range of the reference);
        - ``sparse_depth``: ``[1, H, W]`` float32 depths of the sparse points the reference observes.
        """
        index = int(index)
        if index < 0:
            index += len(self)
        info, views, (dmin, dmax) = self._select(index)
        idx = np.array([info.reference, *info.sources], np.int64)
        images = np.ascontiguousarray(views.images[idx].transpose(0, 3, 1, 2), dtype=np.float32)
        images *= np.float32(1.0 / 255.0)
        poses = np.tile(np.eye(4), (idx.size, 1, 1))
        poses[:, :3, :] = views.cam_from_world[idx]
        ref = info.reference
        observed = views.points.visibility[:, ref]
        sparse = sparse_depth_map(
            views.points.xyz[observed], views.K[ref], views.cam_from_world[ref], views.height, views.width
        )
        sparse = self._corrupt_hints(sparse, _seed(info.scene_seed, 9, index))
        return {
            "images": torch.from_numpy(images),
            "intrinsics": torch.from_numpy(views.K[idx].astype(np.float32)),
            "cam_from_world": torch.from_numpy(poses.astype(np.float32)),
            "depth": torch.from_numpy(np.ascontiguousarray(views.depths[ref], np.float32)),
            "depth_min": torch.tensor(dmin, dtype=torch.float32),
            "depth_max": torch.tensor(dmax, dtype=torch.float32),
            "sparse_depth": torch.from_numpy(sparse[None]),
        }


__all__ = [
    "SAMPLE_KEYS",
    "SampleInfo",
    "SceneViews",
    "SyntheticDatasetConfig",
    "SyntheticMVSDataset",
    "render_scene",
    "render_views",
    "select_sources",
    "rig_of",
]
