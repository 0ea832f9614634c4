"""Sensor model and map options."""

from __future__ import annotations

import math
import numbers
import sys
from dataclasses import asdict, dataclass, fields
from typing import NoReturn

import numpy as np

MISS_MODELS = ("ndt", "paper")
# NDT miss model: sigma_s when the config leaves it to the map, in cells (3 m at 0.2 m), and
# never below SIGMA_S_MIN metres: an indoor depth camera's rays graze the walls they end on
# over their last metre or two whatever the cell (docs/quality.md).
SIGMA_S_CELLS = 15.0
SIGMA_S_MIN = 1.5
# NDT miss model: variance added on every axis of a Gaussian's covariance before it is
# inverted (kernels.ndt.ndt_floor; eigenvalues l1 <= l2 <= l3): NDT_COV_FLOOR * trace keeps
# flat Gaussians invertible; a line-like one (l2 < NDT_LINE * l3: the points of one scan line
# across the cell, at the ranges where a lidar's rings are a cell or more apart) gets up to
# NDT_LINE_FLOOR * l3 more, so that it stands for the surface the line samples. Without it,
# rays of the other rings never pass within the line's millimetre thickness and the
# Gaussians of objects that left stay (benchmarks/quality.py; docs/quality.md). A line
# spanning the cell (l3 ~ r^2 / 12) then stands for a surface spread evenly over the cell.
# With n points the widening is scaled by min(1, NDT_LINE_POINTS / n): a line that stays a
# line as points join it (a shelf's edge seen from many poses) is a thin structure, and rays
# passing beside it are not evidence against it. NDT_COV_FLOOR (2% of the trace: ~1.2 cm
# across a plane filling a 0.2 m cell) also makes rays that graze a face a few centimetres
# off count a little, as through the flat top of an object that left.
NDT_COV_FLOOR = 0.02
NDT_LINE = 0.5
NDT_LINE_FLOOR = 1.0
NDT_LINE_POINTS = 4.0
# NDT miss model, cells holding fewer than min_points points: their points' mean with this
# standard deviation (metres) added on every axis, so that sparse floor cells are not erased
# by rays grazing far above their points, while a ray passing close to them still clears them.
NDT_SPARSE_SIGMA = 0.05
# Bounds that keep every setting inside the kernels' types (one check, in MapConfig, for the
# API, map files and --config). N_LIMIT: the most points a Gaussian holds; counts are int32
# in the kernels, and the room above it takes a scan's hits without wrapping.
INT32_MAX = 2**31 - 1
N_LIMIT = 2**30
RANGE_LIMIT = 1e15  # metres: min_range and a finite max_range (their squares stay finite)
SIGMA_S_LIMITS = (1e-6, 1e6)  # metres
RESOLUTION_MAX = 1e6  # metres: 1000 km cells
_F32_MAX = 3.4028234663852886e38
_NORMAL_MIN = sys.float_info.min


