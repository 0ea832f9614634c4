"""ndtom_ti.pipeline: recordings -> map + summary, with known answers."""

from __future__ import annotations

import json
import os
import signal
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import test_pipeline_bags as pb  # noqa: E402

import ndtom_ti  # noqa: E402
from ndtom_ti import MapConfig, MapMemoryError, NdtOmMap  # noqa: E402
from ndtom_ti import demo as demo_scene  # noqa: E402
from ndtom_ti.io import RecordingError  # noqa: E402
from ndtom_ti.pipeline import config_with_ranges, load_config_file, map_recording, map_scans  # noqa: E402


@pytest.mark.parametrize("fmt", ["ros1", "sqlite3", "mcap"])
def test_plane_recording_maps_to_the_plane(tmp_path: Path, fmt: str) -> None:
    bag = pb.write_plane_bag(tmp_path, fmt, early_cloud=True)
    seen = []
    m, s = map_recording(bag, pb.RES, progress=lambda summ, rep: seen.append(rep))
    assert s.complete and s.stopped is None
    assert s.cloud_topic == "/points" and s.frame_id == "lidar" and s.fixed_frame == "map"
    assert s.pose_source == "tf: map -> base -> lidar"
    # the cloud before the first transform is skipped and counted, with the reason
    assert s.scans_used == pb.N_CLOUDS and s.clouds_seen == pb.N_CLOUDS + 1
    assert s.skipped == {"no pose at stamp": 1}
    assert any(n.startswith("no pose at stamp: cloud #0") for n in s.skip_notes)
    assert seen[0] is None and len(seen) == pb.N_CLOUDS + 1
    assert s.points_in == sum(r.points_in for r in seen[1:]) == s.points_used
    assert s.gaussians == len(m) and s.known_cells > s.gaussians and s.memory_bytes == m.memory_bytes()
    assert len(s.scan_seconds) == pb.N_CLOUDS and 0 < s.ms_per_scan_median <= s.ms_per_scan_p95
    pb.check_plane_map(m)

    md = m.metadata
    assert md["source"] == str(bag.resolve()) and md["cloud_topic"] == "/points"
    assert md["pose_source"] == s.pose_source and md["ndtom_ti_version"] == ndtom_ti.__version__
    assert md["recording"]["format"] == ("ros1" if fmt == "ros1" else "ros2")
    assert md["complete"] is True and md["summary"]["scans_used"] == pb.N_CLOUDS
    out = m.save(tmp_path / "plane.ndtom")
    del m
    back = NdtOmMap.load(out)
    assert back.metadata["options"]["every"] == 1 and back.metadata["resolution"] == pb.RES
    assert back.metadata["summary"]["skipped"] == {"no pose at stamp": 1}
    pb.check_plane_map(back)


def test_options_select_scans_and_ranges(tmp_path: Path) -> None:
    bag = pb.write_plane_bag(tmp_path)
    m, s = map_recording(bag, pb.RES, every=2)
    assert s.scans_used == 3 and s.skipped == {"every": 2} and s.scans_expected == 3
    del m
    m, s = map_recording(bag, pb.RES, max_scans=2, max_range=4.0, occupancy=False)
    assert s.scans_used == 2 and s.dropped["range"] > 0 and not s.occupancy and not m.occupancy_enabled
    assert m.config.max_range == 4.0 and m.metadata["options"]["max_scans"] == 2
    del m
    # the bag starts with /tf_static 0.9 s before the first cloud; clouds come every 0.2 s
    m, s = map_recording(bag, pb.RES, t_start=1.0, t_end=1.35)
    assert s.scans_used == 2 and s.skipped == {"outside time window": 3}
    del m
    m, s = map_recording(bag, pb.RES, every_distance=0.8)  # the base moves 0.41 m per cloud
    assert s.scans_used == 3 and s.skipped == {"every_distance": 2}
    del m
    with pytest.raises(ValueError, match="every_distance"):
        map_recording(bag, pb.RES, every=2, every_distance=1.0)
    with pytest.raises(ValueError, match="resolution"):
        map_recording(bag, -1.0)


def test_bad_recordings_raise_before_a_map_is_made(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="no usable poses"):
        map_recording(pb.write_plane_bag(tmp_path, name="notf", with_tf=False), pb.RES)
    with pytest.raises(RecordingError, match="/points_front"):
        map_recording(pb.write_plane_bag(tmp_path, name="two", second_topic=True), pb.RES)
    with pytest.raises(RecordingError, match="fields present"):
        map_recording(pb.write_plane_bag(tmp_path, name="abc", bad_fields=True), pb.RES)


def test_poses_from_a_file_and_sensor_frame(tmp_path: Path) -> None:
    """A TUM pose file with T_map_lidar gives the same map as TF; --sensor-frame maps
    each cloud at identity (the floor is then tilted in the map)."""
    bag = pb.write_plane_bag(tmp_path)
    from ndtom_ti.io import rot_to_quat

    lines = []
    for k, t in enumerate(pb.STAMPS):
        T = pb.T_map_lidar(k)
        q = rot_to_quat(T[:3, :3])  # x y z w
        lines.append(f"{t / 1e9:.9f} {T[0, 3]} {T[1, 3]} {T[2, 3]} {q[0]} {q[1]} {q[2]} {q[3]}")
    poses = tmp_path / "poses.txt"
    poses.write_text("\n".join(lines) + "\n")
    m, s = map_recording(bag, pb.RES, poses_file=poses)
    assert s.pose_source.startswith("poses file") and s.scans_used == pb.N_CLOUDS
    pb.check_plane_map(m)
    del m
    m, s = map_recording(bag, pb.RES, sensor_frame_only=True, max_scans=1)
    assert s.fixed_frame == "lidar" and "identity" in s.pose_source
    g = m.gaussians()
    assert np.abs(np.abs(pb.eig_normals(g["cov"])[1][:, 2]) - 1).max() > 0.05  # tilted 15 degrees
    del m


