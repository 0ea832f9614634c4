"""`ndtom map --workers N`, `ndtom merge` and TiledMap facing mistakes and faults: outputs
inside the tiled map, folders that cannot be written, tiles that are damaged or of another
run, a resumed run of other scans, lost workers at a checkpoint. Each is a clear error or
a counted, reported recovery, never a traceback or a wrong map. The workers run in this
process (TiledMap's local engine) unless a test says otherwise."""

from __future__ import annotations

import errno
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import test_cluster_cli as cli
import test_pipeline_bags as pb
from test_cluster_cli import assert_same_cells, assert_user_error, run

from ndtom_ti import pipeline
from ndtom_ti.cluster import TiledMap
from ndtom_ti.mapfile import MapFileError
from ndtom_ti.snapshot import MapSnapshot
from ndtom_ti.tiledfile import MANIFEST

local_engine = cli.local_engine  # the workers in this process
no_mapping = cli.no_mapping  # the command must stop before mapping

TWO = ("--workers", "2", "--tile-size", "1", "--no-progress")


@pytest.fixture
def bag(tmp_path: Path) -> Path:
    return pb.write_plane_bag(tmp_path)


def refuse(*args, **kwargs):
    raise AssertionError("mapping started")


def map_bag(bag: Path, *args: object):
    return run("map", bag, "-r", pb.RES, *TWO, *args)


# ---------------------------------------------------------------------------- A: -o inside --tiled
def test_the_map_file_inside_the_tiled_folder_is_refused(tmp_path: Path, bag: Path, no_mapping) -> None:
    """-o naming the manifest (or any file) inside --tiled DIR would replace it or a tile."""
    q = tmp_path / "q.tiles"
    q.mkdir()
    r = map_bag(bag, "--tiled", q, "-o", q / "manifest.json")
    assert_user_error(r, "lies inside the tiled map (--tiled)", "choose a path outside")
    r = map_bag(bag, "--tiled", q, "-o", q / "m.ndtom")
    assert_user_error(r, "lies inside the tiled map (--tiled)")


def test_the_map_file_inside_a_resumed_tiled_folder_is_refused(tmp_path: Path, bag: Path, local_engine) -> None:
    t = tmp_path / "p.tiles"
    assert map_bag(bag, "--tiled", t, "-o", tmp_path / "m.ndtom").exit_code == 0
    tile = json.loads((t / MANIFEST).read_text())["tiles"][0]
    before = (t / tile).read_bytes()
    r = map_bag(bag, "--tiled", t, "--resume", "-o", t / tile)
    assert_user_error(r, "lies inside the tiled map (--tiled)")
    assert (t / tile).read_bytes() == before


# ---------------------------------------------------------------------------- B: unwritable --tiled
@pytest.mark.parametrize("where", ["afile/sub", "/proc/ndtom-tiles"])
def test_a_tiled_folder_that_cannot_be_made_is_refused_before_mapping(
    tmp_path: Path, bag: Path, no_mapping, where: str
) -> None:
    (tmp_path / "afile").write_text("x")
    folder = tmp_path / where if not where.startswith("/") else Path(where)
    r = map_bag(bag, "--tiled", folder, "-o", tmp_path / "m.ndtom")
    assert r.exit_code in (1, 2), r.output
    assert "Error: cannot make --tiled" in r.output and "Hint:" in r.output, r.output
    assert not (tmp_path / "m.ndtom").exists()


def test_a_checkpoint_that_fails_mid_run_still_writes_the_map(tmp_path: Path, bag: Path, local_engine, monkeypatch):
    """A checkpoint that cannot be written (a full disk) neither stops the mapping nor loses
    it: the map file holds every scan; the run says so and exits 1."""
    ref = tmp_path / "ref.ndtom"
    assert run("map", bag, "-r", pb.RES, "-o", ref, "--no-progress").exit_code == 0

    def full(self, complete=False):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(TiledMap, "checkpoint", full)
    out = tmp_path / "m.ndtom"
    r = map_bag(bag, "--tiled", tmp_path / "T", "--checkpoint-every", "1", "-o", out)
    assert r.exit_code == 1, r.output
    assert "checkpoint of" in r.output and "No space left on device" in r.output, r.output
    assert "the map file was written" in r.output and "internal error" not in r.output
    assert_same_cells(ref, out)


