"""`ndtom export` and ndtom_ti.export: each format re-read and compared with the map."""

from __future__ import annotations

import csv
import gc
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parent))
import test_pipeline_bags as pb  # noqa: E402

from ndtom_ti import NdtOmMap  # noqa: E402
from ndtom_ti.cli import app  # noqa: E402
from ndtom_ti.export import COV_TERMS, export_map, write_ply  # noqa: E402
from ndtom_ti.pipeline import map_scans  # noqa: E402

IJ = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


@pytest.fixture(autouse=True)
def _free_maps():
    yield
    gc.collect()


@pytest.fixture(scope="module")
def map_file(tmp_path_factory) -> Path:
    """The plane scene mapped: occupied floor and wall Gaussians, and some freed ones."""
    rng = np.random.default_rng(3)
    m, _ = map_scans([(pb.sensor_points(k, rng), pb.T_map_lidar(k)) for k in range(4)], pb.RES,
                     source="test scene", metadata={"note": "export test"})
    path = m.save(tmp_path_factory.mktemp("maps") / "scene.ndtom")
    del m
    gc.collect()
    return path


def expected(map_file: Path, min_probability: float = 0.5) -> dict:
    m = NdtOmMap.load(map_file)
    g = m.gaussians(min_probability=min_probability)
    del m
    return g


def run(*args: object):
    r = CliRunner(env={"COLUMNS": "250"}).invoke(app, [str(a) for a in args])
    assert "Traceback" not in r.output, r.output
    return r


