"""Depth of a checkpoint on the Middlebury 2014 Motorcycle stereo pair (scikit-image's copy).

    python benchmarks/middlebury_pair.py                                   # the shipped checkpoint
    python benchmarks/middlebury_pair.py --checkpoint A.pt --checkpoint B.pt --picture mb.jpg

The pair is ``skimage.data.stereo_motorcycle()``: the left and right image and the left GT disparity
of Middlebury 2014's Motorcycle (perfect rectification), downsampled 4x by scikit-image to 741x500
(``downscale_local_mean``; disparities in quarter-resolution pixels, ``inf`` where there is no GT).
scikit-image is a benchmark-only dependency (``pip install scikit-image``), never one of colmap-pvs.
It fetches the three files with pooch from the internet; offline, give ``--data_dir DIR`` holding
``motorcycle_left.png``, ``motorcycle_right.png`` and ``motorcycle_disp.npz`` (checked against the
sha256 of skimage's ``data/_registry.py``; the same files are blobs of the scikit-image GitHub
repository's history, ``skimage/data/`` before the move to ``gitlab.com/scikit-image/data``).

Geometry: Middlebury's ``calib.txt`` of Motorcycle (2964x2000: cam0 ``f = 3979.911``, ``cx = 1244.772``,
``cy = 1019.507``; cam1 ``cx = 1369.115``; ``doffs = 124.343``; baseline 193.001 mm), all divided by 4
for the 741x500 copy (the values of skimage's docstring), so that ``depth = f B / (d + doffs)`` in
metres. The network gets a two-view sample: the left image the reference (``cam_from_world`` the
identity), the right one the source (translation ``(-B, 0, 0)``), each with its own ``K`` (the right
``cx`` is ``doffs`` larger), resized to ``--width`` (default 736) x the height keeping the aspect
ratio, a multiple of 16 (``K`` scaled with the pixel centres). The depth range is the stereo step's
rule (``ViewSelectionConfig``: 1st-99th percentile with a 25 % margin, far outliers dropped) on
``--hints`` (200) GT depths at random valid pixels, standing in for the reference's SfM points;
the same points are the network's ``sparse_depth`` in the ``hints`` rows and absent (all 0) in the
``none`` rows (the depth range is the same for both). Exact GT hints: easier than real SfM points.

Scoring is at the 741x500 of the GT: the network's depth is brought up with the stereo step's
``guided_upsample_depth`` (the left image the guide) and compared on every pixel with a GT disparity
(finite and > 0; Middlebury's non-occluded mask is not in skimage's copy, so pixels the right image
does not see count too): % of pixels with relative depth error under 1/2/5 %, AbsRel, and in
disparity space (our depth -> ``f B / depth - doffs``) the end-point error and bad-2.0 (share of
pixels more than 2 px off) in FULL-resolution pixels (4x the quarter-resolution disparity error).
The raw network depth is scored (no confidence filter, no geometric step), like ``synthetic_val.py``.
``--picture OUT.jpg``: left | right | GT depth, then per checkpoint and hint setting its depth | its
relative depth error (0 black ... 10 % and more red, turbo) | its bad-2.0 pixels in red over the image.
One forward pass per checkpoint and hint setting, single-threaded by default (``--threads``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from colmap_pvs.geometry import scale_intrinsics
from colmap_pvs.io.files import file_sha256
from colmap_pvs.io.maps import colorize_depth
from colmap_pvs.stereo.config import DEFAULT_CHECKPOINT
from colmap_pvs.stereo.network import estimate_depth
from colmap_pvs.upsampling import guided_upsample_depth
from colmap_pvs.views.config import ViewSelectionConfig
from colmap_pvs.views.depth_range import _robust_depth_range

# Middlebury 2014 Motorcycle(-perfect) calib.txt, full resolution.
FULL_SIZE = (2964, 2000)
CAM0 = np.array([[3979.911, 0.0, 1244.772], [0.0, 3979.911, 1019.507], [0.0, 0.0, 1.0]])
CAM1 = np.array([[3979.911, 0.0, 1369.115], [0.0, 3979.911, 1019.507], [0.0, 0.0, 1.0]])
DOFFS = 124.343  # px, = cam1 cx - cam0 cx
BASELINE_M = 0.193001
SKIMAGE_FACTOR = 4  # skimage's copy: downscale_local_mean by 4 -> 741x500

FILES = ("motorcycle_left.png", "motorcycle_right.png", "motorcycle_disp.npz")
# sha256 of skimage's data/_registry.py (0.26), checked against the installed registry when there is one.
SHA256 = {
    "motorcycle_left.png": "db18e9c4157617403c3537a6ba355dfeafe9a7eabb6b9b94cb33f6525dd49179",
    "motorcycle_right.png": "5fc913ae870e42a4b662314bc904d1786bcad8e2f0b9b67dba5a229406357797",
    "motorcycle_disp.npz": "2e49c8cebff3fa20359a0cc6880c82e1c03bbb106da81a177218281bc2f113d7",
}
NO_SKIMAGE = (
    "scikit-image is needed for this benchmark only (it is not a colmap-pvs dependency): "
    "pip install scikit-image   (or give --data_dir with the three files: see the docstring)"
)


def _registry_hashes() -> dict[str, str]:
    try:
        from skimage.data._registry import registry
    except ImportError:
        return dict(SHA256)
    return {name: registry[f"data/{name}"] for name in FILES}


def load_pair(data_dir: str | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Left, right (``[500, 741, 3]`` uint8 RGB) and the left GT disparity (``[500, 741]``, quarter px)."""
    if data_dir is None:
        try:
            from skimage.data import stereo_motorcycle
        except ImportError as exc:
            raise SystemExit(NO_SKIMAGE) from exc
        try:
            left, right, disp = stereo_motorcycle()
        except (ConnectionError, ModuleNotFoundError, OSError) as exc:
            raise SystemExit(
                f"skimage could not get the Motorcycle pair ({type(exc).__name__}: {exc}). It downloads "
                "motorcycle_{left,right}.png and motorcycle_disp.npz (skimage's data/_registry.py) with "
                "pooch; offline, put the three files in a folder and pass --data_dir FOLDER"
            ) from exc
        return np.asarray(left), np.asarray(right), np.asarray(disp, dtype=np.float32)
    folder = Path(data_dir)
    for name, expected in _registry_hashes().items():
        path = folder / name
        if not path.is_file():
            raise SystemExit(f"--data_dir: {str(path)!r} is missing (needs {', '.join(FILES)})")
        got = file_sha256(path)
        if got != expected:
            raise SystemExit(f"{str(path)!r} has sha256 {got}, skimage's registry says {expected}")
    left, right = (cv2.imread(str(folder / n), cv2.IMREAD_COLOR)[:, :, ::-1].copy() for n in FILES[:2])
    with np.load(folder / FILES[2]) as data:
        disp = data["arr_0"].astype(np.float32)
    return left, right, disp


