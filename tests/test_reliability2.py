"""Reliability, round 2 (issue 30): no output ever overwrites an input, every setting and
stored value checked once (API, map file, --config), threads from the first call,
signals, save targets, the viewer's headers and the terminal."""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import test_pipeline_bags as pb

# the first round's CLI runner
from test_reliability import run_cli

from ndtom_ti import NdtOmMap


def digest(path: Path) -> str:
    if path.is_dir():
        return hashlib.sha256(
            b"".join(p.name.encode() + p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file())
        ).hexdigest()
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


# ---------------------------------------------------------------------------- 2-5: every setting checked once
import json  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402

import test_reliability as r1  # noqa: E402 - the crafted-file helpers (parse, build)
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from ndtom_ti import MapFileError  # noqa: E402
from ndtom_ti.config import RESOLUTION_MAX, MapConfig  # noqa: E402
from ndtom_ti.mapfile import read_header  # noqa: E402
from ndtom_ti.pipeline import config_with_ranges, load_config_file  # noqa: E402
from ndtom_ti.snapshot import MapSnapshot  # noqa: E402

N_LIMIT = 2**30  # documented: the most points a Gaussian holds (docs/sensor-model.md)


class Blob(bytes):
    def __repr__(self) -> str:  # hypothesis prints its arguments: not megabytes of them
        return f"<{len(self)} bytes>"


@pytest.fixture(scope="module")
def good_file(tmp_path_factory) -> bytes:
    rng = np.random.default_rng(5)
    with NdtOmMap(0.25) as m:
        for _ in range(3):
            T = np.eye(4)
            T[:3, 3] = rng.normal(size=3)
            m.insert_scan(rng.normal(size=(3000, 3)) * [5.0, 5.0, 1.0] + [6.0, 0.0, 0.0], T)
        return Blob(m.save(tmp_path_factory.mktemp("good") / "good.ndtom").read_bytes())


def with_header(data: bytes, **changes) -> bytes:
    header, arrays = r1.parse(data)
    header.update(changes)
    return r1.build(header, arrays)


def with_config(data: bytes, **config) -> bytes:
    header, _ = r1.parse(data)
    return with_header(data, config={**header["config"], **config})


ISSUE_FILE_CASES = [
    {"min_points": math.inf},
    {"n_max": math.inf},
    {"min_points": 2e70},
    {"sigma_s": 2e70},
    {"sigma_s": 1e308},
    {"max_range": 2**63},
    {"min_range": 1e308},
    {"n_max": 2**63},
]


@pytest.mark.parametrize("config", ISSUE_FILE_CASES, ids=str)
def test_map_files_with_out_of_range_settings_are_refused_by_every_reader(tmp_path, good_file, config):
    path = tmp_path / "bad.ndtom"
    path.write_bytes(with_config(good_file, **config))
    for read in (MapSnapshot.load, NdtOmMap.load, read_header):
        with pytest.raises(MapFileError, match="min_points|n_max|sigma_s|max_range|min_range"):
            read(path)
    for args in (("info", path), ("export", path, "-o", tmp_path / "x.ply")):
        r = run_cli(*args)
        assert r.exit_code == 2 and "Error:" in r.output and "internal error" not in r.output, r.output
    pytest.importorskip("viser")
    r = run_cli("view", path, "--html", tmp_path / "x.html")
    assert r.exit_code == 2 and "Error:" in r.output, r.output


@pytest.mark.parametrize(
    "config",
    [
        {"min_points": float("inf")},
        {"sigma_s": 2**70},
        {"min_points": 2e70},
        {"sigma_s": 1e308},
        {"max_range": 2**63},
        {"min_range": 1e308},
        {"n_max": 2**63},
        {"n_max": 10**400},
        {"logodds_max": 1e-50},
        {"min_points": 2**31},
    ],
    ids=lambda c: str(c)[:40],
)
def test_api_refuses_settings_outside_what_the_kernels_hold(config):
    with pytest.raises(ValueError, match="MapConfig"):
        NdtOmMap(0.2, **config)
    with pytest.raises(ValueError, match="MapConfig"):
        MapConfig(**config)


