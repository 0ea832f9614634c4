"""MapSnapshot: a map's whole content as plain numpy arrays, without Taichi.

A map (:class:`~ndtom_ti.NdtOmMap`) lives in a slot of the process's Taichi storage, and
a process has few slots. A snapshot holds the same content in numpy, so reading a map
file, saving, exporting, coarsening and drawing it take no slot and start no Taichi:

    s = MapSnapshot.load("site.ndtom")      # or m.snapshot() of a map in memory
    s.export("site.ply")                    # every format of ndtom_ti.export
    s.coarsen(2).save("site_2x.ndtom")      # the same cells as m.coarsen(2)
    m = NdtOmMap.from_snapshot(s)           # a map again (takes a slot), to map on

A snapshot never changes: its arrays are read-only, and one taken of a map does not
follow the map's later updates.
"""

from __future__ import annotations

import copy
import numbers
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from . import mapfile, tiledfile
from .cellkeys import lookup_rows, pack
from .cellquery import cell_extent, check_cell_index, known_cells_of, select_gaussians
from .cellstate import ARRAYS, ROWS
from .config import MapConfig, check_resolution
from .kernels.layout import Layout

if TYPE_CHECKING:
    from .export import Exported

__all__ = ["ARRAYS", "MapSnapshot"]

SETTINGS = ("resolution", "occupancy_enabled", "config", "layout", "metadata", "scans_inserted", "points_inserted")


def refuse_export_suffix(path: str | Path, how: str) -> None:
    """ValueError when ``path`` has the suffix of an export format (``map.ply``, ``map.bt``):
    saving writes ndtom_ti's own map file, whatever the name. ``how``: the call that exports."""
    from .export import SUFFIXES

    fmt = SUFFIXES.get(Path(path).suffix.lower())
    if fmt is not None:
        raise ValueError(
            f"{path} names the {fmt} export format, but save() writes ndtom_ti's own map file (.ndtom); "
            f"to export, call {how}, or save under a .ndtom name"
        )


def copy_metadata(metadata: dict) -> dict:
    """A copy the map's later changes do not reach (one level deep for values that
    cannot be copied deeply: saving refuses those anyway)."""
    try:
        return copy.deepcopy(metadata)
    except (TypeError, copy.Error):
        return dict(metadata)


