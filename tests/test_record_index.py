"""The NDT miss model reads, each scan, only the Gaussian records whose cells may lie in the
scan's dense block (ndtom_ti/record_index.py): the records it picks must hold every record
in the box, each once, whatever merge and the rays did to the records since; and a map
whose scans read records by place is the map that reads them all, bit for bit."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ndtom_ti import MapConfig, NdtOmMap
from ndtom_ti.kernels.ndt import U16_MAX_RAYS
from ndtom_ti.record_index import RecordIndex

GLO, GHI = np.array([-64, -64, -16]), np.array([64, 64, 16])


def read(pick, npick, tail0, count):
    """The record numbers a kernel reads for pick's answer."""
    return np.concatenate([pick[:npick], np.arange(tail0, count)])


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_picked_records_hold_the_box_once(data):
    """Random records handed out, erased onto the free stack, taken from it to new cells,
    and boxes queried between (the index brought up to date at some, as often as it may):
    what is read holds every record with points in the box, no record twice, none past
    the count."""
    from ndtom_ti import record_index

    seed = data.draw(st.integers(0, 2**32 - 1))
    update_min = data.draw(st.sampled_from([0, 50, 4096]))
    rng = np.random.default_rng(seed)
    cap = 4000
    cell = np.zeros((cap, 3), np.int32)
    n = np.zeros(cap, np.int32)
    free: list[int] = []
    count = 0
    ix = RecordIndex(GLO, GHI)

    def new_cell():
        return rng.integers(GLO, GHI)

    for _ in range(data.draw(st.integers(1, 20))):
        op = data.draw(st.sampled_from(["add", "erase", "take", "update", "query", "query"]))
        if op == "add":
            k = int(rng.integers(1, 400))
            k = min(k, cap - count)
            cell[count : count + k] = rng.integers(GLO, GHI, (k, 3))
            n[count : count + k] = rng.integers(1, 9, k)
            count += k
        elif op == "erase" and count:
            live = np.flatnonzero(n[:count] > 0)
            gone = rng.choice(live, size=min(len(live), int(rng.integers(1, 300))), replace=False) if len(live) else []
            n[gone] = 0
            free.extend(int(r) for r in gone)
        elif op == "take" and free:
            k = int(rng.integers(1, len(free) + 1))
            taken = np.array(free[-k:], np.int32)
            del free[-k:]
            for r in taken:
                cell[r] = new_cell()
                n[r] = int(rng.integers(1, 9))
            ix.note_taken(taken[::-1].copy())
        elif op == "update":
            ix.update(cell, n, count)
        else:
            lo = rng.integers(GLO, GHI)
            live = np.flatnonzero(n[:count] > 0)
            if len(live) and rng.random() < 0.7:  # a box around a record, most of the time
                lo = np.maximum(cell[rng.choice(live)] - rng.integers(0, 20, 3), GLO)
            hi = np.minimum(lo + rng.integers(0, 40, 3), GHI - 1)
            saved, record_index.UPDATE_MIN = record_index.UPDATE_MIN, update_min
            try:
                got = read(*ix.pick(lo, hi, cell, n, count, min_records=0), count)
            finally:
                record_index.UPDATE_MIN = saved
            assert len(np.unique(got)) == len(got), "a record read twice"
            assert (got < count).all()
            inside = np.flatnonzero((n[:count] > 0) & (cell[:count] >= lo).all(1) & (cell[:count] <= hi).all(1))
            assert np.isin(inside, got).all(), "a record in the box not read"


def test_small_maps_and_wide_boxes_read_every_record():
    cell = np.random.default_rng(1).integers(GLO, GHI, (5000, 3)).astype(np.int32)
    n = np.ones(5000, np.int32)
    ix = RecordIndex(GLO, GHI)
    assert ix.pick(GLO, GLO + 4, cell, n, 5000, min_records=10_000)[1:] == (0, 0)  # small: all
    assert ix.pick(GLO, GHI - 1, cell, n, 5000, min_records=0)[1:] == (0, 0)  # the whole grid: all
    pick, npick, tail0 = ix.pick(GLO, GLO + 4, cell, n, 5000, min_records=0)
    assert 0 < npick < 100 and tail0 == 5000 and ix.partial == 1


