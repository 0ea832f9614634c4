"""A map's cell state as numpy arrays, out of the map and into an empty one (what
``save`` writes and ``load``, ``coarsen`` and the tests read back)."""

from __future__ import annotations

import numpy as np


def state_of(m) -> dict:
    """All cell state of the NdtOmMap ``m`` as numpy arrays (the caller holds its lock)."""
    g = m._raw_gaussians()
    k = m.known_cells()
    return {
        "occ_index": k["index"].astype(np.int32),
        "occ_logodds": k["logodds"].astype(np.float32),
        "g_index": g["index"],
        "g_n": g["n"],
        "g_mean_rel": g["mean_rel"],
        "g_scatter": g["scatter"],
        "g_erased_near": g["erased_near"],
        "g_ndt_state": g["ndt_state"],
    }


def load_into(m, st: dict) -> None:
    """Write cell state into the empty NdtOmMap ``m``: log-odds, then the Gaussian
    records and their cells' record numbers, refused before any write when the memory
    budget has no room for it."""
    glo, ghi = m._glo, m._ghi
    occ_idx = np.ascontiguousarray(st["occ_index"], np.int32)
    g_idx = np.ascontiguousarray(st["g_index"], np.int32)
    for name, idx in (("occupancy", occ_idx), ("Gaussian", g_idx)):
        if len(idx) and (((idx < glo) | (idx >= ghi)).any()):
            raise ValueError(f"{name} cell indices lie outside this map's grid {m.layout.cells}")
    budget, io, slot, fs = m._budget, m._io, m._slot, m._st
    budget.reserve(budget.load_bound(occ_idx, g_idx))
    if len(occ_idx):
        occ_lo = np.ascontiguousarray(st["occ_logodds"], np.float32)
        io.load_known(slot, occ_idx, occ_lo, len(occ_idx), fs.occ_regions, fs.leaf_count)
    if len(g_idx):
        recs = m._records
        recs.load(g_idx, st["g_n"], st["g_mean_rel"], st["g_scatter"], st.get("g_erased_near"), st.get("g_ndt_state"))
        if recs.ndt:
            m._k.ndt_refresh()(nrec=recs.count, records=recs.group, ndt=recs.ndt_group)
        io.load_slots(slot, g_idx, len(g_idx), fs.gidx_regions, fs.occ_regions, fs.leaf_count)
    fs.note_usage()
