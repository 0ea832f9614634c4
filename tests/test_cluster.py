"""One map built by several workers (ndtom_ti.cluster) equals the one-process map of the
same scans, bit for bit: cells, log-odds, Gaussian counts, means, scatters, erased-neighbour
counts and states, for both miss models, real and simulated scans, any tiling, a lost
worker, checkpoints and resumed runs."""

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, _import_simworld
from ndtom_ti.kernels.layout import TileOwner

from ndtom_ti import NdtOmMap
from ndtom_ti.cellkeys import pack
from ndtom_ti.cellstate import ARRAYS
from ndtom_ti.cluster import TiledMap, Tiling
from ndtom_ti.cluster.engines import probe_hash
from ndtom_ti.cluster.worker import TileWorker
from ndtom_ti.mapfile import MapFileError
from ndtom_ti.snapshot import MapSnapshot
from ndtom_ti.tiledfile import MANIFEST

RES = 0.2
MODELS = ("paper", "ndt")
BALM = DATA / "balm_hall_every4"


def sim_scans(sim_hall_dynamic, count: int = 24):
    _import_simworld()
    d = sim_hall_dynamic
    return [(d.scan(i), d.poses[i]) for i in range(min(count, d.n_scans))]


def one_process(scans, model: str) -> MapSnapshot:
    with NdtOmMap(RES, miss_model=model) as m:
        for pts, T in scans:
            m.insert_scan(pts, T)
        return m.snapshot()


def tiled(scans, model: str, **kw) -> MapSnapshot:
    kw.setdefault("engine", "local")
    with TiledMap(RES, miss_model=model, probe=False, **kw) as tm:
        for pts, T in scans:
            tm.insert_scan(pts, T)
        return tm.snapshot()


def assert_same_map(a: MapSnapshot, b: MapSnapshot) -> None:
    diffs = []
    for name in ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        if x.shape != y.shape:
            diffs.append(f"{name}: shapes {x.shape} != {y.shape}")
        elif not np.array_equal(x, y):
            diffs.append(f"{name}: {int((x != y).reshape(len(x), -1).any(axis=1).sum())} rows differ")
    assert not diffs, "; ".join(diffs)
    assert (a.scans_inserted, a.points_inserted) == (b.scans_inserted, b.points_inserted)


@pytest.fixture(scope="module")
def sim(sim_hall_dynamic):
    return sim_scans(sim_hall_dynamic)


@pytest.fixture(scope="module")
def reference(sim):
    return {model: one_process(sim, model) for model in MODELS}


def test_owners_in_numpy_and_in_the_kernels_agree(sim):
    """Each worker's map holds exactly the cells the tiling gives it (the kernels' hash is
    numpy's), negative indices and all."""
    scans = sim[:3]
    til = Tiling(RES, 3, 1.6)
    workers = [TileWorker(til, w, config=NdtOmMap(RES).config) for w in range(3)]
    for pts, T in scans:
        for w in workers:
            w.step(pts, T)
    for i, w in enumerate(workers):
        cells = w.snapshot().occ_index
        assert len(cells) and (cells < 0).any()
        assert (til.owners(cells) == i).all()
        w.close()


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize(("workers", "tile_size"), [(2, 8.0), (3, 3.2)])
def test_tiles_give_the_one_process_map(sim, reference, model, workers, tile_size):
    """Two tilings (tiles of 40 and 16 cells: most rays cross several) give the map of one
    process, bit for bit."""
    assert_same_map(reference[model], tiled(sim, model, workers=workers, tile_size=tile_size))