def test_ctrl_c_stops_after_the_current_scan(tmp_path: Path) -> None:
    bag = pb.write_plane_bag(tmp_path)
    calls = []

    def progress(summary, report):
        calls.append(report)
        if summary.scans_used == 2:
            os.kill(os.getpid(), signal.SIGINT)  # what Ctrl-C sends

    before = signal.getsignal(signal.SIGINT)  # (SIG_IGN in a shell's background job)
    m, s = map_recording(bag, pb.RES, progress=progress)
    assert s.stopped == "interrupted" and not s.complete and s.scans_used == 2
    assert m.scans_inserted == 2 and m.metadata["complete"] is False
    assert signal.getsignal(signal.SIGINT) is before  # restored
    del m


def test_ctrl_c_after_the_last_scan_says_the_map_is_complete(monkeypatch) -> None:
    """Ctrl-C once every scan is mapped (while the summary is made, before the save):
    nothing is cut short, so the map is complete (exit 0) and the message says so, not
    "stopping after the scan in hand"."""
    from ndtom_ti.pipeline import MappingSummary
    from ndtom_ti.signals import stop_signals

    count_map = MappingSummary.count_map

    def count_after_ctrl_c(summary, m):
        os.kill(os.getpid(), signal.SIGINT)
        count_map(summary, m)

    monkeypatch.setattr(MappingSummary, "count_map", count_after_ctrl_c)
    said: list[str] = []
    scans = [(pb.sensor_points(k, np.random.default_rng(k)), pb.T_map_lidar(k)) for k in range(2)]
    with stop_signals((signal.SIGINT,), phase="idle", say=said.append) as sig:
        m, s = map_scans(scans, pb.RES)
    assert sig.count == 1 and s.complete and s.stopped is None and s.scans_used == 2
    assert said == ["Ctrl-C: every scan is mapped; saving the complete map."], said
    del m


def test_keyboard_interrupt_while_reading_keeps_the_map(tmp_path: Path) -> None:
    def scans():
        for k in range(3):
            yield pb.sensor_points(k, np.random.default_rng(k)), pb.T_map_lidar(k)
        raise KeyboardInterrupt

    m, s = map_scans(scans(), pb.RES)
    assert s.stopped == "interrupted" and s.scans_used == 3 and len(m) > 0
    del m


def test_memory_budget_stops_and_keeps_the_scans_before(tmp_path: Path, monkeypatch) -> None:
    bag = pb.write_plane_bag(tmp_path)
    orig = NdtOmMap.insert_scan
    n = {"calls": 0}

    def insert(self, points, T):
        n["calls"] += 1
        if n["calls"] == 3:
            raise MapMemoryError("this update could take Taichi's memory pool past the budget (test)")
        return orig(self, points, T)

    monkeypatch.setattr(NdtOmMap, "insert_scan", insert)
    m, s = map_recording(bag, pb.RES)
    assert s.stopped == "memory" and s.scans_used == 2 and m.scans_inserted == 2
    assert "scan 3 was refused" in s.error and "holds the 2 scans" in s.error
    assert m.metadata["summary"]["stopped"] == "memory"
    del m


def test_map_scans_accepts_pairs_and_objects() -> None:
    rng = np.random.default_rng(1)
    pairs = [(pb.sensor_points(k, rng), pb.T_map_lidar(k)) for k in range(3)]
    m, s = map_scans(pairs, pb.RES, source="test", metadata={"note": "x"})
    assert s.scans_used == 3 and s.clouds_seen == 3 and m.metadata["note"] == "x" and m.metadata["source"] == "test"
    pb.check_plane_map(m)
    del m


@pytest.mark.parametrize(
    "bad",
    [
        None,
        (1, 2, 3),
        {"points": 1},
        "scan",
        ([[0.0, 0.0, 1.0], [1.0, 2.0]], np.eye(4)),
        ("P", np.eye(3)),
        ("P", "pose"),
    ],
    ids=["none", "triple", "dict", "str", "ragged points", "3x3 pose", "str pose"],
)
def test_map_scans_keeps_the_scans_before_a_malformed_one(bad) -> None:
    """A malformed item after good scans stops the loop with the map of the scans before it
    (summary.stopped 'error', a clear message); as the first item it raises a clear error."""
    rng = np.random.default_rng(1)
    good = [(pb.sensor_points(k, rng), pb.T_map_lidar(k)) for k in range(3)]
    if isinstance(bad, tuple) and len(bad) == 2 and isinstance(bad[0], str):
        bad = (good[0][0], bad[1])
    for T0 in (None, 512_300.0):  # near the origin, and far (the frame is shifted)
        scans = [(p, T.copy()) for p, T in good]
        if T0 is not None:
            for _, T in scans:
                T[0, 3] += T0
        m, s = map_scans([*scans[:2], bad, scans[2]], pb.RES)
        assert s.scans_used == 2 and s.stopped == "error" and m.scans_inserted == 2, s.error
        assert "scan 3 could not be inserted" in s.error and "The map holds the 2 scans before it" in s.error
        assert "Traceback" not in s.error and "IndexError" not in s.error
        m.close()
        with pytest.raises((TypeError, ValueError), match=r"scan|points|T_world_sensor|pair"):
            map_scans([bad, *scans], pb.RES)


