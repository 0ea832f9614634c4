"""`ndtom export` and ndtom_ti.export: each format re-read and compared with the map."""

from __future__ import annotations

import csv
import gc
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parent))
import test_pipeline_bags as pb  # noqa: E402

from ndtom_ti import NdtOmMap  # noqa: E402
from ndtom_ti.cli import app  # noqa: E402
from ndtom_ti.export import COV_TERMS, export_file, export_map, write_bt, write_ply  # noqa: E402
from ndtom_ti.pipeline import map_scans  # noqa: E402

IJ = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


@pytest.fixture(scope="module")
def map_file(tmp_path_factory) -> Path:
    """The plane scene mapped: occupied floor and wall Gaussians, and some freed ones."""
    rng = np.random.default_rng(3)
    m, _ = map_scans(
        [(pb.sensor_points(k, rng), pb.T_map_lidar(k)) for k in range(4)],
        pb.RES,
        source="test scene",
        metadata={"note": "export test"},
    )
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
    assert names == ["x", "y", "z", "red", "green", "blue", "p_occ", "n", *COV_TERMS]
    assert "property float x" in header and "property int n" in header and "property uchar red" in header
    assert len(v) == len(g["n"]) > 100
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), g["mean"].astype(np.float32))
    np.testing.assert_array_equal(v["n"], g["n"])
    np.testing.assert_array_equal(v["p_occ"], g["p_occ"].astype(np.float32))
    assert (v["p_occ"] > 0.5).all()
    for name, (a, b) in zip(COV_TERMS, IJ):
        np.testing.assert_array_equal(v[name], g["cov"][:, a, b].astype(np.float32))
    assert np.abs(v["z"][np.abs(v["z"] - pb.PLANE_Z) < 0.2] - pb.PLANE_Z).max() < 0.01  # the floor
    # colour: the height ramp blue, cyan, green, yellow, red over the range the header states
    (line,) = [ln for ln in header if ln.startswith("comment colour: height")]
    words = line.split()
    lo, hi = float(words[words.index("<=") + 1]), float(words[words.index(">=") + 1])
    assert lo < pb.PLANE_Z + 0.05 and hi > 2.0  # floor to wall top
    t = np.clip((v["z"].astype(np.float64) - lo) / (hi - lo), 0, 1) * 4
    ramp = np.array([[0, 0, 255], [0, 255, 255], [0, 255, 0], [255, 255, 0], [255, 0, 0]], np.float64)
    want = np.stack([np.interp(t, np.arange(5), ramp[:, c]) for c in range(3)], axis=1)
    got = np.stack([v["red"], v["green"], v["blue"]], axis=1).astype(np.float64)
    assert np.abs(got - want).max() <= 1.0
    floor_rgb = got[np.abs(v["z"] - pb.PLANE_Z) < 0.05]
    assert len(floor_rgb) and (floor_rgb[:, 2] > 200).all() and (floor_rgb[:, 0] < 30).all()  # floor blue
    assert (got[v["z"] > hi][:, 0] == 255).all() and len(np.unique(got, axis=0)) > 20  # top red, a ramp


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


