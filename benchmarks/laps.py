#!/usr/bin/env python3
"""Memory follows the place, not the run: map several laps of the synthetic hall (dense
HDL-32-like scans, ../shared/tools/simworld.py --stride 10 --static) and print the map's
memory at the end of every lap. The paper's promise: no growth after the first lap.

By default every lap drives the same poses (the speed makes one lap exactly --lap-scans
scans), so only the range noise differs; --speed 1 lets the poses drift 0.15 m per lap
(a 102.85 m loop), so each lap also sees surface the earlier ones missed.

    python benchmarks/laps.py --laps 3 --res 0.2
"""

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SIM = ROOT.parent / "shared" / "tools" / "simworld.py"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--laps", type=int, default=3)
    ap.add_argument("--res", type=float, default=0.2)
    ap.add_argument("--lap-scans", type=int, default=103, help="scans per lap (one kept per second)")
    ap.add_argument("--speed", type=float, default=None, help="m/s (default: one lap per --lap-scans seconds)")
    a = ap.parse_args()
    sys.path.insert(0, str(SIM.parent))
    import simworld

    import ndtom_ti

    lap = a.lap_scans
    speed = a.speed or simworld.build_hall(0).path.length / lap
    out = Path(tempfile.mkdtemp(prefix="ndtom_laps_"))
    subprocess.run(
        [
            sys.executable,
            str(SIM),
            "--scans",
            str(a.laps * lap),
            "--stride",
            "10",
            "--static",
            "--no-bags",
            "--speed",
            repr(speed),
            "--out",
            str(out),
        ],
        check=True,
        capture_output=True,
    )
    print(f"{a.laps} laps of {lap} scans at {speed:.4f} m/s, {a.res:g} m")

    ndtom_ti.init("cpu", pin_threads=True)  # as the ndtom command runs
    d = simworld.SimDataset(out / "hall.npz")
    m = ndtom_ti.NdtOmMap(a.res)
    first = None
    for i in range(d.n_scans):
        m.insert_scan(d.scan(i), d.poses[i])
        if (i + 1) % lap == 0:
            r = m.memory_report()
            mem = r["total_bytes"]
            first = first or mem
            print(
                f"lap {(i + 1) // lap}: {mem / 2**20:8.1f} MiB ({100 * (mem / first - 1):+.1f}% vs lap 1): "
                f"nodes {r['node_bytes'] / 2**20:.1f} MiB, records {r['record_bytes'] / 2**20:.1f} MiB "
                f"({r['records_in_use']} in use), {r['gaussians']} Gaussians, {r['known_cells']} cells known"
            )


if __name__ == "__main__":
    main()