def test_settings_become_plain_numbers():
    c = MapConfig(min_points=np.int64(4), n_max=5.0, max_range=np.float32(30.0), p_occupied=np.float64(0.7), sigma_s=2)
    assert type(c.min_points) is int and type(c.n_max) is int and c.n_max == 5
    assert type(c.max_range) is float and type(c.p_occupied) is float and type(c.sigma_s) is float
    with pytest.raises(ValueError, match="integer"):
        MapConfig(min_points=3.5)


def test_sigma_s_in_cells_must_fit_at_the_map_resolution():
    with pytest.raises(ValueError, match="sigma_s"):
        NdtOmMap(1e-6, sigma_s=1e5)
    NdtOmMap(1e-6, sigma_s=1e5, miss_model="paper").close()  # the paper's model does not use it


@pytest.mark.parametrize(
    "text,name",
    [
        ('{"min_points": Infinity}', "c.json"),
        ('{"n_max": 1e400}', "c.json"),
        ('{"sigma_s": 1e308}', "c.json"),
        ('{"max_range": 9223372036854775808}', "c.json"),
        ("min_points = inf", "c.toml"),
        ("[map]\nn_max = 9223372036854775807", "c.toml"),
    ],
)
def test_config_file_settings_out_of_range_are_bad_input(tmp_path, text, name):
    bag = pb.write_plane_bag(tmp_path)
    cfg = tmp_path / name
    cfg.write_text(text)
    r = run_cli("map", bag, "-r", pb.RES, "--config", cfg, "-o", tmp_path / "m.ndtom", "--no-progress")
    assert r.exit_code == 2, r.output
    assert "Error:" in r.output and "internal error" not in r.output and str(cfg.name) in r.output
    assert not (tmp_path / "m.ndtom").exists()


def test_a_gaussian_of_too_many_points_is_refused(tmp_path, good_file):
    header, arrays = r1.parse(good_file)
    arrays["g_n"][0] = 2**31 - 1
    path = tmp_path / "n.ndtom"
    path.write_bytes(r1.build(header, arrays))
    with pytest.raises(MapFileError, match="g_n"):
        MapSnapshot.load(path)


def test_a_gaussian_at_the_point_limit_keeps_its_points(tmp_path, good_file):
    """N is capped at N_LIMIT (as n_max caps it): the next points into the cell neither wrap
    the kernels' int32 count nor delete the Gaussian."""
    header, arrays = r1.parse(good_file)
    k = int(np.argmax(arrays["g_n"]))
    arrays["g_n"][k] = N_LIMIT
    path = tmp_path / "n.ndtom"
    path.write_bytes(r1.build(header, arrays))
    with NdtOmMap.load(path) as m:
        cell = arrays["g_index"][k]
        centre = (cell + 0.5) * 0.25
        m.insert_scan(centre + np.random.default_rng(1).uniform(-0.1, 0.1, (50, 3)), np.eye(4))
        g = m.gaussians(min_probability=0.0)
        row = np.flatnonzero((g["index"] == cell).all(axis=1))
        assert len(row) == 1 and g["n"][row[0]] == N_LIMIT
        c = m.coarsen(2).gaussians(min_probability=0.0)
        assert (c["n"] > 0).all() and c["n"].max() == N_LIMIT


