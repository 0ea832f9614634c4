"""What every ``ndtom`` command shares: the console and the one-line errors with a hint
(exit codes of :mod:`ndtom_ti.exitcodes`), the checks of options and paths, Taichi's
start, and the small formatters of the tables."""

from __future__ import annotations

import contextlib
import io
import os
import signal
import stat
import tempfile
from collections.abc import Iterator
from enum import Enum
from pathlib import Path
from typing import NoReturn

import typer
from rich.console import Console
from rich.table import Table
from rich.text import Text

from ..atomic import MAP_KIND, kept_kind, temp_prefix
from ..config import check_resolution
from ..exitcodes import EXIT_FAILURE, EXIT_USAGE, signal_exit_code
from ..frames import as_frame_origin
from ..io import RecordingError
from ..mapfile import MapFileError
from ..runtime import MapMemoryError

MAP_SUFFIX = ".ndtom"


class Arch(str, Enum):
    auto = "auto"
    cpu = "cpu"
    cuda = "cuda"


class MissModel(str, Enum):
    ndt = "ndt"
    paper = "paper"


# ---------------------------------------------------------------------------- output helpers
# Output to a file, pipe or CI log has no width: Rich would assume 80 columns and fold
# table cells mid-word ("octoma/p"). Tables there take the width they need, up to this.
LOG_WIDTH = 160


def console_out() -> Console:
    c = Console(highlight=False)
    if not c.is_terminal and not os.environ.get("COLUMNS"):
        c.width = LOG_WIDTH
    return c


def console_err() -> Console:
    return Console(stderr=True, highlight=False, soft_wrap=True)


def fail(message: str, hint: str | None = None, code: int = EXIT_USAGE) -> NoReturn:
    console = console_err()
    console.print(Text.assemble(("Error: ", "bold red"), (message, "red")))
    if hint:
        console.print(Text.assemble(("Hint: ", "bold"), hint))
    raise typer.Exit(code)


def need_extra(module: str, purpose: str) -> None:
    """Stop before any work when an optional package is missing, naming its extra and
    how to install it; exit 1 for every command (``exitcodes``)."""
    from ..extras import available, extra_of, install_hint, missing_message

    if not available(module):
        fail(missing_message(module, purpose), f"install it with: {install_hint(extra_of(module))}", EXIT_FAILURE)


def without_extra(module: str, skipped: str) -> bool:
    """True (after a note saying what is skipped and how to get it) when ``module`` is missing."""
    from ..extras import available, extra_of, install_hint

    if available(module):
        return False
    console_err().print(
        Text(
            f"note: {module} is not installed (extra [{extra_of(module)}]): {skipped}; to get it: "
            f"{install_hint(extra_of(module))}",
            style="yellow",
        ),
        soft_wrap=True,
    )
    return True


MEMORY_HINT = (
    "use a coarser resolution (-r), a smaller --max-range, fewer scans (--every, --max-scans), "
    "or a CUDA device (--arch cuda)"
)


def _command_path() -> str:
    """The command running (``ndtom map``), from Click's context: Typer's own copy of Click
    or Click itself; ``ndtom COMMAND`` outside a command."""
    import importlib

    for name in ("typer._click.globals", "click.globals"):
        try:
            ctx = importlib.import_module(name).get_current_context(silent=True)
        except ImportError:
            continue
        if ctx is not None:
            return ctx.command_path
    return "ndtom COMMAND"


@contextlib.contextmanager
def user_errors(*, recording: str | None = None, map_file: str | None = None) -> Iterator[None]:
    """Turn the errors a user can cause into one red line + hint and an exit code."""
    try:
        yield
    except (typer.Exit, typer.Abort, SystemExit):
        raise
    except RecordingError as exc:
        fail(str(exc), recording or "`ndtom info BAG` shows the topics, TF frames and pose sources of a recording")
    except MapFileError as exc:
        fail(str(exc), map_file or "give a map file written by `ndtom map` or `ndtom demo`")
    except MapMemoryError as exc:
        fail(str(exc), MEMORY_HINT, EXIT_FAILURE)
    except FileNotFoundError as exc:
        fail(str(exc), map_file or "check the path")
    except OSError as exc:
        fail(f"{exc}", "check the path and its permissions", EXIT_FAILURE)
    except (ValueError, TypeError) as exc:
        fail(str(exc), f"`{_command_path()} --help` lists the options and their ranges")
    except KeyboardInterrupt as exc:
        from ..signals import signal_name

        signum = getattr(exc, "signum", signal.SIGINT)
        fail(f"interrupted ({signal_name(signum)}); nothing was written", None, signal_exit_code(signum))
    except Exception as exc:  # the last line of defence: no traceback for users
        from ..cluster.engines import ClusterError  # (--workers: a lost worker, no cluster to join)

        if isinstance(exc, ClusterError):
            fail(str(exc), exc.hint, EXIT_FAILURE)
        if os.environ.get("NDTOM_DEBUG"):
            raise
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        text = lines[0] if len(lines) == 1 else (f"{lines[0]} ... {lines[-1]}" if lines else "")
        fail(
            f"internal error: {type(exc).__name__}: {text}",
            "set NDTOM_DEBUG=1 to see the traceback, and please report it",
            EXIT_FAILURE,
        )


