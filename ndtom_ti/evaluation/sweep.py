"""Resolution sweeps: time per scan of NDT-OM against resolution, beside its floor and
OctoMap on the same world-frame points and origins (the paper's Fig. 5)."""

from __future__ import annotations

import csv
import math
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from .. import runtime
from ..config import MapConfig, check_resolution
from ..frames import far_origin, shifted
from ..map import NdtOmMap
from ..scan import scan_parts
from ..scaninput import as_pose

# A scan inside a sweep: (points (N, 3) float32 sensor frame, T_world_sensor (4, 4) float64).
_Pair = tuple[np.ndarray, np.ndarray]


@dataclass
class SweepRow:
    mapper: str  # "ndtom", "ndtom-floor" or "octomap"
    resolution: float
    scans: int
    points_per_scan: float
    ms_median: float
    ms_p95: float
    points_per_s: float
    visits_per_s: float  # ray-cell visits per second (NaN for OctoMap)
    known_cells: int | None  # None where the mapper does not keep them (the floor)
    gaussians: int | None  # None for mappers without Gaussians (the floor, OctoMap)
    memory_bytes: int
    ratio_to_ndtom: float = math.nan  # this mapper's median / NDT-OM's median


def _near_origin(scans: list, finest: float) -> list:
    """The scans with poses shifted as the mapping loop shifts georeferenced ones
    (frames.py, at the finest resolution's grid): timing is the same anywhere,
    and neither NDT-OM's grid nor OctoMap's keys reach kilometres from the origin."""
    from ..kernels.layout import Layout

    origin = far_origin(scans[0][1], Layout().cells, finest)
    return scans if origin is None else [(pts, shifted(T, origin)) for pts, T in scans]


class ResolutionTooFineError(ValueError):
    """Resolutions whose map grid cannot hold the scans' sensor path: ``resolutions`` (the
    ones refused), ``finest`` (the finest resolution that holds the path, metres) and
    ``what`` (which resolutions of the caller they are)."""

    def __init__(self, message: str, resolutions: list[float], finest: float, what: str) -> None:
        super().__init__(message)
        self.resolutions = resolutions
        self.finest = finest
        self.what = what


def check_grid(scans: Sequence[Any], resolutions: Sequence[float], what: str = "resolutions") -> None:
    """Refuse, before any work, resolutions whose map grid (the default Layout, centred on
    the origin) cannot hold every scan's sensor origin, once shifted as :func:`run_sweep`
    shifts them: the first such scan would stop the sweep. ResolutionTooFineError."""
    from ..kernels.layout import Layout

    if not scans or not resolutions:
        return
    res = [check_resolution(r) for r in resolutions]
    poses = [as_pose(T) for _, T in map(scan_parts, scans)]
    origin = far_origin(poses[0], Layout().cells, min(res))
    pos = np.array([T[:3, 3] for T in poses], np.float64)
    if origin is not None:
        pos = pos - origin
    layout = Layout()
    lo, hi = np.asarray(layout.lo, np.float64), np.asarray(layout.hi, np.float64)
    cells = np.asarray(layout.cells, np.float64)
    bad = []
    for r in res:
        c = np.floor(pos / r)
        if ((c < lo) | (c >= hi)).any():
            bad.append(r)
    if not bad:
        return
    # the finest resolution whose grid holds the path: |p| / r within the half grid, with a margin
    finest = float(np.max(np.abs(pos).max(axis=0) / (cells / 2.0 - 1.0)))
    nice = float(f"{finest * 1.01:.2g}")
    span = " x ".join(f"{v:g}" for v in np.round(cells * min(bad), 6))
    raise ResolutionTooFineError(
        f"{', '.join(f'{r:g}' for r in bad)} m {'is' if len(bad) == 1 else 'are'} too fine for these scans: "
        f"the map's grid holds {layout.cells[0]} x {layout.cells[1]} x {layout.cells[2]} cells "
        f"({span} m at {min(bad):g} m, centred on the origin), and the sensor goes to "
        f"{np.round(pos.min(axis=0), 3).tolist()} .. {np.round(pos.max(axis=0), 3).tolist()} m; "
        f"{nice:g} m or coarser holds it",
        bad,
        nice,
        what,
    )


def _sync() -> None:
    import taichi as ti

    ti.sync()


def _time_scans(fn: Callable[[np.ndarray, np.ndarray], object], scans: Sequence[_Pair]) -> tuple[list[float], list]:
    times, reports = [], []
    for pts, T in scans:
        _sync()
        t0 = time.perf_counter()
        rep = fn(pts, T)
        _sync()
        times.append(time.perf_counter() - t0)
        reports.append(rep)
    return times, reports


def _row(
    mapper: str,
    res: float,
    scans: Sequence[_Pair],
    times: list[float],
    visits: int,
    known: int | None,
    gauss: int | None,
    mem: int,
) -> SweepRow:
    t = np.asarray(times)
    pts = sum(len(p) for p, _ in scans)
    return SweepRow(
        mapper=mapper,
        resolution=res,
        scans=len(scans),
        points_per_scan=pts / len(scans),
        ms_median=float(np.median(t) * 1e3),
        ms_p95=float(np.percentile(t, 95) * 1e3),
        points_per_s=pts / float(t.sum()),
        visits_per_s=visits / float(t.sum()) if visits else math.nan,
        known_cells=known,
        gaussians=gauss,
        memory_bytes=mem,
    )


def octomap_available() -> bool:
    """Whether pyoctomap imports (installed and whole)."""
    from ..extras import available, import_error

    return available("pyoctomap") and import_error("pyoctomap") is None


