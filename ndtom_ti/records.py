"""A map's Gaussian records: dense numpy arrays outside Taichi's pool, and their growth.

A cell that receives points gets a record (its number + 1 sits in the cell's ``gslot`` in
the Gaussian index tree); the RCU merge (kernels/update.py ``merge``) writes it. Records
of erased Gaussians wait on a free stack for the next new ones, so the records held follow
the Gaussians alive, not all ever made. Records grow only when the cells of a scan find
none free (``grow_for``).
"""

from __future__ import annotations

import mmap
import os
import platform
import sys

import numpy as np

from .cellkeys import lex_order
from .kernels.args import NdtRecords, Picked, Records
from .kernels.layout import NDT_RECORD_BYTES, RECORD_BYTES
from .kernels.ndt import NBR_BACK, NBR_COUNT, NBR_FRESH
from .record_index import MIN_RECORDS, NO_PICK, RecordIndex

START_RECORDS = 1024
MAX_RECORDS = 2**31 - 2  # record numbers + 1 are int32 in the kernels
# The NDT miss model's record state bits (kernels/ndt.py), as the two low bits of ndt_state.
STATE_SHIFT = NBR_FRESH.bit_length() - 1
assert NBR_BACK == NBR_FRESH << 1


# The record arrays: dtype and columns (0: one column, a 1-D array), and whether only the NDT
# miss model has them (else a placeholder row).
_ARRAYS = (
    (np.int32, 0, False),  # n
    (np.int32, 3, False),  # cell
    (np.float64, 3, False),  # mean
    (np.float64, 6, False),  # scat
    (np.int32, 0, False),  # free
    (np.int64, 0, True),  # miss
    (np.float64, 9, True),  # icov
    (np.int32, 0, True),  # nbr
)
# Linux's MAP_NORESERVE (x86-64, arm64): the reservation takes no memory until written
_NORESERVE = getattr(mmap, "MAP_NORESERVE", 0x4000 if platform.machine() in ("x86_64", "aarch64") else 0)


