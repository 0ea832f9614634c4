"""A map's frame against its poses' frame: the shift of georeferenced poses.

The grid is centred on its frame's origin (+-3.3 km across at 0.2 m), so poses in UTM or
another frame whose origin lies kilometres away would leave it at the first scan. The
mapping loop (pipeline.run_scans), the sweep and the experiments then map in a frame
shifted by the first pose's position, rounded (``far_origin``), and a map keeps that shift
in its metadata as ``frame_origin``: where its (0, 0, 0) lies in the poses' frame.
Numpy only: ``ndtom info`` and the exports read it without Taichi.
"""

from __future__ import annotations

from typing import Any

import numpy as np

FRAME_ORIGIN_STEP = 100.0  # m: a shifted frame's origin is rounded to this, to read well


def far_origin(T_world_sensor: Any, cells: Any, resolution: float) -> np.ndarray | None:
    """The pose's position rounded to ``FRAME_ORIGIN_STEP`` when it lies outside the middle
    half of a grid of ``cells`` (per axis, centred on the origin) at ``resolution``; else None."""
    p = np.asarray(T_world_sensor, np.float64)[:3, 3]
    quarter = np.asarray(cells, np.float64) * float(resolution) / 4.0
    if not np.isfinite(p).all() or (np.abs(p) <= quarter).all():
        return None
    return np.round(p / FRAME_ORIGIN_STEP) * FRAME_ORIGIN_STEP


def as_frame_origin(value: Any) -> np.ndarray | None:
    """A ``frame_origin`` as kept in metadata or a manifest: three finite metres, else None
    (absent or damaged)."""
    if value is None or isinstance(value, (str, bytes)):
        return None
    try:
        xyz = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        return None
    return xyz if xyz.shape == (3,) and np.isfinite(xyz).all() else None


def shifted(T_world_sensor: Any, origin: np.ndarray) -> np.ndarray:
    """A copy of the pose in the frame whose origin is ``origin``."""
    T = np.array(T_world_sensor, np.float64)
    T[:3, 3] -= origin
    return T
