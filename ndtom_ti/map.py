"""NdtOmMap: the NDT Occupancy Map of Saarinen et al. (ICRA 2013), exact and parallel."""

from __future__ import annotations

import functools
import math
import numbers
import time
import weakref
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import runtime
from .cellkeys import count_distinct, lex_order, pack
from .config import MapConfig, check_resolution
from .kernels.layout import NDT_RECORD_BYTES, RECORD_BYTES, Layout
from .kernels.ndt import (
    C_BLOCK_CELLS,
    C_ERASED,
    C_EXPORT,
    C_FREE,
    C_HIT_CELLS,
    C_HIT_PASSED,
    C_NO_RECORD,
    C_RECORDS,
    C_TOUCHED,
    C_VISITS,
    CTR_SIZE,
    HIT_CHUNKS,
    make_kernels,
    total,
)
from .runtime import MapMemoryError
from .snapshot import MapSnapshot
from .warmup import warm_up

_TOUCHED_START = 1 << 20
# Dense scan-local ray counts over the scan's cell box, at most this many cells (2 or 4 B):
# counting there is several times cheaper than in the sparse tree. Past it the block keeps
# the part nearest the sensor, where rays are densest, and the rest counts in the tree.
BLOCK_CELLS = 1 << 25
_SEEN_MAX = 1 << 24  # leaf flags for counting a scan's new leaves exactly
# NDT miss model: variance added on every axis of a Gaussian's covariance before it is
# inverted (kernels.ndt.ndt_floor; eigenvalues l1 <= l2 <= l3): NDT_COV_FLOOR * trace keeps
# flat Gaussians invertible; a line-like one (l2 < NDT_LINE * l3: the points of one scan line
# across the cell, at the ranges where a lidar's rings are a cell or more apart) gets up to
# NDT_LINE_FLOOR * l3 more, so that it stands for the surface the line samples. Without it,
# rays of the other rings never pass within the line's millimetre thickness and the
# Gaussians of objects that left stay (benchmarks/quality.py; docs/quality.md). A line
# spanning the cell (l3 ~ r^2 / 12) then stands for a surface spread evenly over the cell.
NDT_COV_FLOOR = 1e-3
NDT_LINE = 0.5
NDT_LINE_FLOOR = 1.0
# NDT miss model, cells holding fewer than min_points points: their points' mean with this
# standard deviation (metres) added on every axis, so that sparse floor cells are not erased
# by rays grazing far above their points, while a ray passing close to them still clears them.
NDT_SPARSE_SIGMA = 0.05


@dataclass
class ScanReport:
    """What one ``insert_scan`` did."""

    points_in: int = 0
    points_used: int = 0  # endpoints inserted as hits
    free_rays: int = 0  # rays past max_range carved as free space (max_range_mode="free")
    dropped_nonfinite: int = 0
    dropped_range: int = 0  # closer than min_range, or past max_range with mode "drop"
    dropped_outside_grid: int = 0
    cells_hit: int = 0
    cells_passed: int = 0  # distinct cells rays passed without an endpoint: free-space updates
    ray_cell_visits: int = 0
    gaussians_erased: int = 0
    seconds: float = 0.0

    def as_dict(self) -> dict:
        return asdict(self)


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


