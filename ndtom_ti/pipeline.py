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
A command that maps and then saves wraps both in :func:`ndtom_ti.signals.stop_signals`
(SIGINT and SIGTERM: the map is saved, and signals during the save wait for it).

Poses kilometres from their frame's origin (UTM and other georeferenced frames) would
leave the map's grid at once: when the first pose lies outside the middle half of the grid,
the loop maps in a frame shifted by that pose's position rounded to 100 m
(:func:`frame_origin`), and records the shift in the map's metadata (``frame_origin``) and
in ``summary.frame_origin``; the map's coordinates (Gaussians, exports) are in that frame.

:func:`run_scans` is the one mapping loop: ``ndtom map``, the API and live mapping in the
viewer run it, the viewer as its :class:`Observer` (kiss-icp's visualizer): it paces the
scans, maps them under its lock and draws them; the default observer does nothing.

Example::

    import ndtom_ti
    from ndtom_ti.pipeline import map_recording

    m, summary = map_recording("site.bag", 0.3, every=2)
    print(summary.scans_used, len(m))
    m.save("site.ndtom")
"""

from __future__ import annotations

import math
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .config import MapConfig, check_resolution
from .frames import as_frame_origin, far_origin, shifted
from .io.selection import ScanSelection
from .map import NdtOmMap, ScanReport
from .runtime import MapMemoryError
from .scan import scan_parts
from .signals import loop_signals

if TYPE_CHECKING:
    from .io import ScanStream

__all__ = [
    "MappingSummary",
    "Observer",
    "RecordingRun",
    "config_with_ranges",
    "load_config_file",
    "map_recording",
    "map_scans",
    "open_recording_run",
    "run_scans",
    "version",
]

#: Makes the map a run fills: ``make_map(resolution, occupancy=..., config=..., metadata=...)``
#: (NdtOmMap by default; e.g. ``functools.partial(ndtom_ti.cluster.TiledMap, workers=4)``).
MakeMap = Callable[..., Any]

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
    scans_used: int = 0  # scans inserted into the map (by this run)
    scans_resumed: int = 0  # scans the map held from a stopped run's checkpoint (skipped here)
    skipped: dict = field(default_factory=dict)  # reason -> clouds not used
    skip_notes: list = field(default_factory=list)  # first detail per skip reason
    points_in: int = 0
    points_used: int = 0  # endpoints inserted as hits
    free_rays: int = 0
    dropped: dict = field(default_factory=lambda: {"nonfinite": 0, "range": 0, "outside_grid": 0, "no_return": 0})
    gaussians: int = 0
    known_cells: int = 0
    memory_bytes: int = 0  # this map
    pool_bytes: int = 0  # Taichi's pool, all maps of the process
    pool_budget_bytes: int = 0
    scan_seconds: list = field(default_factory=list, repr=False)  # insert_scan time per scan
    wall_seconds: float = 0.0  # the whole loop: reading, decoding, inserting
    wall_first_scan: float = 0.0  # the loop until the first scan was in (it compiles the kernels)
    points_first_scan: int = 0
    # Where the map's (0, 0, 0) lies in the poses' frame when the loop shifted them (frame_origin)
    frame_origin: list | None = None
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
        self.dropped["no_return"] += rep.dropped_no_return
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

    def metadata(self, extra: dict | None = None) -> dict:
        """The metadata of the map this run makes: the version, the source, the settings
        and options, and ``extra``."""
        import datetime

        md = {
            "ndtom_ti_version": version(),
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "source": self.source,
            "cloud_topic": self.cloud_topic,
            "frame_id": self.frame_id,
            "fixed_frame": self.fixed_frame,
            "pose_source": self.pose_source,
            "resolution": self.resolution,
            "occupancy": self.occupancy,
            "config": self.config,
            "options": self.options,
        }
        md.update(extra or {})
        return md

    def count_map(self, m: NdtOmMap) -> None:
        """Count the map's Gaussians, known cells and memory (once the loop ended)."""
        rep = m.memory_report()
        self.gaussians = int(rep["gaussians"])
        self.known_cells = int(rep["known_cells"])
        self.memory_bytes = int(rep["total_bytes"])
        self.pool_bytes = int(rep["process_pool_bytes"])
        self.pool_budget_bytes = int(rep["process_pool_budget_bytes"])

    def record_in(self, m: NdtOmMap) -> None:
        """Write whether the run was complete, and its summary, into the map's metadata."""
        d = self.to_dict()
        m.metadata["complete"] = self.complete
        m.metadata["summary"] = {
            k: d[k]
            for k in (
                "clouds_seen",
                "scans_used",
                "scans_resumed",
                "skipped",
                "points_in",
                "points_used",
                "free_rays",
                "dropped",
                "gaussians",
                "known_cells",
                "memory_bytes",
                "ms_first_scan",
                "ms_per_scan_median",
                "ms_per_scan_p95",
                "wall_seconds",
                "stopped",
                "error",
            )
        }


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


# ---------------------------------------------------------------------------- the loop
def frame_origin(m: Any, T_world_sensor: np.ndarray) -> np.ndarray | None:
    """Where the map's frame starts in the poses' frame, for a run whose first pose is
    ``T_world_sensor``: the one in the map's metadata (``frame_origin``: a map resumed, or
    made to continue another), else, for a map that holds no scan, that pose's position
    rounded to 100 m when it lies outside the middle half of the map's grid on an axis
    (poses in UTM or another georeferenced frame, kilometres from its origin, where the
    grid ends); else None (the poses as they are)."""
    kept = m.metadata.get("frame_origin") if isinstance(getattr(m, "metadata", None), dict) else None
    if kept is not None:
        origin = as_frame_origin(kept)
        if origin is None:
            raise ValueError(f"the map's metadata has frame_origin {kept!r}, not three finite numbers (metres)")
        return origin
    layout = _layout_of(m)
    if layout is None or getattr(m, "scans_inserted", 0):
        return None
    return far_origin(T_world_sensor, layout.cells, m.resolution)


def _layout_of(m: Any) -> Any:
    """The grid layout of a map or a tiled map (None for another kind of map)."""
    return getattr(m, "layout", None) or getattr(getattr(m, "tiling", None), "layout", None)


class Observer:
    """What the mapping loop tells a viewer of it, and asks it (kiss-icp's visualizer).
    This one watches nothing and never waits; live mapping's (``viewer.live.LiveMapper``)
    waits for Play and for the recording's pace, maps under the viewer's lock (and into a
    comparison map), and draws each scan."""

    def turn(self) -> bool:
        """Before the next scan is read: wait for it to be wanted; False stops the loop."""
        return True

    def due(self, scan: Any) -> bool:
        """The scan is read: wait until it is due; False stops the loop before it."""
        return True

    def insert(self, m: NdtOmMap, points: Any, T_world_sensor: Any) -> ScanReport | None:
        """Insert the scan into ``m``; None stops the loop (nothing inserted)."""
        return m.insert_scan(points, T_world_sensor)

    def inserted(self, rep: ScanReport, scan: Any, points: Any, T_world_sensor: Any) -> None:
        """The scan is in the map and counted in the summary."""


def run_scans(
    m: NdtOmMap,
    scans: Iterable[Any],
    summary: MappingSummary,
    progress: ProgressFn | None = None,
    after_loop: Callable[[], None] | None = None,
    observer: Observer | None = None,
) -> bool:
    """Insert every (points, T_world_sensor) of ``scans`` into ``m``, filling ``summary``;
    ``observer`` (default: none) is asked before each scan and told after it. Returns
    whether the scans ran out (every one was read). Stops and errors: see the module's
    docstring. ``summary.wall_seconds`` leaves out the observer's waits; the caller counts
    the map (``summary.count_map``) when it is done with it."""
    from .io import RecordingError

    obs = observer if observer is not None else Observer()
    t0 = time.perf_counter()
    waited = 0.0  # in the observer's turn() and due(): the pace, not the mapping

    def wall() -> float:
        return time.perf_counter() - t0 - waited

    end: Any = object()
    origin: Any = end  # frame_origin(), once the first scan is read
    ran_out = False  # every scan was inserted: a signal after that stops nothing
    with loop_signals() as sig:
        it = iter(scans)
        try:
            while not sig.count:
                t_wait = time.perf_counter()
                go = obs.turn()
                waited += time.perf_counter() - t_wait
                if not go:
                    break
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
                t_wait = time.perf_counter()
                go = obs.due(scan)
                waited += time.perf_counter() - t_wait
                if not go:
                    break
                try:
                    points, T = scan_parts(scan)
                    if origin is end:  # decided at the first scan, kept in the map's metadata
                        origin = frame_origin(m, T)
                        if origin is not None:
                            summary.frame_origin = origin.tolist()
                            m.metadata["frame_origin"] = summary.frame_origin
                    if origin is not None:
                        T = shifted(T, origin)
                    rep = obs.insert(m, points, T)
                except MapMemoryError as exc:
                    _stopped(summary, "memory", f"scan {summary.scans_used + 1} was refused: {exc}")
                    break
                except (ValueError, TypeError) as exc:  # a bad pose or cloud: the map is unchanged
                    if not summary.scans_used:
                        raise
                    _stopped(summary, "error", f"scan {summary.scans_used + 1} could not be inserted: {exc}")
                    break
                if rep is None:
                    break
                summary.add(rep)
                summary.wall_seconds = wall()
                if summary.scans_used == 1:
                    summary.wall_first_scan = summary.wall_seconds
                obs.inserted(rep, scan, points, T)
                if progress is not None:
                    progress(summary, rep)
        except KeyboardInterrupt:
            sig.count = max(sig.count, 1)
        if sig.count and summary.stopped is None and not ran_out:
            summary.stopped = "interrupted"
            summary.error = f"interrupted ({sig.name}) after {summary.scans_used} scans"
    summary.wall_seconds = wall()
    if after_loop is not None:
        after_loop()
    return ran_out


# m/s: a sensor path faster than this between two poses is a jump of the poses (check_path_fits)
JUMP_SPEED = 150.0


def check_path_fits(m: Any, stream: Any) -> None:
    """Refuse, before any scan, a recording whose sensor leaves the map's grid on the way
    (a long drive at a fine resolution): the run would stop there, after mapping for as long.
    Says how far the path goes, where it leaves, and what fits. RecordingError."""
    from .io import RecordingError

    layout = _layout_of(m)
    sensor_path = getattr(stream, "sensor_path", None)
    if layout is None or sensor_path is None or getattr(m, "scans_inserted", 0):
        return
    got = sensor_path()
    if got is None:
        return
    stamps, pos = got
    first = np.eye(4)
    first[:3, 3] = pos[0]
    origin = frame_origin(m, first)
    rel = pos - origin if origin is not None else pos
    half = np.asarray(layout.cells, np.float64) * float(m.resolution) / 2.0
    out = np.flatnonzero(~((rel >= -half) & (rel < half)).all(axis=1))
    if not out.size:
        return
    k = int(out[0])
    t0 = getattr(stream, "start_ns", int(stamps[0]))
    sec = (stamps - t0) / 1e9
    span = " x ".join(f"{2 * h:g}" for h in half)
    where = f" around {origin.tolist()}, the first pose rounded" if origin is not None else ""
    text = (
        f"the sensor leaves the map's grid on the way: at {float(m.resolution):g} m the grid is {span} m{where}, "
        f"and the sensor reaches {np.round(pos[k], 1).tolist()} m {sec[k]:.1f} s into the recording "
        f"(the path spans {np.round(pos.min(axis=0), 1).tolist()} .. {np.round(pos.max(axis=0), 1).tolist()} m). "
    )
    # Faster than any vehicle that carries a lidar: poses of two frames (a GNSS fix after
    # identity poses, a relocalisation), not a drive.
    dt = np.maximum(np.diff(sec), 1e-9)
    fast = np.linalg.norm(np.diff(pos, axis=0), axis=1) / dt > JUMP_SPEED
    if fast.any():
        a = int(np.argmax(fast))
        b = a + int(np.argmin(np.append(fast[a:], False)))  # the end of that run of fast steps
        text += (
            f"The poses jump by {np.linalg.norm(pos[b] - pos[a]):.0f} m between {sec[a]:.1f} and {sec[b]:.1f} s: "
            f"check them (`ndtom info BAG`), and map the part before (--end {sec[a]:.1f}) or after "
            f"(--start {sec[b]:.1f})"
        )
    else:
        need = np.abs(rel).max(axis=0) * 2.0 / np.asarray(layout.cells, np.float64)
        coarser = float(m.resolution) * 2.0 ** np.ceil(np.log2(max(need.max() / float(m.resolution), 1.0) * 1.0001))
        text += f"Map it at {coarser:g} m or coarser"
        if sec[k] - sec[0] > 1.0:
            text += f", or the part before it (--end {np.floor(sec[k] * 10) / 10:.1f})"
    raise RecordingError(text)


def _after_resumed(m: Any, scans: Iterable[Any], summary: MappingSummary) -> Iterable[Any]:
    """The scans a map made from a stopped run's checkpoint does not hold yet: it holds the
    first ``m.scans_inserted`` of them (``summary.scans_resumed``), which are read and
    skipped (the same selection, so the same scans)."""
    done = int(getattr(m, "scans_inserted", 0))
    summary.scans_resumed = done
    return _skip_resumed(scans, done, m) if done else scans


_NONE = object()  # next()'s default: the stream ended


def _skip_resumed(scans: Iterable[Any], done: int, m: Any) -> Iterator[Any]:
    """``scans`` after the first ``done``. RecordingError when there are fewer: the selection
    now ends (an earlier --end) before scans the checkpoint holds, and its map would hold
    them all the same."""
    from .io import RecordingError

    it = iter(scans)
    for k in range(done):
        if next(it, _NONE) is _NONE:
            folder = getattr(m, "folder", None)
            raise RecordingError(
                f"this selection of the recording ends after {k} scan{'' if k == 1 else 's'}, before the {done} that "
                "the checkpoint being resumed holds (an earlier --end than the stopped run's?): its map would hold "
                "scans past the end. "
                "Resume with the stopped run's --end or a later one"
                + (f", or merge the scans it holds with `ndtom merge {folder}`" if folder is not None else "")
            )
    yield from it


def _stopped(summary: MappingSummary, why: str, text: str) -> None:
    summary.stopped = why
    summary.error = f"{text} The map holds the {summary.scans_used} scans before it."


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
    make_map: MakeMap | None = None,
) -> tuple[Any, MappingSummary]:
    """Map any scan source: an iterable of objects with ``points`` (N, 3) sensor frame and
    ``T_world_sensor`` (4, 4), or of ``(points, T_world_sensor)`` pairs. ``make_map``: as
    for :func:`map_recording`."""
    cfg = config_with_ranges(config, min_range=min_range, max_range=max_range)
    summary = MappingSummary(
        source=source,
        pose_source=pose_source,
        fixed_frame=fixed_frame,
        resolution=float(resolution),
        occupancy=bool(occupancy),
        config=cfg.to_dict(),
        scans_expected=scans_expected,
    )
    if progress is not None:
        progress(summary, None)
    m = (make_map or NdtOmMap)(resolution, occupancy=occupancy, config=cfg, metadata=summary.metadata(metadata))
    try:
        run_scans(m, _after_resumed(m, scans, summary), summary, progress)
        summary.count_map(m)
    except BaseException:
        m.close()  # the slot back now, not when the traceback goes
        raise
    summary.clouds_seen = summary.scans_used
    summary.record_in(m)
    return m, summary


