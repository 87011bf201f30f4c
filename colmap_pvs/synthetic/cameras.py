"""Camera rigs for synthetic scenes: video-like, unstructured and "disturbing" views.

Every view is a pinhole camera (OpenCV axes, ``cam_from_world = [R | t]``). Non-disturbing
views look at the scene's region of interest (ROI) from the scene's :class:`~.scenes.ViewSpace`:

- ``"video"``: a smooth path with small steps (azimuth steps of a few degrees, slowly
  drifting elevation, distance and look-at point): small baselines.
- ``"unstructured"``: independent positions (wide baselines, large rotations, distance and
  zoom changes, some roll).
- ``"mixed"``: per scene, one of video, unstructured, or a video segment plus unstructured views.

"Disturbing" views (``disturbing_fraction`` of the views) make view selection matter:

- ``"occluded"``: the camera stands behind an occluder (an object, pole, tree...) and looks
  at the ROI through it;
- ``"low_overlap"``: the camera looks away so that the ROI is at or beyond the image border.

Views that may serve as training references are checked by rendering a small depth map:
enough valid depth (``min_coverage``), the ROI centre not hidden and nothing very close to
the camera.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from ..errors import ConfigError
from ..geometry import scale_intrinsics
from .render import Renderer, _pair
from .scenes import Scene

logger = logging.getLogger(__name__)

ROLES = ("video", "unstructured", "occluded", "low_overlap")
REFERENCE_ROLES = ("video", "unstructured")


@dataclass(frozen=True)
class CameraConfig:
    """How camera rigs are generated (image size is passed separately)."""

    trajectory: Literal["video", "unstructured", "mixed"] = field(
        default="mixed", metadata={"help": "capture style: video (small baselines), unstructured, or mixed"}
    )
    num_views: tuple[int, ...] = field(
        default=(10, 14), metadata={"help": "range (lo, hi) of views per scene"}
    )
    hfov_deg: tuple[float, ...] = field(
        default=(50.0, 75.0), metadata={"help": "horizontal field of view range"}
    )
    zoom_jitter: float = field(
        default=0.15, metadata={"help": "unstructured views: relative per-view focal length change (+-)"}
    )
    principal_jitter: float = field(
        default=0.02, metadata={"help": "principal point offset, fraction of the image size (+-)"}
    )
    max_roll_deg: float = field(default=10.0, metadata={"help": "maximum roll of unstructured views"})
    video_step_deg: tuple[float, ...] = field(
        default=(1.5, 4.0), metadata={"help": "range of the azimuth step between video frames (degrees)"}
    )
    target_jitter: float = field(
        default=0.35, metadata={"help": "look-at point jitter, as a fraction of the ROI radius"}
    )
    disturbing_fraction: float = field(
        default=0.25, metadata={"help": "fraction of views that are occluded or barely overlapping"}
    )
    min_coverage: float = field(
        default=0.6, metadata={"help": "minimum fraction of valid depth in a reference-candidate view"}
    )
    max_attempts: int = field(default=40, metadata={"help": "pose samples tried per view before relaxing"})
    check_width: int = field(default=40, metadata={"help": "width of the small depth render used for checks"})

    def __post_init__(self) -> None:
        nv = tuple(int(v) for v in self.num_views)
        object.__setattr__(self, "num_views", nv)
        if len(nv) != 2 or not 2 <= nv[0] <= nv[1]:
            raise ConfigError(f"num_views must be two integers 2 <= lo <= hi, got {self.num_views!r}")
        for name in ("hfov_deg", "video_step_deg"):
            object.__setattr__(self, name, _pair(name, getattr(self, name)))
        if not (1.0 <= self.hfov_deg[0] and self.hfov_deg[1] < 170.0):
            raise ConfigError(f"hfov_deg must lie in [1, 170), got {self.hfov_deg!r}")
        for name in (
            "disturbing_fraction",
            "min_coverage",
            "zoom_jitter",
            "principal_jitter",
            "target_jitter",
        ):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if self.max_attempts < 1 or self.check_width < 8:
            raise ConfigError(
                f"max_attempts must be >= 1 and check_width >= 8, got {self.max_attempts}, {self.check_width}"
            )


@dataclass(frozen=True, eq=False)
class CameraRig:
    """Cameras of one scene.

    Attributes:
        K: ``[V, 3, 3]`` float64 intrinsics.
        cam_from_world: ``[V, 3, 4]`` float64 poses.
        roles: ``V`` role names (see :data:`ROLES`).
        width, height: image size.
    """

    K: np.ndarray
    cam_from_world: np.ndarray
    roles: tuple[str, ...]
    width: int
    height: int

    def __len__(self) -> int:
        return int(self.K.shape[0])

    @property
    def centers(self) -> np.ndarray:
        """``[V, 3]`` camera centres in world coordinates."""
        R, t = self.cam_from_world[:, :, :3], self.cam_from_world[:, :, 3]
        return -np.einsum("vji,vj->vi", R, t)

    @property
    def reference_candidates(self) -> np.ndarray:
        """``[k]`` int64 indices of the views whose role may serve as a training reference."""
        return np.array([i for i, r in enumerate(self.roles) if r in REFERENCE_ROLES], np.int64)


def look_at(
    eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0), roll_deg: float = 0.0
) -> np.ndarray:
    """``[3, 4]`` ``cam_from_world`` of a camera at ``eye`` looking at ``target`` (OpenCV axes).

    The image's "up" (-y) is as close to ``up`` as possible, then rolled by ``roll_deg``.
    """
    eye = np.asarray(eye, np.float64)
    f = np.asarray(target, np.float64) - eye
    norm = np.linalg.norm(f)
    if norm == 0:
        raise ValueError(f"eye {eye.tolist()} and target {np.asarray(target).tolist()} coincide")
    f = f / norm
    up = np.asarray(up, np.float64)
    r = np.cross(f, up)
    if np.linalg.norm(r) < 1e-6:  # looking straight along up: pick any right vector
        r = np.cross(f, [1.0, 0.0, 0.0] if abs(f[0]) < 0.9 else [0.0, 1.0, 0.0])
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    R = np.stack([r, d, f])
    if roll_deg:
        a = np.radians(roll_deg)
        Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
        R = Rz @ R
    return np.concatenate([R, (-R @ eye)[:, None]], 1)


def intrinsics(
    width: int,
    height: int,
    hfov_deg: float,
    aspect: float = 1.0,
    principal_offset: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """``[3, 3]`` pinhole ``K`` for a horizontal field of view (pixel-centre convention: cx = W/2)."""
    fx = width / 2 / np.tan(np.radians(hfov_deg) / 2)
    return np.array(
        [
            [fx, 0.0, width / 2 + principal_offset[0] * width],
            [0.0, fx * aspect, height / 2 + principal_offset[1] * height],
            [0.0, 0.0, 1.0],
        ]
    )


def _direction(az_deg: float, el_deg: float) -> np.ndarray:
    az, el = np.radians(az_deg), np.radians(el_deg)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


class _Sampler:
    """Shared state while one rig is generated."""

    def __init__(
        self,
        scene: Scene,
        renderer: Renderer,
        config: CameraConfig,
        width: int,
        height: int,
        rng: np.random.Generator,
    ) -> None:
        self.scene, self.renderer, self.config, self.rng = scene, renderer, config, rng
        self.width, self.height = width, height
        self.vs = scene.view_space
        self.hfov = float(rng.uniform(*config.hfov_deg))
        self.aspect = float(rng.uniform(0.99, 1.01))
        self.cw = config.check_width
        self.ch = max(8, int(round(height * self.cw / width)))

    # -------------------------------------------------------------- checks

    def eye_ok(self, eye: np.ndarray) -> bool:
        vs = self.vs
        if np.any(eye < vs.eye_box[0]) or np.any(eye > vs.eye_box[1]):
            return False
        sol = self.scene.solids
        if sol.shape[0]:
            inside = np.all((eye >= sol[:, 0] - vs.margin) & (eye <= sol[:, 1] + vs.margin), axis=1)
            if inside.any():
                return False
        return True

    def roi_hidden_fraction(self, eye: np.ndarray) -> float:
        """Fraction of a few ROI sample points hidden from ``eye`` (0 = all visible)."""
        sc = self.scene
        pts = sc.roi_center + np.array(
            [[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 0.5]]
        ) * (0.3 * sc.roi_radius)
        d = pts - eye
        t, _, _ = self.renderer.cast(eye, d)
        return float(np.mean(t < 0.9))

    def coverage(self, K: np.ndarray, pose: np.ndarray) -> tuple[float, float]:
        """``(valid fraction, 5th percentile of depth / distance to ROI)`` from a small render."""
        Ks = scale_intrinsics(K, self.cw / self.width, self.ch / self.height)
        depth, _, _ = self.renderer.render_depth(Ks, pose, self.ch, self.cw)
        valid = depth > 0
        if not valid.any():
            return 0.0, 0.0
        eye = -pose[:, :3].T @ pose[:, 3]
        near = float(np.percentile(depth[valid], 5)) / max(np.linalg.norm(self.scene.roi_center - eye), 1e-9)
        return float(valid.mean()), near

    def good_reference(self, K: np.ndarray, pose: np.ndarray, eye: np.ndarray) -> bool:
        cov, near = self.coverage(K, pose)
        return cov >= self.config.min_coverage and near > 0.25 and self.roi_hidden_fraction(eye) <= 0.34

    # -------------------------------------------------------------- sampling

    def K(self, zoom: float = 1.0) -> np.ndarray:
        pj = self.config.principal_jitter
        off = (float(self.rng.uniform(-pj, pj)), float(self.rng.uniform(-pj, pj)))
        hfov = np.degrees(2 * np.arctan(np.tan(np.radians(self.hfov) / 2) / zoom))
        return intrinsics(self.width, self.height, hfov, self.aspect, off)

    def spherical(self) -> tuple[float, float, float]:
        vs = self.vs
        az = vs.az_center_deg + self.rng.uniform(-vs.az_range_deg, vs.az_range_deg)
        el = self.rng.uniform(*vs.el_range_deg)
        lo, hi = vs.dist_range
        dist = float(np.exp(self.rng.uniform(np.log(lo), np.log(hi))))
        return float(az), float(el), dist

    def eye_of(self, az: float, el: float, dist: float) -> np.ndarray:
        return self.scene.roi_center + dist * _direction(az, el)

    def target(self, scale: float = 1.0) -> np.ndarray:
        j = self.config.target_jitter * self.scene.roi_radius * scale
        return self.scene.roi_center + self.rng.uniform(-j, j, 3)

    def unstructured(self) -> tuple[np.ndarray, np.ndarray]:
        """One random reference-quality view (relaxing the checks after ``max_attempts``)."""
        c = self.config
        best = None
        for attempt in range(c.max_attempts * 2):
            az, el, dist = self.spherical()
            eye = self.eye_of(az, el, dist)
            if not self.eye_ok(eye):
                continue
            zoom = float(np.exp(self.rng.uniform(-c.zoom_jitter, c.zoom_jitter)))
            K = self.K(zoom)
            pose = look_at(eye, self.target(), roll_deg=self.rng.uniform(-c.max_roll_deg, c.max_roll_deg))
            if best is None:
                best = (K, pose)
            if attempt >= c.max_attempts or self.good_reference(K, pose, eye):
                return K, pose
        if best is None:
            raise RuntimeError(
                f"could not place a camera in the {self.scene.family} scene (seed {self.scene.seed}) "
                f"after {2 * c.max_attempts} attempts"
            )
        logger.debug("scene seed %d: using a view that fails the coverage checks", self.scene.seed)
        return best

    def video(self, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """``n`` views along a smooth path with small steps."""
        c = self.config
        start = None
        for _ in range(c.max_attempts):
            az, el, dist = self.spherical()
            eye = self.eye_of(az, el, dist)
            if not self.eye_ok(eye):
                continue
            K = self.K()
            if start is None:
                start = (az, el, dist, K)
            if self.good_reference(K, look_at(eye, self.scene.roi_center), eye):
                start = (az, el, dist, K)
                break
        if start is None:  # no valid start: fall back to independent views
            logger.debug("scene seed %d: no valid start for a video path", self.scene.seed)
            return [self.unstructured() for _ in range(n)]
        az, el, dist, K = start
        step = float(self.rng.uniform(*c.video_step_deg)) * (1 if self.rng.random() < 0.5 else -1)
        drift = self.rng.normal(0, 0.15 * self.scene.roi_radius * c.target_jitter, 3)
        target = self.scene.roi_center.copy()
        out: list[tuple[np.ndarray, np.ndarray]] = []
        d_el = float(self.rng.normal(0, abs(step) * 0.3))
        d_log_dist = float(self.rng.normal(0, 0.02))
        vs = self.vs
        for i in range(n):
            if i:
                moved = False
                for _ in range(c.max_attempts):
                    naz = az + step
                    nel = float(np.clip(el + d_el + self.rng.normal(0, 0.3), *vs.el_range_deg))
                    ndist = float(np.clip(dist * np.exp(d_log_dist), *vs.dist_range))
                    if self.eye_ok(self.eye_of(naz, nel, ndist)) and (
                        abs(((naz - vs.az_center_deg + 180) % 360) - 180) <= vs.az_range_deg
                    ):
                        az, el, dist = naz, nel, ndist
                        moved = True
                        break
                    step, d_el = -step, -d_el  # bounce off the edge of the view space
                if not moved:
                    logger.debug("scene seed %d: video path stuck; repeating a pose", self.scene.seed)
                target = target + drift + self.rng.normal(0, 0.02 * self.scene.roi_radius, 3)
                dev = target - self.scene.roi_center
                lim = self.scene.roi_radius * c.target_jitter
                if np.linalg.norm(dev) > lim:
                    drift = -drift
            eye = self.eye_of(az, el, dist)
            out.append((K, look_at(eye, target, roll_deg=float(self.rng.normal(0, 1.0)))))
        return out

    def occluded(self) -> tuple[np.ndarray, np.ndarray] | None:
        """A view of the ROI from behind an occluder, or ``None`` if no placement works."""
        occ = self.scene.occluders
        if occ.shape[0] == 0:
            return None
        c = self.config
        for _ in range(c.max_attempts):
            o = occ[int(self.rng.integers(occ.shape[0]))]
            d = o - self.scene.roi_center
            nd = np.linalg.norm(d)
            if nd < 1e-6:
                d = _direction(self.rng.uniform(0, 360), self.rng.uniform(5, 30))
                nd = 1.0
            lo, hi = self.vs.dist_range
            back = float(self.rng.uniform(0.25, 0.8)) * lo
            eye = o + d / nd * back + self.rng.normal(0, 0.05 * lo, 3)
            if not self.eye_ok(eye):
                continue
            K = self.K()
            pose = look_at(eye, self.target(0.5))
            if self.roi_hidden_fraction(eye) >= 0.3 and self.coverage(K, pose)[0] > 0.2:
                return K, pose
        return None

    def low_overlap(self) -> tuple[np.ndarray, np.ndarray] | None:
        """A view turned away from the ROI so that it is at or beyond the image border, or ``None``."""
        c = self.config
        for _ in range(c.max_attempts):
            az, el, dist = self.spherical()
            eye = self.eye_of(az, el, dist)
            if not self.eye_ok(eye):
                continue
            f = self.scene.roi_center - eye
            f /= np.linalg.norm(f)
            side = np.cross(f, [0.0, 0.0, 1.0])
            if np.linalg.norm(side) < 1e-6:
                side = np.array([1.0, 0.0, 0.0])
            side /= np.linalg.norm(side)
            if self.rng.random() < 0.3:
                side = np.cross(side, f)  # turn up or down instead
            turn = (
                np.radians(self.hfov)
                * float(self.rng.uniform(0.45, 0.8))
                * (1 if self.rng.random() < 0.5 else -1)
            )
            new_f = np.cos(turn) * f + np.sin(turn) * side
            K = self.K()
            pose = look_at(eye, eye + new_f, roll_deg=self.rng.uniform(-c.max_roll_deg, c.max_roll_deg))
            if self.coverage(K, pose)[0] > 0.2:
                return K, pose
        return None


def generate_cameras(
    scene: Scene, renderer: Renderer, config: CameraConfig, width: int, height: int, rng: np.random.Generator
) -> CameraRig:
    """A rig of ``config.num_views`` cameras for ``scene`` (deterministic given ``rng``'s state)."""
    if width < 8 or height < 8:
        raise ConfigError(f"image size must be at least 8x8, got {width}x{height}")
    s = _Sampler(scene, renderer, config, width, height, rng)
    n = int(rng.integers(config.num_views[0], config.num_views[1] + 1))
    n_dist = int(round(n * config.disturbing_fraction))
    n_main = max(n - n_dist, 2)
    n_dist = n - n_main
    style = config.trajectory
    if style == "mixed":
        style = ("video", "unstructured", "both")[int(rng.integers(3))]
    views: list[tuple[np.ndarray, np.ndarray]] = []
    roles: list[str] = []
    if style in ("video", "both"):
        n_video = n_main if style == "video" else max(2, n_main // 2)
        views += s.video(n_video)
        roles += ["video"] * n_video
    while len(views) < n_main:
        views.append(s.unstructured())
        roles.append("unstructured")
    for k in range(n_dist):
        v = s.occluded() if k % 2 == 0 else None
        if v is not None:
            views.append(v)
            roles.append("occluded")
            continue
        v = s.low_overlap()
        if v is not None:
            views.append(v)
            roles.append("low_overlap")
        else:  # no place for a disturbing view: add an ordinary one
            views.append(s.unstructured())
            roles.append("unstructured")
    order = rng.permutation(len(views)) if style != "video" else np.arange(len(views))
    if style == "video":  # keep the video in order, put disturbing views at random positions
        main = list(range(n_main))
        for k in range(n_main, len(views)):
            main.insert(int(rng.integers(len(main) + 1)), k)
        order = np.array(main)
    K = np.stack([views[i][0] for i in order])
    poses = np.stack([views[i][1] for i in order])
    return CameraRig(
        K=K, cam_from_world=poses, roles=tuple(roles[i] for i in order), width=width, height=height
    )
