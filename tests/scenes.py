"""Analytic synthetic scene for tests: a textured ground plane plus a box, seen by pinhole cameras.

Everything is exact: per-pixel z-depth from ray/plane and ray/box intersections, camera-frame
unit normals that face the camera, a procedurally textured RGB rendering and a sparse model
with correct tracks (occlusion-checked). :func:`make_analytic_workspace` writes a complete
COLMAP dense workspace and returns the ground truth.

Pixel conventions: images and the returned GT maps use ours (pixel ``(col, row)`` centre at
``(col + 0.5, row + 0.5)`` for ``K``). Maps written into ``stereo/`` follow ``map_convention``:
``"colmap"`` (default) renders them for :func:`colmap_pvs.io.maps.fusion_intrinsics`, i.e. pixel
``(col, row)`` holds the depth along ``K^-1 [col, row, 1]``, which is how COLMAP's fusion reads them;
``"centre"`` renders them with ``K`` itself (the half-pixel-shifted variant, for convention tests).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from colmap_pvs.geometry import pixel_centers
from colmap_pvs.io import (
    fusion_intrinsics,
    write_depth_map,
    write_fusion_cfg,
    write_normal_map,
    write_patch_match_cfg,
    write_sparse_model,
)
from colmap_pvs.types import Camera, Image, Points3D, SparseModel

# --------------------------------------------------------------------------- scene


@dataclass(frozen=True, eq=False)
class AnalyticScene:
    """The infinite ground plane ``z = ground_z`` (normal +z) plus an axis-aligned box on it."""

    box_min: np.ndarray = field(default_factory=lambda: np.array([-0.6, -0.5, 0.0]))
    box_max: np.ndarray = field(default_factory=lambda: np.array([0.5, 0.6, 0.9]))
    ground_z: float = 0.0

    @property
    def size(self) -> float:
        """A length scale of the scene (the box diagonal)."""
        return float(np.linalg.norm(self.box_max - self.box_min))

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hit of rays ``origins + t * dirs`` (``[N, 3]`` each).

        Returns:
            ``t`` ``[N]`` (``inf`` for a miss) and the outward world normal ``[N, 3]`` at the hit.
        """
        origins = np.broadcast_to(origins, dirs.shape)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_plane = (self.ground_z - origins[:, 2]) / dirs[:, 2]
            t_plane = np.where(t_plane > 0, t_plane, np.inf)
            t1 = (self.box_min - origins) / dirs
            t2 = (self.box_max - origins) / dirs
        t_lo, t_hi = np.fmin(t1, t2), np.fmax(t1, t2)
        t_near, axis = t_lo.max(axis=1), t_lo.argmax(axis=1)
        t_far = t_hi.min(axis=1)
        box_hit = (t_near <= t_far) & (t_near > 0)
        t_box = np.where(box_hit, t_near, np.inf)
        normals = np.zeros(dirs.shape)
        normals[:, 2] = 1.0
        use_box = t_box < t_plane
        rows = np.flatnonzero(use_box)
        normals[rows] = 0.0
        normals[rows, axis[rows]] = -np.sign(dirs[rows, axis[rows]])
        return np.minimum(t_box, t_plane), normals

    def _faces(self) -> list[tuple[int, float, float]]:
        """``(axis, coordinate, outward sign)`` of the box's five visible faces (not the bottom)."""
        faces = [(a, float(self.box_min[a]), -1.0) for a in (0, 1)]
        return faces + [(a, float(self.box_max[a]), 1.0) for a in (0, 1, 2)]

    def _surface_distances(self, points: np.ndarray) -> np.ndarray:
        """``[N, 6]`` distances to the ground plane (column 0) and to each face rectangle."""
        clamped = np.clip(points, self.box_min, self.box_max)
        columns = [np.abs(points[:, 2] - self.ground_z)]
        for axis, coord, _ in self._faces():
            q = clamped.copy()
            q[:, axis] = coord
            columns.append(np.linalg.norm(points - q, axis=1))
        return np.stack(columns, axis=1)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Distance ``[N]`` of ``[N, 3]`` points to the surface (ground plane or box faces)."""
        return self._surface_distances(points).min(axis=1)

    def nearest_normal(self, points: np.ndarray) -> np.ndarray:
        """Outward world normal ``[N, 3]`` of the surface part nearest to each point."""
        table = np.zeros((6, 3))
        table[0, 2] = 1.0
        for k, (axis, _, sign) in enumerate(self._faces()):
            table[k + 1, axis] = sign
        return table[self._surface_distances(points).argmin(axis=1)]

    def texture(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Procedural colour ``[N, 3]`` uint8 of surface points (multi-scale, face-dependent)."""
        x, y, z = points.T
        checker = (np.floor(x * 4) + np.floor(y * 4) + np.floor(z * 4)) % 2
        fine = np.sin(9 * x + 4 * y + 6 * z) * np.cos(5 * x - 8 * y + 5 * z)
        hue = np.abs(normals) @ np.array([0.2, 0.5, 0.8])
        rgb = np.stack(
            [
                0.45 + 0.25 * checker + 0.2 * fine,
                0.35 + 0.3 * np.sin(3 * x + 2 * z + hue * 4) + 0.1 * fine,
                0.5 + 0.2 * np.cos(2 * y - 3 * x) - 0.2 * checker * hue,
            ],
            axis=1,
        )
        return (np.clip(rgb, 0, 1) * 255).round().astype(np.uint8)


