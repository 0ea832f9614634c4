"""LiveMapper: build a map in a worker thread while the viewer shows it grow.

The worker thread runs the mapping loop (:func:`ndtom_ti.pipeline.run_scans`, as
``ndtom map`` does) with the LiveMapper as its observer: it reads the next scan (so a slow
reader does not block the GUI), inserts it into the NDT-OM map and, when given, the
Recursive NDT map (under the viewer's ``map_lock``; nothing else waits on it), and records
the time per scan, the pose and the scan's points. A bad scan stops mapping as it stops
``ndtom map`` (the maps keep the scans before it). A second thread redraws the viewer at
most every ``refresh_interval`` seconds (longer when a redraw takes long), so drawing
never holds up mapping.

Pacing: with ``speed`` the scans play at their recording's own rate (their ``stamp_ns``)
times ``speed``; a scan that is late (mapping slower than the recording) goes at once
and the clock restarts from it, so there is no catch-up burst; a gap of more than
``max_gap_s`` in the recording is shortened to it. Without ``speed``, ``rate_hz`` caps
the scans per second (0: as fast as mapping goes). ``clock`` and ``sleep`` can be given
(tests pace without waiting).
"""

from __future__ import annotations

import math
import threading
import time
import traceback
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from ndtom_ti.pipeline import MappingSummary, Observer, ProgressFn, run_scans

from .geometry import cap_rows
from .livepanel import LivePanel

if TYPE_CHECKING:
    from ndtom_ti import NdtOmMap, ScanReport
    from ndtom_ti.snapshot import MapSnapshot

    from .controls import Controls

__all__ = ["LiveMapper", "LiveView"]


class LiveView(Protocol):
    """What live mapping drives: a :class:`~ndtom_ti.viewer.MapViewer` (the mapper adds its
    folder of controls to the viewer's panel)."""

    server: Any  # viser's: the mapper's controls go into server.gui
    controls: Controls  # the panel: the mapper's LivePanel keeps its handles there (play, pause, ... live_status)
    last_refresh_s: float

    @property
    def map_lock(self) -> Any: ...  # held while inserting: the viewer reads the maps meanwhile

    @property
    def closed(self) -> bool: ...

    def set_maps(self, m: Any, compare: Any = None) -> None: ...

    def set_trajectory(self, positions: Any) -> None: ...

    def set_scan(self, points_world: Any) -> None: ...

    def refresh(self) -> None: ...


