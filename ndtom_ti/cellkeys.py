"""Integer cell indices (K, 3) as one int64 key per row, for sorting and grouping.

Keys order rows as (i, j, k) lexicographically. Sorting one int64 column is many times
faster than ``np.lexsort`` over three, and ``np.unique(..., axis=0)`` of a few million
rows took tens of seconds (numpy 2.4: even its 1-D unique is ~100x slower than a sort).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import DTypeLike


def pack(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(keys, lo, span): key = ((i - lo_i) * span_j + (j - lo_j)) * span_k + (k - lo_k)."""
    idx = np.asarray(idx)
    if len(idx) == 0:
        return np.zeros(0, np.int64), np.zeros(3, np.int64), np.ones(3, np.int64)
    lo = np.array([idx[:, a].min() for a in range(3)], np.int64)  # per column: axis=0 is slow
    span = np.array([idx[:, a].max() for a in range(3)], np.int64) - lo + 1
    if float(span[0]) * float(span[1]) * float(span[2]) >= 2.0**62:
        raise ValueError(f"cell indices span {span.tolist()} cells: too wide for one int64 key")
    keys = idx[:, 0].astype(np.int64) - lo[0]
    keys *= span[1]
    keys += idx[:, 1]
    keys -= lo[1]
    keys *= span[2]
    keys += idx[:, 2]
    keys -= lo[2]
    return keys, lo, span


# Keys unpacked at a time: the chunk's quotients stay in the cache.
_CHUNK = 65536


def unpack(keys: np.ndarray, lo: np.ndarray, span: np.ndarray, dtype: DTypeLike = np.int64) -> np.ndarray:
    """The (K, 3) rows of ``keys`` made by :func:`pack`."""
    keys = np.asarray(keys, np.int64)
    out = np.empty((len(keys), 3), dtype)
    s1, s2 = int(span[1]), int(span[2])
    lo0, lo1, lo2 = (int(v) for v in lo)
    # Each column whole before it is written: numpy's divmod and any operation along rows of
    # 3 (out += lo) are several times slower than floor division by a number and whole columns.
    q, r = np.empty(min(len(keys), _CHUNK), np.int64), np.empty(min(len(keys), _CHUNK), np.int64)
    for a in range(0, len(keys), _CHUNK):
        kk = keys[a : a + _CHUNK]
        m = len(kk)
        qq, rr, o = q[:m], r[:m], out[a : a + m]
        np.floor_divide(kk, s2, out=qq)
        np.multiply(qq, s2, out=rr)
        np.subtract(kk, rr, out=rr)
        rr += lo2
        o[:, 2] = rr
        np.floor_divide(qq, s1, out=rr)
        qq -= rr * s1
        qq += lo1
        o[:, 1] = qq
        rr += lo0
        o[:, 0] = rr
    return out


def lex_order(idx: np.ndarray) -> np.ndarray:
    """The permutation that sorts distinct rows lexicographically (as np.lexsort of the
    reversed columns, for rows without repeats)."""
    return np.argsort(pack(idx)[0])


def count_distinct(keys: np.ndarray) -> int:
    if len(keys) == 0:
        return 0
    s = np.sort(keys)
    return int(np.count_nonzero(s[1:] != s[:-1])) + 1


def group(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(distinct keys sorted, order, starts, inverse): ``keys[order]`` is sorted, the
    groups of equal keys start at ``starts`` in it, and ``inverse`` gives each key's group."""
    order = np.argsort(keys)
    s = keys[order]
    first = np.empty(len(s), bool)
    first[:1] = True
    np.not_equal(s[1:], s[:-1], out=first[1:])
    starts = np.flatnonzero(first)
    inverse = np.empty(len(keys), np.int64)
    inverse[order] = np.cumsum(first) - 1
    return s[starts], order, starts, inverse


def isin_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Which rows of the (K, 3) cell indices ``a`` are also rows of ``b``."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(len(a), bool)
    keys, _, _ = pack(np.concatenate([np.asarray(a, np.int64).reshape(-1, 3), np.asarray(b, np.int64).reshape(-1, 3)]))
    return np.isin(keys[: len(a)], keys[len(a) :])


def lookup_rows(known: np.ndarray, values: np.ndarray, want: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For the (K, 3) cell indices ``want``: whether each is a row of ``known`` (M, 3), and
    that row's entry of ``values`` (M,) (0 where not). A binary search over the packed keys
    (sorted first only if ``known`` is not in key order already)."""
    values = np.asarray(values)
    found, out = np.zeros(len(want), bool), np.zeros(len(want), values.dtype)
    if len(want) == 0 or len(known) == 0:
        return found, out
    keys, _, _ = pack(
        np.concatenate([np.asarray(known, np.int64).reshape(-1, 3), np.asarray(want, np.int64).reshape(-1, 3)])
    )
    kk, wk = keys[: len(known)], keys[len(known) :]
    if (kk[1:] < kk[:-1]).any():
        order = np.argsort(kk, kind="stable")
        kk, values = kk[order], values[order]
    pos = np.minimum(np.searchsorted(kk, wk), len(kk) - 1)
    found = kk[pos] == wk
    out[found] = values[pos[found]]
    return found, out