@dataclass
class RecordingRun:
    """A recording opened for mapping (:func:`open_recording_run`): the selected scans, the
    summary they fill, and what the map's metadata adds to the summary's (``extra``: the
    recording, the caller's metadata)."""

    stream: ScanStream
    summary: MappingSummary
    extra: dict

    def count_clouds(self) -> None:
        """Copy the stream's counts of clouds seen and skipped into the summary (the loop's end)."""
        self.summary.clouds_seen = self.stream.total_seen
        self.summary.skipped = dict(Counter(self.stream.skipped).most_common())
        self.summary.skip_notes = list(self.stream.notes)


@contextmanager
def open_recording_run(
    path: str | Path,
    resolution: float,
    selection: ScanSelection,
    *,
    occupancy: bool = True,
    config: MapConfig,
    metadata: dict | None = None,
) -> Iterator[RecordingRun]:
    """The recording at ``path`` opened, its scans selected (topic and pose source resolved:
    problems raise here), and the run's summary made (``metadata``: more for the map's)."""
    from .io import open_recording

    with open_recording(path) as rec:
        stream = rec.scans(selection)
        summary = MappingSummary(
            source=str(Path(path).resolve()),
            cloud_topic=stream.cloud_topic,
            frame_id=stream.frame_id,
            fixed_frame=stream.fixed_frame,
            pose_source=stream.pose_source,
            resolution=float(resolution),
            occupancy=bool(occupancy),
            config=config.to_dict(),
            options=selection.options(),
            scans_expected=selection.expected_scans(rec, stream.cloud_topic),
        )
        extra = {"recording": {"path": summary.source, "format": rec.format, "storage": rec.storage}}
        extra.update(metadata or {})
        yield RecordingRun(stream, summary, extra)


