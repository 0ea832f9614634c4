"""A small synthetic scene with exact ground truth, for ``ndtom demo`` and tests.

A room 12 m x 8 m with 3 m walls, a floor and no ceiling, four boxes on the floor,
and one more box that is taken away halfway through. A 360-degree lidar (32 rings from
-30 to +10 degrees, 600 rays per ring) 1.5 m above the floor moves along the room's
long axis and turns slowly. Rays are cast exactly against the scene in numpy (slab
method); ranges get 5 mm Gaussian noise from a fixed seed, so every run is the same.
Rays that leave the room over the walls return nothing (no point).

Conventions: the world frame has z up and the floor at z = 0; ``T_world_sensor`` maps
sensor-frame points into the world.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .scan import Scan

__all__ = ["Box", "Scene", "ground_truth_check", "make_scans"]


@dataclass(frozen=True)
class Box:
    """An axis-aligned box [lo, hi] (metres, world frame)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    name: str = "box"
    present_until: int | None = None  # scans with index >= this do not see the box

    def present(self, scan_index: int) -> bool:
        return self.present_until is None or scan_index < self.present_until

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Distance of points (N, 3) to the box's surface (inside or outside)."""
        lo, hi = np.asarray(self.lo), np.asarray(self.hi)
        c, h = (lo + hi) / 2, (hi - lo) / 2
        q = np.abs(points - c) - h
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.minimum(q.max(axis=1), 0.0)
        return np.abs(outside + inside)

    def contains(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        lo, hi = np.asarray(self.lo) - margin, np.asarray(self.hi) + margin
        return np.asarray(((points >= lo) & (points <= hi)).all(axis=1))


@dataclass(frozen=True)
class Scene:
    """The room (interior [0, size] with walls up to ``size[2]``, floor z = 0) and boxes."""

    size: tuple[float, float, float] = (12.0, 8.0, 3.0)
    boxes: tuple[Box, ...] = field(
        default_factory=lambda: (
            Box((2.0, 1.0, 0.0), (3.0, 2.0, 1.0), "box A"),
            Box((9.0, 1.2, 0.0), (10.5, 2.2, 0.8), "box B"),
            Box((4.5, 5.8, 0.0), (5.5, 7.0, 1.6), "box C"),
            Box((8.0, 5.5, 0.0), (8.6, 6.1, 2.2), "pillar"),
            Box((6.0, 1.5, 0.0), (7.0, 2.5, 1.0), "vanishing box", present_until=10),
        )
    )

    @property
    def vanishing(self) -> list[Box]:
        return [b for b in self.boxes if b.present_until is not None]

    def cast(self, origin: np.ndarray, dirs: np.ndarray, scan_index: int) -> np.ndarray:
        """Range along each unit direction (R, 3) from ``origin`` to the first surface;
        inf where the ray leaves the room over the walls."""
        o = np.asarray(origin, np.float64)
        d = np.asarray(dirs, np.float64)
        size = np.asarray(self.size)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            # the room is convex and the sensor inside it: the ray leaves through the
            # nearest plane it moves toward; leaving through the top (z = size[2]) is no return
            t_planes = np.where(d > 0, (size - o) * inv, np.where(d < 0, -o * inv, np.inf))
            exit_axis = np.argmin(t_planes, axis=1)
            t = t_planes[np.arange(len(d)), exit_axis]
            t = np.where((exit_axis == 2) & (d[:, 2] > 0), np.inf, t)
            for b in self.boxes:
                if not b.present(scan_index):
                    continue
                t1 = (np.asarray(b.lo) - o) * inv
                t2 = (np.asarray(b.hi) - o) * inv
                tnear = np.nanmax(np.minimum(t1, t2), axis=1)
                tfar = np.nanmin(np.maximum(t1, t2), axis=1)
                hit = (tnear <= tfar) & (tnear > 0)
                t = np.where(hit & (tnear < t), tnear, t)
        return t

    def surface_distance(self, points: np.ndarray, scan_index: int | None = None) -> np.ndarray:
        """Distance of world points (N, 3) to the nearest surface present at ``scan_index``
        (None: after the last scan, when the vanishing boxes are gone)."""
        p = np.asarray(points, np.float64)
        sx, sy, sz = self.size
        room = np.minimum.reduce([p[:, 0], sx - p[:, 0], p[:, 1], sy - p[:, 1]])
        room = np.where(p[:, 2] <= sz, np.abs(room), np.inf)  # walls end at sz
        d = np.minimum(room, np.abs(p[:, 2]))  # floor
        for b in self.boxes:
            if scan_index is None and b.present_until is not None:
                continue
            if scan_index is not None and not b.present(scan_index):
                continue
            d = np.minimum(d, b.distance(p))
        return d


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def sensor_pose(i: int, n_scans: int) -> np.ndarray:
    """T_world_sensor of scan ``i``: along the room's long axis at 1.5 m height, turning."""
    s = i / max(n_scans - 1, 1)
    T = np.eye(4)
    T[:3, :3] = _rot_z(0.6 * s - 0.2)
    T[:3, 3] = (1.5 + 9.0 * s, 4.0 + 0.6 * math.sin(math.pi * s), 1.5)
    return T


def ray_directions(rings: int = 32, per_ring: int = 600, lo_deg: float = -30.0, hi_deg: float = 10.0) -> np.ndarray:
    """Unit directions (rings * per_ring, 3) of the lidar in its own frame."""
    el = np.radians(np.linspace(lo_deg, hi_deg, rings))
    az = np.linspace(0.0, 2 * math.pi, per_ring, endpoint=False)
    E, A = np.meshgrid(el, az, indexing="ij")
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)


def make_scans(
    n_scans: int = 20,
    *,
    scene: Scene | None = None,
    noise: float = 0.005,
    seed: int = 0,
    rings: int = 32,
    per_ring: int = 600,
) -> list[Scan]:
    """The demo's scans (about 16k points each with the defaults), deterministic."""
    scene = scene or Scene()
    dirs_s = ray_directions(rings, per_ring)
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_scans):
        T = sensor_pose(i, n_scans)
        R, o = T[:3, :3], T[:3, 3]
        r = scene.cast(o, dirs_s @ R.T, i)
        ok = np.isfinite(r)
        r = r[ok] + rng.normal(0.0, noise, ok.sum())
        pts = (dirs_s[ok] * r[:, None]).astype(np.float32)
        out.append(Scan(pts, T, stamp_ns=1_700_000_000 * 10**9 + i * 10**8, index=i))
    return out


def ground_truth_check(gaussians: dict, resolution: float, scene: Scene | None = None) -> dict:
    """Compare a map's Gaussians with the scene after the last scan.

    ``on_surface``: fraction of Gaussian means within ``resolution / 4`` of a true surface;
    ``median_distance``: median distance (m) of the means to the nearest surface;
    ``left_in_vanished``: Gaussians left inside (a margin of ``resolution`` around) the
    box that was taken away, away from the floor (they should be erased by the rays that
    now pass there).
    """
    scene = scene or Scene()
    mean = gaussians["mean"]
    d = scene.surface_distance(mean) if len(mean) else np.zeros(0)
    left = 0
    for b in scene.vanishing:
        inside = b.contains(mean, margin=resolution) & (mean[:, 2] > 2 * resolution)
        left += int(inside.sum())
    return {
        "gaussians": len(mean),
        "on_surface": float((d < resolution / 4).mean()) if len(d) else float("nan"),
        "median_distance": float(np.median(d)) if len(d) else float("nan"),
        "left_in_vanished": left,
    }
