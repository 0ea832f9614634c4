"""The mapping loop: scans of a recording (or any scan source) -> NdtOmMap + summary.

Like kiss-icp's pipeline: the core (:class:`~ndtom_ti.NdtOmMap`) knows only points and
poses; this module reads the recording, runs the loop, times it, counts what was used
and skipped, and records the settings in the map's ``metadata``. The CLI
(``ndtom map``) is a thin layer over :func:`map_recording`.

Stopping early is not an error here: Ctrl-C (SIGINT) finishes the scan being inserted
and stops; a scan that would take the map past its memory budget
(:class:`~ndtom_ti.MapMemoryError`) is refused (the map is unchanged) and the loop
stops; so does a scan that cannot be read or inserted (a pose outside the grid, a
damaged message) once some scans are mapped. All return the map built so far, with
``summary.stopped`` set ('interrupted', 'memory' or 'error') and ``summary.error``
saying why; check ``summary.complete`` before trusting a map to cover the whole
recording. Bad input before the first scan is mapped
(:class:`~ndtom_ti.io.RecordingError`, ``ValueError``) raises, and no map is returned.
A command that maps and then saves wraps both in :func:`stop_signals` (SIGINT and
SIGTERM: the map is saved, and signals during the save wait for it).

Example::

    import ndtom_ti
    from ndtom_ti.pipeline import map_recording

    m, summary = map_recording("site.bag", 0.3, every=2)
    print(summary.scans_used, len(m))
    m.save("site.ndtom")
"""

from __future__ import annotations

import math
import os
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .config import MapConfig, check_resolution
from .exitcodes import signal_exit_code
from .map import NdtOmMap, ScanReport
from .runtime import MapMemoryError
from .scan import scan_parts

__all__ = [
    "Interrupted",
    "MappingSummary",
    "StopSignals",
    "config_with_ranges",
    "load_config_file",
    "map_recording",
    "map_scans",
    "stop_signals",
    "version",
]

#: Called once before the map is made (report None; the recording's topic and pose source
#: are known by then) and after every inserted scan.
ProgressFn = Callable[["MappingSummary", "ScanReport | None"], None]


def version() -> str:
    from . import __version__

    return __version__


@dataclass
class MappingSummary:
    """What a mapping run did. Live while mapping (the progress callback sees it grow)."""

    source: str = ""  # recording path, or a description of the scan source
    cloud_topic: str | None = None
    frame_id: str | None = None  # frame of the clouds
    fixed_frame: str | None = None  # frame of the map
    pose_source: str | None = None  # where the poses came from, in words
    resolution: float = 0.0
    occupancy: bool = True
    config: dict = field(default_factory=dict)
    options: dict = field(default_factory=dict)  # selection options (every, start, ...)
    scans_expected: int | None = None  # estimate for a progress bar (None: unknown)
    clouds_seen: int = 0  # clouds of the topic considered (used + skipped)
    scans_used: int = 0  # scans inserted into the map
    skipped: dict = field(default_factory=dict)  # reason -> clouds not used
    skip_notes: list = field(default_factory=list)  # first detail per skip reason
    points_in: int = 0
    points_used: int = 0  # endpoints inserted as hits
    free_rays: int = 0
    dropped: dict = field(default_factory=lambda: {"nonfinite": 0, "range": 0, "outside_grid": 0})
    gaussians: int = 0
    known_cells: int = 0
    memory_bytes: int = 0  # this map
    pool_bytes: int = 0  # Taichi's pool, all maps of the process
    pool_budget_bytes: int = 0
    scan_seconds: list = field(default_factory=list, repr=False)  # insert_scan time per scan
    wall_seconds: float = 0.0  # the whole loop: reading, decoding, inserting
    wall_first_scan: float = 0.0  # the loop until the first scan was in (it compiles the kernels)
    points_first_scan: int = 0
    stopped: str | None = None  # None (ran to the end), 'interrupted', 'memory' or 'error' (a bad scan)
    error: str | None = None  # why it stopped early

    @property
    def complete(self) -> bool:
        """True when every selected scan was inserted (no signal, memory stop or bad scan)."""
        return self.stopped is None

    def add(self, rep: Any) -> None:
        """Count one inserted scan's ScanReport."""
        self.scans_used += 1
        if self.scans_used == 1:
            self.points_first_scan = rep.points_in
        self.points_in += rep.points_in
        self.points_used += rep.points_used
        self.free_rays += rep.free_rays
        self.dropped["nonfinite"] += rep.dropped_nonfinite
        self.dropped["range"] += rep.dropped_range
        self.dropped["outside_grid"] += rep.dropped_outside_grid
        self.scan_seconds.append(rep.seconds)

    @property
    def skipped_total(self) -> int:
        return int(sum(self.skipped.values()))

    @property
    def _later_scans(self) -> list:
        # The first scan compiles the kernels: it is reported apart (ms_first_scan).
        return self.scan_seconds[1:] if len(self.scan_seconds) > 1 else self.scan_seconds

    @property
    def ms_first_scan(self) -> float:
        return float(self.scan_seconds[0] * 1e3) if self.scan_seconds else float("nan")

    @property
    def ms_per_scan_median(self) -> float:
        """Median ms per scan, the first scan apart (unless it is the only one)."""
        t = self._later_scans
        return float(np.median(t) * 1e3) if t else float("nan")

    @property
    def ms_per_scan_p95(self) -> float:
        """95th percentile of ms per scan, the first scan apart (unless it is the only one)."""
        t = self._later_scans
        return float(np.percentile(t, 95) * 1e3) if t else float("nan")

    @property
    def points_per_second(self) -> float:
        """Points read and mapped a second, the first scan (which compiles the kernels: its
        time is ``ms_first_scan``) apart unless it is the only one."""
        later = self.wall_seconds - self.wall_first_scan
        if self.scans_used > 1 and later > 0:
            return (self.points_in - self.points_first_scan) / later
        return self.points_in / self.wall_seconds if self.wall_seconds > 0 else 0.0

    def to_dict(self) -> dict:
        """Plain JSON-able dict (no per-scan times; their median and p95 instead)."""
        d = asdict(self)
        d.pop("scan_seconds")
        d["complete"] = self.complete
        for k in ("ms_first_scan", "ms_per_scan_median", "ms_per_scan_p95"):
            v = getattr(self, k)
            d[k] = None if math.isnan(v) else round(v, 3)
        d["wall_seconds"] = round(self.wall_seconds, 3)
        return d


