"""The live-mapping folder of a viewer's panel: Play, Pause, Step, the scan counter, the
pace slider, the status line and the chart of time per scan (:class:`LivePanel`).

A :class:`~.live.LiveMapper` builds one and tells it when to redraw; the panel reads the
mapper's progress and calls its controls (:class:`LiveState`: what it uses of it).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    from .controls import Controls

__all__ = ["LivePanel", "LiveState", "chart_series"]


class LiveState(Protocol):
    """What the panel reads of live mapping, and the controls its buttons and slider call."""

    total: int | None
    scans_done: int
    finished: bool
    error: str | None
    times_ms: list[float]
    compare_times_ms: list[float]
    compare: Any  # the Recursive NDT map, or None: the chart's second series
    paced_by_stamps: bool  # the slider sets the speed (x recording), else the scans per second
    speed: float | None
    rate_hz: float

    @property
    def playing(self) -> bool: ...

    def play(self) -> None: ...

    def pause(self) -> None: ...

    def step(self, n: int = 1) -> None: ...

    def set_speed(self, speed: float | None) -> None: ...


def chart_series(times_ms: list[float], compare_ms: list[float] | None = None) -> tuple[tuple, str]:
    """The time-per-scan chart's columns (scan number, NDT-OM ms[, R-NDT ms]) and a note on
    what is left out of them.

    The first scan compiles the kernels (seconds, where later scans take milliseconds): on
    the chart's automatic scale its spike would flatten the rest, so when it is more than
    twice the slowest later scan it is left out, and the note gives its time. No NaN goes to
    the chart (uPlot takes a NaN for a number: the axis range becomes NaN and nothing is
    drawn), so with a comparison the rows are those both series have."""
    n = len(times_ms) if compare_ms is None else min(len(times_ms), len(compare_ms))
    rows = [np.asarray(times_ms[:n], np.float64)] + (
        [] if compare_ms is None else [np.asarray(compare_ms[:n], np.float64)]
    )
    x = np.arange(1, n + 1, dtype=np.float64)
    later = np.concatenate([r[1:] for r in rows]) if n > 1 else np.zeros(0)
    first = max((float(r[0]) for r in rows if n), default=0.0)
    start, note = 0, ""
    if len(later) and first > 2.0 * float(later.max()):
        start, note = 1, f"Scan 1 took {first:,.0f} ms (compiling the kernels): not charted."
    return (x[start:], *(r[start:] for r in rows)), note


class LivePanel:
    """The live-mapping folder of a viewer's panel (``gui``: viser's; the handles are kept in
    ``controls``: ``live_folder``, ``play`` ... ``live_status``), showing ``live``'s progress.
    A previous live run's folder is removed."""

    def __init__(self, gui: Any, controls: Controls, live: LiveState):
        self.controls = controls
        self.live = live
        self.chart_note = ""  # what the chart leaves out (the first scan's compile), said under the status
        c, lm = controls, live
        if c.live_folder is not None:  # a previous live run's controls
            c.live_folder.remove()
        c.live_folder = gui.add_folder("Live mapping", order=-1)
        with c.live_folder:
            c.play = gui.add_button("Play")
            c.pause = gui.add_button("Pause")
            c.step = gui.add_button("Step")
            c.scan = gui.add_markdown(self._counter_text())
            if lm.paced_by_stamps:
                c.rate = gui.add_slider(
                    "Speed (x recording)",
                    min=0.0,
                    max=10.0,
                    step=0.25,
                    initial_value=min(lm.speed or 0.0, 10.0),
                    hint="1: the recording's own rate; 0: as fast as mapping goes",
                )
            else:
                c.rate = gui.add_slider(
                    "Max scans per second",
                    min=0.0,
                    max=50.0,
                    step=0.5,
                    initial_value=min(lm.rate_hz, 50.0),
                    hint="0: as fast as mapping goes",
                )
            c.live_status = gui.add_markdown("Paused: press Play or Step.")
            series = [{"label": "scan"}, {"label": "NDT-OM ms", "stroke": "#c81e1e", "width": 2}]
            if lm.compare is not None:
                series.append({"label": "R-NDT ms", "stroke": "#1e64c8", "width": 1})
            # one (NaN) point to start with: a chart made empty never finds its x range
            c.chart = gui.add_uplot(
                data=tuple(np.array([0.0 if i == 0 else np.nan]) for i in range(len(series))),
                series=tuple(series),
                scales={"x": {"time": False, "auto": True}, "y": {"auto": True}},
                title="Time per scan (ms)",
                aspect=2.0,
            )
        c.play.on_click(lambda _: lm.play())
        c.pause.on_click(lambda _: lm.pause())
        c.step.on_click(lambda _: lm.step())
        if lm.paced_by_stamps:
            c.rate.on_update(lambda _: lm.set_speed(float(c.rate.value)))
        else:
            c.rate.on_update(lambda _: setattr(lm, "rate_hz", float(c.rate.value)))

    def _counter_text(self) -> str:
        lm = self.live
        of = f" / {lm.total}" if lm.total is not None else ""
        return f"**Scans inserted**: {lm.scans_done}{of}"

    def update_status(self) -> None:
        """The status line, and the buttons disabled once nothing is left to play."""
        c, lm = self.controls, self.live
        if c.live_status is None:
            return
        if lm.error:
            text = f"**Stopped**: {lm.error}"
        elif lm.finished:
            text = f"**Done**: {lm.scans_done} scans inserted."
        elif lm.playing:
            text = "Mapping..."
        else:
            text = "Paused: press Play or Step."
        note = self.chart_note
        c.live_status.content = f"{text}  \n{note}" if note else text
        # nothing left to play: the buttons say so
        c.play.disabled = c.pause.disabled = c.step.disabled = lm.finished

    def update(self) -> None:
        """The counter, the chart and the status line."""
        c, lm = self.controls, self.live
        c.scan.content = self._counter_text()
        n = len(lm.times_ms)
        if n:
            cols, self.chart_note = chart_series(
                lm.times_ms[:n], None if lm.compare is None else lm.compare_times_ms[:n]
            )
            if len(cols[0]):
                c.chart.data = cols
        self.update_status()