# --------------------------------------------------------------------------- cameras


def look_at(center: np.ndarray, target: np.ndarray, up: tuple[float, ...] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """``[3, 4]`` cam_from_world of a camera at ``center`` looking at ``target`` (OpenCV axes)."""
    up = np.asarray(up, dtype=np.float64)
    forward = target - center
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])
    return np.concatenate([R, (-R @ center)[:, None]], axis=1)


def sphere_cap_poses(
    n_views: int, radius: float = 4.0, target: tuple[float, ...] = (0.0, 0.0, 0.3)
) -> list[np.ndarray]:
    """``n_views`` poses on a spherical cap (elevation 38..62 deg, azimuth within +-40 deg)."""
    target = np.asarray(target, dtype=np.float64)
    poses = []
    for i in range(n_views):
        frac = (i + 0.5) / n_views
        azimuth = math.radians(-40 + 80 * ((i * 0.618034) % 1.0))
        elevation = math.radians(38 + 24 * frac)
        offset = np.array(
            [
                math.cos(elevation) * math.cos(azimuth),
                math.cos(elevation) * math.sin(azimuth),
                math.sin(elevation),
            ]
        )
        poses.append(look_at(target + radius * offset, target))
    return poses


# --------------------------------------------------------------------------- rendering


def render_view(
    scene: AnalyticScene, K: np.ndarray, cam_from_world: np.ndarray, width: int, height: int
) -> dict[str, np.ndarray]:
    """Exact maps at our pixel centres ``(col + 0.5, row + 0.5)`` for intrinsics ``K``.

    Returns:
        ``depth`` ``[H, W]`` float64 camera z (0 = no hit), ``normals`` ``[H, W, 3]`` float64 unit
        camera-frame normals facing the camera (0 where invalid), ``rgb`` ``[H, W, 3]`` uint8 and
        ``points`` ``[H, W, 3]`` float64 world hit points.
    """
    R, t = cam_from_world[:, :3], cam_from_world[:, 3]
    u, v = pixel_centers(height, width)
    rays_cam = np.stack([u, v, np.ones_like(u)], axis=-1).reshape(-1, 3) @ np.linalg.inv(K).T  # z = 1
    dirs = rays_cam @ R  # world directions, camera z component 1 => t is the z-depth
    center = -R.T @ t
    depth, normals_world = scene.intersect(center[None], dirs)
    valid = np.isfinite(depth)
    depth = np.where(valid, depth, 0.0)
    points = center + dirs * depth[:, None]
    rgb = scene.texture(points, normals_world)
    rgb[~valid] = 0
    normals_cam = normals_world @ R.T
    normals_cam[~valid] = 0.0
    return {
        "depth": depth.reshape(height, width),
        "normals": normals_cam.reshape(height, width, 3),
        "rgb": rgb.reshape(height, width, 3),
        "points": points.reshape(height, width, 3),
    }


def _sample_surface(scene: AnalyticScene, n_points: int, rng: np.random.Generator) -> np.ndarray:
    """``[n_points, 3]`` points: 60% on the ground around the box, 40% on the box's top and sides."""
    n_ground = int(0.6 * n_points)
    ground = np.column_stack(
        [rng.uniform(-2.5, 2.5, (4 * n_ground, 2)), np.full(4 * n_ground, scene.ground_z)]
    )
    in_box = ((ground[:, :2] >= scene.box_min[:2]) & (ground[:, :2] <= scene.box_max[:2])).all(axis=1)
    ground = ground[~in_box][:n_ground]
    box = rng.uniform(scene.box_min, scene.box_max, (n_points - n_ground, 3))
    face = rng.integers(0, 5, len(box))  # 0..3: sides, 4: top
    for k, (axis, side) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1), (2, 1)]):
        box[face == k, axis] = (scene.box_min, scene.box_max)[side][axis]
    return np.concatenate([ground, box])


