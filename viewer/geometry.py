"""Pure-numpy geometry and colours for the viewer (no viser needed: unit-testable).

Conventions: world frame, metres, z up; quaternions are ``wxyz`` (viser's order).
"""

from __future__ import annotations

import functools
import math

import numpy as np

__all__ = [
    "CONFLICT_RGB",
    "FREE_RGB",
    "SCAN_RGB",
    "TRAJECTORY_RGB",
    "bulk_sphere",
    "cap_rows",
    "ceiling_height",
    "cell_keys",
    "colors_for",
    "ellipsoid_instances",
    "finite_rows",
    "height_colors",
    "icosphere",
    "legend_html",
    "occupancy_colors",
    "occupancy_range",
    "rotation_to_wxyz",
    "turbo",
    "unit_box",
]

# Fixed colours of the layers that are not colour-mapped.
CONFLICT_RGB = (230, 0, 230)  # magenta: in neither colour map
FREE_RGB = (110, 170, 230)  # light blue (free cells in "height" mode)
SCAN_RGB = (0, 170, 190)  # teal: the latest scan's points
TRAJECTORY_RGB = (40, 40, 40)

# Occupancy colour map: stops (p, r, g, b). Distinct hues so a test (or a person) can
# tell the occupancy from a pixel: blue (free) -> green (unknown, 0.5) -> orange -> red.
_OCC_STOPS = np.array(
    [
        [0.00, 49, 110, 200],
        [0.50, 60, 170, 80],
        [0.75, 250, 160, 40],
        [1.00, 200, 20, 30],
    ],
    np.float64,
)


@functools.cache
def icosphere(subdivisions: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere: vertices (V, 3) float32 on the unit sphere, faces (F, 3) uint32
    (counter-clockwise seen from outside). ``subdivisions=1``: 42 vertices, 80 faces."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    v = [
        [-1, t, 0],
        [1, t, 0],
        [-1, -t, 0],
        [1, -t, 0],
        [0, -1, t],
        [0, 1, t],
        [0, -1, -t],
        [0, 1, -t],
        [t, 0, -1],
        [t, 0, 1],
        [-t, 0, -1],
        [-t, 0, 1],
    ]
    f = [
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ]
    verts = [np.array(p, np.float64) / np.linalg.norm(p) for p in v]
    faces = [tuple(x) for x in f]

    def midpoint(mid: dict[tuple[int, int], int], a: int, b: int) -> int:
        key = (min(a, b), max(a, b))
        if key not in mid:
            p = verts[a] + verts[b]
            verts.append(p / np.linalg.norm(p))
            mid[key] = len(verts) - 1
        return mid[key]

    for _ in range(subdivisions):
        mid: dict[tuple[int, int], int] = {}
        new = []
        for a, b, c in faces:
            ab, bc, ca = midpoint(mid, a, b), midpoint(mid, b, c), midpoint(mid, c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    V = np.array(verts, np.float32)
    F = np.array(faces, np.uint32)
    V.setflags(write=False)
    F.setflags(write=False)
    return V, F


@functools.cache
def unit_box() -> tuple[np.ndarray, np.ndarray]:
    """Unit cube centred on the origin: vertices (8, 3) float32, faces (12, 3) uint32 (outward)."""
    V = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], np.float32)
    F = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
        ],
        np.uint32,
    )
    V.setflags(write=False)
    F.setflags(write=False)
    return V, F


def rotation_to_wxyz(R: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4) ``wxyz`` of rotation matrices (N, 3, 3) (Shepperd's method)."""
    R = np.asarray(R, np.float64)
    n = len(R)
    q = np.empty((n, 4))
    tr = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    d = np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], axis=1)
    case = np.where(tr > d.max(axis=1), 3, d.argmax(axis=1))

    m = case == 3
    s = np.sqrt(np.maximum(tr[m] + 1.0, 1e-300)) * 2.0
    q[m] = np.stack(
        [0.25 * s, (R[m, 2, 1] - R[m, 1, 2]) / s, (R[m, 0, 2] - R[m, 2, 0]) / s, (R[m, 1, 0] - R[m, 0, 1]) / s], axis=1
    )
    m = case == 0
    s = np.sqrt(np.maximum(1.0 + R[m, 0, 0] - R[m, 1, 1] - R[m, 2, 2], 1e-300)) * 2.0
    q[m] = np.stack(
        [(R[m, 2, 1] - R[m, 1, 2]) / s, 0.25 * s, (R[m, 0, 1] + R[m, 1, 0]) / s, (R[m, 0, 2] + R[m, 2, 0]) / s], axis=1
    )
    m = case == 1
    s = np.sqrt(np.maximum(1.0 + R[m, 1, 1] - R[m, 0, 0] - R[m, 2, 2], 1e-300)) * 2.0
    q[m] = np.stack(
        [(R[m, 0, 2] - R[m, 2, 0]) / s, (R[m, 0, 1] + R[m, 1, 0]) / s, 0.25 * s, (R[m, 1, 2] + R[m, 2, 1]) / s], axis=1
    )
    m = case == 2
    s = np.sqrt(np.maximum(1.0 + R[m, 2, 2] - R[m, 0, 0] - R[m, 1, 1], 1e-300)) * 2.0
    q[m] = np.stack(
        [(R[m, 1, 0] - R[m, 0, 1]) / s, (R[m, 0, 2] + R[m, 2, 0]) / s, (R[m, 1, 2] + R[m, 2, 1]) / s, 0.25 * s], axis=1
    )
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q


