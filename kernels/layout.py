"""Sparse storage of NDT-OMs: two Taichi SNode trees shared by every map in the process.

Both trees are ``pointer(slots x L1) -> pointer(L2) -> dense(leaf^3)`` whose leaves hold
a cell's fields side by side (one ``place`` of them all: a cell's log-odds and ray count
share a cache line; docs: two pointer levels over dense 8^3 leaves measured fastest for
rays). The first index is the map's slot, so all maps share one set of node
allocators: Taichi reserves pool memory per node type in chunks of up to 128 MiB, and
per-map trees would each reserve their own.

* occupancy tree: every cell a ray or a point touched: log-odds (f32) and the number of
  rays that passed the cell in the current scan (i32, zero between scans).
* Gaussian index tree: only cells that received points: the cell's record number in the
  map's dense Gaussian records (N, mean, scatter; numpy on the CPU, outside Taichi's
  pool), and two scan-local scratch integers (points of this scan in the cell, slot of
  the cell in this scan's hit list).

Each L2 pointer cell also holds one i32 "leaf mark" beside its dense leaf, so kernels
count leaves exactly as they create them (Taichi 1.7 has no reliable way to ask).
"""

from __future__ import annotations

import math
import numbers
import threading
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import taichi as ti

POINTER_SLOT_BYTES = 16  # pointer + lock word per slot (CPU backend)
OCC_CELL_BYTES = 4 + 4
GIDX_CELL_BYTES = 4 + 4 + 4
LEAF_MARK_BYTES = 4
# One Gaussian record: N (i32), cell index (3 x i32), mean (3 x f64), scatter (6 x f64),
# and its entry of the free stack (i32) that erased records wait on. With the NDT miss
# model also the scan's miss sum (i64), what rays read (inverse covariance, mean: 9 x f64)
# and its count of neighbours erased (i32).
RECORD_BYTES = 4 + 12 + 24 + 48 + 4
NDT_RECORD_BYTES = 8 + 72 + 4

# Taichi 1.7 CPU pool, measured (see README "Memory"): per node type, chunks hold 16384
# nodes, halved while a chunk would exceed 128 MiB; finalising a tree takes ~17-26 MiB.
_CHUNK_NODES = 16384
_CHUNK_MAX = 128 * 2**20
TREE_BASE_BYTES = 32 * 2**20


def chunk_bytes(node_bytes: int) -> tuple[int, int]:
    """(nodes per chunk, bytes per chunk) of Taichi's CPU node allocator."""
    n = _CHUNK_NODES
    while n > 1 and n * node_bytes > _CHUNK_MAX:
        n //= 2
    return n, n * node_bytes


# Spatial hash of a tile's indices (Teschner et al. 2003): neighbouring tiles land on
# different workers without a table, the same in numpy and in the kernels (int64).
TILE_HASH = (73856093, 19349663, 83492791)


