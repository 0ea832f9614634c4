"""Which Gaussian records lie in a box of cells, without reading every record.

Before a scan's rays the NDT miss model marks, in the scan's dense block, the cells whose
records hold a usable Gaussian, and after them applies those records' summed terms
(kernels/trace.py ``mark_gaussians``, kernels/update.py ``apply_marked``). Read record by
record that costs every scan ~9 ns for each record of the map, wherever the sensor is: a
map of 10 M Gaussians would spend ~0.1 s a scan there. The index keeps the records sorted
by bucket (cubes of ``2**shift`` cells), so a scan reads those of the buckets its block
overlaps.

A record changes cells only when merge hands it from the free stack to a new cell: those
records are noted as moved (their old entries skipped), and records handed out since the
index was last brought up to date form a tail; both are read besides the buckets until the
next update takes them in. Updates merge the new entries into the sorted arrays (linear
in the records), and run when the moved and the tail reach an eighth of the records indexed.
"""

from __future__ import annotations

import numpy as np

# Below this many records every record is read: picking them by place (~3 ms a scan for a
# block of ~90 k records) costs about what reading ~1 M records in order does.
MIN_RECORDS = 1 << 20
# Bucket edge: 2**4 = 16 cells (3.2 m at 0.2 m), larger only where the grid is too wide for keys.
SHIFT = 4
# Columns of buckets (x, y) a box may span before every record is read instead.
MAX_COLUMNS = 1 << 16
_EMPTY = np.zeros(1, np.int32)


