"""Typed argument groups of the update kernels, and kernels called by keyword.

A kernel of the update takes 10-30 arrays and scalars, several of the same dtype and
shape (records' points and the free stack; ray counts and leaf flags), so a positional
call can swap two of them silently. Here the caller names each argument or hands a small
frozen group of them (``Records``, ``Block``, ...): a ``Bound`` kernel checks, once when it
is built, that its parameters are exactly the groups' fields in order, and at every call
that each keyword holds a group of the right type; it then flattens them into the
positional call of the Launcher (kernels/launch.py), whose cost per argument does not
change. Groups a variant does not use (its switch is compiled in with ``ti.static``) are
filled by the binding with shared empty arrays: callers never build placeholders.

Each field's comment gives its shape and meaning; C is the records' capacity, H the scan's
hit cells, N its points, L1 the layout's top-level regions per axis.
"""

from __future__ import annotations

import copy
import inspect
import operator
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import taichi as ti


class Group:
    """Base of the argument groups: frozen dataclasses whose fields are kernel
    parameters of the same names, in the same order."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "_args", tuple(getattr(self, f.name) for f in fields(self)))  # type: ignore[arg-type]

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))  # type: ignore[arg-type]


@dataclass(frozen=True)
class Records(Group):
    """A map's Gaussian records (numpy, outside Taichi's pool; see ndtom_ti.records)."""

    rec_n: np.ndarray  # [C] i32: points of the record's Gaussian (0: free or unused)
    rec_cell: np.ndarray  # [C, 3] i32: the record's cell index
    rec_mean: np.ndarray  # [C, 3] f64: mean minus the cell centre
    rec_scat: np.ndarray  # [C, 6] f64: scatter (sum of outer products) xx xy xz yy yz zz
    rec_free: np.ndarray  # [C] i32: stack of free records (ctr[C_FREE] of them)


@dataclass(frozen=True)
class Picked(Group):
    """The records a kernel reads (ndtom_ti.record_index): ``pick[:npick]``, then the records
    from ``tail0`` up to its record count; npick 0 and tail0 0: every record, in order."""

    pick: np.ndarray  # [P] i32: record numbers
    npick: int
    tail0: int


@dataclass(frozen=True)
class NdtRecords(Group):
    """What the NDT miss model adds to the records (config.MapConfig.miss_model "ndt")."""

    rec_miss: np.ndarray  # [C] i64: the scan's summed log-odds change per record, fixed point (MISS_SCALE)
    rec_icov: np.ndarray  # [C, 9] f64: inverse regularised covariance (6) and mean (3) that rays read
    ndt_prm: np.ndarray  # [9] f64: eta, 1 / (2 sigma_s^2), covariance floors (ndt_floor), min_points, prior (ndt_icov), line points (ndt_floor), near cells (rays)
    ndt_minp: int  # points a Gaussian needs for the miss model
    rec_nbr: np.ndarray  # [C] i32: neighbours' Gaussians erased since the record's last points


@dataclass(frozen=True)
class Nodes(Group):
    """Exact node accounting of the process's sparse trees (kernels/layout.py Storage)."""

    occ_regions: np.ndarray  # [slots, L1x, L1y, L1z] i8: occupancy-tree regions in use
    gidx_regions: np.ndarray  # [slots, L1x, L1y, L1z] i8: Gaussian-index-tree regions in use
    leaves: np.ndarray  # [slots, 2] i64: leaves of the occupancy and the index tree


@dataclass(frozen=True)
class Block(Group):
    """The scan's dense ray-count block (zero between scans), over a leaf-aligned box."""

    block: np.ndarray  # [Bx, By, Bz] u16 or i32: rays that passed each cell
    bflag: np.ndarray  # [Bx, By, Bz / leaf] i8: rows of `leaf` cells along z that rays entered
    base: np.ndarray  # [3] i32: cell index of block[0, 0, 0]
    block1: np.ndarray  # [Bx * By * Bz]: ``block``, flat (the rays step a flat index in it)
    bflag1: np.ndarray  # [Bx * By * Bz / leaf]: ``bflag``, flat

    @classmethod
    def of(cls, block: np.ndarray, bflag: np.ndarray, base: np.ndarray) -> Block:
        return cls(block, bflag, base, block.reshape(-1), bflag.reshape(-1))


@dataclass(frozen=True)
class Rays(Group):
    """The rays of a scan (or of one batch of it): hits first, then free rays."""

    pts: np.ndarray  # [N, 3] f64: world endpoints
    cells: np.ndarray  # [N, 3] i32: endpoint cells
    n_hit: int  # rays [0, n_hit) end in a hit; the rest are free rays
    n: int  # rays


@dataclass(frozen=True)
class Sensor(Group):
    origin: np.ndarray  # [3] f64: world sensor origin
    ocell: np.ndarray  # [3] i32: its cell
    res: float  # cell size (m)
    sbox: np.ndarray  # [8 * 6] i32: each octant's settled box (trace.settled_growth); lo > hi: none


