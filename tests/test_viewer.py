"""The viewer without a browser: geometry, GUI logic (setting a control's ``.value`` fires
its callback as a click would), live mapping, and bad input of ``view_command``.

Maps are tiny: the demo room (``ndtom_ti.demo``: walls, floor, boxes, one box taken away
after scan 10) at 0.5 m, 12 scans of 5.7k points: about 1,600 Gaussians.
"""

from __future__ import annotations

import importlib
import inspect
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from ndtom_ti.viewer import geometry as geo

from ndtom_ti import NdtOmMap, NoFreeSlotError
from ndtom_ti.demo import make_scans

RES = 0.5


@pytest.fixture(scope="module")
def maps(room_scans):
    """(NDT-OM map, Recursive NDT map) of the same scans."""
    m = NdtOmMap(RES)
    r = NdtOmMap(RES, occupancy=False)
    for s in room_scans:
        m.insert_scan(s.points, s.T_world_sensor)
        r.insert_scan(s.points, s.T_world_sensor)
    yield m, r
    del m, r


@pytest.fixture
def make_viewer():
    pytest.importorskip("viser", reason="the viewer needs viser: pip install ndtom_ti[viewer]")
    from ndtom_ti.viewer import MapViewer

    made = []

    def make(*args, **kwargs):
        kwargs.setdefault("verbose", False)
        kwargs.setdefault("environment_map", False)
        v = MapViewer(*args, **kwargs)
        made.append(v)
        return v

    yield make
    for v in made:
        v.close()


def _keys(index):
    return set(map(tuple, np.asarray(index).tolist()))


# ---------------------------------------------------------------------------- geometry


def test_ellipsoids_reproduce_the_covariances(rng):
    A = rng.normal(size=(200, 3, 3))
    cov = A @ np.swapaxes(A, 1, 2) + 1e-3 * np.eye(3)
    wxyz, scales = geo.ellipsoid_instances(cov)
    assert wxyz.shape == (200, 4) and scales.shape == (200, 3)
    assert wxyz.dtype == np.float32 and scales.dtype == np.float32
    w, x, y, z = wxyz.astype(np.float64).T
    R = np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        1,
    )
    assert np.allclose(np.linalg.det(R), 1.0, atol=1e-5)  # proper rotations (det<0 flipped)
    rebuilt = R @ (scales.astype(np.float64)[:, :, None] ** 2 * np.swapaxes(R, 1, 2))
    assert np.allclose(rebuilt, cov, rtol=1e-4, atol=1e-5)
    # a flat Gaussian (a wall) keeps a visible thickness
    _, s = geo.ellipsoid_instances(np.diag([1.0, 1.0, 0.0])[None], min_sigma=0.01)
    assert np.isclose(s.min(), 0.01)


def test_icosphere_is_closed_unit_and_outward():
    V, F = geo.icosphere(1)
    assert V.shape == (42, 3) and F.shape == (80, 3)
    assert np.allclose(np.linalg.norm(V, axis=1), 1.0, atol=1e-6)
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    normals = np.cross(b - a, c - a)
    assert (np.einsum("ij,ij->i", normals, a + b + c) > 0).all()
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all()  # closed surface


def test_colour_maps_and_caps():
    c = geo.occupancy_colors(np.array([0.0, 0.5, 1.0])).astype(int)
    assert c[0, 2] > c[0, 0]  # free: blue
    assert c[1, 1] > max(c[1, 0], c[1, 2])  # unknown: green
    assert c[2, 0] > 2 * max(c[2, 1], c[2, 2])  # occupied: red
    t = geo.turbo(np.array([0.1, 0.9])).astype(int)
    assert t[0, 2] > t[0, 0] and t[1, 0] > t[1, 2]  # blue low, red high
    assert len(geo.cap_rows(10, 50)) == 10
    rows = geo.cap_rows(1000, 50)
    assert len(rows) == 50 and rows[0] == 0 and rows[-1] == 999
    idx = np.array([[0, 0, 0], [-1, 0, 0], [0, -1, 0], [0, 0, -1], [5, -7, 3]])
    assert len(np.unique(geo.cell_keys(idx))) == 5


def _flat(n, rng, z=0.0, half=10.0, normal_z=True):
    """n flat Gaussians (normal along z, or along x) spread over a square at height z."""
    mean = np.c_[rng.uniform(-half, half, (n, 2)), np.full(n, z)]
    d = [0.04, 0.04, 1e-4] if normal_z else [1e-4, 0.04, 0.04]
    return mean, np.tile(np.diag(d), (n, 1, 1))


def test_bulk_sphere_frames_the_bulk_not_a_few_far_cells(rng):
    # outdoors: a ground disc of 20 m, and a few cells 150-190 m away (a lidar's far returns)
    near = np.c_[rng.uniform(-20, 20, (5000, 2)), rng.normal(0, 0.2, 5000)]
    far = np.c_[rng.uniform(150, 190, (60, 2)), np.zeros(60)]
    center, radius = geo.bulk_sphere(np.r_[near, far])
    assert np.linalg.norm(center[:2]) < 3.0 and 15.0 < radius < 30.0, (center, radius)
    # an evenly filled room: its middle, and most of it (the view fits the sphere's width)
    room = rng.uniform([0, 0, 0], [12, 8, 3], (5000, 3))
    center, radius = geo.bulk_sphere(room)
    assert np.allclose(center, [6, 4, 1.5], atol=0.3) and radius >= 0.7 * np.linalg.norm([12, 8, 3]) / 2


