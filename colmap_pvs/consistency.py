"""Multi-view geometric consistency of depth maps: the checks of the ``stereo`` geometric pass and ``fuse``.

A reference pixel with depth ``d`` is back-projected, projected into a source view, and the source
map's depth at the pixel it lands in is back-projected from that pixel's centre and projected back
into the reference (the forward-backward check of COLMAP's geometric PatchMatch and of MVSNet's
filter). The pixel *agrees* with that source when

- the reprojection error ``|(u', v') - (u, v)|`` is at most ``max_reproj_error`` pixels,
- the relative depth error ``|z' - d| / d`` is at most ``max_depth_error``,
- the angle between its normal and the source's normal (rotated into the reference frame) is at
  most ``max_normal_error`` degrees (skipped when ``>= 180`` or when a normal is missing),

and a source is *checked* for that pixel only where the network's learned visibility of that
source (upsampled to the map) is at least ``min_visibility``. Conventions: ``docs/CONVENTIONS.md``.

Two forms of the check live here, on the same source maps (:class:`SourceMaps`):

- :func:`check_consistency`, the geometric pass's: dense per-pixel measurements ``[S, H, W]`` of a
  whole map against all its sources (errors, reprojected depth, parallax, triangulation angle,
  normal angle, learned visibility), limits inclusive (``<=``, relative depth error ``|z' - d| / d``).
- :func:`match_points`, fusion's (``colmap_pvs.fusion``): a list of reference points against one
  source, returning for each agreeing point the source pixel it landed in (whose normal and colour
  fusion averages, which deduplication marks used, which the ``.vis`` lists) and that pixel
  back-projected (the 3D point averaged); no normal or visibility test, limits strict (``<``,
  ``|z' - d| < max_depth_error d``).

They stay two functions because their results differ in kind (dense maps vs matched pixels and
points, which the dense form would cost fusion memory and time to produce) and because their float
arithmetic differs (inverse-``K`` rows through :func:`~colmap_pvs.geometry.affine_row` vs pixel rays
and row products): merging them would move either the geometric maps or the fused cloud by their last
bits, and both must stay byte-identical to earlier releases.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import ShapeError
from .geometry import affine_row, pixel_centers, rowmul


@dataclass
class SourceMaps:
    """One source view's maps: its photometric maps for the check, its geometric depth for the
    dense completion (:func:`colmap_pvs.completion.splat_depths`, without normals).

    Attributes:
        depth: ``[h, w]`` (0 = invalid); normals: ``[h, w, 3]`` camera frame (or ``None``).
        K: ``[3, 3]`` intrinsics of this map in our pixel-centre convention; cam_from_world ``[4, 4]``.
    """

    depth: np.ndarray
    normals: np.ndarray | None
    K: np.ndarray
    cam_from_world: np.ndarray


@dataclass
class ConsistencyResult:
    """Per-pixel outcome for a reference map ``[H, W]``.

    Attributes:
        agree: ``[S, H, W]`` bool, the pixel agrees with source ``s`` (only where checked).
        checked: ``[S, H, W]`` bool, source ``s`` was consulted (learned visibility >= threshold and
            the pixel projects inside that source's map in front of it).
        reproj_error: ``[S, H, W]`` float32 pixels (``inf`` where not measurable).
        depth_error: ``[S, H, W]`` float32 relative depth error (``inf`` where not measurable).
        reprojected_depth: ``[S, H, W]`` float32 the source's depth seen from the reference (0 = none).
        parallax: ``[S, H, W]`` float32 how far (pixels) the pixel's projection into source ``s``
            moves when its depth grows by :data:`PARALLAX_STEP` (0 where it does not project in
            front of the source): how much an agreement with that source says about the depth.
        angle: ``[S, H, W]`` float32 triangulation angle (degrees) at the pixel's 3D point between
            the rays from the reference's and source ``s``'s centres (0 on invalid pixels).
    """

    agree: np.ndarray
    checked: np.ndarray
    reproj_error: np.ndarray
    depth_error: np.ndarray
    reprojected_depth: np.ndarray
    parallax: np.ndarray
    angle: np.ndarray

    @property
    def count(self) -> np.ndarray:
        """``[H, W]`` number of agreeing sources."""
        return self.agree.sum(0)

    def confirming(self, min_angle: float) -> np.ndarray:
        """``[S, H, W]`` bool: agreeing sources whose triangulation :attr:`angle` is at least
        ``min_angle`` degrees (COLMAP's ``filter_min_triangulation_angle``). Two views from nearly the
        same place see the point along nearly the same ray, so their depths agree whether right or
        wrong: such an agreement confirms nothing."""
        return self.agree & (self.angle >= min_angle)

    def mean_depth(self, ref_depth: np.ndarray, agree: np.ndarray | None = None) -> np.ndarray:
        """``[H, W]`` mean of the reference depth and the reprojected depths of the agreeing sources
        (``agree`` ``[S, H, W]``, default :attr:`agree`)."""
        agree = self.agree if agree is None else agree
        num = ref_depth + np.where(agree, self.reprojected_depth, 0.0).sum(0)
        return (num / (1.0 + agree.sum(0))).astype(np.float32)


#: Relative depth step of :attr:`ConsistencyResult.parallax` (the geometric pass's default
#: ``geom_max_depth_error``).
PARALLAX_STEP = 0.03


def check_consistency(
    ref_depth: np.ndarray,
    ref_normals: np.ndarray | None,
    K: np.ndarray,
    cam_from_world: np.ndarray,
    sources: list[SourceMaps],
    visibility: np.ndarray | None = None,
    *,
    max_reproj_error: float = 1.0,
    max_depth_error: float = 0.01,
    max_normal_error: float = 180.0,
    min_visibility: float = 0.0,
    workers: int = 1,
) -> ConsistencyResult:
    """Forward-backward consistency of ``ref_depth`` ``[H, W]`` with each source map.

    Args:
        ref_normals: ``[H, W, 3]`` or ``None``; K: ``[3, 3]``; cam_from_world: ``[3|4, 4]``.
        visibility: ``[S, H, W]`` learned visibility of each source in ``[0, 1]`` (``None``: all 1).
        workers: sources checked at once in threads (numpy releases the GIL in its array loops;
            each source writes only its own slice of the outputs, so the result does not depend on it).
    """
    ref_depth = np.asarray(ref_depth, np.float32)
    if ref_depth.ndim != 2:
        raise ShapeError(f"ref_depth must be [H, W], got shape {ref_depth.shape}")
    H, W = ref_depth.shape
    S = len(sources)
    if visibility is not None and visibility.shape != (S, H, W):
        raise ShapeError(f"visibility must be [{S}, {H}, {W}], got shape {visibility.shape}")
    T_ref = np.eye(4)
    T_ref[:3] = np.asarray(cam_from_world, np.float64)[:3]
    u, v = pixel_centers(H, W)
    valid = ref_depth > 0
    u, v, d = u[valid], v[valid], ref_depth[valid].astype(np.float64)
    K_ref = np.asarray(K, np.float64)
    Kinv_ref = np.linalg.inv(K_ref)
    q = (u * d, v * d, d)  # the pixel with depth d: X = Kinv_ref q in the reference camera frame
    shape = (S, H, W)
    agree = np.zeros(shape, bool)
    checked = np.zeros(shape, bool)
    reproj = np.full(shape, np.inf, np.float32)
    derr = np.full(shape, np.inf, np.float32)
    zrep = np.zeros(shape, np.float32)
    parallax = np.zeros(shape, np.float32)
    angle = np.zeros(shape, np.float32)
    X = tuple(affine_row(row, 0.0, q) for row in Kinv_ref)  # the pixels' points, reference camera frame
    X_norm = np.sqrt(X[0] ** 2 + X[1] ** 2 + X[2] ** 2)
    cos_max = np.cos(np.deg2rad(max_normal_error))
    use_normals = max_normal_error < 180.0 and ref_normals is not None
    if use_normals:
        n_ref = np.asarray(ref_normals, np.float64)[valid]

    def one(s: int, src: SourceMaps) -> None:
        T_src = np.eye(4)
        T_src[:3] = np.asarray(src.cam_from_world, np.float64)[:3]
        T_rel = T_src @ np.linalg.inv(T_ref)  # ref camera -> source camera
        R, t = T_rel[:3, :3], T_rel[:3, 3]
        K_src = np.asarray(src.K, np.float64)
        # Each direction is one affine map of the homogeneous pixel (rows computed one at a time):
        # source camera X_s = R Kinv_ref q + t, its pixel K_src X_s.
        to_cam = R @ Kinv_ref
        z = affine_row(to_cam[2], t[2], q)
        a = K_src @ t
        ux, uy, uw = (affine_row(r, b, q) for r, b in zip(K_src @ to_cam, a, strict=True))
        with np.errstate(divide="ignore", invalid="ignore"):
            us, vs = ux / uw, uy / uw
            # The same pixel at depth (1 + step) d: K_src ((1 + step) R X + t).
            fx, fy, fw = ((1 + PARALLAX_STEP) * c - PARALLAX_STEP * b
                          for c, b in zip((ux, uy, uw), a, strict=True))
            moved = np.hypot(fx / fw - us, fy / fw - vs)
        hs, ws_ = src.depth.shape
        ok = (z > 0) & np.isfinite(us) & np.isfinite(vs)
        far_z = (1 + PARALLAX_STEP) * (z - t[2]) + t[2]
        parallax[s][valid] = np.where(ok & (far_z > 0) & np.isfinite(moved), moved, 0.0)
        centre = -R.T @ t  # the source's centre in the reference frame
        ray = tuple(x - c for x, c in zip(X, centre, strict=True))
        ray_norm = np.sqrt(ray[0] ** 2 + ray[1] ** 2 + ray[2] ** 2)
        with np.errstate(divide="ignore", invalid="ignore"):
            cos = (X[0] * ray[0] + X[1] * ray[1] + X[2] * ray[2]) / (X_norm * ray_norm)
        angle[s][valid] = np.degrees(np.arccos(np.clip(np.nan_to_num(cos, nan=1.0), -1.0, 1.0)))
        col = np.floor(np.where(ok, us, -1)).astype(np.int64)
        row = np.floor(np.where(ok, vs, -1)).astype(np.int64)
        ok &= (col >= 0) & (col < ws_) & (row >= 0) & (row < hs)
        col, row = np.where(ok, col, 0), np.where(ok, row, 0)
        ds = np.where(ok, src.depth[row, col], 0.0).astype(np.float64)
        ok &= ds > 0
        # Back-project the source pixel's centre with its own depth and bring it home:
        # X_b = R^T (Kinv_src r - t), its pixel K_ref X_b.
        r = ((col + 0.5) * ds, (row + 0.5) * ds, ds)
        back = R.T @ np.linalg.inv(K_src)
        off = -R.T @ t
        zb = affine_row(back[2], off[2], r)
        bx, by, bw = (affine_row(m, b, r) for m, b in zip(K_ref @ back, K_ref @ off, strict=True))
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.hypot(bx / bw - u, by / bw - v)
            rel = np.abs(zb - d) / d
        err = np.where(ok & np.isfinite(err), err, np.inf)
        rel = np.where(ok & np.isfinite(rel), rel, np.inf)
        good = ok & (err <= max_reproj_error) & (rel <= max_depth_error)
        if use_normals and src.normals is not None:
            n_src = tuple(np.asarray(src.normals, np.float64)[row, col].T)
            ns = np.stack([affine_row(m, 0.0, n_src) for m in R.T], -1)  # into the reference frame
            cos = np.sum(ns * n_ref, -1)
            has = (np.abs(ns).sum(-1) > 0) & (np.abs(n_ref).sum(-1) > 0)
            good &= ~has | (cos >= cos_max)
        vis_ok = np.ones_like(ok) if visibility is None else visibility[s][valid] >= min_visibility
        checked[s][valid] = ok & vis_ok
        agree[s][valid] = good & vis_ok
        reproj[s][valid] = err
        derr[s][valid] = rel
        zrep[s][valid] = np.where(ok, zb, 0.0)

    if workers > 1 and S > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(min(workers, S), thread_name_prefix="consistency") as pool:
            for f in [pool.submit(one, s, src) for s, src in enumerate(sources)]:
                f.result()
    else:
        for s, src in enumerate(sources):
            one(s, src)
    return ConsistencyResult(agree, checked, reproj, derr, zrep, parallax, angle)


# --------------------------------------------------------------------------- fusion's point check


@dataclass
class PointMatches:
    """The reference points that agree with one source (:func:`match_points`).

    Attributes:
        index: ``[k]`` int64 positions of the agreeing points in the points checked.
        rows, cols: ``[k]`` int64 the source pixel each of them landed in.
        points: ``[k, 3]`` float64 that source pixel back-projected with its own depth, in the
            reference camera frame.
        rotation: ``[3, 3]`` reference camera -> source camera (rotates source normals home as
            ``normals @ rotation``).
    """

    index: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    points: np.ndarray
    rotation: np.ndarray


def _pixel_rays(rows: np.ndarray, cols: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame rays ``[M, 3]`` (z = 1) through map pixel centres ``(cols + 0.5, rows + 0.5)``."""
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    y = (rows + 0.5 - cy) / fy
    x = (cols + 0.5 - cx - skew * y) / fx
    return np.stack([x, y, np.ones_like(x)], axis=1)


def _project(points: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Continuous pixel coordinates ``(u, v)`` of camera-frame points ``[M, 3]`` (z > 0 assumed)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        x = points[:, 0] / points[:, 2]
        y = points[:, 1] / points[:, 2]
    return K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]


def backproject_pixels(rows: np.ndarray, cols: np.ndarray, depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points ``[M, 3]`` float64 of map pixels ``(rows, cols)`` ``[M]`` with depths
    ``depth`` ``[M]`` float64 (the points :func:`match_points` checks)."""
    return _pixel_rays(rows, cols, K) * depth[:, None]


def match_points(
    points: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    K: np.ndarray,
    cam_from_world: np.ndarray,
    source: SourceMaps,
    *,
    max_reproj_error: float,
    max_depth_error: float,
) -> PointMatches:
    """Forward-backward check of reference points against one source map (fusion's form; see the
    module's docstring for how it differs from :func:`check_consistency`).

    Each point is projected into the source, the source's depth at the pixel it lands in is
    back-projected from that pixel's centre and brought back into the reference; the point agrees
    when that lands in front of the reference within ``max_reproj_error`` pixels of its own pixel
    centre and its depth differs by less than ``max_depth_error`` times the point's.

    Args:
        points: ``[P, 3]`` float64 reference camera frame (:func:`backproject_pixels` of ``rows``,
            ``cols``); their z is their depth.
        rows, cols: ``[P]`` int the reference pixels of the points.
        K: ``[3, 3]`` reference intrinsics; cam_from_world: ``[3|4, 4]`` float64 reference pose.
        source: the source's depth ``[h, w]`` (0 = none), ``K`` and ``cam_from_world`` (its normals
            are not used).
    """
    R_ref, t_ref = cam_from_world[:3, :3], cam_from_world[:3, 3]
    R_src, t_src = source.cam_from_world[:3, :3], source.cam_from_world[:3, 3]
    sh, sw = source.depth.shape
    d = points[:, 2]
    A = R_src @ R_ref.T  # reference camera -> source camera rotation
    a = t_src - A @ t_ref
    xs = rowmul(points, A.T) + a
    us, vs = _project(xs, source.K)
    ok = (xs[:, 2] > 0) & (us >= 0) & (us < sw) & (vs >= 0) & (vs < sh)  # NaN compares False
    idx = np.flatnonzero(ok)
    cs = us[idx].astype(np.int64)
    rs = vs[idx].astype(np.int64)
    ds = source.depth[rs, cs]
    has = ds > 0
    idx, cs, rs, ds = idx[has], cs[has], rs[has], ds[has].astype(np.float64)
    # Source pixel back-projected, expressed in the reference camera frame.
    y_ref = rowmul(_pixel_rays(rs, cs, source.K) * ds[:, None] - a, A)
    ur, vr = _project(y_ref, K)
    zr = y_ref[:, 2]
    dref = d[idx]
    with np.errstate(invalid="ignore"):
        good = (
            (zr > 0)
            & (np.hypot(ur - (cols[idx] + 0.5), vr - (rows[idx] + 0.5)) < max_reproj_error)
            & (np.abs(zr - dref) < max_depth_error * dref)
        )
    return PointMatches(idx[good], rs[good], cs[good], y_ref[good], A)
