"""Shared helpers for the tests of ndtom_ti.io: message builders, bag writers, a synthetic scene.

Imported by tests/test_io_*.py (they put this folder on sys.path). Nothing here
reads the real recordings; those live in ../shared/data (see DATA_DIR).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

REPO = Path(__file__).resolve().parents[1]
DATA_DIR = Path(os.environ.get('NDTOM_DATA_DIR', REPO.parent / 'shared' / 'data'))
SIMWORLD = Path(os.environ.get('NDTOM_SIMWORLD', REPO.parent / 'shared' / 'tools' / 'simworld.py'))

FORMATS = ('ros1', 'sqlite3', 'mcap')
T0 = 1_700_000_000 * 10**9  # base stamp of the generated bags (ns)
MS = 1_000_000


# Livox's driver messages (livox_ros_driver and livox_ros_driver2 define the same two)
LIVOX_POINT = '''uint32 offset_time
float32 x
float32 y
float32 z
uint8 reflectivity
uint8 tag
uint8 line
'''
LIVOX_MSG = '''std_msgs/Header header
uint64 timebase
uint32 point_num
uint8 lidar_id
uint8[3] rsvd
{pkg}/CustomPoint[] points
'''
LIVOX_PACKAGES = ('livox_ros_driver', 'livox_ros_driver2')


def _typestores() -> tuple[Any, Any]:
    ts1 = get_typestore(Stores.ROS1_NOETIC)
    if 'tf2_msgs/msg/TFMessage' not in ts1.types:  # noetic store lacks tf2_msgs
        ts1.register(get_types_from_msg('geometry_msgs/TransformStamped[] transforms', 'tf2_msgs/msg/TFMessage'))
    ts2 = get_typestore(Stores.ROS2_HUMBLE)
    for ts in (ts1, ts2):
        for pkg in LIVOX_PACKAGES:
            ts.register(get_types_from_msg(LIVOX_POINT, f'{pkg}/msg/CustomPoint'))
            ts.register(get_types_from_msg(LIVOX_MSG.format(pkg=pkg), f'{pkg}/msg/CustomMsg'))
    return ts1, ts2


TS1, TS2 = _typestores()


# ----------------------------------------------------------------------------- geometry (independent of ndtom_ti)
def axis_angle(axis: Sequence[float], angle: float) -> np.ndarray:
    """Rodrigues: rotation matrix of `angle` about `axis`."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def quat_axis_angle(axis: Sequence[float], angle: float) -> tuple[float, float, float, float]:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    s = math.sin(angle / 2)
    return (a[0] * s, a[1] * s, a[2] * s, math.cos(angle / 2))


