"""Export a map: its Gaussians (PLY, PCD, npz, CSV), its cells as an OctoMap tree (.bt), or
a 2-D occupancy grid of a height band (PGM + YAML, as ROS map_server reads).

Every writer writes atomically (a temporary file in the target folder, renamed over the
target), so a failed export never leaves a half-written file. The Gaussian writers take
the dict of :meth:`NdtOmMap.gaussians` (``index``, ``mean``, ``cov``, ``n``, ``p_occ``,
``logodds``). :func:`export_file` takes a map or a :class:`~ndtom_ti.snapshot.MapSnapshot`
(the same files: a snapshot answers ``gaussians()`` and ``known_cells()`` as its map does,
without a map slot or Taichi).

- PLY: binary little endian; one vertex per Gaussian at its mean, properties
  ``x y z`` (float32), ``red green blue`` (uchar: the height ramp below), ``p_occ``
  (float32), ``n`` (int32) and the covariance terms
  ``cov_xx cov_xy cov_xz cov_yy cov_yz cov_zz`` (float32, m^2).
- PCD (PCL 0.7, binary): one point per Gaussian mean, fields ``x y z`` (float32), ``n``
  (uint32, points in the cell) and ``p_occ`` (float32).
- npz: ``index`` (K, 3) int64, ``mean`` (K, 3) float64, ``cov`` (K, 3, 3) float64,
  ``n`` (K,) int64, ``p_occ`` and ``logodds`` (K,) float64, ``resolution`` (scalar) and
  ``metadata`` (the map's metadata as a JSON string).
- CSV: a header line, then one row per Gaussian:
  ``i,j,k,x,y,z,n,p_occ,logodds,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz``.
- bt: OctoMap's binary tree (what octovis and octomap_server load): every known cell as an
  occupied or free leaf at the map's resolution. OctoMap's tree has 16 levels centred on
  the origin and its leaf key is ``floor(x / resolution) + 32768`` per axis, so map cell
  ``(i, j, k)`` is exactly the leaf of key ``(i, j, k) + 32768``. Eight sibling leaves of one
  state are merged into their parent, as OctoMap's own writer does. Its keys reach +-32768
  cells from the origin (+-3276.8 m at 0.1 m); a map's default grid is half that.
- grid: an image ``NAME.pgm`` (P5; 0 occupied, 254 free, 205 unknown) and ``NAME.yaml``
  (map_server: ``mode: trinary``, origin = the lower-left pixel, the image's name quoted
  where YAML needs it: ``run #3.pgm``). A column of cells is occupied when a cell of the
  height band is, free when a cell of the band is known free and none is occupied,
  unknown otherwise. The band is ``[z_min, z_max]`` in the map
  frame, or by default 0.3 to 2 m above a floor plane fitted to the map (which may be
  tilted: a lidar's start pose is often the map frame).

Occupied means ``p_occ > max(min_probability, 0.5)``; free means ``p_occ < 0.5``; cells in
between are left unknown in ``bt`` and ``grid``.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import IO, Any

import numpy as np

from .atomic import atomic_write, check_target
from .frames import as_frame_origin

__all__ = [
    "COV_TERMS",
    "FORMATS",
    "HEIGHT_RAMP",
    "PLY_PROPERTIES",
    "SUFFIXES",
    "Exported",
    "Grid",
    "export_file",
    "export_map",
    "floor_plane",
    "format_for",
    "grid_paths",
    "height_colors",
    "occupancy_grid",
    "octree_stream",
    "write_bt",
    "write_csv",
    "write_grid",
    "write_npz",
    "write_pcd",
    "write_ply",
]

FORMATS = ("ply", "pcd", "npz", "csv", "bt", "grid")
SUFFIXES = {
    ".ply": "ply",
    ".pcd": "pcd",
    ".npz": "npz",
    ".csv": "csv",
    ".bt": "bt",
    ".pgm": "grid",
    ".yaml": "grid",
    ".yml": "grid",
}
DEFAULT_SUFFIX = {"ply": ".ply", "pcd": ".pcd", "npz": ".npz", "csv": ".csv", "bt": ".bt", "grid": ".pgm"}
COV_TERMS = ("cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz")
_COV_IJ = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
PLY_PROPERTIES = (
    ("x", "float", "<f4"),
    ("y", "float", "<f4"),
    ("z", "float", "<f4"),
    ("red", "uchar", "u1"),
    ("green", "uchar", "u1"),
    ("blue", "uchar", "u1"),
    ("p_occ", "float", "<f4"),
    ("n", "int", "<i4"),
    *((name, "float", "<f4") for name in COV_TERMS),
)
# Height colours: blue, cyan, green, yellow, red at equal steps from the low to the high
# end of the height range (the 1st and 99th percentile of the means' z).
HEIGHT_RAMP = ((0, 0, 255), (0, 255, 255), (0, 255, 0), (255, 255, 0), (255, 0, 0))


def format_for(path: str | Path | None, fmt: str | None = None) -> str:
    """The export format of ``path``: ``fmt`` when given, else from the suffix. An unknown
    format or suffix, or a suffix that names another format than ``fmt``, is a ValueError."""
    known = ", ".join(FORMATS)
    suffixes = ", ".join(SUFFIXES)
    if fmt is not None:
        fmt = fmt.lower()
        if fmt not in FORMATS:
            raise ValueError(f"unknown export format {fmt!r}; choose one of {known}")
    if path is None:
        return fmt or "ply"
    suffix = Path(path).suffix.lower()
    by_suffix = SUFFIXES.get(suffix)
    if fmt is None:
        if by_suffix is None:
            what = f"suffix {suffix!r}" if suffix else "no suffix"
            raise ValueError(
                f"cannot tell the export format of {path} ({what}); use one of the suffixes "
                f"{suffixes} or give the format ({known})"
            )
        return by_suffix
    if by_suffix is not None and by_suffix != fmt:
        raise ValueError(
            f"{path} has the suffix of the {by_suffix} format but the format asked for is {fmt}; "
            f"use the suffix {DEFAULT_SUFFIX[fmt]} or leave the format out"
        )
    return fmt


def _cov6(cov: np.ndarray) -> np.ndarray:
    cov = np.asarray(cov, np.float64).reshape(-1, 3, 3)
    return np.stack([cov[:, a, b] for a, b in _COV_IJ], axis=1)


def height_colors(z: Any, z_range: tuple[float, float] | None = None) -> tuple[np.ndarray, tuple[float, float]]:
    """RGB (K, 3) uint8 of heights ``z`` on :data:`HEIGHT_RAMP`, and the (low, high) range
    used: ``z_range`` or the 1st and 99th percentile of ``z``."""
    z = np.asarray(z, np.float64).reshape(-1)
    if z_range is None:
        z_range = (float(np.percentile(z, 1)), float(np.percentile(z, 99))) if len(z) else (0.0, 1.0)
    lo, hi = z_range
    t = np.clip((z - lo) / (hi - lo), 0.0, 1.0) if hi > lo else np.zeros_like(z)
    steps = np.linspace(0.0, 1.0, len(HEIGHT_RAMP))
    ramp = np.asarray(HEIGHT_RAMP, np.float64)
    rgb = np.stack([np.interp(t, steps, ramp[:, c]) for c in range(3)], axis=1)
    return np.rint(rgb).astype(np.uint8), (lo, hi)


def write_ply(
    g: dict, path: str | Path, *, comment: str | None = None, z_range: tuple[float, float] | None = None
) -> Path:
    """Binary little-endian PLY: one vertex per Gaussian, coloured by height (module doc)."""
    k = len(g["n"])
    dt = np.dtype([(name, code) for name, _, code in PLY_PROPERTIES])
    v = np.zeros(k, dt)
    mean = np.asarray(g["mean"], np.float64).reshape(-1, 3)
    v["x"], v["y"], v["z"] = mean[:, 0], mean[:, 1], mean[:, 2]
    rgb, (lo, hi) = height_colors(mean[:, 2], z_range)
    v["red"], v["green"], v["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    v["p_occ"] = g["p_occ"]
    v["n"] = g["n"]
    c6 = _cov6(g["cov"])
    for j, name in enumerate(COV_TERMS):
        v[name] = c6[:, j]
    lines = ["ply", "format binary_little_endian 1.0"]
    if comment:
        lines += [f"comment {line}" for line in comment.splitlines()]
    lines.append(f"comment colour: height, blue at z <= {lo:.3f} m to red at z >= {hi:.3f} m")
    lines.append(f"element vertex {k}")
    lines += [f"property {ptype} {name}" for name, ptype, _ in PLY_PROPERTIES]
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii", errors="replace")

    def write(fh: IO[bytes]) -> None:
        fh.write(header)
        fh.write(v.tobytes())

    return atomic_write(path, write)


def write_pcd(g: dict, path: str | Path, *, comment: str | None = None) -> Path:
    """PCL's PCD 0.7, binary: one point per Gaussian mean with ``n`` and ``p_occ``;
    ``comment``: header lines (``#``) after the first."""
    k = len(g["n"])
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("n", "<u4"), ("p_occ", "<f4")])
    v = np.zeros(k, dt)
    mean = np.asarray(g["mean"], np.float64).reshape(-1, 3)
    v["x"], v["y"], v["z"] = mean[:, 0], mean[:, 1], mean[:, 2]
    v["n"] = np.asarray(g["n"], np.int64)
    v["p_occ"] = g["p_occ"]
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\n"
        + "".join(f"# {line}\n" for line in (comment or "").splitlines())
        + "VERSION 0.7\n"
        "FIELDS x y z n p_occ\n"
        "SIZE 4 4 4 4 4\n"
        "TYPE F F F U F\n"
        "COUNT 1 1 1 1 1\n"
        f"WIDTH {k}\n"
        "HEIGHT 1\n"
        "VIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {k}\n"
        "DATA binary\n"
    ).encode("ascii")

    def write(fh: IO[bytes]) -> None:
        fh.write(header)
        fh.write(v.tobytes())

    return atomic_write(path, write)


