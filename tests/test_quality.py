"""The dynamic-scene quality metrics (ndtom_ti.quality) on cases whose answer is known, and
the quality benchmark end to end on a small generated scene."""

import csv
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT, SIMWORLD

from ndtom_ti import MapConfig, NdtOmMap
from ndtom_ti import quality as q
from ndtom_ti.cellkeys import isin_rows


def scan(points, dynamic, origin=(0.0, 0.0, 0.0), dyn_box=None):
    T = np.eye(4)
    T[:3, 3] = origin
    lo, hi = (
        (np.zeros((0, 3)), np.zeros((0, 3))) if dyn_box is None else (np.array([dyn_box[0]]), np.array([dyn_box[1]]))
    )
    return q.LabelledScan(np.asarray(points, float), np.asarray(dynamic, bool), np.asarray(origin, float), T, lo, hi)


def test_isin_rows_matches_rows():
    rng = np.random.default_rng(0)
    a = rng.integers(-(1 << 19), 1 << 19, size=(5000, 3))
    b = np.concatenate([a[:100], a[:50] + 1, a[:10] * [1, 1, -1]])
    rows = set(map(tuple, a.tolist()))
    assert isin_rows(b, a).tolist() == [tuple(r) in rows for r in b.tolist()]
    assert isin_rows(b, a[:0]).tolist() == [False] * len(b) and len(isin_rows(a[:0], b)) == 0


def test_ghost_candidates_need_three_points_and_a_free_cell_at_the_end():
    res = 1.0
    # Cell (2,0,0): 3 points of a moving object over two scans; (5,0,0): 2 points only;
    # (8,0,0): 3 points but the object still stands there at the end; (11,0,0): 3 points
    # beside a static box (touching it once grown by the margin).
    s0 = scan([[2.5, 0.5, 0.5], [2.6, 0.5, 0.5], [5.5, 0.5, 0.5], [8.5, 0.5, 0.5], [11.5, 0.5, 0.5]], [1, 1, 1, 1, 1])
    s1 = scan(
        [
            [2.4, 0.4, 0.4],
            [5.4, 0.5, 0.5],
            [8.4, 0.5, 0.5],
            [8.6, 0.5, 0.5],
            [11.4, 0.5, 0.5],
            [11.6, 0.5, 0.5],
            [0.5, 3.5, 0.5],
        ],
        [1, 1, 1, 1, 1, 1, 0],
        dyn_box=([8.2, 0.2, 0.2], [8.8, 0.8, 0.8]),
    )
    static = (np.array([[12.05, -1.0, -1.0]]), np.array([[13.0, 2.0, 2.0]]))
    c = q.ghost_candidates([s0, s1], res, 0.1, static)
    assert c.cells.tolist() == [[2, 0, 0]] and c.last_hit.tolist() == [1]
    c = q.ghost_candidates([s0, s1], res, 0.01, static)  # the grown cell no longer reaches the static box
    assert c.cells.tolist() == [[2, 0, 0], [11, 0, 0]]


def test_observed_only_by_rays_after_the_last_moving_point():
    res = 0.5
    # A moving object's points in cell (4,0,0) in scan 0; scan 1 sees it again; scan 2's
    # ray passes through it to a wall behind; cell (4,4,0) is never passed afterwards.
    obj = [[2.2, 0.2, 0.2], [2.3, 0.3, 0.2], [2.4, 0.2, 0.3]]
    other = [[2.2, 2.2, 0.2], [2.3, 2.3, 0.2], [2.4, 2.2, 0.3]]
    s0 = scan(obj + other, [1] * 6, origin=(0.1, 0.1, 0.1))
    s1 = scan(obj[:1], [1], origin=(0.1, 0.1, 0.1))
    s2 = scan([[6.0, 0.25, 0.25]], [0], origin=(0.1, 0.25, 0.25))
    c = q.mark_observed(q.ghost_candidates([s0, s1, s2], res, 0.0), [s0, s1, s2], res)
    got = {tuple(x): bool(o) for x, o in zip(c.cells.tolist(), c.observed)}
    assert got == {(4, 0, 0): True, (4, 4, 0): False}
    # Without the later scan nothing was observed.
    c = q.mark_observed(q.ghost_candidates([s0, s1], res, 0.0), [s0, s1], res)
    assert not c.observed.any()


def test_score_and_conflicting_on_known_maps(rng):
    res = 0.5
    cand = q.GhostCandidates(
        np.array([[1, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0]]), np.zeros(4, int), np.array([True, True, True, False])
    )
    static = np.array([[0, 5, 0], [1, 5, 0]])
    occupied = q.score(lambda cells: cells[:, 0] == 2, cand, static)
    assert occupied.ghosts == pytest.approx(1 / 3) and occupied.ghost_cells == 3
    assert occupied.ghosts_left.tolist() == [[2, 0, 0]] and occupied.static_kept == 0.0
    # An NDT-OM map: the Gaussian of a blob is occupied; Recursive NDT has one more.
    blob = rng.normal(size=(50, 3)) * 0.05 + [1.25, 0.25, 0.25]
    m = NdtOmMap(res, config=MapConfig(miss_model="ndt"))
    rcu = NdtOmMap(res, occupancy=False)
    for mp in (m, rcu):
        mp.insert_scan(blob, np.eye(4))
    rcu.insert_scan(rng.normal(size=(50, 3)) * 0.05 + [3.25, 3.25, 0.25], np.eye(4))
    assert q.ndtom_occupied(m)(np.array([[2, 0, 0], [3, 0, 0]])).tolist() == [True, False]
    assert q.conflicting(rcu, m) == (1, 1.0)


