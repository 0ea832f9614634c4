"""One redraw of a viewer: a level of the maps (see :meth:`~.levels.LevelCache.take`)
drawn into the scene, and the panel set to say what was drawn.

The viewer (``app``) runs one at a time, outside the maps' lock; this module joins its
parts: ``levels`` (the maps shown), ``scene`` (the layers) and ``controls`` (the panel).
"""

from __future__ import annotations

import numpy as np

from . import geometry as geo
from .controls import Controls
from .levels import Caps, LevelCache
from .panel import stats_markdown
from .scene import MapScene

__all__ = ["redraw"]


def redraw(
    levels: LevelCache,
    scene: MapScene,
    controls: Controls,
    caps: Caps,
    snap: dict,
    want: dict[str, bool],
    traj: np.ndarray,
    scan: np.ndarray,
) -> None:
    """Draw ``snap`` (the layers ``want``ed), the trajectory ``traj`` and the latest scan
    ``scan`` with the panel's settings, and relabel the selectors to what was drawn."""
    c = controls
    color_mode = str(c.color_mode.value)
    g = snap.get("g")
    # nothing non-finite reaches the page (three.js fails on a NaN position; a scan may carry NaN points)
    if g is not None and not (keep := geo.finite_rows(g["mean"], g["cov"])).all():
        g = {k: v[keep] for k, v in g.items()}
    traj = traj[geo.finite_rows(traj)] if len(traj) else traj
    scan = scan[geo.finite_rows(scan)] if len(scan) else scan
    zsrc = g["mean"][:, 2] if g is not None and len(g["n"]) else traj[:, 2] if len(traj) else np.zeros(0)
    c.fit_zclip(zsrc, snap.get("resolution") or 0.1, snap.get("ceiling"))
    clip = c.clip_range()

    def panel(drawn: dict, at_top: float | None) -> None:
        legend = geo.legend_html(
            color_mode,
            threshold=snap["threshold"],
            zrange=drawn["zrange"],
            conflicts=levels.compare is not None,
            live=c.live_layers,
            free=want["free"],
            clip=clip,
            prange=drawn["prange"],
            at_top=at_top,
            frame_z=None if snap.get("frame_origin") is None else float(snap["frame_origin"][2]),
        )
        c.show(
            legend=legend,
            stats=stats_markdown(snap, drawn, caps),
            notes=drawn["notes"],
            conflicts=levels.compare is not None,
        )

    part = scene.draw(
        snap,
        g,
        traj,
        scan,
        want,
        color_mode=color_mode,
        geometry=c.geometry_choice(),
        clip=clip,
        point_size=float(c.point_size.value),
        panel=panel,
    )
    c.redraw.visible = part
    c.relabel_levels(levels.map.resolution if levels.map is not None else None, scene.auto_drawn())
    c.relabel_geometry(scene.drawn["geometry"])
