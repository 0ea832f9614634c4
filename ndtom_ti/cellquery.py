"""The queries a map and its snapshot answer alike: the Gaussians of the records, the
known cells, the box of the known cells, log-odds by cell index and occupancy by point.

``NdtOmMap`` reads its slot and :class:`~ndtom_ti.snapshot.MapSnapshot` its arrays; both
shape the answers here, so the two give the same dicts and arrays.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from .config import check_gaussian_filter
from .scaninput import as_points, cell_box

__all__ = ["cell_extent", "check_cell_index", "known_cells_of", "occupancy_of", "probability", "select_gaussians"]

_COV_IJ = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def probability(logodds: np.ndarray) -> np.ndarray:
    """Occupancy probability of float64 log-odds (a large one reads 1)."""
    with np.errstate(over="ignore"):
        return 1.0 - 1.0 / (1.0 + np.exp(logodds))


def select_gaussians(
    index, n, mean_rel, scatter, logodds, resolution: float, min_points, min_probability, default_min_points: int
) -> dict:
    """The dict of ``gaussians()`` (a map's and a snapshot's) from Gaussian records sorted by
    cell: ``index`` (G, 3), ``n`` (G,), ``mean_rel`` (G, 3) mean minus the cell centre,
    ``scatter`` (G, 6) xx xy xz yy yz zz, ``logodds`` (G,) of their cells."""
    min_points, min_probability = check_gaussian_filter(min_points, min_probability, default_min_points)
    keep = n >= max(min_points, 1)
    lo = np.asarray(logodds).astype(np.float64)
    p = probability(lo)
    if min_probability > 0.0:
        keep &= p > min_probability
    idx = index[keep].astype(np.int64)
    cnt = n[keep].astype(np.int64)
    s = scatter[keep]
    cov = np.empty((len(cnt), 3, 3))
    for col, (a, b) in enumerate(_COV_IJ):
        cov[:, a, b] = s[:, col]
        cov[:, b, a] = s[:, col]
    cov /= np.maximum(cnt - 1, 1).astype(np.float64)[:, None, None]
    cov[cnt < 2] = 0.0
    mean = (idx + 0.5) * resolution + mean_rel[keep]
    return {"index": idx, "mean": mean, "cov": cov, "n": cnt, "p_occ": p[keep], "logodds": lo[keep]}


def known_cells_of(index: np.ndarray, logodds: np.ndarray) -> dict:
    """The dict of ``known_cells()``: ``index`` (K, 3) int64, ``logodds`` (K,) float64,
    ``p_occ`` (K,) float64."""
    lo = logodds.astype(np.float64)
    return {"index": index.astype(np.int64), "logodds": lo, "p_occ": probability(lo)}


def cell_extent(index: np.ndarray, resolution: float) -> tuple[np.ndarray, np.ndarray] | None:
    """World-frame (min corner, max corner) of the box of whole cells ``index`` (K, 3);
    None when there are none."""
    if len(index) == 0:
        return None
    lo, hi = cell_box(index)
    return lo * resolution, (hi + 1) * resolution


def check_cell_index(index: Any) -> np.ndarray:
    """``index`` as an integer (K, 3) array of cell indices; ValueError otherwise."""
    idx = np.asarray(index)
    if idx.ndim != 2 or idx.shape[1] != 3 or not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(f"index must be an integer (K, 3) array of cell indices, got {idx.dtype} {idx.shape}")
    return idx


def occupancy_of(
    points: Any,
    resolution: float,
    in_grid: Callable[[np.ndarray], np.ndarray],
    logodds_at: Callable[[np.ndarray], np.ndarray],
    return_known: bool = False,
) -> Any:
    """``NdtOmMap.occupancy``: the probability of the cells holding world ``points`` (N, 3),
    or of one point (3,), from ``logodds_at`` (cell indices -> log-odds) of the cells
    ``in_grid`` (cells -> mask); cells not finite, outside the grid or unknown read 0.5."""
    if np.ndim(points) == 1 and np.shape(points) == (3,):
        p, k = occupancy_of(np.reshape(points, (1, 3)), resolution, in_grid, logodds_at, return_known=True)
        return (float(p[0]), bool(k[0])) if return_known else float(p[0])
    pts = as_points(points)
    out = np.full(len(pts), 0.5)
    known = np.zeros(len(pts), bool)
    ok = np.isfinite(pts).all(axis=1)
    cells = np.zeros((len(pts), 3))
    cells[ok] = np.floor(pts[ok] / resolution)
    ok &= in_grid(cells)
    if ok.any():
        lo = logodds_at(cells[ok].astype(np.int64))
        out[ok] = probability(lo)
        known[ok] = lo != 0.0
    return (out, known) if return_known else out
