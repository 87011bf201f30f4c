"""CPU ray-casting renderer (open3d ``RaycastingScene``) and per-view photometric changes.

One ray per pixel centre gives the ground truth: pixel ``(col, row)`` is the ray through
continuous coordinate ``(col + 0.5, row + 0.5)`` (``docs/CONVENTIONS.md``). Ray directions
are ``R^T K^-1 [u, v, 1]``, whose camera-frame z is 1, so the hit distance *is* the depth
(camera z). Colours may be supersampled (``supersample`` x ``supersample`` rays per pixel,
box filtered) for anti-aliased edges; depth and normals always come from the centre ray.

Shading is view independent (Lambert with the scene's light, an ambient term and ray-traced
shadows), so a surface point has the same colour in every view before the per-view
photometric changes of :func:`apply_photometric` (exposure, white balance, vignetting,
optical and motion blur, gamma, noise).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import ConfigError, ShapeError
from .scenes import Scene
from .textures import build_mipmaps, sample_textures

logger = logging.getLogger(__name__)


def _pair(name: str, value: tuple[float, ...], lo: float = 0.0) -> tuple[float, float]:
    try:
        pair = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be two numbers, got {value!r}") from None
    if len(pair) != 2 or not lo <= pair[0] <= pair[1]:
        raise ConfigError(f"{name} must be two numbers {lo} <= lo <= hi, got {value!r}")
    return pair  # type: ignore[return-value]


@dataclass(frozen=True)
class RenderConfig:
    """Rendering and per-view photometric changes (all random draws are seeded per view)."""

    supersample: int = field(
        default=2, metadata={"help": "colour rays per pixel along each axis (1 = no AA)"}
    )
    shadows: bool = field(default=True, metadata={"help": "ray-traced shadows from the scene light"})
    exposure_stops: float = field(default=0.5, metadata={"help": "per-view exposure change, +- stops"})
    white_balance: float = field(default=0.08, metadata={"help": "per-view channel gains in 1 +- this"})
    gamma: tuple[float, ...] = field(default=(0.85, 1.2), metadata={"help": "per-view gamma range (lo, hi)"})
    noise_std: tuple[float, ...] = field(
        default=(0.002, 0.02),
        metadata={"help": "per-view Gaussian noise std range (lo, hi), image in [0, 1]"},
    )
    blur_probability: float = field(
        default=0.3, metadata={"help": "probability of a Gaussian (defocus) blur"}
    )
    blur_sigma: tuple[float, ...] = field(default=(0.3, 1.0), metadata={"help": "blur sigma range in pixels"})
    motion_blur_probability: float = field(
        default=0.15, metadata={"help": "probability of a linear motion blur"}
    )
    motion_blur_length: tuple[float, ...] = field(
        default=(2.0, 6.0), metadata={"help": "motion blur length range in pixels"}
    )
    vignetting: float = field(default=0.3, metadata={"help": "maximum brightness loss in the image corners"})

    def __post_init__(self) -> None:
        if self.supersample < 1:
            raise ConfigError(f"supersample must be >= 1, got {self.supersample}")
        for name in ("gamma", "noise_std", "blur_sigma", "motion_blur_length"):
            object.__setattr__(self, name, _pair(name, getattr(self, name)))
        if self.gamma[0] <= 0:
            raise ConfigError(f"gamma must be positive, got {self.gamma!r}")
        for name in ("blur_probability", "motion_blur_probability", "vignetting", "white_balance"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if self.exposure_stops < 0:
            raise ConfigError(f"exposure_stops must be >= 0, got {self.exposure_stops}")


@dataclass(frozen=True, eq=False)
class RenderedView:
    """One rendered view.

    Attributes:
        image: ``[H, W, 3]`` float32 shaded colour (before photometric changes), about [0, 1].
        depth: ``[H, W]`` float32 camera-frame z, 0 where the ray hits nothing.
        normals: ``[H, W, 3]`` float32 unit camera-frame normals facing the camera, 0 where invalid.
        triangle_ids: ``[H, W]`` int64 hit triangle, -1 where invalid.
    """

    image: np.ndarray
    depth: np.ndarray
    normals: np.ndarray
    triangle_ids: np.ndarray


def _check_camera(K: np.ndarray, cam_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    K = np.asarray(K, np.float64)
    pose = np.asarray(cam_from_world, np.float64)
    if K.shape != (3, 3):
        raise ShapeError(f"K must be [3, 3], got shape {K.shape}")
    if pose.shape not in ((3, 4), (4, 4)):
        raise ShapeError(f"cam_from_world must be [3, 4] or [4, 4], got shape {pose.shape}")
    return K, pose[:3, :3], pose[:3, 3]


class Renderer:
    """Renders one :class:`Scene` from arbitrary pinhole cameras.

    Args:
        scene: the scene (its mesh is uploaded to an open3d ``RaycastingScene`` once).
        nthreads: ray-casting threads (0 = all cores).
    """

    def __init__(self, scene: Scene, nthreads: int = 0) -> None:
        import open3d as o3d

        self._o3d = o3d
        self.scene = scene
        self.nthreads = int(nthreads)
        self._rc = o3d.t.geometry.RaycastingScene()
        self._rc.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(scene.vertices, np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(scene.triangles, np.uint32)),
        )
        v = scene.vertices[scene.triangles]  # [F, 3, 3]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        self._tri_normals = n / np.where(norm > 0, norm, 1.0)
        self._tri_normals32 = self._tri_normals.astype(np.float32)
        self._tri_uvs = scene.uvs[scene.triangles].astype(np.float32)  # [F, 3, 2]
        self._tri_uvs[:, 1:] -= self._tri_uvs[:, :1]
        self._mips = build_mipmaps(scene.textures)
        self._tex_size = scene.textures.shape[1]

    # ------------------------------------------------------------------ rays

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cast ``[N, 3]`` rays (origins may be ``[3]``).

        Returns:
            ``(t [N] float64, triangle_ids [N] int64, barycentric [N, 2] float64)``: ``t`` in units of
            the direction length (``inf`` and id -1 where nothing is hit). The hit point is
            ``(1 - a - b) v0 + a v1 + b v2`` for ``(a, b) = barycentric``.
        """
        directions = np.asarray(directions, np.float32).reshape(-1, 3)
        origins = np.broadcast_to(np.asarray(origins, np.float32), directions.shape)
        rays = np.ascontiguousarray(np.concatenate([origins, directions], 1), np.float32)
        out = self._rc.cast_rays(self._o3d.core.Tensor(rays), nthreads=self.nthreads)
        t = out["t_hit"].numpy().astype(np.float64)
        ids = out["primitive_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t)
        ids[~hit] = -1
        return t, ids, out["primitive_uvs"].numpy().astype(np.float64)

    def occluded(
        self, origins: np.ndarray, directions: np.ndarray, tfar: float = np.inf, tnear: float = 0.0
    ) -> np.ndarray:
        """``[N]`` bool: does ray ``origin + t * direction`` hit anything for ``t`` in ``[tnear, tfar]``."""
        directions = np.asarray(directions, np.float32).reshape(-1, 3)
        origins = np.broadcast_to(np.asarray(origins, np.float32), directions.shape)
        rays = np.ascontiguousarray(np.concatenate([origins, directions], 1), np.float32)
        occ = self._rc.test_occlusions(
            self._o3d.core.Tensor(rays), tnear=float(tnear), tfar=float(tfar), nthreads=self.nthreads
        )
        return occ.numpy().astype(bool)

    @staticmethod
    def pixel_rays(
        K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int, supersample: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """Camera centre ``[3]`` and world ray directions ``[H * s, W * s, 3]`` (camera z = 1).

        With ``s = supersample`` the rays of pixel ``(col, row)`` pass through
        ``(col + (i + 0.5) / s, row + (j + 0.5) / s)``; ``s = 1`` gives the pixel centres.
        """
        K, R, t = _check_camera(K, cam_from_world)
        s = int(supersample)
        u = (np.arange(width * s) + 0.5) / s
        v = (np.arange(height * s) + 0.5) / s
        uu, vv = np.meshgrid(u, v)
        pix = np.stack([uu, vv, np.ones_like(uu)], -1)
        d_cam = pix @ np.linalg.inv(K).T
        d_cam /= d_cam[..., 2:3]
        return -R.T @ t, d_cam @ R  # (R^T d)^T = d^T R

    # ------------------------------------------------------------------ rendering

    def _centre_cast(
        self, K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Pixel-centre rays: ``(centre [3], dirs [H*W, 3], t [H*W], ids [H*W], barycentric [H*W, 2])``."""
        _, R, _ = _check_camera(K, cam_from_world)
        centre, dirs = self.pixel_rays(K, cam_from_world, height, width)
        dirs = dirs.reshape(-1, 3)
        t, ids, bary = self.cast(centre, dirs)
        t, ids, bary = self._fill_cracks(centre, dirs, t, ids, bary, K, R, height, width)
        return centre, dirs, t, ids, bary

    def _geometry(
        self, R: np.ndarray, dirs: np.ndarray, t: np.ndarray, ids: np.ndarray, height: int, width: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        hit = ids >= 0
        depth = np.where(hit, t, 0.0).reshape(height, width).astype(np.float32)
        n = self._tri_normals[np.maximum(ids, 0)]
        flip = np.einsum("ij,ij->i", n, dirs) > 0
        n = np.where(flip[:, None], -n, n)
        n_cam = (n @ R.T) * hit[:, None]
        return depth, n_cam.reshape(height, width, 3).astype(np.float32), ids.reshape(height, width)

    def render_depth(
        self, K: np.ndarray, cam_from_world: np.ndarray, height: int, width: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Geometry only: ``(depth [H, W] float32, normals [H, W, 3] float32, triangle_ids [H, W] int64)``."""
        _, R, _ = _check_camera(K, cam_from_world)
        _, dirs, t, ids, _ = self._centre_cast(K, cam_from_world, height, width)
        return self._geometry(R, dirs, t, ids, height, width)

    def _fill_cracks(
        self,
        centre: np.ndarray,
        dirs: np.ndarray,
        t: np.ndarray,
        ids: np.ndarray,
        bary: np.ndarray,
        K: np.ndarray,
        R: np.ndarray,
        height: int,
        width: int,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Re-cast isolated misses (a ray slipping between two triangles that share an edge).

        A miss whose four neighbours all hit is re-cast with the ray moved by 0.02, then 0.1 pixel
        (a negligible change of the sampled depth).
        """
        miss = (ids < 0).reshape(height, width)
        if not miss.any() or height < 3 or width < 3:
            return t, ids, bary
        hit = ~miss
        inner = np.zeros_like(miss)
        inner[1:-1, 1:-1] = miss[1:-1, 1:-1] & hit[:-2, 1:-1] & hit[2:, 1:-1] & hit[1:-1, :-2] & hit[1:-1, 2:]
        sel = np.flatnonzero(inner)
        if sel.size == 0:
            return t, ids, bary
        t, ids, bary = t.copy(), ids.copy(), bary.copy()
        for du, dv in ((0.02, 0.02), (-0.02, -0.02), (0.1, -0.1), (-0.1, 0.1)):
            shift = R.T @ np.array([du / K[0, 0], dv / K[1, 1], 0.0])
            t2, ids2, bary2 = self.cast(centre, dirs[sel] + shift)
            ok = ids2 >= 0
            t[sel[ok]], ids[sel[ok]], bary[sel[ok]] = t2[ok], ids2[ok], bary2[ok]
            sel = sel[~ok]
            if sel.size == 0:
                break
        return t, ids, bary

    def _shade(
        self,
        origin: np.ndarray,
        dirs: np.ndarray,
        t: np.ndarray,
        ids: np.ndarray,
        bary: np.ndarray,
        focal: float,
        shadows: bool,
    ) -> np.ndarray:
        """Colours ``[N, 3]`` of ray hits (background where ``ids < 0``)."""
        sc = self.scene
        out = np.empty((ids.shape[0], 3), np.float32)
        out[:] = sc.background
        hit = np.nonzero(ids >= 0)[0]
        if hit.size == 0:
            return out
        tri = ids[hit]
        f32 = np.float32
        d = dirs[hit].astype(f32)
        th = t[hit].astype(f32)
        p = origin.astype(f32) + th[:, None] * d
        n = self._tri_normals32[tri]
        dn = np.einsum("ij,ij->i", n, d)
        n *= np.where(dn > 0, f32(-1), f32(1))[:, None]
        cos_inc = np.abs(dn) / np.sqrt(np.einsum("ij,ij->i", d, d))
        tuv = self._tri_uvs[tri]
        b = bary[hit].astype(f32)
        uv = tuv[:, 0] + b[:, 0:1] * tuv[:, 1] + b[:, 1:2] * tuv[:, 2]
        footprint = th / f32(focal) / np.maximum(cos_inc, f32(0.2))  # scene units per pixel (t = depth)
        texels = footprint * sc.triangle_density[tri] * f32(self._tex_size)
        albedo = sample_textures(self._mips, sc.triangle_texture[tri], uv, texels)
        light = sc.light
        if light.kind == "directional":
            to_light = -np.asarray(light.vector, np.float64)
            to_light = np.broadcast_to((to_light / np.linalg.norm(to_light)).astype(f32), p.shape)
            atten = f32(1.0)
            tfar = np.inf
        else:
            to_light = np.asarray(light.vector, f32) - p
            dist = np.sqrt(np.einsum("ij,ij->i", to_light, to_light))
            atten = 1.0 / (1.0 + (dist / light.falloff) ** 2) * 2.0
            tfar = 0.999
        ndotl = np.einsum("ij,ij->i", n, to_light) / np.sqrt(np.einsum("ij,ij->i", to_light, to_light))
        lit = ndotl > 0
        vis = lit.astype(f32)
        if shadows and lit.any():
            eps = f32(1e-4) * np.maximum(th, f32(1.0))
            sel = np.nonzero(lit)[0]
            origins = p[sel] + n[sel] * eps[sel, None]
            blocked = self.occluded(origins, to_light[sel], tfar=tfar)
            vis[sel[blocked]] = 0.0
        shade = f32(light.ambient) + f32(light.intensity) * np.maximum(ndotl, 0) * vis * atten
        out[hit] = albedo * shade[:, None]
        return out

    def _edge_pixels(self, normals: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """``[H, W]`` bool: pixels next to a silhouette, crease or material edge (they get supersampled).

        Neighbouring pixels differ when they hit different surface patches or textures, only one of
        them hits, or their normals differ by more than about 25 degrees (tessellation does not count).
        """
        sc = self.scene
        safe = np.maximum(ids, 0)
        part = np.where(ids >= 0, sc.triangle_part[safe], -1)
        tex = np.where(ids >= 0, sc.triangle_texture[safe], -1)
        edge = np.zeros(ids.shape, bool)
        for axis in (0, 1):
            sl_a = (slice(None, -1), slice(None)) if axis == 0 else (slice(None), slice(None, -1))
            sl_b = (slice(1, None), slice(None)) if axis == 0 else (slice(None), slice(1, None))
            crease = np.einsum("ijk,ijk->ij", normals[sl_a], normals[sl_b]) < 0.9
            diff = crease | (part[sl_a] != part[sl_b]) | (tex[sl_a] != tex[sl_b])
            edge[sl_a] |= diff
            edge[sl_b] |= diff
        return edge

    def render(
        self,
        K: np.ndarray,
        cam_from_world: np.ndarray,
        height: int,
        width: int,
        supersample: int = 1,
        shadows: bool = True,
    ) -> RenderedView:
        """Render colour (before photometric changes), depth and normals of one view.

        With ``supersample = s > 1``, pixels next to silhouettes, creases or material edges get ``s x s``
        colour rays (box filtered); the other pixels, where a single ray is exact up to the
        mip-mapped texture, keep their centre ray.
        """
        K, R, _ = _check_camera(K, cam_from_world)
        centre, dirs, t, ids, bary = self._centre_cast(K, cam_from_world, height, width)
        depth, normals, id_map = self._geometry(R, dirs, t, ids, height, width)
        focal = float(np.sqrt(K[0, 0] * K[1, 1]))
        col = self._shade(centre, dirs, t, ids, bary, focal, shadows)
        s = int(supersample)
        if s > 1:
            edge = np.flatnonzero(self._edge_pixels(normals, id_map))
            if edge.size:
                row, colm = np.divmod(edge, width)
                off = (np.arange(s) + 0.5) / s
                ou, ov = np.meshgrid(off, off)
                u = (colm[:, None] + ou.reshape(1, -1)).reshape(-1)
                v = (row[:, None] + ov.reshape(1, -1)).reshape(-1)
                d_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
                d_sub = (d_cam / d_cam[:, 2:3]) @ R
                t2, ids2, bary2 = self.cast(centre, d_sub)
                sub = self._shade(centre, d_sub, t2, ids2, bary2, focal * s, shadows)
                col[edge] = sub.reshape(edge.size, s * s, 3).mean(1)
        image = col.reshape(height, width, 3).astype(np.float32)
        return RenderedView(image=image, depth=depth, normals=normals, triangle_ids=id_map)

    def segments_clear(self, starts: np.ndarray, ends: np.ndarray, rel_tol: float = 1e-3) -> np.ndarray:
        """``[N]`` bool: is the segment from ``starts[i]`` (a camera centre) to ``ends[i]`` free.

        ``ends`` are points on a surface.

        Hits within ``rel_tol`` (relative to the segment length) of the end count as the end point itself.
        """
        starts = np.asarray(starts, np.float64).reshape(-1, 3)
        ends = np.asarray(ends, np.float64).reshape(-1, 3)
        if starts.shape != ends.shape:
            raise ShapeError(f"starts {starts.shape} and ends {ends.shape} must both be [N, 3]")
        t, _, _ = self.cast(starts, ends - starts)
        return t >= 1.0 - rel_tol

    def visible(self, points: np.ndarray, centers: np.ndarray, rel_tol: float = 1e-3) -> np.ndarray:
        """``[P, V]`` bool: :meth:`segments_clear` for every (surface point, camera centre) pair."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        centers = np.asarray(centers, np.float64).reshape(-1, 3)
        P, V = points.shape[0], centers.shape[0]
        starts = np.broadcast_to(centers[None], (P, V, 3)).reshape(-1, 3)
        ends = np.broadcast_to(points[:, None], (P, V, 3)).reshape(-1, 3)
        return self.segments_clear(starts, ends, rel_tol).reshape(P, V)


# --------------------------------------------------------------------------- photometric


def _motion_kernel(length: float, angle: float) -> np.ndarray:
    size = int(np.ceil(length)) | 1
    k = np.zeros((size, size), np.float32)
    c = size // 2
    dx, dy = np.cos(angle), np.sin(angle)
    for s in np.linspace(-length / 2, length / 2, 4 * size):
        x, y = c + s * dx, c + s * dy
        x0, y0 = int(np.floor(x)), int(np.floor(y))
        fx, fy = x - x0, y - y0
        for xi, yi, w in (
            (x0, y0, (1 - fx) * (1 - fy)),
            (x0 + 1, y0, fx * (1 - fy)),
            (x0, y0 + 1, (1 - fx) * fy),
            (x0 + 1, y0 + 1, fx * fy),
        ):
            if 0 <= xi < size and 0 <= yi < size:
                k[yi, xi] += w
    return k / k.sum()


def apply_photometric(image: np.ndarray, rng: np.random.Generator, config: RenderConfig) -> np.ndarray:
    """Per-view camera effects on a ``[H, W, 3]`` float image -> ``[H, W, 3]`` uint8.

    In order: exposure, white balance, vignetting, defocus blur, motion blur, gamma, noise,
    quantisation. Every parameter is drawn from ``rng``.
    """
    if image.ndim != 3 or image.shape[2] != 3:
        raise ShapeError(f"image must be [H, W, 3], got shape {image.shape}")
    h, w = image.shape[:2]
    c = config
    img = image.astype(np.float32) * np.float32(2.0 ** rng.uniform(-c.exposure_stops, c.exposure_stops))
    img = img * rng.uniform(1 - c.white_balance, 1 + c.white_balance, 3).astype(np.float32)
    strength = rng.uniform(0, c.vignetting)
    if strength > 0:
        v, u = np.meshgrid(np.linspace(-1, 1, h), np.linspace(-1, 1, w), indexing="ij")
        img = img * (1 - strength * (u**2 + v**2) / 2).astype(np.float32)[..., None]
    if rng.random() < c.blur_probability:
        img = cv2.GaussianBlur(img, (0, 0), float(rng.uniform(*c.blur_sigma)), borderType=cv2.BORDER_REFLECT)
    if rng.random() < c.motion_blur_probability:
        kern = _motion_kernel(float(rng.uniform(*c.motion_blur_length)), float(rng.uniform(0, np.pi)))
        img = cv2.filter2D(img, -1, kern, borderType=cv2.BORDER_REFLECT)
    img = np.clip(img, 0, 1) ** np.float32(1.0 / rng.uniform(*c.gamma))
    img = img + rng.normal(0, rng.uniform(*c.noise_std), img.shape).astype(np.float32)
    return np.clip(np.round(img * 255), 0, 255).astype(np.uint8)
