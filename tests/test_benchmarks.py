"""benchmarks/speed.py: several fresh processes per setting, each printed, and their medians;
benchmarks/threads.py: a row per loop size; benchmarks/startup.py: the simulated hall's first
scan; benchmarks/big_map.py: records read by place and all of them, at each size of the map;
benchmarks/record_entropy.py: the bits of the Gaussians no lossless coding can drop."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _speed():
    spec = importlib.util.spec_from_file_location("speed_bench", ROOT / "benchmarks" / "speed.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _run(script: str, *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), *args], capture_output=True, text=True, timeout=timeout
    )


def test_a_child_runs_one_setting_once():
    child = _speed()._child_args
    assert child(["--runs", "3", "--pin", "both", "--res", "0.2", "0.4"]) == ["--res", "0.2", "0.4"]
    assert child(["--runs=3", "--pin=on", "--scans", "5"]) == ["--scans", "5"]


def test_runs_prints_each_process_and_the_medians():
    out = _run("speed.py", "--runs", "2", "--scans", "1", "--no-octomap")
    assert out.returncode == 0, out.stderr[-3000:]
    lines = out.stdout.splitlines()
    assert sum(line.split()[:2] == ["off", "0.20"] for line in lines) == 3  # two runs, one median
    assert "medians of 2 processes each:" in out.stdout
    bad = _run("speed.py", "--runs", "0")
    assert bad.returncode == 2 and "--runs must be at least 1" in bad.stderr


def test_threads_prints_a_row_per_loop_size():
    out = _run("threads.py", "--sizes", "0.2", "1", "--repeats", "1", timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    rows = [line.split() for line in out.stdout.splitlines() if line.split()[:1] in (["0.2"], ["1.0"])]
    assert [r[0] for r in rows] == ["0.2", "1.0"]
    for r in rows:  # loop ms, wall ms and busy threads (unpinned; pinned where it could pin)
        assert len(r) in (3, 5) and all(float(x) > 0 for x in r)
    bad = _run("threads.py", "--repeats", "0")
    assert bad.returncode == 2 and "--repeats must be at least 1" in bad.stderr


def test_startup_times_the_halls_first_scan():
    out = _run("startup.py", "--hall", "3", timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    line = out.stdout.splitlines()[-1]
    assert line.startswith("import ") and "init + first scan" in line and "total" in line
    assert int(line.split("(")[1].split()[0].replace(",", "")) > 10_000  # the hall's points, not the random scan's


def test_big_map_times_both_ways_at_each_size():
    out = _run("big_map.py", "--hall-scans", "3", "--scans", "1", "--copies", "1", "2", timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    rows = [line.split() for line in out.stdout.splitlines() if line.split()[:1] in (["0"], ["1"], ["2"])]
    assert [r[0] for r in rows] == ["0", "1", "2"]
    gaussians = [int(r[1].replace(",", "")) for r in rows]
    assert gaussians[0] > 0 and gaussians[2] > gaussians[1] > gaussians[0]  # the map grew elsewhere
    assert all(float(x) > 0 for r in rows for x in r[2:])
    bad = _run("big_map.py", "--copies", "4", "2")
    assert bad.returncode == 2 and "--copies must be increasing" in bad.stderr


def test_record_entropy_counts_the_bits_a_coder_must_keep(arch, tmp_path):
    spec = importlib.util.spec_from_file_location("record_entropy", ROOT / "benchmarks" / "record_entropy.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    rng = np.random.default_rng(0)
    h32 = mod.bit_entropy(rng.normal(size=4096).astype(np.float32).astype(np.float64))
    assert h32[:29].max() == 0 and h32[29:52].min() > 0.9  # a float32 in a float64: 29 zero bits
    assert mod.bit_entropy(rng.normal(size=4096))[:52].min() > 0.9

    import ndtom_ti

    m = ndtom_ti.NdtOmMap(0.5)
    for k in range(3):  # a wall of many points a cell: Gaussians of more than one point
        wall = np.c_[np.full(2000, 5.0), rng.uniform(-3, 3, 2000), rng.uniform(0, 2, 2000)]
        m.insert_scan(wall + rng.normal(scale=0.02, size=wall.shape), np.eye(4))
    m.save(tmp_path / "wall.ndtom")
    out = _run("record_entropy.py", str(tmp_path / "wall.ndtom"), timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    row = out.stdout.splitlines()[-1].split(" | ")
    assert row[0] == "wall.ndtom"
    full, low = (float(x) for x in row[3].split(" / "))
    assert 9 * 40 * 0.8 < low <= 9 * 40 and low < full <= 9 * 64  # near-random low bits, 9 columns
    assert float(row[4]) > 0