# Property-based: any value of any setting, through the API, a map file and --config, gives a
# clear error (ValueError/TypeError naming the setting; MapFileError) or a map that works.
FIELDS = [f for f in MapConfig.__dataclass_fields__]
SPECIAL = [
    0,
    -1,
    1,
    2,
    3,
    0.5,
    0.49,
    0.6,
    -2.0,
    2.0,
    1e-50,
    1e-300,
    5e-324,
    1e-6,
    1e6,
    1e15,
    2e15,
    1e308,
    2e70,
    math.inf,
    -math.inf,
    math.nan,
    2**30,
    2**30 + 1,
    2**31 - 1,
    2**31,
    2**63,
    2**70,
    10**400,
    3.0,
    3.5,
    True,
    "3",
    None,
    [1],
    "ndt",
    "paper",
    "drop",
    "free",
]
value = st.one_of(
    st.sampled_from(SPECIAL), st.floats(), st.floats(-10, 10), st.integers(-(2**70), 2**70), st.integers(0, 10)
)
configs = st.dictionaries(st.sampled_from(FIELDS), value, max_size=4)
PROPERTY = dict(deadline=None, suppress_health_check=list(HealthCheck), database=None, derandomize=True)


def clear(exc: BaseException) -> bool:
    """A clear error: a ValueError or TypeError (MapFileError is one) whose message says
    what was wrong, never an internal one."""
    return isinstance(exc, (ValueError, TypeError)) and len(str(exc)) > 10 and "Traceback" not in str(exc)


def check_valid(c: MapConfig) -> None:
    """The settings of an accepted config are plain, finite-where-needed numbers that fit
    the kernels' types."""
    assert type(c.min_points) is int and 1 <= c.min_points <= N_LIMIT
    assert type(c.n_max) is int and (c.n_max == 0 or 2 <= c.n_max <= N_LIMIT)
    for name in ("p_occupied", "p_empty", "logodds_min", "logodds_max", "min_range", "eta"):
        v = getattr(c, name)
        assert type(v) is float and math.isfinite(v), name
    assert np.isfinite(np.float32(c.logodds_min)) and np.float32(c.logodds_min) < 0 < np.float32(c.logodds_max)
    assert c.max_range == math.inf or c.max_range**2 < math.inf
    assert c.sigma_s is None or (type(c.sigma_s) is float and 0 < c.sigma_s < math.inf)


def exercise(m: NdtOmMap) -> None:
    """The calls that failed on accepted settings: a scan, the queries, coarsen."""
    pts = np.random.default_rng(0).normal(size=(300, 3)) + [3.0, 0.0, 0.0]
    m.insert_scan(pts, np.eye(4))
    m.insert_scan(pts, np.eye(4))
    m.gaussians(min_probability=0.0)
    m.known_cells()
    m.coarsen(2).close()


@settings(max_examples=1200, **PROPERTY)
@given(cfg=configs)
def test_property_api_settings_give_a_clear_error_or_a_valid_config(cfg):
    try:
        c = MapConfig(**cfg)
    except Exception as exc:  # noqa: BLE001 - the property is about which
        assert clear(exc), repr(exc)
        return
    check_valid(c)
    assert MapConfig.from_dict(json.loads(json.dumps(c.to_dict()))) == c  # what a map file stores reads back


@settings(max_examples=40, **PROPERTY)
@given(cfg=configs, res=st.sampled_from([1e-300, 1e-7, 1e-3, 0.05, 0.2, 1.0, 1e3, 1e6]))
def test_property_api_maps_of_accepted_settings_work(cfg, res):
    try:
        m = NdtOmMap(res, **cfg)
    except Exception as exc:  # noqa: BLE001
        assert clear(exc), repr(exc)
        return
    with m:
        check_valid(m.config)
        exercise(m)


@settings(max_examples=700, **PROPERTY)
@given(cfg=configs, res=st.one_of(st.sampled_from([1e-7, 0.25, 1e3, 2e300]), st.floats(1e-9, 1e9)), data=st.data())
def test_property_map_file_settings_give_a_map_file_error_or_a_valid_map(tmp_path_factory, good_file, cfg, res, data):
    path = tmp_path_factory.getbasetemp() / "prop.ndtom"
    header, _ = r1.parse(good_file)
    path.write_bytes(with_header(good_file, resolution=res, config={**header["config"], **cfg}))
    try:
        s = MapSnapshot.load(path)
    except MapFileError as exc:
        assert clear(exc)
        with pytest.raises(MapFileError):  # what `ndtom info` reads refuses it too, or the cells were the fault
            read_header(path) if "options" in str(exc) else (_ for _ in ()).throw(MapFileError("cells"))
        return
    check_valid(s.config)
    read_header(path)
    s.gaussians(min_probability=0.0)
    if 2 * s.resolution <= RESOLUTION_MAX:
        s.coarsen(2)
    else:  # cells past the largest a map takes: a clear refusal
        with pytest.raises(ValueError, match="factor is too large"):
            s.coarsen(2)
    if data.draw(st.integers(0, 9), label="to a map") == 0:  # maps take a slot and Taichi: a tenth of them
        with NdtOmMap.from_snapshot(s) as m:
            exercise(m)


