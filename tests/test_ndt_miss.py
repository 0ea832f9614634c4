"""The NDT miss model (Saarinen et al., IJRR 2013, eqs. 22-24) against a float64 reference,
ray by ray and cell by cell, and on hand-computable cases."""

import math

import numpy as np
import pytest
from conftest import DATA
from reference import (
    ETA,
    NDT_BACK_MISS,
    NDT_COV_FLOOR,
    NDT_ERASED_NEIGHBOURS,
    NDT_FRESH_FLOOR,
    NDT_LINE,
    NDT_LINE_FLOOR,
    NDT_LINE_POINTS,
    NDT_RESET,
    NDT_RESTART,
    NDT_RESTART_CLEAR,
    NDT_SPARSE_SIGMA,
    NDT_WIDE,
    ndt_cov_floor,
    ndt_miss_term,
    ndt_om_logodds,
)
from test_core import BLOCKS, set_block

from ndtom_ti import MapConfig, NdtOmMap

# the record's bit layout (not a documented value of the model)
from ndtom_ti.kernels.ndt import NBR_BACK, NBR_COUNT, NBR_FRESH

NDT = dict(miss_model="ndt")
HAND = dict(miss_model="ndt", sigma_s=3.0)  # hand cases: sigma_s fixed, whatever the cell
FLOORS = (NDT_COV_FLOOR, NDT_LINE, NDT_LINE_FLOOR, NDT_LINE_POINTS)


def sigma_s(res: float) -> float:
    """The default config's sigma_s on a map of this resolution."""
    return MapConfig().sigma_s_at(res)


L_HIT = math.log(0.6 / 0.4)
L_FREE = math.log(0.49 / 0.51)


def insert_world(m, origin, world, block_cells=None):
    """Insert world points seen from ``origin`` (identity rotation)."""
    set_block(m, block_cells)
    T = np.eye(4)
    T[:3, 3] = origin
    m.insert_scan(np.asarray(world, np.float64) - origin, T)


def logodds_of(m) -> dict:
    k = m.known_cells()
    return {tuple(c): v for c, v in zip(k["index"].tolist(), k["logodds"])}


def assert_matches(m, ref_lo, ref_pts, atol=2e-6):
    got = logodds_of(m)
    assert set(got) == set(ref_lo), (
        f"cells differ: missing {list(set(ref_lo) - set(got))[:5]}, extra {list(set(got) - set(ref_lo))[:5]}"
    )
    worst = max(abs(got[c] - v) for c, v in ref_lo.items())
    assert worst <= atol, f"worst log-odds difference {worst:.2e}"
    g = m.gaussians(min_points=1, min_probability=0.0)
    assert {tuple(c): int(n) for c, n in zip(g["index"].tolist(), g["n"])} == {c: len(p) for c, p in ref_pts.items()}


def ndt_state(m, cell) -> int:
    """The cell's Gaussian record state as a snapshot holds it: 1 fresh, 2 back (0: none)."""
    s = m.snapshot()
    return dict(zip(map(tuple, s.g_index.tolist()), s.g_ndt_state.tolist())).get(cell, 0)


def points_of(m, cell) -> int:
    """Points the cell's Gaussian holds, occupied or not (0: none)."""
    g = m.gaussians(min_points=1, min_probability=0.0)
    return dict(zip(map(tuple, g["index"].tolist()), g["n"].tolist())).get(cell, 0)


def blob(rng, centre, n=40, sd=(0.02, 0.02, 0.02)):
    return np.asarray(centre) + rng.normal(size=(n, 3)) * sd


# --------------------------------------------------------------------------- hand cases


def test_ray_through_the_mean_far_from_its_endpoint(rng):
    """x_ML is the mean itself: p(x_ML|N) = 1, p(x_ML|z) ~ 0: l falls by logit(0.5 - eta)."""
    res = 0.5
    m = NdtOmMap(res, config=MapConfig(**HAND, logodds_min=-100, logodds_max=100))
    pts = blob(rng, (2.25, 0.25, 0.25))
    insert_world(m, np.array([0.25, 0.25, 0.25]), pts)
    g = m.gaussians()
    mu = g["mean"][0]
    before = logodds_of(m)[(4, 0, 0)]
    assert before == pytest.approx(NDT_RESTART + 40 * L_HIT, rel=1e-6)
    # From below the cell, through the mean, to an endpoint 30 m past it.
    o = mu - np.array([0.0, 0.0, 3.0])
    insert_world(m, o, [mu + np.array([0.0, 0.0, 30.0])])
    after = logodds_of(m)[(4, 0, 0)]
    assert after - before == pytest.approx(math.log((0.5 - ETA) / (0.5 + ETA)), abs=1e-5)
    # eta = 0.2 (ohm's): -0.8473 per ray.
    m2 = NdtOmMap(res, config=MapConfig(**NDT, eta=0.2, sigma_s=0.05, logodds_min=-100, logodds_max=100))
    insert_world(m2, np.array([0.25, 0.25, 0.25]), pts)
    insert_world(m2, o, [mu + np.array([0.0, 0.0, 30.0])])
    assert logodds_of(m2)[(4, 0, 0)] - before == pytest.approx(-0.8473, abs=1e-4)


