"""`ndtom sweep` and `ndtom experiments` when something goes wrong: a stop signal, a
resolution that does not fit (in memory, or the grid), an optional package that is
installed but broken, georeferenced poses, a recording without poses, odd options. The
user gets a clear error or a reported skip and keeps what was finished."""

from __future__ import annotations

import csv
import importlib.machinery
import json
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA
from typer.testing import CliRunner

from ndtom_ti import demo
from ndtom_ti.cli import app
from ndtom_ti.evaluation import experiments as ex
from ndtom_ti.evaluation import sweep
from ndtom_ti.runtime import MapMemoryError

LUMINAR = DATA / "luminar_embag_test.bag"
MEMORY_TEXT = (
    "this update could take Taichi's memory pool to 9000 MiB, past the 100 MiB budget. Use a coarser "
    "resolution or a smaller max_range, delete other maps, give a larger budget "
    "(ndtom_ti.init(memory_limit_GB=...) before the first map), or use CUDA. The map is unchanged."
)


def read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def stop_at(monkeypatch, resolution: float, exc: BaseException) -> None:
    """The sweep's maps at ``resolution`` raise ``exc`` (a stop signal, the memory budget)."""
    real = sweep.NdtOmMap

    def make(res, *args, **kwargs):
        if res == resolution:
            raise exc
        return real(res, *args, **kwargs)

    monkeypatch.setattr(sweep, "NdtOmMap", make)


def small_npz(path: Path, n: int = 2) -> Path:
    """A simworld-layout npz of the synthetic room's first ``n`` scans."""
    scans = demo.make_scans(n, per_ring=600)
    pts = [np.asarray(s.points, np.float32) for s in scans]
    off = np.cumsum([0] + [len(p) for p in pts])
    np.savez(
        path,
        scan_offsets=off,
        points=np.concatenate(pts),
        no_return=np.zeros(off[-1], bool),
        hit_id=np.zeros(off[-1], np.int32),
        poses=np.stack([np.asarray(s.T_world_sensor, np.float64) for s in scans]),
        static_lo=np.zeros(1),
    )
    return path


class _BrokenFinder:
    """``module`` is found installed but its import fails, as with a missing shared library."""

    def __init__(self, module: str) -> None:
        self.module = module

    def find_spec(self, name, path=None, target=None):
        if name != self.module:
            return None
        return importlib.machinery.ModuleSpec(name, self, origin=f"/fake/{name}.so")

    def create_module(self, spec):
        return None

    def exec_module(self, module):
        raise ImportError("libbroken.so.1: cannot open shared object file: No such file or directory")


@pytest.fixture
def broken(monkeypatch):
    def make(module: str) -> None:
        monkeypatch.delitem(sys.modules, module, raising=False)
        monkeypatch.setattr(sys, "meta_path", [_BrokenFinder(module), *sys.meta_path])

    return make