def build_sparse_model(
    scene: AnalyticScene, cameras: dict[int, Camera], images: dict[int, Image], n_points: int, seed: int
) -> SparseModel:
    """Sparse model whose tracks list exactly the images that see each point (in frame, unoccluded)."""
    rng = np.random.default_rng(seed)
    xyz = _sample_surface(scene, n_points, rng)
    seen = np.zeros((len(xyz), len(images)), dtype=bool)
    image_ids = sorted(images)
    for j, image_id in enumerate(image_ids):
        image = images[image_id]
        cam = cameras[image.camera_id]
        x_cam = xyz @ image.R.T + image.t
        uv = (x_cam @ cam.K.T)[:, :2] / x_cam[:, 2:3]
        inside = (x_cam[:, 2] > 0) & (uv >= 0).all(axis=1) & (uv < [cam.width, cam.height]).all(axis=1)
        depth, _ = scene.intersect(image.center[None], (x_cam / x_cam[:, 2:3]) @ image.R)
        seen[:, j] = inside & (np.abs(depth - x_cam[:, 2]) < 1e-6 * x_cam[:, 2])
    keep = seen.sum(axis=1) >= 2
    xyz, seen = xyz[keep], seen[keep]
    normals = scene.nearest_normal(xyz)
    offsets = np.concatenate([[0], np.cumsum(seen.sum(axis=1))]).astype(np.int64)
    track_ids = np.asarray(image_ids, dtype=np.int64)[np.nonzero(seen)[1]]
    points = Points3D(
        ids=np.arange(1, len(xyz) + 1, dtype=np.int64),
        xyz=xyz,
        rgb=scene.texture(xyz, normals),
        error=np.zeros(len(xyz)),
        track_offsets=offsets,
        track_image_ids=track_ids,
    )
    images = {
        iid: Image(im.image_id, im.name, im.camera_id, im.cam_from_world, points.ids[seen[:, j]])
        for j, (iid, im) in enumerate(sorted(images.items()))
    }
    return SparseModel(cameras, images, points, {im.name: iid for iid, im in images.items()})


# --------------------------------------------------------------------------- workspace


def make_analytic_workspace(
    root: Path,
    *,
    n_views: int = 5,
    width: int = 160,
    height: int = 120,
    focal: float = 150.0,
    n_points: int = 400,
    map_convention: Literal["colmap", "centre"] = "colmap",
    write_maps: bool = True,
    seed: int = 0,
) -> dict:
    """Write a complete dense workspace for the analytic scene into ``root`` and return the GT.

    Writes ``images/view_NNN.png``, ``sparse/`` (binary, PINHOLE, tracks), and unless
    ``write_maps`` is false ``stereo/{depth,normal}_maps/NAME.geometric.bin``; always
    ``stereo/patch-match.cfg`` (every other view as source) and ``stereo/fusion.cfg``.

    Returns:
        dict with ``root``, ``scene`` (:class:`AnalyticScene`), ``model`` (:class:`SparseModel`),
        ``names`` (image names) and per-name dicts ``depth`` ``[H, W]``, ``normals`` ``[H, W, 3]``,
        ``rgb`` ``[H, W, 3]`` (GT at our pixel centres for ``K``) and ``map_K`` (the ``[3, 3]``
        intrinsics the written maps were rendered with).
    """
    root = Path(root)
    scene = AnalyticScene()
    params = np.array([focal, focal, width / 2.0, height / 2.0])
    K = np.array([[focal, 0, width / 2.0], [0, focal, height / 2.0], [0, 0, 1.0]])
    cameras = {1: Camera(1, "PINHOLE", width, height, K, params)}
    images = {
        i + 1: Image(i + 1, f"view_{i:03d}.png", 1, pose, np.zeros(0, dtype=np.int64))
        for i, pose in enumerate(sphere_cap_poses(n_views))
    }
    model = build_sparse_model(scene, cameras, images, n_points, seed)
    write_sparse_model(model, root / "sparse")
    names = [im.name for im in model.images.values()]
    gt: dict = {"root": root, "scene": scene, "model": model, "names": names}
    for key in ("depth", "normals", "rgb", "map_K"):
        gt[key] = {}
    map_K = fusion_intrinsics(K, (width, height)) if map_convention == "colmap" else K
    for image in model.images.values():
        view = render_view(scene, K, image.cam_from_world, width, height)
        (root / "images").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / "images" / image.name), cv2.cvtColor(view["rgb"], cv2.COLOR_RGB2BGR))
        gt["depth"][image.name], gt["normals"][image.name], gt["rgb"][image.name] = (
            view["depth"],
            view["normals"],
            view["rgb"],
        )
        gt["map_K"][image.name] = map_K
        if write_maps:
            maps = render_view(scene, map_K, image.cam_from_world, width, height)
            write_depth_map(root / "stereo" / "depth_maps" / f"{image.name}.geometric.bin", maps["depth"])
            write_normal_map(root / "stereo" / "normal_maps" / f"{image.name}.geometric.bin", maps["normals"])
    write_patch_match_cfg(
        root / "stereo" / "patch-match.cfg", {n: [m for m in names if m != n] for n in names}
    )
    write_fusion_cfg(root / "stereo" / "fusion.cfg", names)
    return gt


