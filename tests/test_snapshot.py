"""MapSnapshot: a map's content in numpy. Round trips through the map file, the same
answers, coarse levels and exports as the map's, and the slot-free property: with every
map slot taken, `ndtom export`, `ndtom info` and the viewer still work on a map file."""

from __future__ import annotations

import gc
import json
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_map_api import _corrupt, scene_map, scene_scans, state_equal
from test_memory import big_state, snapshot_of
from typer.testing import CliRunner

from ndtom_ti import Layout, MapConfig, MapFileError, NdtOmMap, NoFreeSlotError, runtime
from ndtom_ti.cli import app
from ndtom_ti.export import FORMATS, export_file, grid_paths
from ndtom_ti.snapshot import ARRAYS, MapSnapshot

SUFFIX = {"ply": ".ply", "pcd": ".pcd", "npz": ".npz", "csv": ".csv", "bt": ".bt", "grid": ".pgm"}


def dicts_equal(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
        assert np.array_equal(a[k], b[k]), k


def state_close(a: NdtOmMap, b: NdtOmMap) -> None:
    """Equal cells, counts and log-odds; means and scatters to float tolerance (a scan's
    scatter sums run in parallel: their last bits vary from run to run, even between two
    maps loaded from one file)."""
    sa, sb = a.state(), b.state()
    for k in ("occ_index", "occ_logodds", "g_index", "g_n"):
        assert np.array_equal(sa[k], sb[k]), k
    for k in ("g_mean_rel", "g_scatter"):
        np.testing.assert_allclose(sa[k], sb[k], rtol=1e-9, atol=1e-12, err_msg=k)


def snapshot_equals_map(s: MapSnapshot, m: NdtOmMap) -> None:
    st = m.state()
    for name in ARRAYS:
        assert getattr(s, name).dtype == st[name].dtype and np.array_equal(getattr(s, name), st[name]), name
    assert (s.resolution, s.occupancy_enabled, s.config, s.layout) == (
        m.resolution,
        m.occupancy_enabled,
        m.config,
        m.layout,
    )
    assert (s.metadata, s.scans_inserted, s.points_inserted) == (m.metadata, m.scans_inserted, m.points_inserted)


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("occupancy", [True, False])
def test_map_snapshot_file_map_round_trip(rng, tmp_path, occupancy):
    m, _ = scene_map(rng, occupancy=occupancy)
    s = m.snapshot()
    snapshot_equals_map(s, m)
    a, b = m.save(tmp_path / "map.ndtom"), s.save(tmp_path / "snap.ndtom")
    assert a.read_bytes() == b.read_bytes()  # the same file, byte for byte
    m2 = NdtOmMap.load(b)
    state_equal(m, m2)
    snapshot_equals_map(MapSnapshot.load(a), m)
    # a map made of a snapshot continues as the original does
    m3 = NdtOmMap.from_snapshot(MapSnapshot.load(b))
    pts, T = scene_scans(rng, 1)[0]
    r1, r3 = m.insert_scan(pts, T), m3.insert_scan(pts, T)
    assert (r1.cells_hit, r1.cells_passed, r1.gaussians_erased) == (r3.cells_hit, r3.cells_passed, r3.gaussians_erased)
    state_close(m, m3)
    assert m3.scans_inserted == m.scans_inserted and m3.metadata == m.metadata


def test_ndt_miss_model_map_round_trips_and_continues(rng, tmp_path):
    sc = scene_scans(rng, 3)
    cfg = MapConfig(miss_model="ndt")
    m = NdtOmMap(0.25, config=cfg)
    for pts, T in sc[:2]:
        m.insert_scan(pts, T)
    m2 = NdtOmMap.from_snapshot(MapSnapshot.load(m.snapshot().save(tmp_path / "n.ndtom")))
    assert m2.config == cfg
    m.insert_scan(*sc[2])
    m2.insert_scan(*sc[2])
    state_close(m, m2)


def test_snapshot_is_frozen_and_does_not_follow_the_map(rng):
    m, _ = scene_map(rng, scans=2)
    m.metadata["nested"] = {"a": 1}
    s = m.snapshot()
    before = {name: getattr(s, name).copy() for name in ARRAYS}
    m.insert_scan(*scene_scans(rng, 1)[0])
    m.metadata["nested"]["a"] = 2
    for name in ARRAYS:
        assert np.array_equal(getattr(s, name), before[name]), name
        with pytest.raises(ValueError, match="read-only"):
            getattr(s, name)[...] = 0
    assert s.metadata["nested"] == {"a": 1} and s.scans_inserted == 2
    with pytest.raises(AttributeError):
        s.resolution = 1.0  # type: ignore[misc]
    m.close()
    with pytest.raises(ValueError, match="closed"):
        m.snapshot()


def test_constructor_copies_and_checks_its_arrays():
    g_index = np.array([[2, 1, 0], [0, 0, 5]], np.int64)  # not the stored dtype: converted
    arrays = {
        "occ_index": np.array([[0, 0, 5], [2, 1, 0]]),
        "occ_logodds": np.array([-0.5, 1.0]),
        "g_index": g_index,
        "g_n": np.array([3, 1]),
        "g_mean_rel": np.zeros((2, 3)),
        "g_scatter": np.zeros((2, 6)),
    }
    settings = {
        "resolution": 0.5,
        "occupancy_enabled": True,
        "config": MapConfig(),
        "layout": Layout(),
        "metadata": {},
        "scans_inserted": 1,
        "points_inserted": 4,
    }
    s = MapSnapshot(**settings, **arrays)
    assert s.g_index.dtype == np.int32 and s.occ_logodds.dtype == np.float32
    g_index[0, 0] = 7  # the caller's array is not the snapshot's
    assert g_index.flags.writeable
    # rows sorted by cell, each group's arrays together
    assert s.occ_index.tolist() == [[0, 0, 5], [2, 1, 0]] and s.g_index.tolist() == [[0, 0, 5], [2, 1, 0]]
    assert s.g_n.tolist() == [1, 3] and s.logodds_at(np.array([[2, 1, 0], [0, 0, 5], [9, 9, 9]])).tolist() == [
        1.0,
        -0.5,
        0.0,
    ]
    with NdtOmMap.from_snapshot(s) as m:
        dicts_equal(m.gaussians(min_points=1, min_probability=0), s.gaussians(min_points=1, min_probability=0))
        dicts_equal(m.known_cells(), s.known_cells())
    for bad, message in [
        ({"g_n": np.array([3])}, "g_n has 1 rows"),
        ({"g_scatter": np.zeros((2, 3))}, "shape"),
        ({"resolution": 0.0}, "resolution"),
        ({"scans_inserted": -1}, "scans_inserted"),
        ({"config": {}}, "MapConfig"),
        ({"occ_index": [[0, 0, 5], [0, 0, 5]]}, "twice"),
    ]:
        with pytest.raises((ValueError, TypeError), match=message):
            MapSnapshot(**{**settings, **arrays, **bad})
    # a snapshot with cells beyond the grid: no map of it, and no slot kept by the attempt
    far = MapSnapshot(**{**settings, **arrays, "occ_index": [[0, 0, 5], [10**7, 0, 0]]})
    free = len(runtime.storage(far.layout).free_slots)
    with pytest.raises(ValueError, match="outside"):
        NdtOmMap.from_snapshot(far)
    assert len(runtime.storage(far.layout).free_slots) == free


# --------------------------------------------------------------------------- queries


@pytest.mark.parametrize("occupancy", [True, False])
def test_queries_answer_as_the_maps(rng, occupancy):
    m, world = scene_map(rng, occupancy=occupancy)
    s = m.snapshot()
    for kw in (
        {},
        {"min_probability": 0.0},
        {"min_points": 0, "min_probability": 0.0},
        {"min_points": 10},
        {"min_probability": 0.8},
    ):
        dicts_equal(s.gaussians(**kw), m.gaussians(**kw))
    dicts_equal(s.known_cells(), m.known_cells())
    assert len(s) == len(m) > 0
    probe = np.concatenate([m.known_cells()["index"][::7], [[10**6, 0, 0], [-40, 3, 1]]])
    assert np.array_equal(s.logodds_at(probe), m.logodds_at(probe))
    lo, hi = s.data_extent()
    mlo, mhi = m.data_extent()
    assert np.allclose(lo, mlo) and np.allclose(hi, mhi)
    for bad in ({"min_points": -1}, {"min_probability": float("nan")}, {"min_points": True}):
        with pytest.raises(ValueError):
            s.gaussians(**bad)


# --------------------------------------------------------------------------- coarsen


@pytest.mark.parametrize("factor", [2, 3, 4])
@pytest.mark.parametrize("occupancy,n_max", [(True, 0), (False, 0), (False, 3)])
def test_coarsen_gives_what_the_map_gives(rng, factor, occupancy, n_max):
    sc = scene_scans(rng, 3)
    m = NdtOmMap(0.125, occupancy=occupancy, config=MapConfig(n_max=n_max), metadata={"source": "test"})
    for pts, T in sc:
        m.insert_scan(pts, T)
    with m.coarsen(factor) as cm:
        cs = m.snapshot().coarsen(factor)
        st = cm.state()
        # cell for cell: the same keys, log-odds and counts; means and scatters to float tolerance
        for name in ("occ_index", "occ_logodds", "g_index", "g_n"):
            assert np.array_equal(getattr(cs, name), st[name]), name
        for name in ("g_mean_rel", "g_scatter"):
            np.testing.assert_allclose(getattr(cs, name), st[name], rtol=1e-12, atol=1e-15)
        dicts_equal(cs.known_cells(), cm.known_cells())
        g1, g2 = cs.gaussians(min_probability=0.0), cm.gaussians(min_probability=0.0)
        assert np.array_equal(g1["index"], g2["index"]) and np.array_equal(g1["n"], g2["n"])
        np.testing.assert_allclose(g1["mean"], g2["mean"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(g1["cov"], g2["cov"], rtol=1e-12, atol=1e-15)
        assert len(cs) == len(cm)
        assert (cs.resolution, cs.metadata, cs.scans_inserted) == (cm.resolution, cm.metadata, cm.scans_inserted)
    if n_max:
        assert cs.g_n.max() == n_max


def test_coarsen_rejects_bad_factor(rng):
    s, _ = scene_map(rng, scans=1)
    s = s.snapshot()
    for bad in (1, 0, -2, 2.5, "3", True, None):
        with pytest.raises(ValueError, match="factor"):
            s.coarsen(bad)


# --------------------------------------------------------------------------- exports


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory) -> Path:
    m, _ = scene_map(np.random.default_rng(7), res=0.2)
    m.metadata["note"] = "snapshot export test"
    path = m.save(tmp_path_factory.mktemp("snap") / "scene.ndtom")
    del m
    gc.collect()
    return path


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("min_probability", [0.5, 0.0])
def test_every_export_from_a_snapshot_equals_the_maps(scene_file, tmp_path, fmt, min_probability):
    if fmt == "grid" and min_probability == 0.0:
        pytest.skip("the grid takes occupied cells above 0.5 either way")
    s = MapSnapshot.load(scene_file)
    with NdtOmMap.load(scene_file) as m:
        a = export_file(m, tmp_path / f"map{SUFFIX[fmt]}", fmt, min_probability=min_probability)
    b = s.export(tmp_path / f"snap{SUFFIX[fmt]}", fmt, min_probability=min_probability)
    assert (a.count, a.format, len(a.paths)) == (b.count, b.format, len(b.paths)) and a.count > 0
    assert a.summary.replace("map.", "snap.").replace("map.yaml", "snap.yaml") == b.summary
    for pa, pb in zip(a.paths, b.paths, strict=True):
        da, db = pa.read_bytes(), pb.read_bytes()
        if pa.suffix == ".yaml":  # names its image
            da = da.replace(b"map.pgm", b"snap.pgm")
        assert da == db, pa.name


# --------------------------------------------------------------------------- map files


@pytest.mark.parametrize(
    "kind,message",
    [
        ("empty", "not an ndtom_ti map"),
        ("header_cut", "truncated"),
        ("payload_cut", "truncated"),
        ("trailing", "trailing bytes"),
        ("flip_payload", "checksum"),
        ("flip_header", "corrupt"),
        ("newer", "version 99"),
    ],
)
def test_broken_files_are_refused_as_the_map_refuses_them(rng, tmp_path, kind, message):
    m, _ = scene_map(rng, scans=1)
    bad = tmp_path / "bad.ndtom"
    bad.write_bytes(_corrupt(m.save(tmp_path / "m.ndtom").read_bytes(), kind))
    with pytest.raises(MapFileError, match=message) as a:
        MapSnapshot.load(bad)
    with pytest.raises(MapFileError) as b:
        NdtOmMap.load(bad)
    assert str(a.value) == str(b.value)
    with pytest.raises(FileNotFoundError):
        MapSnapshot.load(tmp_path / "absent.ndtom")
    with pytest.raises(MapFileError, match="folder"):
        MapSnapshot.load(tmp_path)


def _rewrite(path: Path, out: Path, header_edit=None, arrays_edit=None) -> Path:
    """``path`` written again with its header or arrays changed (a valid checksum)."""
    import hashlib

    data = path.read_bytes()
    hlen = struct.unpack("<Q", data[12:20])[0]
    header = json.loads(data[20 : 20 + hlen])
    payload = data[20 + hlen :]
    arrays = {
        e["name"]: np.frombuffer(payload, e["dtype"], int(np.prod(e["shape"])), e["offset"]).reshape(e["shape"])
        for e in header["arrays"]
    }
    if arrays_edit:
        arrays = arrays_edit(arrays)
    if header_edit:
        header_edit(header)
    blob = b"".join(np.ascontiguousarray(arrays[e["name"]]).tobytes() for e in header["arrays"])
    header["payload_sha256"] = hashlib.sha256(blob).hexdigest()
    header.pop("header_sha256", None)  # (a hand-made file: as those written before the header's checksum)
    hb = json.dumps(header).encode()
    out.write_bytes(data[:12] + struct.pack("<Q", len(hb)) + hb + blob)
    return out


def test_cells_stored_out_of_order_load_sorted_as_the_map_reads_them(rng, tmp_path):
    from ndtom_ti.mapfile import RAW_VERSION

    m, _ = scene_map(rng, scans=2)
    # format 3 (raw arrays) can list cells in any order; format 4's coding keeps them sorted
    path = m.snapshot().save(tmp_path / "m.ndtom", version=RAW_VERSION)

    def shuffle(a):
        p, q = rng.permutation(len(a["occ_index"])), rng.permutation(len(a["g_index"]))
        return {k: v[p] if k.startswith("occ") else v[q] for k, v in a.items()}

    shuffled = _rewrite(path, tmp_path / "shuffled.ndtom", arrays_edit=shuffle)
    s = MapSnapshot.load(shuffled)
    snapshot_equals_map(s, m)
    with NdtOmMap.load(shuffled) as m2:
        dicts_equal(s.gaussians(min_probability=0), m2.gaussians(min_probability=0))
    bad = _rewrite(path, tmp_path / "p.ndtom", header_edit=lambda h: h["config"].update(p_occupied=0.3))
    with pytest.raises(MapFileError, match="p_occupied"):
        MapSnapshot.load(bad)


def test_a_multi_million_cell_file_opens_as_a_snapshot(rng, tmp_path, capsys):
    """3 M known cells, 300 k Gaussians (the fast-load test's map): the snapshot holds the
    file's cells, sorted, and answers as the loaded map (times printed, paired)."""
    st = big_state(rng, 3_000_000, 300_000)
    m = NdtOmMap.from_snapshot(snapshot_of(st, 0.1))
    path = m.save(tmp_path / "big.ndtom")
    m.close()
    t0 = time.perf_counter()
    s = MapSnapshot.load(path)
    t1 = time.perf_counter()
    m = NdtOmMap.load(path)
    t2 = time.perf_counter()
    order = np.lexsort((st["occ_index"][:, 2], st["occ_index"][:, 1], st["occ_index"][:, 0]))
    assert np.array_equal(s.occ_index, st["occ_index"][order])
    assert np.array_equal(s.occ_logodds, st["occ_logodds"][order])
    dicts_equal(s.known_cells(), m.known_cells())
    dicts_equal(s.gaussians(min_points=1, min_probability=0), m.gaussians(min_points=1, min_probability=0))
    t3 = time.perf_counter()
    c = s.coarsen(2)
    t4 = time.perf_counter()
    with m.coarsen(2) as cm:
        t5 = time.perf_counter()
        assert np.array_equal(c.occ_index, cm.state()["occ_index"]) and np.array_equal(c.g_n, cm.state()["g_n"])
    m.close()
    with capsys.disabled():
        print(
            f"\n3 M cells: MapSnapshot.load {t1 - t0:.2f} s, NdtOmMap.load {t2 - t1:.2f} s; "
            f"coarsen(2): snapshot {t4 - t3:.2f} s, map {t5 - t4:.2f} s"
        )


# --------------------------------------------------------------------------- no map slot needed


@pytest.fixture
def every_slot_taken():
    """Every map slot of the process held (as tests/test_lifetime.py fills them)."""
    st = runtime.storage(NdtOmMap(0.5).layout)
    gc.collect()
    held = [NdtOmMap(0.5) for _ in range(len(st.free_slots))]
    with pytest.raises(NoFreeSlotError):
        NdtOmMap(0.5)
    yield held
    for m in held:
        m.close()


def run(*args: object):
    r = CliRunner(env={"COLUMNS": "250"}).invoke(app, [str(a) for a in args])
    assert "Traceback" not in r.output, r.output
    return r


def test_export_info_and_view_of_a_file_need_no_map_slot(scene_file, tmp_path, every_slot_taken):
    s = MapSnapshot.load(scene_file)  # a snapshot takes no slot either
    for fmt in FORMATS:
        out = tmp_path / f"cli{SUFFIX[fmt]}"
        r = run("export", scene_file, "--format", fmt, "-o", out)
        assert r.exit_code == 0, r.output
        ref = s.export(tmp_path / f"ref{SUFFIX[fmt]}", fmt)
        got = grid_paths(out) if fmt == "grid" else (out,)
        assert [p.read_bytes().replace(b"cli.pgm", b"ref.pgm") for p in got] == [p.read_bytes() for p in ref.paths]
    r = run("info", scene_file)
    assert r.exit_code == 0 and "resolution" in r.output and "0.2 m" in r.output, r.output
    # the viewer: `ndtom view FILE --html`, and a viewer of a loaded file with coarser levels
    pytest.importorskip("viser", reason="the viewer needs viser")
    from ndtom_ti.viewer import MapViewer

    r = run("view", scene_file, "--html", tmp_path / "scene.html")
    assert r.exit_code == 0 and (tmp_path / "scene.html").stat().st_size > 10000, r.output
    v = MapViewer(MapSnapshot.load(scene_file), compare=s, verbose=False, environment_map=False)
    try:
        assert v.drawn["gaussians"] == len(s) > 0
        v.controls.resolution.value = v.controls.resolution.options[1]
        v.controls.layers["occupied"].value = True
        v.refresh()
        assert v.level == 2 and v.drawn["gaussians"] == len(s.coarsen(2)) and v.drawn["occupied"] > 0
        assert "could not be made" not in v.controls.stats.content
        with pytest.raises(ValueError, match="read-only"):
            v.live([], s)
    finally:
        v.close()


def test_export_of_a_file_starts_no_taichi(scene_file, tmp_path):
    """In a fresh process: `ndtom export` and a snapshot's queries and coarse levels run
    without Taichi being initialised (no runtime, no map slot, no compile)."""
    script = (
        "import sys\n"
        "from typer.testing import CliRunner\n"
        "from ndtom_ti import runtime\n"
        "from ndtom_ti.cli import app\n"
        "from ndtom_ti.snapshot import MapSnapshot\n"
        "r = CliRunner().invoke(app, ['export', sys.argv[1], '-o', sys.argv[2]])\n"
        "s = MapSnapshot.load(sys.argv[1]).coarsen(2)\n"
        "print('RESULT', r.exit_code, runtime.current_arch(), len(s.gaussians()['n']) > 0)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", script, str(scene_file), str(tmp_path / "x.ply")],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert "RESULT 0 None True" in out.stdout, out.stdout[-2000:] + out.stderr[-2000:]


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-q"]))
