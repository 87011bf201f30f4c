"""The procedural scene families: ``object``, ``room``, ``facade`` and ``plant`` (see :mod:`.scenes`)."""

from __future__ import annotations

import numpy as np

from .builder import _Builder, _directional_light, _place_discs
from .mesh import Material, rotation_z
from .scene_types import Light, Scene, ViewSpace


def _add_object(b: _Builder, kind: str, xy: np.ndarray, r: float, z0: float) -> float:
    """One tabletop object with footprint radius ``r`` standing at height ``z0``; returns its height."""
    rng, seg = b.rng, b.config.segments
    m = b.material(scale=0.5)
    if kind == "box":
        h = rng.uniform(0.5, 2.5) * r
        w, d = rng.uniform(0.9, 1.4, 2) * r
        b.mesh.add_box([xy[0], xy[1], z0 + h / 2], [w, d, h], rng.uniform(0, np.pi), m)
        if rng.random() < 0.3:  # a smaller box on top
            s = rng.uniform(0.3, 0.6) * r
            b.mesh.add_box(
                [xy[0], xy[1], z0 + h + s / 2], [s, s, s], rng.uniform(0, np.pi), b.material(scale=0.5)
            )
            h += s
    elif kind == "sphere":
        h = 2 * r
        b.mesh.add_sphere([xy[0], xy[1], z0 + r], r, m, seg)
    elif kind == "blob":
        h = 1.8 * r
        b.mesh.add_sphere([xy[0], xy[1], z0 + 0.9 * r], r, m, seg, bumps=b.bumps(0.25))
    elif kind == "cylinder":
        h = rng.uniform(0.6, 3.0) * r
        b.mesh.add_cylinder([xy[0], xy[1], z0], r, r, h, m, b.material(scale=0.5), seg)
    else:  # cone / frustum
        h = rng.uniform(1.0, 3.0) * r
        b.mesh.add_cylinder([xy[0], xy[1], z0], r, r * rng.uniform(0.0, 0.7), h, m, None, seg)
    return float(h)


def _object_scene(b: _Builder, seed: int) -> Scene:
    rng, cfg = b.rng, b.config
    tw, td = rng.uniform(1.2, 2.0), rng.uniform(0.9, 1.4)
    leg_h = rng.uniform(0.65, 0.8)
    floor_z = -leg_h - 0.04
    b.mesh.add_box([0, 0, -0.02], [tw, td, 0.04], 0.0, b.material(scale=1.5))
    b.solid([-tw / 2, -td / 2, floor_z], [tw / 2, td / 2, 0.0])
    if cfg.thin_structures:
        leg_m = b.material(kind="low")
        for sx in (-1, 1):
            for sy in (-1, 1):
                b.mesh.add_cylinder(
                    [sx * (tw / 2 - 0.06), sy * (td / 2 - 0.06), floor_z], 0.02, 0.02, leg_h, leg_m, None, 12
                )
    fs = 10.0
    b.mesh.add_heightfield(
        [-fs / 2, -fs / 2, floor_z],
        [fs, 0, 0],
        [0, fs, 0],
        b.smooth_heights(24, 24, 0.01),
        b.material(scale=3.0),
    )
    for _ in range(int(rng.integers(0, 3))):  # backdrop walls
        az = rng.uniform(0, 2 * np.pi)
        dist = rng.uniform(2.0, 3.5)
        n = np.array([np.cos(az), np.sin(az), 0.0])
        u = np.array([-n[1], n[0], 0.0]) * 8.0
        o = n * dist - u / 2 + np.array([0, 0, floor_z])
        b.mesh.add_heightfield(o, u, [0, 0, 3.0], b.smooth_heights(16, 8, 0.02), b.material(scale=3.0))

    n_obj = int(rng.integers(cfg.min_objects, cfg.max_objects + 1))
    radii = rng.uniform(0.04, 0.13, max(n_obj, 1))
    spread = rng.uniform(0.2, 0.4)
    placed = _place_discs(rng, radii[:n_obj], np.array([[-spread, -spread], [spread, spread]]))
    kinds = ("box", "sphere", "cylinder", "cone", "blob")
    tops, centres = [], []
    for i, xy in placed:
        h = _add_object(b, kinds[int(rng.integers(len(kinds)))], xy, float(radii[i]), 0.0)
        b.solid(np.r_[xy - radii[i], 0.0], np.r_[xy + radii[i], h])
        tops.append(h)
        centres.append(np.r_[xy, h / 2])
        if h > 0.1:
            b.occluders.append(np.r_[xy, h * 0.6])
    if centres:
        c = np.mean(centres, axis=0)
        reach = np.linalg.norm(np.array(centres)[:, :2] - c[:2], axis=1) + radii[[i for i, _ in placed]]
        extent = float(reach.max())
        c[2] = max(tops) * 0.35
    else:
        c, extent = np.zeros(3), 0.25
    roi_r = float(np.clip(extent, 0.15, 0.5))
    d0 = b.nominal_distance
    vs = ViewSpace(
        az_center_deg=0.0,
        az_range_deg=180.0,
        el_range_deg=(12.0, 70.0),
        dist_range=(0.6 * d0, 1.4 * d0),
        eye_box=np.array([[-6.0, -6.0, floor_z + 0.1], [6.0, 6.0, 3.0]]),
        margin=0.05,
    )
    return b.finish("object", seed, _directional_light(rng), c, roi_r, vs)


