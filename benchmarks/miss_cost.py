"""Cost of the NDT miss model against the paper's eq. (12), paired in one process: two maps
of the same scans, one per model, fed scan by scan in alternation (the first scans of each
model warm up its kernels first).

    python benchmarks/miss_cost.py --res 0.1 0.2 0.4 --scans 20

Scans: the synthetic hall of shared/tools/simworld.py (60 scans one second apart, seed 7),
or --bag PATH for a recording. Prints median ms per scan of each model and their ratio.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import ndtom_ti
from ndtom_ti import MapConfig, NdtOmMap

ROOT = Path(__file__).resolve().parents[1]
SIMWORLD = ROOT.parent / "shared" / "tools" / "simworld.py"


def hall_scans(n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run(
            [
                sys.executable,
                str(SIMWORLD),
                "--scans",
                str(n),
                "--stride",
                "10",
                "--seed",
                str(seed),
                "--no-bags",
                "--out",
                tmp,
            ],
            check=True,
            capture_output=True,
        )
        z = np.load(Path(tmp) / "hall.npz")
        out = []
        for i in range(len(z["poses"])):
            a, b = z["scan_offsets"][i], z["scan_offsets"][i + 1]
            out.append((np.ascontiguousarray(z["points"][a:b][~z["no_return"][a:b]]), z["poses"][i]))
        return out


def bag_scans(path: Path, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    from ndtom_ti.io import open_recording

    with open_recording(path) as rec:
        return [(np.ascontiguousarray(s.points, np.float32), s.T_world_sensor) for s in rec.scans(max_scans=n)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", type=float, nargs="+", default=[0.1, 0.2, 0.4])
    ap.add_argument("--scans", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--bag", type=Path, default=None)
    a = ap.parse_args(argv)
    ndtom_ti.init(pin_threads=True)  # as the ndtom command runs
    n = a.scans + a.warmup
    scans = bag_scans(a.bag, n) if a.bag else hall_scans(n, a.seed)
    print(f"{'res':>5} {'paper ms':>9} {'ndt ms':>8} {'ndt/paper':>9}  ({len(scans) - a.warmup} scans paired)")
    for res in a.res:
        maps = {m: NdtOmMap(res, config=MapConfig(miss_model=m)) for m in ("paper", "ndt")}
        times: dict[str, list[float]] = {m: [] for m in maps}
        for k, (pts, T) in enumerate(scans):
            order = list(maps) if k % 2 == 0 else list(maps)[::-1]
            for m in order:
                t0 = time.perf_counter()
                maps[m].insert_scan(pts, T)
                if k >= a.warmup:
                    times[m].append(time.perf_counter() - t0)
        med = {m: 1e3 * float(np.median(t)) for m, t in times.items()}
        ratio = float(np.median(np.array(times["ndt"]) / np.array(times["paper"])))
        print(f"{res:>5g} {med['paper']:>9.2f} {med['ndt']:>8.2f} {ratio:>9.3f}")
        del maps
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
