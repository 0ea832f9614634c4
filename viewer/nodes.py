"""The scene node of each layer a viewer draws, made in viser under ``/ndtom``: the
Gaussians (a batched mesh of 1-sigma ellipsoids, or Gaussian splats), occupied cells
(square points), free cells (translucent boxes), conflicting cells (markers), the
trajectory (a polyline) and the latest scan (points).

``scene`` is viser's scene API (``server.scene``); the arrays are finite. :class:`~.scene.MapScene`
decides what each layer holds and replaces its node.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from . import geometry as geo

__all__ = [
    "CONFLICT_MIN_SIGMA",
    "FREE_OPACITY",
    "SPLAT_MIN_SIGMA",
    "SPLAT_VIEW_SIGMA",
    "cells_node",
    "conflicts_node",
    "free_node",
    "gaussian_node",
    "scan_node",
    "trajectory_node",
]

FREE_OPACITY = 0.15  # free cells: translucent, so the scene shows through them
CONFLICT_MIN_SIGMA = 0.5  # of a cell: the least size of a conflicting cell's marker
SPLAT_MIN_SIGMA = 0.15  # of a cell: the least width of a splat (see gaussian_node)
SPLAT_VIEW_SIGMA = 0.0015  # of the first view's radius: ~1/3 of a pixel there (see gaussian_node)


def gaussian_node(
    scene: Any, g: dict, colors: np.ndarray, res: float, use: str, visible: bool, view_radius: float | None
) -> Any:
    """The Gaussians ``g`` as ``use`` ("splats" or "ellipsoids"); ``view_radius``: the first
    view's (None: the bulk of ``g``'s)."""
    name = "/ndtom/gaussians"
    if use == "splats":
        # splats at least SPLAT_MIN_SIGMA of a cell thick, and about a third of a pixel of the
        # first view: a lidar's ring seen from afar gives line-thin Gaussians, and a splat
        # thinner than a pixel fades out (a big map's native level would be a blank page)
        radius = view_radius if view_radius is not None else geo.bulk_sphere(g["mean"])[1]
        eps = max(SPLAT_MIN_SIGMA * res, SPLAT_VIEW_SIGMA * radius) ** 2
        cov = g["cov"] + eps * np.eye(3)[None]
        return scene.add_gaussian_splats(
            name,
            centers=g["mean"].astype(np.float32),
            covariances=cov.astype(np.float32),
            rgbs=colors.astype(np.float32) / 255.0,
            opacities=np.full((len(cov), 1), 0.9, np.float32),
            visible=visible,
        )
    V, F = geo.icosphere(1)
    wxyz, scales = geo.ellipsoid_instances(g["cov"], min_sigma=0.02 * res)
    return scene.add_batched_meshes_simple(
        name,
        V,
        F,
        batched_wxyzs=wxyz,
        batched_positions=g["mean"].astype(np.float32),
        batched_scales=scales,
        batched_colors=colors,
        lod="off",
        cast_shadow=False,
        receive_shadow=False,
        visible=visible,
    )


def cells_node(scene: Any, key: str, centers: np.ndarray, colors: np.ndarray, res: float, visible: bool) -> Any:
    """Cells of layer ``key`` as square points one cell wide."""
    return scene.add_point_cloud(
        f"/ndtom/{key}",
        centers.astype(np.float32),
        colors,
        point_size=0.9 * res,
        point_shape="square",
        precision="float32",
        visible=visible,
    )


def free_node(scene: Any, centers: np.ndarray, colors: np.ndarray, res: float, visible: bool) -> Any:
    """Free cells as translucent boxes one cell wide: the scene stays visible through them."""
    V, F = geo.unit_box()
    n = len(centers)
    return scene.add_batched_meshes_simple(
        "/ndtom/free",
        V,
        F,
        batched_wxyzs=np.tile(np.array([1.0, 0.0, 0.0, 0.0], np.float32), (n, 1)),
        batched_positions=centers.astype(np.float32),
        batched_scales=np.full((n, 3), 0.9 * res, np.float32),
        batched_colors=colors,
        opacity=FREE_OPACITY,
        lod="off",
        cast_shadow=False,
        receive_shadow=False,
        visible=visible,
    )


def conflicts_node(scene: Any, conf: dict, res: float, visible: bool) -> Any:
    """Markers of the conflicting cells ``conf`` (their Gaussians in the comparison map)."""
    V, F = geo.icosphere(1)
    # at least half a cell in every axis: a few conflicting cells among thousands of
    # Gaussians stay findable (a flat 1-sigma shell vanishes edge-on)
    wxyz, scales = geo.ellipsoid_instances(conf["cov"], min_sigma=CONFLICT_MIN_SIGMA * res)
    return scene.add_batched_meshes_simple(
        "/ndtom/conflicts",
        V,
        F,
        batched_wxyzs=wxyz,
        batched_positions=conf["mean"].astype(np.float32),
        batched_scales=scales * np.float32(1.2),
        batched_colors=geo.CONFLICT_RGB,
        lod="off",
        cast_shadow=False,
        receive_shadow=False,
        visible=visible,
    )


def trajectory_node(scene: Any, traj: np.ndarray, visible: bool) -> Any:
    """The sensor positions ``traj`` (at least two) as a polyline."""
    seg = np.stack([traj[:-1], traj[1:]], axis=1).astype(np.float32)
    return scene.add_line_segments(
        "/ndtom/trajectory",
        seg,
        geo.TRAJECTORY_RGB,
        thickness=3.0,
        thickness_units="screen",
        visible=visible,
    )


def scan_node(scene: Any, scan: np.ndarray, point_size: float, visible: bool) -> Any:
    """The latest scan's points (world frame, float32)."""
    return scene.add_point_cloud(
        "/ndtom/scan",
        scan,
        geo.SCAN_RGB,
        point_size=point_size,
        point_shape="circle",
        precision="float32",
        visible=visible,
    )
