"""NdtOmMap: the NDT Occupancy Map of Saarinen et al. (ICRA 2013), exact and parallel."""

from __future__ import annotations

import functools
import weakref
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from . import runtime
from .budget import MemoryBudget
from .cellkeys import lex_order
from .config import N_LIMIT, MapConfig, check_resolution
from .kernels.families import kernel_set
from .kernels.io import io_kernels
from .kernels.layout import Layout
from .kernels.ndt import C_EXPORT, CTR_SIZE
from .persistence import load_into, state_of
from .records import GaussianRecords
from .runtime import MapMemoryError  # noqa: F401 - raised by the map's updates; imported from here by older code
from .scan_update import BLOCK_CELLS, ScanReport, ScanUpdate, UpdatePlan
from .scaninput import as_points as _as_points
from .scaninput import as_pose, cell_box  # noqa: F401 - part of this module's interface
from .snapshot import MapSnapshot, probability, select_gaussians

# NDT miss model: variance added on every axis of a Gaussian's covariance before it is
# inverted (kernels.ndt.ndt_floor; eigenvalues l1 <= l2 <= l3): NDT_COV_FLOOR * trace keeps
# flat Gaussians invertible; a line-like one (l2 < NDT_LINE * l3: the points of one scan line
# across the cell, at the ranges where a lidar's rings are a cell or more apart) gets up to
# NDT_LINE_FLOOR * l3 more, so that it stands for the surface the line samples. Without it,
# rays of the other rings never pass within the line's millimetre thickness and the
# Gaussians of objects that left stay (benchmarks/quality.py; docs/quality.md). A line
# spanning the cell (l3 ~ r^2 / 12) then stands for a surface spread evenly over the cell.
# With n points the widening is scaled by min(1, NDT_LINE_POINTS / n): a line that stays a
# line as points join it (a shelf's edge seen from many poses) is a thin structure, and rays
# passing beside it are not evidence against it. NDT_COV_FLOOR (2% of the trace: ~1.2 cm
# across a plane filling a 0.2 m cell) also makes rays that graze a face a few centimetres
# off count a little, as through the flat top of an object that left.
NDT_COV_FLOOR = 0.02
NDT_LINE = 0.5
NDT_LINE_FLOOR = 1.0
NDT_LINE_POINTS = 4.0
# NDT miss model, cells holding fewer than min_points points: their points' mean with this
# standard deviation (metres) added on every axis, so that sparse floor cells are not erased
# by rays grazing far above their points, while a ray passing close to them still clears them.
NDT_SPARSE_SIGMA = 0.05


def _locked(method):
    """Run a public method holding the map's lock (see NdtOmMap: thread safety)."""

    @functools.wraps(method)
    def call(self, *args, **kwargs):
        with self._lock:
            self._check_open()
            if _dead_slots:
                _release_dead()
            return method(self, *args, **kwargs)

    return call


_dead_slots: list = []  # (storage, slot) of maps collected while another thread held the lock


def _release_slot(st, slot: int) -> None:
    """Empty a dead map's slot (a kernel: never while another thread's kernels run). The
    garbage collector calls this in any thread, maybe inside another lock's holder: it
    never waits; a slot it cannot empty now is emptied by the next map call."""
    if not st.lock.acquire(blocking=False):
        _dead_slots.append((st, slot))
        return
    try:
        runtime.release_slot(st, slot)
        _release_dead()
    finally:
        st.lock.release()


def _release_dead() -> None:
    while _dead_slots:
        st, slot = _dead_slots.pop()
        runtime.release_slot(st, slot)


