"""Does the learned visibility tell the sources that see a pixel from those that don't? (hololens-dev)

Reads a ``hololens_quick.py`` workspace (its ``stereo/visibility_maps``, the sources in each
evaluated reference's provenance file, the COLMAP model's poses) and the ground-truth depth. For each coarse
pixel of each reference with GT depth, the true visibility in each source is: the GT point projects
in front of that source and inside its image, and the source's own GT depth there agrees within 5 %
(not occluded; a source pixel without GT counts as seeing it). Prints, per source slot (best first;
with ``--disturbed`` workspaces the last two are the far frames), the share of pixels inside and
truly visible, the learned visibility's mean on truly visible and on hidden pixels, and how well it
ranks them (AUC: the chance a visible pixel gets more than a hidden one). The coarse grid is mapped
onto the whole image, exact when the network's input needs no padding (540x360 at network scale
0.8: 432x288, grid 108x72)::

    python benchmarks/hololens_quick.py --stride 3 --offset 0 --disturbed --tag T
    python benchmarks/visibility_check.py --tag T_disturbed
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import real_depth as rd

from colmap_pvs.evaluate import read_gt_depth
from colmap_pvs.geometry import backproject_depth, scale_intrinsics
from colmap_pvs.io.maps import read_array
from colmap_pvs.io.sparse import read_sparse_model
from colmap_pvs.upsampling import resize_nearest

#: Relative depth difference within which a source's GT depth sees the reference's point.
OCCLUSION_TOLERANCE = 0.05


def auc(score: np.ndarray, positive: np.ndarray) -> float:
    """Area under the ROC curve of ``score`` for the boolean ``positive`` (ties count half)."""
    pos, neg = int(positive.sum()), int((~positive).sum())
    if pos == 0 or neg == 0:
        return float("nan")
    order = np.argsort(score, kind="stable")
    ranks = np.empty(len(score))
    sorted_scores = score[order]
    # average ranks over ties
    _, first, counts = np.unique(sorted_scores, return_index=True, return_counts=True)
    avg = first + (counts - 1) / 2.0
    ranks[order] = np.repeat(avg, counts)
    return float((ranks[positive].sum() - pos * (pos - 1) / 2.0) / (pos * neg))


def true_visibility(model, ref_name: str, src_name: str, gt_dir: Path, size: tuple[int, int]):
    """``(inside, visible, valid)`` ``[h, w]`` bool maps on the ``size`` ``(w, h)`` grid of ``ref_name``."""
    w, h = size
    ref = model.image_by_name(ref_name)
    cam = model.cameras[ref.camera_id]
    gt = resize_nearest(read_gt_depth(gt_dir / ref_name, 0.001), h, w)
    valid = gt > 0
    K_grid = scale_intrinsics(cam.K, w / cam.width, h / cam.height)
    points = backproject_depth(gt, K_grid)[valid].T  # [3, P] in the reference camera
    R, t = ref.cam_from_world[:, :3], ref.cam_from_world[:, 3]
    world = R.T @ (points - t[:, None])
    src = model.image_by_name(src_name)
    src_cam = model.cameras[src.camera_id]
    p = src_cam.K @ (src.cam_from_world[:, :3] @ world + src.cam_from_world[:, 3:])
    z = p[2]
    u, v = p[0] / np.maximum(z, 1e-9), p[1] / np.maximum(z, 1e-9)
    ins = (z > 1e-6) & (u >= 0) & (u < src_cam.width) & (v >= 0) & (v < src_cam.height)
    src_gt = read_gt_depth(gt_dir / src_name, 0.001)
    col = np.clip(u.astype(int), 0, src_cam.width - 1)
    row = np.clip(v.astype(int), 0, src_cam.height - 1)
    seen = src_gt[row, col]
    vis = ins & ((seen <= 0) | (np.abs(seen - z) <= OCCLUSION_TOLERANCE * z))
    inside, visible = np.zeros((h, w), bool), np.zeros((h, w), bool)
    inside[valid], visible[valid] = ins, vis
    return inside, visible, valid


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tag", required=True, help="a workspace under WORK/quick, e.g. base_disturbed")
    p.add_argument("--data", type=Path, default=rd.DEFAULT_DATA)
    p.add_argument("--work_dir", type=Path, default=rd.DEFAULT_WORK)
    a = p.parse_args()
    ws = a.work_dir / "quick" / a.tag
    if not (a.data / "depth").is_dir():
        print(f"hololens-dev data not found at {a.data}; nothing to do")
        return 2
    if not (ws / "stereo" / "visibility_maps").is_dir():
        print(f"{ws} has no stereo/visibility_maps: run benchmarks/hololens_quick.py first")
        return 2
    model = read_sparse_model(ws / "sparse")
    provenance = sorted((ws / "stereo" / "provenance").glob("*.photometric.json"))
    metrics = ws / "metrics.photometric.json"
    if metrics.is_file():  # the evaluated references only (the others are sources with maps of their own)
        evaluated = set(json.loads(metrics.read_text())["config"]["images"])
        provenance = [q for q in provenance if q.name[: -len(".photometric.json")] in evaluated]
    slots: dict[int, list] = {}
    learned, truth = [], []
    for path in provenance:
        name = path.name[: -len(".photometric.json")]
        vis_path = ws / "stereo" / "visibility_maps" / f"{name}.bin"
        if not vis_path.is_file():
            continue
        sources = json.loads(path.read_text())["settings"]["sources"]
        vis = read_array(vis_path)
        h, w = vis.shape[:2]
        for k, src in enumerate(sources):
            inside, visible, valid = true_visibility(model, name, src, a.data / "depth", (w, h))
            slots.setdefault(k, []).append((inside[valid].mean(), visible[valid].mean()))
            learned.append(vis[..., k][valid])
            truth.append((visible[valid], np.full(valid.sum(), k)))
    if not learned:
        print(f"{ws}: no reference with a visibility map")
        return 2
    score = np.concatenate(learned)
    visible = np.concatenate([t[0] for t in truth])
    slot = np.concatenate([t[1] for t in truth])
    print(f"{ws}: {len(provenance)} references, {score.size} (pixel, source) pairs with GT")
    print("| source slot | inside its image | truly visible | learned vis., visible | learned vis., hidden "
          "| AUC |")
    print("|---|---|---|---|---|---|")
    for k, rows in sorted(slots.items()):
        m = slot == k
        ins, vis = np.mean(rows, axis=0)
        print(f"| {k + 1} | {100 * ins:.1f} % | {100 * vis:.1f} % | {score[m & visible].mean():.3f} | "
              f"{score[m & ~visible].mean():.3f} | {auc(score[m], visible[m]):.3f} |")
    print(f"| all | | {100 * visible.mean():.1f} % | {score[visible].mean():.3f} | "
          f"{score[~visible].mean():.3f} | {auc(score, visible):.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
