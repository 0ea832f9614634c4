"""The map's updates against float64 references: RCU exactness, DDA, eq. (12), erasure."""

import math

import numpy as np
import pytest
from ndtom_ti.kernels.args import Bound
from ndtom_ti.kernels.ndt import U16_MAX_RAYS
from reference import batch_stats, eq12_logodds, ray_cells, ray_pass_counts

from ndtom_ti import MapConfig, NdtOmMap

WIDE = dict(miss_model="paper", logodds_min=-1e6, logodds_max=1e6)  # eq. (12), clamps out of the way
EQ12 = MapConfig(miss_model="paper")  # the paper's eq. (12) for every cell (these tests check it)


def random_pose(rng, t):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    T = np.eye(4)
    T[:3, :3] = q
    T[:3, 3] = t
    return T


def to_world(pts, T):
    return np.asarray(pts, np.float64) @ T[:3, :3].T + T[:3, 3]


def assert_matches_batch(m, world, cov_rtol=1e-5, mean_atol=1e-6):
    """Every cell's N, mean and covariance equal the batch estimate of all its points."""
    g = m.gaussians(min_points=1, min_probability=0.0)
    ref = batch_stats(world, m.resolution)
    assert np.array_equal(g["index"], ref["index"])
    assert np.array_equal(g["n"], ref["n"])
    np.testing.assert_allclose(g["mean"], ref["mean"], rtol=0, atol=mean_atol)
    scale = np.maximum(np.abs(ref["cov"]).max(axis=(1, 2)), 1e-12)
    err = np.abs(g["cov"] - ref["cov"]).max(axis=(1, 2)) / scale
    assert err.max() <= cov_rtol, f"worst relative covariance error {err.max():.2e}"


def rcu_map(res, occupancy):
    """Recursive NDT, or NDT-OM whose rays count in the dense block (endpoints too) but
    whose free-space updates are too weak to erase any Gaussian."""
    if not occupancy:
        return NdtOmMap(res, occupancy=False)
    return NdtOmMap(res, config=MapConfig(miss_model="paper", p_empty=0.4999999))


@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (1000.0, -1000.0, 20.0)])
@pytest.mark.parametrize("res", [0.2, 0.5])
@pytest.mark.parametrize("occupancy", [False, True])
def test_rcu_equals_batch_random_scans(rng, offset, res, occupancy):
    m = rcu_map(res, occupancy)
    world = []
    for k in range(6):
        T = random_pose(rng, np.asarray(offset) + rng.normal(size=3))
        # Clustered points so cells receive points from several scans.
        pts = (rng.normal(size=(4000, 3)) * [2.0, 2.0, 0.5] + rng.normal(size=3)).astype(np.float32)
        rep = m.insert_scan(pts, T)
        assert rep.points_used == len(pts)
        world.append(to_world(pts, T))
        assert_matches_batch(m, np.concatenate(world))


@pytest.mark.parametrize("occupancy", [False, True])
def test_rcu_equals_batch_on_lidar_scans(sim_hall_scans, occupancy):
    """Real-shaped lidar scans (thin walls, 57k points each), far from the origin too."""
    scans = sim_hall_scans
    m = rcu_map(0.4, occupancy)
    world = []
    for pts, T in scans:
        m.insert_scan(pts, T)
        world.append(to_world(pts, T))
    assert_matches_batch(m, np.concatenate(world))


@pytest.fixture(scope="module")
def sim_hall_scans(sim_hall_dynamic):
    d = sim_hall_dynamic
    return [(d.scan(i), d.poses[i]) for i in range(0, 6, 2)]


def test_n_is_an_integer_count_past_float32_range():
    """N counts exactly where a float32 counter would stall (2^24)."""
    m = NdtOmMap(1.0, occupancy=False)
    pts = np.full((1 << 20, 3), 0.5, np.float32)
    pts[:, 0] += np.linspace(-0.4, 0.4, len(pts), dtype=np.float32)
    for _ in range(17):
        m.insert_scan(pts, np.eye(4))
    g = m.gaussians()
    assert g["n"].tolist() == [17 << 20]


# --------------------------------------------------------------------------- DDA