def run_sweep(
    scans: Sequence[Any],
    resolutions: Sequence[float],
    *,
    floor: bool = True,
    baseline: str | None = None,
    warmup: int = 2,
    max_range: float = -1.0,
    progress: Callable[[str], None] | None = None,
    config: MapConfig | None = None,
    on_row: Callable[[SweepRow], None] | None = None,
) -> list[SweepRow]:
    """Time every resolution on the same scans (:class:`~ndtom_ti.scan.Scan` objects or
    (points, T_world_sensor) pairs). Before timing, ``warmup`` scans go into
    a throwaway map so that kernels are compiled. NDT-OM maps with ``config`` (default:
    ``MapConfig()``; e.g. ``MapConfig(miss_model="paper")`` to time the paper's eq. (12)).
    Returns one row per mapper and resolution; ``ratio_to_ndtom`` compares medians within
    this run. ``on_row`` gets each row as it is finished: a caller keeps them when the sweep
    stops early (Ctrl-C, a resolution that does not fit in memory). Resolutions whose grid
    cannot hold the scans are refused before any work (:func:`check_grid`)."""
    if not scans:
        raise ValueError("a sweep needs at least one scan")
    if baseline not in (None, "octomap"):
        raise ValueError(f"unknown baseline {baseline!r}; the supported baseline is 'octomap'")
    if baseline == "octomap" and not octomap_available():
        from ..extras import require

        require("pyoctomap", "the OctoMap baseline")
    scans = [(np.ascontiguousarray(p, np.float32), as_pose(T)) for p, T in map(scan_parts, scans)]
    check_grid(scans, resolutions)
    scans = _near_origin(scans, min(check_resolution(r) for r in resolutions))
    say = progress or (lambda s: None)
    rows: list[SweepRow] = []

    def done(row: SweepRow) -> None:
        rows.append(row)
        if on_row is not None:
            on_row(row)

    for res in [check_resolution(r) for r in resolutions]:
        say(f"{res:g} m: warm-up")
        with NdtOmMap(res, config=config) as w:  # each map gives its slot back at once
            for pts, T in scans[:warmup]:
                w.insert_scan(pts, T)
                w.traverse_only(pts, T)

        say(f"{res:g} m: NDT-OM")
        with NdtOmMap(res, config=config) as m:
            times, reps = _time_scans(m.insert_scan, scans)
            visits = sum(r.ray_cell_visits for r in reps)
            full = _row("ndtom", res, scans, times, visits, m.known_cell_count(), len(m), m.memory_bytes())
        done(full)
        if floor:
            say(f"{res:g} m: floor")
            with NdtOmMap(res) as f:
                times, reps = _time_scans(f.traverse_only, scans)
                r = _row(
                    "ndtom-floor", res, scans, times, sum(x.ray_cell_visits for x in reps), None, None, f.memory_bytes()
                )
            r.ratio_to_ndtom = r.ms_median / full.ms_median
            done(r)
        if baseline == "octomap":
            say(f"{res:g} m: OctoMap")
            done(_octomap_row(scans, res, full, max_range))
    return rows


def _octomap_row(scans: Sequence[_Pair], res: float, full: SweepRow, max_range: float) -> SweepRow:
    import pyoctomap

    tree = pyoctomap.OcTree(res)  # pyright: ignore[reportAttributeAccessIssue] (a compiled module)
    world = []
    for pts, T in scans:
        ok = np.isfinite(pts).all(axis=1)
        world.append(
            (np.ascontiguousarray(pts[ok].astype(np.float64) @ T[:3, :3].T + T[:3, 3]), np.ascontiguousarray(T[:3, 3]))
        )
    times = []
    for w, o in world:
        t0 = time.perf_counter()
        tree.insertPointCloud(w, o, max_range)
        times.append(time.perf_counter() - t0)
    row = _row("octomap", res, scans, times, 0, int(tree.getNumLeafNodes()), None, int(tree.memoryUsage()))
    row.ratio_to_ndtom = row.ms_median / full.ms_median
    return row


def machine_tags(arch: str) -> dict:
    import taichi as ti

    tags = {
        "machine": platform.node(),
        "cpu": platform.processor() or platform.machine(),
        "cores": __import__("os").cpu_count(),
        "arch": arch,
        "python": platform.python_version(),
        "taichi": ".".join(str(v) for v in ti.__version__),
        "numpy": np.__version__,
        "pinned_threads": len(runtime.pinned_threads()),  # Taichi workers fixed to a CPU (affinity.py)
    }
    if octomap_available():
        import pyoctomap

        tags["pyoctomap"] = getattr(pyoctomap, "__version__", "?")
    return tags


def write_csv(rows: Sequence[SweepRow], path: Path, tags: dict) -> Path:
    """One line per row, then the ``tags`` (machine, versions, data) in every line; a tag
    named like a row field (e.g. ``scans``) is left out: the row's value stands."""
    own = [f.name for f in fields(SweepRow)]
    tags = {k: v for k, v in tags.items() if k not in own}
    names = own + sorted(tags)
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=names)
        w.writeheader()
        for r in rows:
            w.writerow({**asdict(r), **tags})
    return path


def plot(rows: Sequence[SweepRow], path: Path, title: str) -> Path:
    """Time per scan against resolution, every mapper, with the 100 ms real-time line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for mapper, style in (("ndtom", "o-"), ("ndtom-floor", "s--"), ("octomap", "^-")):
        rs = sorted((r for r in rows if r.mapper == mapper), key=lambda r: r.resolution)
        if rs:
            ax.plot([r.resolution for r in rs], [r.ms_median for r in rs], style, label=mapper)
    ax.axhline(100.0, color="red", lw=1, ls=":", label="100 ms (10 Hz)")
    ax.set_xlabel("resolution (m)")
    ax.set_ylabel("time per scan, median (ms)")
    ax.set_yscale("log")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
