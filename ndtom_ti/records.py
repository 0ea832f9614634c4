"""A map's Gaussian records: dense numpy arrays outside Taichi's pool, and their growth.

A cell that receives points gets a record (its number + 1 sits in the cell's ``gslot`` in
the Gaussian index tree); the RCU merge (kernels/update.py ``merge``) writes it. Records
of erased Gaussians wait on a free stack for the next new ones, so the records held follow
the Gaussians alive, not all ever made. Records grow only when the cells of a scan find
none free (``grow_for``).
"""

from __future__ import annotations

import numpy as np

from .cellkeys import lex_order
from .kernels.args import NdtRecords, Picked, Records
from .kernels.layout import NDT_RECORD_BYTES, RECORD_BYTES
from .kernels.ndt import NBR_BACK, NBR_COUNT, NBR_FRESH
from .record_index import MIN_RECORDS, RecordIndex

START_RECORDS = 1024
_ALL = np.zeros(1, np.int32)  # Picked.pick when every record is read
# The NDT miss model's record state bits (kernels/ndt.py), as the two low bits of ndt_state.
STATE_SHIFT = NBR_FRESH.bit_length() - 1
assert NBR_BACK == NBR_FRESH << 1


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
        rays' miss sums not applied yet)."""
        k = self.count
        old = self.n if k or self.nfree else None
        n_ = np.zeros(capacity, np.int32)
        cell = np.zeros((capacity, 3), np.int32)
        mean = np.zeros((capacity, 3), np.float64)
        scat = np.zeros((capacity, 6), np.float64)
        free = np.zeros(capacity, np.int32)
        miss = np.zeros(capacity if self.ndt else 1, np.int64)
        icov = np.zeros((capacity if self.ndt else 1, 9), np.float64)
        nbr = np.zeros(capacity if self.ndt else 1, np.int32)
        if old is not None:
            n_[:k], cell[:k], mean[:k], scat[:k] = self.n[:k], self.cell[:k], self.mean[:k], self.scat[:k]
            if self.ndt:
                miss[:k] = self.miss[:k]
                icov[:k] = self.icov[:k]
                nbr[:k] = self.nbr[:k]
            free[: self.nfree] = self.free[: self.nfree]
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
            return Picked(pick=_ALL, npick=0, tail0=0)
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
