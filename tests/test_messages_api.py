"""What a user reads: command help, summaries and hints in plain words (no internal names),
no Taichi start-up line; and the API points: NdtOmMap's keyword options, its grid and data
extents, occupancy of one point."""

from __future__ import annotations

import inspect
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parent))
import test_pipeline_bags as pb  # noqa: E402

from ndtom_ti import MapConfig, NdtOmMap  # noqa: E402
from ndtom_ti.cli import app  # noqa: E402

INTERNAL = ("sensor_frame_only", "tools_dir", "=None", "max_range=None", "_only=")


def run(*args: object, columns: int = 250):
    r = CliRunner(env={"COLUMNS": str(columns)}).invoke(app, [str(a) for a in args])
    assert "Traceback" not in r.output, r.output
    return r


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("bags")
    return {"plane": pb.write_plane_bag(root), "notf": pb.write_plane_bag(root, name="notf", with_tf=False)}


def test_command_list_shows_each_short_help_whole() -> None:
    """Click cuts a short help at its first full stop ("(the paper's Fig.") or at 45
    characters with "..."; each command names its own, on one line at 80 columns."""
    r = run("--help", columns=80)
    assert r.exit_code == 0
    lines = r.output[r.output.index("Commands:") :].splitlines()[1:]
    listed = {}
    for line in lines:
        assert line.startswith("  ") and not line.startswith("   "), line  # no wrapped line
        name, text = line.split(None, 1)
        listed[name] = text
    assert set(listed) == {"info", "map", "merge", "demo", "sweep", "experiments", "view", "export"}
    for name, text in listed.items():
        assert text.endswith(".") and not text.endswith("...") and "Fig.)" not in text, (name, text)
    assert "Figs. 1-5" in listed["experiments"] and "Fig. 5" in listed["sweep"]


@pytest.mark.parametrize("command", ["info", "map", "demo", "sweep", "experiments", "view", "export"])
def test_help_texts_use_no_internal_names(command: str) -> None:
    r = run(command, "--help")
    assert r.exit_code == 0, r.output
    for word in INTERNAL:
        assert word not in r.output, (word, r.output)


def test_summary_says_why_scans_were_left_out(bags, tmp_path: Path) -> None:
    r = run("map", bags["plane"], "-r", "0.5", "--every", "2", "--no-progress", "-o", tmp_path / "m.ndtom")
    assert r.exit_code == 0, r.output
    assert "2 left out by --every" in r.output
    info = run("info", tmp_path / "m.ndtom")
    assert "max_range=inf" in info.output and "sigma_s=15 cells" in info.output and "None" not in info.output


def test_no_pose_hint_names_options_not_parameters(bags, tmp_path: Path) -> None:
    r = run("map", bags["notf"], "-r", "0.5", "-o", tmp_path / "m.ndtom")
    assert r.exit_code == 2 and "--sensor-frame" in r.output
    for word in INTERNAL:
        assert word not in r.output, (word, r.output)


def test_experiments_names_its_simworld_option(tmp_path: Path) -> None:
    r = run("experiments", "sim:static", "-r", "0.4", "--simworld", tmp_path / "none", "--out", tmp_path / "ex")
    assert r.exit_code == 2 and "--simworld PATH" in r.output and str(tmp_path / "none") in r.output, r.output
    assert "tools_dir" not in r.output and not (tmp_path / "ex").exists()
    # The generator is not part of the package, which looks for it nowhere (not in ../shared either).
    r = run("experiments", "sim:static", "-r", "0.4", "--out", tmp_path / "ex")
    assert r.exit_code == 2 and "--simworld PATH" in r.output and "not part of ndtom_ti" in r.output, r.output
    assert "shared" not in r.output and not (tmp_path / "ex").exists()


def test_no_taichi_start_line(tmp_path: Path) -> None:
    """Neither the library's init nor a command prints Taichi's start-up line."""
    code = (
        "import ndtom_ti, numpy as np\nndtom_ti.init('cpu')\nm = ndtom_ti.NdtOmMap(0.5)\n"
        "m.insert_scan(np.ones((10, 3)), np.eye(4))\n"
    )
    env = {**os.environ, "NDTOM_PIN_THREADS": "0"}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env, check=False)
    assert p.returncode == 0, p.stderr
    assert p.stdout == "" and "[Taichi]" not in p.stderr
    p = subprocess.run(
        [sys.executable, "-m", "ndtom_ti", "demo", "--scans", "2", "--no-progress", "--out", str(tmp_path / "d")],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
        check=False,
    )
    assert p.returncode == 0, p.stderr
    assert "[Taichi]" not in p.stdout + p.stderr


