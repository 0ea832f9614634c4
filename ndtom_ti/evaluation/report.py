"""What an evaluation writes: the mappers' names, the definitions of its numbers, the
paper's figures to compare with, CSV and JSON writing, and the summary as text."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["LABELS", "MAPPERS", "PAPER", "format_summary", "json_default", "json_float", "write_csv"]

MAPPERS = ("rcu", "ndtom", "ndtom_ndt", "er")
LABELS = {
    "rcu": "Recursive NDT (RCU)",
    "ndtom": "NDT-OM (eq. 12)",
    "ndtom_ndt": "NDT-OM, NDT miss model",
    "er": "error refinement (ER)",
}
CONFLICT_DEFINITION = (
    "conflicting = cells with a Gaussian (n >= min_points) in Recursive NDT but none "
    "(n < min_points or l <= 0) in NDT-OM; fraction = conflicting / NDT-OM Gaussians"
)
HORIZONTAL_DEFINITION = (
    "horizontal = conflicting cells whose RCU Gaussian is planar (smallest eigenvalue < 0.1 x the "
    "middle one) with a near-vertical normal (|n_z| > 0.9): floor, shelf boards, tops, which rays of a "
    "ground sensor graze and empty; other = the rest; other_fraction = other / NDT-OM Gaussians"
)
FIG2_DEFINITION = (
    "score = mean_l2_score(test=final map, reference=the cloud's own batch NDT map): "
    "summed similarity over the cloud's cells / the cloud's Gaussians; averaged over clouds"
)

#: Figures of the paper (Saarinen et al., ICRA 2013) to compare against.
PAPER = {
    "conflicting_fraction_factory": 0.25,
    "factory_gaussians_0.3m": 61728,
    "factory_gaussians_0.9m": 11359,
    "rcu_vs_batch": 1.0,
}


CONFLICT_COLUMNS = ["i", "j", "k", "x", "y", "z", "rcu_n", "ndtom_logodds", "horizontal"]


def write_csv(path: Path, rows: list[dict], columns: list[str] | None = None) -> Path:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=columns or list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return path


def json_float(x: float | np.floating) -> float | None:
    """JSON-safe float (NaN -> None)."""
    x = float(x)
    return None if not math.isfinite(x) else x


def json_default(o: Any) -> Any:
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return json_float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def format_summary(s: dict) -> str:
    """Human-readable lines for a summary returned by :func:`run_experiments`."""

    def num(v, fmt=".4f"):
        return "n/a" if v is None else format(v, fmt)

    def pct(v):
        return num(None if v is None else 100.0 * v, ".2f")

    f1, f2 = s["fig1_final_score"], s["fig2_mean_score"]
    c, d, t, nb = s["conflicting_cells"], s["fig4d"], s["time_per_scan_ms"], s["ndtom_vs_batch"]
    f3 = s["fig3_final"]
    lines = [
        f"source: {s['source']}",
        f"resolution {s['resolution']:g} m, {s['scans']} scans, {s['points']} points ({s['arch']})",
        f"{'':28s}{'RCU':>10s}{'NDT-OM':>10s}{'NDT miss':>10s}{'ER':>10s}",
        f"{'Fig. 1 score vs batch (final)':28s}" + "".join(f"{num(f1[m]):>10s}" for m in MAPPERS),
        f"{'Fig. 1 score vs batch (min)':28s}" + "".join(f"{num(s['fig1_min_score'][m]):>10s}" for m in MAPPERS),
        f"{'Fig. 2 self-test (mean)':28s}" + "".join(f"{num(f2[m]):>10s}" for m in MAPPERS),
        f"{'time per scan, median (ms)':28s}" + "".join(f"{num(t[m], '.1f'):>10s}" for m in MAPPERS),
        (
            f"NDT-OM vs batch: {nb['shared']} shared cells, {nb['shared_same_n']} with the same points "
            f"(mean similarity {num(nb['score_shared_same_n'], '.6f')}), {nb['shared_refilled']} refilled, "
            f"{nb['batch_missing_in_ndtom']} batch cells without an NDT-OM Gaussian"
        ),
        (
            f"Fig. 3: mean log-odds occupied {num(f3['mean_logodds_occupied'], '.3f')} "
            f"({f3['occupied_cells']} cells), empty {num(f3['mean_logodds_empty'], '.3f')} ({f3['empty_cells']} cells)"
        ),
        (
            f"Fig. 4b: conflicting cells {c['count']} = {pct(c['fraction'])}% of NDT-OM's {c['ndtom_gaussians']} "
            f"Gaussians ({pct(c['fraction_of_rcu'])}% of RCU's {c['rcu_gaussians']}); {c['count_empty']} of them "
            f"seen empty (l < 0); {c['horizontal']} on horizontal surfaces, {c['other']} other "
            f"({pct(c['other_fraction'])}%); with the NDT miss model {c['count_ndt_miss_model']} "
            f"({pct(c['fraction_ndt_miss_model'])}%)"
            + (f"; {c['with_dynamic_points']} hold points of moving objects" if "with_dynamic_points" in c else "")
        ),
        (
            f"Fig. 4d: {d['fine_resolution']:g} m -> {d['coarse_resolution']:g} m: {d['fine_gaussians']} -> "
            f"{d['coarse_gaussians']} Gaussians (paper: 61728 -> 11359 at 0.3 -> 0.9 m); "
            f"coarsened RCU vs batch at {d['coarse_resolution']:g} m: {num(d['rcu_coarse_vs_batch_score'], '.6f')}"
        ),
        f"ER baseline rule (eps_min={s['er_eps_min']:g}): {s['er_update_rule']}",
    ]
    if s.get("fig5"):
        rows = s["fig5"]["rows"]
        lines.append(
            "Fig. 5: median ms per scan: "
            + ", ".join(f"{r['mapper']} {r['resolution']:g} m {num(r['ms_median'], '.1f')}" for r in rows)
        )
    if s.get("frame_origin") is not None:
        lines.append(f"frame origin {s['frame_origin']} m: the coordinates written are relative to it")
    if s.get("complete") is False:
        f5 = s.get("fig5") or {}
        at = f" ({f5['stopped']} at {f5['stopped_at']:g} m)" if "stopped_at" in f5 else ""
        lines.append(f"partial: the Fig. 5 sweep did not finish{at}; summary.json says complete = false")
    lines.append(f"files: {', '.join(s['files'])}  ({s['seconds']:.1f} s)")
    return "\n".join(lines)