# ---------------------------------------------------------------------------- configuration
def load_config_file(path: str | Path) -> dict:
    """MapConfig keys from a JSON or TOML file (a top-level table, or a [map] table).

    Raises ValueError with the file name for a missing, unreadable or malformed file
    and for keys that are not MapConfig options.
    """
    import json

    if sys.version_info >= (3, 11):
        import tomllib
    else:  # Python 3.10: the tomli backport has the same API
        import tomli as tomllib

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"config file {p} does not exist" if not p.exists() else f"config file {p} is not a file")
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"config file {p} cannot be read: {exc}") from None
    try:
        if p.suffix.lower() == ".json" or (p.suffix.lower() != ".toml" and text.lstrip().startswith("{")):
            data = json.loads(text)
        else:
            data = tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        kind = "JSON" if isinstance(exc, json.JSONDecodeError) else "TOML"
        raise ValueError(f"config file {p} is not valid {kind}: {exc}") from None
    if not isinstance(data, dict):
        raise ValueError(f"config file {p} must hold a table of MapConfig options, got {type(data).__name__}")  # noqa: TRY004 - a bad file
    if set(data) == {"map"} and isinstance(data["map"], dict):
        data = data["map"]
    try:
        MapConfig.from_dict(data)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"config file {p}: {exc}") from None
    return data


def config_with_ranges(
    config: MapConfig | dict | None,
    *,
    min_range: float | None = None,
    max_range: float | None = None,
    miss_model: str | None = None,
) -> MapConfig:
    """A MapConfig from ``config`` with ``min_range``/``max_range``/``miss_model`` overriding it."""
    if config is None:
        base = MapConfig()
    elif isinstance(config, MapConfig):
        base = config
    else:
        base = MapConfig.from_dict(config)
    changes: dict[str, Any] = {}
    if min_range is not None:
        changes["min_range"] = float(min_range)
    if max_range is not None:
        changes["max_range"] = float(max_range)
    if miss_model is not None:
        changes["miss_model"] = miss_model
    return replace(base, **changes) if changes else base


