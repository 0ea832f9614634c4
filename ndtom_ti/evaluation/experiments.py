"""The paper's evaluation (Saarinen et al., ICRA 2013, sec. IV; docs/method.md sec. 5),
rerunnable on any recording or on synthetic halls (simworld ``.npz`` files).

:func:`run_experiments` inserts the same scans, one at a time, into three mappers:

- ``rcu``: Recursive NDT, ``NdtOmMap(r, occupancy=False)`` (exact RCU, no ray tracing);
  its Gaussians are ``gaussians(min_points=3, min_probability=0)``;
- ``ndtom``: NDT-OM as the paper has it, ``NdtOmMap(r, miss_model="paper")`` (eq. 12); its
  Gaussians are the default ``gaussians()`` (``n >= 3`` and occupied, ``l > 0``); beside it
  ``ndtom_ndt``, the same with the NDT miss model (the library's default);
- ``er``: the online error-refinement baseline of :mod:`ndtom_ti.evaluation.er_baseline` (numpy),
  which stands in for Yguel and Aycard's method (the paper prints no formula for it);
  update rule: :data:`ndtom_ti.evaluation.er_baseline.UPDATE_RULE`.

and writes, under ``out_dir``:

- ``fig1_vs_batch.csv/.png``: after every scan, the mean L2 score (method.md sec. 5) of
  each mapper's Gaussians against the batch map of eq. (1) (``metrics.batch_ndt`` of all
  world points inserted so far; the reference);
- ``fig2_self_test.csv/.png``: each single cloud's own NDT map (``batch_ndt`` of that
  cloud alone) against each final map. ``score`` = ``mean_l2_score(test=final map,
  reference=cloud map)``: the summed similarity over the cloud's cells, divided by the
  cloud's Gaussians, i.e. how well the map represents that cloud (1 = perfectly).
  ``coverage`` (the other direction, reference = the final map) is also written; it is
  bounded by the share of the map the cloud sees, so it measures coverage;
- ``fig3_logodds.csv/.png``: mean log-odds of NDT-OM's occupied (``l > 0``) and empty
  (``l < 0``) cells after every scan (``known_cells()``);
- ``fig4b_conflicting.csv/.png``: after every scan, the *conflicting cells*: cells with a
  Gaussian in Recursive NDT but none in NDT-OM. ``fraction`` = conflicting / number of
  NDT-OM Gaussians (the paper's "of NDT-OM's cells"); ``fraction_of_rcu`` = conflicting /
  number of RCU Gaussians is given too;
- ``conflicting_cells.csv``: the final conflicting cells (index, RCU mean and n, NDT-OM
  log-odds, whether the Gaussian is a horizontal plane, and for synthetic data whether the
  cell received points of a moving object);
- ``fig4_maps.png``: top views of the final NDT-OM map with the conflicting cells, and of
  the ``coarsen`` x coarser map made from it (Fig. 4d); counts in ``summary.json``;
- ``fig5_sweep.csv`` and ``fig5_time_per_scan.png`` (optional, ``sweep=[...]``): time per
  scan against resolution via :func:`ndtom_ti.evaluation.sweep.run_sweep` on the same scans, with
  OctoMap beside NDT-OM when ``pyoctomap`` is importable (else the traversal floor only);
- ``summary.json``: the numbers (keys listed in :func:`run_experiments`).

The command is ``ndtom experiments SOURCE -r RES --out DIR``; ``SOURCE`` is a ROS1 bag /
ROS2 bag folder, a simworld ``.npz``, or ``sim:dynamic`` / ``sim:static`` (a hall made on
the fly by a simworld.py whose path is given). The run is in steps: the scans are read
(:mod:`.sources`), inserted into the mappers one at a time with the per-scan rows
(:class:`_Run`), then the final comparisons (:func:`_ndtom_vs_batch`, :func:`_self_test`,
:func:`_final_conflicts`, :func:`_coarsened`), the files (:mod:`.report`, :mod:`.plots`)
and the optional sweep (:func:`_fig5_rows`, :func:`_fig5_files`).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ..cellkeys import isin_rows
from ..config import MapConfig, check_resolution
from ..frames import far_origin, shifted
from ..runtime import MapMemoryError
from ..scan import Scan
from ..signals import signal_name
from .er_baseline import UPDATE_RULE, ErrorRefinementMap
from .metrics import batch_ndt, l2_similarity, mean_l2_score, regularize_cov
from .report import (
    CONFLICT_COLUMNS,
    CONFLICT_DEFINITION,
    FIG2_DEFINITION,
    HORIZONTAL_DEFINITION,
    MAPPERS,
    PAPER,
    json_default,
    json_float,
    write_csv,
)
from .sources import ScanSet
from .stops import mark_written, writing
from .sweep import check_grid

__all__ = ["run_experiments"]

Progress = Callable[[str], None]


FRAME_ORIGIN_NOTE = (
    "the poses lie far from their frame's origin: the maps were made in a frame shifted by frame_origin "
    "(metres of the poses' frame), and the coordinates written (x, y, z of conflicting_cells.csv, the "
    "plots' axes) are relative to it: add frame_origin to return to the poses' frame"
)


# ============================================================================ helpers
def _near_origin(scans: list[Scan], resolution: float) -> tuple[list[Scan], np.ndarray | None]:
    """The scans with poses shifted as the mapping loop shifts georeferenced ones
    (frames.py): every mapper of the run sees the same shifted scans."""
    from ..kernels.layout import Layout

    origin = far_origin(scans[0].T_world_sensor, Layout().cells, resolution)
    if origin is None:
        return scans, None
    return [replace(sc, T_world_sensor=shifted(sc.T_world_sensor, origin)) for sc in scans], origin


def _world_hits(points: np.ndarray, T: np.ndarray, cfg: MapConfig) -> np.ndarray:
    """World-frame endpoints the maps insert as hits (finite, within [min_range,
    max_range]), transformed exactly as ``ScanUpdate.prepare`` does."""
    pts = np.asarray(points, np.float64)
    ok = np.isfinite(pts).all(axis=1)
    rng = np.full(len(pts), np.inf)
    rng[ok] = np.sqrt(np.einsum("ij,ij->i", pts[ok], pts[ok]))
    ok &= (rng >= cfg.min_range) & (rng <= cfg.max_range)
    return pts[ok] @ T[:3, :3].T + np.ascontiguousarray(T[:3, 3])


def _keys(index: np.ndarray) -> np.ndarray:
    idx = np.ascontiguousarray(np.asarray(index, np.int64).reshape(-1, 3))
    return idx.view([("x", np.int64), ("y", np.int64), ("z", np.int64)]).reshape(-1)


def _sync() -> None:
    try:
        import taichi as ti

        ti.sync()
    except Exception:  # noqa: BLE001 - timing helper only: no Taichi, nothing to sync
        return


def _shared_similarity(test: dict, ref: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Similarity (regularised, as the score) of the cells in both maps, and the indices
    into test and reference."""
    _, it, ir = np.intersect1d(_keys(test["index"]), _keys(ref["index"]), assume_unique=True, return_indices=True)
    if len(it) == 0:
        return np.zeros(0), it, ir
    sim = l2_similarity(
        test["mean"][it], regularize_cov(test["cov"][it]), ref["mean"][ir], regularize_cov(ref["cov"][ir])
    )
    return sim, it, ir