@pytest.mark.parametrize(
    "setup, args, texts",
    [
        (lambda t, m: t / "missing.ndtom", [], ["no map file at"]),
        (lambda t, m: (t / "x.ndtom").write_text("hello") and t / "x.ndtom", [], ["not an ndtom_ti map file"]),
        (lambda t, m: (t / "cut.ndtom").write_bytes(m.read_bytes()[:-100]) and t / "cut.ndtom", [], ["truncated"]),
        (lambda t, m: m, ["-o", "{t}/nope/out.ply"], ["folder", "does not exist"]),
        (lambda t, m: m, ["--min-probability", "1.5"], ["--min-probability must be in [0, 1)"]),
        (lambda t, m: m, ["-f", "las"], ["Invalid value for '-f' / '--format'"]),
        (lambda t, m: m, ["-f", "ply", "-o", "{m}"], ["is the map file", "would destroy it"]),
        (lambda t, m: m, ["-o", "{t}/h.xyz"], ["cannot tell the export format", "'.xyz'", "--format"]),
        (lambda t, m: m, ["-o", "{t}/h"], ["cannot tell the export format", "no suffix"]),
        (lambda t, m: m, ["-f", "ply", "-o", "{t}/h.csv"], ["suffix of the csv format", "asked for is ply"]),
        (lambda t, m: m, ["-o", "{t}/h.ply", "--z-min", "1"], ["height band of --format grid only"]),
        (lambda t, m: m, ["-o", "{t}/h.pgm", "--z-min", "2", "--z-max", "1"], ["--z-min (2.0) must be below"]),
        (lambda t, m: m, ["-o", "{t}/h.pgm", "--z-max", "1"], ["give --z-min and --z-max together"]),
        (
            lambda t, m: m,
            ["-o", "{t}/h.pgm", "--z-min", "40", "--z-max", "41"],
            ["no known cells in the height band", "known cells span z"],
        ),
    ],
    ids=[
        "missing",
        "not-a-map",
        "truncated",
        "no-folder",
        "probability",
        "format",
        "overwrite-map",
        "unknown-suffix",
        "no-suffix",
        "suffix-conflict",
        "band-not-grid",
        "band-order",
        "band-half",
        "band-empty",
    ],
)
def test_export_errors_exit_2(map_file: Path, tmp_path: Path, setup, args, texts) -> None:
    path = setup(tmp_path, map_file)
    args = [a.format(t=tmp_path, m=map_file) for a in args]
    before = map_file.read_bytes()
    r = run("export", path, *args)
    assert r.exit_code == 2, r.output
    for t in texts:
        assert t in r.output, (t, r.output)
    assert map_file.read_bytes() == before
    assert not list(tmp_path.glob("h*"))  # nothing written


def test_export_to_a_folder_writes_nothing(map_file: Path, tmp_path: Path) -> None:
    """A target that is a folder is refused before anything is written, with a file name of
    the format's suffix as the hint (it said ``map.ndtom``); for a grid, either of its two
    files: a YAML path that was a folder left the PGM written and exited 1."""
    (tmp_path / "d.ply").mkdir()
    r = run("export", map_file, "-o", tmp_path / "d.ply")
    assert r.exit_code == 2 and "is a folder" in r.output and "d.ply/map.ply" in r.output, r.output
    (tmp_path / "g.yaml").mkdir()
    for out in ("g.pgm", "g.yaml", "g"):
        r = run("export", map_file, "-f", "grid", "-o", tmp_path / out, "--z-min", 1, "--z-max", 2)
        assert r.exit_code == 2, r.output
        assert "g.yaml is a folder" in r.output and "g.yaml/map.pgm" in r.output, r.output
    m = NdtOmMap.load(map_file)
    with pytest.raises(IsADirectoryError, match="g.yaml: it is a folder"):
        export_file(m, tmp_path / "g.pgm", z_min=1.0, z_max=2.0)
    del m
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.ply", "g.yaml"]  # no PGM, no temporaries


def test_python_api_and_empty_maps(tmp_path: Path) -> None:
    empty = {
        "index": np.zeros((0, 3), np.int64),
        "mean": np.zeros((0, 3)),
        "cov": np.zeros((0, 3, 3)),
        "n": np.zeros(0, np.int64),
        "p_occ": np.zeros(0),
        "logodds": np.zeros(0),
    }
    header, v = read_ply(write_ply(empty, tmp_path / "empty.ply", comment="nothing"))
    assert len(v) == 0 and "element vertex 0" in header and "comment nothing" in header
    m = NdtOmMap(0.5)
    path, k = export_map(m, tmp_path / "e.csv")
    assert k == 0 and path.read_text().count("\n") == 1
    with pytest.raises(ValueError, match="cannot tell the export format"):
        export_map(m, tmp_path / "e.xyz")
    with pytest.raises(ValueError, match="unknown export format"):
        export_map(m, tmp_path / "e.ply", "las")
    path, k = export_map(m, tmp_path / "e.bt")  # an empty tree: a header and no nodes
    assert k == 0 and b"\nsize 0\n" in path.read_bytes() and path.read_bytes().endswith(b"data\n")
    _, v = read_pcd(export_map(m, tmp_path / "e.pcd")[0])
    assert len(v) == 0
    del m