class RecordIndex:
    """Records by bucket, for one map's records (``ndtom_ti.records.GaussianRecords``).

    glo, ghi: the grid's smallest valid cell index and largest plus one, per axis.
    """

    def __init__(self, glo, ghi):
        self.glo = np.asarray(glo, np.int64)
        span = np.asarray(ghi, np.int64) - self.glo
        shift = SHIFT
        while float(np.prod((span >> shift) + 1, dtype=np.float64)) >= 2.0**62:
            shift += 1
        self.shift = shift
        self.nb = (span >> shift) + 1  # buckets per axis
        # 4-byte keys where the grid's buckets fit (the default grid's 2**30 do)
        self.key_type = np.int32 if float(np.prod(self.nb, dtype=np.float64)) < 2.0**31 else np.int64
        # picks made, those of part of the records, updates, records seen taken to new cells
        self.reads = self.partial = self.updates = self.moves = 0
        self.reset()

    def reset(self) -> None:
        """Forget every record (the records were replaced, as by a load)."""
        self.keys: np.ndarray | None = None  # sorted bucket keys of the indexed records
        self.order = np.zeros(0, np.int32)  # their record numbers
        self.n_indexed = 0  # records [0, n_indexed) were handed out when the index was updated
        self.stale = np.zeros(0, bool)  # indexed records that moved since
        self.span: tuple[np.ndarray, np.ndarray] | None = None  # may be wider than the records now
        self.moved: list[np.ndarray] = []
        self.n_moved = 0

    def nbytes(self) -> int:
        return (0 if self.keys is None else self.keys.nbytes) + self.order.nbytes + self.stale.nbytes

    def bucket_of(self, c) -> np.ndarray:
        return (np.asarray(c, np.int64) - self.glo) >> self.shift

    def bucket_keys(self, cells: np.ndarray) -> np.ndarray:
        b = (np.asarray(cells, np.int64) - self.glo) >> self.shift
        return ((b[:, 0] * self.nb[1] + b[:, 1]) * self.nb[2] + b[:, 2]).astype(self.key_type)

    def note_taken(self, ids: np.ndarray) -> None:
        """Records merge took from the free stack: their cells may have changed."""
        if self.keys is None or not len(ids):
            return
        ids = ids[ids < self.n_indexed]  # later ones are in the tail
        ids = ids[~self.stale[ids]]
        if len(ids):
            self.stale[ids] = True
            self.moved.append(np.array(ids, np.int32))
            self.n_moved += len(ids)
            self.moves += len(ids)

    def update(self, cell: np.ndarray, n: np.ndarray, count: int) -> None:
        """Take in the tail and the moved records; drop the entries of moved or erased ones."""
        if self.keys is None:
            keys, order = np.zeros(0, self.key_type), np.zeros(0, np.int32)
            new = np.arange(count, dtype=np.int32)
        else:
            keep = ~self.stale[self.order]
            keep &= n[self.order] > 0  # erased: back in the index when merge takes them again
            keys, order = self.keys[keep], self.order[keep]
            new = np.concatenate([*self.moved, np.arange(self.n_indexed, count, dtype=np.int32)])
        new = new[n[new] > 0]
        k = self.bucket_keys(cell[new])
        s = np.argsort(k, kind="stable")
        at = np.searchsorted(keys, k[s], side="right")
        self.keys = np.insert(keys, at, k[s])
        self.order = np.insert(order, at, new[s])
        self.n_indexed = count
        if len(new):  # buckets that held indexed records: a box over all of them reads every record
            c = cell[new]
            lo = self.bucket_of([c[:, a].min() for a in range(3)])
            hi = self.bucket_of([c[:, a].max() for a in range(3)])
            self.span = (lo, hi) if self.span is None else (np.minimum(self.span[0], lo), np.maximum(self.span[1], hi))
        self.stale = np.zeros(count, bool)
        self.moved, self.n_moved = [], 0
        self.updates += 1

    def pick(
        self, lo, hi, cell: np.ndarray, n: np.ndarray, count: int, min_records: int = MIN_RECORDS
    ) -> tuple[np.ndarray, int, int]:
        """The records of ``count`` whose cells may lie in the box [lo, hi] (cell indices,
        inclusive): ``(pick, npick, tail0)``, the kernel reads ``pick[:npick]`` and then
        records ``tail0`` to ``count``; every record once at most. ``(_, 0, 0)``: all of them,
        in order (fewer than ``min_records``, or a box that holds most of the map)."""
        self.reads += 1
        if count < min_records:
            if self.keys is not None:
                self.reset()
            return _EMPTY, 0, 0
        if self.keys is None or count - self.n_indexed + self.n_moved > max(4096, self.n_indexed >> 3):
            self.update(cell, n, count)
        assert self.keys is not None
        blo = np.maximum(self.bucket_of(lo), 0)
        bhi = np.minimum(self.bucket_of(hi), self.nb - 1)
        tail = count - self.n_indexed
        if self.span is not None and (blo <= self.span[0]).all() and (bhi >= self.span[1]).all():
            return _EMPTY, 0, 0  # the box holds every indexed record
        if (blo > bhi).any():
            sel = np.zeros(0, np.int32)
        else:
            cols = int(bhi[0] - blo[0] + 1) * int(bhi[1] - blo[1] + 1)
            if cols > MAX_COLUMNS:
                return _EMPTY, 0, 0
            xs = np.arange(blo[0], bhi[0] + 1, dtype=np.int64)
            ys = np.arange(blo[1], bhi[1] + 1, dtype=np.int64)
            col = ((xs[:, None] * self.nb[1] + ys[None, :]) * self.nb[2]).ravel()
            kt = self.key_type  # (values of the keys' type: numpy would copy the keys to compare others)
            first = np.searchsorted(self.keys, (col + blo[2]).astype(kt), side="left")
            stop = np.searchsorted(self.keys, (col + bhi[2]).astype(kt), side="right")
            lens = stop - first
            total = int(lens.sum())
            if total + self.n_moved + tail > count // 2:
                return _EMPTY, 0, 0  # most of the map: in order is faster
            # the columns' runs of the sorted arrays, those that touch joined, copied as slices
            f, t = first[lens > 0], stop[lens > 0]
            cut = np.flatnonzero(f[1:] != t[:-1]) + 1
            runs = zip(f[np.r_[0, cut]].tolist(), t[np.r_[cut - 1, len(t) - 1]].tolist()) if len(f) else ()
            sel = np.concatenate([self.order[a:b] for a, b in runs] or [np.zeros(0, np.int32)])
            if self.n_moved:
                sel = sel[~self.stale[sel]]
        picked = np.concatenate([sel, *self.moved]) if self.moved else sel
        picked.sort()  # the kernels read the records in memory order
        self.partial += 1
        if not len(picked):
            return _EMPTY, 0, self.n_indexed
        return np.ascontiguousarray(picked, np.int32), len(picked), self.n_indexed
