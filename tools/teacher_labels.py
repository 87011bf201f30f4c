"""Dense real depth labels where independent strong MVS teachers and multi-view consistency agree.

A label-making tool for training (issue 40, item 1); not part of the ``colmap_pvs`` package.

Teachers (MIT licence, never shipped with this repository: the user clones them)::

    git clone https://github.com/FangjinhuaWang/IterMVS /path/IterMVS
    git clone https://github.com/FangjinhuaWang/PatchmatchNet /path/PatchmatchNet

Their model code is imported from the clones at label time and their released weights are loaded
from the clones' ``checkpoints/`` folders; the output records each clone's commit, the first line of
its LICENSE and the sha256 of each weight file.

Usage::

    python tools/teacher_labels.py --itermvs /path/IterMVS --patchmatchnet /path/PatchmatchNet \\
        --scenes ../shared/data/real-train --out runs/labels
    # a single teacher needs only its own clone
    python tools/teacher_labels.py --itermvs /path/IterMVS --scenes S --out runs/labels_itermvs11 \\
        --estimates itermvs_blended:0-10 --min_agree 1 --num_views 11

    # measure the labels against GT depth (scene = one COLMAP model; every 3rd image as reference)
    python tools/teacher_labels.py --itermvs ... --patchmatchnet ... \\
        --scenes /path/hololens-workspace --out runs/labels-holo --ref_every 3 \\
        --evaluate_gt /path/hololens-dev/depth --gt_scale 0.001

``--scenes`` is a scene folder (``images/`` + ``sparse/`` or ``sparse/0``) or a folder of such scene
folders. Per scene:

1. The scene is undistorted into ``OUT/<scene>/`` as a COLMAP dense workspace (``images/``,
   ``sparse/``, ``stereo/depth_maps/``); an all-pinhole scene is linked instead (images untouched,
   so GT depth stays aligned).
2. View selection (MVSNet score, :func:`colmap_pvs.views.select_views`) gives each reference its
   ranked sources and its depth range from the sparse points.
3. Each estimate (``--estimates``, default IterMVS with its DTU weights, IterMVS with its
   BlendedMVS weights and PatchmatchNet, each on the reference's top 4 sources, and IterMVS-BlendedMVS
   again on the sources ranked 5-8) gives depth and its
   own confidence at full resolution (images resized to the teacher's multiple of 32 / 8 and the
   maps resized back). Raw outputs are cached in ``OUT/<scene>/teacher_cache/<estimate>/NAME.npz``.
4. Agreement: a pixel is a candidate where at least ``--min_agree`` estimates agree within
   ``--agree_tol`` relative depth; its depth is the mean of the agreeing estimates (with two or more
   estimates, at least two must agree whatever ``--min_agree``). With a single estimate
   (``--estimates itermvs_blended:0-10 --min_agree 1 --num_views 11``) each of its valid pixels is a
   candidate, and only the view check below filters it.
5. Multi-view consistency: the candidate depth is reprojected into the candidate maps of the
   reference's first ``--check_views`` ranked sources that are references themselves; a view
   confirms a pixel when the round trip lands within ``--geo_pixel`` px and the depths differ by
   less than ``--geo_rel``; pixels with ``>= --min_consistent`` confirming views are kept.
6. Output: ``stereo/depth_maps/NAME.teacher.bin`` (COLMAP depth map, 0 = no label) and
   ``NAME.teacher_weight.bin`` (0.5 * agreeing / estimates + 0.5 * min(confirming, check views) /
   check views, in (0, 1] where labelled; with the defaults it is 0.5 for the weakest labels (3
   agreeing estimates, 1 confirming view) and above 0.5 where all 4 agree or more views confirm),
   ``OUT/<scene>/labels.json`` and the summary ``OUT/labels.json``. A rerun skips the images whose
   settings hash is unchanged.

Default rules, chosen on hololens-dev (see ``--evaluate_gt`` and tools/README.md): 4 estimates,
``--min_agree 3`` within ``--agree_tol 0.02``, ``--min_consistent 1`` of ``--check_views 4``
(``--geo_pixel 1`` px, ``--geo_rel 0.02``). At about the same accuracy this covers more than 2 of 3
(or 2 of 4) estimates within 1 %; requiring the teachers' own confidence or 2 confirming views is
more accurate but covers far less, so the weight carries that instead of dropping the pixels.

With ``--evaluate_gt DIR`` the labels (and each teacher, and the agreement alone) are compared to
GT depth ``DIR/<stem>.png`` (uint16, times ``--gt_scale`` = metres, 0 invalid) and a table is
printed and written to ``OUT/<scene>/evaluation.json``.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from colmap_pvs.consistency import SourceMaps, check_consistency  # noqa: E402
from colmap_pvs.geometry import scale_intrinsics, to_homogeneous  # noqa: E402
from colmap_pvs.io.files import atomic_write_bytes, file_sha256  # noqa: E402
from colmap_pvs.io.images import load_image  # noqa: E402
from colmap_pvs.io.maps import write_depth_map  # noqa: E402
from colmap_pvs.io.sparse import read_sparse_model  # noqa: E402
from colmap_pvs.io.workspace import UndistortConfig, undistort  # noqa: E402
from colmap_pvs.views import ViewSelectionConfig, select_views  # noqa: E402

logger = logging.getLogger("teacher_labels")

#: The default estimates (chosen on hololens-dev: a 4th estimate on other sources adds coverage).
DEFAULT_ESTIMATES = "itermvs_dtu:0-4,itermvs_blended:0-4,patchmatchnet:0-4,itermvs_blended:4-8"

#: Bump when the meaning of the cached teacher outputs changes.
CACHE_VERSION = 1
#: Bumped when the rules' code changes the labels for the same settings (2: the view check is the
#: geometric pass's own, colmap_pvs.consistency; 3: a single estimate is its own candidate).
LABEL_VERSION = 3


# --------------------------------------------------------------------------- teachers


@dataclass(frozen=True)
class TeacherKind:
    """One teacher network with one weight file."""

    repo: str  # "itermvs" or "patchmatchnet"
    weights: str  # path inside the clone
    multiple: int  # image sides are resized to a multiple of this
    conf_threshold: float  # the threshold the teacher's own eval uses on its confidence


TEACHER_KINDS = {
    "itermvs_dtu": TeacherKind("itermvs", "checkpoints/dtu/model_000015.ckpt", 32, 0.3),
    "itermvs_blended": TeacherKind("itermvs", "checkpoints/blendedmvs/model_000015.ckpt", 32, 0.3),
    # eval.py's default photo threshold is 0.5 (0.8 in its DTU script)
    "patchmatchnet": TeacherKind("patchmatchnet", "checkpoints/params_000007.ckpt", 8, 0.5),
}

_CLASHING = ("models", "datasets", "utils")  # generic top-level names both clones use


def _import_from_clone(repo: Path, module: str, attr: str):
    """``attr`` of ``module`` imported from the clone ``repo`` (its ``models`` package is not ours)."""
    saved = {k: sys.modules.pop(k) for k in list(sys.modules) if k.split(".")[0] in _CLASHING}
    sys.path.insert(0, str(repo))
    try:
        return getattr(importlib.import_module(module), attr)
    finally:
        sys.path.remove(str(repo))
        for k in list(sys.modules):
            if k.split(".")[0] in _CLASHING:
                del sys.modules[k]
        sys.modules.update(saved)


def clone_provenance(repo: Path) -> dict:
    """Commit, licence line and upstream of a teacher clone."""
    try:
        commit = subprocess.run(
            ["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    lic = repo / "LICENSE"
    licence = lic.read_text().splitlines()[0].strip() if lic.is_file() else "unknown"
    return {"path": str(repo), "commit": commit, "licence": licence}


#: Public upstreams of the teachers (recorded in the outputs; the user clones them).
UPSTREAMS = {"itermvs": "https://github.com/FangjinhuaWang/IterMVS",
             "patchmatchnet": "https://github.com/FangjinhuaWang/PatchmatchNet"}


def _state_dict(path: Path) -> dict:
    # The teachers' checkpoints are plain pickles of {"model": state_dict, ...}; weights_only=False is
    # acceptable here: third-party teacher weights the user downloaded, loaded by a tool, not the package.
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    state = ckpt.get("model", ckpt) if isinstance(ckpt, dict) else ckpt
    return {k.removeprefix("module."): v for k, v in state.items()}


class Teacher:
    """A loaded teacher: ``run(images, Ks, poses, dmin, dmax) -> (depth, confidence)`` at full size."""

    def __init__(self, key: str, repo: Path):
        self.key = key
        self.kind = TEACHER_KINDS[key]
        self.repo = Path(repo)
        self.weights_path = self.repo / self.kind.weights
        if not self.weights_path.is_file():
            raise SystemExit(f"teacher weights {self.weights_path} not found (clone {self.repo} incomplete?)")
        self.weights_sha256 = file_sha256(self.weights_path)
        state = _state_dict(self.weights_path)
        if self.kind.repo == "itermvs":
            pipeline = _import_from_clone(self.repo, "models.net", "Pipeline")
            self.model = pipeline(iteration=4, test=True)  # eval.py: --iteration 4, test=True
            self.model.load_state_dict(state, strict=True)
        else:
            net = _import_from_clone(self.repo, "models.net", "PatchmatchNet")
            # eval.py's defaults
            self.model = net(
                patchmatch_interval_scale=[0.005, 0.0125, 0.025],
                propagation_range=[6, 4, 2],
                patchmatch_iteration=[1, 2, 2],
                patchmatch_num_sample=[8, 8, 16],
                propagate_neighbors=[0, 8, 16],
                evaluate_neighbors=[9, 9, 9],
            )
            missing, unexpected = self.model.load_state_dict(state, strict=False)  # as eval.py
            if missing:
                raise SystemExit(f"PatchmatchNet weights lack {len(missing)} keys, e.g. {missing[:3]}")
            if unexpected:
                logger.debug("PatchmatchNet: unused weight keys %s", unexpected)
        self.model.eval()

    def provenance(self) -> dict:
        return {**clone_provenance(self.repo), "upstream": UPSTREAMS[self.kind.repo],
                "weights": self.kind.weights,
                "weights_sha256": self.weights_sha256}

    def _prepare(self, images, Ks, height: int, width: int):
        """Images resized to the teacher size ``(tw, th)`` and MVSNet-convention ``K`` (pixel index =
        coordinate, where ours has pixel centres at +0.5)."""
        m = self.kind.multiple
        th, tw = max(m, round(height / m) * m), max(m, round(width / m) * m)
        out_imgs, out_K = [], []
        for img, K in zip(images, Ks, strict=True):
            h, w = img.shape[:2]
            interp = cv2.INTER_AREA if tw < w else cv2.INTER_LINEAR
            out_imgs.append(cv2.resize(img, (tw, th), interpolation=interp) if (h, w) != (th, tw) else img)
            Kt = scale_intrinsics(K, tw / w, th / h)
            Kt[0, 2] -= 0.5
            Kt[1, 2] -= 0.5
            out_K.append(Kt)
        return out_imgs, out_K, th, tw

    @torch.no_grad()
    def run(self, images, Ks, poses, dmin: float, dmax: float):
        """``images`` uint8 RGB (reference first), ``Ks`` ours, ``poses`` cam_from_world ``[4, 4]``."""
        height, width = images[0].shape[:2]
        imgs, Kt, th, tw = self._prepare(images, Ks, height, width)
        ext = np.stack([to_homogeneous(p) for p in poses]).astype(np.float32)
        dmin_t = torch.tensor([dmin], dtype=torch.float32)
        dmax_t = torch.tensor([dmax], dtype=torch.float32)
        if self.kind.repo == "itermvs":
            # datasets/custom.py: 2 * x / 255 - 1; levels 0..3 at 1, 1/2, 1/4, 1/8; proj per level
            x = np.stack([2.0 * im.astype(np.float32) / 255.0 - 1.0 for im in imgs])
            levels, projs = {}, {}
            for lv in range(4):
                s = 0.5**lv
                if lv == 0:
                    arr = x
                else:
                    arr = np.stack([cv2.resize(a, (tw // 2**lv, th // 2**lv), interpolation=cv2.INTER_LINEAR)
                                    for a in x])
                levels[f"level_{lv}"] = torch.from_numpy(arr.transpose(0, 3, 1, 2)[None].copy())
                P = ext.copy()
                for i, K in enumerate(Kt):
                    Kl = K.copy()
                    Kl[:2, :] *= s
                    P[i, :3, :4] = Kl @ ext[i, :3, :4]
                projs[f"level_{lv}"] = torch.from_numpy(P[None])
            out = self.model(levels, projs, dmin_t, dmax_t)
            depth = out["depths_upsampled"].reshape(th, tw).numpy()
            conf = out["confidence_upsampled"].reshape(th, tw).numpy()
        else:
            # datasets/mvs.py: x / 255; intrinsics and extrinsics separately, network scales per stage
            tens = [torch.from_numpy(im.astype(np.float32).transpose(2, 0, 1)[None] / 255.0) for im in imgs]
            intr = torch.from_numpy(np.stack(Kt).astype(np.float32)[None])
            depth, conf, _ = self.model(tens, intr, torch.from_numpy(ext[None]), dmin_t, dmax_t)
            depth = depth.reshape(th, tw).numpy()
            conf = conf.reshape(th, tw).numpy()
        if (th, tw) != (height, width):
            depth = cv2.resize(depth, (width, height), interpolation=cv2.INTER_LINEAR)
            conf = cv2.resize(conf, (width, height), interpolation=cv2.INTER_LINEAR)
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
        return depth, np.nan_to_num(conf).astype(np.float32)


def add_clone_args(p: argparse.ArgumentParser) -> None:
    """The ``--itermvs`` / ``--patchmatchnet`` clone flags (each needed only by its teachers)."""
    p.add_argument("--itermvs", type=Path, help="clone of github.com/FangjinhuaWang/IterMVS with its "
                   "checkpoints/ (for itermvs_*)")
    p.add_argument("--patchmatchnet", type=Path, help="clone of github.com/FangjinhuaWang/PatchmatchNet "
                   "(for patchmatchnet)")


def clones(args) -> dict[str, Path | None]:
    """The clone flags of :func:`add_clone_args` as the ``repos`` of :func:`load_teachers`."""
    return {"itermvs": args.itermvs, "patchmatchnet": args.patchmatchnet}


def teacher_of(estimate: str) -> str:
    """The teacher key of an estimate id ``teacher:first-stop`` (:func:`parse_estimates`)."""
    return estimate.partition(":")[0]


def load_teachers(keys, repos: dict[str, Path | str | None]) -> dict[str, Teacher]:
    """One :class:`Teacher` per key of ``keys`` (``TEACHER_KINDS``), each loaded from the clone its kind
    needs; ``repos`` maps ``"itermvs"`` / ``"patchmatchnet"`` to a clone path or ``None`` (not given)."""
    missing = sorted({TEACHER_KINDS[k].repo for k in keys if repos.get(TEACHER_KINDS[k].repo) is None})
    if missing:
        flags = " and ".join(f"--{r}" for r in missing)
        raise SystemExit(f"teachers {', '.join(sorted(set(keys)))} need {flags}")
    return {k: Teacher(k, Path(repos[TEACHER_KINDS[k].repo])) for k in sorted(set(keys))}


def parse_estimates(spec: str) -> list[str]:
    """``"itermvs_dtu:0-4,..."`` -> estimate ids ``teacher:first-stop`` (a slice of the ranked sources)."""
    out = []
    for item in spec.split(","):
        item = item.strip()
        key, _, rng = item.partition(":")
        if key not in TEACHER_KINDS:
            raise SystemExit(f"unknown teacher {key!r} in --estimates (known: {', '.join(TEACHER_KINDS)})")
        a, _, b = (rng or "0-4").partition("-")
        if not (a.isdigit() and b.isdigit() and int(a) < int(b)):
            raise SystemExit(f"bad source range {rng!r} in --estimates (e.g. itermvs_dtu:0-4)")
        out.append(f"{key}:{int(a)}-{int(b)}")
    return out


# --------------------------------------------------------------------------- agreement and consistency


def agree(depths: np.ndarray, valid: np.ndarray, rel_tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Agreement of ``T`` estimates ``depths`` ``[T, H, W]`` (``valid`` ``[T, H, W]`` bool).

    Two estimates agree at a pixel when both are valid and ``|a - b| <= rel_tol * min(a, b)``. Per
    pixel the estimate that agrees with the most others is the anchor; the agreeing set is the anchor
    and those agreeing with it. Returns ``(depth, count)``: the mean depth of the agreeing set and its
    size (1 where nothing agrees, 0 where no estimate is valid; depth 0 where ``count < 2``, except
    with a single estimate, which is its own depth wherever it is valid: the view check then filters it).
    """
    depths = np.asarray(depths, np.float32)
    valid = np.asarray(valid, bool) & (depths > 0) & np.isfinite(depths)
    t = depths.shape[0]
    pair = np.zeros((t, t) + depths.shape[1:], bool)
    for i in range(t):
        for j in range(i + 1, t):
            a, b = depths[i], depths[j]
            ok = valid[i] & valid[j] & (np.abs(a - b) <= rel_tol * np.minimum(a, b))
            pair[i, j] = pair[j, i] = ok
    support = pair.sum(axis=1)  # [T, H, W]
    support = np.where(valid, support, -1)
    anchor = support.argmax(axis=0)  # [H, W]
    member = np.take_along_axis(pair, anchor[None, None], axis=0)[0]  # [T, H, W]: agrees with anchor
    member |= np.arange(t)[:, None, None] == anchor[None]
    member &= valid
    count = member.sum(axis=0)
    count = np.where(valid.any(axis=0), count, 0)
    depth = np.where(member, depths, 0).sum(axis=0) / np.maximum(count, 1)
    depth = np.where(count >= min(2, t), depth, 0).astype(np.float32)
    return depth, count.astype(np.int32)


