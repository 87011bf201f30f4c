"""Simulated structure-from-motion output: sparse points with tracks, as COLMAP would give them.

Points are sampled on the rendered surfaces, preferably where the image is textured (as
feature detectors do), and each point's track is the set of views that see it: inside
the image, in front of the camera, not too oblique and not occluded (ray cast from the
camera centre). Points seen by fewer than ``min_track`` views are dropped, like
untriangulated features.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ShapeError
from ..types import Camera, Image, Points3D, SparseModel
from .cameras import CameraRig
from .render import Renderer

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class SimulatedPoints:
    """Sparse points of one scene.

    Attributes:
        xyz: ``[P, 3]`` float64 world coordinates (with the simulated triangulation noise).
        rgb: ``[P, 3]`` uint8 colours.
        visibility: ``[P, V]`` bool; ``visibility[p, v]`` means view ``v`` is in point ``p``'s track.
    """

    xyz: np.ndarray
    rgb: np.ndarray
    visibility: np.ndarray

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


def texture_weights(image: np.ndarray) -> np.ndarray:
    """``[H, W]`` float64 sampling weights: gradient magnitude of a ``[H, W, 3]`` uint8 image plus a floor."""
    gray = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY).astype(np.float32)
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
    mag = np.sqrt(gx * gx + gy * gy).astype(np.float64)
    return mag + 0.05 * max(float(mag.mean()), 1e-3)


def project(points: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project ``[P, 3]`` world points: ``(uv [P, 2] continuous pixel coords, z [P] camera depth)``."""
    cam = points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = cam @ K.T
        uv = uvw[:, :2] / uvw[:, 2:3]
    return uv, z


