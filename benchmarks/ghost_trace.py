"""Why the NDT miss model keeps the ghosts it keeps: for each ghost cell left at the end of a
scene (benchmarks/quality.py's scoring), the rays that passed it after its object left, the
NDT terms they gave (float64, from the cell's Gaussian at each scan's start), its points and
record state, and what OctoMap's per-scan miss would have done with the same passes.

    python benchmarks/ghost_trace.py quality/hall_s1001_n60.npz --res 0.4

Prints a summary; --csv writes one row per ghost cell.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
from ndtom_ti.kernels.ndt import NDT_BACK_MISS, NDT_ERASED_NEIGHBOURS, NDT_WIDE

import ndtom_ti
from ndtom_ti import MapConfig, NdtOmMap
from ndtom_ti import quality as q
from ndtom_ti.config import NDT_SPARSE_SIGMA

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))
from reference import ndt_miss_term

OCTO_MISS = math.log(0.4 / 0.6)  # OctoMap's default miss, once per scan a cell is passed
OCTO_MAX = 3.5


def _bench():
    spec = importlib.util.spec_from_file_location("quality_bench", HERE / "quality.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def passing_rays(cell: np.ndarray, res: float, o: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Indices of the rays o -> ends that cross the cell's box and do not end in it."""
    lo, hi = cell * res, (cell + 1) * res
    d = ends - o
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    tmin = np.where(d != 0, np.minimum(t1, t2), np.where((o >= lo) & (o < hi), -np.inf, np.inf)).max(axis=1)
    tmax = np.where(d != 0, np.maximum(t1, t2), np.where((o >= lo) & (o < hi), np.inf, -np.inf)).min(axis=1)
    inside = (np.floor(ends / res) == cell).all(axis=1)
    return np.flatnonzero((tmin <= tmax) & (tmax > 0) & (tmin < 1) & ~inside)