def test_poses_far_from_their_frames_origin_shift_the_maps_frame() -> None:
    """Only a first pose outside the middle half of the grid shifts the frame (rounded to
    100 m, recorded); near-origin poses and a map that already holds scans are left alone."""
    from ndtom_ti.frames import FRAME_ORIGIN_STEP, as_frame_origin
    from ndtom_ti.pipeline import frame_origin

    def at(x, y, z):
        T = np.eye(4)
        T[:3, 3] = (x, y, z)
        return T

    with NdtOmMap(0.2) as m:  # the grid: +-3276.8 m across, +-409.6 m up
        assert frame_origin(m, at(1600.0, -1600.0, 200.0)) is None
        np.testing.assert_array_equal(frame_origin(m, at(1700.0, 5.0, 0.0)), [1700.0, 0.0, 0.0])
        np.testing.assert_array_equal(frame_origin(m, at(10.0, 20.0, 260.0)), [0.0, 0.0, 300.0])
        np.testing.assert_array_equal(frame_origin(m, at(512_345.0, 5_412_349.9, 31.0)), [512_300.0, 5_412_300.0, 0.0])
        assert frame_origin(m, at(np.nan, 0.0, 0.0)) is None  # a bad pose: insert_scan says so
        assert FRAME_ORIGIN_STEP == 100.0
        for bad in (None, "east", b"xyz", [1.0, 2.0], [[1.0, 2.0, 3.0]], [1.0, float("inf"), 0.0], {"x": 1}):
            assert as_frame_origin(bad) is None, bad
        np.testing.assert_array_equal(as_frame_origin((1, 2.5, -3)), [1.0, 2.5, -3.0])
        pts = np.random.default_rng(3).normal([5.0, 0.0, 0.0], 0.01, (200, 3))
        near, summary = map_scans([(pts, at(0.0, 0.0, 1.0))], 0.2)  # a local frame: no shift
        assert summary.frame_origin is None and "frame_origin" not in near.metadata
        near.close()
        m.insert_scan(pts, at(0.0, 0.0, 1.0))
        assert frame_origin(m, at(1700.0, 0.0, 0.0)) is None  # a map with scans keeps its frame
        for bad in ("east", [1.0, 2.0], [1.0, float("nan"), 0.0]):  # a damaged file's metadata
            m.metadata["frame_origin"] = bad
            with pytest.raises(ValueError, match="not three finite numbers"):
                frame_origin(m, at(0.0, 0.0, 0.0))
    far, summary = map_scans([(pts, at(512_345.0, 5_412_345.0, 31.0))], 0.2)
    assert summary.frame_origin == [512_300.0, 5_412_300.0, 0.0] == far.metadata["frame_origin"]
    g = far.gaussians()
    assert far.scans_inserted == 1 and len(g["n"]) > 0 and np.abs(g["mean"] - [50.0, 45.0, 31.0]).max() < 0.1
    far.close()


def test_config_files(tmp_path: Path) -> None:
    j = tmp_path / "c.json"
    j.write_text(json.dumps({"p_occupied": 0.7, "max_range": 30.0}))
    assert load_config_file(j) == {"p_occupied": 0.7, "max_range": 30.0}
    t = tmp_path / "c.toml"
    t.write_text("[map]\nmin_points = 5\nmax_range_mode = 'drop'\n")
    assert load_config_file(t) == {"min_points": 5, "max_range_mode": "drop"}
    cfg = config_with_ranges(load_config_file(j), max_range=10.0, min_range=0.5)
    assert cfg == MapConfig(p_occupied=0.7, max_range=10.0, min_range=0.5)
    for text, suffix, msg in (
        ("{nope", ".json", "not valid JSON"),
        ("a = [", ".toml", "not valid TOML"),
        ('{"resolution": 0.1}', ".json", "unknown options"),
        ('p_empty = 0.7', ".toml", "p_empty must be in"),
    ):
        f = tmp_path / f"bad{suffix}"
        f.write_text(text)
        with pytest.raises(ValueError, match=msg):
            load_config_file(f)
    with pytest.raises(ValueError, match="does not exist"):
        load_config_file(tmp_path / "missing.toml")
    with pytest.raises(ValueError, match="max_range must be > min_range"):
        config_with_ranges(None, min_range=5.0, max_range=2.0)


# ---------------------------------------------------------------------------- the demo scene
def test_demo_ray_caster_is_exact() -> None:
    scene = demo_scene.Scene()
    scans = demo_scene.make_scans(20, scene=scene, noise=0.0)
    assert len(scans) == 20 and all(10_000 <= len(s.points) <= 20_000 for s in scans)
    for s in (scans[0], scans[15]):
        w = s.points.astype(np.float64) @ s.T_world_sensor[:3, :3].T + s.T_world_sensor[:3, 3]
        d = scene.surface_distance(w, s.index)
        assert d.max() < 1e-4  # float32 points: every return lies on a surface
    box = scene.vanishing[0]
    seen = []
    for s in scans:  # returns from the box's sides and top (its bottom face is the floor)
        w = s.points.astype(np.float64) @ s.T_world_sensor[:3, :3].T + s.T_world_sensor[:3, 3]
        seen.append((box.distance(w) < 1e-4) & (w[:, 2] > 0.01))
    assert all(v.sum() > 50 for v in seen[:10]) and not any(v.any() for v in seen[10:])
    # a ray straight down from the sensor hits the floor at exactly its height
    o = scans[0].T_world_sensor[:3, 3]
    assert scene.cast(o, np.array([[0.0, 0.0, -1.0]]), 0)[0] == pytest.approx(o[2])
    assert np.isinf(scene.cast(o, np.array([[0.0, 0.0, 1.0]]), 0)[0])  # no ceiling