def write_npz(g: dict, path: str | Path, *, resolution: float | None = None, metadata: dict | None = None) -> Path:
    """All arrays of the Gaussians (see the module doc), uncompressed npz."""
    arrays: dict[str, Any] = {
        "index": np.asarray(g["index"], np.int64).reshape(-1, 3),
        "mean": np.asarray(g["mean"], np.float64).reshape(-1, 3),
        "cov": np.asarray(g["cov"], np.float64).reshape(-1, 3, 3),
        "n": np.asarray(g["n"], np.int64),
        "p_occ": np.asarray(g["p_occ"], np.float64),
        "logodds": np.asarray(g["logodds"], np.float64),
    }
    if resolution is not None:
        arrays["resolution"] = np.float64(resolution)
    if metadata is not None:
        arrays["metadata"] = np.array(json.dumps(metadata, default=str))
    return atomic_write(path, lambda fh: np.savez(fh, **arrays))


CSV_COLUMNS = ("i", "j", "k", "x", "y", "z", "n", "p_occ", "logodds", *COV_TERMS)


def write_csv(g: dict, path: str | Path) -> Path:
    """One row per Gaussian with a header line (see the module doc)."""
    idx = np.asarray(g["index"], np.int64).reshape(-1, 3)
    mean = np.asarray(g["mean"], np.float64).reshape(-1, 3)
    n = np.asarray(g["n"], np.int64)
    p = np.asarray(g["p_occ"], np.float64)
    lo = np.asarray(g["logodds"], np.float64)
    c6 = _cov6(g["cov"])

    def write(fh: IO[bytes]) -> None:
        fh.write((",".join(CSV_COLUMNS) + "\n").encode())
        # repr of float64 round-trips exactly
        for r in range(len(n)):
            row = [
                *map(str, idx[r].tolist()),
                *map(repr, mean[r].tolist()),
                str(int(n[r])),
                repr(float(p[r])),
                repr(float(lo[r])),
                *map(repr, c6[r].tolist()),
            ]
            fh.write((",".join(row) + "\n").encode())

    return atomic_write(path, write)