def _room_scene(b: _Builder, seed: int) -> Scene:
    rng, cfg = b.rng, b.config
    W, L, H = rng.uniform(3.5, 6.5), rng.uniform(3.5, 6.5), rng.uniform(2.4, 3.2)
    x0, y0 = -W / 2, -L / 2
    wall_kind = "low" if rng.random() < 0.5 else None
    wall_tex = b.texture(wall_kind)
    walls = [
        ([x0, y0, 0], [W, 0, 0], [0, 0, H]),
        ([x0 + W, y0, 0], [0, L, 0], [0, 0, H]),
        ([x0 + W, y0 + L, 0], [-W, 0, 0], [0, 0, H]),
        ([x0, y0 + L, 0], [0, -L, 0], [0, 0, H]),
    ]
    for o, u, v in walls:
        tex = wall_tex if rng.random() < 0.7 else None
        nu = max(2, int(np.linalg.norm(u) * 4))
        b.mesh.add_heightfield(
            o, u, v, b.smooth_heights(nu, 12, 0.005 * rng.random()), b.material(texture=tex, scale=2.0)
        )
        if rng.random() < 0.6:  # a poster / panel on the wall
            un, vn = np.asarray(u, float) / np.linalg.norm(u), np.asarray(v, float) / np.linalg.norm(v)
            n = np.cross(un, vn)
            pw, ph = rng.uniform(0.5, 1.5), rng.uniform(0.4, 1.0)
            po = (
                np.asarray(o, float)
                + un * rng.uniform(0.2, np.linalg.norm(u) - pw - 0.2)
                + vn * rng.uniform(1.0, H - ph - 0.3)
            )
            b.mesh.add_quad(po + n * 0.01, un * pw, vn * ph, b.material(kind="photo", scale=0.5))
    b.mesh.add_heightfield([x0, y0, 0], [W, 0, 0], [0, L, 0], np.zeros((2, 2)), b.material(scale=1.5))
    b.mesh.add_heightfield(
        [x0, y0, H], [0, L, 0], [W, 0, 0], np.zeros((2, 2)), b.material(kind="low", scale=2.0)
    )

    n_items = int(rng.integers(cfg.min_objects, cfg.max_objects + 1)) + 1
    kinds = ("table", "chair", "shelf", "cabinet", "sofa", "lamp", "ball", "boxes")
    radii = rng.uniform(0.3, 0.8, n_items)
    placed = _place_discs(rng, radii, np.array([[x0 + 0.2, y0 + 0.2], [x0 + W - 0.2, y0 + L - 0.2]]))
    centres = []
    thin = cfg.thin_structures
    for i, xy in placed:
        kind = kinds[int(rng.integers(len(kinds)))]
        r = float(radii[i])
        yaw = rng.uniform(0, 2 * np.pi)
        n_before = len(b.mesh.aabbs)
        if kind in ("table", "chair"):
            top_h = rng.uniform(0.7, 0.78) if kind == "table" else rng.uniform(0.42, 0.5)
            sx, sy = (r * 1.4, r * rng.uniform(0.8, 1.3)) if kind == "table" else (0.45, 0.45)
            b.mesh.add_box([xy[0], xy[1], top_h], [sx, sy, 0.04], yaw, b.material(scale=0.7))
            leg_m = b.material(kind="low")
            R = rotation_z(yaw)
            for ox in (-1, 1):
                for oy in (-1, 1):
                    p = np.r_[xy, 0.0] + R @ np.array([ox * (sx / 2 - 0.04), oy * (sy / 2 - 0.04), 0.0])
                    if thin:
                        b.mesh.add_cylinder(p, 0.02, 0.02, top_h - 0.02, leg_m, None, 10)
                    else:
                        b.mesh.add_box(p + [0, 0, (top_h - 0.02) / 2], [0.06, 0.06, top_h - 0.02], yaw, leg_m)
            if kind == "chair":
                back = np.r_[xy, top_h + 0.25] + R @ np.array([0, -sy / 2 + 0.02, 0])
                b.mesh.add_box(back, [sx, 0.04, 0.5], yaw, b.material(scale=0.7))
                b.occluders.append(np.r_[xy, top_h])
            else:
                for _ in range(int(rng.integers(0, 3))):  # things on the table
                    p = (
                        np.r_[xy, 0.0]
                        + R @ np.r_[rng.uniform(-sx / 3, sx / 3), rng.uniform(-sy / 3, sy / 3), 0]
                    )
                    _add_object(
                        b,
                        ("box", "sphere", "cylinder")[int(rng.integers(3))],
                        p[:2],
                        rng.uniform(0.05, 0.12),
                        top_h + 0.02,
                    )
        elif kind in ("shelf", "cabinet", "boxes"):
            h = rng.uniform(0.6, 2.0) if kind != "boxes" else rng.uniform(0.3, 0.6)
            b.mesh.add_box([xy[0], xy[1], h / 2], [r * 1.3, r * 0.8, h], yaw, b.material(scale=1.0))
            if kind == "boxes":
                s = rng.uniform(0.2, 0.4)
                b.mesh.add_box(
                    [xy[0], xy[1], h + s / 2], [s, s, s], yaw + rng.uniform(-0.5, 0.5), b.material()
                )
            b.occluders.append(np.r_[xy, h * 0.6])
        elif kind == "sofa":
            m = b.material(scale=0.8)
            R = rotation_z(yaw)
            b.mesh.add_box([xy[0], xy[1], 0.22], [r * 1.8, 0.8, 0.44], yaw, m)
            b.mesh.add_box(np.r_[xy, 0.6] + R @ [0, -0.32, 0], [r * 1.8, 0.16, 0.5], yaw, m)
        elif kind == "lamp":
            h = rng.uniform(1.3, 1.9)
            pole_r = 0.015 if thin else 0.05
            b.mesh.add_cylinder([xy[0], xy[1], 0], 0.18, 0.18, 0.03, b.material(kind="low"), None, 16)
            b.mesh.add_cylinder([xy[0], xy[1], 0.03], pole_r, pole_r, h, b.material(kind="low"), None, 10)
            b.mesh.add_cylinder([xy[0], xy[1], h - 0.1], 0.2, 0.1, 0.25, b.material(), None, 20)
            b.occluders.append(np.r_[xy, h * 0.5])
        else:  # ball / blob
            rr = rng.uniform(0.1, 0.3)
            b.mesh.add_sphere(
                [xy[0], xy[1], rr],
                rr,
                b.material(scale=0.5),
                cfg.segments,
                bumps=b.bumps(0.15) if rng.random() < 0.5 else None,
            )
        lo, hi = b.last_aabb(len(b.mesh.aabbs) - n_before)
        b.solid(lo, hi)
        centres.append((lo + hi) / 2)
    if centres:
        c = np.array(centres[int(rng.integers(len(centres)))])
        c[2] = np.clip(c[2], 0.4, 1.2)
    else:
        c = np.array([rng.uniform(x0 + 1, x0 + W - 1), y0 + L - 0.3, 1.2])
    roi_r = float(rng.uniform(0.7, 1.3))
    vs = ViewSpace(
        az_center_deg=0.0,
        az_range_deg=180.0,
        el_range_deg=(-10.0, 45.0),
        dist_range=(0.8 * b.nominal_distance, 1.6 * b.nominal_distance),
        eye_box=np.array([[x0 + 0.25, y0 + 0.25, 0.4], [x0 + W - 0.25, y0 + L - 0.25, H - 0.3]]),
        margin=0.15,
    )
    light_pos = (
        float(rng.uniform(x0 + 0.5, x0 + W - 0.5)),
        float(rng.uniform(y0 + 0.5, y0 + L - 0.5)),
        float(H - 0.3),
    )
    light = Light(
        "point",
        light_pos,
        float(rng.uniform(0.6, 1.0)),
        float(rng.uniform(0.3, 0.5)),
        falloff=float(rng.uniform(2.5, 5.0)),
    )
    return b.finish("room", seed, light, c, roi_r, vs)