def read_ply(path: Path) -> tuple[list[str], np.ndarray]:
    """A minimal binary-little-endian PLY reader (independent of ndtom_ti.export)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    assert header[0] == "ply" and header[1] == "format binary_little_endian 1.0"
    types = {"float": "<f4", "double": "<f8", "int": "<i4", "uint": "<u4", "uchar": "u1"}
    props, count = [], None
    for line in header:
        parts = line.split()
        if parts[0] == "element":
            assert parts[1] == "vertex"
            count = int(parts[2])
        elif parts[0] == "property":
            props.append((parts[2], types[parts[1]]))
    arr = np.frombuffer(data[end:], dtype=np.dtype(props), count=count)
    assert len(data) == end + arr.nbytes  # nothing after the vertices
    return header, arr


def test_ply_holds_occupied_gaussians(map_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "cells.ply"
    r = run("export", map_file, "--format", "ply", "-o", out)
    assert r.exit_code == 0, r.output
    g = expected(map_file)
    assert f"Exported {len(g['n']):,} Gaussians" in r.output
    header, v = read_ply(out)
    names = [ln.split()[-1] for ln in header if ln.startswith("property")]
    assert names == ["x", "y", "z", "p_occ", "n", *COV_TERMS]
    assert "property float x" in header and "property int n" in header
    assert len(v) == len(g["n"]) > 100
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), g["mean"].astype(np.float32))
    np.testing.assert_array_equal(v["n"], g["n"])
    np.testing.assert_array_equal(v["p_occ"], g["p_occ"].astype(np.float32))
    assert (v["p_occ"] > 0.5).all()
    for name, (a, b) in zip(COV_TERMS, IJ):
        np.testing.assert_array_equal(v[name], g["cov"][:, a, b].astype(np.float32))
    assert np.abs(v["z"][np.abs(v["z"] - pb.PLANE_Z) < 0.2] - pb.PLANE_Z).max() < 0.01  # the floor


def test_npz_holds_the_full_arrays(map_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "all.npz"
    r = run("export", map_file, "-f", "npz", "-o", out, "--min-probability", "0")
    assert r.exit_code == 0, r.output
    g = expected(map_file, 0.0)
    occupied = expected(map_file, 0.5)
    with np.load(out) as z:
        assert set(z.files) == {"index", "mean", "cov", "n", "p_occ", "logodds", "resolution", "metadata"}
        for k in ("index", "mean", "cov", "n", "p_occ", "logodds"):
            np.testing.assert_array_equal(z[k], g[k])
        assert float(z["resolution"]) == pb.RES
        md = json.loads(str(z["metadata"]))
    assert md["note"] == "export test" and md["source"] == "test scene"
    assert len(g["n"]) >= len(occupied["n"])


def test_csv_has_a_header_and_one_row_per_gaussian(map_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "g.csv"
    r = run("export", map_file, "-o", out)  # the format comes from the suffix
    assert r.exit_code == 0, r.output
    g = expected(map_file)
    with out.open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["i", "j", "k", "x", "y", "z", "n", "p_occ", "logodds", *COV_TERMS]
    body = np.array(rows[1:], dtype=np.float64)
    assert len(body) == len(g["n"])
    np.testing.assert_array_equal(body[:, 0:3], g["index"])
    np.testing.assert_array_equal(body[:, 3:6], g["mean"])  # written with repr: exact
    np.testing.assert_array_equal(body[:, 6], g["n"])
    np.testing.assert_array_equal(body[:, 7], g["p_occ"])
    np.testing.assert_array_equal(body[:, 8], g["logodds"])
    for col, (a, b) in enumerate(IJ, start=9):
        np.testing.assert_array_equal(body[:, col], g["cov"][:, a, b])


def test_default_output_and_min_probability(map_file: Path, tmp_path: Path) -> None:
    local = tmp_path / "scene.ndtom"
    local.write_bytes(map_file.read_bytes())
    r = run("export", local)  # ply next to the map
    assert r.exit_code == 0, r.output
    _, v_all = read_ply(tmp_path / "scene.ply")
    r = run("export", local, "--min-probability", "0.8", "-o", tmp_path / "sure.ply")
    assert r.exit_code == 0, r.output
    _, v_sure = read_ply(tmp_path / "sure.ply")
    assert len(v_sure) == len(expected(map_file, 0.8)["n"]) <= len(v_all)
    assert (v_sure["p_occ"] > 0.8).all()


@pytest.mark.parametrize("setup, args, texts", [
    (lambda t, m: t / "missing.ndtom", [], ["no map file at"]),
    (lambda t, m: (t / "x.ndtom").write_text("hello") and t / "x.ndtom", [], ["not an ndtom_ti map file"]),
    (lambda t, m: (t / "cut.ndtom").write_bytes(m.read_bytes()[:-100]) and t / "cut.ndtom", [], ["truncated"]),
    (lambda t, m: m, ["-o", "{t}/nope/out.ply"], ["folder", "does not exist"]),
    (lambda t, m: m, ["--min-probability", "1.5"], ["--min-probability must be in [0, 1)"]),
    (lambda t, m: m, ["-f", "las"], ["Invalid value for '-f' / '--format'"]),
    (lambda t, m: m, ["-o", "{m}"], ["is the map file itself"]),
], ids=["missing", "not-a-map", "truncated", "no-folder", "probability", "format", "overwrite-map"])
def test_export_errors_exit_2(map_file: Path, tmp_path: Path, setup, args, texts) -> None:
    path = setup(tmp_path, map_file)
    args = [a.format(t=tmp_path, m=map_file) for a in args]
    before = map_file.read_bytes()
    r = run("export", path, *args)
    assert r.exit_code == 2, r.output
    for t in texts:
        assert t in r.output, (t, r.output)
    assert map_file.read_bytes() == before


def test_python_api_and_empty_maps(tmp_path: Path) -> None:
    empty = {"index": np.zeros((0, 3), np.int64), "mean": np.zeros((0, 3)), "cov": np.zeros((0, 3, 3)),
             "n": np.zeros(0, np.int64), "p_occ": np.zeros(0), "logodds": np.zeros(0)}
    header, v = read_ply(write_ply(empty, tmp_path / "empty.ply", comment="nothing"))
    assert len(v) == 0 and "element vertex 0" in header and "comment nothing" in header
    m = NdtOmMap(0.5)
    path, k = export_map(m, tmp_path / "e.csv")
    assert k == 0 and path.read_text().count("\n") == 1
    with pytest.raises(ValueError, match="unknown export format"):
        export_map(m, tmp_path / "e.xyz")
    del m
