"""Start-up time: import, init and the first scan (kernels compiled, or loaded from
Taichi's offline cache when warm: run it twice).

    python benchmarks/startup.py             # 50k random points around the sensor
    python benchmarks/startup.py --hall 101  # the first scan of the simulated hall (57k points)

The hall's scan is made by the simulator before the clock starts and read after it, as a
user's first scan would be; the random scan's rays fill a cube of 80 m, so its first scan
also waits for ~128 MiB of fresh memory (the dense block).
"""

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SIMWORLD = Path(__file__).resolve().parents[2] / "shared" / "tools" / "simworld.py"

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--hall", type=int, metavar="SEED", help="the simulated hall's first scan, this seed")
a = ap.parse_args()
tmp = tempfile.TemporaryDirectory()
if a.hall is not None:
    cmd = [sys.executable, str(SIMWORLD), "--scans", "1", "--seed", str(a.hall), "--no-bags", "--out", tmp.name]
    subprocess.run(cmd, check=True, capture_output=True)

t0 = time.perf_counter()
import numpy as np  # noqa: E402

import ndtom_ti  # noqa: E402

t1 = time.perf_counter()
ndtom_ti.init("cpu")  # the library's defaults
m = ndtom_ti.NdtOmMap(0.2)
if a.hall is None:
    pts, pose = np.random.default_rng(0).normal(size=(50_000, 3)) * 10.0, np.eye(4)
else:
    z = np.load(Path(tmp.name) / "hall.npz")
    end = z["scan_offsets"][1]
    pts, pose = z["points"][:end][~z["no_return"][:end]], z["poses"][0]
m.insert_scan(pts, pose)
t2 = time.perf_counter()
print(f"import {t1 - t0:.2f} s, init + first scan {t2 - t1:.2f} s, total {t2 - t0:.2f} s ({len(pts):,} points)")
