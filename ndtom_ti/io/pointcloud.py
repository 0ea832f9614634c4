"""Decoding of sensor_msgs/PointCloud2 and depth images into (N, 3) xyz arrays."""

from __future__ import annotations

from typing import Any

import numpy as np

from .errors import RecordingError

__all__ = [
    'DEPTH_ENCODINGS',
    'camera_intrinsics',
    'decode_pointcloud2',
    'depth_image_to_points',
    'pointcloud2_size_mismatch',
]

# sensor_msgs/PointField datatypes
_PF_CODE = {1: 'i1', 2: 'u1', 3: 'i2', 4: 'u2', 5: 'i4', 6: 'u4', 7: 'f4', 8: 'f8'}
_PF_NAME = {1: 'INT8', 2: 'UINT8', 3: 'INT16', 4: 'UINT16', 5: 'INT32', 6: 'UINT32', 7: 'FLOAT32', 8: 'FLOAT64'}

DEPTH_ENCODINGS = ('32FC1', '16UC1')


def _as_bytes(data: Any) -> np.ndarray:
    """Message byte payload (numpy uint8 array from rosbags, or bytes) as a uint8 array, no copy."""
    if isinstance(data, np.ndarray):
        return data.view(np.uint8).reshape(-1) if data.dtype != np.uint8 else data.reshape(-1)
    return np.frombuffer(data, dtype=np.uint8)


def _describe_fields(fields: Any) -> str:
    return (
        ', '.join(
            f"{f.name} ({_PF_NAME.get(f.datatype, f'datatype {f.datatype}')} at offset {f.offset}"
            + (f', count {f.count}' if f.count not in (0, 1) else '')
            + ')'
            for f in fields
        )
        or '(no fields)'
    )


def pointcloud2_size_mismatch(msg: Any) -> tuple[bool, str] | None:
    """Where a PointCloud2's data holds points beyond what its height, width and point_step
    say (a driver's wrong width, or height 0): (no points in the header, what disagrees);
    None where they agree (a last partial point or row padding is not a disagreement)."""
    h, w, step = int(msg.height), int(msg.width), int(msg.point_step)
    size = _as_bytes(msg.data).size
    row_step = int(msg.row_step) or w * step
    have = h * row_step if h * w else 0
    if step <= 0 or size - have < step:
        return None
    said = f'height {h} x width {w} x point_step {step} = {h * w * step:,} bytes'
    if not have:
        return True, f'{said} but {size:,} bytes of data ({size // step:,} points\' worth): its header gives no points'
    return False, f'{said} but {size:,} bytes of data ({(size - have) // step:,} more points\' worth)'


