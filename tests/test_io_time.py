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


# ----------------------------------------------------------------------------- clocks that jump back
def _two_runs(source: str, second_stamp0: int = T0, outlier: int | None = None) -> list[fx.Entry]:
    """A drive of 2 s at 10 Hz recorded twice (a looped playback, a restarted simulation): the
    second run recorded from 3 s on, its stamps from ``second_stamp0``, the vehicle 5 m to the
    side. ``outlier``: one transform of the first run stamped there instead."""
    out = [_static()]
    make = _tf if source == 'tf' else _odom
    for run, stamp0 in enumerate((T0, second_stamp0)):
        for k in range(21):
            t, stamp = T0 + run * 3 * S + k * 100 * MS, stamp0 + k * 100 * MS
            xyz = (k * 0.1, 5.0 * run, 0.0)
            if source == 'tf':
                out.append(_tf(t, xyz, stamp=outlier if (run, k) == (0, 10) and outlier else stamp))
            else:
                out.append(('/odom', ODOM, t, lambda m, s=stamp, xyz=xyz: m.odometry(s, 'map', 'base_link', xyz, Q0)))
            out.append(_cloud(t + 10 * MS, stamp=stamp + 10 * MS))
    return out


@pytest.mark.parametrize('source', ['tf', 'odom'])
def test_a_recording_whose_clock_jumps_back_is_mapped_one_run_at_a_time(tmp_path: Path, source: str) -> None:
    """Both runs give poses at the same stamps: merged, each cloud took the pose of either run
    (interleaved). Refused, naming the runs; --start/--end of one maps it with its own poses."""
    bag = _write(tmp_path, _two_runs(source))
    pose_topic = '/odom' if source == 'odom' else None
    edge = 'map -> base_link' if source == 'tf' else '/odom'
    with open_recording(bag) as rec:
        with pytest.raises(RecordingError) as err:
            rec.scans(pose_topic=pose_topic)
        text = str(err.value)
        assert f'jump back at 3.000 s into the recording ({edge} from {(T0 + 2 * S) / 1e9:.3f} s to' in text, text
        assert (
            'it holds 2 runs of one clock' in text and '--start 0.000 --end 2.999 or --start 3.000 --end 5.010' in text
        )
        assert any('jump back at 3.000 s' in n for n in rec.info().notes)
        for run, window in enumerate(({'t_end': 2.999}, {'t_start': 3.0})):
            stream = rec.scans(pose_topic=pose_topic, **window)
            scans = list(stream)
            assert len(scans) == 21
            for s in scans:
                assert s.T_world_sensor[1, 3] == pytest.approx(5.0 * run)
            assert f'poses of run {run + 1} of 2' in ' '.join(stream.notes)
        assert len(list(rec.scans(sensor_frame_only=True))) == 42  # (the recording's poses unused)
        # a run chosen is no choice for what follows
        with pytest.raises(RecordingError, match='Map one run at a time'):
            rec.scans(pose_topic=pose_topic)


def test_a_clock_restarted_before_its_first_stamps_maps_both_runs(tmp_path: Path) -> None:
    """Simulation time from 1 s again: the runs' stamps are apart, so each cloud still finds
    its own run's poses (and none between them: a gap of decades)."""
    with open_recording(_write(tmp_path, _two_runs('tf', second_stamp0=S))) as rec:
        stream = rec.scans()
        scans = list(stream)
    assert len(scans) == 42
    # the clouds' stamps go back with the poses': record times would not help (not offered)
    order = [n for n in stream.notes if 'stamped at or before' in n]
    assert len(order) == 1 and order[0].endswith("a driver's or a clock's fault"), order
    for s in scans:
        assert s.T_world_sensor[1, 3] == pytest.approx(0.0 if s.stamp_ns > T0 else 5.0)


