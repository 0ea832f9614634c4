"""TiledMap: one map built by several workers, equal cell for cell to the one-process map
of the same scans in the same order."""

from __future__ import annotations

import copy
import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from ..config import MapConfig, check_resolution, config_of
from ..frames import as_frame_origin
from ..kernels.layout import tile_owners
from ..runtime import MapMemoryError
from ..scan_update import ScanReport
from ..scaninput import as_points, as_pose
from ..snapshot import MapSnapshot
from ..tiledfile import check_tiles, read_manifest, write_manifest
from .engines import LocalEngine, RayEngine, Start, WorkerLost, WorkerSpec
from .tiling import Tiling

ENGINES = ("ray", "local")
_T = TypeVar("_T")
# Report fields each worker counts for its own cells (summed); the rest every worker
# counts alike for the whole scan.
_OWN_FIELDS = ("cells_hit", "cells_passed", "gaussians_erased")


# What `ndtom map` calls the job's fields (selection.K, config.K), where the name is not --K.
_OPTION_NAMES = {
    "recording": "the recording",
    "occupancy": "--occupancy/--no-occupancy",
    "selection.poses_file": "--poses",
    "selection.sensor_frame_only": "--sensor-frame",
    "selection.static_transforms": "--static-transform",
}
_CONFIG_OPTIONS = ("min_range", "max_range", "miss_model")


def _option_name(key: str) -> str:
    """A job field as `ndtom map` names it: ``selection.every`` -> ``--every (selection.every)``."""
    if key in _OPTION_NAMES:
        return _OPTION_NAMES[key] + (f" ({key})" if "." in key else "")
    group, _, field = key.partition(".")
    if group == "selection" or (group == "config" and field in _CONFIG_OPTIONS):
        return f"--{field.replace('_', '-')} ({key})"
    return f"{key} (a config file's {field})" if group == "config" else key


def _differences(then: dict, now: dict, prefix: str = "") -> list[str]:
    """The fields of two job records that differ, each as `--every (selection.every) was 1,
    now 2`. Fields a record made before they were recorded lacks are not compared."""
    out = []
    for k in sorted(set(then) | set(now)):
        if k not in then:  # (an older record)
            continue
        a, b = then.get(k), now.get(k)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict) and k in ("selection", "config"):
            out += _differences(a, b, f"{k}.")
        elif k == "recording_id":
            if then.get("recording") == now.get("recording"):  # (another path says it already)
                sizes = [r.get("bytes") if isinstance(r, dict) else None for r in (a, b)]
                out.append(
                    f"the recording at that path was replaced ({sizes[0]} bytes then, {sizes[1]} now, or other first "
                    "bytes)"
                )
        else:
            out.append(f"{_option_name(prefix + k)} was {json.dumps(a)}, now {json.dumps(b)}")
    return out


def check_job(folder: Path, doc: dict, job: dict | None) -> None:
    """A resumed run must map the scans of the stopped one (``job``: their source, selection
    and map settings, as the stopped run gave them; None: not checked)."""
    then = doc.get("job")
    if job is None or then is None:
        return
    now: dict = json.loads(json.dumps(job))  # as the manifest holds it: tuples become lists
    diffs = _differences(then, now)
    if diffs:
        raise ValueError(
            f"{folder} holds a run of other scans or settings: {'; '.join(diffs)}. Resume with the stopped run's "
            "recording, selection and map options"
        )


def recording_id(path: str | Path) -> dict | None:
    """What identifies a recording besides its path (a file replaced at the same path has
    another): its bytes and a digest of each file's name, size and first MiB (a ROS2 bag's
    folder: of each of its files). None when there is no such file or folder."""
    p = Path(path)
    try:
        files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p] if p.is_file() else []
        if not files:
            return None
        h, total = hashlib.sha256(), 0
        for f in files[:1000]:
            size = f.stat().st_size
            total += size
            h.update(f"{f.relative_to(p) if f != p else ''}:{size}\n".encode())
            with open(f, "rb") as fh:
                h.update(fh.read(1 << 20))
    except OSError:
        return None
    return {"bytes": total, "head_sha256": h.hexdigest()}


