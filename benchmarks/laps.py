#!/usr/bin/env python3
"""Memory follows the place, not the run: map several laps of the synthetic hall (dense
HDL-32-like scans, ../shared/tools/simworld.py --stride 10 --static) and print the map's
memory at the end of every lap. The paper's promise: no growth after the first lap.

    python benchmarks/laps.py --laps 3 --res 0.2
"""

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SIM = ROOT.parent / "shared" / "tools" / "simworld.py"
LAP_SCANS = 103  # ~103 m loop at 1 m per scan (1 m/s, one scan kept per second)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--laps", type=int, default=3)
    ap.add_argument("--res", type=float, default=0.2)
    a = ap.parse_args()
    out = Path(tempfile.mkdtemp(prefix="ndtom_laps_"))
    n = a.laps * LAP_SCANS
    subprocess.run([sys.executable, str(SIM), "--scans", str(n), "--stride", "10", "--static", "--no-bags",
                    "--out", str(out)], check=True, capture_output=True)  # fmt: skip
    sys.path.insert(0, str(SIM.parent))
    import simworld

    import ndtom_ti

    ndtom_ti.init("cpu")
    d = simworld.SimDataset(out / "hall.npz")
    m = ndtom_ti.NdtOmMap(a.res)
    first = None
    for i in range(d.n_scans):
        m.insert_scan(d.scan(i), d.poses[i])
        if (i + 1) % LAP_SCANS == 0:
            mem = m.memory_bytes()
            first = first or mem
            print(f"lap {(i + 1) // LAP_SCANS}: {mem / 2**20:8.1f} MiB ({100 * (mem / first - 1):+.1f}% vs lap 1), "
                  f"{len(m)} Gaussians")  # fmt: skip


if __name__ == "__main__":
    main()
