"""Where a tiled map's workers run: in this process (``LocalEngine``) or as Ray actors,
one process and one Taichi runtime each (``RayEngine``).

Both run every scan on every worker in global order. A worker's erasures beside other
tiles (events) reach the others before their next scan: the local engine hands them over
itself; Ray passes the object refs of a step's events as arguments of the others' next
steps, which Ray resolves before the call, so no barrier waits on the driver.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import signal
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..config import MapConfig
from ..runtime import MapMemoryError
from ..snapshot import MapSnapshot
from .tiling import Tiling
from .worker import TileWorker

NO_EVENTS = np.zeros((0, 3), np.int32)


@dataclass(frozen=True)
class Start:
    """Where a worker starts from: the tile files of its cells at a checkpoint of ``scans``
    scans and ``points`` points (none: its tiles held nothing yet)."""

    files: tuple[str, ...]
    scans: int
    points: int


class ClusterError(RuntimeError):
    """A fault of the workers or of their cluster that a user can act on: ``hint`` says how."""

    def __init__(self, message: str, hint: str | None = None):
        super().__init__(message)
        self.hint = hint


class WorkerLost(ClusterError):
    """A worker process died (its cells are lost until the job resumes from a checkpoint)."""


@dataclass(frozen=True)
class WorkerSpec:
    """What every worker of a job is made with."""

    tiling: Tiling
    config: MapConfig
    occupancy: bool = True
    metadata: dict = field(default_factory=dict)
    threads: int | None = None  # Taichi CPU threads per worker process (None: Taichi's default)
    memory_limit_GB: float | None = None  # each worker's own budget


def probe_hash() -> str:
    """A hash of a small fixed map (the demo room, both miss models) made here: hosts that
    round differently give other hashes, and their workers would build another map."""
    from ..demo import make_scans
    from ..map import NdtOmMap

    h = hashlib.sha256()
    for model in ("paper", "ndt"):
        with NdtOmMap(0.1, miss_model=model) as m:
            for scan in make_scans(3, rings=8, per_ring=180):
                m.insert_scan(scan.points, scan.T_world_sensor)
            for a in m.snapshot().state().values():
                h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


class _Worker:
    """One worker as an engine drives it (also the body of a Ray actor)."""

    def __init__(self, spec: WorkerSpec, worker: int, start: Start | None = None, init: bool = False):
        if init:  # a process of its own: its Taichi runtime
            from ..runtime import init as ti_init

            ti_init(arch="cpu", cpu_max_num_threads=spec.threads, memory_limit_GB=spec.memory_limit_GB)
        self.spec, self.index = spec, worker
        self.events = 0
        snap = MapSnapshot.join([MapSnapshot.load(f) for f in start.files]) if start and start.files else None
        self.w = TileWorker(
            spec.tiling,
            worker,
            config=spec.config,
            occupancy=spec.occupancy,
            metadata=spec.metadata,
            start=snap,
        )
        if start is not None and snap is None:  # its tiles held nothing at the checkpoint
            self.w.map.scans_inserted, self.w.map.points_inserted = start.scans, start.points

    def step(self, scan: tuple, *events: np.ndarray) -> tuple[np.ndarray, dict]:
        """(this scan's border erasures, its report) after the others' last erasures."""
        try:
            out = self.w.step(scan[0], scan[1], *events)
        except MapMemoryError as exc:
            raise MapMemoryError(f"worker {self.index}: {exc}") from None
        self.events += len(out)
        return out, self.w.last_report

    def settle(self, *events: np.ndarray) -> None:
        """Count the others' erasures of the last scan now (before a checkpoint or the end)."""
        self.w.count(*events)

    def save(self, folder: str, scans: int) -> list[tuple[str, tuple[int, int, int]]]:
        return self.w.save_tiles(folder, scans)

    def snapshot(self) -> MapSnapshot:
        return self.w.snapshot()

    def memory(self) -> dict:
        return self.w.map.memory_report()

    def stats(self) -> dict:
        """This worker's process CPU seconds and the erasure events it sent (rows, bytes)."""
        return {"cpu_seconds": time.process_time(), "events": self.events, "event_bytes": self.events * 12}

    def probe(self) -> str:
        return probe_hash()

    def close(self) -> None:
        self.w.close()


class LocalEngine:
    """The workers in this process (one map slot each), one after another: the same map as
    a cluster's, for tests and for tilings without an engine."""

    def __init__(self, spec: WorkerSpec, starts: list[Start | None]):
        self.n = spec.tiling.workers
        self.workers = [_Worker(spec, w, starts[w]) for w in range(self.n)]
        self.pending = [NO_EVENTS] * self.n

    def _others(self, w: int) -> list[np.ndarray]:
        return [self.pending[v] for v in range(self.n) if v != w]

    def step(self, scan: tuple) -> list[dict]:
        outs = [wk.step(scan, *self._others(i)) for i, wk in enumerate(self.workers)]
        self.pending = [o[0] for o in outs]
        return [o[1] for o in outs]

    def settle(self) -> None:
        for i, wk in enumerate(self.workers):
            wk.settle(*self._others(i))
        self.pending = [NO_EVENTS] * self.n

    def save(self, folder: Path, scans: int) -> list[tuple[str, tuple[int, int, int]]]:
        self.settle()
        return [t for wk in self.workers for t in wk.save(str(folder), scans)]

    def snapshots(self) -> list[MapSnapshot]:
        self.settle()
        return [wk.snapshot() for wk in self.workers]

    def memory(self) -> list[dict]:
        return [wk.memory() for wk in self.workers]

    def stats(self) -> list[dict]:
        return [wk.stats() for wk in self.workers]

    def probe(self) -> list[str]:
        return [probe_hash()]

    def restart(self, starts: list[Start | None]) -> None:
        """New workers from ``starts`` (tile files; None: empty), no events pending."""
        spec = self.workers[0].spec
        self.close()
        self.workers = [_Worker(spec, w, starts[w]) for w in range(self.n)]
        self.pending = [NO_EVENTS] * self.n

    def kill(self, worker: int) -> None:
        raise NotImplementedError("the local engine's workers are this process")

    def close(self) -> None:
        for wk in self.workers:
            wk.close()


def ray_module():
    """Ray, or an ImportError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise ImportError("mapping with several worker processes needs Ray: pip install 'ndtom_ti[cluster]'") from None
    return ray


@contextlib.contextmanager
def _own_sigterm() -> Iterator[None]:
    """Keep this process's SIGTERM handler through ``ray.init``, which sets one that exits
    at once (``ndtom map`` finishes the scan in hand and saves, as for Ctrl-C)."""
    main = threading.current_thread() is threading.main_thread()
    before = signal.getsignal(signal.SIGTERM) if main else None
    try:
        yield
    finally:
        if before is not None:
            signal.signal(signal.SIGTERM, before)


class RayEngine:
    """The workers as Ray actors (``address``: join that cluster; None: start a local one
    with a CPU per worker thread)."""

    def __init__(self, spec: WorkerSpec, starts: list[Start | None], address: str | None = None):
        ray = self.ray = ray_module()
        self.n = spec.tiling.workers
        threads = spec.threads or 1
        if not ray.is_initialized():
            # Ray's own lines (its start, the token note, the workers' output) stay in its
            # logs (/tmp/ray/session_latest/logs), off the user's terminal: errors only.
            quiet = {"include_dashboard": False, "log_to_driver": False, "logging_level": logging.ERROR}
            with _own_sigterm():
                if address is None:
                    ray.init(num_cpus=max(self.n * threads, 1), **quiet)
                else:
                    try:
                        ray.init(address=address, **quiet)
                    except ConnectionError as exc:
                        raise ClusterError(
                            f"no running Ray cluster found at {address} ({exc})"
                            if address != "auto"
                            else "no running Ray cluster found on this machine (--cluster auto)",
                            "start one with `ray start --head`, or drop --cluster to start a local one for this run",
                        ) from None
            self._owns_ray = True
        else:
            self._owns_ray = False
        self.spec = spec
        self.actor = ray.remote(num_cpus=threads, max_restarts=0)(_Worker)
        self.actors: list[Any] = []
        self.restart(starts)

    def restart(self, starts: list[Start | None]) -> None:
        """New worker processes from ``starts`` (tile files; None: empty), no events pending."""
        for a in self.actors:
            self.ray.kill(a, no_restart=True)
        self.actors = [self.actor.remote(self.spec, w, starts[w], True) for w in range(self.n)]
        self.pending = [NO_EVENTS] * self.n

    def _get(self, refs):
        from ray.exceptions import RayActorError, RayTaskError

        try:
            return self.ray.get(refs)
        except RayActorError as exc:
            raise WorkerLost(f"a worker process was lost: {exc}") from None
        except RayTaskError as exc:
            cause = exc.cause if isinstance(getattr(exc, "cause", None), BaseException) else None
            if cause is not None:
                raise cause from None
            raise

    def _others(self, w: int) -> list:
        return [self.pending[v] for v in range(self.n) if v != w]

    def step(self, scan: tuple) -> list[dict]:
        ref = self.ray.put(scan)  # one copy in the object store, read by every worker
        outs = [a.step.options(num_returns=2).remote(ref, *self._others(i)) for i, a in enumerate(self.actors)]
        self.pending = [o[0] for o in outs]
        return self._get([o[1] for o in outs])

    def settle(self) -> None:
        self._get([a.settle.remote(*self._others(i)) for i, a in enumerate(self.actors)])
        self.pending = [NO_EVENTS] * self.n

    def save(self, folder: Path, scans: int) -> list[tuple[str, tuple[int, int, int]]]:
        self.settle()
        return [t for names in self._get([a.save.remote(str(folder), scans) for a in self.actors]) for t in names]

    def snapshots(self) -> list[MapSnapshot]:
        self.settle()
        return self._get([a.snapshot.remote() for a in self.actors])

    def memory(self) -> list[dict]:
        return self._get([a.memory.remote() for a in self.actors])

    def stats(self) -> list[dict]:
        return self._get([a.stats.remote() for a in self.actors])

    def probe(self) -> list[str]:
        return self._get([a.probe.remote() for a in self.actors])

    def kill(self, worker: int) -> None:
        """Kill worker ``worker``'s process (tests: a lost worker)."""
        self.ray.kill(self.actors[worker], no_restart=True)

    def close(self) -> None:
        for a in self.actors:
            self.ray.kill(a, no_restart=True)
        self.actors = []
        if self._owns_ray:
            self.ray.shutdown()
