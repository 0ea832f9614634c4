"""Taichi's CPU workers fixed one to a CPU (affinity.py)."""

import os
import subprocess
import sys
import threading

import pytest

import ndtom_ti
from ndtom_ti import affinity, runtime
from ndtom_ti.kernels.ndt import cpu_threads

linux_cpu = pytest.mark.skipif(
    not sys.platform.startswith("linux") or ndtom_ti.current_arch() != "cpu", reason="Linux CPU backend only"
)


def _cpus() -> list[int]:
    return sorted(os.sched_getaffinity(0))


@linux_cpu
def test_workers_pinned_one_per_cpu():
    if os.environ.get("NDTOM_PIN_THREADS", "1") in ("0", "") or cpu_threads() != len(_cpus()) or cpu_threads() < 2:
        pytest.skip("pinning is off in this process, or Taichi's threads are not one per CPU")
    pinned = runtime.pinned_threads()
    assert len(pinned) == cpu_threads()
    tids, cpus = zip(*pinned)
    assert sorted(cpus) == _cpus()
    assert threading.get_native_id() not in tids
    for tid, cpu in pinned:
        assert os.sched_getaffinity(tid) == {cpu}
    # The probe finds the same threads again: they are the ones that run Taichi's loops.
    assert affinity.pool_threads(cpu_threads()) == sorted(tids)


@linux_cpu
def test_no_pinning_unless_one_thread_per_cpu():
    # Fewer threads than CPUs (CPUs shared with other work), more, or one: left alone.
    n = len(_cpus())
    assert affinity.pin_pool(1) == []
    assert affinity.pin_pool(n + 1) == []
    if n > 2:
        assert affinity.pin_pool(n - 1) == []


@linux_cpu
def test_workers_not_found_pins_nothing(monkeypatch):
    monkeypatch.setattr(affinity, "_run_times", lambda: {})
    assert affinity.pool_threads(cpu_threads()) == []


@pytest.mark.parametrize("env, expect", [("0", False), ("1", True)])
@linux_cpu
def test_environment_switch(env, expect):
    if len(_cpus()) < 2:
        pytest.skip("one CPU: nothing to pin")
    code = "import ndtom_ti; from ndtom_ti import runtime; ndtom_ti.init('cpu'); print(len(runtime.pinned_threads()))"
    out = subprocess.run([sys.executable, "-c", code], env={**os.environ, "NDTOM_PIN_THREADS": env},
                         capture_output=True, text=True, check=True)  # fmt: skip
    assert (int(out.stdout.split()[-1]) == len(_cpus())) is expect
