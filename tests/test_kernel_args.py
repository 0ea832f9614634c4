"""Kernels called by keyword with typed argument groups (kernels/args.py), the kernel
families cached per config (kernels/families.py) and the update plan (scan_update.py)."""

import json
import subprocess
import sys

import numpy as np
import pytest
import taichi as ti

from ndtom_ti import NdtOmMap, runtime
from ndtom_ti.kernels.args import Bound, Model, Records
from ndtom_ti.kernels.families import kernel_set
from ndtom_ti.kernels.ndt import U16_MAX_RAYS
from ndtom_ti.kernels.trace import RaysConfig
from ndtom_ti.kernels.update import FreeConfig, MergeConfig
from ndtom_ti.scan_update import UpdatePlan

F64 = ti.types.ndarray(dtype=ti.f64, ndim=1)
I32 = ti.types.ndarray(dtype=ti.i32, ndim=1)


def _scale(out: F64, l_hit: ti.f64, l_min: ti.f32, n: ti.i32, rec_n: I32, rec_free: I32):
    for i in range(n):
        out[i] = l_hit * rec_n[i] + l_min + rec_free[i]


def _records(k: int) -> Records:
    return Records(
        rec_n=np.arange(k, dtype=np.int32),
        rec_cell=np.zeros((k, 3), np.int32),
        rec_mean=np.zeros((k, 3)),
        rec_scat=np.zeros((k, 6)),
        rec_free=np.full(k, 100, np.int32),
    )


def test_bound_kernel_flattens_groups_in_declared_order():
    k = Bound(_scale, ("out", ("model", Model, ("l_hit", "l_min")), "n", ("records", Records, ("rec_n", "rec_free"))))
    out = np.zeros(4)
    k(out=out, model=Model(l_hit=2.0, l_free=-9.0, l_min=0.5, l_max=9.0), n=4, records=_records(4))
    np.testing.assert_array_equal(out, [100.5, 102.5, 104.5, 106.5])


def test_bound_kernel_rejects_swapped_missing_and_unknown_arguments():
    k = Bound(_scale, ("out", ("model", Model, ("l_hit", "l_min")), "n", ("records", Records, ("rec_n", "rec_free"))))
    model, recs, out = Model(l_hit=1.0, l_free=0.0, l_min=0.0, l_max=0.0), _records(2), np.zeros(2)
    with pytest.raises(TypeError, match="model must be a Model, got Records"):
        k(out=out, model=recs, n=2, records=model)
    with pytest.raises(TypeError, match="missing argument 'n'"):
        k(out=out, model=model, records=recs)
    with pytest.raises(TypeError, match="unexpected arguments"):
        k(out=out, model=model, n=2, records=recs, extra=1)
    assert not out.any()  # nothing ran


def test_bound_kernel_whose_parameters_differ_from_its_groups_is_refused():
    with pytest.raises(TypeError, match="do not match"):
        Bound(_scale, ("out", ("model", Model, ("l_min", "l_hit")), "n", ("records", Records, ("rec_n", "rec_free"))))
    with pytest.raises(TypeError, match="has no fields"):
        Bound(_scale, ("out", ("model", Model, ("l_hit", "l_low")), "n", ("records", Records, ("rec_n", "rec_free"))))


def test_variants_without_a_group_need_no_placeholder():
    """A merge compiled for the paper's model and tree sums takes neither the NDT arrays
    nor the grouped hits: the caller passes none."""
    ks = kernel_set(runtime.storage(NdtOmMap(1.0).layout))
    merge = ks.merge(MergeConfig(bt="i32", grouped=False, ndt=False))
    assert {"sums", "records", "block", "nodes", "model"} <= merge.keywords
    assert not {"ndt", "grouped"} & merge.keywords
    assert "ndt" in ks.merge(MergeConfig(bt="i32", grouped=True, ndt=True)).keywords