def test_demo_map_matches_the_ground_truth() -> None:
    scans = demo_scene.make_scans(20)
    m, s = map_scans(scans[:10], 0.2)
    before = demo_scene.ground_truth_check(m.gaussians(), 0.2)
    del m
    m, s = map_scans(scans, 0.2)
    after = demo_scene.ground_truth_check(m.gaussians(), 0.2)
    del m
    assert before["left_in_vanished"] > 30  # the box was mapped while it stood there
    assert after["left_in_vanished"] == 0  # and erased by the rays once it was gone
    assert after["on_surface"] > 0.98 and after["median_distance"] < 0.01
    assert s.scans_used == 20 and s.gaussians > 5000


def test_points_per_second_leaves_the_first_scan_out() -> None:
    from types import SimpleNamespace

    from ndtom_ti.pipeline import MappingSummary

    s = MappingSummary()
    rep = SimpleNamespace(
        points_in=10**6,
        points_used=10**6,
        free_rays=0,
        dropped_nonfinite=0,
        dropped_range=0,
        dropped_outside_grid=0,
        dropped_no_return=0,
        seconds=0.5,
    )
    s.add(rep)
    s.wall_first_scan = s.wall_seconds = 10.0  # the first scan compiled the kernels
    assert s.points_per_second == pytest.approx(1e5)  # alone: all there is
    s.add(rep)
    s.add(rep)
    s.wall_seconds = 11.0
    assert s.points_per_second == pytest.approx(2e6)  # 2 M points in the 1 s after the first scan


def test_summary_gives_the_first_scan_apart():
    """The first scan compiles the kernels: the median and p95 are of the scans after it."""
    from ndtom_ti.pipeline import MappingSummary

    s = MappingSummary(source="x", resolution=0.2)
    s.scan_seconds = [2.5, 0.010, 0.020, 0.030]
    assert s.ms_first_scan == pytest.approx(2500.0)
    assert s.ms_per_scan_median == pytest.approx(20.0) and s.ms_per_scan_p95 < 31.0
    d = s.to_dict()
    assert d["ms_first_scan"] == 2500.0 and d["ms_per_scan_median"] == 20.0
    s.scan_seconds = [0.5]  # one scan only: it is the median too
    assert s.ms_per_scan_median == pytest.approx(500.0)


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_registered_clouds_map_as_the_sensor_frame_ones(tmp_path: Path, fmt: str) -> None:
    """Clouds already in the world frame (a lidar odometry's registered clouds) with the
    lidar's poses on a topic whose frame is the clouds' own: the points are used as they
    are and each ray starts at the lidar, so the map is the one of the same scans in the
    lidar's frame. Rays from the world frame's origin (under the floor) would carve free
    cells below it."""
    plain, s0 = map_recording(pb.write_plane_bag(tmp_path, fmt, name="plain"), pb.RES)
    bag = pb.write_plane_bag(tmp_path, fmt, name="reg", registered=True)
    with ndtom_ti.io.open_recording(bag) as rec:
        assert "registered clouds" in (rec.info().pose_source or "")
    reg, s = map_recording(bag, pb.RES)
    assert s0.pose_source == "tf: map -> base -> lidar" and s.frame_id == "map" and s.fixed_frame == "map"
    assert s.pose_source.startswith("pose topic /odom (nav_msgs/msg/Odometry map -> lidar)")
    assert "registered clouds" in s.pose_source and s.scans_used == pb.N_CLOUDS
    pb.check_plane_map(reg)
    a, b = plain.known_cells(), reg.known_cells()
    # the points went through float32 in another frame: a point on a cell's face may change cells
    assert abs(len(a["index"]) - len(b["index"])) <= 0.001 * len(a["index"])
    assert abs(len(plain) - len(reg)) <= 2
    below = b["index"][:, 2] * pb.RES < pb.PLANE_Z - pb.RES
    assert not below.any()  # nothing known under the floor: no ray came from below it
    inv = plain.logodds_at(b["index"])
    same = np.abs(inv - b["logodds"]) < 1e-3
    assert same.mean() > 0.995


@pytest.mark.parametrize(("fmt", "registered"), [("ros1", False), ("mcap", False), ("ros1", True)])
def test_transforms_tf2_would_drop_are_dropped_and_noted(tmp_path: Path, fmt: str, registered: bool) -> None:
    """A zero quaternion (an unset pose) or NaN in one transform or pose message is dropped, as
    tf2 drops it, and noted: it neither refuses the recording nor stops the run, and the map is
    the one without it."""
    plain, _ = map_recording(pb.write_plane_bag(tmp_path, fmt, name="plain", registered=registered), pb.RES)
    bag = pb.write_plane_bag(tmp_path, fmt, name="faults", registered=registered, faults=True)
    m, s = map_recording(bag, pb.RES)
    assert s.complete and s.scans_used == pb.N_CLOUDS
    notes = "\n".join(s.skip_notes)
    assert "ignored 1 transform base -> cam with a zero-length quaternion" in notes, notes
    assert "ignored 2 transforms map -> base with a zero-length quaternion (or other faults)" in notes or registered
    if registered:
        assert "/odom: ignored 1 pose with a zero-length quaternion" in notes
        assert "/odom: ignored 1 pose with NaN or Inf values" in notes
    a, b = plain.known_cells(), m.known_cells()
    np.testing.assert_array_equal(a["index"], b["index"])
    np.testing.assert_array_equal(a["logodds"], b["logodds"])
    with ndtom_ti.io.open_recording(bag) as rec:  # `ndtom info` reads it too
        assert any("base -> cam" in n for n in rec.info().notes)


