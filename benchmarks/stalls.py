"""Time every scan of a run in a fresh process: kernels compile at the first scan only.

    python benchmarks/stalls.py --bag ../shared/data/balm_hall_every4 --res 0.2
    python benchmarks/stalls.py --res 0.2          # the synthetic hall (simworld, 40 scans)

Prints the first scan, the median and p95 of the others, and the worst of them against the
median (no scan after the first should take more than a few times the median).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import ndtom_ti
from ndtom_ti import MapConfig, NdtOmMap

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bag", type=Path, default=None)
    ap.add_argument("--res", type=float, default=0.2)
    ap.add_argument("--scans", type=int, default=40)
    ap.add_argument("--miss-model", default=MapConfig().miss_model, choices=["ndt", "paper"])
    a = ap.parse_args(argv)
    if a.bag:
        from miss_cost import bag_scans

        scans = bag_scans(a.bag, a.scans)
    else:
        from miss_cost import hall_scans

        scans = hall_scans(a.scans, 7)
    t0 = time.perf_counter()
    ndtom_ti.init(pin_threads=True)  # as the ndtom command runs
    m = NdtOmMap(a.res, config=MapConfig(miss_model=a.miss_model))
    t_init = time.perf_counter() - t0
    times, sizes = [], []
    for pts, T in scans:
        t = time.perf_counter()
        m.insert_scan(pts, T)
        times.append(1e3 * (time.perf_counter() - t))
        sizes.append(len(pts))
    rest = np.array(times[1:])
    med = float(np.median(rest))
    worst = int(np.argmax(rest)) + 1
    print(
        f"init {t_init * 1e3:.0f} ms; first scan {times[0]:.0f} ms; later scans median {med:.1f} ms, "
        f"p95 {np.percentile(rest, 95):.1f} ms; worst scan {worst} ({sizes[worst]} points) {times[worst]:.1f} ms "
        f"= {times[worst] / med:.2f} x the median; points per scan {min(sizes)}-{max(sizes)}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