def test_ray_passing_a_flat_gaussian_a_few_sigma_above_its_plane(rng):
    """A floor Gaussian (flat in z) and a ray parallel to it h above its mean: x_ML lies
    straight above the mean, p(x_ML|N) = exp(-h^2 / (2 s_z^2)) with the floored variance."""
    res = 0.5
    m = NdtOmMap(res, config=MapConfig(**HAND))  # clamped at 2: f32 log-odds exact to 2e-7
    xy = rng.uniform(0.02, 0.48, size=(200, 2))
    z = 0.2 + rng.normal(size=200) * 0.01
    pts = np.column_stack([xy, z]) + [5.0, 0.0, 0.0]
    insert_world(m, np.array([5.25, 0.25, 3.0]), pts)
    g = m.gaussians()
    assert len(g["n"]) == 1
    mu, C = g["mean"][0], g["cov"][0]
    h = 3.0 * math.sqrt(C[2, 2] + ndt_cov_floor(C, g["n"][0], *FLOORS))
    before = logodds_of(m)[(10, 0, 0)]
    # Along x through the cell, h above the mean, endpoint far beyond.
    o = mu + np.array([-4.0, 0.0, h])
    insert_world(m, o, [mu + np.array([6.0, 0.0, h])])
    after = logodds_of(m)[(10, 0, 0)]
    expected = ndt_miss_term(o, mu + np.array([6.0, 0.0, h]), True, mu, C, ETA, HAND["sigma_s"], g["n"][0])
    assert after - before == pytest.approx(expected, abs=2e-6)
    # A few sigma above: small evidence, far from the paper's constant rate per ray.
    assert -0.05 < expected < 0.0
    # The same ray through the plane's mean height, ending far past it (p(x_ML|z) ~ 0),
    # takes the strong update.
    o2, z2 = mu + np.array([-4.0, 0.0, 0.0]), mu + np.array([16.0, 0.0, 0.0])
    insert_world(m, o2, [z2])
    strong = ndt_miss_term(o2, z2, True, mu, C, ETA, HAND["sigma_s"], g["n"][0])
    assert logodds_of(m)[(10, 0, 0)] - after == pytest.approx(strong, abs=2e-6)
    assert strong < 0.95 * math.log((0.5 - ETA) / (0.5 + ETA))  # near the strongest a ray gives


def test_ray_ending_inside_the_cell_takes_the_hit_update_only(rng):
    res = 0.5
    m = NdtOmMap(res, config=MapConfig(**HAND, logodds_min=-100, logodds_max=100))
    pts = blob(rng, (2.25, 0.25, 0.25))
    insert_world(m, np.array([0.25, 0.25, 0.25]), pts)
    before = logodds_of(m)[(4, 0, 0)]
    # One ray ends in the cell, another passes through its mean from the same origin.
    o = np.array([2.25, 0.25, -3.0])
    insert_world(m, o, [[2.25, 0.25, 0.2], [2.25, 0.25, 4.0]])
    assert logodds_of(m)[(4, 0, 0)] - before == pytest.approx(L_HIT, abs=1e-6)


def test_cell_with_fewer_than_min_points_takes_the_model_with_the_prior(rng):
    """2 < min_points points: their mean and covariance plus NDT_SPARSE_SIGMA^2 on every
    axis. A ray through their mean clears them; one passing 0.24 m beside barely does."""
    res = 0.5
    m = NdtOmMap(res, config=MapConfig(**HAND, logodds_min=-100, logodds_max=100))
    pts = np.array([[2.25, 0.25, 0.2], [2.25, 0.25, 0.3]])
    insert_world(m, np.array([0.25, 0.25, 0.25]), pts)
    before = logodds_of(m)[(4, 0, 0)]
    mu = pts.mean(axis=0)
    d = pts - mu
    C = d.T @ d + NDT_SPARSE_SIGMA**2 * np.eye(3)
    o, z = np.array([2.25, 0.25, -3.0]), np.array([2.25, 0.25, 4.0])
    insert_world(m, o, [z] * 3)
    through = ndt_miss_term(o, z, True, mu, C, ETA, HAND["sigma_s"], 2)
    assert logodds_of(m)[(4, 0, 0)] - before == pytest.approx(3 * through, abs=2e-6)
    assert through < 10 * L_FREE  # far stronger than the count update's -0.04 a ray
    beside = ndt_miss_term(o + [0.24, 0.0, 0.0], z + [0.24, 0.0, 0.0], True, mu, C, ETA, HAND["sigma_s"], 2)
    assert 0.01 * through < beside < 0.0


def test_first_points_of_a_cell_restart_from_the_restart_level(rng):
    """Misses that a cell took while it held no points tested no surface: its first points
    start from NDT_RESTART (NDT miss model); the paper's model keeps the sum."""
    res = 0.5
    for model, start in (("ndt", NDT_RESTART), ("paper", 20 * L_FREE)):
        m = NdtOmMap(res, config=MapConfig(miss_model=model, logodds_min=-100, logodds_max=100))
        insert_world(m, np.array([2.25, 0.25, -3.0]), [[2.25, 0.25, 4.0]] * 20)  # 20 rays pass (4, 0, 0)
        assert logodds_of(m)[(4, 0, 0)] == pytest.approx(20 * L_FREE, abs=1e-5)
        insert_world(m, np.array([0.25, 0.25, 0.25]), [[2.2, 0.2, 0.2]])
        assert logodds_of(m)[(4, 0, 0)] == pytest.approx(start + L_HIT, abs=1e-5)


