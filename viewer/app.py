"""MapViewer: an NDT-OM map in the browser (viser), the way the paper's Fig. 4 shows one.

A viewer composes viser's server with three parts, each its own module: ``levels``
(:class:`~.levels.LevelCache`: the maps shown, the lock on them, their coarser levels),
``scene`` (:class:`~.scene.MapScene`: the layers drawn under ``/ndtom`` and the camera)
and ``controls`` (:class:`~.controls.Controls`: the panel); :func:`~.redraw.redraw` joins
them in one redraw. Live mapping (:class:`~.live.LiveMapper`) drives a viewer through its
public methods.

A map may be an :class:`~ndtom_ti.NdtOmMap` (live mapping) or a
:class:`~ndtom_ti.snapshot.MapSnapshot` (a map file: ``ndtom view``). Coarser levels are
snapshots coarsened in numpy, so the viewer takes no map slot of its own.

Threads: viser runs GUI callbacks in its own thread pool, live mapping inserts scans in
a worker thread. ``map_lock`` (the level cache's) guards every read and write of the
maps. Layers are rebuilt from numpy snapshots outside that lock, one rebuild at a time,
and swapped in one ``server.atomic()`` step.

Security: every HTTP request and WebSocket upgrade passes the Host/Origin checks of
:mod:`.security`; beyond loopback the printed URL carries an access token.
"""

from __future__ import annotations

import contextlib
import io
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ._deps import require_viser
from .controls import Controls
from .levels import Caps, LevelCache, fmt
from .live import LiveMapper
from .panel import html_panel, with_panel
from .redraw import redraw
from .scene import FirstView, MapScene
from .security import AccessGuard
from .server import announcement, listen_port, start_server, url_for

if TYPE_CHECKING:
    from ndtom_ti import NdtOmMap
    from ndtom_ti.snapshot import MapSnapshot

__all__ = ["MapViewer", "show"]


class Collapsing:
    """Runs ``fn`` now, or, when a run is going on, once more after it: requests that
    arrive meanwhile collapse into that one."""

    def __init__(self, fn: Callable[[], None]):
        self._fn = fn
        self._lock = threading.Lock()
        self._running = False
        self._pending = False

    def run(self) -> None:
        with self._lock:
            if self._running:
                self._pending = True
                return
            self._running = True
        try:
            while True:
                self._fn()
                with self._lock:
                    if not self._pending:
                        return
                    self._pending = False
        finally:
            with self._lock:
                self._running = False


