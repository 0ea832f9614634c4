"""The scan: points in the sensor frame and the pose that puts them in the world.

Recordings (:mod:`ndtom_ti.io`), the demo scene and the synthetic halls all give
:class:`Scan` objects; every consumer (the mapping loop, sweeps, experiments, the live
viewer) takes a :class:`Scan` or a plain ``(points, T_world_sensor)`` pair through
:func:`scan_parts`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Scan", "scan_parts"]


@dataclass
class Scan:
    points: np.ndarray  # (N, 3) float32 (float64 from FLOAT64 clouds) in the sensor frame, NaNs kept
    T_world_sensor: np.ndarray  # (4, 4) float64: sensor frame -> world
    stamp_ns: int = 0  # header stamp of the cloud (recordings), or a made-up clock
    frame_id: str = ""  # the sensor frame's name, where the source has one
    index: int = 0  # index of the cloud in its source (0-based, all clouds counted)


def scan_parts(item: Any) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3), T_world_sensor (4, 4) float64) of a :class:`Scan` (or any object
    with ``.points`` and ``.T_world_sensor``) or of a ``(points, T_world_sensor)`` pair,
    checked as ``insert_scan`` checks them (TypeError, ValueError)."""
    from .scaninput import as_points, as_pose

    if hasattr(item, "points") and hasattr(item, "T_world_sensor"):
        return as_points(item.points), as_pose(item.T_world_sensor)
    if isinstance(item, (tuple, list)) and len(item) == 2:
        return as_points(item[0]), as_pose(item[1])
    raise TypeError(
        "each scan must have .points (N, 3) and .T_world_sensor (4, 4), or be a (points, T_world_sensor) "
        f"pair; got {type(item).__name__}"
    )