def consistent_views(
    depth_ref: np.ndarray,
    K_ref: np.ndarray,
    pose_ref: np.ndarray,
    sources: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    pixel_tol: float = 1.0,
    rel_tol: float = 0.01,
) -> np.ndarray:
    """``[H, W]`` number of source maps ``(depth, K, cam_from_world)`` confirming ``depth_ref``.

    The geometric pass's own forward-backward check (:func:`colmap_pvs.consistency.check_consistency`):
    a view confirms a pixel when the round trip through its depth lands within ``pixel_tol`` px and
    the depths differ by at most ``rel_tol`` (relative).
    """
    maps = [SourceMaps(np.asarray(d, np.float32), None, K, pose) for d, K, pose in sources]
    res = check_consistency(depth_ref, None, K_ref, pose_ref, maps,
                            max_reproj_error=pixel_tol, max_depth_error=rel_tol)
    return res.agree.sum(0).astype(np.int32)


def label_weight(n_agree: np.ndarray, n_estimates: int, n_views: np.ndarray, check_views: int) -> np.ndarray:
    """``0.5 * agreeing / estimates + 0.5 * min(confirming, check) / check`` (float32)."""
    a = np.asarray(n_agree, np.float32) / max(n_estimates, 1)
    c = np.minimum(np.asarray(n_views, np.float32), check_views) / max(check_views, 1)
    return (0.5 * a + 0.5 * c).astype(np.float32)