def test_logodds_at_reads_cells_and_rejects_bad_indices():
    m = NdtOmMap(0.5, config=MapConfig(miss_model="paper"))  # eq. (12): a first hit is logit(0.6)
    m.insert_scan(np.array([[2.1, 0.1, 0.1]]), np.eye(4))
    lo = m.logodds_at(np.array([[4, 0, 0], [2, 0, 0], [50, 50, 50], [10**9, 0, 0]]))
    assert lo[0] == pytest.approx(np.log(0.6 / 0.4)) and lo[1] < 0 and lo[2] == 0.0 and lo[3] == 0.0
    with pytest.raises(ValueError, match="integer"):
        m.logodds_at(np.array([[0.5, 0.0, 0.0]]))


@pytest.mark.skipif(not SIMWORLD.exists(), reason="simworld not found")
def test_quality_benchmark_end_to_end(tmp_path):
    """benchmarks/quality.py on a small hall: table, CSV with both models, a top view."""
    out = tmp_path / "q"
    r = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "quality.py"),
            "--scene",
            "hall",
            "--scans",
            "8",
            "--res",
            "0.4",
            "--no-octomap",
            "--out",
            str(out),
            "--simworld",
            str(SIMWORLD),
        ],
        check=False,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert "ndtom-ndt" in r.stdout and "ndtom-paper" in r.stdout and "static kept" in r.stdout
    with open(out / "quality.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [x["mapper"] for x in rows] == ["ndtom-ndt", "ndtom-paper"]
    for x in rows:
        assert 0.0 <= float(x["static_kept_pct"]) <= 100.0 and int(x["static_cells"]) > 1000
        assert 0.0 <= float(x["conflicting_static_pct"]) <= 100.0
    # The NDT miss model keeps more of the static surface than the paper's constant rate.
    assert float(rows[0]["static_kept_pct"]) > float(rows[1]["static_kept_pct"])
    assert (out / "quality_hall.png").stat().st_size > 10_000


def load_benchmark():
    import importlib.util

    spec = importlib.util.spec_from_file_location("quality_bench", ROOT / "benchmarks" / "quality.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def test_quality_benchmark_settings_parse_and_name_scenes():
    b = load_benchmark()
    assert b.parse_combo("default") == b.Settings() and b.Settings().tag() == ""
    st = b.parse_combo("speed=2,pitch=5,stride=1")
    assert (st.speed, st.pitch, st.stride, st.noise) == (2.0, 5.0, 1, 0.02) and isinstance(st.stride, int)
    assert st.tag() == "_v2_p5_k1" and st.label() == "v2 p5 k1"
    with pytest.raises(ValueError, match="bad setting"):
        b.parse_combo("yaw=3")


@pytest.mark.skipif(not SIMWORLD.exists(), reason="simworld not found")
def test_quality_benchmark_grid_reaches_simworld(tmp_path):
    """Grid mode: each combination's settings reach the simulator, and the CSV has a row per
    mapper and combination with the settings as columns."""
    import json

    out = tmp_path / "g"
    r = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "quality.py"),
            "--scene",
            "hall",
            "--scans",
            "3",
            "--res",
            "0.4",
            "--seed",
            "5",
            "--no-octomap",
            "--out",
            str(out),
            "--simworld",
            str(SIMWORLD),
            "--combo",
            "default",
            "speed=2,roll=1,pitch=3,noise=0.04,stride=5",
        ],
        check=False,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    info = json.loads((out / "hall_s5_n3_v2_r1_p3_e0.04_k5_info.json").read_text())["params"]
    assert (info["speed"], info["range_sigma"], info["stride"], info["seed"]) == (2.0, 0.04, 5, 5)
    assert list(info["mount_rpy_deg"]) == [1.0, 3.0, 0.0]
    assert json.loads((out / "hall_s5_n3_info.json").read_text())["params"]["speed"] == 1.0
    assert (out / "hall_s5_n3_v2_r1_p3_e0.04_k5_static_info.json").exists()
    with open(out / "quality.csv") as fh:
        rows = list(csv.DictReader(fh))
    for col in (
        "scene",
        "seed",
        "speed",
        "roll",
        "pitch",
        "noise",
        "stride",
        "resolution",
        "mapper",
        "ghosts_pct",
        "static_kept_pct",
        "conflicting_static_pct",
        "ghosts_vs_octomap",
    ):
        assert col in rows[0]
    assert [(x["speed"], x["pitch"], x["stride"], x["mapper"]) for x in rows] == [
        ("1.0", "0.0", "10", "ndtom-ndt"),
        ("1.0", "0.0", "10", "ndtom-paper"),
        ("2.0", "3.0", "5", "ndtom-ndt"),
        ("2.0", "3.0", "5", "ndtom-paper"),
    ]
    assert all(x["ghosts_vs_octomap"] == "" for x in rows)  # no OctoMap, no ratio
    assert "ndt/octo" in r.stdout and "v2 r1 p3 e0.04 k5" in r.stdout