@pytest.mark.parametrize('outlier', [T0 + 10**6 * S, 5 * S], ids=['future', 'past'])
def test_one_transform_stamped_far_off_is_no_second_run(tmp_path: Path, outlier: int) -> None:
    """A stamp days ahead (or in 1970) among the others, then back: no run of its own."""
    entries = [e for e in _two_runs('tf', outlier=outlier) if e[2] < T0 + 3 * S]
    with open_recording(_write(tmp_path, entries)) as rec:
        stream = rec.scans()
        assert len(list(stream)) == 21
    assert not any('jump' in n for n in stream.notes)


# ----------------------------------------------------------------------------- clouds on another clock
@pytest.mark.parametrize('source', ['tf', 'odom'])
@pytest.mark.parametrize('offset_s', [3.0, -2.0, 0.4])
def test_clouds_stamped_on_another_clock_than_the_poses_are_noted(tmp_path: Path, source: str, offset_s: float) -> None:
    """The sensor's clock 3 s ahead of the computer's that stamps TF: each cloud took the pose
    of 3 s later, silently (those past the last pose skipped). Noted with --cloud-time record,
    which matches them by record time; a lag under a second (a sweep, transport) is not."""
    times = [T0 + k * 100 * MS for k in range(61)]
    make = _tf if source == 'tf' else _odom
    entries = [_static()] + [make(t, (_x(t), 0.0, 0.0)) for t in times]
    bag = _write(tmp_path, entries + [_cloud(t + 5 * MS, stamp=t + round(offset_s * S)) for t in times])
    pose_topic = '/odom' if source == 'odom' else None
    with open_recording(bag) as rec:
        stream = rec.scans(pose_topic=pose_topic)
        list(stream)
        said = [n for n in stream.notes if 'another clock' in n]
        if offset_s == 0.4:
            assert not said
            return
        assert len(said) == 1
        assert (
            f'its clouds are stamped {offset_s - 0.005:+.3f} s from the times they were recorded, the poses +0.000'
            in said[0]
        )
        assert '--cloud-time record' in said[0]
        stream = rec.scans(pose_topic=pose_topic, cloud_time='record')
        scans = list(stream)
        assert len(scans) == 61 and not any('another clock' in n for n in stream.notes)
        for s in scans:
            assert s.T_world_sensor[0, 3] == pytest.approx(_x(s.stamp_ns), abs=0.006)  # (by record time, 5 ms late)


def test_simulation_time_slower_than_the_recorder_is_one_clock(tmp_path: Path) -> None:
    """Simulation time at half the recorder's rate: every stamp drifts from its record time
    alike (by 15 s at the end), so the first clouds are held against the poses recorded with
    them, not against all the poses' lags (the note said "another clock")."""
    stamps = [T0 + k * 100 * MS for k in range(301)]
    rec_t = {t: T0 + 2 * (t - T0) for t in stamps}
    entries = [_static()] + [_tf(rec_t[t], (_x(t), 0.0, 0.0), stamp=t) for t in stamps]
    bag = _write(tmp_path, entries + [_cloud(rec_t[t] + 2, stamp=t) for t in stamps])
    with open_recording(bag) as rec:
        stream = rec.scans()
        assert len(list(stream)) == 301
    assert not [n for n in stream.notes if 'another clock' in n], stream.notes


def test_poses_stamped_on_another_clock_than_the_clouds_are_noted_without_cloud_time(tmp_path: Path) -> None:
    """Odometry stamped 3 s ahead of its record times, the clouds not: the poses' clock is the
    other one, and matching the clouds by record time would not help (not offered)."""
    times = [T0 + k * 100 * MS for k in range(61)]
    odom = [
        ('/odom', ODOM, t, lambda m, t=t: m.odometry(t + 3 * S, 'map', 'base_link', (_x(t), 0.0, 0.0), Q0))
        for t in times
    ]
    bag = _write(tmp_path, [_static(), *odom] + [_cloud(t + 5 * MS) for t in times])
    with open_recording(bag) as rec:
        stream = rec.scans(pose_topic='/odom')
        list(stream)
    said = [n for n in stream.notes if 'another clock' in n]
    assert len(said) == 1 and "the poses +3.000 s from theirs: the poses' stamps look to be" in said[0], said
    assert '--cloud-time' not in said[0]