# --------------------------------------------------------------------------- scenes


def find_scenes(root: Path) -> list[Path]:
    def is_scene(p: Path) -> bool:
        return (p / "images").is_dir() and any(
            (c / "cameras.bin").is_file() or (c / "cameras.txt").is_file()
            for c in (p / "sparse", p / "sparse" / "0")
        )

    if is_scene(root):
        return [root]
    scenes = sorted(p for p in root.iterdir() if p.is_dir() and is_scene(p))
    if not scenes:
        raise SystemExit(f"no scene (images/ + sparse/) in {root}")
    return scenes


def _sparse_dir(root: Path) -> Path:
    for c in (root / "sparse" / "0", root / "sparse"):
        if (c / "cameras.bin").is_file() or (c / "cameras.txt").is_file():
            return c
    raise SystemExit(f"{root} has no sparse model")


def prepare_workspace(scene: Path, out: Path, max_image_size: int) -> Path:
    """``out`` as a dense workspace of ``scene`` (undistorted; linked when already pinhole)."""
    if (out / "sparse").exists() and (out / "images").exists():
        return out
    sparse = _sparse_dir(scene)
    model = read_sparse_model(sparse, require_pinhole=False, warn_distortion=False)
    pinhole = all(c.is_pinhole for c in model.cameras.values())
    small = all(max(c.width, c.height) <= max_image_size for c in model.cameras.values())
    if pinhole and small:
        out.mkdir(parents=True, exist_ok=True)
        for name, target in (("images", scene / "images"), ("sparse", sparse)):
            if not (out / name).exists():
                os.symlink(target.resolve(), out / name)
    else:
        logger.info("undistorting %s into %s", scene, out)
        undistort(UndistortConfig(image_path=scene / "images", input_path=sparse, output_path=out,
                                  max_image_size=max_image_size))
    (out / "stereo" / "depth_maps").mkdir(parents=True, exist_ok=True)
    return out


