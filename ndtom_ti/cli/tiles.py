"""``ndtom map --workers N``'s side of a run on several worker processes (Ray, through
:class:`ndtom_ti.cluster.TiledMap`): its options checked, where its checkpoints go, and
what is kept of them at the end; and ``ndtom merge`` (a tiled map's folder -> one map
file). The mapping loop stays :mod:`ndtom_ti.pipeline`'s."""

from __future__ import annotations

import functools
import math
import os
import shutil
import socket
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.text import Text

from ..exitcodes import EXIT_FAILURE
from ..mapfile import MapFileError
from ..tiledfile import MANIFEST, check_tiles, is_tiled, read_manifest
from .common import (
    MAP_SUFFIX,
    check_map_output,
    check_not_input,
    check_writable,
    console_err,
    console_out,
    fail,
    fmt_count,
    fmt_mib,
    need_extra,
    user_errors,
)
from .root import app

TILES_SUFFIX = ".tiles"  # the checkpoint folder beside the map file without --tiled: OUT.ndtom.tiles
RESUME_HINT = (
    "give the folder of the stopped run with --tiled DIR (without --tiled: OUT.ndtom.tiles beside -o OUT.ndtom)"
)


DAMAGED_HINT = (
    "the tiled map is damaged (a tile file missing, corrupt or of another run): put back the files of its last "
    "checkpoint from a copy, or map again into a new --tiled folder"
)


def default_folder(output: Path) -> Path:
    """Where checkpoints go without --tiled: beside the map file, removed after success."""
    return output.with_name(output.name + TILES_SUFFIX)


@dataclass
class TiledRun:
    """A run of ``ndtom map --workers``: the map's maker, where its checkpoints go, and
    whether that folder stays (``--tiled``) or goes after a complete run."""

    workers: int
    tile_size: float
    address: str | None
    folder: Path
    keep: bool  # --tiled: the folder is a result, its manifest marked complete at the end
    checkpoint_every: int
    resume: bool
    threads: int | None
    memory_limit: float | None
    resumed_scans: int = 0
    checkpoint_failed: str | None = None  # why the last checkpoint could not be written
    job: dict | None = None  # the recording, selection and map settings (checked on --resume)

    def set_job(self, job: dict) -> None:
        """What this run maps; with --resume, the stopped run must have mapped the same."""
        from ..cluster.tiled import check_job, recording_id

        self.job = {**job, "recording_id": recording_id(job["recording"])}
        if self.resume:
            doc = read_manifest(self.folder)
            if doc.get("job") is None:
                fail(
                    f"--resume: {self.folder} was written by the Python API (TiledMap) without a record of its "
                    "recording and selection, so ndtom map cannot tell whether these scans carry it on",
                    "carry it on from Python (TiledMap(..., folder=DIR, resume=True) with the same scans after the "
                    f"{doc['scans']} it holds), or map into a new --tiled folder",
                )
            try:
                check_job(self.folder, doc, self.job)
            except ValueError as exc:
                fail(f"--resume: {exc}", "resume with the stopped run's recording, options and map settings")

    def make_map(self) -> Any:
        """``pipeline.map_recording``'s ``make_map``: a TiledMap on Ray."""
        from ..cluster import TiledMap

        return functools.partial(
            TiledMap,
            workers=self.workers,
            tile_size=self.tile_size,
            engine="ray",
            address=self.address,
            threads=self.threads,
            memory_limit_GB=self.memory_limit,
            folder=self.folder,
            checkpoint_every=self.checkpoint_every,
            resume=self.resume,
            job=self.job,
        )

    def describe(self) -> str:
        where = f"the Ray cluster at {self.address}" if self.address else "a local Ray cluster"
        threads = f", {self.threads} thread{'s' if self.threads != 1 else ''} each" if self.threads else ""
        every = f"every {self.checkpoint_every} scans" if self.checkpoint_every else "at the end"
        text = (
            f"Workers: {self.workers} processes on {where}{threads}; tiles of {self.tile_size:g} m; "
            + (f"a memory budget of {self.memory_limit:.3g} GiB each; " if self.memory_limit is not None else "")
            + f"checkpoints {every} to {self.folder}"
        )
        if self.resume:
            text += f"; resuming after the {self.resumed_scans} scans it holds (read and skipped)"
        return text

    def finish(self, m: Any, summary: Any, command: str) -> None:
        """After the loop, before the map file is written: a complete run's checkpoint
        folder is marked complete (--tiled) or goes away later (:meth:`clean`); a stopped
        run's last scans are checkpointed so that --resume carries on from them."""
        err = console_err()
        if m.restarts:
            err.print(
                Text(
                    f"note: a worker process was lost {m.restarts} time{'s' if m.restarts != 1 else ''}; each time "
                    "the job restarted its workers from the last checkpoint and replayed the scans since (the map is "
                    "the same; its metadata counts them: worker_restarts)",
                    style="yellow",
                )
            )
        if summary.complete and not self.keep:
            return
        if not m.scans_inserted:
            return  # nothing mapped: nothing to keep or resume from
        try:
            m.checkpoint(complete=summary.complete)
        except OSError as exc:  # the map file is still written (-o); the run then exits 1 (clean)
            self.checkpoint_failed = f"the checkpoint of {m.scans_inserted} scans to {self.folder} failed: {exc}"
            err.print(Text(f"Error: {self.checkpoint_failed}; writing the map file anyway", style="red"))
            return
        if not summary.complete:
            err.print(
                Text(
                    f"Checkpoint of {m.scans_inserted} scans written to {self.folder}; carry on with the same "
                    f"command and --resume ({command} ... --resume)",
                    style="yellow",
                )
            )

    def clean(self, summary: Any) -> None:
        """A complete run without --tiled: its checkpoint folder is not needed any more. A
        checkpoint that could not be written fails the run (exit 1) once the map is saved."""
        if self.checkpoint_failed:
            fail(
                f"{self.checkpoint_failed}; the map file was written",
                f"make {self.folder} writable (or give another --tiled DIR) and map again; the map file holds "
                "every scan",
                EXIT_FAILURE,
            )
        if summary.complete and not self.keep and self.folder.is_dir():
            shutil.rmtree(self.folder, ignore_errors=True)