def corridor(scans: int, rng):
    """A sensor driving along a 3 m wide corridor, its range cut at 8 m (the dense block
    holds a stretch of the map), and an object in front of it every few scans that later
    rays clear (Gaussians erased: their records go back to merge)."""
    out = []
    for s in range(scans):
        ang = rng.uniform(-np.pi, np.pi, 4000)
        el = rng.uniform(-0.3, 0.3, 4000)
        r = np.minimum(1.5 / np.maximum(np.abs(np.sin(ang)), 1e-3), 12.0)
        pts = np.stack([r * np.cos(ang) * np.cos(el), r * np.sin(ang) * np.cos(el), r * np.sin(el)], 1)
        if s % 5 < 2:
            pts[:400] = np.array([2.0, 0.0, 0.0]) + rng.normal(scale=0.3, size=(400, 3))
        T = np.eye(4)
        T[:3, 3] = [2.5 * s, 0.0, 0.0]
        out.append((pts, T))
    return out


@pytest.mark.parametrize("plan", [{}, {"u16_rays": U16_MAX_RAYS}])
def test_records_read_by_place_give_the_same_map(plan):
    scans = corridor(24, np.random.default_rng(7))
    maps = []
    for by_place in (True, False):
        m = NdtOmMap(0.2, config=MapConfig(max_range=8.0))
        m.plan.index_records = 0 if by_place else 2**31 - 1
        for k, v in plan.items():
            setattr(m.plan, k, v)
        reps = [m.insert_scan(p, T) for p, T in scans]
        maps.append((m, [(r.cells_hit, r.cells_passed, r.gaussians_erased) for r in reps]))
    (a, ra), (b, rb) = maps
    ix = a._slot.records.index
    assert ix.partial > 5 and ix.moves > 0  # boxes of part of the map; records taken to new cells
    assert sum(e for _, _, e in ra) > 0
    assert ra == rb
    ka, kb = a.known_cells(), b.known_cells()
    np.testing.assert_array_equal(ka["index"], kb["index"])
    np.testing.assert_array_equal(ka["logodds"].view(np.uint32), kb["logodds"].view(np.uint32))
    ga, gb = a.gaussians(min_probability=0), b.gaussians(min_probability=0)
    for key in ("index", "n", "mean", "cov"):
        np.testing.assert_array_equal(ga[key], gb[key])


@pytest.mark.parametrize("reserved", [True, False])
def test_records_grow_keeping_what_they_hold(monkeypatch, reserved):
    """Records grow in place where address space was reserved (Linux: longer views of the
    same memory, nothing copied: copying millions of records made a scan wait for seconds),
    and by copying where it was not; either way they keep what they hold."""
    import sys

    from ndtom_ti import records

    if not reserved:
        monkeypatch.setattr(records._Space, "reserve", classmethod(lambda cls, capacity, ndt: None))
    r = records.GaussianRecords(True)
    r.n[:5], r.cell[:5], r.icov[:5] = 7, [[1, 2, 3]], 0.5
    r.free[:2] = [3, 4]
    r.count, r.nfree = 5, 2
    before = r.icov
    r.grow(300_000)
    assert r.capacity == 300_000 and r.icov.shape == (300_000, 9) and r.cell.shape == (300_000, 3)
    assert (r.n[:5] == 7).all() and (r.cell[:5] == [1, 2, 3]).all() and (r.icov[:5] == 0.5).all()
    assert not r.n[5:].any() and not r.icov[5:].any() and list(r.free[:2]) == [3, 4]
    assert np.shares_memory(before, r.icov) == (reserved and sys.platform.startswith("linux"))