def atomic_json(path: Path, obj) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=1, sort_keys=False) + "\n").encode())


def atomic_npz(path: Path, **arrays) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".npz", dir=path.parent)
    os.close(fd)
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)


# --------------------------------------------------------------------------- labelling one scene


@dataclass
class SceneData:
    root: Path
    names: list[str]  # references to label
    Ks: dict[str, np.ndarray]
    poses: dict[str, np.ndarray]
    sizes: dict[str, tuple[int, int]]  # (h, w)
    selection: object


def load_scene(ws: Path, ref_every: int, vs_config: ViewSelectionConfig) -> SceneData:
    model = read_sparse_model(ws / "sparse")
    selection = select_views(model, vs_config)
    Ks, poses, sizes = {}, {}, {}
    for im in model.images.values():
        cam = model.cameras[im.camera_id]
        Ks[im.name] = np.asarray(cam.K, np.float64)
        poses[im.name] = to_homogeneous(im.cam_from_world)
        sizes[im.name] = (cam.height, cam.width)
    refs = sorted(selection.references)
    refs = [n for k, n in enumerate(refs) if k % ref_every == 0]
    return SceneData(ws, refs, Ks, poses, sizes, selection)


class ImageCache:
    def __init__(self, root: Path):
        self.root = root
        self._c: dict[str, np.ndarray] = {}

    def get(self, name: str) -> np.ndarray:
        if name not in self._c:
            if len(self._c) > 64:
                self._c.clear()
            self._c[name] = load_image(self.root / "images" / name)
        return self._c[name]


