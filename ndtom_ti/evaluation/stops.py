"""Ctrl-C (SIGINT) and SIGTERM during ``ndtom sweep`` and ``ndtom experiments``.

Their maps are thrown away once timed or measured, so the first signal stops the work in
hand at once (:class:`~ndtom_ti.signals.Interrupted`, raised where the work was); the
command then writes what it finished. While results are written (:func:`writing`) a signal
waits until the files are whole. Later signals only say that the results are being
written. From the API (no :func:`catch_stops`), :func:`writing` defers Ctrl-C as
:func:`~ndtom_ti.signals.deferred_interrupt` does.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from ..exitcodes import signal_exit_code
from ..signals import Interrupted, deferred_interrupt, signal_name

__all__ = ["EvalSignals", "catch_stops", "mark_written", "writing", "written_before"]


class EvalSignals:
    """The state of :func:`catch_stops`: ``signum`` (the first signal), ``count``."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.count = 0
        self.raised = False  # the stop has been raised: later signals wait for the writing
        self.pending: int | None = None  # a signal that came while results were written
        self.holding = 0
        self.done = False

    @property
    def name(self) -> str:
        return signal_name(self.signum)

    @property
    def exit_code(self) -> int:
        return signal_exit_code(self.signum or signal.SIGINT)

    def handler(self, signum: int, frame: Any) -> None:
        self.count += 1
        if self.signum is None:
            self.signum = signum
        if self.done:
            return
        name = signal_name(signum)
        if self.raised or self.holding:
            if not self.raised:
                self.pending = self.pending or signum
            _say(f"{name}: writing the results finished so far; they are on disk in a moment.")
            return
        self.raised = True
        raise Interrupted(signum)

    def finishing(self) -> None:
        """The run is over (stopped or not): from now on signals only wait for the writing."""
        self.raised = True


def _say(text: str) -> None:
    # os.write: a handler may run while the main thread is inside a print to stderr.
    try:
        os.write(2, (text + "\n").encode("utf-8", "replace"))
    except OSError:
        pass


_active: EvalSignals | None = None


@contextmanager
def catch_stops(restore: bool = True) -> Iterator[EvalSignals]:
    """SIGINT and SIGTERM handled for the block (main thread only). ``restore=False`` (a
    process that exits after the block) leaves the handler in place, ignoring late signals."""
    global _active
    state = EvalSignals()
    old: dict = {}
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGINT, signal.SIGTERM):
            try:
                old[signum] = signal.signal(signum, state.handler)
            except (ValueError, OSError):  # pragma: no cover - embedded interpreters
                pass
    outer, _active = _active, state
    try:
        yield state
    finally:
        _active = outer
        state.done = True
        if restore:
            for signum, handler in old.items():
                signal.signal(signum, handler)


@contextmanager
def writing(then_stop: bool = True) -> Iterator[None]:
    """Files written in the block are written whole: a stop signal waits for its end, then
    stops the run (unless the stop was already under way, or ``then_stop`` is False: the
    run has nothing left to stop)."""
    state = _active
    if state is None:
        with deferred_interrupt():
            yield
        return
    state.holding += 1
    try:
        yield
    finally:
        state.holding -= 1
    if then_stop and not state.holding and state.pending is not None and not state.raised:
        state.raised = True
        raise Interrupted(state.pending)


_WRITTEN = "ndtom_written"


def mark_written(exc: BaseException, files: list[Path]) -> None:
    """Note on ``exc`` (a stop raised through a run) the files the run wrote before it."""
    setattr(exc, _WRITTEN, list(files))


def written_before(exc: BaseException) -> list[Path] | None:
    """The files :func:`mark_written` noted on ``exc`` (None: none noted)."""
    return getattr(exc, _WRITTEN, None)