def test_ceiling_height_finds_a_roof_not_the_sky(rng):
    floor = _flat(3000, rng, z=0.0)
    roof = _flat(3000, rng, z=4.0)
    wall = _flat(800, rng, z=2.0, normal_z=False)
    wall[0][:, 0] = 10.0
    wall[0][:, 2] = rng.uniform(0, 4, 800)
    mean, cov = (np.r_[a, b, c] for a, b, c in zip(floor, roof, wall))
    h = geo.ceiling_height(mean, cov, 0.2)
    assert h is not None and 3.0 < h < 4.0, h
    # outdoors: sloping ground (6 m over the map) and walls, no roof: no clip
    ground = _flat(3000, rng, z=0.0)
    ground[0][:, 2] = 0.3 * ground[0][:, 0]
    mean, cov = (np.r_[a, b] for a, b in zip(ground, wall))
    assert geo.ceiling_height(mean, cov, 0.2) is None


def test_nothing_non_finite_is_drawn(maps, make_viewer):
    assert geo.finite_rows(np.array([[0, 0, 0], [np.nan, 0, 0], [0, np.inf, 0]], float)).tolist() == [1, 0, 0]
    assert geo.finite_rows(np.zeros((0, 3))).shape == (0,)
    m, _ = maps
    v = make_viewer(m)
    v.set_trajectory([[0, 0, 1], [np.nan, 0, 1], [1, 0, 1]])
    v.set_scan([[1, 2, 0.5], [np.nan, np.nan, np.nan], [2, 2, 0.5]])
    v.refresh()
    scene_arrays = [
        v.scene.nodes["scan"].points,
        v.scene.nodes["trajectory"].points,
        v.scene.nodes["gaussians"].batched_positions,
    ]
    assert v.drawn["scan"] == 2 and all(np.isfinite(np.asarray(a)).all() for a in scene_arrays)


# ---------------------------------------------------------------------------- GUI logic


def test_viewer_draws_the_maps_gaussians_as_ellipsoids(maps, make_viewer):
    m, _ = maps
    v = make_viewer(m)
    g = m.gaussians(min_probability=0.5)
    assert v.drawn["gaussians"] == len(g["n"]) > 500
    assert v.drawn["geometry"] == "ellipsoids"
    h = v.scene.nodes["gaussians"]
    assert np.allclose(h.batched_positions, g["mean"].astype(np.float32))
    # coloured by height by default, on a scale fitted to the map's heights
    assert v.controls.color_mode.value == "height"
    zr = geo.height_range(g["mean"][:, 2])
    assert v.drawn["zrange"] == zr and zr[0] >= g["mean"][:, 2].min() and zr[1] <= g["mean"][:, 2].max()
    assert np.array_equal(h.batched_colors, geo.height_colors(g["mean"][:, 2], zr))
    assert len(np.unique(h.batched_colors, axis=0)) > 20  # not one colour for the whole map
    assert f"{abs(zr[0]):.2f} m" in v.controls.legend.content and f"{zr[1]:.2f} m" in v.controls.legend.content
    assert v.layer_visible("gaussians")
    assert v.url.startswith("http://127.0.0.1:") and v.port == v.server.get_port() > 0
    assert "Gaussians" in v.controls.stats.content and "Level of detail" in v.controls.stats.content


def test_threshold_slider_changes_the_number_of_gaussians(maps, make_viewer):
    m, _ = maps
    v = make_viewer(m)
    before = v.drawn["gaussians"]
    v.controls.threshold.value = 0.85
    expected = len(m.gaussians(min_probability=0.85)["n"])
    assert v.drawn["gaussians"] == expected < before
    assert len(v.scene.nodes["gaussians"].batched_positions) == expected
    v.controls.threshold.value = 0.5
    assert v.drawn["gaussians"] == before


def test_resolution_dropdown_switches_to_coarsened_maps(maps, make_viewer):
    m, _ = maps
    v = make_viewer(m, cache_size=2)
    opts = v.controls.resolution.options
    assert opts == ("0.5 m (native)", "1 m (2x)", "1.5 m (3x)", "2 m (4x)", "auto: 0.5 m drawn")
    assert v.controls.resolution.value == opts[-1]  # auto by default: it says what it draws
    v.controls.resolution.value = opts[1]
    assert v.level == 2 and v.drawn["resolution"] == 2 * RES
    c2 = m.coarsen(2)
    assert v.drawn["gaussians"] == len(c2.gaussians(min_probability=0.5)["n"]) < len(m)
    del c2
    for o in opts[2:4]:
        v.controls.resolution.value = o
        assert len(v.levels) <= 2  # old levels are dropped: the process holds at most 8 maps
    assert v.level == 4
    v.controls.resolution.value = opts[0]
    assert v.level == 1 and v.drawn["gaussians"] == len(m)


