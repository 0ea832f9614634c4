"""Queries, export and load: kernels over a map's slot of the sparse trees, called with a
few positional arguments (no per-scan launch cost to save)."""

from types import SimpleNamespace

import taichi as ti

from .layout import Storage
from .ndt import C_EXPORT, NE_GAUSS, device_funcs, f32_1d, i8_4d, i32_2d, i64_1d, i64_2d


def io_kernels(f: Storage) -> SimpleNamespace:
    """Build (once) the query, export and load kernels of the storage ``f``."""
    built = getattr(f, "kernels", None)
    if built is not None:
        return built
    F = device_funcs(f)
    lo, ne, olm, gslot, glm = f.lo, f.ne, f.olm, f.gslot, f.glm
    row, at, note_leaf = F.row, F.at, F.note_leaf
    L = f.layout
    occ_l1, gidx_l1 = f.l1_nodes
    occ_l2, gidx_l2 = f.l2_nodes

    @ti.kernel
    def query(slot: ti.i32, cells: i32_2d, n: ti.i32, out: f32_1d):
        for i in range(n):
            out[i] = lo[at(slot, row(cells, i))]

    @ti.kernel
    def count_known(slot: ti.i32, ctr: i64_1d):
        for I in ti.grouped(lo):
            if I[0] == slot and lo[I] != 0.0:
                ti.atomic_add(ctr[C_EXPORT], 1)

    @ti.kernel
    def export_known(slot: ti.i32, idx: i32_2d, val: f32_1d, ctr: i64_1d):
        for I in ti.grouped(lo):
            if I[0] == slot and lo[I] != 0.0:
                k = ti.atomic_add(ctr[C_EXPORT], 1)
                for a in ti.static(range(3)):
                    idx[k, a] = I[a + 1]
                val[k] = lo[I]

    @ti.kernel
    def load_known(slot: ti.i32, idx: i32_2d, val: f32_1d, n: ti.i32, regions: i8_4d, leaves: i64_2d):
        for k in range(n):
            c = row(idx, k)
            note_leaf(olm, slot, c, regions, leaves, 0)
            lo[at(slot, c)] = val[k]

    @ti.kernel
    def load_slots(slot: ti.i32, rec_cell: i32_2d, n: ti.i32, regions: i8_4d, occ_regions: i8_4d, leaves: i64_2d):
        for r in range(n):
            c = row(rec_cell, r)
            note_leaf(glm, slot, c, regions, leaves, 1)
            gslot[at(slot, c)] = r + 1
            note_leaf(olm, slot, c, occ_regions, leaves, 0)
            ne[at(slot, c)] = ne[at(slot, c)] | NE_GAUSS

    @ti.kernel
    def count_leaf_cells(ctr: i64_2d):
        # Independent check of the leaf counters (tests): cells of active leaves per slot.
        for I in ti.grouped(lo):
            ti.atomic_add(ctr[I[0], 0], 1)
        for I in ti.grouped(gslot):
            ti.atomic_add(ctr[I[0], 1], 1)

    @ti.kernel
    def clear_slot(slot: ti.i32):
        # Bottom-up: leaves (L2 cells) first, then the L2 blocks, so every node goes back
        # to Taichi's free lists.
        for i, j, k in ti.ndrange(L.l1[0], L.l1[1], L.l1[2]):
            for l1, l2 in ti.static(((occ_l1, occ_l2), (gidx_l1, gidx_l2))):
                if ti.is_active(l1, [slot, i, j, k]):
                    for a, b, c in ti.ndrange(L.l2, L.l2, L.l2):
                        p = [slot, i * L.l2 + a, j * L.l2 + b, k * L.l2 + c]
                        if ti.is_active(l2, p):
                            ti.deactivate(l2, p)
                    ti.deactivate(l1, [slot, i, j, k])

    ns = SimpleNamespace(
        query=query,
        count_known=count_known,
        export_known=export_known,
        load_known=load_known,
        load_slots=load_slots,
        count_leaf_cells=count_leaf_cells,
        clear_slot=clear_slot,
    )
    f.kernels = ns
    return ns