def simulate_sparse_points(
    renderer: Renderer,
    rig: CameraRig,
    images: np.ndarray,
    depths: np.ndarray,
    normals: np.ndarray,
    rng: np.random.Generator,
    num_points: int = 1500,
    min_track: int = 2,
    max_angle_deg: float = 75.0,
    noise: float = 5e-4,
    texture_weighted: bool = True,
) -> SimulatedPoints:
    """Sample surface points and their tracks.

    Args:
        renderer: renders the rig's scene (used for the occlusion tests).
        rig: the cameras.
        images: ``[V, H, W, 3]`` uint8 rendered images (for texture weighting and colours).
        depths: ``[V, H, W]`` float32 GT depth (0 invalid).
        normals: ``[V, H, W, 3]`` float32 camera-frame normals facing the camera.
        num_points: points sampled in total before the track filter (spread evenly over views).
        min_track: minimum track length kept.
        max_angle_deg: a view sees a point only if the angle between the surface normal and the
            direction to the camera is below this.
        noise: triangulation noise std, relative to the distance to the sampling camera.
        texture_weighted: sample pixels with probability proportional to the image gradient.
    """
    V, H, W = depths.shape
    if images.shape != (V, H, W, 3) or normals.shape != (V, H, W, 3) or len(rig) != V:
        raise ShapeError(
            f"expected images [V, H, W, 3], depths [V, H, W], normals [V, H, W, 3] and {V} cameras; got "
            f"{images.shape}, {depths.shape}, {normals.shape}, {len(rig)} cameras"
        )
    per_view = int(np.ceil(num_points / V))
    xyz, nrm, rgb, src = [], [], [], []
    for v in range(V):
        valid = depths[v].reshape(-1) > 0
        if not valid.any():
            continue
        w = texture_weights(images[v]).reshape(-1) if texture_weighted else np.ones(H * W)
        w = w * valid
        k = min(per_view, int(valid.sum()))
        pix = rng.choice(H * W, size=k, replace=False, p=w / w.sum())
        row, col = np.divmod(pix, W)
        z = depths[v].reshape(-1)[pix].astype(np.float64)
        ray = np.stack([col + 0.5, row + 0.5, np.ones_like(z)], 1) @ np.linalg.inv(rig.K[v]).T
        cam = ray / ray[:, 2:3] * z[:, None]
        R, t = rig.cam_from_world[v, :, :3], rig.cam_from_world[v, :, 3]
        xyz.append((cam - t) @ R)
        nrm.append(normals[v].reshape(-1, 3)[pix].astype(np.float64) @ R)
        rgb.append(images[v].reshape(-1, 3)[pix])
        src.append(np.full(k, v))
    if not xyz:
        return SimulatedPoints(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros((0, V), bool))
    xyz_a, nrm_a, rgb_a, src_a = (np.concatenate(a) for a in (xyz, nrm, rgb, src))
    n_sampled = src_a.size
    centers = rig.centers
    vis = np.zeros((xyz_a.shape[0], V), bool)
    cos_max = np.cos(np.radians(max_angle_deg))
    for v in range(V):
        uv, z = project(xyz_a, rig.K[v], rig.cam_from_world[v])
        to_cam = centers[v] - xyz_a
        dist = np.linalg.norm(to_cam, axis=1)
        facing = np.einsum("ij,ij->i", nrm_a, to_cam) / np.maximum(dist, 1e-12)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        vis[:, v] = inside & (facing > cos_max)
    pv, vv = np.nonzero(vis)
    if pv.size:
        clear = renderer.segments_clear(centers[vv], xyz_a[pv], rel_tol=1e-3)
        vis[pv[~clear], vv[~clear]] = False
    vis[np.arange(src_a.size), src_a] = True
    keep = vis.sum(1) >= min_track
    xyz_a, rgb_a, vis, src_a = xyz_a[keep], rgb_a[keep], vis[keep], src_a[keep]
    if noise > 0 and xyz_a.shape[0]:
        dist = np.linalg.norm(xyz_a - centers[src_a], axis=1)
        xyz_a = xyz_a + rng.normal(0, 1, xyz_a.shape) * (noise * dist)[:, None]
        for v in range(V):  # the noise may push an observation out of the image: drop it
            uv, z = project(xyz_a, rig.K[v], rig.cam_from_world[v])
            vis[:, v] &= (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        keep = vis.sum(1) >= min_track
        xyz_a, rgb_a, vis = xyz_a[keep], rgb_a[keep], vis[keep]
    logger.debug(
        "simulated %d sparse points (of %d sampled), mean track %.2f",
        xyz_a.shape[0],
        n_sampled,
        float(vis.sum(1).mean()) if vis.size else 0.0,
    )
    return SimulatedPoints(xyz=xyz_a, rgb=rgb_a.astype(np.uint8), visibility=vis)


def build_sparse_model(
    rig_K: np.ndarray,
    rig_poses: np.ndarray,
    width: int,
    height: int,
    names: Sequence[str],
    xyz: np.ndarray,
    rgb: np.ndarray,
    visibility: np.ndarray,
    errors: np.ndarray | None = None,
) -> SparseModel:
    """A :class:`~colmap_pvs.types.SparseModel`: one PINHOLE camera per image (ids ``1..V``).

    Image ``v`` has image and camera id ``v + 1``; point ids are ``1..P``.

    Args:
        rig_K: ``[V, 3, 3]`` intrinsics; rig_poses: ``[V, 3, 4]`` ``cam_from_world``.
        names: ``V`` image names.
        xyz: ``[P, 3]``; rgb: ``[P, 3]`` uint8; visibility: ``[P, V]`` bool tracks.
        errors: optional ``[P]`` reprojection errors (default 0.5 px).
    """
    V = rig_K.shape[0]
    P = xyz.shape[0]
    if rig_poses.shape != (V, 3, 4) or len(names) != V or visibility.shape != (P, V) or rgb.shape != (P, 3):
        raise ShapeError(
            f"inconsistent shapes: K {rig_K.shape}, poses {rig_poses.shape}, {len(names)} names, "
            f"xyz {xyz.shape}, rgb {rgb.shape}, visibility {visibility.shape}"
        )
    cameras, images = {}, {}
    point_ids = np.arange(1, P + 1, dtype=np.int64)
    for v in range(V):
        K = np.asarray(rig_K[v], np.float64)
        params = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
        cameras[v + 1] = Camera(v + 1, "PINHOLE", int(width), int(height), K, params)
        images[v + 1] = Image(
            v + 1, str(names[v]), v + 1, np.asarray(rig_poses[v], np.float64), point_ids[visibility[:, v]]
        )
    _, cols = np.nonzero(visibility)  # row-major: sorted by point, then image
    offsets = np.zeros(P + 1, np.int64)
    np.cumsum(visibility.sum(1), out=offsets[1:])
    points = Points3D(
        ids=point_ids,
        xyz=np.asarray(xyz, np.float64),
        rgb=np.asarray(rgb, np.uint8),
        error=np.full(P, 0.5) if errors is None else np.asarray(errors, np.float64),
        track_offsets=offsets,
        track_image_ids=(cols + 1).astype(np.int64),
    )
    return SparseModel(
        cameras=cameras,
        images=images,
        points=points,
        image_ids_by_name={str(n): v + 1 for v, n in enumerate(names)},
    )