@pytest.mark.parametrize("how", ["truncated", "no frame"])
def test_a_broken_cloud_among_good_ones_is_skipped_and_counted(tmp_path: Path, how: str) -> None:
    """One broken message mid-recording (data cut short, an empty frame_id) is skipped, counted
    and noted; the scans after it are mapped. As the first cloud it refuses the recording, as
    any bad first cloud does."""
    m, s = map_recording(pb.write_plane_bag(tmp_path, name="b", broken={2: how}), pb.RES)
    assert s.complete and s.scans_used == pb.N_CLOUDS - 1 and s.skipped == {"bad message": 1}
    note = next(n for n in s.skip_notes if n.startswith("bad message: cloud #2"))
    assert ("truncated" if how == "truncated" else "has an empty frame_id") in note, note
    assert m.scans_inserted == pb.N_CLOUDS - 1
    with pytest.raises(RecordingError, match="truncated" if how == "truncated" else "has an empty frame_id.*--start"):
        map_recording(pb.write_plane_bag(tmp_path, name="b0", broken={0: how}), pb.RES)


def test_an_empty_first_cloud_without_a_frame_does_not_choose_the_poses(tmp_path: Path) -> None:
    """A driver's empty start-up cloud with a default header (no frame, stamp 0): the poses are
    chosen by the first cloud that names its frame, and the empty one is counted as empty."""
    plain, _ = map_recording(pb.write_plane_bag(tmp_path, name="plain"), pb.RES)
    m, s = map_recording(pb.write_plane_bag(tmp_path, name="e", broken={-1: "empty"}), pb.RES)
    assert s.frame_id == "lidar" and s.pose_source == "tf: map -> base -> lidar"
    assert s.scans_used == pb.N_CLOUDS and s.skipped == {"empty cloud": 1}
    np.testing.assert_array_equal(plain.known_cells()["logodds"], m.known_cells()["logodds"])


def test_a_pose_without_a_child_frame_is_the_vehicles_that_carries_the_sensor(tmp_path: Path) -> None:
    """A PoseStamped (amcl_pose, motion capture) names no child frame; with tf_static mounting
    the lidar on 'base', its poses are base's: the map is the one TF map -> base gives. Taken
    as the lidar's own poses, the map would lie the mount's offset away (--pose-child-frame)."""
    plain, _ = map_recording(pb.write_plane_bag(tmp_path, name="plain"), pb.RES)
    bag = pb.write_plane_bag(tmp_path, name="ps", pose_stamped=True)
    m, s = map_recording(bag, pb.RES)
    assert s.pose_source == (
        "pose topic /pose (geometry_msgs/msg/PoseStamped map -> base: its messages name no child frame; the frame "
        "tf_static mounts 'lidar' on) + tf_static base -> lidar"
    )
    a, b = plain.known_cells(), m.known_cells()
    np.testing.assert_array_equal(a["index"], b["index"])
    np.testing.assert_array_equal(a["logodds"], b["logodds"])
    lidar, s = map_recording(bag, pb.RES, pose_child_frame="lidar")  # the old reading: 0.5 m too low
    assert "map -> lidar: its messages name no child frame; as given" in s.pose_source
    with pytest.raises(AssertionError):
        pb.check_plane_map(lidar)  # the floor and wall tilted and moved by the mount
    pb.check_plane_map(m)
    with pytest.raises(RecordingError, match="pose_child_frame goes with poses from a pose topic"):
        map_recording(bag, pb.RES, pose_child_frame="base", sensor_frame_only=True)
    odom = pb.write_plane_bag(tmp_path, name="reg", registered=True)
    with pytest.raises(RecordingError, match="its messages name their frame 'lidar'; pose_child_frame"):
        map_recording(odom, pb.RES, pose_topic="/odom", pose_child_frame="base")


def test_pose_messages_stamped_0_are_matched_by_record_time(tmp_path: Path) -> None:
    plain, _ = map_recording(pb.write_plane_bag(tmp_path, name="plain", registered=True), pb.RES)
    m, s = map_recording(pb.write_plane_bag(tmp_path, name="z", registered=True, odom_zero_stamps=True), pb.RES)
    assert s.scans_used == pb.N_CLOUDS and any("/odom: 5 poses stamped 0 (unset)" in n for n in s.skip_notes)
    np.testing.assert_allclose(plain.known_cells()["logodds"].sum(), m.known_cells()["logodds"].sum(), rtol=1e-3)


def test_a_mount_republished_with_other_values_is_noted(tmp_path: Path) -> None:
    _, s = map_recording(pb.write_plane_bag(tmp_path, name="r", remount=True), pb.RES)
    assert any("/tf_static gives base -> lidar more than once with different values" in n for n in s.skip_notes)
    _, s = map_recording(pb.write_plane_bag(tmp_path, name="p"), pb.RES)
    assert not any("/tf_static gives" in n for n in s.skip_notes)


def test_clouds_on_the_sensors_clock_are_matched_by_record_time_when_asked(tmp_path: Path) -> None:
    """A driver that stamps clouds with the sensor's own clock: refused with the option that
    helps; with cloud_time="record" the bag's record times match them to the poses."""
    bag = pb.write_plane_bag(tmp_path, name="clock", sensor_clock=True)
    with pytest.raises(RecordingError, match=r"(?s)do not overlap.*--cloud-time record"):
        map_recording(bag, pb.RES)
    m, s = map_recording(bag, pb.RES, cloud_time="record")
    assert s.scans_used == pb.N_CLOUDS and m.metadata["options"]["cloud_time"] == "record"
    pb.check_plane_map(m)
    with pytest.raises(ValueError, match="cloud_time must be one of header, record"):
        map_recording(bag, pb.RES, cloud_time="sensor")