# ---------------------------------------------------------------------------- Ctrl-C, SIGTERM
class Interrupted(KeyboardInterrupt):
    """A stop signal (SIGINT or SIGTERM) at a point where there is no map to keep."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal_name(signum))
        self.signum = signum


def signal_name(signum: int | None) -> str:
    return "SIGTERM" if signum == signal.SIGTERM else "Ctrl-C"


class StopSignals:
    """What SIGINT (Ctrl-C) and SIGTERM do while a map is made and saved.

    ``phase`` is "idle" (no map yet: the first signal raises :class:`Interrupted`),
    "mapping" (the first signal lets the scan in hand finish, then the loop stops;
    another one stops a read that is under way, never an insert), "finished" (every scan
    is mapped: signals are only told that the complete map is being saved), "saving" (signals
    are counted and only told to wait until the map is on disk) or "done" (ignored). ``count`` and
    ``signum`` (the first signal) say what arrived.
    """

    def __init__(self, phase: str = "mapping", say: Callable[[str], None] | None = None) -> None:
        self.phase = phase
        self.count = 0
        self.signum: int | None = None
        self.reading = False  # the loop is waiting for the next scan: a second signal may stop it
        self._say = say

    @property
    def name(self) -> str:
        return signal_name(self.signum)

    @property
    def exit_code(self) -> int:
        """128 + the first signal's number (130 for Ctrl-C, 143 for SIGTERM)."""
        return signal_exit_code(self.signum or signal.SIGINT)

    def say(self, text: str) -> None:
        if self._say is not None:
            self._say(text)

    def handler(self, signum: int, frame: Any) -> None:
        self.count += 1
        if self.signum is None:
            self.signum = signum
        name = signal_name(signum)
        if self.phase == "idle":
            raise Interrupted(signum)
        if self.phase == "done":  # the map is on disk and the command is ending
            return
        if self.phase == "finished":  # every scan is in the map: nothing is cut short
            self.say(f"{name}: every scan is mapped; saving the complete map.")
        elif self.phase == "saving":
            self.say(f"{name}: saving the map; wait, it is on disk in a moment.")
        elif self.count == 1:
            self.say(f"{name}: stopping after the scan in hand; what was mapped will be saved.")
        elif self.reading:
            self.reading = False  # raise at most once, and only out of a read
            raise Interrupted(signum)
        else:
            self.say(f"{name}: finishing the scan in hand, then saving the map.")


_active: StopSignals | None = None  # installed by stop_signals(); _run uses it when set


def _stderr(text: str) -> None:
    # os.write: a handler may run while the main thread is inside a print to stderr.
    try:
        os.write(2, (text + "\n").encode("utf-8", "replace"))
    except OSError:
        pass


@contextmanager
def stop_signals(
    signums: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM),
    phase: str = "idle",
    say=_stderr,
    restore: bool = True,
) -> Iterator[StopSignals]:
    """Handle ``signums`` with a :class:`StopSignals` for the whole block (a command that
    maps, then saves): mapping loops inside it use this one. Outside the main thread
    signals cannot be handled; the state is returned all the same. ``restore=False``
    (a process that exits after the block) leaves the handler in place, in phase "done"
    when the block ran through: a late signal cannot break the exit."""
    global _active
    state = StopSignals(phase, say)
    old: dict = {}
    if threading.current_thread() is threading.main_thread():
        for signum in signums:
            try:
                old[signum] = signal.signal(signum, state.handler)
            except (ValueError, OSError):  # pragma: no cover - embedded interpreters
                pass
    outer, _active = _active, state
    try:
        yield state
        if not restore:
            state.phase = "done"
    finally:
        _active = outer
        for signum, handler in old.items():
            if restore or state.phase != "done":
                signal.signal(signum, handler)


@contextmanager
def _loop_signals() -> Iterator[StopSignals]:
    """The active StopSignals, or SIGINT handled for the loop alone (API use)."""
    if _active is not None:
        _active.phase = "mapping"
        yield _active
        return
    with stop_signals((signal.SIGINT,), phase="mapping", say=None) as state:
        yield state


# ---------------------------------------------------------------------------- the loop
def _finish(m: NdtOmMap, summary: MappingSummary) -> None:
    rep = m.memory_report()
    summary.gaussians = int(rep["gaussians"])
    summary.known_cells = int(rep["known_cells"])
    summary.memory_bytes = int(rep["total_bytes"])
    summary.pool_bytes = int(rep["process_pool_bytes"])
    summary.pool_budget_bytes = int(rep["process_pool_budget_bytes"])


