#!/usr/bin/env python3
"""Wall Gaussians each miss model keeps on real recordings, against Recursive NDT (no ray
tracing) on the same scans: a model that erases static surface loses walls here.

    python benchmarks/walls.py                      # BALM at 0.2 m, TUM fr2 at 0.05 m
    python benchmarks/walls.py --recording ../shared/data/balm_hall_every4 --res 0.4

A wall Gaussian is planar (smallest eigenvalue < 0.1 x the middle one) with its normal within
17 degrees of horizontal. Printed per model: its walls, how many of them are Recursive NDT's
(and that share of Recursive NDT's walls), and the median thickness sqrt(l1) of its walls.
"""

import argparse
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
DEFAULTS = [(DATA / "balm_hall_every4", 0.2), (DATA / "tum_fr2_pioneer_slam2_10f.bag", 0.05)]


def walls(g: dict) -> tuple[np.ndarray, np.ndarray]:
    """Cell indices and thickness (m) of the wall Gaussians among ``g``."""
    w, V = np.linalg.eigh(g["cov"])
    keep = (w[:, 0] < 0.1 * w[:, 1]) & (np.abs(V[:, 2, 0]) < np.sin(np.radians(17.0)))
    return g["index"][keep], np.sqrt(np.maximum(w[keep, 0], 0.0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recording", type=Path, help="a .bag file or ROS2 folder (default: BALM and TUM)")
    ap.add_argument("--res", type=float, default=0.2)
    a = ap.parse_args()

    import ndtom_ti
    from ndtom_ti import MapConfig, NdtOmMap
    from ndtom_ti.cellkeys import isin_rows
    from ndtom_ti.io import open_recording

    ndtom_ti.init()
    runs = [(a.recording, a.res)] if a.recording else DEFAULTS
    print(
        f"{'recording':34} {'res':>5} {'scans':>5} {'model':>14} {'walls':>7} {'of RCU':>7} {'share':>6} {'thick mm':>8}"
    )
    for path, res in runs:
        maps = {
            "Recursive NDT": NdtOmMap(res, occupancy=False),
            "ndt": NdtOmMap(res, config=MapConfig(miss_model="ndt")),
            "paper": NdtOmMap(res, config=MapConfig(miss_model="paper")),
        }
        n = 0
        with open_recording(path) as rec:
            for scan in rec.scans():
                for m in maps.values():
                    m.insert_scan(scan.points, scan.T_world_sensor)
                n += 1
        ref, _ = walls(maps["Recursive NDT"].gaussians(min_probability=0.0))
        for name, m in maps.items():
            idx, thick = walls(m.gaussians(min_probability=0.0) if name == "Recursive NDT" else m.gaussians())
            both = int(isin_rows(ref, idx).sum())
            print(
                f"{Path(path).name:34} {res:5.2f} {n:5d} {name:>14} {len(idx):7d} {both:7d} "
                f"{100 * both / max(len(ref), 1):5.1f}% {1000 * np.median(thick) if len(thick) else 0:8.2f}"
            )
            m.close()


if __name__ == "__main__":
    main()
