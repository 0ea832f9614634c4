"""Validation of what a caller hands the map: scans' points and poses."""

from __future__ import annotations

from typing import Any

import numpy as np


def cell_box(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest index per axis of (N, 3) cells, as int64. Per column: numpy's
    reduction over axis 0 of an (N, 3) array is ~20x slower."""
    lo = np.array([cells[:, a].min() for a in range(3)], np.int64)
    hi = np.array([cells[:, a].max() for a in range(3)], np.int64)
    return lo, hi


def as_points(points: Any) -> np.ndarray:
    if isinstance(points, np.ma.MaskedArray) and np.ma.getmask(points) is not np.ma.nomask:
        # np.asarray drops the mask: masked coordinates become NaN, dropped and counted as not finite
        points = np.ma.asarray(points, dtype=np.float64).filled(np.nan)
    try:
        arr = np.asarray(points)
    except ValueError as exc:  # numpy on ragged lists
        raise TypeError(f"points must be a real numeric (N, 3) array in metres: {exc}") from None
    if arr.dtype == np.bool_:
        raise TypeError("points must be a real numeric (N, 3) array in metres, got booleans")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise TypeError(f"points must be a real numeric (N, 3) array in metres, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {arr.shape}")
    # float32 and float64 go to the kernels as they are (zero-copy on the CPU).
    return np.ascontiguousarray(arr, dtype=arr.dtype if arr.dtype in (np.float32, np.float64) else np.float64)


_BOTTOM = np.array([0.0, 0.0, 0.0, 1.0])
_EYE3 = np.eye(3)


def as_pose(T: Any, name: str = "T_world_sensor") -> np.ndarray:
    """Validate a rigid 4x4 transform and return it as float64."""
    try:
        M = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be a 4x4 numeric array: {exc}") from None
    if M.shape != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4), got {M.shape}")
    if not np.isfinite(M).all():
        raise ValueError(f"{name} contains NaN or Inf")
    if np.abs(M[3] - _BOTTOM).max() > 1e-9:
        raise ValueError(f"{name} bottom row must be [0, 0, 0, 1], got {M[3].tolist()}")
    R = M[:3, :3]
    err = np.abs(R.T @ R - _EYE3).max()
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    if err > 1e-5 or a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0.0:
        raise ValueError(
            f"{name} is not a rigid transform: its 3x3 block must be a rotation "
            f"(|R^T R - I| = {err:.2e}, det = {np.linalg.det(R):.4f})"
        )
    return M