def _run(
    m: NdtOmMap,
    scans: Iterable[Any],
    summary: MappingSummary,
    progress: ProgressFn | None,
    after_loop: Callable[[], None] | None = None,
) -> None:
    """Insert every (points, T_world_sensor) of ``scans`` into ``m``, filling ``summary``."""
    from .io import RecordingError

    t0 = time.perf_counter()
    end: Any = object()
    ran_out = False  # every scan was inserted: a signal after that stops nothing
    with _loop_signals() as sig:
        it = iter(scans)
        try:
            while not sig.count:
                sig.reading = True
                try:
                    scan = next(it, end)
                except (RecordingError, ValueError, OSError) as exc:
                    if not summary.scans_used:
                        raise
                    _stopped(summary, "error", f"scan {summary.scans_used + 1} could not be read: {exc}")
                    break
                finally:
                    sig.reading = False
                if scan is end:
                    ran_out = True
                    sig.phase = "finished"
                    break
                if sig.count:
                    break
                points, T = scan_parts(scan)
                try:
                    rep = m.insert_scan(points, T)
                except MapMemoryError as exc:
                    _stopped(summary, "memory", f"scan {summary.scans_used + 1} was refused: {exc}")
                    break
                except (ValueError, TypeError) as exc:  # a bad pose or cloud: the map is unchanged
                    if not summary.scans_used:
                        raise
                    _stopped(summary, "error", f"scan {summary.scans_used + 1} could not be inserted: {exc}")
                    break
                summary.add(rep)
                summary.wall_seconds = time.perf_counter() - t0
                if summary.scans_used == 1:
                    summary.wall_first_scan = summary.wall_seconds
                if progress is not None:
                    progress(summary, rep)
        except KeyboardInterrupt:
            sig.count = max(sig.count, 1)
        if sig.count and summary.stopped is None and not ran_out:
            summary.stopped = "interrupted"
            summary.error = f"interrupted ({sig.name}) after {summary.scans_used} scans"
    summary.wall_seconds = time.perf_counter() - t0
    if after_loop is not None:
        after_loop()
    _finish(m, summary)


def _stopped(summary: MappingSummary, why: str, text: str) -> None:
    summary.stopped = why
    summary.error = f"{text} The map holds the {summary.scans_used} scans before it."


def _base_metadata(summary: MappingSummary, extra: dict | None) -> dict:
    import datetime

    md = {
        "ndtom_ti_version": version(),
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "source": summary.source,
        "cloud_topic": summary.cloud_topic,
        "frame_id": summary.frame_id,
        "fixed_frame": summary.fixed_frame,
        "pose_source": summary.pose_source,
        "resolution": summary.resolution,
        "occupancy": summary.occupancy,
        "config": summary.config,
        "options": summary.options,
    }
    md.update(extra or {})
    return md


def _record_result(m: NdtOmMap, summary: MappingSummary) -> None:
    d = summary.to_dict()
    m.metadata["complete"] = summary.complete
    m.metadata["summary"] = {
        k: d[k]
        for k in (
            "clouds_seen", "scans_used", "skipped", "points_in", "points_used", "free_rays", "dropped",
            "gaussians", "known_cells", "memory_bytes", "ms_first_scan", "ms_per_scan_median", "ms_per_scan_p95",
            "wall_seconds", "stopped", "error",
        )
    }  # fmt: skip


def map_scans(
    scans: Iterable[Any],
    resolution: float,
    *,
    occupancy: bool = True,
    config: MapConfig | dict | None = None,
    min_range: float | None = None,
    max_range: float | None = None,
    source: str = "scans",
    pose_source: str | None = None,
    fixed_frame: str | None = None,
    scans_expected: int | None = None,
    metadata: dict | None = None,
    progress: ProgressFn | None = None,
) -> tuple[NdtOmMap, MappingSummary]:
    """Map any scan source: an iterable of objects with ``points`` (N, 3) sensor frame and
    ``T_world_sensor`` (4, 4), or of ``(points, T_world_sensor)`` pairs."""
    cfg = config_with_ranges(config, min_range=min_range, max_range=max_range)
    summary = MappingSummary(
        source=source, pose_source=pose_source, fixed_frame=fixed_frame, resolution=float(resolution),
        occupancy=bool(occupancy), config=cfg.to_dict(), scans_expected=scans_expected,
    )  # fmt: skip
    if progress is not None:
        progress(summary, None)
    m = NdtOmMap(resolution, occupancy=occupancy, config=cfg, metadata=_base_metadata(summary, metadata))
    try:
        _run(m, scans, summary, progress)
    except BaseException:
        del m  # free the map's slot now, not when the traceback goes
        raise
    summary.clouds_seen = summary.scans_used
    _record_result(m, summary)
    return m, summary


