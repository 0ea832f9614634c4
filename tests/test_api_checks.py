"""Bad input to the API gets a clear error (what was wrong, what to do), never a raw numpy,
Taichi or pybind one, a broken process or a silently wrong result."""

import subprocess
import sys
import textwrap

import numpy as np
import pytest

import ndtom_ti
from ndtom_ti import Layout, MapConfig, MapSnapshot, NdtOmMap
from ndtom_ti.io import RecordingError, load_pose_file, make_transform

# Top-level pointer arrays of terabytes on any machine (4096^3 regions x 8 slots x 34 bytes).
HUGE_L1 = (4096, 4096, 4096)


def small_map() -> NdtOmMap:
    m = NdtOmMap(0.2)
    m.insert_scan(np.random.default_rng(0).uniform(-3, 3, (2000, 3)), np.eye(4))
    return m


# --------------------------------------------------------------------------- MapConfig


@pytest.mark.parametrize("kw", [{"n_max": 2}, {"n_max": 4, "min_points": 5}])
def test_n_max_below_min_points_is_refused(kw):
    with pytest.raises(ValueError, match="n_max .* must be at least min_points"):
        MapConfig(**kw)


def test_n_max_equal_to_min_points_is_taken():
    assert MapConfig(n_max=5, min_points=5).n_max == 5


# --------------------------------------------------------------------------- pose files


def test_tum_stamps_in_nanoseconds_are_read(tmp_path):
    p = tmp_path / "ns.txt"
    p.write_text("1311877813991479000 0 0 0 0 0 0 1\n1311877814091479000 1 0 0 0 0 0 1\n")
    assert load_pose_file(p).stamps_ns.tolist() == [1311877813991479000, 1311877814091479000]


def test_kitti_stamps_file_in_nanoseconds_is_read(tmp_path):
    poses, stamps = tmp_path / "k.txt", tmp_path / "t.txt"
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2)
    stamps.write_text("1311877813991479000\n1311877814.091479\n")
    assert load_pose_file(poses, stamps).stamps_ns.tolist() == [1311877813991479000, 1311877814091479000]


@pytest.mark.parametrize("stamp", ["1e30", "1311877813991479", "9.3e9"])
def test_tum_stamp_out_of_range_names_the_units(tmp_path, stamp):
    p = tmp_path / "bad.txt"
    p.write_text(f"{stamp} 0 0 0 0 0 0 1\n")
    with pytest.raises(RecordingError, match="bad.txt:1: time stamp .* out of range.*nanoseconds"):
        load_pose_file(p)


@pytest.mark.parametrize(
    "stamp,message", [("1e999999999", "out of range"), ("Infinity", "out of range"), ("nan", "not a number")]
)
def test_kitti_stamp_out_of_range_is_clear(tmp_path, stamp, message):
    poses, stamps = tmp_path / "k.txt", tmp_path / "t.txt"
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    stamps.write_text(f"{stamp}\n")
    with pytest.raises(RecordingError, match=f"t.txt:1: .*{message}"):
        load_pose_file(poses, stamps)


def test_pose_file_with_a_bom_is_read(tmp_path):
    p = tmp_path / "bom.txt"
    p.write_text("\ufeff1.0 0 0 0 0 0 0 1\n", encoding="utf-8")
    assert load_pose_file(p).stamps_ns.tolist() == [1_000_000_000]


# --------------------------------------------------------------------------- init


@pytest.mark.parametrize("threads", [-1, 0, 2.5, True, "2", 10**30])
def test_bad_cpu_max_num_threads_is_refused(threads):
    with pytest.raises(ValueError, match="cpu_max_num_threads must be an integer from 1"):
        ndtom_ti.init("cpu", cpu_max_num_threads=threads)


# --------------------------------------------------------------------------- Layout


def test_layout_takes_a_list_and_is_hashable():
    lay = Layout(l1=[128, 128, 16])
    assert lay == Layout() and hash(lay) == hash(Layout()) and lay.l1 == (128, 128, 16)


@pytest.mark.parametrize(
    "kw,exc,message",
    [
        ({"l1": (128, 128)}, ValueError, "three sizes"),
        ({"l1": 128}, ValueError, "three sizes"),
        ({"l1": (128.0, 128, 16)}, TypeError, "integer"),
        ({"l2": "32"}, TypeError, "integer"),
        ({"leaf": 6}, ValueError, "power of two"),
        ({"l1": (0, 1, 1)}, ValueError, "positive"),
    ],
)
def test_bad_layout_is_refused_when_made(kw, exc, message):
    with pytest.raises(exc, match=message):
        Layout(**kw)


def test_layout_too_large_for_memory_is_refused_and_maps_still_work():
    with pytest.raises(ValueError, match=r"needs .* GiB for its top-level pointer arrays.*smaller l1"):
        NdtOmMap(0.2, layout=Layout(l1=HUGE_L1))
    assert small_map().known_cell_count() > 0