def _facade_scene(b: _Builder, seed: int) -> Scene:
    rng, cfg = b.rng, b.config
    Wf, Hf = rng.uniform(8, 16), rng.uniform(6, 12)
    res = 0.1
    nu, nv = int(Wf / res) + 1, int(Hf / res) + 1
    xs = np.linspace(-Wf / 2, Wf / 2, nu)[:, None]
    zs = np.linspace(0, Hf, nv)[None, :]
    relief = b.smooth_heights(nu, nv, 0.01, cells=12)  # displacement along -y (towards the street)
    wall_m = b.material(scale=1.5)
    glass_tex = b.texture()
    cell_tex = np.full((nu - 1, nv - 1), wall_m.texture, np.int32)
    floors = max(2, int(Hf / rng.uniform(2.8, 3.5)))
    cols = max(2, int(Wf / rng.uniform(1.8, 3.0)))
    fh, cw = Hf / floors, Wf / cols
    ww, wh = cw * rng.uniform(0.35, 0.6), fh * rng.uniform(0.4, 0.6)
    depth = rng.uniform(0.1, 0.35) * cfg.bumpiness
    cx = (xs[:-1] + xs[1:]) / 2
    cz = (zs[:, :-1] + zs[:, 1:]) / 2
    for f in range(floors):
        for k in range(cols):
            if f == 0 and rng.random() < 0.3:
                continue
            wx0 = -Wf / 2 + k * cw + (cw - ww) / 2
            wz0 = f * fh + (fh - wh) * 0.6
            inside = (xs >= wx0) & (xs <= wx0 + ww) & (zs >= wz0) & (zs <= wz0 + wh)
            relief[inside] = -depth
            cin = (cx >= wx0) & (cx <= wx0 + ww) & (cz >= wz0) & (cz <= wz0 + wh)
            cell_tex[cin] = glass_tex
        if f > 0 and rng.random() < 0.6:  # a ledge band
            band = (zs >= f * fh - 0.15) & (zs <= f * fh + 0.05)
            relief[np.broadcast_to(band, relief.shape)] = 0.08 * cfg.bumpiness
    # n = normalize(u x v) with u = +x, v = +z is -y: heights > 0 protrude towards the street (y < 0).
    b.mesh.add_heightfield([-Wf / 2, 0, 0], [Wf, 0, 0], [0, 0, Hf], relief, wall_m, cell_tex)
    b.solid([-Wf / 2, 0.0, 0.0], [Wf / 2, 5.0, Hf])
    for side in (-1, 1):  # neighbouring facades
        if rng.random() < 0.7:
            w2, h2, dy = rng.uniform(5, 10), rng.uniform(5, 14), rng.uniform(-1.5, 3.0)
            xstart = side * Wf / 2 if side > 0 else -Wf / 2 - w2
            b.mesh.add_heightfield(
                [xstart, dy, 0],
                [w2, 0, 0],
                [0, 0, h2],
                b.smooth_heights(int(w2 * 4), int(h2 * 4), 0.03),
                b.material(scale=1.5),
            )
            if abs(dy) > 0.05:  # the side wall that joins the two facades
                xj = side * Wf / 2
                b.mesh.add_quad(
                    [xj, min(0.0, dy), 0], [0, abs(dy), 0], [0, 0, min(h2, Hf)], b.material(scale=1.5)
                )
            b.solid([xstart, dy, 0.0], [xstart + w2, dy + 5.0, h2])
    # protruding boxes: balconies and pilasters
    for f in range(1, floors):
        if rng.random() < 0.5:
            k = int(rng.integers(cols))
            bx = -Wf / 2 + (k + 0.5) * cw
            bw, bd = cw * rng.uniform(0.6, 0.9), rng.uniform(0.5, 1.0)
            b.mesh.add_box([bx, -bd / 2, f * fh], [bw, bd, 0.12], 0.0, b.material(scale=0.7))
            if cfg.thin_structures:
                rail_m = b.material(kind="low")
                for x in np.linspace(bx - bw / 2 + 0.05, bx + bw / 2 - 0.05, int(bw / 0.3) + 1):
                    b.mesh.add_cylinder([x, -bd + 0.05, f * fh + 0.06], 0.015, 0.015, 0.9, rail_m, None, 8)
                b.mesh.add_box([bx, -bd + 0.05, f * fh + 0.98], [bw, 0.05, 0.05], 0.0, rail_m)
            else:
                b.mesh.add_box([bx, -bd + 0.05, f * fh + 0.5], [bw, 0.05, 0.9], 0.0, b.material())
            b.solid([bx - bw / 2, -bd, f * fh - 0.1], [bx + bw / 2, 0.0, f * fh + 1.0])
    for x in np.linspace(-Wf / 2, Wf / 2, cols + 1)[1:-1]:
        if rng.random() < 0.3:
            pw, pd = rng.uniform(0.2, 0.5), rng.uniform(0.1, 0.3)
            b.mesh.add_box(
                [x, -pd / 2 + 0.01, Hf / 2], [pw, pd, Hf], 0.0, b.material(scale=1.0), skip_bottom=True
            )
    # street
    b.mesh.add_heightfield(
        [-30, -25, 0], [60, 0, 0], [0, 27, 0], b.smooth_heights(30, 20, 0.02), b.material(scale=3.0)
    )
    # street furniture (occluders)
    n_items = int(rng.integers(cfg.min_objects, cfg.max_objects + 1))
    for _ in range(n_items):
        x, y = rng.uniform(-Wf / 2, Wf / 2), rng.uniform(-5.0, -1.2)
        kind = ("pole", "bin", "tree", "car")[int(rng.integers(4))]
        n_before = len(b.mesh.aabbs)
        if kind == "pole":
            h = rng.uniform(2.5, 5.0)
            r = rng.uniform(0.04, 0.1) if cfg.thin_structures else 0.2
            b.mesh.add_cylinder([x, y, 0], r, r * 0.8, h, b.material(scale=0.3), None, 12)
            occ = np.array([x, y, h * 0.6])
        elif kind == "bin":
            h = rng.uniform(0.8, 1.2)
            b.mesh.add_cylinder([x, y, 0], 0.3, 0.35, h, b.material(scale=0.3), None, 20)
            occ = np.array([x, y, h / 2])
        elif kind == "tree":
            h = rng.uniform(2.0, 3.5)
            rc = rng.uniform(0.8, 1.5)
            b.mesh.add_cylinder([x, y, 0], 0.12, 0.1, h, b.material(scale=0.3), None, 12)
            b.mesh.add_sphere(
                [x, y, h + rc * 0.7], rc, b.material(scale=0.3), cfg.segments, bumps=b.bumps(0.3)
            )
            occ = np.array([x, y, h + rc * 0.5])
        else:
            yaw = rng.uniform(-0.2, 0.2)
            b.mesh.add_box([x, y, 0.45], [rng.uniform(3.5, 4.5), 1.8, 0.7], yaw, b.material(scale=0.5))
            b.mesh.add_box([x, y, 1.1], [2.0, 1.6, 0.6], yaw, b.material(kind="low"))
            occ = np.array([x, y, 0.9])
        lo, hi = b.last_aabb(len(b.mesh.aabbs) - n_before)
        b.solid(lo, hi)
        b.occluders.append(occ)
    roi_r = float(rng.uniform(2.0, 3.5))
    c = np.array([rng.uniform(-Wf / 3, Wf / 3), 0.0, rng.uniform(min(2.5, Hf / 2), min(Hf - 1.5, 6.0))])
    vs = ViewSpace(
        az_center_deg=-90.0,
        az_range_deg=60.0,
        el_range_deg=(-10.0, 35.0),
        dist_range=(0.6 * b.nominal_distance, 1.5 * b.nominal_distance),
        eye_box=np.array([[-30.0, -24.0, 1.0], [30.0, -0.6, 14.0]]),
        margin=0.2,
    )
    light = _directional_light(rng, az_deg=-90 + rng.uniform(-70, 70))
    return b.finish("facade", seed, light, c, roi_r, vs)


