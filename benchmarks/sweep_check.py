"""Does a classical NCC plane sweep know something the network does not? (issues 10 and 13, stop 29)

The network's maps of fern and colmap-statue are smooth blobs, while a plain plane sweep with
normalised cross-correlation (NCC) shows the fern's fronds and the statue's crown prongs crisply
(``benchmarks/sweep_fern_statue.jpg``). This script measures, against ground truth, whether the
sweep's depth should replace the network's anywhere. It needs a workspace whose photometric maps
``colmap-pvs stereo`` already wrote (``hololens_quick.py`` makes one; so does ``colmap-pvs demo``,
with exact synthetic GT) and, for each reference, the sweep over the same sources at the map size:

- ``planes`` fronto-parallel planes uniform in inverse depth over the reference's depth range (from
  its provenance), each source warped by the plane's homography (``cv2.warpPerspective``), the NCC of
  ``window x window`` patches by box filters, the mean of the ``best_k`` best sources per pixel (as in
  Gipuma or COLMAP's view selection), the best plane refined by a parabola; patches with a grey
  standard deviation under ``min_texture`` (reference or warped source) or partly outside a source
  score -1;
- the score of the network's own depth (the best score within one plane of it).

Printed, on the GT pixels of every reference: the network's % within 5 %, and for each score threshold
``tau`` and margin ``m``: the pixels where the sweep scores at least ``tau`` and beats the network's
depth by at least ``m`` ("taken"), the % within 5 % there of the sweep and of the network, and of the
merged map. With ``--pictures NAME,...`` it writes image | network | sweep | score | sweep where the
score is >= 0.5 for those references to ``--out``::

    python benchmarks/hololens_quick.py --tag base --stride 9          # the workspace, 20 refs
    python benchmarks/sweep_check.py --workspace outputs/benchmarks/hololens/quick/base_clean \\
        --gt ../shared/data/hololens-dev/depth --gt_scale 0.001
    colmap-pvs demo /tmp/demo && python benchmarks/sweep_check.py --workspace /tmp/demo \\
        --gt /tmp/demo/gt/depth_maps
    python benchmarks/sweep_check.py --workspace outputs/benchmarks/statue/base \\
        --pictures DSC_5290.jpg,DSC_5285.jpg --out benchmarks/sweep_statue.jpg

GT: ``NAME`` (a 16-bit PNG, times ``--gt_scale``) or ``NAME.npy`` in ``--gt``, at the map size.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from colmap_pvs.io.maps import read_array
from colmap_pvs.io.sparse import read_sparse_model

_HALF = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])  # COLMAP pixel = cv2 pixel + 0.5
_HALF_INV = np.linalg.inv(_HALF)


@dataclass(frozen=True, eq=False)
class View:
    """``image`` ``[H, W]`` float32 grey in [0, 1], ``K`` ``[3, 3]`` at that size,
    ``cam_from_world`` ``[3, 4]``."""

    image: np.ndarray
    K: np.ndarray
    cam_from_world: np.ndarray


def plane_homography(ref: View, src: View, depth: float) -> np.ndarray:
    """``[3, 3]`` reference pixel -> source pixel (COLMAP's pixel centres) of the plane ``z = depth``
    of the reference camera: ``K_s (R + t e3^T / depth) K_r^-1`` with ``(R, t)`` = src_from_ref."""
    pr, ps = ref.cam_from_world, src.cam_from_world
    R = ps[:, :3] @ pr[:, :3].T
    t = ps[:, 3] - R @ pr[:, 3]
    return src.K @ (R + np.outer(t, [0.0, 0.0, 1.0 / depth])) @ np.linalg.inv(ref.K)


def _box(x: np.ndarray, window: int) -> np.ndarray:
    return cv2.boxFilter(x, -1, (window, window), borderType=cv2.BORDER_REFLECT)


def _mean_of_best(scores: np.ndarray, k: int) -> np.ndarray:
    """``[H, W]`` mean of the ``k`` largest of ``scores`` ``[S, H, W]`` (a running top-k, no sort)."""
    top = [np.full(scores.shape[1:], -np.inf, np.float32) for _ in range(k)]
    for x in scores:
        for j in range(k):
            top[j], x = np.maximum(top[j], x), np.minimum(top[j], x)
    return sum(top[1:], top[0]) / np.float32(k)


def plane_sweep(ref: View, sources: list[View], depth_range: tuple[float, float], *, planes: int = 64,
                window: int = 7, best_k: int = 2, min_texture: float = 0.01,
                reference_depth: np.ndarray | None = None):
    """``(depth, score, reference_score)`` ``[H, W]`` of ``ref``: the best plane's depth (parabola-refined,
    0 where nothing scored), its score (-1 = none) and the best score within one plane of
    ``reference_depth`` (``None`` without it)."""
    r = np.ascontiguousarray(ref.image, dtype=np.float32)
    h, w = r.shape
    mr = _box(r, window)
    sr = np.sqrt(np.maximum(_box(r * r, window) - mr * mr, 0.0))
    textured = sr >= min_texture
    min_var = np.float32(max(min_texture, 1e-3) ** 2)  # float32 cancellation makes flat patches noise
    inv_sr = np.where(textured, 1.0 / np.maximum(sr, 1e-6), 0.0).astype(np.float32)
    inv = np.linspace(1.0 / depth_range[1], 1.0 / depth_range[0], planes)
    best = np.full((h, w), -np.inf, np.float32)
    before = np.full((h, w), -np.inf, np.float32)  # score at the best plane - 1
    after = np.full((h, w), -np.inf, np.float32)  # score at the best plane + 1
    arg = np.zeros((h, w), np.int32)
    prev = np.full((h, w), -np.inf, np.float32)
    ref_idx = ref_score = None
    if reference_depth is not None:
        with np.errstate(divide="ignore"):
            pos = (np.where(reference_depth > 0, 1.0 / reference_depth, -1.0) - inv[0]) / (inv[1] - inv[0])
        ref_idx = np.where(reference_depth > 0, np.rint(pos), -10).astype(np.int32)
        ref_score = np.full((h, w), -1.0, np.float32)
    images = [np.ascontiguousarray(s.image, dtype=np.float32) for s in sources]
    ones = [np.ones_like(i) for i in images]
    scores = np.empty((len(sources), h, w), np.float32)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    for i, iv in enumerate(inv):
        for k, (view, img) in enumerate(zip(sources, images, strict=True)):
            m = _HALF_INV @ plane_homography(ref, view, 1.0 / iv) @ _HALF
            warped = cv2.warpPerspective(img, m, (w, h), flags=flags, borderValue=0.0)
            # every pixel of the window inside the source (a NaN border would poison the box sums)
            mask = cv2.warpPerspective(ones[k], m, (w, h), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                       borderValue=0.0)
            inside = _box(mask, window)
            mw = _box(warped, window)
            vw = _box(warped * warped, window) - mw * mw
            cov = _box(warped * r, window) - mw * mr
            ok = (vw >= min_var) & (inside > 0.999)
            scores[k] = np.where(ok, cov * inv_sr / np.sqrt(np.maximum(vw, min_var)), -1.0)
        cur = np.where(textured, np.clip(_mean_of_best(scores, best_k), -1.0, 1.0), -1.0).astype(np.float32)
        if ref_idx is not None:
            ref_score = np.where(np.abs(ref_idx - i) <= 1, np.maximum(ref_score, cur), ref_score)
        better = cur > best
        after = np.where(arg == i - 1, cur, after)
        before = np.where(better, prev, before)
        after = np.where(better, -np.inf, after)
        best = np.where(better, cur, best)
        arg = np.where(better, i, arg)
        prev = cur
    denom = before - 2.0 * best + after
    inner = np.isfinite(before) & np.isfinite(after) & (denom < 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        offset = np.where(inner, 0.5 * (before - after) / np.where(inner, denom, -1.0), 0.0)
    inv_depth = inv[arg] + np.clip(offset, -0.5, 0.5) * (inv[1] - inv[0])
    valid = best > -1.0
    return (np.where(valid, 1.0 / inv_depth, 0.0).astype(np.float32),
            np.where(valid, best, -1.0).astype(np.float32), ref_score)


def load_view(ws: Path, model, name: str, size: tuple[int, int]) -> View:
    """:class:`View` of image ``name`` of workspace ``ws`` (sparse ``model``) at ``size`` ``(W, H)``."""
    im = model.image_by_name(name)
    cam = model.camera_of(im)
    w, h = size
    img = cv2.imread(str(ws / "images" / name), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255
    if img.shape != (h, w):
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    K = cam.K.copy()
    K[0] *= w / cam.width
    K[1] *= h / cam.height
    return View(img, K, np.asarray(im.cam_from_world, np.float64)[:3])


def read_gt(folder: Path | None, name: str, scale: float) -> np.ndarray | None:
    """GT depth of ``name`` in ``folder``: ``NAME.npy``, or ``NAME`` (a 16-bit PNG) times ``scale``;
    ``None`` without it."""
    if folder is None:
        return None
    if (folder / f"{name}.npy").is_file():
        return np.load(folder / f"{name}.npy").astype(np.float32)
    if (folder / name).is_file():
        return cv2.imread(str(folder / name), cv2.IMREAD_UNCHANGED).astype(np.float32) * scale
    return None


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--workspace", type=Path, required=True, help="dense workspace after colmap-pvs stereo")
    p.add_argument("--gt", type=Path, default=None, help="GT depth folder (NAME png or NAME.npy)")
    p.add_argument("--gt_scale", type=float, default=1.0, help="GT PNG value -> depth units")
    p.add_argument("--refs", type=int, default=0, help="at most this many references (0 = all with GT)")
    p.add_argument("--planes", type=int, default=64)
    p.add_argument("--window", type=int, default=7)
    p.add_argument("--best_k", type=int, default=2)
    p.add_argument("--min_texture", type=float, default=0.01)
    p.add_argument("--pictures", default="", help="comma-separated reference names to draw")
    p.add_argument("--out", type=Path, default=Path("outputs/benchmarks/sweep_check.jpg"))
    a = p.parse_args()
    ws = a.workspace
    model = read_sparse_model(ws / "sparse")

    def view(name: str, size: tuple[int, int]) -> View:
        return load_view(ws, model, name, size)

    def gt_of(name: str) -> np.ndarray | None:
        return read_gt(a.gt, name, a.gt_scale)

    def run(name: str):
        prov = json.loads((ws / "stereo" / "provenance" / f"{name}.photometric.json").read_text())
        size = tuple(prov["image_size"])
        net = read_array(ws / "stereo" / "depth_maps" / f"{name}.photometric.bin")
        ref = view(name, size)
        t0 = time.perf_counter()
        depth, score, at_net = plane_sweep(ref, [view(s, size) for s in prov["sources"]],
                                           prov["settings"]["depth_range"], planes=a.planes, window=a.window,
                                           best_k=a.best_k, min_texture=a.min_texture, reference_depth=net)
        return prov, net, depth, score, at_net, time.perf_counter() - t0

    suffix = ".photometric.json"
    names = sorted(f.name[: -len(suffix)] for f in (ws / "stereo" / "provenance").glob(f"*{suffix}"))
    seconds, rows = [], []
    if a.gt is not None:
        with_gt = [n for n in names if gt_of(n) is not None]
        for n in with_gt[: a.refs or None]:
            _, net, depth, score, at_net, s = run(n)
            gt = gt_of(n)
            if gt.shape != net.shape:
                print(f"skipping {n}: GT {gt.shape} and map {net.shape} differ")
                continue
            seconds.append(s)
            m = gt > 0
            rows.append(np.stack([gt[m], net[m], depth[m], score[m], at_net[m]]))
        if not rows:
            print(f"no reference of {ws} has GT in {a.gt}")
            return 2
        gt, net, depth, score, at_net = np.concatenate(rows, 1)

        def within(d, sel=slice(None)):
            return 100.0 * np.mean((np.abs(d - gt) / gt)[sel] < 0.05)

        print(f"{ws}: {len(rows)} references, {gt.size} GT pixels, sweep {np.mean(seconds):.2f} s per map "
              f"({a.planes} planes, {a.window}x{a.window}, best {a.best_k}); "
              f"network: {within(net):.1f} % within 5 %")
        print("| tau | margin | taken % | sweep % <5 % there | network % <5 % there | merged % <5 % |")
        print("|---|---|---|---|---|---|")
        for tau in (0.5, 0.7, 0.9):
            for margin in (0.0, 0.1, 0.3):
                take = (score >= tau) & (score - at_net >= margin)
                merged = np.where(take, depth, net)
                print(f"| {tau} | {margin} | {100 * take.mean():.1f} | {within(depth, take):.1f} | "
                      f"{within(net, take):.1f} | {within(merged):.1f} |")
    if a.pictures:
        panels = []
        for n in a.pictures.split(","):
            prov, net, depth, score, _, _ = run(n)
            lo, hi = (1.0 / d for d in prov["settings"]["depth_range"][::-1])
            w, h = prov["image_size"]

            def colour(d, mask=None, lo=lo, hi=hi):
                x = np.clip((1.0 / np.maximum(d, 1e-6) - lo) / (hi - lo), 0, 1)
                c = cv2.applyColorMap((255 * x).astype(np.uint8), cv2.COLORMAP_TURBO)
                c[(d <= 0) if mask is None else ~mask] = 0
                return c

            img = cv2.resize(cv2.imread(str(ws / "images" / n)), (w, h))
            sc = cv2.applyColorMap((255 * np.clip(score, 0, 1)).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
            panels.append(np.hstack([img, colour(net), colour(depth), sc, colour(depth, score >= 0.5)]))
        width = max(x.shape[1] for x in panels)
        panels = [cv2.copyMakeBorder(x, 0, 0, 0, width - x.shape[1], cv2.BORDER_CONSTANT) for x in panels]
        a.out.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(a.out), np.vstack(panels), [cv2.IMWRITE_JPEG_QUALITY, 85])
        print(f"picture: {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