def single_scan_logodds(res, origin, endpoints, block_cells=None):
    """Insert one scan of world ``endpoints`` seen from ``origin``; return the map, its
    log-odds per cell, and the world endpoints exactly as the map computed them."""
    T = np.eye(4)
    T[:3, 3] = origin
    m = NdtOmMap(res, config=MapConfig(**WIDE))
    set_block(m, block_cells)
    local = np.asarray(endpoints, np.float64) - origin
    m.insert_scan(local, T)
    k = m.known_cells()
    return m, {tuple(c): v for c, v in zip(k["index"].tolist(), k["logodds"])}, to_world(local, T)


def assert_logodds_equal(got, ref):
    assert set(got) == set(ref), (
        f"cells differ: missing {list(set(ref) - set(got))[:5]}, extra {list(set(got) - set(ref))[:5]}"
    )
    for c, v in ref.items():
        assert got[c] == pytest.approx(v, rel=1e-5, abs=1e-6), c


# Ray counts go to a dense block over the scan's cells, trimmed to ``block_cells`` around
# the sensor, and to the sparse tree past it: whole block (rows flagged as rays enter
# them, or all rows read as after a dense scan; i32 counts, or u16 as UpdatePlan.u16_rays
# allows), split, tree only.
BLOCKS = [None, "unflagged", "u16", "u16 unflagged", 8**3 * 27, 0]


def set_block(m, block_cells):
    if isinstance(block_cells, str):
        if "unflagged" in block_cells:
            m.plan.row_flags = "never"
        if "u16" in block_cells:
            m.plan.u16_rays = U16_MAX_RAYS
    elif block_cells is not None:
        m.plan.block_cells = block_cells


def interrupt_kernels(monkeypatch, *names):
    """Make the update kernels ``names`` raise KeyboardInterrupt (Ctrl-C between kernels)."""
    call = Bound.__call__

    def maybe_interrupt(self, **kw):
        if self.name in names:
            raise KeyboardInterrupt
        return call(self, **kw)

    monkeypatch.setattr(Bound, "__call__", maybe_interrupt)


def records_made(m):
    """Records handed out so far: in use or on the free stack."""
    rep = m.memory_report()
    return rep["records_in_use"] + rep["records_free"]


@pytest.mark.parametrize("block_cells", BLOCKS)
def test_dda_matches_reference_on_thousands_of_random_rays(rng, block_cells):
    res = 0.2
    for origin in ([0.1, 0.2, 0.3], [-3.37, 5.01, -0.77]):
        origin = np.asarray(origin)
        ends = origin + rng.normal(size=(3000, 3)) * 4.0
        m, got, world = single_scan_logodds(res, origin, ends, block_cells)
        assert_logodds_equal(got, eq12_logodds([(origin, world)], res, **WIDE_REF))
        rep = m.insert_scan(ends - origin, m_pose(origin))
        assert rep.cells_passed == sum(v < 0 for v in got.values())  # free-space updates, both paths
        assert rep.ray_cell_visits == sum(ray_pass_counts(origin, world, res).values())


def test_long_rays_far_from_the_origin_match_the_reference(rng):
    """Thousands of steps per ray, 1 km out, and rational slopes from a cell corner (exact
    ties recurring along the ray): the summed crossings decide as division would."""
    res = 0.1
    far = np.array([1000.03, -1000.07, 20.01])
    ends = far + rng.normal(size=(150, 3)) * [120.0, 120.0, 5.0]
    _, got, world = single_scan_logodds(res, far, ends)
    assert_logodds_equal(got, eq12_logodds([(far, world)], res, **WIDE_REF))
    # Cells of 0.25 m make these plane crossings exact in floating point, so the ties are
    # true ties for both the kernel and the reference (edges and corners every few steps).
    corner = np.array([0.0, 0.0, 0.0])
    ends = np.array([[300.0, 100.0, 0.0], [-150.0, 150.0, 50.0], [240.0, -80.0, 40.0], [-96.0, -32.0, -128.0]])
    _, got, world = single_scan_logodds(0.25, corner, ends)
    assert_logodds_equal(got, eq12_logodds([(corner, world)], 0.25, **WIDE_REF))


def m_pose(origin):
    T = np.eye(4)
    T[:3, 3] = origin
    return T


WIDE_REF = dict(l_min=-1e6, l_max=1e6)


