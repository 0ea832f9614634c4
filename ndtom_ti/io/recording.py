"""Open ROS1/ROS2 recordings and stream (points in sensor frame, T_world_sensor) scans."""

from __future__ import annotations

import difflib
import re
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from itertools import pairwise
from pathlib import Path
from types import SimpleNamespace, TracebackType
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection
from rosbags.typesys import Stores, get_typestore

from ..scan import Scan
from .errors import RecordingError, TransformTimeError
from .livox import LIVOX_TYPES, decode_livox_raw, livox_point_num, livox_points
from .pointcloud import (
    DEPTH_ENCODINGS,
    decode_pointcloud2,
    depth_image_to_points,
    laserscan_to_points,
    pointcloud2_size_mismatch,
)
from .posefile import load_pose_file
from .selection import ScanSelection
from .tf import TfBuffer, TfEdge, normalize_frame, stamp_ns
from .transforms import PoseTrack, hole_text, invalid_transform, invert

__all__ = [
    'PoseSourceInfo',
    'Recording',
    'RecordingInfo',
    'Scan',
    'ScanStream',
    'TopicSummary',
    'open_recording',
]

POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
LASERSCAN = 'sensor_msgs/msg/LaserScan'
IMAGE = 'sensor_msgs/msg/Image'
CAMERA_INFO = 'sensor_msgs/msg/CameraInfo'
TF_TYPES = ('tf2_msgs/msg/TFMessage', 'tf/msg/tfMessage')
POSE_TYPES = (
    'nav_msgs/msg/Odometry',
    'geometry_msgs/msg/PoseStamped',
    'geometry_msgs/msg/PoseWithCovarianceStamped',
    'geometry_msgs/msg/TransformStamped',
)
_ROS1_MAGIC = b'#ROSBAG V2.0\n'
# The pose sources `ndtom map` offers a recording without usable poses (other commands
# name their own: cli/evaluation.py replaces this sentence).
POSE_ADVICE = (
    'Map in the sensor frame (identity poses) with --sensor-frame, give poses with --poses FILE '
    '(TUM or KITTI), or name a pose topic with --pose-topic.'
)


def _s(ns: int) -> str:
    return f'{ns / 1e9:.3f} s'


@dataclass(frozen=True)
class TopicSummary:
    name: str
    msgtype: str
    count: int

    def __iter__(self) -> Iterator[Any]:  # unpacks like the tuple (name, msgtype, count)
        return iter((self.name, self.msgtype, self.count))


@dataclass(frozen=True)
class PoseSourceInfo:
    """A place poses could come from: a TF chain to a cloud frame or a pose topic."""

    kind: str  # 'tf' or 'topic'
    name: str  # 'world -> kinect -> openni_depth_optical_frame' or '/icp_odom'
    msgtype: str  # '' for tf
    parent_frame: str
    child_frame: str  # '' when the message names none (PoseStamped)
    count: int  # poses (dynamic transforms for tf; 0 if the chain is static)
    first_ns: int | None
    last_ns: int | None
    constant: bool  # every pose identical (a fixed pose, not a trajectory)


SIZE_DISAGREES = 'data size disagrees with width x height x point_step'  # a skip reason

# Messages of a topic read for the first one that names its frame (Recording._first_message).
_FRAME_LOOKAHEAD = 50
# Clouds of a topic whose stamps are held against their record times (ScanStream._clock_check).
_LAG_CLOUDS = 20


@dataclass
class RecordingInfo:
    path: Path
    format: str  # 'ros1' | 'ros2'
    storage: str  # 'ros1' | 'sqlite3' | 'mcap'
    start_ns: int  # bag record times (not header stamps)
    end_ns: int
    duration_s: float
    message_count: int
    topics: list[TopicSummary]
    tf_frames: list[str]
    tf_tree: dict[str, str]  # child -> parent
    tf_edges: list[TfEdge]  # with static flag, counts and stamp ranges
    mappable_topics: list[str]  # PointCloud2 first, then depth images with CameraInfo
    cloud_frames: dict[str, str]  # mappable topic -> header.frame_id of its first message
    pose_sources: list[PoseSourceInfo]
    default_cloud_topic: str | None  # what scans() uses without cloud_topic
    pose_source: str | None  # what scans() uses without pose options
    pose_error: str | None  # why scans() without options would fail
    notes: list[str] = field(default_factory=list)


# A cloud message's points, by the kind of its topic (depth images need their CameraInfo)
_DECODERS: dict[str, Callable[[Any], np.ndarray]] = {
    'pointcloud2': decode_pointcloud2,
    'livox': livox_points,
    'laserscan': laserscan_to_points,
}


# ---------------------------------------------------------------------------- pose providers
# A provider maps (stamp, cloud frame, cloud index) to T_fixed_cloud or raises
# TransformTimeError (the cloud is skipped and counted).
PoseFn = Callable[[int, str, int], np.ndarray]


@dataclass
class _PoseChoice:
    fn: PoseFn | None
    description: str  # what was chosen, or why it cannot be used
    fixed_frame: str = ''
    range_ns: tuple[int, int] | None = None
    # T_sensor_cloud: takes a cloud's points into the frame the rays start from, where that
    # is not the cloud's own (registered clouds, ray_origin_frame); None when it is.
    to_sensor: PoseFn | None = None
    notes: tuple[str, ...] = ()  # what a run with this choice should say (poses it dropped)
    # the poses' stamps minus their record times, near a record time, of each moving TF edge
    # of the chain or the pose topic (ScanStream._clock_check)
    lag_at: tuple[Callable[[int], int], ...] = ()

    @property
    def usable(self) -> bool:
        return self.fn is not None


def _identity(stamp: int, frame: str, index: int) -> np.ndarray:
    return np.eye(4)


def _tf_fn(tf: TfBuffer, target: str, source: str | None, tol: int) -> PoseFn:
    """T_target_source from TF at the cloud stamp; source None means the cloud's own frame."""

    def fn(stamp: int, frame: str, index: int) -> np.ndarray:
        return tf.lookup(target, frame if source is None else source, stamp, tol)

    return fn


def _track_fn(track: PoseTrack, tol: int, pre: PoseFn | None = None, post: PoseFn | None = None) -> PoseFn:
    """T = pre(stamp) @ track(stamp) @ post(stamp): pre links the fixed frame to the track's
    parent frame, post the track's body frame to the cloud frame (both from TF)."""

    def fn(stamp: int, frame: str, index: int) -> np.ndarray:
        if track.by_index:
            if index >= len(track):
                raise TransformTimeError(f'{track.source} has {len(track)} poses; cloud #{index} has none')
            T = track.poses[index].copy()
        else:
            T = track.at(stamp, tol)
            if T is None:
                gap = track.gap_ns(stamp)
                raise TransformTimeError(
                    f"{track.source}: no pose at {_s(stamp)}, {abs(gap) / 1e9:.3f} s "
                    f"{'before the first' if gap < 0 else 'after the last'} pose "
                    f'({_s(track.first_ns)} .. {_s(track.last_ns)}; tolerance {tol / 1e9:.3f} s)'
                )
            hole = track.hole_at(stamp, tol)
            if hole is not None:
                raise TransformTimeError(f'{track.source}: {hole_text(track, stamp, *hole)}')
        if pre is not None:
            T = pre(stamp, frame, index) @ T
        if post is not None:
            T = T @ post(stamp, frame, index)
        return T

    return fn


def _cloud_stamp(header_ns: int, record_ns: int, by_record: bool = False) -> int:
    """A cloud's time: its header stamp, or where a driver left it 0 (unset) the bag's record
    time; ``by_record`` (ScanSelection.cloud_time "record"): the record time always."""
    return record_ns if by_record or header_ns == 0 else header_ns


# A pose source whose stamps go back by more than this (and stay back) starts a second run of
# its clock (a looped playback, a restarted simulation), not a late message.
_JUMP_NS = 10**9


def _jumps_back(what: str, record_ns: list[int], stamps: list[int]) -> list[tuple[int, str]]:
    """(record time, what) where the stamps of one pose source, in record order, jump back into
    stamps it gave already: a second run of its clock. A jump is a stamp over a second before
    the median of the 5 before it, with the next two back too (one message stamped in the
    future or the past is no run); a clock that restarts before all of the run it ends (sim
    time from 0 again) gives stamps apart from it, which cannot mix (a gap between them is no
    pose: PoseTrack.hole_at)."""
    st = np.asarray(stamps, np.int64)
    cuts = []
    for i in np.flatnonzero(st[1:] < st[:-1] - _JUMP_NS) + 1:
        ref = int(np.median(st[max(0, i - 5) : i]))
        if (st[i : i + 3] < ref - _JUMP_NS).all():
            cuts.append(int(i))
    runs = [st[a:b] for a, b in zip([0, *cuts], [*cuts, len(st)], strict=True)]
    if not any(a.min() <= b.max() and b.min() <= a.max() for k, a in enumerate(runs) for b in runs[k + 1 :]):
        return []  # (no cuts: no runs to overlap)
    return [(int(record_ns[i]), f'{what} from {_s(int(st[i - 1]))} to {_s(int(st[i]))}') for i in cuts]


def _lag_fn(record_ns: list[int], stamps: list[int]) -> Callable[[int], int]:
    """The stamps of a pose source minus their record times, at the sample recorded nearest a
    record time (the lag drifts where simulation time runs slower than the recorder's)."""
    order = np.argsort(record_ns, kind='stable')
    rec = np.asarray(record_ns, np.int64)[order]
    lag = np.asarray(stamps, np.int64)[order] - rec

    def at(t: int) -> int:
        i = int(np.searchsorted(rec, t))
        near = min((j for j in (i - 1, i) if 0 <= j < len(rec)), key=lambda j: abs(int(rec[j]) - t))
        return int(lag[near])

    return at