class MapViewer:
    """Show an :class:`~ndtom_ti.NdtOmMap` (or a :class:`~ndtom_ti.snapshot.MapSnapshot`) in the browser.

    ``compare``: a map of the same scans built with ``occupancy=False`` (Recursive NDT);
    enables the "Conflicting cells" layer. ``host`` defaults to loopback; ``port=0``
    picks a free port (``viewer.port`` / ``viewer.url`` give the real one; a busy port
    makes viser use the next free one, which is printed).

    Colours: by height (a legend fitted to the heights drawn) or by occupancy (spread over the
    probabilities drawn). Layers
    are offered only when the map has them (conflicting cells with ``compare``, the
    trajectory and the latest scan while mapping live); free cells are off until ticked
    and drawn translucent. A height clip hides what is above or below a band (a hall's
    roof; an indoor map's first view starts below its ceiling), and "Frame the map" returns the
    camera to the first view, which frames the bulk of the map.

    Level of detail: "auto" draws up to ``max_ellipsoids`` Gaussians as ellipsoids, up to
    ``max_splats`` as splats; past the cap of the geometry in use the viewer draws the
    first coarser level (2x .. 8x, coarsened from a snapshot of the map) that fits, and what still
    exceeds it is subsampled evenly. A Resolution chosen by hand is drawn as chosen, up to
    ``max_chosen`` Gaussians (past it, those nearest where the view looks). Free and occupied cells are capped at
    ``max_free_cells`` / ``max_occupied_cells`` (``viewer.caps`` holds them all). Every cap that applies is
    stated at the top of the panel. The defaults keep the page responsive with software WebGL (a
    2-core machine without GPU drew 20,000 splats at ~50 frames/s idle, 4,000 ellipsoids
    of 80 faces each at a few); with a GPU they can be raised several times.

    Parts: ``levels`` (the maps and their coarser levels), ``scene`` (what is drawn:
    ``scene.nodes``, ``drawn``; the camera: ``first_view``), ``controls`` (the panel's
    handles: set ``.value`` from Python and callbacks fire as in a browser), ``server``
    (viser's).

    Access: only pages of the viewer itself may connect (Host and Origin checks, see
    :mod:`ndtom_ti.viewer.security`); a ``host`` beyond loopback also needs the access
    token in ``viewer.url``. ``progress(line)`` receives what the viewer is doing while a
    big map is prepared (``verbose`` prints it).

    Usable from a script or a notebook: the server runs in background threads; call
    :meth:`wait` to block until Ctrl-C, :meth:`close` to stop.
    """

    def __init__(
        self,
        m: NdtOmMap | MapSnapshot | None = None,
        *,
        compare: NdtOmMap | MapSnapshot | None = None,
        host: str = "127.0.0.1",
        port: int = 0,
        label: str = "NDT-OM map",
        threshold: float = 0.5,
        color_mode: str = "height",
        geometry: str = "auto",
        max_ellipsoids: int = 4_000,
        max_splats: int = 20_000,
        max_chosen: int = 100_000,
        max_free_cells: int = 20_000,
        max_occupied_cells: int = 100_000,
        cache_size: int = 2,
        environment_map: bool = True,
        verbose: bool = True,
        progress: Callable[[str], None] | None = None,
        token: str | None = None,
        allowed_hosts: tuple[str, ...] = (),
    ):
        require_viser()  # first: a missing viser is said before anything else
        Controls.check(threshold=threshold, color_mode=color_mode, geometry=geometry)
        port = int(port)
        if not 0 <= port <= 65535:
            raise ValueError(f"port must be in [0, 65535], got {port}")
        self.requested_port = port
        use_port = listen_port(host, port)

        self.caps = Caps(
            int(max_ellipsoids), int(max_splats), int(max_chosen), int(max_free_cells), int(max_occupied_cells)
        )
        self.verbose = verbose
        if progress is None and verbose:
            progress = lambda line: print(line, flush=True)
        self._progress = progress

        self._scene_lock = threading.RLock()  # one layer rebuild at a time
        self._live_lock = threading.Lock()  # trajectory / latest scan buffers
        self._requests = Collapsing(lambda: self.refresh())
        self._trajectory = np.zeros((0, 3), np.float64)
        self._scan_world = np.zeros((0, 3), np.float32)
        self._closed = False
        self.live_mapper: LiveMapper | None = None
        self.last_refresh_s = 0.0
        self.levels = LevelCache(m, compare, size=cache_size)

        self.guard = AccessGuard(host, token=token, allowed_hosts=allowed_hosts)
        self.server = start_server(host, use_port, label=label, guard=self.guard, environment_map=environment_map)
        self.label = label
        self.host = host
        self.port = int(self.server.get_port())
        self.url = url_for(host, self.port, self.guard.token)
        self.port_note = ""
        if port and self.port != port:
            why = "in use" if use_port != port else "not available"
            self.port_note = f"port {port} is {why}; the viewer uses port {self.port} instead"
        self.scene = MapScene(self.server, self.caps)
        try:
            self.controls = Controls(
                self.server.gui,
                self.caps,
                resolution=m.resolution if m is not None else None,
                threshold=float(threshold),
                color_mode=color_mode,
                geometry=geometry,
                conflicts=compare is not None,
                on_change=self.request_refresh,
                on_layer=self._on_layer,
                on_point_size=self.scene.set_point_size,
                on_frame=self.frame,
            )
            if m is not None and len(m) and verbose:
                self._say(f"Preparing the scene: {fmt(len(m))} Gaussians at {m.resolution:g} m ...")
            self.refresh()
        except BaseException:
            self.close()
            raise
        if verbose:
            self.announce()

    def _say(self, line: str) -> None:
        if self._progress is not None:
            self._progress(line)

    def announce(self) -> None:
        """Print where the viewer serves (and, beyond loopback, a warning)."""
        for line in announcement(self.guard, self.host, self.port, self.port_note, self.drawn.get("notes", ())):
            self._say(line)

    # ------------------------------------------------------------------ public API

    @property
    def map(self) -> NdtOmMap | MapSnapshot | None:
        return self.levels.map

    @property
    def compare(self) -> NdtOmMap | MapSnapshot | None:
        return self.levels.compare

    @property
    def map_lock(self) -> threading.RLock:
        """Guards every read and write of the maps shown (Taichi calls are serialised by it)."""
        return self.levels.lock

    @property
    def drawn(self) -> Mapping[str, Any]:
        """What the last refresh drew: counts per layer, level, geometry, colour ranges, notes."""
        return self.scene.drawn

    @property
    def first_view(self) -> FirstView | None:
        """The view that frames the map (*Frame the map*); None until the map has content."""
        return self.scene.first_view

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def level(self) -> int:
        """Factor of the level drawn (1: native), after the level-of-detail rule."""
        return int(self.drawn.get("factor", 1))

    def get_port(self) -> int:
        return self.port

    def set_maps(self, m: NdtOmMap | MapSnapshot | None, compare: NdtOmMap | MapSnapshot | None = None) -> None:
        """Show other maps (the coarsened levels are dropped)."""
        self.levels.set(m, compare)
        self.scene.reframe()
        self.controls.new_maps(compare is not None, m.resolution if m is not None else None, self.scene.auto_drawn())
        self.refresh()

    def set_trajectory(self, positions: Any) -> None:
        """Sensor positions (N, 3) in the world frame, drawn as a polyline."""
        pos = np.asarray(positions, np.float64).reshape(-1, 3)
        with self._live_lock:
            self._trajectory = pos.copy()
        if len(pos):
            self.offer_live_layers()

    def offer_live_layers(self) -> None:
        """Show the Trajectory and Latest scan checkboxes (and the point size slider)."""
        self.controls.offer_live_layers()

    def set_scan(self, points_world: Any) -> None:
        """Points (N, 3) in the world frame, drawn as the latest scan."""
        pts = np.asarray(points_world, np.float32).reshape(-1, 3)
        with self._live_lock:
            self._scan_world = pts.copy()

    def layer_visible(self, key: str) -> bool:
        return self.scene.visible(key)

    def frame(self) -> None:
        """Move every connected browser's camera to the overview of the map (fitted to
        each page's own view)."""
        self.scene.frame()

    def save_html(self, path: str | Path) -> Path:
        """Write a standalone HTML page of the current scene (``scene.as_html()``), atomically:
        a failed write (full disk) leaves an existing file as it was."""
        from ndtom_ti.atomic import atomic_write, check_target

        # the target check of every writer (map saves too): a link is followed and stays,
        # a folder, pipe or device is refused
        path = check_target(path)
        data = with_panel(self.server.scene.as_html(), self.panel_html()).encode("utf-8")
        return atomic_write(path, lambda fh: fh.write(data))

    def panel_html(self) -> str:
        """The legend, statistics and notes of the live panel as one block of HTML (a written
        page has no panel of its own: viser's standalone page holds the scene alone)."""
        return html_panel(self.label, self.controls.legend.content, self.controls.stats.content)

    def live(
        self,
        scans: Any,
        m: NdtOmMap | None = None,
        *,
        compare: NdtOmMap | bool = False,
        play: bool = False,
        total: int | None = None,
        refresh_interval: float = 0.5,
        max_scan_points: int = 50_000,
        rate_hz: float = 0.0,
        **pacing: Any,
    ) -> LiveMapper:
        """Build ``m`` (default: this viewer's map) from ``scans`` in a worker thread and
        watch it grow: Play / Pause / Step, a scan counter and a chart of time per scan.

        ``scans``: an iterable of objects with ``.points`` (N, 3) sensor frame and
        ``.T_world_sensor`` (4, 4), or of ``(points, T_world_sensor)`` pairs.
        ``compare=True`` also builds a Recursive NDT map (``occupancy=False``, same
        resolution and config) for the "Conflicting cells" layer; or pass such a map.
        ``rate_hz``: at most this many scans per second (0: as fast as mapping goes).
        ``pacing``: ``speed`` (x the recording's rate, from the scans' ``stamp_ns``),
        ``max_gap_s``, ``on_scan``, ``clock``, ``sleep``: see :class:`LiveMapper`.
        The viewer stops the mapper when it closes, or when another one starts.
        """
        if self.live_mapper is not None:
            self.live_mapper.stop()
        lm = LiveMapper(
            self,
            scans,
            m if m is not None else self.map,
            compare=compare,
            total=total,
            refresh_interval=refresh_interval,
            max_scan_points=max_scan_points,
            rate_hz=rate_hz,
            **pacing,
        )
        self.live_mapper = lm
        if play:
            lm.play()
        return lm

    def wait(self) -> None:
        """Block until Ctrl-C (then close)."""
        try:
            while not self._closed:
                time.sleep(0.5)
        except KeyboardInterrupt:
            pass
        finally:
            self.close()

    def close(self) -> None:
        """Stop live mapping and the server, and drop the maps (their storage slots free)."""
        if self._closed:
            return
        self._closed = True
        lm = self.live_mapper
        if lm is not None:
            lm.stop()
        with self.map_lock:
            self.levels.set(None, None)
            if lm is not None:  # GUI callbacks may keep it alive: let go of the maps now
                lm.map = lm.compare = None
        self.live_mapper = None
        with contextlib.suppress(Exception), contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()  # (quietly: stopping twice or during interpreter teardown)

    stop = close

    def __enter__(self) -> MapViewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"MapViewer(url={self.url!r}, map={self.map!r})"

    # ------------------------------------------------------------------ drawing

    def request_refresh(self) -> None:
        """Refresh now, or, when a refresh is running (a slider being dragged), once more
        after it: requests that arrive meanwhile collapse into one."""
        self._requests.run()

    def refresh(self) -> None:
        """Rebuild the layers from the maps (after a control changed, or a scan was added)."""
        if self._closed:
            return
        t0 = time.perf_counter()
        c = self.controls
        want = c.wanted()
        with self._scene_lock:
            snap = self.levels.take(
                want,
                threshold=float(c.threshold.value),
                chosen=c.selected_factor(),
                geometry=c.geometry_choice(),
                caps=self.caps,
                find_ceiling=c.zlimits is None,
            )
            with self._live_lock:
                traj, scan = self._trajectory, self._scan_world
            redraw(self.levels, self.scene, c, self.caps, snap, want, traj, scan)
        self.last_refresh_s = time.perf_counter() - t0

    def _on_layer(self, key: str) -> None:
        on = bool(self.controls.layers[key].value)
        if on and key in self.drawn.get("skipped", ()):
            self.request_refresh()  # computed on demand
        else:
            self.scene.show_layer(key, on)


def show(
    m: NdtOmMap | MapSnapshot,
    *,
    compare: NdtOmMap | MapSnapshot | None = None,
    host: str = "127.0.0.1",
    port: int = 0,
    block: bool = False,
    **options: Any,
) -> MapViewer:
    """Open a viewer of ``m`` (prints its URL) and return it; ``viewer.server`` is the
    viser server. ``block=True`` waits until Ctrl-C. Options as for :class:`MapViewer`."""
    v = MapViewer(m, compare=compare, host=host, port=port, **options)
    if block:
        v.wait()
    return v
