"""Taichi's CPU workers fixed one to a CPU (affinity.py)."""

import os
import subprocess
import sys

import pytest

import ndtom_ti
from ndtom_ti import affinity
from ndtom_ti.kernels.ndt import cpu_threads

linux_cpu = pytest.mark.skipif(
    not sys.platform.startswith("linux") or ndtom_ti.current_arch() != "cpu", reason="Linux CPU backend only"
)


def _cpus() -> list[int]:
    return sorted(os.sched_getaffinity(0))


PINNED = """
import os, threading, ndtom_ti
from ndtom_ti import affinity, runtime
from ndtom_ti.kernels.ndt import cpu_threads
ndtom_ti.init("cpu", pin_threads=True)
pinned = runtime.pinned_threads()
tids = sorted(t for t, _ in pinned)
print("N", len(pinned), cpu_threads(), len(os.sched_getaffinity(0)))
print("CPUS", sorted(c for _, c in pinned) == sorted(os.sched_getaffinity(0)))
print("MAIN", threading.get_native_id() not in tids)
print("SET", all(os.sched_getaffinity(t) == {c} for t, c in pinned))
print("PROBE", affinity.pool_threads(cpu_threads()) == tids)
"""


@linux_cpu
def test_workers_pinned_one_per_cpu():
    if len(_cpus()) < 2:
        pytest.skip("one CPU: nothing to pin")
    out = subprocess.run(
        [sys.executable, "-c", PINNED],
        env={k: v for k, v in os.environ.items() if k != "NDTOM_PIN_THREADS"},
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    got = dict(line.split(" ", 1) for line in out.strip().splitlines())
    n, threads, cpus = map(int, got["N"].split())
    if threads != cpus:
        pytest.skip("Taichi's threads are not one per CPU")
    assert n == cpus
    # The probe finds the same threads again: they are the ones that run Taichi's loops.
    assert got["CPUS"] == got["MAIN"] == got["SET"] == got["PROBE"] == "True", got


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
    monkeypatch.setattr(affinity, "_run_times", lambda: {})  # private: the threads' run times, none found
    assert affinity.pool_threads(cpu_threads()) == []


@pytest.mark.parametrize("env, expect", [(None, False), ("0", False), ("1", True)])
@linux_cpu
def test_environment_switch(env, expect):
    """The library leaves the threads alone unless asked (NDTOM_PIN_THREADS=1)."""
    if len(_cpus()) < 2:
        pytest.skip("one CPU: nothing to pin")
    code = "import ndtom_ti; from ndtom_ti import runtime; ndtom_ti.init('cpu'); print(len(runtime.pinned_threads()))"
    environ = {k: v for k, v in os.environ.items() if k != "NDTOM_PIN_THREADS"}
    if env is not None:
        environ["NDTOM_PIN_THREADS"] = env
    out = subprocess.run([sys.executable, "-c", code], env=environ, capture_output=True, text=True, check=True)
    assert (int(out.stdout.split()[-1]) == len(_cpus())) is expect


@pytest.mark.parametrize("option, expect", [("--pin-threads", True), ("--no-pin-threads", False)])
@linux_cpu
def test_the_command_pins_unless_told_not_to(option, expect):
    if len(_cpus()) < 2:
        pytest.skip("one CPU: nothing to pin")
    # private: the command's root callback (it takes the option) alone, without a command to run
    code = (
        "import sys; from ndtom_ti import runtime; from ndtom_ti.cli import common, root; "
        "root._main(pin_threads=sys.argv[1] == '--pin-threads'); "
        "common.init_taichi(common.Arch.cpu); print(len(runtime.pinned_threads()))"
    )
    environ = {k: v for k, v in os.environ.items() if k != "NDTOM_PIN_THREADS"}
    out = subprocess.run([sys.executable, "-c", code, option], env=environ, capture_output=True, text=True, check=True)
    assert (int(out.stdout.split()[-1]) == len(_cpus())) is expect
