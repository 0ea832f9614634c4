"""Recordings whose clocks and stamps are not tidy: poses lost for seconds, clocks that jump
back (a looped playback, a restarted simulation), time windows beyond the recording. Tiny
bags written here with rosbags writers (io_fixtures)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import io_fixtures as fx  # noqa: E402

from ndtom_ti.io import RecordingError, open_recording  # noqa: E402

MS = fx.MS
S = 1000 * MS
Q0 = (0.0, 0.0, 0.0, 1.0)
TF = 'tf2_msgs/msg/TFMessage'
PC2 = 'sensor_msgs/msg/PointCloud2'
ODOM = 'nav_msgs/msg/Odometry'
T0 = fx.T0


def _tf(t: int, xyz: tuple[float, float, float], stamp: int | None = None) -> fx.Entry:
    st = t if stamp is None else stamp
    return ('/tf', TF, t, lambda m: m.tf([(st, 'map', 'base_link', xyz, Q0)]))


def _static(t: int = T0) -> fx.Entry:
    return ('/tf_static', TF, t, lambda m: m.tf([(t, 'base_link', 'velodyne', (0.0, 0.0, 1.0), Q0)]))


def _odom(t: int, xyz: tuple[float, float, float]) -> fx.Entry:
    return ('/odom', ODOM, t, lambda m: m.odometry(t, 'map', 'base_link', xyz, Q0))


def _cloud(t: int, stamp: int | None = None) -> fx.Entry:
    p = fx.pack_cloud(np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]))
    st = t if stamp is None else stamp
    return ('/cloud', PC2, t, lambda m: m.cloud(st, 'velodyne', p))


def _write(tmp_path: Path, entries: list[fx.Entry], fmt: str = 'ros1') -> Path:
    return fx.write_bag(fx.bag_path(tmp_path, fmt), fmt, sorted(entries, key=lambda e: e[2]))


def _x(t: int) -> float:
    """The vehicle's x: 1 m/s, then turning back after 5 s (a gap's straight line misses it)."""
    s = (t - T0) / S
    return s if s < 5 else 10 - s


# ----------------------------------------------------------------------------- poses lost for seconds
@pytest.mark.parametrize('source', ['tf', 'odom'])
def test_clouds_in_a_gap_of_the_poses_are_skipped_not_interpolated(tmp_path: Path, source: str) -> None:
    """Poses at 10 Hz, none from 2 s to 9 s: a cloud in between is skipped and counted (an
    interpolated pose would put it 3 m off the vehicle at 5 s), those beside it mapped."""
    pose_times = [T0 + k * 100 * MS for k in range(121) if not 20 < k < 90]
    make = _tf if source == 'tf' else _odom
    entries = [_static()] + [make(t, (_x(t), 0.0, 0.0)) for t in pose_times]
    cloud_times = [T0 + k * 500 * MS for k in range(1, 24)]
    bag = _write(tmp_path, entries + [_cloud(t + 20 * MS) for t in cloud_times])
    with open_recording(bag) as rec:
        stream = rec.scans(pose_topic='/odom' if source == 'odom' else None)
        scans = list(stream)
    kept = [round((s.stamp_ns - T0) / S, 2) for s in scans]
    assert kept == [0.52, 1.02, 1.52, 2.02, 9.02, 9.52, 10.02, 10.52, 11.02, 11.52]  # 2.02: 0.02 s from a pose
    for s in scans:  # (2.02 s: interpolated towards 9 s, as within the tolerance of an end)
        assert s.T_world_sensor[0, 3] == pytest.approx(_x(s.stamp_ns), abs=1e-6 if s.index != 3 else 0.03)
    assert stream.skipped == {'no pose at stamp': 13}
    note = next(n for n in stream.notes if n.startswith('no pose at stamp'))
    assert 'falls in a gap of 7.000 s without poses' in note and '0.100 s apart as a rule' in note, note


def test_a_cloud_near_the_edge_of_a_gap_keeps_its_pose(tmp_path: Path) -> None:
    """Within the tolerance (0.05 s) of a pose beside the gap, a cloud is mapped as at the ends."""
    pose_times = [T0 + k * 100 * MS for k in range(121) if not 20 < k < 90]
    entries = [_static()] + [_tf(t, (_x(t), 0.0, 0.0)) for t in pose_times]
    bag = _write(tmp_path, entries + [_cloud(T0 + 2030 * MS), _cloud(T0 + 8980 * MS)])
    with open_recording(bag) as rec:
        stream = rec.scans()
        assert len(list(stream)) == 2


# ----------------------------------------------------------------------------- time windows
def _drive(tmp_path: Path) -> Path:
    """2 s at 10 Hz: TF and a cloud at each 0.1 s."""
    times = [T0 + k * 100 * MS for k in range(21)]
    return _write(tmp_path, [_static()] + [_tf(t, (_x(t), 0.0, 0.0)) for t in times] + [_cloud(t) for t in times])


@pytest.mark.parametrize(
    ('window', 'says'),
    [({'t_start': 2.5}, 't_start (--start) 2.5 s is past the end'), ({'t_end': -1.0}, 't_end (--end) -1 s is before')],
)
def test_a_time_window_outside_the_recording_is_refused_with_its_length(
    tmp_path: Path, window: dict, says: str
) -> None:
    with open_recording(_drive(tmp_path)) as rec, pytest.raises(RecordingError) as err:
        rec.scans(**window)
    assert says in str(err.value) and 'is 2.000 s long' in str(err.value)


@pytest.mark.parametrize('window', [{'t_start': -1e300}, {'t_end': 1e300}, {'t_start': -5.0, 't_end': 1e20}])
def test_a_time_window_far_beyond_the_recording_keeps_every_cloud(tmp_path: Path, window: dict) -> None:
    """Seconds past int64 nanoseconds (1e300 * 1e9 is inf) were an OverflowError."""
    with open_recording(_drive(tmp_path)) as rec:
        assert len(list(rec.scans(**window))) == 21
        with pytest.raises(ValueError, match='finite number of seconds'):
            rec.scans(t_start=float('nan'))
