"""The lighter kernel call (kernels/launch.py) and the CPU loops' work queue (make_queue)."""

import collections

import numpy as np
import pytest
import taichi as ti

from ndtom_ti import NdtOmMap, runtime
from ndtom_ti.kernels import launch
from ndtom_ti.kernels.families import kernel_set
from ndtom_ti.kernels.ndt import make_queue
from ndtom_ti.kernels.update import MergeConfig

F64 = ti.types.ndarray(dtype=ti.f64, ndim=1)
I32_2 = ti.types.ndarray(dtype=ti.i32, ndim=2)


@ti.kernel
def _mix(a: F64, b: I32_2, out: F64, k: ti.i32, u: ti.u32, x: ti.f64, pts: ti.types.ndarray(ndim=1)):
    for i in range(a.shape[0]):
        out[i] = a[i] * x + b[i, 0] - b[i, 1] + k + ti.cast(u, ti.f64) + ti.cast(pts[i], ti.f64)


def _args(rng, n, pts_dtype=np.float64):
    return [
        rng.normal(size=n),
        rng.integers(-9, 9, (n, 2)).astype(np.int32),
        np.zeros(n),
        -3,
        7,
        0.5,
        rng.normal(size=n).astype(pts_dtype),
    ]


def _expect(a, b, out, k, u, x, pts):
    return a * x + b[:, 0] - b[:, 1] + k + u + pts.astype(np.float64)


def test_launcher_computes_what_taichi_computes(rng):
    fast = launch.Launcher(_mix)
    # private: which path a call took (its plans, or Taichi's call) is not observable otherwise
    assert fast._kinds is not None, "the launcher fell back to Taichi's call for plain arguments"
    for call in range(3):  # the first call of a signature goes through Taichi, then the plan
        args = _args(rng, 50)
        fast(*args)
        np.testing.assert_allclose(args[2], _expect(*args), rtol=1e-12)
    assert len(fast._plans) == 1
    # Another dtype of the dtype-free argument: a second specialisation, both right.
    args = _args(rng, 40, np.float32)
    for call in range(2):
        fast(*args)
        np.testing.assert_allclose(args[2], _expect(*args), rtol=1e-6)
    assert len(fast._plans) == 2


def test_launcher_hands_what_it_cannot_pass_to_taichi(rng):
    fast = launch.Launcher(_mix)
    args = _args(rng, 30)
    fast(*args)
    # A strided view: Taichi's call and its error, not a pointer to the wrong elements.
    wide = np.zeros((30, 2))
    args[2] = wide[:, 0]
    with pytest.raises(ValueError, match="contiguous"):
        fast(*args)
    assert not wide.any()
    # Wrong dtype: Taichi's own error, not a wrong result.
    args = _args(rng, 30)
    args[1] = args[1].astype(np.int64)
    with pytest.raises(Exception, match="i32|int32|dtype"):
        fast(*args)


def test_launcher_without_the_taichi_internals_it_uses_keeps_taichis_call(rng):
    fast = launch.Launcher(_mix)
    real = fast._k  # private: the Taichi kernel inside, replaced by one without the internals the plans use

    class OtherTaichi:  # compiled kernels without make_launch_context
        arguments = real.arguments
        compiled_kernels = collections.defaultdict(object)

        def ensure_compiled(self, *args):
            return real.ensure_compiled(*args)

    fast._k = OtherTaichi()
    for call in range(2):
        args = _args(rng, 20)
        fast(*args)
        np.testing.assert_allclose(args[2], _expect(*args), rtol=1e-12)
    assert fast._kinds is None and not fast._plans


def test_plain_launch_switch(monkeypatch):
    monkeypatch.setenv("NDTOM_PLAIN_LAUNCH", "1")
    assert not launch.enabled()
    monkeypatch.setenv("NDTOM_PLAIN_LAUNCH", "0")
    assert launch.enabled() or ti.lang.impl.current_cfg().debug
    # Another Taichi release: its internals may differ, so Taichi's own call.
    monkeypatch.setattr(ti, "__version__", (1, 8, 0))
    assert not launch.enabled()


def test_maps_through_both_calls_are_identical(sim_hall_dynamic, monkeypatch):
    a = NdtOmMap(0.4)
    monkeypatch.setenv("NDTOM_PLAIN_LAUNCH", "1")
    b = NdtOmMap(0.4)  # every kernel through Taichi's own call
    monkeypatch.undo()
    st = runtime.storage(a.layout)
    assert isinstance(kernel_set(st).prepare().call, launch.Launcher) == launch.enabled()
    assert not isinstance(kernel_set(st, fast=False).merge(MergeConfig()).call, launch.Launcher)
    d = sim_hall_dynamic
    for i in range(0, 8, 2):
        pts, T = d.scan(i), d.poses[i]
        ra, rb = a.insert_scan(pts, T), b.insert_scan(pts, T)
        assert (ra.cells_hit, ra.cells_passed, ra.ray_cell_visits) == (
            rb.cells_hit,
            rb.cells_passed,
            rb.ray_cell_visits,
        )
    ka, kb = a.known_cells(), b.known_cells()
    np.testing.assert_array_equal(ka["index"], kb["index"])
    np.testing.assert_array_equal(ka["logodds"], kb["logodds"])
    ga, gb = a.gaussians(min_probability=0), b.gaussians(min_probability=0)
    np.testing.assert_array_equal(ga["index"], gb["index"])
    np.testing.assert_array_equal(ga["n"], gb["n"])
    np.testing.assert_allclose(ga["cov"], gb["cov"], rtol=1e-9, atol=1e-15)


def _queue_kernel(threads, chunk):
    q = make_queue(threads, cpu=True)

    @ti.kernel
    def take(
        taken: ti.types.ndarray(dtype=ti.i32, ndim=1),
        seq: ti.types.ndarray(dtype=ti.i32, ndim=1),
        ctr: ti.types.ndarray(dtype=ti.i64, ndim=1),
        n: ti.i32,
    ):
        for wq in range(q.span(n, chunk)):
            j = q.first(wq, ctr, 0)
            while j < q.end(n, chunk):
                for i in range(q.begin(j, n, chunk), q.stop(j, n, chunk)):
                    ti.atomic_add(taken[i], 1)
                    seq[i] = j
                j = q.next(ctr, 0)

    return take


@pytest.mark.parametrize("threads", [1, 2, 3, 4, 16])
@pytest.mark.parametrize("chunk", [1, 7, 64, 1024])  # 1024: the rays' chunk on 1-2 threads
def test_queue_takes_every_item_once(threads, chunk):
    take = _queue_kernel(threads, chunk)
    for n in (0, 1, chunk - 1, chunk, chunk + 1, 2 * chunk + 3, 1000, 57455):
        taken, seq, ctr = np.zeros(n, np.int32), np.full(n, -1, np.int32), np.zeros(1, np.int64)
        take(taken, seq, ctr, n)
        np.testing.assert_array_equal(taken, np.ones(n, np.int32))
        # Chunks alternate between the two halves: the chunk taken second starts half way.
        if n >= 4 * chunk:
            half = -(-n // (2 * chunk)) * chunk
            assert seq[0] == 0 and seq[half] == 1 and seq[chunk] == 2


def test_the_rays_chunk_follows_the_threads_within_its_bounds():
    from ndtom_ti.kernels.trace import ray_chunk

    assert [ray_chunk(t) for t in (1, 2, 3, 4, 8, 16, 32, 64, 256)] == [1024, 1024, 682, 512, 256, 128, 64, 64, 64]
    assert ray_chunk(0) == 1024  # (no thread count known: as one)