def test_families_are_cached_per_config_and_shared_between_launch_kinds():
    st = runtime.storage(NdtOmMap(1.0).layout)
    fast, plain = kernel_set(st, fast=True), kernel_set(st, fast=False)
    assert kernel_set(st, fast=True) is fast
    cfg = RaysConfig(bt="u16", mode="dense", ndt=True)
    assert fast.rays(cfg) is fast.rays(RaysConfig(bt="u16", mode="dense", ndt=True))
    assert fast.rays(cfg).kernel is plain.rays(cfg).kernel  # one Taichi kernel, compiled once
    assert fast.block_apply(FreeConfig("u16", False)) is not fast.block_apply(FreeConfig("u16", True))
    with pytest.raises(ValueError, match="block dtype"):
        RaysConfig(bt="u8")
    with pytest.raises(ValueError, match="rays mode"):
        RaysConfig(mode="sparse")


def test_update_plan_is_checked():
    plan = UpdatePlan()
    with pytest.raises(ValueError, match="row_flags"):
        plan.row_flags = "sometimes"
    with pytest.raises(ValueError, match="block_cells"):
        plan.block_cells = -1
    with pytest.raises(ValueError, match="touched_rows"):
        UpdatePlan(touched_rows=0)
    with pytest.raises(ValueError, match="index_records"):
        UpdatePlan(index_records=-1)
    m = NdtOmMap(1.0)
    m.block_cells = 4096  # the map's older attribute is the plan's
    assert m.plan.block_cells == 4096


def assert_same_map(ref, m):
    """The same cells and log-odds, the same Gaussians, bit for bit (test_determinism.py)."""
    ka, kb = ref.known_cells(), m.known_cells()
    np.testing.assert_array_equal(ka["index"], kb["index"])
    np.testing.assert_array_equal(ka["logodds"], kb["logodds"])
    ga, gb = ref.gaussians(min_probability=0), m.gaussians(min_probability=0)
    for key in ("index", "n", "mean", "cov"):
        np.testing.assert_array_equal(ga[key], gb[key])


@pytest.mark.parametrize(
    "plan",
    [
        {"row_flags": "always"},
        {"row_flags": "never"},
        {"one_pass": False},
        {"touched_rows": 1},
        {"u16_rays": U16_MAX_RAYS},
        {"u16_rays": U16_MAX_RAYS, "row_flags": "never"},
        {"u16_rays": U16_MAX_RAYS, "row_flags": "always"},
        {"block_cells": 0},
        {"index_records": 0},
    ],
)
@pytest.mark.parametrize("model", ["paper", "ndt"])
def test_every_plan_gives_the_same_map(rng, plan, model):
    d = rng.normal(size=(3000, 3))
    scans = [
        (d * rng.uniform(2.0, 8.0, (3000, 1)) / np.linalg.norm(d, axis=1, keepdims=True), np.eye(4)) for _ in range(3)
    ]
    for s, (_, T) in enumerate(scans):
        T[:3, 3] = [0.3 * s, -0.2 * s, 0.1]
    ref, m = NdtOmMap(0.25, miss_model=model), NdtOmMap(0.25, miss_model=model)
    for k, v in plan.items():
        setattr(m.plan, k, v)
    for pts, T in scans:
        ra, rb = ref.insert_scan(pts, T), m.insert_scan(pts, T)
        assert (ra.cells_hit, ra.cells_passed, ra.ray_cell_visits) == (
            rb.cells_hit,
            rb.cells_passed,
            rb.ray_cell_visits,
        )
        assert (rb.ray_batches > 0) == (plan.get("one_pass") is False)
        st = runtime.storage(m.layout)
        assert not st.block_buf.any() and not st.bflag_buf.any()  # counts, marks and flags cleared
    assert_same_map(ref, m)