# ---------------------------------------------------------------------------- OctoMap .bt
_OCTO_DEPTH = 16
_OCTO_OFFSET = 1 << (_OCTO_DEPTH - 1)  # OctoMap's tree_max_val: key = floor(x / res) + 32768
_FREE, _OCCUPIED, _INNER = 1, 2, 3  # the 2-bit child codes of OctoMap's binary stream


def _spread3(v: np.ndarray) -> np.ndarray:
    """Bits of 16-bit integers spread to every third bit (Morton interleave)."""
    v = v.astype(np.uint64) & np.uint64(0xFFFF)
    for shift, mask in ((16, 0x0000FF0000FF), (8, 0x00F00F00F00F), (4, 0x0C30C30C30C3), (2, 0x249249249249)):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def octree_stream(index: Any, occupied: Any) -> tuple[int, bytes]:
    """OctoMap's binary tree of leaves at cell ``index`` (K, 3) (occupied or free):
    (number of nodes, the bit stream). Depth-first, children 0..7 (bit 0: x, 1: y, 2: z of
    the key at that level); per node two bytes of 2-bit child codes."""
    idx = np.asarray(index, np.int64).reshape(-1, 3)
    if len(idx) == 0:
        return 0, b""
    key = idx + _OCTO_OFFSET
    if (key < 0).any() or (key >= 1 << _OCTO_DEPTH).any():
        raise ValueError(
            f"cells beyond OctoMap's tree ({_OCTO_DEPTH} levels: cell indices in "
            f"[-{_OCTO_OFFSET}, {_OCTO_OFFSET}) per axis); use a coarser map"
        )
    code = _spread3(key[:, 0]) | (_spread3(key[:, 1]) << np.uint64(1)) | (_spread3(key[:, 2]) << np.uint64(2))
    order = np.argsort(code, kind="stable")
    code = code[order]
    if len(code) > 1 and (code[1:] == code[:-1]).any():
        raise ValueError("a cell is given twice")
    state = np.where(np.asarray(occupied, bool).reshape(-1)[order], _OCCUPIED, _FREE).astype(np.uint16)
    full, depth, bits = [], [], []
    for d in range(_OCTO_DEPTH, 0, -1):  # nodes at depth d; their parents at d - 1
        parent = code >> np.uint64(3)
        pos = (code & np.uint64(7)).astype(np.uint16)
        starts = np.flatnonzero(np.r_[True, parent[1:] != parent[:-1]])
        v = np.bitwise_or.reduceat(state << (2 * pos), starts).astype(np.uint16)
        code = parent[starts]
        # eight leaves of one state merge into their parent (OctoMap's prune)
        state = np.where(v == 0x5555, _FREE, np.where(v == 0xAAAA, _OCCUPIED, _INNER)).astype(np.uint16)
        inner = state == _INNER
        full.append(code[inner] << np.uint64(3 * (_OCTO_DEPTH - d + 1)))
        depth.append(np.full(int(inner.sum()), d - 1, np.int8))
        bits.append(v[inner])
    full_a, depth_a, bits_a = np.concatenate(full), np.concatenate(depth), np.concatenate(bits)
    if len(bits_a) == 0:  # every leaf merged up to the root: nothing OctoMap can store
        raise ValueError("the cells fill OctoMap's whole tree")
    pre = np.lexsort((depth_a, full_a))  # depth-first pre-order: a node before its subtree
    bits_a = bits_a[pre]
    children = ((bits_a | (bits_a >> 1)) & 0x5555).astype(np.uint16)
    n_children = np.unpackbits(children.view(np.uint8)).sum(dtype=np.int64)
    return 1 + int(n_children), bits_a.astype("<u2").tobytes()