def test_most_rays_cross_three_tiles_or_more(sim):
    """The tilings above are a real test of the seams: at 8 m (two workers) most rays of
    the simulated hall pass 3 or more tiles (sampled every 5 cm along 2,000 rays a scan)."""
    til = Tiling(RES, 2, 8.0)
    rng = np.random.default_rng(1)
    crossing = []
    for pts, T in sim[::6]:
        world = pts[rng.choice(len(pts), 2000, replace=False)] @ T[:3, :3].T + T[:3, 3]
        o = T[:3, 3]
        for z in world:
            n = int(np.linalg.norm(z - o) / 0.05) + 2
            cells = np.floor((o + np.linspace(0, 1, n)[:, None] * (z - o)) / RES).astype(np.int64)
            crossing.append(len(np.unique(cells // til.tile_cells, axis=0)))
    assert np.mean(np.array(crossing) >= 3) > 0.5, np.bincount(crossing)


def test_workers_that_round_differently_are_refused(monkeypatch):
    """The start-up probe: a worker whose fixed scene hashes otherwise stops the job."""
    from ndtom_ti.cluster.engines import LocalEngine

    monkeypatch.setattr(LocalEngine, "probe", lambda self: ["0" * 64])
    with pytest.raises(RuntimeError, match="round"):
        TiledMap(RES, workers=2, engine="local")


def test_erasures_cross_tiles_as_events(sim, reference):
    """Without the events, cells beside another worker's tile miss erased neighbours: with
    tiles of 8 m some cell reaches 6 (its rows widen) only through another worker's erasures."""
    til = Tiling(RES, 2, 8.0)
    cfg = NdtOmMap(RES, miss_model="ndt").config
    workers = [TileWorker(til, w, config=cfg) for w in range(2)]
    for pts, T in sim:
        for w in workers:
            w.step(pts, T)  # the other worker's events dropped
    alone = MapSnapshot.join([w.snapshot() for w in workers])
    for w in workers:
        w.close()
    ref = reference["ndt"]
    ka, kb = pack(ref.g_index)[0], pack(alone.g_index)[0]
    _, ia, ib = np.intersect1d(ka, kb, return_indices=True)
    short = (ref.g_erased_near[ia] >= 6) & (alone.g_erased_near[ib] < 6)
    assert short.any(), "no cell reached 6 erased neighbours through another worker"
    assert_same_map(ref, tiled(sim, "ndt", workers=2, tile_size=8.0))


@pytest.mark.skipif(not BALM.exists(), reason="shared data not present")
@pytest.mark.parametrize("model", MODELS)
def test_real_lidar_scans_in_tiles(model):
    from ndtom_ti.io import open_recording

    with open_recording(BALM) as rec:
        scans = [(s.points, s.T_world_sensor) for s in rec.scans(max_scans=6)]
    assert_same_map(one_process(scans, model), tiled(scans, model, workers=2, tile_size=8.0))


def test_checkpoints_make_a_tiled_map_and_resume(sim, reference, tmp_path):
    """A checkpoint folder is a map (MapSnapshot.load joins it) of the scans so far; a run
    resumed from it ends with the map of one run."""
    folder = tmp_path / "tiles"
    half = len(sim) // 2
    with TiledMap(RES, workers=2, tile_size=8.0, engine="local", probe=False, folder=folder, checkpoint_every=4) as tm:
        for pts, T in sim[:half]:
            tm.insert_scan(pts, T)
    assert_same_map(one_process(sim[:half], "ndt"), MapSnapshot.load(folder))
    names = sorted(p.name for p in folder.iterdir())
    doc = json.loads((folder / MANIFEST).read_text())
    assert names == sorted([MANIFEST, *doc["tiles"]]) and len(doc["tiles"]) > 2  # a file per tile
    assert all(n.startswith("tile_") and n.endswith(f"-scan{half}.ndtom") for n in doc["tiles"])
    for name, tile in zip(doc["tiles"], doc["tile_ids"]):  # each file holds its tile's cells
        part = MapSnapshot.load(folder / name)
        assert (np.concatenate([part.occ_index, part.g_index]) // Tiling(RES, 2, 8.0).tile_cells == tile).all()
    with TiledMap(RES, workers=2, tile_size=8.0, engine="local", probe=False, folder=folder, resume=True) as tm:
        assert tm.scans_inserted == half
        for pts, T in sim[half:]:
            tm.insert_scan(pts, T)
        assert_same_map(reference["ndt"], tm.snapshot())
    with pytest.raises(ValueError, match="same settings"):
        TiledMap(RES, workers=3, tile_size=8.0, engine="local", probe=False, folder=folder, resume=True)


def test_a_resumed_run_keeps_the_shift_of_georeferenced_poses(sim, tmp_path):
    """Poses kilometres from their frame's origin: the mapping loop shifts them by the first
    one's position (rounded); the checkpoint keeps that shift and a resumed run applies it."""
    from ndtom_ti.frames import shifted
    from ndtom_ti.pipeline import MappingSummary, run_scans

    utm = np.array([512_345.0, 5_412_345.0, 251.0])
    far = [(pts, shifted(T, -utm)) for pts, T in sim]
    folder = tmp_path / "tiles"
    half = len(sim) // 2
    kw = {"workers": 2, "tile_size": 8.0, "engine": "local", "probe": False, "folder": folder}
    with TiledMap(RES, **kw) as tm:
        run_scans(tm, far[:half], MappingSummary())
        tm.checkpoint()
        origin = tm.metadata["frame_origin"]
    assert origin == [512_300.0, 5_412_300.0, 300.0]
    assert MapSnapshot.load(folder).metadata["frame_origin"] == origin  # the folder read as a map
    with TiledMap(RES, resume=True, **kw) as tm:
        assert tm.metadata["frame_origin"] == origin and tm.scans_inserted == half
        summary = MappingSummary()
        run_scans(tm, far[half:], summary)
        assert summary.scans_used == len(sim) - half and summary.frame_origin == origin  # the kept one
        got = tm.snapshot()
    assert_same_map(one_process([(pts, shifted(T, np.array(origin))) for pts, T in far], "ndt"), got)
    assert got.metadata["frame_origin"] == origin


def test_a_resumed_run_must_name_the_same_job(sim, tmp_path):
    """``job`` (what the scans are) goes into the checkpoint; resuming with another is refused."""
    folder = tmp_path / "tiles"
    kw = {"workers": 2, "tile_size": 8.0, "engine": "local", "probe": False, "folder": folder}
    with TiledMap(RES, job={"source": "a.bag", "every": (1, 2)}, **kw) as tm:
        tm.insert_scan(*sim[0])
        tm.checkpoint()
    with pytest.raises(ValueError, match="other scans or settings"):
        TiledMap(RES, job={"source": "b.bag", "every": (1, 2)}, resume=True, **kw)
    with TiledMap(RES, job={"source": "a.bag", "every": (1, 2)}, resume=True, **kw) as tm:
        assert tm.scans_inserted == 1


def test_broken_tiled_folders_are_refused(sim, tmp_path):
    folder = tmp_path / "tiles"
    with TiledMap(RES, workers=2, tile_size=8.0, engine="local", probe=False, folder=folder) as tm:
        tm.insert_scan(*sim[0])
        tm.checkpoint()
    manifest = (folder / MANIFEST).read_text()
    (folder / json.loads(manifest)["tiles"][1]).unlink()
    with pytest.raises(MapFileError, match="missing"):
        MapSnapshot.load(folder)
    (folder / MANIFEST).write_text(manifest.replace('"version": 1', '"version": 99'))
    with pytest.raises(MapFileError, match="version 99"):
        MapSnapshot.load(folder)


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="workers"):
        Tiling(RES, 0)
    with pytest.raises(ValueError, match="tile size"):
        Tiling(RES, 2, -1.0)
    with pytest.raises(ValueError, match="leaves"):
        TileOwner(tile=12, workers=2, worker=0).validate(8)
    with pytest.raises(ValueError, match="worker 2"):
        TileOwner(tile=8, workers=2, worker=2).validate(8)
    with pytest.raises(ValueError, match="engine"):
        TiledMap(RES, engine="spark")
    with pytest.raises(ValueError, match="folder"):
        TiledMap(RES, engine="local", checkpoint_every=5)


@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    yield ray
    ray.shutdown()


def test_ray_workers_give_the_one_process_map_and_survive_a_lost_worker(ray_cluster, sim, reference, tmp_path):
    """Two Ray worker processes of one thread each, the NDT miss model: the one-process map;
    a worker killed mid-run makes the job go back to its last checkpoint and replay, with
    the same result. Then the paper's model on the same cluster."""
    scans = sim[:12]
    with TiledMap(
        RES, workers=2, tile_size=8.0, threads=1, folder=tmp_path / "t", checkpoint_every=4, miss_model="ndt"
    ) as tm:
        for i, (pts, T) in enumerate(scans):
            tm.insert_scan(pts, T)
            if i == 6:
                tm.kill_worker(1)
        assert tm.restarts == 1
        tm.kill_worker(0)  # lost at a checkpoint, then at the end: recovered as during a scan
        tm.checkpoint()
        tm.kill_worker(1)
        assert_same_map(one_process(scans, "ndt"), tm.snapshot())
        assert tm.restarts == 3
        assert_same_map(one_process(scans, "ndt"), MapSnapshot.load(tmp_path / "t"))
        with NdtOmMap.from_snapshot(one_process(scans, "ndt")) as m:
            assert tm.memory_report()["gaussians"] == m.memory_report()["gaussians"]
    # the paper's miss model on the same cluster, tiles of 16 m
    with TiledMap(RES, workers=2, tile_size=16.0, threads=1, miss_model="paper", probe=False) as tm:
        for pts, T in scans[:6]:
            tm.insert_scan(pts, T)
        assert_same_map(one_process(scans[:6], "paper"), tm.snapshot())


def test_saved_tiled_map_is_one_map_file(sim, tmp_path):
    """TiledMap.save writes the one-process map's file, byte for byte."""
    scans = sim[:6]
    with NdtOmMap(RES) as m:
        for pts, T in scans:
            m.insert_scan(pts, T)
        a = m.save(tmp_path / "a.ndtom")
    with TiledMap(RES, workers=2, tile_size=8.0, engine="local", probe=False) as tm:
        for pts, T in scans:
            tm.insert_scan(pts, T)
        b = tm.save(tmp_path / "b.ndtom")
    assert Path(a).read_bytes() == Path(b).read_bytes()


@pytest.mark.skipif(not BALM.exists(), reason="shared data not present")
def test_tiled_maps_leave_the_shared_scratch_clean():
    """Maps of the process share the scan scratch (the dense block and its row flags), zero
    between scans: a worker's scans leave it so (the hit marks of other workers' cells
    too), and maps made after them are the maps made before them."""
    from ndtom_ti import runtime
    from ndtom_ti.io import open_recording

    with open_recording(BALM) as rec:
        scans = [(s.points, s.T_world_sensor) for s in rec.scans(max_scans=3)]
    before = probe_hash()
    st = runtime.storage(None)
    with TiledMap(RES, workers=2, tile_size=8.0, engine="local", probe=False, miss_model="ndt") as tm:
        for pts, T in scans:
            tm.insert_scan(pts, T)
            assert not st.block_buf.any() and not st.bflag_buf.any()
    assert probe_hash() == before


_ONE_PROCESS_AT_LIMIT = """
import sys
import ndtom_ti
ndtom_ti.init("cpu", memory_limit_GB=float(sys.argv[2]))
from ndtom_ti import NdtOmMap, MapMemoryError
from ndtom_ti.io import open_recording
with open_recording(sys.argv[1]) as rec, NdtOmMap(0.1) as m:
    for i, s in enumerate(rec.scans()):
        try:
            m.insert_scan(s.points, s.T_world_sensor)
        except MapMemoryError:
            print("refused", i)
            break
"""


@pytest.mark.slow
@pytest.mark.skipif(not BALM.exists(), reason="shared data not present")
def test_a_map_one_process_refuses_builds_on_two_workers_at_its_budget(ray_cluster):
    """Each worker has its own memory budget: BALM at 0.1 m, refused by one process at
    0.52 GB (it holds a few scans), builds whole on two workers at 0.52 GB each, and is the
    map of an unlimited process."""
    import subprocess
    import sys

    from ndtom_ti.io import open_recording

    limit = 0.52
    res = subprocess.run(
        [sys.executable, "-c", _ONE_PROCESS_AT_LIMIT, str(BALM), str(limit)],
        capture_output=True,
        text=True,
        timeout=900,
        check=True,
    )
    assert "refused" in res.stdout, res.stdout
    with open_recording(BALM) as rec:
        scans = [(s.points, s.T_world_sensor) for s in rec.scans()]
    with TiledMap(0.1, workers=2, tile_size=8.0, threads=1, memory_limit_GB=limit, probe=False) as tm:
        for pts, T in scans:
            tm.insert_scan(pts, T)
        tiled_map = tm.snapshot()
    with NdtOmMap(0.1) as m:
        for pts, T in scans:
            m.insert_scan(pts, T)
        assert_same_map(m.snapshot(), tiled_map)


def test_a_scan_one_worker_refuses_is_undone_in_all(sim, monkeypatch):
    """A worker refusing a scan for memory (after another took it): every worker goes back to
    the scans before it, the refusal reaches the caller, and the map goes on from there."""
    from ndtom_ti import MapMemoryError

    scans = sim[:6]
    real = TileWorker.step
    refuse = {"at": 4}

    def step(self, points, pose, *events):
        if self.worker == 1 and self.map.scans_inserted == refuse["at"]:
            refuse["at"] = -1  # once
            raise MapMemoryError("refused (test)")
        return real(self, points, pose, *events)

    monkeypatch.setattr(TileWorker, "step", step)
    with TiledMap(RES, workers=2, tile_size=8.0, engine="local", probe=False) as tm:
        for pts, T in scans[:4]:
            tm.insert_scan(pts, T)
        with pytest.raises(MapMemoryError, match="refused"):
            tm.insert_scan(*scans[4])
        assert tm.restarts == 1 and tm.scans_inserted == 4
        assert_same_map(one_process(scans[:4], "ndt"), tm.snapshot())
        tm.insert_scan(*scans[4])
        tm.insert_scan(*scans[5])
        assert_same_map(one_process(scans, "ndt"), tm.snapshot())