def _inverse_fn(fn: PoseFn) -> PoseFn:
    """The inverse of a rigid transform provider."""

    def inv(stamp: int, frame: str, index: int) -> np.ndarray:
        return invert(fn(stamp, frame, index))

    return inv


# ---------------------------------------------------------------------------- path handling
def _resolve_path(path: Path) -> tuple[list[Path], str, str]:
    """(paths for AnyReader, 'ros1'|'ros2', storage) or RecordingError saying what the path is.
    A folder of ROS1 bags (a recording split by ``rosbag record --split``, or topics recorded
    into several bags) is read as one recording, its messages in time order."""
    if not path.exists():
        raise RecordingError(
            f'{path} does not exist. Give a ROS1 .bag file or a ROS2 bag folder (the folder that holds metadata.yaml).'
        )
    if (
        path.is_file()
        and (path.name == 'metadata.yaml' or path.suffix in ('.db3', '.mcap'))
        and (path.parent / 'metadata.yaml').is_file()
    ):
        path = path.parent  # a file inside a ROS2 bag: read the bag it belongs to
    if path.is_dir():
        meta = path / 'metadata.yaml'
        if not meta.is_file():
            inside = sorted(p.name for p in path.iterdir())
            bags = [path / n for n in inside if n.endswith('.bag') and (path / n).is_file()]
            # `rosbag reindex` keeps the bag it repaired as NAME.orig.bag: its messages twice
            bags = [b for b in bags if not (b.name.endswith('.orig.bag') and b.with_name(b.name[:-9] + '.bag') in bags)]
            if bags:
                for b in bags:
                    _ros1_file(b)
                return _natural(bags), 'ros1', 'ros1'
            hint = (
                ' Pass a ROS1 .bag file, a folder of them, or a ROS2 bag folder (the folder that holds '
                'metadata.yaml and the .db3/.mcap files).'
            )
            listing = ', '.join(inside[:10]) + (' ...' if len(inside) > 10 else '') if inside else 'it is empty'
            if any(n.endswith(('.db3', '.mcap')) for n in inside):
                # a bag whose recorder was killed before it wrote metadata.yaml
                hint = ' `ros2 bag reindex FOLDER` writes its metadata.yaml from the storage files.'
            raise RecordingError(
                f'{path} is a folder but not a ROS2 bag: it has no metadata.yaml (contents: {listing}).{hint}'
            )
        m = re.search(r'storage_identifier:\s*(\S+)', meta.read_text(errors='replace'))
        storage = m.group(1).strip('\'"') if m else 'sqlite3'
        return [path], 'ros2', storage
    return [_ros1_file(path)], 'ros1', 'ros1'


def _natural(paths: list[Path]) -> list[Path]:
    """Names in the order people count them (run_2 before run_10)."""
    return sorted(paths, key=lambda p: [int(x) if x.isdigit() else x for x in re.split(r'(\d+)', p.name)])


def _split_notes(files: list[Path]) -> list[str]:
    """A note when a lone ROS1 bag looks like one part of a split recording (NAME_3.bag with
    NAME_0.bag ... beside it): mapping it maps that part only."""
    if len(files) != 1 or not (m := re.fullmatch(r'(.+)_(\d+)\.bag', files[0].name)):
        return []
    pat = re.compile(re.escape(m.group(1)) + r'_\d+\.bag')
    others = [p for p in files[0].parent.iterdir() if p != files[0] and pat.fullmatch(p.name)]
    if not others:
        return []
    listing = ', '.join(p.name for p in _natural(others)[:3]) + (' ...' if len(others) > 3 else '')
    note = (
        f'{files[0].name} looks like one part of a split recording ({len(others)} more beside it: {listing}); '
        f'this reads it alone. To map every part, pass the folder {files[0].parent} (its .bag files are read '
        'as one recording)'
    )
    return [note]


def _ros1_file(path: Path) -> Path:
    """``path`` if it is a ROS1 bag of format 2.0, else RecordingError saying what it is."""
    if not path.is_file():  # opening a FIFO would wait for a writer
        raise RecordingError(
            f'{path} is neither a regular file nor a folder (a pipe, device or socket). Give a '
            'ROS1 .bag file or a ROS2 bag folder.'
        )
    with path.open('rb') as fh:
        head = fh.read(len(_ROS1_MAGIC))
    if head == _ROS1_MAGIC:
        if path.suffix != '.bag':  # rosbags picks the format by the suffix
            raise RecordingError(f'{path} is a ROS1 bag but is not named *.bag; rename it to end in .bag')
        return path
    if head.startswith(b'#ROSBAG V1'):
        raise RecordingError(
            f'{path} is a ROS1 bag of format version 1.x; convert it with `rosbag fix` (format 2.0 is supported)'
        )
    if path.suffix in ('.mcap', '.db3'):
        raise RecordingError(
            f'{path} is a ROS2 storage file without the metadata.yaml of its bag folder; '
            'pass the bag folder (it needs metadata.yaml next to the storage file)'
        )
    raise RecordingError(
        f'{path} is not a ROS bag (a ROS1 .bag starts with "#ROSBAG V2.0"; it starts with '
        f'{head!r}). Give a ROS1 .bag file or a ROS2 bag folder.'
    )


def open_recording(path: str | Path) -> Recording:
    """Open a ROS1 .bag file, a folder of ROS1 bags (one recording split into several: read
    in time order), or a ROS2 bag folder (sqlite3 or mcap storage)."""
    return Recording(path)