def test_a_mount_the_recording_lacks_can_be_given(tmp_path: Path) -> None:
    """/tf_static not recorded: the lidar is not in the TF tree and the recording is refused;
    the mount given as static_transform_publisher takes it (--static-transform) gives the
    map of the recording that has it."""
    from ndtom_ti.io.selection import parse_static_transform

    plain, _ = map_recording(pb.write_plane_bag(tmp_path, name="plain"), pb.RES)
    bag = pb.write_plane_bag(tmp_path, name="nomount", mount_recorded=False)
    with pytest.raises(RecordingError, match="lidar"):
        map_recording(bag, pb.RES)
    (x, y, z), q = pb.BASE_MOUNT
    text = " ".join(repr(float(v)) for v in (x, y, z, *q)) + " base lidar"
    m, s = map_recording(bag, pb.RES, static_transforms=[text])
    assert "static transform given: base -> lidar" in s.skip_notes
    a, b = plain.known_cells(), m.known_cells()
    np.testing.assert_array_equal(a["index"], b["index"])
    np.testing.assert_array_equal(a["logodds"], b["logodds"])
    assert m.metadata["options"]["static_transforms"] == [["base", "lidar", [x, y, z], [float(v) for v in q]]]
    # yaw pitch roll, as static_transform_publisher takes them: the same rotation
    p, c, t, q2 = parse_static_transform("1 2 3 0.3 -0.2 0.1 base lidar")
    from ndtom_ti.io import quat_to_rot

    cy, sy, cp, sp, cr, sr = np.cos(0.3), np.sin(0.3), np.cos(-0.2), np.sin(-0.2), np.cos(0.1), np.sin(0.1)
    Rz, Ry, Rx = (
        [[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]],
        [[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]],
        [[1, 0, 0], [0, cr, -sr], [0, sr, cr]],
    )
    np.testing.assert_allclose(quat_to_rot(q2), np.array(Rz) @ np.array(Ry) @ np.array(Rx), atol=1e-12)
    assert (p, c, t) == ("base", "lidar", (1.0, 2.0, 3.0))
    for bad, why in (
        ("1 2 3 base lidar", "give 'x y z"),
        ("1 2 x 0 0 0 1 a b", "must be numbers"),
        ("0 0 0 0 0 0 0 a b", "zero length"),
    ):
        with pytest.raises(ValueError, match=why):
            parse_static_transform(bad)


def _registered_f64_bag(root: Path, name: str, offset: np.ndarray) -> Path:
    """The plane scene's clouds registered in 'map' as FLOAT64 points, moved by ``offset``
    (as a lidar odometry in UTM coordinates writes them), with the lidar's poses on /odom."""
    rng = np.random.default_rng(42)
    fx = pb.fx
    e: list = []
    for k in range(pb.N_CLOUDS):
        t, T = pb.STAMPS[k], pb.T_map_lidar(k)
        q = pb.quat_mul(fx.quat_axis_angle((0, 0, 1), 0.05 * k), pb.BASE_MOUNT[1])
        tr = T[:3, 3] + offset
        e.append(("/odom", "nav_msgs/msg/Odometry", t, lambda m, t=t, tr=tr, q=q: m.odometry(t, "map", "lidar", tr, q)))
        w = pb.sensor_points(k, rng) @ T[:3, :3].T + T[:3, 3] + offset
        packed = fx.pack_cloud(w, layout={"x": (0, "f8"), "y": (8, "f8"), "z": (16, "f8")}, point_step=24)
        e.append(("/points", "sensor_msgs/msg/PointCloud2", t + 1, lambda m, t=t, p=packed: m.cloud(t, "map", p)))
    e.sort(key=lambda x: x[2])
    return fx.write_bag(root / f"{name}.bag", "ros1", e)


def test_registered_float64_clouds_far_from_the_origin_keep_their_digits(tmp_path: Path) -> None:
    """Registered FLOAT64 clouds in UTM coordinates (500 km east, 5400 km north) give the map
    of the same clouds near the origin, moved: float32 points would be 0.5 m steps there."""
    off = np.array([512300.0, 5412300.0, 0.0])
    near, _ = map_recording(_registered_f64_bag(tmp_path, "near", np.zeros(3)), pb.RES)
    far, s = map_recording(_registered_f64_bag(tmp_path, "far", off), pb.RES)
    assert s.frame_origin == off.tolist()  # the map's own frame: the first pose, to 100 m
    pb.check_plane_map(near)
    gn, gf = near.gaussians(), far.gaussians()
    assert len(gn["mean"]) == len(gf["mean"]) > 100
    on = np.lexsort(gn["index"].T)
    of = np.lexsort(gf["index"].T)
    np.testing.assert_array_equal(gn["index"][on], gf["index"][of])
    np.testing.assert_allclose(gf["mean"][of], gn["mean"][on], atol=1e-6)
    np.testing.assert_allclose(gf["cov"][of], gn["cov"][on], atol=1e-8)


