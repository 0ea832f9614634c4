"""LevelCache: the maps a viewer shows, the lock on them, and their coarser levels.

Coarser levels are snapshots coarsened in numpy (no map slot), cached by the map's
version (scans and points inserted) and dropped before a replacement is made: the
process holds at most 8 maps. :meth:`LevelCache.take` reads everything the layers need
as numpy arrays under the lock, and picks the level of detail.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ndtom_ti.frames import as_frame_origin
from ndtom_ti.snapshot import MapSnapshot

from . import geometry as geo

if TYPE_CHECKING:
    from ndtom_ti import NdtOmMap

__all__ = ["AUTO", "FACTORS", "Caps", "LevelCache", "coarser", "warm_up"]

FACTORS = (1, 2, 3, 4)  # resolution selector: native and coarser levels made with coarsen()
AUTO = 0  # resolution selector: the level of detail picks the level (its entry says which)
LOD_FACTORS = (2, 3, 4, 6, 8)  # auto level of detail may go this far coarser


@dataclass(frozen=True)
class Caps:
    """How much a page draws (see :class:`~ndtom_ti.viewer.MapViewer`)."""

    ellipsoids: int = 4_000
    splats: int = 20_000
    chosen: int = 100_000
    free_cells: int = 20_000
    occupied_cells: int = 100_000

    def gaussians(self, geometry: str) -> int:
        return self.ellipsoids if geometry == "ellipsoids" else self.splats


def fmt(n: int) -> str:
    return f"{int(n):,}"


def warm_up(m: NdtOmMap | MapSnapshot | None) -> None:
    """Launch one (tiny) kernel of ``m`` on the calling thread.

    Taichi builds its default field tree at the first kernel launch of a process, and
    only the thread that initialised Taichi may do that ("Assertion failure:
    std::this_thread::get_id() == main_thread_id_"). Viewer callbacks and live mapping
    run kernels in other threads, so the viewer launches one here first. A snapshot runs
    no kernel."""
    if m is not None and not isinstance(m, MapSnapshot):
        m.occupancy(np.zeros((1, 3)))


def coarser(m: NdtOmMap | MapSnapshot, factor: int) -> MapSnapshot:
    """``m`` at ``factor`` x its resolution, coarsened in numpy (no map slot)."""
    return (m if isinstance(m, MapSnapshot) else m.snapshot()).coarsen(factor)


class LevelCache:
    """The NDT-OM map and the comparison map shown, and up to ``size`` coarser levels.

    ``lock`` guards every read and write of the maps (Taichi calls are serialised by it,
    live mapping inserts under it): the layers read both maps at one version.
    """

    def __init__(self, m: NdtOmMap | MapSnapshot | None, compare: NdtOmMap | MapSnapshot | None, size: int = 2):
        self.lock = threading.RLock()
        self.size = max(int(size), 0)
        self._maps: dict[str, NdtOmMap | MapSnapshot | None] = {"ndtom": None, "rndt": None}
        self._levels: OrderedDict = OrderedDict()  # (kind, factor) -> (version, map)
        self.set(m, compare)

    @property
    def map(self) -> NdtOmMap | MapSnapshot | None:
        return self._maps["ndtom"]

    @property
    def compare(self) -> NdtOmMap | MapSnapshot | None:
        return self._maps["rndt"]

    def set(self, m: NdtOmMap | MapSnapshot | None, compare: NdtOmMap | MapSnapshot | None) -> None:
        """Hold other maps (the coarser levels are dropped)."""
        with self.lock:
            warm_up(m)
            warm_up(compare)
            self._maps = {"ndtom": m, "rndt": compare}
            self._levels.clear()

    def __iter__(self) -> Iterator[tuple[str, int]]:
        """The levels held now: (``"ndtom"`` or ``"rndt"``, factor), least recently used first."""
        return iter(list(self._levels))

    def __len__(self) -> int:
        return len(self._levels)

    def level(self, kind: str, factor: int) -> NdtOmMap | MapSnapshot:
        """The map ``kind`` at ``factor`` x its resolution (cached; call under ``lock``)."""
        base = self._maps[kind]
        if base is None:
            raise LookupError(f"the viewer holds no {kind} map")  # callers check first
        if factor == 1:
            return base
        key = (kind, factor)
        entry = self._levels.pop(key, None)
        if entry is not None and entry[0] == _version(base):
            self._levels[key] = entry  # most recently used last
            return entry[1]
        del entry  # a stale level is dropped before its replacement is made
        while self._levels and len(self._levels) >= max(self.size, 1):
            self._levels.popitem(last=False)
        cm = coarser(base, factor)
        if self.size:
            self._levels[key] = (_version(base), cm)
        return cm

    def _any_level(self, kind: str, factor: int) -> NdtOmMap | MapSnapshot:
        """A selector's level from the cache; a level beyond the selector's made once."""
        if factor in FACTORS:
            return self.level(kind, factor)
        base = self._maps[kind]
        assert base is not None  # callers check first
        return coarser(base, factor)

    def take(
        self, want: dict[str, bool], *, threshold: float, chosen: int, geometry: str, caps: Caps, find_ceiling: bool
    ) -> dict:
        """Everything the layers need, as numpy arrays, taken under ``lock``.

        ``chosen``: the selector's factor or AUTO; ``geometry``: the selector's ("auto" counts
        as splats for the level of detail); ``find_ceiling``: look for an indoor map's roof
        (the height clip's first fit)."""
        thr = float(threshold)
        sel = chosen or 1  # auto starts from the native level
        out: dict[str, Any] = {"threshold": thr, "selected": chosen, "notes": [], "skipped": []}
        with self.lock:
            base = self._maps["ndtom"]
            if base is None:
                out.update(factor=sel, resolution=None, g=None, skipped=["occupied", "free", "conflicts"])
                return out
            try:
                m = self.level("ndtom", sel)
            except MemoryError as exc:
                out["notes"].append(f"the {sel}x level could not be made ({exc}); showing the native level")
                m, sel = base, 1
            g = m.gaussians(min_probability=thr)
            if find_ceiling and len(g["n"]):
                # indoors, a first view below the roof; found at the chosen level (the native one at
                # first): a coarse level's large tiles take trees and uneven ground for ceilings
                out["ceiling"] = geo.ceiling_height(g["mean"], g["cov"], m.resolution)
            factor = sel
            n_sel = len(g["n"])
            cap = caps.gaussians(geometry)
            if n_sel > cap and chosen == AUTO:  # a level chosen by hand is drawn as chosen
                # Too many to draw: the first coarser level that fits (its Gaussians are larger, so
                # they stay visible from afar, where an even subsample of small ones fades out).
                # Estimate each level's count from the parents of the drawn cells.
                # The estimate can fall short (a coarse cell gets a Gaussian from points that
                # made none in its finer cells): a level that still does not fit gives way to
                # the next coarser one.
                idx = g["index"]
                first = next(
                    (i for i, f in enumerate(LOD_FACTORS) if len(np.unique(geo.cell_keys(idx // f))) <= cap),
                    len(LOD_FACTORS) - 1,
                )
                try:
                    for choice in LOD_FACTORS[first:]:
                        cm = self._any_level("ndtom", sel * choice)
                        m, factor = cm, sel * choice
                        del cm
                        g = m.gaussians(min_probability=thr)
                        if len(g["n"]) <= cap:
                            break
                    out["notes"].append(
                        f"{fmt(n_sel)} Gaussians at {base.resolution * sel:g} m exceed {fmt(cap)}: "
                        f"showing the {factor // sel}x coarser level ({m.resolution:g} m)"
                    )
                except MemoryError as exc:
                    out["notes"].append(f"a coarser level could not be made ({exc})")
            out.update(factor=factor, resolution=m.resolution, g=g, native_resolution=base.resolution)
            out["frame_origin"] = as_frame_origin(base.metadata.get("frame_origin"))  # None: not shifted
            out["stats"] = {
                "scans": base.scans_inserted,
                "points": base.points_inserted,
                "memory": base.memory_bytes(),
                "occupancy": base.occupancy_enabled,
            }
            if want["occupied"] or want["free"]:
                k = m.known_cells()
                out["known"] = len(k["p_occ"])
                occ = k["p_occ"] > thr
                free = k["p_occ"] < 0.5
                out["n_occupied"], out["n_free"] = int(occ.sum()), int(free.sum())
                for key, sel_mask, cap in (("occupied", occ, caps.occupied_cells), ("free", free, caps.free_cells)):
                    if want[key]:
                        rows = np.flatnonzero(sel_mask)
                        rows = rows[geo.cap_rows(len(rows), cap)]
                        out[key] = (m.cell_center(k["index"][rows]), k["p_occ"][rows])
                    else:
                        out["skipped"].append(key)
            else:
                out["skipped"] += ["occupied", "free"]
            if self._maps["rndt"] is not None:
                out["compare_stats"] = {"gaussians": None}
                if want["conflicts"]:
                    self._conflicts(out, m, g, factor, thr)
                else:
                    out["skipped"].append("conflicts")
            del m
        return out

    def _conflicts(self, out: dict, m: NdtOmMap | MapSnapshot, g: dict, factor: int, thr: float) -> None:
        """The comparison map's Gaussians (p > 0.5) where NDT-OM has none, at ``factor``."""
        try:
            cm = self._any_level("rndt", factor)
        except MemoryError as exc:
            out["notes"].append(f"conflicting cells: the comparison map's level could not be made ({exc})")
            return
        ng = m.gaussians(min_probability=0.5) if thr != 0.5 else g
        cg = cm.gaussians(min_probability=0.5)
        conflict = ~np.isin(geo.cell_keys(cg["index"]), geo.cell_keys(ng["index"]))
        out["conflicts"] = {"mean": cg["mean"][conflict], "cov": cg["cov"][conflict]}
        out["compare_stats"] = {"gaussians": len(cg["n"]), "conflicts": int(conflict.sum())}


def _version(m: NdtOmMap | MapSnapshot) -> tuple[int, int]:
    return (m.scans_inserted, m.points_inserted)