def test_dda_visits_exactly_the_reference_cells_per_ray(rng):
    """One ray per map, compared cell for cell, including degenerate rays."""
    r = 0.25
    rays = [
        ([0.1, 0.1, 0.1], [3.1, 0.1, 0.1]),  # axis-aligned +x
        ([0.1, 0.1, 0.1], [0.1, -3.1, 0.1]),  # axis-aligned -y
        ([0.1, 0.1, 0.1], [0.1, 0.1, 2.9]),  # axis-aligned +z
        ([0.1, 0.5, 0.3], [2.9, 0.5, 1.7]),  # along the face y = 2 r
        ([0.3, 0.5, 0.75], [-2.9, 0.5, 0.75]),  # along the edge y = 2 r, z = 3 r
        ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]),  # diagonal through cell corners
        ([0.5, 1.5, 0.5], [1.5, 0.5, 0.5]),  # +x -y through a corner
        ([1.5, 0.5, 0.5], [0.5, 1.5, 0.5]),  # -x +y through a corner
        ([-1.3, -2.7, -0.2], [-4.4, -0.3, -3.3]),  # negative coordinates
        ([0.7, 0.7, 0.7], [0.71, 0.69, 0.72]),  # inside one cell
        ([0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]),  # origin on a face, going down
    ]
    for _ in range(40):
        o = rng.uniform(-3, 3, 3)
        rays.append((o, o + rng.normal(size=3) * rng.uniform(0.1, 6.0)))
    for o, e in rays:
        o, e = np.asarray(o, float), np.asarray(e, float)
        _, got, world = single_scan_logodds(r, o, [e])
        cells = ray_cells(o, world[0], r)
        passes = {tuple(c) for c in cells[:-1].tolist()}
        le = math.log(0.49 / 0.51)
        lo = math.log(0.6 / 0.4)
        expect = {c: le for c in passes}
        expect[tuple(cells[-1].tolist())] = lo
        assert_logodds_equal(got, expect)
    # Zero length: (0, 0, 0) in the sensor frame is a beam with no return, not a hit.
    _, got, _ = single_scan_logodds(r, np.array([0.7, 0.7, 0.7]), [[0.7, 0.7, 0.7]])
    assert got == {}


def test_dda_free_rays_count_their_last_cell():
    """max_range_mode='free': rays past max_range carve free space up to max_range."""
    cfg = MapConfig(max_range=2.0, max_range_mode="free", **WIDE)
    m = NdtOmMap(0.5, config=cfg)
    rep = m.insert_scan(np.array([[10.0, 0.1, 0.1], [1.2, 0.1, 0.1]]), np.eye(4))
    assert (rep.points_used, rep.free_rays) == (1, 1)
    far = np.array([10.0, 0.1, 0.1])
    ends = np.array([far * (2.0 / np.sqrt(far @ far)), [1.2, 0.1, 0.1]])
    ref = eq12_logodds([(np.zeros(3), ends, np.array([False, True]))], 0.5, **WIDE_REF)
    k = m.known_cells()
    got = {tuple(c): v for c, v in zip(k["index"].tolist(), k["logodds"])}
    assert_logodds_equal(got, ref)


@pytest.mark.parametrize("model", ["paper", "ndt"])
def test_free_rays_give_one_map_whatever_the_block_holds(monkeypatch, model):
    """max_range_mode='free' with the dense block holding all, part or none of each scan:
    the same map, bit for bit. A free ray's last cell inside a block that held only part of
    the scan was counted in the tree while the other rays' visits of it counted in the
    block (eq. 12 applied twice; the NDT miss model moved cells by up to 4 in log-odds)."""
    from ndtom_ti import scan_update

    trace = scan_update.RayTracer.trace
    wholes = []

    def noting(self, mode, p):
        out = trace(self, mode, p)
        wholes.append(None if out is None else out[2])
        return out

    monkeypatch.setattr(scan_update.RayTracer, "trace", noting)

    def build(block_cells):
        rng = np.random.default_rng(3)
        m = NdtOmMap(0.2, config=MapConfig(max_range=6.0, max_range_mode="free", miss_model=model))
        if block_cells is not None:
            m.plan.block_cells = block_cells
        free = 0
        for s in range(4):
            T = np.eye(4)
            T[:3, 3] = [0.3 * s, 0.1 * s, 0.0]
            free += m.insert_scan(rng.normal(size=(12000, 3)) * [6.0, 6.0, 1.5], T).free_rays
        assert free > 0
        k = m.known_cells()
        order = np.lexsort(k["index"].T[::-1])
        return k["index"][order], k["logodds"][order]

    cells, lo = build(None)
    assert wholes == [True] * 4
    for block_cells in (8**3 * 216, 0):
        wholes.clear()
        got_cells, got_lo = build(block_cells)
        if block_cells:
            assert False in wholes  # the block held part of a scan
        np.testing.assert_array_equal(got_cells, cells)
        np.testing.assert_array_equal(got_lo.view(np.uint32), lo.view(np.uint32))