def plan(
    *,
    resolution: float,
    workers: int | None,
    tile_size: float | None,
    cluster: str | None,
    tiled: Path | None,
    checkpoint_every: int | None,
    resume: bool,
    worker_threads: int | None,
    memory_limit: float | None,
    output: Path,
    view: bool,
) -> TiledRun | None:
    """The options of a run on several worker processes checked (ValueError, or a failure
    with a hint), before anything is read; None without --workers."""
    if workers is None:
        given = [
            name
            for name, v in (
                ("--tile-size", tile_size),
                ("--cluster", cluster),
                ("--tiled", tiled),
                ("--checkpoint-every", checkpoint_every),
                ("--resume", resume or None),
                ("--worker-threads", worker_threads),
            )
            if v is not None
        ]
        if given:
            raise ValueError(f"{', '.join(given)} {'needs' if len(given) == 1 else 'need'} --workers N")
        return None
    if workers < 1:
        raise ValueError(f"--workers must be at least 1, got {workers}")
    size = 16.0 if tile_size is None else tile_size
    if not (math.isfinite(size) and size > 0):
        raise ValueError(f"--tile-size must be a positive number of metres, got {size:g}")
    from ..cluster.tiling import max_tile_size

    if size > max_tile_size(resolution):
        raise ValueError(
            f"--tile-size must be at most {max_tile_size(resolution):g} m at -r {resolution:g} (a tile as long as "
            f"the map's whole grid), got {size:g}"
        )
    every = 100 if checkpoint_every is None else checkpoint_every
    if every < 0:
        raise ValueError(f"--checkpoint-every must be 0 (only at the end) or more scans, got {every}")
    if worker_threads is not None and worker_threads < 1:
        raise ValueError(f"--worker-threads must be at least 1, got {worker_threads}")
    if view:
        raise ValueError("--view maps in this process: not with --workers")
    need_extra("ray", "mapping with several worker processes (--workers)")
    if cluster is not None:
        check_reachable(cluster)
    folder = (tiled if tiled is not None else default_folder(output)).expanduser()
    what = "--tiled" if tiled is not None else "the checkpoint folder"
    if folder.exists() and not folder.is_dir():
        fail(
            f"{what} {folder} is a file, not a folder",
            "give a folder for the tiled map (created if missing) with --tiled DIR",
        )
    if os.path.realpath(folder) == os.path.realpath(output.expanduser()):
        fail(f"{what} {folder} is the map file -o {output}", "give the tiled map a folder of its own")
    # the map file inside the folder would replace its manifest or a tile, or be taken for one
    check_not_input(output, {f"tiled map ({what})": folder})
    check_folder_writable(folder, what)
    resumed = 0
    if resume:
        if not is_tiled(folder):
            fail(f"--resume: no checkpoint to carry on from at {folder} (it has no {MANIFEST})", RESUME_HINT)
        try:
            doc = read_manifest(folder)
        except MapFileError as exc:
            fail(f"--resume: {exc}", DAMAGED_HINT)
        resumed = int(doc["scans"])
        from ..cluster.tiling import Tiling

        now = (resolution, workers, Tiling(resolution, workers, size).tile_cells)
        then = (doc["resolution"], doc["workers"], doc["tile_cells"])
        if now != then:
            fail(
                f"--resume: {folder} holds a run at -r {doc['resolution']:g} with --workers {doc['workers']} and "
                f"tiles of {doc['tile_cells']} cells (--tile-size {float(doc.get('tile_size', 0.0)):g}), not "
                f"-r {resolution:g} --workers {workers} --tile-size {size:g} ({now[2]} cells)",
                "resume with the stopped run's -r, --workers and --tile-size",
            )
        try:  # every tile read and checked here, before any worker starts from them
            check_tiles(folder, doc)
        except MapFileError as exc:
            fail(
                f"--resume: the checkpoint in {folder} is damaged: {exc}",
                "put back an intact copy of that file if there is one; else map again into a new --tiled folder "
                "(without --resume)",
            )
    elif is_tiled(folder):
        try:
            doc = read_manifest(folder)
        except MapFileError as exc:
            fail(f"{what} {folder} holds a damaged tiled map: {exc}", "give a new or empty folder with --tiled DIR")
        state = "a complete run" if doc.get("complete") else "a stopped run"
        fail(
            f"{folder} already holds a tiled map ({state} of {doc['scans']} scans)",
            "carry on from it with --resume, or give another folder with --tiled (or remove it)",
        )
    elif folder.is_dir() and any(folder.iterdir()):
        fail(
            f"{what} {folder} is not empty and holds no tiled map",
            "give a new or empty folder with --tiled DIR",
        )
    if worker_threads is None and cluster is None:
        worker_threads = max(1, (os.cpu_count() or 1) // workers)  # a local cluster: the CPUs shared
    if cluster is None:
        memory_limit = share_memory(workers, memory_limit)
        cpus = os.cpu_count() or 1
        if workers * (worker_threads or 1) > cpus:
            console_err().print(
                Text(
                    f"note: {workers} workers of {worker_threads or 1} thread{'s' if worker_threads != 1 else ''} "
                    f"on this machine's {cpus} CPUs: they take turns (slower, the same map)",
                    style="yellow",
                )
            )
    return TiledRun(
        workers=workers,
        tile_size=size,
        address=cluster,
        folder=folder,
        keep=tiled is not None,
        checkpoint_every=every,
        resume=resume,
        threads=worker_threads,
        memory_limit=memory_limit,
        resumed_scans=resumed,
    )


def share_memory(workers: int, memory_limit: float | None) -> float:
    """Each worker's memory budget on a local cluster (all on this machine): the default
    budget of one process (a share of the machine's memory) divided among them, or
    ``--memory-limit``, whose total must fit the machine."""
    from ..hostpool import physical_memory
    from ..runtime import CPU_DEFAULT_SHARE

    machine = physical_memory() / 2**30
    if memory_limit is None:
        return CPU_DEFAULT_SHARE * machine / workers
    if memory_limit * workers > machine:
        raise ValueError(
            f"--memory-limit {memory_limit:g} GiB for each of {workers} workers on this machine is "
            f"{memory_limit * workers:g} GiB, more than its {machine:.1f} GiB of memory; give at most "
            f"{math.floor(machine / workers * 100) / 100:g} (--memory-limit is each worker's budget)"
        )
    return memory_limit


def check_folder_writable(folder: Path, what: str) -> None:
    """Fail now, before any scan, when the checkpoints could not be written to ``folder``
    (made when the first checkpoint is written): a read-only or immutable folder, a file on
    its path, a file system that takes no files."""
    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        fail(f"cannot make {what} {folder}: {probe} is a file, not a folder", "choose another folder with --tiled DIR")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".ndtom-check-", dir=probe))
    except OSError as exc:
        action = f"write to {what}" if probe == folder else f"make {what}"
        fail(
            f"cannot {action} {folder}: {exc.strerror or exc}" + ("" if probe == folder else f" (in {probe})"),
            "choose a writable folder for the checkpoints with --tiled DIR",
            EXIT_FAILURE,
        )


