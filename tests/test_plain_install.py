"""A plain install (no extras): each command works without the optional packages, or says
which extra it needs and how to install it from the repository before it computes anything.

Each command runs in a subprocess where the optional packages cannot be imported
(``sys.modules[name] = None``, as if they were not installed)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA

sys.path.insert(0, str(Path(__file__).resolve().parent))
import test_pipeline_bags as pb  # noqa: E402

from ndtom_ti import extras  # noqa: E402

OPTIONAL = ("viser", "matplotlib", "pyoctomap")
REPO = Path(extras.__file__).resolve().parents[1]
TUM = DATA / "tum_fr2_pioneer_slam2_10f.bag"


def ndtom(cwd: Path, *args: object, hide: tuple[str, ...] = OPTIONAL) -> subprocess.CompletedProcess:
    code = (
        "import sys\n"
        f"for name in {list(hide)!r}:\n    sys.modules[name] = None\n"
        f"sys.argv = ['ndtom'] + {[str(a) for a in args]!r}\n"
        "from ndtom_ti.cli import main\nmain()\n"
    )
    env = {**os.environ, "COLUMNS": "250", "NDTOM_PIN_THREADS": "0"}
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=300, check=False
    )
    r.output = r.stdout + r.stderr  # type: ignore[attr-defined]
    assert "Traceback" not in r.output and "internal error" not in r.output, r.output
    return r


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    return pb.write_plane_bag(tmp_path_factory.mktemp("bag"))


@pytest.fixture(scope="module")
def map_file(tmp_path_factory, bag) -> Path:
    folder = tmp_path_factory.mktemp("map")
    r = ndtom(folder, "map", bag, "-r", "0.5", "--no-progress", "-o", "plane.ndtom")
    assert r.returncode == 0, r.output
    return folder / "plane.ndtom"


def test_the_optional_packages_are_hidden(tmp_path: Path) -> None:
    code = (
        "import sys\nfor n in ('viser', 'matplotlib', 'pyoctomap'):\n    sys.modules[n] = None\n"
        "from ndtom_ti import extras\nprint([extras.available(n) for n in ('viser', 'matplotlib', 'pyoctomap')])\n"
        "import matplotlib\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert r.stdout.strip() == "[False, False, False]" and "ModuleNotFoundError" in r.stderr


@pytest.mark.parametrize(
    "args",
    [
        ["info", "{bag}"],
        ["info", "{map}"],
        ["map", "{bag}", "-r", "0.5", "--no-progress", "-o", "again.ndtom"],
        ["demo", "--scans", "2", "--no-progress", "--out", "demo"],
        ["export", "{map}", "-o", "cells.bt"],
        ["export", "{map}", "-o", "floor.pgm", "--z-min", "1", "--z-max", "2"],
        ["export", "{map}", "-o", "means.ply"],
    ],
    ids=["info-bag", "info-map", "map", "demo", "export-bt", "export-grid", "export-ply"],
)
def test_commands_that_need_no_extra(tmp_path: Path, bag: Path, map_file: Path, args: list[str]) -> None:
    r = ndtom(tmp_path, *(a.format(bag=bag, map=map_file) for a in args))
    assert r.returncode == 0, r.output
    assert "not installed" not in r.output


def test_sweep_without_matplotlib_skips_the_plot_and_says_so_first(tmp_path: Path) -> None:
    r = ndtom(tmp_path, "sweep", "--synthetic", "--scans", "2", "--resolutions", "0.8", "--no-floor", "--out", "sw")
    assert r.returncode == 0, r.output
    note = r.stderr.index("matplotlib is not installed (extra [bench])")
    assert r.stderr.index("warm-up") > note  # said before the work starts
    assert f'pip install -e "{REPO}[bench]"' in r.stderr
    assert (tmp_path / "sw" / "sweep.csv").exists() and not (tmp_path / "sw" / "sweep.png").exists()
    assert "no plot: matplotlib missing" in r.stdout


def test_sweep_octomap_baseline_without_pyoctomap_stops_before_work(tmp_path: Path) -> None:
    r = ndtom(tmp_path, "sweep", "--synthetic", "--scans", "2", "--baseline", "octomap", "--out", "sw")
    assert r.returncode == 1, r.output  # the code of every missing extra (the viewer's below)
    assert "the OctoMap baseline (--baseline octomap) needs the optional package pyoctomap" in r.output
    assert "extra [bench]" in r.output and f'pip install -e "{REPO}[bench]"' in r.output
    assert "warm-up" not in r.output and not (tmp_path / "sw" / "sweep.csv").exists()


@pytest.mark.skipif(not TUM.exists(), reason="shared data not present")
def test_experiments_without_matplotlib_writes_the_csvs(tmp_path: Path) -> None:
    r = ndtom(tmp_path, "experiments", TUM, "-r", "0.5", "--max-scans", "2", "--out", "ex")
    assert r.returncode == 0, r.output
    note = r.stderr.index("matplotlib is not installed (extra [bench]): no PNG plots")
    assert r.stderr.index("reading scans") > note
    assert f'pip install -e "{REPO}[bench]"' in r.stderr
    assert (tmp_path / "ex" / "summary.json").exists() and not list((tmp_path / "ex").glob("*.png"))


@pytest.mark.parametrize(
    "args",
    [
        ["view", "{map}"],
        ["view", "{map}", "--html", "page.html"],
        ["map", "{bag}", "-r", "0.5", "--view", "-o", "live.ndtom"],
        ["demo", "--view"],
    ],
    ids=["view", "view-html", "map-view", "demo-view"],
)
def test_viewer_commands_without_viser_stop_first(tmp_path: Path, bag: Path, map_file: Path, args: list[str]) -> None:
    r = ndtom(tmp_path, *(a.format(bag=bag, map=map_file) for a in args))
    assert r.returncode == 1, r.output
    assert "needs the optional package viser, which is not installed (extra [viewer])" in r.output
    assert f'pip install -e "{REPO}[viewer]"' in r.output
    assert "Mapping" not in r.output and "http" not in r.output
    assert not list(tmp_path.iterdir())  # no map, no page


def test_install_hint_outside_a_repository(monkeypatch) -> None:
    assert extras.repo_root() == REPO  # the tests run on an editable install
    monkeypatch.setattr(extras, "repo_root", lambda: None)
    assert extras.install_hint("viewer") == (
        'in the ndtom_ti repository folder: pip install ".[viewer]"  (or: pip install viser)'
    )


def test_run_experiments_checks_matplotlib_before_reading(monkeypatch, tmp_path: Path) -> None:
    from ndtom_ti.evaluation import run_experiments, sources

    monkeypatch.setattr(extras, "available", lambda name: name != "matplotlib")
    read = []
    monkeypatch.setattr(sources, "load_scans", lambda *a, **k: read.append(1))
    scans = [(np.zeros((10, 3)), np.eye(4))]
    with pytest.raises(extras.ExtraMissingError, match=r"plots=False skips them.*extra \[bench\].*pip install"):
        run_experiments(scans, 0.5, tmp_path / "ex")
    assert not read
