"""An online error-refinement NDT baseline (numpy), the third mapper of the paper's Fig. 1.

Saarinen et al. (ICRA 2013, sec. IV-A) compare their exact Recursive Covariance Update
against the online refinement of NDT maps by Yguel and Aycard, but print no formula for
it. :class:`ErrorRefinementMap` **stands in** for that method: it is an error-driven
(stochastic-approximation) estimator of each cell's Gaussian, as such online learners
are, with a bounded learning rate. It is *not* Yguel and Aycard's exact algorithm.

Update rule (exactly what :meth:`ErrorRefinementMap.insert_world` does)
---------------------------------------------------------------------
A point ``x`` (world frame, metres) goes to cell ``k = floor(x / r)``, like every other
map here. Each cell holds a count ``k_c``, a mean ``mu`` and a covariance ``C``. The
points of a scan are applied one at a time, in the order they come in the scan::

    k_c <- k_c + 1
    if k_c == 1:   mu <- x;  C <- 0
    else:
        eps  = max(1 / k_c, eps_min)          # learning rate, bounded below by eps_min
        e    = x - mu                         # the error of the current estimate
        mu  <- mu + eps * e
        C   <- C + eps * (e e^T - C)          # Robbins-Monro step toward e e^T

Defaults: ``eps_min = 0.05``; a cell has a Gaussian when ``k_c >= 3`` (as the others).

Why it is not exact: with ``eps = 1/k`` the mean is the running mean, but the
covariance step weighs ``e e^T`` by ``1/k`` where the exact (Welford) recursion needs
``(k-1)/k^2`` (population) or the RCU's scatter update; and once ``k > 1/eps_min``
the learning rate stops falling, so the estimate forgets old points exponentially
(weight ``(1 - eps_min)^age``) and follows the last few tens of points of the cell, i.e.
mostly the last scan that saw it, in that scan's ray order. Both make it differ from the
batch map of eq. (1), which is what Fig. 1 shows.

Points are applied per cell in scan order; cells are independent, so the update runs
vectorised over cells in "rounds" (round ``j`` applies the ``j``-th point of every cell
hit by the scan), which gives exactly the result of the sequential per-point loop.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ..config import check_resolution

__all__ = ["UPDATE_RULE", "ErrorRefinementMap"]

UPDATE_RULE = (
    "per cell, points applied one at a time in scan order: k += 1; first point: mu = x, C = 0; "
    "else eps = max(1/k, eps_min), e = x - mu, mu += eps*e, C += eps*(e e^T - C) "
    "(error-driven Robbins-Monro step with a bounded learning rate; stands in for Yguel and "
    "Aycard's online refinement, whose formula the paper does not print; not exact)"
)

_BITS = 21
_OFF = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


def _pack(k: np.ndarray) -> np.ndarray:
    """(N, 3) int64 cell indices in [-2^20, 2^20) -> (N,) int64 keys."""
    if len(k) and (np.abs(k).max() >= _OFF):
        raise ValueError(f"cell index beyond +-{_OFF}: use a coarser resolution")
    u = k + _OFF
    return (u[:, 0] << (2 * _BITS)) | (u[:, 1] << _BITS) | u[:, 2]


def _unpack(key: np.ndarray) -> np.ndarray:
    return np.stack([(key >> (2 * _BITS)) & _MASK, (key >> _BITS) & _MASK, key & _MASK], axis=1) - _OFF


class ErrorRefinementMap:
    """Online error-refinement NDT map (see the module docstring for the exact rule)."""

    def __init__(self, resolution: float, *, eps_min: float = 0.05, min_points: int = 3):
        resolution = check_resolution(resolution)
        if not 0.0 < eps_min <= 1.0:
            raise ValueError(f"eps_min must be in (0, 1], got {eps_min}")
        self.resolution = resolution
        self.eps_min = float(eps_min)
        self.min_points = int(min_points)
        self._keys = np.zeros(0, np.int64)  # per slot
        self._sorted = np.zeros(0, np.int64)  # keys sorted
        self._sorted_slot = np.zeros(0, np.int64)  # slot of each sorted key
        self._count = np.zeros(0, np.int64)
        self._mean = np.zeros((0, 3))  # relative to the cell centre
        self._cov = np.zeros((0, 3, 3))
        self.scans_inserted = 0
        self.points_inserted = 0

    # ------------------------------------------------------------------ updates

    def insert_scan(self, points: Any, T_world_sensor: Any) -> float:
        """Insert a scan given in the sensor frame with its pose; returns seconds taken."""
        T = np.asarray(T_world_sensor, np.float64)
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        t0 = time.perf_counter()
        self.insert_world(pts @ T[:3, :3].T + T[:3, 3])
        return time.perf_counter() - t0

    def _slots(self, keys: np.ndarray) -> np.ndarray:
        """Slot of every key, making slots for new keys."""
        pos = np.searchsorted(self._sorted, keys)
        found = np.zeros(len(keys), bool)
        inb = pos < len(self._sorted)
        found[inb] = self._sorted[pos[inb]] == keys[inb]
        slots = np.empty(len(keys), np.int64)
        slots[found] = self._sorted_slot[pos[found]]
        if (~found).any():
            new, inv = np.unique(keys[~found], return_inverse=True)
            base = len(self._keys)
            slots[~found] = base + inv
            m = len(new)
            self._keys = np.concatenate([self._keys, new])
            self._count = np.concatenate([self._count, np.zeros(m, np.int64)])
            self._mean = np.concatenate([self._mean, np.zeros((m, 3))])
            self._cov = np.concatenate([self._cov, np.zeros((m, 3, 3))])
            order = np.argsort(self._keys, kind="stable")
            self._sorted, self._sorted_slot = self._keys[order], order
        return slots

    def insert_world(self, world: Any) -> None:
        """Apply world-frame points (N, 3) in their order (non-finite points are dropped)."""
        w = np.asarray(world, np.float64).reshape(-1, 3)
        w = w[np.isfinite(w).all(axis=1)]
        self.scans_inserted += 1
        if len(w) == 0:
            return
        r = self.resolution
        k = np.floor(w / r).astype(np.int64)
        q = w - (k + 0.5) * r  # relative to the cell centre: well conditioned
        slots = self._slots(_pack(k))
        self.points_inserted += len(w)

        # Rank of each point within its cell, keeping scan order (stable sort).
        order = np.argsort(slots, kind="stable")
        s_sorted = slots[order]
        start = np.ones(len(order), bool)
        start[1:] = s_sorted[1:] != s_sorted[:-1]
        run_start = np.maximum.accumulate(np.where(start, np.arange(len(order)), 0))
        rank = np.empty(len(order), np.int64)
        rank[order] = np.arange(len(order)) - run_start
        # Rounds: round j applies the j-th point of every cell (distinct cells per round).
        by_rank = np.argsort(rank, kind="stable")
        bounds = np.concatenate([[0], np.cumsum(np.bincount(rank))])
        cnt, mean, cov, emin = self._count, self._mean, self._cov, self.eps_min
        for j in range(len(bounds) - 1):
            sel = by_rank[bounds[j] : bounds[j + 1]]
            s, x = slots[sel], q[sel]
            cnt[s] += 1
            c = cnt[s]
            first = c == 1
            if first.any():
                mean[s[first]] = x[first]
                cov[s[first]] = 0.0
            rest = ~first
            if rest.any():
                s2, x2 = s[rest], x[rest]
                eps = np.maximum(1.0 / c[rest], emin)
                e = x2 - mean[s2]
                mean[s2] += eps[:, None] * e
                cov[s2] += eps[:, None, None] * (e[:, :, None] * e[:, None, :] - cov[s2])

    # ------------------------------------------------------------------ queries

    def gaussians(self, min_points: int | None = None) -> dict:
        """Gaussians of cells with at least ``min_points`` points, sorted by cell index:
        ``index`` (K, 3) int64, ``mean`` (K, 3) world, ``cov`` (K, 3, 3), ``n`` (K,)."""
        mp = self.min_points if min_points is None else int(min_points)
        keep = self._sorted_slot[self._count[self._sorted_slot] >= max(mp, 1)]
        # keys sorted ascending == lexicographic order of (x, y, z) indices (offset packing)
        idx = _unpack(self._keys[keep])
        return {
            "index": idx,
            "mean": (idx + 0.5) * self.resolution + self._mean[keep],
            "cov": 0.5 * (self._cov[keep] + np.swapaxes(self._cov[keep], 1, 2)),
            "n": self._count[keep].copy(),
        }

    def __len__(self) -> int:
        return int((self._count >= self.min_points).sum())

    def __repr__(self) -> str:
        return (
            f"ErrorRefinementMap(resolution={self.resolution:g}, eps_min={self.eps_min:g}, "
            f"scans={self.scans_inserted}, gaussians={len(self)})"
        )