def test_the_resolution_chosen_is_drawn_and_auto_says_what_it_draws(maps, make_viewer):
    from viser import GaussianSplatHandle

    m, _ = maps
    n = len(m.gaussians(min_probability=0.5)["n"])
    v = make_viewer(m, max_ellipsoids=50, max_splats=100, max_chosen=1000)
    res = v.controls.resolution
    # auto: a coarser level that fits, named in the selector (and the geometry it draws)
    assert v.level >= 2 and res.value == f"auto: {v.drawn['resolution']:g} m drawn" == res.options[-1]
    assert v.controls.geometry.value == f"auto: {v.drawn['geometry']}"
    # the native level chosen by hand: drawn as chosen (splats), up to max_chosen, with a warning
    res.value = res.options[2]  # 3x: fewer than max_chosen, more than max_splats
    n3 = len(m.coarsen(3).gaussians(min_probability=0.5)["n"])
    assert 100 < n3 <= 1000, n3
    assert v.level == 3 and v.drawn["gaussians"] == n3 and v.drawn["geometry"] == "splats"
    assert res.value == res.options[2] and res.options[-1] == "auto"  # the selector shows what is drawn
    assert isinstance(v.scene.nodes["gaussians"], GaussianSplatHandle) and "respond slowly" in v.controls.notice.content
    # every splat at least 0.15 of a cell thick: line-thin Gaussians (a lidar's rings) stay visible from afar
    cov = np.asarray(v.scene.nodes["gaussians"].covariances, np.float64)
    assert np.linalg.eigvalsh(cov).min() >= 0.99 * (0.15 * 3 * RES) ** 2
    assert not v.controls.redraw.visible
    # past max_chosen: the part around where the view looks
    res.value = res.options[0]
    assert v.level == 1 and v.drawn["gaussians"] == 1000 < n and v.controls.redraw.visible
    assert "nearest the view's centre" in v.controls.notice.content
    drawn = np.asarray(v.scene.nodes["gaussians"].centers)
    center = v.first_view.center  # no page connected: the view looks where the first view does
    g = m.gaussians(min_probability=0.5)
    d_all = np.sort(np.linalg.norm(g["mean"] - center, axis=1))
    assert np.linalg.norm(drawn - center, axis=1).max() <= d_all[999] + 1e-3
    # "Gaussians as" splats / ellipsoids on a chosen level: what the statistics say is drawn
    v.controls.geometry.value = "ellipsoids"
    assert v.drawn["geometry"] == "ellipsoids" and "drawn as ellipsoids" in v.controls.stats.content


def test_layer_toggles_set_visibility_and_compute_on_demand(maps, make_viewer):
    m, _ = maps
    v = make_viewer(m)
    boxes = v.controls.layers
    assert "free" in v.drawn["skipped"] and not v.layer_visible("free")  # free cells: on demand
    boxes["gaussians"].value = False
    assert not v.layer_visible("gaussians")
    boxes["gaussians"].value = True
    assert v.layer_visible("gaussians")
    boxes["free"].value = True
    k = m.known_cells()
    assert v.drawn["free"] == int((k["p_occ"] < 0.5).sum()) > 0 and v.layer_visible("free")
    boxes["occupied"].value = True
    assert v.drawn["occupied"] == int((k["p_occ"] > 0.5).sum()) and v.layer_visible("occupied")
    boxes["free"].value = False
    assert not v.layer_visible("free")


def test_free_cells_are_capped_and_the_cap_is_shown(maps, make_viewer):
    m, _ = maps
    v = make_viewer(m, max_free_cells=50)
    v.controls.layers["free"].value = True
    assert v.drawn["free"] == 50 < v.drawn["free_total"]
    assert f"50 of {v.drawn['free_total']:,} drawn (cap 50)" in v.controls.stats.content


def test_colour_mode_geometry_and_level_of_detail(maps, make_viewer):
    m, _ = maps
    from viser import GaussianSplatHandle

    v = make_viewer(m)
    height_colors = np.array(v.scene.nodes["gaussians"].batched_colors)
    v.controls.color_mode.value = "occupancy"  # one click away
    g = m.gaussians(min_probability=0.5)
    # the scale spans what is drawn (threshold .. highest p): the surest red, the least sure green
    prange = (0.5, float(g["p_occ"].max()))
    assert v.drawn["prange"] == prange
    expected = geo.occupancy_colors(g["p_occ"], prange)
    assert np.array_equal(v.scene.nodes["gaussians"].batched_colors, expected)
    assert not np.array_equal(expected, height_colors)
    surest, least = np.argmax(g["p_occ"]), np.argmin(g["p_occ"])
    assert tuple(expected[surest]) == (200, 20, 30) and expected[least][1] > 150 and expected[least][0] < 100
    at_top = np.mean(g["p_occ"] >= prange[1] - 1e-3)
    legend = v.controls.legend.content
    assert "occupancy probability" in legend and "height of" not in legend
    assert f"{100 * at_top:.0f}% of them at {prange[1]:.2f}" in legend and "least sure" in legend
    v.controls.geometry.value = "splats"
    assert isinstance(v.scene.nodes["gaussians"], GaussianSplatHandle) and v.drawn["geometry"] == "splats"

    # auto: splats past max_ellipsoids; a coarser level past max_splats, said on screen
    lod = make_viewer(m, max_ellipsoids=100, max_splats=len(m) - 1)
    assert lod.drawn["geometry"] == "splats" and lod.level >= 2
    assert lod.drawn["gaussians"] < len(m)
    assert "coarser level" in lod.controls.stats.content and "exceed" in lod.controls.stats.content