# ---------------------------------------------------------------------------- recording
class Recording:
    """An open recording; use as a context manager (``with open_recording(p) as rec:``)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.files, self.format, self.storage = _resolve_path(self.path)
        self.file_notes = _split_notes(self.files) if self.format == 'ros1' else []
        default_ts = get_typestore(Stores.ROS2_HUMBLE) if self.format == 'ros2' else None
        try:
            self._reader = AnyReader(self.files, default_typestore=default_ts)
            self._reader.open()
        except Exception as err:  # rosbags raises several types for damaged files
            raise RecordingError(self._damaged(err)) from err
        start, end = self._reader.start_time, self._reader.end_time
        if end < start:  # no messages: rosbags reports start=int64 max, end=0
            start = end = 0
        self.start_ns, self.end_ns = int(start), int(end)
        self._topics = {
            name: (ti.msgtype or '', ti.msgcount, list(ti.connections))
            for name, ti in sorted(self._reader.topics.items())
        }
        self._tf: TfBuffer | None = None
        self._tf_topics: tuple[str, ...] | None = None  # those use_tf chose (None: every TF topic)
        self._tf_bufs: dict[tuple[tuple[str, ...], tuple[int, int] | None], TfBuffer] = {}
        self._jumps: dict[tuple[tuple[str, ...], tuple[int, int] | None], list[tuple[int, str]]] = {}
        self._tf_lags: dict[tuple[str, ...], dict[str, Callable[[int], int]]] = {}  # TF topics -> child -> lag_at
        self._poses = _PoseSources(self)  # pose topics' tracks and the choice of a pose source
        self._first: dict[str, tuple[int, Any] | None] = {}
        self._closed = False

    def _damaged(self, err: BaseException) -> str:
        hint = (
            'The file looks truncated or corrupt (an interrupted recording loses the index at its end); '
            '`rosbag reindex` can repair a ROS1 bag.'
            if self.format == 'ros1'
            else 'The bag folder looks truncated or corrupt: check metadata.yaml and its storage files '
            '(`ros2 bag reindex FOLDER` rebuilds metadata.yaml; an MCAP file cut short can be recovered with '
            '`mcap recover`).'
        )
        return f'cannot read {self.path} as a {self.format.upper()} bag ({type(err).__name__}: {err}). {hint}'

    # -- context manager
    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._reader.close()

    def __enter__(self) -> Recording:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- low level reading
    @property
    def duration_ns(self) -> int:
        return self.end_ns - self.start_ns

    def topics(self) -> list[TopicSummary]:
        return [TopicSummary(n, t, c) for n, (t, c, _) in self._topics.items()]

    def _messages(self, topic: str, stop: int | None = None) -> Iterator[tuple[int, str, bytes]]:
        """(record time, msgtype, raw) of one topic; reader errors become RecordingError."""
        for _, t, mt, raw in self._messages_of([topic], stop):
            yield t, mt, raw

    def _messages_of(self, topics: list[str], stop: int | None = None) -> Iterator[tuple[str, int, str, bytes]]:
        """(topic, record time, msgtype, raw) of one or more topics, in time order; reader
        errors become RecordingError."""
        if self._closed:
            raise RecordingError(f'{self.path} is closed')
        conns: list[Connection] = [c for tp in topics for c in self._topics[tp][2]]
        if not conns:  # (no connections would mean every message to the reader)
            return
        try:
            for conn, t, raw in self._reader.messages(connections=conns, stop=stop):
                yield conn.topic, t, conn.msgtype, raw
        except RecordingError:
            raise
        except Exception as err:
            raise RecordingError(f'reading {", ".join(topics)} failed: ' + self._damaged(err)) from err

    def _deserialize(self, raw: bytes, msgtype: str, topic: str) -> Any:
        try:
            return self._reader.deserialize(raw, msgtype)
        except KeyError as err:  # the type is neither in the bag nor a standard one
            raise RecordingError(
                f'the {topic} messages ({msgtype}) cannot be decoded: {self.path} holds no definition of that '
                'type (older ROS2 bags, Foxy\'s for one, keep none) and it is not a standard ROS message'
                + (
                    '; their bytes are not laid out as that message either (damaged, or another version of the driver)'
                    if msgtype in LIVOX_TYPES
                    else ''
                )
            ) from err
        except Exception as err:
            raise RecordingError(
                f'a {msgtype} message on {topic} in {self.path} cannot be decoded ({err}); the recording is corrupt'
            ) from err

    def _first_message(self, topic: str) -> tuple[int, Any] | None:
        """The topic's first message that names its frame (what its poses are chosen by): a
        driver's first cloud may be an empty one with a default header. The first message
        when none of the first ``_FRAME_LOOKAHEAD`` names one."""
        if topic not in self._first:
            self._first[topic] = None
            for k, (t, msgtype, raw) in enumerate(self._messages(topic)):
                fast = decode_livox_raw(raw, self.format == 'ros1') if msgtype in LIVOX_TYPES else None
                if fast is not None:
                    # its header from the bytes: a bag may lack the driver's type definitions
                    sec, nsec = divmod(fast[0], 10**9)
                    stamp = SimpleNamespace(sec=sec, nanosec=nsec)
                    msg = SimpleNamespace(header=SimpleNamespace(stamp=stamp, frame_id=fast[1]))
                else:
                    msg = self._deserialize(raw, msgtype, topic)
                if self._first[topic] is None:
                    self._first[topic] = (t, msg)
                if normalize_frame(msg.header.frame_id) or k + 1 >= _FRAME_LOOKAHEAD:
                    if normalize_frame(msg.header.frame_id):
                        self._first[topic] = (t, msg)
                    break
        return self._first[topic]

    def _of_type(self, *types: str) -> list[str]:
        return [n for n, (t, c, _) in self._topics.items() if t in types]

    # -- TF and pose topics
    def _tf_buffer(self, topics: tuple[str, ...], span: tuple[int, int] | None = None) -> TfBuffer:
        """The transforms of these TFMessage topics (names ending in tf_static are static);
        ``span``: the moving ones recorded in [lo, hi) record time only (one run of a clock
        that jumps back, :meth:`_clock_jumps`)."""
        buf = self._tf_bufs.get((topics, span))
        if buf is None:
            buf = TfBuffer()
            seen: dict[str, tuple[list[int], list[int]]] = {}  # 'parent -> child' -> (record times, stamps)
            # static first so that a child on both topics is known as static from the start
            for topic in sorted(topics, key=lambda n: not n.endswith('tf_static')):
                static = topic.endswith('tf_static')
                for t, msgtype, raw in self._messages(topic):
                    if span is not None and not static and not span[0] <= t < span[1]:
                        continue
                    msg = self._deserialize(raw, msgtype, topic)
                    for tr in () if static or span else msg.transforms:
                        edge = f'{normalize_frame(tr.header.frame_id)} -> {normalize_frame(tr.child_frame_id)}'
                        rec_ns, stamps = seen.setdefault(edge, ([], []))
                        rec_ns.append(t)
                        stamps.append(stamp_ns(tr.header.stamp))
                    buf.add_message(msg, static=static)
            self._tf_bufs[(topics, span)] = buf
            self._jumps[(topics, span)] = [j for edge, (r, st) in seen.items() for j in _jumps_back(edge, r, st)]
            if span is None:
                self._tf_lags[topics] = {
                    normalize_frame(edge.split(' -> ')[1]): _lag_fn(r, st) for edge, (r, st) in seen.items()
                }
        return buf

    def _tf_key(self) -> tuple[str, ...]:
        """The TF topics poses come from: those :meth:`use_tf` chose, else every one."""
        return self._tf_topics or tuple(self._of_type(*TF_TYPES))

    def tf(self) -> TfBuffer:
        """The transforms poses come from: every TFMessage topic's, or those :meth:`use_tf`
        chose (one robot's of several with namespaced TF topics)."""
        if self._tf is None:
            self._tf = self._tf_buffer(self._tf_key())
        return self._tf

    def _clock_jumps(self) -> list[tuple[int, str]]:
        """(record time, what) where the stamps of the TF edges or pose topics go back into
        stamps they gave already (:func:`_jumps_back`), in record order."""
        self.tf()
        jumps = list(self._jumps[(self._tf_key(), None)])
        for topic in self.pose_topics():
            if topic not in self._poses.jumps:
                self._poses.track(topic)
            jumps += self._poses.jumps[topic]
        return sorted(jumps)

    def _runs(self) -> list[tuple[int, int]]:
        """[lo, hi) record times of the runs of the recording's clock: one, or one more per
        place where it jumps back (a second jump within a second of the first is the same)."""
        cuts: list[int] = []
        for t, _ in self._clock_jumps():
            if not cuts or t - cuts[-1] > _JUMP_NS:
                cuts.append(t)
        bounds = [self.start_ns, *cuts, self.end_ns + 1]
        return list(pairwise(bounds))

    def _use_run(self, t_start: float | None, t_end: float | None) -> str | None:
        """Where the clock jumps back, the poses of the run that holds the time window only;
        RecordingError where the window spans several runs. A note saying which run, or None."""
        self._poses.span = None
        runs = self._runs()
        if len(runs) < 2:
            return None
        lo = self.start_ns + (0 if t_start is None else round(t_start * 1e9))
        hi = self.end_ns if t_end is None else self.start_ns + round(t_end * 1e9)
        inside = [r for r in runs if r[0] <= hi and r[1] > lo]
        rel = [
            ((a - self.start_ns + 999_999) // 1_000_000 / 1e3, (b - 1 - self.start_ns) // 1_000_000 / 1e3)
            for a, b in runs
        ]
        if len(inside) != 1:
            raise RecordingError(
                f'{self._jump_text(runs)}, so a cloud\'s pose would be either run\'s. Map one run at a time: '
                + ' or '.join(f'--start {a:.3f} --end {b:.3f}' for a, b in rel)
            )
        k = runs.index(inside[0])
        self._tf = self._tf_buffer(self._tf_key(), inside[0])
        self._poses.span = inside[0]
        return (
            f"the recording's clock jumps back (a looped playback, a restarted simulation): poses of run {k + 1} "
            f'of {len(runs)} (--start {rel[k][0]:.3f} --end {rel[k][1]:.3f}) only'
        )

    def _jump_text(self, runs: list[tuple[int, int]]) -> str:
        jumps = self._clock_jumps()
        at = ', '.join(_s(b - self.start_ns) for b, _ in runs[1:])
        return (
            f'the stamps of {self.path} jump back at {at} into the recording ({jumps[0][1]}'
            f'{", and more" if len(jumps) > 1 else ""}): it holds {len(runs)} runs of one clock (a looped playback, '
            'a restarted simulation) that give poses at the same stamps'
        )

    def use_tf(self, cloud_topics: list[str], tf_topic: str | None = None) -> None:
        """Choose the TF topics for these cloud topics. Namespaced TF topics that give the same
        frames (each robot's /robotN/tf with map, base_link ..., as Nav2 runs several robots)
        would mix the robots' poses in one tree: the clouds' namespace chooses, or
        ``tf_topic`` (a TF topic or its namespace, with its tf_static); else RecordingError."""
        self._poses.span = None  # (one run of the clock, an earlier scans()'s: all of it again)
        topics = self._of_type(*TF_TYPES)
        groups: dict[str, list[str]] = {}
        for t in topics:
            groups.setdefault(t.rsplit('/', 1)[0], []).append(t)
        if tf_topic is not None:
            name = '/' + tf_topic.strip('/')
            ns = name.rsplit('/', 1)[0] if name in topics else name.rstrip('/')
            if ns not in groups:
                raise RecordingError(
                    f'TF topic {tf_topic!r} is not in {self.path}; TF topics: {", ".join(topics) or "(none)"}'
                )
            self._tf_topics = tuple(groups[ns])
            self._tf = self._tf_buffer(self._tf_topics)
            self._tf.source_note = f'TF from {", ".join(groups[ns])} (tf_topic)'
            return
        if len(groups) < 2:
            self._tf = self._tf_topics = None
            return
        children = {ns: set(self._tf_buffer(tuple(g)).tree()) for ns, g in groups.items()}
        shared = sorted({f for a in children for b in children if a < b for f in children[a] & children[b]})
        if not shared:  # namespaces of different frames: one tree
            self._tf = self._tf_topics = None
            return
        which = {max((ns for ns in groups if c.startswith(ns + '/')), key=len, default=None) for c in cloud_topics}
        listing = ', '.join(topics)
        example = next((t for t in topics if t.rsplit('/', 1)[0] and not t.endswith('tf_static')), topics[0])
        if len(which) == 1 and None not in which:
            ns = which.pop()
            assert ns is not None
            self._tf_topics = tuple(groups[ns])
            self._tf = self._tf_buffer(self._tf_topics)
            self._tf.source_note = (
                f'TF topics of several namespaces give the same frames ({", ".join(shared[:4])}): {listing}; '
                f'using {", ".join(groups[ns])}, those of the cloud topic\'s namespace (--tf-topic chooses others)'
            )
            return
        raise RecordingError(
            f'TF topics of several namespaces give the same frames ({", ".join(shared[:4])}): {listing}. '
            'Merged they would mix the poses of several robots, and the cloud topic '
            f'{", ".join(cloud_topics)} is not in the namespace of one of them. Choose the TF topics of the '
            f'robot that carries the sensor with tf_topic (--tf-topic {example}; its tf_static comes with it).'
        )

    def pose_topics(self) -> list[str]:
        return self._of_type(*POSE_TYPES)

    # -- mappable topics
    def _camera_info_topic(self, image_topic: str) -> str | None:
        """The CameraInfo topic beside an image topic (same namespace)."""
        ns = image_topic.rsplit('/', 1)[0]
        infos = [t for t in self._of_type(CAMERA_INFO) if t.rsplit('/', 1)[0] == ns]
        if len(infos) > 1:
            infos = [t for t in infos if t.endswith('/camera_info')] or infos
        return infos[0] if infos else None

    def _is_depth_topic(self, topic: str) -> bool:
        if self._topics[topic][0] != IMAGE or self._camera_info_topic(topic) is None:
            return False
        first = self._first_message(topic)
        return first is not None and str(first[1].encoding).upper() in DEPTH_ENCODINGS

    def mappable_topics(self) -> list[tuple[str, str]]:
        """(topic, kind) with kind 'pointcloud2', 'livox' (Livox's CustomMsg), 'depth_image' or
        'laserscan' (a 2D lidar), in that order."""
        pcs = [(t, 'pointcloud2') for t in self._of_type(POINTCLOUD2) if self._topics[t][1] > 0]
        livox = [(t, 'livox') for t in self._of_type(*LIVOX_TYPES) if self._topics[t][1] > 0]
        depth = [(t, 'depth_image') for t in self._of_type(IMAGE) if self._is_depth_topic(t)]
        scans = [(t, 'laserscan') for t in self._of_type(LASERSCAN) if self._topics[t][1] > 0]
        return pcs + livox + depth + scans

    def _resolve_cloud_topic(self, cloud_topic: str | None) -> tuple[str, str]:
        mappable = self.mappable_topics()
        listing = ', '.join(f'{t} ({k})' for t, k in mappable) or '(none)'
        if cloud_topic is None:
            for kind, what in (
                ('pointcloud2', 'PointCloud2'),
                ('livox', 'Livox CustomMsg'),
                ('depth_image', 'depth image'),
                ('laserscan', 'LaserScan'),
            ):
                cands = [t for t, k in mappable if k == kind]
                if len(cands) == 1:
                    return cands[0], kind
                if len(cands) > 1:
                    raise RecordingError(
                        f'{self.path} has {len(cands)} {what} topics: {", ".join(cands)}. Choose one with '
                        'cloud_topic (--cloud-topic).'
                    )
            present = ', '.join(f'{n} ({t})' for n, (t, _, _) in self._topics.items()) or '(none: the bag is empty)'
            raise RecordingError(
                f'{self.path} has no topic to map: no sensor_msgs/PointCloud2, Livox CustomMsg or LaserScan '
                f'messages and no depth image (32FC1/16UC1) with a CameraInfo topic beside it. Topics present: {present}'
            )
        name = cloud_topic
        if name not in self._topics and '/' + name.lstrip('/') in self._topics:
            name = '/' + name.lstrip('/')
        if name not in self._topics:
            close = difflib.get_close_matches(name, [t for t, _ in mappable] or list(self._topics), n=1, cutoff=0.5)
            hint = f' Did you mean {close[0]!r}?' if close else ''
            raise RecordingError(
                f'cloud topic {cloud_topic!r} is not in {self.path}.{hint} Mappable topics: '
                f'{listing}. All topics: {", ".join(self._topics) or "(none)"}'
            )
        msgtype = self._topics[name][0]
        if msgtype == POINTCLOUD2:
            return name, 'pointcloud2'
        if msgtype in LIVOX_TYPES:
            return name, 'livox'
        if msgtype == LASERSCAN:
            return name, 'laserscan'
        if msgtype == IMAGE:
            if self._camera_info_topic(name) is None:
                raise RecordingError(
                    f'{name} is an image topic but there is no CameraInfo topic beside it, so '
                    f'its pixels cannot be turned into points. Mappable topics: {listing}'
                )
            return name, 'depth_image'
        raise RecordingError(
            f'{name} has type {msgtype}; a cloud topic must be sensor_msgs/PointCloud2, a Livox '
            f'CustomMsg, a LaserScan or a depth sensor_msgs/Image with CameraInfo. Mappable topics: {listing}'
        )

    # -- public API
    def info(self) -> RecordingInfo:
        try:
            default_topic: str | None = self._resolve_cloud_topic(None)[0]
        except RecordingError:
            default_topic = None
        tf_error = None
        try:  # the TF topics of the default cloud topic (one robot's of several)
            self.use_tf([default_topic] if default_topic else [])
        except RecordingError as err:
            tf_error = str(err)
        tf = self.tf()
        mappable = self.mappable_topics()
        cloud_frames: dict[str, str] = {}
        notes = ([tf.source_note] if tf.source_note else []) + list(tf.notes) + self.file_notes
        if len(self.files) > 1:
            notes.append(
                f'{len(self.files)} ROS1 bags in {self.path.name}, read as one recording in time order: '
                + ', '.join(f.name for f in self.files[:4])
                + (f' ... {self.files[-1].name}' if len(self.files) > 4 else '')
            )
        runs = self._runs()
        if len(runs) > 1:
            notes.append(f'{self._jump_text(runs)}: ndtom map maps one run at a time (--start, --end)')
        for topic, _ in mappable:
            first = self._first_message(topic)
            if first is None:
                continue
            t, msg = first
            cloud_frames[topic] = normalize_frame(msg.header.frame_id)
            if stamp_ns(msg.header.stamp) == 0:
                notes.append(f'{topic}: header stamps are 0 (unset): poses are matched by the bag record times')
            off = _cloud_stamp(stamp_ns(msg.header.stamp), t) - t
            if abs(off) > 10**9:
                notes.append(
                    f'{topic}: header stamps differ from the bag record times by {off / 1e9:.3f} s '
                    '(poses are matched by header stamp)'
                )
        sources: list[PoseSourceInfo] = []
        for frame in dict.fromkeys(cloud_frames.values()):
            if frame in tf and tf.root_of(frame) != frame:
                root = tf.root_of(frame)
                rng = tf.dynamic_range_ns(root, frame)
                chain_children = set(tf.path(root, frame)[0][:-1])
                n = sum(e.count for e in tf.edges() if not e.static and e.child in chain_children)
                sources.append(
                    PoseSourceInfo(
                        'tf',
                        tf.chain_str(root, frame),
                        '',
                        root,
                        frame,
                        n,
                        rng[0] if rng else None,
                        rng[1] if rng else None,
                        rng is None,
                    )
                )
        for topic in self.pose_topics():
            track, parent, child, tnotes = self._poses.track(topic)
            notes.extend(tnotes)
            sources.append(
                PoseSourceInfo(
                    'topic',
                    topic,
                    self._topics[topic][0],
                    parent,
                    child or '',
                    len(track),
                    track.first_ns if len(track) else None,
                    track.last_ns if len(track) else None,
                    track.is_constant(),
                )
            )
        default_topic = pose_source = pose_error = None
        try:
            default_topic, _ = self._resolve_cloud_topic(None)
            if tf_error:
                raise RecordingError(tf_error)
            first = self._first_message(default_topic)
            assert first is not None
            choice = self._poses.choose(
                cloud_frames[default_topic],
                _cloud_stamp(stamp_ns(first[1].header.stamp), first[0]),
                fixed_frame=None,
                pose_topic=None,
                poses_file=None,
                sensor_frame_only=False,
                tol=50_000_000,
                what=default_topic,
            )
            pose_source = choice.description
            self._check_clouds(default_topic)
        except RecordingError as err:
            pose_error = str(err)
        return RecordingInfo(
            path=self.path,
            format=self.format,
            storage=self.storage,
            start_ns=self.start_ns,
            end_ns=self.end_ns,
            duration_s=self.duration_ns / 1e9,
            message_count=sum(c for _, c, _ in self._topics.values()),
            topics=self.topics(),
            tf_frames=tf.frames(),
            tf_tree=tf.tree(),
            tf_edges=tf.edges(),
            mappable_topics=[t for t, _ in mappable],
            cloud_frames=cloud_frames,
            pose_sources=sources,
            default_cloud_topic=default_topic,
            pose_source=pose_source,
            pose_error=pose_error,
            notes=notes,
        )

    def _check_clouds(self, topic: str) -> None:
        """RecordingError where the topic's first clouds cannot be mapped: the first that names
        its frame cannot be decoded (its fields), or every one of the first few is empty."""
        kind = dict(self.mappable_topics()).get(topic)
        if kind not in _DECODERS:
            return
        for k, (_, msgtype, raw) in enumerate(self._messages(topic)):
            fast = decode_livox_raw(raw, self.format == 'ros1') if kind == 'livox' else None
            try:
                if fast is not None:
                    pts = fast[2]
                else:
                    msg = self._deserialize(raw, msgtype, topic)
                    if not normalize_frame(msg.header.frame_id) and k + 1 < _FRAME_LOOKAHEAD:
                        continue  # skipped by ndtom map too (no frame)
                    pts = _DECODERS[kind](msg)
            except RecordingError as err:
                raise RecordingError(f'{topic}: cloud #{k} cannot be mapped: {err}') from err
            if len(pts):
                return
            if k + 1 >= _FRAME_LOOKAHEAD:
                break
        n = min(self._topics[topic][1], _FRAME_LOOKAHEAD)
        every = 'all' if n == self._topics[topic][1] else 'the first'
        raise RecordingError(
            f'{topic}: {every} {n} of its clouds {"are" if n != 1 else "is"} empty (no points): nothing to map'
            + ('' if every == 'all' else '; later ones may have points (--start skips the first)')
        )

    def scans(
        self,
        selection: ScanSelection | None = None,
        *,
        extrapolation_s: float = 0.05,
        depth_stride: int = 1,
        **options: Any,
    ) -> ScanStream:
        """Scans of one cloud topic with their poses; see :class:`ScanStream`.

        ``selection``: a :class:`ScanSelection`; or give its fields here by keyword
        (``options``; given with ``selection``, they replace its fields). The topic and
        pose source are resolved now (so problems raise here); the clouds are read lazily
        while iterating. Pose source preference: TF chain from ``fixed_frame`` (default:
        root of the cloud frame's tree) when it has a moving edge; else the single pose
        topic that fits (composed with the TF offset from its body frame to the cloud
        frame); overridden by ``pose_topic``, ``poses_file`` (TUM/KITTI path or a
        PoseTrack) or ``sensor_frame_only`` (identity poses). ``t_start``/``t_end`` are
        seconds from the bag start (record time); ``every`` keeps cloud indices divisible
        by k; ``every_distance`` keeps a cloud once the sensor moved that far from the
        last kept one; ``max_scans`` stops after that many kept scans.
        """
        sel = replace(selection or ScanSelection(), **options)
        every, every_distance, max_scans = sel.every, sel.every_distance, sel.max_scans
        t_start, t_end = sel.t_start, sel.t_end
        if every < 1:
            raise ValueError(f'every must be >= 1, got {every}')
        if every_distance is not None and every_distance < 0:
            raise ValueError(f'every_distance must be >= 0, got {every_distance}')
        if max_scans is not None and max_scans < 1:
            raise ValueError(f'max_scans must be >= 1, got {max_scans}')
        if t_start is not None and t_end is not None and t_end < t_start:
            raise ValueError(f't_end ({t_end}) is before t_start ({t_start})')
        for name, v in (('t_start', t_start), ('t_end', t_end)):
            if v is not None and not np.isfinite(v):
                raise ValueError(f'{name} must be a finite number of seconds from the recording\'s start, got {v}')
        long = f'{self.path} is {self.duration_ns / 1e9:.3f} s long (seconds from its first message, by record time)'
        for name, v in (('t_start (--start)', t_start), ('t_end (--end)', t_end)):
            # a time of the recording's clock (a stamp from rqt_bag, `ros2 bag info`) for seconds from its start
            if v is not None and v * 1e9 > self.duration_ns and self.start_ns <= v * 1e9 <= self.end_ns + 1e9:
                raise RecordingError(
                    f'{name} {v:.3f} is a time of the recording\'s clock, but it counts seconds from its start: '
                    f'{name.split()[-1][1:-1]} {(v * 1e9 - self.start_ns) / 1e9:.3f} is that time. {long}'
                )
        if t_start is not None and t_start * 1e9 > self.duration_ns:
            raise RecordingError(f't_start (--start) {t_start:g} s is past the end: {long}')
        if t_end is not None and t_end < 0:
            raise RecordingError(f't_end (--end) {t_end:g} s is before the start: {long}')
        if depth_stride < 1:
            raise ValueError(f'depth_stride must be >= 1, got {depth_stride}')
        names = [n.strip() for n in sel.cloud_topic.split(',')] if sel.cloud_topic else [None]
        if len(names) > 1 and any(not n for n in names):
            raise ValueError(f'cloud_topic {sel.cloud_topic!r}: give topic names separated by commas')
        self.use_tf([self._resolve_cloud_topic(n)[0] for n in names], sel.tf_topic)
        # (before the mounts given: they go into its TF; poses from a file or none need no run)
        own = not sel.sensor_frame_only and sel.poses_file is None
        run = self._use_run(sel.t_start, sel.t_end) if own else None
        if sel.static_transforms:
            tf = self.tf()
            for parent, child, t, q in sel.static_transforms:  # (a recording without its /tf_static)
                tf.give(parent, child, t, q)
        if len(names) > 1 and sel.poses_file is not None and not isinstance(sel.poses_file, PoseTrack):
            sel = replace(sel, poses_file=load_pose_file(sel.poses_file))  # read once for every topic
        parts = [self._stream_part(n, sel, round(extrapolation_s * 1e9)) for n in names]
        if run is not None:
            parts[0].choice.notes = (run, *parts[0].choice.notes)
        topics = [p.topic for p in parts]
        if len(set(topics)) < len(topics):
            raise ValueError(f'cloud_topic {sel.cloud_topic!r} names a topic twice')
        if len(parts) > 1:
            fixed = {p.choice.fixed_frame for p in parts}
            if len(fixed) > 1:
                raise RecordingError(
                    'the cloud topics get their poses in different frames ('
                    + ', '.join(f'{p.topic}: {p.choice.fixed_frame!r}' for p in parts)
                    + '); give one with fixed_frame (--fixed-frame)'
                )
            if isinstance(sel.poses_file, PoseTrack) and sel.poses_file.by_index:
                raise RecordingError('a poses file without stamps gives the poses of one topic by cloud index')
        return ScanStream(self, parts, selection=sel, depth_stride=depth_stride)

    def _stream_part(self, name: str | None, sel: ScanSelection, tol: int) -> _StreamPart:
        """One cloud topic of a stream: its kind, frame, pose source and camera infos."""
        topic, kind = self._resolve_cloud_topic(name)
        first = self._first_message(topic)
        if first is None:
            raise RecordingError(f'{topic} has no messages')
        frame = normalize_frame(first[1].header.frame_id)
        choice = self._poses.choose(
            frame,
            _cloud_stamp(stamp_ns(first[1].header.stamp), first[0], sel.cloud_time == 'record'),
            fixed_frame=sel.fixed_frame,
            pose_topic=sel.pose_topic,
            poses_file=sel.poses_file,
            sensor_frame_only=sel.sensor_frame_only,
            tol=tol,
            what=topic,
            ray_origin_frame=sel.ray_origin_frame,
            pose_child_frame=sel.pose_child_frame,
        )
        assert choice.fn is not None
        infos: list[tuple[int, Any]] = []
        if kind == 'depth_image':
            info_topic = self._camera_info_topic(topic)
            assert info_topic is not None
            infos = sorted(
                (
                    (stamp_ns(m.header.stamp), m)
                    for m in (self._deserialize(raw, mt, info_topic) for _, mt, raw in self._messages(info_topic))
                ),
                key=lambda x: x[0],
            )
            if not infos:
                raise RecordingError(f'{info_topic} has no messages, so {topic} cannot be turned into points')
        return _StreamPart(topic, kind, choice, frame, infos)


# ---------------------------------------------------------------------------- pose sources
class _PoseSources:
    """The pose sources of a :class:`Recording` (owned by it): the tracks of its pose topics,
    read once, and the choice of where a cloud's poses come from (TF, a pose topic, a poses
    file or the sensor frame), with the reasons each candidate cannot be used."""

    def __init__(self, rec: Recording) -> None:
        self._rec = rec
        # (topic, span) -> (track, parent, child, notes)
        self._pose_tracks: dict[tuple[str, tuple[int, int] | None], tuple[PoseTrack, str, str | None, list[str]]] = {}
        self.jumps: dict[str, list[tuple[int, str]]] = {}  # topic -> where its stamps jump back (_jumps_back)
        self.lags: dict[str, Callable[[int], int]] = {}  # topic -> its stamps minus record times (_lag_fn)
        self.span: tuple[int, int] | None = None  # [lo, hi) record time: one run of a clock (Recording._use_run)

    def track(self, topic: str) -> tuple[PoseTrack, str, str | None, list[str]]:
        """(track T_parent_child, parent frame, child frame or None, notes) of a pose topic
        (its messages recorded in ``span`` only, where that is set)."""
        span = self.span
        if (topic, span) not in self._pose_tracks:
            rec_ns: list[int] = []
            msgtype = self._rec._topics[topic][0]
            stamps: list[int] = []
            ts: list[tuple[float, float, float]] = []
            qs: list[tuple[float, float, float, float]] = []
            notes: list[str] = []
            bad: dict[str, int] = {}
            parent: str | None = None
            child: str | None = None
            zero_stamps = 0
            for t_rec, mt, raw in self._rec._messages(topic):
                if span is not None and not span[0] <= t_rec < span[1]:
                    continue
                m = self._rec._deserialize(raw, mt, topic)
                if msgtype.endswith('TransformStamped'):
                    v, q = m.transform.translation, m.transform.rotation
                else:
                    pose = m.pose.pose if hasattr(m.pose, 'covariance') else m.pose
                    v, q = pose.position, pose.orientation
                c = normalize_frame(m.child_frame_id) if hasattr(m, 'child_frame_id') else None
                p = normalize_frame(m.header.frame_id)
                if parent is None:
                    parent, child = p, c
                elif (p, c) != (parent, child) and not notes:
                    notes.append(
                        f'{topic}: frames change from {parent} -> {child} to {p} -> {c}; using {parent} -> {child}'
                    )
                t, r = (v.x, v.y, v.z), (q.x, q.y, q.z, q.w)
                why = invalid_transform(t, r)
                if why is not None:  # an unset or broken pose (tf2 drops such transforms too)
                    bad[why] = bad.get(why, 0) + 1
                    continue
                stamp = stamp_ns(m.header.stamp)
                zero_stamps += stamp == 0
                rec_ns.append(t_rec)
                stamps.append(_cloud_stamp(stamp, t_rec))  # an unset stamp: the bag's record time, as for clouds
                ts.append(t)
                qs.append(r)
            if zero_stamps:
                notes.append(f'{topic}: {zero_stamps} poses stamped 0 (unset): matched by the bag\'s record time')
            for why, n in bad.items():
                notes.append(f'{topic}: ignored {n} pose{"s" if n != 1 else ""} with {why}')
            track = PoseTrack.from_tq(stamps, ts, qs, source=f'pose topic {topic}')
            self._pose_tracks[(topic, span)] = (track, parent or '', child, notes)
            if span is None:
                self.jumps[topic] = _jumps_back(topic, rec_ns, stamps)
                if stamps:
                    self.lags[topic] = _lag_fn(rec_ns, stamps)
        return self._pose_tracks[(topic, span)]

    def _clock_mismatch(self, first_stamp: int, lo: int, hi: int, tol: int) -> bool:
        """True when the pose stamps cannot be on the clock of the clouds: the clouds, which span
        about the bag duration from the first one, do not overlap [lo - tol, hi + tol] at all."""
        return first_stamp + self._rec.duration_ns < lo - tol or first_stamp > hi + tol

    def _clock_text(self, what: str, first_stamp: int, lo: int, hi: int) -> str:
        far = min(abs(first_stamp - lo), abs(first_stamp - hi)) > 86_400 * 10**9
        return (
            f'{what} is stamped {_s(lo)} .. {_s(hi)} but the clouds from {_s(first_stamp)} on: the times '
            'do not overlap'
            + (' (different clocks, e.g. simulation time, or data of another recording)' if far else '')
            + (
                '; clouds stamped on the sensor\'s own clock are matched by the bag\'s record time with '
                '--cloud-time record (cloud_time="record")'
                if self._rec.start_ns - 10**9 <= lo <= self._rec.start_ns + self._rec.duration_ns + 10**9
                else ''
            )
        )

    def _tf_choice(self, frame: str, fixed_frame: str | None, first_stamp: int, tol: int) -> _PoseChoice:
        tf = self._rec.tf()
        if not tf.frames():
            return _PoseChoice(None, 'TF: the recording has no /tf or /tf_static transforms')
        if frame not in tf:
            # its mount not recorded (/tf_static missing, or in another part of a split recording)
            moving = [e.child for e in tf.edges() if not e.static]
            parent = 'base_link' if 'base_link' in tf else moving[0] if moving else 'PARENT'
            return _PoseChoice(
                None,
                f"TF: the cloud frame {frame!r} is not in the TF tree (frames that exist: {', '.join(tf.frames())}); "
                f"if the recording lacks its mount, give it with --static-transform 'X Y Z QX QY QZ QW {parent} {frame}'"
                + ''.join(f'; {n}' for n in self._rec.file_notes),
            )
        if fixed_frame:  # a frame with two parents: the one towards the fixed frame
            tf.choose_parent(fixed_frame, frame)
        # a frame of the chain with a second parent, ignored: said first where the chain fails
        twice = ''.join(f'{n}; with it, ' for n in tf.parent_notes(tf._ancestors(frame)))
        fixed = normalize_frame(fixed_frame) if fixed_frame else tf.root_of(frame)
        if fixed not in tf:
            return _PoseChoice(
                None,
                f"TF: {twice}the fixed frame {fixed!r} is not in the TF tree (frames that exist: {', '.join(tf.frames())})",
            )
        try:
            chain = tf.chain_str(fixed, frame)
            static = tf.chain_is_static(fixed, frame)
        except RecordingError as err:
            return _PoseChoice(None, f'TF: {twice}{err}')
        if fixed == frame and not fixed_frame:
            moving = [
                f for f in tf.frames() if f != frame and tf.root_of(f) == frame and not tf.chain_is_static(frame, f)
            ]
            hint = (
                f'; if its clouds are registered (already in {frame!r}), give the moving frame the rays start '
                f'from as --ray-origin-frame (ray_origin_frame), one of: {", ".join(moving)}'
                if moving
                else ''
            )
            return _PoseChoice(
                None, f'TF: the cloud frame {frame!r} is the root of its TF tree, so TF does not give its motion{hint}'
            )
        if static and not fixed_frame:
            return _PoseChoice(None, f'TF: the chain {chain} is static only (the sensor mounting, not its motion)')
        rng = tf.dynamic_range_ns(fixed, frame)
        if rng is not None and self._clock_mismatch(first_stamp, rng[0], rng[1], tol):
            return _PoseChoice(None, f'TF: {twice}' + self._clock_text(f'the chain {chain}', first_stamp, *rng))
        up_s, up_t = tf.path(fixed, frame)
        lags = self._rec._tf_lags.get(self._rec._tf_key(), {})
        moving = tuple(lags[f] for f in up_s[:-1] + up_t[:-1] if not tf.is_static(f) and f in lags)
        return _PoseChoice(
            _tf_fn(tf, fixed, None, tol),
            f'tf: {chain}' + (' (static)' if static else ''),
            fixed,
            rng,
            notes=tuple(tf.run_notes()),
            lag_at=moving,
        )

    def _origin_choice(self, frame: str, origin: str, fixed_frame: str | None, tol: int) -> _PoseChoice:
        """Poses from TF with the rays starting at frame ``origin`` rather than at the cloud
        frame: the points are taken into ``origin``'s frame (TF at each cloud's stamp)."""
        tf = self._rec.tf()
        for f, what in ((origin, 'ray origin frame'), (frame, 'cloud frame')):
            if f not in tf:
                raise RecordingError(
                    f'the {what} {f!r} is not in the TF tree (frames that exist: {", ".join(tf.frames()) or "none"})'
                )
        if not tf.connects(origin, frame):
            raise RecordingError(f'TF does not connect the ray origin frame {origin!r} to the cloud frame {frame!r}')
        fixed = normalize_frame(fixed_frame) if fixed_frame else tf.root_of(origin)
        if not tf.connects(fixed, origin):
            raise RecordingError(f'TF does not connect the fixed frame {fixed!r} to the ray origin frame {origin!r}')
        if fixed == origin:
            raise RecordingError(
                f'the ray origin frame {origin!r} is the fixed frame: it does not move. Name the frame of the '
                'sensor (or of the vehicle carrying it) whose motion TF records.'
            )
        desc = f'tf: {tf.chain_str(fixed, origin)}; rays from {origin!r}, the clouds in {frame!r}'
        if frame != origin:
            desc += f' (tf {tf.chain_str(origin, frame)})'
        return _PoseChoice(
            _tf_fn(tf, fixed, origin, tol),
            desc,
            fixed,
            tf.dynamic_range_ns(fixed, origin),
            _tf_fn(tf, origin, None, tol),
        )

    def _topic_choice(
        self,
        topic: str,
        frame: str,
        fixed_frame: str | None,
        first_stamp: int,
        tol: int,
        explicit: bool,
        origin: str | None = None,
        pose_child_frame: str | None = None,
    ) -> _PoseChoice:
        msgtype = self._rec._topics[topic][0]
        track, parent, child, tnotes = self.track(topic)
        label = f'pose topic {topic} ({msgtype} {parent} -> {child if child else "(no child frame)"})'
        if not len(track):
            return _PoseChoice(None, f'{label}: no messages')
        extra = (
            '; it is also constant (the same pose in every message)' if len(track) > 1 and track.is_constant() else ''
        )
        if not explicit and self._clock_mismatch(first_stamp, track.first_ns, track.last_ns, tol):
            return _PoseChoice(
                None, f'{label}: ' + self._clock_text('it', first_stamp, track.first_ns, track.last_ns) + extra
            )
        tf = self._rec.tf()
        given = normalize_frame(pose_child_frame) if pose_child_frame else ''
        if given and child and given != child:
            raise RecordingError(
                f'{label}: its messages name their frame {child!r}; pose_child_frame (--pose-child-frame) '
                f'{given!r} is for poses whose messages name none'
            )
        if not child:
            # A PoseStamped or PoseWithCovarianceStamped (amcl_pose, a motion-capture body) gives
            # a vehicle's pose: by default the frame tf_static mounts the cloud frame on.
            child = given or tf.mount_base(frame, parent)
            if given or child != frame:
                how = 'as given' if given else f'the frame tf_static mounts {frame!r} on'
                label = f'pose topic {topic} ({msgtype} {parent} -> {child}: its messages name no child frame; {how})'
            if child == frame:
                child = None
        post: PoseFn | None = None
        to_sensor: PoseFn | None = None
        desc = label
        if origin is not None:
            # Rays from frame `origin`: the pose topic's body frame, or a frame TF fixes to it.
            body = child or origin
            if body != origin:
                if not tf.connects(body, origin):
                    raise RecordingError(
                        f'{label}: TF does not connect its frame {body!r} to the ray origin {origin!r}'
                    )
                post = _tf_fn(tf, body, origin, tol)
                desc += f' + tf {tf.chain_str(body, origin)}'
            if frame == parent:
                desc += f' (registered clouds in {frame!r}, rays from {origin!r})'
                to_sensor = _inverse_fn(_track_fn(track, tol, None, post))
            elif frame != origin:
                if not tf.connects(frame, origin):
                    raise RecordingError(f'TF does not connect the cloud frame {frame!r} to the ray origin {origin!r}')
                desc += f' (rays from {origin!r}, the clouds in {frame!r}: tf {tf.chain_str(origin, frame)})'
                to_sensor = _tf_fn(tf, origin, None, tol)
        elif frame == parent:
            # The clouds are given in the frame the poses are (registered, as a lidar odometry
            # publishes them): their points stay where they are, and the pose says where
            # the rays start. Without this, rays would start at that frame's origin.
            desc += (
                f' (the clouds are in {frame!r}, the frame of these poses: registered clouds, '
                f'used as they are, each ray from the position of {child or "the pose"!r})'
            )
            to_sensor = _inverse_fn(_track_fn(track, tol))
        elif not child or child == frame:
            if not child and not given:
                desc += (
                    f' (the messages name no child frame, and tf_static mounts {frame!r} on none: taken as its pose)'
                )
        elif tf.connects(child, frame):
            how = 'tf_static' if tf.chain_is_static(child, frame) else 'tf'
            desc += f' + {how} {tf.chain_str(child, frame)}'
            post = _tf_fn(tf, child, None, tol)
        elif explicit:
            desc += f' (TF does not connect {child!r} to the cloud frame {frame!r}: assuming they coincide)'
        else:
            return _PoseChoice(
                None, f'{label}: TF does not connect its frame {child!r} to the cloud frame {frame!r}' + extra
            )
        pre: PoseFn | None = None
        fixed = parent
        if fixed_frame and normalize_frame(fixed_frame) != parent:
            fixed = normalize_frame(fixed_frame)
            if not tf.connects(fixed, parent):
                return _PoseChoice(
                    None,
                    f'{label}: it gives poses in {parent!r}, and TF does not connect that to the fixed frame {fixed!r}',
                )
            desc = f'tf {tf.chain_str(fixed, parent)} + ' + desc
            pre = _tf_fn(tf, fixed, parent, tol)
        return _PoseChoice(
            _track_fn(track, tol, pre, post),
            desc + extra,
            fixed,
            (track.first_ns, track.last_ns),
            to_sensor,
            notes=(*tnotes, *tf.run_notes()),
            lag_at=(self.lags[topic],) if topic in self.lags else (),
        )

    def choose(
        self,
        frame: str,
        first_stamp: int,
        *,
        fixed_frame: str | None,
        pose_topic: str | None,
        poses_file: str | Path | PoseTrack | None,
        sensor_frame_only: bool,
        tol: int,
        what: str,
        ray_origin_frame: str | None = None,
        pose_child_frame: str | None = None,
    ) -> _PoseChoice:
        given = [
            n
            for n, v in (
                ('pose_topic', pose_topic),
                ('poses_file', poses_file),
                ('sensor_frame_only', sensor_frame_only),
            )
            if v
        ]
        if len(given) > 1:
            raise RecordingError(f'give only one pose source; got {" and ".join(given)}')
        origin = normalize_frame(ray_origin_frame) if ray_origin_frame else None
        if origin and given and not pose_topic:
            raise RecordingError(f'ray_origin_frame goes with poses from TF or a pose topic, not with {given[0]}')
        if pose_child_frame and (poses_file is not None or sensor_frame_only):
            raise RecordingError(f'pose_child_frame goes with poses from a pose topic, not with {given[0]}')
        if origin and not pose_topic:
            return self._origin_choice(frame, origin, fixed_frame, tol)
        if sensor_frame_only:
            return _PoseChoice(_identity, f'sensor frame {frame!r} (identity poses)', frame)
        if poses_file is not None:
            track = poses_file if isinstance(poses_file, PoseTrack) else load_pose_file(poses_file)
            if not len(track):
                raise RecordingError(f'{track.source}: no poses')
            rng = None if track.by_index else (track.first_ns, track.last_ns)
            return _PoseChoice(_track_fn(track, tol), f'poses file {track.source}', fixed_frame or 'world', rng)
        if pose_topic is not None:
            name = pose_topic if pose_topic in self._rec._topics else '/' + pose_topic.lstrip('/')
            if name not in self._rec._topics or self._rec._topics[name][0] not in POSE_TYPES:
                cands = self._rec.pose_topics()
                close = difflib.get_close_matches(pose_topic, cands, n=1, cutoff=0.5)
                why = (
                    f'has type {self._rec._topics[name][0]}'
                    if name in self._rec._topics
                    else f'is not in {self._rec.path}'
                )
                raise RecordingError(
                    f'pose topic {pose_topic!r} {why}.'
                    + (f' Did you mean {close[0]!r}?' if close else '')
                    + f' Pose topics ({", ".join(t.split("/")[-1] for t in POSE_TYPES)}) in the recording: '
                    + (', '.join(f'{t} ({self._rec._topics[t][0]})' for t in cands) or '(none)')
                )
            choice = self._topic_choice(
                name,
                frame,
                fixed_frame,
                first_stamp,
                tol,
                explicit=True,
                origin=origin,
                pose_child_frame=pose_child_frame,
            )
            if not choice.usable:
                raise RecordingError(f'{choice.description}. {POSE_ADVICE}')
            return choice
        # automatic: TF first, then a single usable pose topic
        tf_choice = self._tf_choice(frame, fixed_frame, first_stamp, tol)
        if tf_choice.usable:
            return tf_choice
        topic_choices = [
            self._topic_choice(
                t, frame, fixed_frame, first_stamp, tol, explicit=False, pose_child_frame=pose_child_frame
            )
            for t in self._rec.pose_topics()
        ]
        usable = [c for c in topic_choices if c.usable]
        if len(usable) == 1:
            return usable[0]
        if len(usable) > 1:
            raise RecordingError(
                f'several pose topics can give the pose of {frame!r}: '
                + '; '.join(c.description for c in usable)
                + '. Choose one with pose_topic (--pose-topic).'
            )
        reasons = [tf_choice.description] + [c.description for c in topic_choices]
        if not topic_choices:
            reasons.append(
                'no pose topics (nav_msgs/Odometry, geometry_msgs/PoseStamped, '
                'PoseWithCovarianceStamped, TransformStamped)'
            )
        # one line per source tried (the message was one ~600-character line)
        raise RecordingError(
            f'no usable poses for {what} (frame {frame!r}) in {self._rec.path}:\n'
            + ''.join(f'  - {r.rstrip(".")}\n'.replace('; ', ';\n    ') for r in reasons)
            + POSE_ADVICE
        )


@dataclass
class _StreamPart:
    """One cloud topic of a ScanStream."""

    topic: str
    kind: str  # 'pointcloud2' | 'livox' | 'depth_image' | 'laserscan'
    choice: _PoseChoice
    frame_id: str  # frame of its first cloud
    infos: list[tuple[int, Any]]  # (stamp, CameraInfo) of a depth image topic


class ScanStream:
    """Lazily read scans of one topic, or of several in time order (iterate it; it has no
    length).

    After (or during) iteration: ``total_seen`` clouds of the topic were
    considered, ``kept`` yielded, and ``skipped`` counts the rest by reason
    ('outside time window', 'every', 'no pose at stamp', 'empty cloud',
    'every_distance', 'twice in the recording'), so total_seen == kept + sum(skipped.values()) once the
    topic was read to the end (max_scans stops early). ``notes`` holds notes on the
    recording's files (a lone part of a split recording), then the first detailed
    message for each skip reason (e.g. the time gap to the first transform).
    Iterating again starts over.
    """

    def __init__(
        self,
        rec: Recording,
        parts: list[_StreamPart],
        *,
        selection: ScanSelection,
        depth_stride: int,
    ) -> None:
        self._rec = rec
        self._parts = {p.topic: p for p in parts}
        first = parts[0]
        self.cloud_topic = ','.join(p.topic for p in parts)
        self.kind = first.kind  # 'pointcloud2' | 'livox' | 'depth_image' | 'laserscan' (the first topic's)
        self.frame_id = ','.join(dict.fromkeys(p.frame_id for p in parts))  # of each topic's first cloud
        self.fixed_frame = first.choice.fixed_frame
        self.pose_source = '; '.join(
            dict.fromkeys((f'{p.topic}: ' if len(parts) > 1 else '') + p.choice.description for p in parts)
        )
        self.pose_range_ns = first.choice.range_ns
        self._every = selection.every
        self._every_distance = selection.every_distance
        self._record_time = selection.cloud_time == 'record'
        t_start, t_end = selection.t_start, selection.t_end
        # (clamped to the recording, a second either side: 1e300 s is no int64 of ns)
        span = (-1.0, rec.duration_ns / 1e9 + 1.0)
        self._lo = None if t_start is None else rec.start_ns + round(float(np.clip(t_start, *span)) * 1e9)
        self._hi = None if t_end is None else rec.start_ns + round(float(np.clip(t_end, *span)) * 1e9)
        self._max = selection.max_scans
        self._stride = depth_stride
        self.skipped: Counter[str] = Counter()
        self.total_seen = 0
        self.kept = 0
        self.notes: list[str] = []

    def __repr__(self) -> str:
        return (
            f'ScanStream({self.cloud_topic}, pose_source={self.pose_source!r}, kept={self.kept}, '
            f'total_seen={self.total_seen}, skipped={dict(self.skipped)})'
        )

    def _which(self, topic: str, index: int) -> str:
        return f'cloud #{index}' + (f' of {topic}' if len(self._parts) > 1 else '')

    def _count_note(self, key: str, first: str) -> None:  # key: 'data', 'point_num' or 'order'
        """A note of clouds read despite a fault, counted: its line in ``notes`` is rewritten."""
        n, at, text = self._counted.get(key, (0, len(self.notes), first))
        if not n:
            self.notes.append('')
        self._counted[key] = (n + 1, at, text)
        if key == 'order':
            self.notes[at] = (
                f'{n + 1} cloud{"s" if n else ""} {"are" if n else "is"} stamped at or before the cloud recorded '
                f'before {"them" if n else "it"} ({text}): each is placed by its own stamp; stamps out of order are a '
                f"driver's or a clock's fault{self._order_fix}"
            )
            return
        clouds = f'{n + 1} cloud{"s" if n else ""} hold{"" if n else "s"}'
        self.notes[at] = (
            f'{clouds} more data than the header says ({text}): only the header\'s points are read, as rviz '
            "and PCL read them (a driver's width or height may be wrong)"
            if key == 'data'
            else f'{clouds} a point_num that disagrees with the point records that follow ({text}): the records '
            'are read'
        )

    def _skip(self, reason: str, detail: str | None = None) -> None:
        if detail and reason not in self.skipped:
            self.notes.append(f'{reason}: {detail}')
        self.skipped[reason] += 1

    def _clock_check(self, part: _StreamPart, stamp: int | None, record_ns: int = 0) -> None:
        """Note once per topic where its first clouds' stamps sit apart from their record
        times by over a second more (or less) than the poses' stamps recorded then from theirs,
        for every moving edge of a TF chain (AMCL post-dates its map -> odom by a second):
        stamps of another clock (the sensor's, not the computer's that stamps TF) give each
        cloud the pose of another time. Recorded alike, the lags agree (and drift alike where
        simulation time runs slower than the recorder's clock). ``stamp`` None: the topic's
        clouds end here (fewer were read)."""
        lags = self._lags.setdefault(part.topic, [])
        lag_at = part.choice.lag_at
        if self._record_time or not lag_at or len(lags) >= _LAG_CLOUDS:
            return
        if stamp is not None:
            lags.append((stamp - record_ns, *(f(record_ns) for f in lag_at)))
            if len(lags) < _LAG_CLOUDS:
                return
        elif not lags:  # (the end of the clouds: fewer than _LAG_CLOUDS)
            return
        both = np.asarray(lags, np.int64)
        lags += [lags[0]] * _LAG_CLOUDS  # (said once)
        apart = np.median(both[:, :1] - both[:, 1:], axis=0)  # each edge's
        k = int(np.argmin(np.abs(apart)))  # the edge closest to the clouds' clock
        cloud, poses = int(np.median(both[:, 0])), int(np.median(both[:, k + 1]))
        if abs(apart[k]) > _JUMP_NS:
            # the one whose stamps stray from the recorder's clock is on another; only the clouds'
            # can be replaced by their record times
            which = "the poses'" if abs(poses) > abs(cloud) else "the clouds'"
            self.notes.append(
                f'{part.topic}: its clouds are stamped {cloud / 1e9:+.3f} s from the times they were recorded, '
                f'the poses {poses / 1e9:+.3f} s from theirs: {which} stamps look to be on another clock (a '
                "sensor's, another computer's), which gives each cloud the pose of another time"
                + ('; --cloud-time record matches clouds by their record times' if abs(poses) <= _JUMP_NS else '')
            )

    @property
    def start_ns(self) -> int:
        """The recording's start (what t_start and t_end count from)."""
        return self._rec.start_ns

    def sensor_path(self, samples: int = 2000) -> tuple[np.ndarray, np.ndarray] | None:
        """(stamps (K,) ns, positions (K, 3) m) of the sensor over the selected time, from the
        pose source at up to ``samples`` times per topic from its first cloud on (read before
        any scan, to check the path fits the map); None where the poses have no times (a
        poses file by index, identity poses)."""
        stamps, pos = [], []
        for part in self._parts.values():
            rng = part.choice.range_ns
            if rng is None or part.choice.fn is None:
                continue
            first = self._rec._first_message(part.topic)
            t0 = _cloud_stamp(stamp_ns(first[1].header.stamp), first[0], self._record_time) if first else rng[0]
            lo = max(rng[0], t0, self._lo if self._lo is not None else rng[0])
            hi = min(rng[1], self._hi if self._hi is not None else rng[1], self._rec.start_ns + self._rec.duration_ns)
            for t in np.unique(np.linspace(lo, hi, samples).astype(np.int64)) if hi >= lo else ():
                try:
                    T = part.choice.fn(int(t), part.frame_id, 0)
                except (TransformTimeError, RecordingError):
                    continue
                stamps.append(int(t))
                pos.append(T[:3, 3])
        if not pos:
            return None
        order = np.argsort(stamps, kind='stable')
        return np.asarray(stamps, np.int64)[order], np.asarray(pos, np.float64)[order]

    @staticmethod
    def _camera_info(infos: list[tuple[int, Any]], stamp: int) -> Any:
        stamps = [s for s, _ in infos]
        i = int(np.searchsorted(stamps, stamp))
        best = min((j for j in (i - 1, i) if 0 <= j < len(stamps)), key=lambda j: abs(stamps[j] - stamp))
        return infos[best][1]

    def __iter__(self) -> Iterator[Scan]:
        self.skipped = Counter()
        self.total_seen = self.kept = 0
        self.notes = list(self._rec.file_notes)
        self._counted: dict[str, tuple[int, int, str]] = {}
        self._order_fix = ''  # what helps with clouds stamped out of order (_count_note)
        self._other_frames: set[str] = set()  # topics with a cloud in another frame than their first's
        self._lags: dict[
            str, list[tuple[int, ...]]
        ] = {}  # topic -> (cloud, each pose source's) lags of its first clouds
        for part in self._parts.values():
            self.notes += [n for n in part.choice.notes if n not in self.notes]
        rec = self._rec
        last_pos: dict[str, np.ndarray] = {}  # each topic's sensor at its last kept cloud
        stop = None if self._hi is None else self._hi + 1  # reader stop is exclusive
        indices = dict.fromkeys(self._parts, -1)  # a cloud's index within its topic
        seen: dict[tuple, int] = {}  # (topic, record time, stamp, frame, bytes) -> index: duplicates
        last_stamp: dict[str, int] = {}  # each topic's last cloud's stamp
        for topic, t, msgtype, raw in rec._messages_of(list(self._parts), stop=stop):
            part = self._parts[topic]
            kind, pose_fn, to_sensor = part.kind, part.choice.fn, part.choice.to_sensor
            assert pose_fn is not None
            indices[topic] += 1
            index = indices[topic]
            self.total_seen += 1
            if self._lo is not None and t < self._lo:
                self._skip('outside time window')
                continue
            if index % self._every:
                self._skip('every')
                continue
            try:
                pts = None
                fast = decode_livox_raw(raw, rec.format == 'ros1') if kind == 'livox' else None
                if fast is not None:
                    stamp, frame, pts = fast
                    stamp = _cloud_stamp(stamp, t, self._record_time)
                    frame = normalize_frame(frame)
                    empty = len(pts) == 0
                    said = livox_point_num(raw, rec.format == 'ros1')
                    if said is not None and said != len(pts):
                        self._count_note(
                            'point_num', f'{self._which(topic, index)}: point_num {said:,}, {len(pts):,} records'
                        )
                else:
                    msg = rec._deserialize(raw, msgtype, topic)
                    stamp = _cloud_stamp(stamp_ns(msg.header.stamp), t, self._record_time)
                    frame = normalize_frame(msg.header.frame_id)
                    if kind == 'livox':
                        empty = len(msg.points) == 0
                        if int(msg.point_num) != len(msg.points):
                            self._count_note(
                                'point_num',
                                f'{self._which(topic, index)}: point_num {int(msg.point_num):,}, {len(msg.points):,} records',
                            )
                    elif kind == 'laserscan':
                        empty = len(msg.ranges) == 0
                    else:
                        empty = msg.height * msg.width == 0
                        size = pointcloud2_size_mismatch(msg) if kind == 'pointcloud2' else None
                        if size is not None and size[0]:
                            self._skip(SIZE_DISAGREES, f'{self._which(topic, index)}: {size[1]}')
                            continue
                        if size is not None:  # the header's points are read, as rviz and PCL read them
                            self._count_note('data', f'{self._which(topic, index)}: {size[1]}')
                self._clock_check(part, stamp, t)
                key = (topic, t, stamp, frame, len(raw))
                if key in seen:  # the same message twice: the files of a split recording overlap
                    self._skip(
                        'twice in the recording',
                        f'{self._which(topic, index)} is cloud #{seen[key]} again (the same record time, stamp '
                        f'{_s(stamp)}, frame and size): the recording\'s files hold it twice (parts that overlap, '
                        'a part copied twice); it is mapped once',
                    )
                    continue
                seen[key] = index
                if not self._record_time and stamp != t and stamp <= last_stamp.get(topic, stamp - 1):
                    if 'order' not in self._counted:  # record times help where the poses keep to them (not a restart)
                        on_time = any(abs(f(t)) <= _JUMP_NS for f in part.choice.lag_at)
                        self._order_fix = ', and --cloud-time record places the clouds by their record times' * on_time
                    self._count_note(
                        'order',
                        f'{self._which(topic, index)} at {_s(stamp)}, the one before at {_s(last_stamp[topic])}',
                    )
                last_stamp[topic] = stamp
                if frame and frame != part.frame_id and topic not in self._other_frames:
                    self._other_frames.add(topic)  # the poses line names the first cloud's frame only
                    self.notes.append(
                        f'{self._which(topic, index)}{"" if len(self._parts) > 1 else f" of {topic}"} is in frame '
                        f'{frame!r}, not {part.frame_id!r} like the first: each cloud is placed by its own frame'
                    )
                if empty:
                    self._skip('empty cloud', f'{self._which(topic, index)} at {_s(stamp)} has no points')
                    continue
                try:
                    T = pose_fn(stamp, frame, index)
                except TransformTimeError as err:
                    self._skip('no pose at stamp', f'{self._which(topic, index)}: {err}')
                    continue
                except RecordingError as err:
                    if frame:
                        raise
                    # no frame to look up (tf2 refuses an empty frame too)
                    raise RecordingError(f'cloud #{index} of {topic} at {_s(stamp)} has an empty frame_id') from err
                if (
                    self._every_distance
                    and topic in last_pos
                    and float(np.linalg.norm(T[:3, 3] - last_pos[topic])) < self._every_distance
                ):
                    self._skip('every_distance')
                    continue
                if kind == 'depth_image':
                    pts = depth_image_to_points(msg, self._camera_info(part.infos, stamp), self._stride)
                else:
                    if pts is None:
                        pts = _DECODERS[kind](msg)
                    if to_sensor is not None:
                        S = to_sensor(stamp, frame, index)
                        pts = pts.astype(np.float64) @ S[:3, :3].T + S[:3, 3]
            except RecordingError as err:
                if not self.kept:  # the recording's first scan: refused, as when it is opened
                    later = (t - rec.start_ns) // 1_000_000 / 1e3 + 0.001
                    raise RecordingError(
                        f'{err}; it is the first cloud to map (a broken first cloud refuses the recording): '
                        f'--start {later:.3f} skips it'
                    ) from err
                # one broken message (a truncated cloud, a frame TF does not have) among good ones
                self._skip('bad message', f'{self._which(topic, index)}: {err}')
                continue
            last_pos[topic] = T[:3, 3].copy()
            self.kept += 1
            yield Scan(points=pts, T_world_sensor=T, stamp_ns=stamp, frame_id=frame, index=index)
            if self._max is not None and self.kept >= self._max:
                for p in self._parts.values():
                    self._clock_check(p, None)
                return
        for p in self._parts.values():
            self._clock_check(p, None)
        # clouds after t_end were not read (the reader stopped there); count them
        rest = sum(rec._topics[tp][1] for tp in self._parts) - self.total_seen
        if rest > 0 and self._hi is not None:
            self.skipped['outside time window'] += rest
            self.total_seen += rest
