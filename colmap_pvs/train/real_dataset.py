"""Real multi-view training samples without ground-truth depth, from COLMAP models.

Each root is a scene folder with ``images/`` and a COLMAP sparse model (``sparse/`` or
``sparse/0``), or a dense workspace written by COLMAP's ``image_undistorter``. Distorted
models are undistorted once with pycolmap into ``cache_dir`` (never silently treated as
pinhole). Samples are served like the synthetic source's
(:class:`~colmap_pvs.synthetic.SyntheticMVSDataset`):

- sources chosen by the MVSNet view score with the anti-noise strategy (``num_best`` best
  and ``num_worst`` worst candidates, shuffled), depth range from the sparse points
  (:func:`colmap_pvs.views.select_views`);
- images downscaled to ``max_image_size``, then a random crop of the reference (aspect
  ``width:height``, a random fraction ``crop_scale`` of the largest such window) resized to
  ``width x height``; each source takes the same relative window, centred where the
  reference crop's centre projects at the median sparse depth (clamped to the image);
- photometric jitter per view (brightness, contrast, gamma, colour balance, noise) on the
  network input only: the clean images are returned as ``photo_images`` for the
  photometric loss.

The reference's SfM points inside the crop are split at random: a fraction ``hint_fraction``
becomes the network's ``sparse_depth`` hints, the others become ``label_depth``; a point is
never both in one sample.

Pseudo-labels (``pseudo_labels="geometric"``, ``"filled"`` or ``"teacher"``): each root is then a
dense workspace, and the reference's geometric map (``stereo/depth_maps/NAME.geometric.bin``,
written by ``colmap-pvs stereo``: depths that at least ``geom_min_consistent`` sources agree
with, and with ``geom_fill`` the completed pixels other views' completions confirm; 0 elsewhere),
its dense completion (``NAME.filled.bin``, but for its unsupported pixels) or
its teacher labels
(``NAME.teacher.bin``, written by ``tools/teacher_labels.py``: depths where independent teacher
networks and the multi-view check agree) is cropped with the reference's window (nearest pixel)
into ``pseudo_depth``. A reference without such a map gets
an empty ``pseudo_depth``.

Sample dict (``N = 1 + num_best + num_worst``): ``images``, ``photo_images`` ``[N, 3, H, W]``,
``intrinsics`` ``[N, 3, 3]``, ``cam_from_world`` ``[N, 4, 4]``, ``depth`` ``[H, W]`` (all zero:
no ground truth), ``depth_min``, ``depth_max``, ``sparse_depth`` ``[1, H, W]``, ``label_depth``
``[H, W]``, ``pseudo_depth`` ``[H, W]`` (0 = none) and ``is_real`` (1.0).
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from ..errors import ConfigError, MapFormatError, WorkspaceError
from ..geometry import sparse_depth_map, to_homogeneous
from ..io.images import load_image, resize_image
from ..io.maps import read_array, read_depth_map
from ..io.sparse import read_sparse_model
from ..io.workspace import UndistortConfig, detect_workspace, undistort
from ..model.config import NETWORK_STRIDE
from ..types import SparseModel
from ..views import ViewSelection, ViewSelectionConfig, best_and_worst, select_views

logger = logging.getLogger(__name__)

#: Keys of a real sample (the synthetic keys plus ``photo_images``, ``label_depth``, ``is_real``).
REAL_SAMPLE_KEYS = (
    "images",
    "photo_images",
    "intrinsics",
    "cam_from_world",
    "depth",
    "depth_min",
    "depth_max",
    "sparse_depth",
    "label_depth",
    "pseudo_depth",
    "is_real",
)

#: Kinds of pseudo-label a workspace's own ``colmap-pvs stereo`` run provides (test-time adaptation).
STEREO_PSEUDO_LABEL_KINDS = ("none", "geometric", "filled")
#: Kinds of pseudo-label a real root can provide (``RealDatasetConfig.pseudo_labels``).
PSEUDO_LABEL_KINDS = (*STEREO_PSEUDO_LABEL_KINDS, "teacher")


def _pair(name: str, value) -> tuple[float, float]:
    vals = tuple(float(v) for v in value)
    if len(vals) != 2 or not vals[0] <= vals[1]:
        raise ConfigError(f"RealDatasetConfig: {name} must be two numbers lo <= hi, got {value!r}")
    return vals


@dataclass(frozen=True)
class RealDatasetConfig:
    """Real training scenes (see the module docstring)."""

    roots: tuple[Path, ...] = field(
        default=(), metadata={"help": "scene folders (images/ + sparse/) or dense workspaces"}
    )
    cache_dir: Path | None = field(
        default=None,
        metadata={"help": "where distorted scenes are undistorted once (None: output_dir/real_cache)"},
    )
    width: int = field(default=256, metadata={"help": "sample width (multiple of 16)"})
    height: int = field(default=192, metadata={"help": "sample height (multiple of 16)"})
    max_image_size: int = field(
        default=352, metadata={"help": "images are first downscaled to this longest side"}
    )
    crop_scale: tuple[float, ...] = field(
        default=(0.75, 1.0), metadata={"help": "crop size as a fraction of the largest window"}
    )
    num_best: int = field(default=2, metadata={"help": "best-scoring sources per sample"})
    num_worst: int = field(default=2, metadata={"help": "worst-scoring sources per sample (anti-noise)"})
    shuffle_sources: bool = field(default=True, metadata={"help": "shuffle the order of the sources"})
    hint_fraction: float = field(
        default=0.5, metadata={"help": "fraction of the reference's SfM points given as hints"}
    )
    num_samples: int = field(
        default=0, metadata={"help": "dataset length (0: one sample per usable reference image)"}
    )
    seed: int = field(default=0, metadata={"help": "sample i is a pure function of (seed, i)"})
    brightness: float = field(default=0.2, metadata={"help": "jitter: relative brightness std"})
    contrast: float = field(default=0.2, metadata={"help": "jitter: relative contrast std"})
    gamma: tuple[float, ...] = field(default=(0.8, 1.25), metadata={"help": "jitter: gamma range"})
    color: float = field(default=0.05, metadata={"help": "jitter: per-channel gain std"})
    noise: float = field(default=0.01, metadata={"help": "jitter: Gaussian noise std (max)"})
    min_points: int = field(default=20, metadata={"help": "references need this many sparse points"})
    pseudo_labels: str = field(
        default="none",
        metadata={
            "help": "dense pseudo-labels: 'geometric' ('filled', 'teacher') reads each root's "
            "stereo/depth_maps/NAME.geometric.bin (.filled.bin after colmap-pvs stereo, .teacher.bin "
            "after tools/teacher_labels.py); 'none' uses the SfM points only"
        },
    )

    def __post_init__(self) -> None:
        object.__setattr__(self, "roots", tuple(Path(r) for r in self.roots))
        object.__setattr__(self, "crop_scale", _pair("crop_scale", self.crop_scale))
        object.__setattr__(self, "gamma", _pair("gamma", self.gamma))
        for name in ("width", "height"):
            v = getattr(self, name)
            if v < NETWORK_STRIDE or v % NETWORK_STRIDE:
                raise ConfigError(f"RealDatasetConfig: {name} must be a positive multiple of 16, got {v}")
        if not 0 < self.crop_scale[0] <= self.crop_scale[1] <= 1:
            raise ConfigError(f"RealDatasetConfig: crop_scale must be in (0, 1], got {self.crop_scale}")
        if self.num_best < 1 or self.num_worst < 0:
            raise ConfigError(
                f"RealDatasetConfig: need num_best >= 1 and num_worst >= 0, got {self.num_best}, "
                f"{self.num_worst}"
            )
        if not 0.0 <= self.hint_fraction <= 1.0:
            raise ConfigError(f"RealDatasetConfig: hint_fraction must be in [0, 1], got {self.hint_fraction}")
        if self.num_samples < 0 or self.min_points < 1:
            raise ConfigError(
                f"RealDatasetConfig: num_samples must be >= 0 and min_points >= 1, got "
                f"{self.num_samples}, {self.min_points}"
            )
        if min(self.brightness, self.contrast, self.color, self.noise) < 0 or self.gamma[0] <= 0:
            raise ConfigError("RealDatasetConfig: jitter amounts must be >= 0 and gamma > 0")
        if self.pseudo_labels not in PSEUDO_LABEL_KINDS:
            raise ConfigError(
                f"RealDatasetConfig: pseudo_labels must be one of {PSEUDO_LABEL_KINDS}, got "
                f"{self.pseudo_labels!r}"
            )

    @property
    def num_views(self) -> int:
        return 1 + self.num_best + self.num_worst


@dataclass
class _Scene:
    root: Path
    images_dir: Path
    model: SparseModel
    selection: ViewSelection
    references: list[str]
    cache: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    pseudo: dict[str, Path] = field(default_factory=dict)  # reference name -> its pseudo-label map


def _find_sparse(root: Path) -> Path:
    for cand in (root / "sparse" / "0", root / "sparse", root):
        if (cand / "cameras.bin").is_file() or (cand / "cameras.txt").is_file():
            return cand
    raise WorkspaceError(f"training scene {str(root)!r} has no COLMAP model (sparse/ or sparse/0)")


def open_scene(root: Path, cache_dir: Path) -> tuple[Path, SparseModel]:
    """``(images folder, pinhole sparse model)`` of a scene, undistorting it into ``cache_dir`` once."""
    root = Path(root)
    if not root.is_dir():
        raise WorkspaceError(f"training scene folder {str(root)!r} does not exist")
    sparse = _find_sparse(root)
    model = read_sparse_model(sparse, require_pinhole=False)
    if all(cam.is_pinhole for cam in model.cameras.values()):
        return root / "images", model
    key = hashlib.sha1(str(root.resolve()).encode()).hexdigest()[:10]
    out = Path(cache_dir) / f"{root.name}-{key}"
    if not (out / "sparse").is_dir():
        logger.info("undistorting training scene %s into %s", root, out)
        undistort(UndistortConfig(image_path=root / "images", input_path=sparse, output_path=out))
    ws = detect_workspace(out, create_stereo_dirs=False)
    return ws.images_dir, read_sparse_model(ws.sparse_dir)


def _rng(*parts: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(p) & 0xFFFFFFFF for p in parts]))


def _crop_window(width: int, height: int, aspect: float, scale: float, center: tuple[float, float]):
    """``(x0, y0, cw, ch)`` float window of aspect ``aspect`` (w/h) and ``scale`` of the largest, clamped."""
    cw = min(width, height * aspect) * scale
    ch = cw / aspect
    x0 = float(np.clip(center[0] - cw / 2, 0, width - cw))
    y0 = float(np.clip(center[1] - ch / 2, 0, height - ch))
    return x0, y0, cw, ch


def _crop_resize(image: np.ndarray, K: np.ndarray, window, out_w: int, out_h: int):
    """Crop ``window`` from ``image`` and resize it to ``out_w x out_h`` by one affine warp; new ``K``."""
    x0, y0, cw, ch = window
    sx, sy = out_w / cw, out_h / ch
    A = np.array([[sx, 0.0, -x0 * sx], [0.0, sy, -y0 * sy]], np.float64)
    # Pixel-centre convention (+0.5): continuous u' = sx (u - x0); cv2 maps integer centres, so
    # shift by half a pixel on both sides.
    A_cv = A.copy()
    A_cv[:, 2] += 0.5 * np.array([sx, sy]) - 0.5
    interp = cv2.INTER_AREA if sx < 1 else cv2.INTER_LINEAR
    if interp == cv2.INTER_AREA:  # INTER_AREA is not supported by warpAffine: pre-blur instead
        sigma = 0.5 / min(sx, sy)
        image = cv2.GaussianBlur(image, (0, 0), sigma)
        interp = cv2.INTER_LINEAR
    out = cv2.warpAffine(image, A_cv, (out_w, out_h), flags=interp, borderMode=cv2.BORDER_REFLECT)
    K_new = np.array([[sx, 0, -x0 * sx], [0, sy, -y0 * sy], [0, 0, 1.0]]) @ K
    return out, K_new


def _find_pseudo_labels(root: Path, images_dir: Path, references: list[str], kind: str) -> dict[str, Path]:
    """The ``kind`` depth map of each reference in the workspace ``root`` (those that exist)."""
    if images_dir.parent.resolve() != root.resolve():
        raise WorkspaceError(
            f"training scene {str(root)!r} has a distorted model, so it has no pseudo-labels: give the "
            "dense workspace that colmap-pvs undistort + stereo wrote instead"
        )
    maps = root / "stereo" / "depth_maps"
    found = {n: maps / f"{n}.{kind}.bin" for n in references if (maps / f"{n}.{kind}.bin").is_file()}
    if not found:
        raise WorkspaceError(
            f"training scene {str(root)!r} has no {kind} depth map in {str(maps)!r}: run "
            f"{'tools/teacher_labels.py' if kind == 'teacher' else 'colmap-pvs stereo'} on it first "
            f"(pseudo_labels={kind!r})"
        )
    if len(found) < len(references):
        logger.warning("training scene %s: %d of %d references have no %s map (no pseudo-label there)",
                       root, len(references) - len(found), len(references), kind)
    return found


def read_pseudo_label(path: Path, kind: str) -> np.ndarray:
    """``[H, W]`` depth of a pseudo-label map; of a completion only its supported pixels: those of
    confidence 0 hold the network's own depth (``docs/CONVENTIONS.md``), which teaches it nothing."""
    depth = read_depth_map(path)
    conf_path = path.parent.parent / "confidence_maps" / path.name
    if kind == "filled" and conf_path.is_file():
        conf = read_array(conf_path)
        if conf.shape[:2] != depth.shape:
            h, w = depth.shape
            raise MapFormatError(f"confidence map {str(conf_path)!r} is not {w}x{h}")
        depth = np.where(conf.reshape(depth.shape) > 0, depth, 0.0).astype(np.float32)
    return depth


