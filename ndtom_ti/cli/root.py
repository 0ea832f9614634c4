"""The ``ndtom`` Typer app: its root options (``--version``, ``--pin-threads``) and the
entry point :func:`main`. The commands register themselves on :data:`app` from their
modules (see the package docstring)."""

from __future__ import annotations

import importlib
import signal
from typing import Annotated

import typer
from typer.core import TyperGroup

from .. import __version__
from .common import fail, set_own_process, set_pin_threads


def _click_exceptions():
    # Typer 0.2x carries its own copy of Click; older Typer uses Click itself.
    for name in ("typer._click.exceptions", "click.exceptions"):
        try:
            return importlib.import_module(name)
        except ImportError:
            continue
    return None


_CLICK = _click_exceptions()


class _Group(TyperGroup):
    """Click's own usage errors of a command (a required option missing, a value out of its
    range) in the one-line ``Error:``/``Hint:`` form of every other bad option, exit 2."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except Exception as exc:
            if _CLICK is None or not isinstance(exc, _CLICK.UsageError):
                raise
            if type(exc).__name__ == "NoArgsIsHelpError":  # `ndtom` alone: its help, as asked
                raise
            ctx = getattr(exc, "ctx", None)
            sub = ctx.command_path if ctx is not None else "ndtom COMMAND"
            param = getattr(getattr(exc, "param", None), "name", None)
            hint = f"`{sub} --help` lists " + ("the commands" if sub == "ndtom" else "the options and their ranges")
            if param == "resolution":
                hint = f"give the cell size in metres, e.g. {sub} BAG -r 0.2 (0.1-0.5 m suits most lidar maps)"
            fail(getattr(exc, "format_message", exc.__str__)(), hint)


app = typer.Typer(
    cls=_Group,
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