def test_map_options_are_keywords() -> None:
    sig = inspect.signature(NdtOmMap.__init__)
    for name in (
        "p_occupied",
        "p_empty",
        "logodds_min",
        "logodds_max",
        "min_points",
        "min_range",
        "max_range",
        "max_range_mode",
        "n_max",
    ):
        assert sig.parameters[name].kind is inspect.Parameter.KEYWORD_ONLY, name
    assert "resolution" in (NdtOmMap.__init__.__doc__ or "") and "p_occupied" in NdtOmMap.__init__.__doc__
    m = NdtOmMap(0.5, p_occupied=0.7, max_range=30.0)
    assert m.config == MapConfig(p_occupied=0.7, max_range=30.0)
    del m
    older = {"min_points": 5}  # older code passing MapConfig fields by name
    m = NdtOmMap(0.5, **older)
    assert m.config.min_points == 5
    del m
    with pytest.raises(TypeError, match=r"unknown map options \['p_hit'\].*p_occupied"):
        NdtOmMap(0.5, p_hit=0.7)
    with pytest.raises(TypeError, match="not both"):
        NdtOmMap(0.5, config=MapConfig(), p_empty=0.45)
    with pytest.raises(ValueError, match="p_occupied"):
        NdtOmMap(0.5, p_occupied=0.4)


def test_grid_and_data_extents() -> None:
    m = NdtOmMap(0.5)
    assert m.data_extent() is None
    lo, hi = m.grid_extent
    np.testing.assert_array_equal(lo, m.grid_extent[0])
    np.testing.assert_array_equal(hi, m.grid_extent[1])
    assert (hi - lo).min() > 1000  # the grid: kilometres
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    m.insert_scan(np.array([[4.2, 0.1, 0.0], [4.3, 0.2, 0.1], [4.25, 0.0, -0.1]]), T)
    dlo, dhi = m.data_extent()
    idx = m.known_cells()["index"]
    np.testing.assert_allclose(dlo, idx.min(0) * 0.5)
    np.testing.assert_allclose(dhi, (idx.max(0) + 1) * 0.5)
    # the sensor's cell and the hit cell are inside; the box is a few metres, not the grid
    assert (dlo <= [1.0, 2.0, 3.0]).all() and (dhi >= [5.25, 2.1, 3.1]).all() and (dhi - dlo).max() < 6
    del m


def test_occupancy_of_one_point() -> None:
    m = NdtOmMap(0.5)
    T = np.eye(4)
    m.insert_scan(np.tile([[3.1, 0.2, 0.3]], (5, 1)), T)
    p = m.occupancy([3.1, 0.2, 0.3])
    assert isinstance(p, float) and p > 0.5
    assert p == m.occupancy(np.array([[3.1, 0.2, 0.3]]))[0]
    p_free, known = m.occupancy(np.array([1.2, 0.1, 0.1]), return_known=True)
    assert isinstance(known, bool) and known and p_free < 0.5
    assert m.occupancy((40.0, 0.0, 0.0), return_known=True) == (0.5, False)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        m.occupancy([1.0, 2.0])
    del m


def test_readme_reads_a_bag_with_ndtom_ti_io() -> None:
    """The README's example of mapping a recording from Python runs as printed."""
    from conftest import DATA, ROOT

    if not (DATA / "balm_hall_every4").exists():
        pytest.skip("shared data not present")
    text = (ROOT / "README.md").read_text()
    at = text.index("from ndtom_ti.io import open_recording")
    code = text[text.rindex("```python", 0, at) + len("```python") : text.index("```", at)]
    code = code.replace("../shared/data", str(DATA))
    env = {**os.environ, "NDTOM_PIN_THREADS": "0"}
    p = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env, cwd=ROOT, check=False
    )
    assert p.returncode == 0, p.stderr
    first, second = p.stdout.splitlines()
    assert "scans=23, gaussians=" in first and "[-23.4, -45. ,  -3.6]" in first
    gaussians = int(first.split("gaussians=")[1].split(",")[0])
    assert abs(gaussians - 39559) < 100  # the README's figure (CPU)
    assert abs(float(second) - 0.1192) < 1e-3
