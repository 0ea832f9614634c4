"""MapScene: what a viewer draws (scene nodes under ``/ndtom``) and where its camera looks.

Each layer is one node, replaced whole at each redraw: the Gaussians (one batched mesh
of 1-sigma ellipsoids, or Gaussian splats), occupied cells (square points), free cells
(translucent boxes), conflicting cells (markers), the trajectory and the latest scan.
``nodes`` and ``drawn`` are read-only views of what the last redraw made; ``first_view``
is the camera that frames the map.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np

from . import geometry as geo
from .levels import AUTO, FACTORS, Caps, fmt
from .nodes import (
    CONFLICT_MIN_SIGMA,
    FREE_OPACITY,
    SPLAT_MIN_SIGMA,
    SPLAT_VIEW_SIGMA,
    cells_node,
    conflicts_node,
    free_node,
    gaussian_node,
    scan_node,
    trajectory_node,
)

__all__ = [
    "CONFLICT_MIN_SIGMA",
    "FREE_OPACITY",
    "LAYERS",
    "SPLAT_MIN_SIGMA",
    "SPLAT_VIEW_SIGMA",
    "FirstView",
    "MapScene",
]

LAYERS = {  # key -> the panel's label
    "gaussians": "Gaussians",
    "occupied": "Occupied cells",
    "free": "Free cells",
    "conflicts": "Conflicting cells",
    "trajectory": "Trajectory",
    "scan": "Latest scan",
}
_FOV, _ASPECT = math.radians(75.0), 0.75  # a page's view before it says its own: viser's, beside the panel


@dataclass(frozen=True)
class FirstView:
    """The view that frames the bulk of a map: its sphere (``center``, ``radius``), seen
    from ``direction`` (a unit vector, from above at an angle)."""

    center: np.ndarray
    radius: float
    direction: np.ndarray

    @classmethod
    def of(cls, pts: np.ndarray) -> FirstView:
        center, radius = geo.bulk_sphere(pts)  # the bulk: an outdoor map's far rings are no speck's frame
        direction = np.array([-0.45, -0.75, 0.8])
        return cls(center, radius, direction / np.linalg.norm(direction))

    def camera(self, fov: float, aspect: float) -> tuple[tuple, tuple]:
        """(position, look_at) that fit the sphere in a view of vertical field of view
        ``fov`` (radians) and width/height ``aspect``."""
        half = min(fov / 2.0, math.atan(math.tan(fov / 2.0) * max(aspect, 0.1)))
        distance = self.radius / math.sin(half)
        pos = self.center + distance * self.direction
        return tuple(float(x) for x in pos), tuple(float(x) for x in self.center)


class MapScene:
    """The layers of a viewer's scene (``server``: viser's; ``caps``: how much it draws)."""

    def __init__(self, server: Any, caps: Caps):
        self.server = server
        self.caps = caps
        self._nodes: dict[str, Any] = {}
        self._drawn: dict[str, Any] = {}
        self._view: FirstView | None = None
        self._framed = False

    @property
    def nodes(self) -> Mapping[str, Any]:
        """The scene node of each layer drawn (viser handles), by layer key."""
        return MappingProxyType(self._nodes)

    @property
    def drawn(self) -> Mapping[str, Any]:
        """What the last redraw drew: counts per layer, level, geometry, colour ranges, notes."""
        return MappingProxyType(self._drawn)

    @property
    def first_view(self) -> FirstView | None:
        """The view that frames the map (None until the map has content)."""
        return self._view

    def auto_drawn(self) -> float | None:
        """The resolution drawn when auto chose it (the selector's "auto" entry names it)."""
        return self._drawn.get("resolution") if self._drawn.get("selected") == AUTO else None

    def visible(self, key: str) -> bool:
        h = self._nodes.get(key)
        return bool(h is not None and h.visible)

    def show_layer(self, key: str, on: bool) -> None:
        h = self._nodes.get(key)
        if h is not None:
            h.visible = on

    def set_point_size(self, size: float) -> None:
        h = self._nodes.get("scan")
        if h is not None:
            h.point_size = size

    def reframe(self) -> None:
        """Frame the map anew at the next redraw (other maps)."""
        self._framed = False

    # ------------------------------------------------------------------ camera

    def look_at(self, pts: np.ndarray) -> np.ndarray:
        """Where a connected page's camera looks (else the first view's centre, else ``pts``')."""
        for client in self.server.get_clients().values():
            with contextlib.suppress(Exception):
                look = np.asarray(client.camera.look_at, np.float64)
                if look.shape == (3,) and np.isfinite(look).all():
                    return look
        return self._view.center if self._view is not None else geo.bulk_sphere(pts)[0]

    def _frame(self, g: dict | None, traj: np.ndarray) -> None:
        """Point the camera at the map once it has content: its bulk (all of an indoor map)
        in view, seen from above at an angle."""
        pts = g["mean"] if g is not None and len(g["n"]) else traj
        if len(pts) == 0:
            return
        self._view = FirstView.of(pts)
        cam = self.server.initial_camera
        # pages start here: 75 degrees vertical (viser's), a view narrowed by the panel beside it
        # (a page's first camera message comes before its layout: its size cannot be used yet)
        cam.position, cam.look_at = self._view.camera(_FOV, _ASPECT)
        with contextlib.suppress(AttributeError):
            cam.up = (0.0, 0.0, 1.0)
        self._framed = True
        self.frame()

    def frame(self) -> None:
        """Move every connected page's camera to the first view (fitted to each page's own view)."""
        if self._view is None:
            return
        for client in self.server.get_clients().values():
            cam = client.camera
            try:
                fov, aspect = float(cam.fov), float(cam.aspect)
            except (AssertionError, AttributeError, ZeroDivisionError, TypeError, ValueError):
                fov, aspect = _FOV, _ASPECT
            if not (math.isfinite(fov) and 0.05 < fov < 3.0 and math.isfinite(aspect) and aspect > 0):
                fov, aspect = _FOV, _ASPECT
            position, look_at = self._view.camera(fov, aspect)
            cam.position = position
            cam.look_at = look_at

    # ------------------------------------------------------------------ drawing

    def draw(
        self,
        snap: dict,
        g: dict | None,
        traj: np.ndarray,
        scan: np.ndarray,
        want: dict[str, bool],
        *,
        color_mode: str,
        geometry: str,
        clip: tuple[float, float] | None,
        point_size: float,
        panel: Callable[[dict, float | None], None],
    ) -> bool:
        """Replace the layers with ``snap`` (see :meth:`LevelCache.take`; ``g``, ``traj`` and
        ``scan`` finite), inside ``clip``; ``panel(drawn, at_top)`` updates the panel in the
        same step. Frames the map at its first content. True when a level chosen by hand is
        drawn only around the view."""
        caps = self.caps
        res = snap.get("resolution") or 0.1
        drawn: dict[str, Any] = {
            "factor": snap["factor"],
            "resolution": snap.get("resolution"),
            "notes": list(snap["notes"]),
            "skipped": list(snap["skipped"]),
            "clip": clip,
        }
        zsrc = g["mean"][:, 2] if g is not None and len(g["n"]) else traj[:, 2] if len(traj) else np.zeros(0)

        def inside(z: np.ndarray) -> np.ndarray:
            lo, hi = clip if clip is not None else (-np.inf, np.inf)
            return (z >= lo) & (z <= hi)

        unclipped = snap.get("g")
        if g is not None and clip is not None:
            g = {k: v[inside(g["mean"][:, 2])] for k, v in g.items()}
        # the colours fit what is drawn: the clip's heights, the drawn Gaussians' occupancies
        zrange = geo.height_range(g["mean"][:, 2] if g is not None and len(g["n"]) else zsrc)
        prange = geo.occupancy_range(g["p_occ"] if g is not None else np.zeros(0), snap["threshold"])
        n_all = 0 if g is None else len(g["n"])
        use = geometry
        if geometry == "auto":
            use = "ellipsoids" if n_all <= caps.ellipsoids else "splats"
        cap = caps.gaussians(use)
        by_hand = snap["selected"] != AUTO
        part = False
        if by_hand and g is not None and n_all > max(cap, caps.chosen):
            # a level chosen by hand is drawn whole up to caps.chosen; past it, the part around the view
            center = self.look_at(g["mean"])
            rows = np.sort(np.argsort(np.linalg.norm(g["mean"] - center, axis=1), kind="stable")[: caps.chosen])
            g = {k: v[rows] for k, v in g.items()}
            part = True
            drawn["notes"].append(
                f"{fmt(n_all)} Gaussians at {res:g} m: showing the {fmt(len(rows))} nearest the view's centre "
                f"(past {fmt(caps.chosen)} the page stops responding); move the view, then *Draw around the view*"
            )
        elif by_hand and g is not None and n_all > cap:
            drawn["notes"].append(
                f"{fmt(n_all)} Gaussians drawn as {use} at {res:g} m: past {fmt(cap)} the page "
                "may respond slowly (Resolution auto keeps it responsive)"
            )
        elif g is not None and n_all > cap:
            rows = geo.cap_rows(n_all, cap)
            g = {k: v[rows] for k, v in g.items()}
            hint = "; a coarser Resolution shows all of the map" if snap["selected"] < FACTORS[-1] else ""
            drawn["notes"].append(
                f"{fmt(n_all)} Gaussians to draw as {use}: showing an even {fmt(len(rows))} "
                f"of them (past {fmt(cap)} the page stops responding){hint}"
            )
        drawn.update(selected=snap["selected"], gaussians_total=n_all, geometry=use, zrange=zrange, prange=prange)

        with self.server.atomic():
            n_g = self._draw_gaussians(g, res, use, color_mode, zrange, prange, want["gaussians"])
            drawn["gaussians"] = n_g
            self._draw_cells(snap, drawn, want, res, color_mode, zrange, prange, inside if clip is not None else None)
            self._draw_conflicts(snap, drawn, res, inside if clip is not None else None, want["conflicts"])
            self._draw_live(traj, scan, drawn, want, point_size)
            at_top = None
            if g is not None and n_g:
                at_top = float(np.mean(g["p_occ"] >= prange[1] - 1e-3))
            panel(drawn, at_top)
        self._drawn = drawn
        if not self._framed:
            self._frame(g if clip is None else unclipped, traj)
        return part

    def _set(self, key: str, make: Callable[[], Any] | None) -> None:
        """Replace layer ``key`` with ``make()`` (None: remove it)."""
        old = self._nodes.pop(key, None)
        new = make() if make is not None else None
        if new is not None:
            self._nodes[key] = new
        elif old is not None:
            old.remove()

    def _draw_gaussians(
        self, g: dict | None, res: float, use: str, color_mode: str, zrange: tuple, prange: tuple, visible: bool
    ) -> int:
        if g is None or not len(g["n"]):
            self._set("gaussians", None)
            return 0
        cols = geo.colors_for(color_mode, g["p_occ"], g["mean"][:, 2], zrange, prange)
        if self._nodes.get("gaussians") is not None and use != self._drawn.get("geometry"):
            self._nodes.pop("gaussians").remove()  # splats <-> ellipsoids: other node type
        radius = self._view.radius if self._view is not None else None
        self._set("gaussians", lambda: gaussian_node(self.server.scene, g, cols, res, use, visible, radius))
        return len(g["n"])

    def _draw_cells(
        self,
        snap: dict,
        drawn: dict,
        want: dict[str, bool],
        res: float,
        color_mode: str,
        zrange: tuple,
        prange: tuple,
        inside: Callable | None,
    ) -> None:
        """Occupied cells (square points one cell wide) and free cells (translucent boxes)."""
        scene = self.server.scene
        for key in ("occupied", "free"):
            if key in snap["skipped"]:
                drawn[key] = self._drawn.get(key, 0) if key in self._nodes else 0
                if key in self._nodes:
                    self._nodes[key].visible = False
                continue
            centers, p = snap[key]
            if not (fin := geo.finite_rows(centers)).all():
                centers, p = centers[fin], p[fin]
            if inside is not None:
                keep = inside(centers[:, 2])
                centers, p = centers[keep], p[keep]
            if key == "free" and color_mode == "height":
                cols = np.tile(np.array(geo.FREE_RGB, np.uint8), (len(p), 1))
            else:
                cols = geo.colors_for(color_mode, p, centers[:, 2], zrange, prange)
            if len(p) and key == "free":
                self._set(key, lambda centers=centers, cols=cols: free_node(scene, centers, cols, res, want["free"]))
            elif len(p):
                self._set(key, lambda c=centers, cols=cols, key=key: cells_node(scene, key, c, cols, res, want[key]))
            else:
                self._set(key, None)
            drawn[key] = len(p)
        for key, total, cap in (
            ("occupied", snap.get("n_occupied"), self.caps.occupied_cells),
            ("free", snap.get("n_free"), self.caps.free_cells),
        ):
            if total is not None and key not in snap["skipped"]:
                drawn[f"{key}_total"] = total
                if total > cap:
                    drawn["notes"].append(f"{LAYERS[key]}: {fmt(drawn[key])} of {fmt(total)} drawn (cap {fmt(cap)})")

    def _draw_conflicts(self, snap: dict, drawn: dict, res: float, inside: Callable | None, visible: bool) -> None:
        """The comparison map's Gaussians where NDT-OM has none."""
        conf = snap.get("conflicts")
        if conf is None:
            if "conflicts" in snap["skipped"] and "conflicts" in self._nodes:
                self._nodes["conflicts"].visible = False
                drawn["conflicts"] = self._drawn.get("conflicts", 0)
            else:
                self._set("conflicts", None)
                drawn["conflicts"] = 0
            return
        conf = {k: v[geo.finite_rows(conf["mean"], conf["cov"])] for k, v in conf.items()}
        if inside is not None:
            keep = inside(conf["mean"][:, 2])
            conf = {k: v[keep] for k, v in conf.items()}
        n_c = len(conf["mean"])
        if n_c:
            self._set("conflicts", lambda: conflicts_node(self.server.scene, conf, res, visible))
        else:
            self._set("conflicts", None)
        drawn["conflicts"] = n_c

    def _draw_live(
        self, traj: np.ndarray, scan: np.ndarray, drawn: dict, want: dict[str, bool], point_size: float
    ) -> None:
        """The trajectory (a polyline) and the latest scan (points)."""
        scene = self.server.scene
        if len(traj) >= 2:
            self._set("trajectory", lambda: trajectory_node(scene, traj, want["trajectory"]))
        else:
            self._set("trajectory", None)
        drawn["trajectory"] = len(traj)
        if len(scan):
            self._set("scan", lambda: scan_node(scene, scan, point_size, want["scan"]))
        else:
            self._set("scan", None)
        drawn["scan"] = len(scan)