def check_reachable(address: str) -> None:
    """Fail at once when nothing listens at a Ray cluster's ``HOST:PORT`` (``ray://`` too;
    "auto" is Ray's to find): Ray itself would retry for minutes, printing as it goes."""
    if address == "auto":
        return  # (Ray finds it; none running: RayEngine says so)
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(
            f"--cluster must be a Ray cluster's address HOST:PORT (e.g. 10.0.0.5:6379) or auto, got {address!r}"
        )
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=5).close()
    except OSError as exc:
        fail(
            f"cannot reach the Ray cluster at {address}: {exc.strerror or exc}",
            "start one with `ray start --head` (it prints its address), or give its address with --cluster",
        )


# ---------------------------------------------------------------------------- merge
def default_merged(folder: Path) -> Path:
    """``site.tiles`` -> ``site.ndtom``, ``out.ndtom.tiles`` -> ``out.ndtom`` (beside it)."""
    name = folder.expanduser().resolve().name
    stem = name.removesuffix(TILES_SUFFIX)
    return folder.expanduser().resolve().parent / (stem if stem.endswith(MAP_SUFFIX) else stem + MAP_SUFFIX)


@app.command(short_help="Join a tiled map's folder into one map file.")
def merge(
    folder: Annotated[
        Path,
        typer.Argument(
            metavar="DIR",
            help="A tiled map's folder (manifest.json and a map file per tile), as `ndtom map --workers N "
            "--tiled DIR` writes it.",
            show_default=False,
        ),
    ],
    output: Annotated[
        Path | None,
        typer.Option(
            "-o",
            "--output",
            help="Map file to write (atomically). Default: DIR's name with .ndtom, beside it "
            "(site.tiles -> site.ndtom).",
            show_default=False,
        ),
    ] = None,
    compact: Annotated[
        bool,
        typer.Option(
            "--compact",
            help="Write the Gaussians rounded (format 7, as `ndtom map --compact`); the default is lossless.",
        ),
    ] = False,
) -> None:
    """Join the tiles of a tiled map into one map file: the map one process would have
    made of the same scans, cell for cell."""
    from ..snapshot import MapSnapshot

    hint = "give the folder that `ndtom map --workers N --tiled DIR` wrote (it holds a manifest.json)"
    with user_errors(map_file=hint):
        if not folder.exists():
            fail(f"no tiled map at {folder}: it does not exist", hint)
        if not folder.is_dir():
            fail(f"{folder} is a file, not a tiled map's folder", f"{hint}; a map file needs no merge")
        try:
            doc = read_manifest(folder)
            out_path = output if output is not None else default_merged(folder)
            check_not_input(out_path, {"tiled map": folder})
            out_path = check_writable(out_path, "map file")
            check_map_output(out_path)
            snap = MapSnapshot.load(folder)  # each tile checked against the manifest (tiledfile.read_tile)
        except MapFileError as exc:
            if not (folder / MANIFEST).is_file():
                raise
            fail(str(exc), DAMAGED_HINT)
        md = dict(snap.metadata)
        md["merged_from"] = str(folder.expanduser().resolve())
        md["complete"] = bool(doc.get("complete"))
        wrote = replace(snap, metadata=md).save(out_path, compact=compact)
        if not doc.get("complete"):
            console_err().print(
                Text(
                    f"note: {folder} is the checkpoint of a run that did not finish ({doc['scans']} scans); "
                    "the map is marked incomplete",
                    style="yellow",
                ),
                soft_wrap=True,
            )
        console_out().print(
            Text(
                f"Merged {len(doc['tiles'])} tiles ({fmt_count(snap.scans_inserted)} scans, {fmt_count(len(snap))} "
                f"Gaussians) into {wrote} ({fmt_mib(wrote.stat().st_size)})",
                style="green",
            ),
            soft_wrap=True,
        )
