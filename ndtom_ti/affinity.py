"""One CPU per thread of Taichi's CPU thread pool (Linux).

Taichi 1.7's pool wakes all its workers for every parallel loop, and a worker takes the
next run of iterations as soon as it is free. Left to the scheduler on the project's
2-core VM, a loop of ~1 ms ran on both CPUs (0.5 ms) or, by chance, as if on one
(0.9 ms), as when one worker does both halves before the other starts. Most loops of a
scan are that short. Fixed to a CPU of its own, each worker is woken there: hall scans
at 0.4 m took 8.8 ms instead of 9.5 (median) and 9.7 instead of 15 (p90).
Off in the library unless ``init(pin_threads=True)`` or ``NDTOM_PIN_THREADS=1``; on in the
``ndtom`` command unless ``--no-pin-threads`` or ``NDTOM_PIN_THREADS=0``."""

import os
import sys
import threading


def _run_times() -> dict[int, int]:
    """Nanoseconds each thread of this process has run (/proc/self/task/*/schedstat)."""
    out = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/schedstat") as f:
                out[int(tid)] = int(f.read().split()[0])
        except (OSError, ValueError, IndexError):
            continue
    return out


def pool_threads(threads: int) -> list[int]:
    """Thread ids of Taichi's CPU workers: the threads that run while a parallel loop does.
    Empty when they cannot be told apart (not Linux, no schedstat, another count)."""
    if not sys.platform.startswith("linux") or not os.path.exists("/proc/self/task"):
        return []
    import numpy as np
    import taichi as ti

    @ti.kernel
    def probe(out: ti.types.ndarray(dtype=ti.f64, ndim=1)):  # pyright: ignore[reportInvalidTypeForm] (Taichi)
        for i in range(out.shape[0]):
            x = ti.cast(i, ti.f64)
            for _ in range(64):
                x = ti.sqrt(x + 1.0)
            out[i] = x

    buf = np.zeros(1 << 14)
    probe(buf)  # compiled before the counts are read
    main = threading.get_native_id()  # the caller runs no iteration: it waits for the pool
    # On a busy machine one worker may take every iteration while another waits for a CPU:
    # a few tries, each longer than the last.
    for attempt in range(5):
        before = _run_times()
        for _ in range(4 << attempt):
            probe(buf)
        after = _run_times()
        ran = sorted(t for t, ns in after.items() if t != main and ns > before.get(t, ns))
        if len(ran) == threads:
            return ran
    return []


def pin_pool(threads: int) -> list[tuple[int, int]]:
    """Fix each of Taichi's ``threads`` CPU workers to a CPU of its own, when they are as
    many as the CPUs this process may use (Taichi's default). Fewer threads than CPUs
    suggests the CPUs are shared with other work, which pinned threads could not escape.
    Returns the (thread id, cpu) pairs set; none where the workers were not found."""
    try:
        cpus = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return []
    if threads < 2 or threads != len(cpus):
        return []
    workers = pool_threads(threads)
    done = []
    for tid, cpu in zip(workers, cpus):
        try:
            os.sched_setaffinity(tid, {cpu})
        except OSError:
            continue
        done.append((tid, cpu))
    return done
