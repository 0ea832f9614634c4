"""Bags written by ../shared/tools/simworld.py read back to the exact poses and points of its npz."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import io_fixtures as fx  # noqa: E402

from ndtom_ti.io import open_recording  # noqa: E402

pytestmark = pytest.mark.skipif(not fx.SIMWORLD.is_file(), reason=f'{fx.SIMWORLD} not found')


@pytest.fixture(scope='session')
def simworld_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp('simworld')
    for name, storage in (('hall', 'mcap'), ('hall_sqlite', 'sqlite3')):
        subprocess.run(
            [
                sys.executable,
                str(fx.SIMWORLD),
                '--scans',
                '4',
                '--stride',
                '10',
                '--az-step',
                '2',
                '--out',
                str(out),
                '--name',
                name,
                '--ros2-storage',
                storage,
            ],
            check=True,
            capture_output=True,
            timeout=120,
        )
    return out


@pytest.mark.parametrize('bag', ['hall.bag', 'hall_ros2', 'hall_sqlite_ros2'])
def test_simworld_poses_and_points(simworld_dir: Path, bag: str) -> None:
    npz = np.load(simworld_dir / ('hall_sqlite.npz' if bag.startswith('hall_sqlite') else 'hall.npz'))
    offs, nr = npz['scan_offsets'], npz['no_return']
    with open_recording(simworld_dir / bag) as rec:
        info = rec.info()
        assert info.storage == {'hall.bag': 'ros1', 'hall_ros2': 'mcap', 'hall_sqlite_ros2': 'sqlite3'}[bag]
        assert info.tf_tree == {'base_link': 'map', 'velodyne': 'base_link'}
        stream = rec.scans()
        scans = list(stream)
    assert stream.pose_source == 'tf: map -> base_link -> velodyne' and stream.fixed_frame == 'map'
    assert len(scans) == len(npz['poses']) == 4 and not stream.skipped
    for i, s in enumerate(scans):
        assert s.index == i and s.frame_id == 'velodyne' and s.stamp_ns == npz['stamps_ns'][i]
        np.testing.assert_allclose(s.T_world_sensor, npz['poses'][i], atol=1e-6)
        expect = npz['points'][offs[i] : offs[i + 1]][~nr[offs[i] : offs[i + 1]]]
        assert s.points.shape == expect.shape
        np.testing.assert_array_equal(s.points, expect)