@pytest.mark.parametrize(
    ("fmt", "pkg"), [("ros1", "livox_ros_driver"), ("mcap", "livox_ros_driver2"), ("sqlite3", "livox_ros_driver")]
)
def test_livox_custom_messages_map_as_point_clouds(tmp_path: Path, fmt: str, pkg: str) -> None:
    """Livox's CustomMsg (the driver's own message, read from its bytes) gives the map that the
    same float32 points give as PointCloud2."""
    plain, _ = map_recording(pb.write_plane_bag(tmp_path, fmt, name="plain"), pb.RES)
    bag = pb.write_plane_bag(tmp_path, fmt, name="livox", livox=pkg, no_return=7)
    with ndtom_ti.io.open_recording(bag) as rec:
        assert rec.info().mappable_topics == ["/points"]
    m, s = map_recording(bag, pb.RES)
    assert s.cloud_topic == "/points" and s.scans_used == pb.N_CLOUDS and s.pose_source == "tf: map -> base -> lidar"
    assert s.dropped["no_return"] == 7 * pb.N_CLOUDS
    pb.check_plane_map(m)
    a, b = plain.known_cells(), m.known_cells()
    np.testing.assert_array_equal(a["index"], b["index"])
    np.testing.assert_array_equal(a["logodds"], b["logodds"])


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_laserscan_of_a_2d_lidar_maps_the_walls(tmp_path: Path, fmt: str) -> None:
    """A 2D lidar (sensor_msgs/LaserScan) 0.3 m above a moving base in a 10 x 8 m room: its
    beams become points in the scan plane; readings with no return (inf, NaN, 0, under
    range_min, past range_max) are dropped and counted as such."""
    import io_fixtures as fx

    half = np.array([5.0, 4.0])
    n, a0 = 720, -np.pi
    da = 2 * np.pi / n
    e: list = [
        (
            "/tf_static",
            "tf2_msgs/msg/TFMessage",
            fx.T0 - 10 * fx.MS,
            lambda m: m.tf([(fx.T0, "base", "laser", (0.1, 0.0, 0.3), (0.0, 0.0, 0.0, 1.0))]),
        )
    ]
    for k in range(6):
        t = fx.T0 + k * 100 * fx.MS
        xy, yaw = np.array([-1.0 + 0.3 * k, 0.5 - 0.1 * k]), 0.1 * k
        q = fx.quat_axis_angle((0, 0, 1), yaw)
        e.append(
            ("/tf", "tf2_msgs/msg/TFMessage", t, lambda m, t=t, xy=xy, q=q: m.tf([(t, "odom", "base", (*xy, 0.0), q)]))
        )
        origin = xy + [0.1 * np.cos(yaw), 0.1 * np.sin(yaw)]
        ang = yaw + a0 + da * np.arange(n)
        d = np.stack([np.cos(ang), np.sin(ang)], axis=1)
        with np.errstate(divide="ignore"):
            tx = np.where(d[:, 0] != 0, (np.sign(d[:, 0]) * half[0] - origin[0]) / d[:, 0], np.inf)
            ty = np.where(d[:, 1] != 0, (np.sign(d[:, 1]) * half[1] - origin[1]) / d[:, 1], np.inf)
        r = np.minimum(tx, ty)
        r[::50] = np.inf  # no return
        r[1::50] = np.nan
        r[2::50] = 0.0
        r[3::50] = 0.05  # under range_min
        r[4::50] = 40.0  # past range_max
        e.append(
            (
                "/scan",
                "sensor_msgs/msg/LaserScan",
                t + 1,
                lambda m, t=t, r=r: m.laserscan(t, "laser", r, a0, da, 0.1, 30.0),
            )
        )
    e.sort(key=lambda x: x[2])
    bag = fx.write_bag(fx.bag_path(tmp_path, fmt, "scan2d"), fmt, e)
    with ndtom_ti.io.open_recording(bag) as rec:
        assert rec.info().mappable_topics == ["/scan"]
    m, s = map_recording(bag, 0.1)
    assert s.cloud_topic == "/scan" and s.scans_used == 6 and s.pose_source == "tf: odom -> base -> laser"
    bad = 5 * len(range(0, n, 50))
    assert s.points_in == 6 * n and s.dropped["no_return"] == 6 * bad and s.points_used == 6 * (n - bad)
    assert s.dropped["nonfinite"] == 0
    g = m.gaussians()
    mu = g["mean"]
    assert len(mu) > 200
    on_wall = (np.abs(np.abs(mu[:, 0]) - half[0]) < 0.02) | (np.abs(np.abs(mu[:, 1]) - half[1]) < 0.02)
    assert on_wall.all() and np.abs(mu[:, 2] - 0.3).max() < 1e-6
    assert m.occupancy(np.array([0.0, 0.0, 0.3])) < 0.5  # the room's inside is free


def test_registered_clouds_with_their_motion_in_tf_only(tmp_path: Path) -> None:
    """Registered clouds (in 'map') whose sensor motion only TF records: refused with the way
    out named (the moving frames), then mapped from the lidar's frame with ray_origin_frame
    (--ray-origin-frame) as the sensor-frame clouds are."""
    bag = pb.write_plane_bag(tmp_path, name="reg_tf", registered=True, odom=False)
    with pytest.raises(RecordingError) as err:
        map_recording(bag, pb.RES)
    assert (
        "give the moving frame the rays start from as --ray-origin-frame (ray_origin_frame), one of: base, lidar"
        in str(err.value)
    )
    plain, _ = map_recording(pb.write_plane_bag(tmp_path, name="plain"), pb.RES)
    m, s = map_recording(bag, pb.RES, ray_origin_frame="lidar")
    assert s.pose_source == "tf: map -> base -> lidar; rays from 'lidar', the clouds in 'map' (tf lidar -> base -> map)"
    assert m.metadata["options"]["ray_origin_frame"] == "lidar"
    pb.check_plane_map(m)
    a, b = plain.known_cells(), m.known_cells()
    assert abs(len(a["index"]) - len(b["index"])) <= 0.001 * len(a["index"])
    assert (np.abs(plain.logodds_at(b["index"]) - b["logodds"]) < 1e-3).mean() > 0.995
    for bad, text in (
        ({"ray_origin_frame": "nowhere"}, "ray origin frame 'nowhere' is not in the TF tree"),
        ({"ray_origin_frame": "map"}, "is the fixed frame: it does not move"),
        ({"ray_origin_frame": "lidar", "sensor_frame_only": True}, "goes with poses from TF or a pose topic"),
    ):
        with pytest.raises(RecordingError, match=text):
            map_recording(bag, pb.RES, **bad)


