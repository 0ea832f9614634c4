"""The application layer's single points: one scan type, one resolution check, one set of
exit codes, the command list of ``ndtom --help``, and no installed code that looks for the
repository's ../shared folder."""

from __future__ import annotations

import math
import re
import signal
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import ndtom_ti
from ndtom_ti import exitcodes
from ndtom_ti.cli import app
from ndtom_ti.config import check_resolution
from ndtom_ti.demo import make_scans
from ndtom_ti.evaluation import load_scans, run_experiments, sweep
from ndtom_ti.evaluation.er_baseline import ErrorRefinementMap
from ndtom_ti.evaluation.metrics import batch_ndt
from ndtom_ti.pipeline import map_recording, map_scans
from ndtom_ti.signals import StopSignals
from ndtom_ti.scan import Scan, scan_parts

PACKAGE = Path(ndtom_ti.__file__).resolve().parent
REPO = PACKAGE.parent
INSTALLED = [PACKAGE, REPO / "kernels", REPO / "viewer"]  # ndtom_ti, ndtom_ti.kernels, ndtom_ti.viewer


def _installed_sources() -> list[Path]:
    files = [p for d in INSTALLED for p in sorted(d.rglob("*.py"))]
    assert len(files) > 30, files
    return files


# ---------------------------------------------------------------------------- resolution
@pytest.mark.parametrize("value", [0.2, 1, np.float32(0.5), np.float64(3.0), np.int64(2)])
def test_check_resolution_takes_positive_numbers(value) -> None:
    got = check_resolution(value)
    assert type(got) is float and got == float(value)


@pytest.mark.parametrize(
    "value, error",
    [
        (0.0, ValueError),
        (-0.1, ValueError),
        (math.nan, ValueError),
        (math.inf, ValueError),
        (True, TypeError),
        ("0.2", TypeError),
        (None, TypeError),
        ([0.2], TypeError),
    ],
)
def test_check_resolution_refuses_the_rest(value, error) -> None:
    with pytest.raises(error, match=r"^-r/--resolution must be a (positive )?number of metres, got"):
        check_resolution(value, "-r/--resolution")


def _pair() -> tuple[np.ndarray, np.ndarray]:
    pts = np.random.default_rng(3).uniform(-3.0, 3.0, (500, 3)).astype(np.float32)
    return pts, np.eye(4)


@pytest.mark.parametrize(
    "call",
    [
        lambda r, tmp: ndtom_ti.NdtOmMap(r),
        lambda r, tmp: batch_ndt(_pair()[0], r),
        lambda r, tmp: ErrorRefinementMap(r),
        lambda r, tmp: map_recording(tmp / "never-read.bag", r),
        lambda r, tmp: map_scans([_pair()], r),
        lambda r, tmp: run_experiments([_pair()], r, tmp / "ex", plots=False),
        lambda r, tmp: sweep.run_sweep([_pair()], [0.5, r]),
    ],
    ids=["NdtOmMap", "batch_ndt", "ErrorRefinementMap", "map_recording", "map_scans", "run_experiments", "run_sweep"],
)
def test_every_resolution_goes_through_the_one_check(call, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"must be a positive number of metres, got -0\.5$"):
        call(-0.5, tmp_path)
    with pytest.raises(TypeError, match=r"must be a number of metres, got str$"):
        call("0.5", tmp_path)
    assert not (tmp_path / "ex").exists()  # refused before any work


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["sweep", "--synthetic", "--resolutions", "0.4,-1"],
            "--resolutions must be positive numbers of metres, got '0.4,-1'",
        ),
        (["sweep", "--synthetic", "--resolutions", "0.4,x"], "--resolutions must be numbers separated by commas"),
        (["experiments", "nothing.bag", "-r", "0.4", "--sweep", "0.2,0"], "--sweep must be positive numbers of metres"),
        (["experiments", "nothing.bag", "-r", "inf"], "-r/--resolution must be a positive number of metres, got inf"),
        (["demo", "-r", "0"], "-r/--resolution must be a positive number of metres, got 0.0"),
    ],
)
def test_resolution_options_are_checked_before_any_work(args, message, tmp_path: Path) -> None:
    res = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "out")])
    assert res.exit_code == exitcodes.EXIT_USAGE and message in res.output, res.output
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------- scans
def test_one_scan_type() -> None:
    from ndtom_ti import io

    assert io.Scan is Scan
    scans = make_scans(2, rings=4, per_ring=30)
    assert all(type(s) is Scan for s in scans) and [s.index for s in scans] == [0, 1]
    # (quality.LabelledScan is ground truth, world-frame points with labels: not a sensor scan)
    defined = [
        p for p in _installed_sources() if re.search(r"^class (?!LabelledScan)\w*Scan\b.*:", p.read_text(), re.M)
    ]
    assert defined == [PACKAGE / "scan.py"], defined
    assert not [p for p in _installed_sources() if re.search(r"^\w*Scan = ", p.read_text(), re.M)]  # no aliases