# ---------------------------------------------------------------------------- C: huge tiles
@pytest.mark.parametrize("size", ["1e9", "1e20"])
def test_a_tile_larger_than_the_grid_is_refused(tmp_path: Path, bag: Path, no_mapping, size: str) -> None:
    """A tile's cell count must fit the kernels' int32: at most the grid's side."""
    top = 32768 * pb.RES
    r = run("map", bag, "-r", pb.RES, "--workers", "2", "--tile-size", size, "-o", tmp_path / "m.ndtom")
    assert_user_error(r, f"--tile-size must be at most {top:g} m at -r {pb.RES:g}")
    with pytest.raises(ValueError, match=f"at most {top:g} m"):
        TiledMap(pb.RES, tile_size=float(size), engine="local", probe=False)
    with TiledMap(pb.RES, tile_size=top, engine="local", probe=False) as tm:
        assert tm.tiling.tile_cells == 32768


# ---------------------------------------------------------------------------- D: a damaged checkpoint
def damage(path: Path) -> None:
    """Flip a byte of a map file's payload (its checksum no longer matches)."""
    data = bytearray(path.read_bytes())
    data[-5] ^= 0xFF
    path.write_bytes(bytes(data))


def test_resume_from_a_damaged_tile_is_refused_before_any_worker(tmp_path: Path, bag: Path, local_engine, monkeypatch):
    t = tmp_path / "kc.tiles"
    assert map_bag(bag, "--tiled", t, "--max-scans", "2", "-o", tmp_path / "m.ndtom").exit_code == 0
    tile = json.loads((t / MANIFEST).read_text())["tiles"][1]
    damage(t / tile)
    monkeypatch.setattr(pipeline, "map_recording", refuse)  # from here on the command must stop before mapping
    r = map_bag(bag, "--tiled", t, "--resume", "-o", tmp_path / "m2.ndtom")
    assert_user_error(r, "--resume: the checkpoint in", f"{tile} is corrupt", "new --tiled folder")
    assert "internal error" not in r.output and "please report" not in r.output
    with pytest.raises(MapFileError, match=f"{tile} is corrupt"):  # the API: before any worker starts
        TiledMap(pb.RES, workers=2, tile_size=1.0, engine="local", probe=False, folder=t, resume=True)


# ---------------------------------------------------------------------------- E: a worker lost at a checkpoint
def test_a_worker_lost_at_a_checkpoint_or_the_end_is_recovered(tmp_path: Path, monkeypatch) -> None:
    """A worker lost while the map is saved or checkpointed: the job goes back to the last
    checkpoint, replays the scans since and saves again (the same map, one restart more).
    Lost again: WorkerLost naming the checkpoint and --resume."""
    from ndtom_ti import NdtOmMap
    from ndtom_ti.cluster import WorkerLost
    from ndtom_ti.cluster.engines import LocalEngine

    rng = np.random.default_rng(0)
    scans = [(pb.sensor_points(k, rng), pb.T_map_lidar(k)) for k in range(4)]
    with NdtOmMap(0.25) as m:
        for p, T in scans:
            m.insert_scan(p, T)
        m.save(tmp_path / "ref.ndtom")
    lose = {"save": 0, "snapshots": 0}
    for name in lose:
        real = getattr(LocalEngine, name)

        def failing(self, *args, _real=real, _name=name):
            if lose[_name]:
                lose[_name] -= 1
                raise WorkerLost("a worker process was lost: (test)")
            return _real(self, *args)

        monkeypatch.setattr(LocalEngine, name, failing)
    kw = {"workers": 2, "tile_size": 2.0, "engine": "local", "probe": False, "folder": tmp_path / "t"}
    with TiledMap(0.25, **kw) as tm:
        tm.insert_scan(*scans[0])
        tm.checkpoint()
        for p, T in scans[1:]:
            tm.insert_scan(p, T)
        lose["save"] = 1
        tm.checkpoint()
        assert tm.restarts == 1 and MapSnapshot.load(tmp_path / "t").scans_inserted == 4
        lose["snapshots"] = 1
        tm.save(tmp_path / "m.ndtom")
        assert tm.restarts == 2
        assert_same_cells(tmp_path / "m.ndtom", tmp_path / "t")
        lose["snapshots"] = 2  # lost again after the restart
        with pytest.raises(WorkerLost, match="lost again") as err:
            tm.snapshot()
        assert "holds the first 4 scans" in err.value.hint and "--resume" in err.value.hint
    assert_same_cells(tmp_path / "ref.ndtom", tmp_path / "m.ndtom")


