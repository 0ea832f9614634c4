"""The ``ndtom`` Typer app: its root options (``--version``, ``--pin-threads``) and the
entry point :func:`main`. The commands register themselves on :data:`app` from their
modules (see the package docstring)."""

from __future__ import annotations

import signal
from typing import Annotated

import typer

from .. import __version__
from .common import set_own_process, set_pin_threads

app = typer.Typer(
    name="ndtom",
    help="Exact NDT Occupancy Maps from ROS bags (Taichi, CPU or CUDA).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version(value: bool) -> None:
    if value:
        print(f"ndtom_ti {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Show the version and exit.")
    ] = False,
    pin_threads: Annotated[
        bool,
        typer.Option(
            "--pin-threads/--no-pin-threads",
            help="Fix each of Taichi's CPU worker threads to a CPU of its own "
            "(faster short loops; off leaves them to the scheduler, e.g. on CPUs shared with busy drivers).",
        ),
    ] = True,
) -> None:
    """Exact NDT Occupancy Maps from ROS bags (Taichi, CPU or CUDA).

    Exit codes: 0 ok, 1 failed (e.g. memory budget; what was mapped is saved), 2 bad
    input or usage, 130 interrupted by Ctrl-C, 143 by SIGTERM (what was mapped is saved).
    """
    set_pin_threads(pin_threads)


def main() -> None:
    """Entry point of the ``ndtom`` command."""
    set_own_process()  # signal handlers may stay until the process exits
    try:
        app(prog_name="ndtom")
    finally:
        # The work is saved; Python drops its handlers before Taichi's teardown, where a
        # late Ctrl-C or SIGTERM would otherwise kill the process instead of it exiting.
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, signal.SIG_IGN)
