"""Ctrl-C (SIGINT) and SIGTERM while a map is made and saved.

A command that maps and then saves wraps both in :func:`stop_signals`: the first signal
lets the scan in hand finish and stops the loop, later ones wait for the save. The mapping
loop (:mod:`ndtom_ti.pipeline`) takes the command's handler through :func:`loop_signals`,
or handles SIGINT for itself when called from the API. Live mapping (``ndtom map --view``)
maps in a worker thread while the main thread serves the viewer: :class:`LiveSignals` tells
the main thread to stop the worker, and keeps the viewer's words.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from .exitcodes import signal_exit_code

__all__ = [
    "Interrupted",
    "LiveSignals",
    "StopSignals",
    "current_stops",
    "deferred_interrupt",
    "loop_signals",
    "signal_name",
    "stop_signals",
]


class Interrupted(KeyboardInterrupt):
    """A stop signal (SIGINT or SIGTERM) at a point where there is no map to keep."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal_name(signum))
        self.signum = signum


@contextmanager
def deferred_interrupt() -> Iterator[None]:
    """Ctrl-C during the block raises KeyboardInterrupt when the block ends, not inside it:
    a scan's kernels then run whole (raised between two of them, it left half a scan in the
    map). A second Ctrl-C raises at once. Only where Python's own handler would raise it (the
    main thread, SIGINT not taken by the caller); anything else is left as it is."""
    if threading.current_thread() is not threading.main_thread() or (
        signal.getsignal(signal.SIGINT) is not signal.default_int_handler
    ):
        yield
        return
    got: list[int] = []

    def later(signum: int, frame: Any) -> None:
        if got:  # asked twice: now, whatever is half done
            signal.signal(signal.SIGINT, signal.default_int_handler)
            raise KeyboardInterrupt
        got.append(signum)

    signal.signal(signal.SIGINT, later)
    try:
        yield
    finally:
        if signal.getsignal(signal.SIGINT) is later:
            signal.signal(signal.SIGINT, signal.default_int_handler)
    if got:
        raise KeyboardInterrupt


def signal_name(signum: int | None) -> str:
    return "SIGTERM" if signum == signal.SIGTERM else "Ctrl-C"


class StopSignals:
    """What SIGINT (Ctrl-C) and SIGTERM do while a map is made and saved.

    ``phase`` is "idle" (no map yet: the first signal raises :class:`Interrupted`),
    "mapping" (the first signal lets the scan in hand finish, then the loop stops;
    another one stops a read that is under way, never an insert), "finished" (every scan
    is mapped: signals are only told that the complete map is being saved), "saving" (signals
    are counted and only told to wait until the map is on disk) or "done" (ignored). ``count`` and
    ``signum`` (the first signal) say what arrived. Runs whose maps are thrown away (``ndtom
    sweep``, ``ndtom experiments``, :mod:`ndtom_ti.evaluation.stops`) use "working" (the first
    signal raises :class:`Interrupted`, then the phase is "writing") and "writing" (signals are
    only told to wait until the results are written).
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
        if self.phase == "working":  # nothing to keep in hand: stop it now, and only once
            self.phase = "writing"
            raise Interrupted(signum)
        if self.phase == "done":  # the map is on disk and the command is ending
            return
        if self.phase == "finished":  # every scan is in the map: nothing is cut short
            self.say(f"{name}: every scan is mapped; saving the complete map.")
        elif self.phase == "saving":
            self.say(f"{name}: saving the map; wait, it is on disk in a moment.")
        elif self.phase == "writing":
            self.say(f"{name}: writing the results finished so far; they are on disk in a moment.")
        elif self.count == 1:
            self.say(f"{name}: stopping after the scan in hand; what was mapped will be saved.")
        elif self.reading:
            self.reading = False  # raise at most once, and only out of a read
            raise Interrupted(signum)
        else:
            self.say(f"{name}: finishing the scan in hand, then saving the map.")


_active: StopSignals | None = None  # installed by stop_signals(); loop_signals() uses it when set


def current_stops() -> StopSignals | None:
    """The StopSignals of the enclosing :func:`stop_signals` block (None: there is none)."""
    return _active


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
def loop_signals() -> Iterator[StopSignals]:
    """The StopSignals of a mapping loop: the command's (:func:`stop_signals`), or SIGINT
    handled for the loop alone (API use). Signals reach the main thread only: a loop in
    another thread gets one that no signal reaches (its observer stops it)."""
    if _active is not None:
        _active.phase = "mapping"
        yield _active
        return
    if threading.current_thread() is not threading.main_thread():
        yield StopSignals("mapping")
        return
    with stop_signals((signal.SIGINT,), phase="mapping", say=None) as state:
        yield state


class LiveSignals:
    """Ctrl-C (SIGINT) and SIGTERM while mapping live: the first asks mapping to stop after
    the scan in hand (``event`` is set: the main thread stops the worker); during the save,
    further ones wait until the map is on disk; once mapping is over they close the viewer."""

    def __init__(self) -> None:
        self.count = 0
        self.signum: int | None = None  # the first signal: it names the stop and sets the exit code
        self.event = threading.Event()
        self.saving = False
        self.serving = False  # mapping is over, the viewer shows the map
        self.phase = "mapping"  # (set by a finish that saves, as on StopSignals)
        self._old: dict[int, Any] = {}

    @property
    def name(self) -> str:
        return signal_name(self.signum)

    @property
    def exit_code(self) -> int:
        """130 after Ctrl-C, 143 after SIGTERM (the first signal decides)."""
        return signal_exit_code(self.signum if self.signum is not None else signal.SIGINT)

    def handler(self, signum: int, frame: Any) -> None:
        self.count += 1
        if self.signum is None:
            self.signum = signum
        self.event.set()
        name = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
        if self.saving:
            print(f"{name}: saving the map, please wait until it is on disk ...", file=sys.stderr, flush=True)
        elif self.serving:
            print(f"{name}: closing the viewer", file=sys.stderr, flush=True)
        elif self.count == 1:
            print(f"{name}: stopping after the scan in hand, then saving ...", file=sys.stderr, flush=True)

    def __enter__(self) -> LiveSignals:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                with contextlib.suppress(ValueError, OSError):
                    self._old[sig] = signal.signal(sig, self.handler)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, old in self._old.items():
            with contextlib.suppress(ValueError, OSError, TypeError):
                signal.signal(sig, old)
        self._old.clear()
