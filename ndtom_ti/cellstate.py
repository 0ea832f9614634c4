"""The cell arrays of a map's state, by name: what a map's slot gives and takes
(:meth:`~ndtom_ti.slot.MapSlot.state`), a snapshot holds and a map file stores."""

from __future__ import annotations

# name -> (dtype, trailing shape), in file order
ARRAYS: dict[str, tuple[str, tuple[int, ...]]] = {
    "occ_index": ("<i4", (3,)),
    "occ_logodds": ("<f4", ()),
    "g_index": ("<i4", (3,)),
    "g_n": ("<i4", ()),
    "g_mean_rel": ("<f8", (3,)),
    "g_scatter": ("<f8", (6,)),
    "g_erased_near": ("<i4", ()),
    "g_ndt_state": ("|u1", ()),
}
# The arrays that describe the same cells, by the array of their cell indices.
ROWS: dict[str, tuple[str, ...]] = {
    "occ_index": ("occ_index", "occ_logodds"),
    "g_index": ("g_index", "g_n", "g_mean_rel", "g_scatter", "g_erased_near", "g_ndt_state"),
}