def ellipsoid_instances(cov: np.ndarray, min_sigma: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Per-instance rotation and scales of 1-sigma ellipsoids of covariances (N, 3, 3).

    Returns ``wxyz`` (N, 4) float32 (rotation from the unit sphere's axes to the
    eigenvectors; one eigenvector is flipped where they form a left-handed frame) and
    ``scales`` (N, 3) float32, the square roots of the eigenvalues, at least ``min_sigma``
    (flat Gaussians of planar surfaces stay visible).
    """
    cov = np.asarray(cov, np.float64).reshape(-1, 3, 3)
    if len(cov) == 0:
        return np.zeros((0, 4), np.float32), np.zeros((0, 3), np.float32)
    sym = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    w, V = np.linalg.eigh(sym)  # ascending eigenvalues; eigenvectors in columns
    V = V.copy()
    left = np.linalg.det(V) < 0.0
    V[left, :, 0] *= -1.0
    scales = np.sqrt(np.maximum(w, 0.0))
    scales = np.maximum(scales, min_sigma)
    return rotation_to_wxyz(V).astype(np.float32), scales.astype(np.float32)


def _interp_stops(t: np.ndarray, stops: np.ndarray) -> np.ndarray:
    t = np.clip(np.nan_to_num(np.asarray(t, np.float64), nan=0.5), stops[0, 0], stops[-1, 0])
    return np.stack([np.interp(t, stops[:, 0], stops[:, k]) for k in (1, 2, 3)], axis=-1)


def occupancy_colors(p: np.ndarray, prange: tuple[float, float] | None = None) -> np.ndarray:
    """Colours (N, 3) uint8 of occupancy probabilities in [0, 1].

    ``prange=(lo, hi)``: occupied probabilities (p >= 0.5) are spread over the whole occupied
    half of the scale between ``lo`` (green) and ``hi`` (red). What is drawn lies between the
    threshold and the log-odds clamp (0.5-0.88 by default): on the absolute scale all of it
    would be one orange."""
    p = np.nan_to_num(np.asarray(p, np.float64), nan=0.5)
    if prange is not None:
        lo, hi = prange
        lo = min(max(lo, 0.5), 0.99)
        hi = max(hi, lo + 0.01)
        occ = p >= 0.5
        p = p.copy()
        p[occ] = 0.5 + 0.5 * np.clip((p[occ] - lo) / (hi - lo), 0.0, 1.0)
    return np.round(_interp_stops(p, _OCC_STOPS)).astype(np.uint8)


def occupancy_range(p: np.ndarray, threshold: float) -> tuple[float, float]:
    """Range of the occupancy colour scale: from the threshold to the highest p drawn."""
    p = np.asarray(p, np.float64)
    hi = float(np.nanmax(p)) if len(p) else 1.0
    return float(threshold), max(hi, float(threshold) + 0.01)


def turbo(t: np.ndarray) -> np.ndarray:
    """Google's Turbo colour map (polynomial fit) of t in [0, 1] -> (N, 3) uint8."""
    t = np.clip(np.nan_to_num(np.asarray(t, np.float64), nan=0.5), 0.0, 1.0)
    r = 0.13572138 + t * (4.61539260 + t * (-42.66032258 + t * (132.13108234 + t * (-152.94239396 + t * 59.28637943))))
    g = 0.09140261 + t * (2.19418839 + t * (4.84296658 + t * (-14.18503333 + t * (4.27729857 + t * 2.82956604))))
    b = 0.10667330 + t * (12.64194608 + t * (-60.58204836 + t * (110.36276771 + t * (-89.90310912 + t * 27.34824973))))
    return np.round(np.clip(np.stack([r, g, b], axis=-1), 0.0, 1.0) * 255.0).astype(np.uint8)


def height_range(z: np.ndarray) -> tuple[float, float]:
    """Colour range of heights: 2nd to 98th percentile (a few outliers do not wash it out)."""
    z = np.asarray(z, np.float64)
    if len(z) == 0:
        return 0.0, 1.0
    lo, hi = (float(v) for v in np.percentile(z, [2.0, 98.0]))
    if hi - lo < 1e-6:
        lo, hi = lo - 0.5, hi + 0.5
    return lo, hi


def height_colors(z: np.ndarray, zrange: tuple[float, float]) -> np.ndarray:
    lo, hi = zrange
    return turbo((np.asarray(z, np.float64) - lo) / (hi - lo))


def colors_for(
    mode: str,
    p_occ: np.ndarray,
    z: np.ndarray,
    zrange: tuple[float, float],
    prange: tuple[float, float] | None = None,
) -> np.ndarray:
    """Colours (N, 3) uint8 by ``mode`` "occupancy" (of p_occ, over ``prange``) or "height" (of z)."""
    if mode == "height":
        return height_colors(z, zrange)
    return occupancy_colors(p_occ, prange)


def _css(rgb) -> str:
    return f"rgb({int(rgb[0])},{int(rgb[1])},{int(rgb[2])})"


def legend_html(
    mode: str,
    *,
    threshold: float,
    zrange: tuple[float, float],
    conflicts: bool,
    live: bool = False,
    free: bool = False,
    clip: tuple[float, float] | None = None,
    prange: tuple[float, float] | None = None,
    at_top: float | None = None,
    frame_z: float | None = None,
) -> str:
    """A small colour bar with its scale (fitted to the map), and the fixed colours of the
    layers the view offers (conflicting cells with a comparison map, trajectory and latest
    scan while mapping live, free cells when drawn). ``frame_z``: the height of a shifted
    map's origin in its poses' frame (frame_origin), said beside the heights."""
    ts = np.linspace(0.0, 1.0, 9)
    if mode == "height":
        cols = turbo(ts)
        lo, hi = zrange
        left, mid, right = (f"{v + 0.0:.2f} m".replace("-0.00", "0.00") for v in (lo, (lo + hi) / 2, hi))
        title = "Colour: height of the Gaussian's mean"
        if frame_z is not None:
            title += f" in the map's frame (add {frame_z:.2f} m for the poses' frame)"
    elif prange is not None:
        # the occupied half of the scale, spread over what is drawn (threshold .. highest p)
        lo, hi = prange
        cols = occupancy_colors(lo + ts * (hi - lo), prange)
        left, mid, right = f"p = {lo:.2f} (least sure)", f"{(lo + hi) / 2:.2f}", f"{hi:.2f} (surest)"
        title = f"Colour: occupancy probability of the Gaussians drawn (p > {threshold:.2f})"
        if at_top is not None:
            title += f"; {100 * at_top:.0f}% of them at {hi:.2f}"
    else:
        cols = occupancy_colors(ts)
        left, mid, right = "p = 0 (free)", "0.5", "1 (occupied)"
        title = f"Colour: occupancy probability (Gaussians shown where p > {threshold:.2f})"
    grad = ", ".join(f"{_css(c)} {100 * t:.0f}%" for t, c in zip(ts, cols))
    extra = []
    if conflicts:
        extra.append(
            f'<span style="color:{_css(CONFLICT_RGB)}">&#9632;</span> conflicting cells '
            "(a Gaussian in Recursive NDT, none in NDT-OM)"
        )
    if free and mode == "height":
        extra.append(f'<span style="color:{_css(FREE_RGB)}">&#9632;</span> free cells')
    if live:
        extra += [
            f'<span style="color:{_css(SCAN_RGB)}">&#9632;</span> latest scan',
            f'<span style="color:{_css(TRAJECTORY_RGB)}">&#9632;</span> trajectory',
        ]
    if clip is not None:
        extra.append(f"Height clip: {clip[0]:.2f} to {clip[1]:.2f} m")
    return (
        '<div style="font-size:0.8em;padding:0 0.5em">'
        f"<div>{title}</div>"
        f'<div style="height:12px;border-radius:3px;background:linear-gradient(to right, {grad})"></div>'
        '<div style="display:flex;justify-content:space-between">'
        f"<span>{left}</span><span>{mid}</span><span>{right}</span></div>"
        f'<div>{"<br>".join(extra)}</div>'
        "</div>"
    )


def cell_keys(index: np.ndarray) -> np.ndarray:
    """One int64 per integer cell index (N, 3), for set operations (|index| < 2**20)."""
    idx = np.asarray(index, np.int64).reshape(-1, 3) + (1 << 20)
    return (idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2]


def cap_rows(n: int, cap: int) -> np.ndarray:
    """Indices of at most ``cap`` of ``n`` rows, spread evenly (deterministic)."""
    if n <= cap:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, cap).round().astype(np.int64))