@pytest.mark.parametrize("model", ["paper", "ndt"])
def test_a_few_far_points_give_the_same_map(rng, model, capfd):
    """Scans whose few far points make their box larger than the dense block may be (the
    block then covers the rest, the far rays count in the tree) give the map the tree
    alone gives, cell for cell. Neither path prints: the loops kept rolled (ndt.rolled)
    hold a print that must never run."""
    scans = []
    for s in range(3):
        d = rng.normal(size=(4000, 3))
        r = rng.uniform(1.0, 4.0, (4000, 1))
        r[:3] = 30.0  # 3 stray points far away
        T = np.eye(4)
        T[:3, 3] = [0.3 * s, -0.2 * s, 0.1]
        scans.append((d * r / np.linalg.norm(d, axis=1, keepdims=True), T))
    ref, m = NdtOmMap(0.25, miss_model=model), NdtOmMap(0.25, miss_model=model)
    ref.plan.block_cells = 0
    m.plan.block_cells = 64**3  # less than the scans' whole box (~240 cells a side), more than their bulk
    for pts, T in scans:
        ra, rb = ref.insert_scan(pts, T), m.insert_scan(pts, T)
        assert (ra.cells_hit, ra.cells_passed, ra.ray_cell_visits, ra.gaussians_erased) == (
            rb.cells_hit,
            rb.cells_passed,
            rb.ray_cell_visits,
            rb.gaussians_erased,
        )
        st = runtime.storage(m.layout)
        assert not st.block_buf.any() and not st.bflag_buf.any()
    assert_same_map(ref, m)
    assert capfd.readouterr().out == ""


_COMPILES = """
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
import simworld
import ndtom_ti
from ndtom_ti.compiling import on_compile

ndtom_ti.init("cpu")
d = simworld.SimDataset(sys.argv[2])
names = []
on_compile(names.append)
out = {}
for model in ("paper", "ndt"):
    with ndtom_ti.NdtOmMap(0.2, miss_model=model) as m:
        del names[:]
        m.insert_scan(d.scan(0), d.poses[0])
        first = list(names)
        for i in range(1, 12):
            m.insert_scan(d.scan(i), d.poses[i])
            m.insert_scan(d.scan(i)[::7], d.poses[i])  # a sparser scan from the same place
        out[model] = {"first": first, "later": names[len(first):]}
print(json.dumps(out))
"""


def test_kernels_compile_as_a_map_needs_them_and_once(tmp_path):
    """A kernel compiles at its first call in a process, and only the kernels a scan's update
    uses: the first scan of a recording compiles (and announces) those of its path, and its
    later scans, whose rays fill the dense block more or less densely, compile nothing more
    (a fresh process: the test session has compiled every variant)."""
    from conftest import SIMWORLD, _simworld

    npz = _simworld(tmp_path, "--scans", "12", "--stride", "10", "--no-bags") / "hall.npz"
    p = subprocess.run(
        [sys.executable, "-c", _COMPILES, str(SIMWORLD.parent), str(npz)], capture_output=True, text=True, timeout=600
    )
    assert p.returncode == 0, p.stderr[-3000:]
    out = json.loads(p.stdout.strip().splitlines()[-1])
    # The dense block's path, then the tree's (compile_tree_path: far points, memory pressure).
    # Both paths' merge is one variant on the CPU (it sums each cell's points in the scan's
    # order, whichever path grouped them: test_determinism.py).
    assert out["paper"]["first"] == [
        "prepare",
        "rays",
        "hits_dense",
        "merge",
        "block_apply",
        "rays",
        "hits_count",
        "hits_group",
        "apply_free",
    ], out
    # The NDT miss model's map then needs its own variants of four, and two kernels more.
    assert out["ndt"]["first"] == [
        "mark_gaussians",
        "rays",
        "merge",
        "apply_marked",
        "block_apply",
        "rays",
        "apply_free",
    ], out
    assert out["paper"]["later"] == [] and out["ndt"]["later"] == [], out
    assert "Warning" not in p.stderr, p.stderr[-3000:]