def decode_pointcloud2(msg: Any) -> np.ndarray:
    """x, y, z of a sensor_msgs/PointCloud2 as an (N, 3) array in the message's frame:
    float64 when a coordinate is FLOAT64 (registered clouds in UTM or ECEF coordinates need
    its digits: float32 steps are 0.5 m at 5000 km), else float32.

    Handles any layout: FLOAT32 or FLOAT64 x/y/z at any offsets, any point_step,
    padded rows (row_step > width * point_step), extra fields, big-endian data and
    organised clouds (height > 1; rows are flattened row-major). NaN points are
    kept (N == height * width); the mapper drops and counts them.
    """
    fields: dict[str, Any] = {}
    for f in msg.fields:
        first = fields.setdefault(f.name, f)
        if f.name in ('x', 'y', 'z') and (first.offset, first.datatype) != (f.offset, f.datatype):
            raise RecordingError(
                f'PointCloud2 (frame {msg.header.frame_id!r}) has two fields named {f.name!r}, at offsets '
                f'{first.offset} and {f.offset}: which holds {f.name} is ambiguous. Fields present: '
                f'{_describe_fields(msg.fields)}. The driver writing it needs fixing (or rename the field '
                'in the bag).'
            )
    missing = [n for n in 'xyz' if n not in fields]
    if missing:
        raise RecordingError(
            f"PointCloud2 (frame {msg.header.frame_id!r}) has no {'/'.join(missing)} field; fields present: "
            f"{_describe_fields(msg.fields)}. Only clouds with x, y, z fields can be mapped."
        )
    step = int(msg.point_step)
    order = '>' if msg.is_bigendian else '<'
    formats, offsets = [], []
    wide = any(fields[n].datatype == 8 for n in 'xyz')
    out_dtype = np.float64 if wide else np.float32
    for n in 'xyz':
        f = fields[n]
        if f.datatype not in (7, 8):
            raise RecordingError(
                f"PointCloud2 field {n!r} has datatype {_PF_NAME.get(f.datatype, f.datatype)}; x, y, z must be "
                f"FLOAT32 or FLOAT64. Fields present: {_describe_fields(msg.fields)}"
            )
        size = 4 if f.datatype == 7 else 8
        if f.offset < 0 or f.offset + size > step:
            raise RecordingError(
                f'PointCloud2 field {n!r} at offset {f.offset} does not fit in point_step {step}; '
                f'fields present: {_describe_fields(msg.fields)}'
            )
        formats.append(order + _PF_CODE[f.datatype])
        offsets.append(int(f.offset))
    h, w = int(msg.height), int(msg.width)
    if h * w == 0:
        return np.empty((0, 3), dtype=out_dtype)
    row_step = int(msg.row_step) or w * step  # some writers leave row_step 0 for unorganised clouds
    if row_step < w * step:
        raise RecordingError(f'PointCloud2 row_step {row_step} is smaller than width {w} x point_step {step}')
    data = _as_bytes(msg.data)
    need = (h - 1) * row_step + w * step
    if data.size < need:
        raise RecordingError(
            f'PointCloud2 data is {data.size} bytes but height {h}, width {w}, point_step {step}, '
            f'row_step {row_step} need {need}: the message is truncated'
        )
    dtype = np.dtype({'names': ['x', 'y', 'z'], 'formats': formats, 'offsets': offsets, 'itemsize': step})
    # strided view over the raw bytes: no copy, row padding skipped by the row stride
    pts = np.ndarray(shape=(h, w), dtype=dtype, buffer=data, strides=(row_step, step))
    out = np.empty((h * w, 3), dtype=out_dtype)
    out[:, 0] = pts['x'].reshape(-1)
    out[:, 1] = pts['y'].reshape(-1)
    out[:, 2] = pts['z'].reshape(-1)
    return out