def test_refused_layouts_leave_a_fresh_process_usable():
    """In a fresh process init()'s storage is still unused: a refused layout must not take it
    away half built (a Taichi field builder left open broke every later map)."""
    code = textwrap.dedent(
        f"""
        import numpy as np, ndtom_ti
        from ndtom_ti import Layout, NdtOmMap
        ndtom_ti.init("cpu")
        for make in (lambda: Layout(l1=(128, 128)), lambda: NdtOmMap(0.2, layout=Layout(l1={HUGE_L1}))):
            try:
                make()
            except ValueError:
                pass
        m = NdtOmMap(0.2)
        print("used", m.insert_scan(np.random.default_rng(0).uniform(-3, 3, (500, 3)), np.eye(4)).points_used)
        """
    )
    out = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and "used 500" in out.stdout, out.stderr[-2000:]


# --------------------------------------------------------------------------- map API


@pytest.mark.parametrize("factor", [float("inf"), float("nan"), 10**400])
def test_coarsen_by_a_non_finite_factor_is_refused(factor):
    m = small_map()
    with pytest.raises(ValueError, match="factor"):
        m.coarsen(factor)
    with pytest.raises(ValueError, match="factor"):
        m.snapshot().coarsen(factor)


@pytest.mark.parametrize("point", [[np.nan, 0.0, 0.0], [0.0, 1e300, 0.0], [0.0, 0.0, -np.inf]])
def test_cell_index_of_a_point_out_of_int64_is_refused(point):
    m = NdtOmMap(0.2)
    with pytest.raises(ValueError, match="finite, with cell indices that fit int64"):
        m.cell_index([[0.1, 0.1, 0.1], point])
    assert m.cell_index([[0.1, -0.1, 5.0]]).tolist() == [[0, -1, 25]]


def test_logodds_at_one_cell_answers_as_occupancy_of_one_point():
    m = small_map()
    cell = m.known_cells()["index"][0]
    lo = m.logodds_at(cell)
    assert isinstance(lo, float) and isinstance(m.occupancy(m.cell_center(cell)), float)
    assert lo == m.logodds_at(cell[None])[0] != 0.0
    assert m.snapshot().logodds_at(cell) == lo


def test_from_snapshot_of_no_snapshot_is_a_type_error():
    with pytest.raises(TypeError, match="from_snapshot takes a MapSnapshot"):
        NdtOmMap.from_snapshot(None)  # type: ignore[arg-type]


@pytest.mark.parametrize("name", ["map.bt", "map.PLY", "map.npz", "grid.yaml"])
def test_save_under_an_export_suffix_points_to_export(tmp_path, name):
    m = small_map()
    with pytest.raises(ValueError, match=r"export format.*ndtom_ti\.export\.export_file\(m, "):
        m.save(tmp_path / name)
    with pytest.raises(ValueError, match=r"export format.*s\.export\("):
        m.snapshot().save(tmp_path / name)
    assert not (tmp_path / name).exists()
    assert isinstance(MapSnapshot.load(m.save(tmp_path / "map.ndtom")), MapSnapshot)


@pytest.mark.parametrize("rotation", [[0.1, 0.2, 0.3], 1.0, np.eye(4)])
def test_make_transform_of_no_rotation_is_refused(rotation):
    with pytest.raises(ValueError, match="rotation must be a 3x3 rotation matrix or a quaternion"):
        make_transform([0, 0, 0], rotation)


def test_make_transform_of_no_translation_is_refused():
    with pytest.raises(ValueError, match="translation must be 3 numbers"):
        make_transform(5.0, [0, 0, 0, 1])
    np.testing.assert_array_equal(make_transform([1, 2, 3], np.eye(3))[:3, 3], [1, 2, 3])


def test_taichi_started_again_by_other_code_is_refused_not_a_crash():
    """ti.init or ti.reset by other code frees the maps' fields: using a map, or making one,
    then raises RuntimeError (a kernel on the freed trees crashed the process)."""
    code = textwrap.dedent(
        """
        import numpy as np, taichi as ti, ndtom_ti
        m = ndtom_ti.NdtOmMap(0.2)
        pts = np.random.default_rng(0).normal(size=(2000, 3)) + [4, 0, 0]
        m.insert_scan(pts, np.eye(4))
        ti.init(ti.cpu)
        for use in (lambda: m.insert_scan(pts, np.eye(4)), m.gaussians, lambda: ndtom_ti.NdtOmMap(0.2)):
            try:
                use()
            except RuntimeError as e:
                assert "Taichi was initialised again" in str(e), e
            else:
                raise SystemExit("no error")
        print("refused")
        """
    )
    out = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and "refused" in out.stdout, out.stdout + out.stderr


def test_masked_points_are_dropped_as_not_finite():
    m = small_map()
    pts = np.ma.masked_array(np.random.default_rng(1).uniform(-3, 3, (400, 3)), mask=False)
    pts[:10, 1] = np.ma.masked
    rep = m.insert_scan(pts, np.eye(4))
    assert rep.dropped_nonfinite == 10 and rep.points_used == 390


def test_ragged_points_are_a_type_error_in_insert_scan_as_in_map_scans():
    """A list of rows of unequal length is not an (N, 3) array: insert_scan said numpy's
    own ValueError ("inhomogeneous shape"), map_scans a TypeError."""
    ragged = [[1.0, 2.0, 3.0], [1.0, 2.0]]
    with NdtOmMap(0.2) as m:
        with pytest.raises(TypeError, match=r"points must be a real numeric \(N, 3\) array"):
            m.insert_scan(ragged, np.eye(4))
        assert m.scans_inserted == 0
