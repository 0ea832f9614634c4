"""MapViewer: an NDT-OM map in the browser (viser), the way the paper's Fig. 4 shows one.

Layers (scene nodes under ``/ndtom``): the Gaussians as 1-sigma ellipsoids (one batched
mesh) or as Gaussian splats; occupied cells and, on demand, free cells (square points,
capped); the "conflicting cells" of a comparison map built without occupancy updates
(Recursive NDT, paper Fig. 4b); the sensor trajectory and the latest scan (live mapping).

A map may be an :class:`~ndtom_ti.NdtOmMap` (live mapping) or a
:class:`~ndtom_ti.snapshot.MapSnapshot` (a map file: ``ndtom view``). Coarser levels are
snapshots coarsened in numpy, so the viewer takes no map slot of its own.

Threads: viser runs GUI callbacks in its own thread pool, live mapping inserts scans in
a worker thread. ``map_lock`` guards every read and write of the maps (Taichi calls are
serialised by it; coarsened levels are made and dropped under it). Layers are rebuilt
from numpy snapshots outside that lock, one rebuild at a time, and swapped in one
``server.atomic()`` step.

Security: every HTTP request and WebSocket upgrade passes the Host/Origin checks of
:mod:`.security`; beyond loopback the printed URL carries an access token.
"""

from __future__ import annotations

import contextlib
import html
import io
import math
import re
import socket
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ndtom_ti.snapshot import MapSnapshot

from . import geometry as geo
from ._deps import require_viser
from .security import AccessGuard, guarded_server, primary_address

if TYPE_CHECKING:
    from ndtom_ti import NdtOmMap

    from .live import LiveMapper

__all__ = ["MapViewer", "show"]

LAYERS = {  # key -> checkbox label
    "gaussians": "Gaussians",
    "occupied": "Occupied cells",
    "free": "Free cells",
    "conflicts": "Conflicting cells",
    "trajectory": "Trajectory",
    "scan": "Latest scan",
}
_DEFAULT_ON = {"gaussians", "conflicts", "trajectory", "scan"}  # free cells stay off: they bury the scene
_LIVE_LAYERS = ("trajectory", "scan")  # offered once live mapping runs (or a trajectory is set)
FACTORS = (1, 2, 3, 4)  # resolution selector: native and coarser levels made with coarsen()
AUTO = 0  # resolution selector: the level of detail picks the level (its entry says which)
_LOD_FACTORS = (2, 3, 4, 6, 8)  # auto level of detail may go this far coarser
COLOR_MODES = ("height", "occupancy")
GEOMETRIES = ("auto", "ellipsoids", "splats")
FREE_OPACITY = 0.15
CONFLICT_MIN_SIGMA = 0.5  # of a cell: the least size of a conflicting cell's marker
SPLAT_MIN_SIGMA = 0.15  # of a cell: the least width of a splat (see _gaussian_node)
SPLAT_VIEW_SIGMA = 0.0015  # of the first view's radius: ~1/3 of a pixel there (see _gaussian_node)  # free cells: translucent, so the scene shows through them


def _fmt(n: int) -> str:
    return f"{int(n):,}"


def check_listen(host: str, port: int) -> bool:
    """Raise ``ValueError`` if nothing can listen on ``host``; return whether ``port`` is
    free there (viser moves on to the next free port when it is not)."""
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise ValueError(f"cannot listen on host {host!r}: {exc.strerror or exc}") from None

    def try_bind(family: int, addr: tuple, p: int) -> OSError | None:
        s = socket.socket(family, socket.SOCK_STREAM)
        try:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as asyncio's servers do
            s.bind((addr[0], p, *addr[2:]))
            return None
        except OSError as exc:
            return exc
        finally:
            s.close()

    usable = [(fam, addr) for fam, _, _, _, addr in infos if try_bind(fam, addr, 0) is None]
    if not usable:
        err = try_bind(infos[0][0], infos[0][4], 0)
        raise ValueError(f"cannot listen on host {host!r}: {getattr(err, 'strerror', None) or err}")
    return port == 0 or all(try_bind(fam, addr, port) is None for fam, addr in usable)


def warm_up(m: NdtOmMap | MapSnapshot | None) -> None:
    """Launch one (tiny) kernel of ``m`` on the calling thread.

    Taichi builds its default field tree at the first kernel launch of a process, and
    only the thread that initialised Taichi may do that ("Assertion failure:
    std::this_thread::get_id() == main_thread_id_"). Viewer callbacks and live mapping
    run kernels in other threads, so the viewer launches one here first. A snapshot runs
    no kernel."""
    if m is not None and not isinstance(m, MapSnapshot):
        m.occupancy(np.zeros((1, 3)))


def url_for(host: str, port: int, token: str | None = None) -> str:
    """The URL a browser opens: a wildcard bind is shown as this machine's address."""
    # ("::" listens on IPv6 only, as asyncio binds it: its URL is an IPv6 address)
    shown = primary_address(ipv6=host == "::") if host in ("", "0.0.0.0", "::") else host
    if ":" in shown and not shown.startswith("["):
        shown = f"[{shown}]"
    return f"http://{shown}:{port}/" + (f"?token={token}" if token else "")