def test_registered_clouds_with_the_odometry_of_the_vehicle(tmp_path: Path) -> None:
    """Registered clouds beside the odometry of the vehicle ('base'), with the lidar's mount in
    TF: by default the rays start at the vehicle's origin (0.5 m under the lidar); with
    ray_origin_frame='lidar' at the lidar, and the map is the sensor-frame one."""
    plain, _ = map_recording(pb.write_plane_bag(tmp_path, name="plain"), pb.RES)
    bag = pb.write_plane_bag(tmp_path, name="reg_base", registered=True, odom_child="base")
    m0, s0 = map_recording(bag, pb.RES)
    assert "each ray from the position of 'base'" in s0.pose_source
    m, s = map_recording(bag, pb.RES, pose_topic="/odom", ray_origin_frame="lidar")
    assert s.pose_source == (
        "pose topic /odom (nav_msgs/msg/Odometry map -> base) + tf base -> lidar "
        "(registered clouds in 'map', rays from 'lidar')"
    )
    pb.check_plane_map(m)
    a, b, c = plain.known_cells(), m.known_cells(), m0.known_cells()
    assert abs(len(a["index"]) - len(b["index"])) <= 0.001 * len(a["index"])
    assert (np.abs(plain.logodds_at(b["index"]) - b["logodds"]) < 1e-3).mean() > 0.995
    assert (np.abs(plain.logodds_at(c["index"]) - c["logodds"]) < 1e-3).mean() < 0.99  # rays from elsewhere
    with pytest.raises(RecordingError, match="TF does not connect its frame 'base' to the ray origin 'nowhere'"):
        map_recording(bag, pb.RES, pose_topic="/odom", ray_origin_frame="nowhere")


def test_two_lidars_into_one_map(tmp_path: Path) -> None:
    """Two lidars on the vehicle (/points in 'lidar', /points2 in 'lidar2', another mount):
    cloud_topic="/points,/points2" maps both, their clouds in time order, each from its own
    pose, as inserting them by hand does."""
    bag, want = pb.write_two_lidar_bag(tmp_path)
    m, s = map_recording(bag, pb.RES, cloud_topic="/points,/points2")
    assert s.cloud_topic == "/points,/points2" and s.scans_used == 8 and s.clouds_seen == 8
    assert s.frame_id == "lidar,lidar2"
    assert s.pose_source == "/points: tf: map -> base -> lidar; /points2: tf: map -> base -> lidar2"
    assert m.metadata["options"]["cloud_topic"] == "/points,/points2"
    ref = NdtOmMap(pb.RES)
    for p, T in want:
        ref.insert_scan(p, T)
    a, b = ref.known_cells(), m.known_cells()
    np.testing.assert_array_equal(a["index"], b["index"])
    np.testing.assert_allclose(a["logodds"], b["logodds"], atol=1e-5)
    with pytest.raises(ValueError, match="names a topic twice"):
        map_recording(bag, pb.RES, cloud_topic="/points,points")
    with pytest.raises(RecordingError, match="'/nothing' is not in"):
        map_recording(bag, pb.RES, cloud_topic="/points,/nothing")
    _, s2 = map_recording(bag, pb.RES, cloud_topic="/points,/points2", every=2)
    assert s2.scans_used == 4  # every second cloud of each topic
    kitti = tmp_path / "poses.txt"  # KITTI rows: poses by cloud index, which fit one topic
    kitti.write_text("".join(" ".join(f"{v:.6f}" for v in T[:3].ravel()) + "\n" for _, T in want[::2]))
    with pytest.raises(RecordingError, match="gives the poses of one topic by cloud index"):
        map_recording(bag, pb.RES, cloud_topic="/points,/points2", poses_file=kitti)
    _, s3 = map_recording(bag, pb.RES, cloud_topic="/points", poses_file=kitti)
    assert s3.scans_used == 4


def test_two_cloud_topics_posed_in_different_frames_are_refused(tmp_path: Path) -> None:
    import io_fixtures as fx

    e: list = []
    for k in range(3):
        t = pb.STAMPS[k]
        e.append(
            (
                "/tf",
                "tf2_msgs/msg/TFMessage",
                t,
                lambda m, t=t, k=k: m.tf([(t, "map", "lidar", (0.1 * k, 0, 1), (0, 0, 0, 1))]),
            )
        )
        e.append(
            (
                "/tf",
                "tf2_msgs/msg/TFMessage",
                t,
                lambda m, t=t, k=k: m.tf([(t, "odom", "lidar2", (0.1 * k, 0, 1), (0, 0, 0, 1))]),
            )
        )
        for topic, frame in (("/points", "lidar"), ("/points2", "lidar2")):
            p = fx.pack_cloud(np.array([[5.0, 0.0, 0.0], [0.0, 5.0, 0.0]]))
            e.append((topic, "sensor_msgs/msg/PointCloud2", t + 1, lambda m, t=t, f=frame, p=p: m.cloud(t, f, p)))
    e.sort(key=lambda x: x[2])
    bag = fx.write_bag(tmp_path / "apart.bag", "ros1", e)
    with pytest.raises(
        RecordingError, match=r"get their poses in different frames \(/points: 'map', /points2: 'odom'\)"
    ):
        map_recording(bag, pb.RES, cloud_topic="/points,/points2")
    _, s = map_recording(bag, pb.RES, cloud_topic="/points2")
    assert s.scans_used == 3 and s.fixed_frame == "odom"