def estimate_meta(estimate: str, teacher: Teacher, ref: str, sources: list[str], rng) -> str:
    return json.dumps({"v": CACHE_VERSION, "estimate": estimate, "weights": teacher.weights_sha256,
                       "ref": ref, "sources": sources, "range": [float(rng[0]), float(rng[1])]})


def cache_path(ws: Path, estimate: str, name: str) -> Path:
    return ws / "teacher_cache" / estimate.replace(":", "_") / f"{name}.npz"


def run_estimates(sd: SceneData, estimates: list[str], teachers: dict[str, Teacher], runtimes: dict) -> None:
    """Fill the per-image teacher caches (skips valid cache entries)."""
    from tqdm import tqdm

    images = ImageCache(sd.root)
    for name in tqdm(sd.names, desc=f"teachers {sd.root.name}", unit="img", mininterval=10):
        ref = sd.selection.references[name]
        for est in estimates:
            key, _, rng = est.partition(":")
            a, b = (int(x) for x in rng.split("-"))
            sources = list(ref.ranked_names[a:b])
            if not sources:
                continue
            teacher = teachers[key]
            meta = estimate_meta(est, teacher, name, sources, ref.depth_range)
            path = cache_path(sd.root, est, name)
            if path.is_file():
                try:
                    with np.load(path) as z:
                        if str(z["meta"]) == meta:
                            continue
                except (OSError, ValueError, KeyError):
                    pass
            views = [name] + sources
            t0 = time.perf_counter()
            depth, conf = teacher.run([images.get(n) for n in views], [sd.Ks[n] for n in views],
                                      [sd.poses[n] for n in views], *ref.depth_range)
            dt = time.perf_counter() - t0
            runtimes.setdefault(est, []).append(dt)
            logger.debug("%s %s: %.1f s", est, name, dt)
            atomic_npz(path, depth=depth, conf=conf.astype(np.float16), meta=np.array(meta), seconds=dt)


