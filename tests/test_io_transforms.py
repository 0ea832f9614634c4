"""PoseTrack interpolation, TfBuffer lookups and TUM/KITTI pose files."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import io_fixtures as fx  # noqa: E402

from ndtom_ti.io import (  # noqa: E402
    PoseTrack,
    RecordingError,
    TfBuffer,
    TransformTimeError,
    load_pose_file,
    quat_to_rot,
    rot_to_quat,
)

S = 1_000_000_000


def test_quaternion_round_trip_all_pivots() -> None:
    rng = np.random.default_rng(1)
    axes = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 1), *rng.normal(size=(20, 3))]
    for axis in axes:
        for ang in (0.0, 0.3, 3.1, math.pi, -2.0):
            R = fx.axis_angle(axis, ang)
            q = rot_to_quat(R)
            assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
            np.testing.assert_allclose(quat_to_rot(q), R, atol=1e-12)


def test_posetrack_interpolates_translation_linearly_and_rotation_by_slerp() -> None:
    axis = (0.2, -1.0, 0.5)
    stamps = [10 * S, 12 * S, 13 * S]
    angles = [0.1, 1.3, 2.9]  # 2.9 - 1.3 > 90 deg: slerp, not nlerp
    trans = [(0, 0, 0), (2, -4, 6), (3, -4, 0)]
    track = PoseTrack(stamps, [fx.T_of(fx.axis_angle(axis, a), t) for a, t in zip(angles, trans, strict=True)])
    for s, f_ang, f_t in [(11 * S, 0.7, (1, -2, 3)), (12 * S + S // 4, 1.3 + 0.25 * 1.6, (2.25, -4, 4.5))]:
        T = track.at(s, 0)
        np.testing.assert_allclose(T[:3, :3], fx.axis_angle(axis, f_ang), atol=1e-12)
        np.testing.assert_allclose(T[:3, 3], f_t, atol=1e-12)
    np.testing.assert_array_equal(track.at(12 * S), track.poses[1])  # exact sample returned untouched


def test_posetrack_tolerance_clamps_and_returns_none_outside() -> None:
    track = PoseTrack([5 * S, 6 * S], [np.eye(4), fx.T_of(np.eye(3), (1, 0, 0))])
    tol = 50_000_000
    np.testing.assert_array_equal(track.at(5 * S - tol, tol), np.eye(4))  # clamped, not extrapolated
    np.testing.assert_array_equal(track.at(6 * S + tol, tol)[:3, 3], (1, 0, 0))
    assert track.at(5 * S - tol - 1, tol) is None
    assert track.at(6 * S + tol + 1, tol) is None
    assert track.at(5 * S - 1) is None


def test_posetrack_sorts_and_keeps_last_duplicate() -> None:
    track = PoseTrack([3, 1, 3], [fx.T_of(np.eye(3), (3, 0, 0)), np.eye(4), fx.T_of(np.eye(3), (9, 0, 0))])
    assert track.stamps_ns.tolist() == [1, 3]
    assert track.poses[1][0, 3] == 9
    np.testing.assert_allclose(track.at(2)[:3, 3], (4.5, 0, 0))


def _chain_buffer() -> TfBuffer:
    """map -> base (moving), base -> mount -> sensor (static), map -> marker (static)."""
    tf = TfBuffer()
    for t in fx.TF_TIMES:
        tf.add('map', 'base', t, tuple(fx.base_translation(t)), fx.quat_axis_angle(fx.AXIS, fx.base_angle(t)))
    tf.add('base', 'mount', 0, *fx.T_BASE_MOUNT_TQ, static=True)
    tf.add('/mount', 'sensor', 0, *fx.T_MOUNT_SENSOR_TQ, static=True)  # leading '/' as in ROS1 tf
    tf.add('map', 'marker', 0, (5.0, 5.0, 0.0), fx.quat_axis_angle((0, 0, 1), 1.0), static=True)
    return tf


def test_tf_structure() -> None:
    tf = _chain_buffer()
    assert tf.frames() == ['base', 'map', 'marker', 'mount', 'sensor']
    assert tf.tree() == {'base': 'map', 'marker': 'map', 'mount': 'base', 'sensor': 'mount'}
    assert tf.roots() == ['map']
    edges = {e.child: e for e in tf.edges()}
    assert edges['base'].static is False and edges['base'].count == 3
    assert (edges['base'].first_ns, edges['base'].last_ns) == (fx.TF_TIMES[0], fx.TF_TIMES[-1])
    assert edges['sensor'].static is True and edges['sensor'].first_ns is None
    assert tf.chain_str('map', 'sensor') == 'map -> base -> mount -> sensor'


def test_tf_lookup_interpolates_chain_between_stamps() -> None:
    tf = _chain_buffer()
    for t in [fx.T0, fx.T0 + 100 * fx.MS, fx.T0 + 330 * fx.MS, fx.T0 + 400 * fx.MS]:
        np.testing.assert_allclose(tf.lookup('map', 'sensor', t, 0), fx.T_map_sensor(t), atol=1e-12)


def test_tf_lookup_up_then_down() -> None:
    tf = _chain_buffer()
    t = fx.T0 + 150 * fx.MS
    T_map_marker = fx.T_of(fx.axis_angle((0, 0, 1), 1.0), (5, 5, 0))
    expect = np.linalg.inv(T_map_marker) @ fx.T_map_sensor(t)
    np.testing.assert_allclose(tf.lookup('marker', 'sensor', t, 0), expect, atol=1e-12)
    np.testing.assert_allclose(tf.lookup('sensor', 'marker', t, 0), np.linalg.inv(expect), atol=1e-12)
    # static-only path: valid at any time
    np.testing.assert_allclose(
        tf.lookup('base', 'sensor', 0, 0), fx.T_tq(fx.T_BASE_MOUNT_TQ) @ fx.T_tq(fx.T_MOUNT_SENSOR_TQ), atol=1e-12
    )


def test_tf_errors_name_frames_and_time_gap() -> None:
    tf = _chain_buffer()
    tf.add('odom', 'wheel', fx.T0, (0, 0, 0), (0, 0, 0, 1))
    with pytest.raises(RecordingError) as err:
        tf.lookup('map', 'lidar', fx.T0, 0)
    assert "'lidar' is not in the TF tree" in str(err.value) and 'base, map, marker, mount, odom' in str(err.value)
    with pytest.raises(
        RecordingError,
        match="not connected by TF: 'map' is in the tree rooted at 'map', 'wheel' in the tree rooted at 'odom'",
    ):
        tf.lookup('map', 'wheel', fx.T0, 0)
    with pytest.raises(TransformTimeError) as err:
        tf.lookup('map', 'sensor', fx.T0 - 300 * fx.MS, 50 * fx.MS)
    assert 'map -> base' in str(err.value) and '0.300 s before the first of its 3 transforms' in str(err.value)
    with pytest.raises(TransformTimeError, match=r'0\.100 s after the last'):
        tf.lookup('map', 'sensor', fx.T0 + 500 * fx.MS, 0)
    # within the tolerance: clamped to the first sample
    np.testing.assert_allclose(
        tf.lookup('map', 'base', fx.T0 - 40 * fx.MS, 50 * fx.MS), fx.T_map_base(fx.T0), atol=1e-12
    )


def test_tf_conflicting_parent_and_static_over_dynamic_are_noted() -> None:
    tf = TfBuffer()
    tf.add('a', 'b', 0, (1, 0, 0), (0, 0, 0, 1), static=True)
    tf.add('a', 'b', 5, (7, 0, 0), (0, 0, 0, 1))
    tf.add('c', 'b', 5, (0, 0, 0), (0, 0, 0, 1))
    assert tf.tree() == {'b': 'a'}
    np.testing.assert_allclose(tf.lookup('a', 'b', 10**12, 0)[:3, 3], (1, 0, 0))
    assert any('both /tf_static and /tf' in n for n in tf.notes)
    assert any("kept 'a'" in n for n in tf.notes)


# ------------------------------------------------------------------------------------ pose files
def test_tum_file(tmp_path: Path) -> None:
    p = tmp_path / 'gt.txt'
    q = fx.quat_axis_angle((0, 0, 1), 0.5)
    p.write_text(
        '# ground truth\n# timestamp tx ty tz qx qy qz qw\n'
        f'1311877813.991479 1 2 3 {q[0]} {q[1]} {q[2]} {q[3]}\n\n'
        '1311877812.5 0 0 0 0 0 0 1  # comment after data\n'
    )
    track = load_pose_file(p)
    assert track.stamps_ns.tolist() == [1311877812_500000000, 1311877813_991479000]  # exact, sorted
    np.testing.assert_allclose(track.poses[1], fx.T_of(fx.axis_angle((0, 0, 1), 0.5), (1, 2, 3)), atol=1e-12)
    mid = track.at(1311877812_500000000 + (1_491_479_000 // 2))
    np.testing.assert_allclose(mid[:3, 3], (0.5, 1, 1.5), atol=1e-9)
    np.testing.assert_allclose(mid[:3, :3], fx.axis_angle((0, 0, 1), 0.25), atol=1e-9)
    assert not track.by_index


def test_kitti_file_by_index_and_with_stamps(tmp_path: Path) -> None:
    poses = [fx.T_of(fx.axis_angle((0, 1, 0), 0.1 * i), (i, 0, 2 * i)) for i in range(3)]
    p = tmp_path / '00.txt'
    p.write_text(''.join(' '.join(f'{v:.12e}' for v in T[:3].reshape(-1)) + '\n' for T in poses))
    track = load_pose_file(p)
    assert track.by_index and track.stamps_ns.tolist() == [0, 1, 2]
    np.testing.assert_allclose(track.poses, poses, atol=1e-9)
    st = tmp_path / 'times.txt'
    st.write_text('100.0\n100.1\n100.2\n')
    stamped = load_pose_file(p, stamps=st)
    assert not stamped.by_index and stamped.stamps_ns.tolist() == [100_000_000_000, 100_100_000_000, 100_200_000_000]
    np.testing.assert_allclose(stamped.at(100_050_000_000)[:3, 3], (0.5, 0, 1), atol=1e-9)


@pytest.mark.parametrize(
    'text, match',
    [
        ('1 2 3 4 5 6 7\n', r'bad\.txt:1: 7 columns; expected 8 \(TUM.*or 12 \(KITTI'),
        ('# c\n1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n', r'bad\.txt:3: 7 columns, but the file is TUM with 8'),
        ('1 0 0 0 0 0 0 1\n2 0 0 zero 0 0 0 1\n', r"bad\.txt:2: 'zero' \(column 4\) is not a number"),
        ('1 0 0 0 0 0 0 2\n', r'bad\.txt:1: quaternion .* has norm 2\.0000, not 1'),
        ('1 0 0 nan 0 0 0 1\n', r'bad\.txt:1: non-finite'),
        ('1 0 0 0 0 2 0 0 0 0 1 0\n', r'bad\.txt:1: the 3x3 part is not a rotation'),
        ('# only a comment\n', r'no poses'),
    ],
)
def test_bad_pose_files_name_the_line(tmp_path: Path, text: str, match: str) -> None:
    p = tmp_path / 'bad.txt'
    p.write_text(text)
    with pytest.raises(RecordingError, match=match):
        load_pose_file(p)


def test_pose_file_missing_and_stamp_count_mismatch(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match='does not exist'):
        load_pose_file(tmp_path / 'nope.txt')
    p = tmp_path / 'k.txt'
    p.write_text('1 0 0 0 0 1 0 0 0 0 1 0\n')
    with pytest.raises(RecordingError, match='has 1 poses but the stamps have 2 entries'):
        load_pose_file(p, stamps=[1, 2])