def _horizontal_planar(cov: np.ndarray) -> np.ndarray:
    """Planar Gaussians (smallest eigenvalue < 0.1 x middle) with |normal_z| > 0.9."""
    if len(cov) == 0:
        return np.zeros(0, bool)
    lam, vec = np.linalg.eigh(cov)
    return (lam[:, 0] < 0.1 * lam[:, 1]) & (np.abs(vec[:, 2, 0]) > 0.9)


# ============================================================================ the mappers, scan by scan
class _Run:
    """The four mappers fed the same scans, and what is recorded after every scan: the
    Fig. 1 scores against the batch map, the Fig. 3 log-odds, the Fig. 4b conflicting
    cells, the insert times; ``gauss`` holds each mapper's Gaussians after the last scan."""

    def __init__(self, resolution: float, cfg: MapConfig, er_eps_min: float) -> None:
        from ..map import NdtOmMap

        self.resolution, self.cfg, self.mp = resolution, cfg, int(cfg.min_points)
        self.rcu = NdtOmMap(resolution, occupancy=False, config=cfg)
        # The paper's mapper (eq. 12 for every cell) and the same map with the NDT miss model
        # of the authors' journal version, whatever the config chose.
        self.ndt = NdtOmMap(resolution, occupancy=True, config=replace(cfg, miss_model="paper"))
        self.ndt2 = NdtOmMap(resolution, occupancy=True, config=replace(cfg, miss_model="ndt"))
        self.er = ErrorRefinementMap(resolution, eps_min=er_eps_min, min_points=self.mp)
        self.worlds: list[np.ndarray] = []  # each scan's world-frame hits
        self.dyn_cells: list[np.ndarray] = []  # cells of each scan's moving-object points (synthetic data)
        self.fig1: list[dict] = []
        self.fig3: list[dict] = []
        self.fig4b: list[dict] = []
        self.times: dict[str, list[float]] = {m: [] for m in MAPPERS}
        self.gauss: dict[str, dict] = {}

    def close(self) -> None:
        """Give the Taichi maps back (the sweep makes its own)."""
        for m in (self.rcu, self.ndt, self.ndt2):
            m.close()

    def insert(self, scan: Scan, dynamic: np.ndarray | None) -> np.ndarray:
        """Insert one scan into every mapper, timed; returns its world-frame hits."""
        pts, T = scan.points, scan.T_world_sensor
        w = _world_hits(pts, T, self.cfg)
        self.worlds.append(w)
        if dynamic is not None:
            dw = _world_hits(np.asarray(pts, np.float64)[dynamic], T, self.cfg)
            self.dyn_cells.append(np.unique(np.floor(dw / self.resolution).astype(np.int64), axis=0))
        for name, m in (("rcu", self.rcu), ("ndtom", self.ndt), ("ndtom_ndt", self.ndt2)):
            _sync()
            t0 = time.perf_counter()
            m.insert_scan(pts, T)
            _sync()
            self.times[name].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        self.er.insert_world(w)
        self.times["er"].append(time.perf_counter() - t0)
        return w

    def batch(self, resolution: float | None = None) -> dict:
        """The batch NDT map (eq. 1) of every point inserted so far."""
        return batch_ndt(np.concatenate(self.worlds), resolution or self.resolution, self.mp)

    def record(self, i: int) -> str:
        """The rows of scan ``i`` (just inserted); returns its progress line."""
        w = self.worlds[-1]
        batch = self.batch()
        g = self.gauss = {
            "rcu": self.rcu.gaussians(min_points=self.mp, min_probability=0.0),
            "ndtom": self.ndt.gaussians(),
            "ndtom_ndt": self.ndt2.gaussians(),
            "er": self.er.gaussians(),
        }
        scores = {m: mean_l2_score(g[m], batch) for m in MAPPERS}
        self.fig1.append(
            {
                "scan": i,
                "points": len(w),
                "points_total": int(sum(len(x) for x in self.worlds)),
                "batch_gaussians": len(batch["index"]),
                **{f"{m}_gaussians": len(g[m]["index"]) for m in MAPPERS},
                **{f"score_{m}": scores[m] for m in MAPPERS},
                **{f"ms_{m}": self.times[m][-1] * 1e3 for m in MAPPERS},
            }
        )

        lo = self.ndt.known_cells()["logodds"]
        occ, emp = lo[lo > 0], lo[lo < 0]
        self.fig3.append(
            {
                "scan": i,
                "mean_logodds_occupied": float(occ.mean()) if len(occ) else math.nan,
                "mean_logodds_empty": float(emp.mean()) if len(emp) else math.nan,
                "occupied_cells": len(occ),
                "empty_cells": len(emp),
            }
        )

        n_c = int((~isin_rows(g["rcu"]["index"], g["ndtom"]["index"])).sum())
        n_nd, n_rc = len(g["ndtom"]["index"]), len(g["rcu"]["index"])
        n_c2 = int((~isin_rows(g["rcu"]["index"], g["ndtom_ndt"]["index"])).sum())
        n_nd2 = len(g["ndtom_ndt"]["index"])
        self.fig4b.append(
            {
                "scan": i,
                "conflicting": n_c,
                "ndtom_gaussians": n_nd,
                "rcu_gaussians": n_rc,
                "fraction": n_c / n_nd if n_nd else math.nan,
                "fraction_of_rcu": n_c / n_rc if n_rc else math.nan,
                "conflicting_ndt": n_c2,
                "fraction_ndt": n_c2 / n_nd2 if n_nd2 else math.nan,
            }
        )
        return (
            f"{len(w)} points; vs batch rcu {scores['rcu']:.4f} ndtom {scores['ndtom']:.4f} "
            f"er {scores['er']:.4f}; conflicting {n_c} ({self.fig4b[-1]['fraction']:.1%})"
        )