def _frond(b: _Builder, crown: np.ndarray, length: float, width: float, material: Material,
           leaflets: bool) -> np.ndarray:
    """One frond from ``crown``: a tapering strip along a drooping quadratic curve (kept above the
    floor, ``z = 0``), optionally with leaflets (short thin strips) on both sides of it. Returns the
    ``[3]`` middle of its spine."""
    rng = b.rng
    az = rng.uniform(0, 2 * np.pi)
    el = np.radians(rng.uniform(-15, 70))
    out = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    mid = crown + out * length * 0.55
    tip = crown + out * length + np.array([0.0, 0.0, -rng.uniform(0.1, 0.6) * length])
    t = np.linspace(0.0, 1.0, 12)[:, None]
    spine = (1 - t) ** 2 * crown + 2 * t * (1 - t) * mid + t**2 * tip  # [12, 3]
    spine[:, 2] = np.maximum(spine[:, 2], 0.01 * length)
    tangent = np.gradient(spine, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    roll = rng.uniform(-0.6, 0.6)
    side = np.cross(tangent, [0.0, 0.0, 1.0])
    side /= np.maximum(np.linalg.norm(side, axis=1, keepdims=True), 1e-9)
    up = np.cross(side, tangent)
    side = np.cos(roll) * side + np.sin(roll) * up
    half = width * (1.0 - 0.8 * t) / 2  # [12, 1]: tapers towards the tip
    grid = np.stack([spine - side * half, spine + side * half], axis=1)  # [12, 2, 3]
    uv = np.stack(np.meshgrid(np.linspace(0, length, 12), [0.0, width], indexing="ij"), axis=-1)
    b.mesh.add_grid(grid, uv, material)
    if not leaflets:
        return spine[6]
    n = int(rng.integers(6, 14))
    leaf_len = length * rng.uniform(0.12, 0.3)
    leaf_w = max(width * 0.35, 0.004)
    for k in np.linspace(2, 10, n).astype(int):
        for sign in (-1.0, 1.0):
            d = sign * side[k] + 0.6 * tangent[k] + rng.normal(0, 0.15, 3)
            d /= np.linalg.norm(d)
            w = np.cross(d, up[k])
            w = w / max(np.linalg.norm(w), 1e-9) * leaf_w
            o = spine[k] - w / 2
            b.mesh.add_quad(o, d * leaf_len * (1.0 - 0.5 * k / 11), w, material)
    return spine[6]


def _plant_scene(b: _Builder, seed: int) -> Scene:
    rng, cfg = b.rng, b.config
    s = b.nominal_distance / 2.0  # the plant's size scales with the nominal distance
    # floor, a wall behind (+y) and sometimes a side wall
    b.mesh.add_heightfield(
        [-8, -8, 0], [16, 0, 0], [0, 16, 0], b.smooth_heights(24, 24, 0.01), b.material(scale=2.0)
    )
    wall_y = rng.uniform(1.0, 4.0) * s
    b.mesh.add_heightfield(
        [-8, wall_y, 0], [16, 0, 0], [0, 0, 5.0], b.smooth_heights(24, 8, 0.01), b.material(scale=2.0)
    )
    if rng.random() < 0.25:
        x = rng.choice([-1.0, 1.0]) * rng.uniform(2.0, 3.5) * s
        b.mesh.add_heightfield([x, -8, 0], [0, 8 + wall_y, 0], [0, 0, 5.0], np.zeros((2, 2)),
                               b.material(scale=2.0))
    # a planter: a pot or a long box, and the trunk
    pot_h = rng.uniform(0.2, 0.5) * s
    if rng.random() < 0.5:
        r = rng.uniform(0.12, 0.25) * s
        b.mesh.add_cylinder([0, 0, 0], r * 0.8, r, pot_h, b.material(scale=0.5), b.material(scale=0.5),
                            cfg.segments)
    else:
        w, d = rng.uniform(0.6, 1.6) * s, rng.uniform(0.3, 0.6) * s
        b.mesh.add_box([0, 0, pot_h / 2], [w, d, pot_h], rng.uniform(-0.3, 0.3), b.material(scale=0.5))
    b.solid(*b.last_aabb())
    trunk = rng.uniform(0.0, 0.8) * s
    if trunk > 0.05 * s:
        r = rng.uniform(0.02, 0.06) * s
        b.mesh.add_cylinder([0, 0, pot_h], r, r * 0.7, trunk, b.material(scale=0.3), None, 12)
        b.solid(*b.last_aabb())
    crown = np.array([0.0, 0.0, pot_h + trunk])
    # fronds: one or two textures for the whole plant, as leaves of one plant look alike
    mats = [b.material(scale=0.3) for _ in range(int(rng.integers(1, 3)))]
    length = rng.uniform(0.4, 1.0) * s
    middles = []
    for _ in range(int(rng.integers(8, 25))):
        middles.append(_frond(b, crown + rng.normal(0, 0.02 * s, 3), length * rng.uniform(0.7, 1.2),
                              rng.uniform(0.025, 0.09) * s, mats[int(rng.integers(len(mats)))],
                              rng.random() < 0.5))
    # a few straight canes or stalks
    if cfg.thin_structures:
        for _ in range(int(rng.integers(0, 4))):
            xy = rng.normal(0, 0.4 * s, 2)
            r = rng.uniform(0.005, 0.02) * s
            b.mesh.add_cylinder([xy[0], xy[1], 0], r, r, rng.uniform(0.6, 1.8) * s, b.material(scale=0.3),
                                None, 8)
    # occluded views look at the plant from behind the fronds that reach towards the cameras (-y)
    b.occluders.extend(m for m in middles if m[1] < crown[1] - 0.25 * length)
    c = crown + np.array([0.0, 0.0, 0.1 * length])
    vs = ViewSpace(
        az_center_deg=-90.0,
        az_range_deg=70.0,
        el_range_deg=(-5.0, 45.0),
        dist_range=(0.45 * b.nominal_distance, 0.9 * b.nominal_distance),
        eye_box=np.array([[-7.0, -7.5, 0.2], [7.0, wall_y - 0.3, 4.5]]),
        margin=0.05,
    )
    return b.finish("plant", seed, _directional_light(rng), c, float(np.clip(length, 0.3, 1.2)), vs)
