"""The four real recordings in ../shared/data (skipped when they are not there)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import io_fixtures as fx  # noqa: E402

from ndtom_ti.io import RecordingError, open_recording  # noqa: E402

TUM = fx.DATA_DIR / 'tum_fr2_pioneer_slam2_10f.bag'
BALM = fx.DATA_DIR / 'balm_hall_every4'
NORLAB = fx.DATA_DIR / 'norlab_outdoor_stationary_14.bag'
LUMINAR = fx.DATA_DIR / 'luminar_embag_test.bag'


def _need(p: Path) -> Path:
    if not p.exists():
        pytest.skip(f'{p} not available')
    return p


@pytest.mark.parametrize(
    'path, fmt, storage, cloud_topic',
    [
        (TUM, 'ros1', 'ros1', '/camera/depth/points'),
        (BALM, 'ros2', 'mcap', '/livox/points'),
        (NORLAB, 'ros1', 'ros1', '/lidar/points'),
        (LUMINAR, 'ros1', 'ros1', '/luminar_pointcloud'),
    ],
    ids=['tum', 'balm', 'norlab', 'luminar'],
)
def test_all_open(path: Path, fmt: str, storage: str, cloud_topic: str) -> None:
    with open_recording(_need(path)) as rec:
        info = rec.info()
    assert (info.format, info.storage, info.default_cloud_topic) == (fmt, storage, cloud_topic)
    assert info.mappable_topics[0] == cloud_topic


def test_tum_organised_clouds_with_tf_poses() -> None:
    with open_recording(_need(TUM)) as rec:
        info = rec.info()
        assert info.tf_tree == {'kinect': 'world', 'openni_depth_optical_frame': 'kinect'}
        assert {e.child: e.static for e in info.tf_edges} == {'kinect': False, 'openni_depth_optical_frame': True}
        assert info.mappable_topics == ['/camera/depth/points', '/camera/depth/image']
        stream = rec.scans()
        scans = list(stream)
        assert stream.pose_source == 'tf: world -> kinect -> openni_depth_optical_frame'
        assert len(scans) == 10 and not stream.skipped
        for s in scans:
            assert s.points.shape == (76_800, 3) and s.frame_id == 'openni_depth_optical_frame'
            nan = np.isnan(s.points).any(axis=1)
            assert 0.05 < nan.mean() < 0.5
            z = s.points[~nan, 2]
            assert z.min() > 0.4 and z.max() < 12  # Kinect range (up to ~10.5 m here), z forward
        # first /tf sample (world -> kinect), kinect -> optical is identity
        np.testing.assert_allclose(scans[0].T_world_sensor[:3, 3], (-2.2591, -2.38, 0.5901), atol=1e-6)
        # the depth image, every 2nd pixel, back-projected with K equals the published cloud
        depth = rec.scans(cloud_topic='/camera/depth/image', depth_stride=2, max_scans=1)
        (d,) = list(depth)
        np.testing.assert_allclose(d.points, scans[0].points, atol=1e-5, equal_nan=True)
        np.testing.assert_array_equal(d.T_world_sensor, scans[0].T_world_sensor)


def test_balm_ros2_mcap_tf_poses() -> None:
    with open_recording(_need(BALM)) as rec:
        stream = rec.scans()
        n, npts, path_len, prev = 0, [], 0.0, None
        for s in stream:
            n += 1
            npts.append(len(s.points))
            assert s.frame_id == 'livox' and np.isfinite(s.points).all()
            if prev is not None:
                path_len += float(np.linalg.norm(s.T_world_sensor[:3, 3] - prev))
            prev = s.T_world_sensor[:3, 3]
    assert stream.pose_source == 'tf: map -> livox'
    assert n == 45 and not stream.skipped
    assert min(npts) > 60_000 and max(npts) < 95_000
    assert 50 < path_len < 90  # README: 74 m path over all 177 scans


def test_norlab_pose_topic_with_static_offset() -> None:
    with open_recording(_need(NORLAB)) as rec:
        info = rec.info()
        assert info.tf_tree == {'lidar': 'base_link'}
        expected = 'pose topic /icp_odom (nav_msgs/msg/Odometry map -> base_link) + tf_static base_link -> lidar'
        assert info.pose_source == expected
        stream = rec.scans()
        scans = list(stream)
    assert stream.pose_source == expected and stream.fixed_frame == 'map'
    assert len(scans) == 14 and not stream.skipped
    # stamps of /icp_odom equal the cloud stamps; the static offset is identity
    np.testing.assert_allclose(
        scans[0].T_world_sensor[:3, 3], (0.8582466244697571, -0.1377161741256714, 0.03212672472000122), atol=1e-9
    )
    assert all(abs(len(s.points) - 41_400) < 500 for s in scans)
    r = np.linalg.norm(scans[0].points, axis=1)
    assert r.max() < 200


def test_luminar_points_decode_but_poses_are_unusable() -> None:
    with open_recording(_need(LUMINAR)) as rec:
        info = rec.info()
        assert info.pose_source is None and '/base_pose_ground_truth' in info.pose_error
        assert any('header stamps differ from the bag record times' in n for n in info.notes)
        with pytest.raises(RecordingError) as err:
            rec.scans()
        text = str(err.value)
        assert 'no usable poses' in text and 'different clocks' in text and '--sensor-frame' in text
        stream = rec.scans(sensor_frame_only=True)
        scans = list(stream)
    assert len(scans) == 5 and all(s.frame_id == 'luminar_lidar' for s in scans)
    for s in scans:
        assert 35_000 < len(s.points) < 37_000
        r = np.linalg.norm(s.points, axis=1)
        ok = np.isfinite(r) & (r > 0) & (r < 300)
        assert ok.mean() > 0.99
        assert 20 < np.median(r[ok]) < 100


def test_truncated_real_bag(tmp_path: Path) -> None:
    cut = tmp_path / 'cut.bag'
    with _need(TUM).open('rb') as fh:
        cut.write_bytes(fh.read(100_000))
    with pytest.raises(RecordingError) as err:
        open_recording(cut)
    assert 'cut.bag' in str(err.value) and 'truncated or corrupt' in str(err.value)
