"""Recording / ScanStream on bags generated with rosbags Writers (ROS1, ROS2 sqlite3, ROS2 mcap)."""

from __future__ import annotations

import math
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import io_fixtures as fx  # noqa: E402

from ndtom_ti.io import RecordingError, load_pose_file, open_recording  # noqa: E402

MS = fx.MS


@pytest.fixture(scope='module', params=fx.FORMATS)
def scene_bag(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp(f'scene_{request.param}')
    return fx.write_bag(fx.bag_path(root, request.param), request.param, fx.scene_entries(request.param))


def _write(tmp_path: Path, fmt: str, entries: list[fx.Entry], name: str = 'rec') -> Path:
    return fx.write_bag(fx.bag_path(tmp_path, fmt, name), fmt, entries)


def test_info_describes_the_scene(scene_bag: Path) -> None:
    with open_recording(scene_bag) as rec:
        info = rec.info()
    assert info.format == ('ros1' if scene_bag.suffix == '.bag' else 'ros2')
    assert info.storage in ('ros1', 'sqlite3', 'mcap') and (info.storage == 'ros1') == (info.format == 'ros1')
    counts = {t.name: (t.msgtype, t.count) for t in info.topics}
    assert counts['/cloud'] == ('sensor_msgs/msg/PointCloud2', 5)
    assert counts['/tf'] == ('tf2_msgs/msg/TFMessage', 3)
    assert counts['/odom'] == ('nav_msgs/msg/Odometry', 3)
    assert info.start_ns == fx.T0 - 600 * MS
    assert info.duration_s == pytest.approx(1.0, abs=1e-6)
    assert info.tf_tree == {'base': 'map', 'mount': 'base', 'sensor': 'mount', 'cam': 'sensor'}
    assert {e.child: e.static for e in info.tf_edges} == {'base': False, 'mount': True, 'sensor': True, 'cam': True}
    assert info.mappable_topics == ['/cloud', '/cam/depth/image', '/cam16/depth/image']
    assert info.cloud_frames == {'/cloud': 'sensor', '/cam/depth/image': 'cam', '/cam16/depth/image': 'cam'}
    kinds = {(p.kind, p.name) for p in info.pose_sources}
    assert ('tf', 'map -> base -> mount -> sensor') in kinds and ('topic', '/odom') in kinds
    assert info.default_cloud_topic == '/cloud'
    assert info.pose_source == 'tf: map -> base -> mount -> sensor' and info.pose_error is None


def test_scans_decode_points_and_interpolate_tf_poses(scene_bag: Path) -> None:
    clouds = fx.scene_clouds()
    with open_recording(scene_bag) as rec:
        stream = rec.scans()
        scans = list(stream)
    assert stream.pose_source == 'tf: map -> base -> mount -> sensor' and stream.fixed_frame == 'map'
    # cloud #0 is 0.5 s before the first transform: skipped and counted
    assert [s.index for s in scans] == [1, 2, 3, 4]
    assert stream.skipped == {'no pose at stamp': 1} and stream.total_seen == 5 and stream.kept == 4
    assert '0.500 s before the first' in stream.notes[0] and 'map -> base' in stream.notes[0]
    for s in scans:
        assert s.stamp_ns == fx.CLOUD_TIMES[s.index] and s.frame_id == 'sensor'
        f64 = any(c == 'f8' for n, (_, c) in clouds[s.index][1].get('layout', {}).items() if n in 'xyz')
        assert s.T_world_sensor.dtype == np.float64 and s.points.dtype == (np.float64 if f64 else np.float32)
        np.testing.assert_allclose(s.T_world_sensor, fx.T_map_sensor(s.stamp_ns), atol=1e-6)
        np.testing.assert_allclose(s.points, clouds[s.index][0], atol=1e-5, equal_nan=True)
    assert np.isnan(scans[2].points).any(axis=1).sum() == 2  # organised cloud, NaNs kept


def test_pose_topic_composed_with_static_offset(scene_bag: Path) -> None:
    with open_recording(scene_bag) as rec:
        stream = rec.scans(pose_topic='odom')  # leading '/' may be left out
        scans = list(stream)
    assert stream.pose_source.startswith('pose topic /odom (nav_msgs/msg/Odometry map -> base)')
    assert 'tf_static base -> mount -> sensor' in stream.pose_source
    assert [s.index for s in scans] == [1, 2, 3, 4]
    for s in scans:
        np.testing.assert_allclose(s.T_world_sensor, fx.T_map_sensor(s.stamp_ns), atol=1e-6)


def test_pose_topic_found_automatically_without_dynamic_tf(tmp_path: Path) -> None:
    entries = [e for e in fx.scene_entries('mcap', with_depth=False) if e[0] != '/tf']
    with open_recording(_write(tmp_path, 'mcap', entries)) as rec:
        assert rec.info().pose_source.startswith('pose topic /odom')
        stream = rec.scans()
        scans = list(stream)
    assert stream.fixed_frame == 'map' and len(scans) == 4
    np.testing.assert_allclose(scans[1].T_world_sensor, fx.T_map_sensor(fx.CLOUD_TIMES[2]), atol=1e-6)


def test_depth_image_topics(scene_bag: Path) -> None:
    d32, d16 = fx.scene_depth()
    T_sensor_cam = fx.T_tq(fx.T_SENSOR_CAM_TQ)
    with open_recording(scene_bag) as rec:
        for topic, depth_m in (('/cam/depth/image', d32), ('/cam16/depth/image', d16 / 1000.0)):
            stream = rec.scans(cloud_topic=topic, depth_stride=2)
            scans = list(stream)
            assert stream.kind == 'depth_image' and stream.frame_id == 'cam'
            assert [s.index for s in scans] == [0, 1]
            ref = fx.expected_depth_points(depth_m, **fx.DEPTH_K).reshape(5, 8, 3)[::2, ::2].reshape(-1, 3)
            for s in scans:
                np.testing.assert_allclose(s.points, ref, atol=1e-6, equal_nan=True)
                np.testing.assert_allclose(s.T_world_sensor, fx.T_map_sensor(s.stamp_ns) @ T_sensor_cam, atol=1e-6)


def test_poses_files_sensor_frame_and_fixed_frame(scene_bag: Path, tmp_path: Path) -> None:
    tum = tmp_path / 'traj.txt'
    lines = []
    for i, t in enumerate(fx.CLOUD_TIMES[:4]):
        q = fx.quat_axis_angle((0, 0, 1), 0.1 * i)
        lines.append(f'{t // 10**9}.{t % 10**9:09d} {i} {2 * i} 0 {q[0]} {q[1]} {q[2]} {q[3]}')
    tum.write_text('\n'.join(lines) + '\n')
    kitti = tmp_path / 'kitti.txt'
    kitti.write_text(
        '\n'.join(' '.join(map(str, fx.T_of(np.eye(3), (i, 0, 0))[:3].reshape(-1))) for i in range(3)) + '\n'
    )
    with open_recording(scene_bag) as rec:
        stream = rec.scans(poses_file=tum)
        scans = list(stream)
        assert stream.pose_source == 'poses file traj.txt (TUM)'
        assert [s.index for s in scans] == [0, 1, 2, 3] and stream.skipped == {'no pose at stamp': 1}
        for s in scans:
            np.testing.assert_allclose(
                s.T_world_sensor, fx.T_of(fx.axis_angle((0, 0, 1), 0.1 * s.index), (s.index, 2 * s.index, 0)), atol=1e-9
            )
        stream = rec.scans(poses_file=kitti)  # by index: line i <-> cloud i
        assert [s.T_world_sensor[0, 3] for s in stream] == [0.0, 1.0, 2.0]
        assert stream.skipped == {'no pose at stamp': 2}
        stream = rec.scans(poses_file=load_pose_file(tum), every=2)
        assert [s.index for s in stream] == [0, 2] and stream.skipped == {'every': 2, 'no pose at stamp': 1}
        stream = rec.scans(sensor_frame_only=True)
        scans = list(stream)
        assert len(scans) == 5 and all(np.array_equal(s.T_world_sensor, np.eye(4)) for s in scans)
        assert stream.pose_source == "sensor frame 'sensor' (identity poses)"
        stream = rec.scans(fixed_frame='base')  # static chain below the moving edge
        scans = list(stream)
        assert len(scans) == 5 and stream.pose_source == 'tf: base -> mount -> sensor (static)'
        np.testing.assert_allclose(
            scans[0].T_world_sensor, fx.T_tq(fx.T_BASE_MOUNT_TQ) @ fx.T_tq(fx.T_MOUNT_SENSOR_TQ), atol=1e-9
        )
        with pytest.raises(RecordingError, match='give only one pose source'):
            rec.scans(poses_file=tum, sensor_frame_only=True)


def test_selection_every_distance_window_and_max(scene_bag: Path) -> None:
    with open_recording(scene_bag) as rec:
        # base moves ~2.3 m/s: 0.1 s steps are ~0.23 m, 0.2 s ~0.46 m
        stream = rec.scans(every_distance=0.4)
        assert [s.index for s in stream] == [1, 3]
        assert stream.skipped == {'no pose at stamp': 1, 'every_distance': 2}
        # record times: start = T0 - 0.6 s; clouds at +0.1 (#0), +0.6, +0.7, +0.9, +1.0 s
        stream = rec.scans(t_start=0.65, t_end=0.95, sensor_frame_only=True)
        assert [s.index for s in stream] == [2, 3]
        assert stream.skipped == {'outside time window': 3} and stream.total_seen == 5
        stream = rec.scans(max_scans=2)
        assert [s.index for s in stream] == [1, 2]
        assert stream.kept == 2
        with pytest.raises(ValueError, match='every must be >= 1'):
            rec.scans(every=0)


def test_missing_cloud_topic_lists_the_mappable_ones(scene_bag: Path) -> None:
    with open_recording(scene_bag) as rec, pytest.raises(RecordingError) as err:
        rec.scans(cloud_topic='/clouds')
    text = str(err.value)
    assert "cloud topic '/clouds' is not in" in text and "Did you mean '/cloud'?" in text
    assert 'Mappable topics: /cloud (pointcloud2), /cam/depth/image (depth_image)' in text
    with open_recording(scene_bag) as rec, pytest.raises(RecordingError, match='has type nav_msgs/msg/Odometry'):
        rec.scans(cloud_topic='/odom')
    with open_recording(scene_bag) as rec, pytest.raises(RecordingError) as err:
        rec.scans(pose_topic='/odometry')
    assert "Did you mean '/odom'?" in str(err.value) and '/odom (nav_msgs/msg/Odometry)' in str(err.value)


def test_several_cloud_topics_need_a_choice(tmp_path: Path) -> None:
    pts = fx.pack_cloud(np.ones((2, 3)))
    entries = [
        (t, 'sensor_msgs/msg/PointCloud2', fx.T0 + i, lambda m: m.cloud(fx.T0, 'a', pts))
        for i, t in enumerate(['/front/points', '/rear/points'])
    ]
    with open_recording(_write(tmp_path, 'ros1', entries)) as rec, pytest.raises(RecordingError) as err:
        rec.scans(sensor_frame_only=True)
    assert '2 PointCloud2 topics: /front/points, /rear/points' in str(err.value)
    assert '--cloud-topic' in str(err.value)


def test_no_pose_for_cloud_frame_names_existing_frames(tmp_path: Path) -> None:
    entries = [e for e in fx.scene_entries('sqlite3', with_odom=False, with_depth=False) if e[0] != '/cloud']
    pts = fx.pack_cloud(np.ones((2, 3)))
    entries.append(('/cloud', 'sensor_msgs/msg/PointCloud2', fx.T0, lambda m: m.cloud(fx.T0, 'velodyne', pts)))
    with open_recording(_write(tmp_path, 'sqlite3', entries)) as rec:
        info = rec.info()
        assert info.pose_source is None and 'velodyne' in info.pose_error
        with pytest.raises(RecordingError) as err:
            rec.scans()
    text = str(err.value)
    assert "no usable poses for /cloud (frame 'velodyne')" in text
    assert 'frames that exist: base, cam, map, mount, sensor' in text
    assert '--sensor-frame' in text and '--poses FILE' in text and '--pose-topic' in text


def test_all_clouds_before_the_poses_end_cleanly(tmp_path: Path) -> None:
    entries = [e for e in fx.scene_entries('ros1', with_odom=False, with_depth=False)]
    late = 2000 * MS  # the tf samples move 2 s later than every cloud (same clock)
    entries = [
        (t, mt, r + late, lambda m, b=b: _shift_tf(b(m), late)) if t == '/tf' else (t, mt, r, b)
        for t, mt, r, b in entries
    ]
    with open_recording(_write(tmp_path, 'ros1', entries)) as rec:
        stream = rec.scans()
        assert list(stream) == []
    assert stream.skipped == {'no pose at stamp': 5} and stream.total_seen == 5
    assert 'before the first' in stream.notes[0]


def _shift_tf(msg: object, dt: int) -> object:
    for tr in msg.transforms:
        ns = tr.header.stamp.sec * 10**9 + tr.header.stamp.nanosec + dt
        tr.header.stamp.sec, tr.header.stamp.nanosec = ns // 10**9, ns % 10**9
    return msg


def test_pose_topic_on_another_clock_is_unusable(tmp_path: Path) -> None:
    """Like the Luminar bag: a constant Odometry in simulation time next to wall-clock clouds."""
    pts = fx.pack_cloud(np.array([[10.0, 0, 0]]))
    entries: list[fx.Entry] = [
        (
            '/points',
            'sensor_msgs/msg/PointCloud2',
            fx.T0 + i * 100 * MS,
            lambda m, i=i: m.cloud(fx.T0 + i * 100 * MS, 'lidar', pts),
        )
        for i in range(3)
    ]
    entries += [
        (
            '/gt',
            'nav_msgs/msg/Odometry',
            fx.T0 + i * 100 * MS + 1,
            lambda m, i=i: m.odometry(60 * 10**9 + i * 100 * MS, 'odom', '', (1, 0, 0), (0, 0, 1, 0)),
        )
        for i in range(3)
    ]
    with open_recording(_write(tmp_path, 'ros1', entries)) as rec:
        with pytest.raises(RecordingError) as err:
            rec.scans()
        text = str(err.value)
        assert 'pose topic /gt' in text and '60.000 s .. 60.200 s' in text and 'different clocks' in text
        assert 'constant' in text and '--sensor-frame' in text
        # named explicitly it is used; every cloud is then outside its time range
        stream = rec.scans(pose_topic='/gt')
        assert list(stream) == [] and stream.skipped == {'no pose at stamp': 3}


def test_unknown_point_fields_and_image_encoding_in_a_bag(tmp_path: Path) -> None:
    packed = fx.pack_cloud(np.ones((2, 3)), layout={'x': (0, 'f4'), 'y': (4, 'f4'), 'z': (8, 'f4')})
    packed.fields = [('u', 0, 7), ('v', 4, 7), ('range', 8, 7)]
    entries: list[fx.Entry] = [
        ('/scan_cloud', 'sensor_msgs/msg/PointCloud2', fx.T0, lambda m: m.cloud(fx.T0, 'lidar', packed))
    ]
    entries += [
        ('/cam/rgb/image', 'sensor_msgs/msg/Image', fx.T0, lambda m: m.image(fx.T0, 'cam', np.zeros((5, 8)), 'mono16')),
        (
            '/cam/rgb/camera_info',
            'sensor_msgs/msg/CameraInfo',
            fx.T0,
            lambda m: m.camera_info(fx.T0, 'cam', 5, 8, **fx.DEPTH_K),
        ),
    ]
    with open_recording(_write(tmp_path, 'mcap', entries)) as rec:
        assert rec.info().mappable_topics == ['/scan_cloud']  # mono16 is not a depth encoding
        with pytest.raises(
            RecordingError,
            match=r'no x/y/z field; fields present: u \(FLOAT32 at offset 0\), '
            r'v \(FLOAT32 at offset 4\), range',
        ):
            list(rec.scans(sensor_frame_only=True))
        with pytest.raises(RecordingError, match="encoding 'mono16' is not supported"):
            list(rec.scans(cloud_topic='/cam/rgb/image', sensor_frame_only=True))


def test_empty_bag(tmp_path: Path) -> None:
    for fmt in fx.FORMATS:
        with open_recording(_write(tmp_path, fmt, [])) as rec:
            info = rec.info()
            assert info.topics == [] and info.duration_s == 0 and info.mappable_topics == []
            assert 'bag is empty' in info.pose_error
            with pytest.raises(RecordingError, match=r'has no topic to map.*Topics present: \(none: the bag is empty'):
                rec.scans()


def test_bad_paths(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match='does not exist'):
        open_recording(tmp_path / 'missing.bag')
    folder = tmp_path / 'notabag'
    folder.mkdir()
    (folder / 'notes.txt').write_text('hello')
    with pytest.raises(RecordingError, match=r'not a ROS2 bag: it has no metadata.yaml \(contents: notes.txt\)'):
        open_recording(folder)
    with pytest.raises(RecordingError, match=r"is not a ROS bag .*starts with b'hello'"):
        open_recording(folder / 'notes.txt')
    (folder / 'a.bag').write_bytes(b'')
    with pytest.raises(RecordingError, match=r"a.bag is not a ROS bag .*starts with b''"):
        open_recording(folder)  # a folder of ROS1 bags: each must be one


@pytest.mark.parametrize('split', ['time', 'topics'])
def test_a_folder_of_ros1_bags_is_one_recording(tmp_path: Path, split: str) -> None:
    """A recording split in time (rosbag record --split: run_0.bag, run_1.bag ...) or by topic
    (TF in one bag, clouds in another) reads as the single bag it was cut from."""
    entries = fx.scene_entries('ros1')
    whole = _write(tmp_path, 'ros1', entries, name='whole')
    folder = tmp_path / 'parts'
    folder.mkdir()
    if split == 'time':  # three parts; names that sort wrongly as text
        cuts = [fx.T0 - 100 * MS, fx.T0 + 250 * MS]
        parts = [
            [e for e in entries if e[2] < cuts[0]],
            [e for e in entries if cuts[0] <= e[2] < cuts[1]],
            [e for e in entries if e[2] >= cuts[1]],
        ]
        names = ['run_9', 'run_10', 'run_11']
    else:
        parts = [[e for e in entries if e[0].startswith('/tf')], [e for e in entries if not e[0].startswith('/tf')]]
        names = ['tf', 'sensors']
    for name, part in zip(names, parts, strict=True):
        assert part
        fx.write_bag(folder / f'{name}.bag', 'ros1', part)
    # the copy `rosbag reindex` keeps of a bag it repaired is left out
    (folder / f'{names[0]}.orig.bag').write_bytes((folder / f'{names[0]}.bag').read_bytes())
    with open_recording(whole) as rec:
        want = [(s.index, s.stamp_ns, s.T_world_sensor, s.points) for s in rec.scans()]
        topics = rec.info().topics
    with open_recording(folder) as rec:
        info = rec.info()
        got = [(s.index, s.stamp_ns, s.T_world_sensor, s.points) for s in rec.scans()]
    assert info.topics == topics and info.pose_source == 'tf: map -> base -> mount -> sensor'
    note = [n for n in info.notes if 'ROS1 bags' in n]
    assert note and note[0].startswith(f'{len(names)} ROS1 bags in parts, read as one recording in time order')
    if split == 'time':
        assert 'run_9.bag, run_10.bag, run_11.bag' in note[0]
    assert len(got) == len(want) == 4
    for (i, t, T, p), (i2, t2, T2, p2) in zip(got, want, strict=True):
        assert (i, t) == (i2, t2)
        np.testing.assert_array_equal(T, T2)
        np.testing.assert_array_equal(p, p2)


def test_truncated_bags(tmp_path: Path) -> None:
    bag = _write(tmp_path, 'ros1', fx.scene_entries('ros1'))
    cut = tmp_path / 'cut.bag'
    cut.write_bytes(bag.read_bytes()[: bag.stat().st_size // 2])
    with pytest.raises(RecordingError, match=r'truncated or corrupt.*rosbag reindex'):
        open_recording(cut)
    ros2 = _write(tmp_path, 'mcap', fx.scene_entries('mcap'), name='cut2')
    mcap = next(ros2.glob('*.mcap'))
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    with pytest.raises(RecordingError, match=r'cannot read .*cut2_mcap'), open_recording(ros2) as rec:
        list(rec.scans())


def test_ros2_file_inside_bag_folder_opens_the_bag(scene_bag: Path) -> None:
    if scene_bag.suffix == '.bag':
        pytest.skip('ROS2 only')
    with open_recording(scene_bag / 'metadata.yaml') as rec:
        assert rec.path == scene_bag / 'metadata.yaml' and rec.format == 'ros2'
        assert len(list(rec.scans())) == 4


def test_renamed_ros1_bag_is_explained(tmp_path: Path, scene_bag: Path) -> None:
    if scene_bag.suffix != '.bag':
        pytest.skip('ROS1 only')
    p = tmp_path / 'recording.dat'
    shutil.copy(scene_bag, p)
    with pytest.raises(RecordingError, match=r'rename it to end in \.bag'):
        open_recording(p)


def test_slerp_midpoint_in_bag_is_exact(tmp_path: Path) -> None:
    """Two tf samples 90 degrees apart about z; a cloud a quarter of the way: yaw 22.5 degrees."""
    q0 = fx.quat_axis_angle((0, 0, 1), 0.0)
    q1 = fx.quat_axis_angle((0, 0, 1), math.pi / 2)
    pts = fx.pack_cloud(np.ones((1, 3)))
    entries: list[fx.Entry] = [
        ('/tf', 'tf2_msgs/msg/TFMessage', fx.T0, lambda m: m.tf([(fx.T0, 'odom', 'lidar', (0, 0, 0), q0)])),
        ('/points', 'sensor_msgs/msg/PointCloud2', fx.T0 + 250 * MS, lambda m: m.cloud(fx.T0 + 250 * MS, 'lidar', pts)),
        (
            '/tf',
            'tf2_msgs/msg/TFMessage',
            fx.T0 + 1000 * MS,
            lambda m: m.tf([(fx.T0 + 1000 * MS, 'odom', 'lidar', (4, -8, 2), q1)]),
        ),
    ]
    with open_recording(_write(tmp_path, 'sqlite3', entries)) as rec:
        (scan,) = list(rec.scans())
    np.testing.assert_allclose(
        scan.T_world_sensor, fx.T_of(fx.axis_angle((0, 0, 1), math.pi / 8), (1, -2, 0.5)), atol=1e-12
    )


def test_posestamped_and_transformstamped_topics(tmp_path: Path) -> None:
    """No TF at all: PoseStamped (no child frame: taken as the cloud frame) and TransformStamped map->lidar."""
    pts = fx.pack_cloud(np.array([[1.0, 2.0, 3.0]]))
    entries: list[fx.Entry] = []
    for i, t in enumerate(fx.TF_TIMES):
        q = fx.quat_axis_angle(fx.AXIS, fx.base_angle(t))
        tr = fx.base_translation(t)
        entries += [
            ('/pose', 'geometry_msgs/msg/PoseStamped', t, lambda m, t=t, q=q, tr=tr: m.pose_stamped(t, 'map', tr, q)),
            (
                '/tfs',
                'geometry_msgs/msg/TransformStamped',
                t + 1,
                lambda m, t=t, q=q, tr=tr: m.transform(t, 'map', 'lidar', tr, q),
            ),
            (
                '/points',
                'sensor_msgs/msg/PointCloud2',
                t + 100 * MS + 2,
                lambda m, t=t: m.cloud(t + 100 * MS, 'lidar', pts),
            ),
        ]
    with open_recording(_write(tmp_path, 'sqlite3', sorted(entries, key=lambda e: e[2]))) as rec:
        with pytest.raises(RecordingError) as err:
            rec.scans()
        assert 'several pose topics' in str(err.value) and '/pose' in str(err.value) and '/tfs' in str(err.value)
        for topic in ('/pose', '/tfs'):
            stream = rec.scans(pose_topic=topic)
            scans = list(stream)
            assert stream.fixed_frame == 'map' and [s.index for s in scans] == [0, 1]
            assert stream.skipped == {'no pose at stamp': 1}  # the last cloud is 0.1 s after the last pose
            for s in scans:
                np.testing.assert_allclose(s.T_world_sensor, fx.T_map_base(s.stamp_ns), atol=1e-9)
        assert 'no child frame' in rec.scans(pose_topic='/pose').pose_source


@pytest.mark.parametrize('fmt', fx.FORMATS)
def test_livox_bytes_decode_as_the_deserialised_message(tmp_path: Path, fmt: str, monkeypatch) -> None:
    """The points of a Livox CustomMsg read from its bytes, for frame ids of every length mod 8
    (CDR aligns the fields after it), 0, 1 and many points, both driver packages."""
    from ndtom_ti.io import livox as lv

    rng = np.random.default_rng(5)
    frames = ['l', 'ab', 'abc', 'abcd', 'abcde', 'livox_frame', 'livox_frame_1', 'abcdefgh']
    clouds = [rng.normal(size=(n, 3)).astype(np.float32) * 9 for n in (0, 1, 2, 17, 3000, 5, 4, 9)]
    entries: list[fx.Entry] = []
    for i, (fr, pts) in enumerate(zip(frames, clouds, strict=True)):
        pkg = fx.LIVOX_PACKAGES[i % 2]
        t = fx.T0 + i * 100 * MS
        entries.append(
            ('/livox/' + pkg, f'{pkg}/msg/CustomMsg', t, lambda m, t=t, f=fr, p=pts, k=pkg: m.livox(t, f, p, k))
        )
    bag = _write(tmp_path, fmt, entries)
    with open_recording(bag) as rec:
        for topic in ('/livox/livox_ros_driver', '/livox/livox_ros_driver2'):
            for _, msgtype, raw in rec._messages(topic):
                msg = rec._deserialize(raw, msgtype, topic)
                got = lv.decode_livox_raw(raw, fmt == 'ros1')
                assert got is not None, (fmt, msg.header.frame_id)
                stamp, frame, pts = got
                assert frame == msg.header.frame_id and stamp == msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
                np.testing.assert_array_equal(pts, lv.livox_points(msg))
                assert lv.decode_livox_raw(bytes(raw)[:-4], fmt == 'ros1') is None  # truncated: not guessed
                assert lv.decode_livox_raw(bytes(raw) + b'\0' * 8, fmt == 'ros1') is None
        # through a stream, from the bytes and (a layout it does not know) from the message
        fast = [s.points for s in rec.scans(cloud_topic='/livox/livox_ros_driver', sensor_frame_only=True)]
        monkeypatch.setattr('ndtom_ti.io.recording.decode_livox_raw', lambda raw, ros1: None)
        stream = rec.scans(cloud_topic='/livox/livox_ros_driver', sensor_frame_only=True)
        slow = [s.points for s in stream]
    assert stream.skipped == {'empty cloud': 1} and len(fast) == len(slow) == 3
    # a bag without the driver's type definitions (rosbag2 before version 8 keeps none): the
    # bytes are enough to list the topic and map it
    monkeypatch.undo()

    def no_types(self, raw, msgtype, topic):
        if msgtype in lv.LIVOX_TYPES:
            raise AssertionError('deserialised')
        return orig(self, raw, msgtype, topic)

    from ndtom_ti.io.recording import Recording

    orig = Recording._deserialize
    monkeypatch.setattr(Recording, '_deserialize', no_types)
    with open_recording(bag) as rec:
        info = rec.info()
        assert info.cloud_frames['/livox/livox_ros_driver2'] == 'ab'
        got = [s.points for s in rec.scans(cloud_topic='/livox/livox_ros_driver2', sensor_frame_only=True)]
    assert [len(p) for p in got] == [1, 17, 5, 9]
    for a, b, want in zip(fast, slow, clouds[2::2], strict=True):
        np.testing.assert_array_equal(a, want)
        np.testing.assert_array_equal(b, want)


@pytest.mark.parametrize('fmt', ['ros1', 'mcap'])
def test_clouds_stamped_zero_use_the_record_time(tmp_path: Path, fmt: str) -> None:
    """A driver that leaves header stamps at 0: the clouds are matched to poses by the bag's
    record time, and info says so (they were refused: 'the times do not overlap')."""
    entries = [e for e in fx.scene_entries(fmt, with_depth=False) if e[0] != '/cloud']
    for t, (pts, kw) in zip(fx.CLOUD_TIMES, fx.scene_clouds(), strict=True):
        entries.append(
            (
                '/cloud',
                'sensor_msgs/msg/PointCloud2',
                t,
                lambda m, p=pts, kw=kw: m.cloud(0, 'sensor', fx.pack_cloud(p, **kw)),
            )
        )
    entries.sort(key=lambda e: e[2])
    with open_recording(_write(tmp_path, fmt, entries)) as rec:
        info = rec.info()
        assert '/cloud: header stamps are 0 (unset): poses are matched by the bag record times' in info.notes
        assert info.pose_error is None
        scans = list(rec.scans())
    assert [s.index for s in scans] == [1, 2, 3, 4]
    for s in scans:
        assert s.stamp_ns == fx.CLOUD_TIMES[s.index]
        np.testing.assert_allclose(s.T_world_sensor, fx.T_map_sensor(s.stamp_ns), atol=1e-6)


def test_a_lone_part_of_a_split_recording_says_so(tmp_path: Path) -> None:
    entries = fx.scene_entries('ros1', with_depth=False)
    for k in range(3):
        fx.write_bag(tmp_path / f'run_{k}.bag', 'ros1', entries)
    with open_recording(tmp_path / 'run_1.bag') as rec:
        note = 'run_1.bag looks like one part of a split recording (2 more beside it: run_0.bag, run_2.bag)'
        assert any(n.startswith(note) for n in rec.info().notes)
        stream = rec.scans()
        list(stream)
        assert stream.notes[0].startswith(note) and f'pass the folder {tmp_path}' in stream.notes[0]
    alone = tmp_path / 'alone'
    alone.mkdir()
    with open_recording(_write(alone, 'ros1', entries)) as rec:
        assert not any('split recording' in n for n in rec.info().notes)
