"""Independent float64 numpy references for the tests (no Taichi).

Ray traversal
-------------
:func:`ray_cells` is the reference a Taichi Amanatides–Woo DDA is tested against. It is
deliberately *not* a DDA: it does not step from cell to cell. It uses the definition

    visited(o, e, r) = { floor(p / r) : p on the closed segment [o, e] }

with half-open cells ``[k r, (k + 1) r)`` per axis, listed in order along the segment, and
evaluates it like this:

1. Origin cell ``k0 = np.floor(o / r)`` and endpoint cell ``k1 = np.floor(e / r)`` (float64,
   exactly that expression).
2. Per axis ``a`` with ``e_a != o_a``, the grid planes ``j r`` the segment crosses are those
   between the two end cells: ``j = k0_a + 1 .. k1_a`` going ``+``, ``j = k1_a + 1 .. k0_a``
   going ``-``. Each gives a parameter ``t = (j r - o_a) / (e_a - o_a)``; those in (0, 1)
   are kept, then all axes' parameters are sorted and made unique (equal ``t`` on several
   axes = the segment passes through an edge or a corner).
3. The cell is sampled at ``t = 0`` (which is ``k0``), at the midpoint of every interval
   ``[0, t1], [t1, t2], ..., [tn, 1]``, at every crossing ``t_i``, and at ``t = 1`` (which is
   ``k1``), in order; consecutive duplicates are removed. At midpoints the cell is
   ``floor((o + t (e - o)) / r)``. At a crossing the coordinate of every axis crossing there is
   exactly the plane value ``j r``, whose cell index is ``j`` (the point lies on the low face
   of cell ``j``); the other axes use ``floor((o_b + t (e_b - o_b)) / r)``.

Ties (edges and corners). Under the floor semantics the single point where the segment
touches an edge or a corner belongs to the cell whose *low* faces meet there, and that cell is
in the visited set even though the segment only touches it at that one point. Examples
(``r = 1``, z fixed in cell 0):

- ``+x, -y`` through the corner ``(1, 1)``: from ``(0.5, 1.5)`` to ``(1.5, 0.5)`` visits
  ``(0,1,0), (1,1,0), (1,0,0)`` — ``(1,1,0)`` holds the corner point.
- ``+x, +y`` through ``(1, 1)``: ``(0,0,0), (1,1,0)`` — a direct diagonal step, because the
  corner point already lies in the next cell.
- ``-x, -y`` through ``(1, 1)``: ``(1,1,0), (0,0,0)`` — the corner lies in the origin cell.
- ``o = (0,0,0), e = (1,1,1), r = 0.25``: ``(0,0,0), (1,1,1), (2,2,2), (3,3,3), (4,4,4)`` —
  the last because ``e`` itself lies on the low corner of cell 4.

A ray along a cell face (a coordinate constant and exactly ``k r``) stays in cell ``k`` on
that axis. Ties only resolve as described when the ``t`` values of the tied axes compare
equal in float64 (e.g. dyadic coordinates and resolutions); at ulp-level near-ties the order
of the crossings is whatever float64 gives, as for any float DDA. Compare a DDA against this
reference on exact (dyadic) tie cases and on generic random rays.

Occupancy
---------
:func:`ray_pass_counts`, :func:`endpoint_counts` and :func:`eq12_logodds` give ``N_e``,
``N_p`` and the per-cell log-odds of ``docs/method.md`` section 3, cell by cell in Python
dicts keyed by ``(kx, ky, kz)`` integer tuples.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from ndtom_ti.evaluation.metrics import batch_ndt

# The NDT miss model's constants as the docs state them (docs/quality.md; ndtom_ti/map.py and
# kernels/ndt.py hold the code's). Stated here, not imported from the code under test: a
# changed constant (NDT_BACK_MISS 0.5 -> 0.7) must fail the tests that compare with this
# reference, not move the reference with it.
NDT_COV_FLOOR = 0.02  # "P + (0.02 trace(P)) I"
NDT_LINE = 0.5  # "middle eigenvalue l2 < 0.5 l3"
NDT_LINE_FLOOR = 1.0  # "add up to l3 on every axis"
NDT_LINE_POINTS = 4.0  # "min(1, 4 / n)"
NDT_SPARSE_SIGMA = 0.05  # "(5 cm)^2"
NDT_RESET = math.log(0.2 / 0.8)  # "l <= logit(0.2) = -1.39"
NDT_RESTART = 2.0  # "max(l, 2)"
NDT_RESTART_CLEAR = -1.0  # "max(l, -1)"
NDT_ERASED_NEIGHBOURS = 6  # "after 6 of its 26 neighbours' Gaussians were erased"
NDT_WIDE = 1e-9  # "P^-1 = 1e-9 I"
NDT_FRESH_FLOOR = 0.0  # "max(l, 0)"
NDT_BACK_MISS = 0.5  # "its misses count half"
ETA = 0.32  # MapConfig's eta (docs/sensor-model.md)


__all__ = [
    "ray_cells",
    "ray_pass_counts",
    "endpoint_counts",
    "batch_stats",
    "eq12_logodds",
]

Cell = tuple[int, int, int]


def ray_cells(o: np.ndarray, e: np.ndarray, r: float) -> np.ndarray:
    """Cells visited by the closed segment ``[o, e]``, in order (see the module docstring).

    Parameters
    ----------
    o : (3,) array_like, segment origin (world metres, cast to float64).
    e : (3,) array_like, segment endpoint.
    r : cell side (metres, > 0).

    Returns
    -------
    (M, 3) int64, ``M >= 1``: first row ``floor(o / r)``, last row ``floor(e / r)``,
    consecutive rows distinct. A zero-length segment gives the single origin cell.
    """
    o = np.asarray(o, dtype=np.float64).reshape(3)
    e = np.asarray(e, dtype=np.float64).reshape(3)
    r = np.float64(r)
    if not (np.all(np.isfinite(o)) and np.all(np.isfinite(e))):
        raise ValueError("ray origin and endpoint must be finite")
    if not (np.isfinite(r) and r > 0):
        raise ValueError("resolution must be positive and finite")

    k0 = np.floor(o / r).astype(np.int64)
    k1 = np.floor(e / r).astype(np.int64)
    delta = e - o

    # Step 2: every plane crossing (t, axis, plane integer j).
    ts, axes, js = [], [], []
    for a in range(3):
        if delta[a] == 0.0 or k0[a] == k1[a]:
            continue
        if delta[a] > 0:
            j = np.arange(k0[a] + 1, k1[a] + 1, dtype=np.int64)
        else:
            j = np.arange(k1[a] + 1, k0[a] + 1, dtype=np.int64)
        t = (j.astype(np.float64) * r - o[a]) / delta[a]
        inside = (t > 0.0) & (t < 1.0)
        ts.append(t[inside])
        js.append(j[inside])
        axes.append(np.full(int(inside.sum()), a, dtype=np.int64))
    if ts:
        t_all = np.concatenate(ts)
        j_all = np.concatenate(js)
        ax_all = np.concatenate(axes)
    else:
        t_all = np.zeros(0)
        j_all = np.zeros(0, dtype=np.int64)
        ax_all = np.zeros(0, dtype=np.int64)
    t_cross, which = np.unique(t_all, return_inverse=True)  # sorted unique, (n,)
    n = t_cross.size

    # Step 3: sample parameters  mid_0, cross_1, mid_1, ..., cross_n, mid_n.
    bounds = np.concatenate(([0.0], t_cross, [1.0]))  # (n + 2,)
    mids = 0.5 * (bounds[:-1] + bounds[1:])  # (n + 1,)
    t_samp = np.empty(2 * n + 1)
    t_samp[0::2] = mids
    t_samp[1::2] = t_cross
    p = o[None, :] + t_samp[:, None] * delta[None, :]  # (2n + 1, 3)
    cells = np.floor(p / r).astype(np.int64)
    # Crossing samples: the crossing axes sit exactly on their plane j*r -> index j.
    cells[1 + 2 * which.reshape(-1), ax_all] = j_all

    seq = np.concatenate((k0[None, :], cells, k1[None, :]), axis=0)
    keep = np.ones(seq.shape[0], dtype=bool)
    keep[1:] = np.any(seq[1:] != seq[:-1], axis=1)
    return seq[keep]


def _as_hit_mask(hit_mask, n: int) -> np.ndarray:
    if hit_mask is None:
        return np.ones(n, dtype=bool)
    m = np.asarray(hit_mask, dtype=bool).reshape(-1)
    if m.size != n:
        raise ValueError(f"hit_mask has {m.size} entries for {n} endpoints")
    return m


def _count_rows(rows: list[np.ndarray]) -> dict[Cell, int]:
    rows = [x for x in rows if x.size]
    if not rows:
        return {}
    cells, counts = np.unique(np.concatenate(rows, axis=0), axis=0, return_counts=True)
    return {tuple(int(v) for v in c): int(k) for c, k in zip(cells, counts)}


def ray_pass_counts(
    o: np.ndarray, endpoints: np.ndarray, r: float, hit_mask: np.ndarray | None = None
) -> dict[Cell, int]:
    """``N_e``: per cell, the number of rays passing through it without ending there.

    For each ray ``o -> endpoints[i]`` every cell of :func:`ray_cells` is counted once, except
    the endpoint cell when the ray is a hit (``hit_mask[i]`` True); a non-hit (free-space) ray
    counts its endpoint cell too. A hit ray whose endpoint lies in the origin cell counts
    nothing.

    Parameters
    ----------
    o : (3,) sensor origin.
    endpoints : (N, 3) ray endpoints.
    r : cell side.
    hit_mask : (N,) bool, or None for all hits.

    Returns
    -------
    dict ``(kx, ky, kz) -> count`` (only cells with count > 0).
    """
    pts = np.asarray(endpoints, dtype=np.float64).reshape(-1, 3)
    hit = _as_hit_mask(hit_mask, pts.shape[0])
    rows = []
    for i in range(pts.shape[0]):
        c = ray_cells(o, pts[i], r)
        rows.append(c[:-1] if hit[i] else c)
    return _count_rows(rows)


def endpoint_counts(endpoints: np.ndarray, r: float, hit_mask: np.ndarray | None = None) -> dict[Cell, int]:
    """``N_p``: per cell, the number of hit endpoints in it (``np.floor(x / r)``).

    Parameters
    ----------
    endpoints : (N, 3). r : cell side. hit_mask : (N,) bool, or None for all hits.

    Returns
    -------
    dict ``(kx, ky, kz) -> count``.
    """
    pts = np.asarray(endpoints, dtype=np.float64).reshape(-1, 3)
    hit = _as_hit_mask(hit_mask, pts.shape[0])
    k = np.floor(pts[hit] / np.float64(r)).astype(np.int64)
    return _count_rows([k])


def batch_stats(points: np.ndarray, r: float) -> dict:
    """Per-cell ``n``, ``mean``, ``cov`` of all points (every occupied cell, ``n >= 1``).

    Thin wrapper over :func:`ndtom_ti.evaluation.metrics.batch_ndt` with ``min_points=1``: dict with
    ``index`` (K, 3) int64 (lexicographic), ``n`` (K,), ``mean`` (K, 3), ``cov`` (K, 3, 3)
    (zero for ``n == 1``).
    """
    return batch_ndt(points, r, min_points=1)


def eq12_logodds(
    scans: Iterable[Sequence],
    r: float,
    p_o: float = 0.6,
    p_e: float = 0.49,
    l_min: float = -math.inf,
    l_max: float = math.inf,
) -> dict[Cell, float]:
    """Expected per-cell log-odds after a sequence of scans, ``docs/method.md`` section 3.

    Each scan is ``(origin, endpoints)`` or ``(origin, endpoints, hit_mask)`` (hit_mask None
    or omitted: all endpoints are hits; a non-hit is a free-space ray whose endpoint cell is
    traversed, not hit). Per scan, with ``N_p`` from :func:`endpoint_counts` and ``N_e`` from
    :func:`ray_pass_counts`, every touched cell (``N_p > 0`` or ``N_e > 0``) is updated once:

        l += N_p * log(p_o / (1 - p_o))   if N_p > 0
        l += N_e * log(p_e / (1 - p_e))   otherwise
        l  = clamp(l, l_min, l_max)

    Untouched cells start at ``l = 0``. Returns dict ``(kx, ky, kz) -> l`` (float64) for every
    cell ever touched.
    """
    lo = math.log(p_o / (1.0 - p_o))
    le = math.log(p_e / (1.0 - p_e))
    logodds: dict[Cell, float] = {}
    for scan in scans:
        origin, endpoints = scan[0], scan[1]
        hit_mask = scan[2] if len(scan) > 2 else None
        n_p = endpoint_counts(endpoints, r, hit_mask)
        n_e = ray_pass_counts(origin, endpoints, r, hit_mask)
        for cell in set(n_p) | set(n_e):
            npk = n_p.get(cell, 0)
            inc = npk * lo if npk > 0 else n_e.get(cell, 0) * le
            logodds[cell] = min(max(logodds.get(cell, 0.0) + inc, l_min), l_max)
    return logodds


def ndt_cov_floor(cov, n: int, floor: float, line: float, line_floor: float, line_points: float) -> float:
    """Variance the map adds on every axis of the covariance of a Gaussian of ``n`` points
    before inverting it: ``floor * trace``, plus ``line_floor * min(1, line_points / n) *
    max(0, line * l3 - l2) / line`` for a line-like one (eigenvalues ``l1 <= l2 <= l3``)."""
    C = np.asarray(cov, np.float64)
    l1, l2, l3 = np.linalg.eigvalsh(C)
    widen = line_floor * min(1.0, line_points / n) * max(0.0, line * l3 - l2) / line
    return floor * np.trace(C) + widen + 1e-12


def ndt_miss_term(o, z, hit: bool, mean, cov, eta: float, sigma_s: float, n: int, floors=None) -> float:
    """Log-odds change of the NDT miss model (Saarinen et al., IJRR 2013, eqs. 22-24) for
    one ray ``o -> z`` passing a cell whose Gaussian is ``(mean, cov)``.

    ``x_ML`` is the point of the ray of highest likelihood under the Gaussian, kept on the
    segment ``[o, z]``; ``p = 0.5 - eta p(x_ML | N) (1 - p(x_ML | z))`` with
    ``p(x_ML | z) = 0`` for a ray without a hit; the change is ``log(p / (1 - p))``. The
    covariance (of ``n`` points) gets :func:`ndt_cov_floor` added on its diagonal first (the
    map's choice; ``floors``: (floor, line, line_floor, line_points), default the map's
    constants).
    """
    if floors is None:
        floors = (NDT_COV_FLOOR, NDT_LINE, NDT_LINE_FLOOR, NDT_LINE_POINTS)
    o, z, mu = (np.asarray(v, np.float64) for v in (o, z, mean))
    C = np.asarray(cov, np.float64) + ndt_cov_floor(cov, n, *floors) * np.eye(3)
    inv = np.linalg.inv(C)
    d = z - o
    length = float(np.linalg.norm(d))
    u = d / length
    a = inv @ u
    t = min(max(float(a @ (mu - o)) / float(a @ u), 0.0), length)
    x = o + t * u
    e = x - mu
    p_n = math.exp(-0.5 * float(e @ inv @ e))
    p_z = math.exp(-0.5 * float((x - z) @ (x - z)) / sigma_s**2) if hit else 0.0
    p = 0.5 - eta * p_n * (1.0 - p_z)
    return math.log(p / (1.0 - p))


def ndt_om_logodds(
    scans: Iterable[Sequence],
    r: float,
    *,
    miss_model: str = "ndt",
    p_o: float = 0.6,
    p_e: float = 0.49,
    l_min: float = -2.0,
    l_max: float = 2.0,
    min_points: int = 3,
    eta: float = 0.2,
    sigma_s: float = 0.05,
    sparse_sigma: float | None = None,
    reset: float | None = None,
    restart: float | None = None,
    restart_clear: float | None = None,
    erased_neighbours: int | None = None,
    near_cells: int | None = None,
    fresh_floor: float | None = None,
    back_miss: float | None = None,
) -> tuple[dict[Cell, float], dict[Cell, np.ndarray]]:
    """Per-cell log-odds and Gaussian points of an NDT-OM after a sequence of scans, in
    float64, ray by ray and cell by cell (no grouping, no fixed point).

    Each scan is ``(origin, endpoints)`` or ``(origin, endpoints, hit_mask)`` (world
    frame). Per scan, every touched cell is updated once, from the state at the scan's
    start: a cell with hits takes ``N_p log(p_o / (1 - p_o))``; otherwise, with
    ``miss_model="ndt"`` and points, the sum of :func:`ndt_miss_term` over the rays
    passing it (mean and covariance of its points; with fewer than ``min_points`` points
    ``sparse_sigma^2`` added on every axis, default the map's NDT_SPARSE_SIGMA);
    otherwise ``N_e log(p_e / (1 - p_e))``; then the clamp. A free update that leaves
    ``l <= 0`` erases the cell's Gaussian (the NDT miss model's: ``l <= reset``, default
    the kernels' NDT_RESET). With ``miss_model="ndt"`` a hit cell starts from ``max(l, restart)``
    (default the kernels' NDT_RESTART), or from ``max(l, restart_clear)`` (NDT_RESTART_CLEAR)
    for its first points (it holds none) if ``l <= l_min``: such a cell is *fresh* until its
    log-odds reaches ``l_max``, and its next hits start from ``max(l, fresh_floor)``
    (NDT_FRESH_FLOOR) instead. A hit on a cell that is not fresh and holds points at
    ``l <= 0`` makes its Gaussian *back*: the sum of the rays' terms on it is taken times
    ``back_miss`` (NDT_BACK_MISS), and rays never erase its points.
    The scan's hits then join their cells' Gaussians. With ``miss_model="ndt"`` each cell
    that holds points then counts the Gaussians of its 26 neighbours that the scan's rays
    erased (a cell with points of this scan starts again from zero first); from
    ``erased_neighbours`` (default the kernels' NDT_ERASED_NEIGHBOURS) until its next
    points the rays test it with covariance ``I / NDT_WIDE`` (every ray as if through
    its mean). A hit ray tests no Gaussian in the cells within ``near_cells`` (L1, default
    ``MapConfig(sigma_s=sigma_s).near_cells_at(r)``) of its endpoint's cell. Returns
    ``(logodds, points)``: the points of each cell's current Gaussian.
    """
    if sparse_sigma is None:
        sparse_sigma = NDT_SPARSE_SIGMA
    if reset is None:
        reset = NDT_RESET
    if restart is None:
        restart = NDT_RESTART
    if restart_clear is None:
        restart_clear = NDT_RESTART_CLEAR
    if erased_neighbours is None:
        erased_neighbours = NDT_ERASED_NEIGHBOURS
    fresh_floor = NDT_FRESH_FLOOR if fresh_floor is None else fresh_floor
    back_miss = NDT_BACK_MISS if back_miss is None else back_miss
    fresh: set[Cell] = set()
    back: set[Cell] = set()

    around = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) != (0, 0, 0)]
    nbr: dict[Cell, int] = {}
    if near_cells is None:
        from ndtom_ti import MapConfig

        near_cells = MapConfig(sigma_s=sigma_s).near_cells_at(r)
    ndt = miss_model == "ndt"
    lo_hit = math.log(p_o / (1.0 - p_o))
    lo_free = math.log(p_e / (1.0 - p_e))
    logodds: dict[Cell, float] = {}
    points: dict[Cell, list] = {}
    for scan in scans:
        origin = np.asarray(scan[0], np.float64)
        ends = np.asarray(scan[1], np.float64).reshape(-1, 3)
        hit = _as_hit_mask(scan[2] if len(scan) > 2 else None, len(ends))
        n_p = endpoint_counts(ends, r, hit)
        gauss = {}
        for c, pts in points.items():
            if len(pts) >= (1 if ndt else min_points):
                P = np.asarray(pts)
                d = P - P.mean(axis=0)
                C = d.T @ d / max(len(P) - 1, 1)
                if len(P) < min_points:
                    C = C + sparse_sigma**2 * np.eye(3)
                gauss[c] = (P.mean(axis=0), C, len(P), nbr.get(c, 0) >= erased_neighbours)
        passes: dict[Cell, list] = {}
        erased: list[Cell] = []
        for i in range(len(ends)):
            cells = ray_cells(origin, ends[i], r)
            near = np.abs(cells - cells[-1]).sum(axis=1) <= near_cells if hit[i] else np.zeros(len(cells), bool)
            for c, skip in zip(map(tuple, (cells[:-1] if hit[i] else cells).tolist()), near.tolist()):
                passes.setdefault(c, []).append(-1 if skip else i)
        for c in set(n_p) | set(passes):
            erase_at = 0.0
            if n_p.get(c, 0) > 0:
                inc = n_p[c] * lo_hit
                if ndt:
                    l0 = logodds.get(c, 0.0)
                    if c not in points:  # its first points (a new record: no state)
                        fresh.discard(c)
                        back.discard(c)
                    if c not in points and l0 <= l_min:
                        logodds[c] = max(l0, restart_clear)
                        fresh.add(c)
                    elif c in fresh:
                        logodds[c] = max(l0, fresh_floor)
                    else:
                        if c in points and l0 <= 0.0:
                            back.add(c)
                        logodds[c] = max(l0, restart)
                    if min(max(logodds[c] + inc, l_min), l_max) >= l_max:
                        fresh.discard(c)
            elif ndt and c in gauss:
                mu, C, n, wide = gauss[c]
                if wide:
                    C, floors = np.eye(3) / NDT_WIDE, (0.0, 1.0, 0.0, 1.0)
                else:
                    floors = None
                inc = sum(
                    ndt_miss_term(origin, ends[i], bool(hit[i]), mu, C, eta, sigma_s, n, floors)
                    for i in passes[c]
                    if i >= 0
                )
                erase_at = reset
                if c in back:
                    inc *= back_miss
                    erase_at = -math.inf
            else:
                inc = len(passes[c]) * lo_free
            logodds[c] = min(max(logodds.get(c, 0.0) + inc, l_min), l_max)
            if n_p.get(c, 0) == 0 and logodds[c] <= erase_at and points.pop(c, None) is not None and ndt:
                erased.append(c)
        for x in ends[hit]:
            points.setdefault(tuple(np.floor(x / r).astype(np.int64).tolist()), []).append(x)
        for c in n_p:
            nbr.pop(c, None)
        for c in erased:
            for d in around:
                b = (c[0] + d[0], c[1] + d[1], c[2] + d[2])
                if b in points:
                    nbr[b] = nbr.get(b, 0) + 1
    return logodds, {c: np.asarray(v) for c, v in points.items()}