def test_first_points_where_rays_held_the_cell_at_the_free_clamp_restart_lower(rng):
    """A cell that rays had held at the free clamp (an aisle an object crosses) takes its
    first points from NDT_RESTART_CLEAR: two points leave it free. A cell that stopped short
    of the clamp restarts from NDT_RESTART, as does a cell at the clamp that holds points
    (test_a_lowered_gaussian_keeps_its_points_until_the_reset_threshold)."""
    res = 0.5
    origin, far = np.array([2.25, 0.25, -3.0]), [[2.25, 0.25, 4.0]]
    hit_from = np.array([0.25, 0.25, 0.25])
    for passes, start in ((60, NDT_RESTART_CLEAR), (20, NDT_RESTART)):
        m = NdtOmMap(res, config=MapConfig(**NDT))
        insert_world(m, origin, far * passes)  # 60 x -0.04 reaches the clamp (-2), 20 do not
        assert logodds_of(m)[(4, 0, 0)] == pytest.approx(max(passes * L_FREE, -2.0), abs=1e-5)
        insert_world(m, hit_from, [[2.2, 0.2, 0.2], [2.3, 0.3, 0.3]])
        assert logodds_of(m)[(4, 0, 0)] == pytest.approx(min(start + 2 * L_HIT, 2.0), abs=1e-5)
        ref, _ = ndt_om_logodds(
            [(origin, np.array(far * passes)), (hit_from, np.array([[2.2, 0.2, 0.2], [2.3, 0.3, 0.3]]))],
            res,
            miss_model="ndt",
        )
        assert logodds_of(m)[(4, 0, 0)] == pytest.approx(ref[(4, 0, 0)], abs=2e-6)
    # At the clamp, the two points are kept but free (-0.19): not reported as a Gaussian.
    m = NdtOmMap(res, config=MapConfig(**NDT))
    insert_world(m, origin, far * 60)
    insert_world(m, hit_from, [[2.2, 0.2, 0.2], [2.3, 0.3, 0.3]])
    assert points_of(m, (4, 0, 0)) == 2
    assert (4, 0, 0) not in set(map(tuple, m.gaussians(min_points=1)["index"].tolist()))


def test_a_fresh_cell_adds_its_next_hits_to_its_free_past(rng):
    """A cell whose first points came where rays had held it at the free clamp is fresh:
    its next hits add to max(l, NDT_FRESH_FLOOR) instead of restarting from NDT_RESTART (an
    object seen in two looks as it crossed an aisle stays weakly occupied), until it reaches
    the clamp. A later hit after rays made it free brings it back from NDT_RESTART."""
    res = 0.5
    origin, far = np.array([2.25, 0.25, -3.0]), [[2.25, 0.25, 4.0]]
    hit_from = np.array([0.25, 0.25, 0.25])
    m = NdtOmMap(res, config=MapConfig(**HAND))
    scans = [(origin, np.array(far * 60))]  # the free clamp
    want = [NDT_RESTART_CLEAR + L_HIT, NDT_FRESH_FLOOR + 2 * L_HIT, 2.0]
    looks = [blob(rng, (2.25, 0.25, 0.25), n=k, sd=(0.05, 0.05, 0.05)) for k in (1, 2, 4)]
    insert_world(m, *scans[0])
    for pts, lo, fresh in zip(looks, want, (True, True, False)):  # at the clamp: fresh no more
        insert_world(m, hit_from, pts)
        scans.append((hit_from, pts))
        assert logodds_of(m)[(4, 0, 0)] == pytest.approx(lo, abs=1e-5)
        assert ndt_state(m, (4, 0, 0)) == (1 if fresh else 0)
    # Two rays through the mean make the cell free; the next hit restarts it from NDT_RESTART.
    mu = m.gaussians()["mean"][0]
    for pts in ([mu + [0.0, 0.0, 30.0]] * 2, [[2.3, 0.3, 0.3]]):
        o = mu - [0.0, 0.0, 3.0] if len(pts) == 2 else hit_from
        insert_world(m, o, pts)
        scans.append((o, np.asarray(pts)))
    assert logodds_of(m)[(4, 0, 0)] == pytest.approx(2.0, abs=1e-6) and ndt_state(m, (4, 0, 0)) == 2
    ref, ref_pts = ndt_om_logodds(scans, res, eta=ETA, sigma_s=3.0)
    assert_matches(m, ref, ref_pts, atol=2e-6)
    # Without the free past the same looks restart from NDT_RESTART at once.
    m = NdtOmMap(res, config=MapConfig(**HAND))
    insert_world(m, hit_from, looks[0])
    assert logodds_of(m)[(4, 0, 0)] == pytest.approx(2.0, abs=1e-6)