def cached_runtimes(ws: Path, estimates: list[str], names: list[str]) -> dict[str, float]:
    """Mean seconds per image of each estimate, from its cache (so reruns keep the first timings)."""
    out = {}
    for est in estimates:
        secs = []
        for n in names:
            path = cache_path(ws, est, n)
            if path.is_file():
                with np.load(path) as z:
                    secs.append(float(z["seconds"]))
        if secs:
            out[est] = round(float(np.mean(secs)), 2)
    return out


def load_estimate(ws: Path, est: str, name: str):
    path = cache_path(ws, est, name)
    if not path.is_file():
        return None
    with np.load(path) as z:
        return z["depth"], z["conf"].astype(np.float32)


@dataclass(frozen=True)
class Rules:
    agree_tol: float = 0.02
    min_agree: int = 3
    use_confidence: bool = False
    check_views: int = 4
    geo_pixel: float = 1.0
    geo_rel: float = 0.02
    min_consistent: int = 1


def candidates(ws: Path, estimates: list[str], name: str, rules: Rules, hw):
    """``(depth, n_agree)`` of one reference from the cached estimates."""
    ds, vs = [], []
    for est in estimates:
        got = load_estimate(ws, est, name)
        if got is None:
            ds.append(np.zeros(hw, np.float32))
            vs.append(np.zeros(hw, bool))
            continue
        d, c = got
        ok = d > 0
        if rules.use_confidence:
            ok &= c >= TEACHER_KINDS[teacher_of(est)].conf_threshold
        ds.append(d)
        vs.append(ok)
    depth, count = agree(np.stack(ds), np.stack(vs), rules.agree_tol)
    depth = np.where(count >= rules.min_agree, depth, 0).astype(np.float32)
    return depth, count


def check_sources(sd: SceneData, name: str, rules: Rules) -> list[str]:
    refs = set(sd.names)
    return [s for s in sd.selection.references[name].ranked_names if s in refs][: rules.check_views]


def decide(sd: SceneData, estimates: list[str], rules: Rules, names=None, cand_cache=None):
    """Final labels ``{name: (depth, weight, n_agree_map, n_views_map)}`` for ``names``."""
    cand_cache = {} if cand_cache is None else cand_cache

    def cand(n):
        if n not in cand_cache:
            cand_cache[n] = candidates(sd.root, estimates, n, rules, sd.sizes[n])
        return cand_cache[n]

    out = {}
    for name in names if names is not None else sd.names:
        depth, count = cand(name)
        srcs = [(cand(s)[0], sd.Ks[s], sd.poses[s]) for s in check_sources(sd, name, rules)]
        nviews = consistent_views(depth, sd.Ks[name], sd.poses[name], srcs, rules.geo_pixel, rules.geo_rel)
        keep = (depth > 0) & (nviews >= rules.min_consistent)
        final = np.where(keep, depth, 0).astype(np.float32)
        weight = np.where(keep, label_weight(count, len(estimates), nviews, rules.check_views), 0)
        out[name] = (final, weight.astype(np.float32), count, nviews)
    return out


# --------------------------------------------------------------------------- GT evaluation


_HIST_MAX, _HIST_BINS = 0.25, 1000  # histogram of log(pred / gt), 0.0005 wide bins


def _stats(pred: np.ndarray, gt: np.ndarray) -> dict:
    valid = gt > 0
    m = valid & (pred > 0)
    n_gt, n = int(valid.sum()), int(m.sum())
    if n == 0:
        return {"n_gt": n_gt, "n": 0, "abs": 0.0, "rel": 0.0, "w1": 0, "w2": 0, "w5": 0,
                "hist": np.zeros(_HIST_BINS, np.int64)}
    err = np.abs(pred[m] - gt[m]).astype(np.float64)
    rel = err / gt[m]
    logr = np.clip(np.log(pred[m] / gt[m]), -_HIST_MAX, _HIST_MAX)
    hist = np.histogram(logr, bins=_HIST_BINS, range=(-_HIST_MAX, _HIST_MAX))[0]
    return {"n_gt": n_gt, "n": n, "abs": float(err.sum()), "rel": float(rel.sum()),
            "w1": int((rel < 0.01).sum()), "w2": int((rel < 0.02).sum()), "w5": int((rel < 0.05).sum()),
            "hist": hist}


def _add(acc: dict, s: dict) -> None:
    for k, v in s.items():
        acc[k] = acc.get(k, 0) + v


