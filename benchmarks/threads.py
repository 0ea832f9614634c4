#!/usr/bin/env python3
"""How many of Taichi's CPU workers a short parallel loop gets, left to the scheduler and
then pinned (one CPU each, ``ndtom_ti/affinity.py``), in one process.

    python benchmarks/threads.py                      # loops of 1, 2, 5, 10, 20 ms of CPU
    python benchmarks/threads.py --sizes 0.5 3 --repeats 21

Most loops of a scan last 0.5-10 ms. On a machine whose scheduler puts a woken thread
beside the thread that woke it, such a loop runs on one CPU until the other worker is moved:
"busy" (CPU time over wall time, all threads of the process) stays near 1 until pinned.
Unpinned first: a pinned thread cannot be handed back to the scheduler as it was.
"""

import argparse
import os
import statistics
import time

import numpy as np


def _loop(ti):
    @ti.kernel
    def spin(out: ti.types.ndarray(dtype=ti.f64, ndim=1), it: ti.i32):  # pyright: ignore[reportInvalidTypeForm] (Taichi)
        for i in range(out.shape[0]):  # ALU only: no memory traffic to share
            x = ti.cast(i, ti.f64) * 1e-9
            for _ in range(it):
                x = x * 0.999999 + 1e-7
            out[i] = x

    return spin


def _time(spin, out, it: int, repeats: int) -> tuple[float, float]:
    """Median wall and CPU seconds of one call."""
    import taichi as ti

    walls, cpus = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        spin(out, it)
        ti.sync()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return statistics.median(walls), statistics.median(cpus)


def _sweep(spin, out, iters: list[int], repeats: int) -> list[tuple[float, float]]:
    return [_time(spin, out, it, repeats) for it in iters]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=float, nargs="+", default=[1, 2, 5, 10, 20], help="loop lengths, ms of CPU")
    p.add_argument("--repeats", type=int, default=11)
    a = p.parse_args(argv)
    if a.repeats < 1 or min(a.sizes) <= 0:
        p.error("--repeats must be at least 1 and --sizes positive")

    from ndtom_ti.kernels.ndt import cpu_threads

    import ndtom_ti
    from ndtom_ti.affinity import pin_pool

    ndtom_ti.init("cpu")
    import taichi as ti

    threads = cpu_threads()
    spin = _loop(ti)
    out = np.zeros(4 * 1024)
    spin(out, 1)  # compiled
    # Calibration: CPU seconds per inner iteration (all items), from a loop long enough
    # for every worker to take part.
    base = 2000
    _, cpu = _time(spin, out, base, 3)
    per_it = cpu / base
    iters = [max(1, round(ms / 1e3 / per_it)) for ms in a.sizes]

    free = _sweep(spin, out, iters, a.repeats)
    pinned = pin_pool(threads)
    tied = _sweep(spin, out, iters, a.repeats) if pinned else None

    print(f"{threads} Taichi CPU worker(s), {os.cpu_count()} CPU(s); medians of {a.repeats} calls")
    print(f"{'loop ms':>8} {'unpinned ms':>12} {'busy':>5} {'pinned ms':>10} {'busy':>5}")
    for i, ms in enumerate(a.sizes):
        fw, fc = free[i]
        row = f"{ms:8.1f} {1e3 * fw:12.2f} {fc / fw:5.2f}"
        if tied:
            tw, tc = tied[i]
            row += f" {1e3 * tw:10.2f} {tc / tw:5.2f}"
        print(row)
    if not pinned:
        print("not pinned: pinning needs Linux and one worker per CPU this process may use")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