def crop_label_map(
    label: np.ndarray, image_size: tuple[int, int], window, out_w: int, out_h: int
) -> np.ndarray:
    """Nearest-pixel crop of a ``stereo/`` depth map of the whole image into an ``out_h x out_w`` window.

    Output pixel ``(j, i)`` takes the map pixel whose ray is nearest to the ray of its centre. A map
    in ``stereo/`` follows COLMAP's map convention: pixel ``(col, row)`` holds the ray of continuous
    coordinate ``(col, row)`` at the map's scale (``docs/CONVENTIONS.md``), so the nearest pixel is
    ``round``, not ``floor``, of the continuous coordinate.

    Args:
        label: ``[Hm, Wm]`` depth map of the whole image (any resolution; 0 = none).
        image_size: ``(w, h)`` of the image that ``window`` (``x0, y0, cw, ch``) is given in.
    """
    w, h = image_size
    Hm, Wm = label.shape
    x0, y0, cw, ch = window
    u = (x0 + (np.arange(out_w) + 0.5) * cw / out_w) * (Wm / w)  # continuous map coordinates
    v = (y0 + (np.arange(out_h) + 0.5) * ch / out_h) * (Hm / h)
    iu = np.clip(np.floor(u + 0.5).astype(np.int64), 0, Wm - 1)
    iv = np.clip(np.floor(v + 0.5).astype(np.int64), 0, Hm - 1)
    return label[iv[:, None], iu[None, :]].astype(np.float32)