def toml_value(v) -> str | None:
    if v is None:
        return None
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v == math.inf else "-inf" if v == -math.inf else repr(v))
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, str, list)):
        return json.dumps(v)
    raise AssertionError(v)


@settings(max_examples=700, **PROPERTY)
@given(cfg=configs, toml=st.booleans())
def test_property_config_files_give_a_clear_error_or_a_valid_config(tmp_path_factory, cfg, toml):
    """What `ndtom map --config` does with the file (load_config_file, then the -r/--min-range/...
    merge); the command's exit code for its errors is in the tests above."""
    path = tmp_path_factory.getbasetemp() / ("prop.toml" if toml else "prop.json")
    if toml:
        lines = [f"{k} = {toml_value(v)}" for k, v in cfg.items() if toml_value(v) is not None]
        path.write_text("\n".join(lines))
    else:
        path.write_text(json.dumps(cfg))
    try:
        c = config_with_ranges(load_config_file(path))
    except Exception as exc:  # noqa: BLE001
        assert isinstance(exc, ValueError) and path.name in str(exc), repr(exc)
        return
    check_valid(c)


# ---------------------------------------------------------------------------- the checksum
@pytest.fixture(scope="module")
def raw_good_file(tmp_path_factory, good_file) -> bytes:
    """good_file as format version 3, whose arrays lie raw in the payload (format 4's
    compressed frames have their own flip tests in test_reliability.py)."""
    from ndtom_ti.mapfile import RAW_VERSION

    folder = tmp_path_factory.mktemp("raw")
    (folder / "good.ndtom").write_bytes(good_file)
    out = MapSnapshot.load(folder / "good.ndtom").save(folder / "raw.ndtom", version=RAW_VERSION)
    return out.read_bytes()


@pytest.mark.parametrize("name,column", [("g_mean_rel", 1), ("g_scatter", 0), ("occ_logodds", None)])
def test_a_flipped_bit_inside_a_float_array_is_a_checksum_error(tmp_path, raw_good_file, name, column):
    """A bit flip that leaves every value plausible (the lowest mantissa bit of one float:
    inside its cell, within the clamps, still positive semi-definite) passes every structural
    and value check; only the checksum finds it."""
    good_file = raw_good_file
    header, arrays = r1.parse(good_file)
    entry = next(e for e in header["arrays"] if e["name"] == name)
    payload_at = len(good_file) - header["payload_bytes"]
    row = len(arrays[name]) // 2
    item = row * (arrays[name].shape[1] if column is not None else 1) + (column or 0)
    at = payload_at + entry["offset"] + item * arrays[name].itemsize  # little endian: lowest byte first
    data = bytearray(good_file)
    data[at] ^= 1
    flipped = r1.parse(bytes(data))[1][name]
    assert flipped.reshape(-1)[item] != arrays[name].reshape(-1)[item]
    path = tmp_path / "flipped.ndtom"
    path.write_bytes(bytes(data))
    for read in (MapSnapshot.load, NdtOmMap.load):
        with pytest.raises(MapFileError, match="checksum"):
            read(path)
    # the same values with their checksum made right load: nothing but the checksum refused it
    h2, a2 = r1.parse(bytes(data))
    path.write_bytes(r1.build(h2, a2))
    MapSnapshot.load(path)