# ---------------------------------------------------------------------------- sweep: stops
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_sweep_signal_keeps_the_resolutions_finished(tmp_path, signum):
    out = tmp_path / "sw"
    cmd = [sys.executable, "-m", "ndtom_ti", "sweep", "--synthetic", "--scans", "2", "--resolutions", "0.8,0.5"]
    p = subprocess.Popen(
        [*cmd, "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "COLUMNS": "200", "NDTOM_ARCH": "cpu"},
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    lines = []
    assert p.stdout is not None
    for line in p.stdout:
        lines.append(line)
        if "0.5 m: NDT-OM" in line:
            p.send_signal(signum)
    rc = p.wait(timeout=120)
    text = "".join(lines)
    assert rc == 128 + signum, text
    assert "Traceback" not in text and "nothing was written" not in text
    assert ("SIGTERM" if signum == signal.SIGTERM else "Ctrl-C") in text and "partial" in text
    rows = read_rows(out / "sweep.csv")
    assert {r["resolution"] for r in rows} == {"0.8"} and len(rows) == 2
    assert all(r["complete"] == "false" and "0.5 m" in r["stopped"] for r in rows)


def test_sweep_memory_stop_keeps_rows_and_names_its_own_options(tmp_path, monkeypatch):
    stop_at(monkeypatch, 0.25, MapMemoryError(MEMORY_TEXT))
    out = tmp_path / "sw"
    res = CliRunner().invoke(
        app, ["sweep", "--synthetic", "--scans", "1", "--resolutions", "0.5,0.25", "--no-floor", "--out", str(out)]
    )
    assert res.exit_code == 1, res.output
    assert "memory_limit_GB" not in res.output and "--resolutions" in res.output and "0.25" in res.output
    rows = read_rows(out / "sweep.csv")
    assert [(r["mapper"], r["resolution"], r["complete"]) for r in rows] == [("ndtom", "0.5", "false")]
    assert rows[0]["stopped"] == "memory at 0.25 m"


def test_sweep_complete_run_says_so(tmp_path):
    out = tmp_path / "sw"
    res = CliRunner().invoke(
        app, ["sweep", "--synthetic", "--scans", "1", "--resolutions", "0.5,0.5", "--no-floor", "--out", str(out)]
    )
    assert res.exit_code == 0, res.output
    assert "more than once" in res.output
    rows = read_rows(out / "sweep.csv")
    assert [(r["resolution"], r["complete"], r["stopped"]) for r in rows] == [("0.5", "true", "")]


def test_sweep_refuses_a_resolution_the_grid_cannot_hold_before_any_work(tmp_path):
    out = tmp_path / "sw"
    res = CliRunner().invoke(
        app, ["sweep", "--synthetic", "--scans", "1", "--resolutions", "0.5,0.000001", "--out", str(out)]
    )
    assert res.exit_code == 2, res.output
    assert "too fine" in res.output and "--resolutions" in res.output and "Layout" not in res.output
    assert "warm-up" not in res.output and not (out / "sweep.csv").exists()
    with pytest.raises(sweep.ResolutionTooFineError):
        sweep.run_sweep(demo.make_scans(1, per_ring=200), [0.5, 1e-6])


@pytest.mark.parametrize(
    "args,message",
    [
        (["--resolutions", "0.4,,0.8"], "empty entry"),
        (["--resolutions", "0.4,"], "empty entry"),
        (["--resolutions", "0.4", "--out", ""], "--out is empty"),
    ],
)
def test_sweep_odd_options_are_refused(tmp_path, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(app, ["sweep", "--synthetic", "--scans", "1", "--out", str(tmp_path / "o"), *args])
    assert res.exit_code == 2 and message in res.output, res.output
    assert not (tmp_path / "sweep.csv").exists()


def test_sweep_unwritable_out_names_out(tmp_path, monkeypatch):
    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    res = CliRunner().invoke(app, ["sweep", "--synthetic", "--scans", "1", "--out", str(tmp_path / "o")])
    assert res.exit_code == 1 and "with --out" in res.output and "with -o" not in res.output, res.output


# ---------------------------------------------------------------------------- broken extras
def test_sweep_broken_octomap_is_refused_before_work(tmp_path, broken):
    broken("pyoctomap")
    res = CliRunner().invoke(
        app, ["sweep", "--synthetic", "--scans", "1", "--baseline", "octomap", "--out", str(tmp_path / "o")]
    )
    assert res.exit_code == 1, res.output
    assert "installed but cannot be imported" in res.output and "libbroken" in res.output
    assert "reinstall" in res.output and "internal error" not in res.output and "warm-up" not in res.output


def test_experiments_broken_matplotlib_skips_plots_keeps_results(tmp_path, broken):
    npz = small_npz(tmp_path / "room.npz")
    broken("matplotlib")
    out = tmp_path / "ex"
    res = CliRunner().invoke(app, ["experiments", str(npz), "-r", "0.5", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "installed but cannot be imported" in res.output and "no PNG plots" in res.output
    assert (out / "summary.json").exists() and not list(out.glob("*.png"))
    from ndtom_ti.extras import ExtraMissingError

    with pytest.raises(ExtraMissingError, match="cannot be imported"):
        ex.run_experiments(str(npz), 0.5, tmp_path / "api")


# ---------------------------------------------------------------------------- experiments
def test_experiments_refuses_a_too_fine_sweep_before_the_evaluation(tmp_path):
    npz = small_npz(tmp_path / "room.npz")
    out = tmp_path / "ex"
    res = CliRunner().invoke(
        app, ["experiments", str(npz), "-r", "0.5", "--no-plots", "--sweep", "0.8,0.00001", "--out", str(out)]
    )
    assert res.exit_code == 2, res.output
    assert "--sweep" in res.output and "too fine" in res.output and "Layout" not in res.output
    assert not (out / "fig1_vs_batch.csv").exists()


@pytest.mark.parametrize("stop", ["signal", "memory"])
def test_experiments_stopped_sweep_keeps_the_main_results(tmp_path, monkeypatch, stop):
    npz = small_npz(tmp_path / "room.npz")
    out = tmp_path / "ex"
    stop_at(monkeypatch, 0.25, KeyboardInterrupt() if stop == "signal" else MapMemoryError(MEMORY_TEXT))
    res = CliRunner().invoke(
        app, ["experiments", str(npz), "-r", "0.5", "--no-plots", "--sweep", "0.5,0.25", "--out", str(out)]
    )
    assert res.exit_code == (130 if stop == "signal" else 1), res.output
    assert "nothing was written" not in res.output and "summary.json" in res.output
    assert "memory_limit_GB" not in res.output
    s = json.loads((out / "summary.json").read_text())
    assert s["complete"] is False and s["fig5"]["complete"] is False and s["fig5"]["stopped_at"] == 0.25
    assert {r["resolution"] for r in s["fig5"]["rows"]} == {0.5}
    assert {"fig1_vs_batch.csv", "fig5_sweep.csv", "summary.json"} <= set(s["files"])
    assert all(r["complete"] == "false" for r in read_rows(out / "fig5_sweep.csv"))
    assert s["fig1_final_score"]["rcu"] >= 0.999


def test_experiments_summary_keeps_the_frame_origin(tmp_path):
    scans = demo.make_scans(2, per_ring=400)
    far = []
    for sc in scans:
        T = np.array(sc.T_world_sensor, np.float64)
        T[:3, 3] += [512_345.0, 5_412_345.0, 0.0]
        far.append((sc.points, T))
    s = ex.run_experiments(far, 1.0, tmp_path / "far", plots=False)
    assert s["frame_origin"] == [512300.0, 5412300.0, 0.0] and "relative" in s["frame_origin_note"]
    assert json.loads((tmp_path / "far" / "summary.json").read_text())["frame_origin"] == s["frame_origin"]
    near = ex.run_experiments([(sc.points, sc.T_world_sensor) for sc in scans], 1.0, tmp_path / "near", plots=False)
    assert near["frame_origin"] is None and near["complete"] is True


@pytest.mark.skipif(not LUMINAR.exists(), reason="shared data not present")
@pytest.mark.parametrize("command", ["sweep", "experiments"])
def test_recording_without_poses_names_this_commands_options(tmp_path, command):
    args = ["--scans", "1"] if command == "sweep" else ["-r", "0.4", "--no-plots"]
    res = CliRunner().invoke(app, [command, str(LUMINAR), *args, "--out", str(tmp_path / "o")])
    assert res.exit_code == 2, res.output
    assert "give poses with --poses" not in res.output and "--sensor-frame" in res.output
    assert "`ndtom map` also takes --poses FILE" in res.output
