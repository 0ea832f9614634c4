"""Tests of ndtom_ti.evaluation.metrics (batch NDT, L2 similarity, mean L2 score) and of the ray /
occupancy references in tests/reference.py. numpy only, no Taichi."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

_ROOT = str(Path(__file__).resolve().parents[1])
if _ROOT not in sys.path:  # pytest runs with --import-mode=importlib
    sys.path.insert(0, _ROOT)

from tests.reference import (  # noqa: E402
    batch_stats,
    endpoint_counts,
    eq12_logodds,
    ray_cells,
    ray_pass_counts,
)

from ndtom_ti.evaluation.metrics import (  # noqa: E402
    ZERO_COV_FLOOR,
    batch_ndt,
    cell_index,
    l2_similarity,
    mean_l2_score,
    regularize_cov,
)


def _spd(rng: np.random.Generator, scale: float = 0.1) -> np.ndarray:
    """A random symmetric positive definite (3, 3) matrix with std ~ scale."""
    a = rng.normal(size=(3, 3)) * scale
    return a @ a.T + np.eye(3) * (0.1 * scale) ** 2


# --------------------------------------------------------------------------------------
# batch_ndt
# --------------------------------------------------------------------------------------


def test_batch_ndt_hand_computed():
    r = 0.5
    pts = np.array(
        [
            # cell (0, 0, 0): mean (0.2, 0.2, 0.1), cov diag(0.01, 0.03, 0)
            [0.1, 0.1, 0.1],
            [0.3, 0.1, 0.1],
            [0.2, 0.4, 0.1],
            # cell (-1, 0, -2): two points
            [-0.2, 0.1, -0.6],
            [-0.4, 0.3, -0.8],
        ]
    )
    m = batch_ndt(pts, r)
    assert m["index"].tolist() == [[0, 0, 0]]
    assert m["n"].tolist() == [3]
    np.testing.assert_allclose(m["mean"][0], [0.2, 0.2, 0.1], atol=1e-15)
    np.testing.assert_allclose(m["cov"][0], np.diag([0.01, 0.03, 0.0]), atol=1e-15)

    m2 = batch_ndt(pts, r, min_points=2)
    assert m2["index"].tolist() == [[-1, 0, -2], [0, 0, 0]]  # lexicographic
    assert m2["n"].tolist() == [2, 3]
    np.testing.assert_allclose(m2["mean"][0], [-0.3, 0.2, -0.7], atol=1e-15)
    d = np.array([0.1, -0.1, 0.1])  # deviation of the first point; cov = 2 d d^T / 1
    np.testing.assert_allclose(m2["cov"][0], 2 * np.outer(d, d), atol=1e-15)

    assert m["index"].dtype == np.int64 and m["n"].dtype == np.int64
    assert m["mean"].dtype == np.float64 and m["cov"].shape == (1, 3, 3)


def test_batch_ndt_matches_per_cell_numpy_cov():
    rng = np.random.default_rng(0)
    r = 0.3
    pts = rng.normal(scale=1.0, size=(5000, 3))
    m = batch_ndt(pts, r)
    k = cell_index(pts, r)
    np.testing.assert_array_equal(k, np.floor(pts / r).astype(np.int64))
    # sorted lexicographically and unique
    keys = [tuple(row) for row in m["index"]]
    assert keys == sorted(keys) and len(set(keys)) == len(keys)
    total = 0
    for idx, mean, cov, n in zip(m["index"], m["mean"], m["cov"], m["n"]):
        sel = pts[np.all(k == idx, axis=1)]
        assert sel.shape[0] == n >= 3
        np.testing.assert_allclose(mean, sel.mean(axis=0), rtol=0, atol=1e-13)
        np.testing.assert_allclose(cov, np.cov(sel.T), rtol=0, atol=1e-13)
        total += n
    _, counts = np.unique(k, axis=0, return_counts=True)
    assert total == counts[counts >= 3].sum()


def test_batch_ndt_far_from_origin_is_accurate():
    # A kilometre-scale offset with a 1e-4 m std: centre-relative sums keep full precision.
    rng = np.random.default_rng(1)
    r = 0.5
    centre = np.array([1234.25, -5678.25, 901.25])
    local = rng.normal(scale=1e-4, size=(200, 3))
    pts = centre + local
    m = batch_ndt(pts, r)
    assert m["index"].shape == (1, 3)
    exp_cov = np.cov((pts - centre).T)
    np.testing.assert_allclose(m["cov"][0], exp_cov, rtol=1e-6, atol=1e-16)
    np.testing.assert_allclose(m["mean"][0], pts.mean(axis=0), rtol=0, atol=1e-11)


def test_batch_ndt_edge_cases():
    assert batch_ndt(np.zeros((0, 3)), 0.1)["index"].shape == (0, 3)
    m = batch_ndt(np.array([[0.05, 0.05, 0.05], [np.nan, 0, 0], [np.inf, 0, 0]]), 0.1, 1)
    assert m["n"].tolist() == [1]
    np.testing.assert_array_equal(m["cov"][0], np.zeros((3, 3)))
    # a point exactly on a face belongs to the upper cell (floor semantics)
    m = batch_ndt(np.array([[0.5, 0.0, -0.5]]), 0.25, 1)
    assert m["index"].tolist() == [[2, 0, -2]]
    with pytest.raises(ValueError):
        batch_ndt(np.zeros((1, 3)), 0.0)


# --------------------------------------------------------------------------------------
# regularize_cov
# --------------------------------------------------------------------------------------


def test_regularize_cov():
    rng = np.random.default_rng(2)
    good = _spd(rng, 0.2)
    planar = np.diag([4.0, 1.0, 0.0])
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    planar_rot = rot @ planar @ rot.T
    zero = np.zeros((3, 3))
    out = regularize_cov(np.stack([good, planar_rot, zero]))
    assert out.shape == (3, 3, 3)
    # well conditioned: unchanged
    if np.linalg.eigvalsh(good)[0] >= 1e-3 * np.linalg.eigvalsh(good)[-1]:
        np.testing.assert_array_equal(out[0], 0.5 * (good + good.T))
    # rank deficient: smallest eigenvalue raised to 1e-3 * 4, eigenvectors kept
    np.testing.assert_allclose(np.linalg.eigvalsh(out[1]), [4e-3, 1.0, 4.0], rtol=1e-10)
    np.testing.assert_allclose(out[1], rot @ np.diag([4.0, 1.0, 4e-3]) @ rot.T, atol=1e-12)
    # zero covariance: tiny isotropic floor
    np.testing.assert_allclose(out[2], ZERO_COV_FLOOR * np.eye(3), rtol=1e-12)
    for c in out:
        np.testing.assert_array_equal(c, c.T)
        assert np.all(np.linalg.eigvalsh(c) > 0)
    # single matrix and custom ratio
    np.testing.assert_allclose(
        np.linalg.eigvalsh(regularize_cov(np.diag([1.0, 1e-9, 0.5]), ratio=0.1)),
        [0.1, 0.5, 1.0],
    )


# --------------------------------------------------------------------------------------
# l2_similarity
# --------------------------------------------------------------------------------------


def test_similarity_closed_forms():
    s = 0.2
    C = s**2 * np.eye(3)
    # equal isotropic covariances, means d apart: sim = exp(-d^2 / (4 s^2))
    for d in [0.0, 0.05, 0.2, 0.7]:
        sim = l2_similarity([0, 0, 0], C, [d, 0, 0], C)
        assert sim == pytest.approx(math.exp(-(d**2) / (4 * s**2)), rel=1e-12)
    # concentric isotropic, different variances
    s1, s2 = 0.1, 0.3
    exp = 2 * (s1**2 + s2**2) ** -1.5 / ((2 * s1**2) ** -1.5 + (2 * s2**2) ** -1.5)
    sim = l2_similarity(np.zeros(3), s1**2 * np.eye(3), np.zeros(3), s2**2 * np.eye(3))
    assert sim == pytest.approx(exp, rel=1e-12)
    # diagonal covariances: the integrals factorise into 1D Gaussian integrals
    v1, v2 = np.array([0.01, 0.04, 0.09]), np.array([0.02, 0.01, 0.05])
    mu1, mu2 = np.array([0.1, -0.2, 0.3]), np.array([0.0, 0.1, 0.25])
    inner = np.prod(np.exp(-((mu1 - mu2) ** 2) / (2 * (v1 + v2))) / np.sqrt(2 * np.pi * (v1 + v2)))
    n1 = np.prod(1 / np.sqrt(4 * np.pi * v1))
    n2 = np.prod(1 / np.sqrt(4 * np.pi * v2))
    sim = l2_similarity(mu1, np.diag(v1), mu2, np.diag(v2))
    assert sim == pytest.approx(2 * inner / (n1 + n2), rel=1e-12)


def test_similarity_vs_numerical_integration():
    mu1 = np.array([0.05, -0.03, 0.02])
    mu2 = np.array([-0.06, 0.04, 0.0])
    C1 = np.array([[0.030, 0.010, 0.000], [0.010, 0.020, 0.005], [0.000, 0.005, 0.015]])
    C2 = np.array([[0.020, -0.006, 0.004], [-0.006, 0.025, 0.000], [0.004, 0.000, 0.030]])
    h = 0.02
    ax = np.arange(-1.0, 1.0 + h / 2, h)
    X = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), axis=-1).reshape(-1, 3)

    def pdf(mu, C):
        d = X - mu
        m = np.einsum("ni,ij,nj->n", d, np.linalg.inv(C), d)
        return np.exp(-0.5 * m) / np.sqrt((2 * np.pi) ** 3 * np.linalg.det(C))

    f1, f2 = pdf(mu1, C1), pdf(mu2, C2)
    dv = h**3
    num = 2 * np.sum(f1 * f2) * dv / (np.sum(f1 * f1) * dv + np.sum(f2 * f2) * dv)
    sim = l2_similarity(mu1, C1, mu2, C2)
    assert 0.05 < sim < 0.95
    assert sim == pytest.approx(num, abs=1e-3)
    # the norm formula itself: ||f||^2 = (4 pi)^(-3/2) det(C)^(-1/2)
    assert np.sum(f1 * f1) * dv == pytest.approx((4 * np.pi) ** -1.5 / np.sqrt(np.linalg.det(C1)), rel=1e-3)


def test_similarity_properties():
    rng = np.random.default_rng(3)
    K = 200
    mu1 = rng.normal(size=(K, 3)) * 0.1
    mu2 = mu1 + rng.normal(size=(K, 3)) * 0.05
    C1 = np.stack([_spd(rng) for _ in range(K)])
    C2 = np.stack([_spd(rng) for _ in range(K)])
    s12 = l2_similarity(mu1, C1, mu2, C2)
    s21 = l2_similarity(mu2, C2, mu1, C1)
    assert s12.shape == (K,)
    np.testing.assert_allclose(s12, s21, rtol=1e-12, atol=0)
    assert np.all((s12 >= 0) & (s12 <= 1))
    np.testing.assert_allclose(l2_similarity(mu1, C1, mu1, C1), 1.0, rtol=0, atol=1e-14)
    assert np.all(s12 < 1)
    # decreasing as the means part along a fixed direction
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    dist = np.linspace(0, 2, 41)
    sims = l2_similarity(np.zeros(3), C1[0], dist[:, None] * direction, C2[0])
    assert np.all(np.diff(sims) < 0)
    assert sims[-1] < 1e-6
    # broadcasting one Gaussian against a batch
    np.testing.assert_allclose(
        l2_similarity(mu1[0], C1[0], mu2, C2),
        l2_similarity(np.repeat(mu1[:1], K, 0), np.repeat(C1[:1], K, 0), mu2, C2),
    )


def test_similarity_tiny_and_degenerate_covariances():
    tiny = 1e-200 * np.eye(3)  # det = 1e-600 underflows; log space does not
    assert l2_similarity(np.zeros(3), tiny, np.zeros(3), tiny) == pytest.approx(1.0, abs=1e-14)
    sim = l2_similarity(np.zeros(3), tiny, [1e-100, 0, 0], tiny)
    assert sim == pytest.approx(math.exp(-0.25), rel=1e-12)
    assert l2_similarity(np.zeros(3), tiny, np.zeros(3), np.eye(3)) == pytest.approx(0.0, abs=1e-250)
    # one singular covariance: limit 0; both identical singular: undefined
    sing = np.diag([1.0, 1.0, 0.0])
    assert l2_similarity(np.zeros(3), sing, np.zeros(3), np.eye(3)) == 0.0
    assert np.isnan(l2_similarity(np.zeros(3), sing, np.zeros(3), sing))


# --------------------------------------------------------------------------------------
# mean_l2_score
# --------------------------------------------------------------------------------------


def _random_map(seed: int, n_points: int = 4000) -> dict:
    rng = np.random.default_rng(seed)
    return batch_ndt(rng.normal(scale=1.5, size=(n_points, 3)), 0.5)


def test_mean_l2_score_self_and_subsets():
    ref = _random_map(4)
    K = ref["index"].shape[0]
    assert K > 20
    assert mean_l2_score(ref, ref) == pytest.approx(1.0, abs=1e-12)
    reg = dict(ref, cov=regularize_cov(ref["cov"]))  # positive definite
    assert mean_l2_score(reg, reg, regularize=False) == pytest.approx(1.0, abs=1e-12)
    # test map holding every other cell (shuffled order): half the reference
    if K % 2:
        ref = {k: v[:-1] for k, v in ref.items()}
        K -= 1
    rng = np.random.default_rng(5)
    half = rng.permutation(K)[: K // 2]
    test = {k: v[half] for k, v in ref.items()}
    assert mean_l2_score(test, ref) == pytest.approx(0.5, abs=1e-12)
    # reversed roles: every reference cell is in the test map -> 1
    assert mean_l2_score(ref, test) == pytest.approx(1.0, abs=1e-12)
    # extra cells in the test map only add nothing
    extra = {
        "index": np.concatenate([ref["index"], ref["index"][:3] + 1000]),
        "mean": np.concatenate([ref["mean"], ref["mean"][:3] + 500]),
        "cov": np.concatenate([ref["cov"], ref["cov"][:3]]),
    }
    assert mean_l2_score(extra, ref) == pytest.approx(1.0, abs=1e-12)


def test_mean_l2_score_matches_manual_sum():
    ref = _random_map(6)
    rng = np.random.default_rng(7)
    test = dict(ref)
    test["mean"] = ref["mean"] + rng.normal(scale=0.03, size=ref["mean"].shape)
    test["cov"] = ref["cov"] * rng.uniform(0.8, 1.2, size=(len(ref["cov"]), 1, 1))
    test["mean"] = test["mean"].astype(np.float32)  # float32 exports are accepted
    expected = np.sum(
        l2_similarity(
            test["mean"].astype(np.float64),
            regularize_cov(test["cov"]),
            ref["mean"],
            regularize_cov(ref["cov"]),
        )
    ) / len(ref["index"])
    score = mean_l2_score(test, ref)
    assert 0 < score < 1
    assert score == pytest.approx(expected, rel=1e-12)


def test_mean_l2_score_empty():
    ref = _random_map(8)
    empty = batch_ndt(np.zeros((0, 3)), 0.5)
    assert mean_l2_score(ref, empty) == 0.0
    assert mean_l2_score(empty, ref) == 0.0
    assert mean_l2_score(empty, empty) == 0.0


# --------------------------------------------------------------------------------------
# tests/reference.py: ray traversal
# --------------------------------------------------------------------------------------


def _cells(*rows):
    return np.array(rows, dtype=np.int64).reshape(-1, 3)


def test_ray_axis_aligned():
    got = ray_cells([0.1, 0.1, 0.1], [1.1, 0.1, 0.1], 0.25)
    np.testing.assert_array_equal(got, _cells([0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0]))
    got = ray_cells([0.1, 0.1, 0.1], [0.1, 0.1, -0.6], 0.25)
    np.testing.assert_array_equal(got, _cells([0, 0, 0], [0, 0, -1], [0, 0, -2], [0, 0, -3]))
    assert got.dtype == np.int64


def test_ray_along_cell_face():
    # y = 0.5 = 2 r exactly on both ends: the ray stays in y-cell 2 (floor semantics)
    got = ray_cells([0.1, 0.5, 0.1], [0.9, 0.5, 0.1], 0.25)
    np.testing.assert_array_equal(got, _cells([0, 2, 0], [1, 2, 0], [2, 2, 0], [3, 2, 0]))
    # along an edge (y and z both on planes)
    got = ray_cells([0.1, 0.5, -0.25], [0.6, 0.5, -0.25], 0.25)
    np.testing.assert_array_equal(got, _cells([0, 2, -1], [1, 2, -1], [2, 2, -1]))


def test_ray_zero_length_and_single_cell():
    np.testing.assert_array_equal(ray_cells([0.3, -0.3, 7.0], [0.3, -0.3, 7.0], 0.25), _cells([1, -2, 28]))
    np.testing.assert_array_equal(ray_cells([0.3, 0.3, 0.3], [0.4, 0.45, 0.3], 0.25), _cells([1, 1, 1]))


def test_ray_negative_coordinates():
    # r = 0.5: x from -1.2 (cell -3) to 0.3 (cell 0); y from -0.1 (cell -1) to -0.7 (cell -2)
    # x planes -1.0 (t=0.2/1.5), -0.5 (t=0.7/1.5), 0.0 (t=1.2/1.5); y plane -0.5 (t=0.4/0.6)
    got = ray_cells([-1.2, -0.1, -0.2], [0.3, -0.7, -0.2], 0.5)
    # t: x@0.1333, x@0.4667, y@0.6667, x@0.8
    np.testing.assert_array_equal(got, _cells([-3, -1, -1], [-2, -1, -1], [-1, -1, -1], [-1, -2, -1], [0, -2, -1]))
    # starting exactly on a plane and going -x: the origin's own cell comes first
    got = ray_cells([0.0, 0.1, 0.1], [-0.3, 0.1, 0.1], 0.25)
    np.testing.assert_array_equal(got, _cells([0, 0, 0], [-1, 0, 0], [-2, 0, 0]))


def test_ray_diagonal_through_corners():
    # every crossing is a corner; e = (1,1,1) lies on the low corner of cell (4,4,4)
    got = ray_cells([0, 0, 0], [1, 1, 1], 0.25)
    np.testing.assert_array_equal(got, _cells([0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3], [4, 4, 4]))
    # reversed: the corner points lie in the upper cells, so the same set in reverse order
    got = ray_cells([1, 1, 1], [0, 0, 0], 0.25)
    np.testing.assert_array_equal(got, _cells([4, 4, 4], [3, 3, 3], [2, 2, 2], [1, 1, 1], [0, 0, 0]))


def test_ray_corner_plus_x_minus_y():
    # +x, -y through the corner (1, 1): the cell holding the corner point, (1,1,0), is visited
    got = ray_cells([0.5, 1.5, 0.5], [1.5, 0.5, 0.5], 1.0)
    np.testing.assert_array_equal(got, _cells([0, 1, 0], [1, 1, 0], [1, 0, 0]))
    # -x, +y through the same corner: (1,1,0) again (it holds the corner)
    got = ray_cells([1.5, 0.5, 0.5], [0.5, 1.5, 0.5], 1.0)
    np.testing.assert_array_equal(got, _cells([1, 0, 0], [1, 1, 0], [0, 1, 0]))
    # +x, +y: direct diagonal step; -x, -y: likewise
    np.testing.assert_array_equal(ray_cells([0.5, 0.5, 0.5], [1.5, 1.5, 0.5], 1.0), _cells([0, 0, 0], [1, 1, 0]))
    np.testing.assert_array_equal(ray_cells([1.5, 1.5, 0.5], [0.5, 0.5, 0.5], 1.0), _cells([1, 1, 0], [0, 0, 0]))


def test_ray_random_matches_dense_sampling():
    # Generic rays: consecutive cells are face neighbours, the set equals a dense sampling of
    # the segment (which can only miss cells, never add any), and the ends are floor(o/r),
    # floor(e/r).
    rng = np.random.default_rng(9)
    r = 0.3
    ts = np.linspace(0, 1, 20001)
    for _ in range(30):
        o = rng.uniform(-2, 2, 3)
        e = rng.uniform(-2, 2, 3)
        got = ray_cells(o, e, r)
        np.testing.assert_array_equal(got[0], np.floor(o / r))
        np.testing.assert_array_equal(got[-1], np.floor(e / r))
        steps = np.abs(np.diff(got, axis=0)).sum(axis=1)
        assert np.all(steps == 1)
        assert len(got) == 1 + np.abs(np.floor(e / r) - np.floor(o / r)).sum()
        dense = np.floor((o + ts[:, None] * (e - o)) / r).astype(np.int64)
        dense_set = {tuple(c) for c in dense}
        got_set = {tuple(c) for c in got}
        assert dense_set <= got_set
        assert len(got_set) == len(got)  # a convex cell is entered once


# --------------------------------------------------------------------------------------
# tests/reference.py: counts, batch stats, eq. (12)
# --------------------------------------------------------------------------------------


def test_pass_and_endpoint_counts():
    o = np.array([0.1, 0.1, 0.1])
    ends = np.array([[0.6, 0.1, 0.1], [0.6, 0.1, 0.1], [0.1, 0.6, 0.1], [0.2, 0.2, 0.2]])
    # r = 0.25: ray 0/1 pass (0,0,0),(1,0,0), end (2,0,0); ray 2 passes (0,0,0),(0,1,0)
    # and ends (0,2,0); ray 3 ends in the origin cell
    assert ray_pass_counts(o, ends, 0.25) == {(0, 0, 0): 3, (1, 0, 0): 2, (0, 1, 0): 1}
    assert endpoint_counts(ends, 0.25) == {(2, 0, 0): 2, (0, 2, 0): 1, (0, 0, 0): 1}
    hit = np.array([True, False, True, True])
    assert ray_pass_counts(o, ends, 0.25, hit) == {
        (0, 0, 0): 3,
        (1, 0, 0): 2,
        (2, 0, 0): 1,
        (0, 1, 0): 1,
    }
    assert endpoint_counts(ends, 0.25, hit) == {(2, 0, 0): 1, (0, 2, 0): 1, (0, 0, 0): 1}


def test_batch_stats():
    pts = np.array([[0.1, 0.1, 0.1], [0.2, 0.1, 0.1], [-0.1, 0.0, 0.0]])
    s = batch_stats(pts, 0.5)
    assert s["index"].tolist() == [[-1, 0, 0], [0, 0, 0]]
    assert s["n"].tolist() == [1, 2]
    np.testing.assert_allclose(s["mean"], [[-0.1, 0.0, 0.0], [0.15, 0.1, 0.1]], atol=1e-15)
    np.testing.assert_array_equal(s["cov"][0], np.zeros((3, 3)))
    assert s["cov"][1][0, 0] == pytest.approx(0.005)


def test_eq12_logodds():
    lo, le = math.log(0.6 / 0.4), math.log(0.49 / 0.51)
    o = np.array([0.1, 0.1, 0.1])
    scan1 = (o, np.array([[0.6, 0.1, 0.1], [0.6, 0.1, 0.1], [0.35, 0.1, 0.1]]))
    # scan 1: (2,0,0) N_p = 2; (1,0,0) N_p = 1 (ray 3 ends there, so no free update even
    # though rays 1, 2 pass it); (0,0,0) N_e = 3
    got = eq12_logodds([scan1], 0.25)
    assert got == pytest.approx({(2, 0, 0): 2 * lo, (1, 0, 0): lo, (0, 0, 0): 3 * le})
    # scan 2 clears (2,0,0) with 10 free rays going beyond it; clamping at l_min
    scan2 = (o, np.tile([[1.1, 0.1, 0.1]], (10, 1)))
    got = eq12_logodds([scan1, scan2], 0.25, l_min=-0.1, l_max=0.5)
    assert got[(2, 0, 0)] == pytest.approx(max(min(2 * lo, 0.5) + 10 * le, -0.1))
    assert got[(1, 0, 0)] == pytest.approx(max(lo + 10 * le, -0.1))
    assert got[(4, 0, 0)] == pytest.approx(min(10 * lo, 0.5))
    # non-hit rays traverse their endpoint cell
    got = eq12_logodds([(o, scan2[1], np.zeros(10, bool))], 0.25)
    assert got[(4, 0, 0)] == pytest.approx(10 * le)
    assert set(got) == {(0, 0, 0), (1, 0, 0), (2, 0, 0), (3, 0, 0), (4, 0, 0)}
