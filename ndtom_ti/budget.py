"""The memory budget of a map's updates: bounds on the nodes a scan or a load can add to
Taichi's pool, checked against ``runtime.pool_limit()`` before any kernel runs, so that
a refused update leaves the map unchanged (see docs on Taichi 1.7's CPU pool)."""

from __future__ import annotations

import math

import numpy as np

from . import runtime
from .cellkeys import count_distinct, pack
from .kernels.args import Nodes
from .kernels.layout import pool_bytes as layout_pool_bytes
from .runtime import MapMemoryError
from .scaninput import cell_box

_SEEN_MAX = 1 << 24  # leaf flags for counting a scan's new leaves exactly


class MemoryBudget:
    """Node bounds and budget checks for the map in ``slot`` of storage ``st``."""

    def __init__(self, st, slot: int, kernels, occupancy: bool):
        self.st = st
        self.slot = slot
        self.layout = st.layout
        self.k = kernels
        self.occupancy = occupancy
        self.glo = np.array(self.layout.lo, np.int64)
        self.nodes = Nodes(occ_regions=st.occ_regions, gidx_regions=st.gidx_regions, leaves=st.leaf_count)

    def fits(self, nodes: np.ndarray) -> bool:
        """Whether ``nodes`` more (per node type) keep the pool within the budget."""
        return self.st.pool_bytes(nodes, all_types=True) <= runtime.pool_limit()

    def scan_bound(
        self,
        cells: np.ndarray,
        n_hit: int,
        ocell: np.ndarray,
        tight: bool = False,
        rays: bool | None = None,
        box: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """Upper bound of the nodes a scan can add, per node type (occupancy regions,
        occupancy leaves, index regions, index leaves): the nodes of the scan's bounding
        box (``box`` of all ``cells`` when known), or with ``tight`` also at most one node
        per node boundary each ray crosses."""
        out = np.zeros(4, np.int64)
        if len(cells) == 0:
            return out
        L = self.layout
        rays = self.occupancy if rays is None else rays

        def nodes(size: int, c: np.ndarray, box: tuple, with_rays: bool) -> int:
            lo, hi = box
            n_box = int(np.prod(hi // size - lo // size + 1))  # floor division is monotone
            if not tight:
                return n_box
            q = c.astype(np.int64) // size
            per_ray = int((np.abs(q - ocell // size).sum(axis=1) + 1).sum()) if with_rays else len(c)
            return min(n_box, per_ray)

        def box_of(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            if box is not None and len(c) == len(cells):
                return box
            return cell_box(c)

        occ = cells if rays else cells[:n_hit]
        if len(occ):
            lo, hi = box_of(occ)
            if rays:
                lo, hi = np.minimum(lo, ocell), np.maximum(hi, ocell)
            out[0], out[1] = nodes(L.region, occ, (lo, hi), rays), nodes(L.leaf, occ, (lo, hi), rays)
        if n_hit:
            h = cells[:n_hit]
            hbox = box_of(h)
            out[2], out[3] = nodes(L.region, h, hbox, False), nodes(L.leaf, h, hbox, False)
        return out

    def new_hit_nodes(self, hit_cells: np.ndarray) -> np.ndarray:
        """Exact number of nodes per type that writing these hit cells allocates."""
        if len(hit_cells) == 0:
            return np.zeros(4, np.int64)
        L = self.layout
        box = cell_box(hit_cells)
        lo, hi = (b // L.leaf for b in box)
        rlo, rhi = ((b - self.glo) // L.region for b in box)
        rseen = np.zeros(tuple(int(x) for x in rhi - rlo + 1), np.int32)  # at most the grid's regions
        shape = tuple(int(x) for x in hi - lo + 1)
        if math.prod(shape) <= _SEEN_MAX:
            cells, seen, dedup = hit_cells, np.zeros(shape, np.int32), True
        else:  # a sparse, wide scan: one cell per distinct leaf
            key = np.ravel_multi_index((hit_cells // L.leaf - lo).T, shape)
            order = np.argsort(key)  # np.unique is ~100x slower than a sort (numpy 2.4)
            sk = key[order]
            first = order[np.concatenate(([True], sk[1:] != sk[:-1]))]
            cells, seen, dedup = np.ascontiguousarray(hit_cells[first]), np.zeros((1, 1, 1), np.int32), False
        new = np.zeros(4, np.int64)
        self.k.count_new_nodes(dedup)(
            slot=self.slot,
            cells=cells,
            n=len(cells),
            lbase=lo.astype(np.int32),
            seen=seen,
            rbase=rlo.astype(np.int32),
            rseen=rseen,
            nodes=self.nodes,
            out=new,
        )
        return new[[2, 0, 3, 1]]

    def load_bound(self, occ_idx: np.ndarray, g_idx: np.ndarray) -> np.ndarray:
        """Nodes per type that loading these occupancy and Gaussian cells allocates."""
        L = self.layout

        def distinct(idx: np.ndarray, size: int) -> int:
            return count_distinct(pack(idx // size)[0]) if len(idx) else 0

        occ = np.concatenate([occ_idx, g_idx])  # a Gaussian's cell holds its flag in the occupancy tree
        return np.array(
            [distinct(occ, L.region), distinct(occ, L.leaf), distinct(g_idx, L.region), distinct(g_idx, L.leaf)],
            np.int64,
        )

    def reserve(self, extra_nodes: np.ndarray) -> None:
        """Refuse, before any kernel runs, work that could take Taichi's memory pool past
        the budget (runtime.pool_limit)."""
        if not self.fits(extra_nodes):
            raise self.refusal(extra_nodes)

    def refusal(self, extra_nodes: np.ndarray) -> MapMemoryError:
        """The MapMemoryError of an update that adds ``extra_nodes`` (per node type)."""
        st, limit = self.st, runtime.pool_limit()
        want = st.nodes() + np.asarray(extra_nodes, np.int64)
        need = layout_pool_bytes(st.layout, np.maximum(np.maximum(st.node_high_water, want), 1))
        # Taichi keeps each node type's chunks for that type alone: nodes freed by earlier
        # scans or maps serve an update only where it needs their kind.
        idle = need - layout_pool_bytes(st.layout, np.maximum(want, 1))
        kept = ""
        if idle > limit / 16:
            kept = (
                f" Of it, {idle / 2**20:.0f} MiB hold nodes freed earlier (by a refused scan or deleted maps) "
                "of a kind this update does not need: Taichi keeps them for that kind, and a new process "
                "starts without them."
            )
        return MapMemoryError(
            f"this update could take Taichi's memory pool to {need / 2**20:.0f} MiB, past the "
            f"{limit / 2**20:.0f} MiB budget (this map holds {st.slot_bytes(self.slot) / 2**20:.0f} MiB "
            f"of nodes; all maps {st.pool_bytes() / 2**20:.0f} MiB of pool).{kept} Use a coarser "
            f"resolution or a smaller max_range, delete other maps, give a larger budget "
            f"(ndtom_ti.init(memory_limit_GB=...) before the first map), or use CUDA. The map is unchanged."
        )
