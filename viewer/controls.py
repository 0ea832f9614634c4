"""Controls: a viewer's panel (viser GUI handles) and what its selectors hold.

Set a handle's ``.value`` from Python and its callback fires as a click in a browser
would. The selectors relabel themselves to say what is drawn ("auto: 0.6 m drawn",
"auto: splats"); a relabelling fires no redraw. The height clip's range follows the
map's heights (``zlimits``), keeping a band the user chose.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from .levels import AUTO, FACTORS, Caps, fmt
from .scene import LAYERS

__all__ = ["COLOR_MODES", "GEOMETRIES", "Controls"]

COLOR_MODES = ("height", "occupancy")
GEOMETRIES = ("auto", "ellipsoids", "splats")
THRESHOLDS = (0.5, 0.99)  # the occupancy threshold slider's range
DEFAULT_ON = {"gaussians", "conflicts", "trajectory", "scan"}  # free cells stay off: they bury the scene
LIVE_LAYERS = ("trajectory", "scan")  # offered once live mapping runs (or a trajectory is set)


class Controls:
    """The panel's handles (``None`` until made); ``layers`` maps a layer key to its checkbox.

    ``on_change()`` is called when a control asks for a redraw, ``on_layer(key)`` when a
    layer's checkbox changes, ``on_point_size(size)``, ``on_frame()`` for *Frame the map*.
    Live mapping adds its own folder (``live_folder``, ``play`` ... ``live_status``).
    """

    def __init__(
        self,
        gui: Any,
        caps: Caps,
        *,
        resolution: float | None,
        threshold: float,
        color_mode: str,
        geometry: str,
        conflicts: bool,
        on_change: Callable[[], None],
        on_layer: Callable[[str], None],
        on_point_size: Callable[[float], None],
        on_frame: Callable[[], None],
    ):
        self._gui = gui
        self._on_change = on_change
        self._relabelling = False  # a selector relabelled: no redraw
        self._fitting = False  # the height clip refitted: no redraw
        self._zlimits: tuple[float, float] | None = None
        self._live_layers = False
        # live mapping (made by LiveMapper)
        self.live_folder: Any = None
        self.play: Any = None
        self.pause: Any = None
        self.step: Any = None
        self.scan: Any = None
        self.rate: Any = None
        self.chart: Any = None
        self.live_status: Any = None

        labels, self._level_lookup = self._level_options(resolution, None)
        self.notice = gui.add_markdown("", visible=False)  # caps and subsampling, where they apply
        self.frame = gui.add_button("Frame the map", hint="move the camera back to the first view of the whole map")
        with gui.add_folder("Map"):
            self.color_mode = gui.add_dropdown(
                "Colour by",
                COLOR_MODES,
                initial_value=color_mode,
                hint="height of the Gaussian's mean, or its occupancy probability",
            )
            self.zclip = gui.add_multi_slider(
                "Height clip (m)",
                min=0.0,
                max=1.0,
                step=0.05,
                initial_value=(0.0, 1.0),
                hint="draw only what lies between these heights (e.g. below a hall's roof)",
            )
            self.threshold = gui.add_slider(
                "Occupancy threshold",
                min=THRESHOLDS[0],
                max=THRESHOLDS[1],
                step=0.01,
                initial_value=threshold,
                hint="draw Gaussians and occupied cells with occupancy probability above this",
            )
            self.resolution = gui.add_dropdown(
                "Resolution",
                labels,
                initial_value=labels[-1],
                hint=f"a level is drawn whole (past {fmt(caps.chosen)} Gaussians: the part around the view); "
                "auto: the level of detail picks the finest level that keeps the page responsive",
            )
            self.geometry = gui.add_dropdown(
                "Gaussians as",
                GEOMETRIES,
                initial_value=geometry,
                hint=f"auto: ellipsoids up to {fmt(caps.ellipsoids)} Gaussians, splats up to "
                f"{fmt(caps.splats)}, then a coarser level",
            )
            self.redraw = gui.add_button(
                "Draw around the view",
                visible=False,
                hint="draw the chosen level's Gaussians nearest where the view looks",
            )
            self.point_size = gui.add_slider(
                "Point size",
                min=0.005,
                max=0.5,
                step=0.005,
                initial_value=0.03,
                hint="size (m) of the latest scan's points",
                visible=False,
            )
        self.legend = gui.add_html("")
        self.layers: dict[str, Any] = {}
        with gui.add_folder("Layers"):
            for key, lab in LAYERS.items():
                offered = conflicts if key == "conflicts" else key not in LIVE_LAYERS
                self.layers[key] = gui.add_checkbox(lab, key in DEFAULT_ON, visible=offered)
        with gui.add_folder("Statistics", expand_by_default=False):
            self.stats = gui.add_markdown("")

        self.resolution.on_update(lambda _: self._changed())
        self.threshold.on_update(lambda _: on_change())
        self.color_mode.on_update(lambda _: on_change())
        self.geometry.on_update(lambda _: self._changed())
        self.zclip.on_update(lambda _: None if self._fitting else on_change())
        self.point_size.on_update(lambda _: on_point_size(float(self.point_size.value)))
        self.frame.on_click(lambda _: on_frame())
        self.redraw.on_click(lambda _: on_change())
        for key, box in self.layers.items():
            box.on_update(lambda _, key=key: on_layer(key))

    @staticmethod
    def check(*, threshold: float, color_mode: str, geometry: str) -> None:
        """Raise ``ValueError`` for a first value the controls do not offer."""
        if color_mode not in COLOR_MODES:
            raise ValueError(f"color_mode must be one of {COLOR_MODES}, got {color_mode!r}")
        if geometry not in GEOMETRIES:
            raise ValueError(f"geometry must be one of {GEOMETRIES}, got {geometry!r}")
        if not THRESHOLDS[0] <= float(threshold) <= THRESHOLDS[1]:
            raise ValueError(f"threshold must be in [{THRESHOLDS[0]}, {THRESHOLDS[1]}], got {threshold}")

    def _changed(self) -> None:
        if not self._relabelling:
            self._on_change()

    # ------------------------------------------------------------------ what the controls hold

    def wanted(self) -> dict[str, bool]:
        """Layer key -> ticked."""
        return {k: bool(box.value) for k, box in self.layers.items()}

    def selected_factor(self) -> int:
        """The chosen level's factor, or AUTO."""
        v = str(self.resolution.value)
        return AUTO if v.startswith("auto") else self._level_lookup.get(v, AUTO)

    def geometry_choice(self) -> str:
        v = str(self.geometry.value)
        return "auto" if v.startswith("auto") else v

    @property
    def live_layers(self) -> bool:
        """Whether the trajectory and latest scan are offered."""
        return self._live_layers

    @property
    def zlimits(self) -> tuple[float, float] | None:
        """The height clip's range (the map's heights; None until a map with content is drawn)."""
        return self._zlimits

    def clip_range(self) -> tuple[float, float] | None:
        """The height band to draw, or None when the clip spans the whole map."""
        if self._zlimits is None:
            return None
        lo, hi = (float(v) for v in self.zclip.value)
        zlo, zhi = self._zlimits
        if lo <= zlo and hi >= zhi:
            return None
        return lo, hi

    # ------------------------------------------------------------------ changes

    def offer_live_layers(self) -> None:
        """Show the Trajectory and Latest scan checkboxes (and the point size slider)."""
        if self._live_layers:
            return
        self._live_layers = True
        for key in LIVE_LAYERS:
            self.layers[key].visible = True
        self.point_size.visible = True

    def new_maps(self, conflicts: bool, resolution: float | None, drawn_resolution: float | None) -> None:
        """Other maps: the clip is fitted anew, the levels relabelled."""
        self._zlimits = None
        self.layers["conflicts"].visible = conflicts
        self.relabel_levels(resolution, drawn_resolution)

    def show(self, *, legend: str, stats: str, notes: list[str], conflicts: bool) -> None:
        """The legend, statistics and notes of what is drawn."""
        self.legend.content = legend
        self.stats.content = stats
        self.notice.content = "  \n".join(f"**Note**: {n}" for n in notes)
        self.notice.visible = bool(notes)
        self.layers["conflicts"].disabled = not conflicts

    @staticmethod
    def _level_options(resolution: float | None, drawn: float | None) -> tuple[list[str], dict[str, int]]:
        """Labels of the resolution selector: each level, then "auto" (the level of detail's
        choice, named once drawn: the selector says what is drawn)."""
        labels, lookup = [], {}
        for f in FACTORS:
            if resolution is None:
                lab = "native" if f == 1 else f"{f}x coarser"
            else:
                lab = f"{resolution * f:g} m (native)" if f == 1 else f"{resolution * f:g} m ({f}x)"
            labels.append(lab)
            lookup[lab] = f
        auto = "auto" if drawn is None else f"auto: {drawn:g} m drawn"
        labels.append(auto)
        lookup[auto] = AUTO
        return labels, lookup

    def relabel_levels(self, resolution: float | None, drawn: float | None) -> None:
        """Label the levels of a map of ``resolution``; "auto" names the resolution ``drawn``
        (None: not drawn by auto)."""
        labels, lookup = self._level_options(resolution, drawn)
        h = self.resolution
        if list(h.options) != labels:
            old = self.selected_factor()
            self._level_lookup = lookup
            self._relabelling = True
            try:
                h.options = labels
                h.value = labels[-1] if old == AUTO else labels[FACTORS.index(old)]
            finally:
                self._relabelling = False
        self._level_lookup = lookup

    def relabel_geometry(self, use: str) -> None:
        """The geometry selector's "auto" entry says which geometry it draws."""
        h = self.geometry
        label = f"auto: {use}"
        if label in h.options:
            return
        auto_now = str(h.value).startswith("auto")
        self._relabelling = True
        try:
            h.options = [label, *GEOMETRIES[1:]]
            if auto_now:
                h.value = label
        finally:
            self._relabelling = False

    def fit_zclip(self, z: np.ndarray, res: float, ceiling: float | None = None) -> None:
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
        cur = tuple(float(v) for v in self.zclip.value)
        full = old is None or (cur[0] <= old[0] and cur[1] >= old[1])
        if old is not None:
            zlo, zhi = min(zlo, old[0]), max(zhi, old[1])
        self._zlimits = (zlo, zhi)
        self._fitting = True
        try:
            self.zclip.step = step
            self.zclip.min = zlo
            self.zclip.max = zhi
            if old is None and ceiling is not None and zlo < ceiling < zhi:
                self.zclip.value = (zlo, float(np.floor(ceiling / step) * step))
            else:
                self.zclip.value = (zlo, zhi) if full else (max(cur[0], zlo), min(cur[1], zhi))
        finally:
            self._fitting = False
