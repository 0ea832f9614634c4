"""The settled box (kernels/trace.py settled_box): rays cross the sensor's surroundings where
every cell is at the free clamp with no Gaussian and no hit in one step. The map must be the
one the cell-by-cell traversal gives, bit for bit, on every path and model; only the report
moves visits into ``ray_cells_crossed``."""

import numpy as np
import pytest
from reference import eq12_logodds
from test_core import BLOCKS, set_block, to_world

from ndtom_ti import MapConfig, NdtOmMap
from ndtom_ti.cellstate import ARRAYS


def assert_same_snapshot(a: NdtOmMap, b: NdtOmMap) -> None:
    sa, sb = a.snapshot(), b.snapshot()
    diffs = [n for n in ARRAYS if not np.array_equal(getattr(sa, n), getattr(sb, n))]
    assert not diffs, f"arrays differ: {diffs}"


def pair(res: float, plan: dict | None = None, **kw) -> tuple[NdtOmMap, NdtOmMap]:
    """Two maps alike but for the settled box: (with it, without it)."""
    on, off = NdtOmMap(res, **kw), NdtOmMap(res, **kw)
    for k, v in (plan or {}).items():
        setattr(on.plan, k, v)
        setattr(off.plan, k, v)
    off.plan.settled_box = False
    return on, off


def insert_both(on: NdtOmMap, off: NdtOmMap, scans) -> tuple[int, int]:
    """Insert every scan in both maps; reports agree but for the visits the box crossed.
    Returns (visits without the box, steps it crossed)."""
    visits = crossed = 0
    for pts, T in scans:
        a, b = on.insert_scan(pts, T), off.insert_scan(pts, T)
        assert (a.cells_hit, a.gaussians_erased, a.points_used) == (b.cells_hit, b.gaussians_erased, b.points_used)
        assert b.ray_cells_crossed == 0
        # Random rays cross no cell corner exactly: each step crossed is a visit not made.
        assert a.ray_cell_visits + a.ray_cells_crossed == b.ray_cell_visits
        assert a.cells_passed <= b.cells_passed
        visits += b.ray_cell_visits
        crossed += a.ray_cells_crossed
    return visits, crossed


@pytest.fixture(scope="module")
def hall_scans(sim_hall_dynamic):
    d = sim_hall_dynamic
    return [(d.scan(i), d.poses[i]) for i in range(10)]


@pytest.mark.parametrize("model", ["paper", "ndt"])
@pytest.mark.parametrize(
    "plan",
    [{}, {"block_cells": 0}, {"one_pass": False}, {"u16_rays": 65533}, {"row_flags": "always"}],
    ids=["block", "tree", "batches", "u16", "flags"],
)
def test_the_settled_box_gives_the_map_of_the_full_traversal(hall_scans, model, plan):
    on, off = pair(0.4, plan, miss_model=model)
    visits, crossed = insert_both(on, off, hall_scans)
    assert crossed > 0.2 * visits, (crossed, visits)  # the box was there to cross
    assert_same_snapshot(on, off)


def test_the_settled_box_holds_only_cells_a_pass_leaves_as_they_are(hall_scans):
    """Every cell of a scan's eight boxes (one an octant around the sensor's cell) was at the
    free clamp before it, held no Gaussian and no endpoint of the scan; each box starts at the
    sensor's cell and lies within reach."""
    from ndtom_ti.kernels.trace import SETTLED_REACH

    m = NdtOmMap(0.2)
    l_min = np.float32(m.config.logodds_min)
    seen = 0
    for k, (pts, T) in enumerate(hall_scans):
        before = m.snapshot() if k else None
        m.insert_scan(pts, T)
        boxes = m._update.tracer.sbox.reshape(8, 6).astype(np.int64)
        if (boxes[:, :3] > boxes[:, 3:]).any():
            assert (boxes[:, :3] > boxes[:, 3:]).all()  # the sensor's cell: in all or none
            continue
        seen += 1
        assert before is not None  # an empty map has nothing settled
        ocell = np.floor(T[:3, 3] / m.resolution).astype(np.int64)
        known = {tuple(c): v for c, v in zip(before.occ_index.tolist(), before.occ_logodds)}
        hits = np.floor(to_world(pts, T) / m.resolution).astype(np.int64)
        for q, (lo, hi) in enumerate(zip(boxes[:, :3], boxes[:, 3:])):
            # Octant q reaches up from the sensor's cell on the axes of q's set bits, down on the others.
            up = np.array([q & 1, q & 2, q & 4]) > 0
            np.testing.assert_array_equal(np.where(up, lo, hi), ocell)
            assert (hi - lo <= SETTLED_REACH).all()
            g = np.mgrid[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1, lo[2] : hi[2] + 1].reshape(3, -1).T
            assert all(known.get(tuple(c), 0.0) <= l_min for c in g.tolist())
            inside = lambda c, lo=lo, hi=hi: ((c >= lo) & (c <= hi)).all(axis=1)
            assert not inside(before.g_index.astype(np.int64)).any()
            assert not inside(hits).any()
    assert seen >= len(hall_scans) - 2


