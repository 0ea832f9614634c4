"""Map API: coarsen, save/load, bad input, memory budget, init, real recordings."""

import gc
import json
import os
import struct
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from conftest import DATA
from reference import batch_stats
from test_core import assert_matches_batch, interrupt_kernels, random_pose, to_world

import ndtom_ti
from ndtom_ti import MapConfig, MapFileError, MapMemoryError, NdtOmMap, NoFreeSlotError
from ndtom_ti import runtime
from ndtom_ti.kernels.layout import RECORD_BYTES
from ndtom_ti.scan_update import BLOCK_CELLS


def scene_scans(rng, scans=4):
    out = []
    for k in range(scans):
        T = random_pose(rng, rng.normal(size=3))
        out.append(((rng.normal(size=(3000, 3)) * [3.0, 2.0, 0.4] + [4.0, 0.0, 0.0]).astype(np.float32), T))
    return out


def build(res, scans, occupancy=True):
    m = NdtOmMap(res, occupancy=occupancy, metadata={"source": "test"})
    for pts, T in scans:
        m.insert_scan(pts, T)
    return m


def scene_map(rng, res=0.25, occupancy=True, scans=4):
    sc = scene_scans(rng, scans)
    return build(res, sc, occupancy), np.concatenate([to_world(p, T) for p, T in sc])


def state_equal(a, b, rounding=False):
    """The same state byte for byte; with ``rounding``, the Gaussians' float64 sums to rounding:
    a scan's points are summed per cell in the order threads reach them, so maps built apart
    may differ in the last bits."""
    sa, sb = a.state(), b.state()
    assert sa.keys() == sb.keys()
    for k in sa:
        assert sa[k].dtype == sb[k].dtype and sa[k].shape == sb[k].shape, k
        if rounding and sa[k].dtype == np.float64:
            np.testing.assert_allclose(sa[k], sb[k], rtol=1e-12, atol=1e-15, err_msg=k)
        else:
            assert sa[k].tobytes() == sb[k].tobytes(), k


# --------------------------------------------------------------------------- coarsen


