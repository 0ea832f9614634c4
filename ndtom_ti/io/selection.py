"""ScanSelection: which clouds of a recording are mapped, and where their poses come from.

One frozen object for the scan-selection options: the ``ndtom map`` command builds it, and
the pipeline, the live viewer and :meth:`Recording.scans` take it whole.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .transforms import PoseTrack

CLOUD_TIMES = ("header", "record")  # what a cloud's time is (ScanSelection.cloud_time)


@dataclass(frozen=True)
class ScanSelection:
    """The clouds of one topic to map, and their poses (see :meth:`Recording.scans`).

    ``cloud_topic``: the topic (None: the one point-cloud or depth topic), or several
    separated by commas (several sensors into one map, their clouds in time order); pose source:
    ``fixed_frame`` (the TF chain's root), ``pose_topic``, ``poses_file`` (TUM/KITTI path
    or a PoseTrack) or ``sensor_frame_only`` (identity poses); ``ray_origin_frame``: rays start
    at that TF frame's origin, not the cloud frame's (clouds published in a vehicle or world
    frame, e.g. registered clouds with their odometry in TF only); ``pose_child_frame``: the frame
    whose poses a pose topic's messages give when they name none (PoseStamped,
    PoseWithCovarianceStamped; default: the frame tf_static mounts the cloud frame on, else the
    cloud frame); ``cloud_time``: "header" (a cloud's header stamp; its record time where the
    stamp is 0) or "record" (the bag's record time: clouds stamped on the sensor's own clock,
    not the clock of the poses); ``static_transforms``: mounts the recording lacks (its
    /tf_static was not recorded), each ``(parent, child, (x, y, z), (qx, qy, qz, qw))`` or a
    string as ``static_transform_publisher`` takes it (:func:`parse_static_transform`);
    ``tf_topic``: the TF topic (or its namespace, with its tf_static) of the robot carrying the
    sensor, where several robots' namespaced TF topics give the same frames;
    ``every`` keeps cloud
    indices divisible by k, ``every_distance`` a cloud once the sensor moved that far
    (metres); ``t_start``/``t_end`` are seconds from the recording's start; ``max_scans``
    stops after that many kept scans.
    """

    cloud_topic: str | None = None
    fixed_frame: str | None = None
    pose_topic: str | None = None
    poses_file: str | Path | PoseTrack | None = None
    sensor_frame_only: bool = False
    ray_origin_frame: str | None = None
    pose_child_frame: str | None = None
    cloud_time: str = "header"
    static_transforms: tuple = ()
    tf_topic: str | None = None
    every: int = 1
    every_distance: float | None = None
    t_start: float | None = None
    t_end: float | None = None
    max_scans: int | None = None

    def __post_init__(self) -> None:
        if self.cloud_time not in CLOUD_TIMES:
            raise ValueError(f"cloud_time must be one of {', '.join(CLOUD_TIMES)}, got {self.cloud_time!r}")
        given = self.static_transforms
        if isinstance(given, (str, bytes)) or not isinstance(given, (tuple, list)):
            raise TypeError("static_transforms must be a list of transforms, each a string or (parent, child, t, q)")
        object.__setattr__(self, "static_transforms", tuple(_static(t) for t in given))

    def options(self) -> dict:
        """The selection as a map's metadata records it (``start``/``end``; a pose file's
        absolute path)."""
        poses = self.poses_file
        return {
            "cloud_topic": self.cloud_topic,
            "fixed_frame": self.fixed_frame,
            "pose_topic": self.pose_topic,
            "poses_file": str(Path(poses).resolve()) if poses is not None else None,  # type: ignore[arg-type]
            "sensor_frame_only": self.sensor_frame_only,
            **({"ray_origin_frame": self.ray_origin_frame} if self.ray_origin_frame else {}),
            **({"pose_child_frame": self.pose_child_frame} if self.pose_child_frame else {}),
            **({"cloud_time": self.cloud_time} if self.cloud_time != "header" else {}),
            **({"tf_topic": self.tf_topic} if self.tf_topic else {}),
            **(
                {"static_transforms": [[p, c, list(t), list(q)] for p, c, t, q in self.static_transforms]}
                if self.static_transforms
                else {}
            ),
            "every": self.every,
            "every_distance": self.every_distance,
            "start": self.t_start,
            "end": self.t_end,
            "max_scans": self.max_scans,
        }

    def expected_scans(self, rec: Any, topic: str) -> int | None:
        """About how many scans of ``topic`` in recording ``rec`` this selection keeps (for a
        progress bar; None: unknown)."""
        counts = {n: c for n, _, c in rec.topics()}
        count = sum(counts.get(t, 0) for t in topic.split(','))
        if not count:
            return None
        if self.t_start is not None or self.t_end is not None:
            dur = rec.duration_ns / 1e9
            if dur > 0:
                lo = max(0.0, self.t_start or 0.0)
                hi = min(dur, dur if self.t_end is None else self.t_end)
                count = max(0, round(count * max(0.0, hi - lo) / dur)) + 1
        count = math.ceil(count / self.every)
        if self.max_scans is not None:
            count = min(count, self.max_scans)
        return count


def parse_static_transform(text: str) -> tuple[str, str, tuple, tuple]:
    """A mount as ``static_transform_publisher`` takes it: ``x y z qx qy qz qw parent child``
    or ``x y z yaw pitch roll parent child`` (radians) -> (parent, child, t, q). ValueError."""
    tok = text.replace(",", " ").split()
    if len(tok) not in (8, 9):
        raise ValueError(
            f"static transform {text!r}: give 'x y z qx qy qz qw PARENT CHILD' or 'x y z yaw pitch roll PARENT CHILD'"
        )
    try:
        v = [float(x) for x in tok[:-2]]
    except ValueError:
        raise ValueError(f"static transform {text!r}: its first {len(tok) - 2} values must be numbers") from None
    if not all(math.isfinite(x) for x in v):
        raise ValueError(f"static transform {text!r}: values must be finite")
    if len(v) == 6:  # yaw pitch roll (Z Y X), as static_transform_publisher
        (cy, sy), (cp, sp), (cr, sr) = ((math.cos(a / 2), math.sin(a / 2)) for a in v[3:])
        q = (
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy,
        )
    else:
        q = tuple(v[3:])
        if math.sqrt(sum(x * x for x in q)) < 1e-12:
            raise ValueError(f"static transform {text!r}: the quaternion has zero length")
    return tok[-2], tok[-1], tuple(v[:3]), tuple(q)


def _static(item: Any) -> tuple[str, str, tuple, tuple]:
    if isinstance(item, str):
        return parse_static_transform(item)
    try:
        parent, child, t, q = item
        t, q = tuple(float(x) for x in t), tuple(float(x) for x in q)
    except (TypeError, ValueError):
        raise TypeError(
            f"a static transform is a string or (parent, child, (x, y, z), (qx, qy, qz, qw)); got {item!r}"
        ) from None
    if len(t) != 3 or len(q) != 4 or not all(math.isfinite(x) for x in (*t, *q)):
        raise ValueError(f"static transform {item!r}: give 3 finite translation and 4 quaternion values")
    return str(parent), str(child), t, q