class RealMVSDataset(Dataset):
    """Real MVS samples without GT depth (see the module docstring)."""

    def __init__(self, config: RealDatasetConfig, cache_dir: Path | None = None) -> None:
        if not config.roots:
            raise ConfigError("RealDatasetConfig.roots is empty: name at least one scene folder")
        self.config = config
        cache = config.cache_dir if config.cache_dir is not None else cache_dir
        if cache is None:
            raise ConfigError("RealMVSDataset needs a cache_dir for undistorted scenes")
        self.scenes: list[_Scene] = []
        vcfg = ViewSelectionConfig(num_views=config.num_views, min_points=config.min_points)
        for root in config.roots:
            images_dir, model = open_scene(Path(root), Path(cache))
            selection = select_views(model, vcfg)
            refs = [n for n, r in selection.references.items() if len(r.ranked_names) >= config.num_best]
            if not refs:
                logger.warning("training scene %s has no usable reference image; skipped", root)
                continue
            scene = _Scene(Path(root), images_dir, model, selection, sorted(refs))
            if config.pseudo_labels != "none":
                scene.pseudo = _find_pseudo_labels(Path(root), images_dir, scene.references,
                                                   config.pseudo_labels)
            self.scenes.append(scene)
        self.index = [(s, name) for s, scene in enumerate(self.scenes) for name in scene.references]
        if not self.index:
            raise WorkspaceError(f"no usable reference image in the training scenes {config.roots}")
        logger.info(
            "real training data: %d scenes, %d references", len(self.scenes), len(self.index)
        )

    def __len__(self) -> int:
        return self.config.num_samples or len(self.index)

    def _image(self, scene: _Scene, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Downscaled float32 RGB ``[h, w, 3]`` in [0, 1] and its ``K`` (cached)."""
        hit = scene.cache.get(name)
        if hit is None:
            im = scene.model.image_by_name(name)
            cam = scene.model.camera_of(im)
            pix = load_image(scene.images_dir / name)
            if pix.shape[:2] != (cam.height, cam.width):
                raise WorkspaceError(
                    f"image {str(scene.images_dir / name)!r} is {pix.shape[1]}x{pix.shape[0]}, its camera "
                    f"says {cam.width}x{cam.height}"
                )
            small, sx, sy = resize_image(pix, self.config.max_image_size)
            K = np.diag([sx, sy, 1.0]) @ cam.K
            hit = (small.astype(np.float32) / 255.0, K)
            scene.cache[name] = hit
        return hit

    def _jitter(self, image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        c = self.config
        out = image ** rng.uniform(*c.gamma)
        mean = out.mean()
        out = (out - mean) * (1 + rng.normal(0, c.contrast)) + mean
        out = out * (1 + rng.normal(0, c.brightness)) * (1 + rng.normal(0, c.color, 3))
        out = out + rng.normal(0, rng.uniform(0, c.noise), out.shape)
        return np.clip(out, 0, 1).astype(np.float32)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        c = self.config
        index = int(index)
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError(f"sample index {index} out of range [0, {len(self)})")
        s, ref_name = self.index[index % len(self.index)]
        scene = self.scenes[s]
        rng = _rng(c.seed, index, 0xEA1)
        sel = scene.selection
        row = sel.score_row(ref_name)
        best, worst = best_and_worst(row, c.num_best, c.num_worst)
        chosen = [int(i) for i in np.concatenate([best, worst])]
        n_src = c.num_best + c.num_worst
        while len(chosen) < n_src:  # too few candidates: repeat the best ones cyclically
            chosen.append(chosen[len(chosen) % max(1, len(best))])
        if c.shuffle_sources:
            chosen = [chosen[i] for i in rng.permutation(len(chosen))]
        names = [ref_name] + [sel.names[i] for i in chosen]
        model = scene.model
        ref = model.image_by_name(ref_name)
        dmin, dmax = sel.references[ref_name].depth_range

        aspect = c.width / c.height
        scale = rng.uniform(*c.crop_scale)
        ref_img, ref_K = self._image(scene, ref_name)
        h0, w0 = ref_img.shape[:2]
        cw = min(w0, h0 * aspect) * scale
        ch = cw / aspect
        ctr = (rng.uniform(cw / 2, w0 - cw / 2), rng.uniform(ch / 2, h0 - ch / 2))
        # the 3D point at the crop centre, at the median depth of the reference's points
        rows = np.flatnonzero(np.isin(model.points.ids, ref.point3D_ids))
        xyz = model.points.xyz[rows]
        cam_pts = xyz @ ref.cam_from_world[:, :3].T + ref.cam_from_world[:, 3]
        z_med = float(np.median(cam_pts[:, 2][cam_pts[:, 2] > 0])) if len(cam_pts) else 0.5 * (dmin + dmax)
        ray = np.linalg.inv(ref_K) @ np.array([ctr[0], ctr[1], 1.0])
        X_cam = ray / ray[2] * z_med
        R, t = ref.cam_from_world[:, :3], ref.cam_from_world[:, 3]
        X_world = R.T @ (X_cam - t)

        images, photo, Ks, poses = [], [], [], []
        for k, name in enumerate(names):
            img, K = (ref_img, ref_K) if k == 0 else self._image(scene, name)
            h, w = img.shape[:2]
            im = model.image_by_name(name)
            if k == 0:
                center = ctr
            else:
                p = im.cam_from_world[:, :3] @ X_world + im.cam_from_world[:, 3]
                uv = (K @ p)[:2] / p[2] if p[2] > 0 else np.array([w / 2, h / 2])
                center = (float(uv[0]), float(uv[1])) if np.all(np.isfinite(uv)) else (w / 2, h / 2)
            window = _crop_window(w, h, aspect, scale, center)
            if k == 0:
                ref_window = window
            out, K_new = _crop_resize(img, K, window, c.width, c.height)
            photo.append(out.transpose(2, 0, 1))
            images.append(self._jitter(out, rng).transpose(2, 0, 1))
            Ks.append(K_new)
            poses.append(to_homogeneous(im.cam_from_world))

        # split the reference's points into hints and labels
        is_hint = rng.random(len(xyz)) < c.hint_fraction
        hints = sparse_depth_map(xyz[is_hint], Ks[0], ref.cam_from_world, c.height, c.width)
        labels = sparse_depth_map(xyz[~is_hint], Ks[0], ref.cam_from_world, c.height, c.width)
        labels[hints > 0] = 0.0  # a pixel holding a hint never also holds a label
        pseudo = np.zeros((c.height, c.width), np.float32)
        if ref_name in scene.pseudo:
            pseudo = crop_label_map(read_pseudo_label(scene.pseudo[ref_name], c.pseudo_labels), (w0, h0),
                                    ref_window, c.width, c.height)
        f32 = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
        return {
            "images": f32(np.stack(images)),
            "photo_images": f32(np.stack(photo)),
            "intrinsics": f32(np.stack(Ks)),
            "cam_from_world": f32(np.stack(poses)),
            "depth": torch.zeros(c.height, c.width),
            "depth_min": torch.tensor(dmin, dtype=torch.float32),
            "depth_max": torch.tensor(dmax, dtype=torch.float32),
            "sparse_depth": f32(hints[None]),
            "label_depth": f32(labels),
            "pseudo_depth": f32(pseudo),
            "is_real": torch.tensor(1.0),
        }


class MixedDataset(Dataset):
    """Synthetic (supervised) and real (self-supervised) samples in a fixed ratio.

    Index ``i`` is real when ``hash(seed, i)`` falls below ``real_fraction`` (a pure function of
    the index); real samples cycle through ``real``, synthetic ones through ``synthetic``.
    Synthetic samples get the real sample's extra keys (``photo_images`` = ``images``,
    empty ``label_depth`` and ``pseudo_depth``, ``is_real`` = 0).
    """

    def __init__(self, synthetic: Dataset | None, real: Dataset, real_fraction: float, seed: int = 0) -> None:
        if not 0.0 < real_fraction <= 1.0:
            raise ConfigError(f"real_fraction must be in (0, 1], got {real_fraction}")
        if synthetic is None and real_fraction < 1.0:
            raise ConfigError("a real_fraction below 1 needs a synthetic dataset")
        self.synthetic, self.real, self.real_fraction, self.seed = synthetic, real, real_fraction, seed
        self._length = max(len(real), len(synthetic) if synthetic is not None else 0)

    def __len__(self) -> int:
        return self._length

    def is_real(self, index: int) -> bool:
        return bool(_rng(self.seed, index, 0x313).random() < self.real_fraction)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        index = int(index)
        if self.is_real(index):
            return self.real[index % len(self.real)]
        sample = dict(self.synthetic[index % len(self.synthetic)])
        sample["photo_images"] = sample["images"]
        sample["label_depth"] = torch.zeros_like(sample["depth"])
        sample["pseudo_depth"] = torch.zeros_like(sample["depth"])
        sample["is_real"] = torch.tensor(0.0)
        return sample


__all__ = [
    "PSEUDO_LABEL_KINDS",
    "REAL_SAMPLE_KEYS",
    "MixedDataset",
    "RealDatasetConfig",
    "RealMVSDataset",
    "crop_label_map",
    "open_scene",
]