@pytest.mark.parametrize("factor", [2, 3])
def test_coarsen_equals_direct_build(rng, factor):
    scans = scene_scans(rng)
    coarse = build(0.125, scans, occupancy=False).coarsen(factor)
    direct = build(0.125 * factor, scans, occupancy=False)
    assert coarse.resolution == direct.resolution
    gc_, gd = (x.gaussians(min_points=1, min_probability=0) for x in (coarse, direct))
    assert np.array_equal(gc_["index"], gd["index"]) and np.array_equal(gc_["n"], gd["n"])
    np.testing.assert_allclose(gc_["mean"], gd["mean"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(gc_["cov"], gd["cov"], rtol=1e-9, atol=1e-12)
    world = np.concatenate([to_world(p, T) for p, T in scans])
    assert_matches_batch(coarse, world, cov_rtol=1e-9, mean_atol=1e-9)


def test_coarsen_parent_logodds_is_max_of_children(rng):
    fine, _ = scene_map(rng, res=0.2, occupancy=True, scans=2)
    coarse = fine.coarsen(3)
    kf, kc = fine.known_cells(), coarse.known_cells()
    parents = np.floor_divide(kf["index"], 3)
    expect = {}
    for p, v in zip(map(tuple, parents.tolist()), kf["logodds"]):
        expect[p] = max(expect.get(p, -np.inf), v)
    got = dict(zip(map(tuple, kc["index"].tolist()), kc["logodds"]))
    assert got.keys() == expect.keys()
    for p, v in expect.items():
        assert got[p] == pytest.approx(v, abs=1e-7)


def test_coarsen_rejects_bad_factor(rng):
    m = NdtOmMap(0.5)
    for bad in (1, 0, -2, 2.5, "3", True):
        with pytest.raises(ValueError, match="factor"):
            m.coarsen(bad)


# --------------------------------------------------------------------------- save / load


def test_save_load_round_trip_is_bit_exact(rng, tmp_path):
    m, _ = scene_map(rng)
    path = m.save(tmp_path / "a.ndtom")
    m2 = NdtOmMap.load(path)
    state_equal(m, m2)
    assert (m2.resolution, m2.occupancy_enabled, m2.config) == (m.resolution, m.occupancy_enabled, m.config)
    assert m2.metadata == {"source": "test"} and m2.scans_inserted == m.scans_inserted
    # Both continue identically.
    T = random_pose(rng, [0.5, 0.2, 0.1])
    pts = rng.normal(size=(2000, 3)) * 3
    r1, r2 = m.insert_scan(pts, T), m2.insert_scan(pts, T)
    assert (r1.cells_hit, r1.cells_passed, r1.gaussians_erased) == (r2.cells_hit, r2.cells_passed, r2.gaussians_erased)
    state_equal(m, m2, rounding=True)


def test_save_is_atomic_and_keeps_the_old_file_on_failure(rng, tmp_path, monkeypatch):
    m, _ = scene_map(rng, scans=1)
    path = m.save(tmp_path / "map.ndtom")
    good = path.read_bytes()
    m.insert_scan(rng.normal(size=(100, 3)), np.eye(4))

    def boom(fd):
        raise OSError("disk full")

    monkeypatch.setattr("ndtom_ti.atomic.os.fsync", boom)
    with pytest.raises(OSError, match="disk full"):
        m.save(path)
    assert path.read_bytes() == good
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.ndtom"]


def test_save_to_missing_folder_is_clear(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        NdtOmMap(0.5).save(tmp_path / "nope" / "m.ndtom")


def _corrupt(data: bytes, kind: str) -> bytes:
    if kind == "empty":
        return b""
    if kind == "magic_only":
        return data[:5]
    if kind == "header_cut":
        return data[:30]
    if kind == "payload_cut":
        return data[:-7]
    if kind == "trailing":
        return data + b"\0"
    if kind == "flip_payload":
        b = bytearray(data)
        b[-3] ^= 0xFF
        return bytes(b)
    if kind == "flip_header":
        b = bytearray(data)
        b[25] = ord("#")
        return bytes(b)
    if kind == "foreign":
        return b"\x89PNG\r\n\x1a\n" + data[8:]
    if kind == "newer":
        return data[:8] + struct.pack("<I", 99) + data[12:]
    raise AssertionError(kind)


@pytest.mark.parametrize(
    "kind,message",
    [
        ("empty", "not an ndtom_ti map"),
        ("magic_only", "truncated"),
        ("header_cut", "truncated"),
        ("payload_cut", "truncated"),
        ("trailing", "trailing bytes"),
        ("flip_payload", "checksum"),
        ("flip_header", "corrupt"),
        ("foreign", "not an ndtom_ti map"),
        ("newer", "version 99"),
    ],
)
def test_broken_map_files_are_rejected_clearly(rng, tmp_path, kind, message):
    m, _ = scene_map(rng, scans=1)
    path = m.save(tmp_path / "m.ndtom")
    bad = tmp_path / "bad.ndtom"
    bad.write_bytes(_corrupt(path.read_bytes(), kind))
    with pytest.raises(MapFileError, match=message):
        NdtOmMap.load(bad)


def test_load_missing_file_and_folder(tmp_path):
    with pytest.raises(FileNotFoundError):
        NdtOmMap.load(tmp_path / "absent.ndtom")
    with pytest.raises(MapFileError, match="folder"):
        NdtOmMap.load(tmp_path)


def test_load_rejects_settings_that_do_not_validate(rng, tmp_path):
    m, _ = scene_map(rng, scans=1)
    data = m.save(tmp_path / "m.ndtom").read_bytes()
    hlen = struct.unpack("<Q", data[12:20])[0]
    header = json.loads(data[20 : 20 + hlen])
    header["config"]["p_occupied"] = 0.3
    header.pop("header_sha256")  # (a file from before the header's checksum)
    hb = json.dumps(header).encode()
    (tmp_path / "b.ndtom").write_bytes(data[:12] + struct.pack("<Q", len(hb)) + hb + data[20 + hlen :])
    with pytest.raises(MapFileError, match="p_occupied"):
        NdtOmMap.load(tmp_path / "b.ndtom")


# --------------------------------------------------------------------------- bad input


def test_nonfinite_out_of_range_and_outside_grid_points_are_counted(rng):
    m = NdtOmMap(0.5, config=MapConfig(min_range=0.5, max_range=30.0))
    pts = rng.normal(size=(100, 3)) * 3 + [5, 0, 0]
    pts[:5] = np.nan
    pts[5:8] = [np.inf, 0, 0]
    pts[8:10] = [0.1, 0.0, 0.0]  # closer than min_range
    pts[10:13] = [100.0, 0.0, 0.0]  # past max_range
    rep = m.insert_scan(pts, np.eye(4))
    assert (rep.dropped_nonfinite, rep.dropped_range, rep.points_used) == (8, 5, 87)
    # (0, 0, 0): a beam with no return (organised clouds, Livox), not a hit at the sensor;
    # with or without a min_range, and under any pose
    for cfg in (MapConfig(), MapConfig(min_range=0.5)):
        z = NdtOmMap(0.5, config=cfg)
        pts = np.concatenate([rng.normal(size=(50, 3)) + [5, 0, 0], np.zeros((20, 3))])
        T = np.eye(4)
        T[:3, 3] = [1.0, 2.0, 0.3]
        rep = z.insert_scan(pts, T)
        assert (rep.dropped_no_return, rep.dropped_range, rep.points_used) == (20, 0, 50)
        g = z.gaussians(min_points=1)
        assert np.linalg.norm(g["mean"] - T[:3, 3], axis=1).min() > 2.0
        assert z.occupancy(T[:3, 3]) < 0.5  # the sensor's own cell is not occupied
    far = NdtOmMap(0.001)  # grid of +-16 m at 1 mm
    rep = far.insert_scan(np.array([[1.0, 0, 0], [20.0, 0, 0], [-17.0, 0, 0]]), np.eye(4))
    assert (rep.dropped_outside_grid, rep.points_used) == (2, 1)


def test_empty_scans_and_float64_input(rng):
    m = NdtOmMap(0.3)
    rep = m.insert_scan(np.zeros((0, 3)), np.eye(4))
    assert rep.points_in == 0 and len(m.known_cells()["index"]) == m.known_cell_count() == 0
    pts = rng.normal(size=(500, 3)) + [3, 0, 0]
    a, b = NdtOmMap(0.3), NdtOmMap(0.3)
    a.insert_scan(pts.astype(np.float64), np.eye(4))
    b.insert_scan(pts.tolist(), np.eye(4).tolist())
    state_equal(a, b, rounding=True)


@pytest.mark.parametrize(
    "points,pose,exc,message",
    [
        (np.zeros((5, 2)), np.eye(4), ValueError, r"shape \(N, 3\)"),
        (np.zeros(3), np.eye(4), ValueError, r"shape \(N, 3\)"),
        (np.array([["a", "b", "c"]]), np.eye(4), TypeError, "numeric"),
        (np.zeros((2, 3), complex), np.eye(4), TypeError, "numeric"),
        (np.zeros((2, 3), bool), np.eye(4), TypeError, "booleans"),
        (np.ones((4, 3)), np.eye(3), ValueError, r"shape \(4, 4\)"),
        (np.ones((4, 3)), np.diag([2.0, 2.0, 2.0, 1.0]), ValueError, "not a rigid transform"),
        (np.ones((4, 3)), np.diag([1.0, 1.0, -1.0, 1.0]), ValueError, "not a rigid transform"),
        (np.ones((4, 3)), np.full((4, 4), np.nan), ValueError, "NaN"),
        (np.ones((4, 3)), np.vstack([np.eye(4)[:3], [0, 0, 1, 1]]), ValueError, "bottom row"),
    ],
)
def test_bad_input_raises_and_leaves_the_map_unchanged(rng, points, pose, exc, message):
    m, _ = scene_map(rng, scans=1)
    before = m.state()
    with pytest.raises(exc, match=message):
        m.insert_scan(points, pose)
    after = m.state()
    assert all(before[k].tobytes() == after[k].tobytes() for k in before)


def test_sensor_outside_grid_is_an_error():
    m = NdtOmMap(0.001)
    T = np.eye(4)
    T[0, 3] = 100.0
    with pytest.raises(ValueError, match="outside the map grid"):
        m.insert_scan(np.ones((3, 3)), T)


@pytest.mark.parametrize(
    "kwargs,message",
    [
        (dict(resolution=0.0), "positive"),
        (dict(resolution=float("nan")), "positive"),
        (dict(resolution="0.2"), "number"),
        (dict(resolution=0.2, p_occupied=0.4), "p_occupied"),
        (dict(resolution=0.2, p_empty=0.6), "p_empty"),
        (dict(resolution=0.2, logodds_min=1.0), "logodds_min"),
        (dict(resolution=0.2, max_range=-1.0), "max_range"),
        (dict(resolution=0.2, max_range_mode="clip"), "max_range_mode"),
        (dict(resolution=0.2, max_range_mode="free"), "finite max_range"),
        (dict(resolution=0.2, n_max=1), "n_max"),
        (dict(resolution=0.2, bogus=1), "bogus"),
    ],
)
def test_bad_options_are_clear(kwargs, message):
    with pytest.raises((ValueError, TypeError), match=message):
        NdtOmMap(**kwargs)


# --------------------------------------------------------------------------- API surface


def test_len_repr_and_memory_report(rng):
    m, _ = scene_map(rng, scans=2)
    g = m.gaussians()
    assert len(m) == len(g["n"]) > 0
    r = repr(m)
    assert r.startswith("NdtOmMap(resolution=0.25, occupancy=True, scans=2") and "MiB" in r
    rep = m.memory_report()
    assert rep["total_bytes"] == m.memory_bytes() > 0
    known = len(m.known_cells()["index"])
    assert rep["gaussians"] == len(m) and rep["known_cells"] == m.known_cell_count() == known > 0
    assert m.snapshot().known_cell_count() == known
    assert rep["bytes_per_gaussian"] > 0 and rep["process_pool_bytes"] <= rep["process_pool_budget_bytes"]
    # every cell with points holds a record: at least the Gaussians, at most what is held
    assert len(m) <= rep["records_in_use"] <= rep["record_bytes"] // RECORD_BYTES
    assert rep["records_in_use"] == len(m.gaussians(min_probability=0.0, min_points=1)["n"])
    # the dense ray-count block: at least this scene's box, at most its cap (+ row flags)
    assert 0 < rep["process_scratch_bytes"] <= BLOCK_CELLS * (4 + 1 / 8)
    st = runtime.storage(m.layout)
    assert not st.block_buf.any() and not st.bflag_buf.any()  # zero between updates


def test_interrupted_update_leaves_the_shared_block_zero(rng, monkeypatch):
    scans = scene_scans(rng, 1)
    m, other = NdtOmMap(0.25), NdtOmMap(0.25)

    interrupt_kernels(monkeypatch, "merge")  # after the rays and the hits counted in the block
    with pytest.raises(KeyboardInterrupt):
        m.insert_scan(*scans[0])
    monkeypatch.undo()
    st = runtime.storage(m.layout)
    assert not st.block_buf.any() and not st.bflag_buf.any()
    ref = NdtOmMap(0.25)
    for mm in (other, ref):
        mm.insert_scan(*scans[0])
    a, b = other.known_cells(), ref.known_cells()
    np.testing.assert_array_equal(a["index"], b["index"])
    np.testing.assert_array_equal(a["logodds"], b["logodds"])


def test_ctrl_c_during_a_scan_is_raised_once_it_is_inserted_whole(rng, monkeypatch):
    """Ctrl-C (SIGINT) arriving between a scan's kernels: the scan is inserted whole, then
    KeyboardInterrupt is raised (raised between two kernels, it left half a scan)."""
    import signal

    from ndtom_ti.kernels.args import Bound

    scans = scene_scans(rng, 2)
    ref = build(0.25, scans)
    m = build(0.25, scans[:1])
    call = Bound.__call__
    sent = []

    def ctrl_c_in_merge(self, **kw):
        if self.name == "merge" and not sent:  # (once: a second Ctrl-C raises at once)
            sent.append(1)
            os.kill(os.getpid(), signal.SIGINT)  # what Ctrl-C sends; its handler runs before the next line
        return call(self, **kw)

    monkeypatch.setattr(Bound, "__call__", ctrl_c_in_merge)
    # Python's own handler, as in a terminal: a test run started as a shell's background job
    # inherits SIGINT ignored, and the scan would then rightly never see the Ctrl-C.
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            m.insert_scan(*scans[1])
        monkeypatch.undo()
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
    finally:
        signal.signal(signal.SIGINT, before)
    assert m.scans_inserted == 2
    state_equal(m, ref)


def test_gaussian_filters():
    m = NdtOmMap(1.0)
    pts = np.array([[3.5, 0.5, 0.5]] * 2 + [[5.2, 0.5, 0.5], [5.4, 0.5, 0.5], [5.6, 0.6, 0.4]])
    m.insert_scan(pts, np.eye(4))
    assert m.gaussians()["index"].tolist() == [[5, 0, 0]]
    assert m.gaussians(min_points=2)["index"].tolist() == [[3, 0, 0], [5, 0, 0]]
    g = m.gaussians(min_points=1, min_probability=0.0)
    assert g["n"].tolist() == [2, 3] and (g["p_occ"] > 0.5).all()
    np.testing.assert_allclose(g["mean"][1], [5.4, 0.5 + 0.1 / 3, 0.5 - 0.1 / 3])


def test_n_max_caps_the_count_and_scales_the_scatter(rng):
    pts = rng.uniform(0.01, 0.99, size=(50, 3))
    capped = NdtOmMap(1.0, occupancy=False, n_max=20)
    free = NdtOmMap(1.0, occupancy=False)
    for m in (capped, free):
        m.insert_scan(pts, np.eye(4))
    gc_, gf = capped.gaussians(), free.gaussians()
    assert gc_["n"].tolist() == [20] and gf["n"].tolist() == [50]
    np.testing.assert_allclose(gc_["mean"], gf["mean"])
    # Scatter scaled by (20-1)/(50-1): covariance S/(N-1) is unchanged.
    np.testing.assert_allclose(gc_["cov"], gf["cov"], rtol=1e-12)


# --------------------------------------------------------------------------- memory


def test_leaf_counters_are_exact_and_slots_are_emptied(rng):
    st = runtime.storage(ndtom_ti.Layout())
    m, _ = scene_map(rng, scans=3)
    slot = m._slot.index  # private: the slot's number (slots are the process's internals, no public API)
    cells = np.zeros((st.slots, 2), np.int64)
    st.kernels.count_leaf_cells(cells)
    assert (cells // st.layout.leaf_cells == st.leaf_count).all()
    assert st.leaf_count[slot].min() > 0
    del m
    gc.collect()
    cells[:] = 0
    st.kernels.count_leaf_cells(cells)
    assert cells[slot].tolist() == [0, 0] and st.leaf_count[slot].tolist() == [0, 0]
    assert slot in st.free_slots


def test_cached_node_counts_follow_the_regions_of_reused_slots(rng):
    """Storage caches a slot's region counts by its leaf counts: an emptied slot reused by
    a new map must be counted anew."""
    st = runtime.storage(ndtom_ti.Layout())

    def fresh(slot):
        return [
            np.count_nonzero(st.occ_regions[slot]),
            st.leaf_count[slot, 0],
            np.count_nonzero(st.gidx_regions[slot]),
            st.leaf_count[slot, 1],
        ]

    m, _ = scene_map(rng, scans=2)
    slot = m._slot.index  # private: the slot's number (slots are the process's internals, no public API)
    assert st.nodes(slot).tolist() == fresh(slot) and st.nodes(slot)[0] > 0
    del m
    gc.collect()
    assert st.nodes(slot).tolist() == [0, 0, 0, 0]
    m = NdtOmMap(0.5)  # the emptied slot again, far from the last scene
    assert m._slot.index == slot  # private: as above
    m.insert_scan(rng.normal(size=(500, 3)) * 3.0 + [300.0, -200.0, 5.0], np.eye(4))
    assert st.nodes(slot).tolist() == fresh(slot) and st.nodes(slot)[0] > 0


def test_map_refuses_updates_past_the_pool_budget_and_stays_unchanged(rng):
    st = runtime.storage(ndtom_ti.Layout())
    old = runtime.pool_limit()
    m = NdtOmMap(0.1)
    try:
        ndtom_ti.init(memory_limit_GB=(st.pool_bytes() + 130 * 2**20) / 2**30)
        done = 0
        with pytest.raises(MapMemoryError, match="budget"):
            for k in range(500):
                before = m.state()
                pts = rng.normal(size=(2000, 3)) * 5
                pts[:1000] = pts[:1000] * 0.01 + [1.0, 0.0, 0.0]
                m.insert_scan(pts, random_pose(rng, [0.5 * k, 0.0, 0.0]))
                done += 1
        assert done > 3
        after = m.state()
        assert all(before[k].tobytes() == after[k].tobytes() for k in before)
        assert st.pool_bytes() <= runtime.pool_limit()
        assert len(m.known_cells()["index"]) > 0 and m.occupancy(np.zeros((1, 3)))[0] < 0.5  # still usable
    finally:
        del m
        gc.collect()
        ndtom_ti.init(memory_limit_GB=old / 2**30)  # the budget before, to the byte


def test_init_rejects_unsafe_budget_and_arch_switch(arch):
    if arch == "cpu":
        with pytest.raises(ValueError, match="safely"):  # past the pool chunk fixed at start
            ndtom_ti.init(memory_limit_GB=runtime.pool_chunk() / 2**30 + 1.0)
        with pytest.raises(RuntimeError, match="one arch"):
            ndtom_ti.init("cuda")
    with pytest.raises(ValueError, match="arch"):
        ndtom_ti.init("vulkan")
    assert ndtom_ti.init("auto") == arch


def test_too_many_maps_is_a_clear_error():
    maps = []
    with pytest.raises(NoFreeSlotError, match="maps are open already"):
        for _ in range(100):
            maps.append(NdtOmMap(1.0))
    del maps
    gc.collect()
    NdtOmMap(1.0)


FILL = textwrap.dedent(
    """
    import sys, numpy as np, ndtom_ti
    ndtom_ti.init("cpu", memory_limit_GB=float(sys.argv[1]))
    rng = np.random.default_rng(0)
    maps = [ndtom_ti.NdtOmMap(r) for r in (0.1, 0.13)]
    try:
        for k in range(100000):
            m = maps[k % 2]
            T = np.eye(4); T[:3, 3] = rng.uniform(-300, 300, 3) * [1, 1, 0.1]
            d = rng.normal(size=(20000, 3))
            m.insert_scan(d / np.linalg.norm(d, axis=1, keepdims=True) * 8, T)
    except ndtom_ti.MapMemoryError as exc:
        st = ndtom_ti.runtime.storage(maps[0].layout)
        ok = all(float(x.occupancy(np.zeros((1, 3)))[0]) >= 0 for x in maps)
        print("REFUSED", k, st.pool_bytes(), ok, str(exc)[:60])
    """
)


def test_filling_the_pool_ends_in_a_clear_refusal_not_a_crash():
    """With the budget lifted, this workload segfaulted Taichi 1.7.4 after 76 scans
    (~2.1 GiB of pool); with it, the maps refuse cleanly and stay usable."""
    out = subprocess.run(
        [sys.executable, "-c", FILL, "0.875"],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "NDTOM_ARCH": "cpu"},
    )
    assert out.returncode == 0, out.stderr[-2000:]
    line = [s for s in out.stdout.splitlines() if s.startswith("REFUSED")][0]
    _, k, pool, ok, *_ = line.split()
    assert int(k) > 2 and ok == "True"
    assert int(pool) <= runtime.CPU_POOL_LIMIT_BYTES


# --------------------------------------------------------------------------- real data


@pytest.mark.skipif(not (DATA / "balm_hall_every4").exists(), reason="shared data not present")
def test_rcu_exact_on_real_lidar_scans():
    from ndtom_ti.io import open_recording

    with open_recording(DATA / "balm_hall_every4") as rec:
        scans = list(rec.scans(max_scans=3))
    m = NdtOmMap(0.3, occupancy=False)
    world = []
    for s in scans:
        m.insert_scan(s.points, s.T_world_sensor)
        p = s.points[np.isfinite(s.points).all(axis=1)]
        world.append(to_world(p, s.T_world_sensor))
    assert_matches_batch(m, np.concatenate(world))
    assert len(batch_stats(np.concatenate(world), 0.3)["n"]) > 10000


def test_batched_tracing_under_memory_pressure_gives_the_same_map(rng):
    """Near the budget, rays are traced in batches without the dense sensor block; the
    map must equal the one-pass map exactly (log-odds, N)."""
    scans = scene_scans(rng, scans=3)
    a = build(0.1, scans)
    st = runtime.storage(ndtom_ti.Layout())
    old = runtime.pool_limit()
    b = NdtOmMap(0.1, metadata={"source": "test"})
    b.plan.one_pass = False  # traced in batches, each checked against the budget
    try:
        rep = a.memory_report()
        nodes = [rep[k] for k in ("occupancy_regions", "occupancy_leaves", "index_regions", "index_leaves")]
        ndtom_ti.init(memory_limit_GB=st.pool_bytes(np.array(nodes)) / 2**30)  # to the byte: bytes / 2**30 is exact
        batches = [b.insert_scan(pts, T).ray_batches for pts, T in scans]
    finally:
        ndtom_ti.init(memory_limit_GB=old / 2**30)
    assert min(batches) >= 1, batches  # batched every time
    ka, kb = a.known_cells(), b.known_cells()
    assert np.array_equal(ka["index"], kb["index"]) and np.array_equal(ka["logodds"], kb["logodds"])
    ga, gb = a.gaussians(min_points=1, min_probability=0), b.gaussians(min_points=1, min_probability=0)
    assert np.array_equal(ga["index"], gb["index"]) and np.array_equal(ga["n"], gb["n"])
    np.testing.assert_allclose(ga["cov"], gb["cov"], rtol=1e-9, atol=1e-15)


def test_memory_follows_the_place_not_the_run(tmp_path):
    """Three laps of a static hall on the same poses (only the range noise differs):
    after the first lap, memory grows < 5%. (HDL-32-like scans every 5 m; benchmarks/laps.py
    maps ten laps with a scan every metre.)"""
    from conftest import _import_simworld, _simworld

    simworld = _import_simworld()
    lap = 21  # scans 5 s apart (stride 50 at 10 Hz), one lap of the loop exactly
    speed = simworld.build_hall(0).path.length / (5.0 * lap)
    _simworld(tmp_path, "--scans", str(3 * lap), "--stride", "50", "--static", "--no-bags", "--speed", repr(speed))
    d = simworld.SimDataset(tmp_path / "hall.npz")
    np.testing.assert_allclose(d.poses[lap], d.poses[0], atol=1e-6)
    m = NdtOmMap(0.2)
    mem = []
    for i in range(d.n_scans):
        m.insert_scan(d.scan(i), d.poses[i])
        if (i + 1) % lap == 0:
            mem.append(m.memory_bytes())
    assert mem[2] <= 1.05 * mem[0], mem


def test_import_creates_no_taichi_program():
    code = "import ndtom_ti, taichi as ti; print(ti.lang.impl.get_runtime().prog is None)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip().splitlines()[-1] == "True", out.stderr[-500:]


@pytest.mark.parametrize("kw", [{"leaf": 6}, {"leaf": 0}, {"l2": 0}, {"l1": (0, 1, 1)}])
def test_bad_layout_is_refused(kw):
    with pytest.raises(ValueError, match="power of two|positive"):
        ndtom_ti.Layout(**kw).validate()
