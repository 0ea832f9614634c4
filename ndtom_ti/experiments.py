"""The paper's evaluation (Saarinen et al., ICRA 2013, sec. IV; docs/method.md sec. 5),
rerunnable on any recording or on the synthetic halls of ``shared/tools/simworld.py``.

:func:`run_experiments` inserts the same scans, one at a time, into three mappers:

- ``rcu``: Recursive NDT, ``NdtOmMap(r, occupancy=False)`` (exact RCU, no ray tracing);
  its Gaussians are ``gaussians(min_points=3, min_probability=0)``;
- ``ndtom``: NDT-OM, ``NdtOmMap(r)``; its Gaussians are the default ``gaussians()``
  (``n >= 3`` and occupied, ``l > 0``);
- ``er``: the online error-refinement baseline of :mod:`ndtom_ti.er_baseline` (numpy),
  which stands in for Yguel and Aycard's method (the paper prints no formula for it);
  update rule: :data:`ndtom_ti.er_baseline.UPDATE_RULE`.

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
  scan against resolution via :func:`ndtom_ti.sweep.run_sweep` on the same scans, with
  OctoMap beside NDT-OM when ``pyoctomap`` is importable (else the traversal floor only);
- ``summary.json``: the numbers (keys listed in :func:`run_experiments`).

Run it with ``python -m ndtom_ti.experiments SOURCE -r RES --out DIR`` (see :func:`main`);
``SOURCE`` is a ROS1 bag / ROS2 bag folder, a simworld ``.npz``, or ``sim:dynamic`` /
``sim:static`` (a hall generated with simworld.py on the fly).
"""

from __future__ import annotations

import argparse
import csv
import gc
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .cellkeys import isin_rows
from .er_baseline import UPDATE_RULE, ErrorRefinementMap
from .metrics import batch_ndt, l2_similarity, mean_l2_score, regularize_cov

__all__ = [
    "PAPER",
    "ScanSet",
    "find_simworld",
    "format_summary",
    "load_scans",
    "main",
    "make_simworld",
    "run_experiments",
]

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

Progress = Callable[[str], None]


# ============================================================================ sources
@dataclass
class ScanSet:
    """Scans to map: ``scans`` is a list of (points (N, 3) float32 sensor frame,
    T_world_sensor (4, 4)); ``dynamic`` (synthetic data only) a per-scan boolean mask of
    the points that hit a moving or vanishing object."""

    scans: list[tuple[np.ndarray, np.ndarray]]
    description: str
    kind: str  # "recording" | "simworld" | "scans"
    dynamic: list[np.ndarray] | None = None
    info: dict = field(default_factory=dict)


def find_simworld(tools_dir: str | Path | None = None) -> Path:
    """Path of ``simworld.py``: ``tools_dir`` (the file or its folder) when given, else
    ``$NDTOM_SHARED/tools``, ``../shared/tools`` from the current folder, or
    ``../shared/tools`` next to the repository."""
    if tools_dir is not None:
        cands = [Path(tools_dir).expanduser()]
    else:
        cands = [Path(os.environ["NDTOM_SHARED"]) / "tools"] if os.environ.get("NDTOM_SHARED") else []
        cands += [Path.cwd().parent / "shared" / "tools", Path(__file__).resolve().parents[2] / "shared" / "tools"]
    for d in cands:
        p = d if d.suffix == ".py" else d / "simworld.py"
        if p.is_file():
            return p
    raise FileNotFoundError(f"simworld.py (the generator of the synthetic hall of sim: sources) is not in "
                            f"{', '.join(str(c) for c in cands)}; give its path, or set NDTOM_SHARED to the "
                            f"folder that holds tools/simworld.py")