# --------------------------------------------------------------------------- eq. (12)


def test_occupancy_hand_computed_with_clamps():
    lo = math.log(0.6 / 0.4)
    le = math.log(0.49 / 0.51)
    m = NdtOmMap(1.0, config=EQ12)  # clamp [-2, 2]
    origin = np.array([0.5, 0.5, 0.5])
    T = np.eye(4)
    T[:3, 3] = origin
    ends = np.array([[5.5, 0.5, 0.5], [5.2, 0.7, 0.1], [5.9, 0.1, 0.9]]) - origin
    for s in range(1, 21):
        m.insert_scan(ends, T)
        p = m.occupancy(np.array([[5.5, 0.5, 0.5], [2.5, 0.5, 0.5], [0.5, 0.5, 0.5]]))
        l_hit = min(3 * lo * s, 2.0)
        l_pass = max(3 * le * s, -2.0)
        expect = [1 - 1 / (1 + math.exp(v)) for v in (l_hit, l_pass, l_pass)]
        np.testing.assert_allclose(p, expect, rtol=1e-5)
    k = m.known_cells()
    assert len(k["index"]) == 6
    assert sorted(k["logodds"].round(5).tolist()) == [-2.0] * 5 + [2.0]


@pytest.mark.parametrize("block_cells", BLOCKS)
def test_cell_both_hit_and_passed_takes_the_hit_update(block_cells):
    lo = math.log(0.6 / 0.4)
    le = math.log(0.49 / 0.51)
    m = NdtOmMap(1.0, config=EQ12)
    set_block(m, block_cells)
    T = np.eye(4)
    T[:3, 3] = [0.5, 0.5, 0.5]
    # Ray A ends in cell (2,0,0); ray B passes it and ends in (5,0,0).
    m.insert_scan(np.array([[2.0, 0.0, 0.0], [5.0, 0.0, 0.0]]), T)
    k = m.known_cells()
    got = {tuple(c): v for c, v in zip(k["index"].tolist(), k["logodds"])}
    assert got[(2, 0, 0)] == pytest.approx(lo, rel=1e-6)
    assert got[(5, 0, 0)] == pytest.approx(lo, rel=1e-6)
    assert got[(1, 0, 0)] == pytest.approx(2 * le, rel=1e-6)
    assert got[(3, 0, 0)] == pytest.approx(le, rel=1e-6)


def test_scan_of_more_rays_than_u16_counts_hold():
    # Every ray passes the sensor's cell: 65546 passes would wrap to 10 in 16 bits.
    m = NdtOmMap(1.0, config=EQ12)
    T = m_pose([0.5, 0.5, 0.5])
    d = np.random.default_rng(3).normal(size=(65546, 3))
    m.insert_scan(d / np.linalg.norm(d, axis=1, keepdims=True) * 6.0, T)
    assert m.occupancy(np.array([[0.5, 0.5, 0.5]]))[0] == pytest.approx(1 / (1 + math.exp(-m.config.logodds_min)))


def test_occupancy_of_unknown_cells_is_prior_and_flagged():
    m = NdtOmMap(0.5, config=EQ12)
    m.insert_scan(np.array([[3.0, 0.2, 0.2]]), np.eye(4))
    p, known = m.occupancy(
        np.array([[3.1, 0.1, 0.1], [1.0, 0.1, 0.1], [50.0, 50.0, 50.0], [np.nan, 0, 0]]), return_known=True
    )
    assert known.tolist() == [True, True, False, False]
    assert p[0] > 0.5 and p[1] < 0.5 and p[2] == 0.5 and p[3] == 0.5