# ---------------------------------------------------------------------------- CI: ../shared required
def test_ci_switch_makes_missing_shared_data_a_failure(tmp_path):
    import subprocess

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "NDTOM_SHARED": str(tmp_path / "nothing"), "NDTOM_REQUIRE_SHARED": "1"}
    r = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "--collect-only", "-p", "no:cacheprovider", "tests/test_docs.py"],
        cwd=root,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode != 0 and "NDTOM_REQUIRE_SHARED" in r.stdout + r.stderr, r.stdout + r.stderr
    from conftest import SHARED

    if all((SHARED / p).exists() for p in ("data", "tools")):  # the real folder is there: the switch passes
        env["NDTOM_SHARED"] = str(SHARED)
        r = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "--collect-only", "-p", "no:cacheprovider", "tests/test_docs.py"],
            cwd=root,
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert r.returncode == 0, r.stdout + r.stderr
    assert "NDTOM_REQUIRE_SHARED=1" in (root / ".ci" / "run").read_text()


# ---------------------------------------------------------------------------- 6: threads from the first call
FIRST_USE = r"""
import os, sys, tempfile, threading
import numpy as np
import ndtom_ti
from ndtom_ti import NdtOmMap

case = sys.argv[1]
if case != "race":
    ndtom_ti.init("cpu")
errors = []
rng = np.random.default_rng(0)
pts = rng.normal(size=(2000, 3)) + [3.0, 0.0, 0.0]

def guarded(fn):
    def run():
        try:
            fn()
        except BaseException as exc:
            errors.append(repr(exc))
    return run

if case == "reader":  # the main thread made the map; a reader's first calls come while it inserts
    m = NdtOmMap(0.2)
    start = threading.Event()

    def read():
        start.wait()
        for _ in range(3):
            m.known_cells()
            m.save(os.path.join(tempfile.mkdtemp(), "r.ndtom"))
            m.gaussians()

    t = threading.Thread(target=guarded(read))
    t.start()
    start.set()
    for _ in range(3):
        m.insert_scan(pts, np.eye(4))
    t.join()
elif case == "worker":  # the first map of the process is made and used in a worker thread
    def work():
        with NdtOmMap(0.2) as m:
            m.insert_scan(pts, np.eye(4))
            m.known_cells()
            NdtOmMap.load(m.save(os.path.join(tempfile.mkdtemp(), "w.ndtom"))).close()
    t = threading.Thread(target=guarded(work))
    t.start()
    t.join()
elif case == "race":  # no init(): four threads make the process's first maps at once
    ready = threading.Barrier(4)
    counts = []

    def first():
        ready.wait()
        with NdtOmMap(0.2) as m:
            m.insert_scan(pts, np.eye(4))
            counts.append(len(m))

    ts = [threading.Thread(target=guarded(first)) for _ in range(4)]
    [t.start() for t in ts]
    [t.join() for t in ts]
    if len(set(counts)) != 1 or len(counts) != 4 or counts[0] == 0:
        errors.append(f"maps differ: {counts}")
elif case == "layout":  # a worker thread's map of a layout the process has not built: refused clearly
    def other_layout():
        try:
            NdtOmMap(0.2, layout=ndtom_ti.Layout(l1=(64, 64, 16)))
            errors.append("a new layout was built in a worker thread")
        except RuntimeError as exc:
            if "make the first map of this layout there" not in str(exc):
                raise
    t = threading.Thread(target=guarded(other_layout))
    t.start()
    t.join()
    with NdtOmMap(0.2) as m:  # the process is still usable
        m.insert_scan(pts, np.eye(4))
elif case == "settings":  # what init() still lets a process choose before its first map
    ndtom_ti.init(max_maps=2)
    a, b = NdtOmMap(0.5), NdtOmMap(0.5)
    try:
        NdtOmMap(0.5)
        errors.append("a third map was made")
    except ndtom_ti.NoFreeSlotError:
        pass
print("ERRORS", errors)
sys.exit(1 if errors else 0)
"""