# ============================================================================ after the last scan
def _ndtom_vs_batch(run: _Run) -> dict:
    """NDT-OM's final Gaussians against the batch map, cell by cell."""
    batch = run.batch()
    nd = run.gauss["ndtom"]
    sim, it, ir = _shared_similarity(nd, batch)
    same_n = nd["n"][it] == batch["n"][ir]
    return {
        "ndtom_gaussians": len(nd["index"]),
        "batch_gaussians": len(batch["index"]),
        "shared": len(it),
        "shared_same_n": int(same_n.sum()),
        "shared_refilled": int((~same_n).sum()),  # erased once, then new points: fewer points than batch
        "score_shared": json_float(sim.mean()) if len(sim) else None,
        "score_shared_same_n": json_float(sim[same_n].mean()) if same_n.any() else None,
        "min_similarity_shared_same_n": json_float(sim[same_n].min()) if same_n.any() else None,
        "batch_missing_in_ndtom": int(len(batch["index"]) - len(it)),
    }


def _self_test(run: _Run) -> list[dict]:
    """Fig. 2: each single cloud's own NDT map against each final map."""
    fig2 = []
    for i, w in enumerate(run.worlds):
        cloud = batch_ndt(w, run.resolution, run.mp)
        row: dict = {"cloud": i, "cloud_gaussians": len(cloud["index"])}
        for m in MAPPERS:
            row[f"score_{m}"] = mean_l2_score(run.gauss[m], cloud) if len(cloud["index"]) else math.nan
        for m in MAPPERS:
            row[f"coverage_{m}"] = mean_l2_score(cloud, run.gauss[m])
        fig2.append(row)
    return fig2


