#!/usr/bin/env python3
"""Resolution sweep on the synthetic hall (../shared/tools/simworld.py --variant hall
--stride 10: HDL-32-like, ~57k points per scan, 70 m range) or on a recording, with
NDT-OM, its floor mode and OctoMap (pyoctomap) on the same points in the same run.

    python benchmarks/sweep_hall.py --scans 20 --out out/bench_hall
    python benchmarks/sweep_hall.py --bag ../shared/data/balm_hall_every4 --scans 20 --out out/bench_balm
    python benchmarks/sweep_hall.py --scans 20 --miss-model paper   # the paper's eq. (12)
"""

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"


def hall_scans(n: int) -> list:
    sim = SHARED / "tools" / "simworld.py"
    out = Path(tempfile.mkdtemp(prefix="ndtom_hall_"))
    subprocess.run(
        [
            sys.executable,
            str(sim),
            "--variant",
            "hall",
            "--stride",
            "10",
            "--scans",
            str(n),
            "--no-bags",
            "--out",
            str(out),
        ],
        check=True,
        capture_output=True,
    )
    sys.path.insert(0, str(sim.parent))
    import simworld

    d = simworld.SimDataset(out / "hall.npz")
    return [(d.scan(i), d.poses[i]) for i in range(d.n_scans)]


def bag_scans(path: str, n: int) -> list:
    from ndtom_ti.io import open_recording

    with open_recording(path) as rec:
        return [(s.points, s.T_world_sensor) for s in rec.scans(max_scans=n)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bag", help="a recording instead of the synthetic hall")
    ap.add_argument("--scans", type=int, default=20)
    ap.add_argument("--resolutions", default="0.1,0.2,0.4,0.8")
    ap.add_argument("--no-octomap", action="store_true")
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"])
    ap.add_argument("--miss-model", choices=["ndt", "paper"], help="NDT-OM's miss model (default: MapConfig's)")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "bench")
    a = ap.parse_args()

    import ndtom_ti
    from ndtom_ti.evaluation import sweep

    arch = ndtom_ti.init(a.arch, pin_threads=True)  # as the ndtom command runs
    scans = bag_scans(a.bag, a.scans) if a.bag else hall_scans(a.scans)
    res = [float(x) for x in a.resolutions.split(",")]
    baseline = None if a.no_octomap or not sweep.octomap_available() else "octomap"
    config = ndtom_ti.MapConfig(miss_model=a.miss_model) if a.miss_model else None
    rows = sweep.run_sweep(scans, res, baseline=baseline, progress=lambda s: print(s, file=sys.stderr), config=config)
    a.out.mkdir(parents=True, exist_ok=True)
    name = Path(a.bag).stem if a.bag else "hall"
    tags = {**sweep.machine_tags(arch), "data": name}  # the rows hold the number of scans
    sweep.write_csv(rows, a.out / f"sweep_{name}.csv", tags)
    sweep.plot(rows, a.out / f"sweep_{name}.png", f"{name}, {len(scans)} scans, {arch}, {tags['cores']} cores")
    print(
        f"{'mapper':12} {'res':>5} {'median ms':>10} {'p95 ms':>8} {'Mvisits/s':>9} {'x ndtom':>8} {'Gaussians':>9} {'MiB':>7}"
    )
    for r in rows:
        print(
            f"{r.mapper:12} {r.resolution:5.2f} {r.ms_median:10.1f} {r.ms_p95:8.1f} {r.visits_per_s / 1e6:9.1f} "
            f"{r.ratio_to_ndtom:8.2f} {'-' if r.gaussians is None else r.gaussians:>9} "
            f"{r.memory_bytes / 2**20:7.1f}"
        )
    print(f"points/scan {np.mean([len(p) for p, _ in scans]):.0f}; csv and png in {a.out}")


if __name__ == "__main__":
    main()
