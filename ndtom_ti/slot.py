"""MapSlot: one map's place in the process's Taichi storage, and everything it holds.

A map's cells live in a slot of the sparse trees shared by the maps of a process; its
Gaussians in dense numpy records beside them. The slot's owner is this class: the slot,
the records, the memory budget, the kernels that read and write them, the cell state out
as numpy arrays and in from them, and the finalizer that empties the slot when it is
closed or collected. :class:`~ndtom_ti.NdtOmMap` (API, lock, config, queries) and
:class:`~ndtom_ti.scan_update.ScanUpdate` (the updates and the first scan's compiles)
use it through its public methods.
"""

from __future__ import annotations

import weakref

import numpy as np

from . import runtime
from .budget import MemoryBudget
from .cellkeys import lex_order
from .kernels.families import kernel_set
from .kernels.io import io_kernels
from .kernels.ndt import C_EXPORT, CTR_SIZE
from .records import GaussianRecords

_dead_slots: list = []  # (storage, slot) of maps collected while another thread held the lock


def _release_slot(st, slot: int) -> None:
    """Empty a dead map's slot (a kernel: never while another thread's kernels run). The
    garbage collector calls this in any thread, maybe inside another lock's holder: it
    never waits; a slot it cannot empty now is emptied by the next map call. Nor does it
    run where this thread holds the lock: the collector may have stopped a map call in
    the middle, even inside Taichi's compile of a kernel, which a kernel of ours would
    re-enter (Python 3.11's parser state then fails every later compile)."""
    if st.lock._is_owned() or not st.lock.acquire(blocking=False):
        _dead_slots.append((st, slot))
        return
    try:
        runtime.release_slot(st, slot)
        release_dead()
    finally:
        st.lock.release()


def release_dead() -> None:
    """Empty the slots of maps collected while the storage's lock was held (the caller
    holds it now)."""
    while _dead_slots:
        st, slot = _dead_slots.pop()
        runtime.release_slot(st, slot)


