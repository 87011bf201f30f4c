"""Dense completion of a geometric map: the third stereo pass, ``NAME.filled.bin``.

The geometric pass keeps the pixels that its sources confirm and drops the rest, mostly untextured
walls and cupboards where the network's photometric depth is mostly wrong. The completion fills them in
three steps, each kept because it made the completed maps more accurate (``benchmarks/RESULTS.md``, "A
dense completion of the geometric maps" and the stops after it):

1. **The other views' kept pixels** (:func:`splat_depths`). A pixel this view dropped is often kept
   by a source that saw it better; the sources' geometric maps are projected into the reference
   (nearest surface per source) and a dropped pixel takes the median where ``min_sources`` of them
   agree within 3 % of it (the re-estimate from the sources' maps of COLMAP's geometric pass).
2. **A robust plane per image segment** (:func:`segment_planes`). An untextured wall or door is a
   region between image edges whose known pixels lie on one plane; the region's plane, where it fits
   them, fills it without blending in the surface across its edge (the superpixel planes of
   TAPA-MVS, Romanoni & Matteucci 2019).
3. **A plane fit of what is known** (:func:`complete_depth`) for the rest. Those regions are mostly
   planes whose textured borders are known, so a local plane fit in inverse depth extends the borders
   into the wall; planar-prior stereo (ACMP, Xu & Tao 2020) builds its prior from its reliable pixels
   the same way.

A completed depth needs support: a segment whose inliers cover under :data:`SEGMENT_MIN_SUPPORT` of
its area, or a fitted pixel with under :data:`FIT_MIN_SUPPORT` known pixels around it
(:func:`fit_support`), is *unsupported*; the stereo step writes the network's depth there with
confidence 0, which ``fuse`` never fuses (fused, such pixels draw a background beyond the depth range
as sheets and streaks: ``benchmarks/RESULTS.md``, "A completion that needs support").

The stereo step hands these functions the *seeds* of the geometric pass as the kept pixels (those
that 3 sources agree with within 2.5 %, ``stereo/seed_maps``; why strict seeds: ``benchmarks/RESULTS.md``,
"Stop 28"), of the reference and of its sources. Every kept pixel
stays as it is. :func:`completed_confidence` ranks, where the network is sure, the kept pixels first,
then the pixels the sources or the segment planes gave, then the fitted ones; each times the network's
probability. The
stereo step writes the result as ``NAME.filled.bin`` in ``stereo/depth_maps`` and ``stereo/confidence_maps``
(``docs/CONVENTIONS.md``); COLMAP's fusion never reads it. Arrays are numpy ``[H, W]`` (depth in
the map's units, 0 = none).
"""

from __future__ import annotations

import numpy as np
import torch

from .consistency import SourceMaps
from .errors import ShapeError
from .geometry import affine_row
from .model.cost import affine_fill_inverse_depth
from .upsampling import resize_bilinear

#: Relative depth tolerance within which splatted source depths agree with their median.
SPLAT_AGREEMENT = 0.03

#: Scales of the plane fit, in cells of the pooled grid (a cell is ``factor`` pixels).
FILL_SIGMAS = (2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0, 48.0)

#: Canny thresholds (on 0-255 grey) of the segmentations of :func:`segment_planes`, finest first.
SEGMENT_EDGE_THRESHOLDS = ((30, 90), (60, 180), (100, 300))

#: Relative inverse-depth residual within which a known pixel is an inlier of its segment's plane.
SEGMENT_INLIER_RESIDUAL = 0.03

#: Iterations of the robust plane fit: a least-squares start, two reweighted (L1-like) steps, then
#: least squares on the inliers (by then the inlier sets have settled: ``benchmarks/RESULTS.md``).
SEGMENT_IRLS_STEPS = 9

#: Known pixels a segment needs to give its plane, and the least fraction of them within
#: ``SEGMENT_INLIER_RESIDUAL`` of it.
SEGMENT_MIN_PIXELS = 30
SEGMENT_MIN_INLIERS = 0.6

