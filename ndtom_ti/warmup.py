"""Compile every kernel variant a map's updates can need before its first scan returns.

Taichi compiles a kernel at its first call with a given argument signature. An update
picks among several variants scan by scan (16- or 32-bit ray counts, row-flagged or not,
the dense block or the tree, float32 or float64 points, each miss model, one pass or batches), so without this
a scan that first needs one stalls for a second or more in the middle of a run (a real
Livox recording: 1.3 s at its first scan of fewer than 65,535 points). ``warm_up`` runs
tiny scans through each path on a scratch map of the same storage and model; with the
offline cache (on by default) later processes load them instead of compiling.
"""

from __future__ import annotations

import numpy as np

_DONE: set = set()


def _scans(res: float) -> list[np.ndarray]:
    # Rays to clusters of 4 points per cell on a 3-cell-radius shell: cells get Gaussians
    # (>= 3 points) and later rays pass cells holding them.
    rng = np.random.default_rng(0)
    d = rng.normal(size=(48, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    centres = np.floor(d * 3.0) * res + 0.5 * res
    pts = np.repeat(centres, 4, axis=0) + rng.uniform(-0.3, 0.3, size=(192, 3)) * res
    far = d * 6.0 * res  # through the shell to beyond it
    return [np.concatenate([pts, far]), np.concatenate([far, pts])]


def warm_up(m) -> None:
    """Compile the update kernels ``m`` (an NdtOmMap) can need, once per process and per
    (miss model, occupancy). Skipped when no map slot is free for the scratch map or the
    memory budget has no room for it: those variants then compile as scans need them."""
    from .map import NdtOmMap
    from .runtime import NoFreeSlotError

    key = (id(m._st), m.config.miss_model, m.occupancy_enabled)
    if key in _DONE:
        return
    _DONE.add(key)
    try:
        w = NdtOmMap(0.5, config=m.config, occupancy=m.occupancy_enabled, layout=m.layout)
    except (NoFreeSlotError, MemoryError):
        return
    try:
        scans = _scans(w.resolution)
        T = np.eye(4)
        plan = w.plan
        modes = [
            {"row_flags": "always"},  # dense block, rows flagged
            {"row_flags": "never"},  # dense block, every row read
            {"block_cells": w.layout.leaf**3},  # a block that holds part of the scan, the tree the rest
            {"block_cells": 0},  # the tree only (also the batched path's kernel)
            {"block_cells": 0, "touched_rows": 1},  # touched list overflow
            {"one_pass": False},  # rays in batches, as under memory pressure (exact node counts)
        ]
        # Every variant, whatever the plan of the map that asked: the warm-up is once per
        # process, and later maps may have other plans.
        block_cells, u16_rays = plan.block_cells, plan.u16_rays
        for dtype in (np.float32, np.float64):
            for u16 in (u16_rays, 0):  # 16- and 32-bit ray counts
                for opts in modes:
                    for pts in scans:
                        plan.u16_rays = u16
                        for k, v in opts.items():
                            setattr(plan, k, v)
                        w._update.insert_guarded(pts.astype(dtype), T)  # not a user's scan
                    plan.block_cells, plan.row_flags, plan.one_pass = block_cells, "auto", True
        # The exact node count of hits spread over more leaves than it flags one by one (a
        # sparse, wide scan under memory pressure): two cells far apart.
        span = np.array([w.layout.lo, np.array(w.layout.hi) - 1], np.int32)  # the grid's corners, any layout
        w._budget.new_hit_nodes(span)
        w._warm = True
        len(w)
        w.known_cells()
        w.gaussians()
    except MemoryError:
        pass
    finally:
        w.close()  # the scratch map's slot goes back to the storage