@dataclass
class Controls:
    """Handles of the GUI controls (set ``.value`` from Python: callbacks fire as in a browser)."""

    resolution: Any = None
    threshold: Any = None
    color_mode: Any = None
    geometry: Any = None
    point_size: Any = None
    layers: dict = field(default_factory=dict)  # layer key -> checkbox
    legend: Any = None
    stats: Any = None
    notice: Any = None
    frame: Any = None
    redraw: Any = None
    zclip: Any = None
    # live mapping (made by ``MapViewer.live``)
    live_folder: Any = None
    play: Any = None
    pause: Any = None
    step: Any = None
    scan: Any = None
    rate: Any = None
    chart: Any = None
    live_status: Any = None


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
    ``max_free_cells`` / ``max_occupied_cells``. Every cap that applies is stated at the
    top of the panel. The defaults keep the page responsive with software WebGL (a
    2-core machine without GPU drew 20,000 splats at ~50 frames/s idle, 4,000 ellipsoids
    of 80 faces each at a few); with a GPU they can be raised several times.

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
        viser = require_viser()
        if color_mode not in COLOR_MODES:
            raise ValueError(f"color_mode must be one of {COLOR_MODES}, got {color_mode!r}")
        if geometry not in GEOMETRIES:
            raise ValueError(f"geometry must be one of {GEOMETRIES}, got {geometry!r}")
        if not 0.5 <= float(threshold) <= 0.99:
            raise ValueError(f"threshold must be in [0.5, 0.99], got {threshold}")
        port = int(port)
        if not 0 <= port <= 65535:
            raise ValueError(f"port must be in [0, 65535], got {port}")
        self.requested_port = port
        port_free = check_listen(host, port)

        self.max_ellipsoids = int(max_ellipsoids)
        self.max_splats = int(max_splats)
        self.max_chosen = int(max_chosen)
        self.max_free_cells = int(max_free_cells)
        self.max_occupied_cells = int(max_occupied_cells)
        self.cache_size = max(int(cache_size), 0)
        self.verbose = verbose
        if progress is None and verbose:
            progress = lambda line: print(line, flush=True)
        self._progress = progress

        self.map_lock = threading.RLock()  # every map access (Taichi) goes through it
        self._scene_lock = threading.RLock()  # one layer rebuild at a time
        self._live_lock = threading.Lock()  # trajectory / latest scan buffers
        self._pending_lock = threading.Lock()
        self._refreshing = False
        self._pending = False
        self._maps: dict[str, NdtOmMap | MapSnapshot | None] = {"ndtom": m, "rndt": compare}
        self._cache: OrderedDict = OrderedDict()  # (kind, factor) -> (version, map)
        self._handles: dict[str, Any] = {}
        self._trajectory = np.zeros((0, 3), np.float64)
        self._scan_world = np.zeros((0, 3), np.float32)
        self._live_layers = False
        self._zlimits: tuple[float, float] | None = None  # range of the height clip slider
        self._framed = False
        self._closed = False
        self.live_mapper: LiveMapper | None = None
        #: what the last refresh drew: counts per layer, level, geometry, notes
        self.drawn: dict[str, Any] = {}
        self.last_refresh_s = 0.0
        with self.map_lock:
            warm_up(m)
            warm_up(compare)

        self.guard = AccessGuard(host, token=token, allowed_hosts=allowed_hosts)
        # viser's own messages (a URL without the token, "server stopped") stay off: the viewer
        # prints a URL that works
        with guarded_server(self.guard), contextlib.redirect_stdout(io.StringIO()):
            self.server = viser.ViserServer(host=host, port=port, label=label, verbose=False)
        self.label = label
        self.host = host
        self.port = int(self.server.get_port())
        self.url = url_for(host, self.port, self.guard.token)
        self.port_note = ""
        if port and self.port != port:
            why = "in use" if not port_free else "not available"
            self.port_note = f"port {port} is {why}; the viewer uses port {self.port} instead"
        scene = self.server.scene
        scene.configure_default_lights(enabled=True, cast_shadow=False)  # shadows of 1000s of ellipsoids: slow
        if not environment_map:
            # no image-based light: an even sky/ground light keeps the colours readable
            scene.configure_environment_map(hdri=None)
            scene.add_light_hemisphere("/lights/hemisphere", sky_color=(255, 255, 255),
                                       ground_color=(160, 160, 160), intensity=1.2)  # fmt: skip
        # no "share" button: it would send the map to a public relay
        self.server.gui.configure_theme(show_share_button=False)
        # the panel docked at the right edge: the scene is drawn beside it, never under it
        with contextlib.suppress(AttributeError):
            self.server.gui.main_panel.dock_right()
            self.server.gui.main_panel.set_width(280)

        self.controls = Controls()
        try:
            self._build_gui(threshold=float(threshold), color_mode=color_mode, geometry=geometry)
            if m is not None and len(m) and verbose:
                self._say(f"Preparing the scene: {_fmt(len(m))} Gaussians at {m.resolution:g} m ...")
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
        for note in self.drawn.get("notes", ()):
            self._say(f"Note: {note}")
        if self.port_note:
            self._say(f"Note: {self.port_note}")
        if not self.guard.loopback:
            self._say(
                f"WARNING: the viewer listens on {self.host}, beyond this machine: anyone who can reach "
                f"port {self.port} and has the URL below (with its access token) can see the map and "
                "use the controls. Use --host 127.0.0.1 to keep it on this machine."
            )
        self._say(f"NDT-OM viewer: {self.url}")
        if self.host in ("", "0.0.0.0", "::"):
            local = "::1" if self.host == "::" else "127.0.0.1"
            self._say(f"  (on this machine also: {url_for(local, self.port, self.guard.token)})")

    # ------------------------------------------------------------------ public API

    @property
    def map(self) -> NdtOmMap | MapSnapshot | None:
        return self._maps["ndtom"]

    @property
    def compare(self) -> NdtOmMap | MapSnapshot | None:
        return self._maps["rndt"]

    def get_port(self) -> int:
        return self.port

    def set_maps(self, m: NdtOmMap | MapSnapshot | None, compare: NdtOmMap | MapSnapshot | None = None) -> None:
        """Show other maps (the coarsened levels are dropped)."""
        with self.map_lock:
            warm_up(m)
            warm_up(compare)
            self._maps = {"ndtom": m, "rndt": compare}
            self._cache.clear()
        self._framed = False
        self._zlimits = None
        c = self.controls
        if "conflicts" in c.layers:
            c.layers["conflicts"].visible = compare is not None
        self._update_resolution_options()
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
        if self._live_layers:
            return
        self._live_layers = True
        c = self.controls
        for key in _LIVE_LAYERS:
            if key in c.layers:
                c.layers[key].visible = True
        if c.point_size is not None:
            c.point_size.visible = True

    def set_scan(self, points_world: Any) -> None:
        """Points (N, 3) in the world frame, drawn as the latest scan."""
        pts = np.asarray(points_world, np.float32).reshape(-1, 3)
        with self._live_lock:
            self._scan_world = pts.copy()

    @property
    def level(self) -> int:
        """Factor of the level drawn (1: native), after the level-of-detail rule."""
        return int(self.drawn.get("factor", 1))

    def layer_visible(self, key: str) -> bool:
        h = self._handles.get(key)
        return bool(h is not None and h.visible)

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
        c = self.controls
        label = html.escape(self.label)  # (the statistics end with the notes)
        return (
            '<details id="ndtom-panel" open style="position:fixed;top:8px;right:8px;z-index:1000;width:300px;'
            "max-height:90vh;overflow:auto;background:rgba(255,255,255,0.92);border:1px solid #ccc;"
            'border-radius:6px;padding:6px 8px;font:13px/1.4 sans-serif;color:#222">'
            f"<summary><b>{label}</b></summary>{c.legend.content}"
            f'<div style="font-size:0.85em;margin-top:4px">{_md_html(c.stats.content)}</div></details>'
        )

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
        """
        from .live import LiveMapper

        if self.live_mapper is not None:
            self.live_mapper.stop()
        lm = LiveMapper(
            self, scans, m if m is not None else self.map, compare=compare, total=total,
            refresh_interval=refresh_interval, max_scan_points=max_scan_points, rate_hz=rate_hz, **pacing,
        )  # fmt: skip
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
            self._cache.clear()
            self._maps = {"ndtom": None, "rndt": None}
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

    # ------------------------------------------------------------------ GUI

    def _level_options(self) -> tuple[list[str], dict[str, int]]:
        """Labels of the resolution selector: each level, then "auto" (the level of detail's
        choice, named once drawn: the selector says what is drawn)."""
        m = self.map
        r = m.resolution if m is not None else None
        labels, lookup = [], {}
        for f in FACTORS:
            if r is None:
                lab = "native" if f == 1 else f"{f}x coarser"
            else:
                lab = f"{r * f:g} m (native)" if f == 1 else f"{r * f:g} m ({f}x)"
            labels.append(lab)
            lookup[lab] = f
        drawn = self.drawn.get("resolution") if self.drawn.get("selected") == AUTO else None
        auto = "auto" if drawn is None else f"auto: {drawn:g} m drawn"
        labels.append(auto)
        lookup[auto] = AUTO
        return labels, lookup

    def _update_resolution_options(self) -> None:
        labels, lookup = self._level_options()
        h = self.controls.resolution
        if h is not None and list(h.options) != labels:
            old = self._selected_factor()
            self._level_lookup = lookup
            self._setting_choice = True  # a relabelling, not a choice: no refresh
            try:
                h.options = labels
                h.value = labels[-1] if old == AUTO else labels[FACTORS.index(old)]
            finally:
                self._setting_choice = False
        self._level_lookup = lookup

    def _selected_factor(self) -> int:
        """The chosen level's factor, or AUTO."""
        h = self.controls.resolution
        if h is None:
            return AUTO
        v = str(h.value)
        return AUTO if v.startswith("auto") else self._level_lookup.get(v, AUTO)

    def _geometry_choice(self) -> str:
        v = str(self.controls.geometry.value)
        return "auto" if v.startswith("auto") else v

    def _update_geometry_label(self, use: str) -> None:
        """The geometry selector's "auto" entry says which geometry it draws."""
        h = self.controls.geometry
        label = f"auto: {use}"
        if h is None or label in h.options:
            return
        auto_now = str(h.value).startswith("auto")
        self._setting_choice = True
        try:
            h.options = [label, *GEOMETRIES[1:]]
            if auto_now:
                h.value = label
        finally:
            self._setting_choice = False

    def _on_choice(self) -> None:
        if not getattr(self, "_setting_choice", False):
            self.request_refresh()

    def _build_gui(self, *, threshold: float, color_mode: str, geometry: str) -> None:
        gui = self.server.gui
        c = self.controls
        labels, self._level_lookup = self._level_options()
        c.notice = gui.add_markdown("", visible=False)  # caps and subsampling, where they apply
        c.frame = gui.add_button("Frame the map", hint="move the camera back to the first view of the whole map")
        with gui.add_folder("Map"):
            c.color_mode = gui.add_dropdown("Colour by", COLOR_MODES, initial_value=color_mode,
                                            hint="height of the Gaussian's mean, or its occupancy probability")  # fmt: skip
            c.zclip = gui.add_multi_slider(
                "Height clip (m)", min=0.0, max=1.0, step=0.05, initial_value=(0.0, 1.0),
                hint="draw only what lies between these heights (e.g. below a hall's roof)",
            )  # fmt: skip
            c.threshold = gui.add_slider(
                "Occupancy threshold", min=0.5, max=0.99, step=0.01, initial_value=threshold,
                hint="draw Gaussians and occupied cells with occupancy probability above this",
            )  # fmt: skip
            c.resolution = gui.add_dropdown(
                "Resolution", labels, initial_value=labels[-1],
                hint=f"a level is drawn whole (past {_fmt(self.max_chosen)} Gaussians: the part around the view); "
                "auto: the level of detail picks the finest level that keeps the page responsive",
            )  # fmt: skip
            c.geometry = gui.add_dropdown(
                "Gaussians as", GEOMETRIES, initial_value=geometry,
                hint=f"auto: ellipsoids up to {_fmt(self.max_ellipsoids)} Gaussians, splats up to "
                f"{_fmt(self.max_splats)}, then a coarser level",
            )  # fmt: skip
            c.redraw = gui.add_button("Draw around the view", visible=False,
                                      hint="draw the chosen level's Gaussians nearest where the view looks")  # fmt: skip
            c.point_size = gui.add_slider("Point size", min=0.005, max=0.5, step=0.005, initial_value=0.03,
                                          hint="size (m) of the latest scan's points",
                                          visible=self._live_layers)  # fmt: skip
        c.legend = gui.add_html("")
        with gui.add_folder("Layers"):
            for key, lab in LAYERS.items():
                offered = key not in _LIVE_LAYERS or self._live_layers
                if key == "conflicts":
                    offered = self.compare is not None
                c.layers[key] = gui.add_checkbox(lab, key in _DEFAULT_ON, visible=offered)
        with gui.add_folder("Statistics", expand_by_default=False):
            c.stats = gui.add_markdown("")

        c.resolution.on_update(lambda _: self._on_choice())
        c.threshold.on_update(lambda _: self.request_refresh())
        c.color_mode.on_update(lambda _: self.request_refresh())
        c.geometry.on_update(lambda _: self._on_choice())
        c.zclip.on_update(lambda _: self._on_zclip())
        c.point_size.on_update(lambda _: self._on_point_size())
        c.frame.on_click(lambda _: self.frame())
        c.redraw.on_click(lambda _: self.request_refresh())
        for key, box in c.layers.items():
            box.on_update(lambda _, key=key: self._on_layer(key))

    def _on_zclip(self) -> None:
        if not getattr(self, "_setting_zclip", False):
            self.request_refresh()

    def _clip_range(self) -> tuple[float, float] | None:
        """The height band to draw, or None when the clip spans the whole map."""
        c = self.controls
        if c.zclip is None or self._zlimits is None:
            return None
        lo, hi = (float(v) for v in c.zclip.value)
        zlo, zhi = self._zlimits
        if lo <= zlo and hi >= zhi:
            return None
        return lo, hi

    def _update_zclip(self, z: np.ndarray, res: float, ceiling: float | None = None) -> None:
        """Fit the height clip slider to the map's heights (kept where the user moved it);
        at the first fit, ``ceiling`` (an indoor map's roof) starts the clip below it."""
        if len(z) == 0:
            return
        step = max(round(float(res) / 2.0, 3), 0.01)
        zlo = float(np.floor(np.min(z) / step) * step)
        zhi = float(np.ceil(np.max(z) / step) * step)
        if zhi <= zlo:
            zhi = zlo + step
        old = self._zlimits
        if old is not None and zlo >= old[0] and zhi <= old[1]:
            return  # the map grew inside the range
        c = self.controls
        cur = tuple(float(v) for v in c.zclip.value)
        full = old is None or (cur[0] <= old[0] and cur[1] >= old[1])
        if old is not None:
            zlo, zhi = min(zlo, old[0]), max(zhi, old[1])
        self._zlimits = (zlo, zhi)
        self._setting_zclip = True
        try:
            c.zclip.step = step
            c.zclip.min = zlo
            c.zclip.max = zhi
            if old is None and ceiling is not None and zlo < ceiling < zhi:
                c.zclip.value = (zlo, float(np.floor(ceiling / step) * step))
            else:
                c.zclip.value = (zlo, zhi) if full else (max(cur[0], zlo), min(cur[1], zhi))
        finally:
            self._setting_zclip = False

    def _on_layer(self, key: str) -> None:
        on = bool(self.controls.layers[key].value)
        h = self._handles.get(key)
        if on and key in self.drawn.get("skipped", ()):
            self.request_refresh()  # computed on demand
        elif h is not None:
            h.visible = on

    def _on_point_size(self) -> None:
        h = self._handles.get("scan")
        if h is not None:
            h.point_size = float(self.controls.point_size.value)

    # ------------------------------------------------------------------ data (under map_lock)

    def _version(self, m: NdtOmMap | MapSnapshot) -> tuple[int, int]:
        return (m.scans_inserted, m.points_inserted)

    def _map_at(self, kind: str, factor: int) -> NdtOmMap | MapSnapshot:
        """The map ``kind`` at ``factor`` x its resolution (cached; call under map_lock)."""
        base = self._maps[kind]
        if base is None:
            raise LookupError(f"the viewer holds no {kind} map")  # callers check first
        if factor == 1:
            return base
        key = (kind, factor)
        entry = self._cache.pop(key, None)
        if entry is not None and entry[0] == self._version(base):
            self._cache[key] = entry  # most recently used last
            return entry[1]
        del entry  # a stale level is dropped before its replacement is made
        while self._cache and len(self._cache) >= max(self.cache_size, 1):
            self._cache.popitem(last=False)
        cm = _coarser(base, factor)
        if self.cache_size:
            self._cache[key] = (self._version(base), cm)
        return cm

    def _snapshot(self, want: dict[str, bool]) -> dict:
        """Everything the layers need, as numpy arrays, taken under map_lock."""
        thr = float(self.controls.threshold.value)
        chosen = self._selected_factor()
        sel = chosen or 1  # auto starts from the native level
        mode = self._geometry_choice()
        out: dict[str, Any] = {"threshold": thr, "selected": chosen, "notes": [], "skipped": []}
        with self.map_lock:
            base = self._maps["ndtom"]
            if base is None:
                out.update(factor=sel, resolution=None, g=None, skipped=["occupied", "free", "conflicts"])
                return out
            try:
                m = self._map_at("ndtom", sel)
            except MemoryError as exc:
                out["notes"].append(f"the {sel}x level could not be made ({exc}); showing the native level")
                m, sel = base, 1
            g = m.gaussians(min_probability=thr)
            if self._zlimits is None and len(g["n"]):
                # indoors, a first view below the roof; found at the chosen level (the native one at
                # first): a coarse level's large tiles take trees and uneven ground for ceilings
                out["ceiling"] = geo.ceiling_height(g["mean"], g["cov"], m.resolution)
            factor = sel
            n_sel = len(g["n"])
            cap = self.max_ellipsoids if mode == "ellipsoids" else self.max_splats
            if n_sel > cap and chosen == AUTO:  # a level chosen by hand is drawn as chosen
                # Too many to draw: the first coarser level that fits (its Gaussians are larger, so
                # they stay visible from afar, where an even subsample of small ones fades out).
                # Estimate each level's count from the parents of the drawn cells.
                idx = g["index"]
                choice = None
                for f in _LOD_FACTORS:
                    if len(np.unique(geo.cell_keys(idx // f))) <= cap:
                        choice = f
                        break
                choice = choice or _LOD_FACTORS[-1]
                try:
                    cm = (
                        self._map_at("ndtom", sel * choice) if sel * choice in FACTORS else _coarser(base, sel * choice)
                    )
                    m, factor = cm, sel * choice
                    del cm
                    g = m.gaussians(min_probability=thr)
                    out["notes"].append(
                        f"{_fmt(n_sel)} Gaussians at {base.resolution * sel:g} m exceed {_fmt(cap)}: "
                        f"showing the {choice}x coarser level ({m.resolution:g} m)"
                    )
                except MemoryError as exc:
                    out["notes"].append(f"a coarser level could not be made ({exc})")
            out.update(factor=factor, resolution=m.resolution, g=g, native_resolution=base.resolution)
            out["stats"] = {
                "scans": base.scans_inserted,
                "points": base.points_inserted,
                "memory": base.memory_bytes(),
                "occupancy": base.occupancy_enabled,
            }
            need_cells = want["occupied"] or want["free"]
            if need_cells:
                k = m.known_cells()
                out["known"] = len(k["p_occ"])
                occ = k["p_occ"] > thr
                free = k["p_occ"] < 0.5
                out["n_occupied"], out["n_free"] = int(occ.sum()), int(free.sum())
                for key, sel_mask, cap in (("occupied", occ, self.max_occupied_cells),
                                           ("free", free, self.max_free_cells)):  # fmt: skip
                    if want[key]:
                        rows = np.flatnonzero(sel_mask)
                        rows = rows[geo.cap_rows(len(rows), cap)]
                        out[key] = (m.cell_center(k["index"][rows]), k["p_occ"][rows])
                    else:
                        out["skipped"].append(key)
            else:
                out["skipped"] += ["occupied", "free"]
            cmp_base = self._maps["rndt"]
            if cmp_base is not None:
                out["compare_stats"] = {"gaussians": None}
                if want["conflicts"]:
                    try:
                        cm = self._map_at("rndt", factor) if factor in FACTORS else _coarser(cmp_base, factor)
                    except MemoryError as exc:
                        cm = None
                        out["notes"].append(f"conflicting cells: the comparison map's level could not be made ({exc})")
                    if cm is not None:
                        ng = m.gaussians(min_probability=0.5) if thr != 0.5 else g
                        cg = cm.gaussians(min_probability=0.5)
                        conflict = ~np.isin(geo.cell_keys(cg["index"]), geo.cell_keys(ng["index"]))
                        out["conflicts"] = {"mean": cg["mean"][conflict], "cov": cg["cov"][conflict]}
                        out["compare_stats"] = {"gaussians": len(cg["n"]), "conflicts": int(conflict.sum())}
                    del cm
                else:
                    out["skipped"].append("conflicts")
            del m
        return out

    # ------------------------------------------------------------------ drawing

    def request_refresh(self) -> None:
        """Refresh now, or, when a refresh is running (a slider being dragged), once more
        after it: requests that arrive meanwhile collapse into one."""
        with self._pending_lock:
            if self._refreshing:
                self._pending = True
                return
            self._refreshing = True
        try:
            while True:
                self.refresh()
                with self._pending_lock:
                    if not self._pending:
                        return
                    self._pending = False
        finally:
            with self._pending_lock:
                self._refreshing = False

    def refresh(self) -> None:
        """Rebuild the layers from the maps (after a control changed, or a scan was added)."""
        if self._closed:
            return
        t0 = time.perf_counter()
        c = self.controls
        want = {k: bool(box.value) for k, box in c.layers.items()}
        with self._scene_lock:
            snap = self._snapshot(want)
            with self._live_lock:
                traj, scan = self._trajectory, self._scan_world
            self._draw(snap, want, traj, scan)
        self.last_refresh_s = time.perf_counter() - t0

    def _gaussian_node(self, g: dict, colors: np.ndarray, res: float, use: str, visible: bool) -> Any:
        scene = self.server.scene
        name = "/ndtom/gaussians"
        if use == "splats":
            # splats at least SPLAT_MIN_SIGMA of a cell thick, and about a third of a pixel of the
            # first view: a lidar's ring seen from afar gives line-thin Gaussians, and a splat
            # thinner than a pixel fades out (a big map's native level would be a blank page)
            view = getattr(self, "_view", None)
            radius = view[1] if view is not None else geo.bulk_sphere(g["mean"])[1]
            eps = max(SPLAT_MIN_SIGMA * res, SPLAT_VIEW_SIGMA * radius) ** 2
            cov = g["cov"] + eps * np.eye(3)[None]
            return scene.add_gaussian_splats(
                name, centers=g["mean"].astype(np.float32), covariances=cov.astype(np.float32),
                rgbs=colors.astype(np.float32) / 255.0, opacities=np.full((len(cov), 1), 0.9, np.float32),
                visible=visible,
            )  # fmt: skip
        V, F = geo.icosphere(1)
        wxyz, scales = geo.ellipsoid_instances(g["cov"], min_sigma=0.02 * res)
        return scene.add_batched_meshes_simple(
            name, V, F, batched_wxyzs=wxyz, batched_positions=g["mean"].astype(np.float32),
            batched_scales=scales, batched_colors=colors, lod="off", cast_shadow=False, receive_shadow=False,
            visible=visible,
        )  # fmt: skip

    def _free_node(self, centers: np.ndarray, colors: np.ndarray, res: float, visible: bool) -> Any:
        """Free cells as translucent boxes one cell wide: the scene stays visible through them."""
        V, F = geo.unit_box()
        n = len(centers)
        return self.server.scene.add_batched_meshes_simple(
            "/ndtom/free", V, F, batched_wxyzs=np.tile(np.array([1.0, 0.0, 0.0, 0.0], np.float32), (n, 1)),
            batched_positions=centers.astype(np.float32), batched_scales=np.full((n, 3), 0.9 * res, np.float32),
            batched_colors=colors, opacity=FREE_OPACITY, lod="off", cast_shadow=False, receive_shadow=False,
            visible=visible,
        )  # fmt: skip

    def _set(self, key: str, make: Any) -> None:
        """Replace layer ``key`` with ``make()`` (None: remove it)."""
        old = self._handles.pop(key, None)
        new = make() if make is not None else None
        if new is not None:
            self._handles[key] = new
        elif old is not None:
            old.remove()

    def _draw(self, snap: dict, want: dict[str, bool], traj: np.ndarray, scan: np.ndarray) -> None:
        c = self.controls
        scene = self.server.scene
        color_mode = str(c.color_mode.value)
        geometry = self._geometry_choice()
        g = snap.get("g")
        res = snap.get("resolution") or 0.1
        # nothing non-finite reaches the page (three.js fails on a NaN position; a scan may carry NaN points)
        if g is not None and not (keep := geo.finite_rows(g["mean"], g["cov"])).all():
            g = {k: v[keep] for k, v in g.items()}
        traj = traj[geo.finite_rows(traj)] if len(traj) else traj
        scan = scan[geo.finite_rows(scan)] if len(scan) else scan
        drawn: dict[str, Any] = {"factor": snap["factor"], "resolution": snap.get("resolution"),
                                 "notes": list(snap["notes"]), "skipped": list(snap["skipped"])}  # fmt: skip
        zsrc = g["mean"][:, 2] if g is not None and len(g["n"]) else traj[:, 2] if len(traj) else np.zeros(0)
        self._update_zclip(zsrc, res, snap.get("ceiling"))
        clip = self._clip_range()
        drawn["clip"] = clip

        def inside(z: np.ndarray) -> np.ndarray:
            lo, hi = clip if clip is not None else (-np.inf, np.inf)
            return (z >= lo) & (z <= hi)

        if g is not None and clip is not None:
            g = {k: v[inside(g["mean"][:, 2])] for k, v in g.items()}
        # the colours fit what is drawn: the clip's heights, the drawn Gaussians' occupancies
        zrange = geo.height_range(g["mean"][:, 2] if g is not None and len(g["n"]) else zsrc)
        prange = geo.occupancy_range(g["p_occ"] if g is not None else np.zeros(0), snap["threshold"])
        n_all = 0 if g is None else len(g["n"])
        use = geometry
        if geometry == "auto":
            use = "ellipsoids" if n_all <= self.max_ellipsoids else "splats"
        cap = self.max_ellipsoids if use == "ellipsoids" else self.max_splats
        by_hand = snap["selected"] != AUTO
        part = False
        if by_hand and g is not None and n_all > max(cap, self.max_chosen):
            # a level chosen by hand is drawn whole up to max_chosen; past it, the part around the view
            center = self._view_center(g["mean"])
            rows = np.sort(np.argsort(np.linalg.norm(g["mean"] - center, axis=1), kind="stable")[: self.max_chosen])
            g = {k: v[rows] for k, v in g.items()}
            part = True
            drawn["notes"].append(
                f"{_fmt(n_all)} Gaussians at {res:g} m: showing the {_fmt(len(rows))} nearest the view's centre "
                f"(past {_fmt(self.max_chosen)} the page stops responding); move the view, then *Draw around the view*"
            )
        elif by_hand and g is not None and n_all > cap:
            drawn["notes"].append(f"{_fmt(n_all)} Gaussians drawn as {use} at {res:g} m: past {_fmt(cap)} the page "
                                  "may respond slowly (Resolution auto keeps it responsive)")  # fmt: skip
        elif g is not None and n_all > cap:
            rows = geo.cap_rows(n_all, cap)
            g = {k: v[rows] for k, v in g.items()}
            drawn["notes"].append(f"{_fmt(n_all)} Gaussians to draw as {use}: showing an even {_fmt(len(rows))} "
                                  f"of them (past {_fmt(cap)} the page stops responding){self._coarser_hint()}")  # fmt: skip
        drawn["selected"] = snap["selected"]
        n_g = 0 if g is None else len(g["n"])
        drawn["gaussians_total"] = n_all
        drawn["geometry"] = use
        drawn["zrange"] = zrange
        drawn["prange"] = prange

        with self.server.atomic():
            # Gaussians
            if g is not None and n_g:
                cols = geo.colors_for(color_mode, g["p_occ"], g["mean"][:, 2], zrange, prange)
                if self._handles.get("gaussians") is not None and drawn["geometry"] != self.drawn.get("geometry"):
                    self._handles.pop("gaussians").remove()  # splats <-> ellipsoids: other node type
                self._set("gaussians", lambda: self._gaussian_node(g, cols, res, use, want["gaussians"]))
            else:
                self._set("gaussians", None)
            drawn["gaussians"] = n_g

            # Occupied cells (square points one cell wide) and free cells (translucent boxes)
            for key in ("occupied", "free"):
                if key in snap["skipped"]:
                    drawn[key] = self.drawn.get(key, 0) if key in self._handles else 0
                    if key in self._handles:
                        self._handles[key].visible = False
                    continue
                centers, p = snap[key]
                if not (fin := geo.finite_rows(centers)).all():
                    centers, p = centers[fin], p[fin]
                if clip is not None:
                    keep = inside(centers[:, 2])
                    centers, p = centers[keep], p[keep]
                if key == "free" and color_mode == "height":
                    cols = np.tile(np.array(geo.FREE_RGB, np.uint8), (len(p), 1))
                else:
                    cols = geo.colors_for(color_mode, p, centers[:, 2], zrange, prange)
                if len(p) and key == "free":
                    self._set(key, lambda centers=centers, cols=cols: self._free_node(centers, cols, res, want["free"]))
                elif len(p):
                    self._set(key, lambda centers=centers, cols=cols, key=key: scene.add_point_cloud(
                        f"/ndtom/{key}", centers.astype(np.float32), cols, point_size=0.9 * res,
                        point_shape="square", precision="float32", visible=want[key]))  # fmt: skip
                else:
                    self._set(key, None)
                drawn[key] = len(p)
            for key, total, cap in (("occupied", snap.get("n_occupied"), self.max_occupied_cells),
                                    ("free", snap.get("n_free"), self.max_free_cells)):  # fmt: skip
                if total is not None and key not in snap["skipped"]:
                    drawn[f"{key}_total"] = total
                    if total > cap:
                        drawn["notes"].append(f"{LAYERS[key]}: {_fmt(drawn[key])} of {_fmt(total)} drawn "
                                              f"(cap {_fmt(cap)})")  # fmt: skip

            # Conflicting cells: the comparison map's Gaussians where NDT-OM has none
            conf = snap.get("conflicts")
            if conf is not None:
                conf = {k: v[geo.finite_rows(conf["mean"], conf["cov"])] for k, v in conf.items()}
                if clip is not None:
                    keep = inside(conf["mean"][:, 2])
                    conf = {k: v[keep] for k, v in conf.items()}
                n_c = len(conf["mean"])
                if n_c:
                    V, F = geo.icosphere(1)
                    # at least half a cell in every axis: a few conflicting cells among thousands of
                    # Gaussians stay findable (a flat 1-sigma shell vanishes edge-on)
                    wxyz, scales = geo.ellipsoid_instances(conf["cov"], min_sigma=CONFLICT_MIN_SIGMA * res)
                    self._set("conflicts", lambda: scene.add_batched_meshes_simple(
                        "/ndtom/conflicts", V, F, batched_wxyzs=wxyz,
                        batched_positions=conf["mean"].astype(np.float32),
                        batched_scales=scales * np.float32(1.2), batched_colors=geo.CONFLICT_RGB,
                        lod="off", cast_shadow=False, receive_shadow=False, visible=want["conflicts"]))  # fmt: skip
                else:
                    self._set("conflicts", None)
                drawn["conflicts"] = n_c
            elif "conflicts" in snap["skipped"] and "conflicts" in self._handles:
                self._handles["conflicts"].visible = False
                drawn["conflicts"] = self.drawn.get("conflicts", 0)
            else:
                self._set("conflicts", None)
                drawn["conflicts"] = 0

            # Trajectory and latest scan
            if len(traj) >= 2:
                seg = np.stack([traj[:-1], traj[1:]], axis=1).astype(np.float32)
                self._set("trajectory", lambda: scene.add_line_segments(
                    "/ndtom/trajectory", seg, geo.TRAJECTORY_RGB, thickness=3.0, thickness_units="screen",
                    visible=want["trajectory"]))  # fmt: skip
            else:
                self._set("trajectory", None)
            drawn["trajectory"] = len(traj)
            if len(scan):
                self._set("scan", lambda: scene.add_point_cloud(
                    "/ndtom/scan", scan, geo.SCAN_RGB, point_size=float(c.point_size.value),
                    point_shape="circle", precision="float32", visible=want["scan"]))  # fmt: skip
            else:
                self._set("scan", None)
            drawn["scan"] = len(scan)

            at_top = None
            if g is not None and n_g:
                at_top = float(np.mean(g["p_occ"] >= prange[1] - 1e-3))
            c.legend.content = geo.legend_html(
                color_mode, threshold=snap["threshold"], zrange=zrange, conflicts=self.compare is not None,
                live=self._live_layers, free=want["free"], clip=clip, prange=prange, at_top=at_top,
            )  # fmt: skip
            c.stats.content = self._stats_markdown(snap, drawn)
            notes = drawn["notes"]
            c.notice.content = "  \n".join(f"**Note**: {n}" for n in notes)
            c.notice.visible = bool(notes)
            c.layers["conflicts"].disabled = self.compare is None
        self.drawn = drawn
        c.redraw.visible = part
        self._update_resolution_options()  # "auto" names the level drawn
        self._update_geometry_label(use)
        if not self._framed:
            self._frame(g if clip is None else snap.get("g"), traj)

    def _view_center(self, pts: np.ndarray) -> np.ndarray:
        """Where a connected page's camera looks (else the map's framed centre)."""
        for client in self.server.get_clients().values():
            with contextlib.suppress(Exception):
                look = np.asarray(client.camera.look_at, np.float64)
                if look.shape == (3,) and np.isfinite(look).all():
                    return look
        view = getattr(self, "_view", None)
        return view[0] if view is not None else geo.bulk_sphere(pts)[0]

    def _coarser_hint(self) -> str:
        return "; a coarser Resolution shows all of the map" if self._selected_factor() < FACTORS[-1] else ""

    def _frame(self, g: dict | None, traj: np.ndarray) -> None:
        """Point the camera at the map once it has content: its bulk (all of an indoor map)
        in view, seen from above at an angle."""
        pts = g["mean"] if g is not None and len(g["n"]) else traj
        if len(pts) == 0:
            return
        center, radius = geo.bulk_sphere(pts)  # the bulk: an outdoor map's far rings are no speck's frame
        direction = np.array([-0.45, -0.75, 0.8])
        self._view = (center, radius, direction / np.linalg.norm(direction))
        cam = self.server.initial_camera
        # pages start here: 75 degrees vertical (viser's), a view narrowed by the panel beside it
        # (a page's first camera message comes before its layout: its size cannot be used yet)
        cam.position, cam.look_at = self._camera_for(np.radians(75.0), 0.75)
        with contextlib.suppress(AttributeError):
            cam.up = (0.0, 0.0, 1.0)
        self._framed = True
        self.frame()

    def _camera_for(self, fov: float, aspect: float) -> tuple[tuple, tuple]:
        """(position, look_at) that fit the map's bounding sphere in a view of vertical field
        of view ``fov`` (radians) and width/height ``aspect``."""
        center, radius, direction = self._view
        half = min(fov / 2.0, math.atan(math.tan(fov / 2.0) * max(aspect, 0.1)))
        distance = radius / math.sin(half)
        pos = center + distance * direction
        return tuple(float(x) for x in pos), tuple(float(x) for x in center)

    def frame(self) -> None:
        """Move every connected browser's camera to the overview of the map (fitted to
        each page's own view)."""
        if getattr(self, "_view", None) is None:
            return
        for client in self.server.get_clients().values():
            self._frame_client(client)

    def _frame_client(self, client: Any) -> None:
        if getattr(self, "_view", None) is None:
            return
        cam = client.camera
        try:
            fov, aspect = float(cam.fov), float(cam.aspect)
        except (AssertionError, AttributeError, ZeroDivisionError, TypeError, ValueError):
            fov, aspect = math.radians(75.0), 0.75
        if not (math.isfinite(fov) and 0.05 < fov < 3.0 and math.isfinite(aspect) and aspect > 0):
            fov, aspect = math.radians(75.0), 0.75
        position, look_at = self._camera_for(fov, aspect)
        cam.position = position
        cam.look_at = look_at

    def _stats_markdown(self, snap: dict, drawn: dict) -> str:
        if snap.get("g") is None:
            return "No map loaded."
        st = snap["stats"]
        f = drawn["factor"]
        lines = [
            (
                f"**Map**: {'NDT-OM' if st['occupancy'] else 'Recursive NDT'}, "
                f"{snap['resolution']:g} m{' (native)' if f == 1 else f' ({f}x coarser)'}"
            ),
            f"**Scans**: {_fmt(st['scans'])}, {_fmt(st['points'])} points",
            (
                f"**Gaussians**: {_fmt(drawn['gaussians_total'])} with p > {snap['threshold']:.2f}"
                + (f" between {drawn['clip'][0]:.2f} and {drawn['clip'][1]:.2f} m" if drawn.get("clip") else "")
                + f", {_fmt(drawn['gaussians'])} drawn as {drawn['geometry']}"
            ),
            (
                f"**Level of detail** (auto): ellipsoids up to {_fmt(self.max_ellipsoids)} Gaussians, "
                f"splats up to {_fmt(self.max_splats)}, then a coarser level"
            ),
        ]
        if "known" in snap:
            lines.append(f"**Cells**: {_fmt(snap['known'])} known, {_fmt(snap['n_occupied'])} occupied "
                         f"(p > {snap['threshold']:.2f}), {_fmt(snap['n_free'])} free")  # fmt: skip
        lines.append(f"**Free cells** drawn at most {_fmt(self.max_free_cells)}, occupied cells at most "
                     f"{_fmt(self.max_occupied_cells)}")  # fmt: skip
        cs = snap.get("compare_stats")
        if cs is not None:
            if cs.get("gaussians") is None:
                lines.append("**Recursive NDT**: loaded (turn on *Conflicting cells* to compare)")
            else:
                lines.append(f"**Recursive NDT**: {_fmt(cs['gaussians'])} Gaussians; "
                             f"**{_fmt(cs['conflicts'])} conflicting cells**")  # fmt: skip
        lines.append(f"**Memory**: {st['memory'] / 2**20:.1f} MiB")
        for note in drawn["notes"]:
            lines.append(f"**Note**: {note}")
        return "  \n".join(lines)


def _md_html(text: str) -> str:
    """The panel's markdown (``**bold**``, ``*italic*``, hard line breaks) as HTML."""
    out = html.escape(str(text))
    out = re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", out)
    out = re.sub(r"\*(.+?)\*", r"<i>\1</i>", out)
    return out.replace("  \n", "<br>").replace("\n", "<br>")


def with_panel(page: str, panel: str) -> str:
    """``page`` (viser's standalone HTML) with ``panel`` laid over the scene."""
    end = page.rfind("</body>")
    return page + panel if end < 0 else page[:end] + panel + page[end:]


def _coarser(m: NdtOmMap | MapSnapshot, factor: int) -> MapSnapshot:
    """``m`` at ``factor`` x its resolution, coarsened in numpy (no map slot)."""
    return (m if isinstance(m, MapSnapshot) else m.snapshot()).coarsen(factor)


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
