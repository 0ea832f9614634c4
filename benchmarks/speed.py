#!/usr/bin/env python3
"""Time per scan with the library's defaults against OctoMap, in one process.

    python benchmarks/speed.py                                   # hall, 0.2 m, threads left to the OS
    python benchmarks/speed.py --res 0.1 0.2 0.4 --pin both      # unpinned and pinned, each resolution
    python benchmarks/speed.py --bag ../shared/data/balm_hall_every4 --res 0.2
    python benchmarks/speed.py --profile                          # wall and CPU ms per kernel, per scan
    python benchmarks/speed.py --runs 5                           # 5 fresh processes: each, and the medians

``NdtOmMap(res)`` as a user makes it (NDT miss model, no thread pinning asked), and OctoMap
(pyoctomap ``insertPointCloud``) on the same world points in the same process. Pinning is a
process-wide choice, so ``--pin both`` runs each setting in a fresh child process. Prints the
median ms per scan after two scans of warm-up, and OctoMap's median over ours.
"""

from __future__ import annotations

import argparse
import collections
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def _scans(a) -> list:
    from miss_cost import bag_scans, hall_scans

    return bag_scans(Path(a.bag), a.scans + 2) if a.bag else hall_scans(a.scans + 2, a.seed)


def _octomap_ms(scans, res: float, n: int) -> float:
    import pyoctomap

    tree = pyoctomap.OcTree(res)  # pyright: ignore[reportAttributeAccessIssue]
    times = []
    for pts, T in scans[:n]:
        ok = np.isfinite(pts).all(axis=1)
        w = np.ascontiguousarray(pts[ok].astype(np.float64) @ T[:3, :3].T + T[:3, 3])
        o = np.ascontiguousarray(T[:3, 3])
        t = time.perf_counter()
        tree.insertPointCloud(w, o, -1.0)
        times.append(time.perf_counter() - t)
    return 1e3 * float(np.median(times))


def _profiled(m, scans):
    """Wall and CPU ms per kernel of each scan (ti.sync around every kernel call), the
    scans taken by a map that has not seen them (as when they were timed)."""
    import taichi as ti

    from ndtom_ti.kernels import args

    call = args.Bound.__call__
    cur: dict = {}

    def timed(self, **kw):
        ti.sync()
        w, c = time.perf_counter(), time.process_time()
        out = call(self, **kw)
        ti.sync()
        a, b = cur.get(self.name, (0.0, 0.0))
        cur[self.name] = (a + time.perf_counter() - w, b + time.process_time() - c)
        return out

    args.Bound.__call__ = timed
    per = collections.defaultdict(list)
    try:
        for pts, T in scans:
            cur.clear()
            m.insert_scan(pts, T)
            for k, v in cur.items():
                per[k].append(v)
    finally:
        args.Bound.__call__ = call
    return {
        k: (1e3 * float(np.median([w for w, _ in v])), 1e3 * float(np.median([c for _, c in v])))
        for k, v in per.items()
    }


def run_one(a) -> dict:
    t0 = time.perf_counter()
    import taichi as ti

    import ndtom_ti

    ndtom_ti.init("cpu", pin_threads=a.pin == "on")
    scans = _scans(a)
    out: dict = {"pin": a.pin, "rows": []}
    for res in a.res:
        m = ndtom_ti.NdtOmMap(res)
        t = time.perf_counter()
        m.insert_scan(*scans[0])
        first = time.perf_counter() - t
        m.insert_scan(*scans[1])
        times = []
        for pts, T in scans[2:]:
            ti.sync()
            t = time.perf_counter()
            m.insert_scan(pts, T)
            ti.sync()
            times.append(time.perf_counter() - t)
        row = {"res": res, "ms": 1e3 * float(np.median(times)), "first_s": first, "since_start_s": None}
        if res == a.res[0]:
            row["since_start_s"] = time.perf_counter() - t0
        m.close()
        if a.profile:  # a fresh map: the same scans again into m would make no new cells
            m = ndtom_ti.NdtOmMap(res)
            m.insert_scan(*scans[0])
            m.insert_scan(*scans[1])
            row["kernels"] = _profiled(m, scans[2:])
            m.close()
        if not a.no_octomap:
            row["octomap_ms"] = _octomap_ms(scans[2:], res, min(a.octomap_scans, len(scans) - 2))
        out["rows"].append(row)
    return out


