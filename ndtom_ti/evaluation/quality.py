"""Map quality in dynamic scenes against exact ground truth (docs/quality.md).

Scenes come as :class:`LabelledScan` sequences: world points with a label saying which were
returns of moving objects, the sensor origin, and the boxes of the moving objects present
at that scan. A simulator (e.g. ``shared/tools/simworld.py``, read by
``benchmarks/quality.py``) provides them; nothing here needs it.

Metrics (cells ``floor(x / resolution)``):

- **ghosts**: of the cells that got >= 3 points of moving objects over the run, that are
  free at the end (the cell grown by ``margin`` touches no box, static or moving, present
  at the last scan),
  and that a later scan than their last moving-object point *observed* (a ray passed
  them, none ended there), the share where the map still reports an occupied Gaussian
  (NDT-OM: N >= min_points and p > 0.5; OctoMap: p > 0.5).
- **static kept**: of the cells of the batch NDT (eq. 1, N >= 3) of the static points of
  all scans, the share where the map reports an occupied Gaussian (OctoMap: p > 0.5).
- **conflicting** (paper Fig. 4b, on a scene without moving objects): cells holding a
  Gaussian in Recursive NDT but none in NDT-OM, as a share of NDT-OM's Gaussians.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..cellkeys import group, isin_rows, pack, unpack
from ..config import MapConfig
from ..map import NdtOmMap
from .metrics import batch_ndt

MIN_DYNAMIC_POINTS = 3


@dataclass
class LabelledScan:
    """One scan of a scene with ground truth, in the world frame."""

    points: np.ndarray  # (N, 3) world points (returns only)
    dynamic: np.ndarray  # (N,) bool: the point is a return of a moving object
    origin: np.ndarray  # (3,) sensor origin
    T_world_sensor: np.ndarray  # (4, 4)
    dyn_lo: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (B, 3) moving boxes present
    dyn_hi: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


@dataclass
class GhostCandidates:
    cells: np.ndarray  # (K, 3) int64: free at the end, >= 3 moving-object points
    last_hit: np.ndarray  # (K,) scan of each cell's last moving-object point
    observed: np.ndarray | None = None  # (K,) bool: a later scan's ray passed the cell


def ghost_candidates(
    scans: Sequence[LabelledScan],
    resolution: float,
    margin: float,
    static_boxes: tuple[np.ndarray, np.ndarray] | None = None,
) -> GhostCandidates:
    """Cells that moving objects left: >= 3 of their points over the run, and free at the
    end: grown by ``margin``, they touch no box present at the last scan (its moving
    boxes, and the static ones: ``static_boxes`` = (lo, hi), each (B, 3))."""
    cells, last = [], []
    for s, sc in enumerate(scans):
        c = np.floor(sc.points[sc.dynamic] / resolution).astype(np.int64)
        cells.append(c)
        last.append(np.full(len(c), s))
    if not cells or not sum(len(c) for c in cells):
        return GhostCandidates(np.zeros((0, 3), np.int64), np.zeros(0, np.int64))
    keys, klo, kspan = pack(np.concatenate(cells))
    uniq, _, _, inv = group(keys)
    counts = np.bincount(inv, minlength=len(uniq))
    last_hit = np.zeros(len(uniq), np.int64)
    np.maximum.at(last_hit, inv, np.concatenate(last))
    keep = counts >= MIN_DYNAMIC_POINTS
    cells, last_hit = unpack(uniq[keep], klo, kspan), last_hit[keep]
    lo = cells * resolution - margin
    hi = (cells + 1) * resolution + margin
    end = scans[-1]
    blos, bhis = [end.dyn_lo], [end.dyn_hi]
    if static_boxes is not None:
        blos.append(static_boxes[0])
        bhis.append(static_boxes[1])
    free = np.ones(len(cells), bool)
    for blo, bhi in zip(np.concatenate(blos), np.concatenate(bhis)):
        free &= ~((lo < bhi) & (hi > blo)).all(axis=1)
    return GhostCandidates(cells[free], last_hit[free])


def mark_observed(cand: GhostCandidates, scans: Sequence[LabelledScan], resolution: float) -> GhostCandidates:
    """Which candidates a scan after their last moving-object point observed: one of its
    rays passed the cell and none ended there. A probe map of the paper's eq. (12) with no
    clamps tells: a cell's log-odds falls in exactly such a scan."""
    cand.observed = np.zeros(len(cand.cells), bool)
    if len(cand.cells) == 0:
        return cand
    # Clamps far out, where f32 still resolves a ray's 0.04.
    with NdtOmMap(resolution, config=MapConfig(miss_model="paper", logodds_min=-1e5, logodds_max=1e5)) as probe:
        before = np.zeros(len(cand.cells))
        for s, sc in enumerate(scans):
            T = sc.T_world_sensor
            probe.insert_scan((sc.points - T[:3, 3]) @ T[:3, :3], T)
            after = probe.logodds_at(cand.cells)
            cand.observed |= (after < before) & (s > cand.last_hit)
            before = after
    return cand


