"""benchmarks/speed.py: several fresh processes per setting, each printed, and their medians;
benchmarks/threads.py: a row per loop size; benchmarks/startup.py: the simulated hall's first
scan; benchmarks/big_map.py: records read by place and all of them, at each size of the map."""

import importlib.util
import subprocess
import sys
from pathlib import Path

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