def make_simworld(
    out_dir: str | Path,
    *,
    n_scans: int = 30,
    stride: int = 10,
    static: bool = False,
    seed: int = 0,
    tools_dir: str | Path | None = None,
) -> Path:
    """Run ``simworld.py --scans N --stride K --no-bags [--static] --out DIR`` (the hall
    variant) and return the written ``hall.npz``."""
    script = find_simworld(tools_dir)
    out = Path(out_dir)
    args = [
        sys.executable,
        str(script),
        "--scans",
        str(int(n_scans)),
        "--stride",
        str(int(stride)),
        "--seed",
        str(int(seed)),
        "--no-bags",
        "--out",
        str(out),
    ]
    if static:
        args.append("--static")
    res = subprocess.run(args, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise RuntimeError(f"simworld.py failed ({res.returncode}): {res.stderr.strip()[-2000:]}")
    return out / "hall.npz"


def _read_npz(path: Path, every: int, max_scans: int | None) -> ScanSet:
    """Scans of a simworld npz (same layout ``simworld.SimDataset`` reads)."""
    z = np.load(path, allow_pickle=False)
    off, pts, nr, hit, poses = z["scan_offsets"], z["points"], z["no_return"], z["hit_id"], z["poses"]
    n_static = len(z["static_lo"])
    params = json.loads(str(z["params_json"])) if "params_json" in z.files else {}
    scans, dyn = [], []
    for i in range(len(poses)):
        if i % every:
            continue
        a, b = off[i], off[i + 1]
        keep = ~nr[a:b]
        scans.append((np.ascontiguousarray(pts[a:b][keep], np.float32), np.asarray(poses[i], np.float64)))
        dyn.append(hit[a:b][keep] >= n_static)
        if max_scans is not None and len(scans) >= max_scans:
            break
    static = bool(params.get("static", False))
    desc = f"simworld {params.get('variant', 'hall')} ({'static' if static else 'dynamic'}) {path}"
    return ScanSet(scans, desc, "simworld", dyn, {"simworld_params": params})


def load_scans(
    source: Any,
    *,
    every: int = 1,
    max_scans: int | None = None,
    sensor_frame_only: bool = False,
    sim_scans: int = 30,
    sim_stride: int = 10,
    sim_seed: int = 0,
    tools_dir: str | Path | None = None,
    **scan_options: Any,
) -> ScanSet:
    """The scans of ``source``:

    - a sequence of ``(points, T_world_sensor)`` pairs (used as given);
    - ``"sim:dynamic"`` / ``"sim:static"``: a simworld hall of ``sim_scans`` scans
      ``sim_stride`` frames apart (with or without moving objects), generated in a
      temporary folder;
    - a path ending in ``.npz``: a simworld dataset;
    - any other path: a recording (``open_recording(path).scans(every=..., max_scans=...,
      sensor_frame_only=..., **scan_options)``).
    """
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    if max_scans is not None and max_scans < 1:
        raise ValueError(f"max_scans must be >= 1, got {max_scans}")
    if not isinstance(source, (str, Path)):
        scans = [(np.asarray(p, np.float32), np.asarray(T, np.float64)) for p, T in source]
        scans = scans[::every][:max_scans]
        return ScanSet(scans, f"{len(scans)} given scans", "scans")
    s = str(source)
    if s.startswith("sim:"):
        variant = s[4:]
        if variant not in ("dynamic", "static"):
            raise ValueError(f"unknown synthetic source {s!r}; use 'sim:dynamic' or 'sim:static'")
        with tempfile.TemporaryDirectory(prefix="ndtom_sim_") as tmp:
            npz = make_simworld(
                tmp,
                n_scans=sim_scans,
                stride=sim_stride,
                static=variant == "static",
                seed=sim_seed,
                tools_dir=tools_dir,
            )
            out = _read_npz(npz, every, max_scans)
        out.description = f"simworld hall ({variant}), {sim_scans} scans, stride {sim_stride}, seed {sim_seed}"
        return out
    path = Path(s)
    if path.suffix == ".npz":
        return _read_npz(path, every, max_scans)
    from .io import open_recording

    with open_recording(path) as rec:
        stream = rec.scans(every=every, max_scans=max_scans, sensor_frame_only=sensor_frame_only, **scan_options)
        scans = [(np.asarray(sc.points, np.float32), np.asarray(sc.T_world_sensor, np.float64)) for sc in stream]
        info = {"cloud_topic": stream.cloud_topic, "pose_source": stream.pose_source, "skipped": dict(stream.skipped)}
    return ScanSet(scans, f"recording {path}", "recording", None, info)


# ============================================================================ helpers
def _world_hits(points: np.ndarray, T: np.ndarray, cfg) -> np.ndarray:
    """World-frame endpoints the maps insert as hits (finite, within [min_range,
    max_range]), transformed exactly as ``NdtOmMap._prepare`` does."""
    pts = np.asarray(points, np.float64)
    ok = np.isfinite(pts).all(axis=1)
    rng = np.full(len(pts), np.inf)
    rng[ok] = np.sqrt(np.einsum("ij,ij->i", pts[ok], pts[ok]))
    ok &= (rng >= cfg.min_range) & (rng <= cfg.max_range)
    return pts[ok] @ T[:3, :3].T + np.ascontiguousarray(T[:3, 3])


def _keys(index: np.ndarray) -> np.ndarray:
    idx = np.ascontiguousarray(np.asarray(index, np.int64).reshape(-1, 3))
    return idx.view([("x", np.int64), ("y", np.int64), ("z", np.int64)]).reshape(-1)


def _in(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rows of index array ``a`` that are also in ``b``."""
    return isin_rows(a, b)


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


CONFLICT_COLUMNS = ["i", "j", "k", "x", "y", "z", "rcu_n", "ndtom_logodds", "horizontal"]


def _write_csv(path: Path, rows: list[dict], columns: list[str] | None = None) -> Path:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=columns or list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return path


def _f(x: float | np.floating) -> float | None:
    """JSON-safe float (NaN -> None)."""
    x = float(x)
    return None if not math.isfinite(x) else x


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

    Parameters (all CLI-ready)
    --------------------------
    source: recording path (ROS1 bag / ROS2 folder), simworld ``.npz``, ``"sim:dynamic"``
        or ``"sim:static"``, or a sequence of (points, T_world_sensor) (see :func:`load_scans`).
    every, max_scans, sensor_frame_only: scan selection (as ``Recording.scans``; for
        simworld data ``every``/``max_scans`` pick scan indices).
    coarsen: factor of the coarse map of Fig. 4d (``NdtOmMap.coarsen``), >= 2.
    sweep: resolutions for Fig. 5 (``None``/empty: skip). OctoMap runs beside NDT-OM when
        pyoctomap is importable.
    er_eps_min: learning-rate floor of the error-refinement baseline.
    config: ``MapConfig`` for both Taichi maps (default: the paper's parameters).
    sim_scans, sim_stride, sim_seed, tools_dir: the synthetic hall (``sim:`` sources).
    plots: write the PNGs (matplotlib, Agg).
    progress: callable receiving one-line progress messages.

    Summary keys: ``source``, ``resolution``, ``scans``, ``points``, ``fig1_final_score``
    {rcu, ndtom, er}, ``fig1_min_score``, ``ndtom_vs_batch``, ``fig2_mean_score``,
    ``fig2_mean_coverage``, ``fig3_final``, ``conflicting_cells`` {count, fraction,
    fraction_of_rcu, count_empty, ...}, ``fig4d`` {fine_resolution, fine_gaussians,
    coarse_resolution, coarse_gaussians, ...}, ``time_per_scan_ms``, ``fig5`` (or None),
    ``er_update_rule``, ``definitions``, ``paper``, ``files``, ``seconds``.
    """
    from . import runtime
    from .config import MapConfig
    from .map import NdtOmMap

    say = progress or (lambda s: None)
    t_start = time.perf_counter()
    resolution = float(resolution)
    if not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"resolution must be a positive number of metres, got {resolution}")
    if isinstance(coarsen, bool) or int(coarsen) != coarsen or coarsen < 2:
        raise ValueError(f"coarsen must be an integer >= 2, got {coarsen!r}")
    cfg = config if config is not None else MapConfig()
    if plots:  # before any work: the plots are drawn at the end
        from .extras import require

        require("matplotlib", "the plots (plots=False skips them)")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    runtime.ensure_init()

    say("reading scans")
    data = load_scans(
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
    S = len(data.scans)
    mp = int(cfg.min_points)

    rcu = NdtOmMap(resolution, occupancy=False, config=cfg)
    # The paper's mapper (eq. 12 for every cell) and the same map with the NDT miss model
    # of the authors' journal version, whatever the config chose.
    ndt = NdtOmMap(resolution, occupancy=True, config=replace(cfg, miss_model="paper"))
    ndt2 = NdtOmMap(resolution, occupancy=True, config=replace(cfg, miss_model="ndt"))
    er = ErrorRefinementMap(resolution, eps_min=er_eps_min, min_points=mp)

    worlds: list[np.ndarray] = []
    dyn_cells: list[np.ndarray] = []
    fig1, fig3, fig4b = [], [], []
    times = {m: [] for m in MAPPERS}
    gauss = {}
    for i, (pts, T) in enumerate(data.scans):
        w = _world_hits(pts, T, cfg)
        worlds.append(w)
        if data.dynamic is not None:
            d = np.asarray(pts, np.float64)[data.dynamic[i]]
            dw = _world_hits(d, T, cfg)
            dyn_cells.append(np.unique(np.floor(dw / resolution).astype(np.int64), axis=0))
        for name, m in (("rcu", rcu), ("ndtom", ndt), ("ndtom_ndt", ndt2)):
            _sync()
            t0 = time.perf_counter()
            m.insert_scan(pts, T)
            _sync()
            times[name].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        er.insert_world(w)
        times["er"].append(time.perf_counter() - t0)

        batch = batch_ndt(np.concatenate(worlds), resolution, mp)
        gauss = {
            "rcu": rcu.gaussians(min_points=mp, min_probability=0.0),
            "ndtom": ndt.gaussians(),
            "ndtom_ndt": ndt2.gaussians(),
            "er": er.gaussians(),
        }
        scores = {m: mean_l2_score(gauss[m], batch) for m in MAPPERS}
        fig1.append(
            {
                "scan": i,
                "points": len(w),
                "points_total": int(sum(len(x) for x in worlds)),
                "batch_gaussians": len(batch["index"]),
                **{f"{m}_gaussians": len(gauss[m]["index"]) for m in MAPPERS},
                **{f"score_{m}": scores[m] for m in MAPPERS},
                **{f"ms_{m}": times[m][-1] * 1e3 for m in MAPPERS},
            }
        )

        known = ndt.known_cells()
        lo = known["logodds"]
        occ, emp = lo[lo > 0], lo[lo < 0]
        fig3.append(
            {
                "scan": i,
                "mean_logodds_occupied": float(occ.mean()) if len(occ) else math.nan,
                "mean_logodds_empty": float(emp.mean()) if len(emp) else math.nan,
                "occupied_cells": len(occ),
                "empty_cells": len(emp),
            }
        )

        conflict = ~_in(gauss["rcu"]["index"], gauss["ndtom"]["index"])
        n_c, n_nd, n_rc = int(conflict.sum()), len(gauss["ndtom"]["index"]), len(gauss["rcu"]["index"])
        n_c2 = int((~_in(gauss["rcu"]["index"], gauss["ndtom_ndt"]["index"])).sum())
        n_nd2 = len(gauss["ndtom_ndt"]["index"])
        fig4b.append(
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
        say(
            f"scan {i + 1}/{S}: {len(w)} points; vs batch rcu {scores['rcu']:.4f} ndtom {scores['ndtom']:.4f} "
            f"er {scores['er']:.4f}; conflicting {n_c} ({fig4b[-1]['fraction']:.1%})"
        )

    # -------------------------------------------------- NDT-OM against the batch map, cell by cell
    batch = batch_ndt(np.concatenate(worlds), resolution, mp)
    sim, it, ir = _shared_similarity(gauss["ndtom"], batch)
    same_n = gauss["ndtom"]["n"][it] == batch["n"][ir]
    ndtom_vs_batch = {
        "ndtom_gaussians": len(gauss["ndtom"]["index"]),
        "batch_gaussians": len(batch["index"]),
        "shared": len(it),
        "shared_same_n": int(same_n.sum()),
        "shared_refilled": int((~same_n).sum()),  # erased once, then new points: fewer points than batch
        "score_shared": _f(sim.mean()) if len(sim) else None,
        "score_shared_same_n": _f(sim[same_n].mean()) if same_n.any() else None,
        "min_similarity_shared_same_n": _f(sim[same_n].min()) if same_n.any() else None,
        "batch_missing_in_ndtom": int(len(batch["index"]) - len(it)),
    }
    del batch

    # -------------------------------------------------- Fig. 2: representation self-test
    say("Fig. 2: single clouds against the final maps")
    fig2 = []
    for i, w in enumerate(worlds):
        cloud = batch_ndt(w, resolution, mp)
        row: dict = {"cloud": i, "cloud_gaussians": len(cloud["index"])}
        for m in MAPPERS:
            row[f"score_{m}"] = mean_l2_score(gauss[m], cloud) if len(cloud["index"]) else math.nan
        for m in MAPPERS:
            row[f"coverage_{m}"] = mean_l2_score(cloud, gauss[m])
        fig2.append(row)

    # -------------------------------------------------- Fig. 4b / 4d
    final_conflict = ~_in(gauss["rcu"]["index"], gauss["ndtom"]["index"])
    conflict_idx = gauss["rcu"]["index"][final_conflict]
    horizontal = _horizontal_planar(gauss["rcu"]["cov"][final_conflict])
    nd_known = ndt.known_cells()
    _, ic, ik = np.intersect1d(_keys(conflict_idx), _keys(nd_known["index"]), assume_unique=True, return_indices=True)
    conflict_lo = np.zeros(len(conflict_idx))
    conflict_lo[ic] = nd_known["logodds"][ik]
    del nd_known
    last = fig4b[-1]
    conflicting = {
        "count": last["conflicting"],
        "fraction": _f(last["fraction"]),
        "fraction_of": "ndtom_gaussians",
        "fraction_of_rcu": _f(last["fraction_of_rcu"]),
        "count_empty": int((conflict_lo < 0).sum()),  # NDT-OM log-odds < 0 there (seen free)
        "horizontal": int(horizontal.sum()),
        "other": int((~horizontal).sum()),
        "other_fraction": _f((~horizontal).sum() / last["ndtom_gaussians"]) if last["ndtom_gaussians"] else None,
        "ndtom_gaussians": last["ndtom_gaussians"],
        "rcu_gaussians": last["rcu_gaussians"],
        "count_ndt_miss_model": last["conflicting_ndt"],
        "fraction_ndt_miss_model": _f(last["fraction_ndt"]),
        "definition": CONFLICT_DEFINITION,
        "horizontal_definition": HORIZONTAL_DEFINITION,
    }
    conflict_dyn = None
    if data.dynamic is not None:
        dc = np.unique(np.concatenate(dyn_cells), axis=0) if dyn_cells else np.zeros((0, 3), np.int64)
        conflict_dyn = _in(conflict_idx, dc)
        conflicting["with_dynamic_points"] = int(conflict_dyn.sum())
        conflicting["dynamic_point_cells"] = len(dc)
    conflict_rows = [
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
            gauss["rcu"]["mean"][final_conflict],
            gauss["rcu"]["n"][final_conflict],
            conflict_lo,
            horizontal,
            conflict_dyn if conflict_dyn is not None else np.zeros(len(conflict_idx)),
        )
    ]

    say(f"Fig. 4d: coarsening x{coarsen}")
    coarse = ndt.coarsen(int(coarsen))
    cg = coarse.gaussians()
    rcu_coarse = rcu.coarsen(int(coarsen))
    rcg = rcu_coarse.gaussians(min_points=mp, min_probability=0.0)
    coarse_batch = batch_ndt(np.concatenate(worlds), resolution * coarsen, mp)
    fig4d = {
        "factor": int(coarsen),
        "fine_resolution": resolution,
        "fine_gaussians": len(gauss["ndtom"]["index"]),
        "coarse_resolution": round(resolution * coarsen, 12),
        "coarse_gaussians": len(cg["index"]),
        "ratio": _f(len(gauss["ndtom"]["index"]) / len(cg["index"])) if len(cg["index"]) else None,
        "rcu_fine_gaussians": len(gauss["rcu"]["index"]),
        "rcu_coarse_gaussians": len(rcg["index"]),
        "rcu_coarse_vs_batch_score": _f(mean_l2_score(rcg, coarse_batch)),
    }
    del coarse_batch, rcu_coarse

    fig3_last = fig3[-1]
    summary: dict = {
        "source": data.description,
        "source_kind": data.kind,
        "source_info": data.info,
        "resolution": resolution,
        "scans": S,
        "points": int(sum(len(w) for w in worlds)),
        "points_per_scan": _f(np.mean([len(w) for w in worlds])),
        "arch": runtime.current_arch(),
        "config": cfg.to_dict(),
        "fig1_final_score": {m: _f(fig1[-1][f"score_{m}"]) for m in MAPPERS},
        "fig1_min_score": {m: _f(min(r[f"score_{m}"] for r in fig1)) for m in MAPPERS},
        "ndtom_vs_batch": ndtom_vs_batch,
        "fig2_mean_score": {m: _f(np.nanmean([r[f"score_{m}"] for r in fig2])) for m in MAPPERS},
        "fig2_mean_coverage": {m: _f(np.mean([r[f"coverage_{m}"] for r in fig2])) for m in MAPPERS},
        "fig3_final": {k: (_f(v) if isinstance(v, float) else v) for k, v in fig3_last.items() if k != "scan"},
        "conflicting_cells": conflicting,
        "fig4d": fig4d,
        "time_per_scan_ms": {m: _f(np.median(times[m]) * 1e3) for m in MAPPERS},
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

    files = [
        _write_csv(out / "fig1_vs_batch.csv", fig1),
        _write_csv(out / "fig2_self_test.csv", fig2),
        _write_csv(out / "fig3_logodds.csv", fig3),
        _write_csv(out / "fig4b_conflicting.csv", fig4b),
        _write_csv(
            out / "conflicting_cells.csv",
            conflict_rows,
            CONFLICT_COLUMNS + (["dynamic_points"] if conflict_dyn is not None else []),
        ),
    ]
    if plots:
        say("plots")
        files += _plots(out, fig1, fig2, fig3, fig4b, gauss, conflict_idx, cg, resolution, fig4d, data.description)

    # free every map before the sweep (it makes its own)
    del rcu, ndt, ndt2, coarse, er, gauss, cg, rcg
    gc.collect()

    if sweep:
        from . import sweep as sw

        baseline = "octomap" if sw.octomap_available() else None
        say(f"Fig. 5: sweep over {list(sweep)} ({'with OctoMap' if baseline else 'no pyoctomap: floor only'})")
        rows = sw.run_sweep(data.scans, list(sweep), baseline=baseline, progress=say)
        files.append(sw.write_csv(rows, out / "fig5_sweep.csv", sw.machine_tags(runtime.current_arch() or "cpu")))
        if plots:
            files.append(
                sw.plot(
                    rows,
                    out / "fig5_time_per_scan.png",
                    f"Fig. 5: {S} scans, {summary['points_per_scan']:.0f} points/scan",
                )
            )
        summary["fig5"] = {
            "baseline": baseline,
            "rows": [
                {
                    "mapper": r.mapper,
                    "resolution": r.resolution,
                    "ms_median": _f(r.ms_median),
                    "ms_p95": _f(r.ms_p95),
                    "ratio_to_ndtom": _f(r.ratio_to_ndtom),
                }
                for r in rows
            ],
        }

    summary["seconds"] = time.perf_counter() - t_start
    summary["files"] = sorted([p.name for p in files] + ["summary.json"])
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=_json_default) + "\n")
    return summary


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return _f(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


# ============================================================================ plots
def _finish(ax, xlabel: str, ylabel: str, title: str) -> None:
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)


def _plots(out: Path, fig1, fig2, fig3, fig4b, gauss, conflict_idx, cg, res, fig4d, title) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    styles = {"rcu": "o-", "ndtom": "s-", "ndtom_ndt": "d-", "er": "^-"}

    def save(fig, name: str) -> None:
        fig.tight_layout()
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        files.append(out / name)

    fig, ax = plt.subplots(figsize=(6.4, 4))
    for m in MAPPERS:
        ax.plot([r["scan"] + 1 for r in fig1], [r[f"score_{m}"] for r in fig1], styles[m], ms=3, label=LABELS[m])
    ax.set_ylim(0, 1.05)
    _finish(ax, "clouds inserted", "mean L2 score vs batch map", f"Fig. 1: against the batch map ({res:g} m)")
    save(fig, "fig1_vs_batch.png")

    fig, ax = plt.subplots(figsize=(6.4, 4))
    for m in MAPPERS:
        ax.plot([r["cloud"] for r in fig2], [r[f"score_{m}"] for r in fig2], styles[m], ms=3, label=LABELS[m])
    ax.set_ylim(0, 1.05)
    _finish(ax, "cloud", "score of the cloud's NDT map in the final map", "Fig. 2: representation self-test")
    save(fig, "fig2_self_test.png")

    fig, ax = plt.subplots(figsize=(6.4, 4))
    x = [r["scan"] + 1 for r in fig3]
    ax.plot(x, [r["mean_logodds_occupied"] for r in fig3], "o-", ms=3, label="occupied cells (l > 0)")
    ax.plot(x, [r["mean_logodds_empty"] for r in fig3], "s-", ms=3, label="empty cells (l < 0)")
    ax.axhline(0, color="k", lw=0.8)
    _finish(ax, "clouds inserted", "mean log-odds (NDT-OM)", "Fig. 3: mean log-odds")
    save(fig, "fig3_logodds.png")

    fig, ax = plt.subplots(figsize=(6.4, 4))
    x = [r["scan"] + 1 for r in fig4b]
    ax.plot(x, [100 * r["fraction"] for r in fig4b], "o-", ms=3, label="% of NDT-OM Gaussians")
    ax.plot(x, [100 * r["fraction_of_rcu"] for r in fig4b], "s--", ms=3, label="% of RCU Gaussians")
    ax.plot(x, [100 * r["fraction_ndt"] for r in fig4b], "d-", ms=3, label="NDT miss model: % of its Gaussians")
    _finish(ax, "clouds inserted", "conflicting cells (%)", f"Fig. 4b: Gaussian in RCU, none in NDT-OM (final {fig4b[-1]['conflicting']} cells)")
    save(fig, "fig4b_conflicting.png")

    fig, axes = plt.subplots(1, 2, figsize=(12, 5.2))
    nd = gauss["ndtom"]["mean"]
    rng = np.random.default_rng(0)
    sub = nd if len(nd) <= 150_000 else nd[rng.choice(len(nd), 150_000, replace=False)]
    ax = axes[0]
    ax.scatter(sub[:, 0], sub[:, 1], s=0.3, c="0.55", lw=0, label=f"NDT-OM Gaussians ({len(nd)})")
    if len(conflict_idx):
        cc = (conflict_idx + 0.5) * res
        ax.scatter(cc[:, 0], cc[:, 1], s=1.5, c="red", lw=0, label=f"conflicting cells ({len(conflict_idx)})")
    ax.set_title(f"NDT-OM {res:g} m, top view", fontsize=10)
    ax.set_aspect("equal", "datalim")
    ax.legend(fontsize=8, markerscale=6, loc="upper right")
    ax = axes[1]
    cm = cg["mean"]
    if len(cm):
        ax.scatter(cm[:, 0], cm[:, 1], s=1.0, c=cm[:, 2], cmap="viridis", lw=0)
    ax.set_title(
        f"Fig. 4d: coarsened x{fig4d['factor']} to {fig4d['coarse_resolution']:g} m: "
        f"{fig4d['fine_gaussians']} -> {fig4d['coarse_gaussians']} Gaussians",
        fontsize=10,
    )
    ax.set_aspect("equal", "datalim")
    fig.suptitle(title, fontsize=9)
    save(fig, "fig4_maps.png")
    return files


# ============================================================================ summary text / CLI
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
    lines.append(f"files: {', '.join(s['files'])}  ({s['seconds']:.1f} s)")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m ndtom_ti.experiments SOURCE -r RES --out DIR [options]``: run
    :func:`run_experiments` and print :func:`format_summary`."""
    ap = argparse.ArgumentParser(prog="ndtom experiments", description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("source", help="ROS1 bag, ROS2 bag folder, simworld .npz, or sim:dynamic / sim:static")
    ap.add_argument("-r", "--resolution", type=float, required=True, help="cell size (m)")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--every", type=int, default=1, help="keep every k-th cloud")
    ap.add_argument("--max-scans", type=int, default=None)
    ap.add_argument("--sensor-frame-only", action="store_true", help="identity poses")
    ap.add_argument("--coarsen", type=int, default=3, help="factor of the coarse map (Fig. 4d)")
    ap.add_argument("--sweep", type=str, default="", help="resolutions for Fig. 5, e.g. 0.2,0.3,0.4")
    ap.add_argument("--er-eps-min", type=float, default=0.05, help="learning-rate floor of the ER baseline")
    ap.add_argument("--sim-scans", type=int, default=30)
    ap.add_argument("--sim-stride", type=int, default=10)
    ap.add_argument("--sim-seed", type=int, default=0)
    ap.add_argument("--arch", choices=("auto", "cpu", "cuda"), default="auto")
    ap.add_argument("--no-plots", action="store_true")
    ap.add_argument("-q", "--quiet", action="store_true")
    a = ap.parse_args(argv)

    from . import init

    init(a.arch)
    sweep = [float(v) for v in a.sweep.split(",") if v.strip()] if a.sweep else None
    say = (lambda s: None) if a.quiet else (lambda s: print(s, file=sys.stderr, flush=True))
    s = run_experiments(
        a.source,
        a.resolution,
        a.out,
        every=a.every,
        max_scans=a.max_scans,
        sensor_frame_only=a.sensor_frame_only,
        coarsen=a.coarsen,
        sweep=sweep,
        er_eps_min=a.er_eps_min,
        sim_scans=a.sim_scans,
        sim_stride=a.sim_stride,
        sim_seed=a.sim_seed,
        plots=not a.no_plots,
        progress=say,
    )
    print(format_summary(s))
    return 0


if __name__ == "__main__":
    sys.exit(main())