def _final_conflicts(run: _Run, dynamic: bool) -> tuple[dict, list[dict], list[str], np.ndarray]:
    """Fig. 4b after the last scan: the summary's ``conflicting_cells``, the rows of
    ``conflicting_cells.csv`` and their columns, and the conflicting cells' indices.
    ``dynamic``: the scans marked their moving-object points (the rows say which cells
    hold some)."""
    rcu = run.gauss["rcu"]
    final_conflict = ~isin_rows(rcu["index"], run.gauss["ndtom"]["index"])
    conflict_idx = rcu["index"][final_conflict]
    horizontal = _horizontal_planar(rcu["cov"][final_conflict])
    nd_known = run.ndt.known_cells()
    _, ic, ik = np.intersect1d(_keys(conflict_idx), _keys(nd_known["index"]), assume_unique=True, return_indices=True)
    conflict_lo = np.zeros(len(conflict_idx))
    conflict_lo[ic] = nd_known["logodds"][ik]
    del nd_known
    last = run.fig4b[-1]
    conflicting = {
        "count": last["conflicting"],
        "fraction": json_float(last["fraction"]),
        "fraction_of": "ndtom_gaussians",
        "fraction_of_rcu": json_float(last["fraction_of_rcu"]),
        "count_empty": int((conflict_lo < 0).sum()),  # NDT-OM log-odds < 0 there (seen free)
        "horizontal": int(horizontal.sum()),
        "other": int((~horizontal).sum()),
        "other_fraction": (
            json_float((~horizontal).sum() / last["ndtom_gaussians"]) if last["ndtom_gaussians"] else None
        ),
        "ndtom_gaussians": last["ndtom_gaussians"],
        "rcu_gaussians": last["rcu_gaussians"],
        "count_ndt_miss_model": last["conflicting_ndt"],
        "fraction_ndt_miss_model": json_float(last["fraction_ndt"]),
        "definition": CONFLICT_DEFINITION,
        "horizontal_definition": HORIZONTAL_DEFINITION,
    }
    conflict_dyn = None
    if dynamic:
        dc = np.unique(np.concatenate(run.dyn_cells), axis=0) if run.dyn_cells else np.zeros((0, 3), np.int64)
        conflict_dyn = isin_rows(conflict_idx, dc)
        conflicting["with_dynamic_points"] = int(conflict_dyn.sum())
        conflicting["dynamic_point_cells"] = len(dc)
    rows = [
        {
            "i": int(k[0]),
            "j": int(k[1]),
            "k": int(k[2]),
            "x": float(c[0]),
            "y": float(c[1]),
            "z": float(c[2]),
            "rcu_n": int(n),
            "ndtom_logodds": float(lo),
            "horizontal": int(h),
            **({"dynamic_points": int(dy)} if conflict_dyn is not None else {}),
        }
        for k, c, n, lo, h, dy in zip(
            conflict_idx,
            rcu["mean"][final_conflict],
            rcu["n"][final_conflict],
            conflict_lo,
            horizontal,
            conflict_dyn if conflict_dyn is not None else np.zeros(len(conflict_idx)),
        )
    ]
    columns = CONFLICT_COLUMNS + (["dynamic_points"] if conflict_dyn is not None else [])
    return conflicting, rows, columns, conflict_idx