@pytest.mark.parametrize("block_cells", BLOCKS)
def test_multi_scan_logodds_match_reference(rng, block_cells):
    """Several scans from different origins, clamps active: eq. (12) per scan exactly."""
    res = 0.3
    scans = []
    cfg = MapConfig(miss_model="paper", logodds_min=-0.5, logodds_max=1.0)
    m = NdtOmMap(res, config=cfg)
    for k in range(5):
        set_block(m, block_cells)  # the block's density is measured anew each scan
        o = rng.uniform(-1, 1, 3)
        ends = rng.normal(size=(600, 3)) * 2.0 + [3.0, 0.0, 0.0]
        T = np.eye(4)
        T[:3, 3] = o
        m.insert_scan(ends - o, T)
        scans.append((o, to_world(ends - o, T)))
    ref = eq12_logodds(scans, res, l_min=-0.5, l_max=1.0)
    k = m.known_cells()
    got = {tuple(c): v for c, v in zip(k["index"].tolist(), k["logodds"])}
    assert_logodds_equal(got, ref)


# --------------------------------------------------------------------------- erasure


@pytest.mark.parametrize("block_cells", [None, 0])
@pytest.mark.parametrize("reload", [False, True])
def test_gaussian_reset_when_logodds_falls_to_zero(block_cells, reload, tmp_path):
    m = NdtOmMap(1.0, config=EQ12)
    T = np.eye(4)
    T[:3, 3] = [0.5, 0.5, 0.5]
    wall = np.array([[5.5, 0.5, 0.5], [5.2, 0.6, 0.4], [5.7, 0.3, 0.6], [5.4, 0.4, 0.5]]) - T[:3, 3]
    m.insert_scan(wall, T)
    if reload:  # a loaded map knows which cells hold Gaussians too
        m = NdtOmMap.load(m.save(tmp_path / "wall.ndtom"))
    set_block(m, block_cells)
    assert m.gaussians()["index"].tolist() == [[5, 0, 0]]
    # The object leaves: rays now pass cell 5 and end in cell 9.
    far = np.array([[9.5, 0.5, 0.5]] * 10) - T[:3, 3]
    erased = 0
    scans = 0
    while m.gaussians(min_probability=0.0, min_points=1)["index"].tolist().count([5, 0, 0]):
        erased += m.insert_scan(far, T).gaussians_erased
        scans += 1
        assert scans < 20
    # l = 4 * 0.405 = 1.62; each scan subtracts 10 * 0.04 = 0.40 -> l <= 0 after 5 scans.
    assert scans == 5 and erased == 1
    assert m.occupancy(np.array([[5.5, 0.5, 0.5]]))[0] < 0.5
    # New points start a fresh Gaussian.
    m.insert_scan(np.array([[5.5, 0.5, 0.5]] * 3) - T[:3, 3] + [[0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0]], T)
    g = m.gaussians(min_probability=0.0)
    i = g["index"].tolist().index([5, 0, 0])
    assert g["n"][i] == 3
    np.testing.assert_allclose(g["mean"][i], [5.7, 0.5, 0.5], atol=1e-9)
    # It leaves again: the new Gaussian is erased too (the hit re-armed the cell).
    erased = scans = 0
    while m.gaussians(min_probability=0.0, min_points=1)["index"].tolist().count([5, 0, 0]):
        erased += m.insert_scan(far, T).gaussians_erased
        scans += 1
        assert scans < 20
    assert erased == 1 and m.occupancy(np.array([[5.5, 0.5, 0.5]]))[0] < 0.5


