"""`ndtom sweep` and the sweep module on tiny inputs."""

import csv

import numpy as np
import pytest
from typer.testing import CliRunner

from ndtom_ti import MapConfig, NdtOmMap
from ndtom_ti.evaluation import sweep
from ndtom_ti.cli import app


def test_run_sweep_rows_and_floor(rng):
    scans = []
    for k in range(3):
        T = np.eye(4)
        T[:3, 3] = [0.2 * k, 0.0, 0.0]
        d = rng.normal(size=(3000, 3))
        scans.append((d / np.linalg.norm(d, axis=1, keepdims=True) * 6.0, T))
    rows = sweep.run_sweep(scans, [0.5, 1.0], warmup=1)
    assert [(r.mapper, r.resolution) for r in rows] == [
        ("ndtom", 0.5),
        ("ndtom-floor", 0.5),
        ("ndtom", 1.0),
        ("ndtom-floor", 1.0),
    ]
    for r in rows:
        assert r.scans == 3 and r.ms_median > 0 and r.ms_p95 >= r.ms_median and r.visits_per_s > 0
    full, fl = rows[0], rows[1]
    assert full.gaussians > 0 and full.memory_bytes > 0
    assert fl.ratio_to_ndtom == pytest.approx(fl.ms_median / full.ms_median)


def test_run_sweep_maps_with_the_config_given(rng):
    d = rng.normal(size=(3000, 3))
    scans = [(d / np.linalg.norm(d, axis=1, keepdims=True) * 6.0, np.eye(4))]
    counts = {}
    for cfg in (MapConfig(), MapConfig(miss_model="paper", min_points=40)):
        (row,) = sweep.run_sweep(scans, [0.5], floor=False, warmup=0, config=cfg)
        with NdtOmMap(0.5, config=cfg) as m:
            m.insert_scan(*scans[0])
            assert row.gaussians == len(m)
        counts[cfg.min_points] = row.gaussians
    assert counts[40] < counts[MapConfig().min_points]


def test_run_sweep_times_georeferenced_scans_near_the_origin(rng):
    """Poses in UTM: the sweep maps them shifted as the mapping loop would (same map)."""
    d = rng.normal(size=(3000, 3))
    pts = d / np.linalg.norm(d, axis=1, keepdims=True) * 6.0
    T = np.eye(4)
    T[:3, 3] = [512_345.0, 5_412_345.0, 31.0]
    (row,) = sweep.run_sweep([(pts, T)], [0.5], floor=False, warmup=0)
    with NdtOmMap(0.5) as m:
        T[:3, 3] -= [512_300.0, 5_412_300.0, 0.0]
        m.insert_scan(pts, T)
        assert row.gaussians == len(m) > 0 and row.known_cells == m.known_cell_count()


def test_run_sweep_rejects_bad_input():
    with pytest.raises(ValueError, match="at least one scan"):
        sweep.run_sweep([], [0.5])
    with pytest.raises(ValueError, match="baseline"):
        sweep.run_sweep([(np.ones((3, 3)), np.eye(4))], [0.5], baseline="voxblox")


@pytest.mark.skipif(not sweep.octomap_available(), reason="pyoctomap not installed")
def test_cli_sweep_synthetic_with_octomap(tmp_path):
    res = CliRunner(env={"COLUMNS": "250"}).invoke(
        app,
        [
            "sweep",
            "--synthetic",
            "--scans",
            "2",
            "--resolutions",
            "0.5",
            "--baseline",
            "octomap",
            "--out",
            str(tmp_path / "sw"),
        ],
    )
    assert res.exit_code == 0, res.output
    with open(tmp_path / "sw" / "sweep.csv") as fh:
        header = next(csv.reader(fh))
    assert len(header) == len(set(header)) and "scans" in header  # each column once
    rows = list(csv.DictReader(open(tmp_path / "sw" / "sweep.csv")))
    assert [r["mapper"] for r in rows] == ["ndtom", "ndtom-floor", "octomap"]
    assert int(rows[0]["gaussians"]) > 0 and rows[1]["gaussians"] == rows[2]["gaussians"] == ""  # not 0: none
    assert all(int(r["scans"]) == 2 for r in rows)
    table = {
        line.split("│")[1].strip(): [c.strip() for c in line.split("│")[1:-1]]
        for line in res.output.splitlines()
        if line.startswith("│")
    }
    assert table["octomap"][7] == table["ndtom-floor"][7] == "-" and table["ndtom"][7] not in ("-", "0")
    assert all(r["arch"] and r["taichi"] and r["machine"] for r in rows)
    from ndtom_ti import runtime

    assert all(int(r["pinned_threads"]) == len(runtime.pinned_threads()) for r in rows)
    assert float(rows[2]["ratio_to_ndtom"]) > 0
    assert (tmp_path / "sw" / "sweep.png").stat().st_size > 5000


@pytest.mark.parametrize(
    "args,message",
    [
        (["--resolutions", "0.5"], "either a recording BAG or --synthetic"),
        (["--synthetic", "--resolutions", "a,b"], "numbers separated by commas"),
        (["--synthetic", "--resolutions", "-1"], "positive"),
        (["--synthetic", "--baseline", "voxblox"], "unknown baseline"),
    ],
)
def test_cli_sweep_bad_options(tmp_path, args, message):
    res = CliRunner().invoke(app, ["sweep", *args, "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and message in res.output, res.output


def test_write_csv_holds_each_column_once(tmp_path):
    row = sweep.SweepRow("octomap", 0.5, 3, 100.0, 1.0, 2.0, 3.0, float("nan"), 10, None, 1000)
    path = sweep.write_csv([row], tmp_path / "s.csv", {"scans": 99, "machine": "m"})
    with open(path) as fh:
        header = next(csv.reader(fh))
    assert header.count("scans") == 1 and header[-1] == "machine"
    with open(path) as fh:
        (line,) = csv.DictReader(fh)
    assert line["scans"] == "3" and line["gaussians"] == "" and line["machine"] == "m"
