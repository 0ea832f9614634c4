"""Reading recordings: ROS1 bags and ROS2 bag folders -> (points in sensor frame, T_world_sensor).

No mapping here; :func:`open_recording` and :meth:`Recording.scans` are the entry
points, the rest are the building blocks they use.
"""

from __future__ import annotations

from .errors import RecordingError, TransformTimeError
from .pointcloud import camera_intrinsics, decode_pointcloud2, depth_image_to_points
from .posefile import load_pose_file
from .recording import (
    PoseSourceInfo,
    Recording,
    RecordingInfo,
    Scan,
    ScanStream,
    TopicSummary,
    open_recording,
)
from .selection import ScanSelection
from .tf import TfBuffer, TfEdge
from .transforms import PoseTrack, invert, make_transform, quat_to_rot, rot_to_quat, slerp

__all__ = [
    'PoseSourceInfo',
    'PoseTrack',
    'Recording',
    'RecordingError',
    'RecordingInfo',
    'Scan',
    'ScanSelection',
    'ScanStream',
    'TfBuffer',
    'TfEdge',
    'TopicSummary',
    'TransformTimeError',
    'camera_intrinsics',
    'decode_pointcloud2',
    'depth_image_to_points',
    'invert',
    'load_pose_file',
    'make_transform',
    'open_recording',
    'quat_to_rot',
    'rot_to_quat',
    'slerp',
]