@pytest.mark.parametrize("block_cells", [None, 0])
def test_gaussian_erased_when_logodds_falls_to_exactly_zero(block_cells):
    """The boundary of eq. (12)'s reset, l <= 0, reached exactly: with p_o = 0.6 and p_e = 0.4
    (l_free = -l_hit) three hits then three rays through the cell leave l == 0, and the
    Gaussian goes (a reset at l < 0 only would keep it)."""
    m = NdtOmMap(1.0, config=MapConfig(p_occupied=0.6, p_empty=0.4, miss_model="paper"))
    set_block(m, block_cells)
    T = np.eye(4)
    T[:3, 3] = [0.5, 0.5, 0.5]
    m.insert_scan(np.array([[5.5, 0.5, 0.5], [5.2, 0.6, 0.4], [5.7, 0.3, 0.6]]) - T[:3, 3], T)
    assert m.gaussians(min_probability=0.0)["index"].tolist() == [[5, 0, 0]]
    rep = m.insert_scan(np.array([[9.5, 0.5, 0.5]] * 3) - T[:3, 3], T)  # three rays through cell 5
    assert m.logodds_at(np.array([[5, 0, 0]]))[0] == 0.0
    assert rep.gaussians_erased == 1
    assert [5, 0, 0] not in m.gaussians(min_probability=0.0, min_points=1)["index"].tolist()


@pytest.mark.parametrize("block_cells", [None, 0])
def test_records_of_erased_gaussians_are_reused(block_cells):
    """Objects that come and go do not grow the records: a new Gaussian takes an erased
    one's record, also when a scan brings more new cells than there are free records."""
    m = NdtOmMap(1.0, config=EQ12)
    set_block(m, block_cells)
    T = np.eye(4)
    T[:3, 3] = [0.5, 0.5, 0.5]
    far = np.array([[9.5, 0.5, 0.5]] * 10) - T[:3, 3]
    blob = np.array([[0.1, 0.0, 0.0], [0.2, 0.1, 0.0], [0.3, 0.0, 0.1]])
    for x in (5, 6, 7, 8):  # an object in cell x, then gone
        m.insert_scan(blob + [x, 0.0, 0.0], T)
        for _ in range(20):
            m.insert_scan(far, T)
            if [x, 0, 0] not in m.gaussians(min_probability=0.0)["index"].tolist():
                break
        else:
            raise AssertionError(f"the Gaussian of cell {x} was not erased")
        assert records_made(m) == 2  # cell 9's and the one reused by each object in turn
    # Five new cells at once, one free record: one takes it, four get new records.
    cells = np.array([[2, 2, 0], [2, -2, 0], [-2, 2, 0], [-2, -2, 0], [0, 3, 0]])
    m.insert_scan(np.repeat(cells + 0.5, 3, axis=0) + np.tile(blob, (5, 1)) * 0.5 - T[:3, 3], T)
    assert records_made(m) == 6
    g = m.gaussians(min_probability=0.0)
    got = {tuple(i): (n, mu) for i, n, mu in zip(g["index"].tolist(), g["n"].tolist(), g["mean"])}
    assert set(got) == {(9, 0, 0), *map(tuple, cells.tolist())}
    for c in cells:
        n, mu = got[tuple(c)]
        assert n == 3
        np.testing.assert_allclose(mu, c + 0.5 + blob.mean(axis=0) * 0.5, atol=1e-9)