def read_pcd(path: Path) -> tuple[dict, np.ndarray]:
    """A minimal reader of binary PCD 0.7 files (independent of ndtom_ti.export)."""
    data = path.read_bytes()
    head, pos = {}, 0
    while True:
        end = data.index(b"\n", pos)
        line = data[pos:end].decode("ascii")
        pos = end + 1
        if line.startswith("#"):
            continue
        key, *vals = line.split()
        head[key] = vals
        if key == "DATA":
            break
    # PCL's writer's order. Found with pcl_pcd2ply (PCL 1.13) and Open3D 0.20: both fail on a
    # FIELDS after SIZE/TYPE/COUNT, PCL on a TYPE before SIZE; DATA ends the header
    assert list(head) == [
        "VERSION",
        "FIELDS",
        "SIZE",
        "TYPE",
        "COUNT",
        "WIDTH",
        "HEIGHT",
        "VIEWPOINT",
        "POINTS",
        "DATA",
    ]
    assert len(head["VIEWPOINT"]) == 7 and all(len(head[k]) == len(head["FIELDS"]) for k in ("SIZE", "TYPE", "COUNT"))
    assert head["VERSION"] == ["0.7"] and head["DATA"] == ["binary"] and head["HEIGHT"] == ["1"]
    kinds = {("F", "4"): "<f4", ("U", "4"): "<u4", ("I", "4"): "<i4", ("F", "8"): "<f8"}
    assert set(head["COUNT"]) == {"1"}
    dt = np.dtype([(n, kinds[t, z]) for n, t, z in zip(head["FIELDS"], head["TYPE"], head["SIZE"])])
    count = int(head["POINTS"][0])
    assert int(head["WIDTH"][0]) == count
    v = np.frombuffer(data[pos:], dtype=dt, count=count)
    assert len(data) == pos + v.nbytes
    return head, v


def test_pcd_holds_means_n_and_occupancy(map_file: Path, tmp_path: Path) -> None:
    out = tmp_path / "means.pcd"
    r = run("export", map_file, "-o", out)
    assert r.exit_code == 0, r.output
    assert f"to {out}" in r.output
    g = expected(map_file)
    head, v = read_pcd(out)
    assert head["FIELDS"] == ["x", "y", "z", "n", "p_occ"]
    assert len(v) == len(g["n"]) > 100
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), g["mean"].astype(np.float32))
    np.testing.assert_array_equal(v["n"], g["n"])
    np.testing.assert_array_equal(v["p_occ"], g["p_occ"].astype(np.float32))


def test_a_shifted_maps_exports_say_its_frame_origin(map_file: Path, tmp_path: Path) -> None:
    """A map made in a shifted frame (georeferenced poses, pipeline.frame_origin): PLY and
    PCD headers, the .bt's and the npz's metadata say where the file's (0, 0, 0) lies; a
    CSV cannot, and its export says so; the grid's origin is in the poses' frame, as
    map_server places it."""
    m = NdtOmMap.load(map_file)
    plain = export_map(m, tmp_path / "plain.ply")[0]
    assert not [line for line in read_ply(plain)[0] if "frame_origin" in line]
    for fmt in ("csv", "bt"):
        assert export_file(m, tmp_path / f"plain.{fmt}").notes == []
    export_file(m, tmp_path / "plain.pgm", z_min=1.0, z_max=2.0)
    m.metadata["frame_origin"] = [512_300.0, 5_412_300.0, 0.0]
    for fmt in ("csv", "bt"):
        (said,) = export_file(m, tmp_path / f"m.{fmt}").notes
        assert "shifted frame: frame_origin 512300.000 5412300.000 0.000" in said
    assert b"\n# frame_origin 512300.000 5412300.000 0.000: add it" in (tmp_path / "m.bt").read_bytes()[:400]
    try:
        import pyoctomap
    except ImportError:
        pass
    else:  # OctoMap's reader skips the comment line
        trees = [pyoctomap.OcTree(1.0) for _ in range(2)]
        assert all(t.readBinary(str(tmp_path / f"{n}.bt")) for t, n in zip(trees, ("plain", "m"), strict=True))
        assert trees[0].size() == trees[1].size() > 100
    export_file(m, tmp_path / "m.pgm", z_min=1.0, z_max=2.0)
    assert (tmp_path / "m.pgm").read_bytes() == (tmp_path / "plain.pgm").read_bytes()
    (x0, y0, _), (x1, y1, _) = (
        read_map_yaml(tmp_path / "plain.yaml")["origin"],
        read_map_yaml(tmp_path / "m.yaml")["origin"],
    )
    assert (x1 - x0, y1 - y0) == pytest.approx((512_300.0, 5_412_300.0), abs=1e-6)
    assert "frame_origin 512300.000 5412300.000 0.000 added" in (tmp_path / "m.yaml").read_text()
    note = "frame_origin 512300.000 5412300.000 0.000: add it to these coordinates for the recording's frame"
    header, v = read_ply(export_map(m, tmp_path / "m.ply")[0])
    assert f"comment {note}" in header and len(v) > 100
    head, v2 = read_pcd(export_map(m, tmp_path / "m.pcd")[0])
    assert len(v2) == len(v) and (tmp_path / "m.pcd").read_bytes().split(b"\n")[1] == f"# {note}".encode()
    with np.load(export_map(m, tmp_path / "m.npz")[0]) as z:
        assert json.loads(str(z["metadata"]))["frame_origin"] == [512_300.0, 5_412_300.0, 0.0]
    m.metadata["frame_origin"] = "east"  # damaged metadata: no note, the export goes on
    assert not [line for line in read_ply(export_map(m, tmp_path / "d.ply")[0])[0] if "frame_origin" in line]
    del m