def init_taichi(arch: Arch, memory_limit: float | None = None) -> str:
    """Initialise Taichi once (its start-up line is not shown); a wrong arch is a usage
    error. Why the CPU memory budget is below the one asked for is shown as a note."""
    import warnings

    import ndtom_ti

    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        try:
            used = ndtom_ti.init(arch.value, memory_limit_GB=memory_limit, pin_threads=pin_threads())
        except RuntimeError as exc:
            fail(str(exc), "use --arch cpu (or auto)")
        except ValueError as exc:
            if memory_limit is None:
                raise
            fail(
                str(exc).replace("memory_limit_GB=", "--memory-limit ").replace("memory_limit_GB", "--memory-limit"),
                "give --memory-limit in GiB, below the machine's memory",
            )
    for w in caught:
        if issubclass(w.category, RuntimeWarning) and w.message is not None:
            console_err().print(Text(f"note: {w.message}", style="dim"))
    return used


def check_writable(path: Path, what: str = "output", option: str = "-o", suffix: str = MAP_SUFFIX) -> Path:
    """Fail now (before any mapping) when ``path`` cannot be written; the hints name ``option``
    (and a file name of ``suffix`` for a folder given)."""
    path = path.expanduser()
    if path.is_dir():
        fail(f"the {what} path {path} is a folder", f"give a file name, e.g. {path / ('map' + suffix)}")
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.exists():
        fail(
            f"cannot write the {what} {path}: folder {folder} does not exist",
            f"create the folder first or choose another path with {option}",
        )
    if not folder.is_dir():
        fail(f"cannot write the {what} {path}: {folder} is not a folder", f"choose another path with {option}")
    try:
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path), suffix=".check", dir=folder)
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:  # a read-only or full file system: "could not write" is exit 1 however found
        fail(
            f"cannot write the {what} {path}: {exc.strerror or exc}",
            f"choose a writable folder with {option}",
            EXIT_FAILURE,
        )
    if path.exists() and not path.is_file():
        fail(
            f"cannot write the {what} {path}: it exists and is not a regular file", f"choose another path with {option}"
        )
    kind = kept_kind(path)
    if kind is not None and not (what == "map file" and kind == MAP_KIND):  # (maps replace maps)
        fail(f"cannot write the {what} {path}: {kind}, which writing it would destroy", "choose another path")
    return path


def output_folder(out: Path, what: str) -> Path:
    """``--out``, a folder for ``what``, made if missing; a file there or a folder that cannot
    be made is a clear error (not a raw OSError)."""
    out = out.expanduser()
    if out.exists() and not out.is_dir():
        fail(f"--out {out} is a file, not a folder", f"give a folder for {what}")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        fail(f"cannot create the folder {out}: {exc.strerror or exc}", "choose another folder with --out")
    return out


_RECORDING_SUFFIXES = (".bag", ".db3", ".mcap")


def check_map_output(path: Path, option: str = "-o") -> None:
    """Fail (before any work) when a map file's output ``path`` names another format, which a
    user would expect to get, or is an existing file that is not a map file: writing the map
    there would destroy it (another recording, a point cloud). Map files are replaced, and
    so is a damaged file named as one, unless it is a recording."""
    from ..export import SUFFIXES
    from ..mapfile import MAGIC

    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
    except OSError:
        head = b""  # not there (or unreadable: check_writable says why)
    suffix = path.suffix.lower()
    if head and not head.startswith(MAGIC):
        # (a damaged file named as a map is replaced; a recording is not, whatever its name)
        kind = kept_kind(path)
        if kind is not None or suffix != MAP_SUFFIX:
            fail(
                f"{path} exists and is not an ndtom map file ({kind or 'it is a file of another kind'}): writing "
                "the map would destroy it",
                f"choose another path with {option}, or remove {path} first if it is not needed",
            )
    as_map = path.with_suffix(MAP_SUFFIX)
    if suffix in SUFFIXES:
        fail(
            f"the map file {path} is named as a {SUFFIXES[suffix]} file, but maps are written in ndtom's own format",
            f"write the map to {as_map} and convert it: ndtom export {as_map} -o {path}",
        )
    if suffix in _RECORDING_SUFFIXES:
        fail(f"the map file {path} is named as a recording ({suffix})", f"choose a {MAP_SUFFIX} path with {option}")