def test_a_gaussian_brought_back_counts_its_misses_half_and_keeps_its_points(rng):
    """A hit on a Gaussian whose cell rays had made free (a board seen between the rings)
    marks it as back: from then on its misses count NDT_BACK_MISS of their sum, and rays no
    longer erase its points (past NDT_RESET, down to the clamp), so its next hit brings it
    back with them."""
    res = 0.5
    step = math.log((0.5 - ETA) / (0.5 + ETA))  # a ray through the mean, far from its endpoint
    hit_from = np.array([0.25, 0.25, 0.25])
    m = NdtOmMap(res, config=MapConfig(**HAND))
    scans = []

    def look(o, pts):
        insert_world(m, o, pts)
        scans.append((np.asarray(o, np.float64), np.asarray(pts, np.float64)))

    def through_mean(k):
        mu = m.gaussians(min_probability=0.0)["mean"][0]
        look(mu - [0.0, 0.0, 3.0], [mu + [0.0, 0.0, 30.0]] * k)

    look(hit_from, blob(rng, (2.25, 0.25, 0.25), n=4))
    through_mean(2)
    assert logodds_of(m)[(4, 0, 0)] == pytest.approx(2.0 + 2 * step, abs=1e-5)  # free, points kept
    assert ndt_state(m, (4, 0, 0)) == 0
    look(hit_from, [[2.3, 0.3, 0.3]])
    assert ndt_state(m, (4, 0, 0)) == 2 and logodds_of(m)[(4, 0, 0)] == pytest.approx(2.0, abs=1e-6)
    through_mean(2)
    assert logodds_of(m)[(4, 0, 0)] == pytest.approx(2.0 + NDT_BACK_MISS * 2 * step, abs=1e-4)
    through_mean(6)
    assert logodds_of(m)[(4, 0, 0)] == pytest.approx(-2.0, abs=1e-6)  # past NDT_RESET ...
    assert points_of(m, (4, 0, 0)) == 5  # ... its points stay
    look(hit_from, [[2.2, 0.2, 0.3]])
    assert logodds_of(m)[(4, 0, 0)] == pytest.approx(2.0, abs=1e-6)
    assert points_of(m, (4, 0, 0)) == 6
    ref, ref_pts = ndt_om_logodds(scans, res, eta=ETA, sigma_s=3.0)
    assert_matches(m, ref, ref_pts, atol=2e-5)


def test_a_lowered_gaussian_keeps_its_points_until_the_reset_threshold(rng):
    """Rays that lower a Gaussian's cell to <= 0 make it free, but its points stay until
    the log-odds falls to <= NDT_RESET (logit 0.2); a hit then restarts the cell from
    NDT_RESTART (here past the clamp of 1) and merges into them. Below the threshold they are
    gone, and a hit starts a new Gaussian (here from NDT_RESTART_CLEAR: the rays took the
    cell to the free clamp)."""
    res = 0.5
    step = math.log((0.5 - ETA) / (0.5 + ETA))  # a ray through the mean, far from its endpoint
    for rays, kept in ((1, 4), (2, 0)):
        m = NdtOmMap(res, config=MapConfig(**HAND, logodds_max=1.0))
        insert_world(m, np.array([0.25, 0.25, 0.25]), blob(rng, (2.25, 0.25, 0.25), n=4))
        mu = m.gaussians()["mean"][0]
        o = mu - np.array([0.0, 0.0, 3.0])
        insert_world(m, o, [mu + np.array([0.0, 0.0, 30.0])] * rays)
        lo = logodds_of(m)[(4, 0, 0)]
        assert lo == pytest.approx(max(1.0 + rays * step, -2.0), abs=1e-5)
        assert lo <= 0.0 and (lo > NDT_RESET) == (kept > 0)
        assert len(m.gaussians()["n"]) == 0 and len(m) == 0  # free either way
        assert points_of(m, (4, 0, 0)) == kept
        insert_world(m, np.array([0.25, 0.25, 0.25]), [[2.3, 0.3, 0.3]])
        assert lo > -2.0 or kept == 0  # (the second case reaches the clamp)
        want = 1.0 if kept else NDT_RESTART_CLEAR + L_HIT
        assert logodds_of(m)[(4, 0, 0)] == pytest.approx(want, abs=1e-6)
        assert points_of(m, (4, 0, 0)) == kept + 1
    # The paper's model erases at 0: one point left after the same two steps.
    m = NdtOmMap(res, config=MapConfig(miss_model="paper", p_empty=0.2))
    insert_world(m, np.array([0.25, 0.25, 0.25]), blob(rng, (2.25, 0.25, 0.25), n=4))
    insert_world(m, np.array([2.25, 0.25, -3.0]), [[2.25, 0.25, 4.0]] * 2)
    assert logodds_of(m)[(4, 0, 0)] == pytest.approx(4 * L_HIT + 2 * math.log(0.25), abs=1e-5)
    insert_world(m, np.array([0.25, 0.25, 0.25]), [[2.3, 0.3, 0.3]])
    assert points_of(m, (4, 0, 0)) == 1


