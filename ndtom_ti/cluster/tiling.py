"""How a tiled map divides its cells among workers.

Tiles are cubes on the global integer cell indices (no offsets per tile), so a ray's
cells are the same in every worker; ``kernels.layout.TileOwner`` hashes a tile's indices
to its worker, in numpy here and in the kernels alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ..cellstate import ROWS
from ..kernels.layout import Layout, TileOwner


@dataclass(frozen=True)
class Tiling:
    """``workers`` workers sharing the cells of a map of ``resolution`` in cubic tiles of
    about ``tile_size`` metres (rounded up to whole leaves of ``layout``)."""

    resolution: float
    workers: int
    tile_size: float = 16.0
    layout: Layout = field(default_factory=Layout)

    def __post_init__(self) -> None:
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 1:
            raise ValueError(f"workers must be an integer >= 1, got {self.workers!r}")
        if not (isinstance(self.tile_size, (int, float)) and math.isfinite(self.tile_size) and self.tile_size > 0):
            raise ValueError(f"tile size must be a positive number of metres, got {self.tile_size!r}")
        if self.layout.owner is not None:
            object.__setattr__(self, "layout", replace(self.layout, owner=None))
        top = max_tile_size(self.resolution, self.layout)
        if self.tile_size > top:  # (its cell count would overflow the kernels' int32 tiles)
            raise ValueError(
                f"tile size must be at most {top:g} m at {self.resolution:g} m (the whole grid, "
                f"{max(self.layout.cells)} cells a side), got {self.tile_size:g}"
            )

    @property
    def tile_cells(self) -> int:
        leaf = self.layout.leaf
        return leaf * max(1, math.ceil(self.tile_size / self.resolution / leaf - 1e-9))

    def owner(self, worker: int) -> TileOwner:
        own = TileOwner(tile=self.tile_cells, workers=self.workers, worker=worker)
        own.validate(self.layout.leaf)
        return own

    def layout_of(self, worker: int) -> Layout:
        """The layout of worker ``worker``'s map: the global grid, its cells marked."""
        return replace(self.layout, owner=self.owner(worker))

    def owners(self, cells: np.ndarray) -> np.ndarray:
        return self.owner(0).owners(cells)

    def at_border(self, cells: np.ndarray) -> np.ndarray:
        """Rows of ``cells`` with a neighbour (of 26) in another tile: the erasures other
        workers may have to count."""
        r = np.asarray(cells, np.int64).reshape(-1, 3) % self.tile_cells
        return ((r == 0) | (r == self.tile_cells - 1)).any(axis=1)


def max_tile_size(resolution: float, layout: Layout | None = None) -> float:
    """The largest tile edge in metres at ``resolution``: the grid's longest side (one tile
    then holds whole slabs of the grid; a larger one would hold nothing more)."""
    return max((layout or Layout()).cells) * resolution


def split_tiles(state: dict, tile_cells: int) -> dict[tuple[int, int, int], dict]:
    """A map's cell arrays (``state``, rows sorted by cell) cut by tile: tile indices ->
    that tile's arrays, rows still sorted."""
    parts: dict[tuple[int, int, int], dict] = {}
    for first, names in ROWS.items():
        idx = state[first]
        if not len(idx):
            continue
        t = idx.astype(np.int64) // tile_cells
        order = np.lexsort((t[:, 2], t[:, 1], t[:, 0]))  # stable: a tile's rows keep their order
        ts = t[order]
        cut = np.flatnonzero((np.diff(ts, axis=0) != 0).any(axis=1)) + 1
        for rows in np.split(order, cut):
            i, j, k = (int(x) for x in t[rows[0]])
            key = (i, j, k)
            part = parts.setdefault(key, {})
            for name in names:
                part[name] = state[name][rows]
    for part in parts.values():  # a tile of Gaussians only, or of known cells only
        for name, a in state.items():
            part.setdefault(name, a[:0])
    return parts
