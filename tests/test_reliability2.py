"""Reliability, round 2 (issue 30): no output ever overwrites an input, every setting and
stored value checked once (API, map file, --config), threads from the first call,
signals, save targets, the viewer's headers and the terminal."""

from __future__ import annotations

import gc
import hashlib
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parent))
import test_pipeline_bags as pb

from ndtom_ti import NdtOmMap
from ndtom_ti.cli import app


@pytest.fixture(autouse=True)
def _free_maps():
    yield
    gc.collect()


def run_cli(*args: object):
    r = CliRunner(env={"COLUMNS": "250"}).invoke(app, [str(a) for a in args])
    assert "Traceback" not in r.output, r.output
    return r


def digest(path: Path) -> str:
    if path.is_dir():
        return hashlib.sha256(b"".join(p.name.encode() + p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file())).hexdigest()
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def small_map_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("map") / "m.ndtom"
    rng = np.random.default_rng(3)
    with NdtOmMap(0.5) as m:
        m.insert_scan(rng.normal(size=(2000, 3)) + [4.0, 0.0, 0.0], np.eye(4))
        m.save(path)
    return path


# ---------------------------------------------------------------------------- 1: outputs that are inputs
def test_map_refuses_an_output_that_is_its_recording(tmp_path):
    bag = pb.write_plane_bag(tmp_path)
    before = digest(bag)
    (tmp_path / "link.bag").symlink_to(bag)
    os.link(bag, tmp_path / "hard.bag")
    for out in (bag, tmp_path / "link.bag", tmp_path / "hard.bag", tmp_path / "sub" / ".." / bag.name):
        (tmp_path / "sub").mkdir(exist_ok=True)
        r = run_cli("map", bag, "-r", pb.RES, "-o", out, "--no-progress")
        assert r.exit_code == 2, (out, r.output)
        assert "Error:" in r.output and "would destroy" in r.output and "Hint:" in r.output
        assert digest(bag) == before


def test_map_refuses_an_output_inside_a_ros2_bag_folder(tmp_path):
    bag = pb.write_plane_bag(tmp_path, "mcap")
    assert bag.is_dir()
    before = digest(bag)
    (tmp_path / "alias").symlink_to(bag)
    for out in (bag / "x.mcap", bag / "metadata.yaml", tmp_path / "alias" / "m.ndtom", bag):
        r = run_cli("map", bag, "-r", pb.RES, "-o", out, "--no-progress")
        assert r.exit_code == 2, (out, r.output)
        assert "Error:" in r.output
        assert digest(bag) == before
    assert sorted(p.name for p in bag.iterdir()) == sorted(p.name for p in bag.iterdir() if not p.name.startswith("."))


def test_map_refuses_an_output_that_is_its_pose_or_config_file(tmp_path):
    bag = pb.write_plane_bag(tmp_path)
    cfg = tmp_path / "c.json"
    cfg.write_text('{"min_points": 4}')
    r = run_cli("map", bag, "-r", pb.RES, "--config", cfg, "-o", cfg, "--no-progress")
    assert r.exit_code == 2 and "config file" in r.output, r.output
    assert cfg.read_text() == '{"min_points": 4}'


def test_export_and_view_html_refuse_to_overwrite_the_map(tmp_path, small_map_file):
    src = tmp_path / "m.ndtom"
    src.write_bytes(small_map_file.read_bytes())
    before = digest(src)
    (tmp_path / "link.ply").symlink_to(src)
    os.link(src, tmp_path / "hard.ply")
    for out in (src, tmp_path / "link.ply", tmp_path / "hard.ply"):
        r = run_cli("export", src, "-o", out, "--format", "ply")
        assert r.exit_code == 2, (out, r.output)
        assert digest(src) == before
    pytest.importorskip("viser")
    for out in (src, tmp_path / "link.ply"):
        r = run_cli("view", src, "--html", out)
        assert r.exit_code == 2, (out, r.output)
        assert "would destroy" in r.output
        assert digest(src) == before