def test_a_gaussian_whose_neighbours_were_erased_stands_for_its_whole_cell(rng):
    """Once NDT_ERASED_NEIGHBOURS of the 26 neighbouring cells' Gaussians were erased by
    rays, a ray through any part of the cell tests as one through its mean; its next points
    end that. One neighbour fewer leaves the ray 40 cm from the points without effect."""
    res = 0.5
    below, far = np.array([0.0, 0.0, -3.0]), np.array([0.0, 0.0, 30.0])
    corner = (2.05, 0.05, 0.05)  # the points of cell (4, 0, 0), in one corner
    side = [(2.25 + 0.5 * dx, 0.25 + 0.5 * dy, 0.25) for dx in (-1, 0, 1) for dy in (-1, 1)]
    step = math.log((0.5 - ETA) / (0.5 + ETA))
    for erased in (NDT_ERASED_NEIGHBOURS - 1, NDT_ERASED_NEIGHBOURS):
        m = NdtOmMap(res, config=MapConfig(**HAND))
        scans = []

        def look(o, world):
            insert_world(m, o, world)
            scans.append((np.asarray(o, float), np.asarray(world, float)))

        for centre in [corner, *side]:
            look(np.asarray(centre) + below, blob(rng, centre, n=5, sd=(0.01, 0.01, 0.01)))
        g = {tuple(c): mu for c, mu in zip(m.gaussians()["index"].tolist(), m.gaussians()["mean"])}
        for centre in side[:erased]:
            mu = g[tuple(np.floor(np.asarray(centre) / res).astype(int).tolist())]
            look(mu + below, [mu + far] * 3)  # 2 - 3 x 1.5: erased
        near = m.gaussians()["index"][:, 2] == 0  # (the rays' endpoints far above hold points too)
        assert points_of(m, (4, 0, 0)) == 5 and near.sum() == 7 - erased
        through = np.array([2.45, 0.45, 0.25])  # 40 cm from the points, through the cell
        before = logodds_of(m)[(4, 0, 0)]
        look(through + below, [through + far])
        change = logodds_of(m)[(4, 0, 0)] - before
        if erased < NDT_ERASED_NEIGHBOURS:
            assert abs(change) < 1e-6
        else:
            assert change == pytest.approx(step, abs=1e-5)
            look(np.asarray(corner) + below, [np.asarray(corner)])  # its next point
            before = logodds_of(m)[(4, 0, 0)]
            look(through + below, [through + far])
            assert abs(logodds_of(m)[(4, 0, 0)] - before) < 1e-6
        ref_lo, ref_pts = ndt_om_logodds(scans, res, eta=ETA, sigma_s=3.0)
        assert_matches(m, ref_lo, ref_pts)


def test_a_hit_ray_tests_no_gaussian_in_its_last_cells(rng):
    """A hit ray does not test the Gaussians of the cells within near_cells_at (L1) of its
    endpoint's cell (sigma_s 3 m at 0.5 m: 2 cells): through the mean, ending 2 cells
    further up, nothing; ending 3 cells up, the model's term."""
    res = 0.5
    cfg = MapConfig(**HAND)
    assert cfg.near_cells_at(res) == 2
    for up, tested in ((2, False), (3, True)):
        m = NdtOmMap(res, config=cfg)
        pts = blob(rng, (2.25, 0.25, 0.25), sd=(0.05, 0.05, 0.05))
        insert_world(m, np.array([0.25, 0.25, 0.25]), pts)
        mu = m.gaussians()["mean"][0]
        o, z = mu - np.array([0.0, 0.0, 3.0]), np.array([mu[0], mu[1], 0.5 * up + 0.25])
        before = logodds_of(m)[(4, 0, 0)]
        insert_world(m, o, [z])
        change = logodds_of(m)[(4, 0, 0)] - before
        g = m.gaussians(min_points=1, min_probability=0.0)
        term = ndt_miss_term(o, z, True, mu, g["cov"][0], ETA, 3.0, int(g["n"][0]))
        assert change == pytest.approx(term if tested else 0.0, abs=1e-6)
        assert term < -0.03 and (abs(change) > 0.03) == tested  # (the skipped term is not negligible)
        ref_lo, ref_pts = ndt_om_logodds(
            [(np.array([0.25, 0.25, 0.25]), pts), (o, np.array([z]))], res, eta=ETA, sigma_s=3.0
        )
        assert_matches(m, ref_lo, ref_pts)


def test_coarsening_leaves_out_the_points_of_free_cells(rng):
    """A free cell whose Gaussian keeps its points (above NDT_RESET) adds nothing to the
    coarser cell's Gaussian, in the map and in its snapshot."""
    res = 0.5
    m = NdtOmMap(res, config=MapConfig(**HAND, logodds_max=1.0))
    insert_world(m, np.array([0.25, 0.25, 0.25]), blob(rng, (2.25, 0.25, 0.25), n=4))  # cell (4, 0, 0)
    mu = m.gaussians()["mean"][0]
    insert_world(m, mu - np.array([0.0, 0.0, 3.0]), [mu + np.array([0.0, 0.0, 30.0])])
    assert points_of(m, (4, 0, 0)) == 4 and logodds_of(m)[(4, 0, 0)] <= 0.0
    kept = blob(rng, (2.75, 0.25, 0.25), n=6)  # cell (5, 0, 0): same parent at factor 2
    insert_world(m, np.array([2.75, 0.25, 3.0]), kept)
    assert points_of(m, (4, 0, 0)) == 4
    for c in (m.coarsen(2), m.snapshot().coarsen(2)):
        g = c.gaussians(min_points=1, min_probability=0.0)
        row = g["index"].tolist().index([2, 0, 0])
        assert g["n"][row] == 6
        np.testing.assert_allclose(g["mean"][row], kept.mean(axis=0), atol=1e-9)


