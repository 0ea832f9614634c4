"""`ndtom map --workers N` (one map built by worker processes on Ray), `ndtom merge`, and
the commands that read a tiled map's folder (info, export, view).

One test starts Ray (a real `ndtom` process, as a user runs it: its terminal shows none
of Ray's lines); the others run the workers in this process (TiledMap's local engine,
the same map) or stop before any work."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parent))
import test_pipeline_bags as pb  # noqa: E402

from ndtom_ti.cli import tiles  # noqa: E402
from ndtom_ti.cli import app  # noqa: E402
from ndtom_ti.cluster import TiledMap  # noqa: E402
from ndtom_ti.mapfile import read_header  # noqa: E402
from ndtom_ti.snapshot import MapSnapshot  # noqa: E402

BALM = DATA / "balm_hall_every4"
REPO = Path(__file__).resolve().parents[1]
# a small selection of the BALM hall, as `ndtom map` maps it
SIX = ("-r", "0.3", "--max-scans", "6", "--no-progress")
WORKERS = ("--workers", "2", "--tile-size", "8", "--worker-threads", "1")


def need_balm() -> Path:
    if not BALM.exists():
        pytest.skip(f"{BALM} not available")
    return BALM


def run(*args: object):
    r = CliRunner(env={"COLUMNS": "250"}).invoke(app, [str(a) for a in args])
    assert "Traceback" not in r.output, r.output
    return r


def ndtom(cwd: Path, *args: object, hide: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    """The `ndtom` command in a process of its own (``hide``: modules made unimportable)."""
    code = (
        "import sys\n"
        f"for name in {list(hide)!r}:\n    sys.modules[name] = None\n"
        f"sys.argv = ['ndtom'] + {[str(a) for a in args]!r}\n"
        "from ndtom_ti.cli import main\nmain()\n"
    )
    env = {**os.environ, "COLUMNS": "250", "NDTOM_PIN_THREADS": "0"}
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=600, check=False
    )
    assert "Traceback" not in r.stdout + r.stderr and "internal error" not in r.stdout + r.stderr, r.stderr
    return r


def assert_same_cells(a: str | Path, b: str | Path) -> None:
    """Two maps (files or tiled folders) hold the same cells, bit for bit."""
    sa, sb = MapSnapshot.load(a), MapSnapshot.load(b)
    assert (sa.scans_inserted, sa.points_inserted) == (sb.scans_inserted, sb.points_inserted)
    for name, x in sa.state().items():
        y = sb.state()[name]
        assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), name


def assert_user_error(r, *texts: str, code: int = 2) -> None:
    assert r.exit_code == code, r.output
    assert "Error:" in r.output and "Hint:" in r.output, r.output
    for t in texts:
        assert t in r.output, (t, r.output)


@pytest.fixture(scope="module")
def one_process(tmp_path_factory) -> Path:
    """Six BALM scans mapped by `ndtom map` without --workers."""
    out = tmp_path_factory.mktemp("one") / "six.ndtom"
    r = run("map", need_balm(), *SIX, "-o", out)
    assert r.exit_code == 0, r.output
    return out


@pytest.fixture
def local_engine(monkeypatch):
    """`ndtom map --workers` with its workers in this process (no Ray start): the same map."""
    made = []

    def make_map(self):
        def make(*args, **kwargs):
            mine = {"workers": self.workers, "tile_size": self.tile_size, "folder": self.folder}
            mine.update(checkpoint_every=self.checkpoint_every, resume=self.resume, job=self.job)
            mine.update(engine="local", probe=False)
            m = TiledMap(*args, **kwargs, **mine)
            made.append(m)
            return m

        return make

    monkeypatch.setattr(tiles.TiledRun, "make_map", make_map)
    yield made
    for m in made:
        m.close()


# ---------------------------------------------------------------------------- on Ray
def test_map_with_workers_on_ray_is_the_one_process_map(one_process: Path, tmp_path: Path) -> None:
    """`ndtom map --workers 2` on a local Ray cluster writes the map file `ndtom map` writes
    (cell for cell), keeps --tiled DIR as a complete tiled map that info and merge read,
    and shows none of Ray's own lines."""
    r = ndtom(tmp_path, "map", need_balm(), *SIX, *WORKERS, "--tiled", "T", "-o", "six.ndtom")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "Workers: 2 processes on a local Ray cluster, 1 thread each; tiles of 8 m" in r.stderr
    for noise in ("Ray instance", "Token authentication", "INFO", "WARNING", "(pid="):
        assert noise not in r.stdout + r.stderr, (noise, r.stderr)
    assert_same_cells(one_process, tmp_path / "six.ndtom")
    md = MapSnapshot.load(tmp_path / "six.ndtom").metadata
    assert md["complete"] is True and md["workers"] == {"workers": 2, "tile_size": 8.0, "engine": "ray"}
    assert not (tmp_path / "six.ndtom.tiles").exists()  # --tiled: the checkpoints went to T

    assert_same_cells(one_process, tmp_path / "T")
    info = run("info", tmp_path / "T")
    assert info.exit_code == 0, info.output
    assert "Tiled map" in info.output and re.search(r"\d+ tiles of 8 m \(\d+ cells\) from 2 workers", info.output)
    assert "complete;" in info.output
    assert re.search(r"scans inserted\s*│\s*6\s", info.output), info.output
    merged = run("merge", tmp_path / "T", "-o", tmp_path / "merged.ndtom")
    assert merged.exit_code == 0, merged.output
    assert re.search(r"Merged \d+ tiles \(6 scans", merged.output), merged.output
    assert_same_cells(one_process, tmp_path / "merged.ndtom")