@dataclass(frozen=True)
class TileOwner:
    """The cells a worker of a tiled map owns: cubes of ``tile`` cells a side on the global
    cell indices, each given to one of ``workers`` by a hash of its indices. A map whose
    layout has an owner updates only its own cells; every worker sees every ray."""

    tile: int
    workers: int
    worker: int

    def validate(self, leaf: int) -> None:
        if self.tile < leaf or self.tile % leaf:
            raise ValueError(f"a tile must be a whole number of {leaf}-cell leaves, got {self.tile} cells")
        if not 0 <= self.worker < self.workers:
            raise ValueError(f"worker {self.worker} is not one of {self.workers} workers")

    def owners(self, cells: np.ndarray) -> np.ndarray:
        """The worker owning each of ``cells`` ([N, 3] integer cell indices)."""
        return tile_owners(np.asarray(cells, np.int64) // self.tile, self.workers)

    def owned(self, cells: np.ndarray) -> np.ndarray:
        return self.owners(cells) == self.worker


def tile_owners(tiles: np.ndarray, workers: int) -> np.ndarray:
    """The worker of each of ``tiles`` ([N, 3] tile indices), as the kernels compute it."""
    t = np.asarray(tiles, np.int64)
    with np.errstate(over="ignore"):
        h = (t[:, 0] * TILE_HASH[0]) ^ (t[:, 1] * TILE_HASH[1]) ^ (t[:, 2] * TILE_HASH[2])
    return h % workers  # numpy's integer % is Python's: never negative


@dataclass(frozen=True)
class Layout:
    """Shape of the sparse grid, in cells. The grid is centred on cell index 0.
    ``owner``: the cells this map updates when it is one tile set of a tiled map (None: all)."""

    l1: tuple[int, int, int] = (128, 128, 16)
    l2: int = 32
    leaf: int = 8
    owner: TileOwner | None = None

    def __post_init__(self) -> None:
        # Sizes as plain ints and l1 as a tuple (a list is not hashable: layouts key the
        # storages), checked before any Taichi field is built from them.
        def size(name: str, v: object) -> int:
            if isinstance(v, bool) or not isinstance(v, numbers.Integral):
                raise TypeError(f"Layout: {name} must be an integer number of cells, got {v!r} ({type(v).__name__})")
            return int(v)

        l1 = self.l1
        if isinstance(l1, (str, bytes)) or not hasattr(l1, "__len__") or len(l1) != 3:
            raise ValueError(f"Layout: l1 must be three sizes (x, y, z), a tuple or list, got {l1!r}")
        object.__setattr__(self, "l1", tuple(size("l1", n) for n in l1))
        object.__setattr__(self, "l2", size("l2", self.l2))
        object.__setattr__(self, "leaf", size("leaf", self.leaf))
        if self.owner is not None and not isinstance(self.owner, TileOwner):
            raise TypeError(f"Layout: owner must be a TileOwner or None, got {type(self.owner).__name__}")
        self.validate()

    @property
    def region(self) -> int:
        """Cells per axis under one top-level pointer slot."""
        return self.l2 * self.leaf

    @property
    def cells(self) -> tuple[int, int, int]:
        return tuple(n * self.region for n in self.l1)  # type: ignore[return-value]

    @property
    def lo(self) -> tuple[int, int, int]:
        """Smallest valid cell index per axis (inclusive)."""
        return tuple(-(c // 2) for c in self.cells)  # type: ignore[return-value]

    @property
    def hi(self) -> tuple[int, int, int]:
        """Largest valid cell index per axis plus one (exclusive)."""
        return tuple(c - c // 2 for c in self.cells)  # type: ignore[return-value]

    @property
    def leaf_cells(self) -> int:
        return self.leaf**3

    @property
    def region_bytes(self) -> int:
        """One activated top-level slot: its block of L2 pointer slots."""
        return self.l2**3 * POINTER_SLOT_BYTES

    @property
    def occ_leaf_bytes(self) -> int:
        return self.leaf_cells * OCC_CELL_BYTES + LEAF_MARK_BYTES

    @property
    def gidx_leaf_bytes(self) -> int:
        return self.leaf_cells * GIDX_CELL_BYTES + LEAF_MARK_BYTES

    def node_bytes(self) -> tuple[int, int, int, int]:
        """Bytes per node of the four allocated node types: occupancy regions,
        occupancy leaves, index regions, index leaves."""
        return (self.region_bytes, self.occ_leaf_bytes, self.region_bytes, self.gidx_leaf_bytes)

    def validate(self) -> None:
        if any(n < 1 for n in self.l1) or self.l2 < 1 or self.leaf < 1:
            raise ValueError(f"grid layout sizes must be positive, got {self}")
        if self.leaf & (self.leaf - 1):
            raise ValueError(f"the leaf size must be a power of two (kernels shift by it), got {self.leaf}")
        if any(c >= 2**30 for c in self.cells):
            raise ValueError(f"grid of {self.cells} cells per axis overflows 32-bit cell indices")
        if self.owner is not None:
            self.owner.validate(self.leaf)

    def fixed_bytes(self, slots: int) -> int:
        """Bytes the storage of ``slots`` maps of this layout holds before any cell: per tree
        a pointer slot per top-level region of every map slot (Taichi allocates and zeroes
        them when the tree is built), and numpy's flag of each region in use."""
        regions = slots * math.prod(self.l1)
        return regions * (2 * POINTER_SLOT_BYTES + 2)


def pool_bytes(layout: Layout, nodes) -> int:
    """Pool bytes Taichi reserves for ``nodes`` (counts of the four node types)."""
    total = 2 * TREE_BASE_BYTES
    for count, nb in zip(nodes, layout.node_bytes()):
        per, size = chunk_bytes(nb)
        total += math.ceil(count / per) * size
    return total


class Storage:
    """The Taichi fields of up to ``slots`` maps. Built once per process and layout;
    never destroyed (destroying a tree leaks in Taichi 1.7 and drops compiled kernels)."""

    def __init__(self, layout: Layout, slots: int):
        layout.validate()
        self.layout = replace(layout, owner=None)  # one storage for every owner (per slot)
        self.slots = slots
        off = (0, *layout.lo)
        moff = (0, *(o // layout.leaf for o in layout.lo))

        self.lo = ti.field(ti.f32)  # occupancy log-odds
        self.ne = ti.field(ti.i32)  # rays that passed the cell in this scan
        self.olm = ti.field(ti.i32)  # leaf mark of the occupancy tree
        self.gslot = ti.field(ti.i32)  # record number + 1 of the cell's Gaussian (0: none)
        self.hn = ti.field(ti.i32)  # points of this scan in the cell
        self.hslot = ti.field(ti.i32)  # the cell's slot in this scan's hit list
        self.glm = ti.field(ti.i32)  # leaf mark of the Gaussian index tree
        self.l1_nodes = []
        self.l2_nodes = []
        self._trees = []
        for mark, cells in ((self.olm, (self.lo, self.ne)), (self.glm, (self.gslot, self.hn, self.hslot))):
            fb = ti.FieldsBuilder()
            l1 = fb.pointer(ti.ijkl, (slots, *layout.l1))
            l2 = l1.pointer(ti.ijkl, (1, layout.l2, layout.l2, layout.l2))
            l2.place(mark, offset=moff)
            l2.dense(ti.ijkl, (1, layout.leaf, layout.leaf, layout.leaf)).place(*cells, offset=off)
            self.l1_nodes.append(l1)
            self.l2_nodes.append(l2)
            self._trees.append(fb.finalize())

        # Per slot, the cells its map updates (kernels/ndt.py owned): tile size in cells,
        # workers, this worker; workers 1: every cell.
        self.tiles = ti.field(ti.i64)
        fb = ti.FieldsBuilder()
        fb.dense(ti.ij, (slots, 3)).place(self.tiles)
        self._trees.append(fb.finalize())
        for s in range(slots):
            self.set_owner(s, None)

        # Exact node counts kept by the kernels, per slot: [occupancy leaves, index leaves],
        # and the top-level regions in use per slot and tree.
        self.leaf_count = np.zeros((slots, 2), np.int64)
        self.occ_regions = np.zeros((slots, *layout.l1), np.int8)
        self.gidx_regions = np.zeros((slots, *layout.l1), np.int8)
        # Most nodes of each type ever allocated: Taichi keeps freed nodes for reuse but
        # never returns a chunk, so the pool follows the high-water mark.
        self.node_high_water = np.zeros(4, np.int64)
        self._counts: dict = {}  # slot -> (its leaf counts, its node counts)
        self.free_slots = list(range(slots - 1, -1, -1))
        self.kernels: Any = None  # queries, export, load: built lazily by kernels.io.io_kernels
        # Scan scratch shared by the maps: the dense ray-count block and its row flags, all
        # zero between updates, which hold ``lock`` while they use it.
        self.block_buf = np.zeros(0, np.int32)
        self.bflag_buf = np.zeros(0, np.int8)
        # The settled boxes' hit marks (trace.settled_growth): a scan's stamp where it hits.
        self.hmask_buf: np.ndarray = np.zeros((1, 1, 1), np.uint8)
        self.hmask_stamp = 0
        self.lock = threading.RLock()

    def set_owner(self, slot: int, owner: TileOwner | None) -> None:
        """Which cells the map in ``slot`` updates (None: all)."""
        spec = (1, 1, 0) if owner is None else (owner.tile, owner.workers, owner.worker)
        for a, v in enumerate(spec):
            self.tiles[slot, a] = v

    def nodes(self, slot: int | None = None) -> np.ndarray:
        """Live node counts of the four node types, for one slot or all."""
        if slot is None:  # free slots hold no nodes: count up to the last slot in use
            free = set(self.free_slots)
            slots = range(max((s + 1 for s in range(self.slots) if s not in free), default=0))
        else:
            slots = range(slot, slot + 1)
        out = np.zeros(4, np.int64)
        for s in slots:
            out += self._slot_nodes(s)
        return out

    def _slot_nodes(self, slot: int) -> np.ndarray:
        # Kernels flag a region only when they create a leaf in it, so a slot's region
        # counts change only with its leaf counts (or when the slot is emptied: forget).
        key = (int(self.leaf_count[slot, 0]), int(self.leaf_count[slot, 1]))
        hit = self._counts.get(slot)
        if hit is None or hit[0] != key:
            regions = (np.count_nonzero(self.occ_regions[slot]), np.count_nonzero(self.gidx_regions[slot]))
            hit = self._counts[slot] = (key, np.array([regions[0], key[0], regions[1], key[1]], np.int64))
        return hit[1]

    def forget(self, slot: int) -> None:
        """Drop the cached node counts of an emptied slot."""
        self._counts.pop(slot, None)

    def slot_bytes(self, slot: int) -> int:
        """Bytes of nodes one map holds (without chunk rounding)."""
        return int((self.nodes(slot) * np.array(self.layout.node_bytes())).sum())

    def note_usage(self) -> None:
        np.maximum(self.node_high_water, self.nodes(), out=self.node_high_water)

    def pool_bytes(self, extra=(0, 0, 0, 0), all_types: bool = False) -> int:
        """Pool bytes reserved now, or after ``extra`` more nodes of each type. With
        ``all_types``, as if every node type held its first chunk already: budget checks
        count them, so a scan that fills the pool with one type cannot leave a budget in
        which the next map's first hits (index nodes) no longer fit."""
        want = np.maximum(self.node_high_water, self.nodes() + np.asarray(extra, np.int64))
        if all_types:
            want = np.maximum(want, 1)
        return pool_bytes(self.layout, want)