def test_a_line_that_stays_a_line_as_points_join_it_is_widened_less(rng):
    """A line-like Gaussian is widened toward the surface one scan line samples, by
    min(1, NDT_LINE_POINTS / n) of the amount: a ray passing 12 cm beside a line of 4 points
    lowers it; beside the same line sampled by 40 points (a shelf's edge) it barely does."""
    res = 0.5
    terms = {}
    for n in (4, 40):
        m = NdtOmMap(res, config=MapConfig(**HAND))
        x = np.linspace(2.05, 2.45, n)
        pts = np.column_stack([x, 0.25 + rng.normal(size=n) * 0.002, 0.25 + rng.normal(size=n) * 0.002])
        insert_world(m, np.array([2.25, 0.25, 3.0]), pts)
        g = m.gaussians(min_points=1, min_probability=0.0)
        mu, C = g["mean"][0], g["cov"][0]
        before = logodds_of(m)[(4, 0, 0)]
        o, z = np.array([2.25, -3.0, 0.37]), np.array([2.25, 30.0, 0.37])  # across the line, 12 cm above
        insert_world(m, o, [z])
        terms[n] = logodds_of(m)[(4, 0, 0)] - before
        # (to 2e-6, as every reference comparison: the line's eigenvalues are exact in f64)
        assert terms[n] == pytest.approx(ndt_miss_term(o, z, True, mu, C, ETA, HAND["sigma_s"], n), abs=2e-6)
    assert terms[4] < -0.5 and -0.05 < terms[40] < 0.0


def test_sigma_s_defaults_to_fifteen_cells(rng, tmp_path):
    """Left to the map, sigma_s is 15 of its cells, at least 1.5 m: the same map as that
    number of metres given, another with the 0.2 m map's 3 m; it stays unset through a map
    file."""
    assert MapConfig().sigma_s is None and MapConfig(sigma_s=0.05).sigma_s_at(0.1) == 0.05
    assert [MapConfig().sigma_s_at(r) for r in (0.05, 0.1, 0.2, 0.4)] == pytest.approx([1.5, 1.5, 3.0, 6.0])
    scans = random_scans(rng, n_scans=2)
    logs = {}
    free = dict(max_range=6.0, max_range_mode="free")
    for name, cfg in (
        ("default", MapConfig(**NDT, **free)),
        ("1.5", MapConfig(**NDT, **free, sigma_s=1.5)),
        ("3", MapConfig(**NDT, **free, sigma_s=3.0)),
    ):
        m = build(scans, 0.1, cfg)
        logs[name] = m.known_cells()["logodds"]
        if name == "default":
            assert NdtOmMap.load(m.save(tmp_path / "m.ndtom")).config.sigma_s is None
    assert np.array_equal(logs["default"], logs["1.5"]) and not np.array_equal(logs["default"], logs["3"])
    # At 0.05 m the floor: 1.5 m, not 15 cells (0.75 m).
    fine = {
        ss: build(scans, 0.05, MapConfig(**NDT, **free, sigma_s=ss)).known_cells()["logodds"]
        for ss in (None, 1.5, 0.75)
    }
    assert np.array_equal(fine[None], fine[1.5]) and not np.array_equal(fine[None], fine[0.75])
    ref_lo, ref_pts = ndt_om_logodds(reference_scans(scans, 6.0), 0.1, eta=ETA, sigma_s=1.5)
    assert_matches(build(scans, 0.1, MapConfig(**NDT, **free)), ref_lo, ref_pts)
    with pytest.raises(ValueError, match="sigma_s must be a positive number of metres"):
        MapConfig(sigma_s=0.0)


def test_paper_model_keeps_eq12_for_gaussian_cells(rng):
    res = 0.5
    m = NdtOmMap(res, config=MapConfig(miss_model="paper", logodds_min=-100, logodds_max=100))
    insert_world(m, np.array([0.25, 0.25, 0.25]), blob(rng, (2.25, 0.25, 0.25)))
    before = logodds_of(m)[(4, 0, 0)]
    insert_world(m, np.array([2.25, 0.25, -3.0]), [[2.25, 0.25, 4.0]] * 5)
    assert logodds_of(m)[(4, 0, 0)] - before == pytest.approx(5 * L_FREE, abs=1e-6)


def test_the_ndt_miss_model_is_the_default(rng):
    assert MapConfig().miss_model == "ndt"
    scans = random_scans(rng, n_scans=3)
    kw = dict(max_range=6.0)
    default = logodds_of(build(scans, 0.5, MapConfig(**kw)))
    assert default == logodds_of(build(scans, 0.5, MapConfig(miss_model="ndt", **kw)))
    assert default != logodds_of(build(scans, 0.5, MapConfig(miss_model="paper", **kw)))