def test_clouds_stamped_out_of_order_are_counted_in_a_note(tmp_path: Path) -> None:
    """Cloud #4 stamped as #2 (a repeat), #7 stamped 0.5 s back: each was placed by its stamp
    without a word. Counted in one note; by record time they are in order (none)."""
    times = [T0 + k * 100 * MS for k in range(11)]
    stamps = {4: times[2], 7: times[7] - 500 * MS}
    entries = [_static()] + [_tf(t, (_x(t), 0.0, 0.0)) for t in times]
    bag = _write(tmp_path, entries + [_cloud(t + 2, stamp=stamps.get(k, t)) for k, t in enumerate(times)])
    with open_recording(bag) as rec:
        stream = rec.scans()
        assert len(list(stream)) == 11
        said = [n for n in stream.notes if 'stamped at or before' in n]
        assert said == [
            f'2 clouds are stamped at or before the cloud recorded before them (cloud #4 at {times[2] / 1e9:.3f} s, the '
            f"one before at {times[3] / 1e9:.3f} s): each is placed by its own stamp; stamps out of order are a driver's "
            "or a clock's fault, and --cloud-time record places the clouds by their record times"
        ]
        stream = rec.scans(cloud_time='record')
        list(stream)
        assert not [n for n in stream.notes if 'stamped at or before' in n]


# ----------------------------------------------------------------------------- a mount sent on /tf
def test_a_mount_sent_once_on_tf_names_the_static_transform_that_gives_it(tmp_path: Path) -> None:
    """base_link -> velodyne sent once on /tf (no /tf_static): tf2 and ndtom map have it at
    that stamp only, so every later cloud was skipped with no way out named."""
    times = [T0 + k * 100 * MS for k in range(11)]
    mount = ('/tf', TF, T0, lambda m: m.tf([(T0, 'base_link', 'velodyne', (0.25, 0.0, 1.5), Q0)]))
    bag = _write(tmp_path, [mount] + [_tf(t + 1, (_x(t), 0.0, 0.0)) for t in times] + [_cloud(t + 2) for t in times])
    with open_recording(bag) as rec:
        stream = rec.scans()
        assert len(list(stream)) == 1 and stream.skipped == {'no pose at stamp': 10}
        note = next(n for n in stream.notes if n.startswith('no pose at stamp'))
        assert "It has one transform: a mount sent on /tf rather than /tf_static? --static-transform" in note, note
        given = note.split('--static-transform ')[1].split("'")[1]
        assert given == '0.25 0 1.5 0 0 0 1 base_link velodyne'
        scans = list(rec.scans(static_transforms=[given]))
    assert len(scans) == 11
    assert scans[5].T_world_sensor[:3, 3] == pytest.approx([_x(times[5]) + 0.25, 0.0, 1.5], abs=1e-6)


# ----------------------------------------------------------------------------- split recordings
def test_the_parts_of_a_split_recording_that_overlap_map_each_cloud_once(tmp_path: Path) -> None:
    """A folder of two bags whose times overlap (the second starts 0.5 s before the first
    ends, its messages the same): the clouds of the overlap were mapped twice, their points
    counted twice in each Gaussian. Skipped and counted; a gap between parts maps what is there."""
    times = [T0 + k * 100 * MS for k in range(21)]
    entries = [_static()] + [_tf(t, (_x(t), 0.0, 0.0)) for t in times] + [_cloud(t + 2) for t in times]
    folder = tmp_path / 'split'
    folder.mkdir()
    fx.write_bag(folder / 'run_0.bag', 'ros1', sorted([e for e in entries if e[2] <= T0 + S + 2], key=lambda e: e[2]))
    part2 = [e for e in entries if e[2] >= T0 + 500 * MS or e[0] == '/tf_static']
    fx.write_bag(folder / 'run_1.bag', 'ros1', sorted(part2, key=lambda e: e[2]))
    with open_recording(folder) as rec:
        stream = rec.scans()
        scans = list(stream)
    assert [s.stamp_ns for s in scans] == [t + 2 for t in times]
    assert stream.skipped == {'twice in the recording': 6} and stream.total_seen == 27
    note = next(n for n in stream.notes if n.startswith('twice in the recording'))
    assert 'cloud #6 is cloud #5 again' in note and "the recording's files hold it twice" in note, note