def job_of(metadata: dict, occupancy: bool, config: MapConfig) -> dict | None:
    """The job record of a map the mapping loop makes (``pipeline.map_recording``'s metadata:
    the recording and its selection), as `ndtom map` records it; None for other scans."""
    source, options = metadata.get("source"), metadata.get("options")
    if not isinstance(source, str) or not isinstance(options, dict) or not Path(source).exists():
        return None
    return {
        "recording": source,
        # where a run stops (max_scans, end) may change when it is resumed
        "selection": {k: v for k, v in options.items() if k not in ("max_scans", "end")},
        "occupancy": occupancy,
        "config": config.to_dict(),
    }


class TiledMap:
    """An NDT-OM whose cells are shared among ``workers`` worker processes in cubic tiles
    of ``tile_size`` metres (:class:`~ndtom_ti.cluster.tiling.Tiling`).

    Every scan goes to every worker, which traces all its rays and updates its own cells;
    the NDT miss model's erased-neighbour rule crosses tiles as events between scans. The
    result is the map one process makes, bit for bit (``snapshot``, ``save``).

    ``engine``: "ray" (a local Ray cluster, or the one at ``address``) or "local" (the
    workers in this process, one after another). ``threads``: Taichi threads per worker;
    ``memory_limit_GB``: each worker's budget. ``folder``: where checkpoints go (a tiled
    map: a manifest and a map file per tile), every ``checkpoint_every`` scans; a lost
    worker makes the job restart every worker from the last one and replay the scans
    since. A periodic checkpoint that cannot be written (OSError) does not stop the job:
    ``checkpoint_error`` says why, and the next checkpoint tries again. ``resume``: carry on from the checkpoint in ``folder``. Map options as for
    :class:`~ndtom_ti.NdtOmMap` (``config``, ``occupancy`` or MapConfig fields).
    """

    def __init__(
        self,
        resolution: float,
        *,
        workers: int = 2,
        tile_size: float = 16.0,
        engine: str = "ray",
        address: str | None = None,
        occupancy: bool = True,
        config: MapConfig | None = None,
        metadata: dict | None = None,
        threads: int | None = None,
        memory_limit_GB: float | None = None,
        folder: str | Path | None = None,
        checkpoint_every: int = 0,
        resume: bool = False,
        probe: bool = True,
        job: dict | None = None,
        **options: Any,
    ):
        self.resolution = check_resolution(resolution)
        self.config = config_of(config, options)  # NdtOmMap's own checks of its options
        self.config.check_at(self.resolution)
        if engine not in ENGINES:
            raise ValueError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
        if isinstance(checkpoint_every, bool) or not isinstance(checkpoint_every, int) or checkpoint_every < 0:
            raise ValueError(f"checkpoint_every must be an integer >= 0, got {checkpoint_every!r}")
        if checkpoint_every and folder is None:
            raise ValueError("checkpoints need a folder to go to")
        self.tiling = Tiling(self.resolution, workers, tile_size)
        self.occupancy_enabled = bool(occupancy)
        self.metadata: dict = dict(metadata or {})
        # What the scans are (their source and selection): saved with checkpoints, and a
        # resumed run must name the same (JSON's form: tuples become lists).
        if job is None:  # made by the mapping loop (pipeline.map_recording): its recording and selection
            job = job_of(self.metadata, self.occupancy_enabled, self.config)
        if job is not None and "recording" in job and "recording_id" not in job:
            job = {**job, "recording_id": recording_id(job["recording"])}
        self.job = json.loads(json.dumps(job)) if job is not None else None
        self.folder = Path(folder) if folder is not None else None
        self.checkpoint_every = checkpoint_every
        self.scans_inserted = 0
        self.points_inserted = 0
        self.restarts = 0  # times a lost worker made the job go back to a checkpoint
        # why the last periodic checkpoint could not be written (None: it was, or none was due)
        self.checkpoint_error: str | None = None
        self.scan_bytes = 0  # the scans' points and poses sent (once to each worker's host)
        self._since: list[tuple] = []  # scans since the last checkpoint: replayed after a loss
        self._starts: list[Start | None] = [None] * workers
        if resume:
            self._resume()
        self._spec = WorkerSpec(
            tiling=self.tiling,
            config=self.config,
            occupancy=self.occupancy_enabled,
            metadata=self.metadata,
            threads=threads,
            memory_limit_GB=memory_limit_GB,
        )
        self.engine = (
            RayEngine(self._spec, self._starts, address) if engine == "ray" else LocalEngine(self._spec, self._starts)
        )
        try:
            if probe:
                self._probe()
        except BaseException:
            self.engine.close()
            raise

    # ------------------------------------------------------------------ the job

    def _resume(self) -> None:
        if self.folder is None:
            raise ValueError("resume needs the folder of the stopped run's checkpoints")
        doc = read_manifest(self.folder)
        want = {"resolution": self.resolution, "workers": self.tiling.workers, "tile_cells": self.tiling.tile_cells}
        got = {k: doc[k] for k in want}
        if got != want:
            raise ValueError(f"{self.folder} holds a run of {got}, not {want}: resume it with the same settings")
        check_job(self.folder, doc, self.job)
        check_tiles(self.folder, doc)  # a damaged tile: MapFileError here, not in a worker
        self.scans_inserted = int(doc["scans"])
        stop = (self.metadata.get("options") or {}).get("max_scans")
        if isinstance(stop, int) and stop < self.scans_inserted:
            raise ValueError(
                f"{self.folder} already holds {self.scans_inserted} scans, more than the {stop} asked for "
                f"(--max-scans, max_scans): a resumed run only adds scans. Give --max-scans {self.scans_inserted} "
                f"or more (or none) to carry on; `ndtom merge {self.folder}` writes the map of the "
                f"{self.scans_inserted} it holds"
            )
        self.points_inserted = int(doc.get("points", 0))
        kept = doc.get("frame_origin")
        if kept is not None:  # the resumed scans are shifted as the stopped run's were
            origin = as_frame_origin(kept)
            if origin is None:
                raise ValueError(f"{self.folder}'s manifest has a bad frame_origin {kept!r}: three numbers expected")
            self.metadata["frame_origin"] = origin.tolist()
        self._starts = self._starts_of(doc["tiles"], doc["tile_ids"])

    def _probe(self) -> None:
        from .engines import probe_hash

        mine = probe_hash()
        theirs = self.engine.probe()
        bad = [i for i, h in enumerate(theirs) if h != mine]
        if bad:
            raise RuntimeError(
                f"workers {bad} map a fixed scene differently from this process (hosts that round "
                "differently): their cells would differ from a one-process map; run the job on "
                f"hosts of one CPU type and the same ndtom_ti and Taichi versions (hashes: this "
                f"process {mine[:12]}, workers {[h[:12] for h in theirs]})"
            )

    def insert_scan(self, points: Any, T_world_sensor: Any) -> ScanReport:
        """Insert one scan on every worker (see :meth:`NdtOmMap.insert_scan`)."""
        t0 = time.perf_counter()
        scan = (as_points(points), as_pose(T_world_sensor))
        try:
            reps = self._step(scan)
        except MapMemoryError:
            self._recover()  # workers that took the scan go back: the map holds the scans before it
            raise
        self._since.append(scan)
        self.scans_inserted += 1
        self.scan_bytes += scan[0].nbytes + scan[1].nbytes
        rep = ScanReport(**{k: v for k, v in reps[0].items() if k not in _OWN_FIELDS})
        for k in _OWN_FIELDS:
            setattr(rep, k, sum(int(r[k]) for r in reps))
        rep.seconds = time.perf_counter() - t0
        self.points_inserted += rep.points_used
        if self.checkpoint_every and self.scans_inserted % self.checkpoint_every == 0:
            try:
                self.checkpoint()
            except OSError as exc:  # the scans stay in the workers (and here, to replay): the next one tries again
                self.checkpoint_error = f"the checkpoint of {self.scans_inserted} scans failed: {exc}"
        return rep

    def _step(self, scan: tuple) -> list[dict]:
        return self._surviving(lambda: self.engine.step(scan))

    def _surviving(self, call: Callable[[], _T]) -> _T:
        """``call()`` on the workers; a worker lost on the way makes every worker go back to
        the last checkpoint and replay the scans since, then ``call()`` again. Lost again:
        WorkerLost saying where the last checkpoint is and how to carry on from it."""
        try:
            return call()
        except WorkerLost:
            pass
        try:
            self._recover()
            return call()
        except WorkerLost as exc:
            raise self._lost(exc) from None

    def _lost(self, exc: WorkerLost) -> WorkerLost:
        held = self._starts[0].scans if self._starts[0] is not None else 0
        if self.folder is not None and held:
            hint = (
                f"the checkpoint in {self.folder} holds the first {held} scans: carry on from it with the same command "
                "and --resume (TiledMap(..., resume=True))"
            )
        else:
            hint = "no checkpoint was written yet: map again (checkpoints every K scans: --checkpoint-every K)"
        return WorkerLost(f"{exc}; it was lost again after the job restarted its workers", hint)

    def _recover(self) -> None:
        """Every worker back to the last checkpoint, then the scans since replayed."""
        self.restarts += 1
        self.engine.restart(self._starts)
        for scan in self._since:
            self.engine.step(scan)

    def checkpoint(self, complete: bool = False) -> Path:
        """Write the workers' cells to ``folder`` (a tiled map that ``MapSnapshot.load``,
        ``ndtom info/export/view`` read and ``resume`` carries on from)."""
        if self.folder is None:
            raise ValueError("this map has no checkpoint folder")
        self.folder.mkdir(parents=True, exist_ok=True)
        folder = self.folder
        names = self._surviving(lambda: self.engine.save(folder, self.scans_inserted))
        info = {
            "resolution": self.resolution,
            "tile_size": self.tiling.tile_size,
            "tile_cells": self.tiling.tile_cells,
            "workers": self.tiling.workers,
            "scans": self.scans_inserted,
            "points": self.points_inserted,
            "complete": bool(complete),
            "job": self.job,
        }
        if self.metadata.get("frame_origin") is not None:  # the loop's shift of the poses (pipeline)
            info["frame_origin"] = self.metadata["frame_origin"]
        path = write_manifest(self.folder, info, names)
        self._starts = self._starts_of([n for n, _ in names], [t for _, t in names])
        self._since = []
        self.checkpoint_error = None
        return path

    def _starts_of(self, names: list[str], tiles: list) -> list[Start | None]:
        """Each worker's tile files of a checkpoint (in ``folder``), by the tiles' owners."""
        assert self.folder is not None
        owners = tile_owners(np.array(tiles, np.int64).reshape(-1, 3), self.tiling.workers)
        return [
            Start(
                tuple(str(self.folder / n) for n, o in zip(names, owners) if o == w),
                self.scans_inserted,
                self.points_inserted,
            )
            for w in range(self.tiling.workers)
        ]

    # ------------------------------------------------------------------ the map

    def snapshot(self) -> MapSnapshot:
        """The whole map (every worker's cells joined), as one process would have made it."""
        s = MapSnapshot.join(self._surviving(self.engine.snapshots))
        md = copy.deepcopy(self.metadata)
        if self.restarts:  # recovered losses of a worker (the map is the same)
            md["worker_restarts"] = self.restarts
        return replace(s, metadata=md)

    def save(self, path: str | Path, *, compact: bool = False) -> Path:
        """Write the whole map to one map file (as ``NdtOmMap.save``)."""
        return self.snapshot().save(path, compact=compact)

    def memory_report(self) -> dict:
        """The workers' memory reports, summed (``workers``: each one's)."""
        each = self._surviving(self.engine.memory)
        total: dict[str, Any] = {k: sum(r[k] for r in each) for k in each[0] if isinstance(each[0][k], int)}
        total["workers"] = each
        return total

    def stats(self) -> list[dict]:
        """Per worker: its process's CPU seconds so far and the erasure events it sent."""
        return self._surviving(self.engine.stats)

    def kill_worker(self, worker: int) -> None:
        """Kill one worker's process (to test recovery): the next scan restarts the job
        from the last checkpoint."""
        self.engine.kill(worker)

    def close(self) -> None:
        self.engine.close()

    def __enter__(self) -> TiledMap:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