def test_conflicting_cells_layer(maps, make_viewer):
    m, r = maps
    v = make_viewer(m, compare=r)
    expected = _keys(r.gaussians(min_probability=0.5)["index"]) - _keys(m.gaussians(min_probability=0.5)["index"])
    assert v.drawn["conflicts"] == len(expected) > 0  # the box taken away after scan 10
    h = v.scene.nodes["conflicts"]
    assert tuple(np.asarray(h.batched_colors).reshape(-1, 3)[0]) == geo.CONFLICT_RGB
    assert f"{len(expected):,} conflicting cells" in v.controls.stats.content
    # each marker at least about a cell wide, flat Gaussians too: a few among thousands stay findable
    assert (np.asarray(h.batched_scales) >= 0.5 * RES).all()
    v.controls.layers["conflicts"].value = False
    assert not v.layer_visible("conflicts")
    alone = make_viewer(m)
    assert alone.drawn["conflicts"] == 0 and alone.controls.layers["conflicts"].disabled


def test_live_mapping_pause_step_play(room_scans, maps, make_viewer):
    m_ref, r_ref = maps
    v = make_viewer()
    lm = v.live(room_scans, NdtOmMap(RES), compare=True, refresh_interval=0.05)
    c = v.controls
    time.sleep(0.3)
    assert lm.scans_done == 0 and not lm.playing  # starts paused
    c.step.value = True  # a click
    assert lm.wait_scans(1, timeout=20) and lm.scans_done == 1
    c.play.value = True
    assert lm.wait(timeout=60) and lm.error is None
    assert lm.scans_done == len(room_scans) and len(lm.times_ms) == len(room_scans) == len(lm.compare_times_ms)
    time.sleep(0.5)  # the drawing thread catches up
    for _ in range(100):
        if c.scan.content.endswith(f" {len(room_scans)} / {len(room_scans)}") and v.drawn.get("trajectory") == len(
            room_scans
        ):
            break
        time.sleep(0.05)
    assert c.scan.content == f"**Scans inserted**: {len(room_scans)} / {len(room_scans)}"
    assert v.drawn["trajectory"] == len(room_scans) and v.drawn["scan"] > 1000
    # every scan, or all but the first where it took more than twice the slowest later one
    # (the chart's rule for a compile: 20-30 ms against 2-3 ms, seen on a busy machine, is so too)
    from ndtom_ti.viewer.livepanel import chart_series

    charted = chart_series(lm.times_ms, lm.compare_times_ms)[0][0]
    assert len(c.chart.data[0]) == len(charted) >= len(room_scans) - 1
    # the same map as one built directly (known answer), and its comparison map
    with v.map_lock:  # the drawing thread may be reading the maps
        assert _keys(lm.map.gaussians()["index"]) == _keys(m_ref.gaussians()["index"])
        assert _keys(lm.compare.gaussians()["index"]) == _keys(r_ref.gaussians()["index"])
    assert v.drawn["conflicts"] > 0 and "Done" in c.live_status.content
    lm.stop()


def test_time_per_scan_chart_leaves_out_the_first_scans_compile():
    from ndtom_ti.viewer.livepanel import chart_series

    (x, ys, y2), note = chart_series([5300.0, 40.0, 55.0, 48.0], [900.0, 20.0, 30.0])
    assert x.tolist() == [2, 3] and ys.tolist() == [40.0, 55.0] and y2.tolist() == [20.0, 30.0]  # no NaN
    assert note == "Scan 1 took 5,300 ms (compiling the kernels): not charted."
    (x, ys), note = chart_series([60.0, 40.0, 55.0])  # no spike: all of it
    assert x.tolist() == [1, 2, 3] and ys.tolist() == [60.0, 40.0, 55.0] and note == ""
    assert chart_series([5300.0])[0][1].tolist() == [5300.0]


def test_live_pause_stops_mapping(room_scans, make_viewer):
    v = make_viewer()
    lm = v.live(room_scans, NdtOmMap(RES), rate_hz=20.0)
    lm.play()
    assert lm.wait_scans(2, timeout=20)
    v.controls.pause.value = True
    time.sleep(0.2)
    n = lm.scans_done
    time.sleep(0.4)
    assert lm.scans_done == n < len(room_scans) and not lm.finished
    lm.stop()


def test_slow_drawing_does_not_stall_mapping(room_scans, make_viewer, monkeypatch):
    v = make_viewer()
    gate = threading.Event()  # a redraw that cannot finish until mapping is done
    started = threading.Event()
    real = v.refresh

    def stuck_refresh():
        started.set()
        gate.wait(60)
        real()

    lm = v.live(room_scans, NdtOmMap(RES), refresh_interval=0.05)
    monkeypatch.setattr(v, "refresh", stuck_refresh)
    lm.play()
    # mapping reaches the end while the first redraw is still stuck
    assert lm.wait(timeout=60) and started.is_set() and not gate.is_set()
    assert lm.scans_done == len(room_scans)
    gate.set()
    lm.stop()


