"""`ndtom view`, `ndtom map --view` and `ndtom demo --view` as wired in the CLI."""

import numpy as np
from test_pipeline_bags import write_plane_bag
from typer.testing import CliRunner

from ndtom_ti import NdtOmMap
from ndtom_ti.cli import app


def test_view_html_snapshot_and_missing_map(tmp_path):
    m = NdtOmMap(0.5)
    m.insert_scan(np.random.default_rng(0).normal(size=(2000, 3)) * [3, 3, 0.05] + [0, 0, -1.0], np.eye(4))
    path = m.save(tmp_path / "m.ndtom")
    del m
    res = CliRunner().invoke(app, ["view", str(path), "--html", str(tmp_path / "snap.html")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "snap.html").stat().st_size > 10000
    res = CliRunner().invoke(app, ["view", str(tmp_path / "absent.ndtom")])
    assert res.exit_code == 2


def test_map_view_hands_the_scans_to_the_live_viewer(tmp_path, monkeypatch):
    bag = write_plane_bag(tmp_path, "ros1")
    seen = {}

    def fake_live(scans, resolution, host, port, *, config=None, save=None, **kw):
        seen.update(n=sum(1 for _ in scans), resolution=resolution, host=host, port=port, save=save)
        return 0

    monkeypatch.setattr("ndtom_ti.viewer.cli.live_command", fake_live)
    out = tmp_path / "live.ndtom"
    res = CliRunner().invoke(app, ["map", str(bag), "-r", "0.5", "-o", str(out), "--view", "--port", "9123"])
    assert res.exit_code == 0, res.output
    assert seen["n"] > 0 and seen["resolution"] == 0.5 and seen["port"] == 9123
    assert seen["host"] == "127.0.0.1" and seen["save"] == out


def test_demo_view_runs_the_live_demo(monkeypatch):
    seen = {}
    monkeypatch.setattr("ndtom_ti.viewer.cli.live_demo_command",
                        lambda host, port, **kw: seen.update(host=host, port=port, **kw) or 0)  # fmt: skip
    res = CliRunner().invoke(app, ["demo", "--view", "--port", "9124", "--scans", "5"])
    assert res.exit_code == 0, res.output
    assert seen == {"host": "127.0.0.1", "port": 9124, "resolution": 0.2, "n_scans": 5}
