#!/usr/bin/env python3
"""Time per scan at one place as the map grows elsewhere, with the NDT miss model reading
the Gaussian records by place (the default) and reading every record, in one process.

    python benchmarks/big_map.py                        # hall, 0.2 m, up to 8 copies of it
    python benchmarks/big_map.py --copies 2 4 16 --scans 10
    python benchmarks/big_map.py --only every          # one map per process, read one way

Two maps take the simulated hall's scans, then copies of them placed ``--spacing`` metres
apart (the map grows where the sensor is not: rows of eight along x), then the hall's last scans again, where
both are timed: scan by scan, alternating between the maps. ``NdtOmMap(res)`` as a user
makes it; the second map's ``plan.index_records`` is set so that it reads every record.
Prints the median ms per scan of each and their ratio at each size of the map. (Each map
is in the other's caches: ``--only`` times one map alone.)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=101, help="the hall's seed (simworld)")
    ap.add_argument("--res", type=float, default=0.2)
    ap.add_argument("--hall-scans", type=int, default=30, help="scans of the hall (and of each copy)")
    ap.add_argument("--scans", type=int, default=8, help="scans timed at each size")
    ap.add_argument("--copies", type=int, nargs="+", default=[2, 4, 8], help="sizes: copies of the hall")
    ap.add_argument("--spacing", type=float, default=300.0, help="metres between copies")
    ap.add_argument(
        "--only",
        choices=("place", "every"),
        help="one map, read that way (the other map's memory traffic left out of the process)",
    )
    a = ap.parse_args(argv)
    if a.scans < 1 or a.hall_scans < 2:
        ap.error("--scans must be at least 1 and --hall-scans at least 2")
    if sorted(a.copies) != a.copies or a.copies[0] < 0:
        ap.error("--copies must be increasing and not negative")

    from miss_cost import hall_scans

    import ndtom_ti

    scans = hall_scans(a.hall_scans, a.seed)
    timed = scans[-a.scans :]
    ndtom_ti.init()
    ways = (a.only,) if a.only else ("place", "every")
    maps = []
    for way in ways:
        m = ndtom_ti.NdtOmMap(a.res)
        if way == "every":
            m.plan.index_records = 2**31 - 1
        maps.append(m)

    def insert(pts, T):
        for m in maps:
            m.insert_scan(pts, T)

    for pts, T in scans:
        insert(pts, T)
    print(f"hall seed {a.seed}, {a.res:g} m: {len(scans)} scans a copy, {a.spacing:g} m apart; {a.scans} scans timed")
    heads = {"place": "by place ms", "every": "every ms"}
    print(
        f"{'copies':>6} {'gaussians':>10} "
        + " ".join(f"{heads[w]:>12}" for w in ways)
        + ("  ratio" if len(ways) == 2 else "")
    )
    done = 0
    for copies in [0, *a.copies]:
        for k in range(done + 1, copies + 1):
            for pts, T in scans:
                T2 = T.copy()  # rows of 8 copies along x, a row further along y every 8
                T2[:2, 3] += a.spacing * np.array([(k - 1) % 8 + 1, (k - 1) // 8])
                insert(pts, T2)
        done = copies
        ms: list[list[float]] = [[] for _ in maps]
        for pts, T in timed:
            for m, out in zip(maps, ms):
                t = time.perf_counter()
                m.insert_scan(pts, T)
                out.append(1e3 * (time.perf_counter() - t))
        med = [float(np.median(x)) for x in ms]
        row = f"{copies:>6} {len(maps[0]):>10,} " + " ".join(f"{v:>12.1f}" for v in med)
        if len(med) == 2:
            row += f" {med[1] / med[0]:>6.2f}"
        print(row, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