def _child_args(argv: list[str]) -> list[str]:
    """The command line without --pin and --runs (a child runs one setting once)."""
    out, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg in ("--pin", "--runs"):
            skip = True
        elif not arg.startswith(("--pin=", "--runs=")):
            out.append(arg)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bag", help="a recording instead of the synthetic hall")
    ap.add_argument("--seed", type=int, default=101, help="the hall's seed (simworld)")
    ap.add_argument("--scans", type=int, default=20)
    ap.add_argument("--res", type=float, nargs="+", default=[0.2])
    ap.add_argument("--pin", choices=["off", "on", "both"], default="off", help="pin Taichi's threads (default: off)")
    ap.add_argument("--profile", action="store_true", help="ms per kernel (wall, and CPU of all threads)")
    ap.add_argument("--no-octomap", action="store_true")
    ap.add_argument("--octomap-scans", type=int, default=10)
    ap.add_argument(
        "--runs",
        type=int,
        default=1,
        help="fresh processes per setting, alternated; prints each and their medians (a VM's "
        "figures move by up to 25%% between processes)",
    )
    ap.add_argument("--json", action="store_true", help=argparse.SUPPRESS)  # a child's output
    a = ap.parse_args()
    if a.runs < 1:
        ap.error("--runs must be at least 1")
    if a.pin == "both" or a.runs > 1:
        runs = []
        pins = ("off", "on") if a.pin == "both" else (a.pin,)
        for _ in range(a.runs):
            for pin in pins:
                cmd = [sys.executable, __file__, *_child_args(sys.argv[1:]), "--pin", pin, "--json"]
                p = subprocess.run(cmd, capture_output=True, text=True, check=True)
                runs.append(json.loads(p.stdout.strip().splitlines()[-1]))
    else:
        runs = [run_one(a)]
        if a.json:
            print(json.dumps(runs[0]))
            return
    print(f"{'pinned':>6} {'res':>5} {'ndtom ms':>9} {'octomap ms':>10} {'ratio':>6} {'first scan s':>12}")
    for r in runs:
        for row in r["rows"]:
            om = row.get("octomap_ms")
            ratio = f"{om / row['ms']:6.1f}" if om else "     -"
            print(
                f"{r['pin']:>6} {row['res']:5.2f} {row['ms']:9.1f} {om or float('nan'):10.1f} {ratio} "
                f"{row['first_s']:12.2f}"
            )
            for k, (w, c) in sorted(row.get("kernels", {}).items(), key=lambda kv: -kv[1][0]):
                print(f"{'':13}{k:16} {w:7.2f} ms wall {c:7.2f} ms cpu")
    if a.runs > 1:
        print(f"medians of {a.runs} processes each:")
        by = collections.defaultdict(list)
        for r in runs:
            for row in r["rows"]:
                by[(r["pin"], row["res"])].append(row)
        for (pin, res), rows in by.items():
            ms = [row["ms"] for row in rows]
            ratios = [row["octomap_ms"] / row["ms"] for row in rows if row.get("octomap_ms")]
            ratio = f"{np.median(ratios):6.1f} ({min(ratios):.1f}-{max(ratios):.1f})" if ratios else "     -"
            print(f"{pin:>6} {res:5.2f} {np.median(ms):9.1f} ms ({min(ms):.1f}-{max(ms):.1f})  ratio {ratio}")


if __name__ == "__main__":
    main()
