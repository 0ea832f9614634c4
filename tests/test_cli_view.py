"""`ndtom view`, `ndtom map --view` and `ndtom demo --view` as wired in the CLI."""

import numpy as np
import pytest
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
    # a page never replaces a recording or a map (another one, here a copy)
    for victim, kind in ((tmp_path / "rec.bag", "a ROS1 bag"), (tmp_path / "other.ndtom", "an ndtom map file")):
        victim.write_bytes(b"#ROSBAG V2.0\n" + bytes(100) if kind == "a ROS1 bag" else path.read_bytes())
        before = victim.read_bytes()
        res = CliRunner().invoke(app, ["view", str(path), "--html", str(victim)])
        assert res.exit_code == 2 and f"it is {kind}" in res.output, res.output
        assert victim.read_bytes() == before


def test_map_view_maps_the_recording_live_and_saves_it(tmp_path, monkeypatch):
    pytest.importorskip("viser")
    from ndtom_ti.viewer import cli as vcli

    bag = write_plane_bag(tmp_path, "ros1")
    served = []
    # private: the command's wait for Ctrl-C after mapping has no public hook
    monkeypatch.setattr(vcli, "_serve_until_stopped", lambda viewer, stop: served.append(viewer.url))
    out = tmp_path / "live.ndtom"
    res = CliRunner().invoke(
        app, ["map", str(bag), "-r", "0.5", "-o", str(out), "--view", "--no-wait", "--rate", "max", "--port", "0"]
    )
    assert res.exit_code == 0, res.output
    # the same summary as `ndtom map`, and the map written with its metadata
    assert "Mapping summary" in res.output and "scans used" in res.output and "Map written to" in res.output
    assert "NDT-OM viewer: http://127.0.0.1:" in res.output and len(served) == 1
    m = NdtOmMap.load(out)
    assert m.scans_inserted > 0 and m.metadata["command"] == "ndtom map --view" and m.metadata["complete"]
    assert m.metadata["summary"]["scans_used"] == m.scans_inserted and m.metadata["cloud_topic"]
    plain = tmp_path / "plain.ndtom"
    assert CliRunner().invoke(app, ["map", str(bag), "-r", "0.5", "-o", str(plain)]).exit_code == 0
    ref = NdtOmMap.load(plain)
    assert ref.scans_inserted == m.scans_inserted and len(ref) == len(m)


def test_map_view_bad_rate(tmp_path):
    bag = write_plane_bag(tmp_path, "ros1")
    res = CliRunner().invoke(
        app, ["map", str(bag), "-r", "0.5", "-o", str(tmp_path / "x.ndtom"), "--view", "--rate", "fast"]
    )
    assert res.exit_code == 2 and "--rate" in res.output
    assert not (tmp_path / "x.ndtom").exists()