@pytest.mark.parametrize("case", ["reader", "worker", "race", "layout", "settings"])
def test_first_taichi_use_from_a_worker_thread(tmp_path, case):
    import subprocess

    script = tmp_path / "first_use.py"
    script.write_text(FIRST_USE)
    r = subprocess.run(
        [sys.executable, str(script), case],
        capture_output=True,
        text=True,
        timeout=400,
        env={**os.environ, "NDTOM_PIN_THREADS": "0"},
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "ERRORS []" in r.stdout


# ---------------------------------------------------------------------------- 7: SIGTERM in `ndtom map --view`
@pytest.mark.parametrize("signum,code,name", [(15, 143, "SIGTERM"), (2, 130, "Ctrl-C")])
def test_map_view_names_the_signal_and_exits_with_its_code(tmp_path, monkeypatch, signum, code, name):
    pytest.importorskip("viser")
    import signal

    from ndtom_ti.viewer import cli as vcli

    bag = pb.write_plane_bag(tmp_path)
    # private: the command's wait for Ctrl-C after mapping has no public hook
    monkeypatch.setattr(vcli, "_serve_until_stopped", lambda viewer, stop: None)
    insert = NdtOmMap.insert_scan
    done = []

    def insert_then_signal(self, points, T):
        rep = insert(self, points, T)
        done.append(1)
        if len(done) == 2:
            os.kill(os.getpid(), signum)  # handled by the main thread, between two scans
        return rep

    monkeypatch.setattr(NdtOmMap, "insert_scan", insert_then_signal)
    before = signal.getsignal(signum)
    out = tmp_path / "live.ndtom"
    r = run_cli(
        "map", bag, "-r", pb.RES, "-o", out, "--view", "--no-wait", "--rate", "0.5", "--port", "0", "--no-progress"
    )
    assert signal.getsignal(signum) == before
    assert r.exit_code == code, r.output
    assert f"({name}; the map is marked incomplete)" in r.output, r.output
    assert NdtOmMap.load(out).metadata["complete"] is False


def test_live_default_finish_exits_143_on_sigterm(tmp_path, monkeypatch):
    pytest.importorskip("viser")
    import signal

    from ndtom_ti.demo import make_scans
    from ndtom_ti.viewer import cli as vcli

    # private: the command's wait for Ctrl-C after mapping has no public hook
    monkeypatch.setattr(vcli, "_serve_until_stopped", lambda viewer, stop: None)

    def scans():
        for i, s in enumerate(make_scans(6, rings=4, per_ring=100)):
            if i == 2:
                os.kill(os.getpid(), signal.SIGTERM)
            if i >= 2:
                time.sleep(0.3)  # the main thread handles the signal before the scans run out
            yield s

    out = tmp_path / "d.ndtom"
    assert (
        vcli.live_command(scans(), 0.5, "127.0.0.1", 0, speed=None, wait_for_browser=False, save=out, compare=False)
        == 143
    )
    assert NdtOmMap.load(out).scans_inserted >= 1


# ---------------------------------------------------------------------------- 8-10: save targets
def test_view_html_follows_links_as_map_saves_do(tmp_path, small_map_file):
    pytest.importorskip("viser")
    target = tmp_path / "real.html"
    target.write_text("old page")
    link = tmp_path / "link.html"
    link.symlink_to(target)
    r = run_cli("view", small_map_file, "--html", link)
    assert r.exit_code == 0, r.output
    assert link.is_symlink() and os.readlink(link) == str(target)  # the link stays
    assert "<html" in target.read_text().lower()
    # a dangling link: written through to where it points, exactly as a map save does
    for name, write in (
        ("page.html", lambda p: run_cli("view", small_map_file, "--html", p)),
        ("map.ndtom", lambda p: MapSnapshot.load(small_map_file).save(p)),
    ):
        dangling = tmp_path / f"dangling-{name}"
        dangling.symlink_to(tmp_path / f"absent-{name}")
        write(dangling)
        assert dangling.is_symlink() and (tmp_path / f"absent-{name}").is_file(), name
    # a link to a folder is refused, as by map saves
    (tmp_path / "folder").mkdir()
    (tmp_path / "to-folder.html").symlink_to(tmp_path / "folder")
    r = run_cli("view", small_map_file, "--html", tmp_path / "to-folder.html")
    assert r.exit_code in (1, 2) and "Error:" in r.output and (tmp_path / "to-folder.html").is_symlink()


def test_the_longest_legal_file_names_can_be_written(tmp_path, small_map_file):
    s = MapSnapshot.load(small_map_file)
    for n in (242, 250, 255):
        path = tmp_path / ("m" * (n - len(".ndtom")) + ".ndtom")
        assert len(path.name) == n
        s.save(path)
        assert MapSnapshot.load(path).resolution == s.resolution
        out = path.with_suffix(".ply")
        r = run_cli("export", path, "-o", out)
        assert r.exit_code == 0 and out.is_file(), r.output
    utf8 = tmp_path / ("é" * 120 + ".ndtom")  # 246 bytes: the temporary name is cut by bytes
    s.save(utf8)
    assert utf8.is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.endswith((".tmp", ".check"))]


