"""NdtOmMap: the NDT Occupancy Map of Saarinen et al. (ICRA 2013), exact and parallel."""

from __future__ import annotations

import functools
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from . import runtime
from .atomic import check_target
from .cellquery import cell_extent, check_cell_index, known_cells_of, occupancy_of, select_gaussians
from .config import N_LIMIT, MapConfig, check_resolution, config_of
from .kernels.layout import Layout
from .mapfile import MapFileError
from .memreport import memory_report
from .scan_update import BLOCK_CELLS, ScanReport, ScanUpdate, UpdatePlan
from .scaninput import as_points as _as_points
from .signals import deferred_interrupt
from .slot import MapSlot, release_dead
from .snapshot import SETTINGS, MapSnapshot, copy_metadata, refuse_export_suffix


def _locked(method):
    """Run a public method holding the map's lock (see NdtOmMap: thread safety)."""

    @functools.wraps(method)
    def call(self, *args, **kwargs):
        runtime.check_process()  # before the lock: one another thread held at a fork stays held
        with self._lock:
            self._slot.check_open()
            release_dead()
            return method(self, *args, **kwargs)

    return call


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
        NoFreeSlotError when every map slot of the process is taken.
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
        resolution = check_resolution(resolution)
        self.config = config_of(config, {**{k: v for k, v in given.items() if v is not None}, **options})
        self.config.check_at(resolution)
        self.resolution = resolution
        self.occupancy_enabled = bool(occupancy)
        self.layout = layout or Layout()
        self.metadata: dict = dict(metadata or {})
        self.scans_inserted = 0
        self.points_inserted = 0

        c = self.config
        # The slot is emptied by close(), or when the map is collected.
        self._slot = MapSlot(
            self.layout,
            ndt=c.ndt_misses,
            ndt_params=c.ndt_params(self.resolution),
            ndt_min_points=c.ndt_min_points,
            occupancy=self.occupancy_enabled,
        )
        self._lock = self._slot.lock
        # How the updates run (speed only). On CUDA a numpy block is copied to the device
        # and back at every launch: keep it to the 1M cells nearest the sensor there.
        self.plan = UpdatePlan(block_cells=BLOCK_CELLS if self.arch == "cpu" else 1 << 20)
        # Without n_max the updates still cap N at N_LIMIT: past 2**31 the kernels' int32
        # counts would wrap, and a Gaussian of a negative count is deleted.
        upd_cfg = self.config if self.config.n_max else replace(self.config, n_max=N_LIMIT)
        self._update = ScanUpdate(
            slot=self._slot,
            plan=self.plan,
            config=upd_cfg,
            resolution=self.resolution,
            occupancy=self.occupancy_enabled,
            arch=self.arch,
        )

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
        return self._slot.glo * self.resolution, self._slot.ghi * self.resolution

    def data_extent(self) -> tuple[np.ndarray, np.ndarray] | None:
        """World-frame bounds (metres) of the known cells, occupied or free: (min corner,
        max corner) of the box of whole cells holding them; None for an empty map."""
        return cell_extent(self.known_cells()["index"], self.resolution)

    def cell_index(self, points: Any) -> np.ndarray:
        """Cell indices ``floor(x / resolution)`` (int64) of world points (N, 3). ValueError
        for points not finite or too far for an int64 index."""
        pts = _as_points(points)
        with np.errstate(over="ignore", invalid="ignore"):
            q = np.floor(pts / self.resolution)
        bad = np.flatnonzero(~(np.abs(q) < 2.0**63).all(axis=1))  # (NaN fails too: astype gives -2**63)
        if len(bad):
            raise ValueError(
                f"points must be finite, with cell indices that fit int64 (|x| < {2.0**63 * self.resolution:.3g} m); "
                f"point {bad[0]} is {pts[bad[0]].tolist()}"
            )
        return q.astype(np.int64)

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
        self._slot.close()

    @property
    def closed(self) -> bool:
        return self._slot.closed

    def __enter__(self) -> NdtOmMap:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def insert_scan(self, points: Any, T_world_sensor: Any) -> ScanReport:
        """Insert one scan: ``points`` (N, 3) in the sensor frame (metres), and the pose
        ``T_world_sensor`` (4, 4) mapping sensor-frame points into the world.

        NaN/Inf points, points outside [min_range, max_range] and points outside the grid
        are dropped and counted in the returned report. A call that raises an error leaves
        the map unchanged; Ctrl-C during a call (KeyboardInterrupt, in the main thread) is
        raised once the scan is inserted whole (a second Ctrl-C raises at once).
        """
        with self._lock, deferred_interrupt():  # the dense block is shared by the maps of the process
            self._slot.check_open()
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
        return self._slot.node_bytes() + self._slot.records.nbytes()

    @_locked
    def memory_report(self) -> dict:
        """Memory held, by part, with bytes per known cell and per Gaussian (see
        :func:`~ndtom_ti.memreport.memory_report`)."""
        return memory_report(self._slot, self.known_cell_count(), len(self), self.memory_bytes())

    # ------------------------------------------------------------------ queries

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
        raw = self._slot.gaussian_records()
        return select_gaussians(
            raw["index"],
            raw["n"],
            raw["mean_rel"],
            raw["scatter"],
            raw["logodds"],
            self.resolution,
            min_points,
            min_probability,
            self.config.min_points,
        )

    @_locked
    def known_cells(self) -> dict:
        """Every cell with a non-zero log-odds (occupied and free), sorted by index:
        ``index`` (K, 3) int64, ``logodds`` (K,) float64, ``p_occ`` (K,) float64."""
        return known_cells_of(*self._slot.known())

    @_locked
    def known_cell_count(self) -> int:
        """How many cells ``known_cells()`` would return, counted without exporting them."""
        return self._slot.known_count()

    @_locked
    def occupancy(self, points: Any, *, return_known: bool = False) -> Any:
        """Occupancy probability of the cells holding world ``points`` (N, 3), or of one
        point (3,) (then a float, and a bool with ``return_known``).

        Unknown cells (never touched, or outside the grid) read 0.5, the prior; pass
        ``return_known=True`` to also get a boolean mask of the cells that are known.
        """
        return occupancy_of(points, self.resolution, self._slot.in_grid, self.logodds_at, return_known)

    @_locked
    def logodds_at(self, index: Any) -> Any:
        """Log-odds (float64) of cells given by integer index (K, 3), or of one cell (3,)
        (then a float, as ``occupancy`` of one point); unknown cells and cells outside the
        grid read 0."""
        if np.shape(index) == (3,):
            return float(self.logodds_at(np.reshape(index, (1, 3)))[0])
        idx = check_cell_index(index)
        out = np.zeros(len(idx))
        ok = self._slot.in_grid(idx)
        if ok.any():
            out[ok] = self._slot.logodds(idx[ok])
        return out

    @_locked
    def __len__(self) -> int:
        """Number of Gaussians: cells with ``n >= min_points`` that are occupied."""
        return self._slot.occupied_gaussians(self.config.min_points)

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
        """All cell state as numpy arrays (what ``save`` writes; ``cellstate.ARRAYS``)."""
        return self._slot.state()

    def save(self, path: str | Path, *, compact: bool = False) -> Path:
        """Write the map to one versioned file, atomically (see ``ndtom_ti.mapfile``).
        ``compact``: the Gaussians rounded (means to res / 131070, scatter to float32), for
        files about half the size where Gaussians are dense; the default is lossless."""
        refuse_export_suffix(path, f"ndtom_ti.export.export_file(m, {str(path)!r})")
        path = check_target(path)  # before the work: a FIFO, device or folder is refused
        return self.snapshot().save(path, compact=compact)

    @classmethod
    def load(cls, path: str | Path) -> NdtOmMap:
        """Read a map written by ``save``; broken or foreign files raise MapFileError."""
        s = MapSnapshot.load(path)
        try:
            return cls.from_snapshot(s)
        except (KeyError, TypeError, ValueError) as exc:
            raise MapFileError(f"{path} has invalid settings: {exc}") from None

    @_locked
    def snapshot(self) -> MapSnapshot:
        """The map's content now as plain numpy arrays (:class:`~ndtom_ti.snapshot.MapSnapshot`):
        save, export, coarsen and view it without a map slot."""
        # a map has the snapshot's settings by name; its metadata is copied, not shared
        settings = {name: getattr(self, name) for name in SETTINGS}
        settings["metadata"] = copy_metadata(self.metadata)
        return MapSnapshot.adopt(settings, self._slot.state())

    @classmethod
    def from_snapshot(cls, s: MapSnapshot) -> NdtOmMap:
        """A new map holding snapshot ``s`` (its settings, cells and counters), to map on.
        Takes a map slot, as any new map does."""
        import copy

        if not isinstance(s, MapSnapshot):
            raise TypeError(
                f"from_snapshot takes a MapSnapshot (MapSnapshot.load(path) or m.snapshot()), got {type(s).__name__}"
            )
        m = cls(
            s.resolution,
            occupancy=s.occupancy_enabled,
            config=s.config,
            layout=s.layout,
            metadata=copy.deepcopy(s.metadata),
        )  # the map's metadata changes; the snapshot's must not
        try:
            with m._lock:
                m._slot.load_state(s.state())
                m.scans_inserted = s.scans_inserted
                m.points_inserted = s.points_inserted
        except BaseException:
            m.close()  # the slot back at once: the map was never handed out
            raise
        return m

    @_locked
    def coarsen(self, factor: int) -> NdtOmMap:
        """A new map at ``factor * resolution`` (the paper's sec. III-B).

        Every cell's (N, mean, scatter) is merged with the RCU into its parent
        ``floor(index / factor)``: the Gaussian part equals a map built directly at the
        coarse resolution from the same points. The Gaussians of free cells (which the NDT
        miss model keeps for their next hit) are left out. A parent's log-odds is the
        maximum of its known children's (an occupied child makes the parent occupied: safe
        for planning).
        """
        from .multires import check_factor, coarsen_state

        f = check_factor(factor, self.resolution)
        out = NdtOmMap(
            self.resolution * f,
            occupancy=self.occupancy_enabled,
            config=self.config,
            layout=self.layout,
            metadata={**self.metadata, "coarsened_from": self.resolution, "factor": f},
        )
        out._slot.load_state(coarsen_state(self.state(), self.resolution, f, self.config.n_max))
        out.scans_inserted = self.scans_inserted
        out.points_inserted = self.points_inserted
        return out

    @_locked
    def count_erased_near(self, cells: Any) -> None:
        """A tiled map's worker (:mod:`ndtom_ti.cluster`): count other workers' erasures of
        the last scan (``cells``, [N, 3]) in the NDT miss model's erased-neighbour rule."""
        self._update.count_erased_near(np.asarray(cells, np.int32))