class _Space:
    """Address space reserved for ``rows`` records (Linux): anonymous mappings, one per
    array, backed by memory only where written, so that the records grow in place. Copying
    millions of records into new arrays made a scan wait for seconds (3.4 s at 7 M records:
    fresh memory is slow to touch on some virtual machines)."""

    def __init__(self, maps: list, rows: int, ndt: bool):
        self.maps, self.rows, self.ndt = maps, rows, ndt

    @classmethod
    def reserve(cls, capacity: int, ndt: bool) -> _Space | None:
        if not sys.platform.startswith("linux") or not _NORESERVE:
            return None
        try:
            ram = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError, AttributeError):
            return None
        row = sum(np.dtype(t).itemsize * max(c, 1) for t, c, _ in _ARRAYS)
        rows = max(capacity, min(MAX_RECORDS, ram // row))  # no more records than memory holds
        maps = []
        try:
            for t, c, only_ndt in _ARRAYS:
                n = rows if ndt or not only_ndt else 1
                size = max(n * np.dtype(t).itemsize * max(c, 1), 1)
                maps.append(mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | _NORESERVE))
        except (OSError, ValueError, OverflowError):  # refused (strict overcommit): copy as before
            for m in maps:
                m.close()
            return None
        return cls(maps, rows, ndt)

    def views(self, capacity: int) -> tuple:
        out = []
        for m, (t, c, only_ndt) in zip(self.maps, _ARRAYS):
            n = capacity if self.ndt or not only_ndt else 1
            a = np.frombuffer(m, t, n * max(c, 1))
            out.append(a.reshape(n, c) if c else a)
        return tuple(out)


class GaussianRecords:
    """The records of one map.

    ``n`` [C] i32 points (0: unused or erased), ``cell`` [C, 3] i32 cell index, ``mean``
    [C, 3] f64 mean minus the cell centre, ``scat`` [C, 6] f64 scatter (xx xy xz yy yz
    zz), ``free`` [C] i32 the free stack (its first ``nfree`` entries). With the NDT miss
    model also ``miss`` [C] i64, the scan's summed log-odds changes (zero between updates),
    ``icov`` [C, 9] f64, what rays read (inverse regularised covariance, mean), and ``nbr``
    [C] i32, the neighbouring cells' Gaussians erased since the record's last points and,
    above them, its NBR_FRESH and NBR_BACK bits (kernels/ndt.py); a
    placeholder row each without it. ``count``: records handed out so far (in use or on
    the free stack). ``index``: the records by place (record_index), for the NDT miss
    model's kernels that read those of a scan's block; ``grid`` (lo, hi): the grid's cell
    index range.
    """

    def __init__(
        self,
        ndt: bool,
        ndt_prm: np.ndarray | None = None,
        ndt_minp: int = 0,
        capacity: int = START_RECORDS,
        grid: tuple | None = None,
    ):
        lo, hi = grid if grid is not None else ((-(2**30),) * 3, (2**30,) * 3)
        self.index = RecordIndex(lo, hi)
        # The box of every cell a record was given (None: none yet): it may be wider than the
        # cells of the records now.
        self.extent: tuple[np.ndarray, np.ndarray] | None = None
        self.ndt = bool(ndt)
        self.ndt_prm = np.zeros(9) if ndt_prm is None else ndt_prm
        self.ndt_minp = int(ndt_minp)
        self.count = 0
        self.nfree = 0
        self.n = np.zeros(0, np.int32)
        self._space: _Space | None = None
        self.grow(capacity)

    @property
    def capacity(self) -> int:
        return len(self.n)

    @property
    def in_use(self) -> int:
        return self.count - self.nfree

    def nbytes(self) -> int:
        return self.capacity * (RECORD_BYTES + (NDT_RECORD_BYTES if self.ndt else 0)) + self.index.nbytes()

    def grow(self, capacity: int) -> None:
        """Hold ``capacity`` records, keeping those handed out (and, mid-update, the
        rays' miss sums not applied yet). Within the reserved space (Linux) the arrays grow
        in place: longer views of the same memory, nothing copied."""
        k = self.count
        if self._space is None or capacity > self._space.rows:
            self._space = _Space.reserve(capacity, self.ndt)
            if self._space is not None and (k or self.nfree):
                self._copy_into(self._space.views(capacity))
        if self._space is not None:
            self._use(*self._space.views(capacity))
            return
        # no reserved space: new arrays, the records copied into them
        n_ = np.zeros(capacity, np.int32)
        cell = np.zeros((capacity, 3), np.int32)
        mean = np.zeros((capacity, 3), np.float64)
        scat = np.zeros((capacity, 6), np.float64)
        free = np.zeros(capacity, np.int32)
        miss = np.zeros(capacity if self.ndt else 1, np.int64)
        icov = np.zeros((capacity if self.ndt else 1, 9), np.float64)
        nbr = np.zeros(capacity if self.ndt else 1, np.int32)
        if k or self.nfree:
            self._copy_into((n_, cell, mean, scat, free, miss, icov, nbr))
        self._use(n_, cell, mean, scat, free, miss, icov, nbr)

    def _copy_into(self, arrays) -> None:
        n_, cell, mean, scat, free, miss, icov, nbr = arrays
        k = self.count
        n_[:k], cell[:k], mean[:k], scat[:k] = self.n[:k], self.cell[:k], self.mean[:k], self.scat[:k]
        if self.ndt:
            miss[:k] = self.miss[:k]
            icov[:k] = self.icov[:k]
            nbr[:k] = self.nbr[:k]
        free[: self.nfree] = self.free[: self.nfree]

    def _use(self, n_, cell, mean, scat, free, miss, icov, nbr) -> None:
        self.n, self.cell, self.mean, self.scat, self.free = n_, cell, mean, scat, free
        self.miss, self.icov, self.nbr = miss, icov, nbr
        # The arrays as kernel arguments (rebuilt with them).
        self.group = Records(rec_n=n_, rec_cell=cell, rec_mean=mean, rec_scat=scat, rec_free=free)
        self.ndt_group = (
            NdtRecords(rec_miss=miss, rec_icov=icov, ndt_prm=self.ndt_prm, ndt_minp=self.ndt_minp, rec_nbr=nbr)
            if self.ndt
            else None
        )

    def grow_for(self, new_cells: int) -> None:
        """Grow when new cells found no record: by an eighth, or by a scan's hit cells
        (fewer copies while a small map explores), as the memory should follow the place."""
        cap = self.capacity
        self.grow(cap + max(cap // 8, new_cells))

    def in_box(self, lo, hi, min_records: int = MIN_RECORDS) -> Picked:
        """The records whose cells may lie in the box [lo, hi] (cell indices, inclusive);
        every record where the map has fewer than ``min_records``, or where the box holds
        every cell a record was given (no index is built for a map the block holds)."""
        ext = self.extent
        if ext is not None and (ext[0] >= lo).all() and (ext[1] <= hi).all():
            return Picked(pick=NO_PICK, npick=0, tail0=0)
        pick, npick, tail0 = self.index.pick(lo, hi, self.cell, self.n, self.count, min_records)
        return Picked(pick=pick, npick=npick, tail0=tail0)

    def taken(self, nfree_before: int, count_before: int) -> None:
        """Merge took the free stack from ``nfree_before`` records down to ``nfree`` and
        handed out records from ``count_before`` on: those records have new cells."""
        ids = self.free[self.nfree : nfree_before]
        if len(ids):
            self.index.note_taken(ids)
            self._widen(self.cell[ids])
        if self.count > count_before:
            self._widen(self.cell[count_before : self.count])

    def _widen(self, cells: np.ndarray) -> None:
        lo = np.array([cells[:, a].min() for a in range(3)], np.int64)  # per column: axis=0 is slow
        hi = np.array([cells[:, a].max() for a in range(3)], np.int64)
        ext = self.extent
        self.extent = (lo, hi) if ext is None else (np.minimum(ext[0], lo), np.maximum(ext[1], hi))

    def clear_miss(self) -> None:
        self.miss[:] = 0

    def holding_points(self) -> dict:
        """Every record that holds points, sorted by cell index: ``index`` (K, 3) i32,
        ``n``, ``mean_rel``, ``scatter``, and the NDT miss model's ``erased_near`` (i32) and
        ``ndt_state`` (u8: 1 NBR_FRESH, 2 NBR_BACK; zeros without the model)."""
        k = self.count
        keep = self.n[:k] > 0
        idx = self.cell[:k][keep]
        order = lex_order(idx)
        nbr = self.nbr[:k][keep][order] if self.ndt else np.zeros(len(idx), np.int32)
        return {
            "index": np.ascontiguousarray(idx[order]),
            "n": self.n[:k][keep][order],
            "mean_rel": self.mean[:k][keep][order],
            "scatter": self.scat[:k][keep][order],
            "erased_near": (nbr & NBR_COUNT).astype(np.int32),
            "ndt_state": ((nbr >> STATE_SHIFT) & 3).astype(np.uint8),
        }

    def with_points(self, min_points: int) -> np.ndarray:
        """Cells (K, 3) of the records with at least ``min_points`` points."""
        cand = np.flatnonzero(self.n[: self.count] >= min_points)
        return np.ascontiguousarray(self.cell[cand])

    def load(
        self,
        index: np.ndarray,
        n: np.ndarray,
        mean_rel: np.ndarray,
        scatter: np.ndarray,
        erased_near: np.ndarray | None = None,
        ndt_state: np.ndarray | None = None,
    ) -> None:
        """Fill an empty set of records with loaded Gaussians (record i: cell ``index[i]``)."""
        k = len(index)
        self.index.reset()
        self.extent = None
        if k:
            self._widen(np.asarray(index))
        self.grow(max(START_RECORDS, k))
        self.n[:k] = n
        self.cell[:k] = index
        self.mean[:k] = mean_rel
        self.scat[:k] = scatter
        if self.ndt:
            if erased_near is not None:
                self.nbr[:k] = np.minimum(erased_near, NBR_COUNT)
            if ndt_state is not None:
                self.nbr[:k] |= (np.asarray(ndt_state, np.int32) & 3) << STATE_SHIFT
        self.count = k