def test_a_save_removes_the_temporaries_killed_saves_left(tmp_path, small_map_file):
    import fcntl

    s = MapSnapshot.load(small_map_file)
    target = tmp_path / "m.ndtom"
    old = time.time() - 3600
    stale = [tmp_path / f".m.ndtom.{c * 8}.tmp" for c in "ab"]
    for p in stale:
        p.write_bytes(b"half a map")
        os.utime(p, (old, old))
    fresh = tmp_path / ".m.ndtom.cccccccc.tmp"  # a save under way elsewhere, just started
    fresh.write_bytes(b"x")
    locked = tmp_path / ".m.ndtom.dddddddd.tmp"  # a save under way elsewhere, writing slowly
    locked.write_bytes(b"x")
    os.utime(locked, (old, old))
    other = tmp_path / ".other.ndtom.eeeeeeee.tmp"  # another target's: not ours to remove
    other.write_bytes(b"x")
    os.utime(other, (old, old))
    keep = tmp_path / ".m.ndtom.notes.tmp"  # not a name our saves make
    keep.write_bytes(b"x")
    os.utime(keep, (old, old))
    with open(locked, "rb") as held:
        fcntl.flock(held.fileno(), fcntl.LOCK_EX)
        s.save(target)
    assert MapSnapshot.load(target).resolution == s.resolution
    assert not any(p.exists() for p in stale)
    assert fresh.exists() and locked.exists() and other.exists() and keep.exists()


# ---------------------------------------------------------------------------- 11: checksum in bounded memory
BIG_ZEROS = r"""
import json, resource, struct, sys
from ndtom_ti.mapfile import MapFileError, RAW_VERSION as VERSION  # raw arrays: a payload of zeros
from ndtom_ti.snapshot import ARRAYS, MapSnapshot

path, rows = sys.argv[1], int(sys.argv[2])
table, off = [], 0
for name, (dtype, cols) in ARRAYS.items():
    n = rows if name.startswith("occ_") else 0
    shape = [n, *cols]
    nbytes = n * int(__import__("math").prod(cols)) * int(dtype[-1])
    table.append({"name": name, "dtype": dtype, "shape": shape, "offset": off, "nbytes": nbytes})
    off += nbytes
header = {"format": "ndtom_ti map", "version": VERSION, "resolution": 0.2, "occupancy": True, "config": {},
          "layout": {"l1": [128, 128, 16], "l2": 32, "leaf": 8}, "scans_inserted": 1, "points_inserted": 1,
          "metadata": {}, "arrays": table, "payload_bytes": off, "payload_sha256": "0" * 64}
hb = json.dumps(header).encode()
with open(path, "wb") as fh:
    fh.write(b"NDTOMTI\n" + struct.pack("<IQ", VERSION, len(hb)) + hb)
    fh.truncate(fh.tell() + off)  # a sparse file of zeros
limit = 600 * 2**20 + resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
resource.setrlimit(resource.RLIMIT_DATA, (limit, limit))  # far below the declared payload
try:
    MapSnapshot.load(path)
except MapFileError as exc:
    print("REFUSED", exc)
except MemoryError:
    print("MEMORY ERROR")
"""


