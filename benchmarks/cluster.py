"""One map from several Ray workers against one process: wall time a scan, total CPU, and
what crosses between processes a scan, on the same scans (the maps are checked equal).

    python benchmarks/cluster.py --bag ../shared/data/balm_hall_every4 --res 0.2 --workers 2 --threads 1
    python benchmarks/cluster.py --sim --scans 24 --tile-size 8

The one-process map runs in this process on workers x threads Taichi threads; the tiled
map on a local Ray cluster of ``workers`` processes of ``threads`` threads each.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SHARED = HERE.parent.parent / "shared"


def load_scans(args) -> list:
    if args.sim:
        sys.path.insert(0, str(SHARED / "tools"))
        import simworld

        out = Path(tempfile.mkdtemp())
        subprocess.run(
            [sys.executable, str(SHARED / "tools" / "simworld.py"), "--scans", str(args.scans), "--stride", "10"]
            + ["--no-bags", "--seed", str(args.seed), "--out", str(out)],
            check=True,
            capture_output=True,
        )
        d = simworld.SimDataset(out / "hall.npz")
        return [(d.scan(i), d.poses[i]) for i in range(d.n_scans)]
    from ndtom_ti.io import open_recording

    with open_recording(args.bag) as rec:
        return [(s.points, s.T_world_sensor) for s in rec.scans(max_scans=args.scans)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bag", type=Path, default=SHARED / "data" / "balm_hall_every4")
    ap.add_argument("--sim", action="store_true", help="a simulated hall instead of --bag")
    ap.add_argument("--seed", type=int, default=4242)
    ap.add_argument("--res", type=float, default=0.2)
    ap.add_argument("--scans", type=int, default=30)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1, help="Taichi threads per worker")
    ap.add_argument("--tile-size", type=float, default=16.0)
    ap.add_argument("--model", default="ndt")
    args = ap.parse_args()

    import ndtom_ti
    from ndtom_ti import NdtOmMap
    from ndtom_ti.cellstate import ARRAYS
    from ndtom_ti.cluster import TiledMap

    ndtom_ti.init("cpu", cpu_max_num_threads=args.workers * args.threads)
    scans = load_scans(args)
    print(f"{len(scans)} scans, {np.mean([len(p) for p, _ in scans]):.0f} points a scan, {args.res} m")

    k = min(2, len(scans) - 1)  # the first scans compile: times and CPU from scan k on
    walls = []
    with NdtOmMap(args.res, miss_model=args.model) as m:
        for i, (p, T) in enumerate(scans):
            if i == k:
                cpu0 = time.process_time()
            t = time.perf_counter()
            m.insert_scan(p, T)
            walls.append(time.perf_counter() - t)
        cpu_one = time.process_time() - cpu0
        one = m.snapshot()

    t_start = time.perf_counter()
    with TiledMap(
        args.res,
        workers=args.workers,
        tile_size=args.tile_size,
        threads=args.threads,
        miss_model=args.model,
        probe=False,
    ) as tm:
        started = time.perf_counter() - t_start
        twalls = []
        for i, (p, T) in enumerate(scans):
            if i == k:
                cpu_before = sum(s["cpu_seconds"] for s in tm.stats())
                drv0 = time.process_time()
            t = time.perf_counter()
            tm.insert_scan(p, T)
            twalls.append(time.perf_counter() - t)
        stats = tm.stats()
        cpu_tiled = sum(s["cpu_seconds"] for s in stats) - cpu_before + time.process_time() - drv0
        events = sum(s["event_bytes"] for s in stats)
        tiled = tm.snapshot()
        scan_bytes = tm.scan_bytes
    same = all(np.array_equal(getattr(one, n), getattr(tiled, n)) for n in ARRAYS)
    n = len(scans)
    print(
        f"one process ({args.workers * args.threads} threads): median {statistics.median(walls[k:]) * 1e3:.1f} ms a scan, "
        f"CPU {cpu_one:.1f} s from scan {k + 1} on"
    )
    print(
        f"{args.workers} Ray workers x {args.threads} thread(s), tiles of {args.tile_size} m: started in {started:.1f} s, "
        f"median {statistics.median(twalls[k:]) * 1e3:.1f} ms a scan ({statistics.median(twalls[k:]) / statistics.median(walls[k:]):.2f}x), "
        f"CPU {cpu_tiled:.1f} s ({cpu_tiled / cpu_one:.2f}x; the workers and this driver)"
    )
    print(f"traffic a scan: the scan {scan_bytes / n / 1e6:.2f} MB to each worker's host, events {events / n:.0f} B")
    print(f"maps equal: {same}")


if __name__ == "__main__":
    main()