@pytest.mark.parametrize("block_cells", BLOCKS)
def test_multi_scan_logodds_match_reference_across_the_settled_box(rng, block_cells):
    """Many scans from close origins (the cells around the sensor reach the clamp and the box
    grows): eq. (12) per scan exactly, as the float64 reference gives it."""
    res = 0.25
    cfg = MapConfig(miss_model="paper", logodds_min=-0.5, logodds_max=1.0)
    m = NdtOmMap(res, config=cfg)
    scans, crossed = [], 0
    for _ in range(8):
        set_block(m, block_cells)
        o = rng.uniform(-0.3, 0.3, 3)
        d = rng.normal(size=(800, 3))
        ends = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(2.0, 4.0, (800, 1))
        T = np.eye(4)
        T[:3, 3] = o
        crossed += m.insert_scan(ends, T).ray_cells_crossed
        scans.append((o, to_world(ends, T)))
    assert crossed > 0
    ref = eq12_logodds(scans, res, l_min=-0.5, l_max=1.0)
    k = m.known_cells()
    got = {tuple(c): float(v) for c, v in zip(k["index"].tolist(), k["logodds"])}
    assert got.keys() == ref.keys()
    np.testing.assert_allclose([got[c] for c in ref], [ref[c] for c in ref], rtol=0, atol=1e-5)


@pytest.mark.parametrize("model", ["paper", "ndt"])
def test_free_rays_that_end_in_the_box_and_hits_inside_its_reach(rng, model):
    """Rays past max_range carved as free rays that end within the settled box (the whole ray
    crossed at once), and an object that appears beside the sensor in settled space (its
    cells are held out of the box): the same map as without the box."""
    cfg = {"max_range": 1.2, "max_range_mode": "free"}
    on, off = pair(0.2, miss_model=model, **cfg)
    scans = []
    for s in range(8):
        d = rng.normal(size=(3000, 3))
        r = rng.uniform(0.5, 6.0, (3000, 1))
        pts = d / np.linalg.norm(d, axis=1, keepdims=True) * r
        if s >= 5:
            pts[:40] = [0.7, 0.1, 0.0] + rng.normal(size=(40, 3)) * 0.05  # a new object 0.7 m away
        T = np.eye(4)
        T[:3, 3] = [0.05 * s, 0.0, 0.0]
        scans.append((pts, T))
    _, crossed = insert_both(on, off, scans)
    assert crossed > 0
    assert_same_snapshot(on, off)


def test_rays_through_cell_corners_cross_the_box_as_they_step(rng):
    """A sensor on a cell corner and endpoints on cell corners: the rays' exits from the box
    tie with other faces' crossings; the traversal then steps as before (the same map)."""
    on, off = pair(0.5, miss_model="paper")
    T = np.eye(4)
    k = rng.integers(-12, 13, size=(4000, 3)).astype(np.float64)
    k = k[np.abs(k).sum(axis=1) > 6]
    pts = k * 0.5
    diag = np.repeat(rng.integers(3, 12, size=(400, 1)), 3, axis=1) * rng.choice([-0.5, 0.5], size=(400, 3))
    pts = np.concatenate([pts, diag])
    for _ in range(3):
        a, b = on.insert_scan(pts, T), off.insert_scan(pts, T)
        assert a.cells_hit == b.cells_hit
    assert on.insert_scan(pts, T).ray_cells_crossed > 0
    off.insert_scan(pts, T)
    assert_same_snapshot(on, off)


def test_the_settled_box_is_off_when_asked_and_takes_only_a_bool():
    m = NdtOmMap(0.2)
    m.plan.settled_box = False
    with pytest.raises(ValueError, match="settled_box"):
        m.plan.settled_box = 1
    pts = np.random.default_rng(3).normal(size=(2000, 3)) * 3
    for _ in range(4):
        assert m.insert_scan(pts, np.eye(4)).ray_cells_crossed == 0


# ---------------------------------------------------------------------------- random scenes
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