def _coarsened(run: _Run, factor: int) -> tuple[dict, dict]:
    """Fig. 4d: NDT-OM and Recursive NDT made ``factor`` x coarser; returns the summary's
    ``fig4d`` and the coarse NDT-OM's Gaussians."""
    coarse = run.ndt.coarsen(factor)
    rcu_coarse = run.rcu.coarsen(factor)
    try:
        cg = coarse.gaussians()
        rcg = rcu_coarse.gaussians(min_points=run.mp, min_probability=0.0)
    finally:
        coarse.close()
        rcu_coarse.close()
    coarse_batch = run.batch(run.resolution * factor)
    fine = len(run.gauss["ndtom"]["index"])
    return {
        "factor": factor,
        "fine_resolution": run.resolution,
        "fine_gaussians": fine,
        "coarse_resolution": round(run.resolution * factor, 12),
        "coarse_gaussians": len(cg["index"]),
        "ratio": json_float(fine / len(cg["index"])) if len(cg["index"]) else None,
        "rcu_fine_gaussians": len(run.gauss["rcu"]["index"]),
        "rcu_coarse_gaussians": len(rcg["index"]),
        "rcu_coarse_vs_batch_score": json_float(mean_l2_score(rcg, coarse_batch)),
    }, cg


def _summary(
    data: ScanSet,
    run: _Run,
    *,
    ndtom_vs_batch: dict,
    fig2: list[dict],
    conflicting: dict,
    fig4d: dict,
    er_eps_min: float,
) -> dict:
    from .. import runtime

    fig1, worlds = run.fig1, run.worlds
    return {
        "source": data.description,
        "source_kind": data.kind,
        "source_info": data.info,
        "resolution": run.resolution,
        "scans": len(data.scans),
        "points": int(sum(len(w) for w in worlds)),
        "points_per_scan": json_float(np.mean([len(w) for w in worlds])),
        "arch": runtime.current_arch(),
        "config": run.cfg.to_dict(),
        "fig1_final_score": {m: json_float(fig1[-1][f"score_{m}"]) for m in MAPPERS},
        "fig1_min_score": {m: json_float(min(r[f"score_{m}"] for r in fig1)) for m in MAPPERS},
        "ndtom_vs_batch": ndtom_vs_batch,
        "fig2_mean_score": {m: json_float(np.nanmean([r[f"score_{m}"] for r in fig2])) for m in MAPPERS},
        "fig2_mean_coverage": {m: json_float(np.mean([r[f"coverage_{m}"] for r in fig2])) for m in MAPPERS},
        "fig3_final": {
            k: (json_float(v) if isinstance(v, float) else v) for k, v in run.fig3[-1].items() if k != "scan"
        },
        "conflicting_cells": conflicting,
        "fig4d": fig4d,
        "time_per_scan_ms": {m: json_float(np.median(run.times[m]) * 1e3) for m in MAPPERS},
        "er_eps_min": er_eps_min,
        "er_update_rule": UPDATE_RULE,
        "definitions": {
            "fig1": "mean_l2_score(test=mapper's Gaussians, reference=batch_ndt(all world points so far))",
            "fig2": FIG2_DEFINITION,
            "fig3": "mean NDT-OM log-odds of cells with l > 0 (occupied) and l < 0 (empty)",
            "conflicting": CONFLICT_DEFINITION,
            "rcu_gaussians": "gaussians(min_points=3, min_probability=0)",
            "ndtom_gaussians": "gaussians() (n >= 3 and l > 0)",
        },
        "paper": PAPER,
        "fig5": None,
    }