def _row(acc: dict) -> dict:
    n = max(acc.get("n", 0), 1)
    hist = acc.get("hist", np.zeros(_HIST_BINS))
    centers = np.linspace(-_HIST_MAX, _HIST_MAX, _HIST_BINS + 1)
    centers = 0.5 * (centers[1:] + centers[:-1])
    cum = np.cumsum(hist)
    med = float(centers[np.searchsorted(cum, cum[-1] / 2)]) if cum[-1] else 0.0
    aligned = 100.0 * hist[np.abs(centers - med) < np.log(1.01)].sum() / n
    return {"coverage_pct": 100.0 * acc.get("n", 0) / max(acc.get("n_gt", 0), 1),
            "median_ratio": float(np.exp(med)), "within_1pct_aligned": float(aligned),
            "within_1pct": 100.0 * acc.get("w1", 0) / n, "within_2pct": 100.0 * acc.get("w2", 0) / n,
            "within_5pct": 100.0 * acc.get("w5", 0) / n, "absrel": acc.get("rel", 0) / n,
            "mae": acc.get("abs", 0) / n, "pixels": int(acc.get("n", 0))}


def evaluate(sd: SceneData, estimates: list[str], rules: Rules, gt_dir: Path, gt_scale: float) -> dict:
    """Rows of the evaluation table (pooled over pixels of all references)."""
    gts = {}
    for n in sd.names:
        p = gt_dir / (Path(n).stem + ".png")
        if p.is_file():
            g = cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.float32) * gt_scale
            if g.shape != sd.sizes[n]:
                raise SystemExit(f"GT {p} is {g.shape}, image is {sd.sizes[n]}")
            gts[n] = g
    if not gts:
        raise SystemExit(f"no GT depth for the references in {gt_dir}")
    acc: dict[str, dict] = {}

    def add(label, pred, g):
        _add(acc.setdefault(label, {}), _stats(pred, g))

    variants = {
        "agree>=2": Rules(**{**rules.__dict__, "min_agree": 2, "use_confidence": False}),
        "agree>=2 conf": Rules(**{**rules.__dict__, "min_agree": 2, "use_confidence": True}),
        "agree>=3": Rules(**{**rules.__dict__, "min_agree": 3, "use_confidence": False}),
    }
    caches = {k: {} for k in variants}
    for n, g in gts.items():
        for est in estimates:
            got = load_estimate(sd.root, est, n)
            if got is None:
                continue
            d, c = got
            add(f"{est} all", d, g)
            thr = TEACHER_KINDS[teacher_of(est)].conf_threshold
            add(f"{est} conf>={thr}", np.where(c >= thr, d, 0), g)
        for label, r in variants.items():
            cand, _ = candidates(sd.root, estimates, n, r, sd.sizes[n])
            caches[label][n] = (cand, _)
            add(f"{label} (no view check)", cand, g)
    chosen = decide(sd, estimates, rules, names=list(gts))
    for n, (final, weight, *_rest) in chosen.items():
        add("chosen rules", final, gts[n])
        for wmin in (0.625, 0.75):
            add(f"chosen rules, weight>={wmin}", np.where(weight >= wmin, final, 0), gts[n])
    for label, r in variants.items():
        for mc in (1, 2):
            rr = Rules(**{**r.__dict__, "min_consistent": mc})
            res = decide(sd, estimates, rr, names=list(gts), cand_cache=caches[label])
            for n, (final, *_rest) in res.items():
                add(f"{label} + views>={mc}", final, gts[n])
    return {k: _row(v) for k, v in acc.items()}