def room_scan(rng, origin, half, res, n, grid_frac, blob):
    """Endpoints of one scan from ``origin`` in a room of half-size ``half``: its walls,
    floor and ceiling, a share ``grid_frac`` of them snapped to cell corners (exits that tie
    with other faces), and ``blob`` points of an object near the sensor (hits in settled
    space)."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t = np.min(np.where(d != 0, (np.sign(d) * half - origin) / np.where(d != 0, d, 1.0), np.inf), axis=1)
    pts = origin + d * t[:, None] * rng.uniform(0.97, 1.0, (n, 1))
    k = int(grid_frac * n)
    pts[:k] = np.round(pts[:k] / res) * res
    if blob:
        pts[:blob] = origin + rng.uniform(0.4, 1.2, 3) * rng.choice([-1.0, 1.0], 3) + rng.normal(size=(blob, 3)) * 0.05
    return pts


def room_walk(rng, res, scans, speed, far, grid_frac, blob_at):
    """A sensor's walk through a random room: (endpoints in the sensor frame, pose) a scan,
    the sensor moving ``speed`` m a scan, every second pose on a cell corner, all of it
    ``far`` m from the grid's origin (less in z: the grid is flatter than wide), an object
    beside the sensor in scan ``blob_at``."""
    half = rng.uniform(3.0, 9.0, 3) * [1.0, 1.0, 0.4]
    o = rng.uniform(-0.3, 0.3, 3) * half
    heading = rng.normal(size=3) * [1.0, 1.0, 0.1]
    heading /= np.linalg.norm(heading)
    walk = []
    for s in range(scans):
        at = o + s * speed * heading
        if s % 2:
            at = np.round(at / res) * res  # the sensor on a cell corner
        pts = room_scan(rng, at, half, res, 3000, grid_frac, 60 if s == blob_at else 0)
        T = np.eye(4)
        T[:3, 3] = at + [far, -far, far / 50.0]
        walk.append((pts - at, T))
    return walk


def room_config(model, clamp, free_past=None) -> MapConfig:
    """The miss model, the free clamp (None: the default) and, with ``free_past``, rays past
    that range carved as free."""
    kw: dict = {"miss_model": model}
    if clamp is not None:
        kw["logodds_min"] = clamp
    if free_past is not None:
        kw.update(max_range=free_past, max_range_mode="free")
    return MapConfig(**kw)


def rooms(examples: int):
    """The property tests' settings: ``examples`` rooms, no deadline, no example database."""
    return settings(max_examples=examples, deadline=None, database=None, suppress_health_check=list(HealthCheck))


# What the property tests draw alike: a seed, the miss model, the free clamp (the default,
# or reached in one look) and the sensor's speed.
ROOM = {
    "seed": st.integers(0, 2**31 - 1),
    "model": st.sampled_from(["paper", "ndt"]),
    "clamp": st.sampled_from([None, -0.5]),
    "speed": st.sampled_from([0.0, 0.05, 0.3]),
}


@rooms(30)
@given(
    **ROOM,
    res=st.sampled_from([0.1, 0.2, 0.35, 0.5]),
    far=st.sampled_from([0.0, 731.3, -1201.7]),
    scans=st.integers(4, 8),
    grid_frac=st.sampled_from([0.0, 0.3, 1.0]),
    blob_at=st.integers(1, 8),
)
def test_random_rooms_give_the_map_of_the_full_traversal(
    seed, res, model, clamp, far, scans, speed, grid_frac, blob_at
):
    """Random rooms, sensor paths (also far from the grid's origin and on cell corners),
    resolutions, clamps and models: the settled box changes no array of the map."""
    walk = room_walk(np.random.default_rng(seed), res, scans, speed, far, grid_frac, blob_at)
    on, off = pair(res, config=room_config(model, clamp))
    try:
        crossed = insert_both_exact(on, off, walk)
        assert_same_snapshot(on, off)
        if clamp is not None and speed <= 0.05 and res <= 0.35:
            # A clamp reached in one look and a slow sensor: the box is there (in rooms a few
            # 0.5 m cells high a hit in the sensor's own 2^3-cell brick can hold every box back).
            assert crossed > 0
    finally:
        on.close()
        off.close()


def insert_both_exact(on: NdtOmMap, off: NdtOmMap, scans) -> int:
    """insert_both for scans whose rays may pass cell corners: a step through a corner
    moves two or three axes at one visit, so the box's steps crossed may exceed the visits
    they stand for. Returns the steps the box crossed."""
    crossed = 0
    for pts, T in scans:
        a, b = on.insert_scan(pts, T), off.insert_scan(pts, T)
        assert (a.cells_hit, a.gaussians_erased, a.points_used) == (b.cells_hit, b.gaussians_erased, b.points_used)
        assert a.ray_cell_visits <= b.ray_cell_visits <= a.ray_cell_visits + a.ray_cells_crossed
        crossed += a.ray_cells_crossed
    return crossed


PLANS = [{"block_cells": 0}, {"one_pass": False}, {"row_flags": "always"}, {"u16_rays": 0}, {"settled_box": False}]


@rooms(15)
@given(
    **ROOM,
    res=st.sampled_from([0.1, 0.2, 0.25, 0.35]),
    free_past=st.sampled_from([None, 3.0]),
    far=st.sampled_from([0.0, -613.9]),
    plan=st.sampled_from(PLANS),
)
def test_random_rooms_give_one_map_on_every_plan(seed, res, model, clamp, free_past, far, speed, plan):
    """The same random rooms through the default plan and another (the tree, batches, row
    flags, 32-bit counts, no settled box), with rays past max_range carved as free or not:
    one map."""
    walk = room_walk(np.random.default_rng(seed), res, 6, speed, far, 0.3, 3)
    cfg = room_config(model, clamp, free_past)
    a, b = NdtOmMap(res, config=cfg), NdtOmMap(res, config=cfg)
    try:
        for k, v in plan.items():
            setattr(b.plan, k, v)
        for pts, T in walk:
            ra, rb = a.insert_scan(pts, T), b.insert_scan(pts, T)
            assert (ra.cells_hit, ra.gaussians_erased) == (rb.cells_hit, rb.gaussians_erased)
        assert_same_snapshot(a, b)
    finally:
        a.close()
        b.close()
