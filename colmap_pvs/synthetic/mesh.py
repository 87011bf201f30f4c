"""Textured triangle-mesh primitives for synthetic scenes (plain numpy, open3d on export).

Every primitive gets its own vertices (nothing is shared between primitives), so per-vertex
texture coordinates are enough. Texture coordinates are first expressed in scene units
along the surface, then mapped to texture tiles by a per-primitive random rotation,
offset and *density* (tiles per scene unit). The density is kept per triangle because the
renderer needs it to choose the mip level.

World axes: +z is up. Lengths are in scene units (metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ShapeError


def rotation_z(angle: float) -> np.ndarray:
    """``[3, 3]`` rotation by ``angle`` radians about +z."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Material:
    """How a primitive is textured.

    Attributes:
        texture: index into the scene's texture stack.
        density: texture tiles per scene unit along the surface.
        angle: rotation (radians) of the texture on the surface.
        offset: ``[2]`` offset in tiles.
    """

    texture: int
    density: float
    angle: float = 0.0
    offset: tuple[float, float] = (0.0, 0.0)


class MeshBuilder:
    """Accumulates textured primitives; :meth:`arrays` returns the merged mesh."""

    def __init__(self) -> None:
        self._vertices: list[np.ndarray] = []
        self._triangles: list[np.ndarray] = []
        self._uvs: list[np.ndarray] = []
        self._tex: list[np.ndarray] = []
        self._density: list[np.ndarray] = []
        self._part: list[np.ndarray] = []
        self._count = 0
        self.aabbs: list[np.ndarray] = []
        """``[2, 3]`` bounds of every primitive added, in order."""

    # ------------------------------------------------------------------ core

    def add_triangles(
        self,
        vertices: np.ndarray,
        triangles: np.ndarray,
        surface_uv: np.ndarray,
        material: Material,
        triangle_texture: np.ndarray | None = None,
    ) -> None:
        """Add a triangle soup.

        Args:
            vertices: ``[V, 3]`` positions.
            triangles: ``[F, 3]`` vertex indices into ``vertices``.
            surface_uv: ``[V, 2]`` coordinates along the surface in scene units.
            material: texture, density and placement of the texture.
            triangle_texture: optional ``[F]`` texture ids overriding ``material.texture``.
        """
        vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
        triangles = np.asarray(triangles, np.int64).reshape(-1, 3)
        surface_uv = np.asarray(surface_uv, np.float64).reshape(-1, 2)
        if surface_uv.shape[0] != vertices.shape[0]:
            raise ShapeError(f"surface_uv has {surface_uv.shape[0]} rows, expected {vertices.shape[0]}")
        if triangles.size and (triangles.min() < 0 or triangles.max() >= vertices.shape[0]):
            raise ShapeError(f"triangle indices out of range [0, {vertices.shape[0]})")
        n_tri = triangles.shape[0]
        c, s = np.cos(material.angle), np.sin(material.angle)
        rot = np.array([[c, -s], [s, c]])
        uv = surface_uv @ rot.T * material.density + np.asarray(material.offset)
        if triangle_texture is None:
            tex = np.full(n_tri, material.texture, np.int32)
        else:
            tex = np.asarray(triangle_texture, np.int32).reshape(-1)
            if tex.shape[0] != n_tri:
                raise ShapeError(f"triangle_texture has {tex.shape[0]} entries, expected F={n_tri}")
        self._vertices.append(vertices)
        self._triangles.append(triangles + self._count)
        self._uvs.append(uv.astype(np.float32))
        self._tex.append(tex)
        self._density.append(np.full(n_tri, material.density, np.float32))
        self._part.append(np.full(n_tri, len(self._part), np.int32))
        self._count += vertices.shape[0]
        self.aabbs.append(np.stack([vertices.min(0), vertices.max(0)]))

    def add_grid(
        self,
        points: np.ndarray,
        surface_uv: np.ndarray,
        material: Material,
        cell_texture: np.ndarray | None = None,
    ) -> None:
        """Add a ``[nu, nv]`` grid of points (``[nu, nv, 3]``) with ``[nu, nv, 2]`` surface coordinates.

        Each grid cell becomes two triangles; ``cell_texture`` (``[nu - 1, nv - 1]``) optionally
        overrides the texture id per cell.
        """
        nu, nv = points.shape[:2]
        idx = np.arange(nu * nv).reshape(nu, nv)
        a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
        c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        tris = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)])
        tex = None if cell_texture is None else np.concatenate([np.ravel(cell_texture)] * 2)
        self.add_triangles(points.reshape(-1, 3), tris, surface_uv.reshape(-1, 2), material, tex)

    # ------------------------------------------------------------------ primitives

    def add_quad(
        self, origin: np.ndarray, axis_u: np.ndarray, axis_v: np.ndarray, material: Material
    ) -> None:
        """A parallelogram ``origin + s * axis_u + t * axis_v``, ``s, t`` in [0, 1]."""
        self.add_heightfield(origin, axis_u, axis_v, np.zeros((2, 2)), material)

    def add_heightfield(
        self,
        origin: np.ndarray,
        axis_u: np.ndarray,
        axis_v: np.ndarray,
        heights: np.ndarray,
        material: Material,
        cell_texture: np.ndarray | None = None,
    ) -> None:
        """A bumpy rectangle: ``origin + s * axis_u + t * axis_v + h(s, t) * n``.

        Args:
            heights: ``[nu, nv]`` displacements along ``n = normalize(axis_u x axis_v)`` at a
                regular grid of ``(s, t)`` in ``[0, 1]^2``.
            cell_texture: optional ``[nu - 1, nv - 1]`` texture ids per grid cell.
        """
        origin, axis_u, axis_v = (np.asarray(x, np.float64) for x in (origin, axis_u, axis_v))
        heights = np.asarray(heights, np.float64)
        nu, nv = heights.shape
        normal = np.cross(axis_u, axis_v)
        normal /= np.linalg.norm(normal)
        s = np.linspace(0, 1, nu)[:, None, None]
        t = np.linspace(0, 1, nv)[None, :, None]
        pts = origin + s * axis_u + t * axis_v + heights[..., None] * normal
        lu, lv = np.linalg.norm(axis_u), np.linalg.norm(axis_v)
        uv = np.concatenate([np.broadcast_to(s * lu, (nu, nv, 1)), np.broadcast_to(t * lv, (nu, nv, 1))], -1)
        self.add_grid(pts, uv, material, cell_texture)

    def add_box(
        self,
        center: np.ndarray,
        size: np.ndarray,
        yaw: float,
        materials: Material | list[Material],
        skip_bottom: bool = False,
    ) -> None:
        """An oriented box: ``size`` ``[3]`` edge lengths, rotated by ``yaw`` about +z around ``center``."""
        center = np.asarray(center, np.float64)
        hx, hy, hz = np.asarray(size, np.float64) / 2
        R = rotation_z(yaw)
        ex, ey, ez = R[:, 0] * hx, R[:, 1] * hy, R[:, 2] * hz
        faces = [
            (center + ex - ey - ez, 2 * ey, 2 * ez),  # +x
            (center - ex + ey - ez, -2 * ey, 2 * ez),  # -x
            (center + ey + ex - ez, -2 * ex, 2 * ez),  # +y
            (center - ey - ex - ez, 2 * ex, 2 * ez),  # -y
            (center + ez - ex - ey, 2 * ex, 2 * ey),  # +z
            (center - ez - ex + ey, 2 * ex, -2 * ey),  # -z
        ]
        if isinstance(materials, Material):
            materials = [materials] * 6
        for k, (o, u, v) in enumerate(faces):
            if skip_bottom and k == 5:
                continue
            self.add_quad(o, u, v, materials[k])

    def add_sphere(
        self,
        center: np.ndarray,
        radius: float,
        material: Material,
        segments: int = 32,
        bumps: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> None:
        """A UV sphere (``segments`` longitudes, ``segments // 2`` latitudes), optionally bumpy.

        Args:
            bumps: ``(directions [B, 3] unit, amplitudes [B], widths [B])``: the radius becomes
                ``radius * (1 + sum_b a_b exp(-|d - d_b|^2 / w_b^2))`` in direction ``d``.
        """
        n_lat = max(segments // 2, 3)
        lat = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 1)[:, None]
        lon = np.linspace(0, 2 * np.pi, segments + 1)[None, :]
        d = np.stack(
            np.broadcast_arrays(np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat) + 0 * lon),
            -1,
        )
        r = np.full(d.shape[:2], float(radius))
        if bumps is not None:
            dirs, amps, widths = bumps
            dist2 = ((d[:, :, None, :] - dirs[None, None]) ** 2).sum(-1)
            r = r * (1 + (amps * np.exp(-dist2 / widths**2)).sum(-1))
        pts = np.asarray(center, np.float64) + r[..., None] * d
        uv = np.concatenate(np.broadcast_arrays(lon[..., None] * radius, lat[..., None] * radius), -1)
        self.add_grid(pts, uv, material)

    def add_cylinder(
        self,
        base: np.ndarray,
        radius_bottom: float,
        radius_top: float,
        height: float,
        material: Material,
        cap_material: Material | None = None,
        segments: int = 24,
        caps: bool = True,
    ) -> None:
        """A vertical cylinder / cone frustum standing on ``base`` (centre of its bottom disc)."""
        base = np.asarray(base, np.float64)
        ang = np.linspace(0, 2 * np.pi, segments + 1)
        z = np.array([0.0, height])
        radii = np.array([radius_bottom, radius_top])
        circ = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], -1)
        pts = base + radii[:, None, None] * circ[None] + z[:, None, None] * np.array([0, 0, 1.0])
        mean_r = 0.5 * (radius_bottom + radius_top)
        slant = float(np.hypot(height, radius_bottom - radius_top))
        uv = np.stack(np.broadcast_arrays(ang[None, :] * mean_r, np.array([0.0, slant])[:, None]), -1)
        self.add_grid(pts, uv, material)
        if not caps:
            return
        cap_material = cap_material or material
        for zc, rc in ((0.0, radius_bottom), (height, radius_top)):
            if rc <= 0:
                continue
            ring = base + rc * circ[:-1] + np.array([0, 0, zc])
            verts = np.concatenate([ring, (base + np.array([0, 0, zc]))[None]])
            k = np.arange(segments)
            tris = np.stack([np.full(segments, segments), k, (k + 1) % segments], -1)
            self.add_triangles(verts, tris, (verts - base)[:, :2], cap_material)

    # ------------------------------------------------------------------ output

    def arrays(self) -> dict[str, np.ndarray]:
        """The merged mesh.

        Keys: ``vertices [V, 3]`` float64, ``triangles [F, 3]`` int32, ``uvs [V, 2]`` float32 (tiles),
        ``triangle_texture [F]`` int32, ``triangle_density [F]`` float32 and ``triangle_part [F]`` int32
        (one id per :meth:`add_triangles` call: a box face, a sphere, a height field...).
        """
        if not self._vertices:
            raise ShapeError("the mesh is empty: no primitive was added")
        return {
            "vertices": np.concatenate(self._vertices),
            "triangles": np.concatenate(self._triangles).astype(np.int32),
            "uvs": np.concatenate(self._uvs),
            "triangle_texture": np.concatenate(self._tex),
            "triangle_density": np.concatenate(self._density),
            "triangle_part": np.concatenate(self._part),
        }