def write_bt(index: Any, occupied: Any, resolution: float, path: str | Path, comment: str | None = None) -> Path:
    """OctoMap binary tree (``.bt``) of cells ``index`` (K, 3) at ``resolution`` (module doc);
    ``comment``: one more header comment line (OctoMap's reader skips them)."""
    idx, r = np.asarray(index, np.int64).reshape(-1, 3), float(resolution)
    if len(idx) and (idx.min() < -_OCTO_OFFSET or idx.max() >= _OCTO_OFFSET):
        # only a map of a larger grid than the default (Layout) reaches this: say it in metres
        reach = max(-int(idx.min()), int(idx.max()) + 1) * r
        limit = _OCTO_OFFSET * r
        fits = r * 2 ** math.ceil(math.log2(reach / limit))
        raise ValueError(
            f"the map's cells reach {reach:.1f} m from its origin, past OctoMap's tree ({_OCTO_DEPTH} levels of "
            f"keys: +-{limit:g} m at {r:g} m cells); its map coarsened to {fits:g} m cells fits (coarsen), "
            "or export another format"
        )
    size, data = octree_stream(idx, occupied)
    header = (
        "# Octomap OcTree binary file\n"
        "# written by ndtom_ti: known cells of an NDT Occupancy Map, occupied or free\n"
        + (f"# {comment}\n" if comment else "")
        + f"id OcTree\nsize {size}\nres {float(resolution)!r}\ndata\n"
    ).encode("ascii")

    def write(fh: IO[bytes]) -> None:
        fh.write(header)
        fh.write(data)

    return atomic_write(path, write)