def finite_rows(*arrays: np.ndarray) -> np.ndarray:
    """Mask of the rows finite in every array (a NaN position would reach the page's
    bounding-sphere computations)."""
    n = len(arrays[0])
    keep = np.ones(n, bool)
    for a in arrays:
        keep &= np.isfinite(np.asarray(a, np.float64).reshape(n, -1)).all(axis=1) if n else keep
    return keep


def bulk_sphere(pts: np.ndarray, share: float = 0.8) -> tuple[np.ndarray, float]:
    """Centre and radius of the sphere that frames the bulk of ``pts`` (N, 3).

    A lidar map outdoors thins out with range: its 1-99% box is mostly empty rings and a
    few far cells, and a camera fitted to it sees the map as a speck. The sphere here holds
    ``share`` of the points around the middle of their 10-90% box (most of an evenly filled
    room), and is never larger than the 1-99% box."""
    pts = np.asarray(pts, np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        return np.zeros(3), 1.0
    lo, hi = np.percentile(pts, 1.0, axis=0), np.percentile(pts, 99.0, axis=0)
    box_center, box_radius = (lo + hi) / 2.0, float(np.linalg.norm(hi - lo)) / 2.0
    center = (np.percentile(pts, 10.0, axis=0) + np.percentile(pts, 90.0, axis=0)) / 2.0  # walls count as floor
    bulk = float(np.percentile(np.linalg.norm(pts - center, axis=1), 100.0 * share))
    if bulk >= box_radius:
        return box_center, max(box_radius, 1.0)
    return center, max(bulk, 1.0)


def ceiling_height(
    mean: np.ndarray, cov: np.ndarray, resolution: float, *, min_share: float = 0.3, storey: float = 2.0
) -> float | None:
    """Height to clip a map's first view at so that its ceiling does not hide the interior,
    or None (no ceiling: outdoors, or a room seen without its ceiling).

    A ceiling covers the map from above: in most of the map's footprint (tiles of 1 m or 4
    cells) the highest Gaussian is flat (a horizontal surface), lies at least ``storey``
    above the lowest one of its tile (the floor) and has open space under it (sloping ground
    and trees outdoors fill their tiles, walls' tops are not flat). The clip goes just below the median of those tops: the main
    roof goes (a lower ceiling over a side room may stay), a sloped roof is cut halfway."""
    mean = np.asarray(mean, np.float64).reshape(-1, 3)
    cov = np.asarray(cov, np.float64).reshape(-1, 3, 3)
    ok = finite_rows(mean, cov)
    mean, cov = mean[ok], cov[ok]
    if len(mean) < 100:
        return None
    tile = max(4.0 * float(resolution), 1.0)
    keys = cell_keys(np.floor(np.c_[mean[:, :2] / tile, np.zeros(len(mean))]).astype(np.int64))
    order = np.lexsort((mean[:, 2], keys))  # by tile, then height
    k = keys[order]
    last = np.flatnonzero(np.r_[k[1:] != k[:-1], True])  # the highest Gaussian of each tile
    first = np.r_[0, last[:-1] + 1]  # the lowest
    top, bottom = order[last], order[first]
    _, vec = np.linalg.eigh(0.5 * (cov[top] + np.swapaxes(cov[top], 1, 2)))
    flat = np.abs(vec[:, 2, 0]) > 0.8  # normal (least-variance axis) near vertical
    # and open space under it: a gap of half a storey with nothing in it (trees, uneven ground
    # and walls fill their tiles from the bottom up)
    zs = mean[order, 2]
    tile_of = np.cumsum(np.r_[0, (k[1:] != k[:-1]).astype(np.int64)])
    gap = np.zeros(len(last))
    same = k[1:] == k[:-1]
    np.maximum.at(gap, tile_of[1:][same], np.diff(zs)[same])
    high = flat & (mean[top, 2] - mean[bottom, 2] >= storey) & (gap >= storey / 2.0)
    if high.mean() < min_share:
        return None
    return float(np.median(mean[top[high], 2])) - max(float(resolution), 0.1)