def static_reference(scans: Sequence[LabelledScan], resolution: float, min_points: int = 3) -> np.ndarray:
    """Cells of the batch NDT (eq. 1) of all static points, N >= min_points."""
    pts = np.concatenate([sc.points[~sc.dynamic] for sc in scans])
    return batch_ndt(pts, resolution, min_points=min_points)["index"]


@dataclass
class Quality:
    ghosts: float  # share of observed left cells still occupied
    ghost_cells: int  # observed left cells (the denominator)
    ghosts_left: np.ndarray  # (G, 3) those still occupied
    static_kept: float
    static_cells: int


def score(
    occupied: Callable[[np.ndarray], np.ndarray],
    cand: GhostCandidates,
    static_cells: np.ndarray,
) -> Quality:
    """Quality of a map given ``occupied(cells) -> bool`` (an occupied Gaussian for NDT-OM,
    p > 0.5 for OctoMap)."""
    obs = cand.cells[cand.observed] if cand.observed is not None else cand.cells
    occ = occupied(obs) if len(obs) else np.zeros(0, bool)
    kept = occupied(static_cells) if len(static_cells) else np.zeros(0, bool)
    return Quality(
        ghosts=float(occ.mean()) if len(obs) else float("nan"),
        ghost_cells=len(obs),
        ghosts_left=obs[occ],
        static_kept=float(kept.mean()) if len(kept) else float("nan"),
        static_cells=len(static_cells),
    )


def ndtom_occupied(m: NdtOmMap) -> Callable[[np.ndarray], np.ndarray]:
    """``occupied(cells)`` of an NDT-OM: an occupied Gaussian (N >= min_points, p > 0.5)."""
    index = m.gaussians()["index"]
    return lambda cells: isin_rows(cells, index)


def octree_occupied(tree, resolution: float) -> Callable[[np.ndarray], np.ndarray]:
    """``occupied(cells)`` of a pyoctomap OcTree of the same resolution: p > 0.5."""

    def occupied(cells: np.ndarray) -> np.ndarray:
        out = np.zeros(len(cells), bool)
        for i, c in enumerate((np.asarray(cells, np.float64) + 0.5) * resolution):
            node = tree.search(c)
            out[i] = node is not None and node.getOccupancy() > 0.5
        return out

    return occupied


def conflicting(rcu: NdtOmMap, ndtom: NdtOmMap) -> tuple[int, float]:
    """Cells with a Gaussian in Recursive NDT but none in NDT-OM (paper Fig. 4b): their
    number, and their share of NDT-OM's Gaussians."""
    a = rcu.gaussians(min_probability=0.0)["index"]
    b = ndtom.gaussians()["index"]
    n = int((~isin_rows(a, b)).sum())
    return n, n / max(len(b), 1)