@pytest.mark.slow  # two Ray starts: about 70 s on two cores
def test_map_joins_a_running_cluster(one_process: Path, tmp_path: Path) -> None:
    """--cluster ADDRESS: the workers run on a Ray cluster started beforehand (here by this
    process), which the command leaves running; the same map."""
    import logging

    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    try:
        address = ray.get_runtime_context().gcs_address
        r = ndtom(tmp_path, "map", need_balm(), *SIX, *WORKERS, "--cluster", address, "-o", "six.ndtom")
        assert r.returncode == 0, r.stdout + r.stderr
        assert f"processes on the Ray cluster at {address}" in r.stderr
        assert ray.is_initialized() and ray.cluster_resources().get("CPU") == 2  # still up
    finally:
        ray.shutdown()
    assert_same_cells(one_process, tmp_path / "six.ndtom")


# ---------------------------------------------------------------------------- in this process
def test_resume_carries_on_to_the_same_map(one_process: Path, tmp_path: Path, local_engine) -> None:
    """A run of 3 scans kept in --tiled T, resumed to 6: the map of 6 at once."""
    t = tmp_path / "T"
    r = run(
        "map", BALM, *SIX[:2], "--max-scans", "3", "--no-progress", *WORKERS, "--tiled", t, "-o", tmp_path / "3.ndtom"
    )
    assert r.exit_code == 0, r.output
    assert MapSnapshot.load(t).scans_inserted == 3
    again = run("map", BALM, *SIX, *WORKERS, "--tiled", t, "-o", tmp_path / "3.ndtom")
    assert_user_error(again, "already holds a tiled map (a complete run of 3 scans)", "--resume")
    r = run("map", BALM, *SIX, *WORKERS, "--tiled", t, "--resume", "-o", tmp_path / "6.ndtom")
    assert r.exit_code == 0, r.output
    assert "resuming after the 3 scans it holds" in r.output
    assert "3 of 6 clouds read" in r.output
    assert_same_cells(one_process, tmp_path / "6.ndtom")
    assert_same_cells(one_process, t)


def test_resume_refuses_other_scans_or_settings(tmp_path: Path, local_engine) -> None:
    """--resume after a run of other scans (--every) or another miss model: refused before
    any scan, naming what differs; where the run stops (--max-scans) may change."""
    t = tmp_path / "T"
    r = run("map", need_balm(), "-r", "0.3", "--max-scans", "2", "--no-progress", *WORKERS, "--tiled", t)
    assert r.exit_code == 0, r.output
    other = run("map", BALM, *SIX, "--every", "2", *WORKERS, "--tiled", t, "--resume", "-o", tmp_path / "x.ndtom")
    assert_user_error(other, "other scans or settings", "selection")
    model = run(
        "map", BALM, *SIX, "--miss-model", "paper", *WORKERS, "--tiled", t, "--resume", "-o", tmp_path / "y.ndtom"
    )
    assert_user_error(model, "other scans or settings", "config")
    assert MapSnapshot.load(t).scans_inserted == 2  # untouched