@dataclass(frozen=True)
class MapConfig:
    """Options of an NDT-OM.

    Defaults for ``p_occupied``, ``p_empty`` and ``min_points`` are the paper's
    (Saarinen et al., ICRA 2013, sec. III and IV: p_o = 0.6, p_e = 0.49, 3 points per
    Gaussian). The paper gives no clamp; we clamp log-odds to [-2.0, 2.0] (p in
    [0.12, 0.88]) so that, with the paper's miss model (p_e per ray), a cell of an object
    that left is cleared after ~50 rays pass it (a few scans of a 32-beam lidar) while a
    wall hit by ~5 points per scan needs ~10 such scans of misses in a row to lose its
    Gaussian. The default miss model, ``"ndt"``, lowers a cell by how squarely each ray
    passes its Gaussian (``miss_model``, ``eta``, ``sigma_s``; docs/sensor-model.md).
    """

    p_occupied: float = 0.6  # p_o: probability a cell holding an endpoint is occupied
    p_empty: float = 0.49  # p_e: probability a cell a ray passes is occupied
    logodds_min: float = -2.0
    logodds_max: float = 2.0
    min_points: int = 3  # a Gaussian needs at least this many points
    min_range: float = 0.0  # points closer to the sensor are dropped (metres)
    max_range: float = math.inf  # points farther are dropped, or carved as free rays
    max_range_mode: str = "drop"  # "drop" | "free": free rays clipped at max_range, no hit
    n_max: int = 0  # cap on N (adaptive Gaussians, method.md sec. 2); 0 disables
    # How a ray passing a cell that holds a Gaussian of >= min_points points lowers it:
    # "ndt": by how squarely it passes the Gaussian (Saarinen et al., IJRR 2013, eqs.
    # 22-24); "paper": by p_empty per ray, as every other cell (ICRA 2013, eq. 12). "ndt"
    # by default: against ground truth it keeps far fewer Gaussians of objects that left
    # and far more of the static surface, at ~1.2x the time per scan (docs/quality.md).
    miss_model: str = "ndt"
    # NDT miss model: a ray's point of highest likelihood x_ML within sigma_s metres of its
    # own endpoint is no evidence of emptiness; None: SIGMA_S_CELLS cells of the map (3 m
    # at 0.2 m), at least SIGMA_S_MIN. ohm uses its range noise, 0.05 m, which erased
    # sparse floor cells: a ray that grazes the surface it ends on passes just above its
    # Gaussians over a last stretch that grows with the cell (docs/quality.md).
    sigma_s: float | None = None
    # NDT miss model: the strongest evidence of one ray, p = 0.5 - eta for a ray through a
    # Gaussian's mean (ohm: 0.2, from its p_miss 0.4); 0.32 clears objects that left, most
    # seen by a few rays only, while one stray ray still cannot erase a saturated cell
    # (-1.5 against +2; docs/quality.md).
    eta: float = 0.32

    def __post_init__(self) -> None:
        def bad(msg: str) -> NoReturn:
            raise ValueError(f"MapConfig: {msg}")

        # Types first (a config file may hold "0.6" or [1]): comparisons below need numbers.
        # Numbers become plain floats or ints here, so that no value reaches a kernel as an
        # int too big for a float (2**1100), a float where an int is needed, or a numpy scalar.
        for f in fields(self):
            value, default = getattr(self, f.name), f.default
            if value is None and default is None:
                continue
            if isinstance(default, str):
                if not isinstance(value, str):
                    bad(f"{f.name} must be a string, got {value!r}")
                continue
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                bad(f"{f.name} must be a number, got {value!r} ({type(value).__name__})")
            try:
                as_float = float(value)
            except (OverflowError, ValueError):
                bad(f"{f.name} must be a finite number, got {value!r}")
            if isinstance(default, int):
                if not (math.isfinite(as_float) and as_float == int(as_float)):
                    bad(f"{f.name} must be a finite integer, got {value!r}")
                # an integral float (3.0, from JSON) is taken as the integer it is
                object.__setattr__(self, f.name, int(value) if isinstance(value, numbers.Integral) else int(as_float))
            else:
                if abs(as_float) < _NORMAL_MIN:  # a subnormal number is 0 where Taichi has the CPU flush them
                    as_float = 0.0
                object.__setattr__(self, f.name, as_float)

        if not 0.5 < self.p_occupied < 1.0:
            bad(f"p_occupied must be in (0.5, 1), got {self.p_occupied}")
        if not 0.0 < self.p_empty < 0.5:
            bad(f"p_empty must be in (0, 0.5), got {self.p_empty}")
        if not (math.isfinite(self.logodds_min) and math.isfinite(self.logodds_max)):
            bad("log-odds clamps must be finite")
        # the kernels hold log-odds as float32: the clamps must be float32 numbers on either side of 0
        if not -_F32_MAX <= self.logodds_min < 0.0 < self.logodds_max <= _F32_MAX:
            bad(f"need logodds_min < 0 < logodds_max, got {self.logodds_min}, {self.logodds_max}")
        if not (float(np.float32(self.logodds_min)) < 0.0 < float(np.float32(self.logodds_max))):
            bad(f"log-odds clamps {self.logodds_min}, {self.logodds_max} are 0 as 32-bit floats")
        if not 1 <= self.min_points <= N_LIMIT:
            bad(f"min_points must be a positive integer (at most {N_LIMIT}), got {self.min_points:.6g}")
        if not (0.0 <= self.min_range <= RANGE_LIMIT):
            bad(f"min_range must be finite, >= 0 and at most {RANGE_LIMIT:g} m, got {self.min_range}")
        if not (self.max_range <= RANGE_LIMIT or self.max_range == math.inf):
            bad(f"max_range must be at most {RANGE_LIMIT:g} m, or inf (null) for no limit, got {self.max_range}")
        if not self.max_range > self.min_range:
            bad(f"max_range must be > min_range, got {self.max_range} <= {self.min_range}")
        if self.max_range_mode not in ("drop", "free"):
            bad(f"max_range_mode must be 'drop' or 'free', got {self.max_range_mode!r}")
        if self.max_range_mode == "free" and not math.isfinite(self.max_range):
            bad("max_range_mode='free' needs a finite max_range")
        if not (self.n_max == 0 or 2 <= self.n_max <= N_LIMIT):
            bad(f"n_max must be 0 (off) or an integer from 2 to {N_LIMIT}, got {self.n_max:.6g}")
        if 0 < self.n_max < self.min_points:  # N would never reach min_points: no cell ever holds a Gaussian
            bad(
                f"n_max ({self.n_max}) must be at least min_points ({self.min_points}), or 0 (no cap); "
                "raise n_max or lower min_points"
            )
        if self.miss_model not in MISS_MODELS:
            bad(f"miss_model must be one of {MISS_MODELS}, got {self.miss_model!r}")
        lo, hi = SIGMA_S_LIMITS
        if self.sigma_s is not None and not (lo <= self.sigma_s <= hi):
            bad(
                f"sigma_s must be a positive number of metres, from {lo:g} to {hi:g} (or None: {SIGMA_S_CELLS:g} cells, "
                f"at least {SIGMA_S_MIN:g} m), got {self.sigma_s!r}"
            )
        if not 0.0 < self.eta < 0.5:
            bad(f"eta must be in (0, 0.5), got {self.eta!r}")

    def check_at(self, resolution: float) -> None:
        """The settings that depend on the map's resolution: with the NDT miss model, sigma_s
        in cells must fit the kernels' 32-bit integers. ValueError otherwise."""
        cells = self.sigma_s_at(resolution) / float(resolution)
        if self.ndt_misses and not cells <= N_LIMIT:
            raise ValueError(
                f"MapConfig: sigma_s {self.sigma_s_at(resolution):g} m is {cells:.3g} cells of {resolution:g} m, "
                f"more than the kernels count ({N_LIMIT}); give a smaller sigma_s or a coarser resolution"
            )

    @property
    def l_hit(self) -> float:
        return math.log(self.p_occupied / (1.0 - self.p_occupied))

    @property
    def l_free(self) -> float:
        return math.log(self.p_empty / (1.0 - self.p_empty))

    @property
    def ndt_misses(self) -> bool:
        return self.miss_model == "ndt"

    def sigma_s_at(self, resolution: float) -> float:
        """The NDT miss model's sigma_s in metres for a map of this resolution."""
        if self.sigma_s is None:
            return max(SIGMA_S_CELLS * float(resolution), SIGMA_S_MIN)
        return float(self.sigma_s)

    def near_cells_at(self, resolution: float) -> int:
        """NDT miss model: the cells before a hit ray's endpoint cell (by L1 distance) whose
        Gaussians it does not test: a quarter of sigma_s, rounded (4 at the default). There
        x_ML lies within about half of sigma_s of the endpoint, p(x_ML|z) is near 1, and the
        ray runs along the surface it ends on (docs/quality.md)."""
        return math.floor(0.25 * self.sigma_s_at(resolution) / float(resolution) + 0.5)

    def ndt_params(self, resolution: float) -> np.ndarray:
        """The NDT miss model's kernel parameters at this resolution (kernels/args.py
        NdtRecords.ndt_prm, read by kernels/ndt.py in this order)."""
        return np.array(
            [
                self.eta,
                0.5 / self.sigma_s_at(resolution) ** 2,
                NDT_COV_FLOOR,
                NDT_LINE,
                NDT_LINE_FLOOR,
                self.min_points,
                NDT_SPARSE_SIGMA**2,
                NDT_LINE_POINTS,
                self.near_cells_at(resolution),
            ]
        )

    @property
    def ndt_min_points(self) -> int:
        """Points a cell needs for the NDT miss model (1: every cell with points, those with
        fewer than min_points under the sparse prior); 0: the paper's model (a kernel switch)."""
        return 1 if self.ndt_misses else 0

    def to_dict(self) -> dict:
        d = asdict(self)
        if math.isinf(d["max_range"]):
            d["max_range"] = None
        return d

    @classmethod
    def from_dict(cls, d: dict) -> MapConfig:
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"MapConfig: unknown options {sorted(unknown)}; known: {sorted(known)}")
        d = dict(d)
        if d.get("max_range", 0.0) is None:
            d["max_range"] = math.inf
        return cls(**d)


