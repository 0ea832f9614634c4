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
next update takes them in. The index is one sorted int64 array, bucket key above record
number: an update sorts the new entries and merges them into it (numpy's stable sort finds
the two sorted runs: linear in the records), when the moved and the tail reach an eighth of
the records indexed.
"""

from __future__ import annotations

import numpy as np

# Below this many records every record is read: picking them by place (~3 ms a scan for a
# block of ~90 k records) costs about what reading ~1 M records in order does.
MIN_RECORDS = 1 << 20
# Bucket edge: 2**4 = 16 cells (3.2 m at 0.2 m), larger only where the grid has more than
# 2**31 buckets (a key and a record number share an int64).
SHIFT = 4
# Moved and tail records an update waits for at least (besides an eighth of those indexed).
UPDATE_MIN = 4096
# Columns of buckets (x, y) a box may span before every record is read instead.
MAX_COLUMNS = 1 << 16
NO_PICK = np.zeros(1, np.int32)  # ``pick`` of an answer that picks none by place (npick 0)
_RECORD = np.int64(0xFFFFFFFF)  # the low half of an entry: its record number


class RecordIndex:
    """Records by bucket, for one map's records (``ndtom_ti.records.GaussianRecords``).

    glo, ghi: the grid's smallest valid cell index and largest plus one, per axis.
    """

    def __init__(self, glo, ghi):
        self.glo = np.asarray(glo, np.int64)
        span = np.asarray(ghi, np.int64) - self.glo
        shift = SHIFT
        while float(np.prod((span >> shift) + 1, dtype=np.float64)) >= 2.0**31:
            shift += 1
        self.shift = shift
        self.nb = (span >> shift) + 1  # buckets per axis
        # picks made, those of part of the records, updates, records seen taken to new cells
        self.reads = self.partial = self.updates = self.moves = 0
        self.reset()

    def reset(self) -> None:
        """Forget every record (the records were replaced, as by a load)."""
        self.entries: np.ndarray | None = None  # sorted: bucket key << 32 | record number
        self.n_indexed = 0  # records [0, n_indexed) were handed out when the index was updated
        self.stale = np.zeros(0, bool)  # indexed records that moved since
        self.moved: list[np.ndarray] = []
        self.n_moved = 0
        # buffers reused by updates: the entries' (self.entries is a view of it), the other
        # one merges write into, the merge's mask, the stale flags'
        self._whole: np.ndarray | None = None
        self._spare: np.ndarray | None = None
        self._fresh: np.ndarray | None = None
        self._stale = np.zeros(0, bool)

    def nbytes(self) -> int:
        bufs = (self._whole, self._spare, self._fresh, self._stale)
        return sum(b.nbytes for b in bufs if b is not None)

    def bucket_of(self, c) -> np.ndarray:
        return (np.asarray(c, np.int64) - self.glo) >> self.shift

    def bucket_keys(self, cells: np.ndarray) -> np.ndarray:
        b = self.bucket_of(cells)
        k = b[:, 0] * self.nb[1]
        k += b[:, 1]
        k *= self.nb[2]
        k += b[:, 2]
        return k

    def _entries(self, ids: np.ndarray, cell: np.ndarray) -> np.ndarray:
        """Sorted entries of records ``ids``."""
        e = self.bucket_keys(cell[ids])
        e <<= 32
        e |= ids
        e.sort()
        return e

    def note_taken(self, ids: np.ndarray) -> None:
        """Records merge took from the free stack: their cells may have changed."""
        if self.entries is None or not len(ids):
            return
        ids = ids[ids < self.n_indexed]  # later ones are in the tail
        ids = ids[~self.stale[ids]]
        if len(ids):
            self.stale[ids] = True
            self.moved.append(np.array(ids, np.int32))
            self.n_moved += len(ids)
            self.moves += len(ids)

    def update(self, cell: np.ndarray, n: np.ndarray, count: int) -> None:
        """Take in the tail and the moved records (without points: none); drop the entries
        of moved ones. (Erased records keep theirs until merge takes them: the kernels skip
        records without points, and a pass over the index to find them cost more.)"""
        if self.entries is None:
            new = np.flatnonzero(n[:count] > 0)
            self.entries = self._whole = self._entries(new, cell)
        else:
            kept = self.entries
            if self.n_moved:
                kept = kept[~self.stale[kept & _RECORD]]
            new = np.concatenate([*self.moved, np.arange(self.n_indexed, count, dtype=np.int32)])
            new = new[n[new] > 0]
            add = self._entries(new, cell)
            # merged into the other of two buffers kept from update to update: fresh memory is
            # slow to touch on some virtual machines (~0.3 s for this merge at 6 M records)
            total = len(kept) + len(add)
            spare = self._spare if self._spare is not None and len(self._spare) >= total else None
            if spare is None:
                spare = np.empty(total + (total >> 3), np.int64)
            at = np.searchsorted(kept, add, side="right")
            at += np.arange(len(add))
            out = spare[:total]
            if self._fresh is None or len(self._fresh) < total:
                self._fresh = np.empty(len(spare), bool)
            fresh = self._fresh[:total]
            fresh[:] = False
            fresh[at] = True
            out[at] = add
            np.logical_not(fresh, out=fresh)
            out[fresh] = kept
            self._spare = self._whole
            self._whole, self.entries = spare, out
        self.n_indexed = count
        if len(self._stale) < count:
            self._stale = np.zeros(count + (count >> 3), bool)
        self.stale = self._stale[:count]
        self.stale[:] = False
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
            if self.entries is not None:
                self.reset()
            return NO_PICK, 0, 0
        if self.entries is None or count - self.n_indexed + self.n_moved > max(UPDATE_MIN, self.n_indexed >> 3):
            self.update(cell, n, count)
        assert self.entries is not None
        blo = np.maximum(self.bucket_of(lo), 0)
        bhi = np.minimum(self.bucket_of(hi), self.nb - 1)
        tail = count - self.n_indexed
        if (blo > bhi).any():
            sel = np.zeros(0, np.int32)
        else:
            cols = int(bhi[0] - blo[0] + 1) * int(bhi[1] - blo[1] + 1)
            if cols > MAX_COLUMNS:
                return NO_PICK, 0, 0
            xs = np.arange(blo[0], bhi[0] + 1, dtype=np.int64)
            ys = np.arange(blo[1], bhi[1] + 1, dtype=np.int64)
            col = ((xs[:, None] * self.nb[1] + ys[None, :]) * self.nb[2]).ravel()
            first = np.searchsorted(self.entries, (col + blo[2]) << 32, side="left")
            stop = np.searchsorted(self.entries, (col + bhi[2] + 1) << 32, side="left")
            lens = stop - first
            if int(lens.sum()) + self.n_moved + tail > count // 2:
                return NO_PICK, 0, 0  # most of the map: in order is faster
            # the columns' runs of the sorted entries, those that touch joined, copied as slices
            f, t = first[lens > 0], stop[lens > 0]
            cut = np.flatnonzero(f[1:] != t[:-1]) + 1
            runs = zip(f[np.r_[0, cut]].tolist(), t[np.r_[cut - 1, len(t) - 1]].tolist()) if len(f) else ()
            sel = np.concatenate([self.entries[a:b] for a, b in runs] or [np.zeros(0, np.int64)])
            sel = (sel & _RECORD).astype(np.int32)
            if self.n_moved:
                sel = sel[~self.stale[sel]]
        picked = np.concatenate([sel, *self.moved]) if self.moved else sel
        picked.sort()  # the kernels read the records in memory order
        self.partial += 1
        if not len(picked):
            return NO_PICK, 0, self.n_indexed
        return np.ascontiguousarray(picked, np.int32), len(picked), self.n_indexed
