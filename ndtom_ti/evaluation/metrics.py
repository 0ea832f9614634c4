"""Batch NDT maps and the paper's map-comparison score (numpy, float64, no Taichi).

This module is the *ground truth* side of the project (the paper's eqs. (1)-(3), sec. IV-A):

- :func:`batch_ndt` is the batch NDT map of paper eq. (1): every point of every scan binned
  into cells ``k = floor(x / r)`` and each cell's sample mean and covariance computed at once.
  The recursive (RCU) map built scan by scan must equal it to float tolerance.
- :func:`l2_similarity` and :func:`mean_l2_score` are the paper's evaluation (section IV-A):
  the L2 similarity of two Gaussians and the mean L2 score of a test map against a reference.
- :func:`regularize_cov` is the eigenvalue floor applied to covariances before scoring.

Everything is vectorised over cells (no per-cell Python loops) and runs in float64.

Map dictionaries
----------------
A *map* here is a plain dict of arrays, the format :func:`batch_ndt` returns and the format
of the map's ``gaussians()`` export:

``index``  (K, 3) int64 — integer cell indices ``k``,
``mean``   (K, 3) float — absolute (world-frame) sample means,
``cov``    (K, 3, 3) float — sample covariances (divided by ``n - 1``),
``n``      (K,) int64 — point counts (optional for scoring).
"""

from __future__ import annotations

import numpy as np

from ..config import check_resolution

__all__ = [
    "batch_ndt",
    "cell_index",
    "l2_similarity",
    "mean_l2_score",
    "regularize_cov",
]

#: Isotropic variance floor (m^2) used by :func:`regularize_cov` for a covariance whose
#: eigenvalues are all zero (e.g. a single point, or identical points): 1e-12 m^2, i.e. a
#: standard deviation of one micrometre. Such a "point mass" then only matches a Gaussian
#: with (nearly) the same mean and the same tiny covariance.
ZERO_COV_FLOOR = 1e-12


