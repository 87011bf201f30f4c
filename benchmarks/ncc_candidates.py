"""Can correlation pick among the network's own depths, and is the GT photo-consistent? (issue 10, stop 30)

Two measurements on a workspace whose photometric maps ``colmap-pvs stereo`` wrote, with GT depth:

- ``candidates``: each pixel's candidates are the network's depth map shifted by ``--radii`` pixels in 8
  directions (and unshifted), so a pixel next to a depth edge gets the depths of both sides. Each
  candidate map is scored like ``sweep_check.py`` (``window x window`` NCC, mean of the ``best_k`` best
  sources), but with every window warped by the candidate map itself (per-pixel depth, not a plane).
  Prints the network's % within 5 %, the oracle's (the best candidate per pixel) and, for each score
  threshold and margin over the network's own score, the pixels where the NCC winner replaces the
  network's depth and the % within 5 % of the merged map.
- ``gt_scale``: the same NCC at the GT depth times 0.94 ... 1.06 and at the GT shifted by 2 or 4 px.
  If the GT agrees with the images and poses, the mean score peaks at scale 1 and shift 0::

    python benchmarks/hololens_quick.py --tag all --all_references --stride 3
    python benchmarks/ncc_candidates.py candidates --workspace outputs/benchmarks/hololens/quick/all_clean \\
        --gt ../shared/data/hololens-dev/depth --gt_scale 0.001 --refs 8
    python benchmarks/ncc_candidates.py gt_scale --workspace outputs/benchmarks/hololens/quick/all_clean \\
        --gt ../shared/data/hololens-dev/depth --gt_scale 0.001 --refs 20

Results: ``benchmarks/RESULTS.md``, stop 30.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
from sweep_check import _HALF_INV, View, _box, _mean_of_best, load_view, read_gt

from colmap_pvs.io.maps import read_array
from colmap_pvs.io.sparse import read_sparse_model

DIRECTIONS = ((1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1))


def source_coords(ref: View, src: View, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y)`` ``[H, W]`` float32 cv2 pixel coordinates in ``src`` of each reference pixel at
    ``depth`` (``-1e4`` where invalid or behind the source)."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)  # COLMAP pixel centres
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(ref.K).T
    pr, ps = ref.cam_from_world, src.cam_from_world
    R = ps[:, :3] @ pr[:, :3].T
    t = ps[:, 3] - R @ pr[:, 3]
    p = (rays * depth[..., None] @ R.T + t) @ src.K.T @ _HALF_INV.T
    ok = (p[..., 2] > 1e-6) & (depth > 0)
    z = np.where(ok, p[..., 2], 1.0)
    return (np.where(ok, p[..., 0] / z, -1e4).astype(np.float32),
            np.where(ok, p[..., 1] / z, -1e4).astype(np.float32))


def ncc_of_depth(ref: View, sources: list[View], depth: np.ndarray, *, window: int = 7, best_k: int = 2,
                 min_texture: float = 0.01) -> np.ndarray:
    """``[H, W]`` score of ``depth`` ``[H, W]``: the mean NCC of the ``best_k`` best sources, every
    window warped by ``depth`` itself; -1 where untextured or unseen."""
    r = ref.image
    mr = _box(r, window)
    sr = np.sqrt(np.maximum(_box(r * r, window) - mr * mr, 0.0))
    textured = sr >= min_texture
    min_var = np.float32(min_texture**2)
    inv_sr = np.where(textured, 1.0 / np.maximum(sr, 1e-6), 0.0).astype(np.float32)
    scores = np.empty((len(sources), *r.shape), np.float32)
    for k, s in enumerate(sources):
        x, y = source_coords(ref, s, depth)
        warped = cv2.remap(s.image, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        inside = _box(cv2.remap(np.ones_like(s.image), x, y, cv2.INTER_NEAREST,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=0), window)
        mw = _box(warped, window)
        vw = _box(warped * warped, window) - mw * mw
        cov = _box(warped * r, window) - mw * mr
        ok = (vw >= min_var) & (inside > 0.999)
        scores[k] = np.where(ok, cov * inv_sr / np.sqrt(np.maximum(vw, min_var)), -1.0)
    return np.where(textured, np.clip(_mean_of_best(scores, best_k), -1, 1), -1).astype(np.float32)


def shifted(depth: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """``out[r, c] = depth[r + dy, c + dx]`` (0 outside)."""
    h, w = depth.shape
    out = np.zeros_like(depth)
    out[max(0, -dy):h + min(0, -dy), max(0, -dx):w + min(0, -dx)] = \
        depth[max(0, dy):h + min(0, dy), max(0, dx):w + min(0, dx)]
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("what", choices=("candidates", "gt_scale"))
    p.add_argument("--workspace", type=Path, required=True)
    p.add_argument("--gt", type=Path, required=True, help="GT depth folder (NAME png or NAME.npy)")
    p.add_argument("--gt_scale", type=float, default=1.0, help="GT PNG value -> depth units")
    p.add_argument("--refs", type=int, default=8, help="references, evenly spread over those with GT")
    p.add_argument("--radii", type=int, nargs="+", default=[4, 8, 16, 32])
    a = p.parse_args()
    ws = a.workspace
    model = read_sparse_model(ws / "sparse")

    def view(name: str, size: tuple[int, int]) -> View:
        return load_view(ws, model, name, size)

    suffix = ".photometric.json"
    names = sorted(f.name[: -len(suffix)] for f in (ws / "stereo" / "provenance").glob(f"*{suffix}"))
    names = [n for n in names if read_gt(a.gt, n, a.gt_scale) is not None]
    names = names[:: max(1, len(names) // a.refs)][: a.refs]
    if not names:
        print(f"no reference of {ws} has GT in {a.gt}")
        return 2
    rows, curves = [], []
    scales = (0.94, 0.96, 0.98, 1.0, 1.02, 1.04, 1.06)
    shifts = ((0, 0), (2, 0), (-2, 0), (0, 2), (0, -2), (4, 0), (-4, 0), (0, 4), (0, -4))
    for n in names:
        prov = json.loads((ws / "stereo" / "provenance" / f"{n}{suffix}").read_text())
        size = tuple(prov["image_size"])
        ref, srcs = view(n, size), [view(s, size) for s in prov["sources"]]
        gt = read_gt(a.gt, n, a.gt_scale)
        t0 = time.perf_counter()
        if a.what == "gt_scale":
            base = ncc_of_depth(ref, srcs, gt)
            m = (gt > 0) & (base > -1)
            curve = [float(ncc_of_depth(ref, srcs, gt * s)[m].mean()) for s in scales]
            by_shift = []
            for dx, dy in shifts:
                g = shifted(gt, dx, dy)
                by_shift.append(float(ncc_of_depth(ref, srcs, g)[m & (g > 0)].mean()))
            curves.append(curve)
            print(f"{n}: textured {100 * m.mean():.0f} % of the pixels; score at GT x "
                  + " ".join(f"{s}: {c:.3f}" for s, c in zip(scales, curve, strict=True))
                  + f"; best shift {shifts[int(np.argmax(by_shift))]} ({time.perf_counter() - t0:.1f} s)")
            continue
        net = read_array(ws / "stereo" / "depth_maps" / f"{n}.photometric.bin")
        own = ncc_of_depth(ref, srcs, net)
        best, best_depth = own.copy(), net.copy()
        oracle = np.abs(net - gt) / np.maximum(gt, 1e-6)
        for r in a.radii:
            for ux, uy in DIRECTIONS:
                norm = np.hypot(ux, uy)
                cand = shifted(net, int(round(r * ux / norm)), int(round(r * uy / norm)))
                score = ncc_of_depth(ref, srcs, cand)
                better = (score > best) & (cand > 0)
                best, best_depth = np.where(better, score, best), np.where(better, cand, best_depth)
                err = np.abs(cand - gt) / np.maximum(gt, 1e-6)
                oracle = np.where(cand > 0, np.minimum(oracle, err), oracle)
        m = gt > 0
        rows.append(np.stack([gt[m], net[m], best_depth[m], best[m], own[m], oracle[m]]))
        print(f"{n}: {time.perf_counter() - t0:.1f} s")
    if a.what == "gt_scale":
        mean = np.mean(curves, axis=0)
        print("mean score at GT x " + " ".join(f"{s}: {c:.3f}" for s, c in zip(scales, mean, strict=True)))
        print("best scale per reference: " + " ".join(str(scales[int(np.argmax(c))]) for c in curves))
        return 0
    gt, net, cand, score, own, oracle = np.concatenate(rows, 1)

    def within(d: np.ndarray, sel: np.ndarray | slice = slice(None)) -> float:
        return 100.0 * float(np.mean((np.abs(d - gt) / gt)[sel] < 0.05))

    print(f"{len(rows)} references, {gt.size} GT pixels: network {within(net):.1f} % within 5 %, "
          f"best candidate (oracle) {100 * np.mean(oracle < 0.05):.1f} %")
    print("| score >= | margin | taken % | NCC winner % <5 % there | network % there | merged % <5 % |")
    print("|---|---|---|---|---|---|")
    for tau in (0.5, 0.7, 0.8):
        for margin in (0.0, 0.1, 0.2):
            take = (score >= tau) & (score - own >= margin) & (cand != net)
            print(f"| {tau} | {margin} | {100 * take.mean():.1f} | {within(cand, take):.1f} | "
                  f"{within(net, take):.1f} | {within(np.where(take, cand, net)):.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