def known(map_file: Path) -> dict:
    m = NdtOmMap.load(map_file)
    k = m.known_cells()
    del m
    return k


def test_bt_is_read_by_octomap(map_file: Path, tmp_path: Path) -> None:
    """OctoMap's own reader loads the tree; every known cell queried at its centre has the
    map's state, cells never seen are unknown, and the bytes equal OctoMap's own writer's."""
    pyoctomap = pytest.importorskip("pyoctomap", reason="the .bt check needs OctoMap's reader (pyoctomap)")
    out = tmp_path / "cells.bt"
    r = run("export", map_file, "-o", out)
    assert r.exit_code == 0, r.output
    k = known(map_file)
    occ, free = k["p_occ"] > 0.5, k["p_occ"] < 0.5
    assert occ.sum() > 100 and free.sum() > 1000
    assert f"{occ.sum():,} occupied and {free.sum():,} free cells" in r.output and str(out) in r.output

    tree = pyoctomap.OcTree(1.0)
    assert tree.readBinary(str(out))
    assert tree.getResolution() == pb.RES
    res = pb.RES
    for cell, is_occ in zip(k["index"], occ):
        node = tree.search((cell + 0.5) * res)
        assert node is not None and tree.isNodeOccupied(node) == is_occ, cell
    # a point beside each occupied cell's centre (not only the centre) falls in it
    for cell in k["index"][occ][:50]:
        node = tree.search((cell + np.array([0.01, 0.99, 0.5])) * res)
        assert node is not None and tree.isNodeOccupied(node)
    # known cells are a tiny part of their bounding box: unknown cells stay unknown
    lo, hi = k["index"].min(0), k["index"].max(0)
    rng = np.random.default_rng(0)
    probe = rng.integers(lo, hi + 1, (2000, 3))
    keys = {tuple(c) for c in k["index"].tolist()}
    unknown = [c for c in probe.tolist() if tuple(c) not in keys]
    assert len(unknown) > 500
    for cell in unknown:
        assert tree.search((np.array(cell) + 0.5) * res) is None, cell
    # the wall and the floor, at world coordinates
    wall = tree.search(np.array([pb.WALL_X, 0.5, 1.5]))
    assert wall is not None and tree.isNodeOccupied(wall)

    # OctoMap's own writer, given the same cells, writes the same tree byte for byte
    ref = pyoctomap.OcTree(res)
    for cell, is_occ in zip(k["index"][occ | free], occ[occ | free]):
        ref.updateNode((cell + 0.5) * res, bool(is_occ))
    ref.writeBinary(str(tmp_path / "ref.bt"))
    ours, theirs = out.read_bytes(), (tmp_path / "ref.bt").read_bytes()
    assert ours[ours.index(b"\nid OcTree\n") :] == theirs[theirs.index(b"\nid OcTree\n") :]