@pytest.mark.parametrize("block_cells", [None, 0])
def test_records_grow_only_for_cells_that_need_one(block_cells):
    """The records held follow the Gaussians: a scan that hits many known cells and a few
    new ones grows them only when the new ones do not fit (by an eighth, or by the scan's
    hit cells); the cells that found no record are merged after the growth."""
    m = NdtOmMap(1.0, config=EQ12)
    set_block(m, block_cells)
    cap0 = m.memory_report()["records_held"]
    blob = np.array([[0.1, 0.0, 0.0], [0.2, 0.1, 0.0], [0.3, 0.0, 0.1]]) - 0.1
    # A wall of cells facing the sensor: every ray ends in its own cell.
    wall = np.array([[30, y, z] for y in range(-20, 20) for z in range(-13, 13)])
    wall = wall[: cap0 - 24]
    extra = np.array([[30, y, z] for y in range(20, 26) for z in range(-12, 12)])

    def scan(cells):
        return (np.repeat(cells + 0.5, 3, axis=0) + np.tile(blob, (len(cells), 1))).astype(np.float64)

    m.insert_scan(scan(wall), np.eye(4))
    m.insert_scan(scan(np.vstack([wall, extra[:20]])), np.eye(4))  # all known cells hit again
    assert (records_made(m), m.memory_report()["records_held"]) == (cap0 - 4, cap0)
    m.insert_scan(scan(np.vstack([wall, extra[20:60]])), np.eye(4))
    assert records_made(m) == cap0 + 36
    assert cap0 + 36 <= m.memory_report()["records_held"] <= cap0 + max(cap0 // 8, len(wall) + 40)
    g = m.gaussians(min_probability=0.0)
    got = dict(zip(map(tuple, g["index"].tolist()), g["n"].tolist()))
    assert got == {**{tuple(c): 9 for c in wall.tolist()}, **{tuple(c): 3 for c in extra[:60].tolist()}}
    np.testing.assert_allclose(g["mean"], g["index"] + 0.5 + blob.mean(axis=0), atol=1e-9)


def test_interrupt_after_merge_does_not_hand_out_a_record_twice(monkeypatch):
    """A record merge took from the free stack stays taken when the update is cut short
    after merge (Ctrl-C between kernels)."""
    m = NdtOmMap(1.0, config=EQ12)
    T = np.eye(4)
    T[:3, 3] = [0.5, 0.5, 0.5]
    blob = np.array([[0.1, 0.0, 0.0], [0.2, 0.1, 0.0], [0.3, 0.0, 0.1]])
    m.insert_scan(blob + [5.0, 0.0, 0.0], T)
    far = np.array([[9.5, 0.5, 0.5]] * 10) - T[:3, 3]
    while [5, 0, 0] in m.gaussians(min_probability=0.0)["index"].tolist():
        m.insert_scan(far, T)
    assert m.memory_report()["records_free"] == 1

    interrupt_kernels(monkeypatch, "block_apply")  # after merge took the free record for (0, 3, 0)
    with pytest.raises(KeyboardInterrupt):
        m.insert_scan(blob + [0.0, 3.0, -0.5], T)
    monkeypatch.undo()
    m.insert_scan(blob + [0.0, -3.0, -0.5], T)  # another new Gaussian: a new record
    g = m.gaussians(min_probability=0.0)
    got = {tuple(i): mu for i, mu in zip(g["index"].tolist(), g["mean"])}
    for c, shift in (([0, 3, 0], [0.0, 3.0, -0.5]), ([0, -3, 0], [0.0, -3.0, -0.5])):
        np.testing.assert_allclose(got[tuple(c)], blob.mean(axis=0) + shift + T[:3, 3], atol=1e-9)


def _in_box(pts, lo, hi, pad):
    return ((pts >= lo - pad) & (pts <= hi + pad)).all(axis=1)


def test_dynamic_object_erased_static_surfaces_kept(sim_hall_dynamic):
    d = sim_hall_dynamic
    names = [str(n) for n in d.dyn_names]
    j = names.index("pallet_removed")
    gone = int(np.argmin(d.dyn_present[:, j]))  # first scan without the pallet
    assert 0 < gone < d.n_scans - 6
    lo_b, hi_b = d.dyn_lo[0][j], d.dyn_hi[0][j]
    res = 0.2
    m = NdtOmMap(res, config=EQ12)
    counts = []
    for i in range(d.n_scans):
        m.insert_scan(d.scan(i), d.poses[i])
        g = m.gaussians()
        # The floor under the pallet becomes visible once it is gone: not the pallet's.
        inb = _in_box(g["mean"], lo_b, hi_b, 0.05) & (g["mean"][:, 2] > 0.2)
        counts.append(int(inb.sum()))
    assert counts[gone - 1] >= 50, counts
    assert counts[gone + 4] <= 0.05 * counts[gone - 1], counts
    assert max(counts[gone + 5 :]) == 0, counts
    # Static structure keeps its Gaussians: walls, pillars and racks seen in the last
    # scans still hold Gaussians where their points fall.
    static = np.concatenate(
        [d.scan(i, "world")[d.scan_labels(i) < d.n_static] for i in range(d.n_scans - 3, d.n_scans)]
    )
    cells, n = np.unique(np.floor(static / res).astype(np.int64), axis=0, return_counts=True)
    cells = cells[n >= 5]  # well observed: sparse far cells may hold fewer than 3 points
    g = m.gaussians()
    have = {tuple(c) for c in g["index"].tolist()}
    kept = np.mean([tuple(c) in have for c in cells.tolist()])
    assert kept > 0.95, kept