def _fig5_rows(data: ScanSet, resolutions: Sequence[float], say: Progress, on_row: Callable) -> str | None:
    """Fig. 5: time per scan against resolution on the same scans (OctoMap beside NDT-OM
    when pyoctomap imports); each row goes to ``on_row`` as it is finished. Returns the
    baseline used."""
    from . import sweep as sw

    baseline = "octomap" if sw.octomap_available() else None
    say(f"Fig. 5: sweep over {list(resolutions)} ({'with OctoMap' if baseline else 'no pyoctomap: floor only'})")
    sw.run_sweep(data.scans, list(resolutions), baseline=baseline, progress=say, on_row=on_row)
    return baseline


def _fig5_files(
    rows: list,
    baseline: str | None,
    out: Path,
    plots: bool,
    title: str,
    stopped: tuple[str, float] | None = None,
) -> tuple[dict, list[Path]]:
    """The summary's ``fig5`` and the files of the sweep's ``rows`` (``stopped``: why and at
    which resolution the sweep stopped; the files hold the rows finished, marked partial)."""
    from .. import runtime
    from . import sweep as sw

    tags = {**sw.machine_tags(runtime.current_arch() or "cpu"), "complete": "false" if stopped else "true"}
    if stopped:
        tags["stopped"] = f"{stopped[0]} at {stopped[1]:g} m"
    files = []
    if rows:
        files.append(sw.write_csv(rows, out / "fig5_sweep.csv", tags))
        if plots:
            files.append(sw.plot(rows, out / "fig5_time_per_scan.png", title + (" (partial)" if stopped else "")))
    fig5 = {
        "baseline": baseline,
        "complete": stopped is None,
        "rows": [
            {
                "mapper": r.mapper,
                "resolution": r.resolution,
                "ms_median": json_float(r.ms_median),
                "ms_p95": json_float(r.ms_p95),
                "ratio_to_ndtom": json_float(r.ratio_to_ndtom),
            }
            for r in rows
        ],
    }
    if stopped:
        fig5["stopped"], fig5["stopped_at"] = stopped
    return fig5, files