def test_ctrl_c_checkpoints_and_resume_finishes(tmp_path: Path, local_engine, monkeypatch) -> None:
    """Ctrl-C: the scan in hand is finished, the map written, the checkpoint kept beside it
    (OUT.tiles); --resume carries on from it to the map of one run, and removes it."""
    bag = pb.write_plane_bag(tmp_path)
    ref = tmp_path / "ref.ndtom"
    assert run("map", bag, "-r", pb.RES, "-o", ref, "--no-progress").exit_code == 0

    orig = TiledMap.insert_scan
    calls = {"n": 0}

    def insert(self, points, T):
        calls["n"] += 1
        if calls["n"] == 2:
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C in the middle of the second scan
        return orig(self, points, T)

    monkeypatch.setattr(TiledMap, "insert_scan", insert)
    out = tmp_path / "m.ndtom"
    r = run("map", bag, "-r", pb.RES, "-o", out, "--workers", "2", "--tile-size", "1", "--no-progress")
    assert r.exit_code == 130, r.output
    assert "Interrupted: saved the 2 scans" in r.output and "Checkpoint of 2 scans written to" in r.output
    folder = tmp_path / "m.ndtom.tiles"
    assert MapSnapshot.load(folder).scans_inserted == 2 and MapSnapshot.load(out).metadata["complete"] is False
    assert MapSnapshot.load(folder).metadata["complete"] is False  # the folder read as a map says it too
    assert run("export", folder, "-o", tmp_path / "ckpt.npz").exit_code == 0
    with np.load(tmp_path / "ckpt.npz") as z:
        assert json.loads(str(z["metadata"]))["complete"] is False
    monkeypatch.setattr(TiledMap, "insert_scan", orig)
    r = run("map", bag, "-r", pb.RES, "-o", out, "--workers", "2", "--tile-size", "1", "--no-progress", "--resume")
    assert r.exit_code == 0, r.output
    assert_same_cells(ref, out)
    assert not folder.exists()  # a complete run: its checkpoints are not needed


# ---------------------------------------------------------------------------- errors
@pytest.fixture
def no_mapping(monkeypatch):
    import ndtom_ti.pipeline

    def refuse(*a, **k):
        raise AssertionError("mapping started")

    monkeypatch.setattr(ndtom_ti.pipeline, "map_recording", refuse)


@pytest.mark.parametrize(
    "args, texts",
    [
        (["--workers", "0"], ["--workers must be at least 1, got 0"]),
        (["--workers", "2", "--tile-size", "0"], ["--tile-size must be a positive number of metres"]),
        (["--workers", "2", "--tile-size", "-3"], ["--tile-size must be a positive number of metres"]),
        (["--workers", "2", "--checkpoint-every", "-1"], ["--checkpoint-every must be 0"]),
        (["--workers", "2", "--worker-threads", "0"], ["--worker-threads must be at least 1"]),
        (["--tile-size", "8"], ["--tile-size needs --workers N"]),
        (["--resume", "--tiled", "{tmp}/T"], ["--tiled, --resume need --workers N"]),
        (["--workers", "2", "--resume"], ["--resume: no checkpoint to carry on from", "m.ndtom.tiles"]),
        (["--workers", "2", "--resume", "--tiled", "{tmp}/none"], ["no checkpoint to carry on from", "--tiled DIR"]),
        (
            ["--workers", "3", "--resume", "--tiled", "{tmp}/old"],
            ["holds a run at -r 0.25 with --workers 2", "-r, --workers"],
        ),
        (["--workers", "2", "--tile-size", "4", "--resume", "--tiled", "{tmp}/old"], ["(--tile-size 1)"]),
        (["--workers", "2", "--tiled", "{tmp}/afile"], ["--tiled", "afile is a file, not a folder"]),
        (["--workers", "2", "--tiled", "{tmp}/full"], ["full is not empty and holds no tiled map"]),
        (["--workers", "2", "--tiled", "{tmp}/m.ndtom"], ["is the map file -o"]),
        (["--workers", "2", "--view"], ["--view maps in this process: not with --workers"]),
        (["--workers", "2", "--cluster", "nowhere"], ["--cluster must be a Ray cluster's address HOST:PORT"]),
        (
            ["--workers", "2", "--cluster", "127.0.0.1:{port}"],
            ["cannot reach the Ray cluster at 127.0.0.1:", "ray start"],
        ),
    ],
    ids=[
        "workers-0",
        "tile-size-0",
        "tile-size-negative",
        "checkpoint-every-negative",
        "threads-0",
        "tile-size-alone",
        "resume-alone",
        "resume-no-checkpoint",
        "resume-empty-folder",
        "resume-other-workers",
        "resume-other-tiles",
        "tiled-is-a-file",
        "tiled-not-empty",
        "tiled-is-the-output",
        "view",
        "cluster-not-an-address",
        "cluster-unreachable",
    ],
)
def test_bad_options_fail_before_mapping(tmp_path: Path, no_mapping, args: list[str], texts: list[str]) -> None:
    (tmp_path / "afile").write_text("x")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("x")
    old = tmp_path / "old"  # the checkpoint of a stopped run: -r 0.25, 2 workers, tiles of 1 m (4 cells)
    old.mkdir()
    for name in ("a.ndtom", "b.ndtom"):
        (old / name).write_bytes(b"")
    info = {"resolution": pb.RES, "tile_size": 1.0, "tile_cells": 4, "workers": 2, "scans": 2, "complete": False}
    doc = {"format": "ndtom-tiled", "version": 1, **info, "tiles": ["a.ndtom", "b.ndtom"]}
    (old / "manifest.json").write_text(json.dumps({**doc, "tile_ids": [[0, 0, 0], [1, 0, 0]]}))
    bag = pb.write_plane_bag(tmp_path)
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    r = run("map", bag, "-r", pb.RES, "-o", tmp_path / "m.ndtom", *(a.format(tmp=tmp_path, port=port) for a in args))
    assert_user_error(r, *texts)