# --------------------------------------------------------------------------- references


def random_scans(rng, n_scans=5, n=500):
    """Scans of a noisy wall and blobs, from origins around them: many rays pass cells
    that hold Gaussians, at all angles; free rays too."""
    scans = []
    for k in range(n_scans):
        o = rng.uniform(-1.0, 1.0, 3)
        wall = np.column_stack(
            [np.full(n, 4.0) + rng.normal(size=n) * 0.03, rng.uniform(-3, 3, n), rng.uniform(-1, 2, n)]
        )
        blobs = rng.normal(size=(n // 2, 3)) * 0.15 + rng.choice([[2.0, 0.5, 0.3], [2.5, -1.0, 0.0]], n // 2)
        ends = np.concatenate([wall, blobs])
        hit = rng.uniform(size=len(ends)) > 0.1
        scans.append((o, ends, hit))
    return scans


def build(scans, res, cfg, block_cells=None):
    m = NdtOmMap(res, config=cfg)
    for o, ends, hit in scans:
        set_block(m, block_cells)
        T = np.eye(4)
        T[:3, 3] = o
        # Free rays: beyond max_range, carved up to it (their endpoint cell is passed).
        local = ends - o
        local[~hit] *= (cfg.max_range * 1.5) / np.linalg.norm(local[~hit], axis=1, keepdims=True)
        m.insert_scan(local, T)
    return m


def reference_scans(scans, max_range):
    """What the map makes of ``build``'s scans: every ray past max_range (the free ones,
    and hits that far) is a free ray clipped there."""
    out = []
    for o, ends, hit in scans:
        e = ends.copy()
        far = ~hit | (np.linalg.norm(e - o, axis=1) > max_range)
        d = e[far] - o
        e[far] = o + d * (max_range / np.linalg.norm(d, axis=1, keepdims=True))
        out.append((o, e, ~far))
    return out


@pytest.mark.parametrize("block_cells", BLOCKS)
def test_logodds_match_the_float64_reference_in_every_ray_path(rng, block_cells):
    """Every touched cell's log-odds and every Gaussian's N after 5 scans, through the
    dense block (flagged or not, u16 or i32), a block split with the tree, and the tree."""
    res = 0.25
    cfg = MapConfig(**NDT, max_range=6.0, max_range_mode="free")
    scans = random_scans(rng)
    m = build(scans, res, cfg, block_cells)
    ref_lo, ref_pts = ndt_om_logodds(reference_scans(scans, 6.0), res, eta=ETA, sigma_s=sigma_s(res))
    assert_matches(m, ref_lo, ref_pts)
    # The scans test the model: the paper's eq. (12) gives other log-odds.
    paper, _ = ndt_om_logodds(reference_scans(scans, 6.0), res, miss_model="paper")
    assert sum(abs(paper.get(c, 0.0) - v) > 0.1 for c, v in ref_lo.items()) > 20


def test_batched_tracing_matches_the_reference(rng):
    """Under memory pressure the rays are traced in batches through the tree only."""
    res = 0.25
    cfg = MapConfig(**NDT, max_range=6.0, max_range_mode="free")
    scans = random_scans(rng, n_scans=3)
    m = NdtOmMap(res, config=cfg)
    m.plan.one_pass = False
    batches = []
    for o, ends, hit in reference_scans(scans, 6.0):
        T = np.eye(4)
        T[:3, 3] = o
        local = ends - o
        local[~hit] *= 1.5
        batches.append(m.insert_scan(local, T).ray_batches)
    assert min(batches) >= 1  # batched every time
    ref_lo, ref_pts = ndt_om_logodds(reference_scans(scans, 6.0), res, eta=ETA, sigma_s=sigma_s(res))
    assert_matches(m, ref_lo, ref_pts)


def test_result_does_not_depend_on_thread_order(rng):
    """Integer sums: two maps of the same scans are bit-identical."""
    scans = random_scans(rng, n_scans=3, n=2000)
    cfg = MapConfig(**NDT, max_range=6.0, max_range_mode="free")
    a, b = build(scans, 0.2, cfg), build(scans, 0.2, cfg)
    ka, kb = a.known_cells(), b.known_cells()
    assert np.array_equal(ka["index"], kb["index"]) and np.array_equal(ka["logodds"], kb["logodds"])


def test_synthetic_lidar_scans_match_the_reference(sim_hall_dynamic):
    """Hall scans with moving objects (subsampled: the reference is pure Python)."""
    sim = sim_hall_dynamic
    res = 0.4
    rng = np.random.default_rng(7)
    m = NdtOmMap(res, config=MapConfig(**NDT))
    scans = []
    for i in range(0, 12, 2):
        world = sim.scan(i, frame="world")
        world = world[rng.choice(len(world), 1500, replace=False)]
        o = sim.origin(i)
        insert_world(m, o, world)
        scans.append((o, world))
    ref_lo, ref_pts = ndt_om_logodds(scans, res, eta=ETA, sigma_s=sigma_s(res))
    assert_matches(m, ref_lo, ref_pts, atol=5e-6)


def test_synthetic_scans_where_objects_left_match_the_reference(sim_hall_dynamic):
    """All 24 hall scans at 0.3 m: objects leave, Gaussians beside the erased ones come to
    stand for their whole cells (NDT_ERASED_NEIGHBOURS), and records turn fresh and back
    (NBR_FRESH, NBR_BACK)."""
    sim = sim_hall_dynamic
    res = 0.3
    rng = np.random.default_rng(7)
    m = NdtOmMap(res, config=MapConfig(**NDT))
    scans = []
    for i in range(24):
        world = sim.scan(i, frame="world")
        world = world[rng.choice(len(world), 2000, replace=False)]
        o = sim.origin(i)
        insert_world(m, o, world)
        scans.append((o, world))
    rec = m._slot.records  # private: the records' neighbour state and inverse covariances are not in state()
    state, alive = rec.nbr[: rec.count], rec.n[: rec.count] > 0
    wide = ((state & NBR_COUNT) >= NDT_ERASED_NEIGHBOURS) & alive
    assert wide.any() and (rec.icov[: rec.count][wide][:, [0, 3, 5]] == NDT_WIDE).all()
    # Both record states occur here (fresh Gaussians and ones brought back), and match too.
    assert ((state & NBR_FRESH) != 0).any() and ((state & NBR_BACK) != 0).any()
    ref_lo, ref_pts = ndt_om_logodds(scans, res, eta=ETA, sigma_s=sigma_s(res))
    assert_matches(m, ref_lo, ref_pts, atol=5e-6)


@pytest.mark.skipif(not (DATA / "balm_hall_every4").exists(), reason="shared data not found")
def test_real_lidar_scans_match_the_reference():
    from ndtom_ti.io import open_recording

    rec = open_recording(DATA / "balm_hall_every4")
    rng = np.random.default_rng(3)
    res = 0.5
    m = NdtOmMap(res, config=MapConfig(**NDT))
    scans = []
    for k, scan in enumerate(rec.scans()):
        if k == 3:
            break
        p = scan.points[np.isfinite(scan.points).all(axis=1)]
        p = p[rng.choice(len(p), 1500, replace=False)].astype(np.float64)
        T = scan.T_world_sensor
        m.insert_scan(p, T)
        scans.append((T[:3, 3].copy(), p @ T[:3, :3].T + T[:3, 3]))
    ref_lo, ref_pts = ndt_om_logodds(scans, res, eta=ETA, sigma_s=sigma_s(res))
    assert_matches(m, ref_lo, ref_pts, atol=5e-6)


def test_a_map_loaded_where_objects_left_continues_as_the_one_saved(sim_hall_dynamic, tmp_path):
    """The counts of erased neighbours and the record states travel in the file
    (g_erased_near, g_ndt_state): a loaded map's wide, fresh and brought-back Gaussians
    take rays and hits as the saved map's do."""
    sim = sim_hall_dynamic
    rng = np.random.default_rng(7)
    scans = []
    for i in range(24):
        world = sim.scan(i, frame="world")
        scans.append((sim.origin(i), world[rng.choice(len(world), 2000, replace=False)]))
    a = NdtOmMap(0.3, config=MapConfig(**NDT))
    for o, world in scans[:20]:
        insert_world(a, o, world)
    s = a.snapshot()
    assert (s.g_erased_near >= NDT_ERASED_NEIGHBOURS).any()
    assert (s.g_ndt_state == 1).any() and (s.g_ndt_state == 2).any()
    b = NdtOmMap.load(a.save(tmp_path / "a.ndtom"))
    assert np.array_equal(b.snapshot().g_erased_near, s.g_erased_near)
    assert np.array_equal(b.snapshot().g_ndt_state, s.g_ndt_state)
    for m in (a, b):
        for o, world in scans[20:]:
            insert_world(m, o, world)
    ka, kb = a.known_cells(), b.known_cells()
    assert np.array_equal(ka["index"], kb["index"]) and np.array_equal(ka["logodds"], kb["logodds"])


def test_a_loaded_map_continues_as_the_one_saved(rng, tmp_path):
    """The inverse covariances the rays read are rebuilt on load: the next scan gives the
    same map whether or not it went through a file."""
    scans = random_scans(rng, n_scans=3)
    cfg = MapConfig(**NDT, max_range=6.0, max_range_mode="free")
    a = build(scans[:2], 0.25, cfg)
    b = NdtOmMap.load(a.save(tmp_path / "a.ndtom"))
    assert b.config.miss_model == "ndt"
    for m in (a, b):
        o, ends, hit = scans[2]
        T = np.eye(4)
        T[:3, 3] = o
        local = ends - o
        local[~hit] *= 9.0 / np.linalg.norm(local[~hit], axis=1, keepdims=True)
        m.insert_scan(local, T)
    ka, kb = a.known_cells(), b.known_cells()
    assert np.array_equal(ka["index"], kb["index"]) and np.array_equal(ka["logodds"], kb["logodds"])
    ref_lo, _ = ndt_om_logodds(reference_scans(scans, 6.0), 0.25, eta=ETA, sigma_s=sigma_s(0.25))
    assert_matches(b, ref_lo, ndt_om_logodds(reference_scans(scans, 6.0), 0.25, eta=ETA, sigma_s=sigma_s(0.25))[1])