def T_of(R: np.ndarray, t: Sequence[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


# ----------------------------------------------------------------------------- messages
class Msgs:
    """Message builders for one typestore (ROS1 and ROS2 types differ: Header.seq, CameraInfo K/k)."""

    def __init__(self, ros1: bool) -> None:
        self.ros1 = ros1
        self.ts = TS1 if ros1 else TS2
        self.T = self.ts.types

    def header(self, stamp: int, frame: str) -> Any:
        tm = self.T['builtin_interfaces/msg/Time'](sec=stamp // 10**9, nanosec=stamp % 10**9)
        H = self.T['std_msgs/msg/Header']
        return H(seq=0, stamp=tm, frame_id=frame) if self.ros1 else H(stamp=tm, frame_id=frame)

    def transform(self, stamp: int, parent: str, child: str, t: Sequence[float], q: Sequence[float]) -> Any:
        T = self.T
        return T['geometry_msgs/msg/TransformStamped'](
            header=self.header(stamp, parent),
            child_frame_id=child,
            transform=T['geometry_msgs/msg/Transform'](
                translation=T['geometry_msgs/msg/Vector3'](x=float(t[0]), y=float(t[1]), z=float(t[2])),
                rotation=T['geometry_msgs/msg/Quaternion'](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
            ),
        )

    def tf(self, transforms: Sequence[tuple[int, str, str, Sequence[float], Sequence[float]]]) -> Any:
        return self.T['tf2_msgs/msg/TFMessage'](transforms=[self.transform(*x) for x in transforms])

    def pose(self, t: Sequence[float], q: Sequence[float]) -> Any:
        T = self.T
        return T['geometry_msgs/msg/Pose'](
            position=T['geometry_msgs/msg/Point'](x=float(t[0]), y=float(t[1]), z=float(t[2])),
            orientation=T['geometry_msgs/msg/Quaternion'](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        )

    def odometry(self, stamp: int, parent: str, child: str, t: Sequence[float], q: Sequence[float]) -> Any:
        T = self.T
        return T['nav_msgs/msg/Odometry'](
            header=self.header(stamp, parent),
            child_frame_id=child,
            pose=T['geometry_msgs/msg/PoseWithCovariance'](pose=self.pose(t, q), covariance=np.zeros(36)),
            twist=T['geometry_msgs/msg/TwistWithCovariance'](
                twist=T['geometry_msgs/msg/Twist'](
                    linear=T['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=0.0),
                    angular=T['geometry_msgs/msg/Vector3'](x=0.0, y=0.0, z=0.0),
                ),
                covariance=np.zeros(36),
            ),
        )

    def pose_stamped(self, stamp: int, parent: str, t: Sequence[float], q: Sequence[float]) -> Any:
        return self.T['geometry_msgs/msg/PoseStamped'](header=self.header(stamp, parent), pose=self.pose(t, q))

    def cloud(self, stamp: int, frame: str, packed: PackedCloud) -> Any:
        PF = self.T['sensor_msgs/msg/PointField']
        return self.T['sensor_msgs/msg/PointCloud2'](
            header=self.header(stamp, frame),
            height=packed.height,
            width=packed.width,
            fields=[PF(name=n, offset=o, datatype=d, count=1) for n, o, d in packed.fields],
            is_bigendian=packed.bigendian,
            point_step=packed.point_step,
            row_step=packed.row_step,
            data=np.frombuffer(packed.data, dtype=np.uint8),
            is_dense=False,
        )

    def laserscan(
        self, stamp: int, frame: str, ranges: np.ndarray, a0: float, da: float, rmin: float, rmax: float
    ) -> Any:
        return self.T['sensor_msgs/msg/LaserScan'](
            header=self.header(stamp, frame),
            angle_min=a0,
            angle_max=a0 + da * (len(ranges) - 1),
            angle_increment=da,
            time_increment=0.0,
            scan_time=0.1,
            range_min=rmin,
            range_max=rmax,
            ranges=np.asarray(ranges, np.float32),
            intensities=np.zeros(len(ranges), np.float32),
        )

    def livox(self, stamp: int, frame: str, points: np.ndarray, pkg: str = 'livox_ros_driver') -> Any:
        P = self.T[f'{pkg}/msg/CustomPoint']
        pts = [
            P(offset_time=i * 10, x=float(x), y=float(y), z=float(z), reflectivity=7, tag=16, line=i % 4)
            for i, (x, y, z) in enumerate(np.asarray(points, np.float32).tolist())
        ]
        return self.T[f'{pkg}/msg/CustomMsg'](
            header=self.header(stamp, frame),
            timebase=stamp,
            point_num=len(pts),
            lidar_id=1,
            rsvd=np.zeros(3, np.uint8),
            points=pts,
        )

    def image(
        self, stamp: int, frame: str, depth: np.ndarray, encoding: str, bigendian: bool = False, pad: int = 0
    ) -> Any:
        """Image from a (h, w) array (float metres for 32FC1, uint16 mm for 16UC1); `pad` bytes per row."""
        code = {'32FC1': 'f4', '16UC1': 'u2', 'rgb8': 'u1', 'mono16': 'u2'}[encoding]
        arr = np.ascontiguousarray(depth, dtype=('>' if bigendian else '<') + code)
        h, w = arr.shape[:2]
        rows = arr.reshape(h, -1).view(np.uint8)
        data = np.concatenate([rows, np.full((h, pad), 0xAB, np.uint8)], axis=1) if pad else rows
        return self.T['sensor_msgs/msg/Image'](
            header=self.header(stamp, frame),
            height=h,
            width=w,
            encoding=encoding,
            is_bigendian=int(bigendian),
            step=data.shape[1],
            data=data.reshape(-1).copy(),
        )

    def camera_info(self, stamp: int, frame: str, h: int, w: int, fx: float, fy: float, cx: float, cy: float) -> Any:
        T = self.T
        K = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], float)
        R = np.eye(3).reshape(-1)
        P = np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], float)
        roi = T['sensor_msgs/msg/RegionOfInterest'](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        mats = dict(D=np.zeros(5), K=K, R=R, P=P) if self.ros1 else dict(d=np.zeros(5), k=K, r=R, p=P)
        return T['sensor_msgs/msg/CameraInfo'](
            header=self.header(stamp, frame),
            height=h,
            width=w,
            distortion_model='plumb_bob',
            binning_x=0,
            binning_y=0,
            roi=roi,
            **mats,
        )


# ----------------------------------------------------------------------------- PointCloud2 packing
@dataclass
class PackedCloud:
    fields: list[tuple[str, int, int]]  # (name, offset, datatype)
    point_step: int
    row_step: int
    height: int
    width: int
    bigendian: bool
    data: bytes


_DT = {'f4': 7, 'f8': 8, 'u1': 2, 'i1': 1, 'u2': 4, 'i2': 3, 'u4': 6, 'i4': 5}


def pack_cloud(
    points: np.ndarray,
    *,
    layout: dict[str, tuple[int, str]] | None = None,
    point_step: int = 12,
    bigendian: bool = False,
    height: int = 1,
    row_pad: int = 0,
    extra_values: dict[str, np.ndarray] | None = None,
) -> PackedCloud:
    """Serialise (N, 3) points with the given field layout {name: (offset, 'f4'|'f8'|...)}.

    Unused bytes are filled with 0xAB so that decoding the wrong bytes shows up.
    """
    layout = layout or {'x': (0, 'f4'), 'y': (4, 'f4'), 'z': (8, 'f4')}
    pts = np.asarray(points, float).reshape(-1, 3)
    n = len(pts)
    width = n // height
    order = '>' if bigendian else '<'
    dt = np.dtype(
        {
            'names': list(layout),
            'formats': [order + c for _, c in layout.values()],
            'offsets': [o for o, _ in layout.values()],
            'itemsize': point_step,
        }
    )
    raw = np.full(n * point_step, 0xAB, np.uint8)
    arr = raw.view(dt)
    for i, name in enumerate('xyz'):
        arr[name] = pts[:, i]
    for name, vals in (extra_values or {}).items():
        arr[name] = vals
    rows = raw.reshape(height, width * point_step)
    if row_pad:
        rows = np.concatenate([rows, np.full((height, row_pad), 0xCD, np.uint8)], axis=1)
    fields = [(name, o, _DT[c]) for name, (o, c) in layout.items()]
    return PackedCloud(fields, point_step, width * point_step + row_pad, height, width, bigendian, rows.tobytes())


# ----------------------------------------------------------------------------- bag writing
# A message to write: (topic, msgtype, record time ns, builder(Msgs) -> message)
Entry = tuple[str, str, int, Callable[[Msgs], Any]]


def bag_path(root: Path, fmt: str, name: str = 'rec') -> Path:
    return root / (f'{name}.bag' if fmt == 'ros1' else f'{name}_{fmt}')


def write_bag(path: Path, fmt: str, entries: Sequence[Entry], latched: Sequence[str] = ('/tf_static',)) -> Path:
    """Write `entries` as a ROS1 bag (fmt 'ros1') or a ROS2 bag folder ('sqlite3' or 'mcap')."""
    ros1 = fmt == 'ros1'
    m = Msgs(ros1)
    topics: dict[str, str] = {}
    for topic, msgtype, _, _ in entries:
        topics.setdefault(topic, msgtype)
    if ros1:
        with Writer1(path) as w:
            conns = {
                t: w.add_connection(t, mt, typestore=TS1, callerid='/test', latching=1 if t in latched else None)
                for t, mt in topics.items()
            }
            for topic, msgtype, t, build in entries:
                w.write(conns[topic], t, TS1.serialize_ros1(build(m), msgtype))
    else:
        zero = QosTime(sec=0, nsec=0)
        latched_qos = Qos(
            history=QosHistory.KEEP_LAST,
            depth=1,
            reliability=QosReliability.RELIABLE,
            durability=QosDurability.TRANSIENT_LOCAL,
            deadline=zero,
            lifespan=zero,
            liveliness=QosLiveliness.AUTOMATIC,
            liveliness_lease_duration=zero,
            avoid_ros_namespace_conventions=False,
        )
        plugin = StoragePlugin.MCAP if fmt == 'mcap' else StoragePlugin.SQLITE3
        with Writer2(path, version=8, storage_plugin=plugin) as w:
            conns = {
                t: w.add_connection(t, mt, typestore=TS2, offered_qos_profiles=[latched_qos] if t in latched else [])
                for t, mt in topics.items()
            }
            for topic, msgtype, t, build in entries:
                w.write(conns[topic], t, TS2.serialize_cdr(build(m), msgtype))
    return path


# ----------------------------------------------------------------------------- the synthetic scene
# Frames: map -> base (moving, /tf and /odom), base -> mount -> sensor (static, two edges;
# two /tf_static messages in ROS2, one latched message in ROS1), sensor -> cam (static).
# Clouds on /cloud in frame 'sensor'; depth images on /cam/depth/image (32FC1) and
# /cam16/depth/image (16UC1) in frame 'cam', each with a camera_info beside it.
TF_TIMES = [T0, T0 + 200 * MS, T0 + 400 * MS]
CLOUD_TIMES = [T0 - 500 * MS, T0, T0 + 100 * MS, T0 + 300 * MS, T0 + 400 * MS]  # #0 is before the first tf
AXIS = (1.0, 2.0, 3.0)  # the base rotates about this fixed axis: slerp = linear angle


def base_angle(stamp: int) -> float:
    return 0.2 + 1.5 * (stamp - T0) / 1e9  # rad; 0.2 .. 0.8 over the tf samples


def base_translation(stamp: int) -> np.ndarray:
    s = (stamp - T0) / 1e9
    return np.array([1.0 + 2.0 * s, -0.5 + 1.0 * s, 0.3 - 0.5 * s])


def T_map_base(stamp: int) -> np.ndarray:
    """Ground truth of the moving edge; linear in time, so interpolation between samples is exact."""
    return T_of(axis_angle(AXIS, base_angle(stamp)), base_translation(stamp))


T_BASE_MOUNT_TQ = ((0.5, 0.0, 1.0), quat_axis_angle((0, 0, 1), math.pi / 2))
T_MOUNT_SENSOR_TQ = ((0.0, 0.1, 0.05), quat_axis_angle((1, 0, 0), math.radians(10)))
T_SENSOR_CAM_TQ = ((0.0, 0.0, 0.2), quat_axis_angle((0.3, 1, 0), -0.4))


def T_tq(tq: tuple[Sequence[float], Sequence[float]]) -> np.ndarray:
    t, q = tq
    x, y, z, w = q
    ang = 2 * math.atan2(math.sqrt(x * x + y * y + z * z), w)
    axis = (x, y, z) if ang else (0, 0, 1)
    return T_of(axis_angle(axis, ang), t)


def T_map_sensor(stamp: int) -> np.ndarray:
    return T_map_base(stamp) @ T_tq(T_BASE_MOUNT_TQ) @ T_tq(T_MOUNT_SENSOR_TQ)


def scene_clouds() -> list[tuple[np.ndarray, dict[str, Any]]]:
    """(expected (N,3) points with NaNs, pack_cloud kwargs) for the 5 clouds, one layout each."""
    rng = np.random.default_rng(7)
    out: list[tuple[np.ndarray, dict[str, Any]]] = []
    p = rng.uniform(-20, 20, (6, 3))
    out.append((p, {}))  # plain float32
    p = rng.uniform(-20, 20, (5, 3))
    out.append(
        (
            p,
            dict(
                layout={'t': (0, 'f8'), 'z': (9, 'f8'), 'x': (17, 'f8'), 'intensity': (25, 'f4'), 'y': (31, 'f8')},
                point_step=41,
                extra_values={'t': np.arange(5.0), 'intensity': np.ones(5)},
            ),
        )
    )  # float64, odd offsets
    p = rng.uniform(-20, 20, (4, 3))
    out.append(
        (
            p,
            dict(
                layout={'x': (0, 'f4'), 'y': (4, 'f4'), 'z': (8, 'f4'), 'ring': (12, 'u2')},
                point_step=16,
                bigendian=True,
                extra_values={'ring': np.arange(4)},
            ),
        )
    )  # big-endian
    p = rng.uniform(-20, 20, (6, 3))
    p[[1, 4]] = np.nan
    out.append(
        (
            p,
            dict(
                height=2,
                row_pad=8,
                point_step=20,
                layout={'x': (4, 'f4'), 'y': (8, 'f4'), 'z': (12, 'f4'), 'rgb': (16, 'u4')},
            ),
        )
    )  # organised
    p = rng.uniform(-20, 20, (3, 3))
    out.append((p, dict(layout={'x': (0, 'f8'), 'y': (8, 'f8'), 'z': (16, 'f8')}, point_step=24)))
    return out


DEPTH_K = dict(fx=50.0, fy=60.0, cx=3.5, cy=2.0)


def scene_depth() -> tuple[np.ndarray, np.ndarray]:
    """(32FC1 metres with NaN/0/inf holes, 16UC1 millimetres with 0 holes), both 5x8."""
    rng = np.random.default_rng(3)
    d32 = rng.uniform(0.5, 4.0, (5, 8)).astype(np.float32)
    d32[0, 0] = np.nan
    d32[2, 3] = 0.0
    d32[4, 7] = np.inf
    d16 = rng.integers(300, 5000, (5, 8)).astype(np.uint16)
    d16[1, 1] = 0
    return d32, d16


def scene_entries(fmt: str, *, with_odom: bool = True, with_tf: bool = True, with_depth: bool = True) -> list[Entry]:
    ros1 = fmt == 'ros1'
    e: list[Entry] = []
    if with_tf:
        static = [
            (T0, 'base', 'mount', *T_BASE_MOUNT_TQ),
            (T0, 'mount', 'sensor', *T_MOUNT_SENSOR_TQ),
            (T0, 'sensor', 'cam', *T_SENSOR_CAM_TQ),
        ]
        if ros1:  # one latched message
            e.append(('/tf_static', 'tf2_msgs/msg/TFMessage', T0 - 600 * MS, lambda m, s=static: m.tf(s)))
        else:  # ROS2 publishers send one message each
            for i, s in enumerate(static):
                e.append(('/tf_static', 'tf2_msgs/msg/TFMessage', T0 - 600 * MS + i, lambda m, s=s: m.tf([s])))
        for t in TF_TIMES:
            q = quat_axis_angle(AXIS, base_angle(t))
            e.append(
                (
                    '/tf',
                    'tf2_msgs/msg/TFMessage',
                    t,
                    lambda m, t=t, q=q: m.tf([(t, 'map', 'base', base_translation(t), q)]),
                )
            )
    if with_odom:
        for t in TF_TIMES:
            q = quat_axis_angle(AXIS, base_angle(t))
            e.append(
                (
                    '/odom',
                    'nav_msgs/msg/Odometry',
                    t + 1,
                    lambda m, t=t, q=q: m.odometry(t, 'map', 'base', base_translation(t), q),
                )
            )
    for t, (pts, kw) in zip(CLOUD_TIMES, scene_clouds(), strict=True):
        e.append(
            (
                '/cloud',
                'sensor_msgs/msg/PointCloud2',
                t + 2,
                lambda m, t=t, pts=pts, kw=kw: m.cloud(t, 'sensor', pack_cloud(pts, **kw)),
            )
        )
    if with_depth:
        d32, d16 = scene_depth()
        for t in CLOUD_TIMES[1:3]:
            e.append(
                (
                    '/cam/depth/camera_info',
                    'sensor_msgs/msg/CameraInfo',
                    t + 3,
                    lambda m, t=t: m.camera_info(t, 'cam', 5, 8, **DEPTH_K),
                )
            )
            e.append(
                (
                    '/cam/depth/image',
                    'sensor_msgs/msg/Image',
                    t + 3,
                    lambda m, t=t: m.image(t, 'cam', d32, '32FC1', pad=4),
                )
            )
            e.append(
                (
                    '/cam16/depth/camera_info',
                    'sensor_msgs/msg/CameraInfo',
                    t + 3,
                    lambda m, t=t: m.camera_info(t, 'cam', 5, 8, **DEPTH_K),
                )
            )
            e.append(
                (
                    '/cam16/depth/image',
                    'sensor_msgs/msg/Image',
                    t + 3,
                    lambda m, t=t: m.image(t, 'cam', d16, '16UC1', bigendian=True),
                )
            )
    return sorted(e, key=lambda x: x[2])


def expected_depth_points(depth_m: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Pinhole back-projection written out per pixel (the reference for the vectorised code)."""
    out = []
    for v in range(depth_m.shape[0]):
        for u in range(depth_m.shape[1]):
            z = float(depth_m[v, u])
            if z == 0:  # no depth measured: the mapper's mark of no return
                out.append((0.0, 0.0, 0.0))
            elif not math.isfinite(z) or z < 0:
                out.append((math.nan, math.nan, math.nan))
            else:
                out.append(((u - cx) * z / fx, (v - cy) * z / fy, z))
    return np.array(out)