# ---------------------------------------------------------------------------- 2-D grid
@dataclass
class Grid:
    """A 2-D occupancy grid: ``image`` (H, W) uint8, row 0 at the largest y (as written to
    PGM); ``origin`` (x, y) of the lower-left corner of the lower-left pixel (metres)."""

    image: np.ndarray
    resolution: float
    origin: tuple[float, float]
    z_band: tuple[float, float]  # metres: map-frame heights, or heights above the floor plane
    band: str  # the band in words
    z_band_note: str = ""  # how the floor was found, for a band above it
    origin_note: str = ""  # what frame ``origin`` is in, when not the map's

    OCCUPIED = 0
    FREE = 254
    UNKNOWN = 205


MAX_GRID_PIXELS = 1 << 28


def floor_plane(m: Any, *, min_probability: float = 0.5) -> tuple[np.ndarray, str]:
    """The floor as a plane ``z = a + b x + c y`` (returns ``[a, b, c]`` and a note): the
    lowest occupied Gaussians of 1 m tiles, fitted by RANSAC (inliers within 0.15 m, tilt
    at most 15 degrees) and least squares on the inliers. Tilted map frames (a sensor's
    start pose as the map frame) get a tilted floor. A map without occupied Gaussians (too
    few points a cell for one) is fitted to the centres of its occupied cells."""
    thr = max(float(min_probability), 0.5)
    mean, what = m.gaussians(min_probability=thr)["mean"], "Gaussians"
    if len(mean) == 0:
        k = m.known_cells()
        mean, what = (k["index"][k["p_occ"] > thr] + 0.5) * float(m.resolution), "occupied cells"
    if len(mean) == 0:
        raise ValueError(
            "the map has no occupied cells to find the floor by; give the height band (z_min and z_max; --z-min and --z-max in ndtom export)"
        )
    tile = max(1.0, 4 * float(m.resolution))
    t = np.floor(mean[:, :2] / tile).astype(np.int64)
    order = np.lexsort((mean[:, 2], t[:, 1], t[:, 0]))
    t, pts = t[order], mean[order]
    first = np.flatnonzero(np.r_[True, (t[1:] != t[:-1]).any(axis=1)])
    low = pts[first]  # the lowest Gaussian of each tile
    a_design = np.c_[np.ones(len(low)), low[:, 0], low[:, 1]]
    best = np.array([float(np.percentile(low[:, 2], 5)), 0.0, 0.0])
    if len(low) >= 3:
        rng = np.random.default_rng(0)
        best_in = -1
        max_slope = math.tan(math.radians(15))
        for _ in range(300):
            sel = rng.choice(len(low), 3, replace=False)
            try:
                coef = np.linalg.solve(a_design[sel], low[sel, 2])
            except np.linalg.LinAlgError:
                continue
            if math.hypot(coef[1], coef[2]) > max_slope:
                continue
            inl = int((np.abs(a_design @ coef - low[:, 2]) < 0.15).sum())
            if inl > best_in:
                best, best_in = coef, inl
        inliers = np.abs(a_design @ best - low[:, 2]) < 0.15
        if inliers.sum() >= 3:
            best = np.linalg.lstsq(a_design[inliers], low[inliers, 2], rcond=None)[0]
    tilt = math.degrees(math.atan(math.hypot(best[1], best[2])))
    return best, (
        f"floor plane z = {best[0]:.2f} {best[1]:+.4f} x {best[2]:+.4f} y (tilt {tilt:.1f} deg), fitted to "
        f"the lowest {what} of {len(low)} tiles of {tile:g} m"
    )