def camera_intrinsics(camera_info: Any) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) from sensor_msgs/CameraInfo (field 'K' in ROS1, 'k' in ROS2)."""
    K = getattr(camera_info, 'k', None)
    if K is None:
        K = getattr(camera_info, 'K', None)
    if K is None or len(K) != 9:
        raise RecordingError('CameraInfo has no 3x3 intrinsic matrix K')
    fx, cx, fy, cy = float(K[0]), float(K[2]), float(K[4]), float(K[5])
    if not (fx > 0 and fy > 0):
        raise RecordingError(
            f'CameraInfo K has fx={fx}, fy={fy}: the camera is not calibrated, so depth pixels cannot be '
            'turned into points. Record a calibrated camera_info or use the PointCloud2 topic.'
        )
    return fx, fy, cx, cy


def depth_image_to_points(msg: Any, camera_info: Any, stride: int = 1) -> np.ndarray:
    """Back-project a depth image to (N, 3) float32 points in its optical frame (z forward, x right, y down).

    Encodings: 32FC1 (metres) and 16UC1 (millimetres). Every ``stride``-th pixel
    of every ``stride``-th row is used (N = ceil(h/stride) * ceil(w/stride)).
    Pixels without depth give rows rather than being dropped, so the output keeps the image
    layout like an organised cloud: 0 (no depth measured, 0 m or 0 mm) gives (0, 0, 0), which
    the mapper counts as no return, as a lidar's beam; NaN, inf or negative depths give NaN
    rows, counted as not finite. The pinhole model of K is used;
    distortion coefficients are ignored (depth images are normally rectified).
    """
    enc = str(msg.encoding)
    if enc.upper() not in DEPTH_ENCODINGS:
        raise RecordingError(
            f"depth image encoding {enc!r} is not supported; expected 32FC1 (metres) or 16UC1 (millimetres). "
            'Colour or other images cannot be mapped; use a depth or point cloud topic.'
        )
    if stride < 1:
        raise ValueError(f'stride must be >= 1, got {stride}')
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    ci_w, ci_h = int(getattr(camera_info, 'width', 0)), int(getattr(camera_info, 'height', 0))
    if ci_w and ci_h and (ci_w, ci_h) != (w, h):
        raise RecordingError(
            f'CameraInfo is for {ci_w}x{ci_h} images but the depth image is {w}x{h}: the intrinsics do not '
            'apply. Use the camera_info topic that belongs to this image.'
        )
    fx, fy, cx, cy = camera_intrinsics(camera_info)
    is_float = enc.upper() == '32FC1'
    item = 4 if is_float else 2
    if h * w == 0:
        return np.empty((0, 3), dtype=np.float32)
    step = step or w * item
    data = _as_bytes(msg.data)
    need = (h - 1) * step + w * item
    if step < w * item or data.size < need:
        raise RecordingError(f'depth image data is {data.size} bytes, step {step}, but {w}x{h} {enc} needs {need}')
    dtype = np.dtype(('>' if msg.is_bigendian else '<') + ('f4' if is_float else 'u2'))
    img = np.ndarray(shape=(h, w), dtype=dtype, buffer=data, strides=(step, item))[::stride, ::stride]
    z = img.astype(np.float64) if is_float else img.astype(np.float64) * 1e-3
    z[~np.isfinite(z) | (z < 0)] = np.nan  # (z == 0, no depth measured, gives (0, 0, 0): no return)
    u = np.arange(0, w, stride, dtype=np.float64)
    v = np.arange(0, h, stride, dtype=np.float64)
    out = np.empty((*z.shape, 3), dtype=np.float32)
    out[..., 0] = (u[None, :] - cx) / fx * z
    out[..., 1] = (v[:, None] - cy) / fy * z
    out[..., 2] = z
    return out.reshape(-1, 3)


def laserscan_to_points(msg: Any) -> np.ndarray:
    """A sensor_msgs/LaserScan (a 2D lidar's sweep) as (N, 3) float32 points in its frame,
    in its x-y plane: beam i at angle ``angle_min + i angle_increment``. Readings outside
    ``[range_min, range_max]`` or not finite mean no return (the message's convention): they
    give (0, 0, 0), the mapper's mark of a beam with no return (dropped and counted)."""
    r = np.asarray(msg.ranges, dtype=np.float64).reshape(-1)
    if not r.size:
        return np.empty((0, 3), dtype=np.float32)
    a0, da = float(msg.angle_min), float(msg.angle_increment)
    lo, hi = float(msg.range_min), float(msg.range_max)
    if not (np.isfinite(a0) and np.isfinite(da)):
        raise RecordingError(
            f'LaserScan angle_min {a0} / angle_increment {da} are not finite: its beams have no direction'
        )
    ang = a0 + da * np.arange(r.size, dtype=np.float64)
    bad = ~np.isfinite(r) | (r <= 0)
    if np.isfinite(lo):
        bad |= r < lo
    if np.isfinite(hi) and hi > 0:
        bad |= r > hi
    r = np.where(bad, 0.0, r)
    out = np.zeros((r.size, 3), dtype=np.float32)
    out[:, 0] = r * np.cos(ang)
    out[:, 1] = r * np.sin(ang)
    return out