def test_a_worker_lost_for_good_is_a_clear_error(tmp_path: Path, bag: Path, local_engine, monkeypatch) -> None:
    from ndtom_ti.cluster import WorkerLost

    def lost(self, points, T):
        raise WorkerLost("a worker process was lost: (test)", "carry on with --resume (test)")

    monkeypatch.setattr(TiledMap, "insert_scan", lost)
    r = map_bag(bag, "-o", tmp_path / "m.ndtom")
    assert_user_error(r, "a worker process was lost: (test)", "carry on with --resume (test)", code=1)
    assert "internal error" not in r.output and "please report" not in r.output


# ---------------------------------------------------------------------------- F, H: a resumed run of other scans
def test_a_tiled_map_of_the_api_records_its_job(tmp_path: Path, bag: Path) -> None:
    """TiledMap made by the mapping loop records the recording and selection as `ndtom map`
    does: a CLI --resume with another recording is refused."""
    import functools

    t = tmp_path / "api.tiles"
    make = functools.partial(TiledMap, workers=2, tile_size=1.0, engine="local", probe=False, folder=t)
    m, _ = pipeline.map_recording(bag, pb.RES, max_scans=2, make_map=make)
    m.checkpoint(complete=True)
    m.close()
    job = json.loads((t / MANIFEST).read_text())["job"]
    assert job["recording"] == str(bag.resolve()) and job["recording_id"]["bytes"] == bag.stat().st_size
    (tmp_path / "o").mkdir()
    other = pb.write_plane_bag(tmp_path / "o", name="other", n_clouds=pb.N_CLOUDS - 1)
    r = map_bag(other, "--tiled", t, "--resume", "-o", tmp_path / "x.ndtom")
    assert_user_error(r, "other scans or settings", "the recording was")


def test_a_cli_resume_of_an_api_folder_without_a_job_is_refused(tmp_path: Path, bag: Path, no_mapping) -> None:
    t = tmp_path / "api.tiles"
    rng = np.random.default_rng(0)
    with TiledMap(pb.RES, workers=2, tile_size=1.0, engine="local", probe=False, folder=t) as tm:
        tm.insert_scan(pb.sensor_points(0, rng), pb.T_map_lidar(0))
        tm.checkpoint()
    assert json.loads((t / MANIFEST).read_text())["job"] is None
    r = map_bag(bag, "--tiled", t, "--resume", "-o", tmp_path / "x.ndtom")
    assert_user_error(r, "written by the Python API", "resume=True", "new --tiled folder")


def test_a_recording_replaced_at_the_same_path_is_refused(tmp_path: Path, local_engine) -> None:
    (tmp_path / "a").mkdir()
    bag = pb.write_plane_bag(tmp_path / "a")
    t = tmp_path / "T"
    assert map_bag(bag, "--tiled", t, "--max-scans", "2", "-o", tmp_path / "m.ndtom").exit_code == 0
    (tmp_path / "b").mkdir()
    shutil.copy(pb.write_plane_bag(tmp_path / "b", n_clouds=pb.N_CLOUDS - 1), bag)  # another recording there
    r = map_bag(bag, "--tiled", t, "--resume", "-o", tmp_path / "m.ndtom")
    assert_user_error(r, "the recording at that path was replaced (")


