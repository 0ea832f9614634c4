"""Merging cells into coarser ones (method.md sec. 4), on exported cell state."""

from __future__ import annotations

import math
import numbers

import numpy as np

from .cellkeys import group, lookup_rows, pack, unpack
from .config import N_LIMIT, RESOLUTION_MAX

_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def check_factor(factor: object, resolution: float) -> int:
    """The coarsening ``factor`` of a map at ``resolution`` as an int: ValueError unless it is
    an integer >= 2 (not inf or NaN) whose cells stay within RESOLUTION_MAX."""
    f = 0
    if isinstance(factor, bool):
        pass
    elif isinstance(factor, numbers.Integral):
        f = int(factor)
    elif isinstance(factor, numbers.Real) and math.isfinite(factor) and float(factor).is_integer():
        f = int(float(factor))
    if f < 2:
        raise ValueError(f"factor must be an integer >= 2, got {factor!r}")
    if f > RESOLUTION_MAX / resolution:  # (compared, not multiplied: 10**400 * 0.2 overflows)
        raise ValueError(
            f"factor is too large: the cells would be larger than {RESOLUTION_MAX:g} m; for cells of {resolution:g} m "
            f"it can be at most {math.floor(RESOLUTION_MAX / resolution)}"
        )
    return f


def _group(index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique rows of an int (K, 3) array, sorted, and per row its group number (by
    packed int64 keys: np.unique(axis=0) took tens of seconds on millions of rows)."""
    keys, lo, span = pack(index)
    ukeys, _, _, inv = group(keys)
    return unpack(ukeys, lo, span, index.dtype), inv


def _free_gaussians(st: dict) -> np.ndarray:
    """Which Gaussians of the cell state lie in cells of log-odds <= 0 (none without
    occupancy)."""
    found, lo = lookup_rows(st["occ_index"], st["occ_logodds"], st["g_index"])
    return found & (lo <= 0.0)


def coarsen_state(st: dict, resolution: float, factor: int, n_max: int = 0) -> dict:
    """Cell state (as ``NdtOmMap.state()``) of the map at ``factor * resolution``."""
    out: dict = {}

    occ_parent = np.floor_divide(st["occ_index"].astype(np.int64), factor)
    if len(occ_parent):
        keys, klo, span = pack(occ_parent)
        ukeys, order, starts, _ = group(keys)
        lo = np.maximum.reduceat(st["occ_logodds"].astype(np.float32)[order], starts)
        out["occ_index"], out["occ_logodds"] = unpack(ukeys, klo, span, np.int32), lo
    else:
        out["occ_index"], out["occ_logodds"] = np.zeros((0, 3), np.int32), np.zeros(0, np.float32)

    free = _free_gaussians(st)
    if free.any():
        # A free cell's Gaussian (the NDT miss model keeps its points until its log-odds
        # falls to NDT_RESET) is no matter of the coarser cell.
        st = {**st, **{k: st[k][~free] for k in ("g_index", "g_n", "g_mean_rel", "g_scatter")}}
    idx = st["g_index"].astype(np.int64)
    if len(idx) == 0:
        out.update(
            g_index=np.zeros((0, 3), np.int32),
            g_n=np.zeros(0, np.int32),
            g_mean_rel=np.zeros((0, 3)),
            g_scatter=np.zeros((0, 6)),
        )
        return out
    parent = np.floor_divide(idx, factor)
    uniq, inv = _group(parent)
    n = st["g_n"].astype(np.float64)
    # Child means relative to the parent's centre, so sums stay well conditioned.
    q = (idx + 0.5) * resolution + st["g_mean_rel"] - (parent + 0.5) * (resolution * factor)
    G = len(uniq)
    ntot = np.bincount(inv, weights=n, minlength=G)
    mean = np.stack([np.bincount(inv, weights=n * q[:, a], minlength=G) for a in range(3)], axis=1) / ntot[:, None]
    d = q - mean[inv]
    scat = np.empty((G, 6))
    for col, (a, b) in enumerate(_PAIRS):
        scat[:, col] = np.bincount(inv, weights=st["g_scatter"][:, col] + n * d[:, a] * d[:, b], minlength=G)
    n_int = ntot.astype(np.int64)
    # without n_max, N is still capped at N_LIMIT (as a map's updates cap it): the sum of
    # the children's counts must fit the kernels' int32
    cap = n_max or N_LIMIT
    over = n_int > cap
    if over.any():
        scat[over] *= ((cap - 1) / (n_int[over] - 1))[:, None]
        n_int[over] = cap
    out.update(g_index=uniq.astype(np.int32), g_n=n_int.astype(np.int32), g_mean_rel=mean, g_scatter=scat)
    return out