@dataclass(frozen=True, eq=False)
class MapSnapshot:
    """A map's content: settings, counters, known cells and Gaussians.

    Settings: ``resolution`` (cell size, metres; cell ``(i, j, k)`` spans
    ``[i r, (i + 1) r)`` per axis), ``occupancy_enabled`` (NDT-OM with ray tracing, or
    Recursive NDT), ``config`` (:class:`MapConfig`), ``layout`` (the grid the cells lie
    in), ``metadata`` (the dict saved with the map), ``scans_inserted`` and
    ``points_inserted``.

    Cell arrays (read-only, rows sorted by cell index ``(i, j, k)`` lexicographically):

    - ``occ_index`` (K, 3) int32: every known cell (log-odds not zero);
    - ``occ_logodds`` (K,) float32: its log-odds, within the config's clamps (> 0
      occupied, < 0 free);
    - ``g_index`` (G, 3) int32: every cell holding a Gaussian (at least one point); its
      log-odds is its row in ``occ_index``, or 0 when it has none;
    - ``g_n`` (G,) int32: the Gaussian's number of points N;
    - ``g_mean_rel`` (G, 3) float64: its mean minus the cell's centre (metres);
    - ``g_scatter`` (G, 6) float64: its scatter matrix, the sum of
      ``(x - mean)(x - mean)^T`` over its points, as ``xx xy xz yy yz zz`` (m^2); the
      sample covariance is ``scatter / (N - 1)``;
    - ``g_erased_near`` (G,) int32: with the NDT miss model, the neighbouring cells'
      Gaussians that rays erased since its last points (zeros when not given);
    - ``g_ndt_state`` (G,) uint8: with the NDT miss model, what the Gaussian remembers of
      its cell's past: 1 its points came since rays had held the cell free, 2 a hit
      brought it back after rays had made the cell free (kernels/ndt.py NBR_FRESH,
      NBR_BACK; zeros when not given).

    :meth:`gaussians`, :meth:`known_cells` and ``len()`` answer as the map's do. Arrays
    given to the constructor are copied, checked for shape and sorted (unless already
    read-only: then they are taken as they are); a cell listed twice is a ValueError.
    """

    resolution: float
    occupancy_enabled: bool
    config: MapConfig
    layout: Layout
    metadata: dict
    scans_inserted: int
    points_inserted: int
    occ_index: np.ndarray
    occ_logodds: np.ndarray
    g_index: np.ndarray
    g_n: np.ndarray
    g_mean_rel: np.ndarray
    g_scatter: np.ndarray
    g_erased_near: np.ndarray | None = None
    g_ndt_state: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "resolution", check_resolution(self.resolution))
        object.__setattr__(self, "occupancy_enabled", bool(self.occupancy_enabled))
        if not isinstance(self.config, MapConfig):
            raise TypeError(f"config must be a MapConfig, got {type(self.config).__name__}")
        self.config.check_at(self.resolution)
        if not isinstance(self.layout, Layout):
            raise TypeError(f"layout must be a Layout, got {type(self.layout).__name__}")
        if not isinstance(self.metadata, dict):
            raise TypeError(f"metadata must be a dict, got {type(self.metadata).__name__}")
        for key in ("scans_inserted", "points_inserted"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 0:
                raise ValueError(f"{key} must be an integer >= 0, got {v!r}")
            object.__setattr__(self, key, int(v))
        copied = set()
        for name in ("g_erased_near", "g_ndt_state"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.zeros(len(self.g_index), ARRAYS[name][0]))
        for name, (dtype, cols) in ARRAYS.items():
            a = getattr(self, name)
            if not (
                isinstance(a, np.ndarray)
                and a.dtype == np.dtype(dtype)
                and a.flags.c_contiguous
                and not a.flags.writeable
            ):
                a = np.array(a, dtype=dtype, order="C")  # a copy: the caller's array stays theirs
                a.flags.writeable = False
                copied.add(name)
            if a.ndim != 1 + len(cols) or a.shape[1:] != cols:
                want = "(rows" + "".join(f", {c}" for c in cols) + ")"
                raise ValueError(f"{name} must have shape {want}, got {a.shape}")
            object.__setattr__(self, name, a)
        for first, (_, *others) in ROWS.items():
            for name in others:
                if len(getattr(self, name)) != len(getattr(self, first)):
                    raise ValueError(
                        f"{name} has {len(getattr(self, name))} rows but {first} has {len(getattr(self, first))}"
                    )
            if first in copied:  # arrays from outside: sorted here (read-only ones are the caller's word)
                self._sort_rows(first, (first, *others))

    def _sort_rows(self, first: str, names: tuple[str, ...]) -> None:
        keys = pack(getattr(self, first))[0]
        if len(keys) < 2 or (np.diff(keys) > 0).all():
            return
        order = np.argsort(keys, kind="stable")
        if (np.diff(keys[order]) == 0).any():
            raise ValueError(f"{first} lists a cell twice")
        for name in names:
            a = getattr(self, name)[order]
            a.flags.writeable = False
            object.__setattr__(self, name, a)

    # ------------------------------------------------------------------ making one

    @classmethod
    def adopt(cls, settings: dict, arrays: dict) -> MapSnapshot:
        """A snapshot of ``settings`` (the fields before the arrays, by name) and cell
        ``arrays`` nobody else holds: made read-only in place, not copied, and taken as
        sorted (a map's slot and the map file give them so)."""
        own = {}
        for name, (dtype, _) in ARRAYS.items():
            if name not in arrays:  # (coarsened maps: no erasures to carry)
                continue
            a = np.ascontiguousarray(arrays[name], dtype=dtype)
            a.flags.writeable = False
            own[name] = a
        return cls(**settings, **own)

    @classmethod
    def load(cls, path: str | Path) -> MapSnapshot:
        """Read a map file (written by ``NdtOmMap.save`` or :meth:`save`), or a tiled map's
        folder (its tiles joined), checked as ``NdtOmMap.load`` checks it: broken or foreign
        files and folders raise MapFileError."""
        if tiledfile.is_tiled(path):  # a tiled map's folder: its tiles joined
            doc = tiledfile.read_manifest(path)
            if not doc["tiles"]:
                raise mapfile.MapFileError(f"{path} is a tiled map of {doc['scans']} scans without a known cell yet")
            joined = cls.join([cls.adopt(*tile) for tile in tiledfile.read_tiles(path, doc)])  # each checked
            if doc.get("frame_origin") is not None:  # the run's shift of the poses (pipeline.frame_origin)
                joined.metadata["frame_origin"] = doc["frame_origin"]
            joined.metadata["complete"] = bool(doc.get("complete"))  # a checkpoint of a run not finished: False
            return joined
        if Path(path).is_dir():
            raise mapfile.MapFileError(tiledfile.not_tiled(path))
        settings, arrays = mapfile.read(path)
        try:
            return cls.adopt(settings, arrays)
        except (KeyError, TypeError, ValueError) as exc:
            raise mapfile.MapFileError(f"{path} has invalid settings: {exc}") from None

    @classmethod
    def join(cls, parts: list[MapSnapshot]) -> MapSnapshot:
        """One map of the parts of a tiled map (each worker's cells: disjoint, the same
        settings and scans)."""
        if not parts:
            raise ValueError("no parts to join")
        first = parts[0]
        for p in parts[1:]:
            if p.resolution != first.resolution or p.scans_inserted != first.scans_inserted:
                raise mapfile.MapFileError(
                    f"the tiles of a map disagree: resolution {p.resolution} / {first.resolution} m, "
                    f"scans {p.scans_inserted} / {first.scans_inserted}"
                )
        kw: dict[str, Any] = {**first.settings(), "layout": replace(first.layout, owner=None)}
        kw.update({name: np.concatenate([getattr(p, name) for p in parts]) for name in ARRAYS})  # sorted by cls
        return cls(**kw)

    # ------------------------------------------------------------------ writing

    def save(self, path: str | Path, *, version: int | None = None, compact: bool = False) -> Path:
        """Write a map file, atomically, byte for byte as ``NdtOmMap.save`` of the same
        map writes it (``NdtOmMap.load`` and :meth:`load` read it). ``compact``: the
        Gaussians rounded, means to res / 131070 and scatter to float32 (format 7; about
        half the bytes where Gaussians are dense; not lossless). ``version=RAW_VERSION``
        (``ndtom_ti.mapfile``) writes the uncompressed format that ndtom_ti before format 4
        reads."""
        refuse_export_suffix(path, f"s.export({str(path)!r}) (ndtom_ti.export.export_file)")
        if compact and version not in (None, mapfile.COMPACT_VERSION):
            raise ValueError(f"compact maps are format {mapfile.COMPACT_VERSION}; version {version} is lossless")
        if version is None:
            version = mapfile.COMPACT_VERSION if compact else mapfile.VERSION
        return mapfile.write(path, self.settings(), self.state(), version=version)

    def export(self, path: str | Path, fmt: str | None = None, **options: Any) -> Exported:
        """Export as ``ndtom_ti.export.export_file`` does (ply, pcd, npz, csv, bt, grid)."""
        from .export import export_file

        return export_file(self, path, fmt, **options)

    # ------------------------------------------------------------------ queries

    def state(self) -> dict:
        """The cell arrays by name (read-only; what the map file stores)."""
        return {name: getattr(self, name) for name in ARRAYS}

    def settings(self) -> dict:
        """The settings and counters by name (the fields before the arrays)."""
        return {name: getattr(self, name) for name in SETTINGS}

    def cell_center(self, index: Any) -> np.ndarray:
        """World centres of cells (N, 3) from integer indices."""
        return (np.asarray(index, np.float64) + 0.5) * self.resolution

    def logodds_at(self, index: Any) -> Any:
        """Log-odds (float64) of cells given by integer index (K, 3), or of one cell (3,)
        (then a float, as ``NdtOmMap.logodds_at``); unknown cells read 0."""
        if np.shape(index) == (3,):
            return float(self.logodds_at(np.reshape(index, (1, 3)))[0])
        return self._lookup(check_cell_index(index)).astype(np.float64)

    def _lookup(self, idx: np.ndarray) -> np.ndarray:
        """float32 log-odds of cells ``idx`` (K, 3): binary search in the sorted known cells."""
        return lookup_rows(self.occ_index, self.occ_logodds.astype(np.float32, copy=False), idx)[1]

    @cached_property
    def _g_logodds(self) -> np.ndarray:
        return self._lookup(self.g_index)

    def gaussians(self, min_points: int | None = None, min_probability: float = 0.5) -> dict:
        """The Gaussians, as ``NdtOmMap.gaussians`` gives them (the same dict and arrays):
        ``index`` (K, 3) int64, ``mean`` (K, 3) float64 world frame, ``cov`` (K, 3, 3)
        float64 (scatter / (N - 1); 0 for N < 2), ``n`` (K,) int64, ``p_occ`` and
        ``logodds`` (K,) float64. Cells need ``n >= min_points`` (default: the config's)
        and ``p_occ > min_probability`` (0: occupied or not)."""
        return select_gaussians(
            self.g_index,
            self.g_n,
            self.g_mean_rel,
            self.g_scatter,
            self._g_logodds,
            self.resolution,
            min_points,
            min_probability,
            self.config.min_points,
        )

    def known_cells(self) -> dict:
        """Every known cell (occupied and free), as ``NdtOmMap.known_cells`` gives them:
        ``index`` (K, 3) int64, ``logodds`` (K,) float64, ``p_occ`` (K,) float64."""
        return known_cells_of(self.occ_index, self.occ_logodds)

    def known_cell_count(self) -> int:
        """How many cells ``known_cells()`` returns (``NdtOmMap.known_cell_count``)."""
        return len(self.occ_index)

    def __len__(self) -> int:
        """Number of Gaussians: cells with ``n >= min_points`` that are occupied."""
        return int(np.count_nonzero((self.g_n >= max(self.config.min_points, 1)) & (self._g_logodds > 0.0)))

    def data_extent(self) -> tuple[np.ndarray, np.ndarray] | None:
        """World-frame (min corner, max corner) of the box of known cells; None when empty."""
        return cell_extent(self.occ_index, self.resolution)

    def memory_bytes(self) -> int:
        """Bytes of the snapshot's arrays."""
        return sum(getattr(self, name).nbytes for name in ARRAYS)

    def __repr__(self) -> str:
        return (
            f"MapSnapshot(resolution={self.resolution:g}, occupancy={self.occupancy_enabled}, "
            f"scans={self.scans_inserted}, gaussians={len(self)}, known_cells={len(self.occ_index)})"
        )

    # ------------------------------------------------------------------ coarser levels

    def coarsen(self, factor: int) -> MapSnapshot:
        """The snapshot at ``factor * resolution``, the cells ``NdtOmMap.coarsen`` gives:
        each Gaussian merged with the RCU into its parent ``floor(index / factor)`` (N
        capped at the config's ``n_max``; free cells' Gaussians left out), each parent's
        log-odds the maximum of its known children's (the paper's sec. III-B). Runs in
        numpy: no map slot."""
        from .multires import check_factor, coarsen_state

        f = check_factor(factor, self.resolution)
        settings = {
            "resolution": self.resolution * f,
            "occupancy_enabled": self.occupancy_enabled,
            "config": self.config,
            "layout": self.layout,
            "metadata": {**copy_metadata(self.metadata), "coarsened_from": self.resolution, "factor": f},
            "scans_inserted": self.scans_inserted,
            "points_inserted": self.points_inserted,
        }
        return MapSnapshot.adopt(settings, coarsen_state(self.state(), self.resolution, f, self.config.n_max))