class LiveMapper(Observer):
    """Insert ``scans`` into ``m`` (and a Recursive NDT map) while ``viewer`` (a
    ``MapViewer``) shows it.

    Starts paused: :meth:`play`, :meth:`pause`, :meth:`step` (or the GUI buttons).
    ``scans_done``, ``times_ms`` (NDT-OM insert time per scan), ``finished`` and
    ``error`` (``exception``) report progress; :meth:`wait` blocks until the scans run
    out. ``on_scan(report, scan)`` is called from the worker thread after each insert.
    ``work_seconds``: time spent reading and inserting (not waiting for the pace).
    ``summary`` (a :class:`~ndtom_ti.pipeline.MappingSummary`, made when not given) is
    filled as ``ndtom map`` fills it, ``progress(summary, report)`` called after each scan
    and ``after_loop()`` when mapping ends.
    """

    def __init__(
        self,
        viewer: LiveView,
        scans: Any,
        m: NdtOmMap | MapSnapshot | None,
        *,
        compare: NdtOmMap | bool | None = False,
        total: int | None = None,
        refresh_interval: float = 0.5,
        max_scan_points: int = 50_000,
        rate_hz: float = 0.0,
        speed: float | None = None,
        max_gap_s: float = 2.0,
        on_scan: Callable[[Any, Any], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], bool] | None = None,
        summary: MappingSummary | None = None,
        progress: ProgressFn | None = None,
        after_loop: Callable[[], None] | None = None,
    ):
        from ndtom_ti import NdtOmMap
        from ndtom_ti.snapshot import MapSnapshot

        if speed is not None and not (speed > 0):
            raise ValueError(f"speed must be positive (1: the recording's own rate), got {speed}")

        if m is None or isinstance(m, MapSnapshot):
            raise ValueError(
                "live mapping needs a map to insert into: pass m=NdtOmMap(resolution) (a snapshot "
                "of a map file is read-only: NdtOmMap.from_snapshot(s) makes a map of it)"
            )
        if compare is True:
            with viewer.map_lock:
                compare = NdtOmMap(
                    m.resolution,
                    occupancy=False,
                    config=m.config,
                    layout=m.layout,
                    metadata={"role": "Recursive NDT (comparison)"},
                )
        elif compare is False:
            compare = None
        self.viewer = viewer
        self.map: NdtOmMap | None = m
        self.compare = compare
        if total is None:
            try:
                total = len(scans)
            except TypeError:
                total = None
        self.total = total
        self.refresh_interval = float(refresh_interval)
        self.max_scan_points = int(max_scan_points)
        self.rate_hz = float(rate_hz)
        self.speed = None if speed is None or math.isinf(speed) else float(speed)
        self.paced_by_stamps = speed is not None
        self.max_gap_s = float(max_gap_s)
        self.on_scan = on_scan
        self.summary = (
            summary
            if summary is not None
            else MappingSummary(
                source="scans",
                resolution=m.resolution,
                occupancy=m.occupancy_enabled,
                config=m.config.to_dict(),
                scans_expected=total,
            )
        )
        self._progress = progress
        self._after_loop = after_loop
        self._clock = clock
        self._sleep = sleep if sleep is not None else self._stop_wait
        self._anchor: tuple[float, int] | None = None  # (clock, stamp_ns) the pace is measured from
        self.waits: list[float] = []  # seconds waited for the pace before each scan
        self.work_seconds = 0.0
        self.exception: BaseException | None = None
        self.scans_done = 0
        self.times_ms: list[float] = []
        self.compare_times_ms: list[float] = []
        self.points_used: list[int] = []
        self.finished = False  # the worker ended: scans ran out, stopped, or an error
        self.completed = False  # every scan was inserted
        self.error: str | None = None
        self.reports: list = []

        self._scans = scans
        self._t_read = 0.0  # when the scan in hand was asked for
        self._t_ins = 0.0  # when it went to the maps
        self._work = 0.0  # reading it
        self._last = -math.inf  # when the last scan went (rate_hz)
        self._compare_rep: ScanReport | None = None
        self._positions: list[np.ndarray] = []
        self._playing = threading.Event()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._steps = 0
        self._step_lock = threading.Lock()
        self._dirty = threading.Event()
        self._done = threading.Event()

        viewer.set_maps(m, compare)
        viewer.set_trajectory(np.zeros((0, 3)))
        viewer.set_scan(np.zeros((0, 3)))
        self._panel = LivePanel(viewer.server.gui, viewer.controls, self)
        self._worker = threading.Thread(target=self._run, name="ndtom-live-mapping", daemon=True)
        self._drawer = threading.Thread(target=self._draw_loop, name="ndtom-live-draw", daemon=True)
        self._worker.start()
        self._drawer.start()

    # ------------------------------------------------------------------ controls

    @property
    def playing(self) -> bool:
        return self._playing.is_set()

    def play(self) -> None:
        if not self.finished:
            self._playing.set()
            self._wake.set()
            self._panel.update_status()

    def pause(self) -> None:
        self._playing.clear()
        self._anchor = None  # the pace restarts at the next scan
        self._panel.update_status()

    def set_speed(self, speed: float | None) -> None:
        """Playback speed (x the recording's rate; None: as fast as mapping goes)."""
        self.speed = None if speed is None or speed <= 0 or math.isinf(speed) else float(speed)
        self._anchor = None

    def step(self, n: int = 1) -> None:
        """Insert the next ``n`` scans (while paused)."""
        with self._step_lock:
            self._steps += int(n)
        self._wake.set()

    def _stop_wait(self, seconds: float) -> bool:
        return self._stop.wait(seconds)

    def stop(self) -> None:
        """End mapping (the maps keep what was inserted) and the drawing thread."""
        self._stop.set()
        self._wake.set()
        self._playing.clear()
        for t in (self._worker, self._drawer):
            if t is not threading.current_thread() and t.is_alive():
                t.join(timeout=10.0)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until every scan is inserted (or mapping stopped); True if it finished."""
        self._done.wait(timeout)
        return self._done.is_set()

    def wait_scans(self, n: int, timeout: float = 30.0) -> bool:
        """Block until at least ``n`` scans are inserted (or mapping ended)."""
        t_end = time.monotonic() + timeout
        while self.scans_done < n and not self._done.is_set() and time.monotonic() < t_end:
            time.sleep(0.01)
        return self.scans_done >= n

    # ------------------------------------------------------------------ threads

    def _take_turn(self) -> bool:
        """Wait until the next scan may be inserted; False when stopping."""
        while not self._stop.is_set():
            if self._playing.is_set():
                return True
            with self._step_lock:
                if self._steps > 0:
                    self._steps -= 1
                    return True
            self._wake.wait(0.1)
            self._wake.clear()
        return False

    def _pace(self, item: Any, last: float) -> bool:
        """Wait until ``item`` is due; False when stopping meanwhile."""
        now = self._clock()
        if self.paced_by_stamps:
            stamp, speed = getattr(item, "stamp_ns", None), self.speed
            if stamp is None or speed is None:
                self._anchor = None
                return True
            stamp = int(stamp)
            if self._anchor is None:
                self._anchor = (now, stamp)
                return True
            t_prev, s_prev = self._anchor  # when the previous scan was due, and its stamp
            gap = min(max((stamp - s_prev) / 1e9, 0.0), self.max_gap_s)
            due = t_prev + gap / speed
            if due <= now:
                self._anchor = (now, stamp)  # late: go now, and no catch-up burst later
                return True
            self.waits.append(due - now)
            if self._sleep(due - now):
                return False
            self._anchor = (due, stamp)
            return True
        if self.rate_hz > 0:
            wait = last + 1.0 / self.rate_hz - now
            if wait > 0:
                self.waits.append(wait)
                return not self._sleep(wait)
        return True

    # ------------------------------------------------------------------ the loop's observer

    def turn(self) -> bool:
        ok = self._take_turn()
        self._t_read = self._clock()
        return ok

    def due(self, scan: Any) -> bool:
        self._work = self._clock() - self._t_read
        if not self._pace(scan, self._last):
            return False
        self._last = self._clock()
        self._t_ins = self._clock()
        return True

    def insert(self, m: NdtOmMap, points: Any, T_world_sensor: Any) -> ScanReport | None:
        with self.viewer.map_lock:
            if self.map is None:  # the viewer was closed
                return None
            rep = m.insert_scan(points, T_world_sensor)
            self._compare_rep = self.compare.insert_scan(points, T_world_sensor) if self.compare is not None else None
        return rep

    def inserted(self, rep: ScanReport, scan: Any, points: Any, T_world_sensor: Any) -> None:
        v = self.viewer
        self.work_seconds += self._work + (self._clock() - self._t_ins)
        self.reports.append(rep)
        self.times_ms.append(rep.seconds * 1e3)
        if self._compare_rep is not None:
            self.compare_times_ms.append(self._compare_rep.seconds * 1e3)
        self.points_used.append(rep.points_used)
        # pose and the scan's points for the viewer (world frame, capped)
        T = T_world_sensor
        P = np.asarray(points, np.float64)
        P = P[np.isfinite(P).all(axis=1)]
        P = P[cap_rows(len(P), self.max_scan_points)]
        world = (P @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        self._positions.append(T[:3, 3].copy())
        v.set_trajectory(np.array(self._positions))
        v.set_scan(world)
        self.scans_done += 1
        if self.on_scan is not None:
            self.on_scan(rep, scan)
        self._dirty.set()

    def _run(self) -> None:
        try:
            m = self.map
            if m is not None:
                self.completed = run_scans(m, self._scans, self.summary, self._progress, self._after_loop, self)
            if self.summary.stopped in ("error", "memory"):  # a bad or refused scan, as `ndtom map` stops
                self.error = self.summary.error
        except Exception as exc:  # noqa: BLE001 - shown on screen; the maps keep what was inserted
            self.exception = exc
            self.error = f"{type(exc).__name__}: {exc}"
            self._error_traceback = traceback.format_exc()
        finally:
            self.finished = True
            self._playing.clear()
            self._dirty.set()
            self._done.set()

    def _draw_loop(self) -> None:
        v = self.viewer
        while True:
            self._dirty.wait(0.2)
            stopping = self._stop.is_set() or self._done.is_set()
            if self._dirty.is_set():
                self._dirty.clear()
                try:
                    self._panel.update()
                    v.refresh()
                except Exception as exc:  # noqa: BLE001 - keep mapping; say what went wrong
                    if v.closed:
                        return
                    self.error = self.error or f"drawing failed: {type(exc).__name__}: {exc}"
                # throttle: at least refresh_interval, and never more than ~1/3 of the time drawing
                pause = max(self.refresh_interval, 2.0 * v.last_refresh_s)
                if self._stop.wait(pause) and not self._dirty.is_set():
                    return
                continue
            if stopping:
                self._panel.update()
                return