def test_live_mapping_reports_bad_scans(make_viewer):
    v = make_viewer()
    good = make_scans(2, rings=4, per_ring=60)
    lm = v.live([good[0], "not a scan", good[1]], NdtOmMap(RES), refresh_interval=0.05)
    lm.play()
    assert lm.wait(timeout=20)
    assert lm.scans_done == 1 and "scan 2 could not be inserted: each scan must have .points" in lm.error
    time.sleep(0.3)
    assert "Stopped" in v.controls.live_status.content


def test_show_and_defaults_are_loopback(maps, make_viewer, capsys):
    from ndtom_ti.viewer import MapViewer, show
    from ndtom_ti.viewer.cli import view_command

    for fn in (show, MapViewer, view_command):
        assert inspect.signature(fn).parameters["host"].default == "127.0.0.1"
    m, _ = maps
    v = show(m, environment_map=False)
    try:
        assert v.server.get_port() == v.port > 0
        assert v.url in capsys.readouterr().out
        with socket.create_connection(("127.0.0.1", v.port), timeout=5):
            pass
    finally:
        v.close()


# ---------------------------------------------------------------------------- bad input


@pytest.fixture(scope="module")
def map_file(maps, tmp_path_factory):
    return maps[0].save(tmp_path_factory.mktemp("viewer") / "room.ndtom")


def test_view_missing_map_file(tmp_path, capsys):
    from ndtom_ti.viewer.cli import view_command

    assert view_command(tmp_path / "nope.ndtom", "127.0.0.1", 0, None) == 2
    err = capsys.readouterr().err
    assert "nope.ndtom" in err and "does not exist" in err
    assert view_command(tmp_path, "127.0.0.1", 0, None) == 2
    assert "folder" in capsys.readouterr().err


