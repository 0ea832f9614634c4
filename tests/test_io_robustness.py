"""Recordings that are unusual but real: several robots' TF, conflicting TF parents, clouds
whose sizes or fields disagree, messages without their type definitions. Tiny bags written
here with rosbags writers (io_fixtures)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import io_fixtures as fx  # noqa: E402

from ndtom_ti.io import RecordingError, open_recording  # noqa: E402

MS = fx.MS
Q0 = (0.0, 0.0, 0.0, 1.0)
TF = 'tf2_msgs/msg/TFMessage'
PC2 = 'sensor_msgs/msg/PointCloud2'
STAMPS = [fx.T0 + k * 100 * MS for k in range(5)]


def _tf(topic: str, t: int, parent: str, child: str, xyz: tuple[float, float, float]) -> fx.Entry:
    return (topic, TF, t, lambda m: m.tf([(t, parent, child, xyz, Q0)]))


def _cloud(topic: str, t: int, frame: str = 'velodyne', packed: fx.PackedCloud | None = None) -> fx.Entry:
    p = packed or fx.pack_cloud(np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]))
    return (topic, PC2, t, lambda m: m.cloud(t, frame, p))


def _write(tmp_path: Path, entries: list[fx.Entry], fmt: str = 'ros1', latched: tuple[str, ...] = ()) -> Path:
    entries = sorted(entries, key=lambda e: e[2])
    return fx.write_bag(fx.bag_path(tmp_path, fmt), fmt, entries, latched=latched or ('/tf_static',))


# ----------------------------------------------------------------------------- several robots' TF
def _two_robots(cloud_topic: str) -> list[fx.Entry]:
    """/robot1/tf and /robot2/tf with the same frames; robot 2 is 6 m to the side."""
    out = []
    for ns, y in (('/robot1', 0.0), ('/robot2', 6.0)):
        out.append(_tf(f'{ns}/tf_static', STAMPS[0], 'base_link', 'velodyne', (0.0, 0.0, 1.0)))
        out += [_tf(f'{ns}/tf', t + 20 * MS * (y > 0), 'map', 'base_link', (k, y, 0.0)) for k, t in enumerate(STAMPS)]
    return out + [_cloud(cloud_topic, t + 10 * MS) for t in STAMPS[:-1]]


@pytest.mark.parametrize('fmt', ['ros1', 'mcap'])
def test_namespaced_tf_of_several_robots_uses_the_clouds_namespace(tmp_path: Path, fmt: str) -> None:
    bag = _write(tmp_path, _two_robots('/robot1/velodyne_points'), fmt, ('/robot1/tf_static', '/robot2/tf_static'))
    with open_recording(bag) as rec:
        info = rec.info()
        assert info.pose_error is None
        stream = rec.scans()
        scans = list(stream)
    assert len(scans) == 4
    for s in scans:  # robot 1's poses only (merged, they were interpolated between both robots)
        np.testing.assert_allclose(s.T_world_sensor[:3, 3], [s.index + 0.1, 0.0, 1.0], atol=1e-6)
    note = 'using /robot1/tf, /robot1/tf_static, those of the cloud topic\'s namespace'
    assert any(note in n for n in stream.notes) and any(note in n for n in info.notes)


def test_namespaced_tf_outside_the_clouds_namespace_must_be_chosen(tmp_path: Path) -> None:
    bag = _write(tmp_path, _two_robots('/velodyne_points'), 'ros1', ('/robot1/tf_static', '/robot2/tf_static'))
    with open_recording(bag) as rec:
        with pytest.raises(RecordingError, match=r'several namespaces give the same frames .*--tf-topic /robot1/tf'):
            rec.scans()
        assert 'same frames' in (rec.info().pose_error or '')
        scans = list(rec.scans(tf_topic='/robot2'))
        with pytest.raises(RecordingError, match="TF topic '/robot3/tf' is not in"):
            rec.scans(tf_topic='/robot3/tf')
    np.testing.assert_allclose(scans[1].T_world_sensor[:3, 3], [0.9, 6.0, 1.0], atol=1e-6)


# ----------------------------------------------------------------------------- a frame with two parents
def _two_parents(first_odom_only: bool) -> list[fx.Entry]:
    """base_link under odom (drifting 0.5 m a cloud in y; or one early transform) and under world."""
    out = [_tf('/tf_static', STAMPS[0], 'base_link', 'velodyne', (0.0, 0.0, 1.0))]
    for k, t in enumerate(STAMPS):
        if not first_odom_only:
            out.append(_tf('/tf', t - MS, 'odom', 'base_link', (k, 0.5 * k, 0.0)))
        out.append(_tf('/tf', t, 'world', 'base_link', (k, 0.0, 0.0)))
    if first_odom_only:
        out.append(_tf('/tf', STAMPS[0] - 100 * MS, 'odom', 'base_link', (0.0, 0.0, 0.0)))
    return out + [_cloud('/points', t) for t in STAMPS]


def test_a_frame_with_two_parents_is_noted_and_the_fixed_frame_chooses(tmp_path: Path) -> None:
    with open_recording(_write(tmp_path, _two_parents(False))) as rec:
        stream = rec.scans()
        list(stream)
        assert stream.fixed_frame == 'odom'
        assert any(
            "frame 'base_link' has two parents on TF: odom -> base_link (5 transforms) is used, "
            'world -> base_link (5 transforms) ignored' in n
            for n in stream.notes
        )
        stream = rec.scans(fixed_frame='world')
        scans = list(stream)
    assert len(scans) == 5 and "using 'world' (towards the fixed frame 'world'), not 'odom'" in stream.notes[0]
    for s in scans:
        np.testing.assert_allclose(s.T_world_sensor[:3, 3], [s.index, 0.0, 1.0], atol=1e-6)


def test_an_early_second_parent_is_named_where_the_chain_fails(tmp_path: Path) -> None:
    with open_recording(_write(tmp_path, _two_parents(True))) as rec:
        with pytest.raises(RecordingError) as err:
            rec.scans()
        assert len(list(rec.scans(fixed_frame='world'))) == 5
    assert "frame 'base_link' has two parents on TF: odom -> base_link (1 transform) is used" in str(err.value)
    assert '--fixed-frame world' in str(err.value)


# ----------------------------------------------------------------------------- PointCloud2 sizes and fields
def _scene_tf() -> list[fx.Entry]:
    return [_tf('/tf_static', STAMPS[0], 'base_link', 'velodyne', (0.0, 0.0, 1.0))] + [
        _tf('/tf', t, 'map', 'base_link', (k, 0.0, 0.0)) for k, t in enumerate(STAMPS)
    ]


def _edited_cloud(t: int, edit: object, pts: np.ndarray | None = None) -> fx.Entry:
    """A cloud of 4 points whose message ``edit`` changes (a driver's wrong header)."""
    p = fx.pack_cloud(np.arange(12, dtype=float).reshape(4, 3) + 1 if pts is None else pts)

    def build(m: fx.Msgs) -> object:
        msg = m.cloud(t, 'velodyne', p)
        edit(msg)  # type: ignore[operator]
        return msg

    return ('/points', PC2, t, build)


def _half_width(msg: object) -> None:
    msg.width, msg.row_step = 2, 24  # type: ignore[attr-defined]


def _height0(msg: object) -> None:
    msg.height = 0  # type: ignore[attr-defined]


def test_cloud_data_longer_than_its_header_is_noted_and_height0_skipped(tmp_path: Path) -> None:
    entries = _scene_tf() + [
        _edited_cloud(STAMPS[0], lambda m: None),
        _edited_cloud(STAMPS[1], _half_width),
        _edited_cloud(STAMPS[2], _height0),
        _edited_cloud(STAMPS[3], _half_width),
    ]
    with open_recording(_write(tmp_path, entries)) as rec:
        stream = rec.scans()
        scans = list(stream)
    assert [len(s.points) for s in scans] == [4, 2, 2]
    assert stream.skipped == {'data size disagrees with width x height x point_step': 1}
    notes = '\n'.join(stream.notes)
    assert '2 clouds hold more data than the header says (cloud #1: height 1 x width 2 x point_step 12' in notes
    assert "(2 more points' worth)): only the header's points are read" in notes
    assert "cloud #2: height 0 x width 4 x point_step 12 = 0 bytes but 48 bytes of data" in notes


def test_a_field_named_twice_is_refused(tmp_path: Path) -> None:
    def dup_x(msg: object) -> None:
        pf = type(msg.fields[0])  # type: ignore[attr-defined]
        msg.fields.insert(0, pf(name='x', offset=12, datatype=7, count=1))  # type: ignore[attr-defined]
        msg.point_step, msg.row_step = 16, 16 * msg.width  # type: ignore[attr-defined]
        msg.data = np.zeros(16 * msg.width, np.uint8)  # type: ignore[attr-defined]

    entries = _scene_tf() + [_edited_cloud(t, dup_x) for t in STAMPS[:2]]
    with open_recording(_write(tmp_path, entries)) as rec:
        with pytest.raises(
            RecordingError, match="two fields named 'x', at offsets 12 and 0: which holds x is ambiguous"
        ):
            list(rec.scans())


def test_info_says_why_the_first_clouds_cannot_be_mapped(tmp_path: Path) -> None:
    upper = fx.pack_cloud(np.ones((3, 3)))
    upper.fields = [(n.upper(), o, d) for n, o, d in upper.fields]
    int16 = fx.pack_cloud(np.ones((3, 3)), layout={'x': (0, 'i2'), 'y': (2, 'i2'), 'z': (4, 'i2')}, point_step=6)
    empty = fx.pack_cloud(np.empty((0, 3)))
    for name, packed, why in (
        ('upper', upper, "/points: cloud #0 cannot be mapped: PointCloud2 (frame 'velodyne') has no x/y/z field"),
        ('int16', int16, "/points: cloud #0 cannot be mapped: PointCloud2 field 'x' has datatype INT16"),
        ('empty', empty, '/points: all 3 of its clouds are empty (no points)'),
    ):
        entries = _scene_tf() + [_cloud('/points', t, packed=packed) for t in STAMPS[:3]]
        with open_recording(fx.write_bag(tmp_path / f'{name}.bag', 'ros1', sorted(entries, key=lambda e: e[2]))) as rec:
            info = rec.info()
        assert info.pose_source == 'tf: map -> base_link -> velodyne'
        assert (info.pose_error or '').startswith(why), info.pose_error


# ----------------------------------------------------------------------------- Livox CustomMsg
@pytest.mark.parametrize('fmt', ['ros1', 'sqlite3'])
def test_livox_point_num_that_disagrees_is_noted_and_its_records_read(
    tmp_path: Path, fmt: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    pts = np.arange(30, dtype=np.float32).reshape(10, 3) + 1

    def msg(m: fx.Msgs, t: int) -> object:
        out = m.livox(t, 'livox', pts, 'livox_ros_driver2')
        out.point_num = 0  # a driver that leaves it unset
        return out

    entries = [_tf('/tf', t, 'map', 'livox', (k, 0.0, 0.0)) for k, t in enumerate(STAMPS)]
    entries += [('/livox/lidar', 'livox_ros_driver2/msg/CustomMsg', t, lambda m, t=t: msg(m, t)) for t in STAMPS[:3]]
    bag = _write(tmp_path, entries, fmt)
    note = '3 clouds hold a point_num that disagrees with the point records that follow (cloud #0: point_num 0, 10 records)'
    for fast in (True, False):  # from the bytes, and deserialised
        if not fast:
            monkeypatch.setattr('ndtom_ti.io.recording.decode_livox_raw', lambda raw, ros1: None)
        with open_recording(bag) as rec:
            stream = rec.scans()
            scans = list(stream)
        assert [len(s.points) for s in scans] == [10, 10, 10]
        assert any(n.startswith(note) for n in stream.notes), stream.notes
    with open_recording(bag) as rec, pytest.raises(RecordingError, match='holds no definition of that type'):
        rec._deserialize(b'\0' * 8, 'some_driver/msg/Unknown', '/x')


# ----------------------------------------------------------------------------- hints
def test_a_cloud_frame_without_its_mount_offers_static_transform_and_the_split_folder(tmp_path: Path) -> None:
    tfs = _scene_tf()
    fx.write_bag(tmp_path / 'run_0.bag', 'ros1', tfs[:3] + [_cloud('/points', STAMPS[0])])
    fx.write_bag(tmp_path / 'run_1.bag', 'ros1', tfs[3:] + [_cloud('/points', t) for t in STAMPS[3:]])
    with open_recording(tmp_path / 'run_1.bag') as rec, pytest.raises(RecordingError) as err:
        rec.scans()
    text = str(err.value)
    assert "give it with --static-transform 'X Y Z QX QY QZ QW base_link velodyne'" in text
    assert 'run_1.bag looks like one part of a split recording' in text and f'pass the folder {tmp_path}' in text
    with open_recording(tmp_path) as rec:  # the folder: both parts
        assert len(list(rec.scans())) == 3


def test_a_static_transform_given_over_a_recorded_mount_says_both(tmp_path: Path) -> None:
    entries = _scene_tf() + [_cloud('/points', t) for t in STAMPS]
    given = '0 0 2 0 0 0 1 base_link velodyne'
    with open_recording(_write(tmp_path, entries)) as rec:
        for _ in range(2):  # given again by a second scans(): the same note
            stream = rec.scans(static_transforms=[given])
            scans = list(stream)
    np.testing.assert_allclose(scans[1].T_world_sensor[:3, 3], [1.0, 0.0, 2.0], atol=1e-9)
    assert stream.notes == [
        'static transform given: base_link -> velodyne, replacing the recorded base_link -> velodyne: given '
        'xyz (0, 0, 2) m, quaternion xyzw (0, 0, 0, 1), recorded xyz (0, 0, 1) m, quaternion xyzw (0, 0, 0, 1)'
    ]


def test_a_first_cloud_without_a_frame_is_named_and_start_offered(tmp_path: Path) -> None:
    entries = _scene_tf() + [_cloud('/points', STAMPS[0], frame='')] + [_cloud('/points', t) for t in STAMPS[1:]]
    with open_recording(_write(tmp_path, entries)) as rec:
        with pytest.raises(RecordingError) as err:
            list(rec.scans())
        assert len(list(rec.scans(t_start=0.001))) == 4
    assert str(err.value) == (
        'cloud #0 of /points at 1700000000.000 s has an empty frame_id; it is the first cloud to map '
        '(a broken first cloud refuses the recording): --start 0.001 skips it'
    )


def test_a_cloud_in_another_frame_than_the_first_is_noted(tmp_path: Path) -> None:
    entries = _scene_tf() + [_tf('/tf_static', STAMPS[0], 'base_link', 'rear', (-1.0, 0.0, 0.0))]
    entries += [_cloud('/points', t, frame='rear' if k == 2 else 'velodyne') for k, t in enumerate(STAMPS)]
    with open_recording(_write(tmp_path, entries)) as rec:
        stream = rec.scans()
        scans = list(stream)
    assert "cloud #2 of /points is in frame 'rear', not 'velodyne' like the first" in '\n'.join(stream.notes)
    np.testing.assert_allclose(scans[2].T_world_sensor[:3, 3], [1.0, 0.0, 0.0], atol=1e-9)
