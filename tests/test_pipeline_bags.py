"""Small recordings with a known answer, for the pipeline and CLI tests.

A sensor ('lidar', mounted on 'base' with a static, tilted offset) moves over a flat
floor at z = PLANE_Z (world frame 'map') facing a wall at x = WALL_X. Each cloud holds
the floor and wall points seen from its pose (exact, plus 2 mm noise from a fixed
seed), so the right map has floor Gaussians with mean z = PLANE_Z and vertical normals,
and wall Gaussians with mean x = WALL_X and normals along x.

``write_plane_bag`` writes it as ROS1 / ROS2 sqlite3 / ROS2 mcap with variations for
the error tests (a second cloud topic, no TF, a cloud before the first transform,
clouds without x/y/z fields). The test below checks the builder itself (no ndtom_ti).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import io_fixtures as fx  # noqa: E402

PLANE_Z = 0.37
WALL_X = 7.13
RES = 0.25
N_CLOUDS = 5
MS = fx.MS
T0 = fx.T0
STAMPS = [T0 + k * 200 * MS for k in range(N_CLOUDS)]
BASE_MOUNT = ((0.2, 0.0, 0.5), fx.quat_axis_angle((0, 1, 0), math.radians(15)))  # base -> lidar


def T_map_base(k: float) -> np.ndarray:
    return fx.T_of(fx.axis_angle((0, 0, 1), 0.05 * k), (0.4 * k, 0.1 * k, 2.0))


def T_map_lidar(k: float) -> np.ndarray:
    return T_map_base(k) @ fx.T_tq(BASE_MOUNT)


def world_points(k: int, rng: np.random.Generator) -> np.ndarray:
    """Floor (grid around the sensor) and wall points in the world frame, with noise."""
    x0, y0 = T_map_base(k)[:2, 3]
    gx, gy = np.meshgrid(np.arange(-3.0, 3.0, 0.05), np.arange(-3.0, 3.0, 0.05), indexing="ij")
    floor = np.stack([gx.ravel() + x0, gy.ravel() + y0, np.full(gx.size, PLANE_Z)], axis=1)
    floor = floor[floor[:, 0] < WALL_X - 0.3]
    wy, wz = np.meshgrid(np.arange(-2.0, 2.0, 0.05), np.arange(0.9, 2.4, 0.05), indexing="ij")
    wall = np.stack([np.full(wy.size, WALL_X), wy.ravel() + y0, wz.ravel()], axis=1)
    pts = np.concatenate([floor, wall])
    return pts + rng.normal(0.0, 0.002, pts.shape)


def sensor_points(k: int, rng: np.random.Generator) -> np.ndarray:
    T = T_map_lidar(k)
    w = world_points(k, rng)
    return (w - T[:3, 3]) @ T[:3, :3]  # R^T (w - t)


def quat_mul(a: tuple, b: tuple) -> tuple[float, float, float, float]:
    """Hamilton product of quaternions (x, y, z, w): the rotation b, then a."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def write_plane_bag(
    root: Path,
    fmt: str = "ros1",
    *,
    name: str = "plane",
    with_tf: bool = True,
    early_cloud: bool = False,
    second_topic: bool = False,
    bad_fields: bool = False,
    n_clouds: int = N_CLOUDS,
    registered: bool = False,
    odom: bool = True,
    odom_child: str = "lidar",
    no_return: int = 0,
    livox: str | None = None,
    faults: bool = False,
    broken: dict[int, str] | None = None,
    pose_stamped: bool = False,
    odom_zero_stamps: bool = False,
    remount: bool = False,
    sensor_clock: bool = False,
    mount_recorded: bool = True,
) -> Path:
    """Write the scene; returns the bag path (a .bag file or a ROS2 folder). ``registered``:
    the clouds' points in the world frame 'map', as a lidar odometry publishes them, with
    the poses of ``odom_child`` ('lidar' or 'base') on /odom unless not ``odom``. ``no_return``: that many (0, 0, 0) points
    in each cloud, as drivers of organised clouds mark beams with no return. ``livox``: the
    clouds as that Livox driver package's CustomMsg instead of PointCloud2. ``faults``: transforms
    and poses that tf2 drops (a zero quaternion, NaN) among the good ones: an unset static
    mount of an unused frame, an unset first pose before the first cloud, a NaN pose between
    clouds 1 and 2; the map is the one without them. ``broken``: {cloud index: 'truncated' |
    'no frame'}: that cloud's data cut short, or its frame_id left empty; and {-1: 'empty'}: an
    empty cloud with a default header (no frame, stamp 0) before the first, as some drivers
    publish at start-up. ``pose_stamped``: the vehicle's ('base') poses on /pose as
    PoseStamped, which names no child frame, in place of TF's map -> base (tf_static keeps the
    mount base -> lidar). ``odom_zero_stamps``: /odom's header stamps left 0 (its record times
    are right). ``remount``: /tf_static gives base -> lidar a second time, 10 cm higher.
    ``sensor_clock``: the clouds' header stamps on another clock (1000 s behind the poses'),
    their record times right. ``mount_recorded``: False leaves /tf_static out (base -> lidar
    is then unknown to the recording)."""
    rng = np.random.default_rng(42)
    e: list = []
    if faults:
        zero, nan3 = (0.0, 0.0, 0.0, 0.0), (float("nan"), 0.0, 0.0)
        e.append(
            (
                "/tf_static",
                "tf2_msgs/msg/TFMessage",
                T0 - 800 * MS,
                lambda m: m.tf([(T0, "base", "cam", (0, 0, 1), zero)]),
            )
        )
        for topic in ("/tf", "/odom") if registered and odom else ("/tf",):
            for t, tr, q in (
                (T0 - 100 * MS, (0.0, 0.0, 0.0), zero),
                (STAMPS[1] + 100 * MS, nan3, (0.0, 0.0, 0.0, 1.0)),
            ):
                if topic == "/tf":
                    e.append(
                        (
                            topic,
                            "tf2_msgs/msg/TFMessage",
                            t,
                            lambda m, t=t, tr=tr, q=q: m.tf([(t, "map", "base", tr, q)]),
                        )
                    )
                else:
                    e.append(
                        (
                            topic,
                            "nav_msgs/msg/Odometry",
                            t,
                            lambda m, t=t, tr=tr, q=q: m.odometry(t, "map", odom_child, tr, q),
                        )
                    )
    if registered and odom:
        for k in range(n_clouds):
            t, qz = STAMPS[k], fx.quat_axis_angle((0, 0, 1), 0.05 * k)
            T, q = (T_map_lidar(k), quat_mul(qz, BASE_MOUNT[1])) if odom_child == "lidar" else (T_map_base(k), qz)
            e.append(
                (
                    "/odom",
                    "nav_msgs/msg/Odometry",
                    t,
                    lambda m, t=t, tr=T[:3, 3].copy(), q=q: m.odometry(
                        0 if odom_zero_stamps else t, "map", odom_child, tr, q
                    ),
                )
            )
    if with_tf and mount_recorded:
        e.append(
            (
                "/tf_static",
                "tf2_msgs/msg/TFMessage",
                T0 - 900 * MS,
                lambda m: m.tf([(T0, "base", "lidar", *BASE_MOUNT)]),
            )
        )
    if with_tf:
        if remount:
            up = ((0.2, 0.0, 0.6), BASE_MOUNT[1])
            e.append(
                ("/tf_static", "tf2_msgs/msg/TFMessage", T0 - 850 * MS, lambda m: m.tf([(T0, "base", "lidar", *up)]))
            )
        for k in range(n_clouds):
            T = T_map_base(k)
            q = fx.quat_axis_angle((0, 0, 1), 0.05 * k) if k else (0.0, 0.0, 0.0, 1.0)
            t = STAMPS[k]
            if pose_stamped:
                e.append(
                    (
                        "/pose",
                        "geometry_msgs/msg/PoseStamped",
                        t,
                        lambda m, t=t, tr=T[:3, 3].copy(), q=q: m.pose_stamped(t, "map", tr, q),
                    )
                )
                continue
            e.append(
                (
                    "/tf",
                    "tf2_msgs/msg/TFMessage",
                    t,
                    lambda m, t=t, tr=T[:3, 3].copy(), q=q: m.tf([(t, "map", "base", tr, q)]),
                )
            )
    clouds = []
    if early_cloud:
        clouds.append((T0 - 500 * MS, sensor_points(0, rng)))
    clouds += [(STAMPS[k], sensor_points(k, rng)) for k in range(n_clouds)]
    frame = "map" if registered else "lidar"
    for i, (t, pts) in enumerate(clouds):
        if registered:
            T = T_map_lidar(max(i - 1, 0) if early_cloud else i)  # (the early cloud is cloud 0's)
            pts = pts @ T[:3, :3].T + T[:3, 3]
        if no_return:
            pts = np.concatenate([pts[: len(pts) // 2], np.zeros((no_return, 3)), pts[len(pts) // 2 :]])
        if livox:
            e.append(
                (
                    "/points",
                    f"{livox}/msg/CustomMsg",
                    t + 1,
                    lambda m, t=t, p=pts, pkg=livox: m.livox(t, frame, p, pkg),
                )
            )
            continue
        packed = fx.pack_cloud(pts)
        how = (broken or {}).get(i)
        if how == "truncated":
            packed.data = packed.data[: len(packed.data) // 2]
        if how == "no frame":
            e.append(("/points", "sensor_msgs/msg/PointCloud2", t + 1, lambda m, t=t, p=packed: m.cloud(t, "", p)))
            continue
        if bad_fields:  # the same bytes, but the fields are called range, bearing, elevation
            packed.fields = [(new, o, d) for new, (_, o, d) in zip(("range", "bearing", "elevation"), packed.fields)]
        ts = t - 1000 * 10**9 if sensor_clock else t
        e.append(("/points", "sensor_msgs/msg/PointCloud2", t + 1, lambda m, t=ts, p=packed: m.cloud(t, frame, p)))
        if second_topic:
            e.append(
                ("/points_front", "sensor_msgs/msg/PointCloud2", t + 2, lambda m, t=t, p=packed: m.cloud(t, frame, p))
            )
    if (broken or {}).get(-1) == "empty":
        empty = fx.pack_cloud(np.zeros((0, 3)))
        e.append(("/points", "sensor_msgs/msg/PointCloud2", T0 - 700 * MS, lambda m: m.cloud(0, "", empty)))
    e.sort(key=lambda x: x[2])
    return fx.write_bag(fx.bag_path(root, fmt, name), fmt, e)


MOUNT2 = ((-0.3, 0.2, 0.8), fx.quat_axis_angle((1, 0, 0), 0.3))  # base -> lidar2


def write_two_lidar_bag(root: Path, n_clouds: int = 4) -> tuple[Path, list[tuple[np.ndarray, np.ndarray]]]:
    """The scene seen by two lidars ('lidar' on /points, 'lidar2' on /points2, each a third of
    the points); returns the ROS1 bag and [(points, T_map_sensor)] in time order."""
    rng = np.random.default_rng(3)
    e: list = [
        (
            "/tf_static",
            "tf2_msgs/msg/TFMessage",
            T0 - 900 * MS,
            lambda m: m.tf([(T0, "base", "lidar", *BASE_MOUNT), (T0, "base", "lidar2", *MOUNT2)]),
        )
    ]
    want = []
    for k in range(n_clouds):
        t = STAMPS[k]
        qz = fx.quat_axis_angle((0, 0, 1), 0.05 * k) if k else (0.0, 0.0, 0.0, 1.0)
        tr = T_map_base(k)[:3, 3].copy()
        e.append(("/tf", "tf2_msgs/msg/TFMessage", t, lambda m, t=t, tr=tr, q=qz: m.tf([(t, "map", "base", tr, q)])))
        for topic, frame, T, dt in (
            ("/points", "lidar", T_map_lidar(k), 1),
            ("/points2", "lidar2", T_map_base(k) @ fx.T_tq(MOUNT2), 2),
        ):
            w = world_points(k, rng)[::3]
            p = ((w - T[:3, 3]) @ T[:3, :3]).astype(np.float32)
            e.append(
                (
                    topic,
                    "sensor_msgs/msg/PointCloud2",
                    t + dt,
                    lambda m, t=t, f=frame, p=p: m.cloud(t, f, fx.pack_cloud(p)),
                )
            )
            want.append((p, T))
    e.sort(key=lambda x: x[2])
    return fx.write_bag(root / "two.bag", "ros1", e), want


def eig_normals(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(eigenvalues ascending (K, 3), unit normal = eigenvector of the smallest (K, 3))."""
    w, v = np.linalg.eigh(cov)
    return w, v[:, :, 0]


def check_plane_map(m: Any) -> None:
    """Floor Gaussians lie on z = PLANE_Z with vertical normals; wall ones on x = WALL_X."""
    g = m.gaussians()
    w, nrm = eig_normals(g["cov"])
    floor = np.abs(g["mean"][:, 2] - PLANE_Z) < 0.2
    wall = np.abs(g["mean"][:, 0] - WALL_X) < 0.2
    assert floor.sum() > 100 and wall.sum() > 30
    assert (floor | wall).all()  # nothing anywhere else
    np.testing.assert_allclose(g["mean"][floor, 2], PLANE_Z, atol=0.005)
    np.testing.assert_allclose(g["mean"][wall, 0], WALL_X, atol=0.005)
    assert np.sqrt(np.maximum(w[:, 0], 0)).max() < 0.005  # 2 mm noise: every Gaussian is thin
    # the normal is defined where the points spread in two directions (not a single row of
    # points at the edge of the floor patch)
    flat = w[:, 1] > 0.03**2
    assert (flat & floor).sum() > 0.8 * floor.sum() and (flat & wall).sum() > 0.8 * wall.sum()
    assert np.abs(nrm[flat & floor, 2]).min() > 0.99
    assert np.abs(nrm[flat & wall, 0]).min() > 0.99


def test_builder_quaternions_compose_as_the_matrices() -> None:
    q = quat_mul(fx.quat_axis_angle((0, 0, 1), 0.15), BASE_MOUNT[1])
    np.testing.assert_allclose(fx.T_tq(((0, 0, 0), q))[:3, :3], T_map_lidar(3)[:3, :3], atol=1e-12)


def test_builder_points_lie_on_the_scene() -> None:
    rng = np.random.default_rng(0)
    for k in (0, 3):
        p = sensor_points(k, rng)
        T = T_map_lidar(k)
        w = p @ T[:3, :3].T + T[:3, 3]
        on_floor = np.abs(w[:, 2] - PLANE_Z) < 0.01
        on_wall = np.abs(w[:, 0] - WALL_X) < 0.01
        assert (on_floor | on_wall).all() and on_floor.sum() > 10_000 and on_wall.sum() > 2_000