def test_scan_parts_takes_a_scan_or_a_pair() -> None:
    pts, T = _pair()
    for item in (Scan(pts, T), (pts, T), [pts, T]):
        p, t = scan_parts(item)
        assert p is pts or np.array_equal(p, pts)
        assert t.dtype == np.float64 and np.array_equal(t, T)
    for bad in ((pts, T, 0), pts, None):
        with pytest.raises(TypeError, match=r"\(points, T_world_sensor\) pair"):
            scan_parts(bad)


def test_scans_and_pairs_are_the_same_input(tmp_path: Path) -> None:
    scans = make_scans(3, rings=6, per_ring=60)
    pairs = [(s.points, s.T_world_sensor) for s in scans]
    a, b = load_scans(scans), load_scans(pairs)
    assert len(a.scans) == len(b.scans) == 3
    for x, y in zip(a.scans, b.scans):
        assert np.array_equal(x.points, y.points) and np.array_equal(x.T_world_sensor, y.T_world_sensor)
    rows = [sweep.run_sweep(s, [1.0], floor=False, warmup=0) for s in (scans, pairs)]
    assert rows[0][0].gaussians == rows[1][0].gaussians > 0 and rows[0][0].known_cells == rows[1][0].known_cells


# ---------------------------------------------------------------------------- exit codes
def test_one_set_of_exit_codes() -> None:
    from ndtom_ti.viewer import cli as viewer_cli

    assert (exitcodes.EXIT_OK, exitcodes.EXIT_FAILURE, exitcodes.EXIT_USAGE) == (0, 1, 2)
    assert (exitcodes.EXIT_INTERRUPTED, exitcodes.EXIT_TERMINATED) == (130, 143)
    for name in ("EXIT_OK", "EXIT_FAILURE", "EXIT_USAGE", "EXIT_INTERRUPTED"):
        assert getattr(viewer_cli, name) == getattr(exitcodes, name)
    sig = StopSignals()
    sig.signum = signal.SIGTERM
    assert sig.exit_code == exitcodes.EXIT_TERMINATED
    # no other module defines exit codes of its own
    own = [p for p in _installed_sources() if re.search(r"^\s*EXIT_\w+\s*=", p.read_text(), re.M)]
    assert own == [PACKAGE / "exitcodes.py"], own


# ---------------------------------------------------------------------------- the command
def test_help_lists_the_commands_in_their_order() -> None:
    res = CliRunner().invoke(app, ["--help"], env={"COLUMNS": "120"})
    assert res.exit_code == 0
    names = re.findall(r"^\s{2}(\w+)\s{2,}", res.output.split("Commands:")[1], re.M)
    assert names == ["info", "map", "merge", "demo", "sweep", "experiments", "view", "export"], res.output


def test_nothing_installed_looks_for_the_shared_folder(tmp_path: Path, monkeypatch) -> None:
    # a simworld.py where the old lookups went: $NDTOM_SHARED/tools and ../shared/tools
    for folder in (tmp_path / "env" / "tools", tmp_path / "shared" / "tools"):
        folder.mkdir(parents=True)
        (folder / "simworld.py").write_text("raise SystemExit(3)\n")
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    monkeypatch.setenv("NDTOM_SHARED", str(tmp_path / "env"))
    with pytest.raises(FileNotFoundError, match="not part of ndtom_ti"):
        load_scans("sim:static")
    res = CliRunner().invoke(app, ["experiments", "sim:static", "-r", "0.5", "--out", str(tmp_path / "ex")])
    assert res.exit_code == exitcodes.EXIT_USAGE and "--simworld PATH" in res.output, res.output
    for path in _installed_sources():
        text = path.read_text()
        assert "NDTOM_SHARED" not in text and not re.search(r"""\.\./shared|/ *["']shared["']""", text), path
