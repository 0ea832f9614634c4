"""`ndtom experiments` end to end on a small real input, and its bad options."""

import json

import pytest
from conftest import DATA
from typer.testing import CliRunner

from ndtom_ti.cli import app

TUM = DATA / "tum_fr2_pioneer_slam2_10f.bag"


@pytest.mark.skipif(not TUM.exists(), reason="shared data not present")
def test_cli_experiments_on_tum(tmp_path):
    res = CliRunner().invoke(
        app, ["experiments", str(TUM), "-r", "0.3", "--max-scans", "3", "--no-plots", "--out", str(tmp_path / "ex")]
    )
    assert res.exit_code == 0, res.output
    s = json.loads((tmp_path / "ex" / "summary.json").read_text())
    assert s["fig1_final_score"]["rcu"] >= 0.999
    assert s["fig1_final_score"]["er"] < s["fig1_final_score"]["rcu"]
    assert s["fig4d"]["coarse_resolution"] == pytest.approx(0.9)
    assert "Fig. 4b" in res.output


@pytest.mark.parametrize(
    "args,message",
    [
        (["-r", "-0.2"], "positive"),
        (["-r", "0.3", "--sweep", "a"], "numbers separated by commas"),
    ],
)
def test_cli_experiments_bad_options(tmp_path, args, message):
    res = CliRunner().invoke(app, ["experiments", str(TUM), *args, "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and message in res.output, res.output


def test_cli_experiments_missing_recording(tmp_path):
    res = CliRunner().invoke(app, ["experiments", str(tmp_path / "nope.bag"), "-r", "0.3", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "Error" in res.output, res.output