class MapSlot:
    """A slot of the storage of ``layout`` with its Gaussian records (``ndt``: with the NDT
    miss model's, ``ndt_params`` and ``ndt_min_points`` its kernel parameters) and its
    memory budget (``occupancy``: the updates trace rays).

    ``storage`` and ``index``: the storage and the slot's number in it; ``lock``: the
    storage's lock (re-entrant), held by every call that runs kernels; ``kernels``: the
    update kernels (kernels/families.py); ``records``, ``budget``. The slot is emptied by
    :meth:`close` or when this object is collected; every other method needs it open and
    the lock held.
    """

    def __init__(self, layout, *, ndt: bool, ndt_params: np.ndarray, ndt_min_points: int, occupancy: bool):
        with runtime.storage(layout).lock:
            release_dead()  # slots of maps collected while the lock was held: free them first
        self.storage, self.index = runtime.acquire_slot(layout)
        self.layout = layout
        self.lock = self.storage.lock
        with self.lock:
            self.kernels = kernel_set(self.storage)
            self._io = io_kernels(self.storage)  # queries, export, load
            self.storage.set_owner(self.index, layout.owner)  # a tiled map's worker: its cells
        # Nothing to do at interpreter exit.
        self._release = weakref.finalize(self, _release_slot, self.storage, self.index)
        self._release.atexit = False
        self._ctr = np.zeros(CTR_SIZE, np.int64)  # export's counters
        self.glo = np.array(layout.lo, np.int64)
        self.ghi = np.array(layout.hi, np.int64)
        self.records = GaussianRecords(ndt, ndt_params, ndt_min_points, grid=(self.glo, self.ghi))
        self.budget = MemoryBudget(self.storage, self.index, self.kernels, occupancy)

    # ------------------------------------------------------------------ lifetime

    def close(self) -> None:
        """Give the slot back now (runs once: the collector will not release it again)."""
        with self.lock:
            if self._release.detach() is not None:  # not closed before
                runtime.release_slot(self.storage, self.index)
                release_dead()

    @property
    def closed(self) -> bool:
        return not self._release.alive

    def check_open(self) -> None:
        if not self._release.alive:
            raise ValueError("this map is closed (NdtOmMap.close()); make a new map or load one")
        runtime.check_taichi()

    # ------------------------------------------------------------------ memory

    def node_bytes(self) -> int:
        """Bytes of the slot's nodes in the sparse trees (counted exactly by the kernels)."""
        return self.storage.slot_bytes(self.index)

    def node_counts(self) -> np.ndarray:
        """Nodes per type: occupancy regions, occupancy leaves, index regions, index leaves."""
        return self.storage.nodes(self.index)

    # ------------------------------------------------------------------ reads

    def in_grid(self, idx: np.ndarray) -> np.ndarray:
        """Which cells of ``idx`` (K, 3) lie inside the grid."""
        return np.asarray(((idx >= self.glo) & (idx < self.ghi)).all(axis=1))

    def logodds(self, idx: np.ndarray) -> np.ndarray:
        """float32 log-odds of cells ``idx`` (K, 3) inside the grid (0: unknown)."""
        out = np.zeros(len(idx), np.float32)
        if len(idx):
            self._io.query(self.index, np.ascontiguousarray(idx, np.int32), len(idx), out)
        return out

    def known_count(self) -> int:
        """Cells with a non-zero log-odds, counted in the tree (nothing exported or sorted)."""
        ctr = self._ctr
        ctr[:] = 0
        self._io.count_known(self.index, ctr)
        return int(ctr[C_EXPORT])

    def known(self) -> tuple[np.ndarray, np.ndarray]:
        """Every cell with a non-zero log-odds, sorted by index: (K, 3) i32 and (K,) f32."""
        K = self.known_count()
        ctr = self._ctr
        idx = np.empty((K, 3), np.int32)
        val = np.empty(K, np.float32)
        if K:
            ctr[:] = 0
            self._io.export_known(self.index, idx, val, ctr)
        order = lex_order(idx)
        return idx[order], val[order]

    def gaussian_records(self) -> dict:
        """Every record that holds points, sorted by cell index, with its cell's f32 log-odds
        (``GaussianRecords.holding_points`` and ``logodds``)."""
        raw = self.records.holding_points()
        return {**raw, "logodds": self.logodds(raw["index"])}

    def occupied_gaussians(self, min_points: int) -> int:
        """Records of at least ``min_points`` points whose cells are occupied."""
        cells = self.records.with_points(min_points)
        if len(cells) == 0:
            return 0
        return int(np.count_nonzero(self.logodds(cells) > 0.0))

    # ------------------------------------------------------------------ state in/out

    def state(self) -> dict:
        """All cell state as numpy arrays (what a map file stores; see snapshot.ARRAYS)."""
        g = self.gaussian_records()
        occ_index, occ_logodds = self.known()
        return {
            "occ_index": occ_index,
            "occ_logodds": occ_logodds,
            "g_index": g["index"],
            "g_n": g["n"],
            "g_mean_rel": g["mean_rel"],
            "g_scatter": g["scatter"],
            "g_erased_near": g["erased_near"],
            "g_ndt_state": g["ndt_state"],
        }

    def load_state(self, st: dict) -> None:
        """Write cell state into this empty slot: log-odds, then the Gaussian records and
        their cells' record numbers, refused before any write when a cell lies outside the
        grid or the memory budget has no room for it."""
        occ_idx = np.ascontiguousarray(st["occ_index"], np.int32)
        g_idx = np.ascontiguousarray(st["g_index"], np.int32)
        for name, idx in (("occupancy", occ_idx), ("Gaussian", g_idx)):
            if len(idx) and not self.in_grid(idx).all():
                raise ValueError(f"{name} cell indices lie outside this map's grid {self.layout.cells}")
        io, slot, fs = self._io, self.index, self.storage
        self.budget.reserve(self.budget.load_bound(occ_idx, g_idx))
        if len(occ_idx):
            occ_lo = np.ascontiguousarray(st["occ_logodds"], np.float32)
            io.load_known(slot, occ_idx, occ_lo, len(occ_idx), fs.occ_regions, fs.leaf_count)
        if len(g_idx):
            recs = self.records
            recs.load(
                g_idx, st["g_n"], st["g_mean_rel"], st["g_scatter"], st.get("g_erased_near"), st.get("g_ndt_state")
            )
            if recs.ndt:
                self.kernels.ndt_refresh()(nrec=recs.count, records=recs.group, ndt=recs.ndt_group)
            io.load_slots(slot, g_idx, len(g_idx), fs.gidx_regions, fs.occ_regions, fs.leaf_count)
        fs.note_usage()
