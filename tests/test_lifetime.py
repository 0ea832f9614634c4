"""Map lifetimes: close(), `with`, and a named error when every map slot is taken."""

import gc

import numpy as np
import pytest

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
