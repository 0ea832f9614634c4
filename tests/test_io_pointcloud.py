"""PointCloud2 and depth-image decoding (ndtom_ti.io.pointcloud)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import io_fixtures as fx  # noqa: E402

from ndtom_ti.io import RecordingError, decode_pointcloud2, depth_image_to_points  # noqa: E402

M1, M2 = fx.Msgs(ros1=True), fx.Msgs(ros1=False)


def _cloud(points: np.ndarray, **kw: object) -> object:
    return M2.cloud(fx.T0, 'lidar', fx.pack_cloud(points, **kw))


@pytest.mark.parametrize('i', range(5))
def test_scene_layouts_decode_exactly(i: int) -> None:
    pts, kw = fx.scene_clouds()[i]
    for m in (M1, M2):
        out = decode_pointcloud2(m.cloud(fx.T0, 'sensor', fx.pack_cloud(pts, **kw)))
        wide = any(c == 'f8' for _, c in (kw.get('layout') or {'x': (0, 'f4')}).values())
        assert out.dtype == (np.float64 if wide else np.float32) and out.shape == pts.shape
        np.testing.assert_allclose(out, pts.astype(out.dtype), atol=1e-6, equal_nan=True)
        assert np.array_equal(np.isnan(out), np.isnan(pts))


def test_float64_fields_keep_their_digits() -> None:
    """Registered clouds in UTM or ECEF coordinates: float32 would round a point 5000 km out
    to 0.5 m (the map's rays and Gaussians would be made of those steps)."""
    pts = np.array([[1e-3, 123.456789012, -98765.4321], [512345.678901, 5412345.123456, 301.2345678]])
    out = decode_pointcloud2(_cloud(pts, layout={'x': (0, 'f8'), 'y': (8, 'f8'), 'z': (16, 'f8')}, point_step=24))
    assert out.dtype == np.float64 and out.tolist() == pts.tolist()
    mixed = decode_pointcloud2(_cloud(pts, layout={'x': (0, 'f8'), 'y': (8, 'f4'), 'z': (12, 'f4')}, point_step=16))
    assert mixed.dtype == np.float64 and mixed[:, 0].tolist() == pts[:, 0].tolist()
    empty = decode_pointcloud2(_cloud(pts[:0], layout={'x': (0, 'f8'), 'y': (8, 'f8'), 'z': (16, 'f8')}, point_step=24))
    assert empty.shape == (0, 3) and empty.dtype == np.float64


def test_big_endian_float64_with_padding_and_extra_fields() -> None:
    pts = np.array([[1.5, -2.25, 3.0], [4.0, 5.5, -6.75], [7.0, 8.0, 9.0], [0.5, 0.25, 0.125]])
    layout = {'intensity': (0, 'f4'), 'x': (4, 'f8'), 'y': (12, 'f8'), 'z': (20, 'f8'), 'ring': (28, 'u2')}
    msg = _cloud(
        pts,
        layout=layout,
        point_step=32,
        bigendian=True,
        height=2,
        row_pad=3,
        extra_values={'intensity': np.arange(4), 'ring': np.arange(4)},
    )
    assert msg.row_step == 2 * 32 + 3
    np.testing.assert_array_equal(decode_pointcloud2(msg), pts)


def test_organised_cloud_keeps_nans_in_row_major_order() -> None:
    pts = np.arange(24, dtype=float).reshape(8, 3)
    pts[[2, 5]] = np.nan
    out = decode_pointcloud2(_cloud(pts, height=4, row_pad=12))
    assert out.shape == (8, 3)
    assert np.flatnonzero(np.isnan(out[:, 0])).tolist() == [2, 5]
    np.testing.assert_array_equal(out[~np.isnan(out[:, 0])], pts[~np.isnan(pts[:, 0])])


def test_empty_cloud_gives_zero_rows() -> None:
    out = decode_pointcloud2(_cloud(np.zeros((0, 3))))
    assert out.shape == (0, 3) and out.dtype == np.float32


def test_decode_accepts_bytes_payload() -> None:
    msg = _cloud(np.array([[1.0, 2.0, 3.0]]))
    msg.data = bytes(msg.data)
    assert decode_pointcloud2(msg).tolist() == [[1.0, 2.0, 3.0]]


def test_missing_xyz_fields_names_the_fields_present() -> None:
    layout = {'a': (0, 'f4'), 'b': (4, 'f4'), 'c': (8, 'f4')}
    msg = M2.cloud(
        fx.T0, 'lidar', fx.pack_cloud(np.zeros((2, 3)), layout={'x': (0, 'f4'), 'y': (4, 'f4'), 'z': (8, 'f4')})
    )
    PF = M2.T['sensor_msgs/msg/PointField']
    msg.fields = [PF(name=n, offset=o, datatype=7, count=1) for n, (o, _) in layout.items()]
    with pytest.raises(RecordingError) as err:
        decode_pointcloud2(msg)
    text = str(err.value)
    assert 'no x/y/z field' in text and 'a (FLOAT32 at offset 0)' in text and 'c (FLOAT32 at offset 8)' in text
    assert "'lidar'" in text


def test_integer_xyz_is_rejected_with_field_list() -> None:
    msg = _cloud(np.ones((2, 3)), layout={'x': (0, 'i2'), 'y': (2, 'i2'), 'z': (4, 'i2')}, point_step=6)
    with pytest.raises(RecordingError, match=r"field 'x' has datatype INT16.*FLOAT32 or FLOAT64.*z \(INT16"):
        decode_pointcloud2(msg)


def test_truncated_data_and_bad_offsets_are_reported() -> None:
    msg = _cloud(np.ones((4, 3)))
    msg.data = msg.data[:-5]
    with pytest.raises(RecordingError, match='truncated'):
        decode_pointcloud2(msg)
    msg = _cloud(np.ones((4, 3)))
    msg.point_step = 10  # z at 8..12 no longer fits
    with pytest.raises(RecordingError, match="'z' at offset 8 does not fit in point_step 10"):
        decode_pointcloud2(msg)


# ------------------------------------------------------------------------------------------- depth
@pytest.mark.parametrize('m', [M1, M2], ids=['ros1', 'ros2'])
def test_depth_32fc1_back_projection(m: fx.Msgs) -> None:
    d32, _ = fx.scene_depth()
    img = m.image(fx.T0, 'cam', d32, '32FC1', pad=4)
    info = m.camera_info(fx.T0, 'cam', 5, 8, **fx.DEPTH_K)
    out = depth_image_to_points(img, info)
    ref = fx.expected_depth_points(d32, **fx.DEPTH_K)
    assert out.shape == (40, 3) and out.dtype == np.float32
    np.testing.assert_allclose(out, ref, atol=1e-6, equal_nan=True)
    assert np.isnan(out).all(axis=1).sum() == 2  # NaN and inf pixels -> NaN rows, layout kept
    assert (out == 0).all(axis=1).sum() == 1  # 0: no depth measured, (0, 0, 0) as a lidar's beam with no return


def test_depth_16uc1_millimetres_big_endian_and_stride() -> None:
    _, d16 = fx.scene_depth()
    img = M2.image(fx.T0, 'cam', d16, '16UC1', bigendian=True)
    info = M2.camera_info(fx.T0, 'cam', 5, 8, **fx.DEPTH_K)
    ref = fx.expected_depth_points(d16 / 1000.0, **fx.DEPTH_K).reshape(5, 8, 3)
    np.testing.assert_allclose(depth_image_to_points(img, info), ref.reshape(-1, 3), atol=1e-6, equal_nan=True)
    out = depth_image_to_points(img, info, stride=3)
    assert out.shape == (2 * 3, 3)
    np.testing.assert_allclose(out, ref[::3, ::3].reshape(-1, 3), atol=1e-6, equal_nan=True)
    assert (depth_image_to_points(img, info)[1 * 8 + 1] == 0).all()  # 0 mm = no depth: no return, not 'not finite'


def test_unsupported_image_encoding_and_bad_camera_info() -> None:
    rgb = M2.image(fx.T0, 'cam', np.zeros((5, 24), np.uint8), 'rgb8')
    rgb.width = 8
    info = M2.camera_info(fx.T0, 'cam', 5, 8, **fx.DEPTH_K)
    with pytest.raises(RecordingError, match=r"encoding 'rgb8' is not supported; expected 32FC1.*16UC1"):
        depth_image_to_points(rgb, info)
    d32, _ = fx.scene_depth()
    img = M2.image(fx.T0, 'cam', d32, '32FC1')
    with pytest.raises(RecordingError, match='not calibrated'):
        depth_image_to_points(img, M2.camera_info(fx.T0, 'cam', 5, 8, fx=0.0, fy=0.0, cx=0.0, cy=0.0))
    with pytest.raises(RecordingError, match='CameraInfo is for 16x10 images but the depth image is 8x5'):
        depth_image_to_points(img, M2.camera_info(fx.T0, 'cam', 10, 16, **fx.DEPTH_K))
