"""Exact renderings of a smoothly textured 3D plane (for tests and sanity checks of the model).

Conventions as everywhere (``docs/CONVENTIONS.md``): pixel ``(col, row)`` has its centre at
``(col + 0.5, row + 0.5)``; ``cam_from_world`` is ``[4, 4]`` with ``x_cam = R x_world + t``;
depth is the camera-frame z.
"""

from __future__ import annotations

import numpy as np


def plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit normal and two orthonormal in-plane axes ``(n, e1, e2)``."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    helper = np.array([0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(helper, n)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    return n, e1, e2


def plane_texture(s: np.ndarray, t: np.ndarray, period: float) -> np.ndarray:
    """Smooth RGB texture ``[3, ...]`` in ``[0, 1]`` of in-plane coordinates ``(s, t)`` (world units)."""
    w = 2.0 * np.pi / period
    chans = []
    for c, phase in enumerate((0.0, 1.3, 2.9)):
        v = (
            0.5
            + 0.2 * np.sin(w * s + phase)
            + 0.15 * np.sin(0.8 * w * t + 2 * phase + 0.4)
            + 0.1 * np.sin(0.6 * w * (s + t) + 0.5 * c)
        )
        chans.append(v)
    return np.stack(chans, 0)


def render_plane(
    K: np.ndarray,
    cam_from_world: np.ndarray,
    height: int,
    width: int,
    *,
    normal: np.ndarray,
    offset: float,
    period: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Render the plane ``{X : n . X = offset}`` (world frame) with :func:`plane_texture`.

    Each pixel samples the texture exactly at the ray through its centre (no anti-aliasing).

    Returns:
        ``(image [3, H, W] float64 in [0, 1], depth [H, W] float64)``; depth is 0 (and the image 0)
        where the ray misses the plane or hits it behind the camera.
    """
    n, e1, e2 = plane_basis(normal)
    n_raw = np.asarray(normal, dtype=np.float64)
    offset = offset / np.linalg.norm(n_raw)
    T = np.asarray(cam_from_world, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    center = -R.T @ t
    v, u = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    rays_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T  # z = 1
    rays_world = rays_cam @ R  # R^T d
    denom = rays_world @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (offset - center @ n) / denom  # = camera depth because rays_cam has z = 1
    ok = np.isfinite(lam) & (lam > 1e-9)
    lam = np.where(ok, lam, 0.0)
    X = center + lam[..., None] * rays_world
    image = plane_texture(X @ e1, X @ e2, period) * ok
    return image, lam
