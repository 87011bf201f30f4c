"""tools/teacher_labels.py: agreement and multi-view consistency on synthetic depth maps (no teacher)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import load_tool


@pytest.fixture(scope="module")
def tl():
    return load_tool("teacher_labels")


H, W = 48, 64
K = np.array([[60.0, 0, W / 2], [0, 60.0, H / 2], [0, 0, 1]])


def _pose(tx: float) -> np.ndarray:
    """cam_from_world of a camera at x = tx looking down +z (world = first camera)."""
    T = np.eye(4)
    T[0, 3] = -tx
    return T


def _plane_depth(pose: np.ndarray, z0: float = 5.0) -> np.ndarray:
    """Depth of the fronto-parallel plane z = z0 (world) seen by a camera translated along x."""
    return np.full((H, W), z0 - pose[2, 3], np.float32)


def test_agree_mean_of_agreeing_and_drops_disagreement(tl):
    a = np.full((H, W), 5.0, np.float32)
    b = a * 1.004  # within 1 %
    c = a * 1.2  # disagrees with both
    depth, count = tl.agree(np.stack([a, b, c]), np.ones((3, H, W), bool), 0.01)
    assert np.all(count == 2)
    assert np.allclose(depth, (a + b) / 2)
    # only one estimate, or all disagreeing: no candidate
    far = np.stack([a, a * 1.1, a * 1.3])
    depth, count = tl.agree(far, np.ones((3, H, W), bool), 0.01)
    assert np.all(count == 1) and np.all(depth == 0)
    # an invalid (masked) estimate does not vote
    valid = np.ones((3, H, W), bool)
    valid[1, :10] = False
    depth, count = tl.agree(np.stack([a, b, c]), valid, 0.01)
    assert np.all(depth[:10] == 0) and np.all(count[:10] == 1)
    assert np.all(depth[10:] > 0)


def test_a_single_estimate_is_its_own_candidate_where_valid(tl):
    a = np.full((H, W), 3.0, np.float32)
    valid = np.ones((1, H, W), bool)
    valid[0, :5] = False
    depth, count = tl.agree(a[None], valid, 0.01)
    assert np.all(depth[:5] == 0) and np.all(count[:5] == 0)
    assert np.allclose(depth[5:], 3.0) and np.all(count[5:] == 1)


def test_agree_all_three_counted(tl):
    a = np.full((H, W), 2.0, np.float32)
    depth, count = tl.agree(np.stack([a, a * 1.002, a * 0.998]), np.ones((3, H, W), bool), 0.01)
    assert np.all(count == 3)
    assert np.allclose(depth, 2.0, rtol=1e-4)


def test_consistent_views_plane(tl):
    ref_pose, src_pose = _pose(0.0), _pose(0.5)
    d_ref, d_src = _plane_depth(ref_pose), _plane_depth(src_pose)
    count = tl.consistent_views(d_ref, K, ref_pose, [(d_src, K, src_pose)], 1.0, 0.01)
    # pixels whose ray hits the plane where the source sees it are confirmed; 0.5 m baseline at 5 m
    # shifts by 6 px, so the left columns fall outside the source image
    inside = count[:, 10:-10]
    assert inside.min() == 1
    assert count[:, :4].max() == 0
    # a source that sees something 5 % nearer contradicts everywhere
    count = tl.consistent_views(d_ref, K, ref_pose, [(d_src * 0.95, K, src_pose)], 1.0, 0.01)
    assert count.max() == 0
    # a local contradiction drops only the pixels that project there; holes never confirm
    bad = d_src.copy()
    bad[20:30, 30:40] *= 1.1
    bad[:, 50:] = 0
    count = tl.consistent_views(d_ref, K, ref_pose, [(bad, K, src_pose), (d_src, K, src_pose)], 1.0, 0.01)
    assert count[25, 40] == 1  # projects to column ~34 of the source: contradicted there
    assert count[25, 20] == 2
    assert count[25, 60] == 1  # projects to ~54: a hole in the first source
    # a reference pixel without depth gets no count
    d_ref2 = d_ref.copy()
    d_ref2[5, 30] = 0
    assert tl.consistent_views(d_ref2, K, ref_pose, [(d_src, K, src_pose)], 1.0, 0.01)[5, 30] == 0


def test_label_weight_rises(tl):
    w = tl.label_weight(np.array([2, 3, 3]), 3, np.array([1, 1, 4]), 4)
    assert 0 < w[0] < w[1] < w[2] <= 1.0
    assert w[2] == pytest.approx(1.0)


def test_parse_estimates(tl):
    got = tl.parse_estimates("itermvs_dtu:0-4, patchmatchnet:4-8")
    assert got == ["itermvs_dtu:0-4", "patchmatchnet:4-8"]
    with pytest.raises(SystemExit):
        tl.parse_estimates("nonsense:0-4")
    with pytest.raises(SystemExit):
        tl.parse_estimates("itermvs_dtu:4-2")


def test_only_the_clones_the_estimates_use_are_required(tl):
    args = tl.build_parser().parse_args(["--itermvs", "I", "--scenes", "S", "--out", "O"])
    assert args.patchmatchnet is None  # a run of IterMVS estimates alone needs no PatchmatchNet clone
    with pytest.raises(SystemExit, match="need --patchmatchnet$"):
        tl.load_teachers({"itermvs_blended", "patchmatchnet"}, {"itermvs": "I", "patchmatchnet": None})
    with pytest.raises(SystemExit, match="need --itermvs and --patchmatchnet"):
        tl.load_teachers(["itermvs_dtu", "patchmatchnet"], {"itermvs": None, "patchmatchnet": None})