@dataclass(frozen=True)
class Touched(Group):
    """Cells of the tree that rays touched first in this scan (for eq. 12's second pass)."""

    touched: np.ndarray  # [cap, 3] i32: the cells (the first ctr[C_TOUCHED], if <= cap)
    cap: int  # its rows


@dataclass(frozen=True)
class Model(Group):
    """The sensor model's log-odds terms (eq. 12) and clamp."""

    l_hit: float  # per point of a cell (f64)
    l_free: float  # per ray passing a cell (f64)
    l_min: float  # clamp (f32)
    l_max: float


@dataclass(frozen=True)
class TreeSums(Group):
    """Hit cells counted and summed in the Gaussian index tree (hits_count, hits_sum)."""

    acc: np.ndarray  # [H, 9] f64: sum q (3), sum q q^T (6), q = point - cell centre


@dataclass(frozen=True)
class GroupedHits(Group):
    """Hit cells whose points hits_dense grouped in the dense block, or hits_group in the
    tree after hits_count (merge sorts and sums them, cell_sums)."""

    hcnt: np.ndarray  # [H] i32: points per hit cell
    off: np.ndarray  # [H] i32: where each hit cell's points start in ``order``
    order: np.ndarray  # [N] i32: the hit points grouped by cell (merge sorts each cell's)
    pts: np.ndarray  # [N, 3] f64: world points of the hits
    in_tree: int  # 1: counted in the tree (hits_count; merge clears its counts), 0: in the block (hits_dense)


def _empty(dtype, ndim: int) -> np.ndarray:
    return np.zeros((1,) * ndim, dtype)


# Stand-ins for groups a compiled variant never reads (one per process, never written).
EMPTY: dict[type, Group] = {
    NdtRecords: NdtRecords(_empty(np.int64, 1), _empty(np.float64, 2), np.zeros(5), 0, _empty(np.int32, 1)),
    TreeSums: TreeSums(_empty(np.float64, 2)),
    GroupedHits: GroupedHits(_empty(np.int32, 1), _empty(np.int32, 1), _empty(np.int32, 1), _empty(np.float64, 2), 0),
}


def _whole(t: tuple) -> tuple:
    return t


class Bound:
    """A Taichi kernel called by keyword. ``parts``: the kernel's parameters in order,
    each ``name`` (one argument) or ``(name, GroupType)`` (that group's fields), or
    ``(name, GroupType, fields)`` (only those fields); with name None, a group the
    variant does not read, passed as a shared empty stand-in."""

    def __init__(self, func, parts: tuple):
        self.name = func.__name__
        self.kernel = ti.kernel(func)
        self.call = self.kernel  # how it is launched (see launched)
        flat: list[str] = []
        plan = []
        for p in parts:
            if isinstance(p, str):
                flat.append(p)
                plan.append((p, None, None))
                continue
            name, typ, *sel = p
            use = tuple(sel[0]) if sel else typ.names()
            unknown = set(use) - set(typ.names())
            if unknown:
                raise TypeError(f"{self.name}: {typ.__name__} has no fields {sorted(unknown)}")
            flat.extend(use)
            idx = [typ.names().index(u) for u in use]
            if use == typ.names():
                get = _whole
            elif len(idx) == 1:
                get = lambda t, g=operator.itemgetter(idx[0]): (g(t),)
            else:
                get = operator.itemgetter(*idx)
            if name is None:  # a group this variant does not read: its stand-in's fields
                plan.append((None, typ, get(EMPTY[typ]._args)))
            else:
                plan.append((name, typ, get))
        params = list(inspect.signature(func).parameters)
        if flat != params:
            raise TypeError(f"kernel {self.name}: parameters {params} do not match its argument groups {flat}")
        self._plan = tuple(plan)
        self.keywords = frozenset(p[0] for p in plan if p[0] is not None)

    def launched(self, wrap) -> Bound:
        """The same kernel (compiled once), launched through ``wrap(kernel)``."""
        out = copy.copy(self)
        out.call = wrap(self.kernel)
        return out

    def __call__(self, **kw: Any):
        args: list = []
        for name, typ, get in self._plan:
            if name is None:  # a group this variant does not read
                args.extend(get)
                continue
            try:
                v = kw.pop(name)
            except KeyError:
                raise TypeError(f"{self.name}() missing argument {name!r}") from None
            if typ is None:
                args.append(v)
            elif type(v) is not typ:
                raise TypeError(f"{self.name}(): {name} must be a {typ.__name__}, got {type(v).__name__}")
            else:
                args.extend(get(v._args))
        if kw:
            raise TypeError(f"{self.name}() got unexpected arguments {sorted(kw)}")
        return self.call(*args)