def test_a_post_dated_edge_of_the_chain_is_no_other_clock(tmp_path: Path) -> None:
    """odom -> base_link post-dated by 1.5 s (robot_localization's transform_time_offset; AMCL
    post-dates map -> odom alike), map -> odom on time: the clouds keep the clock of that one,
    so nothing is noted (the edge nearest the sensor alone said "another clock")."""
    times = [T0 + k * 100 * MS for k in range(41)]
    slam = [('/tf', TF, t, lambda m, t=t: m.tf([(t, 'map', 'odom', (0.0, 0.0, 0.0), Q0)])) for t in times]
    ekf = [
        ('/tf', TF, t + 1, lambda m, t=t: m.tf([(t + 1500 * MS, 'odom', 'base_link', (_x(t), 0.0, 0.0), Q0)]))
        for t in times
    ]
    bag = _write(tmp_path, [_static(), *slam, *ekf] + [_cloud(t + 2) for t in times[15:35]])
    with open_recording(bag) as rec:
        stream = rec.scans()
        assert len(list(stream)) == 20
    assert not [n for n in stream.notes if 'another clock' in n], stream.notes


def test_a_mount_republished_with_another_value_says_both_and_how_to_keep_the_first(tmp_path: Path) -> None:
    """/tf_static gives base_link -> velodyne again halfway, 1 m higher: the last is used for
    every cloud (as tf2 keeps it); the note now gives both values and the --static-transform
    that maps with the first, which then is the only one said."""
    times = [T0 + k * 100 * MS for k in range(11)]
    again = ('/tf_static', TF, T0 + 500 * MS, lambda m: m.tf([(T0, 'base_link', 'velodyne', (0.0, 0.0, 2.0), Q0)]))
    entries = [_static(), again] + [_tf(t, (_x(t), 0.0, 0.0)) for t in times]
    bag = _write(tmp_path, entries + [_cloud(t + 2) for t in times])
    with open_recording(bag) as rec:
        stream = rec.scans()
        assert {s.T_world_sensor[2, 3] for s in stream} == {2.0}
        note = next(n for n in stream.notes if n.startswith('/tf_static gives'))
        assert 'first xyz (0, 0, 1) m' in note and 'last xyz (0, 0, 2) m' in note, note
        given = note.split('--static-transform ')[1].split("'")[1]
        assert given == '0 0 1 0 0 0 1 base_link velodyne'
        stream = rec.scans(static_transforms=[given])
        assert {s.T_world_sensor[2, 3] for s in stream} == {1.0}
        assert not [n for n in stream.notes if n.startswith('/tf_static gives')], stream.notes


@pytest.mark.parametrize('name', ['t_start', 't_end'])
def test_a_time_of_the_recordings_clock_given_for_start_or_end_names_the_seconds(tmp_path: Path, name: str) -> None:
    """--end 1700000001.5 (a stamp, as rqt_bag shows times) mapped the whole recording:
    taken as seconds from the start, it is past the end."""
    with open_recording(_drive(tmp_path)) as rec, pytest.raises(RecordingError) as err:
        rec.scans(**{name: T0 / 1e9 + 1.5})
    opt = '--start' if name == 't_start' else '--end'
    assert f"is a time of the recording's clock, but it counts seconds from its start: {opt} 1.500 is that" in str(
        err.value
    )