def occupancy_grid(
    m: Any,
    z_min: float | None = None,
    z_max: float | None = None,
    *,
    min_probability: float = 0.5,
    above_floor: tuple[float, float] = (0.3, 2.0),
) -> Grid:
    """The 2-D occupancy grid of map ``m`` (see the module doc) over a height band: the
    cells whose height span meets ``[z_min, z_max]`` (metres, map frame), or, when neither
    is given, the cells whose centre is ``above_floor`` metres (at least one cell) over the
    :func:`floor_plane`."""
    note = ""
    r = float(m.resolution)
    k = m.known_cells()
    idx, p = k["index"], k["p_occ"]
    if z_min is None and z_max is None:
        plane, note = floor_plane(m, min_probability=min_probability)
        c = (idx + 0.5) * r
        height = c[:, 2] - (plane[0] + plane[1] * c[:, 0] + plane[2] * c[:, 1])
        lo, hi = max(float(above_floor[0]), r), float(above_floor[1])
        band = (height >= lo) & (height <= hi)
        z_band = (lo, hi)
        what = f"{lo:.2f} .. {hi:.2f} m above the floor"
    else:
        if z_min is None or z_max is None:
            raise ValueError(
                "give both ends of the height band (z_min and z_max), or neither to take 0.3 .. 2 m above the floor"
            )
        z_min, z_max = float(z_min), float(z_max)
        if not (math.isfinite(z_min) and math.isfinite(z_max) and z_min < z_max):
            raise ValueError(f"the height band needs finite z_min < z_max, got [{z_min}, {z_max}]")
        # cell k spans [k r, (k + 1) r): it meets the band when (k + 1) r > z_min and k r < z_max
        kz_lo, kz_hi = math.floor(z_min / r), math.ceil(z_max / r) - 1
        band = (idx[:, 2] >= kz_lo) & (idx[:, 2] <= kz_hi)
        z_band = (z_min, z_max)
        what = f"z = {z_min:.2f} .. {z_max:.2f} m"
    if not band.any():
        span = (
            f"the map's known cells span z = {idx[:, 2].min() * r:.2f} .. {(idx[:, 2].max() + 1) * r:.2f} m"
            if len(idx)
            else "the map has no known cells"
        )
        raise ValueError(f"no known cells in the height band {what}; {span}")
    idx, p = idx[band], p[band]
    thr = max(float(min_probability), 0.5)
    x0, y0 = int(idx[:, 0].min()), int(idx[:, 1].min())
    w, h = int(idx[:, 0].max()) - x0 + 1, int(idx[:, 1].max()) - y0 + 1
    if w * h > MAX_GRID_PIXELS:
        raise ValueError(f"the grid would be {w} x {h} pixels; use a coarser map or a narrower height band")
    col = (idx[:, 0] - x0).astype(np.int64)
    row = (h - 1 - (idx[:, 1] - y0)).astype(np.int64)
    img = np.full((h, w), Grid.UNKNOWN, np.uint8)
    free = p < 0.5
    img[row[free], col[free]] = Grid.FREE
    occ = p > thr
    img[row[occ], col[occ]] = Grid.OCCUPIED  # after free: an occupied cell wins its column
    return Grid(img, r, (x0 * r, y0 * r), z_band, what, note)