def map_recording(
    path: str | Path,
    resolution: float,
    selection: ScanSelection | None = None,
    *,
    occupancy: bool = True,
    config: MapConfig | dict | None = None,
    min_range: float | None = None,
    max_range: float | None = None,
    metadata: dict | None = None,
    progress: ProgressFn | None = None,
    make_map: MakeMap | None = None,
    **options: Any,
) -> tuple[Any, MappingSummary]:
    """Map a ROS1 bag or ROS2 bag folder at ``resolution`` metres.

    ``selection``: a :class:`~ndtom_ti.io.ScanSelection` (cloud topic, pose source, scan
    selection; ``t_start``/``t_end`` in seconds from the bag start), or its fields as
    keyword ``options``. The map's options: ``occupancy``, ``config``;
    ``min_range``/``max_range`` override the config's. ``progress(summary, report)`` is
    called before the first scan (report None) and after each one.

    ``make_map(resolution, occupancy=, config=, metadata=)`` makes the map (default
    :class:`~ndtom_ti.NdtOmMap`); e.g. ``functools.partial(TiledMap, workers=4,
    folder="site.tiles", checkpoint_every=100)`` maps with four worker processes
    (:class:`ndtom_ti.cluster.TiledMap`, the same map). A map that already holds scans
    (``TiledMap(..., resume=True)``: a stopped run's checkpoint) gets the selected scans
    after them; the selection must be the stopped run's.

    Returns ``(map, summary)``; the map's ``metadata`` records the recording, topic,
    pose source, options, settings, the ndtom_ti version and the summary. Raises
    RecordingError for a recording that cannot be mapped and ValueError for bad
    options; the recording is checked (topic, poses) before the map is made. A run
    stopped by Ctrl-C or by the memory budget returns the map so far (see
    ``summary.stopped``).
    """
    resolution = check_resolution(resolution)
    selection = replace(selection or ScanSelection(), **options)
    if selection.every_distance is not None and selection.every > 1:
        raise ValueError("give either every (keep every N-th cloud) or every_distance, not both")
    cfg = config_with_ranges(config, min_range=min_range, max_range=max_range)
    with open_recording_run(path, resolution, selection, occupancy=occupancy, config=cfg, metadata=metadata) as run:
        summary = run.summary
        if progress is not None:
            progress(summary, None)  # before the map (and Taichi) is made: the recording is fine
        m = (make_map or NdtOmMap)(resolution, occupancy=occupancy, config=cfg, metadata=summary.metadata(run.extra))
        try:
            check_path_fits(m, run.stream)
            run_scans(m, _after_resumed(m, run.stream, summary), summary, progress, after_loop=run.count_clouds)
            summary.count_map(m)
        except BaseException:
            m.close()  # the slot back now, not when the traceback goes
            raise
    summary.record_in(m)
    return m, summary