#: Window (pixels) in which the coarsest segmentation needs as many inliers as outliers of the planes.
SEGMENT_LOCAL_WINDOW = 31

#: Factor by which a segment's plane may leave the range of its inliers' depths: beyond it the plane is
#: extrapolated past its support and the pixel gets no depth from the segment.
SEGMENT_MAX_EXTRAPOLATION = 1.25

#: Smallest spread (standard deviation, pixels) of a segment's inliers across their weakest axis:
#: below it they lie on a line and the plane's tilt across it is a guess.
SEGMENT_MIN_SPREAD = 2.0

#: Least share of a segment's area its inliers must cover: a large region with a few known specks
#: (a background beyond the depth range, where only chance matches pass the check) gets no plane, and
#: its pixels get no completed depth either (:func:`segment_planes`' ``refused``).
SEGMENT_MIN_SUPPORT = 0.05

#: How far past the convex hull of its inliers a segment's plane reaches: the larger of this share of
#: the image width and ``SEGMENT_REACH`` times the radius of the largest disc inside the segment. A
#: compact region (a wall known along one side) is reached whole; a thin strip that a neighbouring
#: object's pixels pin at one end (a corridor wall between two shelf edges, drawn at a plant's depth:
#: ``benchmarks/RESULTS.md``, "Fern's bar") only near that end. The radius is the segment's largest
#: (a strip joined to a wide region reaches as far as that region); distances are OpenCV's 3x3-mask
#: approximations, and the image border counts as the segment's edge. A pixel out of reach is left to
#: the coarser segmentations and the local fit.
SEGMENT_HULL_MARGIN = 0.03
SEGMENT_REACH = 3.0

#: Window of :func:`fit_support`, as a fraction of the image width (61 pixels at 540).
FIT_SUPPORT_WINDOW = 0.113

#: Least share of known pixels in that window for the local plane fit to give a pixel its depth.
FIT_MIN_SUPPORT = 0.01


