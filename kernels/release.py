"""Giving back the empty occupancy leaves a refused scan left in a map's tree.

Rays of a scan refused while it was traced in batches have created leaves that hold
nothing (log-odds 0, no ray count, no Gaussian). They are deactivated here, so Taichi's
node allocators hand them out again to later scans of any map, and the map's node counts
fall back to what it holds.
"""

import numpy as np
import taichi as ti

from .layout import Storage

i32_2d = ti.types.ndarray(dtype=ti.i32, ndim=2)
i64_1d = ti.types.ndarray(dtype=ti.i64, ndim=1)
i8_3d = ti.types.ndarray(dtype=ti.i8, ndim=3)
i8_4d = ti.types.ndarray(dtype=ti.i8, ndim=4)


def make_release_kernels(f: Storage):
    """Build (once) the kernels that find and deactivate a slot's empty occupancy leaves."""
    got = getattr(f, "release_kernels", None)
    if got is not None:
        return got
    L = f.layout
    leaf, region = L.leaf, L.region
    lo, ne, olm = f.lo, f.ne, f.olm
    occ_l1, occ_l2 = f.l1_nodes[0], f.l2_nodes[0]
    grid_lo = ti.Vector(list(L.lo))
    leaf_lo = ti.Vector([c // leaf for c in L.lo])

    @ti.kernel
    def find_empty(slot: ti.i32, out: i32_2d, ctr: i64_1d, keep: i8_3d):
        # out: leaf indices of the slot's leaves whose cells are all zero; keep: the
        # regions that still hold a leaf with something in it.
        for I in ti.grouped(olm):
            if I[0] == slot:
                empty = True
                for a, b, c in ti.ndrange(leaf, leaf, leaf):
                    cell = ti.Vector([slot, I[1] * leaf + a, I[2] * leaf + b, I[3] * leaf + c])
                    if lo[cell] != 0.0 or ne[cell] != 0:
                        empty = False
                lf = ti.Vector([I[1], I[2], I[3]])
                if empty:
                    k = ti.atomic_add(ctr[0], 1)
                    if k < out.shape[0]:
                        for a in ti.static(range(3)):
                            out[k, a] = lf[a]
                else:
                    r = (lf * leaf - grid_lo) // region
                    keep[r[0], r[1], r[2]] = ti.i8(1)

    @ti.kernel
    def drop_leaves(slot: ti.i32, leaves: i32_2d, n: ti.i32):
        for k in range(n):
            p = ti.Vector([leaves[k, 0], leaves[k, 1], leaves[k, 2]]) - leaf_lo  # physical index
            ti.deactivate(occ_l2, [slot, p[0], p[1], p[2]])

    @ti.kernel
    def drop_regions(slot: ti.i32, regions: i8_4d, keep: i8_3d, ctr: i64_1d):
        for i, j, k in ti.ndrange(L.l1[0], L.l1[1], L.l1[2]):
            if regions[slot, i, j, k] != 0 and keep[i, j, k] == 0:
                ti.deactivate(occ_l1, [slot, i, j, k])
                regions[slot, i, j, k] = ti.i8(0)
                ti.atomic_add(ctr[1], 1)

    f.release_kernels = (find_empty, drop_leaves, drop_regions)
    return f.release_kernels


def release_empty_leaves(f: Storage, slot: int) -> int:
    """Deactivate the slot's empty occupancy leaves (and regions left without leaves);
    returns how many leaves were given back. Node counts are updated."""
    find_empty, drop_leaves, drop_regions = make_release_kernels(f)
    n_leaves = int(f.leaf_count[slot, 0])
    if n_leaves == 0:
        return 0
    out = np.empty((n_leaves, 3), np.int32)
    ctr = np.zeros(2, np.int64)
    keep = np.zeros(f.layout.l1, np.int8)
    find_empty(slot, out, ctr, keep)
    n = min(int(ctr[0]), n_leaves)
    if n:
        drop_leaves(slot, out, n)
    drop_regions(slot, f.occ_regions, keep, ctr)
    f.leaf_count[slot, 0] -= n
    f.forget(slot)
    return n