def test_resume_with_fewer_scans_than_the_checkpoint_holds_is_refused(tmp_path: Path, bag: Path, local_engine):
    t = tmp_path / "T"
    assert map_bag(bag, "--tiled", t, "--max-scans", "3", "-o", tmp_path / "m.ndtom").exit_code == 0
    r = map_bag(bag, "--tiled", t, "--resume", "--max-scans", "2", "-o", tmp_path / "m2.ndtom")
    assert_user_error(r, "already holds 3 scans, more than the 2 asked for", "--max-scans 3 or more")
    assert not (tmp_path / "m2.ndtom").exists()


def test_resume_with_an_end_before_the_checkpoints_scans_is_refused(tmp_path: Path, bag: Path, local_engine):
    """--end is not part of the job (a resumed run may go further), but an earlier one left a
    map of all the checkpoint's scans, past that end, written with exit 0."""
    t = tmp_path / "T"
    assert map_bag(bag, "--tiled", t, "--max-scans", "3", "-o", tmp_path / "m.ndtom").exit_code == 0
    r = map_bag(bag, "--tiled", t, "--resume", "--end", "0.05", "-o", tmp_path / "m2.ndtom")
    assert_user_error(r, "ends after 0 scans, before the 3 that the checkpoint being resumed holds", f"ndtom merge {t}")
    assert not (tmp_path / "m2.ndtom").exists()
    assert json.loads((t / MANIFEST).read_text())["scans"] == 3  # the checkpoint is as it was


def test_a_resume_with_another_option_names_it(tmp_path: Path, bag: Path, local_engine) -> None:
    t = tmp_path / "T"
    assert map_bag(bag, "--tiled", t, "--max-scans", "2", "-o", tmp_path / "m.ndtom").exit_code == 0
    r = map_bag(bag, "--tiled", t, "--resume", "--every", "2", "-o", tmp_path / "m2.ndtom")
    assert_user_error(r, "--every (selection.every) was 1, now 2")
    assert "{" not in r.output.split("Hint:")[0]  # no dicts dumped


# ---------------------------------------------------------------------------- G: tiles of another run
def test_merge_refuses_a_tile_of_another_run(tmp_path: Path, bag: Path, local_engine) -> None:
    """Same resolution and scan count, other selection: the tile file is not the one the
    manifest names (its digest); without digests (an older manifest) its selection differs
    from the manifest's job; a tile under another tile's name holds cells outside it."""
    a, b = tmp_path / "a.tiles", tmp_path / "b.tiles"
    assert map_bag(bag, "--tiled", a, "--max-scans", "2", "-o", tmp_path / "a.ndtom").exit_code == 0
    assert map_bag(bag, "--tiled", b, "--max-scans", "2", "--every", "2", "-o", tmp_path / "b.ndtom").exit_code == 0
    doc = json.loads((a / MANIFEST).read_text())
    shared = sorted(set(doc["tiles"]) & set(json.loads((b / MANIFEST).read_text())["tiles"]))
    assert shared
    mix = tmp_path / "mix.tiles"
    shutil.copytree(a, mix)
    shutil.copy(b / shared[0], mix / shared[0])
    r = run("merge", mix, "-o", tmp_path / "mix.ndtom")
    assert_user_error(r, shared[0], "is not the file its manifest.json names", "damaged")
    assert not (tmp_path / "mix.ndtom").exists()
    old = {k: v for k, v in doc.items() if k != "tile_sha256"}  # a manifest without digests
    (mix / MANIFEST).write_text(json.dumps(old))
    assert_user_error(run("merge", mix, "-o", tmp_path / "mix.ndtom"), shared[0], "another selection of scans")
    src = next(n for n in doc["tiles"] if n != shared[0])
    shutil.copy(a / src, mix / shared[0])  # another tile's cells under this name
    assert_user_error(run("merge", mix, "-o", tmp_path / "mix.ndtom"), "holds cells outside tile")
    with pytest.raises(MapFileError, match="cells outside tile"):  # the folder read as a map: the same checks
        MapSnapshot.load(mix)


