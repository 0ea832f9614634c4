"""A map's memory report: what its slot holds, by part (``NdtOmMap.memory_report``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from . import runtime

if TYPE_CHECKING:
    from .slot import MapSlot

__all__ = ["memory_report"]


def memory_report(slot: MapSlot, known: int, gauss: int, total: int) -> dict:
    """Memory held by ``slot``'s map, by part, with bytes per known cell and per Gaussian
    (``known`` cells, ``gauss`` Gaussians and ``total`` bytes: the map's own counts)."""
    recs = slot.records
    nodes = slot.node_counts()
    return {
        "total_bytes": total,
        "node_bytes": slot.node_bytes(),
        "record_bytes": recs.nbytes(),
        "records_held": recs.capacity,
        "records_in_use": recs.in_use,
        "records_free": recs.nfree,
        "occupancy_regions": int(nodes[0]),
        "occupancy_leaves": int(nodes[1]),
        "index_regions": int(nodes[2]),
        "index_leaves": int(nodes[3]),
        "known_cells": known,
        "gaussians": gauss,
        "bytes_per_known_cell": total / known if known else float("nan"),
        "bytes_per_gaussian": total / gauss if gauss else float("nan"),
        # Scan scratch of all maps, outside the pool: the dense ray-count block.
        "process_scratch_bytes": slot.storage.block_buf.nbytes + slot.storage.bflag_buf.nbytes,
        "process_pool_bytes": slot.storage.pool_bytes(),
        "process_pool_budget_bytes": runtime.pool_limit(),
    }