def test_view_corrupt_map_file(map_file, tmp_path, capsys):
    pytest.importorskip("viser")
    from ndtom_ti.viewer.cli import view_command

    data = map_file.read_bytes()
    truncated = tmp_path / "truncated.ndtom"
    truncated.write_bytes(data[: len(data) // 2])
    garbage = tmp_path / "garbage.ndtom"
    garbage.write_bytes(b"this is not a map file\n" * 10)
    flipped = tmp_path / "flipped.ndtom"
    b = bytearray(data)
    b[-10] ^= 0xFF
    flipped.write_bytes(bytes(b))
    for bad in (truncated, garbage, flipped):
        assert view_command(bad, "127.0.0.1", 0, None) == 2
        err = capsys.readouterr().err
        assert f"cannot read map file {bad}" in err and "Traceback" not in err


def test_view_port_in_use_uses_the_next_and_prints_it(map_file, monkeypatch, capsys):
    pytest.importorskip("viser")
    from ndtom_ti.viewer import MapViewer, cli

    busy = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    busy.bind(("127.0.0.1", 0))
    busy.listen(1)
    port = busy.getsockname()[1]
    seen = {}

    def block(viewer):
        seen["port"] = viewer.port
        with socket.create_connection(("127.0.0.1", viewer.port), timeout=5):
            seen["listening"] = True

    monkeypatch.setattr(MapViewer, "wait", block)  # the command serves until Ctrl-C: here, a connection
    try:
        assert cli.view_command(map_file, "127.0.0.1", port, None) == 0
    finally:
        busy.close()
    out = capsys.readouterr().out
    assert seen["listening"] and seen["port"] != port
    assert f"port {port} is in use" in out and f"http://127.0.0.1:{seen['port']}" in out


def test_view_with_no_free_port_up_to_65535_is_a_clear_error(map_file, capsys):
    """viser looks for the next free port itself and raised in a thread past 65535 (the
    command then hung without a viewer): the top port busy is a user error now."""
    pytest.importorskip("viser")
    from ndtom_ti.viewer.cli import view_command

    busy = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        busy.bind(("127.0.0.1", 65535))
    except OSError:
        busy.close()
        pytest.skip("port 65535 is taken on this machine")
    busy.listen(1)
    try:
        assert view_command(map_file, "127.0.0.1", 65535, None) == 2
    finally:
        busy.close()
    err = capsys.readouterr().err
    assert "every port above it up to 65535" in err and "choose another port" in err and "Traceback" not in err


def test_view_refuses_a_bad_port_or_page_folder_before_loading_the_map(map_file, capsys):
    pytest.importorskip("viser")
    from ndtom_ti.viewer.cli import view_command

    assert view_command(map_file, "127.0.0.1", 70000, None) == 2
    out, err = capsys.readouterr()
    assert "port must be in [0, 65535], got 70000" in err and "Loading" not in out
    if sys.platform.startswith("linux"):  # /proc takes no new file
        assert view_command(map_file, "127.0.0.1", 0, "/proc/page.html") == 2
        out, err = capsys.readouterr()
        assert "cannot write /proc/page.html: folder /proc" in err and "Loading" not in out


def test_view_host_that_cannot_be_listened_on(map_file, capsys):
    pytest.importorskip("viser")
    from ndtom_ti.viewer.cli import view_command

    assert view_command(map_file, "192.0.2.1", 0, None) == 2  # TEST-NET-1: not this machine
    assert "cannot listen on host '192.0.2.1'" in capsys.readouterr().err


def test_view_html_snapshot(map_file, tmp_path, capsys):
    pytest.importorskip("viser")
    from ndtom_ti.viewer.cli import view_command

    out = tmp_path / "snapshot.html"
    assert view_command(map_file, "127.0.0.1", 0, out) == 0
    text = out.read_text()
    assert text.lstrip().lower().startswith("<!doctype html") and len(text) > 100_000
    # the page carries the panel's legend and statistics, laid over the scene
    panel = text[text.index('<details id="ndtom-panel"') :]
    assert "Colour: height of the Gaussian" in panel and "<b>Gaussians</b>:" in panel and "</details>" in panel
    assert f"Wrote {out}" in capsys.readouterr().out
    assert view_command(map_file, "127.0.0.1", 0, tmp_path / "no" / "such" / "s.html") == 2
    assert "does not exist" in capsys.readouterr().err


def test_viewer_without_viser(maps, map_file, monkeypatch, capsys):
    import ndtom_ti

    monkeypatch.setattr(ndtom_ti, "viewer", sys.modules["ndtom_ti.viewer"])  # restored afterwards
    monkeypatch.setitem(sys.modules, "viser", None)  # `import viser` raises ImportError
    for name in [n for n in sys.modules if n == "ndtom_ti.viewer" or n.startswith("ndtom_ti.viewer.")]:
        monkeypatch.delitem(sys.modules, name)
    viewer = importlib.import_module("ndtom_ti.viewer")  # importing needs no viser
    cli = importlib.import_module("ndtom_ti.viewer.cli")
    # The hint installs the extra from this repository (the package is not on PyPI).
    with pytest.raises(viewer.ViewerNotInstalledError, match=r'pip install -e ".*\[viewer\]"'):
        viewer.MapViewer(maps[0])
    assert cli.view_command(map_file, "127.0.0.1", 0, None) == 1
    err = capsys.readouterr().err
    assert "[viewer]\"" in err and "ndtom_ti[viewer]" not in err


def test_viewer_keeps_within_the_map_limit(maps, make_viewer):
    """Coarsened levels are dropped: many switches never exhaust the 8 map slots."""
    m, r = maps
    v = make_viewer(m, compare=r, cache_size=2)
    opts = v.controls.resolution.options
    for _ in range(3):
        for o in opts:
            v.controls.resolution.value = o
    assert len(v.levels) <= 2
    extra = [NdtOmMap(RES) for _ in range(3)]  # room is left for others
    del extra


def test_map_lock_serialises_concurrent_refreshes(maps, make_viewer):
    m, r = maps
    v = make_viewer(m, compare=r)
    errors = []

    def hammer(vals):
        try:
            for val in vals:
                v.controls.threshold.value = val
        except Exception as exc:  # noqa: BLE001
            errors.append(exc)

    ts = [threading.Thread(target=hammer, args=([0.5, 0.7, 0.9, 0.6] if i else [0.55, 0.8, 0.65],)) for i in range(2)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert not errors
    v.refresh()
    assert v.drawn["gaussians"] == len(m.gaussians(min_probability=float(v.controls.threshold.value))["n"])


def test_live_mapping_in_a_fresh_process():
    """Taichi lets only the main thread build its default field tree, at the first kernel
    launch of a process: the viewer launches one there before mapping in a worker thread."""
    pytest.importorskip("viser")
    script = (
        "import ndtom_ti, sys\n"
        "ndtom_ti.init('cpu')\n"
        "from ndtom_ti.demo import make_scans\n"
        "from ndtom_ti.viewer import MapViewer\n"
        "v = MapViewer(verbose=False, environment_map=False)\n"
        "lm = v.live(make_scans(3, rings=4, per_ring=60), ndtom_ti.NdtOmMap(0.5), compare=True, play=True)\n"
        "ok = lm.wait(120)\n"
        "print('RESULT', lm.scans_done, lm.error)\n"
        "v.close()\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, check=False)
    assert "RESULT 3 None" in out.stdout, out.stdout[-2000:] + out.stderr[-2000:]


def test_coarser_levels_need_no_map_slot(maps, make_viewer):
    """Levels are snapshots coarsened in numpy: with every map slot taken they are still
    made, and equal the map's own coarsen()."""
    m, r = maps
    v = make_viewer(m, compare=r)
    hog = []
    with pytest.raises(NoFreeSlotError, match="maps are open already"):
        while True:
            hog.append(NdtOmMap(RES))
    v.controls.resolution.value = v.controls.resolution.options[1]
    assert v.level == 2 and "could not be made" not in v.controls.stats.content
    v.controls.layers["conflicts"].value = True
    v.refresh()
    assert "could not be made" not in v.controls.stats.content
    hog.pop().close()  # a slot for the reference
    with m.coarsen(2) as c2:
        assert v.drawn["gaussians"] == len(c2.gaussians(min_probability=float(v.controls.threshold.value))["n"])
    for h in hog:
        h.close()


# ---------------------------------------------------------------------------- what a static map offers


def test_layers_are_offered_only_when_the_map_has_them(maps, make_viewer, room_scans):
    m, r = maps
    v = make_viewer(m)
    boxes = v.controls.layers
    # a map file holds no trajectory, no latest scan and no comparison map
    assert not boxes["trajectory"].visible and not boxes["scan"].visible and not boxes["conflicts"].visible
    assert not v.controls.point_size.visible  # it sizes the latest scan's points only
    assert boxes["gaussians"].visible and boxes["occupied"].visible and boxes["free"].visible
    assert not boxes["free"].value  # free cells: off until ticked
    assert "trajectory" not in v.controls.legend.content and "conflicting" not in v.controls.legend.content
    # with a comparison map: conflicting cells offered
    assert make_viewer(m, compare=r).controls.layers["conflicts"].visible
    # live mapping: the trajectory and latest scan (and the point size) appear
    lv = make_viewer()
    lm = lv.live(room_scans[:2], NdtOmMap(RES), refresh_interval=0.05)
    lm.step(2)
    assert lm.wait_scans(2, timeout=30)
    for _ in range(100):
        if lv.controls.layers["trajectory"].visible:
            break
        time.sleep(0.05)
    assert lv.controls.layers["trajectory"].visible and lv.controls.layers["scan"].visible
    assert lv.controls.point_size.visible
    lm.stop()


def test_free_cells_are_translucent_boxes(maps, make_viewer):
    from ndtom_ti.viewer.scene import FREE_OPACITY

    m, _ = maps
    v = make_viewer(m)
    v.controls.layers["free"].value = True
    h = v.scene.nodes["free"]
    assert 0.0 < h.opacity == FREE_OPACITY <= 0.3
    assert len(h.batched_positions) == v.drawn["free"] > 0
    assert "free cells" in v.controls.legend.content


def test_height_clip_hides_what_is_above_the_band(maps, make_viewer):
    m, _ = maps
    v = make_viewer(m)
    g = m.gaussians(min_probability=0.5)
    z = g["mean"][:, 2]
    zlo, zhi = v.controls.zlimits
    assert zlo <= z.min() and zhi >= z.max()
    assert tuple(v.controls.zclip.value) == (zlo, zhi) and v.drawn["clip"] is None
    v.controls.zclip.value = (zlo, 1.0)  # below the room's ceiling and the walls' tops
    expected = int(((z >= zlo) & (z <= 1.0)).sum())
    assert v.drawn["gaussians"] == expected < len(z)
    assert (np.asarray(v.scene.nodes["gaussians"].batched_positions)[:, 2] <= 1.0).all()
    # the colours refit to the clip: its lowest to its highest Gaussian span the whole colour bar
    assert v.drawn["zrange"] == geo.height_range(z[z <= 1.0]) != geo.height_range(z)
    assert "Height clip" in v.controls.legend.content and "between" in v.controls.stats.content
    v.controls.layers["occupied"].value = True
    assert (np.asarray(v.scene.nodes["occupied"].points)[:, 2] <= 1.0 + RES).all()
    v.controls.zclip.value = (zlo, zhi)
    assert v.drawn["gaussians"] == len(z)


def test_frame_button_returns_the_camera_to_the_first_view(maps, make_viewer):
    m, _ = maps
    v = make_viewer(m)
    g = m.gaussians(min_probability=0.5)
    lo, hi = g["mean"].min(axis=0), g["mean"].max(axis=0)
    pos, look = (np.array(x) for x in v.first_view.camera(np.radians(50.0), 0.75))
    assert np.all(np.abs(look - (lo + hi) / 2) < 0.15 * (hi - lo) + 1e-6)  # looks at the middle of its bulk
    assert pos[2] > hi[2]  # from above
    # a narrow view steps back further than a wide one (the whole map stays in view)
    narrow, wide = (np.linalg.norm(np.array(v.first_view.camera(np.radians(50.0), a)[0]) - look) for a in (0.5, 2.0))
    assert narrow > 1.5 * wide

    class FakeCamera:
        fov, aspect = np.radians(50.0), 0.5

        def __init__(self):
            self.__dict__["moved"] = []

        def __setattr__(self, k, val):
            self.moved.append((k, tuple(val)))

    cam = FakeCamera()

    class FakeClient:
        camera = cam

    v.server.get_clients = lambda: {0: FakeClient()}
    v.controls.frame.value = True  # a click
    expected = v.first_view.camera(np.radians(50.0), 0.5)
    assert cam.moved == [("position", expected[0]), ("look_at", expected[1])]


def test_every_geometry_is_capped_with_a_notice(maps, make_viewer):
    m, _ = maps
    n = len(m.gaussians(min_probability=0.5)["n"])
    # chosen by hand too, too many ellipsoids: a coarser level that fits, said at the top
    v = make_viewer(m, max_ellipsoids=300, max_splats=600)
    v.controls.geometry.value = "ellipsoids"
    assert v.level >= 2 and 0 < v.drawn["gaussians"] <= 300 and v.drawn["geometry"] == "ellipsoids"
    assert v.controls.notice.visible and "coarser level" in v.controls.notice.content
    v.controls.geometry.value = "splats"
    assert v.level >= 2 and 300 < v.drawn["gaussians"] <= 600
    # even the coarsest level exceeds the cap: an even subsample of it, said at the top
    tiny = make_viewer(m, max_ellipsoids=20, max_splats=20)
    assert tiny.drawn["gaussians"] == 20 < tiny.drawn["gaussians_total"]
    assert len(tiny.scene.nodes["gaussians"].centers) == 20 and "showing an even 20" in tiny.controls.notice.content
    big = make_viewer(m)
    assert big.drawn["gaussians"] == n and big.level == 1 and not big.controls.notice.visible


def test_html_snapshot_is_written_atomically(map_file, tmp_path, capsys, monkeypatch):
    pytest.importorskip("viser")
    from ndtom_ti.viewer import cli
    from ndtom_ti.viewer.app import MapViewer

    out = tmp_path / "snap.html"
    out.write_text("previous snapshot")
    real = MapViewer.save_html

    def full_disk(self, path):
        import os as _os

        def fail(*a, **k):
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(_os, "fsync", fail)
        try:
            return real(self, path)
        finally:
            monkeypatch.undo()

    monkeypatch.setattr(MapViewer, "save_html", full_disk)
    assert cli.view_command(map_file, "127.0.0.1", 0, out) == 1
    assert out.read_text() == "previous snapshot"  # the old snapshot survives
    assert [p.name for p in tmp_path.iterdir()] == ["snap.html"]  # no temporary file left
    err = capsys.readouterr().err
    assert "No space left" in err and "unchanged" in err
    monkeypatch.setattr(MapViewer, "save_html", real)
    assert cli.view_command(map_file, "127.0.0.1", 0, out) == 0
    text = capsys.readouterr().out
    assert f"Wrote {out.resolve()}" in text and out.resolve().as_uri() in text
    assert "http://" not in text  # no URL of a server that is gone
    assert out.stat().st_size > 10_000


def test_view_says_what_it_does_while_a_map_loads(map_file, monkeypatch, capsys):
    pytest.importorskip("viser")
    from ndtom_ti.viewer import MapViewer, cli

    # private names: the command's load, progress line and tick period have no public hook,
    # and a big map's slow load is made here without a big map
    real_load = cli._load
    ticks = threading.Event()

    def slow_load(path, what="map"):  # a big map: the load outlasts one tick
        assert ticks.wait(30)
        return real_load(path, what)

    real_ticking = cli._ticking
    monkeypatch.setattr(cli, "_load", slow_load)

    def fast_ticking(what, every=10.0):
        return real_ticking(what, every=0.05)

    real_say = cli._say

    def say(line):
        real_say(line)
        if "loading (" in line:
            ticks.set()

    monkeypatch.setattr(cli, "_ticking", fast_ticking)
    monkeypatch.setattr(cli, "_say", say)
    seen = []
    monkeypatch.setattr(MapViewer, "wait", lambda viewer: seen.append(viewer.url))
    assert cli.view_command(map_file, "127.0.0.1", 0, None) == 0
    out = capsys.readouterr().out.splitlines()
    first = [i for i, line in enumerate(out) if line.startswith("Loading ")]
    tick = [i for i, line in enumerate(out) if "... loading (" in line]
    url = [i for i, line in enumerate(out) if line.startswith("NDT-OM viewer: http://127.0.0.1:")]
    assert first and tick and url and first[0] < tick[0] < url[0], out
    assert any(line.startswith("Loaded ") and "Gaussians" in line for line in out)
    assert seen and url and seen[0] in out[url[0]]  # the URL is printed once it serves


def test_auto_level_of_detail_draws_the_first_coarser_level_that_fits(make_viewer, rng):
    """A coarse cell gets a Gaussian from points that made none in its finer cells, so the
    count estimated from the native Gaussians falls short (2x: 184 estimated, 373 there):
    auto moves on until a level fits whole (6x here), not an even subsample of one that
    does not."""
    m = NdtOmMap(0.2)
    wall = np.c_[np.full(300, 6.05), rng.integers(-40, 40, 300) * 0.2 + 0.1, rng.integers(0, 10, 300) * 0.2 + 0.1]
    dense = np.repeat(wall, 5, 0) + rng.normal(scale=0.02, size=(1500, 3))
    sparse = np.c_[np.full(1500, 8.05), rng.uniform(-16, 16, 1500), rng.uniform(0, 4, 1500)]
    m.insert_scan(np.r_[dense, sparse], np.eye(4))
    counts = {f: len(m.coarsen(f).gaussians(min_probability=0.5)["n"]) for f in (2, 3, 4, 6, 8)}
    fits = min(f for f, n in counts.items() if n <= 200)
    assert fits >= 4, counts  # the estimate alone would pick 2x
    v = make_viewer(m, max_ellipsoids=50, max_splats=200)
    assert v.drawn["factor"] == fits and v.drawn["gaussians"] == counts[fits], (v.drawn["factor"], counts)
    assert f"showing the {fits}x coarser level" in v.controls.stats.content
    m.close()


def test_a_shifted_map_says_its_frame_origin_beside_positions_and_heights(maps, make_viewer):
    """A georeferenced map is drawn in its shifted frame (frame_origin): the panel says where
    that frame lies, and the height legend what to add (it showed 12-20 m for 312-320 m)."""
    m, _ = maps
    s = m.snapshot()
    s.metadata["frame_origin"] = [512_300.0, 5_402_300.0, 300.0]
    v = make_viewer(s)
    assert "(512300.00, 5402300.00, 300.00) m of the poses' frame" in v.controls.stats.content
    assert "add 300.00 m for the poses' frame" in v.controls.legend.content
    plain = make_viewer(m.snapshot())
    assert "Frame origin" not in plain.controls.stats.content and "add " not in plain.controls.legend.content
