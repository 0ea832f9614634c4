"""Map lifetimes: close(), `with`, and a named error when every map slot is taken."""

import gc
import os

import numpy as np
import pytest
from conftest import run_py

from ndtom_ti import NdtOmMap, NoFreeSlotError, runtime


@pytest.fixture(autouse=True)
def _free_maps():
    gc.collect()
    yield
    gc.collect()


def scan(rng):
    return rng.normal(size=(500, 3)) * 2.0 + [5.0, 0.0, 0.0], np.eye(4)


def test_close_gives_the_slot_back_at_once_and_the_map_refuses_use(rng):
    m = NdtOmMap(0.5)
    m.insert_scan(*scan(rng))
    st = runtime.storage(m.layout)
    slot = m._slot.index  # private: the slot's number (slots are the process's internals, no public API)
    assert slot not in st.free_slots and st.nodes(slot).sum() > 0
    m.close()
    assert m.closed and slot in st.free_slots and st.nodes(slot).sum() == 0
    for call in (
        lambda: m.insert_scan(*scan(rng)),
        m.known_cells,
        m.gaussians,
        lambda: len(m),
        m.memory_report,
        lambda: m.save("x.ndtom"),
    ):
        with pytest.raises(ValueError, match="closed"):
            call()
    assert "closed" in repr(m)
    m.close()  # again: nothing
    m = None
    gc.collect()
    assert st.free_slots.count(slot) == 1  # the collector did not release it twice


def test_with_closes_the_map_even_on_an_error(rng):
    with NdtOmMap(0.5) as m:
        m.insert_scan(*scan(rng))
        slot = m._slot.index  # private: the slot's number (slots are the process's internals, no public API)
        assert len(m) > 0
    assert m.closed and slot in runtime.storage(m.layout).free_slots
    with pytest.raises(RuntimeError, match="boom"), NdtOmMap(0.5) as m2:
        raise RuntimeError("boom")
    assert m2.closed


def test_no_free_slot_is_a_named_error_that_says_what_to_do():
    st = runtime.storage(NdtOmMap(0.5).layout)
    gc.collect()
    held = [NdtOmMap(0.5) for _ in range(len(st.free_slots))]
    with pytest.raises(NoFreeSlotError, match=r"close\(\)") as err:
        NdtOmMap(0.5)
    assert isinstance(err.value, RuntimeError)  # callers catching RuntimeError still do
    held.pop().close()
    NdtOmMap(0.5).close()  # a slot again
    for m in held:
        m.close()


def test_a_map_the_collector_frees_inside_a_compile_waits_for_the_next_call():
    """A map in a reference cycle (an exception's traceback keeps one) is freed whenever
    the collector runs, also inside Taichi's compile of another map's kernel. Emptying
    its slot there ran a kernel inside the compile, and Python 3.11's parser state then
    failed every later compile ("AST constructor recursion depth mismatch")."""
    code = """
        import gc, numpy as np, ndtom_ti
        ndtom_ti.init("cpu")
        pts = np.random.default_rng(0).normal(size=(2000, 3)) * 0.3 + [3.0, 0.0, 0.0]
        a = ndtom_ti.NdtOmMap(0.2)
        a.insert_scan(pts, np.eye(4))
        a.cycle = a  # a map only the collector frees
        del a
        gc.set_threshold(1)  # collections at (nearly) every allocation, inside the next compile too
        b = ndtom_ti.NdtOmMap(0.2, miss_model="paper")  # kernels this process has not compiled
        b.insert_scan(pts, np.eye(4))
        gc.set_threshold(700)
        c = ndtom_ti.NdtOmMap(0.2)
        c.insert_scan(pts, np.eye(4))
        st = ndtom_ti.runtime.storage(b.layout)
        print("OK", len(b) > 0, len(b) == len(c), st.slots - len(st.free_slots))
    """
    out = run_py(code, timeout=600)
    assert "OK True True 2" in out, out


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork is POSIX only")
def test_a_process_forked_after_the_first_map_refuses_maps_instead_of_hanging():
    """Taichi's worker threads do not survive fork: a map used or made in a child forked after
    the parent's first map hung at its first kernel (multiprocessing's default start method on
    Linux). It is a RuntimeError naming 'spawn' now; snapshots (numpy only) still work, and the
    child's copy of a map is dropped without a kernel."""
    code = """
        import gc, os, numpy as np, ndtom_ti
        m = ndtom_ti.NdtOmMap(0.2)
        m.insert_scan(np.random.default_rng(0).normal(size=(2000, 3)) + [3.0, 0.0, 0.0], np.eye(4))
        snap, n = m.snapshot(), len(m)
        pid = os.fork()
        if pid == 0:  # (it leaves by os._exit, as multiprocessing's children do)
            try:
                out = [len(snap.gaussians()["n"]) == n > 0]
                for use in (lambda: len(m), lambda: ndtom_ti.NdtOmMap(0.2)):
                    try:
                        use()
                        out.append("used")
                    except RuntimeError as exc:
                        out.append("refused" if "'spawn'" in str(exc) else str(exc))
                del m
                gc.collect()
                print("CHILD", *out, flush=True)
            finally:
                os._exit(0)
        os.waitpid(pid, 0)
        m.insert_scan(np.random.default_rng(1).normal(size=(2000, 3)) + [3.0, 0.0, 0.0], np.eye(4))
        print("PARENT", m.scans_inserted, flush=True)
    """
    out = run_py(code, timeout=120)
    assert "CHILD True refused refused" in out and "PARENT 2" in out, out


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork is POSIX only")
def test_a_child_forked_after_the_first_map_ends_by_sys_exit():
    """A child forked from a process running Taichi that left by sys.exit (or the end of its
    code) never ended: Taichi's program, destroyed at exit, waited for worker threads fork did
    not copy. The child ends now, with its own exit status."""
    code = """
        import os, sys, time, numpy as np, ndtom_ti
        m = ndtom_ti.NdtOmMap(0.2)
        m.insert_scan(np.random.default_rng(0).normal(size=(2000, 3)) + [3.0, 0.0, 0.0], np.eye(4))
        pid = os.fork()
        if pid == 0:
            sys.exit(3)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                print("CHILD", os.waitstatus_to_exitcode(status), flush=True)
                break
            time.sleep(0.05)
        else:
            os.kill(pid, 9)
            print("CHILD hung", flush=True)
        m.insert_scan(np.random.default_rng(1).normal(size=(2000, 3)) + [3.0, 0.0, 0.0], np.eye(4))
        print("PARENT", m.scans_inserted, flush=True)
    """
    out = run_py(code, timeout=180)
    assert "CHILD 3" in out and "PARENT 2" in out, out
