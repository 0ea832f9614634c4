"""One process is deterministic: the same scans give bit-identical map files, whatever the
order of Taichi's threads, their number, or the update plan (dense block, tree, batches).

Where thread order once reached the map (issue 32): the points of a hit cell were summed in
the order threads reached them (hits_dense's atomic rank, hits_sum's float64 atomic adds),
and the NDT miss model's count of erased neighbours could pass 6 by a check-then-add race.
"""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, _import_simworld

import ndtom_ti
from ndtom_ti import NdtOmMap
from ndtom_ti.snapshot import MapSnapshot
from ndtom_ti.snapshot import ARRAYS

RES = 0.2
MODELS = ("paper", "ndt")
BALM = DATA / "balm_hall_every4"


@pytest.fixture(scope="module")
def sim_npz(sim_hall_dynamic) -> Path:
    return sim_hall_dynamic.path


def sim_scans(path: Path, count: int = 12):
    _import_simworld()
    import simworld

    d = simworld.SimDataset(path)
    return [(d.scan(i), d.poses[i]) for i in range(min(count, d.n_scans))]


def build(scans, model: str, tmp: Path, name: str, plan: dict | None = None) -> Path:
    m = NdtOmMap(RES, miss_model=model)
    for k, v in (plan or {}).items():
        setattr(m.plan, k, v)
    for pts, T in scans:
        m.insert_scan(pts, T)
    path = m.save(tmp / f"{name}.ndtom")
    del m
    return path


def assert_same_file(a: Path, b: Path) -> None:
    """Bit-identical files; where not, the arrays that differ and by how much."""
    if a.read_bytes() == b.read_bytes():
        return
    sa, sb = MapSnapshot.load(a), MapSnapshot.load(b)
    diffs = []
    for name in ARRAYS:
        x, y = getattr(sa, name), getattr(sb, name)
        if x.shape != y.shape:
            diffs.append(f"{name}: shapes {x.shape} != {y.shape}")
        elif not np.array_equal(x, y):
            bad = (x != y).reshape(len(x), -1).any(axis=1)
            worst = float(np.abs(x.astype(np.float64) - y.astype(np.float64)).max())
            diffs.append(f"{name}: {int(bad.sum())} of {len(x)} rows differ (largest {worst:.3g})")
    raise AssertionError("map files differ: " + ("; ".join(diffs) or "header only"))


@pytest.mark.parametrize("model", MODELS)
def test_two_runs_give_identical_map_files(sim_npz, tmp_path, model):
    scans = sim_scans(sim_npz)
    a = build(scans, model, tmp_path, "a")
    b = build(scans, model, tmp_path, "b")
    assert_same_file(a, b)


@pytest.mark.parametrize("model", MODELS)
def test_every_update_plan_gives_the_same_map_file(sim_npz, tmp_path, model):
    """Dense block (16- and 32-bit counts), the sparse tree alone, and batched tracing as
    under memory pressure: one map, bit for bit."""
    scans = sim_scans(sim_npz, 8)
    ref = build(scans, model, tmp_path, "ref")
    plans = {
        "u16": {"u16_rays": 65533},
        "tree": {"block_cells": 0},
        "batched": {"one_pass": False},
        "small_block": {"block_cells": 16**3 * 8},  # the scan's far cells in the tree
    }
    for name, plan in plans.items():
        assert_same_file(ref, build(scans, model, tmp_path, name, plan))


_ONE_THREAD = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    import ndtom_ti
    ndtom_ti.init("cpu", cpu_max_num_threads=int(sys.argv[3]))
    import taichi as ti
    from taichi.lang import impl
    assert impl.current_cfg().cpu_max_num_threads == int(sys.argv[3])
    sys.path.insert(0, sys.argv[4])
    from test_determinism import build, sim_scans, MODELS
    scans = sim_scans(Path(sys.argv[1]))
    for model in MODELS:
        build(scans, model, Path(sys.argv[2]), f"t_{model}")
    """
)


def test_one_thread_gives_the_map_of_many(sim_npz, tmp_path):
    """A worker process on one Taichi thread builds the map this process builds on all of
    its threads, bit for bit."""
    from taichi.lang import impl

    if ndtom_ti.current_arch() != "cpu":
        pytest.skip("CPU thread counts")
    assert impl.current_cfg().cpu_max_num_threads > 1
    env = {**os.environ, "NDTOM_ARCH": "cpu"}
    tests = str(Path(__file__).resolve().parent)
    res = subprocess.run(
        [sys.executable, "-c", _ONE_THREAD, str(sim_npz), str(tmp_path), "1", tests],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert res.returncode == 0, res.stderr[-3000:]
    scans = sim_scans(sim_npz)
    for model in MODELS:
        assert_same_file(tmp_path / f"t_{model}.ndtom", build(scans, model, tmp_path, f"many_{model}"))


@pytest.mark.skipif(not BALM.exists(), reason="shared data not present")
@pytest.mark.parametrize("model", MODELS)
def test_real_lidar_scans_give_identical_map_files(tmp_path, model):
    from ndtom_ti.io import open_recording

    with open_recording(BALM) as rec:
        scans = [(s.points, s.T_world_sensor) for s in rec.scans(max_scans=4)]
    assert_same_file(build(scans, model, tmp_path, "a"), build(scans, model, tmp_path, "b"))
    assert_same_file(build(scans, model, tmp_path, "a"), build(scans, model, tmp_path, "tree", {"block_cells": 0}))


def test_erased_neighbour_counts_stop_at_six(sim_npz):
    """The NDT miss model's count of erased neighbours is exact up to 6 and stays there:
    no thread adds past it (only ">= 6" is read, but the count is saved)."""
    _import_simworld()
    import simworld

    d = simworld.SimDataset(sim_npz)
    m = NdtOmMap(RES, miss_model="ndt")
    for i in range(d.n_scans):
        m.insert_scan(d.scan(i), d.poses[i])
    near = m.snapshot().g_erased_near
    assert near.max() <= 6, np.bincount(near)


@pytest.mark.parametrize("n", [5, 64, 65, 1 << 20])
def test_a_cells_points_are_summed_in_scan_order_whatever_order_they_come_in(n):
    """cell_sums sorts a cell's point indices before summing: insertion sort for a few,
    heapsort for many (2^20 points in one cell whose threads' runs interleaved took
    insertion sort minutes). Any order in, the indices come out ascending."""
    import taichi as ti

    from ndtom_ti.kernels.update import cell_sums

    rng = np.random.default_rng(n)
    pts = rng.normal(size=(n, 3))
    order = rng.permutation(n).astype(np.int32)
    out = np.zeros(9)

    @ti.kernel
    def sums(
        order: ti.types.ndarray(dtype=ti.i32, ndim=1),
        pts: ti.types.ndarray(dtype=ti.f64, ndim=2),
        out: ti.types.ndarray(dtype=ti.f64, ndim=1),
        n: ti.i32,
    ):
        for _ in range(1):
            v = cell_sums(order, 0, n, pts, ti.Vector([0.0, 0.0, 0.0], dt=ti.f64))
            for a in ti.static(range(9)):
                out[a] = v[a]

    sums(order, pts, out, n)
    assert (order == np.arange(n)).all()
    x = pts
    want = np.r_[x.sum(0), [(x[:, a] * x[:, b]).sum() for a, b in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))]]
    assert np.allclose(out, want, rtol=1e-9, atol=1e-9)