def calibration(width: int, height: int) -> tuple[np.ndarray, np.ndarray, float, float]:
    """``K0``, ``K1``, ``doffs`` (px) and baseline (m) at skimage's size, checked against it."""
    expected = (FULL_SIZE[0] // SKIMAGE_FACTOR, FULL_SIZE[1] // SKIMAGE_FACTOR)
    if (width, height) != expected:
        raise SystemExit(
            f"the pair is {width}x{height}, expected {expected[0]}x{expected[1]} (2964x2000 / 4)"
        )
    s = np.diag([1.0 / SKIMAGE_FACTOR, 1.0 / SKIMAGE_FACTOR, 1.0])
    return s @ CAM0, s @ CAM1, DOFFS / SKIMAGE_FACTOR, BASELINE_M


def scaled_K(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """``K`` (Middlebury: pixel centres at integers) for an image resized by ``sx, sy``, in the network's
    convention (pixel ``(c, r)`` centred at ``(c + 0.5, r + 0.5)``). Both views move alike: no depth
    change."""
    shifted = K.astype(np.float64).copy()
    shifted[:2, 2] += 0.5
    return scale_intrinsics(shifted, sx, sy)


def metrics(depth: np.ndarray, gt: np.ndarray, valid: np.ndarray, f: float, b: float) -> dict:
    """Relative depth errors and full-resolution disparity errors on ``valid`` (``doffs`` cancels in the
    disparity difference); a pixel without a predicted depth counts as relative error 1, bad-2.0, no EPE."""
    d, g = depth[valid].astype(np.float64), gt[valid].astype(np.float64)
    ok = np.isfinite(d) & (d > 0)
    rel = np.where(ok, np.abs(d - g) / g, 1.0)
    disp_err = np.where(ok, np.abs(f * b / np.where(ok, d, 1.0) - f * b / g), np.inf) * SKIMAGE_FACTOR
    return {
        "absrel": float(rel.mean()),
        "pct1": float((rel < 0.01).mean() * 100),
        "pct2": float((rel < 0.02).mean() * 100),
        "pct5": float((rel < 0.05).mean() * 100),
        "epe": float(disp_err[np.isfinite(disp_err)].mean()),
        "bad2": float((disp_err > 2.0).mean() * 100),
        "missing": int((~ok).sum()),
    }


def _label(img: np.ndarray, text: str) -> np.ndarray:
    img = np.ascontiguousarray(img)
    cv2.putText(img, text, (10, 36), cv2.FONT_HERSHEY_SIMPLEX, 1.1, (0, 0, 0), 7, cv2.LINE_AA)
    cv2.putText(img, text, (10, 36), cv2.FONT_HERSHEY_SIMPLEX, 1.1, (255, 255, 255), 2, cv2.LINE_AA)
    return img


def picture(path: str, left, right, gt, valid, rows, f, b, scale: float = 0.5) -> None:
    """left | right | GT depth; per row: depth | relative error (0..10 %) | bad-2.0 pixels (BGR jpg)."""
    bgr = lambda rgb: np.ascontiguousarray(rgb[:, :, ::-1])  # noqa: E731
    lo, hi = np.percentile(gt[valid], [2.0, 98.0])
    grid = [[_label(bgr(left), "left (reference)"), _label(bgr(right), "right (source)"),
             _label(colorize_depth(np.where(valid, gt, 0), lo, hi), "GT depth")]]
    grey = cv2.cvtColor(cv2.cvtColor(bgr(left), cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
    for name, depth in rows:
        rel = np.where(valid, np.abs(depth - gt) / np.where(valid, gt, 1.0), 0.0)
        scaled = (np.clip(rel / 0.10, 0, 1) * 255).round().astype(np.uint8)
        err = cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)
        err[~valid] = 0
        with np.errstate(divide="ignore"):
            derr = np.abs(f * b / depth - f * b / np.where(valid, gt, 1.0)) * SKIMAGE_FACTOR
        bad = grey.copy()
        bad[valid & ~(derr <= 2.0)] = (0, 0, 255)
        grid.append([_label(colorize_depth(depth, lo, hi), f"{name}: depth"),
                     _label(err, "rel. error, 0 to 10+ %"), _label(bad, "bad-2.0 in red")])
    img = np.concatenate([np.concatenate(r, axis=1) for r in grid], axis=0)
    img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(path, img, [cv2.IMWRITE_JPEG_QUALITY, 88])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", action="append", default=None,
                    help="checkpoint to score (repeat to compare; default the shipped one)")
    ap.add_argument("--data_dir", default=None, help="folder with skimage's three files (offline)")
    ap.add_argument("--width", type=int, default=736, help="network input width (height keeps the aspect)")
    ap.add_argument("--hints", type=int, default=200, help="GT depths sampled as SfM-like points")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--picture", default=None, help="write left | right | GT, then depth | error rows")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    checkpoints = args.checkpoint or [str(DEFAULT_CHECKPOINT)]

    left, right, disp = load_pair(args.data_dir)
    H0, W0 = disp.shape
    K0, K1, doffs, b = calibration(W0, H0)
    f = float(K0[0, 0])
    valid = np.isfinite(disp) & (disp > 0)
    gt = np.where(valid, f * b / np.where(valid, disp + doffs, 1.0), 0.0).astype(np.float32)

    W = args.width
    H = max(16, int(round(W * H0 / W0 / 16)) * 16)
    sx, sy = W / W0, H / H0
    images = np.stack([cv2.resize(im, (W, H), interpolation=cv2.INTER_AREA) for im in (left, right)])
    images = images.transpose(0, 3, 1, 2).astype(np.float32) / 255.0
    Ks = np.stack([scaled_K(K0, sx, sy), scaled_K(K1, sx, sy)]).astype(np.float32)
    poses = np.stack([np.eye(4), np.eye(4)]).astype(np.float32)
    poses[1, 0, 3] = -b

    rng = np.random.default_rng(args.seed)
    rows, cols = np.nonzero(valid)
    pick = rng.choice(rows.size, size=min(args.hints, rows.size), replace=False)
    r, c = rows[pick], cols[pick]
    hint_depths = gt[r, c]
    depth_range, _ = _robust_depth_range(hint_depths.astype(np.float64), ViewSelectionConfig(), "left")
    sparse = np.zeros((H, W), np.float32)
    net_r = np.minimum(((r + 0.5) * sy).astype(int), H - 1)
    net_c = np.minimum(((c + 0.5) * sx).astype(int), W - 1)
    sparse[net_r, net_c] = hint_depths
    guide = left.astype(np.float32) / 255.0

    print(f"Middlebury 2014 Motorcycle (skimage, {W0}x{H0} = 2964x2000 / 4): {int(valid.sum())} GT pixels "
          f"({valid.mean() * 100:.1f} %), GT depth {gt[valid].min():.3f}..{gt[valid].max():.3f} m; "
          f"f {f:.3f} px, doffs {doffs:.3f} px, B {b} m; network {W}x{H}, 2 views; depth range "
          f"{depth_range[0]:.3f}..{depth_range[1]:.3f} m from {pick.size} GT hints (seed {args.seed})")
    print("| checkpoint | hints | AbsRel | % <1% | % <2% | % <5% | EPE (full-res px) | bad-2.0 | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    from colmap_pvs.model import load_checkpoint

    drawn = []
    for path in checkpoints:
        model, _ = load_checkpoint(path, map_location="cpu")
        label = Path(path).name if len(checkpoints) == 1 else path  # two model.pt: tell them apart
        model.eval()
        for name, hints in (("none", np.zeros_like(sparse)), (f"{pick.size} GT", sparse)):
            t0 = time.perf_counter()
            depth, _, _, _ = estimate_depth(model, images, Ks, poses, depth_range, hints, torch.device("cpu"))
            seconds = time.perf_counter() - t0
            full = guided_upsample_depth(depth, guide)
            m = metrics(full, gt, valid, f, b)
            missing = f" ({m['missing']} px without depth)" if m["missing"] else ""
            print(f"| {label} | {name} | {m['absrel']:.4f} | {m['pct1']:.1f} | {m['pct2']:.1f} | "
                  f"{m['pct5']:.1f} | {m['epe']:.2f} | {m['bad2']:.1f} %{missing} | {seconds:.1f} |")
            drawn.append((f"{label}, {'no' if name == 'none' else name} hints", full))
    if args.picture:
        picture(args.picture, left, right, gt, valid, drawn, f, b)
        print(f"picture: {args.picture}")


if __name__ == "__main__":
    main()
