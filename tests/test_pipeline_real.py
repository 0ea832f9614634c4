"""The four real recordings in ../shared/data, mapped through the pipeline and the CLI,
with checks that the maps are right (skipped when the data is not there)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import DATA
from typer.testing import CliRunner

from ndtom_ti import NdtOmMap
from ndtom_ti.cli import app
from ndtom_ti.io import open_recording
from ndtom_ti.mapfile import read_header
from ndtom_ti.pipeline import map_recording

TUM = DATA / "tum_fr2_pioneer_slam2_10f.bag"
BALM = DATA / "balm_hall_every4"
NORLAB = DATA / "norlab_outdoor_stationary_14.bag"
LUMINAR = DATA / "luminar_embag_test.bag"


def need(p: Path) -> Path:
    if not p.exists():
        pytest.skip(f"{p} not available")
    return p


def cli(*args: str):
    return CliRunner(env={"COLUMNS": "250"}).invoke(app, [str(a) for a in args])


def normals(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w, v = np.linalg.eigh(cov)
    return np.maximum(w, 0.0), v[:, :, 0]


def test_tum_floor_is_flat_at_its_height() -> None:
    """TUM fr2/pioneer_slam2: the motion-capture world frame has the floor at z ~ 0.03 m
    (per-scan medians of the raw points near the camera range from -0.005 to 0.05). Most
    planar Gaussians with vertical normals are that floor."""
    m, s = map_recording(need(TUM), 0.2)
    assert s.complete and s.scans_used == 10 and not s.skipped
    assert s.points_in == 10 * 76_800 and s.dropped["nonfinite"] > 0.1 * s.points_in  # NaN = no depth
    g = m.gaussians()
    del m
    w, n = normals(g["cov"])
    planar = w[:, 0] < 0.1 * w[:, 1]
    vertical = planar & (np.abs(n[:, 2]) > 0.95)
    z = g["mean"][vertical, 2]
    assert vertical.sum() > 500
    on_floor = np.abs(z - 0.03) < 0.12
    assert on_floor.mean() > 0.8, on_floor.mean()
    assert -0.02 < np.median(z[on_floor]) < 0.08
    assert np.median(np.sqrt(w[vertical][on_floor, 0])) < 0.03  # thin


def test_balm_hall_walls_are_thin_and_vertical(tmp_path: Path) -> None:
    """BALM hall (Livox, ROS2 mcap) through the CLI, every 4th scan at 0.3 m: Gaussians with
    horizontal normals (the walls) are thin planes: smallest eigenvalue a few cm^2 at most
    and much smaller than the other two."""
    out = tmp_path / "hall.ndtom"
    r = cli("map", need(BALM), "-r", "0.3", "--every", "4", "-o", out, "--no-progress")
    assert r.exit_code == 0, r.output
    assert "12 of 45 clouds read" in r.output and "33 left out by --every" in r.output
    m = NdtOmMap.load(out)
    assert m.metadata["pose_source"] == "tf: map -> livox" and m.metadata["recording"]["storage"] == "mcap"
    assert m.metadata["options"]["every"] == 4 and m.scans_inserted == 12
    g = m.gaussians()
    del m
    w, n = normals(g["cov"])
    wall = (np.abs(n[:, 2]) < 0.1) & (g["n"] >= 10)
    assert wall.sum() > 1000
    thickness = np.sqrt(w[wall, 0])
    assert np.median(thickness) < 0.03 and np.percentile(thickness, 90) < 0.06
    assert np.median(w[wall, 0] / w[wall, 2]) < 0.1  # planes, not blobs
    # a wall's in-plane spread has a large vertical part: the plane is vertical
    big = np.linalg.eigh(g["cov"][wall])[1][:, :, 1:]  # the two in-plane directions
    assert np.median(np.abs(big[:, 2, :]).max(axis=1)) > 0.7


def test_norlab_long_ranges_fit_the_memory_budget(tmp_path: Path) -> None:
    """norlab: ~190 m ranges. At 0.4 m all 14 scans (every ray traced to its end) fit the
    CPU pool budget. At 0.1 m under a budget within Taichi's own 1 GiB chunk
    (--memory-limit 0.875) the first scan does not fit: `ndtom map` stops with exit 1 and
    says why in its own options (the default budget, half the machine's memory, maps all
    14: docs/large-maps.md). A separate process: a process has one pool and one budget."""
    import os
    import subprocess
    import sys

    out = tmp_path / "norlab.ndtom"
    r = cli("map", need(NORLAB), "-r", "0.4", "-o", out, "--no-progress")
    assert r.exit_code == 0, r.output
    assert "14 of 14 clouds read" in r.output and "/icp_odom" in r.output
    m = NdtOmMap.load(out)
    rep = m.memory_report()
    assert m.scans_inserted == 14 and rep["gaussians"] > 10_000
    assert rep["process_pool_bytes"] <= rep["process_pool_budget_bytes"]
    assert m.metadata["fixed_frame"] == "map" and m.metadata["summary"]["dropped"]["range"] == 0
    g = m.gaussians()
    del m
    assert np.linalg.norm(g["mean"][:, :2], axis=1).max() > 150  # the far returns are in the map

    fine = tmp_path / "fine.ndtom"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "ndtom_ti",
            "map",
            str(NORLAB),
            "-r",
            "0.1",
            "-o",
            str(fine),
            "--no-progress",
            "--memory-limit",
            "0.875",
            "--arch",
            "cpu",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
        env={**os.environ, "COLUMNS": "200"},
    )
    text = r.stdout + r.stderr
    assert r.returncode == 1, text
    assert (
        "scan 1 was refused: it could take Taichi's memory pool past its 0.88 GiB budget" in text
        and "--memory-limit" in text
        and "-r 0.2" in text
    )
    assert "Traceback" not in text and "memory_limit_GB" not in text and "--every" not in text
    assert "Nothing was mapped; no map written" in text and not fine.exists()


def test_luminar_fields_decode_and_missing_poses_are_reported(tmp_path: Path) -> None:
    """Luminar: 7 fields, point_step 32; xyz decode to the float32 bytes at their offsets.
    Its only pose topic is a constant pose on another clock: `ndtom map` says so; with
    --sensor-frame it maps."""
    from rosbags.highlevel import AnyReader

    with AnyReader([need(LUMINAR)]) as reader:
        conn = next(c for c in reader.connections if c.topic == "/luminar_pointcloud")
        _, _, raw = next(reader.messages(connections=[conn]))
        msg = reader.deserialize(raw, conn.msgtype)
    fields = {f.name: (f.offset, f.datatype) for f in msg.fields}
    assert len(fields) == 7 and msg.point_step == 32
    assert all(fields[a][1] == 7 for a in "xyz")  # FLOAT32
    buf = np.frombuffer(bytes(msg.data), np.uint8).reshape(-1, msg.point_step)
    xyz = np.stack([buf[:, fields[a][0] : fields[a][0] + 4].copy().view("<f4")[:, 0] for a in "xyz"], axis=1)
    with open_recording(LUMINAR) as rec:
        scan = next(iter(rec.scans(sensor_frame_only=True)))
    np.testing.assert_array_equal(scan.points, xyz)

    r = cli("map", LUMINAR, "-r", "0.3", "-o", tmp_path / "lum.ndtom")
    assert r.exit_code == 2
    assert "no usable poses" in r.output and "--sensor-frame" in r.output and "different clocks" in r.output
    assert "Traceback" not in r.output and not (tmp_path / "lum.ndtom").exists()

    r = cli("map", LUMINAR, "-r", "0.5", "--sensor-frame", "-o", tmp_path / "lum.ndtom", "--no-progress")
    assert r.exit_code == 0, r.output
    h = read_header(tmp_path / "lum.ndtom")
    assert h["scans_inserted"] == 5 and h["metadata"]["fixed_frame"] == "luminar_lidar"
    assert "identity" in h["metadata"]["pose_source"] and h["metadata"]["options"]["sensor_frame_only"] is True


def test_info_on_the_real_recordings() -> None:
    r = cli("info", need(TUM))
    assert r.exit_code == 0, r.output
    for text in (
        "/camera/depth/points",
        "openni_depth_optical_frame",
        "world",
        "kinect",
        "Pose sources",
        "tf: world -> kinect -> openni_depth_optical_frame",
        "Ready: ndtom map",
    ):
        assert text in r.output, text
    r = cli("info", need(NORLAB))
    assert r.exit_code == 0 and "/icp_odom" in r.output and "nav_msgs/msg/Odometry" in r.output
    r = cli("info", need(LUMINAR))
    assert r.exit_code == 0 and "Cannot map with the defaults" in r.output and "--sensor-frame" in r.output