class NdtOmMap:
    """An NDT Occupancy Map.

    Cells are cubes of side ``resolution`` (metres); a point ``x`` (world frame) falls in
    cell ``floor(x / resolution)``. Each cell holds a Gaussian (N, mean, covariance)
    updated exactly by the Recursive Covariance Update and, with ``occupancy=True``, a
    log-odds updated by ray tracing (eq. 12): Gaussians of cells that rays show empty are
    erased. ``occupancy=False`` is the paper's "Recursive NDT": no ray tracing; log-odds
    only rise with hits.

    The grid spans ``layout.cells`` cells per axis centred on the origin (default
    32768 x 32768 x 4096: +-1.6 km x +-1.6 km x +-205 m at 0.1 m). Points outside it are
    dropped and counted.

    Thread safety: every public method holds the map's lock (``_lock``, re-entrant). It is
    one lock for all maps of the process, because they share Taichi's runtime, the sparse
    trees and the scan scratch: calls from several threads, on one map or on several, are
    safe and run one at a time.
    """

    def __init__(
        self,
        resolution: float,
        *,
        occupancy: bool = True,
        config: MapConfig | None = None,
        layout: Layout | None = None,
        metadata: dict | None = None,
        p_occupied: float | None = None,
        p_empty: float | None = None,
        logodds_min: float | None = None,
        logodds_max: float | None = None,
        min_points: int | None = None,
        min_range: float | None = None,
        max_range: float | None = None,
        max_range_mode: str | None = None,
        n_max: int | None = None,
        **options: Any,
    ):
        """A new, empty map.

        resolution: cell size in metres (> 0).
        occupancy: ray-trace free space (NDT-OM); False is the paper's Recursive NDT
            (Gaussians only, no ray tracing).
        config: a :class:`MapConfig` with the sensor model; or give its options here one
            by one (not both): ``p_occupied`` (p_o, default 0.6), ``p_empty`` (p_e, 0.49),
            ``logodds_min`` / ``logodds_max`` (clamp, -2 / 2), ``min_points`` (points a
            Gaussian needs, 3), ``min_range`` / ``max_range`` (m, 0 / inf),
            ``max_range_mode`` ("drop" or "free"), ``n_max`` (cap on N, 0 = off). Options
            left out (None) keep MapConfig's defaults; ``**options`` takes any other
            MapConfig field.
        layout: grid size (default :class:`Layout`: 32768 x 32768 x 4096 cells).
        metadata: a dict saved with the map (source, settings, ...).

        Raises TypeError or ValueError for a bad resolution or option, and
        MapMemoryError when every map slot of the process is taken.
        """
        given = {
            "p_occupied": p_occupied,
            "p_empty": p_empty,
            "logodds_min": logodds_min,
            "logodds_max": logodds_max,
            "min_points": min_points,
            "min_range": min_range,
            "max_range": max_range,
            "max_range_mode": max_range_mode,
            "n_max": n_max,
        }
        options = {**{k: v for k, v in given.items() if v is not None}, **options}
        resolution = check_resolution(resolution)
        if config is not None and options:
            raise TypeError("pass either config=MapConfig(...) or keyword options, not both")
        if options:
            from dataclasses import fields

            unknown = sorted(set(options) - {f.name for f in fields(MapConfig)})
            if unknown:
                raise TypeError(
                    f"unknown map options {unknown}; the options are MapConfig's: "
                    f"{', '.join(f.name for f in fields(MapConfig))}"
                )
        self.config = config if config is not None else MapConfig(**options)
        if not isinstance(self.config, MapConfig):
            raise TypeError(f"config must be a MapConfig, got {type(self.config).__name__}")
        self.config.check_at(resolution)
        self.resolution = resolution
        self.occupancy_enabled = bool(occupancy)
        self.layout = layout or Layout()
        self.metadata: dict = dict(metadata or {})
        self.scans_inserted = 0
        self.points_inserted = 0

        with runtime.storage(self.layout).lock:
            if _dead_slots:  # slots of maps collected while the lock was held: free them first
                _release_dead()
        self._st, self._slot = runtime.acquire_slot(self.layout)
        self._lock = self._st.lock
        with self._lock:
            self._k = kernel_set(self._st)  # the update kernels (kernels/families.py)
            self._io = io_kernels(self._st)  # queries, export, load
        # Empty the slot for the next map (close(), or when the map is collected); nothing
        # to do at interpreter exit.
        self._release = weakref.finalize(self, _release_slot, self._st, self._slot)
        self._release.atexit = False
        self._ctr = np.zeros(CTR_SIZE, np.int64)  # export's counters
        self._glo = np.array(self.layout.lo, np.int64)
        self._ghi = np.array(self.layout.hi, np.int64)
        c = self.config
        sigma_s = c.sigma_s_at(self.resolution)
        self._ndt_prm = np.array([c.eta, 0.5 / sigma_s**2, NDT_COV_FLOOR, NDT_LINE, NDT_LINE_FLOOR, c.min_points,
                                  NDT_SPARSE_SIGMA**2, NDT_LINE_POINTS, c.near_cells_at(self.resolution)])  # fmt: skip
        # Points a cell needs for the NDT miss model (1: every cell with points, those with
        # fewer than min_points under the prior above); 0: the paper's model (kernel switch).
        self._ndt_minp = 1 if c.ndt_misses else 0
        self._records = GaussianRecords(c.ndt_misses, self._ndt_prm, self._ndt_minp)
        self._budget = MemoryBudget(self._st, self._slot, self._k, self.occupancy_enabled)
        # How the updates run (speed only). On CUDA a numpy block is copied to the device
        # and back at every launch: keep it to the 1M cells nearest the sensor there.
        self.plan = UpdatePlan(block_cells=BLOCK_CELLS if self.arch == "cpu" else 1 << 20)
        # Without n_max the updates still cap N at N_LIMIT: past 2**31 the kernels' int32
        # counts would wrap, and a Gaussian of a negative count is deleted.
        upd_cfg = self.config if self.config.n_max else replace(self.config, n_max=N_LIMIT)
        self._update = ScanUpdate(st=self._st, slot=self._slot, kernels=self._k, records=self._records,
                                  budget=self._budget, plan=self.plan, config=upd_cfg, resolution=self.resolution,
                                  occupancy=self.occupancy_enabled, arch=self.arch)  # fmt: skip

    # ------------------------------------------------------------------ properties

    @property
    def arch(self) -> str:
        return runtime.current_arch() or "cpu"

    @property
    def block_cells(self) -> int:
        """Most cells of the dense ray-count block (``plan.block_cells``)."""
        return self.plan.block_cells

    @block_cells.setter
    def block_cells(self, value: int) -> None:
        self.plan.block_cells = value

    @property
    def grid_extent(self) -> tuple[np.ndarray, np.ndarray]:
        """World-frame bounds (metres) of the grid the map can hold: (min corner, max
        corner). Points outside are dropped. For the part holding data: :meth:`data_extent`."""
        return self._glo * self.resolution, self._ghi * self.resolution

    @property
    def extent(self) -> tuple[np.ndarray, np.ndarray]:
        """The same as :attr:`grid_extent` (the grid, not the data; kept for older code)."""
        return self.grid_extent

    def data_extent(self) -> tuple[np.ndarray, np.ndarray] | None:
        """World-frame bounds (metres) of the known cells, occupied or free: (min corner,
        max corner) of the box of whole cells holding them; None for an empty map."""
        idx = self.known_cells()["index"]
        if len(idx) == 0:
            return None
        lo, hi = cell_box(idx)
        return lo * self.resolution, (hi + 1) * self.resolution

    def cell_index(self, points: Any) -> np.ndarray:
        """Cell indices ``floor(x / resolution)`` (int64) of world points (N, 3)."""
        return np.floor(_as_points(points) / self.resolution).astype(np.int64)

    def cell_center(self, index: Any) -> np.ndarray:
        """World centres of cells (N, 3) from integer indices."""
        return (np.asarray(index, np.float64) + 0.5) * self.resolution

    # ------------------------------------------------------------------ updates

    @_locked
    def traverse_only(self, points: Any, T_world_sensor: Any) -> ScanReport:
        """Benchmark floor: the scan's rays traversed through the same sparse layout with
        one integer atomic per visited cell and nothing else. It leaves ray counters set:
        use a map made for this purpose only."""
        return self._update.traverse_only(points, T_world_sensor)

    # ------------------------------------------------------------------ lifetime

    def close(self) -> None:
        """Give the map's slot and memory back now (a process holds ``init(max_maps=...)``
        maps at once; otherwise that happens when the map is garbage-collected). Any later
        use of the map raises ValueError; closing again does nothing."""
        with self._lock:
            self._release()  # runs once: the collector will not release the slot again

    @property
    def closed(self) -> bool:
        return not self._release.alive

    def __enter__(self) -> NdtOmMap:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _check_open(self) -> None:
        if not self._release.alive:
            raise ValueError("this map is closed (NdtOmMap.close()); make a new map or load one")

    def insert_scan(self, points: Any, T_world_sensor: Any) -> ScanReport:
        """Insert one scan: ``points`` (N, 3) in the sensor frame (metres), and the pose
        ``T_world_sensor`` (4, 4) mapping sensor-frame points into the world.

        NaN/Inf points, points outside [min_range, max_range] and points outside the grid
        are dropped and counted in the returned report. A call that raises leaves the map
        unchanged.
        """
        with self._st.lock:  # the dense block is shared by the maps of the process
            self._check_open()
            # Kernels compile (or load from Taichi's offline cache) at their first call in
            # the process: a scan's time includes those its update needed first.
            rep = self._update.insert_guarded(points, T_world_sensor)
            self.scans_inserted += 1
            self.points_inserted += rep.points_used
            return rep

    @_locked
    def memory_bytes(self) -> int:
        """Bytes this map holds: nodes of its sparse trees (counted exactly by the
        kernels) plus its Gaussian records."""
        return self._st.slot_bytes(self._slot) + self._records.nbytes()

    @_locked
    def memory_report(self) -> dict:
        """Memory held, by part, with bytes per known cell and per Gaussian."""
        nodes = self._st.nodes(self._slot)
        known = len(self.known_cells()["index"])
        gauss = len(self)
        total = self.memory_bytes()
        return {
            "total_bytes": total,
            "node_bytes": self._st.slot_bytes(self._slot),
            "record_bytes": self._records.nbytes(),
            "records_held": self._records.capacity,
            "records_in_use": self._records.in_use,
            "records_free": self._records.nfree,
            "occupancy_regions": int(nodes[0]),
            "occupancy_leaves": int(nodes[1]),
            "index_regions": int(nodes[2]),
            "index_leaves": int(nodes[3]),
            "known_cells": known,
            "gaussians": gauss,
            "bytes_per_known_cell": total / known if known else float("nan"),
            "bytes_per_gaussian": total / gauss if gauss else float("nan"),
            # Scan scratch of all maps, outside the pool: the dense ray-count block.
            "process_scratch_bytes": self._st.block_buf.nbytes + self._st.bflag_buf.nbytes,
            "process_pool_bytes": self._st.pool_bytes(),
            "process_pool_budget_bytes": runtime.pool_limit(),
        }

    # ------------------------------------------------------------------ queries

    def _raw_gaussians(self) -> dict:
        """Every record that holds points, sorted by cell index, with its log-odds."""
        raw = self._records.holding_points()
        idx = raw["index"]
        lo = np.zeros(len(idx), np.float32)
        if len(idx):
            self._io.query(self._slot, idx, len(idx), lo)
        return {**raw, "logodds": lo}

    @_locked
    def gaussians(self, min_points: int | None = None, min_probability: float = 0.5) -> dict:
        """The map's Gaussians, sorted by cell index.

        Returns a dict of numpy arrays: ``index`` (K, 3) int64 cell indices, ``mean``
        (K, 3) float64 world frame, ``cov`` (K, 3, 3) float64 sample covariance (divided
        by N - 1), ``n`` (K,) int64, ``p_occ`` (K,) float64 occupancy probability,
        ``logodds`` (K,) float64. Cells need ``n >= min_points`` (default: the config's
        min_points) and ``p_occ > min_probability``; ``min_probability=0`` also returns
        Gaussians of cells not (yet) occupied, and under the NDT miss model those of free
        cells whose log-odds rays lowered short of the reset threshold (they keep their
        points for their next hit).
        """
        raw = self._raw_gaussians()
        return select_gaussians(raw["index"], raw["n"], raw["mean_rel"], raw["scatter"], raw["logodds"],
                                self.resolution, min_points, min_probability, self.config.min_points)  # fmt: skip

    @_locked
    def known_cells(self) -> dict:
        """Every cell with a non-zero log-odds (occupied and free), sorted by index:
        ``index`` (K, 3) int64, ``logodds`` (K,) float64, ``p_occ`` (K,) float64."""
        ctr = self._ctr
        ctr[:] = 0
        self._io.count_known(self._slot, ctr)
        K = int(ctr[C_EXPORT])
        idx = np.empty((K, 3), np.int32)
        val = np.empty(K, np.float32)
        if K:
            ctr[:] = 0
            self._io.export_known(self._slot, idx, val, ctr)
        order = lex_order(idx)
        lo = val[order].astype(np.float64)
        return {"index": idx[order].astype(np.int64), "logodds": lo, "p_occ": probability(lo)}

    @_locked
    def occupancy(self, points: Any, *, return_known: bool = False) -> Any:
        """Occupancy probability of the cells holding world ``points`` (N, 3), or of one
        point (3,) (then a float, and a bool with ``return_known``).

        Unknown cells (never touched, or outside the grid) read 0.5, the prior; pass
        ``return_known=True`` to also get a boolean mask of the cells that are known.
        """
        if np.ndim(points) == 1 and np.shape(points) == (3,):
            p, k = self.occupancy(np.reshape(points, (1, 3)), return_known=True)
            return (float(p[0]), bool(k[0])) if return_known else float(p[0])
        pts = _as_points(points)
        out = np.full(len(pts), 0.5)
        known = np.zeros(len(pts), bool)
        ok = np.isfinite(pts).all(axis=1)
        cells = np.zeros((len(pts), 3))
        cells[ok] = np.floor(pts[ok] / self.resolution)
        ok &= ((cells >= self._glo) & (cells < self._ghi)).all(axis=1)
        if ok.any():
            lo = self.logodds_at(cells[ok].astype(np.int64))
            out[ok] = probability(lo)
            known[ok] = lo != 0.0
        return (out, known) if return_known else out

    @_locked
    def logodds_at(self, index: Any) -> np.ndarray:
        """Log-odds (float64) of cells given by integer index (K, 3); unknown cells and
        cells outside the grid read 0."""
        idx = np.asarray(index)
        if idx.ndim != 2 or idx.shape[1] != 3 or not np.issubdtype(idx.dtype, np.integer):
            raise ValueError(f"index must be an integer (K, 3) array of cell indices, got {idx.dtype} {idx.shape}")
        out = np.zeros(len(idx))
        ok = ((idx >= self._glo) & (idx < self._ghi)).all(axis=1)
        if ok.any():
            lo = np.empty(int(ok.sum()), np.float32)
            self._io.query(self._slot, np.ascontiguousarray(idx[ok], np.int32), len(lo), lo)
            out[ok] = lo
        return out

    @_locked
    def __len__(self) -> int:
        """Number of Gaussians: cells with ``n >= min_points`` that are occupied."""
        return int(np.count_nonzero(self._occupied_gaussian_mask()))

    def _occupied_gaussian_mask(self) -> np.ndarray:
        """Of the records with at least min_points points, which cells are occupied."""
        cells = self._records.with_points(self.config.min_points)
        if len(cells) == 0:
            return np.zeros(0, bool)
        lo = np.zeros(len(cells), np.float32)
        self._io.query(self._slot, cells, len(cells), lo)
        return lo > 0.0

    def __repr__(self) -> str:
        if self.closed:
            return f"NdtOmMap(resolution={self.resolution:g}, occupancy={self.occupancy_enabled}, closed)"
        return (
            f"NdtOmMap(resolution={self.resolution:g}, occupancy={self.occupancy_enabled}, "
            f"scans={self.scans_inserted}, gaussians={len(self)}, arch={self.arch!r}, "
            f"memory={self.memory_bytes() / 2**20:.1f} MiB)"
        )

    # ------------------------------------------------------------------ state in/out

    @_locked
    def state(self) -> dict:
        """All cell state as numpy arrays (what ``save`` writes)."""
        return state_of(self)

    def _load_state(self, st: dict) -> None:
        """Write cell state into this (empty) map (see persistence.load_into)."""
        load_into(self, st)

    def save(self, path: str | Path) -> Path:
        """Write the map to one versioned file, atomically (see ``ndtom_ti.mapfile``)."""
        from .mapfile import save_map

        return save_map(self, path)

    @classmethod
    def load(cls, path: str | Path) -> NdtOmMap:
        """Read a map written by ``save``; broken or foreign files raise MapFileError."""
        from .mapfile import load_map

        return load_map(path)

    @_locked
    def snapshot(self) -> MapSnapshot:
        """The map's content now as plain numpy arrays (:class:`~ndtom_ti.snapshot.MapSnapshot`):
        save, export, coarsen and view it without a map slot."""
        return MapSnapshot.of(self)

    @classmethod
    def from_snapshot(cls, s: MapSnapshot) -> NdtOmMap:
        """A new map holding snapshot ``s`` (its settings, cells and counters), to map on.
        Takes a map slot, as any new map does."""
        import copy

        m = cls(
            s.resolution,
            occupancy=s.occupancy_enabled,
            config=s.config,
            layout=s.layout,
            metadata=copy.deepcopy(s.metadata),
        )  # the map's metadata changes; the snapshot's must not
        try:
            with m._lock:
                m._load_state(s.state())
                m.scans_inserted = s.scans_inserted
                m.points_inserted = s.points_inserted
        except BaseException:
            m.close()  # the slot back at once: the map was never handed out
            raise
        return m

    @_locked
    def coarsen(self, factor: int) -> NdtOmMap:
        """A new map at ``factor * resolution`` (method.md sec. 4).

        Every cell's (N, mean, scatter) is merged with the RCU into its parent
        ``floor(index / factor)``: the Gaussian part equals a map built directly at the
        coarse resolution from the same points. A parent's log-odds is the maximum of its
        known children's (an occupied child makes the parent occupied: safe for planning).
        """
        if isinstance(factor, bool) or int(factor) != factor or factor < 2:
            raise ValueError(f"factor must be an integer >= 2, got {factor!r}")
        from .multires import coarsen_state

        f = int(factor)
        out = NdtOmMap(
            self.resolution * f,
            occupancy=self.occupancy_enabled,
            config=self.config,
            layout=self.layout,
            metadata={**self.metadata, "coarsened_from": self.resolution, "factor": f},
        )
        out._load_state(coarsen_state(self.state(), self.resolution, f, self.config.n_max))
        out.scans_inserted = self.scans_inserted
        out.points_inserted = self.points_inserted
        return out