def test_without_ray_says_which_extra(tmp_path: Path) -> None:
    bag = pb.write_plane_bag(tmp_path)
    r = ndtom(tmp_path, "map", bag, "-r", pb.RES, "-o", "m.ndtom", "--workers", "2", hide=("ray",))
    assert r.returncode == 1, r.stderr  # the code of every missing extra (the viewer's too)
    assert "needs the optional package ray, which is not installed (extra [cluster])" in r.stderr
    assert f'pip install -e "{REPO}[cluster]"' in r.stderr
    assert "Mapping" not in r.stderr and sorted(p.name for p in tmp_path.iterdir()) == ["plane.bag"]


def test_commands_refuse_a_folder_without_manifest(tmp_path: Path) -> None:
    folder = tmp_path / "tiles"
    folder.mkdir()
    assert_user_error(run("merge", folder), "tiles is not a tiled map: it has no manifest.json")
    assert_user_error(run("merge", tmp_path / "nope"), "no tiled map at")
    assert_user_error(run("export", folder, "-o", tmp_path / "x.ply"), "is a folder without a manifest.json")
    assert_user_error(run("info", folder), "tiled map's folder (with its manifest.json)")
    (tmp_path / "f.ndtom").write_bytes(b"x")
    assert_user_error(run("merge", tmp_path / "f.ndtom"), "is a file, not a tiled map's folder")


def test_a_tiled_folder_is_read_as_a_map(tmp_path: Path, local_engine) -> None:
    """export and view take a tiled folder (its tiles joined); merge's default name; a
    stopped run's folder is merged with a note and marked incomplete."""
    bag = pb.write_plane_bag(tmp_path)
    t = tmp_path / "site.tiles"
    r = run("map", bag, "-r", pb.RES, "-o", tmp_path / "m.ndtom", "--workers", "2", "--tile-size", "1", "--tiled", t)
    assert r.exit_code == 0, r.output
    assert_same_cells(tmp_path / "m.ndtom", t)
    r = run("export", t, "-o", tmp_path / "t.ply")
    assert r.exit_code == 0 and "Exported" in r.output, r.output
    assert run("merge", t).exit_code == 0
    assert_same_cells(tmp_path / "m.ndtom", tmp_path / "site.ndtom")
    assert run("merge", t, "-o", tmp_path / "small.ndtom", "--compact").exit_code == 0
    assert (
        read_header(tmp_path / "small.ndtom")["version"] == 7 and read_header(tmp_path / "site.ndtom")["version"] == 6
    )
    pytest.importorskip("viser")
    from ndtom_ti.viewer.cli import view_command

    assert view_command(t, "127.0.0.1", 0, tmp_path / "t.html") == 0
    assert (tmp_path / "t.html").stat().st_size > 1000


def test_ray_init_leaves_the_commands_sigterm_handler() -> None:
    """ray.init sets a SIGTERM handler that exits at once; the engine puts the command's
    back (SIGTERM: the scan in hand finishes and the map is saved, as for Ctrl-C)."""
    from ndtom_ti.cluster.engines import _own_sigterm

    def mine(signum, frame):
        pass

    before = signal.signal(signal.SIGTERM, mine)
    try:
        with _own_sigterm():
            signal.signal(signal.SIGTERM, lambda s, f: None)  # what ray.init does
        assert signal.getsignal(signal.SIGTERM) is mine
    finally:
        signal.signal(signal.SIGTERM, before)