def test_merge_of_a_folder_missing_a_tile_says_it_is_damaged(tmp_path: Path, bag: Path, local_engine) -> None:
    t = tmp_path / "t.tiles"
    assert map_bag(bag, "--tiled", t, "-o", tmp_path / "m.ndtom").exit_code == 0
    gone = json.loads((t / MANIFEST).read_text())["tiles"][0]
    (t / gone).unlink()
    r = run("merge", t)
    assert_user_error(r, f"its tile file {gone} is missing", "the tiled map is damaged")
    assert "give the folder that" not in r.output


# ---------------------------------------------------------------------------- I: memory of the workers
def test_local_workers_share_the_machines_memory(tmp_path: Path, bag: Path, no_mapping, monkeypatch) -> None:
    """On a local cluster the default budget (half the machine) is divided among the workers,
    and an explicit --memory-limit is each worker's: their total must fit the machine."""
    from ndtom_ti import hostpool
    from ndtom_ti.cli import tiles

    monkeypatch.setattr(hostpool, "physical_memory", lambda: 23 * 2**30)
    assert tiles.share_memory(2, None) == pytest.approx(5.75)
    assert tiles.share_memory(2, 11.0) == 11.0
    r = map_bag(bag, "--memory-limit", "20", "-o", tmp_path / "m.ndtom")
    assert_user_error(r, "--memory-limit 20 GiB for each of 2 workers on this machine is 40 GiB", "at most 11.5")
    run_plan = tiles.plan(
        resolution=pb.RES,
        workers=2,
        tile_size=None,
        cluster=None,
        tiled=None,
        checkpoint_every=None,
        resume=False,
        worker_threads=1,
        memory_limit=None,
        output=tmp_path / "m.ndtom",
        view=False,
    )
    assert run_plan is not None and run_plan.memory_limit == pytest.approx(5.75)
    assert "a memory budget of 5.75 GiB each" in run_plan.describe()


# ---------------------------------------------------------------------------- J: messages
def test_cluster_auto_without_a_running_cluster_says_so(tmp_path: Path, bag: Path, monkeypatch) -> None:
    ray = pytest.importorskip("ray")

    def no_cluster(*args, **kwargs):
        raise ConnectionError("Could not find any running Ray instance. Please specify ... RAY_ADDRESS")

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", no_cluster)
    r = map_bag(bag, "--cluster", "auto", "-o", tmp_path / "m.ndtom")
    assert_user_error(r, "no running Ray cluster found on this machine (--cluster auto)", "ray start --head", code=1)
    assert "RAY_ADDRESS" not in r.output and "permissions" not in r.output


def test_a_recovered_worker_loss_is_reported(tmp_path: Path, bag: Path, local_engine, monkeypatch) -> None:
    from ndtom_ti.cluster import WorkerLost
    from ndtom_ti.cluster.engines import LocalEngine

    real, lose = LocalEngine.step, {"n": 1}

    def step(self, scan):
        if lose["n"] and self.workers[0].w.map.scans_inserted == 2:
            lose["n"] = 0
            raise WorkerLost("a worker process was lost: (test)")
        return real(self, scan)

    monkeypatch.setattr(LocalEngine, "step", step)
    ref = tmp_path / "ref.ndtom"
    assert run("map", bag, "-r", pb.RES, "-o", ref, "--no-progress").exit_code == 0
    r = map_bag(bag, "--checkpoint-every", "1", "-o", tmp_path / "m.ndtom")
    assert r.exit_code == 0, r.output
    assert "a worker process was lost 1 time" in r.output
    assert MapSnapshot.load(tmp_path / "m.ndtom").metadata["worker_restarts"] == 1
    assert_same_cells(ref, tmp_path / "m.ndtom")


def test_resume_of_a_folder_missing_a_tile_says_it_is_damaged(tmp_path: Path, bag: Path, local_engine) -> None:
    t = tmp_path / "T"
    assert map_bag(bag, "--tiled", t, "--max-scans", "2", "-o", tmp_path / "m.ndtom").exit_code == 0
    (t / json.loads((t / MANIFEST).read_text())["tiles"][0]).unlink()
    r = map_bag(bag, "--tiled", t, "--resume", "-o", tmp_path / "m.ndtom")
    assert_user_error(r, "--resume: the tiled map", "is missing", "the tiled map is damaged")
    assert "give a map file" not in r.output