def test_a_huge_damaged_file_is_refused_in_bounded_memory(tmp_path):
    import subprocess

    script = tmp_path / "zeros.py"
    script.write_text(BIG_ZEROS)
    rows = 80_000_000  # 1.28 GB of occ_index and occ_logodds, all zeros
    r = subprocess.run(
        [sys.executable, str(script), str(tmp_path / "zeros.ndtom"), str(rows)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert "REFUSED" in r.stdout and "checksum" in r.stdout, r.stdout + r.stderr[-2000:]


# ---------------------------------------------------------------------------- 14: the terminal
def test_info_shows_control_characters_of_a_map_instead_of_sending_them(tmp_path):
    path = tmp_path / "esc.ndtom"
    evil = "\x1b]0;pwned\x07\x1b[2J\x1b[31mred\x9b1m\x00[bold]x[/bold]"
    with NdtOmMap(0.5, metadata={"source": evil, "cloud_topic": "/a\rb", "created": "\x1b[8m"}) as m:
        m.save(path)
    r = run_cli("info", path)
    assert r.exit_code == 0, r.output
    assert not any(c in r.output for c in "\x1b\x07\x00\x9b\r"), repr(r.output)
    assert "\\x1b]0;pwned\\x07" in r.output and "[bold]x[/bold]" in r.output and "/a\\x0db" in r.output


# ---------------------------------------------------------------------------- export: one code for "could not write"
@pytest.mark.parametrize("where", ["before (read-only)", "during (disk full)"])
def test_export_that_cannot_write_exits_1_whenever_it_finds_out(tmp_path, small_map_file, monkeypatch, where):
    import errno
    import tempfile

    import ndtom_ti.atomic as atomic

    if where.startswith("before"):

        def refuse(*a, **k):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))

        monkeypatch.setattr(tempfile, "mkstemp", refuse)
    else:
        real = atomic.atomic_write

        def full(path, write):
            def fill(fh):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

            return real(path, fill)

        monkeypatch.setattr(atomic, "atomic_write", full)
        import ndtom_ti.export as export

        monkeypatch.setattr(export, "atomic_write", full)
    out = tmp_path / "x.ply"
    r = run_cli("export", small_map_file, "-o", out)
    assert r.exit_code == 1, r.output
    assert "Error:" in r.output and "internal error" not in r.output and not out.exists()


# ---------------------------------------------------------------------------- 13: --host ::
def test_viewer_on_ipv6_wildcard_prints_urls_that_answer(small_map_file):
    pytest.importorskip("viser")
    import re
    import socket
    from urllib.parse import urlsplit

    from ndtom_ti.viewer import MapViewer

    try:
        socket.create_server(("::1", 0), family=socket.AF_INET6).close()
    except OSError:
        pytest.skip("no IPv6 on this machine")
    said: list[str] = []
    v = MapViewer(MapSnapshot.load(small_map_file), host="::", port=0, environment_map=False, progress=said.append)
    try:
        urls = re.findall(r"http://\S+?/(?:\?token=[\w-]+)?(?=[\s)]|$)", "\n".join(said))
        assert len(urls) == 2, said
        for url in urls:
            u = urlsplit(url)
            with socket.create_connection((u.hostname, u.port), timeout=5) as s:  # refused before: IPv4 URLs
                s.sendall(f"GET /?{u.query} HTTP/1.1\r\nHost: {u.netloc}\r\nConnection: close\r\n\r\n".encode())
                s.settimeout(5)
                head = s.recv(64)
            assert head.startswith(b"HTTP/1.1 200"), (url, head)
    finally:
        v.close()
