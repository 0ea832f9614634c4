"""One worker of a tiled map: the map of its own cells, fed every scan in global order."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from ..config import MapConfig
from ..map import NdtOmMap
from ..snapshot import MapSnapshot
from ..tiledfile import tile_name
from .tiling import Tiling, split_tiles


class TileWorker:
    """Worker ``worker`` of ``tiling``: an :class:`NdtOmMap` that updates only the cells the
    tiling gives it. Every scan reaches every worker, which traces all of its rays with the
    one-process arithmetic (so a ray's cells are the same everywhere); the one rule that
    reads other cells, the NDT miss model's erased neighbours, crosses tiles as events: the
    cells whose Gaussians a worker's scan erased next to another tile, counted by the
    others before their next scan (:meth:`step`)."""

    def __init__(
        self,
        tiling: Tiling,
        worker: int,
        *,
        config: MapConfig | None = None,
        occupancy: bool = True,
        metadata: dict | None = None,
        start: MapSnapshot | None = None,
    ):
        self.tiling, self.worker = tiling, worker
        layout = tiling.layout_of(worker)
        if start is not None:  # resuming from a checkpoint of this worker's cells
            self.map = NdtOmMap.from_snapshot(replace(start, layout=layout))
        else:
            self.map = NdtOmMap(tiling.resolution, occupancy=occupancy, config=config, layout=layout, metadata=metadata)

    def count(self, *events: np.ndarray) -> None:
        """Count other workers' erasures of the last scan (``events``: [K, 3] cells each)."""
        if events:
            self.map.count_erased_near(np.concatenate([np.asarray(e, np.int32).reshape(-1, 3) for e in events]))

    def step(self, points: np.ndarray, pose: np.ndarray, *events: np.ndarray) -> np.ndarray:
        """Count the other workers' erasures of the last scan (``events``), then insert
        this scan (its report: ``last_report``). Returns this scan's erasures that other
        workers may count (cells at the border of their tiles), [K, 3] int32."""
        self.count(*events)
        rep = self.map.insert_scan(points, pose)
        self.last_report = rep.as_dict()
        cells = rep.erased_cells
        return np.ascontiguousarray(cells[self.tiling.at_border(cells)], np.int32)

    def snapshot(self) -> MapSnapshot:
        return self.map.snapshot()

    def save_tiles(self, folder: str | Path, scans: int) -> list[tuple[str, tuple[int, int, int]]]:
        """Write this worker's cells to ``folder``, a map file per tile (``tiledfile``);
        returns (file name, tile indices) of each."""
        snap = self.map.snapshot()
        settings = {**snap.settings(), "layout": replace(snap.layout, owner=None)}
        out = []
        for tile, arrays in split_tiles(snap.state(), self.tiling.tile_cells).items():
            name = tile_name(tile, scans)
            MapSnapshot.adopt(settings, arrays).save(Path(folder) / name)
            out.append((name, tile))
        return out

    def close(self) -> None:
        self.map.close()