def gaussian_of(st: dict, cell: np.ndarray, res: float):
    hit = np.flatnonzero((st["g_index"] == cell).all(axis=1))
    if len(hit) == 0:
        return None
    i = hit[0]
    n = int(st["g_n"][i])
    s = st["g_scatter"][i].astype(np.float64)
    cov = np.array([[s[0], s[1], s[2]], [s[1], s[3], s[4]], [s[2], s[4], s[5]]]) / max(n - 1, 1)
    if n < 2:
        cov[:] = 0.0
    if n < MapConfig().min_points:  # the map's prior for cells of 1-2 points
        cov += NDT_SPARSE_SIGMA**2 * np.eye(3)
    mean = (cell + 0.5) * res + st["g_mean_rel"][i].astype(np.float64)
    return n, mean, cov, int(st["g_erased_near"][i]), int(st["g_ndt_state"][i])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("npz", type=Path)
    ap.add_argument("--res", type=float, default=0.2)
    ap.add_argument("--csv", type=Path)
    a = ap.parse_args(argv)
    b = _bench()
    ndtom_ti.init()
    scans, sigma, boxes = b.read_scene(a.npz)
    res = a.res
    cand = q.mark_observed(q.ghost_candidates(scans, res, 3.0 * sigma, boxes), scans, res)
    cells, last = cand.cells[cand.observed], cand.last_hit[cand.observed]
    cfg = MapConfig(miss_model="ndt")
    eta, sigma_s, near = cfg.eta, cfg.sigma_s_at(res), cfg.near_cells_at(res)
    m = NdtOmMap(res, config=cfg)
    states, lo_after = [], []
    for sc in scans:
        states.append({k: v for k, v in m.state().items() if k.startswith("g_")})
        m.insert_scan(b.local_points(sc), sc.T_world_sensor)
        lo_after.append(m.logodds_at(cells.astype(np.int64)))
    ghost = q.ndtom_occupied(m)(cells)
    tree, _ = b.build_octree(scans, res)
    octo_ghost = q.octree_occupied(tree, res)(cells)
    print(f"OctoMap: {octo_ghost.sum()} ghosts ({100 * octo_ghost.mean():.1f}%), {(octo_ghost & ghost).sum()} shared")
    print(
        f"{a.npz.name} at {res:g} m: {len(cells)} observed cells left by moving objects, {ghost.sum()} ghosts "
        f"({100 * ghost.mean():.1f}%); sigma_s {sigma_s:g} m, near cells {near}, eta {eta:g}"
    )
    rows = []
    for k in np.flatnonzero(ghost):
        c, h = cells[k], int(last[k])
        passes = tested = skipped_near = 0
        terms, scan_sums, octo_scans, dists = [], [], 0, []
        for j in range(h + 1, len(scans)):
            sc = scans[j]
            idx = passing_rays(c, res, sc.origin, sc.points)
            in_cell = (np.floor(sc.points / res) == c).all(axis=1).any()
            if len(idx) == 0:
                continue
            if in_cell:
                continue  # a hit scan takes the hit update only
            octo_scans += 1
            passes += len(idx)
            g = gaussian_of(states[j], c, res)
            end_cells = np.floor(sc.points[idx] / res)
            far = np.abs(end_cells - c).sum(axis=1) > near
            skipped_near += int((~far).sum())
            if g is None:
                continue
            n, mean, cov, erased_near, state = g
            if erased_near >= NDT_ERASED_NEIGHBOURS:
                cov = np.eye(3) / NDT_WIDE
            s = 0.0
            for i in idx[far]:
                u = sc.points[i] - sc.origin
                f = np.clip((mean - sc.origin) @ u / (u @ u), 0.0, 1.0)
                dists.append(float(np.linalg.norm(sc.origin + f * u - mean)))
                t = ndt_miss_term(sc.origin, sc.points[i], True, mean, cov, eta, sigma_s, n)
                if t < -1e-6:
                    tested += 1
                    terms.append(t)
                s += t
            scan_sums.append(s * (NDT_BACK_MISS if state & 2 else 1.0))
        g_end = gaussian_of(states[-1], c, res)
        rows.append(
            {
                "cell": tuple(int(v) for v in c),
                "last_hit": h,
                "scans_after": len(scans) - 1 - h,
                "scans_passed": octo_scans,
                "passes": passes,
                "near_skipped": skipped_near,
                "terms": tested,
                "term_median": float(np.median(terms)) if terms else 0.0,
                "term_min": min(terms, default=0.0),
                "ray_to_mean_m": float(np.median(dists)) if dists else float("nan"),
                "sum": float(np.sum(scan_sums)),
                "logodds_at_leave": float(lo_after[h][k]),
                "logodds_end": float(lo_after[-1][k]),
                "n": g_end[0] if g_end else 0,
                "erased_near": g_end[3] if g_end else 0,
                "state": g_end[4] if g_end else 0,
                # OctoMap from its clamp: one miss a scan the cell is passed
                "octomap_clears": OCTO_MAX + octo_scans * OCTO_MISS <= 0.0,
                "octomap_ghost": bool(octo_ghost[k]),
            }
        )
    summarize(rows)
    if a.csv:
        import csv

        with open(a.csv, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    return 0


def summarize(rows: list[dict]) -> None:
    if not rows:
        print("no ghosts")
        return

    def q3(key):
        v = np.array([r[key] for r in rows], float)
        v = v[np.isfinite(v)]
        return f"median {np.median(v):.3g} (quartiles {np.percentile(v, 25):.3g}-{np.percentile(v, 75):.3g})"

    print(f"ghosts: {len(rows)}")
    for key in (
        "scans_after",
        "scans_passed",
        "passes",
        "near_skipped",
        "terms",
        "term_median",
        "term_min",
        "ray_to_mean_m",
        "sum",
        "logodds_at_leave",
        "logodds_end",
        "n",
        "erased_near",
    ):
        print(f"  {key:17} {q3(key)}")
    st = np.array([r["state"] for r in rows])
    print(f"  state: fresh {int((st & 1).sum())}, back {int((st & 2 > 0).sum())}, none {int((st == 0).sum())}")
    few = sum(r["passes"] < 10 for r in rows)
    none_tested = sum(r["terms"] == 0 for r in rows)
    print(f"  passed by < 10 rays: {few}; no ray tested the Gaussian: {none_tested}")
    print(
        f"  OctoMap's miss (-0.41 a passing scan from its clamp 3.5) would clear {sum(r['octomap_clears'] for r in rows)}; "
        f"OctoMap keeps {sum(r['octomap_ghost'] for r in rows)} of them"
    )


if __name__ == "__main__":
    raise SystemExit(main())
