"""Ctrl-C (SIGINT) and SIGTERM during ``ndtom sweep`` and ``ndtom experiments``.

Their maps are thrown away once timed or measured, so the first signal stops the work in
hand at once (:class:`~ndtom_ti.signals.Interrupted`, raised where the work was); the
command then writes what it finished. While results are written (:func:`writing`) a signal
waits until the files are whole. Later signals only say that the results are being
written. From the API (no :func:`catch_stops`), :func:`writing` defers Ctrl-C as
:func:`~ndtom_ti.signals.deferred_interrupt` does.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ..signals import Interrupted, StopSignals, current_stops, deferred_interrupt, stop_signals

__all__ = ["catch_stops", "mark_written", "writing", "written_before"]


@contextmanager
def catch_stops(restore: bool = True) -> Iterator[StopSignals]:
    """SIGINT and SIGTERM handled for the block (main thread only) by a
    :class:`~ndtom_ti.signals.StopSignals` in phase "working"; the command sets phase "writing"
    once the run is over (stopped or not). ``restore=False`` (a process that exits after the
    block) leaves the handler in place, ignoring late signals."""
    with stop_signals(phase="working", restore=restore) as state:
        try:
            yield state
        finally:
            # "done" also when the block raised: the exit after a stop must not be broken
            state.phase = "done"


@contextmanager
def writing(then_stop: bool = True) -> Iterator[None]:
    """Files written in the block are written whole: a stop signal waits for its end, then
    stops the run (unless the stop was already under way, or ``then_stop`` is False: the
    run has nothing left to stop)."""
    state = current_stops()
    if state is None:
        with deferred_interrupt():
            yield
        return
    if state.phase != "working":  # a stop under way (or an outer block): signals already wait
        yield
        return
    state.phase = "writing"
    try:
        yield
    finally:
        if state.phase == "writing":
            state.phase = "working"
    # "working" before the block: any signal so far came while it ran
    if then_stop and state.signum is not None:
        state.phase = "writing"
        raise Interrupted(state.signum)


_WRITTEN = "ndtom_written"


def mark_written(exc: BaseException, files: list[Path]) -> None:
    """Note on ``exc`` (a stop raised through a run) the files the run wrote before it."""
    setattr(exc, _WRITTEN, list(files))


def written_before(exc: BaseException) -> list[Path] | None:
    """The files :func:`mark_written` noted on ``exc`` (None: none noted)."""
    return getattr(exc, _WRITTEN, None)
