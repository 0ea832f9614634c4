"""Livox's own point cloud message (``livox_ros_driver/CustomMsg``, ``livox_ros_driver2``).

Livox lidars (Avia, Mid-360, HAP ...) are often recorded with their driver's CustomMsg rather
than PointCloud2: a header, then one record per point (offset time, x, y, z in metres as
float32, reflectivity, tag, line). Deserialised field by field it takes ~50 ms a message of
20k points (a Python object per point), longer than mapping it, so the points are read from
the message's bytes; a message whose bytes do not have the layout expected falls back to the
deserialised message. Its point records are read, as deserialising does, where its point_num
field disagrees (the caller notes it). A beam with no return is (0, 0, 0), which the map leaves out.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

LIVOX_TYPES = ('livox_ros_driver/msg/CustomMsg', 'livox_ros_driver2/msg/CustomMsg')

# A point's record: offset_time u32, x y z f32, reflectivity tag line u8. ROS1 packs it in 19
# bytes; CDR aligns each record's u32 to 4 bytes, so records are 20 apart (the last may be 19).
_ROS1_POINT = np.dtype({'names': ['x', 'y', 'z'], 'formats': ['<f4'] * 3, 'offsets': [4, 8, 12], 'itemsize': 19})
_CDR_POINT = np.dtype({'names': ['x', 'y', 'z'], 'formats': ['<f4'] * 3, 'offsets': [4, 8, 12], 'itemsize': 20})


def _xyz(buf: bytes, start: int, count: int, dt: np.dtype) -> np.ndarray:
    recs = np.frombuffer(buf, dtype=dt, count=count, offset=start)
    out = np.empty((count, 3), np.float32)
    out[:, 0], out[:, 1], out[:, 2] = recs['x'], recs['y'], recs['z']
    return out


def decode_livox_raw(raw: bytes | memoryview, ros1: bool) -> tuple[int, str, np.ndarray] | None:
    """(stamp ns, frame id, (N, 3) float32 points) from a serialised CustomMsg, or None when
    the bytes are not laid out as the message's definition says (the caller deserialises)."""
    buf = bytes(raw)
    try:
        if ros1:
            _, sec, nsec, flen = struct.unpack_from('<IIII', buf, 0)
            frame = buf[16 : 16 + flen].decode()
            at = 16 + flen
            count = struct.unpack_from('<16xI', buf, at)[0]
            start = at + 20
            if len(buf) != start + 19 * count:
                return None
            return sec * 10**9 + nsec, frame, _xyz(buf, start, count, _ROS1_POINT)
        if buf[:2] != b'\x00\x01':  # CDR little-endian only (what ROS2 writes on every common host)
            return None
        body = 4  # the encapsulation header; alignment counts from here
        sec, nsec, flen = struct.unpack_from('<iII', buf, body)
        frame = buf[body + 12 : body + 12 + flen].rstrip(b'\x00').decode()
        rel = 12 + flen
        rel += -rel % 8  # timebase is a u64
        count = struct.unpack_from('<16xI', buf, body + rel)[0]
        start = body + rel + 20
        if not (start + 20 * count - 1 <= len(buf) <= start + 20 * count + 3):
            return None
        if count == 0:
            return sec * 10**9 + nsec, frame, np.empty((0, 3), np.float32)
        # the last record may lack its padding byte: read the others as records, then it
        xyz = np.empty((count, 3), np.float32)
        xyz[:-1] = _xyz(buf, start, count - 1, _CDR_POINT)
        xyz[-1] = struct.unpack_from('<3f', buf, start + 20 * (count - 1) + 4)
        return sec * 10**9 + nsec, frame, xyz
    except (struct.error, ValueError, UnicodeDecodeError):
        return None


def livox_point_num(raw: bytes | memoryview, ros1: bool) -> int | None:
    """The message's point_num field (a driver's count of its points; the records that follow
    are what it holds), or None where the bytes are not a CustomMsg's."""
    buf = bytes(raw)
    try:
        if ros1:
            at = 16 + struct.unpack_from('<12xI', buf, 0)[0]
        else:
            rel = 12 + struct.unpack_from('<8xI', buf, 4)[0]
            at = 4 + rel + (-rel % 8)
        return int(struct.unpack_from('<8xI', buf, at)[0])
    except struct.error:
        return None


def livox_points(msg: Any) -> np.ndarray:
    """(N, 3) float32 points of a deserialised CustomMsg."""
    pts = msg.points
    out = np.empty((len(pts), 3), np.float32)
    for i, p in enumerate(pts):
        out[i] = (p.x, p.y, p.z)
    return out