def test_bt_merges_full_octants_and_rejects_cells_beyond_octomap(tmp_path: Path) -> None:
    from ndtom_ti.export import octree_stream

    block = np.stack(np.meshgrid(*[np.arange(8, 10)] * 3, indexing="ij"), -1).reshape(-1, 3)
    n_one, one = octree_stream(block[:1], [True])
    n_all, full = octree_stream(block, np.ones(8, bool))  # eight siblings: one leaf a level up
    assert n_one == 17 and len(one) == 2 * 16  # root, 15 inner nodes, the leaf; 2 bytes per non-leaf
    assert n_all == 16 and len(full) == 2 * 15
    n_mixed, mixed = octree_stream(block, block[:, 2] == 9)  # mixed states stay eight leaves
    assert n_mixed == 16 + 8 and len(mixed) == 2 * 16
    assert mixed[-2:] == bytes([0b01010101, 0b10101010])  # children 0-3 free (01), 4-7 (z up) occupied (10)
    with pytest.raises(ValueError, match="beyond OctoMap's tree"):
        octree_stream([[0, 0, 40000]], [True])
    with pytest.raises(ValueError, match="twice"):
        octree_stream([[1, 2, 3], [1, 2, 3]], [True, False])
    # a map of a grid larger than the default (Layout) can hold cells past OctoMap's keys:
    # the refusal says it in metres and names the coarser resolution that fits
    with pytest.raises(ValueError, match=r"reach 4000\.1 m .* \+-3276\.8 m at 0\.1 m cells.* 0\.2 m cells fits"):
        write_bt([[-5, 0, 0], [40000, 0, 0]], [True, False], 0.1, tmp_path / "far.bt")
    with pytest.raises(ValueError, match=r"reach 3276\.9 m .* 0\.2 m cells fits"):
        write_bt([[-32769, 0, 0]], [True], 0.1, tmp_path / "far.bt")
    assert write_bt([[-32768, 0, 32767]], [True], 0.1, tmp_path / "edge.bt").is_file()  # the last keys fit
    assert not (tmp_path / "far.bt").exists()


def read_pgm(path: Path) -> np.ndarray:
    """A minimal reader of binary (P5, 8-bit) PGM images."""
    data = path.read_bytes()
    tokens, pos = [], 0
    while len(tokens) < 4:
        while data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end : end + 1].isspace():
            end += 1
        tokens.append(data[pos:end].decode("ascii"))
        pos = end
    pos += 1  # the one whitespace after maxval
    assert tokens[0] == "P5" and tokens[3] == "255"
    w, h = int(tokens[1]), int(tokens[2])
    assert len(data) == pos + w * h
    return np.frombuffer(data[pos:], np.uint8).reshape(h, w)


def read_map_yaml(path: Path) -> dict:
    """map_server's YAML keys (flat ``key: value`` lines, the origin a list), read by YAML's
    rules for scalars (as yaml-cpp and PyYAML read them): a double-quoted value is a JSON
    string; a plain one ends at `` #`` (a comment), may not hold ``: `` and may not start
    with an indicator character (``[``, ``&``, ``#``, ...): such a line is an error."""
    out: dict = {}
    for line in path.read_text().splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        key, value = line.split(":", 1)
        value = value.strip()
        if value.startswith('"'):
            out[key], end = json.JSONDecoder().raw_decode(value)
            assert not value[end:].strip() or value[end:].strip().startswith("#"), line
            continue
        value = value.split(" #", 1)[0].strip()
        assert ": " not in value and not value.endswith(":"), f"a YAML error: {line!r}"
        assert value[:1] not in set("-?:,[]{}#&*!|>'%@`") or value.startswith("["), f"a YAML error: {line!r}"
        if value.startswith("["):
            out[key] = [float(x) for x in value.strip("[]").split(",")]
        else:
            try:
                out[key] = float(value)
            except ValueError:
                out[key] = value
    return out


def test_grid_yaml_names_any_image(map_file: Path, tmp_path: Path) -> None:
    """The YAML's ``image`` names the PGM whatever its name: plain when YAML reads it back
    as written, quoted otherwise (``run #3.pgm`` was read as ``run``, and ``site: a.pgm`` or
    ``[old].pgm`` made map_server's YAML fail; checked with PyYAML)."""
    m = NdtOmMap.load(map_file)
    for name in ("floor_2.pgm", "run #3.pgm", "site: a.yaml", "[old] &x.pgm", "'q\"é.pgm"):
        pgm, yml = export_file(m, tmp_path / name, z_min=1.0, z_max=2.0).paths
        meta = read_map_yaml(yml)
        assert meta["image"] == pgm.name and (yml.parent / meta["image"]).is_file(), (name, yml.read_text())
        assert meta["resolution"] == pb.RES and len(meta["origin"]) == 3
        try:
            import yaml
        except ImportError:
            continue
        assert yaml.safe_load(yml.read_text())["image"] == pgm.name
    assert "image: floor_2.pgm\n" in (tmp_path / "floor_2.yaml").read_text()  # plain where it can be
    del m


