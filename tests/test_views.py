"""Tests for colmap_pvs.views: MVSNet view scores, depth ranges, source resolution."""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
from pathlib import Path

import numpy as np
import pytest

from colmap_pvs import views
from colmap_pvs.config import config_from_dict, config_to_dict
from colmap_pvs.errors import ConfigError, WorkspaceError
from colmap_pvs.types import Camera, Image, Points3D, SparseModel
from colmap_pvs.views import (
    ViewSelectionConfig,
    angle_weight,
    best_and_worst,
    compute_depth_range,
    compute_pair_statistics,
    compute_view_scores,
    format_selection_table,
    rank_sources,
    resolve_sources,
    select_views,
)

STATUE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "colmap-statue"


# --------------------------------------------------------------------------- helpers


def look_at(center: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``[3, 4]`` cam_from_world of a camera at ``center`` looking at ``target`` (OpenCV axes)."""
    z = target - center
    z = z / np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return np.concatenate([R, (-R @ center)[:, None]], axis=1)


def make_model(
    centers: np.ndarray,
    xyz: np.ndarray,
    tracks: list[list[int]],
    image_ids: list[int] | None = None,
    point_ids: list[int] | None = None,
) -> SparseModel:
    """A SparseModel with one camera per image, all looking at the origin.

    ``tracks[p]`` lists the image ids observing point ``p``; each image's ``point3D_ids``
    is derived from the tracks.
    """
    n = len(centers)
    image_ids = image_ids or list(range(1, n + 1))
    point_ids = point_ids or list(range(100, 100 + len(xyz)))
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    cameras = {
        cid: Camera(cid, "PINHOLE", 640, 480, K.copy(), np.array([500.0, 500.0, 320, 240]))
        for cid in image_ids
    }
    observed: dict[int, list[int]] = {i: [] for i in image_ids}
    for pid, track in zip(point_ids, tracks, strict=True):
        for i in track:
            if i in observed:
                observed[i].append(pid)
    images = {
        iid: Image(
            iid,
            f"img_{iid:03d}.jpg",
            iid,
            look_at(np.asarray(c, dtype=np.float64), np.zeros(3)),
            np.array(observed[iid], dtype=np.int64),
        )
        for iid, c in zip(image_ids, centers, strict=True)
    }
    lengths = [len(t) for t in tracks]
    points = Points3D(
        ids=np.array(point_ids, dtype=np.int64),
        xyz=np.asarray(xyz, dtype=np.float64).reshape(-1, 3),
        rgb=np.zeros((len(xyz), 3), dtype=np.uint8),
        error=np.zeros(len(xyz)),
        track_offsets=np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
        track_image_ids=np.array([i for t in tracks for i in t], dtype=np.int64),
    )
    return SparseModel(cameras, images, points, {im.name: iid for iid, im in images.items()})


def ring_model(seed: int = 0, n_images: int = 8, n_points: int = 60) -> SparseModel:
    """Cameras on a ring of radius 5 around a random cloud; random tracks of length 2..n_images."""
    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 2 * np.pi, n_images, endpoint=False)
    centers = np.stack([5 * np.cos(ang), 5 * np.sin(ang), 0.5 * rng.standard_normal(n_images)], axis=1)
    xyz = rng.uniform(-1, 1, size=(n_points, 3))
    tracks = []
    for _ in range(n_points):
        k = int(rng.integers(2, n_images + 1))
        tracks.append([int(i) + 1 for i in rng.choice(n_images, size=k, replace=False)])
    return make_model(centers, xyz, tracks)


def brute_force_scores(model: SparseModel, cfg: ViewSelectionConfig) -> tuple[np.ndarray, np.ndarray]:
    """Double loop over points and their track pairs, with the textbook formula."""
    ids = sorted(model.images)
    idx = {i: k for k, i in enumerate(ids)}
    S = np.zeros((len(ids), len(ids)))
    N = np.zeros((len(ids), len(ids)), dtype=np.int64)
    for p in range(len(model.points)):
        X = model.points.xyz[p]
        track = sorted({int(i) for i in model.points.track(p) if int(i) in idx})
        for i, j in itertools.combinations(track, 2):
            ri = X - model.images[i].center
            rj = X - model.images[j].center
            c = float(ri @ rj / (np.linalg.norm(ri) * np.linalg.norm(rj)))
            theta = math.degrees(math.acos(max(-1.0, min(1.0, c))))
            sigma = cfg.sigma1 if theta <= cfg.theta0_deg else cfg.sigma2
            g = math.exp(-((theta - cfg.theta0_deg) ** 2) / (2 * sigma**2))
            for a, b in ((i, j), (j, i)):
                S[idx[a], idx[b]] += g
                N[idx[a], idx[b]] += 1
    return S, N


# --------------------------------------------------------------------------- G and config


def test_angle_weight_piecewise():
    t0, s1, s2 = 5.0, 1.0, 10.0
    got = angle_weight(np.array([4.0, 5.0, 7.0, 30.0]), t0, s1, s2)
    expected = [math.exp(-1 / 2), 1.0, math.exp(-4 / 200), math.exp(-625 / 200)]
    np.testing.assert_allclose(got, expected, rtol=1e-12)
    # below theta0 the narrow sigma1 applies, above it the wide sigma2
    assert angle_weight(3.0, t0, s1, s2) < angle_weight(7.0, t0, s1, s2)
    assert float(angle_weight(5.0, t0, s1, s2)) == 1.0


def test_config_validation_and_roundtrip():
    cfg = config_from_dict(ViewSelectionConfig, {"num_views": 3, "depth_percentiles": [2, 98]})
    assert cfg.depth_percentiles == (2.0, 98.0)
    assert config_from_dict(ViewSelectionConfig, config_to_dict(cfg)) == cfg
    for bad in (
        {"num_views": 1},
        {"sigma1": 0.0},
        {"min_shared_points": 0},
        {"min_points": 0},
        {"depth_percentiles": [99, 1]},
        {"depth_margin": 1.0},
        {"min_depth_ratio": 0.0},
    ):
        with pytest.raises(ConfigError):
            config_from_dict(ViewSelectionConfig, bad)
    for f in ViewSelectionConfig.__dataclass_fields__.values():
        assert f.metadata.get("help"), f"field {f.name} has no help text"


# --------------------------------------------------------------------------- scores


@pytest.mark.parametrize("seed", [0, 1])
def test_scores_match_brute_force(seed):
    model = ring_model(seed)
    cfg = ViewSelectionConfig()
    ids, S = compute_view_scores(model, cfg)
    assert list(ids) == sorted(model.images)
    np.testing.assert_array_equal(S, S.T)
    assert np.all(np.diag(S) == 0)
    S_ref, N_ref = brute_force_scores(model, cfg)
    np.testing.assert_allclose(S, S_ref, rtol=1e-9, atol=1e-12)
    stats = compute_pair_statistics(model, cfg)
    np.testing.assert_array_equal(stats.shared_points, N_ref)
    assert S.max() > 0


def test_scores_chunking_is_invisible(monkeypatch):
    model = ring_model(3, n_images=10, n_points=200)
    _, S_full = compute_view_scores(model)
    monkeypatch.setattr(views.scores, "_MAX_PAIRS_PER_CHUNK", 7)  # where the chunking reads it
    _, S_chunked = compute_view_scores(model)
    np.testing.assert_allclose(S_chunked, S_full, rtol=1e-12)


def test_scores_are_computed_a_step_at_a_time_in_bounded_memory_with_the_same_bits(monkeypatch):
    import tracemalloc

    model = ring_model(4, n_images=40, n_points=1500)  # ~300,000 observation pairs, one chunk
    monkeypatch.setattr(views.scores, "_MAX_PAIRS_PER_STEP", 1 << 30, raising=False)
    whole = compute_pair_statistics(model)
    monkeypatch.setattr(views.scores, "_MAX_PAIRS_PER_STEP", 1 << 12, raising=False)
    tracemalloc.start()
    try:
        stepped = compute_pair_statistics(model)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(stepped.scores, whole.scores)  # the same sums, to the last bit
    np.testing.assert_array_equal(stepped.shared_points, whole.shared_points)
    # ~16 B per pair kept until the chunk's bincount; the angles of all pairs at once take ~150 B per pair.
    assert peak < 15e6


def test_scores_ignore_duplicates_and_unknown_images():
    centers = np.array([[5.0, 0, 0], [0, 5.0, 0], [-5.0, 0, 0]])
    xyz = np.array([[0.1, 0.2, 0.0], [0.0, -0.3, 0.2]])
    clean = make_model(centers, xyz, [[1, 2], [2, 3]])
    # same observations plus a repeated one and an unregistered image id 99
    dirty = make_model(centers, xyz, [[1, 2, 1, 99], [2, 3]])
    np.testing.assert_allclose(compute_view_scores(dirty)[1], compute_view_scores(clean)[1])


def test_scores_prefer_theta0():
    # image 2 sees the point at ~5 degrees from image 1, image 3 at ~60 degrees
    X = np.zeros(3)
    c1 = np.array([10.0, 0, 0])
    rot = lambda d: np.array([10 * math.cos(math.radians(d)), 10 * math.sin(math.radians(d)), 0])  # noqa: E731
    model = make_model(np.stack([c1, rot(5), rot(60)]), X[None], [[1, 2, 3]])
    _, S = compute_view_scores(model)
    assert S[0, 1] == pytest.approx(1.0)
    assert S[0, 2] == pytest.approx(math.exp(-(55**2) / 200))
    assert rank_sources(np.where(np.arange(3) == 0, -np.inf, S[0])).tolist() == [1, 2]


def test_empty_model_scores():
    model = make_model(np.array([[5.0, 0, 0], [0, 5.0, 0]]), np.zeros((0, 3)), [])
    ids, S = compute_view_scores(model)
    assert ids.shape == (2,) and np.all(S == 0)


# --------------------------------------------------------------------------- depth ranges


def test_depth_range_contains_percentiles_and_is_positive():
    model = ring_model(4, n_images=6, n_points=300)
    cfg = ViewSelectionConfig()
    for image in model.images.values():
        rng_ = compute_depth_range(model, image, cfg)
        assert rng_ is not None
        dmin, dmax = rng_
        assert 0 < dmin < dmax
        rows = np.searchsorted(model.points.ids, image.point3D_ids)
        z = model.points.xyz[rows] @ image.R[2] + image.t[2]
        lo, hi = np.percentile(z, cfg.depth_percentiles)
        assert dmin <= lo and hi <= dmax
        assert dmin == pytest.approx(lo * (1 - cfg.depth_margin))
        assert dmax == pytest.approx(hi * (1 + cfg.depth_margin))


def test_depth_range_ignores_points_behind_camera_and_guards_dmin():
    centers = np.array([[5.0, 0, 0], [0, 5.0, 0]])
    # 12 points in front of image 1 (depths ~5 +- 0.5) and 5 behind it (x > 5)
    front = np.stack([np.linspace(-0.5, 0.5, 12), np.zeros(12), np.zeros(12)], axis=1)
    behind = np.stack([np.full(5, 8.0), np.zeros(5), np.zeros(5)], axis=1)
    xyz = np.concatenate([front, behind])
    model = make_model(centers, xyz, [[1, 2]] * 17)
    cfg = ViewSelectionConfig(depth_percentiles=(0.0, 100.0), depth_margin=0.0)
    dmin, dmax = compute_depth_range(model, model.images[1], cfg)
    assert dmin == pytest.approx(4.5) and dmax == pytest.approx(5.5)
    # the guard keeps dmin away from 0 even for a point almost at the camera centre
    near = make_model(centers, np.concatenate([front, [[4.99999, 0, 0]]]), [[1, 2]] * 13)
    # (outlier rejection off: that near point is a depth outlier, tests/test_robustness_views.py)
    cfg2 = ViewSelectionConfig(depth_percentiles=(0.0, 100.0), min_depth_ratio=0.01, depth_outlier_sigmas=0)
    dmin, dmax = compute_depth_range(near, near.images[1], cfg2)
    assert dmin == pytest.approx(0.01 * dmax)


def test_too_few_points_is_skipped_with_warning(caplog):
    rng = np.random.default_rng(5)
    centers = np.array([[5.0, 0, 0], [0, 5.0, 0], [-5.0, 0, 0], [0, -5.0, 0]])
    xyz = rng.uniform(-1, 1, size=(40, 3))
    # image 3 sees 3 points, image 4 sees none
    tracks = [[1, 2, 3] if p < 3 else [1, 2] for p in range(40)]
    model = make_model(centers, xyz, tracks)
    cfg = ViewSelectionConfig(min_points=10, min_shared_points=1)
    with caplog.at_level(logging.WARNING, logger="colmap_pvs.views"):
        assert compute_depth_range(model, model.images[3], cfg) is None
        sel = select_views(model, cfg)
    assert set(sel.references) == {"img_001.jpg", "img_002.jpg"}
    skipped = {s.name: s for s in sel.skipped}
    assert set(skipped) == {"img_003.jpg", "img_004.jpg"}
    assert skipped["img_003.jpg"].num_points == 3 and skipped["img_004.jpg"].num_points == 0
    assert "img_003.jpg" in caplog.text and "img_004.jpg" in caplog.text
    # issue 41: one summary WARNING for the images select_views skips, not one per image
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="colmap_pvs.views"):
        select_views(model, cfg)
    assert len(caplog.records) == 1 and "skips 2 of 4 image(s)" in caplog.records[0].getMessage()
    # a skipped reference is still a usable source for others
    assert "img_003.jpg" in sel.references["img_001.jpg"].ranked_names
    assert sel.sources("img_004.jpg") == ()
    table = format_selection_table(sel)
    assert "SKIPPED" in table and "img_004.jpg" in table and "img_001.jpg" in table


def test_no_candidate_source_is_skipped(caplog):
    centers = np.array([[5.0, 0, 0], [0, 5.0, 0], [-5.0, 0, 0]])
    xyz = np.random.default_rng(6).uniform(-1, 1, size=(30, 3))
    tracks = [[1, 2]] * 20 + [[3]] * 10  # image 3 shares nothing
    model = make_model(centers, xyz, tracks)
    with caplog.at_level(logging.WARNING, logger="colmap_pvs.views"):
        sel = select_views(model, ViewSelectionConfig(min_points=5))
    assert [s.name for s in sel.skipped] == ["img_003.jpg"]
    assert "shares" in sel.skipped[0].reason


def depths_model(depths, observed_ids=None, point_ids=None) -> tuple[SparseModel, Image]:
    """One image at the origin looking down +z (``[I | 0]``) and points on its axis at exactly ``depths``;
    the image observes ``observed_ids`` (default: every point)."""
    xyz = np.stack([np.zeros(len(depths)), np.zeros(len(depths)), np.asarray(depths, float)], axis=1)
    model = make_model(np.array([[5.0, 0, 0]]), xyz, [[1]] * len(depths), point_ids=point_ids)
    ids = model.points.ids if observed_ids is None else np.asarray(observed_ids, dtype=np.int64)
    image = dataclasses.replace(model.images[1], cam_from_world=np.eye(3, 4), point3D_ids=ids)
    return model, image


def test_points_at_one_depth_get_a_range_one_percent_wide():
    model, image = depths_model([2.0] * 12)
    cfg = ViewSelectionConfig(depth_percentiles=(0.0, 100.0), depth_margin=0.0)
    assert compute_depth_range(model, image, cfg) == pytest.approx((1.98, 2.02), rel=1e-12)


def test_an_image_with_exactly_min_points_gets_a_range(caplog):
    model, image = depths_model(np.linspace(2.0, 3.0, 10))
    assert compute_depth_range(model, image, ViewSelectionConfig(min_points=10)) is not None
    with caplog.at_level(logging.WARNING, logger="colmap_pvs.views"):
        assert compute_depth_range(model, image, ViewSelectionConfig(min_points=11)) is None
    assert "observes 10 sparse point(s)" in caplog.text
    # a single observed point is enough where min_points is 1
    one, image1 = depths_model([4.0])
    cfg = ViewSelectionConfig(min_points=1, depth_percentiles=(0.0, 100.0), depth_margin=0.0)
    assert compute_depth_range(one, image1, cfg) == pytest.approx((3.96, 4.04))


def test_points_on_or_just_behind_the_camera_plane_do_not_count():
    model, image = depths_model([-0.5, 0.0, 2.0, 2.5, 3.0])
    cfg = ViewSelectionConfig(min_points=3, depth_percentiles=(0.0, 100.0), depth_margin=0.0)
    assert compute_depth_range(model, image, cfg) == pytest.approx((2.0, 3.0))
    assert compute_depth_range(model, image, dataclasses.replace(cfg, min_points=4)) is None


def test_observed_ids_missing_from_the_model_are_dropped_with_a_debug_note(caplog):
    """A track that names points the model no longer has (a filtered or edited model): the known
    points give the range, the rest are counted at DEBUG."""
    cfg = ViewSelectionConfig(min_points=3, depth_percentiles=(0.0, 100.0), depth_margin=0.0)
    model, image = depths_model([2.0, 2.5, 3.0], observed_ids=[7, 100, 101, 102, 5000, 9])
    with caplog.at_level(logging.DEBUG, logger="colmap_pvs.views"):
        assert compute_depth_range(model, image, cfg) == pytest.approx((2.0, 3.0))
    assert "3 observed point ids are not in the model's points" in caplog.text
    caplog.clear()
    model, image = depths_model([2.0, 2.5, 3.0])
    with caplog.at_level(logging.DEBUG, logger="colmap_pvs.views"):
        compute_depth_range(model, image, cfg)
    assert "not in the model's points" not in caplog.text
    # a model without points at all: no range, with the warning, not a crash
    empty, image = depths_model([], observed_ids=[100, 101, 102])
    with caplog.at_level(logging.WARNING, logger="colmap_pvs.views"):
        assert compute_depth_range(empty, image, cfg) is None
    assert "observes 0 sparse point(s)" in caplog.text


# --------------------------------------------------------------------------- selection and resolution


def test_select_views_top_k_and_min_shared():
    model = ring_model(7, n_images=8, n_points=400)
    cfg = ViewSelectionConfig(num_views=4, min_shared_points=3, min_points=5, coverage_decay=1.0,
                              wide_sources=0)
    sel = select_views(model, cfg)
    assert not sel.skipped
    for k, name in enumerate(sel.names):
        ref = sel.references[name]
        assert name not in ref.ranked_names
        assert ref.source_names == ref.ranked_names[:3]
        scores = np.array(ref.source_scores)
        assert np.all(np.diff(scores) <= 0) and np.all(scores > 0)
        expected = [sel.names[j] for j in np.argsort(-sel.score_row(name), kind="stable")[:3]]
        assert list(ref.source_names) == expected
        for s in ref.ranked_names:
            assert sel.shared_points[k, sel.index_of(s)] >= 3
    # raising min_shared_points removes weak pairs
    strict = select_views(model, ViewSelectionConfig(num_views=4, min_shared_points=10**6, min_points=5))
    assert not strict.references and len(strict.skipped) == 8


def test_resolve_sources_modes():
    model = ring_model(8, n_images=6, n_points=200)
    sel = select_views(model, ViewSelectionConfig(num_views=3, min_points=5))
    ref = sel.names[0]
    assert resolve_sources(sel, ref, "auto", (), 2) == sel.references[ref].source_names
    assert resolve_sources(sel, ref, "auto", (), 100) == sel.references[ref].ranked_names
    everything = resolve_sources(sel, ref, "all", (), 0)
    assert len(everything) == 5 and ref not in everything
    row = sel.score_row(ref)
    assert everything[: len(sel.references[ref].ranked_names)] == sel.references[ref].ranked_names
    assert resolve_sources(sel, ref, "explicit", (sel.names[3], sel.names[1], sel.names[3]), 0) == (
        sel.names[3],
        sel.names[1],
    )
    # plain (names, scores) input: by decreasing score
    by_score = resolve_sources((sel.names, sel.scores), ref, "all", (), 0)
    assert set(by_score) == set(everything)
    assert [row[sel.index_of(n)] for n in by_score] == sorted(row[row > -np.inf], reverse=True)
    with pytest.raises(WorkspaceError, match="nope.jpg"):
        resolve_sources(sel, ref, "explicit", ("nope.jpg",), 0)
    with pytest.raises(WorkspaceError, match="ghost.jpg"):
        resolve_sources(sel, "ghost.jpg", "auto", (), 2)
    with pytest.raises(WorkspaceError, match="own source"):
        resolve_sources(sel, ref, "explicit", (ref,), 0)
    with pytest.raises(WorkspaceError):
        resolve_sources(sel, ref, "explicit", (), 0)
    with pytest.raises(WorkspaceError, match="0"):
        resolve_sources(sel, ref, "auto", (), 0)


def test_best_and_worst():
    scores = np.array([-np.inf, 5.0, 0.0, 1.0, 9.0, 3.0, 0.5, np.nan])
    best, worst = best_and_worst(scores, 2, 2)
    assert best.tolist() == [4, 1]
    assert worst.tolist() == [6, 3]  # zero-score (index 2), reference and NaN are not candidates
    masked = np.ma.masked_array([7.0, 5.0, 1.0, 2.0], mask=[True, False, False, False])
    best, worst = best_and_worst(masked, 1, 1)
    assert best.tolist() == [1] and worst.tolist() == [2]
    # too few candidates: best first, worst gets what is left, never overlapping
    best, worst = best_and_worst(np.array([-np.inf, 2.0, 1.0, 0.5]), 2, 2)
    assert best.tolist() == [1, 2] and worst.tolist() == [3]
    best, worst = best_and_worst(np.array([-np.inf, 0.0, 0.0]))
    assert best.size == 0 and worst.size == 0
    # ties broken by index
    best, worst = best_and_worst(np.array([1.0, 1.0, 1.0, 1.0, -np.inf]), 1, 2)
    assert best.tolist() == [0] and worst.tolist() == [1, 2]


# --------------------------------------------------------------------------- real data


def _read_statue() -> SparseModel:
    try:
        from colmap_pvs.io.sparse import read_sparse_model
    except ImportError:
        read_sparse_model = None
    if read_sparse_model is not None:
        return read_sparse_model(STATUE / "sparse")
    pycolmap = pytest.importorskip("pycolmap")
    rec = pycolmap.Reconstruction(str(STATUE / "sparse"))
    cameras = {
        cid: Camera(cid, c.model.name, c.width, c.height, c.calibration_matrix(), np.asarray(c.params))
        for cid, c in rec.cameras.items()
    }
    images = {}
    for iid, im in rec.images.items():
        pids = [p.point3D_id for p in im.points2D if p.has_point3D()]
        images[iid] = Image(
            iid, im.name, im.camera_id, im.cam_from_world().matrix(), np.array(pids, dtype=np.int64)
        )
    pids = sorted(rec.points3D)
    pts = [rec.points3D[p] for p in pids]
    tracks = [[e.image_id for e in p.track.elements] for p in pts]
    points = Points3D(
        ids=np.array(pids, dtype=np.int64),
        xyz=np.array([p.xyz for p in pts]),
        rgb=np.array([p.color for p in pts], dtype=np.uint8),
        error=np.array([p.error for p in pts]),
        track_offsets=np.concatenate([[0], np.cumsum([len(t) for t in tracks])]).astype(np.int64),
        track_image_ids=np.array([i for t in tracks for i in t], dtype=np.int64),
    )
    return SparseModel(cameras, images, points, {im.name: iid for iid, im in images.items()})


def test_colmap_statue_selection():
    if not (STATUE / "sparse" / "points3D.bin").is_file():
        pytest.skip(f"real data not found at {STATUE} (see ../shared/data/README.md)")
    model = _read_statue()
    assert len(model.images) == 23 and len(model.points) == 1443
    cfg = ViewSelectionConfig()
    sel = select_views(model, cfg)
    assert not sel.skipped
    assert len(sel.references) == 23
    for ref in sel.references.values():
        assert len(ref.source_names) == cfg.num_views - 1
        image = model.images[ref.image_id]
        rows = np.searchsorted(model.points.ids, image.point3D_ids)
        z = model.points.xyz[rows] @ image.R[2] + image.t[2]
        dmin, dmax = ref.depth_range
        assert 0 < dmin < dmax
        inside = (z >= dmin) & (z <= dmax)
        assert inside.mean() >= 0.95, (ref.name, inside.mean())
        lo, hi = np.percentile(z[z > 0], cfg.depth_percentiles)
        assert dmin <= lo and hi <= dmax
    table = format_selection_table(sel)
    assert table.count("DSC_") >= 23


# --------------------------------------------------------------------------- coverage-aware order


def two_cluster_model() -> SparseModel:
    """Reference 1 sees a left cluster (points 0-29) and a right cluster (30-39).

    Images 2 and 3 see only the left cluster, image 4 only the right one; all at ~5 degrees
    from the reference, so by plain score 2 and 3 (30 shared points) beat 4 (10).
    """
    rng = np.random.default_rng(3)
    left = rng.uniform(-0.3, 0.3, (30, 3)) + [-1.0, 0.0, 0.0]
    right = rng.uniform(-0.3, 0.3, (10, 3)) + [1.0, 0.0, 0.0]
    xyz = np.concatenate([left, right])
    a = np.radians(5.0)
    centers = np.array([
        [0.0, -10.0, 0.0],
        [10 * np.sin(a), -10 * np.cos(a), 0.0],
        [-10 * np.sin(a), -10 * np.cos(a), 0.0],
        [0.0, -10 * np.cos(a), 10 * np.sin(a)],
    ])
    tracks = [[1, 2, 3]] * 30 + [[1, 4]] * 10
    return make_model(centers, xyz, tracks)


def test_coverage_order_prefers_views_of_uncovered_points():
    model = two_cluster_model()
    plain = select_views(model, ViewSelectionConfig(num_views=3, min_points=5, coverage_decay=1.0,
                                                   wide_sources=0))
    aware = select_views(model, ViewSelectionConfig(num_views=3, min_points=5, coverage_decay=0.1,
                                                   wide_sources=0))
    ref = "img_001.jpg"
    assert plain.references[ref].source_names[1] in ("img_002.jpg", "img_003.jpg")
    # the best by score still comes first; the second covers the right cluster
    assert aware.references[ref].source_names[0] == plain.references[ref].source_names[0]
    assert aware.references[ref].source_names[1] == "img_004.jpg"
    # every candidate is still listed once, and the scores follow the names
    assert sorted(aware.references[ref].ranked_names) == sorted(plain.references[ref].ranked_names)
    row = aware.score_row(ref)
    entry = aware.references[ref]
    for name, score in zip(entry.source_names, entry.source_scores, strict=True):
        assert score == pytest.approx(row[aware.index_of(name)])
    # decay 1 is the plain top-N on any model
    ring = ring_model(5, n_images=7, n_points=300)
    plain_ring = select_views(ring, ViewSelectionConfig(num_views=4, min_points=5, coverage_decay=1.0,
                                                        wide_sources=0))
    for name, entry in plain_ring.references.items():
        order = np.argsort(-np.array([entry.ranked_scores]), kind="stable")[0]
        assert list(order) == list(range(len(order))), name


def test_wide_sources_are_picked_by_the_score_at_the_wide_angle():
    # the reference at 0 degrees on a circle around a small cloud, the others at 3 .. 30 degrees
    rng = np.random.default_rng(3)
    angles = [0, 3, 5, 7, 9, 15, 30]
    rad = np.radians(angles)
    centers = np.stack([10 * np.cos(rad), 10 * np.sin(rad), np.zeros_like(rad)], axis=1)
    xyz = 0.05 * rng.standard_normal((40, 3))
    model = make_model(centers, xyz, [list(range(1, len(angles) + 1))] * len(xyz))
    name = {a: f"img_{k + 1:03d}.jpg" for k, a in enumerate(angles)}
    plain = select_views(model, ViewSelectionConfig(num_views=5, min_points=5, wide_sources=0))
    wide = select_views(model, ViewSelectionConfig(num_views=5, min_points=5, wide_sources=2))  # at 15 deg
    ref = name[0]
    # theta0 = 5 alone: the four views nearest 5 degrees (3 degrees scores low: sigma1 = 1 below theta0)
    assert plain.references[ref].source_names == tuple(name[a] for a in (5, 7, 9, 15))
    # two by theta0 = 5, then the two best by the score at 15 degrees among the rest
    assert wide.references[ref].source_names == tuple(name[a] for a in (5, 7, 15, 30))
    entry = wide.references[ref]
    assert entry.source_names == entry.ranked_names[:4]
    assert sorted(entry.ranked_names) == sorted(plain.references[ref].ranked_names)
    row = wide.score_row(ref)
    for n, score in zip(entry.ranked_names, entry.ranked_scores, strict=True):
        assert score == pytest.approx(row[wide.index_of(n)])
    # at most half of the sources are wide: N = 3 keeps 1 by theta0 and takes 1 wide
    small = select_views(model, ViewSelectionConfig(num_views=3, min_points=5, wide_sources=5))
    assert small.references[ref].source_names == (name[5], name[15])
    with pytest.raises(ConfigError, match="wide_sources"):
        ViewSelectionConfig(wide_sources=-1)
    with pytest.raises(ConfigError, match="wide_theta0_deg"):
        ViewSelectionConfig(wide_theta0_deg=200.0)


def test_coverage_decay_validation():
    with pytest.raises(ConfigError, match="coverage_decay"):
        ViewSelectionConfig(coverage_decay=1.5)


def test_depth_near_factor_scales_the_near_end_only_and_keeps_the_guard():
    rng = np.random.default_rng(0)
    model = make_model(np.array([[5.0, 0, 0], [0, 5.0, 0]]), rng.uniform(-0.5, 0.5, (12, 3)), [[1, 2]] * 12)
    base = compute_depth_range(model, model.images[1], ViewSelectionConfig())
    half = compute_depth_range(model, model.images[1], ViewSelectionConfig(depth_near_factor=0.5))
    assert half == pytest.approx((0.5 * base[0], base[1]))
    selected = views.select_views(model, ViewSelectionConfig(num_views=2, depth_near_factor=0.5))
    assert selected.references["img_001.jpg"].depth_range == pytest.approx(half)
    guard = ViewSelectionConfig(depth_near_factor=0.01, min_depth_ratio=0.1)
    assert compute_depth_range(model, model.images[1], guard)[0] == pytest.approx(0.1 * base[1])
    for bad in (0.0, 1.5, float("nan")):
        with pytest.raises(ConfigError, match="depth_near_factor"):
            ViewSelectionConfig(depth_near_factor=bad)