def cell_index(points: np.ndarray, resolution: float) -> np.ndarray:
    """Integer cell index of each point: ``np.floor(points / resolution)`` in float64.

    Parameters
    ----------
    points : (N, 3) array_like, metres (cast to float64).
    resolution : cell side ``r`` in metres.

    Returns
    -------
    (N, 3) int64. This is exactly ``np.floor(points / resolution)`` evaluated in float64, so
    other code (kernels, references) can reproduce the binning bit for bit.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return np.floor(pts / np.float64(resolution)).astype(np.int64)


def _empty_map() -> dict:
    return {
        "index": np.zeros((0, 3), dtype=np.int64),
        "mean": np.zeros((0, 3), dtype=np.float64),
        "cov": np.zeros((0, 3, 3), dtype=np.float64),
        "n": np.zeros((0,), dtype=np.int64),
    }


def batch_ndt(points: np.ndarray, resolution: float, min_points: int = 3) -> dict:
    """Batch NDT map of paper eq. (1): per-cell sample mean and covariance of all points.

    Each point ``x`` goes to cell ``k = floor(x / r)`` computed as
    ``np.floor(points / resolution)`` in float64 (see :func:`cell_index`). For every cell with
    ``n >= min_points`` points, the mean and the *sample* covariance (scatter divided by
    ``n - 1``) are returned. Sums are taken relative to the cell centre ``c_k = (k + 0.5) r``
    and the covariance uses two passes (mean first, then the scatter of the deviations from
    it), so the result stays accurate far from the origin.

    Points with a NaN or infinite coordinate are dropped. A cell with ``n == 1`` (only
    possible with ``min_points <= 1``) gets a zero covariance.

    Parameters
    ----------
    points : (N, 3) array_like, world-frame metres (cast to float64).
    resolution : cell side ``r`` (metres, > 0).
    min_points : smallest point count for a cell to be returned (default 3, as the paper).

    Returns
    -------
    dict with
        ``index`` (K, 3) int64, rows sorted lexicographically (x, then y, then z);
        ``mean``  (K, 3) float64, absolute means;
        ``cov``   (K, 3, 3) float64, symmetric sample covariances;
        ``n``     (K,) int64, point counts.
    """
    r = np.float64(check_resolution(resolution))
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if pts.shape[0] == 0:
        return _empty_map()

    k = np.floor(pts / r).astype(np.int64)  # (N, 3)

    # Group by cell: sort rows lexicographically (primary key x), find run starts.
    order = np.lexsort((k[:, 2], k[:, 1], k[:, 0]))
    k = k[order]
    pts = pts[order]
    new_run = np.empty(k.shape[0], dtype=bool)
    new_run[0] = True
    np.any(k[1:] != k[:-1], axis=1, out=new_run[1:])
    starts = np.flatnonzero(new_run)  # (K,)
    counts = np.diff(np.append(starts, k.shape[0]))  # (K,)
    group = np.cumsum(new_run) - 1  # (N,) group id of each sorted point

    index = k[starts]  # (K, 3)
    centre = (index + 0.5) * r  # (K, 3)

    # Pass 1: mean relative to the cell centre.
    q = pts - centre[group]  # (N, 3), |q| <= r (roughly)
    mean_q = np.add.reduceat(q, starts, axis=0) / counts[:, None]  # (K, 3)

    # Pass 2: scatter of the deviations from the mean.
    d = q - mean_q[group]  # (N, 3)
    outer = (d[:, :, None] * d[:, None, :]).reshape(-1, 9)  # (N, 9)
    scatter = np.add.reduceat(outer, starts, axis=0).reshape(-1, 3, 3)  # (K, 3, 3)
    scatter = 0.5 * (scatter + np.swapaxes(scatter, 1, 2))

    denom = np.maximum(counts - 1, 1).astype(np.float64)
    cov = scatter / denom[:, None, None]
    cov[counts < 2] = 0.0

    keep = counts >= int(min_points)
    return {
        "index": np.ascontiguousarray(index[keep]),
        "mean": centre[keep] + mean_q[keep],
        "cov": cov[keep],
        "n": counts[keep].astype(np.int64),
    }


def regularize_cov(cov: np.ndarray, ratio: float = 1e-3) -> np.ndarray:
    """Raise small eigenvalues of covariances to ``ratio * max eigenvalue``.

    The paper's (and the authors' code's) conditioning before scoring: for each matrix, every
    eigenvalue below ``ratio * lambda_max`` is set to ``ratio * lambda_max`` and the matrix is
    rebuilt as ``V diag(lambda) V^T``. Matrices that need no change are returned bit for bit
    unchanged (only the symmetrised copy of the input).

    Degenerate case: when ``lambda_max <= 0`` (a zero covariance, e.g. a cell with one point or
    identical points, or a negative semi-definite round-off result) the floor is the tiny
    isotropic variance :data:`ZERO_COV_FLOOR` (1e-12 m^2), so that the result is always
    positive definite and :func:`l2_similarity` is defined.

    Parameters
    ----------
    cov : (..., 3, 3) array_like, symmetric (a single (3, 3) or a batch (K, 3, 3)).
    ratio : eigenvalue floor relative to the largest eigenvalue (default 1e-3).

    Returns
    -------
    (..., 3, 3) float64, symmetric positive definite.
    """
    c = np.asarray(cov, dtype=np.float64)
    if c.shape[-2:] != (3, 3):
        raise ValueError(f"cov must have shape (..., 3, 3), got {c.shape}")
    shape = c.shape
    c = c.reshape(-1, 3, 3)
    c = 0.5 * (c + np.swapaxes(c, 1, 2))
    out = c.copy()
    if c.shape[0] == 0:
        return out.reshape(shape)

    lam, vec = np.linalg.eigh(c)  # ascending eigenvalues, (K, 3), (K, 3, 3)
    lam_max = lam[:, -1]
    floor = np.where(lam_max > 0, ratio * lam_max, ZERO_COV_FLOOR)  # (K,)
    fix = np.any(lam < floor[:, None], axis=1)  # (K,)
    if np.any(fix):
        lam_f = np.maximum(lam[fix], floor[fix, None])
        v = vec[fix]
        rebuilt = np.einsum("kij,kj,klj->kil", v, lam_f, v)
        out[fix] = 0.5 * (rebuilt + np.swapaxes(rebuilt, 1, 2))
    return out.reshape(shape)


def l2_similarity(mu1: np.ndarray, C1: np.ndarray, mu2: np.ndarray, C2: np.ndarray) -> np.ndarray:
    """L2 similarity of Gaussian pairs, ``sim = 2 <f1, f2> / (||f1||^2 + ||f2||^2)``.

    With ``f_i = N(mu_i, C_i)`` in 3D (the paper's sec. IV-A):

        <f1, f2>  = N(mu1 - mu2; 0, C1 + C2)
        ||f||^2   = (4 pi)^(-3/2) det(C)^(-1/2)

    The common factor ``(2 pi)^(-3/2)`` cancels, leaving

        sim = 2 exp(a - m / 2) / (exp(b1) + exp(b2)),
        a   = -1/2 log det(C1 + C2),   b_i = -1/2 log det(2 C_i),
        m   = d^T (C1 + C2)^(-1) d,    d = mu1 - mu2,

    evaluated in log space (log-determinants and ``m`` from the eigen-decompositions of the
    symmetric matrices, then ``logaddexp``), so tiny covariances (det ~ 1e-600) neither
    overflow nor underflow. ``sim`` is 1 for identical Gaussians, symmetric, in
    [0, 1] (Cauchy–Schwarz), and decreases to 0 as the means part.

    Covariances should be positive definite (see :func:`regularize_cov`; the covariance of
    coplanar points is singular and round-off can make it slightly indefinite). If one of
    ``C1``, ``C2`` is singular (smallest eigenvalue exactly 0, the other PD) the limit
    ``sim = 0`` is returned; if either has a negative eigenvalue, or ``C1 + C2`` is not
    positive definite, the result is NaN. Inputs are assumed symmetric.

    Parameters
    ----------
    mu1, mu2 : (K, 3) or (3,) array_like.
    C1, C2 : (K, 3, 3) or (3, 3) array_like.

    Returns
    -------
    (K,) float64 (shape () for unbatched inputs).
    """
    mu1 = np.asarray(mu1, dtype=np.float64)
    mu2 = np.asarray(mu2, dtype=np.float64)
    C1 = np.asarray(C1, dtype=np.float64)
    C2 = np.asarray(C2, dtype=np.float64)
    scalar = mu1.ndim == 1 and mu2.ndim == 1 and C1.ndim == 2 and C2.ndim == 2
    mu1, mu2 = np.atleast_2d(mu1), np.atleast_2d(mu2)
    C1 = C1.reshape(-1, 3, 3)
    C2 = C2.reshape(-1, 3, 3)
    mu1, mu2, C1, C2 = _broadcast(mu1, mu2, C1, C2)

    d = mu1 - mu2  # (K, 3)
    Cs = C1 + C2  # (K, 3, 3)
    with np.errstate(all="ignore"):
        # Log-determinants from eigenvalues (symmetric, batched, never raise), by the same
        # routine for all three matrices, so identical inputs (C + C == 2 C bit for bit) give
        # sim = 1 up to the last bit. Mahalanobis term from the eigen-decomposition of Cs.
        a = _neg_half_logdet(Cs)
        b1 = _neg_half_logdet(2.0 * C1)
        b2 = _neg_half_logdet(2.0 * C2)
        lam_s, vec_s = np.linalg.eigh(Cs)  # (K, 3), (K, 3, 3)
        ok = (lam_s[:, 0] > 0) & np.isfinite(a)  # C1 + C2 positive definite
        y = np.einsum("kij,ki->kj", vec_s, d)  # V^T d
        m = np.sum(y * y / np.where(ok[:, None], lam_s, 1.0), axis=1)  # d^T Cs^-1 d
        log_sim = np.log(2.0) + a - 0.5 * m - np.logaddexp(b1, b2)
        sim = np.clip(np.exp(log_sim), 0.0, 1.0)
        valid = ok & ~np.isnan(b1) & ~np.isnan(b2)
        # A singular C_i (b_i = +inf, ||f_i|| = inf) gives the limit sim = 0.
        sim = np.where(valid, np.where(np.isinf(b1) | np.isinf(b2), 0.0, sim), np.nan)
    return sim[0] if scalar else sim


def _neg_half_logdet(C: np.ndarray) -> np.ndarray:
    """-1/2 log det C for symmetric (K, 3, 3) C: +inf if C is singular positive
    semi-definite (smallest eigenvalue exactly 0), NaN if it has a negative eigenvalue."""
    lam = np.linalg.eigvalsh(C)  # (K, 3) ascending
    with np.errstate(divide="ignore"):
        out = -0.5 * np.sum(np.log(np.maximum(lam, 0.0)), axis=1)
    return np.where(lam[:, 0] < 0, np.nan, out)


def _broadcast(mu1, mu2, C1, C2):
    """Broadcast a single Gaussian against a batch; all outputs get the same leading K."""
    K = max(mu1.shape[0], mu2.shape[0], C1.shape[0], C2.shape[0])
    out = []
    for arr in (mu1, mu2, C1, C2):
        if arr.shape[0] not in (1, K):
            raise ValueError("batched inputs must have the same leading dimension")
        out.append(np.broadcast_to(arr, (K,) + arr.shape[1:]))
    return out


def _row_keys(index: np.ndarray) -> np.ndarray:
    """(K, 3) int64 -> (K,) structured array, so rows can be matched with set routines."""
    idx = np.ascontiguousarray(np.asarray(index, dtype=np.int64).reshape(-1, 3))
    return idx.view([("x", np.int64), ("y", np.int64), ("z", np.int64)]).reshape(-1)


def mean_l2_score(test: dict, reference: dict, regularize: bool = True) -> float:
    """Mean L2 score of a test map against a reference map (paper section IV-A).

    ``sum over cells holding a Gaussian in both maps of l2_similarity / number of Gaussians in
    the reference``. Cells are matched by their integer index. Cells only in ``test`` add
    nothing; cells only in ``reference`` count as similarity 0. Returns 0.0 for an empty
    reference.

    Parameters
    ----------
    test, reference : map dicts with ``index`` (K, 3) int, ``mean`` (K, 3), ``cov`` (K, 3, 3)
        — as returned by :func:`batch_ndt` or the map's ``gaussians()`` export. Indices must
        be unique within a map.
    regularize : apply :func:`regularize_cov` (ratio 1e-3) to both maps' covariances first
        (default True, as the paper and the authors' code).

    Returns
    -------
    float in [0, 1].
    """
    n_ref = int(np.asarray(reference["index"]).reshape(-1, 3).shape[0])
    if n_ref == 0:
        return 0.0
    n_test = int(np.asarray(test["index"]).reshape(-1, 3).shape[0])
    if n_test == 0:
        return 0.0
    kt = _row_keys(test["index"])
    kr = _row_keys(reference["index"])
    _, it, ir = np.intersect1d(kt, kr, assume_unique=True, return_indices=True)
    if it.size == 0:
        return 0.0
    mt = np.asarray(test["mean"], dtype=np.float64).reshape(-1, 3)[it]
    mr = np.asarray(reference["mean"], dtype=np.float64).reshape(-1, 3)[ir]
    ct = np.asarray(test["cov"], dtype=np.float64).reshape(-1, 3, 3)[it]
    cr = np.asarray(reference["cov"], dtype=np.float64).reshape(-1, 3, 3)[ir]
    if regularize:
        ct = regularize_cov(ct)
        cr = regularize_cov(cr)
    sim = l2_similarity(mt, ct, mr, cr)
    return float(np.sum(sim) / n_ref)