def _pooled_inverse_depth(kept: np.ndarray, factor: int) -> np.ndarray:
    """``[ceil(H/f), ceil(W/f)]`` depth of the mean inverse depth of each cell's kept pixels (0: none)."""
    H, W = kept.shape
    hc, wc = -(-H // factor), -(-W // factor)
    pad = np.zeros((hc * factor, wc * factor), np.float64)
    pad[:H, :W] = kept
    valid = pad > 0
    inv = np.where(valid, 1.0 / np.where(valid, pad, 1.0), 0.0)
    cells = (hc, factor, wc, factor)
    count = valid.reshape(cells).sum((1, 3))
    total = inv.reshape(cells).sum((1, 3))
    return np.where(count > 0, count / np.maximum(total, 1e-300), 0.0).astype(np.float32)


def _plane_fit_inverse_depth(kept: np.ndarray, factor: int, min_weight: float,
                             sigmas: tuple[float, ...]) -> np.ndarray | None:
    """``[H, W]`` inverse depth of the local plane fit of ``kept`` (finite, 0 = none): pooled into
    ``factor`` cells, :func:`~colmap_pvs.model.cost.affine_fill_inverse_depth` at ``sigmas`` (cells),
    bilinear back to the pixels. ``None`` when nothing is kept."""
    H, W = kept.shape
    hint = _pooled_inverse_depth(kept, factor)
    if not (hint > 0).any():
        return None
    with torch.no_grad():
        inv = affine_fill_inverse_depth(torch.from_numpy(hint)[None, None], sigmas=sigmas,
                                        min_weight=min_weight)[0, 0].numpy()
    hc, wc = hint.shape
    return resize_bilinear(inv.astype(np.float32), hc * factor, wc * factor)[:H, :W]


def complete_depth(
    kept: np.ndarray, fallback: np.ndarray, factor: int = 4, min_weight: float = 6.0
) -> np.ndarray:
    """``[H, W]`` dense depth: ``kept`` where it is > 0, a local plane fit of it elsewhere.

    The kept pixels are pooled into cells of ``factor`` x ``factor`` pixels (mean inverse depth);
    :func:`~colmap_pvs.model.cost.affine_fill_inverse_depth` fits each cell a plane in inverse depth
    to the cells around it (Gaussian weights at the smallest scale of :data:`FILL_SIGMAS` that holds
    ``min_weight`` cells, clipped near the local range), and the fit is interpolated bilinearly in
    inverse depth back to the pixels. Pixels the fit cannot give a positive depth (an image without a
    single kept pixel) take ``fallback`` (the photometric depth).

    Args:
        kept: ``[H, W]`` geometric depth, 0 where dropped.
        fallback: ``[H, W]`` depth for pixels without a fit.
        factor: pooling factor (>= 1).
        min_weight: cells' worth of weight a scale needs (see the fit).

    Returns:
        ``[H, W]`` float32 depth, > 0 wherever ``kept`` or ``fallback`` is.
    """
    if kept.ndim != 2 or fallback.shape != kept.shape:
        raise ShapeError(f"kept and fallback must be the same [H, W], got {kept.shape} and {fallback.shape}")
    if factor < 1:
        raise ValueError(f"factor must be >= 1, got {factor}")
    kept = np.where(np.isfinite(kept) & (kept > 0), kept, 0.0)  # NaN / inf count as dropped
    inv = _plane_fit_inverse_depth(kept, factor, min_weight, FILL_SIGMAS)
    if inv is None:
        return np.where(kept > 0, kept, fallback).astype(np.float32)
    fill = np.where(inv > 0, 1.0 / np.maximum(inv, 1e-12), fallback)
    return np.where(kept > 0, kept, fill).astype(np.float32)


def fit_support(known: np.ndarray) -> np.ndarray:
    """``[H, W]`` float32 share of known pixels (``> 0`` and finite) in the square of side
    :data:`FIT_SUPPORT_WINDOW` x the image width around each pixel (reflected at the borders).

    The local plane fit of :func:`complete_depth` extends whatever is known into any gap, however
    wide; where less than :data:`FIT_MIN_SUPPORT` of the window is known its plane is a guess.
    """
    import cv2

    if known.ndim != 2:
        raise ShapeError(f"known must be [H, W], got {known.shape}")
    win = max(3, int(FIT_SUPPORT_WINDOW * known.shape[1]) | 1)
    has = (np.isfinite(known) & (known > 0)).astype(np.float32)
    return cv2.boxFilter(has, -1, (win, win), normalize=True, borderType=cv2.BORDER_REFLECT)


#: Scales of the plane fit that :func:`plane_deviation` compares a pixel with (cells of 4 pixels).
DEVIATION_SIGMAS = (2.0, 3.0, 4.0, 6.0, 8.0)


def plane_deviation(kept: np.ndarray, factor: int = 4, min_weight: float = 6.0) -> np.ndarray:
    """``[H, W]`` relative deviation ``|d * f - 1|`` of each kept depth ``d`` from the local plane fit
    ``1 / f`` of the kept pixels around it (inverse depth, as :func:`complete_depth`, at the scales
    :data:`DEVIATION_SIGMAS`); 0 where nothing is kept.

    A kept pixel that stands off the surface its neighbours agree on is more often wrong: the geometric
    confidence weighted by ``exp(-deviation / 0.02)`` ranks errors better (``benchmarks/RESULTS.md``,
    "Geometric confidence with the plane deviation").

    On an exact plane it is below 0.5 % away from the borders of the kept region and the image, up
    to about 1.5 % at them (a border cell's mean sits off its centre, and the upsampling holds the
    last cell's value), so border pixels rank a little lower too.

    Args:
        kept: ``[H, W]`` depth, 0 (or non-finite) where none.
    """
    if kept.ndim != 2:
        raise ShapeError(f"kept must be [H, W], got {kept.shape}")
    kept = np.where(np.isfinite(kept) & (kept > 0), kept, 0.0)
    inv = _plane_fit_inverse_depth(kept, factor, min_weight, DEVIATION_SIGMAS)
    if inv is None:
        return np.zeros(kept.shape, np.float32)
    return np.where(kept > 0, np.abs(kept * inv - 1.0), 0.0).astype(np.float32)


def _centred(rows: np.ndarray, cols: np.ndarray, H: int, W: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel centres as plane-fit coordinates: centred on the image and divided by its width, so the
    fit's normal equations are well scaled."""
    return (cols + 0.5 - W / 2) / W, (rows + 0.5 - H / 2) / W


def _within_reach(
    labels: np.ndarray, boxes: np.ndarray, seg_labels: np.ndarray, in_rows: np.ndarray, in_cols: np.ndarray,
    in_seg: np.ndarray, rows: np.ndarray, cols: np.ndarray, seg: np.ndarray,
) -> np.ndarray:
    """``[P]`` bool: target pixel ``(rows, cols)`` of segment ``seg`` (an index into ``seg_labels``, the
    segments' labels in ``labels``, whose bounding boxes ``boxes`` holds as ``cv2`` component stats) lies
    within the reach of its segment's plane (:data:`SEGMENT_HULL_MARGIN`, :data:`SEGMENT_REACH`) from the
    convex hull of that segment's inliers ``(in_rows, in_cols)`` (segment ``in_seg``)."""
    import cv2

    W = labels.shape[1]
    out = np.zeros(rows.size, bool)
    t_order = np.argsort(seg, kind="stable")
    i_order = np.argsort(in_seg, kind="stable")
    in_rows, in_cols, in_seg = in_rows[i_order], in_cols[i_order], in_seg[i_order]
    segs, t_start = np.unique(seg[t_order], return_index=True)
    t_end = np.append(t_start[1:], rows.size)
    i_start, i_end = np.searchsorted(in_seg, segs, "left"), np.searchsorted(in_seg, segs, "right")
    for j, s in enumerate(segs):
        t = t_order[t_start[j]:t_end[j]]
        pr, pc = in_rows[i_start[j]:i_end[j]], in_cols[i_start[j]:i_end[j]]
        c0, r0, bw, bh = (int(v) for v in boxes[seg_labels[s], :4])  # the segment's bounding box
        r1, c1 = r0 + bh, c0 + bw
        hull = np.ones((r1 - r0, c1 - c0), np.uint8)  # 0 inside the hull
        cv2.fillConvexPoly(hull, cv2.convexHull(np.stack([pc - c0, pr - r0], 1).astype(np.int32)), 0)
        outside = cv2.distanceTransform(hull, cv2.DIST_L2, 3)[rows[t] - r0, cols[t] - c0]
        reach = SEGMENT_HULL_MARGIN * W
        if (outside > reach).any():  # the region's largest disc only where the margin is not enough
            region = np.pad((labels[r0:r1, c0:c1] == seg_labels[s]).astype(np.uint8), 1)
            reach = max(reach, SEGMENT_REACH * float(cv2.distanceTransform(region, cv2.DIST_L2, 3).max()))
        out[t] = outside <= reach
    return out


def _segment_planes_once(
    inv: np.ndarray, targets: np.ndarray, grey: np.ndarray, thresholds: tuple[int, int], min_pixels: int,
    min_inliers: float, guard: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One segmentation's robust planes: ``[H, W]`` inverse depth (0 = none), inlier fraction and the
    target pixels of segments too thinly supported for a plane (``SEGMENT_MIN_SUPPORT``), for the
    segments that hold a target pixel (``grey``: the blurred uint8 image)."""
    import cv2

    H, W = inv.shape
    edges = cv2.Canny(grey, *thresholds)
    edges = cv2.dilate(edges, np.ones((3, 3), np.uint8))
    count, labels, boxes, _ = cv2.connectedComponentsWithStats((edges == 0).astype(np.uint8), connectivity=4)
    known = (inv > 0) & (labels > 0)  # label 0: the edges, which belong to no segment
    n_known = np.bincount(labels[known], minlength=count)
    wanted = np.bincount(labels[targets], minlength=count) > 0
    known &= ((n_known >= min_pixels) & wanted)[labels]
    rows, cols = np.nonzero(known)
    none = np.zeros((H, W)), np.zeros((H, W), np.float32)
    if not rows.size:
        return none + (np.zeros((H, W), bool),)
    order = np.argsort(labels[rows, cols], kind="stable")
    rows, cols = krows, kcols = rows[order], cols[order]
    lab = labels[rows, cols]
    segs, starts, sizes = np.unique(lab, return_index=True, return_counts=True)
    idx = np.repeat(np.arange(segs.size), sizes)  # each known pixel's segment, 0..len(segs)-1
    z = inv[rows, cols].astype(np.float64)
    u, v = _centred(rows, cols, H, W)
    feats = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v, z, u * z, v * z], axis=1)
    weights = np.ones_like(z)
    for step in range(SEGMENT_IRLS_STEPS):  # two reweighted L1 steps, then least squares on the inliers
        m = np.add.reduceat(feats * weights[:, None], starts, axis=0)  # [segments, 9]
        normal = m[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3) + np.eye(3)[None] * 1e-9
        plane = np.linalg.solve(normal, m[:, 6:9, None])[..., 0]  # [segments, 3]: a, b, c
        residual = np.abs((plane[idx, 0] + plane[idx, 1] * u + plane[idx, 2] * v) / z - 1.0)
        inlier = residual <= SEGMENT_INLIER_RESIDUAL
        weights = inlier.astype(np.float64) if step >= 2 else 1.0 / np.maximum(residual, 0.005)
    m = np.add.reduceat(feats[:, :6] * inlier[:, None], starts, axis=0)
    n_in = np.maximum(m[:, 0], 1)
    mean_u, mean_v = m[:, 1] / n_in, m[:, 2] / n_in
    cuu, cuv, cvv = m[:, 3] / n_in - mean_u**2, m[:, 4] / n_in - mean_u * mean_v, m[:, 5] / n_in - mean_v**2
    weakest = 0.5 * (cuu + cvv) - np.sqrt(0.25 * (cuu - cvv) ** 2 + cuv**2)  # smallest eigenvalue
    z_in = np.where(inlier, z, np.nan)
    lo, hi = np.fmin.reduceat(z_in, starts), np.fmax.reduceat(z_in, starts)
    fraction = m[:, 0] / sizes
    area = boxes[segs, cv2.CC_STAT_AREA]
    thin = m[:, 0] < SEGMENT_MIN_SUPPORT * area  # a few specks in a large region pin no plane
    good = (fraction >= min_inliers) & (weakest * W * W >= SEGMENT_MIN_SPREAD**2)
    refused = np.zeros((H, W), bool)
    if (good & thin).any():
        refused = np.isin(labels, segs[good & thin]) & targets
    good &= ~thin
    if not good.any():
        return none + (refused,)
    if guard:  # known pixels of the accepted segments on / off their plane, counted around each pixel
        on = good[idx]
        tally = np.zeros((2, H, W), np.float32)
        tally[0, krows[on & inlier], kcols[on & inlier]] = 1.0
        tally[1, krows[on & ~inlier], kcols[on & ~inlier]] = 1.0
        win = (SEGMENT_LOCAL_WINDOW, SEGMENT_LOCAL_WINDOW)
        local_in, local_out = (
            cv2.boxFilter(t, -1, win, normalize=False, borderType=cv2.BORDER_CONSTANT) for t in tally
        )
    on_plane = inlier & good[idx]  # the accepted segments' inliers, their segment an index into segs
    in_rows, in_cols, in_seg = krows[on_plane], kcols[on_plane], idx[on_plane]
    seg_labels, kept_segs = segs, np.flatnonzero(good)
    segs, plane, lo, hi, fraction = segs[good], plane[good], lo[good], hi[good], fraction[good]
    lookup = np.full(count, -1)
    lookup[segs] = np.arange(segs.size)
    rows, cols = np.nonzero((lookup[labels] >= 0) & targets)
    k = lookup[labels[rows, cols]]
    u, v = _centred(rows, cols, H, W)
    out = plane[k, 0] + plane[k, 1] * u + plane[k, 2] * v
    # Near the inliers' inverse depths: no far extrapolation of a tilted fit.
    ok = (out >= lo[k] / SEGMENT_MAX_EXTRAPOLATION) & (out <= SEGMENT_MAX_EXTRAPOLATION * hi[k])
    if guard:  # a segment spanning two surfaces must not give the majority's plane to the other
        ok &= local_in[rows, cols] >= local_out[rows, cols]
    # Near its inliers' hull: a plane pinned at one end of a thin strip is not drawn along all of it.
    reach = _within_reach(labels, boxes, seg_labels, in_rows, in_cols, in_seg, rows[ok], cols[ok],
                          kept_segs[k[ok]])
    ok[np.flatnonzero(ok)[~reach]] = False
    plane_inv, frac = none
    plane_inv[rows[ok], cols[ok]] = out[ok]
    frac[rows[ok], cols[ok]] = fraction[k[ok]]
    return plane_inv, frac, refused


def segment_planes(
    known: np.ndarray,
    image: np.ndarray,
    targets: np.ndarray | None = None,
    *,
    min_pixels: int = SEGMENT_MIN_PIXELS,
    min_inliers: float = SEGMENT_MIN_INLIERS,
    thresholds: tuple[tuple[int, int], ...] = SEGMENT_EDGE_THRESHOLDS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth from one robust plane per colour segment of the image (the planar prior of TAPA-MVS).

    An untextured wall or cupboard door is a region without image edges whose known pixels (its
    textured specks and the inner side of its borders) lie on one plane. The image is cut into the
    connected regions between its edges (Canny at ``thresholds``, dilated by one pixel, 4-connected);
    each region with at least ``min_pixels`` known pixels fits a plane in inverse depth
    (``1/d = a + b u + c v``, exact on any 3D plane) by iteratively reweighted least squares, and
    gives its depth to every pixel of the region where at least ``min_inliers`` of its known pixels
    lie within :data:`SEGMENT_INLIER_RESIDUAL` of the plane, the inliers are spread across both axes
    (:data:`SEGMENT_MIN_SPREAD`) and the plane stays within :data:`SEGMENT_MAX_EXTRAPOLATION` of their
    depths (a plane is not drawn far beyond its support; past it the pixel is left to the fit), and
    the pixel lies within reach of the convex hull of the inliers (:data:`SEGMENT_HULL_MARGIN`,
    :data:`SEGMENT_REACH`: a thin strip pinned at one end takes its plane only near that end). A
    region that passes those tests but whose inliers cover less than :data:`SEGMENT_MIN_SUPPORT` of its
    area gives no plane either, and its pixels are ``refused``, also for the coarser segmentations: a
    background beyond the depth range is such a region, whose few chance specks would draw sheets and
    streaks around the object in front, and a coarser region merging it with that object would give it
    the object's plane (``benchmarks/RESULTS.md``, "A completion that needs support"). The segmentations
    go from fine to coarse; a pixel
    takes the finest region that gives it a depth or refuses it.
    The coarsest one's regions (when there are at least two segmentations) can span two surfaces
    whose boundary shows only a weak edge (an occlusion edge of one colour), so there a pixel also
    needs at least as many inliers as outliers among the accepted regions' known pixels in the
    :data:`SEGMENT_LOCAL_WINDOW`-pixel square around it; a pixel with none of them around it passes
    (the middle of a large wall), so a surface without a single known pixel of its own can still take
    its neighbour's plane.

    Args:
        known: ``[H, W]`` depth, 0 (or non-finite) where unknown.
        image: ``[3, H, W]`` RGB in ``[0, 1]`` (or ``[H, W]`` grey), the same size.
        targets: ``[H, W]`` bool, the pixels that need a depth (default: the unknown ones); only
            segments holding one are fitted, and only targets are given a depth.
        min_pixels: known pixels a region needs; min_inliers: the fraction of them on its plane.

    Returns:
        depth ``[H, W]`` float32 (0 where no region gives one, and off the targets), ``[H, W]``
        float32 the inlier fraction of the region that gave it (0 where none), and ``[H, W]`` bool
        the targets whose finest deciding region was refused because its inliers cover less than
        :data:`SEGMENT_MIN_SUPPORT` of its area: nothing here supports a depth for them.
    """
    import cv2

    image = np.asarray(image, dtype=np.float32)
    known = np.asarray(known, dtype=np.float32)
    if image.ndim == 3 and image.shape[0] == 3:
        image = np.tensordot(np.array([0.299, 0.587, 0.114], np.float32), image, axes=1)
    targets = ~(np.isfinite(known) & (known > 0)) if targets is None else np.asarray(targets, bool)
    if known.ndim != 2 or known.size == 0 or image.shape != known.shape or targets.shape != known.shape:
        raise ShapeError(f"known and targets must be [H, W] and image [3, H, W] or [H, W], all of one "
                         f"size, got {known.shape}, {targets.shape} and {image.shape}")
    if min_pixels < 3 or not 0.0 <= min_inliers <= 1.0:
        raise ValueError(
            f"min_pixels must be >= 3 and min_inliers in [0, 1], got {min_pixels} and {min_inliers}"
        )
    grey = cv2.GaussianBlur(np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8), (3, 3), 0)
    known = np.where(np.isfinite(known) & (known > 0), known, 0.0)
    inv = np.where(known > 0, 1.0 / np.maximum(known, 1e-12), 0.0)
    depth = np.zeros(known.shape, np.float64)
    fraction = np.zeros(known.shape, np.float32)
    refused = np.zeros(known.shape, bool)
    todo = targets.copy()
    for i, level in enumerate(thresholds):
        coarsest = i == len(thresholds) - 1 and i > 0
        plane_inv, frac, thin = _segment_planes_once(
            inv, todo, grey, level, min_pixels, min_inliers, coarsest
        )
        new = todo & (plane_inv > 0)
        # A refused pixel stays refused: a coarser region that merges its thin one with a well supported
        # surface (a statue and the background behind it) would hand it that surface's plane.
        refused |= todo & thin & ~new
        todo &= ~(new | thin)
        depth[new] = 1.0 / plane_inv[new]
        fraction[new] = frac[new]
    return depth.astype(np.float32), fraction, refused


def splat_depths(
    K: np.ndarray, cam_from_world: np.ndarray, size: tuple[int, int], sources: list[SourceMaps],
    min_sources: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """The sources' depth maps projected into a reference view, and where enough of them agree.

    Every valid source pixel (centre, our convention) is back-projected with its depth and projected
    into the reference (``K`` ``[3, 3]``, ``cam_from_world`` ``[4, 4]``, ``size`` ``(W, H)``); it lands
    in pixel ``floor(u), floor(v)``. Per source the nearest surface wins (a z-buffer). A pixel's
    value is the median over the sources that reach it, kept where at least ``min_sources`` of them
    lie within :data:`SPLAT_AGREEMENT` of that median.

    Returns:
        depth ``[H, W]`` float32 (0 where fewer than ``min_sources`` agree) and the number of
        agreeing sources ``[H, W]`` int32.
    """
    W, H = size
    if not sources:
        return np.zeros((H, W), np.float32), np.zeros((H, W), np.int32)
    stack = np.zeros((len(sources), H, W), np.float32)
    for k, src in enumerate(sources):
        rows, cols = np.nonzero(src.depth > 0)
        if not rows.size:
            continue
        d = src.depth[rows, cols].astype(np.float64)
        # Source pixel centre (our convention) with depth d, into the reference: x ~ A [u d, v d, d] + b
        # (row by row, geometry.affine_row).
        ref_from_src = cam_from_world @ np.linalg.inv(src.cam_from_world)
        A = K @ ref_from_src[:3, :3] @ np.linalg.inv(src.K)
        b = K @ ref_from_src[:3, 3]
        pts = ((cols + 0.5) * d, (rows + 0.5) * d, d)
        z = affine_row(A[2], b[2], pts)
        front = z > 1e-9
        z = z[front]
        pts = tuple(c[front] for c in pts)
        u = np.floor(affine_row(A[0], b[0], pts) / z)
        v = np.floor(affine_row(A[1], b[1], pts) / z)
        inside = (u >= 0) & (v >= 0) & (u < W) & (v < H)
        index = (v[inside] * W + u[inside]).astype(np.int64)
        zbuf = np.full(H * W, np.inf)
        np.minimum.at(zbuf, index, z[inside])
        stack[k] = np.where(np.isfinite(zbuf), zbuf, 0.0).reshape(H, W)
    reached = stack > 0
    count = reached.sum(0)
    ordered = np.sort(np.where(reached, stack, np.inf), axis=0)  # the reached values first
    lo = np.take_along_axis(ordered, np.maximum(count - 1, 0)[None] // 2, 0)[0]
    hi = np.take_along_axis(ordered, (count // 2)[None].clip(max=len(sources) - 1), 0)[0]
    median = np.where(count > 0, 0.5 * (lo + hi), 0.0).astype(np.float32)
    agree = (reached & (np.abs(stack / np.maximum(median, 1e-12) - 1.0) <= SPLAT_AGREEMENT)).sum(0)
    agree = agree.astype(np.int32)
    return np.where(agree >= min_sources, median, 0.0).astype(np.float32), agree


#: Least factor of the network's probability in :func:`completed_confidence`: a pixel where the network
#: gave no depth (probability 0) keeps a positive score, above the unsupported pixels' 0.
NETWORK_FACTOR_FLOOR = 1e-3


def completed_confidence(
    kept: np.ndarray, splatted: np.ndarray, geometric: np.ndarray, photometric: np.ndarray,
    splat_support: np.ndarray, segmented: np.ndarray | None = None, segment_inliers: np.ndarray | None = None,
) -> np.ndarray:
    """``[H, W]`` confidence score of a completed map in ``[0, 1]``: its tier times the network's.

    The tier: ``0.5 + 0.5 * geometric`` where ``kept``; ``0.25 + 0.25 * splat_support`` where
    ``splatted`` (the fraction of the sources that agreed, in ``[0, 1]``); ``0.25 + 0.25 *
    segment_inliers`` where ``segmented`` (the inlier fraction of the segment plane that gave the
    pixel, :func:`segment_planes`); ``0.25`` elsewhere (all inputs ``[H, W]``, confidences in
    ``[0, 1]``). The sources confirmed the kept pixels, the splatted ones come from pixels the sources
    kept, a segment's plane from the known pixels of its own surface, and nobody confirmed the fitted
    ones. ``segmented`` wins over ``splatted``. The score is the tier times ``photometric``, the
    network's probability at the pixel (at least :data:`NETWORK_FACTOR_FLOOR`, so that every pixel
    keeps a positive score): within every tier the depth is more often wrong where the network was
    unsure, and a kept pixel the network doubts ranks below a well-supported plane's
    (``benchmarks/RESULTS.md``, "The network's confidence in the completion's").
    """
    segmented = np.zeros_like(kept) if segmented is None else segmented
    segment_inliers = np.zeros(kept.shape, np.float32) if segment_inliers is None else segment_inliers
    arrays = (kept, splatted, geometric, photometric, splat_support, segmented, segment_inliers)
    shapes = {a.shape for a in arrays}
    if len(shapes) != 1 or kept.ndim != 2:
        raise ShapeError(f"the inputs must all be the same [H, W], got shapes {sorted(shapes)}")

    def unit(a):
        return np.clip(np.nan_to_num(a.astype(np.float32)), 0.0, 1.0)

    tier = np.where(splatted, 0.25 + 0.25 * unit(splat_support), np.float32(0.25))
    tier = np.where(segmented, 0.25 + 0.25 * unit(segment_inliers), tier)
    tier = np.where(kept, 0.5 + 0.5 * unit(geometric), tier)
    return (tier * np.maximum(unit(photometric), NETWORK_FACTOR_FLOOR)).astype(np.float32)
