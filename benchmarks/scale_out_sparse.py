"""What every Ray worker holds before its first image: the sparse model and the view selection of a
large scene (numbers for ``docs/SCALE_OUT.md``).

    python benchmarks/scale_out_sparse.py --images 5000
    python benchmarks/scale_out_sparse.py --images 1000 2000 5000 --points_per_image 2000 --track_length 6

Builds a synthetic :class:`colmap_pvs.types.SparseModel` (cameras on a long path, every point seen by
``track_length`` consecutive images, ``points_per_image`` observations per image: the shape of a
COLMAP model of a video-like capture) and, each size in its own subprocess, prints: the model's array
bytes and its pickled size (what shipping it through Ray's object store would cost),
the time and the peak-RSS increase of :func:`colmap_pvs.views.select_views` (what
``prepare_stereo`` runs once per worker) and the bytes of the selection that stays resident
(its dense ``[n, n]`` score and shared-point matrices).
"""

from __future__ import annotations

import argparse
import json
import pickle
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def _model(n_images: int, points_per_image: int, track_length: int, seed: int = 0):
    import numpy as np

    from colmap_pvs.types import Camera, Image, Points3D, SparseModel

    rng = np.random.default_rng(seed)
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    cameras = {1: Camera(1, "PINHOLE", 640, 480, K, np.array([500.0, 500.0, 320, 240]))}
    step = max(1, points_per_image // track_length)  # new points per image
    n_points = n_images * step
    # Point j is first seen by image j // step and by the next track_length - 1 images.
    first = np.arange(n_points) // step
    lengths = np.minimum(track_length, n_images - first)
    offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    track = (np.repeat(first, lengths) + np.arange(offsets[-1]) - np.repeat(offsets[:-1], lengths) + 1)
    xs = np.arange(n_images, dtype=np.float64) * 0.1  # cameras 0.1 apart along x, looking along +z
    xyz = np.stack([xs[first] + rng.uniform(0, 0.1 * track_length, n_points),
                    rng.uniform(-1, 1, n_points), rng.uniform(4, 6, n_points)], axis=1)
    points = Points3D(np.arange(1, n_points + 1, dtype=np.int64), xyz,
                      rng.integers(0, 255, (n_points, 3), dtype=np.uint8), np.full(n_points, 0.5),
                      offsets, track.astype(np.int64))
    order = np.argsort(track, kind="stable")
    point_rows = np.repeat(np.arange(n_points), lengths)[order]
    per_image = np.split(points.ids[point_rows], np.cumsum(np.bincount(track - 1, minlength=n_images))[:-1])
    images = {}
    for i in range(n_images):
        pose = np.concatenate([np.eye(3), [[-xs[i]], [0.0], [0.0]]], axis=1)
        images[i + 1] = Image(i + 1, f"img_{i:05d}.jpg", 1, pose, per_image[i])
    return SparseModel(cameras, images, points, {im.name: k for k, im in images.items()})


def _child(n: int, ppi: int, length: int) -> dict:
    import numpy as np

    from colmap_pvs.views import ViewSelectionConfig, select_views

    model = _model(n, ppi, length)
    arrays = [model.points.ids, model.points.xyz, model.points.rgb, model.points.error,
              model.points.track_offsets, model.points.track_image_ids,
              *(im.point3D_ids for im in model.images.values())]
    model_mb = sum(a.nbytes for a in arrays) / 2**20
    pickled_mb = len(pickle.dumps(model, protocol=5)) / 2**20
    before_rss = _rss_mb()
    before_peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    start = time.perf_counter()
    selection = select_views(model, ViewSelectionConfig(num_views=5))
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    resident = sum(np.asarray(a).nbytes for a in (selection.scores, selection.shared_points)) / 2**20
    return {"images": n, "points": len(model.points), "observations": int(model.points.track_offsets[-1]),
            "model_mb": model_mb, "pickled_mb": pickled_mb, "select_s": seconds,
            "select_peak_increase_mb": max(peak, before_peak) - before_rss, "selection_resident_mb": resident,
            "references": len(selection.references)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, nargs="+", default=[1000, 5000])
    parser.add_argument("--points_per_image", type=int, default=2000)
    parser.add_argument("--track_length", type=int, default=6)
    parser.add_argument("--_child", type=int, dest="child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print("RESULT " + json.dumps(_child(args.child, args.points_per_image, args.track_length)))
        return
    print(f"synthetic sparse models: {args.points_per_image} observations per image, tracks of "
          f"{args.track_length} images")
    print("| images | points | observations | model arrays (MB) | pickled (MB) | select_views (s) | "
          "select_views peak RSS increase (MB) | selection resident (MB) |")
    print("|---|---|---|---|---|---|---|---|")
    for n in args.images:
        out = subprocess.run([sys.executable, __file__, "--_child", str(n), "--points_per_image",
                              str(args.points_per_image), "--track_length", str(args.track_length)],
                             capture_output=True, text=True, cwd=REPO)
        line = next((ln for ln in out.stdout.splitlines() if ln.startswith("RESULT ")), None)
        if line is None:
            print(f"| {n} | failed (rc {out.returncode}): {out.stderr.strip().splitlines()[-1:]} |")
            continue
        r = json.loads(line[7:])
        print(f"| {r['images']} | {r['points']} | {r['observations']} | {r['model_mb']:.0f} | "
              f"{r['pickled_mb']:.0f} | {r['select_s']:.1f} | {r['select_peak_increase_mb']:.0f} | "
              f"{r['selection_resident_mb']:.0f} |")


if __name__ == "__main__":
    main()