def _expected_scans(
    rec: Any, topic: str, every: int, t_start: float | None, t_end: float | None, max_scans: int | None
) -> int | None:
    count = next((c for n, _, c in rec.topics() if n == topic), None)
    if not count:
        return None
    if t_start is not None or t_end is not None:
        dur = rec.duration_ns / 1e9
        if dur > 0:
            lo = max(0.0, t_start or 0.0)
            hi = min(dur, dur if t_end is None else t_end)
            count = max(0, round(count * max(0.0, hi - lo) / dur)) + 1
    count = math.ceil(count / every)
    if max_scans is not None:
        count = min(count, max_scans)
    return count


def map_recording(
    path: str | Path,
    resolution: float,
    *,
    cloud_topic: str | None = None,
    fixed_frame: str | None = None,
    pose_topic: str | None = None,
    poses_file: str | Path | None = None,
    sensor_frame_only: bool = False,
    every: int = 1,
    every_distance: float | None = None,
    t_start: float | None = None,
    t_end: float | None = None,
    max_scans: int | None = None,
    occupancy: bool = True,
    config: MapConfig | dict | None = None,
    min_range: float | None = None,
    max_range: float | None = None,
    metadata: dict | None = None,
    progress: ProgressFn | None = None,
) -> tuple[NdtOmMap, MappingSummary]:
    """Map a ROS1 bag or ROS2 bag folder at ``resolution`` metres.

    The options are those of :meth:`ndtom_ti.io.Recording.scans` (cloud topic, pose
    source, scan selection; ``t_start``/``t_end`` in seconds from the bag start) and of
    the map (``occupancy``, ``config``; ``min_range``/``max_range`` override the
    config's). ``progress(summary, report)`` is called before the first scan (report
    None) and after each one.

    Returns ``(map, summary)``; the map's ``metadata`` records the recording, topic,
    pose source, options, settings, the ndtom_ti version and the summary. Raises
    RecordingError for a recording that cannot be mapped and ValueError for bad
    options; the recording is checked (topic, poses) before the map is made. A run
    stopped by Ctrl-C or by the memory budget returns the map so far (see
    ``summary.stopped``).
    """
    from .io import open_recording

    resolution = check_resolution(resolution)
    if every_distance is not None and every > 1:
        raise ValueError("give either every (keep every N-th cloud) or every_distance, not both")
    cfg = config_with_ranges(config, min_range=min_range, max_range=max_range)
    options = {
        "cloud_topic": cloud_topic, "fixed_frame": fixed_frame, "pose_topic": pose_topic,
        "poses_file": str(Path(poses_file).resolve()) if poses_file is not None else None,
        "sensor_frame_only": sensor_frame_only, "every": every, "every_distance": every_distance,
        "start": t_start, "end": t_end, "max_scans": max_scans,
    }  # fmt: skip
    with open_recording(path) as rec:
        stream = rec.scans(
            cloud_topic=cloud_topic, fixed_frame=fixed_frame, pose_topic=pose_topic, poses_file=poses_file,
            sensor_frame_only=sensor_frame_only, every=every, every_distance=every_distance,
            t_start=t_start, t_end=t_end, max_scans=max_scans,
        )  # fmt: skip
        summary = MappingSummary(
            source=str(Path(path).resolve()), cloud_topic=stream.cloud_topic, frame_id=stream.frame_id,
            fixed_frame=stream.fixed_frame, pose_source=stream.pose_source, resolution=float(resolution),
            occupancy=bool(occupancy), config=cfg.to_dict(), options=options,
            scans_expected=_expected_scans(rec, stream.cloud_topic, every, t_start, t_end, max_scans),
        )  # fmt: skip
        extra = {"recording": {"path": summary.source, "format": rec.format, "storage": rec.storage}}
        extra.update(metadata or {})
        if progress is not None:
            progress(summary, None)  # before the map (and Taichi) is made: the recording is fine
        m = NdtOmMap(resolution, occupancy=occupancy, config=cfg, metadata=_base_metadata(summary, extra))

        def counts() -> None:
            summary.clouds_seen = stream.total_seen
            summary.skipped = dict(Counter(stream.skipped).most_common())
            summary.skip_notes = list(stream.notes)

        try:
            _run(m, stream, summary, progress, after_loop=counts)
        except BaseException:
            del m  # free the map's slot now, not when the traceback goes
            raise
    _record_result(m, summary)
    return m, summary