def config_of(config: object, options: dict) -> MapConfig:
    """A new map's MapConfig: ``config``, or one made of keyword ``options`` (MapConfig's
    fields; what was left out keeps its default). TypeError for both, an unknown option or a
    ``config`` that is no MapConfig."""
    if config is not None and options:
        raise TypeError("pass either config=MapConfig(...) or keyword options, not both")
    if options:
        unknown = sorted(set(options) - {f.name for f in fields(MapConfig)})
        if unknown:
            raise TypeError(
                f"unknown map options {unknown}; the options are MapConfig's: "
                f"{', '.join(f.name for f in fields(MapConfig))}"
            )
    out = config if config is not None else MapConfig(**options)
    if not isinstance(out, MapConfig):
        raise TypeError(f"config must be a MapConfig, got {type(out).__name__}")
    return out


def check_resolution(resolution: object, name: str = "resolution") -> float:
    """``resolution`` as a float of metres: a TypeError for anything but a real number
    (bools included), a ValueError for one that is not finite and positive. ``name`` is
    how the caller's user knows the value (e.g. ``-r/--resolution``). The one check of
    every resolution the package takes."""
    if isinstance(resolution, bool) or not isinstance(resolution, numbers.Real):
        raise TypeError(f"{name} must be a number of metres, got {type(resolution).__name__}")
    try:
        value = float(resolution)
    except OverflowError:
        value = math.inf
    # (an upper bound: squares and sums of cell sizes must stay finite)
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"{name} must be a positive number of metres, got {value}")
    if value > RESOLUTION_MAX:
        raise ValueError(f"{name} must be at most {RESOLUTION_MAX:g} metres, got {value}")
    return value


def check_gaussian_filter(min_points: object, min_probability: object, default_min_points: int) -> tuple[int, float]:
    """The ``min_points`` (None: ``default_min_points``) and ``min_probability`` of a Gaussians
    query, checked: an integer >= 0 and a number in [0, 1] (NaN fails: it would keep every
    Gaussian)."""
    if min_points is None:
        min_points = default_min_points
    if isinstance(min_points, bool) or not isinstance(min_points, numbers.Integral) or min_points < 0:
        raise ValueError(f"min_points must be an integer >= 0, got {min_points!r}")
    p = float(min_probability) if isinstance(min_probability, numbers.Real) else math.nan
    if isinstance(min_probability, bool):
        p = math.nan
    if not (0.0 <= p <= 1.0):
        raise ValueError(f"min_probability must be a number in [0, 1], got {min_probability!r}")
    return int(min_points), p