def _write_json(path: Path, data: dict) -> Path:
    """Written whole or not at all (a file beside it, then renamed)."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=2, default=json_default) + "\n")
    os.replace(tmp, path)
    return path


# ============================================================================ the run
def run_experiments(
    source: Any,
    resolution: float,
    out_dir: str | Path,
    *,
    every: int = 1,
    max_scans: int | None = None,
    sensor_frame_only: bool = False,
    coarsen: int = 3,
    sweep: Sequence[float] | None = None,
    er_eps_min: float = 0.05,
    config: Any = None,
    sim_scans: int = 30,
    sim_stride: int = 10,
    sim_seed: int = 0,
    tools_dir: str | Path | None = None,
    plots: bool = True,
    progress: Progress | None = None,
) -> dict:
    """Run the paper's evaluation on ``source`` at ``resolution`` (metres) and write the
    CSVs, PNGs and ``summary.json`` into ``out_dir`` (created). Returns the summary.

    Parameters
    ----------
    source: recording path (ROS1 bag / ROS2 folder), simworld ``.npz``, ``"sim:dynamic"``
        or ``"sim:static"``, or a sequence of scans or (points, T_world_sensor) pairs (see
        :func:`~ndtom_ti.evaluation.sources.load_scans`).
    every, max_scans, sensor_frame_only: scan selection (as ``Recording.scans``; for
        simworld data ``every``/``max_scans`` pick scan indices).
    coarsen: factor of the coarse map of Fig. 4d (``NdtOmMap.coarsen``), >= 2.
    sweep: resolutions for Fig. 5 (``None``/empty: skip). OctoMap runs beside NDT-OM when
        pyoctomap is importable.
    er_eps_min: learning-rate floor of the error-refinement baseline.
    config: ``MapConfig`` for both Taichi maps (default: the paper's parameters).
    sim_scans, sim_stride, sim_seed: the synthetic hall of ``sim:`` sources; tools_dir: the
        simworld.py that makes it (the file or its folder; needed for ``sim:`` sources).
    plots: write the PNGs (matplotlib, Agg).
    progress: callable receiving one-line progress messages.

    Summary keys: ``source``, ``resolution``, ``scans``, ``points``, ``fig1_final_score``
    {rcu, ndtom, er}, ``fig1_min_score``, ``ndtom_vs_batch``, ``fig2_mean_score``,
    ``fig2_mean_coverage``, ``fig3_final``, ``conflicting_cells`` {count, fraction,
    fraction_of_rcu, count_empty, ...}, ``fig4d`` {fine_resolution, fine_gaussians,
    coarse_resolution, coarse_gaussians, ...}, ``time_per_scan_ms``, ``fig5`` (or None),
    ``er_update_rule``, ``definitions``, ``paper``, ``files``, ``seconds``, ``frame_origin``
    (where the maps' (0, 0, 0) lies in the poses' frame, None when not shifted; with
    ``frame_origin_note``), ``complete``.

    ``summary.json`` is written once the main figures are, with ``complete`` false while a
    sweep follows, and again after the sweep. A stop during the sweep (KeyboardInterrupt,
    MapMemoryError) writes the rows finished, marked partial, then propagates; the files
    written are on the exception (:func:`~ndtom_ti.evaluation.stops.written_before`).
    Resolutions (``resolution``, ``sweep``) whose grid cannot hold the scans are refused
    before any mapping (:class:`~ndtom_ti.evaluation.sweep.ResolutionTooFineError`).
    """
    from .. import runtime
    from . import sources

    say = progress or (lambda s: None)
    t_start = time.perf_counter()
    resolution = check_resolution(resolution)
    if isinstance(coarsen, bool) or int(coarsen) != coarsen or coarsen < 2:
        raise ValueError(f"coarsen must be an integer >= 2, got {coarsen!r}")
    if sweep:
        sweep = [check_resolution(r, "each sweep resolution") for r in sweep]
    cfg = config if config is not None else MapConfig()
    if plots:  # before any work: the plots are drawn at the end
        from ..extras import require

        require("matplotlib", "the plots (plots=False skips them)")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    runtime.ensure_init()

    say("reading scans")
    data = sources.load_scans(
        source,
        every=every,
        max_scans=max_scans,
        sensor_frame_only=sensor_frame_only,
        sim_scans=sim_scans,
        sim_stride=sim_stride,
        sim_seed=sim_seed,
        tools_dir=tools_dir,
    )
    if not data.scans:
        raise ValueError(f"no scans to map in {data.description}")
    data.scans, origin = _near_origin(data.scans, resolution)
    if origin is not None:
        say(f"poses far from their frame's origin: mapped relative to {origin.tolist()} m (frame_origin)")
    check_grid(data.scans, [resolution], "resolution")
    if sweep:  # before any work: a resolution too fine would stop the sweep at the end
        check_grid(data.scans, sweep, "sweep")

    run = _Run(resolution, cfg, er_eps_min)
    try:
        for i, scan in enumerate(data.scans):
            run.insert(scan, data.dynamic[i] if data.dynamic is not None else None)
            say(f"scan {i + 1}/{len(data.scans)}: {run.record(i)}")
        ndtom_vs_batch = _ndtom_vs_batch(run)
        say("Fig. 2: single clouds against the final maps")
        fig2 = _self_test(run)
        conflicting, conflict_rows, conflict_columns, conflict_idx = _final_conflicts(run, data.dynamic is not None)
        say(f"Fig. 4d: coarsening x{coarsen}")
        fig4d, coarse_gauss = _coarsened(run, int(coarsen))
    finally:
        run.close()  # before the sweep: it makes its own maps
    summary = _summary(
        data, run, ndtom_vs_batch=ndtom_vs_batch, fig2=fig2, conflicting=conflicting, fig4d=fig4d, er_eps_min=er_eps_min
    )
    summary["frame_origin"] = None if origin is None else origin.tolist()
    if origin is not None:
        summary["frame_origin_note"] = FRAME_ORIGIN_NOTE
    if sweep:
        summary["fig5"] = {"complete": False, "resolutions": list(sweep), "rows": []}  # until the sweep is done

    files: list[Path] = []

    def save_summary(complete: bool) -> None:
        summary["complete"] = complete
        summary["seconds"] = time.perf_counter() - t_start
        summary["files"] = sorted([p.name for p in files] + ["summary.json"])
        _write_json(out / "summary.json", summary)

    try:
        # whole files: a stop signal waits for them (and then stops the run before the sweep)
        with writing(then_stop=bool(sweep)):
            files += [
                write_csv(out / "fig1_vs_batch.csv", run.fig1),
                write_csv(out / "fig2_self_test.csv", fig2),
                write_csv(out / "fig3_logodds.csv", run.fig3),
                write_csv(out / "fig4b_conflicting.csv", run.fig4b),
                write_csv(out / "conflicting_cells.csv", conflict_rows, conflict_columns),
            ]
            if plots:
                from .plots import plot_figures

                say("plots")
                files += plot_figures(
                    out,
                    run.fig1,
                    fig2,
                    run.fig3,
                    run.fig4b,
                    run.gauss,
                    conflict_idx,
                    coarse_gauss,
                    resolution,
                    fig4d,
                    data.description,
                )
            save_summary(complete=not sweep)
    except (KeyboardInterrupt, MapMemoryError) as exc:
        if (out / "summary.json").exists():
            mark_written(exc, [*files, out / "summary.json"])
        raise
    if not sweep:
        return summary

    rows: list = []
    title = f"Fig. 5: {len(data.scans)} scans, {summary['points_per_scan']:.0f} points/scan"
    try:
        baseline = _fig5_rows(data, sweep, say, rows.append)
    except (KeyboardInterrupt, MapMemoryError) as exc:
        from . import sweep as sw

        why = signal_name(getattr(exc, "signum", None)) if isinstance(exc, KeyboardInterrupt) else "memory"
        mappers = 3 if sw.octomap_available() else 2
        at = next((r for r in sweep if sum(row.resolution == r for row in rows) < mappers), sweep[-1])
        with writing(then_stop=False):
            summary["fig5"], more = _fig5_files(rows, "octomap" if mappers == 3 else None, out, plots, title, (why, at))
            files += more
            save_summary(complete=False)
        mark_written(exc, [*files, out / "summary.json"])
        raise
    with writing(then_stop=False):
        summary["fig5"], more = _fig5_files(rows, baseline, out, plots, title)
        files += more
        save_summary(complete=True)
    return summary