def format_table(rows: dict) -> str:
    head = (f"{'labels':42s} {'cover%':>7s} {'<1%':>6s} {'<2%':>6s} {'<5%':>6s} {'AbsRel':>7s} {'MAE m':>7s}"
            f" {'med ratio':>9s} {'<1% aligned':>11s}")
    lines = [head, "-" * len(head)]
    for k, r in rows.items():
        lines.append(f"{k:42s} {r['coverage_pct']:7.2f} {r['within_1pct']:6.1f} {r['within_2pct']:6.1f} "
                     f"{r['within_5pct']:6.1f} {r['absrel']:7.4f} {r['mae']:7.4f} {r['median_ratio']:9.4f} "
                     f"{r['within_1pct_aligned']:11.1f}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- main


def settings_of(args, rules: Rules, estimates, teachers: dict[str, Teacher]) -> dict:
    return {
        "estimates": estimates,
        "rules": rules.__dict__,
        "max_image_size": args.max_image_size,
        "ref_every": args.ref_every,
        "num_views": args.num_views,
        "weights": {k: t.weights_sha256 for k, t in teachers.items()},
        "cache_version": CACHE_VERSION,
        "label_version": LABEL_VERSION,
    }


def label_scene(scene: Path, args, teachers, estimates, rules: Rules) -> dict:
    ws = prepare_workspace(scene, Path(args.out) / scene.name, args.max_image_size)
    vs_cfg = ViewSelectionConfig(num_views=args.num_views)
    sd = load_scene(ws, args.ref_every, vs_cfg)
    settings = settings_of(args, rules, estimates, teachers)
    shash = hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]
    labels_json = ws / "labels.json"
    old = json.loads(labels_json.read_text()) if labels_json.is_file() else {}
    old_images = old.get("images", {}) if old.get("settings_hash") == shash else {}
    maps = ws / "stereo" / "depth_maps"

    def done(n):
        return (n in old_images and (maps / f"{n}.teacher.bin").is_file()
                and (maps / f"{n}.teacher_weight.bin").is_file())

    todo = [n for n in sd.names if not done(n)]
    logger.info("%s: %d references, %d to label", scene.name, len(sd.names), len(todo))
    runtimes: dict[str, list[float]] = {}
    # every reference's candidates are needed by its neighbours: run teachers for all (cached)
    if todo:
        run_estimates(sd, estimates, teachers, runtimes)
    images = dict(old_images)
    cand_cache: dict = {}
    for n in todo:
        final, weight, count, nviews = decide(sd, estimates, rules, names=[n], cand_cache=cand_cache)[n]
        (maps / n).parent.mkdir(parents=True, exist_ok=True)
        write_depth_map(maps / f"{n}.teacher.bin", final)
        write_depth_map(maps / f"{n}.teacher_weight.bin", weight)
        h, w = final.shape
        images[n] = {"coverage_pct": round(100.0 * float((final > 0).mean()), 3),
                     "candidate_pct": round(100.0 * float((count >= rules.min_agree).mean()), 3),
                     "mean_weight": round(float(weight[final > 0].mean()) if (final > 0).any() else 0.0, 4),
                     "check_views": check_sources(sd, n, rules), "size": [w, h],
                     "depth_range": list(sd.selection.references[n].depth_range)}
    rt = cached_runtimes(ws, estimates, sd.names)
    record = {
        "scene": scene.name, "source": str(scene), "settings_hash": shash, "settings": settings,
        "teachers": {k: t.provenance() for k, t in teachers.items()},
        "teacher_seconds_per_image": rt,
        "coverage_pct": (round(float(np.mean([v["coverage_pct"] for v in images.values()])), 3)
                         if images else 0),
        "images": {n: images[n] for n in sd.names if n in images},
    }
    if args.evaluate_gt:
        rows = evaluate(sd, estimates, rules, Path(args.evaluate_gt), args.gt_scale)
        table = format_table(rows)
        print(f"\n{scene.name}: {len(sd.names)} references\n{table}\n", flush=True)
        atomic_json(ws / "evaluation.json", {"rules": rules.__dict__, "estimates": estimates, "rows": rows})
        record["evaluation"] = rows
    atomic_json(labels_json, record)
    return record


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_clone_args(p)
    p.add_argument("--scenes", required=True, help="a scene folder or a folder of scene folders")
    p.add_argument("--out", required=True, help="output folder (one dense workspace per scene)")
    p.add_argument("--only", nargs="*", default=None, help="only these scene names")
    p.add_argument("--estimates", default=DEFAULT_ESTIMATES,
                   help="teacher:first-stop (slice of the ranked sources), comma separated")
    p.add_argument("--max_image_size", type=int, default=640, help="longest image side")
    p.add_argument("--num_views", type=int, default=9, help="view selection: views per reference")
    p.add_argument("--ref_every", type=int, default=1, help="label every k-th reference only")
    p.add_argument("--agree_tol", type=float, default=Rules.agree_tol)
    p.add_argument("--min_agree", type=int, default=Rules.min_agree)
    p.add_argument("--use_confidence", action="store_true", help="also require each teacher's confidence")
    p.add_argument("--check_views", type=int, default=Rules.check_views)
    p.add_argument("--geo_pixel", type=float, default=Rules.geo_pixel)
    p.add_argument("--geo_rel", type=float, default=Rules.geo_rel)
    p.add_argument("--min_consistent", type=int, default=Rules.min_consistent)
    p.add_argument("--evaluate_gt", default=None, help="GT depth folder (NAME-stem.png, uint16)")
    p.add_argument("--gt_scale", type=float, default=0.001, help="GT units to metres")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    p.add_argument("-v", "--verbose", action="store_true")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    torch.set_num_threads(args.threads)
    estimates = parse_estimates(args.estimates)
    rules = Rules(args.agree_tol, args.min_agree, args.use_confidence, args.check_views, args.geo_pixel,
                  args.geo_rel, args.min_consistent)
    teachers = load_teachers({teacher_of(e) for e in estimates}, clones(args))
    scenes = find_scenes(Path(args.scenes))
    if args.only:
        scenes = [s for s in scenes if s.name in set(args.only)]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary_path = out / "labels.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {"scenes": {}}
    for scene in scenes:
        t0 = time.perf_counter()
        rec = label_scene(scene, args, teachers, estimates, rules)
        summary["scenes"][scene.name] = {
            "references": len(rec["images"]), "coverage_pct": rec["coverage_pct"],
            "teacher_seconds_per_image": rec["teacher_seconds_per_image"],
            "settings_hash": rec["settings_hash"],
            "wall_seconds": round(time.perf_counter() - t0, 1),
        }
        summary["teachers"] = rec["teachers"]
        atomic_json(summary_path, summary)
        logger.info("%s: coverage %.1f %% (%.0f s)", scene.name, rec["coverage_pct"],
                    time.perf_counter() - t0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