def grid_paths(path: str | Path) -> tuple[Path, Path]:
    """The (PGM, YAML) pair a grid export to ``path`` writes: ``x.pgm`` or ``x`` -> ``x.pgm``
    and ``x.yaml``; ``x.yaml`` (or ``.yml``) -> ``x.pgm`` and that file."""
    path = Path(path)
    is_yaml = path.suffix.lower() in (".yaml", ".yml")
    base = path.with_suffix("") if is_yaml or path.suffix.lower() == ".pgm" else path
    return base.with_name(base.name + ".pgm"), path if is_yaml else base.with_name(base.name + ".yaml")


def _yaml_scalar(text: str) -> str:
    """``text`` as a YAML string: plain when it reads back as itself, else double-quoted (JSON's
    quoting is YAML's). A plain ``run #3.pgm`` is read as ``run`` (a comment), and ``a: b.pgm``
    or ``[x].pgm`` are YAML errors: map_server loads no map."""
    if re.fullmatch(r"\w[\w.+-]*", text):
        return text
    return json.dumps(text, ensure_ascii=False)


def write_grid(grid: Grid, path: str | Path) -> tuple[Path, Path]:
    """``NAME.pgm`` and ``NAME.yaml`` (map_server's format) for ``path`` (either suffix, or
    none). Returns (pgm path, yaml path)."""
    pgm, yml = grid_paths(path)
    for target in (pgm, yml):  # both before either: a YAML path that was a folder left the PGM written
        check_target(target)
    h, w = grid.image.shape
    head = (f"P5\n# ndtom_ti occupancy grid: {grid.band}, {grid.resolution!r} m cells\n{w} {h}\n255\n").encode("ascii")
    ox, oy = grid.origin
    text = (
        f"image: {_yaml_scalar(pgm.name)}\n"
        "mode: trinary\n"
        f"resolution: {grid.resolution!r}\n"
        f"origin: [{ox:.12g}, {oy:.12g}, 0.0]\n"
        "negate: 0\n"
        "occupied_thresh: 0.65\n"
        "free_thresh: 0.196\n"
        f"# cells of {grid.band}; 0 occupied, 254 free, 205 unknown\n"
        + (f"# {grid.origin_note}\n" if grid.origin_note else "")
    )
    atomic_write(pgm, lambda fh: (fh.write(head), fh.write(grid.image.tobytes())))
    atomic_write(yml, lambda fh: fh.write(text.encode("utf-8")))
    return pgm, yml


# ---------------------------------------------------------------------------- one call
@dataclass
class Exported:
    """What :func:`export_file` wrote: ``paths`` (the files), ``format``, ``count`` (Gaussians,
    or cells for ``bt`` and ``grid``) and ``summary`` (one line saying what was written)."""

    paths: list[Path]
    format: str
    count: int
    summary: str
    notes: list[str] = field(default_factory=list)

    @property
    def path(self) -> Path:
        return self.paths[0]


def frame_origin_note(metadata: dict) -> str | None:
    """A header comment for a map made in a shifted frame (``frame_origin`` in its metadata,
    frames.py): where the file's (0, 0, 0) lies in the recording's frame."""
    xyz = as_frame_origin(metadata.get("frame_origin") if isinstance(metadata, dict) else None)
    if xyz is None:
        return None
    return f"frame_origin {xyz[0]:.3f} {xyz[1]:.3f} {xyz[2]:.3f}: add it to these coordinates for the recording's frame"