def test_grid_is_a_map_server_map(map_file: Path, tmp_path: Path) -> None:
    """The PGM + YAML pair, read as map_server reads it: each pixel's state is that of the
    cells of its column in the band, at the place the YAML origin puts it."""
    out = tmp_path / "floor.pgm"
    z0, z1 = 1.0, 2.0
    r = run("export", map_file, "-o", out, "--z-min", z0, "--z-max", z1)
    assert r.exit_code == 0, r.output
    yml = tmp_path / "floor.yaml"
    assert str(out) in r.output and str(yml) in r.output
    meta = read_map_yaml(yml)
    assert meta["image"] == "floor.pgm" and meta["mode"] == "trinary" and meta["negate"] == 0
    assert meta["resolution"] == pb.RES and meta["origin"][2] == 0.0
    assert np.allclose(np.array(meta["origin"][:2]) / pb.RES, np.round(np.array(meta["origin"][:2]) / pb.RES))
    img = read_pgm(out)
    h, w = img.shape
    ox, oy = meta["origin"][:2]
    # map_server: p = (255 - value) / 255; occupied above occupied_thresh, free below free_thresh
    p = (255.0 - img) / 255.0
    state = np.where(p > meta["occupied_thresh"], 1, np.where(p < meta["free_thresh"], 0, -1))
    assert set(np.unique(state)) == {-1, 0, 1}

    k = known(map_file)
    res = pb.RES
    zc = (k["index"][:, 2] + 0.5) * res
    in_band = (zc + res / 2 > z0) & (zc - res / 2 < z1)
    want: dict = {}
    for cell, prob in zip(k["index"][in_band], k["p_occ"][in_band]):
        key = (int(cell[0]), int(cell[1]))
        s = 1 if prob > 0.5 else (0 if prob < 0.5 else -1)
        want[key] = max(want.get(key, -1), s)
    for row in range(h):
        for col in range(w):
            # the pixel's centre in the map frame: row 0 is the top of the image (largest y)
            x = ox + (col + 0.5) * res
            y = oy + (h - 1 - row + 0.5) * res
            key = (int(np.floor(x / res)), int(np.floor(y / res)))
            assert state[row, col] == want.get(key, -1), (row, col, key)
    assert len(want) == int((state >= 0).sum())
    # the wall stands in the band: its column at x = WALL_X is occupied, free before it
    col = int((pb.WALL_X - ox) // res)
    row = h - 1 - int((pb.T_map_base(2)[1, 3] - oy) // res)
    assert state[row, col] == 1 and state[row, col - 4] == 0


def test_grid_default_band_is_above_the_floor(map_file: Path, tmp_path: Path) -> None:
    r = run("export", map_file, "-f", "grid", "-o", tmp_path / "auto.yaml")
    assert r.exit_code == 0, r.output
    found = re.search(r"floor plane z = (\S+) (\S+) x (\S+) y \(tilt 0\.0 deg\)", r.output)
    assert found and "--z-min/--z-max" in r.output, r.output
    a, b, c = map(float, found.groups())
    assert abs(a - pb.PLANE_Z) < 0.01 and abs(b) < 1e-3 and abs(c) < 1e-3
    assert "0.30 .. 2.00 m above the floor" in r.output
    assert (tmp_path / "auto.pgm").exists() and (tmp_path / "auto.yaml").exists()
    img = read_pgm(tmp_path / "auto.pgm")
    # the band starts above the floor's cells: the floor is not drawn as an obstacle
    assert (img == 0).sum() < 0.2 * (img == 254).sum()


def test_grid_finds_the_floor_of_a_map_without_gaussians(rng, tmp_path: Path) -> None:
    """Cells of too few points for a Gaussian (min_points 50) are occupied all the same:
    the default band's floor is fitted to their centres (it was refused as a map with no
    occupied Gaussians)."""
    m = NdtOmMap(0.2, min_points=50, n_max=100)
    floor = np.c_[rng.uniform(-8, 8, (4000, 2)), np.full(4000, -1.25)]
    wall = np.c_[np.full(800, 6.0), rng.uniform(-8, 8, 800), rng.uniform(-1.2, 1.0, 800)]
    m.insert_scan(np.r_[floor, wall], np.eye(4))
    assert len(m) == 0
    e = export_file(m, tmp_path / "g.pgm")
    assert "fitted to the lowest occupied cells of" in e.notes[0]
    a = float(re.search(r"floor plane z = (\S+)", e.notes[0]).group(1))
    assert abs(a - (-1.3)) < 0.01  # the floor cells' centres
    img = read_pgm(tmp_path / "g.pgm")
    assert (img == 0).any() and (img == 254).any()  # the wall an obstacle, the floor's space free
    m.close()