def cell_box(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest index per axis of (N, 3) cells, as int64. Per column: numpy's
    reduction over axis 0 of an (N, 3) array is ~20x slower."""
    lo = np.array([cells[:, a].min() for a in range(3)], np.int64)
    hi = np.array([cells[:, a].max() for a in range(3)], np.int64)
    return lo, hi


def _as_points(points: Any) -> np.ndarray:
    arr = np.asarray(points)
    if arr.dtype == np.bool_:
        raise TypeError("points must be a real numeric (N, 3) array in metres, got booleans")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise TypeError(f"points must be a real numeric (N, 3) array in metres, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {arr.shape}")
    # float32 and float64 go to the kernels as they are (zero-copy on the CPU).
    return np.ascontiguousarray(arr, dtype=arr.dtype if arr.dtype in (np.float32, np.float64) else np.float64)


_BOTTOM = np.array([0.0, 0.0, 0.0, 1.0])
_EYE3 = np.eye(3)


def as_pose(T: Any, name: str = "T_world_sensor") -> np.ndarray:
    """Validate a rigid 4x4 transform and return it as float64."""
    try:
        M = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be a 4x4 numeric array: {exc}") from None
    if M.shape != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4), got {M.shape}")
    if not np.isfinite(M).all():
        raise ValueError(f"{name} contains NaN or Inf")
    if np.abs(M[3] - _BOTTOM).max() > 1e-9:
        raise ValueError(f"{name} bottom row must be [0, 0, 0, 1], got {M[3].tolist()}")
    R = M[:3, :3]
    err = np.abs(R.T @ R - _EYE3).max()
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    if err > 1e-5 or a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0.0:
        raise ValueError(
            f"{name} is not a rigid transform: its 3x3 block must be a rotation "
            f"(|R^T R - I| = {err:.2e}, det = {np.linalg.det(R):.4f})"
        )
    return M


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
        given = {"p_occupied": p_occupied, "p_empty": p_empty, "logodds_min": logodds_min,
                 "logodds_max": logodds_max, "min_points": min_points, "min_range": min_range,
                 "max_range": max_range, "max_range_mode": max_range_mode, "n_max": n_max}
        options = {**{k: v for k, v in given.items() if v is not None}, **options}
        resolution = check_resolution(resolution)
        if config is not None and options:
            raise TypeError("pass either config=MapConfig(...) or keyword options, not both")
        if options:
            from dataclasses import fields

            unknown = sorted(set(options) - {f.name for f in fields(MapConfig)})
            if unknown:
                raise TypeError(f"unknown map options {unknown}; the options are MapConfig's: "
                                f"{', '.join(f.name for f in fields(MapConfig))}")
        self.config = config if config is not None else MapConfig(**options)
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
            self._k = make_kernels(self._st)
        # Empty the slot for the next map (close(), or when the map is collected); nothing
        # to do at interpreter exit.
        self._release = weakref.finalize(self, _release_slot, self._st, self._slot)
        self._release.atexit = False
        self._ctr = np.zeros(CTR_SIZE, np.int64)
        self._touched = np.empty((_TOUCHED_START, 3), np.int32)
        self._chunks = np.empty(HIT_CHUNKS + 1, np.int32)  # hits_dense's scratch
        # On CUDA a numpy block is copied to the device and back at every launch: keep it
        # to the 1M cells nearest the sensor there.
        self.block_cells = BLOCK_CELLS if self.arch == "cpu" else 1 << 20
        self._block_density = 0.0  # ray visits per cell of the last scan's dense block
        # A ray passes a cell once: u16 ray counts hold any scan of up to 65534 rays
        # (65535 marks a cell holding a Gaussian for the NDT miss model).
        self._u16_rays = 65534
        self._group_hits = True  # endpoints grouped in the block where it can (see _insert)
        self._glo = np.array(self.layout.lo, np.int64)
        self._ghi = np.array(self.layout.hi, np.int64)
        # Gaussian records (dense; numpy, outside Taichi's pool), grown when new cells find
        # none (see _insert); those of erased Gaussians wait on a free stack for new ones.
        self._nrec = 0
        self._nfree = 0
        self._alloc_records(1024)
        self._warm = False  # warmup.warm_up done for this map (at its first scan)
        c = self.config
        self._ndt_prm = np.array([c.eta, 0.5 / c.sigma_s**2, NDT_COV_FLOOR, NDT_LINE, NDT_LINE_FLOOR, c.min_points,
                                  NDT_SPARSE_SIGMA**2])  # fmt: skip
        # Points a cell needs for the NDT miss model (1: every cell with points, those with
        # fewer than min_points under the prior above); 0: the paper's model (kernel switch).
        self._ndt_minp = 1 if c.ndt_misses else 0

    # ------------------------------------------------------------------ properties

    @property
    def arch(self) -> str:
        return runtime.current_arch() or "cpu"

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

    def _prepare(self, points: Any, T_world_sensor: Any):
        """Validate a scan and turn it into world endpoints and their cells (hits first,
        then free rays), reserving the pool memory the update may need."""
        pts = _as_points(points)
        T = as_pose(T_world_sensor)
        cfg = self.config
        res = self.resolution
        rep = ScanReport(points_in=len(pts))

        origin = np.ascontiguousarray(T[:3, 3])
        ocell = np.floor(origin / res).astype(np.int64)
        if ((ocell < self._glo) | (ocell >= self._ghi)).any():
            lo, hi = self.grid_extent
            raise ValueError(
                f"sensor origin {origin.tolist()} is outside the map grid "
                f"[{lo.tolist()}, {hi.tolist()}] m; use a coarser resolution or a larger Layout"
            )

        n = len(pts)
        world = np.empty((n, 3), np.float64)
        cells = np.empty((n, 3), np.int32)
        status = np.empty(n, np.int8)
        free_at = cfg.max_range if cfg.max_range_mode == "free" else 0.0
        r2 = np.array([cfg.min_range**2, cfg.max_range**2, free_at])
        if n:
            self._k.prepare(pts, n, np.ascontiguousarray(T[:3, :3]).reshape(-1), origin, res, r2, world, cells, status)
        cnt = np.bincount(status, minlength=5) if n else np.zeros(5, np.int64)
        n_hit, n_free = int(cnt[0]), int(cnt[1])
        if n_hit + n_free < n:
            hit = status == 0
            if n_free:
                free = status == 1
                world = np.concatenate([world[hit], world[free]])
                cells = np.concatenate([cells[hit], cells[free]])
            else:
                world, cells = world[hit], cells[hit]
        elif n_free:  # nothing dropped, but hits must come first
            order = np.argsort(status, kind="stable")
            world, cells = world[order], cells[order]
        rep.dropped_nonfinite, rep.dropped_range, rep.dropped_outside_grid = int(cnt[2]), int(cnt[3]), int(cnt[4])
        rep.points_used = n_hit
        rep.free_rays = n_free
        box = cell_box(cells) if len(cells) else None

        # Memory: the whole scan in one pass when its bound fits; otherwise the hits must
        # fit and the rays are traced in batches, each checked against exact counts.
        limit = runtime.pool_limit()
        bound = self._scan_bound(cells, n_hit, ocell, box=box)
        one_pass = self._st.pool_bytes(bound, all_types=True) <= limit
        self._hit_nodes = None
        if not one_pass:
            # The index tree takes only hit cells: count its new nodes exactly and retry.
            hit_nodes = self._new_hit_nodes(cells[:n_hit])
            bound[2:] = hit_nodes[2:]
            one_pass = self._st.pool_bytes(bound, all_types=True) <= limit
            if not one_pass:
                self._reserve(hit_nodes)
                # What the hits write after the batched rays: each batch must leave room for it.
                self._hit_nodes = (hit_nodes, cells[:n_hit])
        return world, cells, n_hit, origin, ocell, rep, box, one_pass

    def _new_hit_nodes(self, hit_cells: np.ndarray) -> np.ndarray:
        """Exact number of nodes per type that writing these hit cells allocates."""
        if len(hit_cells) == 0:
            return np.zeros(4, np.int64)
        L = self.layout
        box = cell_box(hit_cells)
        lo, hi = (b // L.leaf for b in box)
        rlo, rhi = ((b - self._glo) // L.region for b in box)
        rseen = np.zeros(tuple(int(x) for x in rhi - rlo + 1), np.int32)  # at most the grid's regions
        shape = tuple(int(x) for x in hi - lo + 1)
        if math.prod(shape) <= _SEEN_MAX:
            cells, seen, dedup = hit_cells, np.zeros(shape, np.int32), 1
        else:  # a sparse, wide scan: one cell per distinct leaf
            key = np.asarray(np.ravel_multi_index((hit_cells // L.leaf - lo).T, shape))
            order = np.argsort(key)  # np.unique is ~100x slower than a sort (numpy 2.4)
            sk = key[order]
            first = order[np.concatenate(([True], sk[1:] != sk[:-1]))]
            cells, seen, dedup = np.ascontiguousarray(hit_cells[first]), np.zeros((1, 1, 1), np.int32), 0
        new = np.zeros(4, np.int64)
        st = self._st
        self._k.count_new_nodes(self._slot, cells, len(cells), lo.astype(np.int32), seen, dedup,
                                rlo.astype(np.int32), rseen, st.occ_regions, st.gidx_regions, new)  # fmt: skip
        return new[[2, 0, 3, 1]]

    @_locked
    def traverse_only(self, points: Any, T_world_sensor: Any) -> ScanReport:
        """Benchmark floor: the scan's rays traversed through the same sparse layout with
        one integer atomic per visited cell and nothing else. It leaves ray counters set:
        use a map made for this purpose only."""
        t0 = time.perf_counter()
        world, cells, n_hit, origin, ocell, rep, box, one_pass = self._prepare(points, T_world_sensor)
        self._ctr[:] = 0
        if len(world):
            self._trace("floor", world, cells, n_hit, origin, ocell, box, one_pass)
        rep.ray_cell_visits = total(self._ctr, C_VISITS)
        rep.seconds = time.perf_counter() - t0
        return rep

    def _trace(self, mode: str, world, cells, n_hit, origin, ocell, box, one_pass: bool):
        """Run the ray kernel of ``mode`` ("full" or "floor") over all rays (``box``: their
        cells' bounding box), in batches when memory is tight. Returns the dense block
        they counted in (block, row flags, base, whether the rays set the flags, whether it
        holds every cell of the scan), or None."""
        st, slot = self._st, self._slot
        dense = one_pass and mode == "full"  # the floor counts in the tree only
        # 16-bit counts on the CPU only: NVIDIA GPUs have no 16-bit atomics.
        dtype = np.uint16 if self.arch == "cpu" and len(world) <= self._u16_rays else np.int32
        kb = self._k.block[np.dtype(dtype)]
        ndt = mode == "full" and self.config.ndt_misses
        pre = "ndt_" if ndt else ""
        kernel = getattr(kb, pre + "rays") if mode == "full" else kb.rays_floor
        block, bflag, base = self._block_for(box if dense else None, ocell, dtype)
        args = (origin, ocell.astype(np.int32), self.resolution, self._touched, len(self._touched), self._ctr,
                st.occ_regions, st.leaf_count, block, bflag, base, block.reshape(-1), bflag.reshape(-1))  # fmt: skip
        # The Gaussians the rays test are those of the scan's start: merge runs after them.
        recs = (self._rec_n, self._rec_icov, self._rec_miss, self._ndt_prm, self._ndt_minp)
        if ndt and block.size:
            kb.mark_gaussians(self._nrec, self._rec_n, self._rec_cell, self._ndt_minp, block, bflag, base)
        n = len(world)
        if one_pass:
            lo, hi = np.minimum(box[0], ocell), np.maximum(box[1], ocell)
            flagged, whole = True, False
            if dense and (base <= lo).all() and (base + np.array(block.shape) > hi).all():
                whole = True
                # The block covers every cell of the scan. Row flags pay off only where
                # rays leave most rows empty: the last scan made few visits per block cell
                # (measured on the hall: flags lose by 6% at 0.37 visits/cell, 15% at 1.15).
                flagged = self._block_density < 0.2
                kernel = getattr(kb, pre + ("rays_dense" if flagged else "rays_dense_unflagged"))
            kernel(slot, world, cells, n_hit, n, *args, int(dense), *recs)
            st.note_usage()
            if not (dense and block.size):
                return None
            self._block_density = total(self._ctr, C_VISITS) / block.size  # the only rays kernel of the update
            return block, bflag, base, flagged, whole
        # Hits first, then free rays, each by azimuth: batches stay spatially compact.
        d = world - origin
        az = np.arctan2(d[:, 1], d[:, 0])
        order = np.concatenate([np.argsort(az[:n_hit]), n_hit + np.argsort(az[n_hit:])])
        ws, cs = world[order], cells[order]
        limit = runtime.pool_limit()
        pending = [(0, n)]
        # Nodes the hits write after the rays (merge): an upper bound, counted again exactly
        # when a batch does not fit, as the rays may have made some of them already.
        hits, hit_cells = getattr(self, "_hit_nodes", None) or (np.zeros(4, np.int64), cells[:0])
        fresh = True
        while pending:
            a, b = pending.pop()
            bound = self._scan_bound(cs[a:b], 0, ocell, tight=True, rays=True)
            fits = st.pool_bytes(bound + hits, all_types=True) <= limit
            if not fits and not fresh:
                hits, fresh = self._new_hit_nodes(hit_cells), True
                fits = st.pool_bytes(bound + hits, all_types=True) <= limit
            if fits:
                # No dense block here: its cells would reach the tree outside this batch's bound.
                kernel(slot, np.ascontiguousarray(ws[a:b]), np.ascontiguousarray(cs[a:b]), max(0, min(n_hit - a, b - a)), b - a, *args, 0, *recs)
                st.note_usage()
                fresh = len(hit_cells) == 0
            elif b - a > 1:
                mid = (a + b) // 2
                pending += [(mid, b), (a, mid)]
            else:
                nt = int(self._ctr[C_TOUCHED])
                if nt <= len(self._touched):
                    self._k.reset_rays(slot, self._touched, nt)
                else:
                    self._k.reset_rays_all(slot)
                need = st.pool_bytes(bound + hits, all_types=True)
                # The leaves these rays made hold nothing now: give them back for later scans.
                from .kernels.release import release_empty_leaves

                release_empty_leaves(st, slot)
                self._refuse(need)  # nothing of this scan is kept
        return None

    def _block_for(self, box, ocell: np.ndarray, dtype: type = np.int32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The dense ray-count block (of ``dtype``) of a scan: the leaf-aligned box of its
        cells and the sensor, trimmed on its far sides to ``block_cells`` cells (empty
        with no ``box``)."""
        leaf = self.layout.leaf
        if box is None or self.block_cells < leaf**3:
            return np.zeros((0, 0, 0), dtype), np.zeros((0, 0, 0), np.int8), np.zeros(3, np.int32)
        oleaf = ocell // leaf
        lo = np.minimum(box[0] // leaf, oleaf)  # in leaves
        hi = np.maximum(box[1] // leaf, oleaf) + 1
        while int(np.prod(hi - lo)) * leaf**3 > self.block_cells:
            a = int(np.argmax(hi - lo))
            cut = max(1, int(hi[a] - lo[a]) // 8)
            if hi[a] - oleaf[a] - 1 >= oleaf[a] - lo[a]:  # trim the side farther from the sensor
                hi[a] = max(hi[a] - cut, oleaf[a] + 1)
            else:
                lo[a] = min(lo[a] + cut, oleaf[a])
        shape = tuple(int(x) * leaf for x in hi - lo)
        n = shape[0] * shape[1] * shape[2]
        st = self._st
        words = -(-n * np.dtype(dtype).itemsize // 4)  # the buffer is int32, viewed as dtype
        if words > len(st.block_buf):
            st.block_buf = np.zeros(max(words, min(len(st.block_buf) * 5 // 4, BLOCK_CELLS)), np.int32)
        if n // leaf > len(st.bflag_buf):
            st.bflag_buf = np.zeros(max(n // leaf, min(len(st.bflag_buf) * 5 // 4, BLOCK_CELLS // leaf)), np.int8)
        block = st.block_buf.view(dtype)[:n].reshape(shape)
        bflag = st.bflag_buf[: n // leaf].reshape(shape[0], shape[1], shape[2] // leaf)
        return block, bflag, (lo * leaf).astype(np.int32)

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
            warm = 0.0
            if not self._warm:
                self._warm = True
                t0 = time.perf_counter()
                warm_up(self)
                warm = time.perf_counter() - t0
            rep = self._insert_guarded(points, T_world_sensor)
            rep.seconds += warm  # the first scan's time includes compiling its kernels
            return rep

    def _insert_guarded(self, points: Any, T_world_sensor: Any) -> ScanReport:
        """``_insert``, leaving the shared scratch clean when it raises (the caller holds
        the storage's lock)."""
        try:
            return self._insert(points, T_world_sensor)
        except BaseException:
            # Interrupted between kernels (Ctrl-C) or refused: keep the shared block and
            # the NDT miss sums zero.
            self._st.block_buf[:] = 0
            self._st.bflag_buf[:] = 0
            self._rec_miss[:] = 0
            raise

    def _insert(self, points: Any, T_world_sensor: Any) -> ScanReport:
        t0 = time.perf_counter()
        world, cells, n_hit, origin, ocell, rep, box, one_pass = self._prepare(points, T_world_sensor)
        n = len(world)
        cfg, res = self.config, self.resolution
        k, ctr, fs, slot = self._k, self._ctr, self._st, self._slot
        ctr[:] = 0
        ctr[C_FREE] = self._nfree
        lmin, lmax = float(cfg.logodds_min), float(cfg.logodds_max)
        dense = None
        if self.occupancy_enabled and n:
            dense = self._trace("full", world, cells, n_hit, origin, ocell, box, one_pass)  # may refuse
        block, bflag, base, flagged, whole = dense if dense is not None else (*self._block_for(None, ocell), True, False)
        kb = k.block[block.dtype]
        hitlist = np.empty((max(n_hit, 1), 3), np.int32)
        nh = 0
        # Points per hit cell counted in the block (no tree walks) when it holds them all; on
        # the CPU only (its prefix sum runs on one thread).
        dense_hits = whole and self.arch == "cpu" and self._group_hits
        g = max(n_hit, 1) if dense_hits else 1
        hcnt, off, order = np.empty(g, np.int32), np.empty(g, np.int32), np.empty(g, np.int32)
        if n_hit:
            if dense_hits:
                acc = np.empty((1, 9), np.float64)
                kb.hits_dense(cells, n_hit, hitlist, hcnt, off, np.empty(n_hit, np.int32), order, ctr, block, base, self._chunks)
                nh = int(ctr[C_HIT_CELLS])
            else:
                k.hits_count(slot, cells, n_hit, hitlist, ctr, fs.gidx_regions, fs.leaf_count)
                nh = int(ctr[C_HIT_CELLS])
                acc = np.zeros((nh, 9), np.float64)
                k.hits_sum(slot, world, cells, n_hit, acc, res)
            left, todo = np.empty(nh, np.int32), nh
            while True:
                cap = len(self._rec_n)
                ctr[C_RECORDS], ctr[C_NO_RECORD] = self._nrec, 0
                kb.merge(slot, hitlist, acc, todo, int(cfg.n_max), self._rec_n, self._rec_cell, self._rec_mean, self._rec_scat,
                         ctr, cfg.l_hit, lmin, lmax, fs.occ_regions, fs.leaf_count, block, base, int(dense is not None),
                         hcnt, fs.gidx_regions, int(dense_hits), world, order, off, res, self._rec_free, left,
                         self._rec_miss, self._rec_icov, self._ndt_prm, self._ndt_minp)  # fmt: skip
                # At once, like the record count: an update cut short later must not hand
                # out the records merge took from the free stack again.
                self._nrec, self._nfree = min(int(ctr[C_RECORDS]), cap), int(ctr[C_FREE])
                todo = int(ctr[C_NO_RECORD])
                if not todo:
                    break
                # Records grow only when new cells found none, by an eighth (or a scan's
                # hit cells, fewer copies while a small map explores): the records held
                # follow the Gaussians, as the memory should follow the place.
                self._alloc_records(cap + max(cap // 8, nh))
                s = np.sort(left[:todo])
                hitlist = hitlist[s]
                if dense_hits:
                    hcnt, off = hcnt[s], off[s]
                else:
                    acc = acc[s]
        if dense is not None:
            if flagged:
                kb.block_apply(slot, block, bflag, base, cfg.l_free, lmin, lmax, self._rec_n, ctr, fs.occ_regions, fs.leaf_count,
                               self._rec_free, self._rec_miss)  # fmt: skip
            else:
                kb.block_apply_all(slot, block.reshape(-1).view(np.uint64), np.array(block.shape, np.int32), base, cfg.l_free, lmin, lmax,
                                  self._rec_n, ctr, fs.occ_regions, fs.leaf_count, self._rec_free, self._rec_miss)  # fmt: skip
        if self.occupancy_enabled and n:
            nt = int(ctr[C_TOUCHED])
            if 0 < nt <= len(self._touched):
                k.apply_free(slot, self._touched, nt, cfg.l_free, lmin, lmax, self._rec_n, ctr, self._rec_free, self._rec_miss,
                             self._ndt_minp)  # fmt: skip
            elif nt:
                k.apply_free_all(slot, cfg.l_free, lmin, lmax, self._rec_n, ctr, self._rec_free, self._rec_miss,
                                 self._ndt_minp)  # fmt: skip
                self._touched = np.empty((2 * nt, 3), np.int32)
            rep.cells_passed = nt - int(ctr[C_HIT_PASSED]) + total(ctr, C_BLOCK_CELLS)
        fs.note_usage()
        rep.cells_hit = nh
        rep.ray_cell_visits = total(ctr, C_VISITS)
        rep.gaussians_erased = int(ctr[C_ERASED])
        self._nfree = int(ctr[C_FREE])
        self.scans_inserted += 1
        self.points_inserted += n_hit
        rep.seconds = time.perf_counter() - t0
        return rep

    # ------------------------------------------------------------------ memory

    def _alloc_records(self, capacity: int) -> None:
        old = getattr(self, "_rec_n", None)
        n_ = np.zeros(capacity, np.int32)
        cell = np.zeros((capacity, 3), np.int32)
        mean = np.zeros((capacity, 3), np.float64)
        scat = np.zeros((capacity, 6), np.float64)
        free = np.zeros(capacity, np.int32)
        # NDT miss model: the scan's miss sums (zero between updates), the inverse covariance
        # and mean rays read; a placeholder row with the paper's model.
        ndt = self.config.ndt_misses
        miss = np.zeros(capacity if ndt else 1, np.int64)
        icov = np.zeros((capacity if ndt else 1, 9), np.float64)
        if old is not None:
            k = self._nrec
            n_[:k], cell[:k], mean[:k], scat[:k] = self._rec_n[:k], self._rec_cell[:k], self._rec_mean[:k], self._rec_scat[:k]
            if ndt:
                miss[:k] = self._rec_miss[:k]  # grown mid-update: the rays' sums are not applied yet
                icov[:k] = self._rec_icov[:k]
            free[: self._nfree] = self._rec_free[: self._nfree]
        self._rec_n, self._rec_cell, self._rec_mean, self._rec_scat, self._rec_free = n_, cell, mean, scat, free
        self._rec_miss, self._rec_icov = miss, icov

    def _scan_bound(
        self,
        cells: np.ndarray,
        n_hit: int,
        ocell: np.ndarray,
        tight: bool = False,
        rays: bool | None = None,
        box: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """Upper bound of the nodes a scan can add, per node type (occupancy regions,
        occupancy leaves, index regions, index leaves): the nodes of the scan's bounding
        box (``box`` of all ``cells`` when known), or with ``tight`` also at most one node
        per node boundary each ray crosses."""
        out = np.zeros(4, np.int64)
        if len(cells) == 0:
            return out
        L = self.layout
        rays = self.occupancy_enabled if rays is None else rays

        def nodes(size: int, c: np.ndarray, box: tuple, with_rays: bool) -> int:
            lo, hi = box
            n_box = int(np.prod(hi // size - lo // size + 1))  # floor division is monotone
            if not tight:
                return n_box
            q = c.astype(np.int64) // size
            per_ray = int((np.abs(q - ocell // size).sum(axis=1) + 1).sum()) if with_rays else len(c)
            return min(n_box, per_ray)

        def box_of(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            if box is not None and len(c) == len(cells):
                return box
            return cell_box(c)

        occ = cells if rays else cells[:n_hit]
        if len(occ):
            lo, hi = box_of(occ)
            if rays:
                lo, hi = np.minimum(lo, ocell), np.maximum(hi, ocell)
            out[0], out[1] = nodes(L.region, occ, (lo, hi), rays), nodes(L.leaf, occ, (lo, hi), rays)
        if n_hit:
            h = cells[:n_hit]
            hbox = box_of(h)
            out[2], out[3] = nodes(L.region, h, hbox, False), nodes(L.leaf, h, hbox, False)
        return out

    def _reserve(self, extra_nodes: np.ndarray) -> None:
        """Refuse, before any kernel runs, work that could take Taichi's memory pool past
        the budget (runtime.pool_limit)."""
        need = self._st.pool_bytes(extra_nodes, all_types=True)
        if need > runtime.pool_limit():
            self._refuse(need)

    def _refuse(self, need: int) -> None:
        """Raise the MapMemoryError of an update that needs ``need`` bytes of pool."""
        limit = runtime.pool_limit()
        raise MapMemoryError(
            f"this update could take Taichi's memory pool to {need / 2**20:.0f} MiB, past the "
            f"{limit / 2**20:.0f} MiB budget (this map holds {self._st.slot_bytes(self._slot) / 2**20:.0f} MiB "
            f"of nodes; all maps {self._st.pool_bytes() / 2**20:.0f} MiB of pool). Use a coarser "
            f"resolution or a smaller max_range, delete other maps, give a larger budget "
            f"(ndtom_ti.init(memory_limit_GB=...) before the first map), or use CUDA. The map is unchanged."
        )

    def _record_bytes(self) -> int:
        return len(self._rec_n) * (RECORD_BYTES + (NDT_RECORD_BYTES if self.config.ndt_misses else 0))

    @_locked
    def memory_bytes(self) -> int:
        """Bytes this map holds: nodes of its sparse trees (counted exactly by the
        kernels) plus its Gaussian records."""
        return self._st.slot_bytes(self._slot) + self._record_bytes()

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
            "record_bytes": self._record_bytes(),
            "records_in_use": self._nrec - self._nfree,
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
        k = self._nrec
        keep = self._rec_n[:k] > 0
        idx = self._rec_cell[:k][keep]
        order = lex_order(idx)
        idx = np.ascontiguousarray(idx[order])
        lo = np.zeros(len(idx), np.float32)
        if len(idx):
            self._k.query(self._slot, idx, len(idx), lo)
        return {
            "index": idx,
            "n": self._rec_n[:k][keep][order],
            "mean_rel": self._rec_mean[:k][keep][order],
            "scatter": self._rec_scat[:k][keep][order],
            "logodds": lo,
        }

    @_locked
    def gaussians(self, min_points: int | None = None, min_probability: float = 0.5) -> dict:
        """The map's Gaussians, sorted by cell index.

        Returns a dict of numpy arrays: ``index`` (K, 3) int64 cell indices, ``mean``
        (K, 3) float64 world frame, ``cov`` (K, 3, 3) float64 sample covariance (divided
        by N - 1), ``n`` (K,) int64, ``p_occ`` (K,) float64 occupancy probability,
        ``logodds`` (K,) float64. Cells need ``n >= min_points`` (default: the config's
        min_points) and ``p_occ > min_probability``; ``min_probability=0`` also returns
        Gaussians of cells not (yet) occupied.
        """
        if min_points is None:
            min_points = self.config.min_points
        if isinstance(min_points, bool) or not isinstance(min_points, numbers.Integral) or min_points < 0:
            raise ValueError(f"min_points must be an integer >= 0, got {min_points!r}")
        if isinstance(min_probability, bool) or not isinstance(min_probability, numbers.Real) or not (
            0.0 <= min_probability <= 1.0  # NaN fails: it would have kept every Gaussian
        ):
            raise ValueError(f"min_probability must be a number in [0, 1], got {min_probability!r}")
        raw = self._raw_gaussians()
        keep = raw["n"] >= max(int(min_points), 1)
        lo = raw["logodds"].astype(np.float64)
        p = 1.0 - 1.0 / (1.0 + np.exp(lo))
        if min_probability > 0.0:
            keep &= p > min_probability
        idx = raw["index"][keep].astype(np.int64)
        n = raw["n"][keep].astype(np.int64)
        s = raw["scatter"][keep]
        cov = np.empty((len(n), 3, 3))
        for (a, b), col in zip(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)), range(6)):
            cov[:, a, b] = s[:, col]
            cov[:, b, a] = s[:, col]
        denom = np.maximum(n - 1, 1).astype(np.float64)
        cov /= denom[:, None, None]
        cov[n < 2] = 0.0
        return {
            "index": idx,
            "mean": self.cell_center(idx) + raw["mean_rel"][keep],
            "cov": cov,
            "n": n,
            "p_occ": p[keep],
            "logodds": lo[keep],
        }

    @_locked
    def known_cells(self) -> dict:
        """Every cell with a non-zero log-odds (occupied and free), sorted by index:
        ``index`` (K, 3) int64, ``logodds`` (K,) float64, ``p_occ`` (K,) float64."""
        ctr = self._ctr
        ctr[:] = 0
        self._k.count_known(self._slot, ctr)
        K = int(ctr[C_EXPORT])
        idx = np.empty((K, 3), np.int32)
        val = np.empty(K, np.float32)
        if K:
            ctr[:] = 0
            self._k.export_known(self._slot, idx, val, ctr)
        order = lex_order(idx)
        lo = val[order].astype(np.float64)
        return {"index": idx[order].astype(np.int64), "logodds": lo, "p_occ": 1.0 - 1.0 / (1.0 + np.exp(lo))}

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
            with np.errstate(over="ignore"):  # exp of a large log-odds: p = 1
                out[ok] = 1.0 - 1.0 / (1.0 + np.exp(lo))
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
            self._k.query(self._slot, np.ascontiguousarray(idx[ok], np.int32), len(lo), lo)
            out[ok] = lo
        return out

    @_locked
    def __len__(self) -> int:
        """Number of Gaussians: cells with ``n >= min_points`` that are occupied."""
        return int(np.count_nonzero(self._occupied_gaussian_mask()))

    def _occupied_gaussian_mask(self) -> np.ndarray:
        """Of the records with at least min_points points, which cells are occupied."""
        k = self._nrec
        cand = np.flatnonzero(self._rec_n[:k] >= self.config.min_points)
        if len(cand) == 0:
            return np.zeros(0, bool)
        lo = np.zeros(len(cand), np.float32)
        self._k.query(self._slot, np.ascontiguousarray(self._rec_cell[cand]), len(cand), lo)
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
        g = self._raw_gaussians()
        k = self.known_cells()
        return {
            "occ_index": k["index"].astype(np.int32),
            "occ_logodds": k["logodds"].astype(np.float32),
            "g_index": g["index"],
            "g_n": g["n"],
            "g_mean_rel": g["mean_rel"],
            "g_scatter": g["scatter"],
        }

    def _load_state(self, st: dict) -> None:
        """Write cell state into this (empty) map."""
        occ_idx = np.ascontiguousarray(st["occ_index"], np.int32)
        g_idx = np.ascontiguousarray(st["g_index"], np.int32)
        for name, idx in (("occupancy", occ_idx), ("Gaussian", g_idx)):
            if len(idx) and (((idx < self._glo) | (idx >= self._ghi)).any()):
                raise ValueError(f"{name} cell indices lie outside this map's grid {self.layout.cells}")
        self._reserve(self._load_bound(occ_idx, g_idx))
        fs = self._st
        if len(occ_idx):
            occ_lo = np.ascontiguousarray(st["occ_logodds"], np.float32)
            self._k.load_known(self._slot, occ_idx, occ_lo, len(occ_idx), fs.occ_regions, fs.leaf_count)
        if len(g_idx):
            self._alloc_records(max(1024, len(g_idx)))
            self._rec_n[: len(g_idx)] = st["g_n"]
            self._rec_cell[: len(g_idx)] = g_idx
            self._rec_mean[: len(g_idx)] = st["g_mean_rel"]
            self._rec_scat[: len(g_idx)] = st["g_scatter"]
            self._nrec = len(g_idx)
            if self.config.ndt_misses:
                self._k.ndt_refresh(self._nrec, self._rec_n, self._rec_scat, self._rec_mean, self._ndt_prm, self._rec_icov)
            self._k.load_slots(self._slot, g_idx, len(g_idx), fs.gidx_regions, fs.occ_regions, fs.leaf_count)
        fs.note_usage()

    def _load_bound(self, occ_idx: np.ndarray, g_idx: np.ndarray) -> np.ndarray:
        L = self.layout

        def distinct(idx: np.ndarray, size: int) -> int:
            return count_distinct(pack(idx // size)[0]) if len(idx) else 0

        occ = np.concatenate([occ_idx, g_idx])  # a Gaussian's cell holds its flag in the occupancy tree
        return np.array(
            [distinct(occ, L.region), distinct(occ, L.leaf), distinct(g_idx, L.region), distinct(g_idx, L.leaf)],
            np.int64,
        )

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

        m = cls(s.resolution, occupancy=s.occupancy_enabled, config=s.config, layout=s.layout,
                metadata=copy.deepcopy(s.metadata))  # the map's metadata changes; the snapshot's must not
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