def export_file(
    m: Any,
    path: str | Path,
    fmt: str | None = None,
    *,
    min_probability: float = 0.5,
    min_points: int | None = None,
    z_min: float | None = None,
    z_max: float | None = None,
) -> Exported:
    """Export map ``m`` (an NdtOmMap or a MapSnapshot) to ``path`` as ``fmt`` (default:
    from the suffix; see :func:`format_for`). Gaussian formats hold the Gaussians with
    ``p_occ > min_probability`` (0: every Gaussian, occupied or not); ``bt`` and ``grid`` hold cells
    (module doc); ``grid`` takes the height band ``z_min``, ``z_max`` (metres)."""
    fmt = format_for(path, fmt)
    if not 0.0 <= float(min_probability) < 1.0:
        raise ValueError(f"min_probability must be in [0, 1), got {min_probability}")
    mp = float(min_probability)
    if fmt == "grid":
        grid = occupancy_grid(m, z_min, z_max, min_probability=mp)
        fo = as_frame_origin(m.metadata.get("frame_origin"))
        if fo is not None:  # map_server places the grid in the poses' frame: the shift added
            grid = replace(
                grid,
                origin=(grid.origin[0] + float(fo[0]), grid.origin[1] + float(fo[1])),
                origin_note=f"origin in the poses' frame: the map's frame_origin {fo[0]:.3f} {fo[1]:.3f} {fo[2]:.3f} added",
            )
        pgm, yml = write_grid(grid, path)
        h, w = grid.image.shape
        n_occ = int((grid.image == Grid.OCCUPIED).sum())
        n_free = int((grid.image == Grid.FREE).sum())
        summary = (
            f"occupancy grid {w} x {h} at {grid.resolution:g} m of {grid.band} "
            f"({n_occ:,} occupied, {n_free:,} free cells) to {pgm} and {yml}"
        )
        notes = [f"{grid.z_band_note}; a band of map-frame heights: --z-min/--z-max"] if grid.z_band_note else []
        return Exported([pgm, yml], fmt, n_occ + n_free, summary, notes)
    if fmt == "bt":
        k = m.known_cells()
        thr = max(mp, 0.5)
        occ = k["p_occ"] > thr
        keep = occ | (k["p_occ"] < 0.5)
        shift = frame_origin_note(m.metadata)
        out = write_bt(k["index"][keep], occ[keep], m.resolution, path, comment=shift)
        n_occ = int(occ.sum())
        n_free = int(keep.sum()) - n_occ
        return Exported(
            [out],
            fmt,
            n_occ + n_free,
            f"OctoMap tree of {n_occ:,} occupied and {n_free:,} free cells at {m.resolution:g} m to {out}",
            [_relative(shift, "the tree's cells")] if shift else [],
        )
    g = m.gaussians(min_points=min_points, min_probability=mp)
    shift = frame_origin_note(m.metadata)
    if fmt == "ply":
        from . import __version__

        comment = (
            f"ndtom_ti {__version__} NDT-OM Gaussians: resolution {m.resolution:g} m, "
            f"p_occ > {mp:g}; covariances in m^2"
        )
        out = write_ply(g, path, comment=comment + (f"\n{shift}" if shift else ""))
    elif fmt == "pcd":
        out = write_pcd(g, path, comment=shift)
    elif fmt == "npz":
        out = write_npz(g, path, resolution=m.resolution, metadata=m.metadata)
    else:
        out = write_csv(g, path)
    k = len(g["n"])
    notes = [_relative(shift, "the means and cell indices")] if shift and fmt == "csv" else []
    return Exported([out], fmt, k, f"{k:,} Gaussians (p_occ > {mp:g}) to {out}", notes)


def _relative(shift: str, what: str) -> str:
    """The note of a file that cannot carry a map's frame_origin (CSV) or keeps it in a comment only (.bt)."""
    return f"{what} are in the map's shifted frame: {shift}"


def export_map(
    m: Any,
    path: str | Path,
    fmt: str | None = None,
    *,
    min_probability: float = 0.5,
    min_points: int | None = None,
    z_min: float | None = None,
    z_max: float | None = None,
) -> tuple[Path, int]:
    """:func:`export_file`, returning (first path written, number of Gaussians or cells)."""
    e = export_file(m, path, fmt, min_probability=min_probability, min_points=min_points, z_min=z_min, z_max=z_max)
    return e.path, e.count