def partial_path(output: Path) -> Path:
    """Where a run that stops early (Ctrl-C, the memory budget, a bad scan) writes its map when
    ``output`` held a map before the run: beside it, so the finished map there is kept."""
    return output.with_name(f"{output.stem}.partial{output.suffix}")


def _lies_in(path: Path, folder_stat: os.stat_result) -> bool:
    """Whether ``path`` (resolved) or one of its folders is the folder of ``folder_stat``
    (by device and inode: bind mounts and hard links too)."""
    for p in (path, *path.parents):
        try:
            s = os.stat(p)
        except OSError:
            continue
        if (s.st_dev, s.st_ino) == (folder_stat.st_dev, folder_stat.st_ino):
            return True
    return False


def check_not_input(output: Path, inputs: dict[str, Path | None], option: str = "-o") -> None:
    """Fail (exit 2, before any work) when ``output`` is one of ``inputs`` (named by what
    they are) or lies inside one (a ROS2 bag folder): the same file or inode, symbolic links
    resolved. Writing it would destroy the input."""
    out = Path(os.path.realpath(output.expanduser()))
    try:
        out_stat: os.stat_result | None = os.stat(out)
    except OSError:
        out_stat = None
    for what, given in inputs.items():
        if given is None:
            continue
        src = Path(os.path.realpath(Path(given).expanduser()))
        try:
            src_stat = os.stat(src)
        except OSError:
            continue  # a missing input is refused by the command itself
        same = out == src or (
            out_stat is not None and (out_stat.st_dev, out_stat.st_ino) == (src_stat.st_dev, src_stat.st_ino)
        )
        if same:
            fail(
                f"the output {output} is the {what} {given}: writing it would destroy it",
                f"choose another path with {option}",
            )
        if stat.S_ISDIR(src_stat.st_mode) and _lies_in(out.parent, src_stat):
            fail(
                f"the output {output} lies inside the {what} {given}: writing it would change it",
                f"choose a path outside {given} with {option}",
            )


def fmt_mib(b: float) -> str:
    return f"{b / 2**20:.1f} MiB"


def fmt_count(n: int) -> str:
    return f"{n:,}"


def frame_origin_text(origin: list) -> str:
    """A map's frame_origin (metadata), in words."""
    xyz = as_frame_origin(origin)
    if xyz is None:
        return f"{origin!r} (not three numbers: the file's metadata is damaged)"
    xyz = ", ".join(f"{v:,.0f}" for v in xyz)
    return f"({xyz}) m of the poses' frame is the map's (0, 0, 0): its coordinates and exports are relative to it"


def fmt_secs(ns: int | None, start_ns: int | None = None) -> str:
    """Seconds; relative to the bag start (record time) when ``start_ns`` is given and near."""
    if ns is None:
        return "-"
    if start_ns is not None and abs(ns - start_ns) < 86_400 * 10**9:
        return f"{(ns - start_ns) / 1e9:.3f}"
    return f"{ns / 1e9:.3f} (absolute)"


def make_table(title: str, *columns: str, header: bool = True) -> Table:
    t = Table(title=title, show_header=header, title_justify="left")
    for i, col in enumerate(columns):
        t.add_column(
            col,
            overflow="fold",
            style="bold" if (not header and i == 0) else None,
            justify="right" if col in ("messages", "poses") else "left",
        )
    return t


# ---------------------------------------------------------------------------- process-wide settings
# Set by the root command (--pin-threads/--no-pin-threads) and by main() (the command runs in
# a process of its own, not in a test runner: signal handlers may stay until it exits).
_SETTINGS = {"pin_threads": True, "own_process": False}


def set_pin_threads(on: bool) -> None:
    _SETTINGS["pin_threads"] = on


def pin_threads() -> bool:
    """The command pins Taichi's CPU workers (affinity.py) unless --no-pin-threads or
    NDTOM_PIN_THREADS=0 says not to."""
    return _SETTINGS["pin_threads"] and os.environ.get("NDTOM_PIN_THREADS", "1") not in ("0", "")


def set_own_process() -> None:
    _SETTINGS["own_process"] = True


def own_process() -> bool:
    return _SETTINGS["own_process"]


# ---------------------------------------------------------------------------- options
def resolution_option(value: float) -> float:
    """``-r/--resolution``, checked as every resolution is (:func:`ndtom_ti.config.check_resolution`)."""
    return check_resolution(value, "-r/--resolution")


def resolution_list(text: str, option: str) -> list[float]:
    """Comma-separated resolutions of ``option`` (e.g. ``--resolutions 0.1,0.2``); a
    ValueError naming the option for anything but positive numbers of metres."""
    try:
        values = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"{option} must be numbers separated by commas, got {text!r}") from None
    try:
        if not values:
            raise ValueError("no resolution given")
        return [check_resolution(v, option) for v in values]
    except ValueError:
        raise ValueError(f"{option} must be positive numbers of metres, got {text!r}") from None