# --------------------------------------------------------------------------- PLY


_PLY_TYPES = {
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
    "uchar": "u1",
    "uint8": "u1",
    "char": "i1",
    "int8": "i1",
    "ushort": "u2",
    "uint16": "u2",
    "short": "i2",
    "int16": "i2",
    "uint": "u4",
    "uint32": "u4",
    "int": "i4",
    "int32": "i4",
}


def read_ply_vertices(path: Path) -> np.ndarray:
    """Vertices of a binary little-endian PLY (what COLMAP's fusion writes) as a structured array."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: only binary little-endian PLY files are supported")
    count, fields, in_vertex = 0, [], False
    for line in header:
        parts = line.split()
        if parts[:1] == ["element"]:
            in_vertex = parts[1] == "vertex"
            count = int(parts[2]) if in_vertex else count
        elif parts[:1] == ["property"] and in_vertex:
            fields.append((parts[2], "<" + _PLY_TYPES[parts[1]]))
    return np.frombuffer(data, dtype=np.dtype(fields), count=count, offset=end)


def stereo_config(**flags):
    """A :class:`~colmap_pvs.stereo.StereoConfig` from flag names (``num_views=3, geom_fill=False``),
    as the command line and ``--config_file`` give them."""
    from colmap_pvs.config import config_from_dict
    from colmap_pvs.stereo import StereoConfig

    return config_from_dict(StereoConfig, flags)


def reconstruct_config(**flags):
    """A :class:`~colmap_pvs.reconstruct.ReconstructConfig` from flag names (stereo's included)."""
    from colmap_pvs.config import config_from_dict
    from colmap_pvs.reconstruct import ReconstructConfig

    return config_from_dict(ReconstructConfig, flags)


#: Image names COLMAP allows: sub-folders, spaces and non-ASCII letters.
ODD_NAMES = ("cam0/view 1.png", "cam0/vüe 2.png", "cam 1/ñame 3.png", "cam 1/日本 4.png")


def make_odd_names_workspace(root: Path) -> Path:
    """A synthetic workspace (4 views of 96x72) whose images are named :data:`ODD_NAMES`."""
    import dataclasses
    import shutil

    from colmap_pvs.io.sparse import read_sparse_model, write_sparse_model
    from colmap_pvs.synthetic.workspace import SyntheticWorkspaceConfig, make_synthetic_workspace

    make_synthetic_workspace(root, SyntheticWorkspaceConfig(seed=3, width=96, height=72, num_views=4))
    model = read_sparse_model(root / "sparse")
    images = {}
    for im, new in zip(sorted(model.images.values(), key=lambda im: im.name), ODD_NAMES, strict=True):
        (root / "images" / new).parent.mkdir(parents=True, exist_ok=True)
        shutil.move(root / "images" / im.name, root / "images" / new)
        images[im.image_id] = dataclasses.replace(im, name=new)
    by_name = {im.name: i for i, im in images.items()}
    write_sparse_model(dataclasses.replace(model, images=images, image_ids_by_name=by_name), root / "sparse")
    shutil.rmtree(root / "stereo", ignore_errors=True)
    return root
